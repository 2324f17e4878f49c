//! Errors of the console's routes, each with its HTTP status and a JSON body `{"error": "..."}`.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

use super::console_auth::AuthError;
use crate::site::SiteError;

/// Why a console request failed.
#[derive(Debug, thiserror::Error)]
pub enum ConsoleError {
    /// No or a wrong operator token (401).
    #[error(transparent)]
    Unauthorized(#[from] AuthError),
    /// The site is not served here (404).
    #[error("unknown site {0:?}")]
    UnknownSite(String),
    /// The site has no map at that version yet (404).
    #[error("site {site:?} has no map at version {version} yet")]
    NoMap {
        /// The site.
        site: String,
        /// The version asked for.
        version: u64,
    },
    /// A query parameter is missing or malformed (400).
    #[error("{0}")]
    BadRequest(String),
    /// The site's task stopped or failed (503).
    #[error(transparent)]
    Site(#[from] SiteError),
    /// Rendering or encoding failed (500).
    #[error("{0}")]
    Internal(String),
    /// The rendering task failed (panicked) (500).
    #[error("{0}")]
    Worker(#[source] tokio::task::JoinError),
}

impl ConsoleError {
    /// The HTTP status of the error.
    pub fn status(&self) -> StatusCode {
        match self {
            Self::Unauthorized(_) => StatusCode::UNAUTHORIZED,
            Self::UnknownSite(_) | Self::NoMap { .. } | Self::Site(SiteError::NotFound(_)) => {
                StatusCode::NOT_FOUND
            }
            Self::BadRequest(_) => StatusCode::BAD_REQUEST,
            Self::Site(_) => StatusCode::SERVICE_UNAVAILABLE,
            Self::Internal(_) | Self::Worker(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

impl IntoResponse for ConsoleError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.to_string() }).to_string();
        let mut response = (
            self.status(),
            [(axum::http::header::CONTENT_TYPE, "application/json")],
            body,
        )
            .into_response();
        if matches!(self, Self::Unauthorized(_)) {
            response.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer realm=\"evermap console\""),
            );
        }
        response
    }
}
