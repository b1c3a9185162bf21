//! The one error type of request handling, mapped to an HTTP response.

use std::borrow::Cow;

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// Why a request failed: a status and a short, plain-text reason for the client.
#[derive(Debug)]
pub struct ApiError {
    /// Status to answer with.
    pub status: StatusCode,
    /// One line for the client.
    pub reason: Cow<'static, str>,
}

impl ApiError {
    /// 400: the request names no valid resource (malformed or out-of-domain id, ...).
    pub fn bad_request(reason: impl Into<Cow<'static, str>>) -> ApiError {
        ApiError {
            status: StatusCode::BAD_REQUEST,
            reason: reason.into(),
        }
    }

    /// 404.
    pub fn not_found(reason: impl Into<Cow<'static, str>>) -> ApiError {
        ApiError {
            status: StatusCode::NOT_FOUND,
            reason: reason.into(),
        }
    }

    /// 500 for a failure that cannot recur per blob: logged here; the client only learns
    /// that it failed.
    pub fn internal(repo: &str, cause: &dyn std::fmt::Display) -> ApiError {
        tracing::error!(repo, "serving failed: {cause}");
        ApiError::unreadable()
    }

    /// 500: a repository could not be read (logged by the caller, once per blob).
    pub fn unreadable() -> ApiError {
        ApiError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            reason: "the repository could not be read".into(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut body = self.reason.into_owned();
        body.push('\n');
        let mut response = (self.status, body).into_response();
        let headers = response.headers_mut();
        headers.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; charset=utf-8"),
        );
        headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
        response
    }
}
