//! The hot cache's budget bounds the server's memory: `quincunx serve --cache-mb 8` on a
//! planet of 24,000 small blobs (built here from the bundled ETOPO20 grid, 2048 samples per
//! face side), loaded by `quincunx loadtest` until every blob has been asked for, grows by
//! little more than its budget. Blobs that were views into their 4 KiB pages made it grow
//! by 106 MB.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;

use common::{bin, build, serve_with};

#[test]
fn the_hot_cache_budget_bounds_the_servers_memory() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("big");
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/etopo20_global.json");
    let args = ["--planet", "--max-error-m", "50", "--face-side", "2048"];
    build(&args, &input, &repo);
    let server = serve_with(&[("big", &repo)], &["--cache-mb", "8"]);
    let before = server.rss_bytes();
    let o = bin()
        .args([
            "loadtest",
            "--json",
            "--connections",
            "64",
            "--duration-s",
            "4",
        ])
        .args(["--url", &server.url, "--repo", "big"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["errors"], 0, "{report}");
    let metrics = get(&server.url, "/metrics");
    let metric = |name: &str| -> f64 {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {name} in {metrics}"))
    };
    // The request streams read most of the planet's 24,409 blobs from the file.
    let misses = metric("quincunx_cache_misses_total");
    assert!(misses > 20_000.0, "only {misses} blobs read");
    let grown = server.rss_bytes().saturating_sub(before);
    eprintln!(
        "server RSS {:.1} MB before, grew {:.1} MB; {}",
        before as f64 / 1e6,
        grown as f64 / 1e6,
        metrics
            .lines()
            .filter(|l| l.starts_with("quincunx_cache_"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    // 8 MiB of cache, the 64 connections' buffers and the allocator's slack.
    assert!(
        grown < 24 << 20,
        "the server grew by {:.1} MB under an 8 MiB cache",
        grown as f64 / 1e6
    );
}

/// The body of `GET <path>` (HTTP/1.1, one request, `Connection: close`).
fn get(url: &str, path: &str) -> String {
    let addr = url.trim_start_matches("http://");
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut answer = String::new();
    stream.read_to_string(&mut answer).unwrap();
    let (head, body) = answer.split_once("\r\n\r\n").unwrap();
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    body.to_string()
}
