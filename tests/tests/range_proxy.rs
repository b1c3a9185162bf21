//! A repository file read through an nginx caching proxy that caches fixed slices of it
//! (`ngx_http_slice_module`), the way a CDN in front of a bucket does (`docs/hosting.md`,
//! "CDNs"):
//! - a flight through the proxy is crack-free at every frame, and a second flight is
//!   served from the proxy's slices: the origin sees no request;
//! - the `ETag` the client pins passes through the proxy, and a file replaced at the origin
//!   is an error (the origin's 412 passed on), never a mix of two builds.
//!
//! Prints `SKIP range_proxy...: ...` and passes when nginx is not installed.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

use common::nginx::{Nginx, find_nginx, free_port};
use common::pack_reads::{assert_clean, build, fetch_all, fly_checked, raw_fetcher, stored};
use common::{get, put_file};
use quincunx_client::fetch::{FetchError, Fetched, Key, Remote};
use quincunx_repo_tools::build::BuildArgs;

/// The proxy's slice: small next to the bundled korea file (60 KB), so a flight spans
/// all of them and most requests more than one.
const SLICE: &str = "4k";
const SLICE_BYTES: u64 = 4 << 10;

/// nginx serving `www` as plain files, logging every request.
fn origin(binary: &Path, dir: &Path, www: &Path) -> Nginx {
    let addr = free_port();
    let snippet = format!(
        "access_log {}/access.log;\nserver {{ listen {addr}; root {}; }}",
        dir.display(),
        www.display()
    );
    Nginx::run(binary, dir, addr, &snippet, "/korea.pack")
}

/// nginx caching `origin` in slices of [`SLICE`] (one origin request per slice, however
/// many clients miss it at once: `proxy_cache_lock`), logging each answer's range and cache
/// status, and telling it in `X-Cache-Status`.
fn slice_proxy(binary: &Path, dir: &Path, origin: SocketAddr) -> Nginx {
    let addr = free_port();
    let d = dir.display();
    let snippet = format!(
        "proxy_cache_path {d}/cache levels=1:2 keys_zone=slices:10m max_size=1g \
             inactive=1d use_temp_path=off;\n\
         log_format slices '$request_uri \"$http_range\" $status $upstream_cache_status';\n\
         access_log {d}/access.log slices;\n\
         server {{\n\
           listen {addr};\n\
           location = /ready {{ return 200; }}\n\
           location / {{\n\
             slice {SLICE};\n\
             proxy_cache slices;\n\
             proxy_cache_lock on;\n\
             proxy_cache_key $uri$is_args$args$slice_range;\n\
             proxy_set_header Range $slice_range;\n\
             proxy_cache_valid 200 206 1d;\n\
             proxy_http_version 1.1;\n\
             proxy_set_header Connection \"\";\n\
             add_header X-Cache-Status $upstream_cache_status always;\n\
             proxy_pass http://{origin};\n\
           }}\n\
         }}"
    );
    Nginx::run(binary, dir, addr, &snippet, "/ready")
}

#[test]
fn flights_through_a_slice_caching_proxy_are_crack_free_and_the_second_is_all_hits() {
    let Some(nginx) = find_nginx("range_proxy") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let built = root.join("korea");
    common::build_bundled_korea(&built);
    let www = root.join("www");
    put_file(&built, &www, "korea.pack");
    let file_len = std::fs::metadata(www.join("korea.pack")).unwrap().len();
    let (origin_dir, proxy_dir) = (root.join("origin"), root.join("proxy"));
    let origin = origin(&nginx, &origin_dir, &www);
    let proxy = slice_proxy(&nginx, &proxy_dir, origin.addr);
    let url = format!("http://{}", proxy.addr);

    let before = origin.access_log().len();
    let first = fly_checked(&url, "korea.pack", None);
    assert_clean("first flight", &first);
    let origin_after_first = origin.access_log();
    let proxied = proxy.access_log();
    // Every request the origin saw was for one whole slice, whatever the client asked.
    let slices: Vec<&String> = origin_after_first[before..].iter().collect();
    assert!(!slices.is_empty());
    for line in &slices {
        assert!(
            line.contains("\" 206 "),
            "the origin answers slices: {line}"
        );
    }
    let slice_count = file_len.div_ceil(SLICE_BYTES) as usize;
    assert!(
        slices.len() <= slice_count,
        "{} origin requests for a file of {slice_count} slices",
        slices.len()
    );

    let second = fly_checked(&url, "korea.pack", None);
    assert_clean("second flight", &second);
    let origin_after_second = origin.access_log();
    assert_eq!(
        origin_after_second.len(),
        origin_after_first.len(),
        "the second flight reached the origin: {:?}",
        &origin_after_second[origin_after_first.len()..]
    );
    let second_log = &proxy.access_log()[proxied.len()..];
    let hits = second_log.iter().filter(|l| l.ends_with(" HIT")).count();
    assert_eq!(
        hits,
        second_log.len(),
        "every answer of the second flight a HIT: {second_log:?}"
    );
    assert!(hits as u64 >= second.requests, "{hits} hits, {second:?}");
    println!(
        "range_proxy: korea ({file_len} bytes, {slice_count} slices of {SLICE}): first flight \
         {} requests, the origin saw {} (slices); second flight {} requests, {hits} HITs, \
         0 at the origin; 0 cracks",
        first.requests,
        slices.len(),
        second.requests
    );
    drop(proxy);
    drop(origin);
}

#[test]
fn etags_pass_through_the_proxy_and_a_replaced_file_is_an_error_never_a_mix() {
    let Some(nginx) = find_nginx("range_proxy_replaced") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (old, new) = (root.join("old"), root.join("new"));
    common::build_bundled_korea(&old);
    build(&new, "korea_srtm3_1025.json", |a| BuildArgs {
        rms_m: Some(8.0),
        ..a
    });
    let www = root.join("www");
    put_file(&old, &www, "korea.pack");
    let (origin_dir, proxy_dir) = (root.join("origin"), root.join("proxy"));
    let origin = origin(&nginx, &origin_dir, &www);
    let proxy = slice_proxy(&nginx, &proxy_dir, origin.addr);
    let url = format!("http://{}", proxy.addr);

    // The proxy's answer carries the origin's (strong) ETag, and honours If-Match.
    let at_origin = get(origin.addr, "/korea.pack", &["Range: bytes=30000-30099"]);
    let etag = at_origin.header("etag").unwrap().to_string();
    assert!(!etag.starts_with("W/"), "{etag}");
    let a = get(proxy.addr, "/korea.pack", &["Range: bytes=30000-30099"]);
    assert_eq!(a.status, 206);
    assert_eq!(a.header("etag"), Some(etag.as_str()));
    assert_eq!(a.body, at_origin.body);
    let if_match = format!("If-Match: {etag}");
    let b = get(
        proxy.addr,
        "/korea.pack",
        &["Range: bytes=30000-30099", &if_match],
    );
    assert_eq!((b.status, b.header("x-cache-status")), (206, Some("HIT")));
    let c = get(
        proxy.addr,
        "/korea.pack",
        &["Range: bytes=30000-30099", "If-Match: \"other\""],
    );
    assert_eq!(c.status, 412, "a cached slice checked against If-Match");

    let (remote, _) = Remote::open(&url, "korea.pack", Duration::from_secs(5)).unwrap();
    assert_eq!(remote.pack.as_ref().unwrap().etag.as_deref(), Some(&*etag));
    // Published the way `quincunx build --overwrite` publishes: one rename. The proxy
    // holds the slices read so far (the first, which opening read, and the one above);
    // the others come from the origin, which now has another file.
    let staged = www.join("korea.pack.new");
    std::fs::copy(new.join("repository.pack"), &staged).unwrap();
    std::fs::rename(&staged, www.join("korea.pack")).unwrap();
    let want = stored(&old);
    let keys: Vec<Key> = want.keys().copied().collect();
    let got = fetch_all(&raw_fetcher(remote), &keys, Duration::from_secs(60));
    assert_eq!(got.len(), keys.len());
    let (mut old_blobs, mut changed, mut failed) = (0, 0, 0);
    for (k, r) in &got {
        match r {
            Fetched::Data(v) => {
                assert_eq!(&v[..], &want[k][..], "a blob of the new build");
                old_blobs += 1;
            }
            Fetched::Failed(FetchError::Changed(msg)) => {
                assert!(msg.contains("changed since it was opened"), "{msg}");
                changed += 1;
            }
            // A request whose first slice is cached but a later one is not: the origin's
            // 412 for that slice makes nginx cut the answer short (a transient failure,
            // retried, then reported).
            Fetched::Failed(_) => failed += 1,
            other => panic!("{k:?}: {other:?}"),
        }
    }
    assert!(changed > 0, "no request saw the new file");
    assert!(old_blobs > 0, "no blob came from the cached slices");
    println!(
        "range_proxy: after the file was replaced at the origin, {old_blobs} blobs came from \
         cached slices of the old file, {changed} keys failed as changed, {failed} otherwise, \
         0 blobs of the new build"
    );
    drop(proxy);
    drop(origin);
}
