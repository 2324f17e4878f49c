//! `--perturb` and `--perturb-seed`: the robustness suite's variants on any command that reads a recording.

use anyhow::Context as _;
use clap::Args;
use robot_agent::perturbation::Perturbation;
use robot_agent::source::Recording;

/// Arguments that perturb the recording before it is mapped (see `robot_agent::perturbation`).
#[derive(Args, Clone, Debug, Default)]
pub struct PerturbArgs {
    /// Perturb the recording first, deterministically: a comma-separated list of `clean`, `range8`,
    /// `range4`, `sparse`, `odom`, `slip`, `slow`, `clutter`, `late`, `noise`, `hard`.
    #[arg(long)]
    pub perturb: Option<String>,
    /// The perturbation's random seed.
    #[arg(long, default_value_t = 1, requires = "perturb")]
    pub perturb_seed: u64,
}

impl PerturbArgs {
    /// Refuses an unknown variant before anything is read.
    pub fn check(&self) -> anyhow::Result<()> {
        if let Some(names) = &self.perturb {
            Perturbation::parse(names).context("invalid --perturb")?;
        }
        Ok(())
    }

    /// `recording` perturbed as asked, and what was done (for the report); unchanged without `--perturb`.
    pub fn apply(&self, recording: Recording) -> anyhow::Result<(Recording, serde_json::Value)> {
        let Some(names) = &self.perturb else {
            return Ok((recording, serde_json::Value::Null));
        };
        let perturbation = Perturbation::parse(names).context("invalid --perturb")?;
        let (perturbed, report) = perturbation.apply(&recording, self.perturb_seed);
        eprintln!(
            "perturbed ({names}, seed {}): {} of {} scans kept, {} slips, {} beams cut, {} cluttered",
            self.perturb_seed,
            report.scans_out,
            report.scans_in,
            report.slips,
            report.beams_cut,
            report.beams_cluttered
        );
        Ok((
            perturbed,
            serde_json::json!({
                "variant": names,
                "seed": self.perturb_seed,
                "done": report,
            }),
        ))
    }
}
