//! The server over real loopback sockets: statuses, keep-alive, pipelining, HTTP/2, and
//! the bad-input suite (garbage, huge heads, id limits, floods, slow-loris, limits,
//! shutdown). Every abuse ends with a check that other clients are still served.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::{Read, Write};
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use common::*;

fn healthy(server: &Running) {
    let r = get(server.addr, "/healthz");
    assert_eq!((r.status, r.body.as_slice()), (200, &b"ok\n"[..]));
}

#[test]
fn every_status_over_a_real_socket_on_one_keep_alive_connection() {
    let server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let etag = get(server.addr, &format!("{prefix}/32/32"))
        .header("etag")
        .unwrap()
        .to_string();
    let requests = [
        (
            format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n"),
            200,
        ),
        (
            format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\nIf-None-Match: {etag}\r\n\r\n"),
            304,
        ),
        (
            format!(
                "GET {prefix}/{}/{} HTTP/1.1\r\nHost: t\r\n\r\n",
                PLANAR_LEAF.x, PLANAR_LEAF.y
            ),
            200,
        ),
        (format!("GET {prefix}/0/0 HTTP/1.1\r\nHost: t\r\n\r\n"), 400),
        (
            format!("GET {prefix}/%ZZ/1 HTTP/1.1\r\nHost: t\r\n\r\n"),
            400,
        ),
        (
            "GET /repos/%ZZ/metadata.json HTTP/1.1\r\nHost: t\r\n\r\n".into(),
            404,
        ),
        (
            "GET /repos/nope/metadata.json HTTP/1.1\r\nHost: t\r\n\r\n".into(),
            404,
        ),
        (
            format!("DELETE {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n"),
            405,
        ),
        (
            format!(
                "OPTIONS {prefix}/32/32 HTTP/1.1\r\nHost: t\r\nOrigin: https://a.example\r\nAccess-Control-Request-Method: GET\r\n\r\n"
            ),
            204,
        ),
        ("GET /repos HTTP/1.1\r\nHost: t\r\n\r\n".into(), 200),
    ];
    let mut s = connect(server.addr);
    for (request, status) in &requests {
        s.write_all(request.as_bytes()).unwrap();
        let r = read_responses(&mut s, 1).remove(0);
        assert_eq!(r.status, *status, "{request}");
    }
    assert_eq!(server.state.metrics.connections_accepted.load(Relaxed), 2);
}

#[test]
fn pipelined_requests_come_back_in_order_in_fewer_writes_than_responses() {
    let server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let centres: Vec<[i64; 3]> = planar_centres(PLANAR_M, PLANAR_LEVELS)
        .into_keys()
        .filter(|c| [c[0], c[1]] != [PLANAR_LEAF.x, PLANAR_LEAF.y])
        .collect::<Vec<_>>()
        .into_iter()
        .cycle()
        .take(100)
        .collect();
    let batch: String = centres
        .iter()
        .map(|c| format!("GET {prefix}/{}/{} HTTP/1.1\r\nHost: t\r\n\r\n", c[0], c[1]))
        .collect();
    let mut s = connect(server.addr);
    let writes_before = server.state.metrics.socket_writes.load(Relaxed);
    s.write_all(batch.as_bytes()).unwrap();
    let responses = read_responses(&mut s, 100);
    let writes = server.state.metrics.socket_writes.load(Relaxed) - writes_before;
    for (c, r) in centres.iter().zip(&responses) {
        assert_eq!(r.status, 200);
        assert_eq!(r.body, blob_for(*c), "response for {c:?} out of order");
    }
    // Flushes are aggregated: several responses share a write (and a TCP segment on
    // loopback, whose MSS is 64 KiB).
    assert!(
        writes < 100,
        "{writes} socket writes for 100 pipelined responses"
    );
    eprintln!("100 pipelined responses in {writes} socket writes");
}

#[test]
fn ten_thousand_pipelined_requests_on_one_connection_are_all_answered_in_order() {
    let server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let centres: Vec<[i64; 3]> = planar_centres(PLANAR_M, PLANAR_LEVELS)
        .into_keys()
        .filter(|c| [c[0], c[1]] != [PLANAR_LEAF.x, PLANAR_LEAF.y])
        .collect();
    let n = 10_000;
    let mut s = connect(server.addr);
    let mut writer = s.try_clone().unwrap();
    let (prefix2, centres2) = (prefix.clone(), centres.clone());
    let sender = std::thread::spawn(move || {
        let mut buf = String::new();
        for i in 0..n {
            let c = centres2[i % centres2.len()];
            buf.push_str(&format!(
                "GET {prefix2}/{}/{} HTTP/1.1\r\nHost: t\r\n\r\n",
                c[0], c[1]
            ));
            if buf.len() > 1 << 16 {
                writer.write_all(buf.as_bytes()).unwrap();
                buf.clear();
            }
        }
        writer.write_all(buf.as_bytes()).unwrap();
    });
    let responses = read_responses(&mut s, n);
    sender.join().unwrap();
    for (i, r) in responses.iter().enumerate() {
        assert_eq!(r.status, 200);
        assert_eq!(r.body, blob_for(centres[i % centres.len()]), "response {i}");
    }
    healthy(&server);
}

#[test]
fn garbage_request_lines_get_400_and_the_connection_closes() {
    let server = Running::start(|_| {});
    for garbage in [
        &b"GARBAGE\r\n\r\n"[..],
        b"GET\r\n\r\n",
        b"GET / HTTP/9.9\r\n\r\n",
        b"\x00\x01\x02\x03\xff\xfe\r\n\r\n",
        b"GET /repos HTTP/1.1\r\nHost: t\r\nBad Header\r\n\r\n",
        b"GET /repos HTTP/1.1\r\nContent-Length: -1\r\n\r\n",
    ] {
        let mut s = connect(server.addr);
        s.write_all(garbage).unwrap();
        let (bytes, closed) = read_to_close(&mut s);
        assert!(closed, "{garbage:?}: connection left open");
        if !bytes.is_empty() {
            let (r, _) = parse_response(&bytes, false).unwrap().unwrap();
            assert_eq!(r.status, 400, "{garbage:?}");
        }
    }
    healthy(&server);
}

/// Sends `head` and expects `431` then a close. A client that keeps sending after the
/// limit may see the close as a reset before it reads the answer; both are documented.
fn rejected_with_431(server: &Running, head: &str) {
    let mut s = connect(server.addr);
    let _ = s.write_all(head.as_bytes());
    let (bytes, closed) = read_to_close(&mut s);
    assert!(closed, "connection left open");
    if !bytes.is_empty() {
        let (r, _) = parse_response(&bytes, false).unwrap().unwrap();
        assert_eq!(r.status, 431);
    }
}

#[test]
fn huge_request_heads_get_431_and_a_close() {
    let server = Running::start(|_| {});
    // Sent in one piece well under the socket buffers, so the answer is readable.
    let mut s = connect(server.addr);
    let head = format!(
        "GET /repos HTTP/1.1\r\nHost: t\r\nX-Pad: {}\r\n\r\n",
        "a".repeat(20 << 10)
    );
    s.write_all(head.as_bytes()).unwrap();
    s.shutdown(std::net::Shutdown::Write).unwrap();
    let (bytes, closed) = read_to_close(&mut s);
    assert!(closed);
    let (r, _) = parse_response(&bytes, false)
        .unwrap()
        .expect("a 431 answer");
    assert_eq!(r.status, 431);
    rejected_with_431(
        &server,
        &format!(
            "GET /repos HTTP/1.1\r\nX-Pad: {}\r\n\r\n",
            "a".repeat(1 << 20)
        ),
    );
    let many: String = (0..200).map(|i| format!("X-{i}: v\r\n")).collect();
    rejected_with_431(&server, &format!("GET /repos HTTP/1.1\r\n{many}\r\n"));
    healthy(&server);
}

#[test]
fn ids_at_and_past_integer_limits_are_400() {
    let server = Running::start(|_| {});
    for prefix in [planar_prefix(&server.state), sphere_prefix(&server.state)] {
        let three = prefix.contains("globe");
        for coords in [
            i64::MAX.to_string(),
            i64::MIN.to_string(),
            "9223372036854775808".into(),
            "-9223372036854775809".into(),
            "1".repeat(400),
        ] {
            let tail = if three {
                format!("{coords}/0/0")
            } else {
                format!("{coords}/0")
            };
            let r = get(server.addr, &format!("{prefix}/{tail}"));
            assert_eq!(r.status, 400, "{tail}");
        }
    }
    healthy(&server);
}

#[test]
fn slow_loris_is_closed_after_the_header_timeout_while_others_are_served() {
    let server = Running::start(|c| c.limits.header_timeout_s = 1.0);
    let mut slow = connect(server.addr);
    slow.write_all(b"GET /repos HTTP/1.1\r\n").unwrap();
    let mut closed = false;
    for i in 0..100 {
        std::thread::sleep(Duration::from_millis(100));
        if slow.write_all(format!("X-{i}: v\r\n").as_bytes()).is_err() {
            closed = true;
            break;
        }
        healthy(&server);
    }
    if !closed {
        let (_, c) = read_to_close(&mut slow);
        closed = c;
    }
    assert!(closed, "a head trickling in for 10 s was not cut off");
    // A connection that never sends anything is closed too.
    let mut silent = connect(server.addr);
    let (bytes, closed) = read_to_close(&mut silent);
    assert!(closed && bytes.is_empty());
    assert!(
        server
            .state
            .metrics
            .connections_header_timeout
            .load(Relaxed)
            >= 1
    );
    healthy(&server);
}

#[test]
fn idle_keep_alive_connections_are_closed_after_the_idle_timeout() {
    let server = Running::start(|c| {
        c.limits.idle_timeout_s = 1.0;
        c.limits.header_timeout_s = 30.0;
    });
    let mut s = connect(server.addr);
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
        .unwrap();
    assert_eq!(read_responses(&mut s, 1)[0].status, 200);
    let (bytes, closed) = read_to_close(&mut s);
    assert!(closed && bytes.is_empty());
    assert_eq!(
        server.state.metrics.connections_idle_closed.load(Relaxed),
        1
    );
}

#[test]
fn connections_past_the_limit_get_503_and_others_keep_working() {
    let server = Running::start(|c| c.limits.max_connections = 2);
    let mut held = Vec::new();
    for _ in 0..2 {
        let mut s = connect(server.addr);
        s.write_all(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
            .unwrap();
        assert_eq!(read_responses(&mut s, 1)[0].status, 200);
        held.push(s);
    }
    let mut third = connect(server.addr);
    let (bytes, closed) = read_to_close(&mut third);
    assert!(closed);
    let (r, _) = parse_response(&bytes, false).unwrap().unwrap();
    assert_eq!(r.status, 503);
    // The held connections still work; closing one makes room.
    held[0]
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
        .unwrap();
    assert_eq!(read_responses(&mut held[0], 1)[0].status, 200);
    drop(held.pop());
    let mut ok = None;
    for _ in 0..100 {
        std::thread::sleep(Duration::from_millis(20));
        let r = get(server.addr, "/healthz");
        if r.status == 200 {
            ok = Some(r);
            break;
        }
    }
    assert!(ok.is_some(), "a freed connection slot was never reused");
}

#[test]
fn a_client_that_never_reads_cannot_make_the_server_buffer_without_bound() {
    let server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let mut flood = connect(server.addr);
    flood
        .set_write_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    let request = format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n").repeat(1000);
    let mut written = 0usize;
    // Each request asks for ~1 KiB; the server stops reading once the responses it owes
    // fill the socket buffers, so writing soon blocks.
    while written < 512 << 20 {
        match flood.write(request.as_bytes()) {
            Ok(n) => written += n,
            Err(_) => break,
        }
    }
    assert!(
        written < 64 << 20,
        "wrote {written} bytes of requests without backpressure"
    );
    eprintln!(
        "flooding client blocked after {} KiB of requests",
        written >> 10
    );
    healthy(&server);
}

#[test]
fn graceful_shutdown_finishes_answers_in_flight_and_stops_accepting() {
    let mut server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let mut s = connect(server.addr);
    let batch = format!("GET {prefix}/32/32 HTTP/1.1\r\nHost: t\r\n\r\n").repeat(200);
    s.write_all(batch.as_bytes()).unwrap();
    let mut first = [0u8; 1];
    s.read_exact(&mut first).unwrap();
    let addr = server.addr;
    server.begin_stop();
    // What arrives is whole responses (at least the first), then the connection closes.
    let (mut rest, closed) = read_to_close(&mut s);
    assert!(closed);
    rest.insert(0, first[0]);
    let mut at = 0;
    while at < rest.len() {
        let (r, used) = parse_response(&rest[at..], false)
            .unwrap()
            .expect("a truncated response");
        assert_eq!(r.body, blob_for([32, 32, 0]));
        at += used;
    }
    server.stop();
    assert!(
        std::net::TcpStream::connect(addr).is_err(),
        "still accepting after shutdown"
    );
}

#[test]
fn http2_prior_knowledge_serves_the_same_bytes_on_concurrent_streams() {
    let server = Running::start(|_| {});
    let prefix = planar_prefix(&server.state);
    let addr = server.addr;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async move {
        use http_body_util::{BodyExt, Empty};
        let stream = tokio::net::TcpStream::connect(addr).await.unwrap();
        let (sender, conn) = hyper::client::conn::http2::handshake::<_, _, Empty<bytes::Bytes>>(
            hyper_util::rt::TokioExecutor::new(),
            hyper_util::rt::TokioIo::new(stream),
        )
        .await
        .unwrap();
        tokio::spawn(conn);
        let centres: Vec<[i64; 3]> = planar_centres(PLANAR_M, PLANAR_LEVELS)
            .into_keys()
            .filter(|c| [c[0], c[1]] != [PLANAR_LEAF.x, PLANAR_LEAF.y])
            .take(50)
            .collect();
        let mut tasks = Vec::new();
        for c in centres {
            let mut sender = sender.clone();
            let uri = format!("http://t{prefix}/{}/{}", c[0], c[1]);
            tasks.push(tokio::spawn(async move {
                let request = hyper::Request::get(uri).body(Empty::new()).unwrap();
                let response = sender.send_request(request).await.unwrap();
                assert_eq!(response.status(), 200);
                assert_eq!(response.version(), hyper::Version::HTTP_2);
                assert!(response.headers().contains_key("etag"));
                let body = response.into_body().collect().await.unwrap().to_bytes();
                assert_eq!(body.as_ref(), blob_for(c).as_slice());
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
    });
    assert_eq!(server.state.metrics.connections_h2.load(Relaxed), 1);
    healthy(&server);
}

#[test]
fn a_bare_tcp_reset_mid_request_does_not_disturb_the_server() {
    let server = Running::start(|_| {});
    for _ in 0..50 {
        let mut s = connect(server.addr);
        let _ = s.write_all(b"GET /repos/plain/v/");
        drop(s);
    }
    let mut s = connect(server.addr);
    s.write_all(b"GET /repos HTTP/1.1\r\nHost: t\r\n\r\n")
        .unwrap();
    let mut one = [0u8; 1];
    s.read_exact(&mut one).unwrap();
    healthy(&server);
}
