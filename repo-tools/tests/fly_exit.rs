//! `quincunx fly` says when a flight failed (issue 40): against a server whose blob answers
//! are garbage, truncated or another diamond's, and against a server killed 0.3 s into the
//! flight, the real binary exits non-zero with a one-line reason, and its `--json` report
//! carries the counts and the `failure`. The same proxy answering faithfully flies clean.
//!
//! The proxy stands between the client and a real `quincunx serve`: it reads pipelined
//! HTTP/1.1 requests, asks the server for each one on a connection of its own and answers
//! in order, changing only blob bodies.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::{bin, run_within};

/// What the proxy does to blob answers.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    /// Nothing: the control.
    None,
    /// Random bytes of the same length.
    Garbage,
    /// The head promises the whole body, half of it comes, then the connection closes.
    Truncated,
    /// The body of the blob answered before (another diamond's).
    Swapped,
}

/// The bundled Korea crop, built once per test.
fn korea(dir: &Path) -> std::path::PathBuf {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let out = dir.join("korea");
    common::build(&["--rms-m", "2"], &input, &out);
    out
}

/// One whole answer of `upstream` to `GET path`: status, content type, body.
fn ask(upstream: &str, path: &str) -> Option<(u16, String, Vec<u8>)> {
    let mut s = TcpStream::connect(upstream).ok()?;
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes())
        .ok()?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).ok()?;
    let end = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&raw[..end]).into_owned();
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    let field = |name: &str| {
        head.lines().find_map(|l| {
            let (n, v) = l.split_once(':')?;
            n.eq_ignore_ascii_case(name).then(|| v.trim().to_string())
        })
    };
    let mut body = raw[end + 4..].to_vec();
    if field("transfer-encoding").is_some_and(|v| v.eq_ignore_ascii_case("chunked")) {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let line_end = rest.windows(2).position(|w| w == b"\r\n")?;
            let size =
                usize::from_str_radix(std::str::from_utf8(&rest[..line_end]).ok()?.trim(), 16)
                    .ok()?;
            if size == 0 {
                break;
            }
            out.extend_from_slice(rest.get(line_end + 2..line_end + 2 + size)?);
            rest = rest.get(line_end + 4 + size..)?;
        }
        body = out;
    }
    Some((status, field("content-type").unwrap_or_default(), body))
}

/// A proxy in front of `upstream` doing `fault` to every non-empty blob answer.
fn proxy(upstream: String, fault: Fault) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let previous: Arc<Mutex<Vec<u8>>> = Arc::default();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut client) = stream else { continue };
            let (upstream, previous) = (upstream.clone(), Arc::clone(&previous));
            std::thread::spawn(move || {
                let mut seen = Vec::new();
                let mut buf = [0u8; 16384];
                let mut seed = 0x9E37_79B9_7F4A_7C15u64;
                loop {
                    let Some(end) = seen.windows(4).position(|w| w == b"\r\n\r\n") else {
                        match client.read(&mut buf) {
                            Ok(0) | Err(_) => return,
                            Ok(k) => seen.extend_from_slice(&buf[..k]),
                        }
                        continue;
                    };
                    let head = String::from_utf8_lossy(&seen[..end]).into_owned();
                    seen.drain(..end + 4);
                    let path = head.split_whitespace().nth(1).unwrap_or("/").to_string();
                    let Some((status, kind, mut body)) = ask(&upstream, &path) else {
                        return;
                    };
                    let blob = path.contains("/v/") && status == 200 && !body.is_empty();
                    let mut cut = None;
                    if blob {
                        match fault {
                            Fault::None => {}
                            Fault::Garbage => {
                                for b in &mut body {
                                    seed ^= seed << 13;
                                    seed ^= seed >> 7;
                                    seed ^= seed << 17;
                                    *b = seed as u8;
                                }
                            }
                            Fault::Truncated => cut = Some(body.len() / 2),
                            Fault::Swapped => {
                                let mut p = previous.lock().unwrap();
                                let mine = std::mem::replace(&mut *p, body.clone());
                                if !mine.is_empty() {
                                    body = mine;
                                }
                            }
                        }
                    }
                    let answer = format!(
                        "HTTP/1.1 {status} X\r\ncontent-type: {kind}\r\ncontent-length: {}\r\n\r\n",
                        body.len()
                    );
                    let sent = body.get(..cut.unwrap_or(body.len())).unwrap_or(&body);
                    if client.write_all(answer.as_bytes()).is_err()
                        || client.write_all(sent).is_err()
                    {
                        return;
                    }
                    if cut.is_some() {
                        return;
                    }
                }
            });
        }
    });
    url
}

/// `quincunx fly --json` of the jump path at `url`, ended within 3 minutes.
fn fly(url: &str) -> common::Run {
    run_within(
        bin().args([
            "fly",
            "--url",
            url,
            "--repo",
            "korea",
            "--path",
            "jump",
            "--json",
            "--timeout-s",
            "2",
            "--deadline-s",
            "4",
        ]),
        Duration::from_secs(180),
    )
}

#[test]
fn fly_exits_non_zero_with_the_reason_when_blob_answers_are_bad() {
    let dir = tempfile::tempdir().unwrap();
    let repo = korea(dir.path());
    let server = common::serve(&[("korea", &repo)]);
    let upstream = server
        .url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_string();
    let runs: Vec<_> = [
        Fault::None,
        Fault::Garbage,
        Fault::Truncated,
        Fault::Swapped,
    ]
    .into_iter()
    .map(|fault| {
        let url = proxy(upstream.clone(), fault);
        std::thread::spawn(move || (fault, fly(&url)))
    })
    .collect();
    for run in runs {
        let (fault, run) = run.join().unwrap();
        let report: serde_json::Value =
            serde_json::from_str(run.stdout.trim()).unwrap_or_else(|e| {
                panic!(
                    "{fault:?}: no JSON report ({e}): {}{}",
                    run.stdout, run.stderr
                )
            });
        if fault == Fault::None {
            assert!(run.success, "the faithful proxy: {}", run.stderr);
            assert!(report["failure"].is_null(), "{report}");
            continue;
        }
        assert!(!run.success, "{fault:?}: exit 0: {}", run.stdout);
        let line = run
            .stderr
            .lines()
            .find(|l| l.starts_with("error: "))
            .unwrap_or_else(|| {
                panic!("{fault:?}: no one-line reason: {}", run.stderr);
            });
        assert!(
            line.contains("most requests failed")
                || line.contains("fetched nothing")
                || line.contains("never reached full quality"),
            "{fault:?}: {line}"
        );
        assert_eq!(
            report["failure"].as_str(),
            line.strip_prefix("error: "),
            "{fault:?}"
        );
        assert!(
            report["fetch_errors"].as_u64().unwrap() > 0,
            "{fault:?}: {report}"
        );
        println!(
            "{fault:?}: {} requests, {} fetch errors, {} jumps unfinished: {line}",
            report["requests"], report["fetch_errors"], report["jumps_unfinished"]
        );
    }
}

#[test]
fn fly_exits_non_zero_when_the_server_is_killed_mid_flight() {
    let dir = tempfile::tempdir().unwrap();
    let repo = korea(dir.path());
    let server = common::serve(&[("korea", &repo)]);
    let url = server.url.trim_end_matches('/').to_string();
    let upstream = url.trim_start_matches("http://").to_string();
    let flight = std::thread::spawn(move || fly(&url));
    // Killed 0.3 s after its first blob answer: mid-flight, not before the session opened.
    let blobs_answered = || {
        let (_, _, body) = ask(&upstream, "/metrics")?;
        String::from_utf8_lossy(&body).lines().find_map(|l| {
            l.strip_prefix("quincunx_http_requests_total{route=\"blob\",status=\"200\"} ")?
                .trim()
                .parse::<u64>()
                .ok()
        })
    };
    let waited = std::time::Instant::now();
    while blobs_answered().unwrap_or(0) == 0 {
        assert!(
            waited.elapsed() < Duration::from_secs(60),
            "no blob was ever asked for"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(300));
    drop(server);
    let run = flight.join().unwrap();
    assert!(!run.success, "exit 0 with the server gone: {}", run.stdout);
    let line = run
        .stderr
        .lines()
        .find(|l| l.starts_with("error: "))
        .unwrap_or_else(|| {
            panic!("no one-line reason: {}", run.stderr);
        });
    println!("killed server: {line}");
}
