//! Bearer-token authentication: each robot's token grants access to exactly one site.

use std::collections::HashMap;

use tonic::Status;
use tonic::metadata::MetadataMap;

use crate::server_config::SiteConfig;

/// What a token allows.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Grant {
    /// The only site the token may read and write.
    pub site: String,
    /// The robot the token belongs to (uploads must name it).
    pub robot_id: String,
}

/// Tokens of every configured robot.
#[derive(Debug, Default)]
pub struct Auth {
    grants: HashMap<String, Grant>,
}

impl Auth {
    /// The tokens of the configured sites' robots.
    pub fn from_sites(sites: &[SiteConfig]) -> Self {
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
        Self { grants }
    }

    /// The grant of the request's `authorization: Bearer <token>` if it covers `site`.
    /// No or an unknown token: `UNAUTHENTICATED`; a token of another site: `PERMISSION_DENIED`.
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
}
