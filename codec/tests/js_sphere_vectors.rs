//! Vectors for the JavaScript port of the planet side (`web-demo/js/sphere.mjs`, tested by
//! `web-demo/test/sphere.test.mjs`): ids, keys, hierarchy and positions of the sphere
//! domain, the slots and masks the refiner derives from ids, and small planets (dense,
//! sparse, three channels) with the cube rasters the whole-planet decoder gives.
//!
//! The files live in `web-demo/test/golden/sphere-*.json`. `QUINCUNX_BLESS=1` writes them;
//! otherwise the test checks that the committed files are what the Rust code says today
//! (so a change of the Rust side that the port must follow fails here first).
//!
//! To keep the files small, ids and slots are samples (every id kind, cube edges and
//! corners, each face), and bulky values are encoded:
//! - large integer arrays as the SHA-256 (hex) of their canonical bytes: little-endian i64
//!   coordinates for positions, little-endian u32 for raster indices, one byte (0 or 1) per
//!   point for validity, little-endian i32 for decoded rasters;
//! - byte strings (blobs, entropy models, coverages) in base64 (standard, padded);
//! - bit masks in hex, four bits a digit, first bit highest, the last digit padded with 0.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::{BTreeMap, BTreeSet};

use quincunx_codec::coverage::Coverage;
use quincunx_codec::diamond::sphere::{cube_to_unit_sphere, unit_sphere_to_cube};
use quincunx_codec::diamond::{SphereDomain, SphereId};
use quincunx_codec::encode::{self, EncodeOptions, Encoded, FromEncoded, RateMode};
use quincunx_codec::incremental::{Refiner, SphereRefiner};
use quincunx_codec::sphere_raster::{SphereFrame, SphereGeometry};
use serde_json::{Value, json};

use common::vectors::{base64, bless_or_check, hex, sha256};

#[test]
fn sha256_known_answers() {
    assert_eq!(
        sha256(b""),
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    );
    assert_eq!(
        sha256(b"abc"),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
    assert_eq!(
        sha256(b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
        "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1"
    );
    assert_eq!(
        sha256(&[b'a'; 1000]),
        "41edece42d63e8d9bf515a9ba6932e1c20cbc9f5a5d134645adb5db1b9737ea3"
    );
}

#[test]
fn base64_known_answers() {
    for (bytes, text) in [
        (&b""[..], ""),
        (b"f", "Zg=="),
        (b"fo", "Zm8="),
        (b"foo", "Zm9v"),
        (b"foob", "Zm9vYg=="),
        (b"fooba", "Zm9vYmE="),
        (b"foobar", "Zm9vYmFy"),
        (&[0xfb, 0xff, 0xbf], "+/+/"),
    ] {
        assert_eq!(base64(bytes), text);
    }
}

/// Bits in hex: four a digit, first bit highest, the last digit padded with zero bits.
fn bits_hex(bits: &[bool]) -> String {
    bits.chunks(4)
        .map(|c| {
            let v = (0..4).fold(0u32, |v, k| (v << 1) | u32::from(c.get(k) == Some(&true)));
            char::from_digit(v, 16).unwrap()
        })
        .collect()
}

fn ids(v: &[SphereId]) -> Value {
    Value::from(v.iter().map(|id| json!(id.c)).collect::<Vec<_>>())
}

/// Every `stride`-th item, and the first of every kind the stride misses, in order.
fn sample<T: Copy, K: Ord>(all: &[T], stride: usize, kind: impl Fn(&T) -> K) -> Vec<T> {
    let mut seen = BTreeSet::new();
    all.iter()
        .enumerate()
        .filter(|(k, x)| seen.insert(kind(x)) | k.is_multiple_of(stride))
        .map(|(_, x)| *x)
        .collect()
}

/// Every id of m = 1; every `STRIDE_M2`-th id of m = 2 (and the first of each kind).
const STRIDE_M2: usize = 16;
/// Every `FRAME_STRIDE`-th coded diamond of the 32/8 frame (and the first of each kind).
const FRAME_STRIDE: usize = 5;
/// Every `WALK_STRIDE`-th diamond of the walks of larger frames (and the first of each kind).
const WALK_STRIDE: usize = 3;
/// Planets `(face side, N)`: dense lossless, dense RMS, sparse max-error, three channels.
const P0: (usize, usize) = (16, 4);
const P1: (usize, usize) = (16, 8);
const P2: (usize, usize) = (32, 8);
const P3: (usize, usize) = (16, 4);

/// Deterministic walks from the roots: up to `count` ids per root, `depth` deep.
fn walks(d: &SphereDomain, count: usize, depth: usize) -> Vec<SphereId> {
    let mut out: Vec<SphereId> = walk_paths(d, count, depth).into_iter().flatten().collect();
    out.sort();
    out.dedup();
    out
}

/// The paths of [`walks`], root first, `count` per root in root order.
fn walk_paths(d: &SphereDomain, count: usize, depth: usize) -> Vec<Vec<SphereId>> {
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut out = Vec::new();
    for r in d.roots() {
        for _ in 0..count {
            let mut path = Vec::new();
            let mut id = r;
            for _ in 0..depth {
                path.push(id);
                let kids = d.children(id).unwrap();
                if kids.is_empty() {
                    break;
                }
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                id = kids[(seed >> 33) as usize % kids.len()];
            }
            out.push(path);
        }
    }
    out
}

/// What kind of diamond an id is: its level, whether it straddles a cube edge, whether a
/// corner of it is a cube corner.
fn id_kind(d: &SphereDomain, id: SphereId) -> (u32, bool, bool) {
    let s = d.size();
    let corner = d
        .corners(id)
        .unwrap()
        .iter()
        .any(|p| p.iter().all(|x| x.abs() == s));
    (
        d.level(id).unwrap(),
        d.faces(id).unwrap().1.is_some(),
        corner,
    )
}

/// The vertices and cells whose positions a domain's ids hash: all of them for small `n`,
/// else the corners, their neighbours and an inner point.
fn position_picks(n: usize) -> (Vec<[usize; 2]>, Vec<[usize; 2]>) {
    let grid = |side: usize| -> Vec<[usize; 2]> {
        (0..side)
            .flat_map(|i| (0..side).map(move |j| [i, j]))
            .collect()
    };
    if n <= 8 {
        return (grid(n + 1), grid(n));
    }
    (
        vec![
            [0, 0],
            [n, 0],
            [n, n],
            [0, n],
            [1, 0],
            [0, 1],
            [n / 2, n / 3],
            [n - 1, 1],
        ],
        vec![[0, 0], [n - 1, 0], [n - 1, n - 1], [n / 2, n / 3]],
    )
}

/// Everything the port computes of one id; the positions of the picked vertices, then
/// cells, as the SHA-256 of their coordinates (i64 little-endian).
fn id_vector(d: &SphereDomain, id: SphereId, n: usize, picks: &[Vec<[usize; 2]>; 2]) -> Value {
    let (face, other) = d.faces(id).unwrap();
    let (cf, co, chart) = d.chart_frame(id).unwrap();
    assert_eq!((cf, co), (face, other));
    let mut positions = Vec::new();
    for &[i, j] in &picks[0] {
        for x in d.vertex_position(id, n, i, j).unwrap() {
            positions.extend_from_slice(&x.to_le_bytes());
        }
    }
    for &[i, j] in &picks[1] {
        for x in d.cell_position(id, n, i, j).unwrap() {
            positions.extend_from_slice(&x.to_le_bytes());
        }
    }
    let key = d.key(id).unwrap();
    assert_eq!(d.id_from_key(&key).unwrap(), id);
    json!({
        "c": id.c,
        "level": d.level(id).unwrap(),
        "half_extent": d.half_extent(id).unwrap(),
        "faces": [face, other],
        "key": hex(&key),
        "children": ids(&d.children(id).unwrap()),
        "parents": ids(&d.parents(id).unwrap()),
        "corners": d.corners(id).unwrap(),
        "neighbours": ids(&d.neighbours(id).unwrap()),
        "chart_frame": chart,
        "positions": sha256(&positions),
    })
}

fn geometry_vectors() -> Value {
    let mut domains = Vec::new();
    // Every id of the smallest domain, every kind and a sample of the next, walks of larger
    // ones (m = 40: the port's limit).
    for (m, n) in [
        (1u32, 2usize),
        (2, 4),
        (5, 8),
        (12, 32),
        (23, 64),
        (40, 512),
    ] {
        let d = SphereDomain::new(m).unwrap();
        let s = d.size();
        let chosen: Vec<SphereId> = if m <= 2 {
            let mut all = Vec::new();
            for x in -s..=s {
                for y in -s..=s {
                    for z in -s..=s {
                        let id = SphereId::new([x, y, z]);
                        if d.on_surface(id.c) && d.check(id).is_ok() {
                            all.push(id);
                        }
                    }
                }
            }
            let mut chosen = if m == 1 {
                all.clone()
            } else {
                sample(&all, STRIDE_M2, |id| id_kind(&d, *id))
            };
            chosen.extend(d.roots());
            chosen.sort();
            chosen.dedup();
            let kinds =
                |v: &[SphereId]| -> BTreeSet<_> { v.iter().map(|id| id_kind(&d, *id)).collect() };
            assert_eq!(
                kinds(&chosen),
                kinds(&all),
                "m = {m}: an id kind is missing"
            );
            chosen
        } else {
            // A walk from each root: its two coarsest and two finest levels, and one between
            // (axis-aligned or rotated by turns).
            let max = d.max_level();
            let mut chosen: Vec<SphereId> = walk_paths(&d, 1, max as usize + 1)
                .into_iter()
                .enumerate()
                .flat_map(|(k, path)| {
                    let middle = max / 2 + k as u32 % 2;
                    path.into_iter().filter(move |id| {
                        let l = d.level(*id).unwrap();
                        l <= 1 || l + 2 > max || l == middle
                    })
                })
                .collect();
            chosen.sort();
            chosen.dedup();
            chosen
        };
        let faces: BTreeSet<u8> = chosen.iter().map(|id| d.faces(*id).unwrap().0).collect();
        assert_eq!(faces.len(), 6, "m = {m}: a face is missing");
        assert!(
            chosen.iter().any(|id| id_kind(&d, *id).1),
            "m = {m}: no edge diamond"
        );
        assert!(
            chosen.iter().any(|id| id_kind(&d, *id).2),
            "m = {m}: no cube corner"
        );
        let (vertices, cells) = position_picks(n);
        let picks = [vertices, cells];
        let vectors: Vec<Value> = chosen
            .iter()
            .map(|&id| id_vector(&d, id, n, &picks))
            .collect();
        // Points that are no centre, or off the domain: the port must refuse them.
        let rejected = [
            [s, s, s],
            [-s, s, -s],
            [0, 0, 0],
            [s + 1, 0, 0],
            [s, 1, 0],
            [1, s, 3],
            [s, s, 1],
        ]
        .into_iter()
        .filter(|p| d.check(SphereId::new(*p)).is_err())
        .collect::<Vec<_>>();
        let bad_keys: Vec<String> = [
            vec![],
            vec![0],
            vec![0, 6, 0],
            vec![(2 * m + 2) as u8, 0, 0],
            vec![0, 0, 0xff],
            vec![0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
            vec![1, 0, 0x0f],
            vec![3, 2, 0x00],
        ]
        .into_iter()
        .filter(|k| d.id_from_key(k).is_err())
        .map(|k| hex(&k))
        .collect();
        domains.push(json!({
            "m": m,
            "size": s,
            "max_level": d.max_level(),
            "roots": ids(&d.roots()),
            "n": n,
            "vertex_picks": picks[0],
            "cell_picks": picks[1],
            "ids": vectors,
            "rejected": rejected,
            "bad_keys": bad_keys,
        }));
    }
    let points: Vec<Value> = [
        [1.0, 0.3, -0.7],
        [-0.2, -1.0, 0.99],
        [0.5, 0.5, 1.0],
        [1.0, 1.0, 1.0],
        [0.0, 0.0, -1.0],
        [2048.0, -1000.0, 17.0],
        [-3.0, 12.0, 5.0],
    ]
    .iter()
    .map(|&p| {
        let q = cube_to_unit_sphere(p);
        json!({"p": p, "sphere": q, "cube": unit_sphere_to_cube(q)})
    })
    .collect();
    json!({"domains": domains, "unit_sphere": points})
}

/// A coverage of a planet with holes: no data on face 1, a quarter of face 2 and a band
/// of face 4 (mixed, full and empty diamonds, across cube edges).
fn holes(face_side: usize, k: usize) -> bool {
    let w = face_side + 1;
    let (face, rest) = (k / (w * w), k % (w * w));
    let (u, y) = (rest % w, rest / w);
    face == 1
        || (face == 2 && u < w / 2 && y < w / 2)
        || (face == 4 && (face_side * 5 / 16..face_side * 9 / 16).contains(&y))
}

/// The children of a coded diamond whose side information its blob carries: those that
/// carry details and whose first parent it is (none below the finest level: those children
/// are leaves).
fn owned_children(frame: &SphereFrame, r: &SphereRefiner, id: SphereId, level: usize) -> usize {
    if level + 1 >= frame.detail_levels() {
        return 0;
    }
    r.info(id)
        .unwrap()
        .children
        .iter()
        .filter(|c| r.parents(**c).first() == Some(&id))
        .count()
}

/// What kind of slot an id has: its coded level (none: not coded), whether it straddles a
/// cube edge, whether it is masked (part of it outside the coverage), its owned children
/// and blob context group.
type SlotKind = Option<(usize, bool, bool, usize, usize)>;

fn slot_kind(frame: &SphereFrame, r: &SphereRefiner, id: SphereId) -> SlotKind {
    let (level, slot) = frame.coded_slot(id)?;
    let owned = owned_children(frame, r, id, level);
    let group = frame.slot_context(level, &slot, owned).group;
    Some((level, slot.is_edge(), slot.mask.is_some(), owned, group))
}

/// A slot: its raster indices (vertices, then cells) as the SHA-256 of their u32
/// little-endian bytes, its masks in hex.
fn slot_vector(frame: &SphereFrame, r: &SphereRefiner, id: SphereId) -> Value {
    let n = frame.n();
    let Some((level, slot)) = frame.coded_slot(id) else {
        return json!({"c": id.c, "coded": false, "info": r.info(id).is_some()});
    };
    let mut indices = Vec::new();
    for i in 0..=n {
        for j in 0..=n {
            let k = u32::try_from(slot.vertex_index(i, j)).unwrap();
            indices.extend_from_slice(&k.to_le_bytes());
        }
    }
    for i in 0..n {
        for j in 0..n {
            let k = u32::try_from(slot.cell_index(i, j)).unwrap();
            indices.extend_from_slice(&k.to_le_bytes());
        }
    }
    let mask = slot.mask.as_ref().map(|m| {
        let bits = |f: &dyn Fn(usize, usize) -> bool, side: usize| -> String {
            let bits: Vec<bool> = (0..side * side).map(|k| f(k / side, k % side)).collect();
            bits_hex(&bits)
        };
        json!({
            "vertex": bits(&|i, j| m.vertex(i, j), n + 1),
            "cell": bits(&|i, j| m.cell(i, j), n),
        })
    });
    let info = r.info(id).unwrap();
    let owned = owned_children(frame, r, id, level);
    let ctx = frame.slot_context(level, &slot, owned);
    json!({
        "c": id.c,
        "coded": true,
        "level": level,
        "key": hex(&slot.key),
        "edge": slot.is_edge(),
        "indices": sha256(&indices),
        "mask": mask,
        "group": ctx.group,
        "owned": owned,
        "children": ids(&info.children),
    })
}

fn frame_vectors() -> Value {
    let mut frames = Vec::new();
    for (face_side, n, sparse) in [
        (16usize, 4usize, false),
        (32, 8, false),
        (64, 8, true),
        (128, 16, true),
    ] {
        let coverage = sparse.then(|| Coverage::of_cube(face_side, n, |k| !holes(face_side, k)));
        let frame = SphereFrame::new(face_side, n, coverage.as_ref()).unwrap();
        let r = SphereRefiner::new(
            face_side,
            n,
            coverage.as_ref(),
            vec![256; frame.detail_levels()],
            Default::default(),
            vec![vec![0; (n + 1) * (n + 1)]; 6],
        )
        .unwrap();
        let d = frame.domain();
        // A sample of the coded diamonds of the small frames, of walks (and the leaves below)
        // of larger ones; every kind of slot in each.
        let mut chosen = if face_side <= 32 {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let all = (0..g.detail_levels())
                .flat_map(|l| g.level(l).iter().map(|s| s.id).collect::<Vec<_>>())
                .collect::<Vec<_>>();
            let stride = if face_side <= 16 { 2 } else { FRAME_STRIDE };
            sample(&all, stride, |id| slot_kind(&frame, &r, *id))
        } else {
            let all = walks(
                &d,
                if face_side >= 128 { 1 } else { 2 },
                frame.detail_levels() + 1,
            );
            sample(&all, WALK_STRIDE, |id| slot_kind(&frame, &r, *id))
        };
        chosen.extend(d.roots());
        chosen.sort();
        chosen.dedup();
        let kinds: BTreeSet<_> = chosen.iter().map(|id| slot_kind(&frame, &r, *id)).collect();
        assert!(
            kinds.iter().flatten().any(|k| k.1),
            "{face_side}/{n}: no edge slot"
        );
        assert_eq!(
            kinds.iter().flatten().any(|k| k.2),
            sparse,
            "{face_side}/{n}: masked slots"
        );
        let slots: Vec<Value> = chosen
            .iter()
            .map(|&id| slot_vector(&frame, &r, id))
            .collect();
        let valid: Option<String> = coverage.as_ref().map(|_| {
            let bytes: Vec<u8> = (0..frame.cube_len())
                .map(|k| u8::from(frame.is_valid(k)))
                .collect();
            sha256(&bytes)
        });
        frames.push(json!({
            "face_side": face_side,
            "n": n,
            "detail_levels": frame.detail_levels(),
            "coverage": coverage.as_ref().map(|c| base64(&c.to_bytes())),
            "valid": valid,
            "slots": slots,
        }));
    }
    json!({"frames": frames})
}

/// LEB128 framing of channel blobs (meta/src/channels.rs `frame_channels`).
fn frame_channels(parts: &[Option<&Vec<u8>>]) -> Option<Vec<u8>> {
    if parts.len() == 1 {
        return parts[0].cloned();
    }
    if parts.iter().all(Option::is_none) {
        return None;
    }
    let mut out = Vec::new();
    for p in parts {
        let p = p.map(Vec::as_slice).unwrap_or_default();
        let mut len = p.len();
        loop {
            let byte = (len & 0x7F) as u8;
            len >>= 7;
            if len == 0 {
                out.push(byte);
                break;
            }
            out.push(byte | 0x80);
        }
        out.extend_from_slice(p);
    }
    Some(out)
}

/// A planet's metadata (the fields a client reads; the entropy models and the coverage in
/// base64 instead of byte lists), blobs by centre (base64) and the decoded rasters (length
/// and SHA-256 of the i32 little-endian values).
fn planet_vector(name: &str, encs: &[Encoded]) -> Value {
    let first = &encs[0];
    let encode::EncodedDomain::Sphere { face_side } = first.domain else {
        panic!("not a planet");
    };
    let r = SphereRefiner::from_encoded(first).unwrap();
    let d = r.domain();
    let by_key: Vec<_> = encs.iter().map(|e| e.blobs_by_key().unwrap()).collect();
    let mut keys: Vec<&Vec<u8>> = by_key.iter().flat_map(|m| m.keys()).collect();
    keys.sort();
    keys.dedup();
    let mut blobs = BTreeMap::new();
    for key in keys {
        let parts: Vec<Option<&Vec<u8>>> = by_key.iter().map(|m| m.get(key)).collect();
        if let Some(bytes) = frame_channels(&parts) {
            let id = d.id_from_key(key).unwrap();
            blobs.insert(
                format!("{}/{}/{}", id.c[0], id.c[1], id.c[2]),
                base64(&bytes),
            );
        }
    }
    let channels: Vec<Value> = encs
        .iter()
        .enumerate()
        .map(|(c, e)| {
            json!({
                "name": format!("c{c}"),
                "value_scale": e.value_scale_m,
                "value_offset": e.value_offset_m,
                "steps": e.steps,
                "model": base64(&e.model.to_bytes()),
                "roots": e.roots,
            })
        })
        .collect();
    let decoded: Vec<Value> = encs
        .iter()
        .map(|e| {
            let values = encode::decode_sphere_integers(e).unwrap();
            let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            json!({"len": values.len(), "sha256": sha256(&bytes)})
        })
        .collect();
    json!({
        "name": name,
        "metadata": {
            "domain": "sphere",
            "complete": true,
            "m": d.m(),
            "n": first.n,
            "levels": r.detail_levels(),
            "extent": [face_side, face_side],
            "radius_m": 6_371_000.0,
            "coverage": first.coverage.as_ref().map(|c| base64(&c.to_bytes())),
            "channels": channels,
        },
        "blobs": blobs,
        "decoded": decoded,
    })
}

fn planet(face_side: usize, n: usize, mode: RateMode, sparse: bool, shift: f64) -> Encoded {
    let mut g = common::synthetic_planet(face_side, n).unwrap();
    for (k, v) in g.values_m.iter_mut().enumerate() {
        *v = (*v * (1.0 + shift)).round() + shift * 100.0;
        if sparse && holes(face_side, k) {
            *v = f64::NAN;
        }
    }
    encode::encode_sphere(
        &g,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo: Default::default(),
        },
    )
    .unwrap()
}

#[test]
fn js_sphere_vectors_match_the_rust_planet_code() {
    bless_or_check(
        "sphere-geometry.json",
        &geometry_vectors(),
        "js_sphere_vectors",
        "web-demo/js/sphere.mjs",
    );
    bless_or_check(
        "sphere-frames.json",
        &frame_vectors(),
        "js_sphere_vectors",
        "web-demo/js/sphere.mjs",
    );
    let planets = vec![
        planet_vector(
            &format!("dense lossless {}/{}", P0.0, P0.1),
            &[planet(P0.0, P0.1, RateMode::Lossless, false, 0.0)],
        ),
        planet_vector(
            &format!("dense rms {}/{}", P1.0, P1.1),
            &[planet(P1.0, P1.1, RateMode::RmsM(4.0), false, 0.0)],
        ),
        planet_vector(
            &format!("sparse max-error {}/{}", P2.0, P2.1),
            &[planet(P2.0, P2.1, RateMode::MaxErrorM(3.0), true, 0.0)],
        ),
        planet_vector(
            &format!("three channels {}/{}", P3.0, P3.1),
            &[
                planet(P3.0, P3.1, RateMode::Lossless, false, 0.0),
                planet(P3.0, P3.1, RateMode::RmsM(6.0), false, 0.5),
                planet(P3.0, P3.1, RateMode::MaxErrorM(20.0), false, -0.7),
            ],
        ),
    ];
    bless_or_check(
        "sphere-planets.json",
        &Value::from(planets),
        "js_sphere_vectors",
        "web-demo/js/sphere.mjs",
    );
}
