//! `/`, `/view`, `/demo/...`, `/healthz` and `/metrics`. The web demo's files are compiled into
//! the binary: no request path ever reaches the filesystem.

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::{IntoResponse, Response};

use crate::error::ApiError;
use crate::state::AppState;

/// One of the web demo's files: path under `/demo/`, content type, ETag (of its bytes),
/// bytes.
type DemoFile = (&'static str, &'static str, &'static str, &'static [u8]);

/// The web demo's files, listed by `build.rs`: `index.html` and every file under
/// `web-demo/js/`.
const DEMO_FILES: &[DemoFile] = include!(concat!(env!("OUT_DIR"), "/demo_files.rs"));

/// A demo file, revalidated on every load (`no-cache`, so a rebuilt server is picked up
/// at once) and answered `304` when the browser holds these bytes (its ETag).
fn file_response(request: &HeaderMap, (_, content_type, etag, bytes): &DemoFile) -> Response {
    let etag = HeaderValue::from_static(etag);
    if super::not_modified(request, &etag) {
        return super::not_modified_response(etag, "no-cache");
    }
    let mut response = Response::new(Body::from(*bytes));
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    headers.insert(header::ETAG, etag);
    response
}

/// `GET /` and `GET /view?...`: the web demo's page (the query string is the view, read
/// by the page's script).
pub(super) async fn index(headers: HeaderMap) -> Response {
    match DEMO_FILES.iter().find(|f| f.0 == "index.html") {
        Some(f) => file_response(&headers, f),
        None => ApiError::not_found("the web demo is not compiled in").into_response(),
    }
}

/// `GET /demo/<file>`.
pub(super) async fn demo_file(Path(file): Path<String>, headers: HeaderMap) -> Response {
    match DEMO_FILES.iter().find(|f| f.0 == file) {
        Some(f) => file_response(&headers, f),
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
