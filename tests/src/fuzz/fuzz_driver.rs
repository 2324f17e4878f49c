//! Runs one target over mutated seeds: every seed once, then `inputs` mutated inputs (at most
//! `max_seconds`), each under `catch_unwind` with the heap it used measured. A panic, a heap above the
//! target's budget or (when asked) an input slower than `slow_input_s` is a finding; each distinct finding
//! (panic location, heap, slow) is shrunk with proptest's value tree to a small reproducer.
//!
//! Heap is measured by [`peak_alloc::PeakAlloc`], which must be the binary's global allocator
//! (`evermap-fuzz` and the fuzz test declare it); without it the report says the heap was not measured.

use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Mutex;
use std::time::Instant;

use peak_alloc::PeakAlloc;
use proptest::strategy::{Strategy as _, ValueTree as _};
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use serde_json::json;

use super::fuzz_target::{FuzzTarget, Verdict};
use super::mutation::{MutatedInput, mutated_inputs};

/// How long and how hard to fuzz one target.
#[derive(Clone, Debug)]
pub struct FuzzOptions {
    /// Mutated inputs to run (after the seeds), count. Default 1000.
    pub inputs: u64,
    /// Stop earlier after this many seconds of wall time. Default 600.
    pub max_seconds: f64,
    /// Seed of the mutation generator (same seed, same inputs). Default 1.
    pub rng_seed: u64,
    /// Report inputs slower than this, seconds; `None` (default) reports none (tests are never timed).
    pub slow_input_s: Option<f64>,
    /// Shrinking steps per distinct finding, count. Default 256.
    pub shrink_steps: u32,
}

impl Default for FuzzOptions {
    fn default() -> Self {
        Self {
            inputs: 1000,
            max_seconds: 600.0,
            rng_seed: 1,
            slow_input_s: None,
            shrink_steps: 256,
        }
    }
}

/// An invalid [`FuzzOptions`] field.
#[derive(Debug, thiserror::Error)]
#[error("fuzz options: {field} must be positive and finite, got {value}")]
pub struct FuzzOptionsError {
    /// The field.
    pub field: &'static str,
    /// Its value.
    pub value: f64,
}

impl FuzzOptions {
    /// Checks the options.
    pub fn validate(&self) -> Result<(), FuzzOptionsError> {
        let positive = |field, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(FuzzOptionsError { field, value })
            }
        };
        positive("max_seconds", self.max_seconds)?;
        if let Some(s) = self.slow_input_s {
            positive("slow_input_s", s)?;
        }
        Ok(())
    }
}

/// What kind of trouble an input caused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum FindingKind {
    /// The decoder panicked (or an invariant of its output broke).
    Panic,
    /// The decoder used more heap than the target's budget for the input's size.
    Heap,
    /// The input took longer than `slow_input_s`.
    Slow,
}

/// One distinct finding, with its smallest reproducer.
#[derive(Clone, Debug)]
pub struct Finding {
    /// Kind.
    pub kind: FindingKind,
    /// What tells findings apart: the panic's location, or the kind.
    pub key: String,
    /// The panic message, heap used or time taken, for the smallest reproducer.
    pub message: String,
    /// Inputs that hit it.
    pub hits: u64,
    /// The smallest reproducer found.
    pub input: Vec<u8>,
    /// The seed and mutations that make it.
    pub recipe: String,
}

/// The result of fuzzing one target.
#[derive(Clone, Debug)]
pub struct FuzzReport {
    /// Target name.
    pub target: &'static str,
    /// What it decodes.
    pub what: &'static str,
    /// Inputs run (seeds included), count.
    pub inputs: u64,
    /// Inputs decoded.
    pub accepted: u64,
    /// Inputs refused with an error.
    pub rejected: u64,
    /// Wall time of the inputs, mutation included and shrinking excluded, seconds.
    pub seconds: f64,
    /// Largest heap one input used, bytes (0 when not measured).
    pub max_heap_bytes: usize,
    /// Whether heap was measured (the global allocator is `PeakAlloc`).
    pub heap_measured: bool,
    /// The slowest input, seconds.
    pub slowest_input_s: f64,
    /// Distinct findings.
    pub findings: Vec<Finding>,
}

impl FuzzReport {
    /// Inputs per second.
    pub fn inputs_per_s(&self) -> f64 {
        if self.seconds > 0.0 {
            self.inputs as f64 / self.seconds
        } else {
            0.0
        }
    }

    /// The report as JSON (findings without their input bytes).
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "target": self.target,
            "what": self.what,
            "inputs": self.inputs,
            "accepted": self.accepted,
            "rejected": self.rejected,
            "seconds": self.seconds,
            "inputs_per_s": self.inputs_per_s(),
            "max_heap_bytes": self.heap_measured.then_some(self.max_heap_bytes),
            "slowest_input_s": self.slowest_input_s,
            "findings": self.findings.iter().map(|f| json!({
                "kind": format!("{:?}", f.kind),
                "key": f.key,
                "message": f.message,
                "hits": f.hits,
                "input_bytes": f.input.len(),
                "recipe": f.recipe,
            })).collect::<Vec<_>>(),
        })
    }
}

/// The message and location of the last panic on this process (set by the driver's panic hook).
static LAST_PANIC: Mutex<Option<(String, String)>> = Mutex::new(None);

struct Run {
    verdict: Option<Verdict>,
    panic: Option<(String, String)>,
    heap: usize,
    seconds: f64,
}

fn run_one(target: &mut FuzzTarget, input: &[u8]) -> Run {
    if let Ok(mut last) = LAST_PANIC.lock() {
        *last = None;
    }
    PeakAlloc.reset_peak_usage();
    let base = PeakAlloc.current_usage();
    let started = Instant::now();
    let result = catch_unwind(AssertUnwindSafe(|| (target.run)(input)));
    let seconds = started.elapsed().as_secs_f64();
    let heap = PeakAlloc.peak_usage().saturating_sub(base);
    match result {
        // A panic on another thread during the input (a server worker, a blocking task) is a finding too.
        Ok(verdict) => Run {
            verdict: Some(verdict),
            panic: LAST_PANIC
                .lock()
                .ok()
                .and_then(|mut last| last.take())
                .map(|(location, message)| (location, format!("on another thread: {message}"))),
            heap,
            seconds,
        },
        Err(payload) => {
            let hooked = LAST_PANIC.lock().ok().and_then(|mut last| last.take());
            let panic = hooked.unwrap_or_else(|| {
                let message = payload
                    .downcast_ref::<&str>()
                    .map(|s| (*s).to_owned())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "non-string panic payload".to_owned());
                ("unknown location".to_owned(), message)
            });
            Run {
                verdict: None,
                panic: Some(panic),
                heap,
                seconds,
            }
        }
    }
}

/// The finding an input makes, if any: (kind, key, message).
fn classify(
    target: &FuzzTarget,
    options: &FuzzOptions,
    len: usize,
    run: &Run,
) -> Option<(FindingKind, String, String)> {
    if let Some((location, message)) = &run.panic {
        return Some((FindingKind::Panic, location.clone(), message.clone()));
    }
    let budget = target.heap_budget(len);
    if run.heap > budget {
        return Some((
            FindingKind::Heap,
            "heap".to_owned(),
            format!(
                "{} bytes of heap for a {len}-byte input (budget {budget})",
                run.heap
            ),
        ));
    }
    if let Some(limit) = options.slow_input_s
        && run.seconds > limit
    {
        return Some((
            FindingKind::Slow,
            "slow".to_owned(),
            format!(
                "{:.3} s for a {len}-byte input (limit {limit} s)",
                run.seconds
            ),
        ));
    }
    None
}

fn rng(seed: u64) -> TestRng {
    let mut bytes = [0_u8; 32];
    for (i, chunk) in bytes.chunks_mut(8).enumerate() {
        chunk.copy_from_slice(
            &seed
                .wrapping_add((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
                .to_le_bytes(),
        );
    }
    TestRng::from_seed(RngAlgorithm::ChaCha, &bytes)
}

fn materialize(target: &FuzzTarget, input: &MutatedInput) -> Vec<u8> {
    let mut bytes = input.apply(&target.seeds);
    if let Some(fixup) = target.fixup {
        fixup(&mut bytes);
    }
    bytes
}

/// Fuzzes `target` as `options` say. Installs a quiet panic hook for the duration (panics become
/// findings, not noise) and restores the previous one.
pub fn fuzz(target: &mut FuzzTarget, options: &FuzzOptions) -> FuzzReport {
    // `EVERMAP_FUZZ_PRINT_PANICS=1`: print every panic as it happens (any thread), to debug a finding.
    let print_panics = std::env::var_os("EVERMAP_FUZZ_PRINT_PANICS").is_some();
    let previous_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let location = info
            .location()
            .map_or_else(|| "unknown location".to_owned(), ToString::to_string);
        let message = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| (*s).to_owned())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "non-string panic payload".to_owned());
        if print_panics {
            eprintln!(
                "panic at {location}: {message}\n{}",
                std::backtrace::Backtrace::force_capture()
            );
        }
        if let Ok(mut last) = LAST_PANIC.lock() {
            *last = Some((location, message));
        }
    }));
    // A panic of the harness itself (not of the target) must not leave the quiet hook installed.
    let report = catch_unwind(AssertUnwindSafe(|| fuzz_quietly(target, options)));
    std::panic::set_hook(previous_hook);
    report.unwrap_or_else(|payload| std::panic::resume_unwind(payload))
}

fn fuzz_quietly(target: &mut FuzzTarget, options: &FuzzOptions) -> FuzzReport {
    let heap_measured = PeakAlloc.current_usage() > 0;
    let mut report = FuzzReport {
        target: target.name,
        what: target.what,
        inputs: 0,
        accepted: 0,
        rejected: 0,
        seconds: 0.0,
        max_heap_bytes: 0,
        heap_measured,
        slowest_input_s: 0.0,
        findings: Vec::new(),
    };
    // Distinct findings by (kind, key): index into report.findings.
    let mut seen: BTreeMap<(FindingKind, String), usize> = BTreeMap::new();
    let record = |report: &mut FuzzReport, run: &Run| {
        report.inputs += 1;
        report.max_heap_bytes = report.max_heap_bytes.max(run.heap);
        report.slowest_input_s = report.slowest_input_s.max(run.seconds);
        match &run.verdict {
            Some(Verdict::Accepted) => report.accepted += 1,
            Some(Verdict::Rejected(_)) => report.rejected += 1,
            None => {}
        }
    };

    let started = Instant::now();
    let mut shrinking_s = 0.0;
    let seeds = target.seeds.clone();
    for (index, seed) in seeds.iter().enumerate() {
        let run = run_one(target, seed);
        record(&mut report, &run);
        if let Some((kind, key, message)) = classify(target, options, seed.len(), &run) {
            let entry = seen.entry((kind, key.clone())).or_insert_with(|| {
                report.findings.push(Finding {
                    kind,
                    key,
                    message,
                    hits: 0,
                    input: seed.clone(),
                    recipe: format!("seed {index} unchanged"),
                });
                report.findings.len() - 1
            });
            report.findings[*entry].hits += 1;
        }
    }

    let strategy = mutated_inputs(target.seeds.len(), target.text);
    let mut runner = TestRunner::new_with_rng(Config::default(), rng(options.rng_seed));
    for _ in 0..options.inputs {
        if started.elapsed().as_secs_f64() - shrinking_s > options.max_seconds {
            break;
        }
        let Ok(mut tree) = strategy.new_tree(&mut runner) else {
            break;
        };
        let bytes = materialize(target, &tree.current());
        let run = run_one(target, &bytes);
        record(&mut report, &run);
        let Some((kind, key, message)) = classify(target, options, bytes.len(), &run) else {
            continue;
        };
        if let Some(&index) = seen.get(&(kind, key.clone())) {
            report.findings[index].hits += 1;
            continue;
        }
        // A new finding: shrink it while it stays the same finding.
        let shrink_started = Instant::now();
        let mut smallest = (bytes, message, format!("{:?}", tree.current()));
        let mut failing = true;
        for _ in 0..options.shrink_steps {
            let moved = if failing {
                tree.simplify()
            } else {
                tree.complicate()
            };
            if !moved {
                break;
            }
            let candidate = materialize(target, &tree.current());
            let run = run_one(target, &candidate);
            failing = match classify(target, options, candidate.len(), &run) {
                Some((k2, key2, message2)) if k2 == kind && key2 == key => {
                    if candidate.len() <= smallest.0.len() {
                        smallest = (candidate, message2, format!("{:?}", tree.current()));
                    }
                    true
                }
                _ => false,
            };
        }
        shrinking_s += shrink_started.elapsed().as_secs_f64();
        seen.insert((kind, key.clone()), report.findings.len());
        report.findings.push(Finding {
            kind,
            key,
            message: smallest.1,
            hits: 1,
            input: smallest.0,
            recipe: smallest.2,
        });
    }
    report.seconds = (started.elapsed().as_secs_f64() - shrinking_s).max(0.0);
    report
}
