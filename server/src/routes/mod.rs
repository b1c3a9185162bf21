//! The HTTP API (documented in `docs/http-api.md`): routes, conditional requests, CORS,
//! and per-request telemetry.

mod repos;
mod site;

use std::time::Instant;

use axum::Router;
use axum::body::HttpBody as _;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;

use crate::error::ApiError;
use crate::metrics::Route;
use crate::state::AppState;

/// The application: every route, with telemetry and CORS around them.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(site::index))
        .route("/view", get(site::index))
        .route("/demo/{*file}", get(site::demo_file))
        .route("/healthz", get(site::healthz))
        .route("/metrics", get(site::metrics))
        .route("/repos", get(repos::list))
        .route("/repos/{*rest}", get(repos::under_repos))
        .fallback(not_found)
        .layer(middleware::from_fn_with_state(state.clone(), telemetry))
        .with_state(state)
}

/// Everything no route takes: 404, except methods that no resource here allows
/// (`CONNECT`: this is no proxy; `PRI`: the HTTP/2 preface's method, never a request).
async fn not_found(method: Method) -> Response {
    if method == Method::CONNECT || method.as_str() == "PRI" {
        return (
            StatusCode::METHOD_NOT_ALLOWED,
            [(header::ALLOW, "GET, HEAD, OPTIONS")],
            format!("{method} is not allowed here (not a proxy; GET, HEAD or OPTIONS)\n"),
        )
            .into_response();
    }
    ApiError::not_found("no such resource (see /repos)").into_response()
}

/// The metric label of a request path.
fn route_of(path: &str) -> Route {
    match path {
        "/healthz" => Route::Health,
        "/metrics" => Route::Metrics,
        "/repos" => Route::List,
        "/" | "/view" => Route::Static,
        _ if path.starts_with("/repos/") => {
            if path.ends_with("/metadata.json") {
                Route::Metadata
            } else {
                Route::Blob
            }
        }
        _ if path.starts_with("/demo/") => Route::Static,
        _ => Route::Other,
    }
}

/// Counts and logs every request, answers CORS preflights and adds CORS headers.
async fn telemetry(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let start = Instant::now();
    let route = route_of(request.uri().path());
    let origin = request.headers().get(header::ORIGIN).cloned();
    let debug = tracing::enabled!(tracing::Level::DEBUG);
    let (method, path) = if debug {
        (request.method().clone(), request.uri().path().to_string())
    } else {
        (Method::GET, String::new())
    };
    let mut response = if request.method() == Method::OPTIONS
        && request
            .headers()
            .contains_key(header::ACCESS_CONTROL_REQUEST_METHOD)
    {
        preflight()
    } else {
        next.run(request).await
    };
    cors(&state, origin.as_ref(), response.headers_mut());
    let status = response.status().as_u16();
    let bytes = response.body().size_hint().exact().unwrap_or(0);
    let took = start.elapsed();
    state.metrics.observe(route, status, bytes, took);
    if debug {
        tracing::debug!(%method, path, status, bytes, micros = took.as_micros() as u64, "request");
    }
    response
}

fn preflight() -> Response {
    let mut response = StatusCode::NO_CONTENT.into_response();
    let headers = response.headers_mut();
    headers.insert(
        header::ACCESS_CONTROL_ALLOW_METHODS,
        HeaderValue::from_static("GET, HEAD, OPTIONS"),
    );
    headers.insert(
        header::ACCESS_CONTROL_ALLOW_HEADERS,
        HeaderValue::from_static("if-none-match, if-modified-since, range"),
    );
    headers.insert(
        header::ACCESS_CONTROL_MAX_AGE,
        HeaderValue::from_static("86400"),
    );
    response
}

/// Adds CORS headers for an allowed origin.
fn cors(state: &AppState, origin: Option<&HeaderValue>, headers: &mut HeaderMap) {
    let allowed = &state.cors.allow_origins;
    if allowed.is_empty() {
        return;
    }
    if allowed.iter().any(|o| o == "*") {
        headers.insert(
            header::ACCESS_CONTROL_ALLOW_ORIGIN,
            HeaderValue::from_static("*"),
        );
    } else {
        // The answer depends on the Origin header: caches must key on it.
        headers.append(header::VARY, HeaderValue::from_static("origin"));
        match origin {
            Some(o) if allowed.iter().any(|a| a.as_bytes() == o.as_bytes()) => {
                headers.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, o.clone());
            }
            _ => return,
        }
    }
    // Only a cross-origin request (one with an Origin) needs the ETag exposed to scripts;
    // leaving it off the rest keeps the heads of tiny blob answers short (a client fetching
    // thousands of them pays for every header byte on a narrow link). A shared cache may
    // hand the short answer to a browser: that browser's scripts then cannot read the
    // ETag, which versioned, immutable blob URLs do not need.
    if origin.is_some() {
        headers.insert(
            header::ACCESS_CONTROL_EXPOSE_HEADERS,
            HeaderValue::from_static("etag, content-length"),
        );
    }
}

/// Whether `If-None-Match` in `headers` matches `etag` (weak comparison, RFC 9110 13.1.2).
fn not_modified(headers: &HeaderMap, etag: &HeaderValue) -> bool {
    let Some(inm) = headers.get(header::IF_NONE_MATCH) else {
        return false;
    };
    let Ok(inm) = inm.to_str() else {
        return false;
    };
    let etag = etag.as_bytes();
    let opaque = |t: &str| t.trim().trim_start_matches("W/").as_bytes() == etag;
    inm.trim() == "*" || inm.split(',').any(opaque)
}

/// `304 Not Modified` carrying the validator and caching headers of the full response.
fn not_modified_response(etag: HeaderValue, cache_control: &'static str) -> Response {
    let mut response = StatusCode::NOT_MODIFIED.into_response();
    let headers = response.headers_mut();
    headers.insert(header::ETAG, etag);
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(cache_control),
    );
    response
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn if_none_match_uses_weak_comparison_and_lists() {
        let etag = HeaderValue::from_static("\"abc.1.2\"");
        let mut h = HeaderMap::new();
        assert!(!not_modified(&h, &etag));
        for (value, expect) in [
            ("\"abc.1.2\"", true),
            ("W/\"abc.1.2\"", true),
            ("\"x\", \"abc.1.2\"", true),
            ("*", true),
            ("\"abc.1.3\"", false),
            ("abc.1.2", false),
        ] {
            h.insert(header::IF_NONE_MATCH, HeaderValue::from_static(value));
            assert_eq!(not_modified(&h, &etag), expect, "{value}");
        }
    }

    #[test]
    fn paths_map_to_metric_routes() {
        assert_eq!(route_of("/repos/a/v/0123/d/1/2"), Route::Blob);
        assert_eq!(route_of("/repos/a/metadata.json"), Route::Metadata);
        assert_eq!(route_of("/repos"), Route::List);
        assert_eq!(route_of("/nope"), Route::Other);
    }
}
