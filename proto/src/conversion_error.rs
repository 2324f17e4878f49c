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
    #[error("{message}.{field} is out of range: {value}")]
    OutOfRange {
        /// The message type.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// The offending value, printed.
        value: String,
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
