//! Faults over real sockets: a server killed and restarted mid-run, and a fake server that
//! truncates, corrupts, refuses, fails or stalls. No panic, errors reported per key, exact
//! bytes once a good server is back.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::time::{Duration, Instant};

use common::*;
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::fetch::{ErrorKind, FetchConfig, FetchError, Fetched, Fetcher, Transport};

#[test]
fn a_server_killed_and_restarted_mid_run_loses_and_corrupts_nothing() {
    for transport in Transport::ALL {
        let server = TestServer::start();
        let addr = server.addr;
        // A slow link, so the kill lands mid-run.
        let link = LinkProxy::start(addr, 400.0, Duration::from_millis(20)).unwrap();
        let mut c = config(&format!("http://{}", link.local_addr()), "plain", transport);
        c.request_timeout = Duration::from_secs(2);
        c.max_backoff = Duration::from_millis(200);
        let fetcher = Fetcher::spawn(c, raw()).unwrap();
        let wants = planar_wants();
        fetcher.submit(wants.clone());
        let start = Instant::now();
        let mut early = Vec::new();
        while early.len() < 10 && start.elapsed() < Duration::from_secs(20) {
            std::thread::sleep(Duration::from_millis(5));
            early.extend(fetcher.poll());
            fetcher.submit(wants.clone());
        }
        assert!(
            early.len() >= 10 && early.len() < wants.len(),
            "{transport:?}: {}",
            early.len()
        );
        server.kill();
        // Down for a while: connections are refused or reset.
        let down = Instant::now();
        while down.elapsed() < Duration::from_millis(500) {
            std::thread::sleep(Duration::from_millis(5));
            early.extend(fetcher.poll());
            fetcher.submit(wants.clone());
        }
        let restarted = TestServer::start_on(addr);
        let open: Vec<_> = wants
            .iter()
            .filter(|(k, _)| {
                !early
                    .iter()
                    .any(|(e, r)| e == k && !matches!(r, Fetched::Failed(_)))
            })
            .copied()
            .collect();
        let (mut answers, _failures) = drive(&fetcher, &open, Duration::from_secs(60), true);
        for (k, r) in early {
            if !matches!(r, Fetched::Failed(_)) {
                answers.insert(k, r);
            }
        }
        assert_exact(&answers, &wants);
        let stats = fetcher.stats();
        assert!(
            stats.errors.total() > 0,
            "{transport:?}: the kill was noticed"
        );
        drop(restarted);
    }
}

fn fake_config(fake: &FakeServer, transport: Transport) -> FetchConfig {
    let mut c = FetchConfig::new(fake.remote());
    c.transport = transport;
    c.request_timeout = Duration::from_millis(500);
    c.retry_backoff = Duration::from_millis(20);
    c.max_backoff = Duration::from_millis(100);
    c.max_attempts = 3;
    c
}

/// Runs `fault`, checks each key is reported Failed with an error of `kind`, then switches
/// the server to good answers and checks every key arrives exactly.
fn fault_then_recovery(fault: Fault, kind: ErrorKind, transport: Transport) {
    let fake = FakeServer::start(fault);
    let fetcher = Fetcher::spawn(fake_config(&fake, transport), raw()).unwrap();
    let wants: Vec<_> = planar_wants().into_iter().take(12).collect();
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), false);
    assert_eq!(
        answers.len(),
        wants.len(),
        "{fault:?} {transport:?}: every key reported"
    );
    for (k, r) in &answers {
        match r {
            Fetched::Failed(e) => assert_eq!(e.kind(), kind, "{fault:?} {transport:?} {k:?}: {e}"),
            _ => panic!("{fault:?} {transport:?} {k:?}: not a failure"),
        }
    }
    let stats = fetcher.stats();
    assert!(stats.errors.total() >= wants.len() as u64);
    if kind == ErrorKind::ClientStatus {
        // Permanent: one attempt per key.
        assert_eq!(
            stats.requests,
            wants.len() as u64,
            "{fault:?} {transport:?}"
        );
    } else {
        assert!(
            stats.requests >= 2 * wants.len() as u64,
            "{fault:?} {transport:?}: retried"
        );
    }
    fake.set(Fault::Good);
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), true);
    assert_exact(&answers, &wants);
}

#[test]
fn a_404_is_a_leaf_only_from_a_static_export() {
    let fake = FakeServer::start(Fault::LeafNotFound);
    let wants = planar_wants();
    assert!(wants.iter().any(|(k, _)| *k == PLANAR_LEAF));
    // The fake server speaks HTTP/1.1 only.
    for transport in [Transport::Pipelined, Transport::Plain] {
        // From a static export (the metadata's `static_export`) the leaf's 404 is a leaf.
        let mut c = fake_config(&fake, transport);
        c.remote.static_export = true;
        let fetcher = Fetcher::spawn(c, raw()).unwrap();
        let (answers, failures) = drive(&fetcher, &wants, Duration::from_secs(30), false);
        assert!(failures.is_empty(), "{transport:?}: {failures:?}");
        assert_exact(&answers, &wants);
        let stats = fetcher.stats();
        assert_eq!(stats.errors.total(), 0, "{transport:?}");
        assert_eq!(stats.leaves, 1, "{transport:?}");
        // From `quincunx serve` a 404 is an error: the version asked for is not served.
        let fetcher = Fetcher::spawn(fake_config(&fake, transport), raw()).unwrap();
        let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), false);
        match &answers[&PLANAR_LEAF] {
            Fetched::Failed(e) => assert_eq!(e, &FetchError::Status(404), "{transport:?}"),
            other => panic!("{transport:?}: the 404 was taken as {other:?}"),
        }
        assert_eq!(fetcher.stats().errors.client_status, 1, "{transport:?}");
    }
}

#[test]
fn truncated_bodies_are_connection_errors_and_recover() {
    fault_then_recovery(Fault::Truncate, ErrorKind::Connection, Transport::Pipelined);
    fault_then_recovery(Fault::Truncate, ErrorKind::Connection, Transport::Plain);
}

#[test]
fn corrupted_status_lines_are_protocol_errors_and_recover() {
    fault_then_recovery(
        Fault::CorruptStatus,
        ErrorKind::Protocol,
        Transport::Pipelined,
    );
    // hyper reports a malformed response as a request error too.
    let fake = FakeServer::start(Fault::CorruptStatus);
    let fetcher = Fetcher::spawn(fake_config(&fake, Transport::Plain), raw()).unwrap();
    let wants: Vec<_> = planar_wants().into_iter().take(4).collect();
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), false);
    assert!(
        answers
            .values()
            .all(|r| matches!(r, Fetched::Failed(e) if e.is_transient()))
    );
}

#[test]
fn not_found_is_permanent_and_reported_once_per_key() {
    fault_then_recovery(
        Fault::NotFound,
        ErrorKind::ClientStatus,
        Transport::Pipelined,
    );
    fault_then_recovery(Fault::NotFound, ErrorKind::ClientStatus, Transport::Plain);
}

#[test]
fn server_errors_are_retried_then_reported_and_recover() {
    fault_then_recovery(
        Fault::ServerError,
        ErrorKind::ServerStatus,
        Transport::Pipelined,
    );
    fault_then_recovery(
        Fault::ServerError,
        ErrorKind::ServerStatus,
        Transport::Plain,
    );
}

#[test]
fn a_stalled_server_times_out_and_recovers() {
    fault_then_recovery(Fault::Stall, ErrorKind::Timeout, Transport::Pipelined);
    fault_then_recovery(Fault::Stall, ErrorKind::Timeout, Transport::Plain);
}

#[test]
fn an_unreachable_server_is_reported_per_key() {
    // A port nothing listens on.
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let fake = FakeServer::start(Fault::Good);
    let mut remote = fake.remote();
    remote.endpoint.addr.set_port(port);
    remote.endpoint.host = format!("127.0.0.1:{port}");
    for transport in Transport::ALL {
        let mut c = fake_config(&fake, transport);
        c.remote = remote.clone();
        let fetcher = Fetcher::spawn(c, raw()).unwrap();
        let wants: Vec<_> = planar_wants().into_iter().take(5).collect();
        let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), false);
        assert_eq!(answers.len(), 5);
        assert!(
            answers
                .values()
                .all(|r| matches!(r, Fetched::Failed(FetchError::Connection(_)))),
            "{transport:?}: {answers:?}"
        );
    }
}

/// A server that answers every request with a valid head announcing a 100 000-byte body,
/// then trickles the body one byte every 50 ms: always making progress, done in 5000 s.
fn start_trickler() -> std::net::SocketAddr {
    use std::io::Read;
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for s in listener.incoming() {
            let Ok(mut s) = s else { return };
            std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                // Whatever was asked: one long answer, a byte at a time.
                if s.read(&mut buf).unwrap_or(0) == 0 {
                    return;
                }
                // The head at once (reqwest wants it within its read timeout), then the
                // body a byte at a time.
                quincunx_testkit::http::trickle_answer(&mut s);
            });
        }
    });
    addr
}

#[test]
fn a_trickling_server_meets_the_request_deadline_and_is_counted() {
    let addr = start_trickler();
    let fake = FakeServer::start(Fault::Good);
    for transport in [Transport::Pipelined, Transport::Plain] {
        let mut c = fake_config(&fake, transport);
        let base = format!("http://{addr}");
        c.remote.endpoint = quincunx_client::fetch::http1::Endpoint::from_url(&base).unwrap();
        c.remote.base_url = base;
        // A byte every 50 ms is progress: the 500 ms progress timeout never fires.
        c.request_deadline = Duration::from_millis(1500);
        c.max_attempts = 2;
        let fetcher = Fetcher::spawn(c, raw()).unwrap();
        let wants: Vec<_> = planar_wants().into_iter().take(4).collect();
        // The answers would take 5000 s to trickle in: only the deadline ends them.
        let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(40), false);
        assert_eq!(
            answers.len(),
            wants.len(),
            "{transport:?}: every key reported"
        );
        for (k, r) in &answers {
            match r {
                Fetched::Failed(e) => {
                    assert_eq!(e.kind(), ErrorKind::Timeout, "{transport:?} {k:?}: {e}");
                    assert!(
                        matches!(e, FetchError::Deadline(d) if *d == Duration::from_millis(1500)),
                        "{transport:?} {k:?}: {e}"
                    );
                }
                other => panic!("{transport:?} {k:?}: {other:?}"),
            }
        }
        let stats = fetcher.stats();
        assert!(
            stats.errors.timeout >= wants.len() as u64,
            "{transport:?}: {:?}",
            stats.errors
        );
        assert_eq!(stats.bytes_fetched, 0, "{transport:?}");
    }
}
