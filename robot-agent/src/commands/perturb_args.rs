//! `--perturb` and `--perturb-seed`: the robustness suite's variants on any command that reads a recording.

use anyhow::Context as _;
use clap::Args;
use robot_agent::perturbation::{Perturbation, PerturbationReport};
use robot_agent::source::Recording;

/// Arguments that perturb the recording before it is mapped (see `robot_agent::perturbation`).
#[derive(Args, Clone, Debug, Default)]
pub struct PerturbArgs {
    /// Perturb the recording first, deterministically: a comma-separated list of `clean`, `range8`,
    /// `range4`, `sparse`, `odom`, `slip`, `slow`, `clutter`, `late`, `noise`, `stall`, `hard`, `thin`,
    /// `lag`, `burst`.
    #[arg(long)]
    pub perturb: Option<String>,
    /// The perturbation's random seed.
    #[arg(long, default_value_t = 1, requires = "perturb")]
    pub perturb_seed: u64,
}

impl PerturbArgs {
    /// The perturbation asked for (`None` without `--perturb`); an unknown variant is refused here, so
    /// call it before reading the recording.
    pub fn perturbation(&self) -> anyhow::Result<Option<Perturbation>> {
        self.perturb
            .as_deref()
            .map(|names| Perturbation::parse(names).context("invalid --perturb"))
            .transpose()
    }

    /// `recording` perturbed by `perturbation` (from [`Self::perturbation`]), what was done for the
    /// report, and in full (each scan's capture time: [`PerturbationReport::capture_time`]); unchanged
    /// when there is none.
    pub fn apply(
        &self,
        perturbation: Option<&Perturbation>,
        recording: Recording,
    ) -> (Recording, serde_json::Value, PerturbationReport) {
        let (Some(perturbation), Some(names)) = (perturbation, &self.perturb) else {
            return (
                recording,
                serde_json::Value::Null,
                PerturbationReport::default(),
            );
        };
        let (perturbed, report) = perturbation.apply(&recording, self.perturb_seed);
        eprintln!(
            "perturbed ({names}, seed {}): {} of {} scans kept, {} slips, {} odometry stalls, {} beams cut, {} cluttered",
            self.perturb_seed,
            report.scans_out,
            report.scans_in,
            report.slips,
            report.stalls,
            report.beams_cut,
            report.beams_cluttered
        );
        let done = serde_json::json!({
            "variant": names,
            "seed": self.perturb_seed,
            "done": report,
        });
        (perturbed, done, report)
    }
}
