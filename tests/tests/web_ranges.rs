//! The browser's range reading (`quincunx-web`'s `pack_*` calls, what the page's
//! `?pack=<URL>` glue runs as WebAssembly) driven natively through the byte API, against
//! nginx serving a repository file: the client converges to the cut a local refinement
//! gives, crack-free in every frame; answers a page can see from a misconfigured or
//! changed host are clear errors; hostile input is an error, never a panic.
//!
//! Prints `SKIP web_ranges...: ...` and passes when nginx is not installed (the hostile
//! input test always runs).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

use bytes::Bytes;
use glam::DVec3;
use quincunx_client::fetch::Key;
use quincunx_client::refine::SystemClock;
use quincunx_client::view::View;
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_web::api::Module;
use quincunx_web::client::Client;
use quincunx_web::decode::AnswerDecoder;
use quincunx_web::open::Open;
use quincunx_web::wire::{Reader, Writer};

use common::nginx::{Nginx, find_nginx, free_port};
use common::put_file;
use common::stream::{cut_of, reference_cut};

const FIRST_READ: u64 = quincunx_web::pack::PackReader::FIRST_READ;

/// An answer as the page passes it: `u32 status, bytes content_range, bytes etag, body`.
fn answer_bytes(w: &mut Writer, r: &common::Response) {
    w.u32(u32::from(r.status));
    w.bytes(r.header("content-range").unwrap_or("").as_bytes());
    w.bytes(r.header("etag").unwrap_or("").as_bytes());
    w.out.extend_from_slice(&r.body);
}

fn range(addr: SocketAddr, path: &str, from: u64, len: u64) -> common::Response {
    let header = format!("Range: bytes={from}-{}", from + len - 1);
    common::get(addr, path, &[&header])
}

/// The page's opening: the first read, the rest if needed, then `pack_new`. Returns the
/// reader's handle and the metadata, or the error text.
fn open(m: &mut Module, addr: SocketAddr, path: &str) -> Result<(u32, serde_json::Value), String> {
    let url = format!("http://{addr}{path}");
    let first = range(addr, path, 0, FIRST_READ);
    let mut w = Writer::default();
    w.bytes(url.as_bytes());
    answer_bytes(&mut w, &first);
    let out = m.pack_first(&w.out)?;
    let mut r = Reader::new(&out);
    let (file_len, open_len) = (r.f64().unwrap(), r.f64().unwrap());
    let mut w = Writer::default();
    w.bytes(url.as_bytes());
    w.f64(file_len);
    w.f64(open_len);
    w.bytes(first.header("etag").unwrap_or("").as_bytes());
    w.bytes(&first.body);
    let have = first.body.len() as u64;
    if open_len as u64 > have {
        w.u8(1);
        answer_bytes(&mut w, &range(addr, path, have, open_len as u64 - have));
    } else {
        w.u8(0);
    }
    let (h, json) = m.pack_new(&w.out)?;
    let json: serde_json::Value = serde_json::from_slice(&json).unwrap();
    assert_eq!(json["fileLen"].as_f64(), Some(file_len));
    Ok((h, json["meta"].clone()))
}

/// A step's parts: leaves, `(key, kind, payload)` answers, `(tag, offset, len)` requests.
type Parsed = (
    Vec<[i64; 3]>,
    Vec<([i64; 3], u8, Vec<u8>)>,
    Vec<(f64, u64, u64)>,
);

fn parse_step(out: &[u8]) -> Parsed {
    let mut r = Reader::new(out);
    let leaves = (0..r.count(24).unwrap())
        .map(|_| r.key().unwrap())
        .collect();
    let n = r.count(29).unwrap();
    let mut blobs = Vec::new();
    for _ in 0..n {
        let key = r.key().unwrap();
        let kind = r.u8().unwrap();
        blobs.push((key, kind, r.bytes().unwrap().to_vec()));
    }
    let requests = (0..r.count(24).unwrap())
        .map(|_| {
            let tag = r.f64().unwrap();
            (tag, r.f64().unwrap() as u64, r.f64().unwrap() as u64)
        })
        .collect();
    r.f64().unwrap();
    r.finish().unwrap();
    (leaves, blobs, requests)
}

/// One key's answer from a step handed to the client as the page would (kind 0: `u32
/// status, body`), its body decoded if the client says so.
/// Hands an answer to the client; a body to decode goes to `decoding` (the page's
/// workers decode it while frames go on).
fn hand_on(
    client: &mut Client<PlanarRefiner>,
    decoding: &mut Vec<(Key, Bytes, bool)>,
    key: Key,
    payload: &[u8],
) {
    let mut r = Reader::new(payload);
    let status = r.u32().unwrap() as u16;
    let body = Bytes::copy_from_slice(&payload[4..]);
    let decode = client
        .answer(0, key, Ok((status, body.clone())), Duration::ZERO)
        .unwrap();
    if let Some(packaged) = decode {
        decoding.push((key, body, packaged));
    }
}

#[test]
fn the_browsers_client_streams_a_repository_file_from_nginx_to_the_local_cut() {
    let Some(nginx) = find_nginx("web_ranges") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let built = root.join("korea");
    common::build_bundled_korea(&built);
    let www = root.join("www");
    put_file(&built, &www, "korea.pack");
    let server = static_nginx(&nginx, &root.join("nginx"), &www);
    let addr = server.addr;

    let mut m = Module::default();
    let (pack, meta) = open(&mut m, addr, "/korea.pack").unwrap();
    // Default configuration: the planner asks for packages, read as one range each.
    let open_json = serde_json::to_vec(&serde_json::json!({
        "elevation": {"name": "korea.pack", "meta": meta},
    }))
    .unwrap();
    let opened: Open = serde_json::from_slice(&open_json).unwrap();
    let mut client = Client::<PlanarRefiner>::new(&opened, Duration::ZERO).unwrap();
    let decoder = AnswerDecoder::new(&opened).unwrap();
    let view = View {
        eye: DVec3::new(40_000.0, 30_000.0, 6_000.0),
        target: DVec3::new(50_000.0, 40_000.0, 0.0),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1280, 720],
        tolerance_px: 1.0,
    };
    let clock = SystemClock(Instant::now());
    let (mut requests, mut keys_planned) = (0u64, 0u64);
    let mut queue: VecDeque<(f64, u64, u64)> = VecDeque::new();
    let mut converged = false;
    let mut decoding: Vec<(Key, Bytes, bool)> = Vec::new();
    for frame in 0..2_000 {
        let f = client
            .frame(&view, Duration::ZERO, Duration::from_millis(8), &clock)
            .unwrap();
        let check = client.core().dag().check_cut();
        assert!(check.ok(), "frame {frame}: {check:?}");
        if f.refine.converged && f.wanted == 0 {
            converged = true;
            break;
        }
        // The page's glue: the planner's keys to the range reader (byte API), its
        // requests to `fetch`, every answer back through the reader to the client, its
        // bodies decoded a frame later (by the workers).
        let mut keys = Writer::default();
        let planned = client.plan(Duration::ZERO);
        keys.count(planned.len());
        for (layer, key, packaged) in planned {
            assert_eq!(layer, 0);
            assert!(
                !decoding.iter().any(|(k, _, _)| *k == key),
                "frame {frame}: {key:?} asked for again while its answer is decoded"
            );
            keys.u8(u8::from(packaged));
            keys.key(key);
            keys_planned += 1;
        }
        let mut answered = Vec::new();
        let mut steps = vec![m.pack_plan(pack, &keys.out).unwrap()];
        while let Some(step) = steps.pop() {
            let (leaves, blobs, reqs) = parse_step(&step);
            for key in leaves {
                hand_on(&mut client, &mut answered, key, &200u32.to_le_bytes());
            }
            for (key, kind, payload) in blobs {
                assert_eq!(kind, 0, "{key:?}: {}", String::from_utf8_lossy(&payload));
                hand_on(&mut client, &mut answered, key, &payload);
            }
            queue.extend(reqs);
            if let Some((tag, offset, len)) = queue.pop_front() {
                let a = range(addr, "/korea.pack", offset, len);
                requests += 1;
                let mut w = Writer::default();
                w.f64(tag);
                w.u8(0);
                answer_bytes(&mut w, &a);
                steps.push(m.pack_answered(pack, &w.out).unwrap());
            }
        }
        // The workers finish what was answered a frame ago.
        for (key, body, packaged) in std::mem::replace(&mut decoding, answered) {
            let details = decoder.decode(0, key, &body, packaged).unwrap();
            client.decoded(0, key, &details, Duration::ZERO).unwrap();
        }
    }
    assert!(converged, "no convergence");
    let stats = client.stats();
    assert_eq!(stats["errors"]["total"], 0, "{stats}");
    let reference = reference_cut::<PlanarRefiner>(&built, "korea", &view, client.core().world());
    let cut = cut_of(client.core().dag());
    assert!(cut.len() > 50, "{} halves", cut.len());
    assert!(
        cut == reference,
        "the streamed cut differs from the local one"
    );
    // The planner releases at most its window (16 keys) at a time; neighbours among
    // them share a request, and leaves need none.
    assert!(
        requests < keys_planned,
        "{requests} range requests for {keys_planned} keys"
    );
    println!(
        "web_ranges: korea from nginx: {keys_planned} keys in {requests} range requests, \
         {} halves, the local cut, crack-free in every frame",
        cut.len()
    );

    // What a page sees from a misconfigured or changed host: clear errors.
    let url = format!("http://{addr}/x.pack");
    let first = |status: u32, cr: &str, body: &[u8]| {
        let mut w = Writer::default();
        w.bytes(url.as_bytes());
        w.u32(status);
        w.bytes(cr.as_bytes());
        w.bytes(b"");
        w.out.extend_from_slice(body);
        Module::default().pack_first(&w.out).unwrap_err()
    };
    let whole = std::fs::read(www.join("korea.pack")).unwrap();
    assert!(first(200, "", &whole).contains("ignored the Range header"));
    assert!(first(404, "", b"").contains("status 404"));
    assert!(first(403, "", b"").contains("status 403"));
    assert!(
        first(206, "", &whole[..FIRST_READ as usize]).contains("Access-Control-Expose-Headers")
    );
    assert!(first(206, "bytes 0-9/10", b"0123456789").contains("x.pack"));
    let err = open(&mut m, addr, "/nothing.pack").unwrap_err();
    assert!(err.contains("status 404"), "{err}");
    // A 412 (the file changed) or another ETag: every key of the request fails as changed.
    let mut keys = Writer::default();
    let far: Vec<Key> = reference_keys(&built);
    keys.count(far.len());
    for k in &far {
        keys.u8(0);
        keys.key(*k);
    }
    for (status, etag) in [(412, ""), (206, "\"another\"")] {
        // Each failed request's keys are planned again, as the planner retries them.
        let (_, _, reqs) = parse_step(&m.pack_plan(pack, &keys.out).unwrap());
        let (tag, offset, len) = reqs[0];
        let a = range(addr, "/korea.pack", offset, len);
        let mut w = Writer::default();
        w.f64(tag);
        w.u8(0);
        w.u32(status);
        w.bytes(a.header("content-range").unwrap().as_bytes());
        w.bytes(etag.as_bytes());
        w.out.extend_from_slice(&a.body);
        let (_, blobs, _) = parse_step(&m.pack_answered(pack, &w.out).unwrap());
        assert!(!blobs.is_empty());
        for (_, kind, msg) in blobs {
            let msg = String::from_utf8_lossy(&msg);
            assert_eq!(kind, 3, "{msg}");
            assert!(msg.contains("changed since it was opened"), "{msg}");
        }
    }
    drop(server);
}

/// Some stored keys of `repo` (the deepest ones: blobs past the first read).
fn reference_keys(repo: &Path) -> Vec<Key> {
    let repo = quincunx_store::Repository::open(repo).unwrap();
    let space = quincunx_store::answer::IdSpace::of(repo.metadata()).unwrap();
    let quincunx_store::answer::IdSpace::Planar(d) = space else {
        panic!("planar")
    };
    let mut keys: Vec<Key> = repo
        .blobs()
        .map(|kv| {
            let (k, _) = kv.unwrap();
            let id = d.id_from_key(&k).unwrap();
            [id.x, id.y, 0]
        })
        .collect();
    keys.reverse();
    keys.truncate(20);
    keys
}

fn static_nginx(binary: &Path, dir: &Path, www: &Path) -> Nginx {
    let addr = free_port();
    let snippet = format!(
        "access_log {}/access.log;\nserver {{ listen {addr}; root {}; }}",
        dir.display(),
        www.display()
    );
    Nginx::run(binary, dir, addr, &snippet, "/korea.pack")
}

#[test]
fn hostile_input_to_the_range_calls_is_an_error_not_a_panic() {
    let mut m = Module::default();
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    for round in 0..5_000 {
        let len = (next() % 200) as usize;
        let mut input: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        if round % 2 == 0 && input.len() > 8 {
            // A short, plausible length prefix.
            input[..4].copy_from_slice(&((next() % 16) as u32).to_le_bytes());
        }
        assert!(
            m.pack_first(&input).is_err(),
            "random bytes are no repository file"
        );
        let _ = m.pack_new(&input);
        let h = (next() % 3) as u32;
        let _ = m.pack_plan(h, &input);
        let _ = m.pack_answered(h, &input);
        let _ = m.client_answer(h, &input, 0.0);
    }
}
