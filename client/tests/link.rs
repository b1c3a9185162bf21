//! The emulated link delivers its configured rate and round trip.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use quincunx_client::fetch::link::LinkProxy;

/// A server that echoes everything back.
fn echo_server() -> std::net::SocketAddr {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    std::thread::spawn(move || {
        for s in l.incoming() {
            let Ok(mut s) = s else { return };
            std::thread::spawn(move || {
                let mut buf = [0u8; 65536];
                while let Ok(n) = s.read(&mut buf) {
                    if n == 0 || s.write_all(&buf[..n]).is_err() {
                        return;
                    }
                }
            });
        }
    });
    addr
}

/// A server that sends `bytes` bytes on each connection, then closes.
fn source_server(bytes: usize) -> std::net::SocketAddr {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    std::thread::spawn(move || {
        for s in l.incoming() {
            let Ok(mut s) = s else { return };
            std::thread::spawn(move || {
                let data = vec![7u8; bytes];
                let _ = s.write_all(&data);
            });
        }
    });
    addr
}

/// Reads to the end; the rate between the first and the last byte, bit/s, and the count.
fn receive_rate(s: &mut TcpStream) -> (f64, usize) {
    let mut buf = [0u8; 65536];
    let mut first: Option<(Instant, usize)> = None;
    let mut total = 0;
    let mut last = Instant::now();
    loop {
        let n = s.read(&mut buf).unwrap();
        if n == 0 {
            break;
        }
        last = Instant::now();
        if first.is_none() {
            first = Some((last, n));
        }
        total += n;
    }
    let (t0, n0) = first.unwrap();
    ((total - n0) as f64 * 8.0 / (last - t0).as_secs_f64(), total)
}

#[test]
fn a_bulk_transfer_runs_within_ten_percent_of_the_link_rate() {
    // Downstream: 300 kB at 2 Mbit/s takes 1.2 s.
    let bytes = 300_000;
    let link = LinkProxy::start(source_server(bytes), 2000.0, Duration::from_millis(40)).unwrap();
    let mut s = TcpStream::connect(link.local_addr()).unwrap();
    let (rate, total) = receive_rate(&mut s);
    assert_eq!(total, bytes);
    assert!((rate / 2e6 - 1.0).abs() < 0.1, "downstream {rate:.0} bit/s");
    assert_eq!(link.bytes_down(), bytes as u64);

    // Upstream: send through the link to an echo server and time the echo (which comes
    // back down the same rate, pipelined behind the upload).
    let link = LinkProxy::start(echo_server(), 2000.0, Duration::from_millis(40)).unwrap();
    let mut s = TcpStream::connect(link.local_addr()).unwrap();
    let mut writer = s.try_clone().unwrap();
    let sender = std::thread::spawn(move || {
        writer.write_all(&vec![1u8; bytes]).unwrap();
        writer.shutdown(std::net::Shutdown::Write).unwrap();
    });
    let (rate, total) = receive_rate(&mut s);
    sender.join().unwrap();
    assert_eq!(total, bytes);
    assert!((rate / 2e6 - 1.0).abs() < 0.1, "echo {rate:.0} bit/s");
    assert_eq!(link.bytes_up(), bytes as u64);
}

#[test]
fn a_ping_pong_takes_the_configured_round_trip() {
    let rtt = Duration::from_millis(100);
    let link = LinkProxy::start(echo_server(), 4000.0, rtt).unwrap();
    let mut s = TcpStream::connect(link.local_addr()).unwrap();
    s.set_nodelay(true).unwrap();
    let mut times = Vec::new();
    for i in 0..8u8 {
        let t = Instant::now();
        s.write_all(&[i]).unwrap();
        let mut b = [0u8; 1];
        s.read_exact(&mut b).unwrap();
        assert_eq!(b[0], i);
        times.push(t.elapsed());
    }
    times.sort();
    let median = times[times.len() / 2];
    assert!(
        median >= rtt && median < rtt + Duration::from_millis(30),
        "median round trip {median:?}"
    );
}
