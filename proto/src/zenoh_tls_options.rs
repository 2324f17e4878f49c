//! Mutual TLS on zenoh links: the certificates a robot, a server or a router presents and the
//! certificate authority it trusts, turned into zenoh's `transport/link/tls` settings.
//!
//! Both ends always authenticate (`enable_mtls`): a router accepts only peers whose certificate the
//! site's CA signed, and its access control (`deploy/zenohd.json5`) then decides, by the certificate's
//! common name, which key expressions each may reach — a robot's CN names its site's robots' subject,
//! so it can only query and hear its own site's `evermap/<site>/**`.

use std::path::PathBuf;

use serde::Deserialize;

use crate::ZenohLinkOptionsError;

/// The PEM files of one zenoh participant (TOML section `[zenoh.tls]`). Used on `tls/host:port`
/// endpoints, both to listen and to connect.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohTlsOptions {
    /// The certificate authority that signs every participant's certificate (PEM): peers whose
    /// certificate it did not sign are refused.
    pub root_ca_pem: PathBuf,
    /// This participant's certificate (PEM). Its common name is what routers' access control rules
    /// name; a listener's certificate must also carry the DNS name or IP address others connect to.
    pub cert_pem: PathBuf,
    /// The certificate's private key (PEM, PKCS#8, PKCS#1 or SEC1).
    pub key_pem: PathBuf,
}

impl ZenohTlsOptions {
    /// zenoh configuration entries (key, JSON value) for these files, mutual TLS on (for a
    /// `zenoh::Config::insert_json5`, e.g. into a router's configuration).
    pub fn entries(&self) -> Result<Vec<(&'static str, String)>, ZenohLinkOptionsError> {
        let path = |field: &'static str, path: &PathBuf| {
            let text = path.to_str().ok_or_else(|| ZenohLinkOptionsError {
                field,
                reason: format!("{} is not valid UTF-8", path.display()),
                source: None,
            })?;
            serde_json::to_string(text).map_err(|e| ZenohLinkOptionsError {
                field,
                reason: e.to_string(),
                source: Some(Box::new(e)),
            })
        };
        let ca = path("tls.root_ca_pem", &self.root_ca_pem)?;
        let cert = path("tls.cert_pem", &self.cert_pem)?;
        let key = path("tls.key_pem", &self.key_pem)?;
        Ok(vec![
            ("transport/link/tls/root_ca_certificate", ca),
            ("transport/link/tls/listen_certificate", cert.clone()),
            ("transport/link/tls/listen_private_key", key.clone()),
            ("transport/link/tls/connect_certificate", cert),
            ("transport/link/tls/connect_private_key", key),
            ("transport/link/tls/enable_mtls", "true".into()),
        ])
    }
}
