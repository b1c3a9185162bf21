//! Slow and stalling clients over real loopback sockets: the rules of "Slow clients" in
//! `docs/http-api.md`. Timeouts are configured short (about a second) so the tests run in
//! seconds; the bounds asserted are generous multiples of them, and a well-behaved client
//! checks throughout that others are still served.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::{Read, Write};
use std::net::IpAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use common::*;

const LOCAL: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

fn ip(s: &str) -> IpAddr {
    s.parse().unwrap()
}

fn short_timeouts(c: &mut quincunx_server::ServerConfig) {
    c.limits.header_timeout_s = 1.0;
    c.limits.write_timeout_s = 1.0;
    c.limits.idle_timeout_s = 30.0;
}

/// Writes `bytes` every `every` until the server closes the connection or `limit` passes;
/// returns how long the connection lived, or `None` if it outlived `limit`.
fn trickle(
    s: &mut std::net::TcpStream,
    bytes: &[u8],
    every: Duration,
    limit: Duration,
) -> Option<Duration> {
    let start = Instant::now();
    s.set_read_timeout(Some(every)).unwrap();
    let mut chunk = [0u8; 4096];
    while start.elapsed() < limit {
        if s.write_all(bytes).is_err() {
            return Some(start.elapsed());
        }
        match s.read(&mut chunk) {
            Ok(0) => return Some(start.elapsed()),
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => {
                return Some(start.elapsed());
            }
            Err(_) => {} // timed out: the connection is still open
        }
    }
    None
}

#[test]
fn crlf_trickling_is_closed_by_the_head_timer_not_restarted_by_empty_lines() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    // A new connection: empty lines every 300 ms (4 are tolerated, so the head timer,
    // started at the accept, ends it first).
    let mut s = connect(server.addr);
    let lived = trickle(
        &mut s,
        b"\r\n",
        Duration::from_millis(300),
        Duration::from_secs(10),
    );
    assert!(
        lived.is_some(),
        "a CRLF-trickling connection was held for 10 s"
    );
    // After a request, the timer starts at the first empty line.
    let mut s = connect(server.addr);
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
        .unwrap();
    assert_eq!(read_responses(&mut s, 1)[0].status, 200);
    let lived = trickle(
        &mut s,
        b"\r\n",
        Duration::from_millis(300),
        Duration::from_secs(10),
    );
    assert!(
        lived.is_some(),
        "a keep-alive connection trickling CRLF was held for 10 s"
    );
    let m = &server.state.metrics;
    assert_eq!(m.connections_header_timeout.load(Relaxed), 2);
    assert_eq!(m.connections_idle_closed.load(Relaxed), 0);
    good.stop();
}

#[test]
fn a_burst_of_empty_lines_closes_the_connection_at_once() {
    let server = Running::start(|c| c.limits.header_timeout_s = 30.0);
    let mut s = connect(server.addr);
    s.write_all(&b"\r\n".repeat(100)).unwrap();
    assert!(closed_within(&mut s, Duration::from_secs(10)));
    assert_eq!(
        server.state.metrics.connections_empty_lines.load(Relaxed),
        1
    );
    // The tolerated few before a request line are ignored.
    let r = roundtrip(
        server.addr,
        "\r\n\r\nGET /healthz HTTP/1.1\r\nHost: t\r\n\r\n",
    );
    assert_eq!(r.status, 200);
}

#[test]
fn a_new_connection_must_complete_its_first_head_within_the_timeout_of_the_accept() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    // Silent for most of the timeout, then a head trickled a header line at a time.
    let mut s = connect(server.addr);
    std::thread::sleep(Duration::from_millis(700));
    s.write_all(b"GET /healthz HTTP/1.1\r\n").unwrap();
    let lived = trickle(
        &mut s,
        b"X-A: b\r\n",
        Duration::from_millis(100),
        Duration::from_secs(10),
    );
    assert!(lived.is_some(), "a trickled first head was held for 10 s");
    good.stop();
}

#[test]
fn one_address_cannot_hold_more_than_its_connection_cap() {
    let server = Running::start(|c| {
        c.limits.max_connections_per_ip = 1;
        c.limits.per_ip_exempt = vec!["127.0.0.3".into()];
    });
    let request = b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n";
    let mut first = connect_from(LOCAL, server.addr, None);
    first.write_all(request).unwrap();
    assert_eq!(read_responses(&mut first, 1)[0].status, 200);
    // A second connection from the same address: 429 and closed.
    let mut second = connect_from(LOCAL, server.addr, None);
    let (bytes, closed) = read_to_close(&mut second);
    assert!(closed);
    let (r, _) = parse_response(&bytes, false)
        .unwrap()
        .expect("a 429 answer");
    assert_eq!(r.status, 429);
    assert_eq!(
        server
            .state
            .metrics
            .connections_rejected_per_ip
            .load(Relaxed),
        1
    );
    // Another address is served meanwhile, and the held connection still works.
    let mut other = connect_from(ip("127.0.0.2"), server.addr, None);
    other.write_all(request).unwrap();
    assert_eq!(read_responses(&mut other, 1)[0].status, 200);
    first.write_all(request).unwrap();
    assert_eq!(read_responses(&mut first, 1)[0].status, 200);
    // An exempt address may open more.
    let mut exempt: Vec<_> = (0..3)
        .map(|_| connect_from(ip("127.0.0.3"), server.addr, None))
        .collect();
    for s in &mut exempt {
        s.write_all(request).unwrap();
        assert_eq!(read_responses(s, 1)[0].status, 200);
    }
    // Closing the held connection frees the address's slot.
    drop(first);
    let mut served = false;
    for _ in 0..100 {
        let mut s = connect_from(LOCAL, server.addr, None);
        let _ = s.write_all(request);
        let (bytes, _) = read_to_close_or_one(&mut s);
        if let Ok(Some((r, _))) = parse_response(&bytes, false)
            && r.status == 200
        {
            served = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(served, "the address's slot was not freed");
}

/// Reads one response or until close.
fn read_to_close_or_one(s: &mut std::net::TcpStream) -> (Vec<u8>, bool) {
    let mut out = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        if let Ok(Some(_)) = parse_response(&out, false) {
            return (out, false);
        }
        match s.read(&mut chunk) {
            Ok(0) | Err(_) => return (out, true),
            Ok(n) => out.extend_from_slice(&chunk[..n]),
        }
    }
}

#[test]
fn a_slow_but_steady_pipelined_reader_gets_every_answer() {
    // A head timeout far below the time the server spends blocked on this reader.
    let server = Running::start(|c| {
        c.limits.header_timeout_s = 0.1;
        c.limits.write_timeout_s = 5.0;
        c.limits.idle_timeout_s = 30.0;
    });
    let prefix = planar_prefix(&server.state);
    let centres: Vec<[i64; 3]> = planar_centres(PLANAR_M, PLANAR_LEVELS)
        .into_keys()
        .filter(|c| [c[0], c[1]] != [PLANAR_LEAF.x, PLANAR_LEAF.y])
        .collect();
    let n = 5000;
    let mut s = connect_from(LOCAL, server.addr, Some(4096));
    let mut writer = s.try_clone().unwrap();
    let batch: String = (0..n)
        .map(|i| {
            let c = centres[i % centres.len()];
            format!("GET {prefix}/{}/{} HTTP/1.1\r\nHost: t\r\n\r\n", c[0], c[1])
        })
        .collect();
    let sender = std::thread::spawn(move || writer.write_all(batch.as_bytes()));
    // Read 4 KiB at a time with a 10 ms pause after each: about 5 MB of answers at
    // about 400 KB/s. That is more than the 4 MB the kernel lets the server's send
    // buffer grow to, so the server ends up blocked on this client for many head
    // timeouts in all, with request heads half read (the previous code cut this client
    // after about 1,600 answers), while the client never pauses for more than 10 ms.
    let mut buf = Vec::new();
    let mut got = 0;
    let mut chunk = [0u8; 4096];
    while got < n {
        match parse_response(&buf, false).unwrap() {
            Some((r, used)) => {
                assert_eq!(r.status, 200);
                assert_eq!(
                    r.body,
                    blob_for(centres[got % centres.len()]),
                    "answer {got}"
                );
                buf.drain(..used);
                got += 1;
            }
            None => {
                let k = s.read(&mut chunk).unwrap();
                assert!(k > 0, "connection closed after {got} of {n} answers");
                buf.extend_from_slice(&chunk[..k]);
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
    sender.join().unwrap().unwrap();
    let m = &server.state.metrics;
    assert_eq!(m.connections_header_timeout.load(Relaxed), 0);
    assert_eq!(m.connections_write_timeout.load(Relaxed), 0);
}

#[test]
fn a_reader_that_stops_is_cut_by_the_write_timeout() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    let prefix = planar_prefix(&server.state);
    let mut s = connect_from(LOCAL, server.addr, Some(4096));
    let batch = format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n").repeat(2000);
    let mut writer = s.try_clone().unwrap();
    let sender = std::thread::spawn(move || {
        let _ = writer.write_all(batch.as_bytes());
    });
    std::thread::sleep(Duration::from_secs(4));
    assert!(closed_within(&mut s, Duration::from_secs(10)));
    let _ = sender.join();
    let m = &server.state.metrics;
    assert_eq!(m.connections_write_timeout.load(Relaxed), 1);
    assert_eq!(m.connections_header_timeout.load(Relaxed), 0);
    good.stop();
}

#[test]
fn http2_partial_preface_and_a_preface_without_requests_are_closed() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    let mut partial = connect(server.addr);
    partial.write_all(&h2::PREFACE[..10]).unwrap();
    assert!(
        closed_within(&mut partial, Duration::from_secs(10)),
        "a partial preface was held"
    );
    let mut quiet = connect(server.addr);
    quiet.write_all(h2::PREFACE).unwrap();
    quiet.write_all(&h2::settings(&[])).unwrap();
    let seen = h2::read_frames(&mut quiet, Duration::from_secs(10), |_| false);
    assert!(seen.closed, "a preface without requests was held: {seen:?}");
    assert_eq!(seen.goaway, Some(0), "{seen:?}");
    assert_eq!(
        server
            .state
            .metrics
            .connections_header_timeout
            .load(Relaxed),
        2
    );
    good.stop();
}

#[test]
fn http2_trickled_headers_are_closed() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    for after_a_request in [false, true] {
        let mut s = connect(server.addr);
        if after_a_request {
            s.write_all(&h2::hello("/healthz")).unwrap();
            let seen = h2::read_frames(&mut s, Duration::from_secs(5), |seen| {
                !seen.statuses.is_empty()
            });
            assert_eq!(seen.statuses, [(1, 200)]);
        } else {
            s.write_all(h2::PREFACE).unwrap();
            s.write_all(&h2::settings(&[])).unwrap();
        }
        // A HEADERS block that never ends: one byte of CONTINUATION every 100 ms.
        let stream = if after_a_request { 3 } else { 1 };
        let block = h2::get_block("/healthz");
        s.write_all(&h2::frame(h2::HEADERS, h2::END_STREAM, stream, &block[..2]))
            .unwrap();
        let start = Instant::now();
        let mut closed = false;
        for b in block[2..].iter().cycle().take(100) {
            if s.write_all(&h2::frame(h2::CONTINUATION, 0, stream, &[*b]))
                .is_err()
            {
                closed = true;
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
            if start.elapsed() > Duration::from_secs(8) {
                break;
            }
        }
        if !closed {
            closed = h2::read_frames(&mut s, Duration::from_secs(2), |_| false).closed;
        }
        assert!(
            closed,
            "trickled HEADERS held (after a request: {after_a_request})"
        );
    }
    good.stop();
}

#[test]
fn http2_half_open_and_stalled_streams_are_closed() {
    let server = Running::start(short_timeouts);
    let good = WellBehaved::start(server.addr, "/healthz".into());
    let prefix = planar_prefix(&server.state);
    let path = format!("{prefix}/32/32");
    // (a) A stream left open by the client (no END_STREAM) on a window of 0: its answer
    // cannot move. PINGs keep bytes flowing; the stream's lack of progress ends it.
    let mut s = connect(server.addr);
    s.write_all(h2::PREFACE).unwrap();
    s.write_all(&h2::settings(&[(4, 0)])).unwrap(); // INITIAL_WINDOW_SIZE = 0
    s.write_all(&h2::frame(
        h2::HEADERS,
        h2::END_HEADERS,
        1,
        &h2::get_block(&path),
    ))
    .unwrap();
    let start = Instant::now();
    let mut closed = false;
    while start.elapsed() < Duration::from_secs(10) {
        if s.write_all(&h2::frame(h2::PING, 0, 0, &[0; 8])).is_err() {
            closed = true;
            break;
        }
        let seen = h2::read_frames(&mut s, Duration::from_millis(200), |_| false);
        if seen.closed {
            closed = true;
            break;
        }
    }
    assert!(closed, "a stalled stream kept its connection for 10 s");
    assert_eq!(
        server.state.metrics.connections_write_timeout.load(Relaxed),
        1
    );
    // (b) A half-open stream that is answered, then PINGs and no further request.
    let mut s = connect(server.addr);
    s.write_all(h2::PREFACE).unwrap();
    s.write_all(&h2::settings(&[])).unwrap();
    s.write_all(&h2::frame(
        h2::HEADERS,
        h2::END_HEADERS,
        1,
        &h2::get_block("/healthz"),
    ))
    .unwrap();
    let start = Instant::now();
    let mut closed = false;
    let mut answered = false;
    while start.elapsed() < Duration::from_secs(10) {
        if s.write_all(&h2::frame(h2::PING, 0, 0, &[0; 8])).is_err() {
            closed = true;
            break;
        }
        let seen = h2::read_frames(&mut s, Duration::from_millis(200), |_| false);
        answered |= seen.statuses.contains(&(1, 200));
        if seen.closed {
            closed = true;
            break;
        }
    }
    assert!(answered, "the half-open stream was not answered");
    assert!(
        closed,
        "PINGs after a half-open stream kept the connection for 10 s"
    );
    good.stop();
}

#[test]
fn an_idle_http2_connection_is_not_cut_by_the_head_timer() {
    let server = Running::start(short_timeouts);
    let mut s = connect(server.addr);
    s.write_all(&h2::hello("/healthz")).unwrap();
    let seen = h2::read_frames(&mut s, Duration::from_secs(5), |seen| {
        !seen.statuses.is_empty()
    });
    assert_eq!(seen.statuses, [(1, 200)]);
    // A trailing frame, then silence for three head timeouts: an idle connection.
    s.write_all(&h2::frame(h2::WINDOW_UPDATE, 0, 0, &100u32.to_be_bytes()))
        .unwrap();
    let seen = h2::read_frames(&mut s, Duration::from_secs(3), |_| false);
    assert!(!seen.closed, "{seen:?}");
    s.write_all(&h2::frame(
        h2::HEADERS,
        h2::END_HEADERS | h2::END_STREAM,
        3,
        &h2::get_block("/healthz"),
    ))
    .unwrap();
    let seen = h2::read_frames(&mut s, Duration::from_secs(5), |seen| {
        !seen.statuses.is_empty()
    });
    assert_eq!(seen.statuses, [(3, 200)], "{seen:?}");
    assert_eq!(
        server
            .state
            .metrics
            .connections_header_timeout
            .load(Relaxed),
        0
    );
}

#[test]
fn a_full_server_closes_its_least_useful_connection_to_admit_a_new_one() {
    let server = Running::start(|c| {
        c.limits.max_connections = 4;
        c.limits.max_connections_per_ip = 0;
        c.limits.header_timeout_s = 4.0; // productive connections idle for 1 s may go
    });
    let m = &server.state.metrics;
    let request = b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n";
    let mut active = connect(server.addr);
    active.write_all(request).unwrap();
    assert_eq!(read_responses(&mut active, 1)[0].status, 200);
    let mut silent: Vec<_> = (0..3).map(|_| connect(server.addr)).collect();
    for _ in 0..100 {
        if m.connections_open.load(Relaxed) == 4 {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(m.connections_open.load(Relaxed), 4);
    // Older than the silent ones, but it completed requests: never chosen before them.
    active.write_all(request).unwrap();
    assert_eq!(read_responses(&mut active, 1)[0].status, 200);
    std::thread::sleep(Duration::from_millis(1200));
    // Full: a new client is admitted in place of a silent connection, not refused.
    let mut new = connect(server.addr);
    new.write_all(request).unwrap();
    assert_eq!(read_responses(&mut new, 1)[0].status, 200);
    assert_eq!(m.connections_evicted.load(Relaxed), 1);
    assert_eq!(m.connections_rejected.load(Relaxed), 0);
    let mut closed = 0;
    for s in &mut silent {
        closed += usize::from(closed_within(s, Duration::from_millis(300)));
    }
    assert_eq!(closed, 1, "exactly one silent connection makes room");
    active.write_all(request).unwrap();
    assert_eq!(read_responses(&mut active, 1)[0].status, 200);
}
