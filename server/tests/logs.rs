//! What the server logs when things go wrong, captured from `tracing`: a corrupt blob
//! logs once however often it is asked for, shutdown names the connections really left,
//! and an absurd `--threads` is one clear error at start.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::Write;
use std::sync::Mutex;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use common::*;

/// Every log line of this test process.
static LOGS: Mutex<Vec<u8>> = Mutex::new(Vec::new());

struct Capture;

impl Write for Capture {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        LOGS.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn capture_logs() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let subscriber = tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new("quincunx_server=info"))
            .with_ansi(false)
            .with_writer(|| Capture)
            .finish();
        tracing::subscriber::set_global_default(subscriber).unwrap();
    });
}

/// Log lines containing all of `needles`.
fn lines_with(needles: &[&str]) -> Vec<String> {
    let logs = LOGS.lock().unwrap();
    String::from_utf8_lossy(&logs)
        .lines()
        .filter(|l| needles.iter().all(|n| l.contains(n)))
        .map(String::from)
        .collect()
}

/// Truncates every file of the repository at `dir` to a few bytes: whatever the store
/// has not read yet can no longer be read.
fn corrupt(dir: &std::path::Path) {
    for entry in walk(dir) {
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(&entry)
            .unwrap();
        f.set_len(16.min(f.metadata().unwrap().len())).unwrap();
    }
}

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn a_corrupt_blob_is_logged_once_and_every_failure_counted() {
    capture_logs();
    let server = Running::start(|c| c.cache_bytes = 1);
    corrupt(&server.repo_dir("plain"));
    let c = planar_centres(PLANAR_M, PLANAR_LEVELS)
        .into_keys()
        .find(|c| [c[0], c[1]] != [PLANAR_LEAF.x, PLANAR_LEAF.y])
        .unwrap();
    let prefix = planar_prefix(&server.state);
    let mut s = connect(server.addr);
    let request = format!("GET {prefix}/{}/{} HTTP/1.1\r\nHost: t\r\n\r\n", c[0], c[1]);
    for _ in 0..101 {
        s.write_all(request.as_bytes()).unwrap();
        assert_eq!(read_responses(&mut s, 1)[0].status, 500);
    }
    let centre = format!("{c:?}");
    let lines = lines_with(&["ERROR", "plain", &centre]);
    assert_eq!(lines.len(), 1, "{lines:#?}");
    assert_eq!(
        server.state.metrics.repository_read_errors.load(Relaxed),
        101
    );
    let metrics = get(server.addr, "/metrics");
    let text = String::from_utf8_lossy(&metrics.body);
    assert!(
        text.contains("quincunx_repository_read_errors_total 101"),
        "{text}"
    );
}

#[test]
fn shutdown_names_the_connections_really_left_open() {
    capture_logs();
    let mut server = Running::start(|c| {
        c.limits.shutdown_grace_s = 1.0;
        c.limits.write_timeout_s = 60.0;
    });
    let prefix = planar_prefix(&server.state);
    // Three clients that pipeline and never read: their answers cannot be finished, so
    // the connections outlive the grace period.
    let batch = format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n").repeat(2000);
    let mut held = Vec::new();
    for _ in 0..3 {
        let mut s = connect_from("127.0.0.1".parse().unwrap(), server.addr, Some(4096));
        let mut w = s.try_clone().unwrap();
        let b = batch.clone();
        std::thread::spawn(move || {
            let _ = w.write_all(b.as_bytes());
        });
        let mut one = [0u8; 1];
        std::io::Read::read_exact(&mut s, &mut one).unwrap();
        held.push(s);
    }
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(server.state.metrics.connections_open.load(Relaxed), 3);
    server.begin_stop();
    server.stop();
    let lines = lines_with(&["shutdown grace period over"]);
    assert_eq!(lines.len(), 1, "{lines:#?}");
    assert!(lines[0].contains("closing 3 connections"), "{lines:#?}");
}

#[test]
fn an_absurd_thread_count_is_one_clear_error_at_start() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_quincunx-server"))
        .args([
            "--threads",
            "100000",
            "--repo",
            "a=/nonexistent",
            "--addr",
            "127.0.0.1:0",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("100000") && stderr.contains("at most 4 per core"),
        "{stderr}"
    );
}
