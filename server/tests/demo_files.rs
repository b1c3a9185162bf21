//! The web demo's files over a real socket: the WebAssembly module comes back byte for byte
//! with the type `WebAssembly.instantiateStreaming` insists on, and with the same caching
//! as the JavaScript modules that load it: revalidated on every load, by ETag, so an
//! unchanged file costs a `304` and no body.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::*;

/// The committed module (web-demo/build-wasm.sh), as `build.rs` compiled it in: a change
/// to the file rebuilds both.
const MODULE: &[u8] = include_bytes!("../../web-demo/js/quincunx.wasm");

/// `GET path` as a browser asks: compression welcome.
fn browser_get(addr: std::net::SocketAddr, path: &str) -> Response {
    roundtrip(
        addr,
        &format!("GET {path} HTTP/1.1\r\nHost: t\r\nAccept-Encoding: gzip, br\r\n\r\n"),
    )
}

/// Header names of `response`, lower-case and sorted.
fn header_names(response: &Response) -> Vec<String> {
    let mut names: Vec<String> = response
        .headers
        .iter()
        .map(|(n, _)| n.to_ascii_lowercase())
        .collect();
    names.sort();
    names
}

#[test]
fn the_webassembly_module_is_served_as_application_wasm() {
    let server = Running::start(|_| {});
    let module = browser_get(server.addr, "/demo/js/quincunx.wasm");
    assert_eq!(module.status, 200, "{}", module.text());
    assert_eq!(module.header("content-type"), Some("application/wasm"));
    assert!(module.body.starts_with(b"\0asm"), "no wasm magic");
    assert!(
        module.body == MODULE,
        "not the bytes of web-demo/js/quincunx.wasm"
    );
    assert_eq!(
        module.header("content-length"),
        Some(MODULE.len().to_string().as_str())
    );

    // The module that loads it: the same headers, the same caching (revalidated on every
    // load, like the page, so a rebuilt server is picked up at once), neither compressed.
    let loader = browser_get(server.addr, "/demo/js/wasm.mjs");
    assert_eq!(loader.status, 200, "{}", loader.text());
    assert_eq!(
        loader.header("content-type"),
        Some("text/javascript; charset=utf-8")
    );
    assert_eq!(header_names(&module), header_names(&loader));
    for name in ["cache-control", "content-encoding", "vary"] {
        assert_eq!(module.header(name), loader.header(name), "{name}");
    }
    assert_eq!(module.header("cache-control"), Some("no-cache"));
    server.stop();
}

#[test]
fn demo_files_carry_etags_and_revalidate_with_304() {
    let server = Running::start(|_| {});
    let mut tags = Vec::new();
    for path in [
        "/",
        "/demo/index.html",
        "/demo/js/quincunx.wasm",
        "/demo/js/wasm.mjs",
    ] {
        let first = browser_get(server.addr, path);
        assert_eq!(first.status, 200, "{path}");
        let etag = first.header("etag").expect("an ETag").to_string();
        assert!(
            etag.starts_with('"') && etag.ends_with('"'),
            "{path}: {etag}"
        );
        // The same bytes, the same tag.
        assert_eq!(
            browser_get(server.addr, path).header("etag"),
            Some(etag.as_str())
        );
        let ask = |inm: &str| {
            roundtrip(
                server.addr,
                &format!("GET {path} HTTP/1.1\r\nHost: t\r\nIf-None-Match: {inm}\r\n\r\n"),
            )
        };
        // The browser's copy is current: 304, no body, the validator and caching kept.
        let again = ask(&etag);
        assert_eq!(again.status, 304, "{path}");
        assert!(again.body.is_empty(), "{path}: a 304 with a body");
        assert_eq!(again.header("etag"), Some(etag.as_str()));
        assert_eq!(again.header("cache-control"), Some("no-cache"));
        // In a list, or weak: still current.
        assert_eq!(ask(&format!("\"x\", W/{etag}")).status, 304, "{path}");
        // Another tag: the whole file.
        let other = ask("\"0000000000000000-1\"");
        assert_eq!(other.status, 200, "{path}");
        assert_eq!(other.body, first.body, "{path}");
        tags.push(etag);
    }
    // `/` is index.html; different files have different tags.
    assert_eq!(tags[0], tags[1]);
    assert!(tags[1] != tags[2] && tags[2] != tags[3] && tags[1] != tags[3]);
    server.stop();
}
