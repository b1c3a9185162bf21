//! The browser's client (`quincunx-web`, what the page runs as WebAssembly: the sans-IO
//! client core with its request planner) driven natively: over real sockets against
//! `quincunx serve`, and by a harness with a hand-moved clock whose scripted answers come
//! out of order, late, twice, lost, failing or corrupt. Both converge to the cut a local
//! refinement with every blob at hand gives, crack-free in every frame; and hostile calls
//! on its byte-buffer API are errors, never panics.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::cell::Cell;
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;

use glam::DVec3;
use quincunx_client::fetch::{FetchError, Key};
use quincunx_client::refine::{Clock, SystemClock};
use quincunx_client::view::View;
use quincunx_codec::incremental::{PlanarRefiner, Refiner};
use quincunx_store::Repository;
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

/// An oblique 1280 x 720 view over the middle of the crop, 1 px.
fn oblique_view() -> View {
    View {
        eye: DVec3::new(40_000.0, 30_000.0, 6_000.0),
        target: DVec3::new(50_000.0, 40_000.0, 0.0),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1280, 720],
        tolerance_px: 1.0,
    }
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
    let view = oblique_view();
    // Frames until the cut is at full quality for `view`; (requests, packages) sent.
    let converge = |client: &mut Client<PlanarRefiner>, view: &View| {
        let (mut requests, mut packages) = (0, 0);
        for frame in 0.. {
            assert!(frame < 2_000, "no convergence");
            let f = client
                .frame(view, start.elapsed(), Duration::from_millis(8), &clock)
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
        (requests, packages)
    };
    let (requests, packages) = converge(&mut client, &view);
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
    let hits = |client: &mut Client<PlanarRefiner>| client.stats()["cacheHits"].as_u64().unwrap();
    let before = hits(&mut client);

    // High above: the cut coarsens. Back again: every diamond comes from the cache.
    let above = View {
        eye: DVec3::new(50_000.0, 40_000.0, 400_000.0),
        target: DVec3::new(50_000.0, 40_000.0, 0.0),
        up: DVec3::Y,
        ..view
    };
    converge(&mut client, &above);
    assert!(
        cut_of(client.core().dag()).len() < cut.len() / 4,
        "no coarsening"
    );
    let (again, _) = converge(&mut client, &view);
    assert_eq!(
        again, 0,
        "requests on the way back: the cache holds the cut"
    );
    assert!(cut_of(client.core().dag()) == reference);
    let back = hits(&mut client) - before;
    assert!(back > 50, "{back} cache hits on the way back");
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
        let _ = m.reconstruct(&input, (round % 3) as u32, &Clock);
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

/// A clock the harness moves.
struct Manual(Cell<Duration>);

impl Clock for Manual {
    fn now(&self) -> Duration {
        self.0.get()
    }
}

/// What happens to a request.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Fate {
    /// Answered.
    Good,
    /// Answered with a byte flipped (the blob's checksum fails).
    Corrupt,
    /// 503.
    Unavailable,
    /// Never answered: the transport reports a timeout.
    Lost,
    /// Answered, and answered again much later.
    Twice,
}

#[test]
fn the_sans_io_client_stays_crack_free_through_scripted_faults() {
    let dir = tempfile::tempdir().unwrap();
    let built = dir.path().join("korea");
    common::build_bundled_korea(&built);
    let repo = Repository::open(&built).unwrap();
    let meta = serde_json::to_value(repo.metadata()).unwrap();
    // Bare blobs: the answers come from the repository file, not a server's packages.
    let open: Open = serde_json::from_value(serde_json::json!({
        "elevation": {"name": REPO, "meta": meta},
        "config": {"packageFactor": 0},
    }))
    .unwrap();
    let mut client = Client::<PlanarRefiner>::new(&open, Duration::ZERO).unwrap();
    let decoder = AnswerDecoder::new(&open).unwrap();
    let refiner = Arc::clone(client.core().refiner());
    let view = oblique_view();
    let clock = Manual(Cell::new(Duration::ZERO));
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut rng = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    // (frame due, key, fate), and attempts per key.
    let mut flights: Vec<(u64, Key, Fate)> = Vec::new();
    let mut attempts: HashMap<Key, u32> = HashMap::new();
    let mut fates: HashMap<Fate, usize> = HashMap::new();
    for frame in 0..5_000u64 {
        let now = Duration::from_millis(16 * frame);
        clock.0.set(now);
        // The answers due, in a scrambled order.
        let mut due: Vec<(u64, Key, Fate)> = Vec::new();
        flights.retain(|f| {
            let keep = f.0 > frame;
            if !keep {
                due.push(*f);
            }
            keep
        });
        for k in (1..due.len()).rev() {
            due.swap(k, (rng() % (k as u64 + 1)) as usize);
        }
        for (_, key, fate) in due {
            let info = refiner.info(PlanarRefiner::id_of(key)).unwrap();
            let body = repo.get(&info.key).unwrap().unwrap_or_default().to_vec();
            let result = match fate {
                Fate::Lost => Err(FetchError::Timeout(Duration::from_millis(500))),
                Fate::Unavailable => Ok((503, Bytes::from_static(b"busy"))),
                Fate::Corrupt => {
                    let mut b = body.clone();
                    if let Some(x) = b.get_mut(body.len() / 2) {
                        *x ^= 0x5a;
                    }
                    Ok((200, Bytes::from(b)))
                }
                Fate::Good | Fate::Twice => Ok((200, Bytes::from(body.clone()))),
            };
            let sent = match &result {
                Ok((_, b)) => b.clone(),
                Err(_) => Bytes::new(),
            };
            if let Some(packaged) = client.answer(0, key, result, now).unwrap() {
                match decoder.decode(0, key, &sent, packaged) {
                    Ok(details) => client.decoded(0, key, &details, now).unwrap(),
                    Err(e) => client.decode_failed(0, key, e, now).unwrap(),
                }
            }
            if fate == Fate::Twice {
                // The same answer again, long after it was settled: stale.
                flights.push((frame + 40, key, Fate::Good));
            }
        }
        let f = client
            .frame(&view, now, Duration::from_millis(8), &clock)
            .unwrap();
        let check = client.core().dag().check_cut();
        assert!(check.ok(), "frame {frame}: {check:?}");
        if f.refine.converged && f.wanted == 0 {
            let reference =
                reference_cut::<PlanarRefiner>(&built, REPO, &view, client.core().world());
            assert!(cut_of(client.core().dag()) == reference, "the cut differs");
            for fate in [Fate::Corrupt, Fate::Unavailable, Fate::Lost, Fate::Twice] {
                assert!(
                    fates.get(&fate).copied().unwrap_or(0) > 0,
                    "no {fate:?}: {fates:?}"
                );
            }
            let e = &client.stats()["errors"];
            assert!(
                e["decode"].as_u64() > Some(0)
                    && e["serverStatus"].as_u64() > Some(0)
                    && e["timeout"].as_u64() > Some(0),
                "{e}"
            );
            return;
        }
        // Faults on first attempts only, so that every key arrives in the end.
        for (_, key, _) in client.plan(now) {
            let attempt = attempts.entry(key).or_insert(0);
            *attempt += 1;
            let fate = if *attempt > 1 {
                Fate::Good
            } else {
                match rng() % 20 {
                    0 | 1 => Fate::Corrupt,
                    2 => Fate::Unavailable,
                    3 | 4 => Fate::Lost,
                    5 => Fate::Twice,
                    _ => Fate::Good,
                }
            };
            *fates.entry(fate).or_default() += 1;
            let delay = if fate == Fate::Lost {
                30
            } else {
                1 + rng() % 6
            };
            flights.push((frame + delay, key, fate));
        }
    }
    panic!("no convergence through the faults: {fates:?}");
}
