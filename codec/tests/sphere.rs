//! The planet codec through the public API: lossless round trips, the rate modes'
//! promises, seams across cube edges (all copies of a point agree after decoding, and a
//! random mixed-level cut built diamond by diamond is seamless), id <-> (level, index)
//! lookups and decoding one blob from its id alone.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::{BTreeMap, HashMap};

use quincunx_codec::blob;
use quincunx_codec::diamond::SphereId;
use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{
    self, CubeGrid, EncodeOptions, Encoded, EncodedDomain, RateMode, decode_sphere_integers,
};
use quincunx_codec::lifting;
use quincunx_codec::raster::Transform;
use quincunx_codec::sphere_raster::SphereGeometry;

fn synthetic_planet(face_side: usize, n: usize) -> CubeGrid {
    common::synthetic_planet(face_side, n).unwrap()
}

fn encode_planet(g: &CubeGrid, n: usize, mode: RateMode) -> Encoded {
    encode::encode_sphere(
        g,
        EncodeOptions {
            n,
            mode,
            sparse: false,
            rdo: Default::default(),
        },
    )
    .unwrap_or_else(|e| panic!("encode {mode:?} failed: {e}"))
}

/// RMS and max error over the distinct valid points (canonical copies).
fn errors(geom: &SphereGeometry, original: &[f64], decoded: &[f64]) -> (f64, f64, usize) {
    let (mut sum, mut max, mut count) = (0.0, 0.0f64, 0usize);
    for (k, (&a, &b)) in decoded.iter().zip(original).enumerate() {
        if !geom.is_canonical(k) || !b.is_finite() {
            continue;
        }
        let e = (a - b).abs();
        sum += e * e;
        max = max.max(e);
        count += 1;
    }
    ((sum / count.max(1) as f64).sqrt(), max, count)
}

/// Copies of cube edge and corner points whose decoded values differ from the canonical
/// copy, and the number of non-canonical copies compared.
fn copy_mismatches(geom: &SphereGeometry, decoded: &[i32]) -> (usize, usize) {
    let w = geom.face_side() + 1;
    let (mut compared, mut mismatches) = (0, 0);
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let copies: Vec<usize> = geom
                    .point_indices(geom.sample_position(face, u, v))
                    .collect();
                assert!(copies.contains(&geom.cube_index(face, u, v)));
                let here = geom.cube_index(face, u, v);
                if copies[0] != here {
                    compared += 1;
                    mismatches += usize::from(decoded[here] != decoded[copies[0]]);
                }
            }
        }
    }
    (compared, mismatches)
}

#[test]
fn lossless_round_trip_is_bit_exact_for_n8_and_n32() {
    for (face_side, n) in [(64, 8), (128, 32), (32, 32)] {
        let g = synthetic_planet(face_side, n);
        let enc = encode_planet(&g, n, RateMode::Lossless);
        assert_eq!(enc.domain, EncodedDomain::Sphere { face_side });
        assert_eq!(enc.roots.len(), 6);
        assert_eq!(enc.width * enc.height, g.values_m.len());
        let dec = encode::decode(&enc).unwrap();
        assert_eq!(dec, g.values_m, "face side {face_side}, N = {n}");
        assert_eq!(enc.report.max_abs_m, 0.0);
        assert_eq!(enc.report.samples, 6 * face_side * face_side + 2);
        assert_eq!(enc.report.valid_samples, enc.report.samples);
        println!(
            "face side {face_side}, N = {n}: {} blobs, {:.3} bits/sample",
            enc.report.blob_count, enc.report.bits_per_sample
        );
    }
}

#[test]
fn nodata_is_filled_and_excluded_and_the_canonical_copy_wins() {
    let (face_side, n) = (64, 8);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let mut g = synthetic_planet(face_side, n);
    let w = face_side + 1;
    // Holes everywhere (a function of the point, so copies agree) and the whole interior
    // of face -Z missing.
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let p = geom.sample_position(face, u, v);
                let hole = (p[0] * 31 + p[1] * 17 + p[2] * 7).rem_euclid(23) == 0;
                let interior = (1..w - 1).contains(&u) && (1..w - 1).contains(&v);
                if hole || (face == 5 && interior) {
                    g.values_m[geom.cube_index(face, u, v)] = f64::NAN;
                }
            }
        }
    }
    // A non-canonical copy that disagrees: the canonical copy is the point's value.
    let p = geom.sample_position(0, 0, 5);
    let copies: Vec<usize> = geom.point_indices(p).collect();
    assert_eq!(copies.len(), 2);
    let truth = g.values_m[copies[0]];
    g.values_m[copies[1]] = truth + 1000.0;

    let enc = encode_planet(&g, n, RateMode::Lossless);
    let dec = encode::decode(&enc).unwrap();
    let mut expected = g.values_m.clone();
    geom.make_consistent(&mut expected).unwrap();
    let (rms, max, count) = errors(&geom, &expected, &dec);
    assert_eq!((rms, max), (0.0, 0.0));
    assert_eq!(count, enc.report.valid_samples);
    assert!(count < enc.report.samples);
    assert_eq!(dec[copies[1]], truth);
    assert!(dec.iter().all(|x| x.is_finite()));
}

#[test]
fn max_error_mode_meets_its_bound() {
    let (face_side, n) = (64, 8);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let g = synthetic_planet(face_side, n);
    for e in [0.5, 2.5, 10.0] {
        let enc = encode_planet(&g, n, RateMode::MaxErrorM(e));
        let dec = encode::decode(&enc).unwrap();
        let (_, max, _) = errors(&geom, &g.values_m, &dec);
        assert!(max <= e + 1e-9, "e = {e}: max error {max}");
        assert!((enc.report.max_abs_m - max).abs() < 1e-9);
        // Every copy is within the bound too.
        let all = dec
            .iter()
            .zip(&g.values_m)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(all <= e + 1e-9);
    }
}

#[test]
fn rms_mode_meets_its_target_and_copies_agree() {
    let (face_side, n) = (128, 32);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let g = synthetic_planet(face_side, n);
    let lossless = encode_planet(&g, n, RateMode::Lossless)
        .report
        .bits_per_sample;
    for t in [1.0, 5.0] {
        let enc = encode_planet(&g, n, RateMode::RmsM(t));
        let dec = encode::decode(&enc).unwrap();
        let (rms, _, _) = errors(&geom, &g.values_m, &dec);
        assert!(rms <= t, "t = {t}: rms {rms}");
        assert!((enc.report.rms_m - rms).abs() < 1e-9);
        assert!(enc.report.bits_per_sample < lossless);
        let ints = decode_sphere_integers(&enc).unwrap();
        let (compared, mismatches) = copy_mismatches(&geom, &ints);
        assert_eq!(
            compared,
            12 * (face_side - 1) + 8 * 2,
            "edge and corner copies"
        );
        assert_eq!(mismatches, 0, "t = {t}: copies of edge points disagree");
        println!(
            "rms {t} m: {:.3} bits/sample (lossless {lossless:.3}), rms {rms:.3}",
            enc.report.bits_per_sample
        );
    }
}

#[test]
fn ids_keys_and_slots_look_each_other_up() {
    let geom = SphereGeometry::new(128, 8).unwrap();
    let d = geom.domain();
    assert_eq!(geom.detail_levels(), 8);
    let mut total = 0;
    for l in 0..geom.detail_levels() {
        let slots = geom.level(l);
        // Every diamond of the level is present: the level tiles the cube surface.
        let t = d.level_exponent(l as u32);
        let area = (1i64 << t) * (1i64 << t) * if l % 2 == 0 { 4 } else { 2 };
        let face = geom.face_side() as i64 * geom.face_side() as i64;
        assert_eq!(slots.len() as i64 * area, 6 * face, "level {l}");
        for (i, s) in slots.iter().enumerate() {
            assert_eq!(d.level(s.id).unwrap() as usize, l);
            assert_eq!(d.key(s.id).unwrap(), s.key);
            assert_eq!(d.id_from_key(&s.key).unwrap(), s.id);
            assert_eq!(geom.locate(s.id), Some((l, i)));
            assert_eq!(geom.locate_key(&s.key), Some((l, i)));
            assert_eq!(s.children.len(), if l + 1 < 8 { 4 } else { 0 });
            for &k in &s.owned {
                let child = geom.level(l + 1)[k].id;
                assert_eq!(d.parents(child).unwrap()[0], s.id);
            }
            total += 1;
        }
    }
    // Every child is owned by exactly one parent.
    for l in 0..geom.detail_levels() - 1 {
        let mut owners = vec![0; geom.level(l + 1).len()];
        for s in geom.level(l) {
            for &k in &s.owned {
                owners[k] += 1;
            }
        }
        assert!(owners.iter().all(|&c| c == 1), "level {}", l + 1);
    }
    assert_eq!(
        geom.level(0).iter().map(|s| s.id).collect::<Vec<_>>(),
        d.roots().to_vec()
    );
    // Deeper than the detail levels, off the surface, malformed: no slot.
    let deep = d.children(geom.level(7)[0].id).unwrap()[0];
    assert_eq!(geom.locate(deep), None);
    assert_eq!(geom.locate(SphereId::new([0, 0, 0])), None);
    assert_eq!(geom.locate_key(&[]), None);
    assert_eq!(geom.locate_key(&[3, 9, 0, 0]), None);
    println!("{total} diamonds looked up");
}

#[test]
fn one_blob_decodes_from_its_id_alone() {
    let (face_side, n) = (128, 32);
    let g = synthetic_planet(face_side, n);
    let enc = encode_planet(&g, n, RateMode::RmsM(2.0));
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let mut decoded = 0;
    for (l, level) in enc.blobs.iter().enumerate() {
        for (i, b) in level.iter().enumerate() {
            let Some(bytes) = b else { continue };
            // A client knows the id (from the DAG) and the repository metadata only.
            let id = geom.level(l)[i].id;
            let (ll, ii) = geom.locate(id).unwrap();
            let ctx = blob::BlobContext {
                step: enc.steps[ll],
                ..geom.blob_context(ll, ii)
            };
            let content = blob::decode(bytes, &ctx, &enc.model).unwrap();
            assert_eq!(content.q.len(), n * n);
            assert_eq!(content.child_classes.len(), geom.level(l)[i].owned.len());
            // The wrong id's context is detected by the checksum.
            let other = (i + 1) % level.len();
            if other != i {
                assert!(blob::decode(bytes, &geom.blob_context(l, other), &enc.model).is_err());
            }
            decoded += 1;
        }
    }
    assert!(decoded > 0);
}

/// A diamond whose vertex grid is known (both parents are refined).
struct Node {
    level: usize,
    slot: usize,
    coarse: Vec<i32>,
    refined: Option<(Vec<i32>, Vec<i32>)>,
}

/// SplitMix64.
struct Rng(u64);

impl Rng {
    fn chance(&mut self, p: f64) -> bool {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64 <= p
    }
}

#[test]
fn any_mixed_level_cut_is_seamless_across_cube_edges() {
    const N: usize = 8;
    const W: usize = N + 1;
    let face_side = 128;
    let geom = SphereGeometry::new(face_side, N).unwrap();
    let d = geom.domain();
    let two_n = 2 * N as i64;
    let g = synthetic_planet(face_side, N);
    let original: Vec<i32> = g.values_m.iter().map(|&v| v as i32).collect();
    let mut raster = original.clone();
    let details = geom.analyze(&mut raster).unwrap();
    let roots = geom.gather_roots(&raster);
    let levels = geom.detail_levels();

    // Refine everything near a cube corner (three faces meet there) and randomly elsewhere.
    let focus = cube_to_unit_sphere([1.0, 0.9, 0.8]);
    let dist = |id: SphereId| {
        let q = cube_to_unit_sphere(id.c.map(|x| x as f64));
        ((q[0] - focus[0]).powi(2) + (q[1] - focus[1]).powi(2) + (q[2] - focus[2]).powi(2)).sqrt()
    };
    let mut rng = Rng(0x51DE_5EA5);
    let mut nodes: BTreeMap<SphereId, Node> = BTreeMap::new();
    for (face, grid) in roots.into_iter().enumerate() {
        let id = d.roots()[face];
        let (level, slot) = geom.locate(id).unwrap();
        assert_eq!(level, 0);
        nodes.insert(
            id,
            Node {
                level,
                slot,
                coarse: grid,
                refined: None,
            },
        );
    }
    let (mut parents_compared, mut parents_disagree, mut unwritten) = (0, 0, 0);
    for (level, level_details) in details.iter().enumerate() {
        let ids: Vec<SphereId> = nodes
            .iter()
            .filter(|(_, n)| n.level == level)
            .map(|(&id, _)| id)
            .collect();
        for id in ids {
            // All roots are refined; then the always-refined radius shrinks slower than
            // parents spread apart, so the focus keeps complete parents all the way down.
            let p = if level == 0 || dist(id) < 0.05 + 3.0 * 0.5f64.powf(level as f64 / 2.0) {
                1.0
            } else {
                0.5
            };
            if !rng.chance(p) {
                continue;
            }
            let node = nodes.get_mut(&id).unwrap();
            let mut v = node.coarse.clone();
            let mut c = vec![0; N * N];
            lifting::synthesize(N, &mut v, &level_details[node.slot], &mut c, None);
            node.refined = Some((v, c));
        }
        if level + 1 == levels {
            break;
        }
        // A child's grid is its parents' refined lattices, matched by 3D position.
        for (slot, s) in geom.level(level + 1).iter().enumerate() {
            let parents = d.parents(s.id).unwrap();
            if !parents
                .iter()
                .all(|p| nodes.get(p).is_some_and(|n| n.refined.is_some()))
            {
                continue;
            }
            let mut lattice: HashMap<[i64; 3], i32> = HashMap::new();
            for p in &parents {
                let (v, c) = nodes[p].refined.as_ref().unwrap();
                for i in 0..=N {
                    for j in 0..=N {
                        let mut put = |pos: [i64; 3], x: i32| {
                            if let Some(&old) = lattice.get(&pos) {
                                parents_compared += 1;
                                parents_disagree += usize::from(old != x);
                            }
                            lattice.insert(pos, x);
                        };
                        put(d.vertex_position(*p, N, i, j).unwrap(), v[i * W + j]);
                        if i < N && j < N {
                            put(d.cell_position(*p, N, i, j).unwrap(), c[i * N + j]);
                        }
                    }
                }
            }
            let mut grid = vec![0; W * W];
            for (k, x) in grid.iter_mut().enumerate() {
                match lattice.get(&d.vertex_position(s.id, N, k / W, k % W).unwrap()) {
                    Some(&value) => *x = value,
                    None => unwritten += 1,
                }
            }
            nodes.insert(
                s.id,
                Node {
                    level: level + 1,
                    slot,
                    coarse: grid,
                    refined: None,
                },
            );
        }
    }
    let mut per_level: BTreeMap<usize, (usize, usize)> = BTreeMap::new();
    for node in nodes.values() {
        let e = per_level.entry(node.level).or_default();
        e.0 += 1;
        e.1 += usize::from(node.refined.is_some());
    }
    println!("(diamonds with a grid, refined) per level: {per_level:?}");
    assert_eq!(unwritten, 0, "child vertices no parent lattice holds");
    assert!(parents_compared > 0);
    assert_eq!(parents_disagree, 0, "the two parents of a child disagree");

    // Refined finest diamonds reproduce the data.
    let at = |pos: [i64; 3]| {
        assert!(
            pos.iter().all(|x| x % two_n == 0),
            "finest lattice off the samples"
        );
        original[geom.point_indices(pos.map(|x| x / two_n)).next().unwrap()]
    };
    let mut finest = 0;
    for (&id, node) in nodes.iter().filter(|(_, n)| n.level + 1 == levels) {
        let Some((v, c)) = &node.refined else {
            continue;
        };
        for i in 0..=N {
            for j in 0..=N {
                assert_eq!(v[i * W + j], at(d.vertex_position(id, N, i, j).unwrap()));
                if i < N && j < N {
                    assert_eq!(c[i * N + j], at(d.cell_position(id, N, i, j).unwrap()));
                }
                finest += 1;
            }
        }
    }
    assert!(finest > 0, "the cut never reached the finest level");

    // The cut: unrefined diamonds with a grid; wherever two share a position they agree,
    // including positions on cube edges and corners shared by diamonds of different faces.
    let mut drawn: HashMap<[i64; 3], (SphereId, usize, i32)> = HashMap::new();
    let (mut compared, mut mismatches, mut across_levels, mut across_faces) = (0, 0, 0, 0);
    let mut cut_levels: BTreeMap<usize, usize> = BTreeMap::new();
    for (&id, node) in nodes.iter().filter(|(_, n)| n.refined.is_none()) {
        *cut_levels.entry(node.level).or_default() += 1;
        for k in 0..W * W {
            let pos = d.vertex_position(id, N, k / W, k % W).unwrap();
            let value = node.coarse[k];
            match drawn.get(&pos) {
                Some(&(other, other_level, other_value)) => {
                    compared += 1;
                    mismatches += usize::from(value != other_value);
                    across_levels += usize::from(other_level != node.level);
                    across_faces +=
                        usize::from(d.faces(other).unwrap().0 != d.faces(id).unwrap().0);
                }
                None => {
                    drawn.insert(pos, (id, node.level, value));
                }
            }
        }
    }
    println!(
        "cut per level {cut_levels:?}: {compared} shared vertices, {across_levels} across levels, {across_faces} across faces, {mismatches} mismatches"
    );
    assert!(
        cut_levels.len() >= 3,
        "cut not mixed enough: {cut_levels:?}"
    );
    assert!(across_levels > 0 && across_faces > 0);
    assert_eq!(mismatches, 0);
}
