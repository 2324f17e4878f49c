//! Shared test values (`cfg(test)`, or the `testing` feature for other crates' tests).

use crate::SessionStartCounts;

/// Session-start counts whose every field holds a different nonzero value (1 to 7, in field order), so a
/// conversion that drops or swaps a field shows in a round trip.
pub fn distinct_session_start_counts() -> SessionStartCounts {
    SessionStartCounts {
        priors: 1,
        placed: 2,
        refused: 3,
        retries: 4,
        committed: 5,
        revoked: 6,
        gave_up: 7,
    }
}
