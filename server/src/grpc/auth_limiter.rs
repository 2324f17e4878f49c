//! A wrong token costs the caller, not the server: each (peer address, site) may fail authentication at
//! most `max_failures` times per window of `window_s` seconds; past that, its requests for that site are
//! refused with `RESOURCE_EXHAUSTED` before the token is even looked at, until the window ends. A
//! fixed-window counter (not a token bucket): one integer and one instant per tracked pair, and an
//! attacker guessing tokens gets `max_failures` guesses per window whatever it does.
//!
//! The peer is the TCP peer's IP address as gRPC sees it (the port is ignored: a new connection is not a
//! new peer). Requests arriving through the zenoh front end carry no peer address (the server only sees
//! the router): they share one counter per site, so a robot of a site that keeps failing slows down its
//! own site's zenoh requests and nobody else's — with the router's access control (`deploy/zenohd.json5`)
//! only that site's own certified robots can reach its key expressions in the first place.
//!
//! Memory is bounded: at most `max_tracked` pairs are counted. When the table is full, expired windows
//! are dropped; if it is still full, a new pair is not counted (its failures are then only refused, not
//! limited) rather than evicting a pair that is being limited.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use serde::Deserialize;

/// Limits on failed authentications (TOML section `[auth]` of the server configuration).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuthLimitOptions {
    /// Failed authentications (unknown token, or a token of another site or robot) one peer may make for
    /// one site per window, count; the next requests are refused unchecked until the window ends.
    /// 0 = no limit. Default 10.
    pub max_failures: u32,
    /// The window, seconds (> 0). Default 60.
    pub window_s: f64,
    /// (peer, site) pairs counted at once, count (≥ 1): bounds the table's memory. Default 65536.
    pub max_tracked: usize,
}

impl Default for AuthLimitOptions {
    fn default() -> Self {
        Self {
            max_failures: 10,
            window_s: 60.0,
            max_tracked: 65536,
        }
    }
}

/// Invalid [`AuthLimitOptions`].
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("auth.{field}: {reason}")]
pub struct AuthLimitOptionsError {
    /// The offending field.
    pub field: &'static str,
    /// Why.
    pub reason: &'static str,
}

impl AuthLimitOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), AuthLimitOptionsError> {
        if self.window().is_none() {
            return Err(AuthLimitOptionsError {
                field: "window_s",
                reason: "must be a number of seconds > 0",
            });
        }
        if self.max_tracked == 0 {
            return Err(AuthLimitOptionsError {
                field: "max_tracked",
                reason: "must be at least 1",
            });
        }
        Ok(())
    }

    fn window(&self) -> Option<Duration> {
        Duration::try_from_secs_f64(self.window_s)
            .ok()
            .filter(|d| !d.is_zero())
    }
}

/// Who failed: the peer's IP address (`None` through zenoh) and the site asked for.
type PeerSite = (Option<IpAddr>, String);

#[derive(Clone, Copy, Debug)]
struct Window {
    start: Instant,
    failures: u32,
}

/// The failure counters. Thread-safe (one short lock per check).
#[derive(Debug)]
pub struct AuthLimiter {
    max_failures: u32,
    window: Duration,
    max_tracked: usize,
    windows: Mutex<HashMap<PeerSite, Window>>,
}

impl Default for AuthLimiter {
    fn default() -> Self {
        Self::new(&AuthLimitOptions::default())
    }
}

impl AuthLimiter {
    /// Counters with `options` (invalid options fall back to the defaults' window and table size; call
    /// [`AuthLimitOptions::validate`] first).
    pub fn new(options: &AuthLimitOptions) -> Self {
        let defaults = AuthLimitOptions::default();
        Self {
            max_failures: options.max_failures,
            window: options
                .window()
                .or_else(|| defaults.window())
                .unwrap_or(Duration::from_secs(60)),
            max_tracked: options.max_tracked.max(1),
            windows: Mutex::new(HashMap::new()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<PeerSite, Window>> {
        // A panic while holding the lock cannot leave the counters inconsistent (plain integers).
        self.windows
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// `Err(wait)` if `peer` has used up its failures for `site` in the current window (retry after
    /// `wait`), `Ok(())` if its token may be checked.
    pub fn check(&self, peer: Option<IpAddr>, site: &str, now: Instant) -> Result<(), Duration> {
        if self.max_failures == 0 {
            return Ok(());
        }
        let windows = self.lock();
        let Some(window) = windows.get(&(peer, site.to_owned())) else {
            return Ok(());
        };
        let elapsed = now.saturating_duration_since(window.start);
        if elapsed < self.window && window.failures >= self.max_failures {
            Err(self.window.saturating_sub(elapsed))
        } else {
            Ok(())
        }
    }

    /// Counts one failed authentication of `peer` for `site`.
    pub fn record_failure(&self, peer: Option<IpAddr>, site: &str, now: Instant) {
        if self.max_failures == 0 {
            return;
        }
        let mut windows = self.lock();
        let key = (peer, site.to_owned());
        if !windows.contains_key(&key) && windows.len() >= self.max_tracked {
            let window = self.window;
            windows.retain(|_, w| now.saturating_duration_since(w.start) < window);
            if windows.len() >= self.max_tracked {
                return;
            }
        }
        let entry = windows.entry(key).or_insert(Window {
            start: now,
            failures: 0,
        });
        if now.saturating_duration_since(entry.start) >= self.window {
            *entry = Window {
                start: now,
                failures: 0,
            };
        }
        entry.failures = entry.failures.saturating_add(1);
    }

    /// Pairs currently counted.
    pub fn tracked(&self) -> usize {
        self.lock().len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limiter(max_failures: u32, max_tracked: usize) -> AuthLimiter {
        AuthLimiter::new(&AuthLimitOptions {
            max_failures,
            window_s: 60.0,
            max_tracked,
        })
    }

    #[test]
    fn failures_past_the_limit_are_refused_until_the_window_ends() {
        let limiter = limiter(3, 16);
        let t0 = Instant::now();
        let peer = Some(IpAddr::from([10, 0, 0, 7]));
        for i in 0..3 {
            assert_eq!(limiter.check(peer, "a", t0), Ok(()), "failure {i}");
            limiter.record_failure(peer, "a", t0 + Duration::from_secs(i));
        }
        let wait = limiter.check(peer, "a", t0 + Duration::from_secs(10));
        assert_eq!(wait, Err(Duration::from_secs(50)));
        // Another site, another peer, and zenoh (no peer) are counted apart.
        assert_eq!(limiter.check(peer, "b", t0), Ok(()));
        assert_eq!(
            limiter.check(Some(IpAddr::from([10, 0, 0, 8])), "a", t0),
            Ok(())
        );
        assert_eq!(limiter.check(None, "a", t0), Ok(()));
        // The window ends: the peer may try again, and its count starts over.
        let later = t0 + Duration::from_secs(60);
        assert_eq!(limiter.check(peer, "a", later), Ok(()));
        limiter.record_failure(peer, "a", later);
        assert_eq!(limiter.check(peer, "a", later), Ok(()));
    }

    #[test]
    fn zero_means_no_limit_and_the_table_is_bounded() {
        let unlimited = limiter(0, 16);
        let t0 = Instant::now();
        for _ in 0..100 {
            unlimited.record_failure(None, "a", t0);
        }
        assert_eq!(unlimited.check(None, "a", t0), Ok(()));
        assert_eq!(unlimited.tracked(), 0);

        let small = limiter(1, 4);
        for i in 0..10_u8 {
            small.record_failure(Some(IpAddr::from([10, 0, 0, i])), "a", t0);
        }
        assert_eq!(small.tracked(), 4, "full table: new peers are not counted");
        assert!(
            small
                .check(Some(IpAddr::from([10, 0, 0, 0])), "a", t0)
                .is_err()
        );
        // Once their windows have expired, old pairs make room.
        let later = t0 + Duration::from_secs(61);
        small.record_failure(Some(IpAddr::from([10, 0, 0, 9])), "a", later);
        assert_eq!(small.tracked(), 1);
        assert!(
            small
                .check(Some(IpAddr::from([10, 0, 0, 9])), "a", later)
                .is_err()
        );
    }

    #[test]
    fn bad_options_are_named() {
        assert_eq!(AuthLimitOptions::default().validate(), Ok(()));
        let zero_window = AuthLimitOptions {
            window_s: 0.0,
            ..AuthLimitOptions::default()
        };
        assert_eq!(zero_window.validate().unwrap_err().field, "window_s");
        let nan = AuthLimitOptions {
            window_s: f64::NAN,
            ..AuthLimitOptions::default()
        };
        assert_eq!(nan.validate().unwrap_err().field, "window_s");
        let no_table = AuthLimitOptions {
            max_tracked: 0,
            ..AuthLimitOptions::default()
        };
        assert_eq!(no_table.validate().unwrap_err().field, "max_tracked");
    }
}
