//! `/`, `/view`, `/demo/...`, `/healthz` and `/metrics`. The web demo's files are compiled into
//! the binary: no request path ever reaches the filesystem.

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};

use crate::error::ApiError;
use crate::state::AppState;

/// The web demo's files: (path under `/demo/`, content type, bytes), listed by
/// `build.rs`: `index.html` and every file under `web-demo/js/`.
const DEMO_FILES: &[(&str, &str, &[u8])] = include!(concat!(env!("OUT_DIR"), "/demo_files.rs"));

fn file_response(content_type: &'static str, bytes: &'static [u8]) -> Response {
    let mut response = Response::new(Body::from(bytes));
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// `GET /` and `GET /view?...`: the web demo's page (the query string is the view, read
/// by the page's script).
pub(super) async fn index() -> Response {
    match DEMO_FILES.iter().find(|(name, _, _)| *name == "index.html") {
        Some((_, content_type, bytes)) => file_response(content_type, bytes),
        None => ApiError::not_found("the web demo is not compiled in").into_response(),
    }
}

/// `GET /demo/<file>`.
pub(super) async fn demo_file(Path(file): Path<String>) -> Response {
    match DEMO_FILES.iter().find(|(name, _, _)| *name == file) {
        Some((_, content_type, bytes)) => file_response(content_type, bytes),
        None => ApiError::not_found("no such demo file").into_response(),
    }
}

/// `GET /healthz`: 200 while the server accepts requests.
pub(super) async fn healthz() -> Response {
    let mut response = "ok\n".into_response();
    response
        .headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    response
}

/// `GET /metrics`: Prometheus text exposition.
pub(super) async fn metrics(State(state): State<AppState>) -> Response {
    let (bytes, entries) = state.cache_usage();
    let mut response = Response::new(Body::from(state.metrics.render(bytes, entries)));
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    response
}
