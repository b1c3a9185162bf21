//! Every route in memory (`router().oneshot(..)`): statuses, headers, 304s, empty leaves,
//! CORS.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use http_body_util::BodyExt;
use quincunx_server::{AppState, ServerConfig, router};
use tower::ServiceExt;

use common::*;

struct Fixture {
    state: AppState,
    _dir: tempfile::TempDir,
}

fn fixture(tweak: impl FnOnce(&mut ServerConfig)) -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let mut config = ServerConfig {
        repos: build_fixtures(dir.path()),
        ..Default::default()
    };
    tweak(&mut config);
    Fixture {
        state: AppState::open(&config).unwrap(),
        _dir: dir,
    }
}

struct Answer {
    status: StatusCode,
    headers: axum::http::HeaderMap,
    body: Vec<u8>,
}

async fn send(state: &AppState, request: Request<Body>) -> Answer {
    let response = router(state.clone()).oneshot(request).await.unwrap();
    let status = response.status();
    let headers = response.headers().clone();
    let body = response
        .into_body()
        .collect()
        .await
        .unwrap()
        .to_bytes()
        .to_vec();
    Answer {
        status,
        headers,
        body,
    }
}

async fn get(state: &AppState, uri: &str) -> Answer {
    send(state, Request::get(uri).body(Body::empty()).unwrap()).await
}

#[tokio::test]
async fn blobs_are_served_with_immutable_caching_and_a_strong_etag() {
    let f = fixture(|_| {});
    let prefix = planar_prefix(&f.state);
    let a = get(&f.state, &format!("{prefix}/32/32")).await;
    assert_eq!(a.status, StatusCode::OK);
    assert_eq!(a.body, blob_for([32, 32, 0]));
    assert_eq!(a.headers[header::CONTENT_TYPE], "application/octet-stream");
    assert_eq!(
        a.headers[header::CACHE_CONTROL],
        "public, max-age=31536000, immutable"
    );
    let etag = a.headers[header::ETAG].to_str().unwrap();
    assert!(etag.starts_with('"') && !etag.starts_with("W/"), "{etag}");
    // Every stored blob comes back byte for byte, and ETags differ per diamond.
    let mut etags = std::collections::HashSet::new();
    for (c, _) in planar_centres(PLANAR_M, PLANAR_LEVELS) {
        let a = get(&f.state, &format!("{prefix}/{}/{}", c[0], c[1])).await;
        assert_eq!(a.status, StatusCode::OK);
        if [c[0], c[1]] == [PLANAR_LEAF.x, PLANAR_LEAF.y] {
            assert!(a.body.is_empty());
        } else {
            assert_eq!(a.body, blob_for(c), "{c:?}");
        }
        assert!(etags.insert(a.headers[header::ETAG].clone()));
    }
}

#[tokio::test]
async fn if_none_match_gives_304_with_the_validator() {
    let f = fixture(|_| {});
    let uri = format!("{}/32/32", planar_prefix(&f.state));
    let etag = get(&f.state, &uri).await.headers[header::ETAG].clone();
    for inm in [
        etag.to_str().unwrap().to_string(),
        format!("\"x\", W/{}", etag.to_str().unwrap()),
        "*".into(),
    ] {
        let request = Request::get(&uri)
            .header(header::IF_NONE_MATCH, inm)
            .body(Body::empty())
            .unwrap();
        let a = send(&f.state, request).await;
        assert_eq!(a.status, StatusCode::NOT_MODIFIED);
        assert_eq!(a.headers[header::ETAG], etag);
        assert!(a.body.is_empty());
    }
    let request = Request::get(&uri)
        .header(header::IF_NONE_MATCH, "\"other\"")
        .body(Body::empty())
        .unwrap();
    assert_eq!(send(&f.state, request).await.status, StatusCode::OK);
    // Metadata revalidates the same way.
    let meta = get(&f.state, "/repos/plain/metadata.json").await;
    let request = Request::get("/repos/plain/metadata.json")
        .header(header::IF_NONE_MATCH, meta.headers[header::ETAG].clone())
        .body(Body::empty())
        .unwrap();
    assert_eq!(
        send(&f.state, request).await.status,
        StatusCode::NOT_MODIFIED
    );
}

#[tokio::test]
async fn leaves_in_the_domain_are_empty_200s() {
    let f = fixture(|_| {});
    let prefix = planar_prefix(&f.state);
    // A diamond whose blob is missing, and one deeper than the repository's levels.
    for (x, y) in [(PLANAR_LEAF.x, PLANAR_LEAF.y), (1, 1), (63, 0)] {
        let a = get(&f.state, &format!("{prefix}/{x}/{y}")).await;
        assert_eq!(a.status, StatusCode::OK, "{x},{y}");
        assert!(a.body.is_empty());
        assert_eq!(a.headers[header::CONTENT_LENGTH], "0");
        assert_eq!(
            a.headers[header::CACHE_CONTROL],
            "public, max-age=31536000, immutable"
        );
    }
}

#[tokio::test]
async fn sphere_ids_have_three_coordinates() {
    let f = fixture(|_| {});
    let prefix = sphere_prefix(&f.state);
    for (c, _) in sphere_centres(SPHERE_M, 2) {
        let a = get(&f.state, &format!("{prefix}/{}/{}/{}", c[0], c[1], c[2])).await;
        assert_eq!(a.status, StatusCode::OK);
        assert_eq!(a.body, blob_for(c));
    }
    // A valid deeper centre on an edge: empty. Inside the cube or a corner: 400.
    assert!(
        get(&f.state, &format!("{prefix}/8/1/0"))
            .await
            .body
            .is_empty()
    );
    for bad in ["0/0/0", "8/8/8", "8/0", "8/0/0/0", "9/0/0"] {
        let a = get(&f.state, &format!("{prefix}/{bad}")).await;
        assert_eq!(a.status, StatusCode::BAD_REQUEST, "{bad}");
    }
}

#[tokio::test]
async fn malformed_and_out_of_domain_ids_are_400_with_a_reason() {
    let f = fixture(|_| {});
    let prefix = planar_prefix(&f.state);
    for bad in [
        "0/0",                                     // a corner, not a centre
        "65/32",                                   // outside [0, 64]^2
        "-32/32",                                  // outside
        "64/64",                                   // a domain corner
        "0/64",                                    // a domain corner
        "032/32",                                  // not canonical
        "+32/32",                                  // not canonical
        "32",                                      // too few coordinates
        "32/32/32",                                // too many for planar
        "32/32/",                                  // empty coordinate
        "x/y",                                     // not numbers
        "9223372036854775807/9223372036854775807", // i64::MAX: out of domain
        "-9223372036854775808/0",                  // i64::MIN
        "9223372036854775808/0",                   // overflow
        "99999999999999999999999999/0",            // overflow
        "%33%32/32",                               // percent-encoded digits
    ] {
        let a = get(&f.state, &format!("{prefix}/{bad}")).await;
        assert_eq!(a.status, StatusCode::BAD_REQUEST, "{bad}");
        assert!(
            !a.body.is_empty() && a.body.len() < 200,
            "{bad}: short reason"
        );
        assert_eq!(a.headers[header::CACHE_CONTROL], "no-store");
    }
}

#[tokio::test]
async fn unknown_repository_version_and_paths_are_404() {
    let f = fixture(|_| {});
    for uri in [
        "/repos/nope/metadata.json",
        "/repos/../plain/metadata.json",
        "/repos/pla%69n/metadata.json",
        "/repos/plain/v/0000000000000000/d/32/32",
        "/repos/plain/v",
        "/repos/plain/metadata.json/x",
        "/repos/plain",
        "/etc/passwd",
        "/demo/../../Cargo.toml",
        "/demo/nope.js",
    ] {
        assert_eq!(
            get(&f.state, uri).await.status,
            StatusCode::NOT_FOUND,
            "{uri}"
        );
    }
}

#[tokio::test]
async fn listing_metadata_health_metrics_and_demo_answer() {
    let f = fixture(|_| {});
    let list = get(&f.state, "/repos").await;
    assert_eq!(list.status, StatusCode::OK);
    let json: serde_json::Value = serde_json::from_slice(&list.body).unwrap();
    let repos = json["repositories"].as_array().unwrap();
    assert_eq!(repos.len(), 2);
    assert_eq!(repos[0]["name"], "plain");
    assert_eq!(repos[1]["domain"], "sphere");
    assert!(
        repos[0]["blob_url_template"]
            .as_str()
            .unwrap()
            .ends_with("/d/{x}/{y}")
    );

    let meta = get(&f.state, "/repos/globe/metadata.json").await;
    assert_eq!(meta.status, StatusCode::OK);
    assert_eq!(meta.headers[header::CONTENT_TYPE], "application/json");
    let parsed: quincunx_store::Metadata = serde_json::from_slice(&meta.body).unwrap();
    assert_eq!(parsed.domain, quincunx_store::Domain::Sphere);
    assert_eq!(parsed.radius_m, Some(6_371_000.0));
    assert_eq!(
        meta.headers[header::ETAG].to_str().unwrap(),
        format!("\"{}\"", parsed.content_hash)
    );

    assert_eq!(get(&f.state, "/healthz").await.body, b"ok\n");
    get(&f.state, &format!("{}/32/32", planar_prefix(&f.state))).await;
    let metrics = String::from_utf8(get(&f.state, "/metrics").await.body).unwrap();
    assert!(
        metrics.contains("quincunx_http_requests_total{route=\"blob\",status=\"200\"} 1"),
        "{metrics}"
    );
    assert!(metrics.contains("quincunx_cache_misses_total 1"));
    let index = get(&f.state, "/").await;
    assert_eq!(index.status, StatusCode::OK);
    let page = String::from_utf8(index.body.clone()).unwrap();
    assert!(page.contains("/demo/js/viewer.mjs"), "{page}");
    // `/view?...` is the same page (its script reads the view from the query).
    let view = get(&f.state, "/view?repo=korea&uv=0.5,0.5&height_m=2000").await;
    assert_eq!(view.status, StatusCode::OK);
    assert_eq!(view.body, index.body);
    assert_eq!(
        get(&f.state, "/demo/index.html").await.status,
        StatusCode::OK
    );
    // Every module the page imports is compiled in, as JavaScript.
    for module in [
        "viewer", "client", "wasm", "worker", "render", "camera", "ground",
    ] {
        let r = get(&f.state, &format!("/demo/js/{module}.mjs")).await;
        assert_eq!(r.status, StatusCode::OK, "{module}");
        assert!(
            r.headers[header::CONTENT_TYPE]
                .to_str()
                .unwrap()
                .starts_with("text/javascript"),
            "{module}"
        );
        assert!(!r.body.is_empty());
    }
    // Only the page and its modules: no tools, tests, packages or parent paths.
    for path in [
        "/demo/tools/decode-repo.mjs",
        "/demo/package.json",
        "/demo/test/decode-repo.test.mjs",
        "/demo/js/../../Cargo.toml",
        "/demo/../Cargo.toml",
    ] {
        assert_eq!(
            get(&f.state, path).await.status,
            StatusCode::NOT_FOUND,
            "{path}"
        );
    }
}

#[tokio::test]
async fn repeated_blob_requests_hit_the_hot_cache() {
    let f = fixture(|_| {});
    let uri = format!("{}/32/32", planar_prefix(&f.state));
    for _ in 0..5 {
        assert_eq!(get(&f.state, &uri).await.body, blob_for([32, 32, 0]));
    }
    let m = &f.state.metrics;
    use std::sync::atomic::Ordering::Relaxed;
    assert_eq!(m.cache_misses.load(Relaxed), 1);
    assert_eq!(m.cache_hits.load(Relaxed), 4);
}

#[tokio::test]
async fn other_methods_are_405_and_head_has_no_body() {
    let f = fixture(|_| {});
    let uri = format!("{}/32/32", planar_prefix(&f.state));
    for method in ["POST", "PUT", "DELETE"] {
        let request = Request::builder()
            .method(method)
            .uri(&uri)
            .body(Body::empty())
            .unwrap();
        assert_eq!(
            send(&f.state, request).await.status,
            StatusCode::METHOD_NOT_ALLOWED,
            "{method}"
        );
    }
    let a = send(&f.state, Request::head(&uri).body(Body::empty()).unwrap()).await;
    assert_eq!(a.status, StatusCode::OK);
    assert!(a.body.is_empty());
    assert_eq!(
        a.headers[header::CONTENT_LENGTH],
        blob_for([32, 32, 0]).len().to_string()
    );
}

#[tokio::test]
async fn cors_allows_any_origin_by_default_and_answers_preflights() {
    let f = fixture(|_| {});
    let uri = format!("{}/32/32", planar_prefix(&f.state));
    let request = Request::get(&uri)
        .header(header::ORIGIN, "https://viewer.example")
        .body(Body::empty())
        .unwrap();
    let a = send(&f.state, request).await;
    assert_eq!(a.headers[header::ACCESS_CONTROL_ALLOW_ORIGIN], "*");
    assert!(
        a.headers[header::ACCESS_CONTROL_EXPOSE_HEADERS]
            .to_str()
            .unwrap()
            .contains("etag")
    );
    // Without an Origin (not a CORS request), the exposure list is left off.
    let plain = send(&f.state, Request::get(&uri).body(Body::empty()).unwrap()).await;
    assert_eq!(plain.headers[header::ACCESS_CONTROL_ALLOW_ORIGIN], "*");
    assert!(
        !plain
            .headers
            .contains_key(header::ACCESS_CONTROL_EXPOSE_HEADERS)
    );
    let preflight = Request::options(&uri)
        .header(header::ORIGIN, "https://viewer.example")
        .header(header::ACCESS_CONTROL_REQUEST_METHOD, "GET")
        .header(header::ACCESS_CONTROL_REQUEST_HEADERS, "if-none-match")
        .body(Body::empty())
        .unwrap();
    let a = send(&f.state, preflight).await;
    assert_eq!(a.status, StatusCode::NO_CONTENT);
    assert!(
        a.headers[header::ACCESS_CONTROL_ALLOW_METHODS]
            .to_str()
            .unwrap()
            .contains("GET")
    );
    assert!(
        a.headers[header::ACCESS_CONTROL_ALLOW_HEADERS]
            .to_str()
            .unwrap()
            .contains("if-none-match")
    );
}

#[tokio::test]
async fn cors_lists_echo_allowed_origins_only() {
    let f = fixture(|c| c.cors.allow_origins = vec!["https://ok.example".into()]);
    let uri = format!("{}/32/32", planar_prefix(&f.state));
    let with = |origin: &'static str| {
        Request::get(uri.clone())
            .header(header::ORIGIN, origin)
            .body(Body::empty())
            .unwrap()
    };
    let a = send(&f.state, with("https://ok.example")).await;
    assert_eq!(
        a.headers[header::ACCESS_CONTROL_ALLOW_ORIGIN],
        "https://ok.example"
    );
    assert_eq!(a.headers[header::VARY], "origin");
    let a = send(&f.state, with("https://evil.example")).await;
    assert!(a.headers.get(header::ACCESS_CONTROL_ALLOW_ORIGIN).is_none());
    assert_eq!(a.status, StatusCode::OK);
    let none = fixture(|c| c.cors.allow_origins.clear());
    let request = Request::get(format!("{}/32/32", planar_prefix(&none.state)))
        .header(header::ORIGIN, "https://ok.example")
        .body(Body::empty())
        .unwrap();
    assert!(
        send(&none.state, request)
            .await
            .headers
            .get(header::ACCESS_CONTROL_ALLOW_ORIGIN)
            .is_none()
    );
}
