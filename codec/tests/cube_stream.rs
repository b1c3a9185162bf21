//! The out-of-core planet encoder ([`encode_cube`]) against the in-memory one: the same
//! bytes where both run (every rate mode, no nodata inside covered blocks), under budgets
//! that make the tile cache evict, and clear errors for what it cannot do.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{
    self, CubeGrid, EncodeError, EncodeOptions, Encoded, RateMode, RdoMode,
};
use quincunx_codec::sphere_raster::SphereGeometry;
use quincunx_codec::stream::{
    BlobSink, CubeEncoded, CubeOptions, CubeSource, MemorySpill, MemoryTiles, TileStore,
    encode_cube,
};

/// A [`CubeGrid`] read a band of rows at a time.
struct GridRows<'a> {
    g: &'a CubeGrid,
    fail_at: Option<usize>,
    reads: usize,
}

impl CubeSource for GridRows<'_> {
    fn face_side(&self) -> usize {
        self.g.face_side
    }

    fn read_face_rows(
        &mut self,
        face: usize,
        first: usize,
        count: usize,
        out: &mut [f64],
    ) -> Result<(), String> {
        self.reads += 1;
        if self.fail_at == Some(self.reads) {
            return Err("disk on fire".into());
        }
        let w = self.g.face_side + 1;
        let start = (face * w + first) * w;
        out.copy_from_slice(&self.g.values_m[start..start + count * w]);
        Ok(())
    }

    fn quantum_m(&self) -> Option<f64> {
        self.g.quantum_m
    }
}

/// Blobs by level and index.
struct Blobs(Vec<Vec<Option<Vec<u8>>>>);

impl BlobSink for Blobs {
    fn put(&mut self, level: usize, index: usize, _key: &[u8], blob: &[u8]) -> Result<(), String> {
        let slot = &mut self.0[level][index];
        if slot.is_some() {
            return Err(format!("blob ({level}, {index}) put twice"));
        }
        *slot = Some(blob.to_vec());
        Ok(())
    }
}

/// An empty sink for a planet of `face_side` coded with `N = n`.
fn blobs_for(face_side: usize, n: usize) -> Blobs {
    let geom = SphereGeometry::new(face_side, n).unwrap();
    Blobs(
        (0..geom.detail_levels())
            .map(|l| vec![None; geom.level(l).len()])
            .collect(),
    )
}

fn in_memory(g: &CubeGrid, n: usize, mode: RateMode, sparse: bool) -> Encoded {
    encode::encode_sphere(
        g,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo: RdoMode::Auto,
        },
    )
    .unwrap()
}

fn out_of_core(
    g: &CubeGrid,
    n: usize,
    mode: RateMode,
    sparse: bool,
    budget: usize,
) -> Result<(CubeEncoded, Encoded), EncodeError> {
    out_of_core_with(g, n, mode, sparse, budget, RdoMode::Auto)
}

fn out_of_core_with(
    g: &CubeGrid,
    n: usize,
    mode: RateMode,
    sparse: bool,
    budget: usize,
    rdo: RdoMode,
) -> Result<(CubeEncoded, Encoded), EncodeError> {
    let mut sink = blobs_for(g.face_side, n);
    let mut src = GridRows {
        g,
        fail_at: None,
        reads: 0,
    };
    let opts = CubeOptions {
        n,
        mode,
        memory_budget_bytes: budget,
        sparse,
        rdo,
        keep_decoded: false,
    };
    let enc = encode_cube(
        &mut src,
        opts,
        &mut sink,
        &mut MemorySpill::default(),
        &mut MemoryTiles::default(),
        &mut |_| {},
    )?;
    Ok((enc.clone(), enc.into_encoded(sink.0)))
}

fn assert_same(a: &Encoded, b: &Encoded, what: &str) {
    assert_eq!(a.value_scale_m, b.value_scale_m, "{what}: scale");
    assert_eq!(a.value_offset_m, b.value_offset_m, "{what}: offset");
    assert_eq!(a.steps, b.steps, "{what}: steps");
    assert_eq!(a.roots, b.roots, "{what}: roots");
    assert_eq!(a.model, b.model, "{what}: model");
    assert_eq!(a.coverage, b.coverage, "{what}: coverage");
    for (l, (x, y)) in a.blobs.iter().zip(&b.blobs).enumerate() {
        assert_eq!(x.len(), y.len(), "{what}: level {l} size");
        for (i, (p, q)) in x.iter().zip(y).enumerate() {
            assert_eq!(p, q, "{what}: blob ({l}, {i})");
        }
    }
    assert_eq!(a.blobs.len(), b.blobs.len(), "{what}: levels");
    assert_eq!(a.report, b.report, "{what}: report");
}

/// The synthetic planet with the non-canonical copies of its edge points disturbed (both
/// encoders must take the lowest face's copy).
fn disturbed_planet(face_side: usize, n: usize) -> CubeGrid {
    let mut g = common::synthetic_planet(face_side, n).unwrap();
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let w = face_side + 1;
    for face in 0..6u8 {
        for v in 0..w {
            for u in [0, w - 1]
                .into_iter()
                .chain(if v == 0 || v == w - 1 { 0..w } else { 0..0 })
            {
                let k = geom.cube_index(face, u, v);
                if !geom.is_canonical(k) {
                    g.values_m[k] += 37.0;
                }
            }
        }
    }
    g
}

#[test]
fn planets_out_of_core_equal_the_in_memory_encoder_byte_for_byte() {
    let (face_side, n) = (256, 16);
    let g = disturbed_planet(face_side, n);
    let mut float = g.clone();
    // Float data of unknown precision (max error only).
    float.quantum_m = None;
    float
        .values_m
        .iter_mut()
        .enumerate()
        .for_each(|(k, v)| *v += (k % 7) as f64 * 0.013);
    let cases = [
        (&g, RateMode::Lossless, "lossless"),
        (&g, RateMode::MaxErrorM(2.0), "max error 2 m"),
        (&float, RateMode::MaxErrorM(0.5), "float, max error 0.5 m"),
        (&g, RateMode::RmsM(3.0), "rms 3 m"),
        (&float, RateMode::RmsM(1.0), "float, rms 1 m"),
    ];
    // 1 MB: tiles of 32 points and a cache of 128 of the 486 tiles of R_0 (evictions);
    // 64 MB: one band a face... of 256 rows, and every tile cached.
    for budget in [1 << 20, 64 << 20] {
        for (grid, mode, what) in cases {
            let want = in_memory(grid, n, mode, false);
            let (facts, got) = out_of_core(grid, n, mode, false, budget).unwrap();
            assert!(
                facts.peak_buffer_bytes <= budget,
                "{what}: peak {} > budget {budget}",
                facts.peak_buffer_bytes
            );
            assert_same(&got, &want, &format!("{what}, budget {budget}"));
            if let RateMode::RmsM(target) = mode {
                let r = &got.report;
                assert!(r.verification_decodes >= 1, "{what}: no decode");
                assert!(
                    r.rms_m <= target && r.rms_m > 0.5 * target,
                    "{what}: rms {}",
                    r.rms_m
                );
            }
        }
    }
    // The rate-distortion quantiser's cost model is trained from the spilled details.
    let (rms, rdo) = (RateMode::RmsM(6.0), RdoMode::On);
    let want = encode::encode_sphere(
        &g,
        EncodeOptions {
            n,
            mode: rms,
            sparse: false,
            rdo,
        },
    )
    .unwrap();
    assert!(want.report.rdo);
    let got = out_of_core_with(&g, n, rms, false, 1 << 20, rdo).unwrap().1;
    assert_same(&got, &want, "rms 6 m, rate-distortion quantiser");
}

/// The synthetic planet with data in a cap around a cube corner only (NaN elsewhere).
fn capped_planet(face_side: usize, n: usize) -> CubeGrid {
    let mut g = common::synthetic_planet(face_side, n).unwrap();
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let w = face_side + 1;
    let c = {
        let d: [f64; 3] = [1.0, 0.9, 0.8];
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.map(|x| x / l)
    };
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let q = cube_to_unit_sphere(geom.sample_position(face, u, v).map(|x| x as f64));
                if q[0] * c[0] + q[1] * c[1] + q[2] * c[2] < 0.8 {
                    g.values_m[geom.cube_index(face, u, v)] = f64::NAN;
                }
            }
        }
    }
    g
}

#[test]
fn sparse_planets_out_of_core_code_no_hole_and_match_in_one_band() {
    let (n, g) = (16, capped_planet(128, 16));
    let mode = RateMode::MaxErrorM(1.0);
    let want = in_memory(&g, n, mode, true);
    // One band holds a face (129 rows <= 256): the fills equal the in-memory encoder's.
    let (_, one_band) = out_of_core(&g, n, mode, true, 64 << 20).unwrap();
    assert_same(&one_band, &want, "sparse, one band a face");
    let rms = RateMode::RmsM(2.0);
    let (_, got) = out_of_core(&g, n, rms, true, 64 << 20).unwrap();
    assert_same(&got, &in_memory(&g, n, rms, true), "sparse, rms 2 m");
    // Bands of 32 rows: the fills of the cap's border may differ, the data may not.
    let (facts, banded) = out_of_core(&g, n, mode, true, 1 << 20).unwrap();
    assert_eq!(banded.coverage, want.coverage);
    assert!(facts.peak_buffer_bytes <= 1 << 20);
    let decoded = encode::decode_sphere_integers(&banded).unwrap();
    let (mut worst, mut counted) = (0.0f64, 0usize);
    for (k, (&v, &d)) in g.values_m.iter().zip(&decoded).enumerate() {
        let _ = k;
        if v.is_finite() {
            let m = banded.value_offset_m + f64::from(d) * banded.value_scale_m;
            worst = worst.max((m - v).abs());
            counted += 1;
        }
    }
    assert!(counted > 0 && worst <= 1.0 + 1e-9, "max error {worst}");
    let coded = |e: &Encoded| e.blobs.iter().flatten().flatten().count();
    assert_eq!(
        coded(&banded),
        coded(&want),
        "the same diamonds carry blobs"
    );
}

#[test]
fn bad_settings_and_failing_sources_are_errors_not_panics() {
    let (face_side, n) = (64, 16);
    let g = common::synthetic_planet(face_side, n).unwrap();
    // The error, never an encoding (whose Debug form would flood the log).
    let refused = |g: &CubeGrid, mode: RateMode, sparse, budget| match out_of_core(
        g, n, mode, sparse, budget,
    ) {
        Ok(_) => panic!("{mode:?} at {budget} bytes was not refused"),
        Err(e) => e,
    };
    let err = refused(&g, RateMode::RmsM(0.0), false, 16 << 20);
    assert!(matches!(err, EncodeError::BadTolerance(_)), "{err}");
    let err = refused(&g, RateMode::Lossless, false, 1000);
    assert!(matches!(err, EncodeError::Budget { .. }), "{err}");
    let err = refused(&g, RateMode::MaxErrorM(-1.0), false, 16 << 20);
    assert!(matches!(err, EncodeError::BadTolerance(_)), "{err}");
    let mut nodata = g.clone();
    nodata.values_m.iter_mut().for_each(|v| *v = f64::NAN);
    let err = refused(&nodata, RateMode::Lossless, true, 16 << 20);
    assert_eq!(err, EncodeError::AllNodata);
    // One band a face (tiles of 128 points): reads 1-6 are pass 0, 7-12 pass 1.
    for fail_at in [1, 4, 9] {
        let mut sink = blobs_for(face_side, n);
        let mut src = GridRows {
            g: &g,
            fail_at: Some(fail_at),
            reads: 0,
        };
        let opts = CubeOptions {
            n,
            mode: RateMode::Lossless,
            memory_budget_bytes: 1 << 20,
            sparse: false,
            rdo: RdoMode::Auto,
            keep_decoded: false,
        };
        let err = encode_cube(
            &mut src,
            opts,
            &mut sink,
            &mut MemorySpill::default(),
            &mut MemoryTiles::default(),
            &mut |_| {},
        )
        .unwrap_err();
        assert_eq!(
            err,
            EncodeError::Source("disk on fire".into()),
            "read {fail_at}"
        );
    }
}

#[test]
fn the_decoded_planet_left_in_the_tiles_is_the_decoders() {
    let (face_side, n) = (128, 16);
    let g = disturbed_planet(face_side, n);
    let w = face_side + 1;
    for mode in [
        RateMode::Lossless,
        RateMode::MaxErrorM(3.0),
        RateMode::RmsM(4.0),
    ] {
        let mut sink = blobs_for(face_side, n);
        let mut src = GridRows {
            g: &g,
            fail_at: None,
            reads: 0,
        };
        let mut tiles = MemoryTiles::default();
        let opts = CubeOptions {
            n,
            mode,
            memory_budget_bytes: 1 << 20,
            sparse: false,
            rdo: RdoMode::Auto,
            keep_decoded: true,
        };
        let enc = encode_cube(
            &mut src,
            opts,
            &mut sink,
            &mut MemorySpill::default(),
            &mut tiles,
            &mut |_| {},
        )
        .unwrap();
        let layout = enc.decoded.expect("decoded tiles");
        let want = encode::decode_sphere_integers(&enc.into_encoded(sink.0)).unwrap();
        // Bands that do not follow the tiles: 50 rows, the last shorter.
        let mut got = vec![0; 6 * w * w];
        for face in 0..6 {
            for first in (0..w).step_by(50) {
                let count = 50.min(w - first);
                let at = (face * w + first) * w;
                layout
                    .read_rows(
                        &mut tiles,
                        (face, first, count),
                        &mut got[at..at + count * w],
                    )
                    .unwrap();
            }
        }
        assert_eq!(got, want, "{mode:?}");
        let tiles_dyn: &mut dyn TileStore = &mut tiles;
        let err = layout.read_rows(tiles_dyn, (6, 0, 1), &mut vec![0; w]);
        assert!(err.is_err());
    }
}
