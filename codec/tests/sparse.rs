//! Sparse encoding through the public API: nodata areas of whole coverage blocks are left
//! out of the hierarchy (no details, no blobs), data points keep every guarantee, small
//! voids stay filled, the coverage survives its byte form and rejects hostile bytes.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use quincunx_codec::blob;
use quincunx_codec::coverage::Coverage;
use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{
    self, CubeGrid, EncodeOptions, Encoded, Grid, RateMode, decode_sphere_integers,
};
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::sphere_raster::SphereGeometry;

fn encode_planet(g: &CubeGrid, n: usize, mode: RateMode, sparse: bool) -> Encoded {
    encode::encode_sphere(
        g,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo: Default::default(),
        },
    )
    .unwrap_or_else(|e| panic!("encode {mode:?} sparse={sparse} failed: {e}"))
}

fn encode_grid(g: &Grid, n: usize, mode: RateMode, sparse: bool) -> Encoded {
    encode::encode(
        g,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo: Default::default(),
        },
    )
    .unwrap_or_else(|e| panic!("encode {mode:?} sparse={sparse} failed: {e}"))
}

/// Unit direction of latitude/longitude in degrees (+Z north, +X = 0E, +Y = 90E).
fn direction(lat_deg: f64, lon_deg: f64) -> [f64; 3] {
    let (lat, lon) = (lat_deg.to_radians(), lon_deg.to_radians());
    [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()]
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    d.clamp(-1.0, 1.0).acos().to_degrees()
}

/// The synthetic planet with data only in a cap of `radius_deg` around a direction near a
/// cube corner (so the cap spans three faces and their edges); NaN elsewhere.
fn capped_planet(face_side: usize, n: usize, radius_deg: f64) -> CubeGrid {
    let mut g = common::synthetic_planet(face_side, n).unwrap();
    // Bit-exact comparisons: no negative zeros.
    g.values_m.iter_mut().for_each(|v| *v += 0.0);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let centre = direction(30.0, 40.0);
    let w = face_side + 1;
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let p = geom.sample_position(face, u, v);
                let q = cube_to_unit_sphere(p.map(|c| c as f64));
                if angle_deg(q, centre) > radius_deg {
                    g.values_m[geom.cube_index(face, u, v)] = f64::NAN;
                }
            }
        }
    }
    g
}

/// RMS and max error over the distinct data points (canonical copies).
fn planet_errors(geom: &SphereGeometry, original: &[f64], decoded: &[f64]) -> (f64, f64, usize) {
    let (mut sum, mut max, mut count) = (0.0, 0.0f64, 0usize);
    for (k, (&a, &b)) in decoded.iter().zip(original).enumerate() {
        if !geom.is_canonical(k) || !b.is_finite() {
            continue;
        }
        let e = (a - b).abs();
        let e = if e.is_nan() { f64::INFINITY } else { e };
        sum += e * e;
        max = max.max(e);
        count += 1;
    }
    ((sum / count.max(1) as f64).sqrt(), max, count)
}

fn blob_stats(enc: &Encoded) -> (usize, usize) {
    let blobs = enc.blobs.iter().flatten().flatten();
    (blobs.clone().count(), blobs.map(Vec::len).sum())
}

#[test]
fn sparse_planet_cap_is_lossless_on_data_with_far_fewer_blobs() {
    let (face_side, n) = (128, 16);
    let g = capped_planet(face_side, n, 30.0);
    let dense = encode_planet(&g, n, RateMode::Lossless, false);
    let sparse = encode_planet(&g, n, RateMode::Lossless, true);
    assert!(dense.coverage.is_none());
    let cov = sparse
        .coverage
        .as_ref()
        .expect("sparse output carries a coverage");
    let (dn, db) = blob_stats(&dense);
    let (sn, sb) = blob_stats(&sparse);
    println!(
        "cap 30 deg, face_side {face_side}, N {n}: coverage {} of {} blocks of {} samples \
         ({} bytes); blobs dense {dn} ({db} B), sparse {sn} ({sb} B)",
        cov.covered_blocks(),
        cov.blocks(),
        cov.block_side(),
        cov.to_bytes().len()
    );
    assert!(sn * 10 < dn * 4, "sparse {sn} blobs vs dense {dn}");
    assert!(sb < db);

    let geom = SphereGeometry::with_coverage(face_side, n, cov).unwrap();
    let dec_dense = encode::decode(&dense).unwrap();
    let dec_sparse = encode::decode(&sparse).unwrap();
    let (_, max, count) = planet_errors(&geom, &g.values_m, &dec_sparse);
    assert!(count > 0);
    assert_eq!(max, 0.0);
    assert_eq!(sparse.report.max_abs_m, 0.0);
    let ints_dense = decode_sphere_integers(&dense).unwrap();
    let ints_sparse = decode_sphere_integers(&sparse).unwrap();
    for (k, &v) in g.values_m.iter().enumerate() {
        if v.is_finite() {
            assert_eq!(dec_sparse[k].to_bits(), v.to_bits(), "entry {k}");
            assert_eq!(dec_sparse[k], dec_dense[k]);
            assert_eq!(
                ints_sparse[k] as f64 * sparse.value_scale_m + sparse.value_offset_m,
                ints_dense[k] as f64 * dense.value_scale_m + dense.value_offset_m
            );
        }
        // Invalid points decode to NaN metres and integer 0; valid ones are finite.
        if geom.is_valid(k) {
            assert!(dec_sparse[k].is_finite(), "valid entry {k}");
        } else {
            assert!(
                dec_sparse[k].is_nan() && ints_sparse[k] == 0,
                "invalid entry {k}"
            );
        }
    }
    // Copies of cube edge points agree on validity and value.
    let w = face_side + 1;
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let copies: Vec<usize> = geom
                    .point_indices(geom.sample_position(face, u, v))
                    .collect();
                for &c in &copies[1..] {
                    assert_eq!(geom.is_valid(c), geom.is_valid(copies[0]));
                    assert_eq!(ints_sparse[c], ints_sparse[copies[0]]);
                }
            }
        }
    }
}

#[test]
fn sparse_planet_keeps_max_error_and_rms_bounds_on_data() {
    let (face_side, n) = (128, 32);
    let g = capped_planet(face_side, n, 30.0);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    for e in [0.5, 3.0] {
        let enc = encode_planet(&g, n, RateMode::MaxErrorM(e), true);
        let (_, max, _) = planet_errors(&geom, &g.values_m, &encode::decode(&enc).unwrap());
        assert!(max <= e + 1e-9, "max-error {e}: {max}");
        assert!((enc.report.max_abs_m - max).abs() < 1e-9);
    }
    for t in [1.0, 4.0] {
        let enc = encode_planet(&g, n, RateMode::RmsM(t), true);
        let dense = encode_planet(&g, n, RateMode::RmsM(t), false);
        let (rms, _, _) = planet_errors(&geom, &g.values_m, &encode::decode(&enc).unwrap());
        assert!(rms <= t, "rms {t}: {rms}");
        assert!((enc.report.rms_m - rms).abs() < 1e-9);
        println!(
            "rms {t}: sparse {} blobs {} B, dense {} blobs {} B",
            blob_stats(&enc).0,
            blob_stats(&enc).1,
            blob_stats(&dense).0,
            blob_stats(&dense).1
        );
        assert!(blob_stats(&enc).1 < blob_stats(&dense).1);
    }
}

#[test]
fn sparse_blobs_decode_from_id_and_coverage_bytes_alone() {
    let (face_side, n) = (128, 16);
    let g = capped_planet(face_side, n, 30.0);
    let enc = encode_planet(&g, n, RateMode::RmsM(2.0), true);
    // A client knows the repository metadata (the coverage bytes) and ids only.
    let bytes = enc.coverage.as_ref().unwrap().to_bytes();
    let geom = SphereGeometry::with_coverage(face_side, n, &Coverage::from_bytes(&bytes).unwrap())
        .unwrap();
    let (mut decoded, mut empty) = (0, 0);
    for (l, level) in enc.blobs.iter().enumerate() {
        for (i, b) in level.iter().enumerate() {
            let slot = &geom.level(l)[i];
            let valid_cells = slot.mask.as_ref().map_or(n * n, |m| m.valid_cells());
            let Some(bytes) = b else {
                empty += usize::from(valid_cells == 0);
                continue;
            };
            let (ll, ii) = geom.locate(slot.id).unwrap();
            let ctx = blob::BlobContext {
                step: enc.steps[ll],
                ..geom.blob_context(ll, ii)
            };
            let content = blob::decode(bytes, &ctx, &enc.model).unwrap();
            assert_eq!(content.child_classes.len(), slot.owned.len());
            if valid_cells == 0 {
                assert!(content.q.iter().all(|&x| x == 0));
            }
            decoded += 1;
        }
    }
    assert!(
        decoded > 0 && empty > 0,
        "{decoded} blobs, {empty} empty diamonds"
    );
    // A geometry built without that coverage is refused.
    assert!(
        encode::decode_sphere_integers_with(&SphereGeometry::new(face_side, n).unwrap(), &enc)
            .is_err()
    );
}

/// A smooth integer raster with the right half nodata and small voids in the left half.
fn half_raster(w: usize, h: usize) -> (Grid, Vec<usize>) {
    let mut values_m: Vec<f64> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f64, (k / w) as f64);
            // `+ 0.0`: no negative zeros (bit-exact comparisons).
            (300.0 * (x / 17.0).sin() * (y / 23.0).cos() + 0.5 * x + ((k * 7919) % 13) as f64)
                .round()
                + 0.0
        })
        .collect();
    for (k, v) in values_m.iter_mut().enumerate() {
        if k % w >= w / 2 {
            *v = f64::NAN;
        }
    }
    let mut voids = Vec::new();
    let spots = [(20, 30), (70, 100), (40, 170), (100, 60)];
    for (cx, cy) in spots
        .into_iter()
        .filter(|&(x, y)| x + 3 < w / 2 && y + 3 < h)
    {
        for dy in 0..3 {
            for dx in 0..3 {
                let k = (cy + dy) * w + cx + dx;
                values_m[k] = f64::NAN;
                voids.push(k);
            }
        }
    }
    (
        Grid {
            width: w,
            height: h,
            values_m,
            quantum_m: Some(1.0),
        },
        voids,
    )
}

#[test]
fn planar_half_nodata_is_lossless_with_fewer_blobs_and_small_voids_filled() {
    let (w, h, n) = (300, 200, 16);
    let (g, voids) = half_raster(w, h);
    let dense = encode_grid(&g, n, RateMode::Lossless, false);
    let sparse = encode_grid(&g, n, RateMode::Lossless, true);
    let cov = sparse.coverage.as_ref().unwrap();
    let (dn, db) = blob_stats(&dense);
    let (sn, sb) = blob_stats(&sparse);
    println!(
        "planar {w}x{h} half nodata: coverage {}/{} blocks of {}; blobs dense {dn} ({db} B), \
         sparse {sn} ({sb} B)",
        cov.covered_blocks(),
        cov.blocks(),
        cov.block_side()
    );
    assert!(sn < dn && sb < db);
    assert!(sn * 10 < dn * 7, "sparse {sn} vs dense {dn}");
    let dec = encode::decode(&sparse).unwrap();
    let errors = common::errors(&g, &dec);
    assert_eq!((errors.inexact, errors.max_abs_m), (0, 0.0));
    let valid = g.values_m.iter().filter(|v| v.is_finite());
    let lo = valid.clone().copied().fold(f64::INFINITY, f64::min);
    let hi = valid.copied().fold(f64::NEG_INFINITY, f64::max);
    for &k in &voids {
        assert!(
            dec[k].is_finite() && (lo..=hi).contains(&dec[k]),
            "void sample {k}: {}",
            dec[k]
        );
    }
    // Far into the empty half everything is invalid: NaN.
    assert!(dec[100 * w + w - 1].is_nan());
    for mode in [RateMode::MaxErrorM(2.0), RateMode::RmsM(3.0)] {
        let enc = encode_grid(&g, n, mode, true);
        let e = common::errors(&g, &encode::decode(&enc).unwrap());
        match mode {
            RateMode::MaxErrorM(b) => assert!(e.max_abs_m <= b + 1e-9, "{mode:?}: {e:?}"),
            RateMode::RmsM(t) => assert!(e.rms_m <= t, "{mode:?}: {e:?}"),
            RateMode::Lossless => {}
        }
    }
}

#[test]
fn sparse_without_nodata_covers_everything_and_decodes_like_dense() {
    let (mut g, _) = half_raster(130, 97);
    for (k, v) in g.values_m.iter_mut().enumerate() {
        if v.is_nan() {
            *v = (k % 50) as f64;
        }
    }
    let dense = encode_grid(&g, 32, RateMode::Lossless, false);
    let sparse = encode_grid(&g, 32, RateMode::Lossless, true);
    let cov = sparse.coverage.as_ref().unwrap();
    assert_eq!(cov.covered_blocks(), cov.blocks());
    assert_eq!(sparse.blobs, dense.blobs);
    assert_eq!(
        encode::decode(&sparse).unwrap(),
        encode::decode(&dense).unwrap()
    );
}

#[test]
fn coverage_round_trips_and_hostile_bytes_are_errors() {
    let (g, _) = half_raster(300, 200);
    let enc = encode_grid(&g, 16, RateMode::Lossless, true);
    let cov = enc.coverage.unwrap();
    let bytes = cov.to_bytes();
    assert_eq!(Coverage::from_bytes(&bytes).unwrap(), cov);
    // Geometries check the coverage's shape.
    assert!(RasterGeometry::with_coverage(300, 200, 16, &cov).is_ok());
    assert!(RasterGeometry::with_coverage(600, 200, 16, &cov).is_err());
    assert!(SphereGeometry::with_coverage(128, 16, &cov).is_err());
    let planet = Coverage::of_cube(128, 16, |k| k % 3 == 0);
    assert!(SphereGeometry::with_coverage(256, 16, &planet).is_err());
    assert!(RasterGeometry::with_coverage(300, 200, 16, &planet).is_err());
    // Truncations, extensions and byte mutations: Err or a well-formed coverage, no panic.
    for len in 0..bytes.len() {
        assert!(Coverage::from_bytes(&bytes[..len]).is_err());
    }
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    for _ in 0..20_000 {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        let mut b = bytes.clone();
        let at = (seed % b.len().min(24) as u64) as usize;
        b[at] = (seed >> 32) as u8;
        if seed.is_multiple_of(5) {
            b.truncate((seed >> 40) as usize % (b.len() + 1));
        }
        if let Ok(c) = Coverage::from_bytes(&b) {
            assert_eq!(Coverage::from_bytes(&c.to_bytes()).unwrap(), c);
            let _ = RasterGeometry::with_coverage(300, 200, 16, &c);
        }
    }
    for hostile in [
        &[][..],
        &[1, 1, 4, 255, 255, 255, 255, 255, 255, 255, 255][..],
        &[1, 6, 4, 2, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0][..],
        &[1, 1, 200, 1, 0, 0, 0, 1, 0, 0, 0, 0][..],
        &[1, 1, 0, 1, 0, 0, 0, 1, 0, 0, 0, 2][..],
        &[2, 1, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1][..],
    ] {
        assert!(Coverage::from_bytes(hostile).is_err(), "{hostile:?}");
    }
    assert!(Coverage::from_bytes(&[1, 1, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]).is_ok());
}

/// Nearest ETOPO5 sample (4320 x 2161, node-registered, row 0 = 90N, column 0 = 180W).
fn etopo_at(values: &[i16], q: [f64; 3]) -> f64 {
    let lat = q[2].clamp(-1.0, 1.0).asin().to_degrees();
    let lon = q[1].atan2(q[0]).to_degrees();
    let row = ((90.0 - lat) * 12.0).round().clamp(0.0, 2160.0) as usize;
    let col = ((lon + 180.0) * 12.0).round().rem_euclid(4320.0) as usize;
    values[row * 4320 + col] as f64
}

#[test]
fn real_partial_planet_north_america_needs_few_blobs() {
    let Some(path) = common::shared_file(
        "real_partial_planet_north_america_needs_few_blobs",
        "etopo5_global.i16",
    ) else {
        return;
    };
    let bytes = std::fs::read(path).unwrap();
    let values: Vec<i16> = bytes
        .chunks_exact(2)
        .map(|c| i16::from_le_bytes([c[0], c[1]]))
        .collect();
    assert_eq!(values.len(), 4320 * 2161);
    let face_side: usize = std::env::var("QUINCUNX_SPARSE_FACE_SIDE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(512);
    let n = 32;
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let w = face_side + 1;
    let mut values_m = vec![f64::NAN; geom.cube_len()];
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let p = geom.sample_position(face, u, v);
                let q = cube_to_unit_sphere(p.map(|c| c as f64));
                let lat = q[2].clamp(-1.0, 1.0).asin().to_degrees();
                let lon = q[1].atan2(q[0]).to_degrees();
                if (20.0..=60.0).contains(&lat) && (-130.0..=-60.0).contains(&lon) {
                    values_m[geom.cube_index(face, u, v)] = etopo_at(&values, q);
                }
            }
        }
    }
    let g = CubeGrid {
        face_side,
        values_m,
        quantum_m: Some(1.0),
    };
    for mode in [RateMode::Lossless, RateMode::RmsM(10.0)] {
        let dense = encode_planet(&g, n, mode, false);
        let sparse = encode_planet(&g, n, mode, true);
        let cov = sparse.coverage.as_ref().unwrap();
        let (dn, db) = blob_stats(&dense);
        let (sn, sb) = blob_stats(&sparse);
        println!(
            "etopo5 North America, face_side {face_side}, N {n}, {mode:?}: coverage {}/{} \
             blocks of {} samples ({} bytes); blobs dense {dn} ({db} B), sparse {sn} ({sb} B); \
             rms {:.3}/{:.3} m",
            cov.covered_blocks(),
            cov.blocks(),
            cov.block_side(),
            cov.to_bytes().len(),
            dense.report.rms_m,
            sparse.report.rms_m,
        );
        // RMS-mode dense encodings already drop blobs over smooth filled areas: compare
        // blob counts in lossless mode, bytes in both.
        if mode == RateMode::Lossless {
            assert!(sn * 10 < dn * 4, "{sn} vs {dn}");
        }
        assert!(sn < dn && sb < db);
        let (rms, max, _) = planet_errors(&geom, &g.values_m, &encode::decode(&sparse).unwrap());
        match mode {
            RateMode::Lossless => assert_eq!(max, 0.0),
            _ => assert!(rms <= 10.0, "rms {rms}"),
        }
    }
}
