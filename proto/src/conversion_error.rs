//! Why a wire message could not become a `mapping` value.

use std::sync::Arc;

/// A wire message that cannot be converted: every variant names the message and field at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConversionError {
    /// A required (message-typed) field is absent.
    #[error("{message}.{field} is missing")]
    MissingField {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
    },
    /// A number is NaN or infinite.
    #[error("{message}.{field} is not a finite number")]
    NotFinite {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
    },
    /// A size does not match what the other fields imply, or exceeds a limit.
    #[error("{message}.{field} has a bad size: expected {expected}, got {got}")]
    BadSize {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// The size expected (or the limit).
        expected: usize,
        /// The size found.
        got: usize,
    },
    /// A value is outside its valid range (e.g. a non-positive resolution, an unknown enum value).
    #[error("{message}.{field} is out of range: {value}, expected {expected}")]
    OutOfRange {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// The offending value.
        value: FieldValue,
        /// What the field must be ("in [0, 1]", "a known ConstraintKind").
        expected: &'static str,
    },
    /// A `oneof` holds another kind than the one this exchange expects (a reply to another request).
    #[error("{message}.{field} is {got}, expected {expected}")]
    WrongKind {
        /// The message type.
        message: &'static str,
        /// The `oneof` field.
        field: &'static str,
        /// The kind expected.
        expected: &'static str,
        /// The kind found.
        got: &'static str,
    },
    /// A repeated field lists the same key twice: the encoder writes each once, so a repeat is damage.
    #[error("{message}.{field} lists {key} twice")]
    Duplicate {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// The repeated key, printed.
        key: String,
    },
    /// An item of a repeated field (or a message of a sequence of chunks) is where it may not be.
    #[error("{message}.{field}: item {index} is misplaced: {rule}")]
    Misplaced {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// The item's index (from 0).
        index: usize,
        /// The rule it breaks.
        rule: &'static str,
    },
    /// The fields are each valid but do not make a valid value together (a pose graph whose constraint
    /// names a missing variable); `source` is the `mapping` type's own refusal.
    #[error("{message}.{field} is invalid: {source}")]
    Invalid {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// Why: the error of the constructor that refused it.
        #[source]
        source: ErrorSource,
    },
    /// The record was written with a format version this build does not read.
    #[error(
        "{message} has format_version {got}, this build reads {}",
        readable_versions(*.oldest, *.newest)
    )]
    UnsupportedFormatVersion {
        /// The message type.
        message: &'static str,
        /// The version found.
        got: u32,
        /// The oldest version this build reads.
        oldest: u32,
        /// The version this build writes, the newest it reads.
        newest: u32,
    },
    /// The bytes are not a protobuf encoding of the message (a transport that carries raw bytes).
    #[error("{message} cannot be decoded: {source}")]
    Decode {
        /// The message type.
        message: &'static str,
        /// Why: the decoder's error.
        #[source]
        source: ErrorSource,
    },
    /// Compressed grid values could not be decompressed.
    #[error("{message}.{field} cannot be decompressed: {source}")]
    Decompress {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// Why: the decompressor's error.
        #[source]
        source: ErrorSource,
    },
}

/// The value of a field [`ConversionError::OutOfRange`] refuses, as the wire carries it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FieldValue {
    /// An unsigned integer (a count, a sequence number, a cell value).
    Unsigned(u64),
    /// A signed integer (an enum's wire value).
    Signed(i64),
    /// A floating-point number.
    Float(f64),
}

impl std::fmt::Display for FieldValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unsigned(v) => v.fmt(f),
            Self::Signed(v) => v.fmt(f),
            Self::Float(v) => v.fmt(f),
        }
    }
}

impl From<u64> for FieldValue {
    fn from(v: u64) -> Self {
        Self::Unsigned(v)
    }
}

impl From<u32> for FieldValue {
    fn from(v: u32) -> Self {
        Self::Unsigned(v.into())
    }
}

impl From<u16> for FieldValue {
    fn from(v: u16) -> Self {
        Self::Unsigned(v.into())
    }
}

impl From<i32> for FieldValue {
    fn from(v: i32) -> Self {
        Self::Signed(v.into())
    }
}

impl From<f64> for FieldValue {
    fn from(v: f64) -> Self {
        Self::Float(v)
    }
}

impl From<f32> for FieldValue {
    fn from(v: f32) -> Self {
        Self::Float(v.into())
    }
}

/// The underlying error of a [`ConversionError`], kept for `source()`. Shared, so that the error stays
/// `Clone`; compared by its message, as the `reason` string it replaced was, so that it stays
/// `PartialEq`. It displays as the error it holds and passes on that error's own source.
#[derive(Debug, Clone)]
pub struct ErrorSource(Arc<dyn std::error::Error + Send + Sync>);

impl ErrorSource {
    /// Keeps `error`.
    pub fn new(error: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self(Arc::new(error))
    }
}

impl PartialEq for ErrorSource {
    fn eq(&self, other: &Self) -> bool {
        self.0.to_string() == other.0.to_string()
    }
}

impl std::fmt::Display for ErrorSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

impl std::error::Error for ErrorSource {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.0.source()
    }
}

/// "only 3", "2 to 3".
fn readable_versions(oldest: u32, newest: u32) -> String {
    if oldest == newest {
        format!("only {newest}")
    } else {
        format!("{oldest} to {newest}")
    }
}
