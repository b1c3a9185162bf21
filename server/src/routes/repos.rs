//! `/repos`, `/repos/<name>/metadata.json` and `/repos/<name>/v/<version>/d/<x>/<y>[/<z>]`.
//!
//! The repository part of a path is matched byte for byte against configured names (no
//! percent-decoding, so no request path can name anything else), and coordinates must be
//! canonical decimal integers, so each blob has exactly one URL and caches never hold two
//! copies of it.

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};

use super::{not_modified, not_modified_response};
use crate::error::ApiError;
use crate::state::{AppState, IdSpace};

/// Blob URLs never change meaning: the version in the path is the content hash.
const IMMUTABLE: &str = "public, max-age=31536000, immutable";
/// Metadata changes when a repository is rebuilt under the same name: revalidate often.
const METADATA_CACHE: &str = "public, max-age=60";

/// `GET /repos`: the served repositories (JSON).
pub(super) async fn list(State(state): State<AppState>) -> Response {
    let mut response = Response::new(Body::from(state.listing.clone()));
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// Everything under `/repos/`.
pub(super) async fn under_repos(State(state): State<AppState>, request: Request) -> Response {
    match resource(&state, &request) {
        Ok(response) => response,
        Err(e) => e.into_response(),
    }
}

fn resource(state: &AppState, request: &Request) -> Result<Response, ApiError> {
    let path = request.uri().path();
    let rest = path.strip_prefix("/repos/").unwrap_or_default();
    let mut parts = rest.split('/');
    let name = parts.next().unwrap_or_default();
    let (index, served) = state
        .repo(name)
        .ok_or_else(|| ApiError::not_found("unknown repository (see /repos)"))?;
    match parts.next() {
        Some("metadata.json") if parts.next().is_none() => {
            if not_modified(request.headers(), &served.metadata_etag) {
                return Ok(not_modified_response(
                    served.metadata_etag.clone(),
                    METADATA_CACHE,
                ));
            }
            Ok(bytes_response(
                served.metadata_json.clone(),
                "application/json",
                served.metadata_etag.clone(),
                METADATA_CACHE,
            ))
        }
        Some("v") => {
            if parts.next() != Some(served.version.as_str()) {
                return Err(ApiError::not_found(
                    "this version of the repository is not served (current: see metadata.json)",
                ));
            }
            let packaged = match parts.next() {
                Some("d") => false,
                Some("p") if served.packaged => true,
                Some("p") => {
                    return Err(ApiError::not_found(
                        "this repository has no packages (no inlining limit): use .../d/",
                    ));
                }
                _ => return Err(ApiError::not_found("expected .../d/<x>/<y>[/<z>]")),
            };
            let centre = parse_centre(parts, served.domain)?;
            let blob = state.blob(index, centre, packaged)?;
            if not_modified(request.headers(), &blob.etag) {
                return Ok(not_modified_response(blob.etag, IMMUTABLE));
            }
            Ok(bytes_response(
                blob.body,
                "application/octet-stream",
                blob.etag,
                IMMUTABLE,
            ))
        }
        _ => Err(ApiError::not_found(
            "expected /repos/<name>/metadata.json or /repos/<name>/v/<version>/d/<x>/<y>[/<z>]",
        )),
    }
}

fn bytes_response(
    body: bytes::Bytes,
    content_type: &'static str,
    etag: HeaderValue,
    cache_control: &'static str,
) -> Response {
    let mut response = Response::new(Body::from(body));
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    headers.insert(header::ETAG, etag);
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(cache_control),
    );
    response
}

/// The centre in the remaining path segments: exactly as many canonical integers as the
/// domain has coordinates.
fn parse_centre<'a>(
    parts: impl Iterator<Item = &'a str>,
    domain: IdSpace,
) -> Result<[i64; 3], ApiError> {
    let dims = domain.dims();
    let mut centre = [0i64; 3];
    let mut count = 0;
    for part in parts {
        if count == dims {
            return Err(wrong_dims(dims));
        }
        centre[count] = parse_coordinate(part)?;
        count += 1;
    }
    if count != dims {
        return Err(wrong_dims(dims));
    }
    Ok(centre)
}

fn wrong_dims(dims: usize) -> ApiError {
    ApiError::bad_request(if dims == 2 {
        "a planar diamond id is /d/<x>/<y>"
    } else {
        "a sphere diamond id is /d/<x>/<y>/<z>"
    })
}

/// A canonical decimal `i64`: optional `-`, no leading zeros, no `+`, no `-0`.
fn parse_coordinate(s: &str) -> Result<i64, ApiError> {
    let digits = s.strip_prefix('-').unwrap_or(s);
    let canonical = !digits.is_empty()
        && digits.len() <= 20
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits == "0" || !digits.starts_with('0'))
        && s != "-0";
    if !canonical {
        return Err(ApiError::bad_request(
            "coordinates must be canonical decimal integers",
        ));
    }
    s.parse::<i64>()
        .map_err(|_| ApiError::bad_request("coordinate overflows a 64-bit integer"))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn only_canonical_integers_are_coordinates() {
        for ok in [
            "0",
            "7",
            "-7",
            "9223372036854775807",
            "-9223372036854775808",
        ] {
            assert_eq!(parse_coordinate(ok).unwrap().to_string(), ok);
        }
        for bad in [
            "",
            "-",
            "+1",
            "01",
            "-0",
            "00",
            "1.0",
            "1e3",
            " 1",
            "%31",
            "9223372036854775808",
            "-9223372036854775809",
            "123456789012345678901234",
        ] {
            assert!(parse_coordinate(bad).is_err(), "{bad:?}");
        }
    }
}
