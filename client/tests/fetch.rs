//! The fetch layer against a real quincunx server over loopback sockets.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::time::{Duration, Instant};

use common::*;
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::fetch::{Fetched, Fetcher, Key, Transport};

#[test]
fn every_transport_fetches_the_same_exact_bytes() {
    let server = TestServer::start();
    for (repo, wants) in [("plain", planar_wants()), ("globe", sphere_wants())] {
        for transport in Transport::ALL {
            let fetcher = Fetcher::spawn(config(&server.url(), repo, transport), raw()).unwrap();
            let (answers, failures) = drive(&fetcher, &wants, Duration::from_secs(30), false);
            assert!(failures.is_empty(), "{repo} {transport:?}: {failures:?}");
            assert_exact(&answers, &wants);
            let stats = fetcher.stats();
            assert_eq!(stats.requests, wants.len() as u64, "{repo} {transport:?}");
            assert_eq!(stats.errors.total(), 0);
            let bytes: usize = wants
                .iter()
                .filter(|(k, _)| *k != PLANAR_LEAF)
                .map(|(k, _)| blob_for(*k).len())
                .sum();
            assert_eq!(stats.bytes_fetched, bytes as u64);
        }
    }
}

#[test]
fn leaves_are_delivered_as_leaf_and_never_requested_twice() {
    let server = TestServer::start();
    let fetcher =
        Fetcher::spawn(config(&server.url(), "plain", Transport::Pipelined), raw()).unwrap();
    let before = server.blob_requests();
    let wants = [(PLANAR_LEAF, 1.0)];
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(10), false);
    assert!(matches!(answers[&PLANAR_LEAF], Fetched::Leaf));
    assert!(fetcher.is_leaf(PLANAR_LEAF));
    for _ in 0..5 {
        fetcher.submit(wants.to_vec());
        // The leaf set answers at once, on the frame loop's thread.
        let got = fetcher.poll();
        assert!(matches!(got.as_slice(), [(k, Fetched::Leaf)] if *k == PLANAR_LEAF));
    }
    std::thread::sleep(Duration::from_millis(100));
    assert!(fetcher.poll().is_empty());
    assert_eq!(fetcher.stats().requests, 1);
    assert_eq!(fetcher.stats().leaves, 1);
    assert_eq!(fetcher.stats().cache_hits, 5);
    assert_eq!(server.blob_requests() - before, 1.0);
}

#[test]
fn cached_values_are_answered_without_a_request() {
    let server = TestServer::start();
    let fetcher =
        Fetcher::spawn(config(&server.url(), "plain", Transport::Pipelined), raw()).unwrap();
    let wants = planar_wants();
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(10), false);
    assert_exact(&answers, &wants);
    let requests = fetcher.stats().requests;
    fetcher.submit(wants.clone());
    let again: std::collections::HashMap<Key, Fetched<_>> = fetcher.poll().into_iter().collect();
    assert_exact(&again, &wants);
    assert_eq!(fetcher.stats().requests, requests);
    assert!(fetcher.cached(wants[0].0).is_some());
}

/// One connection, one request at a time, over a link slow enough that the queue builds.
fn serial_fetcher(server: &TestServer, link: &LinkProxy) -> Fetcher<bytes::Bytes> {
    let _ = server;
    let mut c = config(
        &format!("http://{}", link.local_addr()),
        "plain",
        Transport::Pipelined,
    );
    c.connections = 1;
    c.pipeline_depth = 1;
    c.max_in_flight = 1;
    Fetcher::spawn(c, raw()).unwrap()
}

#[test]
fn higher_priority_keys_are_issued_first() {
    let server = TestServer::start();
    let link = LinkProxy::start(server.addr, 100_000.0, Duration::from_millis(10)).unwrap();
    let fetcher = serial_fetcher(&server, &link);
    // Priorities unrelated to key order.
    let wants: Vec<(Key, f32)> = planar_wants()
        .into_iter()
        .filter(|(k, _)| *k != PLANAR_LEAF)
        .take(20)
        .enumerate()
        .map(|(i, (k, _))| (k, ((i * 7) % 20) as f32))
        .collect();
    fetcher.submit(wants.clone());
    let mut order = Vec::new();
    let start = Instant::now();
    while order.len() < wants.len() && start.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(5));
        order.extend(fetcher.poll().into_iter().map(|(k, _)| k));
        // Re-submitting the same frame keeps the queue (minus what arrived).
        let open: Vec<_> = wants
            .iter()
            .filter(|(k, _)| !order.contains(k))
            .copied()
            .collect();
        fetcher.submit(open);
    }
    let mut by_priority = wants.clone();
    by_priority.sort_by(|a, b| b.1.total_cmp(&a.1));
    let expected: Vec<Key> = by_priority.iter().map(|(k, _)| *k).collect();
    assert_eq!(order, expected);
}

#[test]
fn wants_dropped_from_the_next_submit_are_not_fetched() {
    let server = TestServer::start();
    let link = LinkProxy::start(server.addr, 100_000.0, Duration::from_millis(100)).unwrap();
    let fetcher = serial_fetcher(&server, &link);
    let wants: Vec<(Key, f32)> = planar_wants()
        .into_iter()
        .filter(|(k, _)| *k != PLANAR_LEAF)
        .take(10)
        .collect();
    let first = (wants[0].0, 100.0);
    let mut frame = wants.clone();
    frame[0] = first;
    fetcher.submit(frame);
    // Next frame: only the first key is still wanted.
    fetcher.submit(vec![first]);
    let start = Instant::now();
    let mut got = Vec::new();
    while start.elapsed() < Duration::from_secs(1) {
        std::thread::sleep(Duration::from_millis(10));
        got.extend(fetcher.poll().into_iter().map(|(k, _)| k));
        fetcher.submit(if got.is_empty() { vec![first] } else { vec![] });
    }
    assert_eq!(got, vec![first.0]);
    assert_eq!(fetcher.stats().requests, 1);
}

#[test]
fn a_key_resubmitted_before_its_answer_is_polled_is_reported_once() {
    // The race the frame loop runs into: an answer arrives between one frame's poll and
    // the next frame's submit, which still wants the key and so hits the cache.
    let server = TestServer::start();
    let link = LinkProxy::start(server.addr, 100_000.0, Duration::from_millis(1)).unwrap();
    let fetcher = serial_fetcher(&server, &link);
    let key = planar_wants()
        .into_iter()
        .map(|(k, _)| k)
        .find(|k| *k != PLANAR_LEAF)
        .unwrap();
    fetcher.submit(vec![(key, 1.0)]);
    let start = Instant::now();
    while fetcher.cached(key).is_none() && start.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(fetcher.cached(key).is_some(), "the blob never arrived");
    fetcher.submit(vec![(key, 1.0)]);
    let keys: Vec<Key> = fetcher.poll().into_iter().map(|(k, _)| k).collect();
    assert_eq!(keys, vec![key]);
    assert_eq!(fetcher.stats().requests, 1);
}

#[test]
fn prefetch_is_issued_only_after_the_wants_and_lands_in_the_cache() {
    let server = TestServer::start();
    let link = LinkProxy::start(server.addr, 100_000.0, Duration::from_millis(10)).unwrap();
    let fetcher = serial_fetcher(&server, &link);
    let keys: Vec<Key> = planar_wants()
        .into_iter()
        .map(|(k, _)| k)
        .filter(|k| *k != PLANAR_LEAF)
        .take(8)
        .collect();
    let wants: Vec<(Key, f32)> = keys[..4].iter().map(|k| (*k, 1.0)).collect();
    // Prefetch priorities are higher, yet they come after every want.
    let prefetch: Vec<(Key, f32)> = keys[4..].iter().map(|k| (*k, 50.0)).collect();
    let start = Instant::now();
    let mut got = Vec::new();
    while start.elapsed() < Duration::from_secs(20) {
        let open: Vec<_> = wants
            .iter()
            .filter(|(k, _)| !got.contains(k))
            .copied()
            .collect();
        fetcher.submit_with_prefetch(open, prefetch.clone());
        std::thread::sleep(Duration::from_millis(5));
        got.extend(fetcher.poll().into_iter().map(|(k, _)| k));
        if keys[4..].iter().all(|k| fetcher.cached(*k).is_some()) {
            break;
        }
    }
    assert_eq!(got, keys[..4].to_vec(), "only wants are reported");
    for k in &keys[4..] {
        assert_eq!(fetcher.cached(*k).unwrap().as_ref(), &blob_for(*k)[..]);
    }
    assert_eq!(fetcher.stats().requests, 8);
}

#[test]
fn h2_uses_one_connection_and_plain_at_most_its_connections() {
    let server = TestServer::start();
    let wants = planar_wants();
    for (transport, connections, most) in [(Transport::H2, 4, 1.0), (Transport::Plain, 3, 3.0)] {
        let mut c = config(&server.url(), "plain", transport);
        c.connections = connections;
        let accepted = server.metric("quincunx_connections_accepted_total");
        let fetcher = Fetcher::spawn(c, raw()).unwrap();
        let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(20), false);
        assert_exact(&answers, &wants);
        // The metrics request itself is one more connection.
        let opened = server.metric("quincunx_connections_accepted_total") - accepted - 1.0;
        assert!(
            opened >= 1.0 && opened <= most,
            "{transport:?}: {opened} connections"
        );
    }
}

#[test]
fn a_bandwidth_cap_slows_fetching_down() {
    let server = TestServer::start();
    let wants = planar_wants();
    let bytes: usize = wants.iter().map(|(k, _)| blob_for(*k).len()).sum();
    let cap_bit_s = 100_000.0;
    let mut c = config(&server.url(), "plain", Transport::Pipelined);
    c.bandwidth_cap_bit_s = Some(cap_bit_s);
    let fetcher = Fetcher::spawn(c, raw()).unwrap();
    let start = Instant::now();
    let (answers, _) = drive(&fetcher, &wants, Duration::from_secs(30), false);
    let took = start.elapsed().as_secs_f64();
    assert_exact(&answers, &wants);
    // The bucket starts with a 1500 B burst; the rest goes at the cap. Generous bound.
    let floor = (bytes as f64 - 1500.0) * 8.0 / cap_bit_s;
    assert!(
        took > 0.6 * floor,
        "{took:.2} s for {bytes} B at {cap_bit_s} bit/s"
    );
}
