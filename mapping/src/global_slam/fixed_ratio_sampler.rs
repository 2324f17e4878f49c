//! Deterministic subsampling at a fixed ratio.

/// Accepts a fixed fraction of the events it is asked about, spread evenly and deterministically
/// (unlike a random sampler, two runs on the same data search the same loop closures).
#[derive(Clone, Debug, PartialEq)]
pub struct FixedRatioSampler {
    ratio: f64,
    num_pulses: u64,
    num_samples: u64,
}

impl FixedRatioSampler {
    /// A sampler accepting `ratio ∈ [0, 1]` of the pulses.
    pub fn new(ratio: f64) -> Self {
        Self {
            ratio: ratio.clamp(0.0, 1.0),
            num_pulses: 0,
            num_samples: 0,
        }
    }

    /// A sampler that has seen `num_pulses` events and taken `num_samples` of them (a checkpoint's; see
    /// [`Self::ratio`] and [`Self::counts`]).
    pub fn from_counts(ratio: f64, num_pulses: u64, num_samples: u64) -> Self {
        Self {
            ratio: ratio.clamp(0.0, 1.0),
            num_pulses,
            num_samples,
        }
    }

    /// The fraction it takes.
    pub fn ratio(&self) -> f64 {
        self.ratio
    }

    /// `(events seen, events taken)`.
    pub fn counts(&self) -> (u64, u64) {
        (self.num_pulses, self.num_samples)
    }

    /// Registers one event and says whether to take it.
    pub fn pulse(&mut self) -> bool {
        self.num_pulses += 1;
        if (self.num_samples as f64) / (self.num_pulses as f64) < self.ratio {
            self.num_samples += 1;
            true
        } else {
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn takes_the_requested_fraction() {
        for ratio in [0.0, 0.1, 0.3, 1.0] {
            let mut s = FixedRatioSampler::new(ratio);
            let taken = (0..1000).filter(|_| s.pulse()).count();
            assert!(
                (taken as f64 - 1000.0 * ratio).abs() <= 1.0,
                "ratio {ratio}: took {taken}"
            );
        }
    }
}
