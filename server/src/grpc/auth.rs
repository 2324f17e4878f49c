//! Bearer-token authentication: each robot's token grants access to exactly one site, and a peer that
//! keeps failing is refused unchecked for a while ([`AuthLimiter`]). Tokens never appear in a status
//! message or a log line.

use std::collections::{BTreeSet, HashMap};
use std::net::IpAddr;
use std::time::Instant;

use tonic::Status;
use tonic::metadata::MetadataMap;

use super::auth_limiter::{AuthLimitOptions, AuthLimiter};
use crate::server_config::SiteConfig;

/// What a token allows.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Grant {
    /// The only site the token may read and write.
    pub site: String,
    /// The robot the token belongs to (uploads must name it).
    pub robot_id: String,
}

/// Tokens of every configured robot, and the failure counters.
#[derive(Debug, Default)]
pub struct Auth {
    grants: HashMap<String, Grant>,
    sites: BTreeSet<String>,
    limiter: AuthLimiter,
}

impl Auth {
    /// The tokens of the configured sites' robots, failures limited by `AuthLimitOptions::default()`.
    pub fn from_sites(sites: &[SiteConfig]) -> Self {
        Self::with_limits(sites, &AuthLimitOptions::default())
    }

    /// The tokens of the configured sites' robots, failures limited by `limits`.
    pub fn with_limits(sites: &[SiteConfig], limits: &AuthLimitOptions) -> Self {
        let grants = sites
            .iter()
            .flat_map(|site| {
                site.robots.iter().map(|robot| {
                    (
                        robot.token.clone(),
                        Grant {
                            site: site.id.clone(),
                            robot_id: robot.id.clone(),
                        },
                    )
                })
            })
            .collect();
        Self {
            grants,
            sites: sites.iter().map(|s| s.id.clone()).collect(),
            limiter: AuthLimiter::new(limits),
        }
    }

    /// The failure counters' key for `site`: itself if configured, else one shared key (so that made-up
    /// site names cannot grow the table).
    fn limit_key<'a>(&self, site: &'a str) -> &'a str {
        if self.sites.contains(site) { site } else { "" }
    }

    /// Refuses `peer` unchecked while it is over its failure limit for `site`.
    fn check_limit(&self, peer: Option<IpAddr>, site: &str, now: Instant) -> Result<(), Status> {
        self.limiter
            .check(peer, self.limit_key(site), now)
            .map_err(|wait| {
                Status::resource_exhausted(format!(
                    "too many failed authentications from this peer for site {site:?}: \
                     retry in {} s",
                    wait.as_secs() + 1
                ))
            })
    }

    /// [`Self::authorize`] for a request from `peer` (its IP address; `None` when unknown, as through
    /// zenoh) at `now`: a peer that has failed too often for `site` lately gets `RESOURCE_EXHAUSTED`
    /// without its token being checked, and each failure counts.
    pub fn authorize_from(
        &self,
        metadata: &MetadataMap,
        peer: Option<IpAddr>,
        site: &str,
        now: Instant,
    ) -> Result<&Grant, Status> {
        self.check_limit(peer, site, now)?;
        self.authorize(metadata, site).inspect_err(|_| {
            self.limiter.record_failure(peer, self.limit_key(site), now);
        })
    }

    /// [`Self::grant`] for a request from `peer` at `now`, failures limited as in
    /// [`Self::authorize_from`] (under one key for every site).
    pub fn grant_from(
        &self,
        metadata: &MetadataMap,
        peer: Option<IpAddr>,
        now: Instant,
    ) -> Result<&Grant, Status> {
        self.check_limit(peer, "", now)?;
        self.grant(metadata).ok_or_else(|| {
            self.limiter.record_failure(peer, "", now);
            Status::unauthenticated("missing or unknown token")
        })
    }

    /// The grant of the request's `authorization: Bearer <token>` if it covers `site`.
    /// No or an unknown token: `UNAUTHENTICATED`; a token of another site: `PERMISSION_DENIED`.
    /// Not limited: front ends call [`Self::authorize_from`].
    pub fn authorize(&self, metadata: &MetadataMap, site: &str) -> Result<&Grant, Status> {
        let header = metadata
            .get("authorization")
            .ok_or_else(|| Status::unauthenticated("missing `authorization: Bearer <token>`"))?;
        let token = header
            .to_str()
            .ok()
            .and_then(|h| h.strip_prefix("Bearer "))
            .ok_or_else(|| Status::unauthenticated("authorization must be `Bearer <token>`"))?;
        let grant = self
            .grants
            .get(token.trim())
            .ok_or_else(|| Status::unauthenticated("unknown token"))?;
        if grant.site != site {
            return Err(Status::permission_denied(format!(
                "this token is not valid for site {site:?}"
            )));
        }
        Ok(grant)
    }

    /// The grant of the request's token, whatever site it is for.
    pub fn grant(&self, metadata: &MetadataMap) -> Option<&Grant> {
        let token = metadata
            .get("authorization")?
            .to_str()
            .ok()?
            .strip_prefix("Bearer ")?;
        self.grants.get(token.trim())
    }
}

#[cfg(test)]
mod tests {
    use tonic::Code;

    use super::*;
    use crate::server_config::RobotConfig;

    fn auth() -> Auth {
        Auth::from_sites(&[SiteConfig {
            id: "a".into(),
            robots: vec![RobotConfig {
                id: "r1".into(),
                token: "secret-a-1".into(),
            }],
        }])
    }

    fn with(token: &str) -> MetadataMap {
        let mut m = MetadataMap::new();
        m.insert("authorization", token.parse().unwrap());
        m
    }

    #[test]
    fn tokens_are_scoped_to_their_site() {
        let auth = auth();
        let grant = auth.authorize(&with("Bearer secret-a-1"), "a").unwrap();
        assert_eq!(grant.robot_id, "r1");
        let code = |m: &MetadataMap, site| auth.authorize(m, site).unwrap_err().code();
        assert_eq!(
            code(&with("Bearer secret-a-1"), "b"),
            Code::PermissionDenied
        );
        assert_eq!(code(&with("Bearer wrong"), "a"), Code::Unauthenticated);
        assert_eq!(code(&with("secret-a-1"), "a"), Code::Unauthenticated);
        assert_eq!(code(&MetadataMap::new(), "a"), Code::Unauthenticated);
    }

    #[test]
    fn a_failing_peer_is_refused_unchecked_until_its_window_ends() {
        let auth = Auth::with_limits(
            &[
                SiteConfig {
                    id: "a".into(),
                    robots: vec![RobotConfig {
                        id: "r1".into(),
                        token: "secret-a-1".into(),
                    }],
                },
                SiteConfig {
                    id: "b".into(),
                    robots: vec![RobotConfig {
                        id: "r1".into(),
                        token: "secret-b-1".into(),
                    }],
                },
            ],
            &AuthLimitOptions {
                max_failures: 2,
                window_s: 60.0,
                ..AuthLimitOptions::default()
            },
        );
        let (t0, peer) = (Instant::now(), Some(IpAddr::from([10, 1, 2, 3])));
        let code = |token: &str, site: &str, at: Instant| {
            auth.authorize_from(&with(token), peer, site, at)
                .map(|g| g.robot_id.clone())
                .map_err(|s| s.code())
        };
        assert_eq!(code("Bearer wrong", "a", t0), Err(Code::Unauthenticated));
        assert_eq!(
            code("Bearer secret-b-1", "a", t0),
            Err(Code::PermissionDenied)
        );
        // Over the limit: even the right token is not looked at.
        assert_eq!(
            code("Bearer secret-a-1", "a", t0),
            Err(Code::ResourceExhausted)
        );
        // Another site, or another peer, is not affected.
        assert_eq!(code("Bearer secret-b-1", "b", t0), Ok("r1".into()));
        let other = auth.authorize_from(&with("Bearer secret-a-1"), None, "a", t0);
        assert!(other.is_ok());
        // Made-up sites share one counter rather than growing the table.
        for i in 0..5 {
            let _ = code("Bearer wrong", &format!("made-up-{i}"), t0);
        }
        assert_eq!(auth.limiter.tracked(), 2);
        // The window ends.
        let later = t0 + std::time::Duration::from_secs(60);
        assert_eq!(code("Bearer secret-a-1", "a", later), Ok("r1".into()));
    }
}
