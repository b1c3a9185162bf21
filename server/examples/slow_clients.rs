//! Measures what slow-loris clients do to a well-behaved one (`docs/serving.md`, "Slow
//! clients"): a server with a 1,000-connection limit on 127.0.0.1 (the test fixtures'
//! repositories), 1,000 clients trickling bare CRLFs and 1,000 half-open HTTP/2 clients
//! (a stream left open on a window of 0, PINGs every 2 s), spread over the source
//! addresses 127.0.0.2-127.0.0.9 and reconnecting whenever they are closed, and one
//! well-behaved client on 127.0.0.1 making blob requests one at a time (every 50th on a
//! new connection) for `DURATION_S` (default 60) seconds. Prints one JSON line.
//!
//! `cargo run --release -p quincunx-server --example slow_clients`; environment:
//! `DURATION_S`, `PER_IP` (max_connections_per_ip, default the server's), `ATTACKERS` (per kind,
//! default 1000). Loopback only; every loop is bounded by the duration.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use quincunx_server::{RepoConfig, Server, ServerConfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[derive(Default)]
struct Counts {
    crlf_open: AtomicU64,
    h2_open: AtomicU64,
    closed_by_server: AtomicU64,
    refused: AtomicU64,
}

fn main() {
    let duration = Duration::from_secs(env("DURATION_S", 60));
    let default_per_ip = quincunx_server::config::Limits::default().max_connections_per_ip;
    let per_ip = env("PER_IP", default_per_ip as u64) as usize;
    let attackers = env("ATTACKERS", 1000) as usize;
    let _ = rlimit::increase_nofile_limit(20_000);
    let dir = tempfile::tempdir().unwrap();
    let repos: Vec<RepoConfig> = quincunx_testkit::build_fixtures(dir.path())
        .into_iter()
        .map(|(name, path)| RepoConfig { name, path })
        .collect();
    let mut config = ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        repos,
        ..Default::default()
    };
    config.limits.max_connections = 1000;
    config.limits.max_connections_per_ip = per_ip;
    let limits = config.limits.clone();

    let server_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let server = server_rt.block_on(Server::bind(config)).unwrap();
    let addr = server.local_addr().unwrap();
    let state = server.state().clone();
    let (version, blob) = {
        let (_, served) = state.repo("plain").unwrap();
        (served.version.clone(), "32/32")
    };
    let path = format!("/repos/plain/v/{version}/d/{blob}");
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server_task = server_rt.spawn(server.run(async {
        let _ = stop_rx.await;
    }));

    // The attackers, on their own runtime and thread.
    let counts = Arc::new(Counts::default());
    let done = Arc::new(AtomicBool::new(false));
    let attack_rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let attack_thread = {
        let (counts, done, path) = (counts.clone(), done.clone(), path.clone());
        std::thread::spawn(move || {
            attack_rt.block_on(async move {
                let mut tasks = Vec::new();
                for i in 0..2 * attackers {
                    let from = IpAddr::V4(Ipv4Addr::new(127, 0, 0, 2 + (i % 8) as u8));
                    let (counts, done, path) = (counts.clone(), done.clone(), path.clone());
                    tasks.push(tokio::spawn(async move {
                        // Spread the first connections over a second.
                        tokio::time::sleep(Duration::from_micros(500 * i as u64)).await;
                        attacker(i % 2 == 0, from, addr, &path, &counts, &done).await;
                    }));
                }
                for t in tasks {
                    let _ = t.await;
                }
            });
        })
    };

    // The well-behaved client.
    let start = Instant::now();
    let mut latencies = Vec::new();
    let mut failures: Vec<String> = Vec::new();
    let mut timeline = Vec::new();
    let mut next_sample = Duration::ZERO;
    let mut conn: Option<std::net::TcpStream> = None;
    let request = format!("GET {path} HTTP/1.1\r\nHost: t\r\n\r\n");
    let mut n = 0u64;
    while start.elapsed() < duration {
        if start.elapsed() >= next_sample {
            timeline.push(serde_json::json!({
                "t_s": next_sample.as_secs(),
                "crlf_attackers_connected": counts.crlf_open.load(Relaxed),
                "h2_attackers_connected": counts.h2_open.load(Relaxed),
                "server_connections_open": state.metrics.connections_open.load(Relaxed),
            }));
            next_sample += Duration::from_secs(5);
        }
        if n.is_multiple_of(50) {
            conn = None;
        }
        n += 1;
        let t0 = Instant::now();
        let result = one_request(&mut conn, addr, request.as_bytes());
        let took = t0.elapsed();
        match result {
            Ok(200) => latencies.push(took),
            Ok(status) => {
                failures.push(format!("status {status}"));
                conn = None;
            }
            Err(e) => {
                failures.push(e);
                conn = None;
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    done.store(true, Relaxed);
    let m = &state.metrics;
    let server_counts = serde_json::json!({
        "header_timeout": m.connections_header_timeout.load(Relaxed),
        "write_timeout": m.connections_write_timeout.load(Relaxed),
        "idle_closed": m.connections_idle_closed.load(Relaxed),
        "empty_lines": m.connections_empty_lines.load(Relaxed),
        "rejected_per_ip_429": m.connections_rejected_per_ip.load(Relaxed),
        "rejected_full_503": m.connections_rejected.load(Relaxed),
        "evicted": m.connections_evicted.load(Relaxed),
        "accepted": m.connections_accepted.load(Relaxed),
    });
    let _ = stop_tx.send(());
    let _ = attack_thread.join();
    let _ = server_rt.block_on(server_task);

    latencies.sort();
    let ms = |d: Duration| (d.as_secs_f64() * 1e5).round() / 1e2;
    let pct = |p: f64| {
        latencies
            .get(((latencies.len() as f64 * p) as usize).min(latencies.len().saturating_sub(1)))
            .map_or(0.0, |d| ms(*d))
    };
    failures.truncate(20);
    let report = serde_json::json!({
        "bench": "slow_clients",
        "duration_s": duration.as_secs(),
        "limits": {
            "max_connections": limits.max_connections,
            "max_connections_per_ip": limits.max_connections_per_ip,
            "header_timeout_s": limits.header_timeout_s,
            "write_timeout_s": limits.write_timeout_s,
            "idle_timeout_s": limits.idle_timeout_s,
        },
        "attackers": {
            "crlf_trickling": attackers,
            "h2_half_open": attackers,
            "source_addresses": "127.0.0.2-127.0.0.9",
            "closed_by_server": counts.closed_by_server.load(Relaxed),
            "refused": counts.refused.load(Relaxed),
        },
        "client": {
            "requests_ok": latencies.len(),
            "requests_failed": n as usize - latencies.len(),
            "new_connection_every": 50,
            "latency_ms": {"p50": pct(0.5), "p99": pct(0.99), "max": latencies.last().map_or(0.0, |d| ms(*d))},
            "first_failures": failures,
        },
        "server": server_counts,
        "timeline": timeline,
    });
    println!("{report}");
}

/// One request on `conn` (connecting first if it is `None`): the status.
fn one_request(
    conn: &mut Option<std::net::TcpStream>,
    addr: SocketAddr,
    request: &[u8],
) -> Result<u16, String> {
    if conn.is_none() {
        let s = std::net::TcpStream::connect(addr).map_err(|e| format!("connect: {e}"))?;
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s.set_nodelay(true).unwrap();
        *conn = Some(s);
    }
    let s = conn.as_mut().unwrap();
    s.write_all(request).map_err(|e| format!("write: {e}"))?;
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    loop {
        let mut headers = [httparse::EMPTY_HEADER; 32];
        let mut r = httparse::Response::new(&mut headers);
        if let Ok(httparse::Status::Complete(head)) = r.parse(&buf) {
            let status = r.code.unwrap_or(0);
            let len = r
                .headers
                .iter()
                .find(|h| h.name.eq_ignore_ascii_case("content-length"))
                .and_then(|h| std::str::from_utf8(h.value).ok()?.parse::<usize>().ok())
                .unwrap_or(0);
            if buf.len() >= head + len {
                return Ok(status);
            }
        }
        let n = s.read(&mut chunk).map_err(|e| format!("read: {e}"))?;
        if n == 0 {
            return Err("closed".into());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

/// One attacker: connects from `from`, misbehaves until the server closes it, then
/// reconnects (after 100 ms; 1 s after a refusal), until `done`.
async fn attacker(
    crlf: bool,
    from: IpAddr,
    addr: SocketAddr,
    path: &str,
    counts: &Counts,
    done: &AtomicBool,
) {
    let open = if crlf {
        &counts.crlf_open
    } else {
        &counts.h2_open
    };
    while !done.load(Relaxed) {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        if socket.bind(SocketAddr::new(from, 0)).is_err() {
            tokio::time::sleep(Duration::from_secs(1)).await;
            continue;
        }
        let Ok(mut s) = socket.connect(addr).await else {
            tokio::time::sleep(Duration::from_secs(1)).await;
            continue;
        };
        open.fetch_add(1, Relaxed);
        let mut refused = false;
        if !crlf {
            let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
            hello.extend(frame(4, 0, 0, &[0, 4, 0, 0, 0, 0])); // INITIAL_WINDOW_SIZE = 0
            let mut block = vec![0x82, 0x86, 0x04, path.len() as u8];
            block.extend_from_slice(path.as_bytes());
            block.extend_from_slice(&[0x01, 0x01, b't']);
            hello.extend(frame(1, 4, 1, &block)); // HEADERS, END_HEADERS, no END_STREAM
            let _ = s.write_all(&hello).await;
        }
        let mut buf = [0u8; 4096];
        while !done.load(Relaxed) {
            let trickle = if crlf {
                b"\r\n".to_vec()
            } else {
                frame(6, 0, 0, &[0; 8]) // PING
            };
            if s.write_all(&trickle).await.is_err() {
                break;
            }
            match tokio::time::timeout(Duration::from_secs(2), s.read(&mut buf)).await {
                Ok(Ok(0) | Err(_)) => break,
                Ok(Ok(_))
                    if buf.starts_with(b"HTTP/1.1 429") || buf.starts_with(b"HTTP/1.1 503") =>
                {
                    refused = true;
                    break;
                }
                // Nothing but a refusal is ever answered to a CRLF trickler.
                Ok(Ok(_)) if crlf => break,
                _ => {} // HTTP/2: SETTINGS, PING acks
            }
        }
        open.fetch_sub(1, Relaxed);
        if refused {
            counts.refused.fetch_add(1, Relaxed);
            tokio::time::sleep(Duration::from_secs(1)).await;
        } else {
            counts.closed_by_server.fetch_add(1, Relaxed);
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
    let len = payload.len() as u32;
    let mut f = vec![(len >> 16) as u8, (len >> 8) as u8, len as u8, kind, flags];
    f.extend_from_slice(&stream.to_be_bytes());
    f.extend_from_slice(payload);
    f
}
