//! Vectors for the JavaScript port of the planar side (`web-demo/js/{lifting,coverage,
//! planar}.mjs`, tested by `web-demo/test/planar.test.mjs`): ids, keys, hierarchy and
//! positions of the planar domain, the slots and masks the refiner derives from ids
//! (raster edges and coverages), one-diamond lifting with and without masks, and the
//! parent-to-child grid maps.
//!
//! The files live in `web-demo/test/golden/planar-*.json`. `QUINCUNX_BLESS=1` writes them;
//! otherwise the test checks that the committed files are what the Rust code says today
//! (so a change of the Rust side that the port must follow fails here first).
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use quincunx_codec::coverage::Coverage;
use quincunx_codec::diamond::{PlanarDomain, PlanarId};
use quincunx_codec::incremental::Refiner;
use quincunx_codec::lifting::{self, DiamondMask};
use quincunx_codec::raster::RasterFrame;
use serde_json::{Value, json};

use common::planar_refiner;
use common::vectors::{bless_or_check, hex};

fn xy(id: PlanarId) -> Value {
    json!([id.x, id.y])
}

fn ids(v: &[PlanarId]) -> Value {
    Value::from(v.iter().map(|&id| xy(id)).collect::<Vec<_>>())
}

fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *seed >> 16
}

/// FNV-1a (32 bits) of a mask's vertex flags then its cell flags, one byte (0/1) each.
fn mask_hash(m: &DiamondMask) -> String {
    let n = m.n();
    let mut h = 0x811c_9dc5u32;
    let mut eat = |b: bool| {
        h ^= u32::from(b);
        h = h.wrapping_mul(0x0100_0193);
    };
    for i in 0..=n {
        for j in 0..=n {
            eat(m.vertex(i, j));
        }
    }
    for i in 0..n {
        for j in 0..n {
            eat(m.cell(i, j));
        }
    }
    format!("{h:08x}")
}

fn mask_vector(m: Option<&DiamondMask>) -> Value {
    match m {
        None => Value::Null,
        Some(m) => json!({"valid_cells": m.valid_cells(), "hash": mask_hash(m)}),
    }
}

/// Deterministic walks from the root: `count` walks, `depth` deep.
fn walks(d: &PlanarDomain, count: usize, depth: usize) -> Vec<PlanarId> {
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut out = Vec::new();
    for _ in 0..count {
        let mut id = d.root();
        for _ in 0..depth {
            out.push(id);
            let kids = d.children(id).unwrap();
            if kids.is_empty() {
                break;
            }
            id = kids[lcg(&mut seed) as usize % kids.len()];
        }
    }
    out.sort();
    out.dedup();
    out
}

/// Every id of `d` whose level is at most `max_level`.
fn all_ids(d: &PlanarDomain, max_level: u32) -> Vec<PlanarId> {
    let s = d.size();
    let mut out = Vec::new();
    for y in 0..=s {
        for x in 0..=s {
            let id = PlanarId::new(x, y);
            if d.level(id).is_ok_and(|l| l <= max_level) {
                out.push(id);
            }
        }
    }
    out
}

fn id_vector(d: &PlanarDomain, id: PlanarId, n: usize) -> Value {
    let key = d.key(id).unwrap();
    assert_eq!(d.id_from_key(&key).unwrap(), id);
    let neighbours: Vec<Value> = d
        .neighbours(id)
        .unwrap()
        .iter()
        .map(|x| x.map_or(Value::Null, xy))
        .collect();
    json!({
        "c": xy(id),
        "level": d.level(id).unwrap(),
        "half_extent": d.half_extent(id).unwrap(),
        "key": hex(&key),
        "corners": d.corners(id).unwrap(),
        "parents": ids(&d.parents(id).unwrap()),
        "children": ids(&d.children(id).unwrap()),
        "neighbours": neighbours,
        "is_half": d.is_half(id).unwrap(),
        "n": n,
        "vertex": [d.vertex_position(id, n, 0, 0).unwrap(), d.vertex_position(id, n, n / 2, n / 3 + 1).unwrap()],
        "cell": [d.cell_position(id, n, 0, 0).unwrap(), d.cell_position(id, n, n - 1, n / 4).unwrap()],
    })
}

fn geometry_vectors() -> Value {
    let mut domains = Vec::new();
    // Every id of small domains, sampled walks of larger ones (m = 40: positions x 2N
    // stay below 2^53).
    for (m, n, every) in [
        (1u32, 2usize, true),
        (2, 4, true),
        (10, 32, false),
        (25, 512, false),
        (40, 512, false),
    ] {
        let d = PlanarDomain::new(m).unwrap();
        let chosen: Vec<PlanarId> = if every {
            all_ids(&d, d.max_level())
        } else {
            // One walk to the deepest level, a few levels of it.
            let top = d.max_level();
            walks(&d, 1, 2 * m as usize)
                .into_iter()
                .filter(|&id| d.level(id).is_ok_and(|l| l % 6 < 2 || l + 2 >= top))
                .collect()
        };
        let s = d.size();
        let rejected: Vec<[i64; 2]> = [
            [0, 0],
            [s, s],
            [0, s],
            [s + 1, 1],
            [-1, 1],
            [1, -2],
            [s, s + 2],
        ]
        .into_iter()
        .filter(|p| d.check(PlanarId::new(p[0], p[1])).is_err())
        .collect();
        let bad_keys: Vec<String> = [
            vec![],
            vec![0],
            vec![0, 0],
            vec![0, 3, 0],
            vec![0, 0x13],
            vec![(2 * m) as u8, 0, 0],
            vec![1, 0],
            vec![1, 0x0b],
            vec![2, 0xff],
            vec![3, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
        ]
        .into_iter()
        .filter(|k| d.id_from_key(k).is_err())
        .map(|k| hex(&k))
        .collect();
        let meeting: Vec<Value> = [(0u32, [0i64, 0, 0, 0]), (1, [0, s / 3, 0, s / 5]), (2, [s / 4, s / 2, s / 8, s - 1]), (3.min(d.max_level()), [1, 2, s - 2, s])]
            .iter()
            .map(|&(level, rect)| json!({"level": level, "rect": rect, "ids": ids(&d.diamonds_meeting(level, rect))}))
            .collect();
        domains.push(json!({
            "m": m,
            "size": s,
            "max_level": d.max_level(),
            "root": xy(d.root()),
            "ids": chosen.iter().map(|&id| id_vector(&d, id, n)).collect::<Vec<_>>(),
            "rejected": rejected,
            "bad_keys": bad_keys,
            "meeting": meeting,
        }));
    }
    json!({
        "about": "planar ids, keys, hierarchy and positions (written by codec/tests/js_planar_vectors.rs; bless with QUINCUNX_BLESS=1)",
        "domains": domains,
    })
}

/// A coverage with holes: blocks with data where `(x / 7 + y / 5) % 3 != 0` or in the
/// top-left corner.
fn holes(w: usize, h: usize, n: usize) -> Coverage {
    Coverage::of_raster(w, h, n, |k| {
        let (x, y) = (k % w, k / w);
        (x / 7 + y / 5) % 3 != 0 || (x < 20 && y < 20)
    })
}

fn frame_vectors() -> Value {
    let mut frames = Vec::new();
    for (w, h, n, sparse, every) in [
        (33usize, 20usize, 4usize, false, true),
        (65, 129, 8, true, false),
        (200, 90, 16, true, false),
        (700, 513, 32, false, false),
        (1025, 1025, 32, false, false),
    ] {
        let coverage = sparse.then(|| holes(w, h, n));
        let r = planar_refiner(w, h, n, coverage.as_ref());
        let frame = RasterFrame::new(w, h, n, coverage.as_ref()).unwrap();
        let d = r.domain();
        let levels = r.detail_levels() as u32;
        let chosen = if every {
            all_ids(&d, levels.min(d.max_level()))
        } else {
            walks(&d, 8, levels as usize + 1)
        };
        let diamonds: Vec<Value> = chosen
            .iter()
            .map(|&id| {
                let coded = r.is_coded(id);
                assert_eq!(coded, frame.is_coded(id));
                let Some(info) = r.info(id) else {
                    return json!({"c": xy(id), "coded": coded, "refinable": r.is_refinable(id)});
                };
                let (level, slot) = frame.slot(id).unwrap();
                assert_eq!(level, info.level);
                let owned: Vec<PlanarId> = if info.level + 1 < r.detail_levels() {
                    info.children
                        .iter()
                        .copied()
                        .filter(|&c| d.parents(c).unwrap().first() == Some(&id))
                        .collect()
                } else {
                    Vec::new()
                };
                let ctx = frame.slot_context(level, &slot, owned.len());
                let (origin, a, b) = slot_frame(&d, id, n);
                json!({
                    "c": xy(id),
                    "coded": coded,
                    "refinable": r.is_refinable(id),
                    "level": info.level,
                    "key": hex(&info.key),
                    "mask": mask_vector(info.mask.as_ref()),
                    "children": ids(&info.children),
                    "owned": ids(&owned),
                    "group": ctx.group,
                    "frame": [origin, a, b],
                })
            })
            .collect();
        frames.push(json!({
            "width": w,
            "height": h,
            "n": n,
            "coverage": coverage.as_ref().map(Coverage::to_bytes),
            "m": d.m(),
            "detail_levels": r.detail_levels(),
            "diamonds": diamonds,
        }));
    }
    json!({
        "about": "raster frames: coded diamonds, keys, masks (FNV-1a of the vertex then cell flags), children, owned children (written by codec/tests/js_planar_vectors.rs; bless with QUINCUNX_BLESS=1)",
        "frames": frames,
    })
}

/// Raster position of vertex (0, 0) and the steps along i and j, from the corners.
fn slot_frame(d: &PlanarDomain, id: PlanarId, n: usize) -> ([i64; 2], [i64; 2], [i64; 2]) {
    let c = d.corners(id).unwrap();
    let n = n as i64;
    (
        c[0],
        [(c[1][0] - c[0][0]) / n, (c[1][1] - c[0][1]) / n],
        [(c[3][0] - c[0][0]) / n, (c[3][1] - c[0][1]) / n],
    )
}

fn lifting_vectors() -> Value {
    let mut seed = 23u64;
    let mut cases = Vec::new();
    for (n, masked, small) in [
        (2usize, false, false),
        (4, false, false),
        (8, false, false),
        (8, false, true),
        (8, true, false),
        (8, true, true),
    ] {
        let mask = masked.then(|| {
            DiamondMask::from_fn(n, |i, j| i + 3 >= j, |i, j| i + 3 > j && (i + j) % 7 != 3)
        });
        let value = |seed: &mut u64| {
            if small {
                (lcg(seed) % 20001) as i32 - 10000
            } else {
                lcg(seed) as i32
            }
        };
        let v: Vec<i32> = (0..(n + 1) * (n + 1)).map(|_| value(&mut seed)).collect();
        let h: Vec<i32> = (0..n * n).map(|_| value(&mut seed)).collect();
        let mut v_out = v.clone();
        let mut c_out = vec![0; n * n];
        lifting::synthesize(n, &mut v_out, &h, &mut c_out, mask.as_ref());
        let mut c_zero = vec![0; n * n];
        lifting::synthesize_zero(n, &v, &mut c_zero, mask.as_ref());
        let mut v_an = v.clone();
        let mut h_an = vec![0; n * n];
        lifting::analyze(n, &mut v_an, &c_out, &mut h_an, mask.as_ref());
        cases.push(json!({
            "n": n,
            "mask": mask.as_ref().map(|m| json!({
                "vertex": (0..(n + 1) * (n + 1)).map(|k| u8::from(m.vertex(k / (n + 1), k % (n + 1)))).collect::<Vec<_>>(),
                "cell": m.cells().iter().map(|&b| u8::from(b)).collect::<Vec<_>>(),
            })),
            "v": v,
            "h": h,
            "v_out": v_out,
            "c_out": c_out,
            "c_zero": c_zero,
            "analyze_v": v_an,
            "analyze_h": h_an,
        }));
    }
    // Parent-to-child grid maps: every child of sampled diamonds against each of its
    // parents, and against diamonds that are not its parents.
    let mut maps = Vec::new();
    for (m, n) in [(3u32, 4usize), (10, 32), (30, 512)] {
        let d = PlanarDomain::new(m).unwrap();
        let top = d.max_level();
        let sampled = walks(&d, 1, 2 * m as usize - 1)
            .into_iter()
            .filter(|&id| m < 10 || d.level(id).is_ok_and(|l| l % 7 == 0 || l + 2 >= top));
        for id in sampled {
            for child in d.children(id).unwrap() {
                let mut against = d.parents(child).unwrap();
                against.push(d.root());
                if let Some(&nb) = d.neighbours(id).unwrap().iter().flatten().next() {
                    against.push(nb);
                }
                for p in against {
                    let map =
                        lifting::child_half(&d.corners(p).unwrap(), &d.corners(child).unwrap(), n);
                    maps.push(json!({
                        "m": m,
                        "n": n,
                        "parent": xy(p),
                        "child": xy(child),
                        "map": map.map(|g| [g.map(0, 0), g.map(1, 0), g.map(0, 1)]),
                    }));
                }
            }
        }
    }
    json!({
        "about": "one-diamond lifting (synthesize, synthesize_zero, analyze) and child_half maps as [map(0,0), map(1,0), map(0,1)] (written by codec/tests/js_planar_vectors.rs; bless with QUINCUNX_BLESS=1)",
        "cases": cases,
        "maps": maps,
    })
}

#[test]
fn js_planar_vectors_match_the_rust_planar_code() {
    bless_or_check(
        "planar-geometry.json",
        &geometry_vectors(),
        "js_planar_vectors",
        "web-demo/js/planar.mjs",
    );
    bless_or_check(
        "planar-frames.json",
        &frame_vectors(),
        "js_planar_vectors",
        "web-demo/js/planar.mjs",
    );
    bless_or_check(
        "planar-lifting.json",
        &lifting_vectors(),
        "js_planar_vectors",
        "web-demo/js/planar.mjs",
    );
}
