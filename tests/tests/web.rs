//! The browser's client (`quincunx-web`, what the page runs as WebAssembly) driven
//! natively over real sockets against `quincunx serve`: it converges to the cut a local
//! refinement with every blob at hand gives, crack-free in every frame; and hostile calls
//! on its byte-buffer API are errors, never panics.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::refine::SystemClock;
use quincunx_client::view::View;
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_web::api::Module;
use quincunx_web::client::Client;
use quincunx_web::decode::AnswerDecoder;
use quincunx_web::open::Open;

use common::stream::{Served, cut_of, reference_cut};

const REPO: &str = "korea";

/// The korea crop, built and served.
fn served(dir: &Path) -> (Served, std::path::PathBuf, Open) {
    let built = dir.join("korea");
    common::build_bundled_korea(&built);
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let meta = common::get(server.addr, &format!("/repos/{REPO}/metadata.json"), &[]);
    assert_eq!(meta.status, 200);
    let open: Open = serde_json::from_value(serde_json::json!({
        "elevation": {"name": REPO, "meta": serde_json::from_slice::<serde_json::Value>(&meta.body).unwrap()},
    }))
    .unwrap();
    (server, built, open)
}

#[test]
fn the_browsers_client_converges_to_the_local_cut_crack_free_over_http() {
    let dir = tempfile::tempdir().unwrap();
    let (server, built, open) = served(dir.path());
    let version = &open.elevation.meta.content_hash[..16];
    let start = Instant::now();
    let mut client = Client::<PlanarRefiner>::new(&open, Duration::ZERO).unwrap();
    let decoder = AnswerDecoder::new(&open).unwrap();
    let clock = SystemClock(start);
    let view = View {
        eye: DVec3::new(40_000.0, 30_000.0, 6_000.0),
        target: DVec3::new(50_000.0, 40_000.0, 0.0),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1280, 720],
        tolerance_px: 1.0,
    };
    let (mut requests, mut packages) = (0, 0);
    for frame in 0.. {
        assert!(frame < 2_000, "no convergence");
        let f = client
            .frame(&view, start.elapsed(), Duration::from_millis(8), &clock)
            .unwrap();
        let check = client.core().dag().check_cut();
        assert!(check.ok(), "frame {frame}: {check:?}");
        if f.refine.converged && f.wanted == 0 {
            break;
        }
        // The page's glue: send what the planner picks, hand back the answers.
        for (layer, key, packaged) in client.plan(start.elapsed()) {
            let kind = if packaged { "p" } else { "d" };
            let path = format!("/repos/{REPO}/v/{version}/{kind}/{}/{}", key[0], key[1]);
            let r = common::get(server.addr, &path, &[]);
            requests += 1;
            packages += usize::from(packaged);
            let body = bytes::Bytes::from(r.body);
            let now = start.elapsed();
            let decode = client
                .answer(layer, key, Ok((r.status, body.clone())), now)
                .unwrap();
            if let Some(packaged) = decode {
                match decoder.decode(layer, key, &body, packaged) {
                    Ok(details) => client.decoded(layer, key, &details, now).unwrap(),
                    Err(e) => panic!("{path}: {e}"),
                }
            }
        }
    }
    let stats = client.stats();
    assert_eq!(stats["errors"]["total"], 0, "{stats}");
    assert!(
        requests > 10 && packages > 0,
        "{requests} requests, {packages} packages"
    );
    let reference = reference_cut::<PlanarRefiner>(&built, REPO, &view, client.core().world());
    let cut = cut_of(client.core().dag());
    assert!(cut.len() > 50, "{} halves", cut.len());
    assert!(
        cut == reference,
        "the streamed cut differs from the local one"
    );
    server.kill();
}

#[test]
fn hostile_calls_on_the_byte_api_are_errors_not_panics() {
    let dir = tempfile::tempdir().unwrap();
    let (server, _built, open) = served(dir.path());
    let json = serde_json::json!({"elevation": {"name": REPO, "meta": serde_json::to_value(&open.elevation.meta).unwrap()}});
    let json = serde_json::to_vec(&json).unwrap();
    let mut m = Module::default();
    let client = m.client_new(&json, 0.0).unwrap();
    let decoder = m.decoder_new(&json).unwrap();
    // Malformed openings.
    for bad in [
        &b""[..],
        b"{",
        b"{\"elevation\": 7}",
        b"[]",
        &json[..json.len() / 2],
    ] {
        assert!(m.client_new(bad, 0.0).is_err());
        assert!(m.decoder_new(bad).is_err());
    }
    assert!(m.client_new(&json, f64::NAN).is_err());
    // Every call with truncated, random and out-of-range input.
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    struct Clock;
    impl quincunx_client::refine::Clock for Clock {
        fn now(&self) -> Duration {
            Duration::ZERO
        }
    }
    for round in 0..3_000 {
        let len = (next() % 120) as usize;
        let mut input: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        if round % 3 == 0 && input.len() > 2 {
            // Mostly valid headers: layer 0/1, small keys.
            input[0] %= 3;
            input[1] %= 4;
        }
        let handle = if round % 7 == 0 { 12345 } else { client };
        let now = (next() % 100_000) as f64;
        let _ = m.client_answer(handle, &input, now);
        let _ = m.client_decoded(handle, &input, now);
        let _ = m.client_decode_failed(handle, &input, now);
        let _ = m.client_frame(handle, &input, now, 1.0, &Clock);
        let _ = m.decoder_decode(if round % 5 == 0 { client } else { decoder }, &input);
        let _ = m.reconstruct(&input);
    }
    for t in [f64::NAN, f64::INFINITY, -1.0] {
        let _ = m.client_plan(client, t);
        let _ = m.client_wake_in(client, t);
    }
    assert!(m.client_stats(client).is_ok());
    assert!(m.client_changes(client).is_ok());
    assert!(m.client_check(client).is_ok());
    assert!(
        m.client_stats(decoder).is_err(),
        "a decoder is not a client"
    );
    m.free(client);
    assert!(m.client_stats(client).is_err(), "freed");
    server.kill();
}
