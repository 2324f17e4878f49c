//! The console's read-only operator token.
//!
//! A request is let in when it carries the token as `authorization: Bearer <token>` (scripts, `curl`),
//! as the `token` query parameter (the link an operator is given; the page's own requests then use the
//! cookie), or as the `evermap_token` cookie, which the server sets (`HttpOnly`, `SameSite=Strict`) on
//! every response to a request authenticated by the query parameter, so the page's images, API calls
//! and event stream need not repeat it. Robot tokens do not open the console. Comparison takes the same
//! time whatever the mismatch.

use axum::http::{HeaderMap, header};

/// The cookie carrying the operator token.
pub const COOKIE_NAME: &str = "evermap_token";

/// How a request was authenticated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Authenticated {
    /// No token is configured: the console is open.
    Open,
    /// By the `authorization` header or the cookie.
    Header,
    /// By the `token` query parameter (the response sets the cookie).
    Query,
}

/// Why a request was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AuthError {
    /// No token in the request.
    #[error(
        "this console needs the operator token: `authorization: Bearer <token>`, `?token=<token>` or the evermap_token cookie"
    )]
    Missing,
    /// A token that is not the operator token.
    #[error("wrong operator token")]
    Wrong,
}

/// Checks requests against the operator token.
#[derive(Clone, Debug, Default)]
pub struct ConsoleAuth {
    token: Option<String>,
}

impl ConsoleAuth {
    /// Requires `token` on every request (none: an open console).
    pub fn new(token: Option<String>) -> Self {
        Self { token }
    }

    /// Whether a token is required.
    pub fn is_required(&self) -> bool {
        self.token.is_some()
    }

    /// Checks a request's headers and query string.
    pub fn check(
        &self,
        headers: &HeaderMap,
        query: Option<&str>,
    ) -> Result<Authenticated, AuthError> {
        let Some(expected) = &self.token else {
            return Ok(Authenticated::Open);
        };
        let bearer = headers
            .get(header::AUTHORIZATION)
            .and_then(|h| h.to_str().ok())
            .and_then(|h| h.strip_prefix("Bearer "))
            .map(str::trim);
        let cookie = headers
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|h| h.to_str().ok())
            .flat_map(|h| h.split(';'))
            .filter_map(|pair| pair.trim().split_once('='))
            .find(|(name, _)| *name == COOKIE_NAME)
            .map(|(_, value)| value.to_owned());
        let from_query = query.and_then(|q| query_param(q, "token"));
        let mut seen = false;
        for (candidate, how) in [
            (bearer.map(str::to_owned), Authenticated::Header),
            (cookie, Authenticated::Header),
            (from_query, Authenticated::Query),
        ] {
            let Some(candidate) = candidate else { continue };
            seen = true;
            if same(candidate.as_bytes(), expected.as_bytes()) {
                return Ok(how);
            }
        }
        Err(if seen {
            AuthError::Wrong
        } else {
            AuthError::Missing
        })
    }

    /// The `set-cookie` value that stores the token in the browser (`None` when none is configured).
    pub fn cookie(&self) -> Option<String> {
        self.token
            .as_ref()
            .map(|t| format!("{COOKIE_NAME}={t}; Path=/; HttpOnly; SameSite=Strict"))
    }
}

/// Compares two byte strings in a time that depends only on their lengths.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0_u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The percent-decoded value of parameter `name` in a query string (`a=1&b=2`); the first one wins.
pub fn query_param(query: &str, name: &str) -> Option<String> {
    query
        .split('&')
        .filter_map(|pair| pair.split_once('='))
        .find(|(key, _)| *key == name)
        .and_then(|(_, value)| {
            percent_encoding::percent_decode_str(value)
                .decode_utf8()
                .ok()
                .map(std::borrow::Cow::into_owned)
        })
}

#[cfg(test)]
mod tests {
    use axum::http::HeaderValue;

    use super::*;

    fn headers(name: header::HeaderName, value: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(name, HeaderValue::from_str(value).unwrap());
        h
    }

    #[test]
    fn the_token_is_taken_from_header_cookie_or_query() {
        let auth = ConsoleAuth::new(Some("operator-1".into()));
        let none = HeaderMap::new();
        assert_eq!(auth.check(&none, None), Err(AuthError::Missing));
        assert_eq!(
            auth.check(&none, Some("version=3")),
            Err(AuthError::Missing)
        );
        assert_eq!(
            auth.check(&headers(header::AUTHORIZATION, "Bearer operator-1"), None),
            Ok(Authenticated::Header)
        );
        assert_eq!(
            auth.check(&headers(header::AUTHORIZATION, "Bearer operator-2"), None),
            Err(AuthError::Wrong)
        );
        assert_eq!(
            auth.check(&headers(header::AUTHORIZATION, "operator-1"), None),
            Err(AuthError::Missing),
            "not a bearer header"
        );
        assert_eq!(
            auth.check(
                &headers(header::COOKIE, "a=b; evermap_token=operator-1"),
                None
            ),
            Ok(Authenticated::Header)
        );
        assert_eq!(
            auth.check(&none, Some("x=1&token=operator%2D1")),
            Ok(Authenticated::Query)
        );
        assert_eq!(
            auth.check(&none, Some("token=operator")),
            Err(AuthError::Wrong)
        );
        let open = ConsoleAuth::new(None);
        assert_eq!(open.check(&none, None), Ok(Authenticated::Open));
        assert!(open.cookie().is_none());
        assert!(auth.cookie().unwrap().contains("HttpOnly"));
    }

    #[test]
    fn query_parameters_are_decoded() {
        assert_eq!(query_param("a=1&b=x%20y", "b").as_deref(), Some("x y"));
        assert_eq!(query_param("a=1", "b"), None);
        assert_eq!(query_param("b=%ff", "b"), None, "not UTF-8");
    }
}
