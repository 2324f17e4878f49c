//! One fuzz target: a decoder, its seeds and what its output must satisfy.

/// What a decoder made of one input. A broken invariant of an accepted input is a panic in the target
/// (`assert!`), so it is reported as a finding like any other panic.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Decoded (and its invariants hold).
    Accepted,
    /// Refused with an error (the error's text).
    Rejected(String),
}

impl Verdict {
    /// `Accepted` for `Ok`, `Rejected` with the error's text for `Err`.
    pub fn of<T, E: std::fmt::Display>(result: &Result<T, E>) -> Self {
        match result {
            Ok(_) => Self::Accepted,
            Err(e) => Self::Rejected(e.to_string()),
        }
    }
}

/// The decoder under test: called once per input.
pub type RunFn = Box<dyn FnMut(&[u8]) -> Verdict>;

/// Repairs an input after mutation (e.g. recomputes checksums so the mutation reaches past them).
pub type FixupFn = fn(&mut [u8]);

/// A decoder, its seed inputs and its limits.
pub struct FuzzTarget {
    /// Short name (`ros1_bag`, `g2o`, ...).
    pub name: &'static str,
    /// What is decoded, for the report.
    pub what: &'static str,
    /// Seed inputs (real files or messages), mutated into the inputs.
    pub seeds: Vec<Vec<u8>>,
    /// Text format: mutations insert hostile number tokens too.
    pub text: bool,
    /// Heap a decoder may use per input byte on top of [`FuzzTarget::base_heap_bytes`] before the
    /// input counts as an unbounded allocation (decompressing formats need more than 1).
    pub heap_per_input_byte: usize,
    /// Heap any input may use, bytes.
    pub base_heap_bytes: usize,
    /// Applied to every mutated input (and never to a seed), if set.
    pub fixup: Option<FixupFn>,
    /// Decodes one input.
    pub run: RunFn,
}

impl FuzzTarget {
    /// A target with the default limits (32 MiB plus 64 bytes of heap per input byte) and no fixup.
    pub fn new(
        name: &'static str,
        what: &'static str,
        seeds: Vec<Vec<u8>>,
        text: bool,
        run: RunFn,
    ) -> Self {
        Self {
            name,
            what,
            seeds,
            text,
            heap_per_input_byte: 64,
            base_heap_bytes: 32 << 20,
            fixup: None,
            run,
        }
    }

    /// The heap one input of `len` bytes may use before it is reported.
    pub fn heap_budget(&self, len: usize) -> usize {
        self.base_heap_bytes
            .saturating_add(self.heap_per_input_byte.saturating_mul(len))
    }
}
