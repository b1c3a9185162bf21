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
    BlobSink, CubeEncoded, CubeMerge, CubeOptions, CubeSource, IoError, MemorySpill, MemoryTiles,
    ShardPart, ShardSpec, TileStore, encode_cube, encode_cube_shard,
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
    ) -> Result<(), IoError> {
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
    fn put(&mut self, level: usize, index: usize, _key: &[u8], blob: &[u8]) -> Result<(), IoError> {
        let slot = &mut self.0[level][index];
        if slot.is_some() {
            return Err(format!("blob ({level}, {index}) put twice").into());
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
            EncodeError::reading("disk on fire".into()),
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

/// Details of a shard's diamonds, as `(level, index, details)`.
type Details = Vec<(usize, usize, Vec<i32>)>;

/// Shard `k` of `count` of a planet (its part through its bytes, and its details).
fn shard(
    g: &CubeGrid,
    opts: CubeOptions,
    (k, count): (usize, usize),
    extra: &[u8],
) -> Result<(ShardPart, Details), EncodeError> {
    let mut details = Vec::new();
    let mut src = GridRows {
        g,
        fail_at: None,
        reads: 0,
    };
    let part = encode_cube_shard(
        &mut src,
        opts,
        ShardSpec { index: k, count },
        extra.to_vec(),
        &mut |l, i, h| {
            details.push((l, i, h.to_vec()));
            Ok(())
        },
        (&mut MemorySpill::default(), &mut MemoryTiles::default()),
    )?;
    let part = ShardPart::from_bytes(&part.to_bytes())?;
    assert_eq!(part.figures.split, part.figures.split.max(1));
    Ok((part, details))
}

/// Merges `parts` and their details (added in batches of 50).
fn merge(
    parts: Vec<ShardPart>,
    details: &[Details],
    face_side: usize,
    n: usize,
) -> Result<Encoded, EncodeError> {
    let (mut spill, mut tiles) = (MemorySpill::default(), MemoryTiles::default());
    let mut merge = CubeMerge::new(parts, &mut spill, &mut tiles)?;
    for d in details {
        for batch in d.chunks(50) {
            merge.add(batch, &mut spill)?;
        }
    }
    let mut sink = blobs_for(face_side, n);
    let enc = merge.finish(&mut sink, &mut spill, &mut tiles)?;
    Ok(enc.into_encoded(sink.0))
}

fn cube_opts(n: usize, mode: RateMode, sparse: bool, budget: usize) -> CubeOptions {
    CubeOptions {
        n,
        mode,
        memory_budget_bytes: budget,
        sparse,
        rdo: RdoMode::Auto,
        keep_decoded: false,
    }
}

/// The disturbed planet with voids: scattered samples (everywhere, or in a few rows of
/// face 3 only) and a hole across the edges of faces 0 and 1.
fn holed_planet(face_side: usize, n: usize, scattered: bool) -> CubeGrid {
    let mut g = disturbed_planet(face_side, n);
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let w = face_side + 1;
    for k in (0..g.values_m.len()).step_by(997) {
        let (face, v) = (k / (w * w), (k / w) % w);
        if scattered || face == 3 && (100..140).contains(&v) {
            g.values_m[k] = f64::NAN;
        }
    }
    for face in [0u8, 1] {
        for v in w / 2 - 9..w / 2 + 9 {
            for u in 0..w {
                if u < 12 || u + 12 >= w {
                    g.values_m[geom.cube_index(face, u, v)] = f64::NAN;
                }
            }
        }
    }
    g
}

#[test]
fn sharded_planets_equal_the_single_out_of_core_build() {
    let (face_side, n) = (256, 16);
    let scattered = holed_planet(face_side, n, true);
    let local = holed_planet(face_side, n, false);
    // 1 MB: tiles of 32 points, evictions; 64 MB: one band a face. Voids everywhere make
    // every shard's integer pass run from the start of each face it needs; local ones let
    // it start where the rows before hold no nodata.
    let mut partial_runs = 0;
    for (g, mode, budget, counts) in [
        (
            &scattered,
            RateMode::MaxErrorM(2.0),
            1 << 20,
            &[1, 2, 3, 7][..],
        ),
        (&scattered, RateMode::Lossless, 1 << 20, &[3][..]),
        (&scattered, RateMode::MaxErrorM(2.0), 64 << 20, &[2][..]),
        (&local, RateMode::MaxErrorM(2.0), 1 << 20, &[2, 3, 7][..]),
    ] {
        let opts = cube_opts(n, mode, false, budget);
        let (_, want) = out_of_core(g, n, mode, false, budget).unwrap();
        for &count in counts {
            let what = format!("{mode:?}, budget {budget}, {count} shards");
            let (mut parts, mut details) = (Vec::new(), Vec::new());
            for k in (0..count).rev() {
                let (p, d) = shard(g, opts, (k, count), b"build").unwrap();
                assert!(p.figures.owned > 0, "{what}: shard {k} owns nothing");
                assert!(p.figures.integer_rows <= 6 * (face_side + 1));
                if p.figures.integer_rows < 6 * (face_side + 1) {
                    partial_runs += 1;
                }
                if count > 1 {
                    assert!(
                        p.figures.analysed < want.blobs.iter().map(Vec::len).sum::<usize>(),
                        "{what}: shard {k} analysed everything"
                    );
                }
                parts.push(p);
                details.push(d);
            }
            let got = merge(parts, &details, face_side, n).unwrap();
            assert_same(&got, &want, &what);
        }
    }
    assert!(
        partial_runs >= 6,
        "{partial_runs} shards skipped integer rows"
    );
    // Sparse: a cap around a cube corner.
    let (n, g) = (16, capped_planet(128, 16));
    let mode = RateMode::MaxErrorM(1.0);
    let (_, want) = out_of_core(&g, n, mode, true, 1 << 20).unwrap();
    for count in [2, 3] {
        let opts = cube_opts(n, mode, true, 1 << 20);
        let (parts, details): (Vec<_>, Vec<_>) = (0..count)
            .map(|k| shard(&g, opts, (k, count), b"sparse").unwrap())
            .unzip();
        let got = merge(parts, &details, 128, n).unwrap();
        assert_same(&got, &want, &format!("sparse, {count} shards"));
    }
}

#[test]
fn planet_merges_refuse_parts_that_do_not_make_one_build() {
    let (face_side, n) = (128, 16);
    let g = disturbed_planet(face_side, n);
    let opts = cube_opts(n, RateMode::MaxErrorM(2.0), false, 1 << 20);
    let (a0, d0) = shard(&g, opts, (0, 3), b"x").unwrap();
    let (a1, d1) = shard(&g, opts, (1, 3), b"x").unwrap();
    let (a2, d2) = shard(&g, opts, (2, 3), b"x").unwrap();
    let err = |r: Result<Encoded, EncodeError>| r.err().map(|e| e.to_string()).unwrap_or_default();
    // Missing, repeated, from another build.
    let e = err(merge(vec![a0.clone(), a2.clone()], &[], face_side, n));
    assert!(e.contains("missing part(s): 1"), "{e}");
    let e = err(merge(
        vec![a0.clone(), a1.clone(), a1.clone()],
        &[],
        face_side,
        n,
    ));
    assert!(e.contains("given twice"), "{e}");
    let other = cube_opts(n, RateMode::MaxErrorM(3.0), false, 1 << 20);
    let (b1, _) = shard(&g, other, (1, 3), b"x").unwrap();
    let e = err(merge(vec![a0.clone(), b1, a2.clone()], &[], face_side, n));
    assert!(e.contains("not from the same build"), "{e}");
    // Details missing, repeated, or not the build's.
    let parts = || vec![a0.clone(), a1.clone(), a2.clone()];
    let e = err(merge(parts(), &[d0.clone(), d1.clone()], face_side, n));
    assert!(e.contains("lack diamond"), "{e}");
    let e = err(merge(
        parts(),
        &[d0.clone(), d1.clone(), d2.clone(), d1.clone()],
        face_side,
        n,
    ));
    assert!(e.contains("come twice"), "{e}");
    let mut bad = d2.clone();
    bad[0].2.push(1);
    let e = err(merge(parts(), &[d0.clone(), d1.clone(), bad], face_side, n));
    assert!(e.contains("do not belong"), "{e}");
    // The whole set merges; truncated bytes are an error.
    assert!(merge(parts(), &[d0, d1, d2], face_side, n).is_ok());
    let bytes = a1.to_bytes();
    let e = ShardPart::from_bytes(&bytes[..bytes.len() - 3])
        .unwrap_err()
        .to_string();
    assert!(e.contains("truncated"), "{e}");
    // RMS and bad requests are refused before any work.
    let rms = cube_opts(n, RateMode::RmsM(3.0), false, 1 << 20);
    let e = shard(&g, rms, (0, 2), b"x").unwrap_err().to_string();
    assert!(e.contains("--lossless or --max-error-m"), "{e}");
    let e = shard(&g, opts, (2, 2), b"x").unwrap_err().to_string();
    assert!(e.contains("shard 2 of 2"), "{e}");
    let e = shard(&g, opts, (0, 100), b"x").unwrap_err().to_string();
    assert!(e.contains("100 shards"), "{e}");
}
