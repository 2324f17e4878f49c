//! Mutations of seed inputs: byte flips, truncation, deletion, insertion, splices (from the input itself or
//! another seed), length fields blown up (u32 little-endian and protobuf varints) and, for text formats,
//! hostile number tokens. Positions are [`Index`]es, scaled to the input's length when applied, so a
//! mutation list stays meaningful while proptest shrinks it.

use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::Index;

/// u32 values that break length fields: zero, one past small sizes, sign bits, the maximum.
const HOSTILE_U32: [u32; 10] = [
    0,
    1,
    0xFF,
    0xFFFF,
    0x0010_0000,
    0x7FFF_FFFF,
    0x8000_0000,
    0xFFFF_FFF0,
    0xFFFF_FFFE,
    0xFFFF_FFFF,
];

/// Tokens that break text parsers: non-finite and out-of-range numbers, signs, separators.
const HOSTILE_TOKENS: [&str; 16] = [
    " nan ",
    " inf ",
    " -inf ",
    " 1e308 ",
    " -1 ",
    " 4294967295 ",
    " 4294967296 ",
    " 18446744073709551615 ",
    " 18446744073709551616 ",
    " 9999999999999999999999 ",
    " 0 ",
    " -0 ",
    "\n",
    " ",
    "#",
    "=",
];

/// One change to an input.
#[derive(Clone, Debug)]
pub enum Mutation {
    /// Flip one bit.
    FlipBit {
        /// Where.
        at: Index,
        /// Which bit (0–7).
        bit: u8,
    },
    /// Overwrite one byte.
    SetByte {
        /// Where.
        at: Index,
        /// The new value.
        value: u8,
    },
    /// Cut the input at a position.
    Truncate {
        /// Where.
        at: Index,
    },
    /// Remove up to `len` bytes.
    Delete {
        /// Where.
        at: Index,
        /// How many bytes at most.
        len: usize,
    },
    /// Insert bytes.
    Insert {
        /// Where.
        at: Index,
        /// What.
        bytes: Vec<u8>,
    },
    /// Copy a range of the input to another place (overwriting), as a repeated record would.
    Duplicate {
        /// Start of the copied range.
        from: Index,
        /// Length of the copied range.
        len: usize,
        /// Where it is inserted.
        to: Index,
    },
    /// Insert a range of another seed.
    Splice {
        /// Which seed.
        seed: Index,
        /// Start of the range in that seed.
        from: Index,
        /// Length of the range.
        len: usize,
        /// Where it is inserted.
        to: Index,
    },
    /// Overwrite four bytes with a hostile little-endian u32 (a length, count or offset field blown up).
    BlowU32 {
        /// Where.
        at: Index,
        /// Which of [`HOSTILE_U32`].
        value: Index,
    },
    /// Overwrite four bytes near the start (file and record headers live there) with a hostile u32.
    BlowHeaderU32 {
        /// Offset from the start, bytes.
        at: usize,
        /// Which of [`HOSTILE_U32`].
        value: Index,
    },
    /// Overwrite bytes with a protobuf varint of a huge value (a length-delimited field blown up).
    BlowVarint {
        /// Where.
        at: Index,
        /// The value.
        value: u64,
    },
    /// Insert a hostile text token (text formats only).
    Token {
        /// Where.
        at: Index,
        /// Which of [`HOSTILE_TOKENS`].
        token: Index,
    },
}

/// A seed and the mutations applied to it, in order.
#[derive(Clone, Debug)]
pub struct MutatedInput {
    /// Index of the seed.
    pub seed: usize,
    /// The mutations.
    pub mutations: Vec<Mutation>,
}

/// Largest range a delete, duplicate or splice moves, bytes.
const MAX_RANGE: usize = 4096;
/// Largest random insertion, bytes.
const MAX_INSERT: usize = 64;
/// How far from the start [`Mutation::BlowHeaderU32`] reaches, bytes.
const HEADER_BYTES: usize = 128;
/// Most mutations per input (few, so that many inputs stay close enough to valid to get deep).
const MAX_MUTATIONS: usize = 4;

fn mutation(text: bool) -> BoxedStrategy<Mutation> {
    let binary = prop_oneof![
        3 => (any::<Index>(), 0..8u8).prop_map(|(at, bit)| Mutation::FlipBit { at, bit }),
        2 => (any::<Index>(), any::<u8>()).prop_map(|(at, value)| Mutation::SetByte { at, value }),
        1 => any::<Index>().prop_map(|at| Mutation::Truncate { at }),
        2 => (any::<Index>(), 1..MAX_RANGE).prop_map(|(at, len)| Mutation::Delete { at, len }),
        1 => (any::<Index>(), vec(any::<u8>(), 1..MAX_INSERT))
            .prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        1 => (any::<Index>(), 1..MAX_RANGE, any::<Index>())
            .prop_map(|(from, len, to)| Mutation::Duplicate { from, len, to }),
        1 => (any::<Index>(), any::<Index>(), 1..MAX_RANGE, any::<Index>())
            .prop_map(|(seed, from, len, to)| Mutation::Splice { seed, from, len, to }),
        3 => (any::<Index>(), any::<Index>()).prop_map(|(at, value)| Mutation::BlowU32 { at, value }),
        2 => (0..HEADER_BYTES, any::<Index>())
            .prop_map(|(at, value)| Mutation::BlowHeaderU32 { at, value }),
        2 => (any::<Index>(), prop_oneof![Just(u64::MAX), Just(1 << 32), Just(1 << 31), 1u64 << 20..1u64 << 40])
            .prop_map(|(at, value)| Mutation::BlowVarint { at, value }),
    ];
    if text {
        prop_oneof![
            3 => binary,
            2 => (any::<Index>(), any::<Index>()).prop_map(|(at, token)| Mutation::Token { at, token }),
        ]
        .boxed()
    } else {
        binary.boxed()
    }
}

/// Inputs made from `seed_count` seeds with 1 to 4 mutations each (`text`: hostile tokens too).
pub fn mutated_inputs(seed_count: usize, text: bool) -> BoxedStrategy<MutatedInput> {
    (0..seed_count.max(1), vec(mutation(text), 1..=MAX_MUTATIONS))
        .prop_map(|(seed, mutations)| MutatedInput { seed, mutations })
        .boxed()
}

/// A position in `0..=len` (`len` itself is the end).
fn position(at: Index, len: usize) -> usize {
    at.index(len + 1)
}

fn varint(mut value: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(10);
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
    out
}

fn overwrite(bytes: &mut Vec<u8>, at: usize, with: &[u8]) {
    let end = (at + with.len()).min(bytes.len());
    bytes.splice(at..end, with.iter().copied());
}

impl MutatedInput {
    /// Applies the mutations to a copy of its seed.
    pub fn apply(&self, seeds: &[Vec<u8>]) -> Vec<u8> {
        let mut bytes = seeds.get(self.seed).cloned().unwrap_or_default();
        for m in &self.mutations {
            apply_one(&mut bytes, m, seeds);
        }
        bytes
    }
}

fn apply_one(bytes: &mut Vec<u8>, m: &Mutation, seeds: &[Vec<u8>]) {
    let len = bytes.len();
    match m {
        Mutation::FlipBit { at, bit } => {
            if len > 0 {
                bytes[at.index(len)] ^= 1 << bit;
            }
        }
        Mutation::SetByte { at, value } => {
            if len > 0 {
                bytes[at.index(len)] = *value;
            }
        }
        Mutation::Truncate { at } => bytes.truncate(position(*at, len)),
        Mutation::Delete { at, len: n } => {
            let start = position(*at, len);
            bytes.drain(start..(start + n).min(len));
        }
        Mutation::Insert { at, bytes: new } => {
            let at = position(*at, len);
            bytes.splice(at..at, new.iter().copied());
        }
        Mutation::Duplicate { from, len: n, to } => {
            if len > 0 {
                let start = from.index(len);
                let range = bytes[start..(start + n).min(len)].to_vec();
                let to = position(*to, len);
                bytes.splice(to..to, range);
            }
        }
        Mutation::Splice {
            seed,
            from,
            len: n,
            to,
        } => {
            if seeds.is_empty() {
                return;
            }
            let other = &seeds[seed.index(seeds.len())];
            if other.is_empty() {
                return;
            }
            let start = from.index(other.len());
            let range = &other[start..(start + n).min(other.len())];
            let to = position(*to, len);
            bytes.splice(to..to, range.iter().copied());
        }
        Mutation::BlowU32 { at, value } => {
            let value = HOSTILE_U32[value.index(HOSTILE_U32.len())];
            overwrite(bytes, position(*at, len), &value.to_le_bytes());
        }
        Mutation::BlowHeaderU32 { at, value } => {
            let value = HOSTILE_U32[value.index(HOSTILE_U32.len())];
            overwrite(bytes, (*at).min(len), &value.to_le_bytes());
        }
        Mutation::BlowVarint { at, value } => {
            overwrite(bytes, position(*at, len), &varint(*value));
        }
        Mutation::Token { at, token } => {
            let token = HOSTILE_TOKENS[token.index(HOSTILE_TOKENS.len())];
            let at = position(*at, len);
            bytes.splice(at..at, token.bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    use proptest::strategy::ValueTree as _;
    use proptest::test_runner::TestRunner;

    use super::*;

    #[test]
    fn mutations_change_inputs_and_never_panic() {
        let seeds = vec![b"VERTEX_SE2 0 1 2 3\n".to_vec(), vec![7; 100], Vec::new()];
        let strategy = mutated_inputs(seeds.len(), true);
        let mut runner = TestRunner::deterministic();
        let mut changed = 0;
        for _ in 0..500 {
            let input = strategy.new_tree(&mut runner).unwrap().current();
            let bytes = input.apply(&seeds);
            if bytes != seeds[input.seed] {
                changed += 1;
            }
        }
        assert!(
            changed > 400,
            "only {changed} of 500 inputs differ from their seed"
        );
    }

    #[test]
    fn varints_and_hostile_lengths_are_written_in_place() {
        assert_eq!(varint(300), vec![0xAC, 0x02]);
        let mut bytes = vec![0_u8; 6];
        overwrite(&mut bytes, 1, &u32::MAX.to_le_bytes());
        assert_eq!(bytes, vec![0, 0xFF, 0xFF, 0xFF, 0xFF, 0]);
        overwrite(&mut bytes, 5, &[1, 2]);
        assert_eq!(bytes, vec![0, 0xFF, 0xFF, 0xFF, 0xFF, 1, 2]);
    }
}
