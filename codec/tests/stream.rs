//! The out-of-core encoder against the in-memory one and the standard decoder: lossless and
//! max-error round trips on real and synthetic rasters of awkward sizes with nodata holes,
//! the memory budget, and failures of the source and the sink.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::time::{Duration, Instant};

use common::{bundled_korea, grid, shared_file};
use quincunx_codec::encode::decode_integers;
use quincunx_codec::encode::{EncodeError, EncodeOptions, Grid, RateMode, RdoMode, decode, encode};
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::stream::{
    BlobSink, IndexSpill, IoError, MemorySpill, RowDecode, RowSource, StreamEncoded, StreamOptions,
    decode_rows, encode_streaming, encode_streaming_with,
};

/// An in-memory row source that records the largest request.
struct GridSource<'a> {
    grid: &'a Grid,
    max_rows: usize,
    reads: usize,
    fail_at_row: Option<usize>,
}

impl<'a> GridSource<'a> {
    fn new(grid: &'a Grid) -> Self {
        GridSource {
            grid,
            max_rows: 0,
            reads: 0,
            fail_at_row: None,
        }
    }
}

impl RowSource for GridSource<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError> {
        self.reads += 1;
        self.max_rows = self.max_rows.max(count);
        if self.fail_at_row.is_some_and(|r| first + count > r) {
            return Err(format!("disk on fire at row {first}").into());
        }
        let w = self.grid.width;
        assert_eq!(out.len(), w * count);
        out.copy_from_slice(&self.grid.values_m[first * w..(first + count) * w]);
        Ok(())
    }
    fn quantum_m(&self) -> Option<f64> {
        self.grid.quantum_m
    }
}

/// Collects blobs by level and index; rejects duplicates.
struct Blobs {
    blobs: Vec<Vec<Option<Vec<u8>>>>,
    fail_after: Option<usize>,
    puts: usize,
}

impl Blobs {
    fn new(g: &Grid, n: usize) -> Self {
        let geom = quincunx_codec::raster::RasterGeometry::new(g.width, g.height, n).unwrap();
        Blobs {
            blobs: (0..geom.detail_levels())
                .map(|l| vec![None; geom.level(l).len()])
                .collect(),
            fail_after: None,
            puts: 0,
        }
    }
}

impl BlobSink for Blobs {
    fn put(&mut self, level: usize, index: usize, _key: &[u8], blob: &[u8]) -> Result<(), IoError> {
        if self.fail_after.is_some_and(|k| self.puts >= k) {
            return Err("store is full".into());
        }
        self.puts += 1;
        let slot = &mut self.blobs[level][index];
        assert!(slot.is_none(), "blob ({level}, {index}) put twice");
        *slot = Some(blob.to_vec());
        Ok(())
    }
}

fn stream(g: &Grid, n: usize, mode: RateMode, budget: usize) -> (StreamEncoded, Blobs, usize) {
    stream_with(
        g,
        StreamOptions {
            n,
            mode,
            memory_budget_bytes: budget,
            sparse: false,
            rdo: Default::default(),
        },
    )
}

fn stream_with(g: &Grid, opts: StreamOptions) -> (StreamEncoded, Blobs, usize) {
    let (n, budget) = (opts.n, opts.memory_budget_bytes);
    let mut src = GridSource::new(g);
    let mut sink = Blobs::new(g, n);
    let enc = encode_streaming(&mut src, opts, &mut sink).unwrap();
    assert!(
        src.max_rows * g.width * 8 <= budget,
        "a read of {} rows exceeds the budget",
        src.max_rows
    );
    assert!(
        enc.peak_buffer_bytes <= budget,
        "peak {} > budget {budget}",
        enc.peak_buffer_bytes
    );
    (enc, sink, src.max_rows)
}

/// Largest error over valid samples.
fn max_error(g: &Grid, decoded: &[f64]) -> f64 {
    g.values_m
        .iter()
        .zip(decoded)
        .filter(|(v, _)| v.is_finite())
        .map(|(v, d)| (v - d).abs())
        .fold(0.0, f64::max)
}

fn round_trip(g: &Grid, n: usize, mode: RateMode, budget: usize) -> (StreamEncoded, usize, f64) {
    let (enc, _, max_rows, max) = timed_round_trip(g, n, mode, budget);
    (enc, max_rows, max)
}

/// Streams, decodes with the standard decoder and checks the reported error; also returns
/// the time of the streaming encode alone.
/// The in-memory lossless encode (N = 32) of the same grid, for comparison, and its time.
fn timed_in_memory_lossless(g: &Grid) -> (quincunx_codec::encode::Encoded, Duration) {
    let t = Instant::now();
    let mem = encode(
        g,
        EncodeOptions {
            n: 32,
            mode: RateMode::Lossless,
            sparse: false,
            rdo: Default::default(),
        },
    )
    .unwrap();
    (mem, t.elapsed())
}

fn timed_round_trip(
    g: &Grid,
    n: usize,
    mode: RateMode,
    budget: usize,
) -> (StreamEncoded, std::time::Duration, usize, f64) {
    let t = Instant::now();
    let (enc, sink, max_rows) = stream(g, n, mode, budget);
    let elapsed = t.elapsed();
    let report = enc.report.clone();
    let decoded = decode(&enc.clone().into_encoded(sink.blobs)).unwrap();
    let max = max_error(g, &decoded);
    assert!(
        (report.max_abs_m - max).abs() < 1e-9,
        "reported max {} measured {max}",
        report.max_abs_m
    );
    (enc, elapsed, max_rows, max)
}

/// The smallest budget (in steps of 25 %) the encoder accepts, from `start` bytes.
fn smallest_budget(g: &Grid, n: usize, start: usize) -> usize {
    let mut budget = start;
    loop {
        let mut src = GridSource::new(g);
        let mut sink = Blobs::new(g, n);
        let opts = StreamOptions {
            n,
            mode: RateMode::Lossless,
            memory_budget_bytes: budget,
            sparse: false,
            rdo: Default::default(),
        };
        match encode_streaming(&mut src, opts, &mut sink) {
            Err(EncodeError::Budget { needed, .. }) => {
                assert!(needed > budget);
                budget = budget * 5 / 4;
            }
            Ok(_) => return budget,
            Err(e) => panic!("{e}"),
        }
    }
}

fn synthetic(w: usize, h: usize, seed: u64) -> Grid {
    let values_m = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f64, (k / w) as f64);
            let noise = ((k as u64 ^ seed).wrapping_mul(2654435761) >> 7) % 13;
            (300.0 * (x / 17.0).sin() * (y / 23.0).cos() + 0.5 * x + noise as f64).round()
        })
        .collect();
    Grid {
        width: w,
        height: h,
        values_m,
        quantum_m: Some(1.0),
    }
}

fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *seed >> 33
}

/// Scattered nodata, a few small holes and one tall hole (rows `h/5 .. 4h/5`).
fn with_holes(mut g: Grid, seed: u64) -> Grid {
    let (w, h) = (g.width, g.height);
    if w * h < 4 {
        return g;
    }
    let mut s = seed;
    for _ in 0..(w * h / 50) {
        let k = (lcg(&mut s) as usize) % (w * h);
        g.values_m[k] = f64::NAN;
    }
    for _ in 0..3 {
        let (cx, cy) = (lcg(&mut s) as usize % w, lcg(&mut s) as usize % h);
        for y in cy.saturating_sub(4)..(cy + 4).min(h) {
            for x in cx.saturating_sub(6)..(cx + 6).min(w) {
                g.values_m[y * w + x] = f64::NAN;
            }
        }
    }
    {
        let (x0, x1) = (w / 3, (2 * w / 3).max(w / 3 + 1).min(w));
        for y in h / 5..(4 * h / 5) {
            for x in x0..x1 {
                g.values_m[y * w + x] = f64::NAN;
            }
        }
    }
    g
}

#[test]
fn streaming_without_nodata_matches_the_in_memory_encoder_blob_for_blob() {
    let g = synthetic(300, 200, 1);
    let budget = smallest_budget(&g, 32, 100_000);
    let (enc, sink, _) = stream(&g, 32, RateMode::Lossless, budget);
    let mem = encode(
        &g,
        EncodeOptions {
            n: 32,
            mode: RateMode::Lossless,
            sparse: false,
            rdo: Default::default(),
        },
    )
    .unwrap();
    assert_eq!(enc.root, mem.root);
    assert_eq!(enc.model, mem.model);
    assert_eq!(enc.steps, mem.steps);
    assert_eq!(sink.blobs, mem.blobs);
    assert_eq!(enc.report, mem.report);
}

/// A raster whose right third and a block-sized window in its left part hold no data,
/// plus scattered voids: sparse mode leaves the empty blocks out.
fn with_block_holes(mut g: Grid) -> Grid {
    let (w, h) = (g.width, g.height);
    let mut s = 7;
    for k in 0..w * h {
        let (x, y) = (k % w, k / w);
        let window = (40..110).contains(&x) && (70..150).contains(&y);
        if x >= 2 * w / 3 || window || lcg(&mut s).is_multiple_of(97) {
            g.values_m[k] = f64::NAN;
        }
    }
    g
}

fn sparse_opts(n: usize, mode: RateMode, budget: usize) -> StreamOptions {
    StreamOptions {
        n,
        mode,
        memory_budget_bytes: budget,
        sparse: true,
        rdo: Default::default(),
    }
}

#[test]
fn sparse_streaming_in_one_chunk_matches_the_in_memory_sparse_encoder_blob_for_blob() {
    // A budget that reads the whole raster at once: the same nodata fill as in memory,
    // so every byte must agree, the coverage included.
    let g = with_block_holes(synthetic(300, 200, 3));
    for mode in [RateMode::Lossless, RateMode::MaxErrorM(2.0)] {
        let (enc, sink, max_rows) = stream_with(&g, sparse_opts(32, mode, 64 << 20));
        assert_eq!(max_rows, g.height, "one chunk");
        let mem = encode(
            &g,
            EncodeOptions {
                n: 32,
                mode,
                sparse: true,
                rdo: Default::default(),
            },
        )
        .unwrap();
        let cov = enc.coverage.clone().expect("sparse output has a coverage");
        assert!(
            cov.covered_blocks() < cov.blocks(),
            "{mode:?}: some blocks are holes"
        );
        assert_eq!(enc.coverage, mem.coverage, "{mode:?}");
        assert_eq!(enc.root, mem.root, "{mode:?}");
        assert_eq!(enc.model, mem.model, "{mode:?}");
        assert_eq!(sink.blobs, mem.blobs, "{mode:?}");
        assert_eq!(enc.report, mem.report, "{mode:?}");
    }
}

#[test]
fn sparse_streaming_under_a_small_budget_codes_no_hole_and_round_trips() {
    let g = with_block_holes(synthetic(300, 200, 3));
    let dense_budget = smallest_budget(&g, 32, 100_000);
    let (enc, sink, max_rows) = stream_with(&g, sparse_opts(32, RateMode::Lossless, dense_budget));
    assert!(max_rows < g.height, "several chunks");
    let mem = encode(
        &g,
        EncodeOptions {
            n: 32,
            mode: RateMode::Lossless,
            sparse: true,
            rdo: Default::default(),
        },
    )
    .unwrap();
    // The same coverage, so the same diamonds have blobs; only the fills of voids
    // inside covered blocks may differ (push-pull per chunk).
    assert_eq!(enc.coverage, mem.coverage);
    let has = |b: &Vec<Vec<Option<Vec<u8>>>>| -> Vec<Vec<bool>> {
        b.iter()
            .map(|l| l.iter().map(Option::is_some).collect())
            .collect()
    };
    assert_eq!(has(&sink.blobs), has(&mem.blobs));
    let dense = stream(&g, 32, RateMode::Lossless, dense_budget).0;
    assert!(
        enc.report.blob_count < dense.report.blob_count,
        "sparse {} blobs, dense {}",
        enc.report.blob_count,
        dense.report.blob_count
    );
    let decoded = decode(&enc.clone().into_encoded(sink.blobs)).unwrap();
    assert_eq!(max_error(&g, &decoded), 0.0);
    assert_eq!(enc.report.max_abs_m, 0.0);
    // Voids filled chunk by chunk (here 1 sample in 97, in chunks of a few rows) cost a
    // little more than one fill over the whole raster: 6 % on this small raster.
    let ratio = enc.report.blob_bytes as f64 / mem.report.blob_bytes as f64;
    assert!((0.95..=1.10).contains(&ratio), "bytes ratio {ratio}");
}

#[test]
fn bundled_korea_streams_losslessly_under_a_budget_smaller_than_the_input() {
    let g = grid(&bundled_korea());
    let budget = 2_000_000;
    let (enc, streamed, max_rows, max) = timed_round_trip(&g, 32, RateMode::Lossless, budget);
    assert_eq!(max, 0.0);
    let (mem, in_memory) = timed_in_memory_lossless(&g);
    let r = &enc.report;
    println!(
        "korea_srtm3_1025 lossless: streaming {} blobs {} bytes ({:.3} bits/sample), peak {} bytes \
         of a {budget} budget, reads of {max_rows} rows, {streamed:.2?}; in memory {} blobs {} bytes \
         ({:.3} bits/sample), {in_memory:.2?}",
        r.blob_count,
        r.blob_bytes,
        r.bits_per_sample,
        enc.peak_buffer_bytes,
        mem.report.blob_count,
        mem.report.blob_bytes,
        mem.report.bits_per_sample
    );
    let ratio = r.blob_bytes as f64 / mem.report.blob_bytes as f64;
    assert!((0.97..=1.03).contains(&ratio), "bytes ratio {ratio}");
    let count_ratio = r.blob_count as f64 / mem.report.blob_count as f64;
    assert!(
        (0.97..=1.03).contains(&count_ratio),
        "count ratio {count_ratio}"
    );
    assert_eq!(r.valid_samples, mem.report.valid_samples);
}

#[test]
fn bundled_korea_max_error_streams_within_the_bound() {
    let g = grid(&bundled_korea());
    for e in [1.0, 4.0] {
        let (enc, _, max) = round_trip(&g, 32, RateMode::MaxErrorM(e), 2_000_000);
        println!(
            "korea_srtm3_1025 max-error {e} m: max {max} m, rms {:.3} m, {:.3} bits/sample",
            enc.report.rms_m, enc.report.bits_per_sample
        );
        assert!(max <= e + 1e-9, "e={e} max={max}");
    }
}

#[test]
fn odd_sizes_with_holes_round_trip_losslessly_on_valid_samples() {
    for (w, h, n) in [
        (300, 200, 32),
        (1000, 37, 32),
        (37, 1000, 32),
        (37, 1000, 8),
        (1, 1, 32),
        (33, 33, 32),
        (65, 66, 32),
        (129, 200, 16),
    ] {
        let g = with_holes(synthetic(w, h, w as u64 * 31 + h as u64), 7 + w as u64);
        let budget = smallest_budget(&g, n, 20_000);
        let (enc, max_rows, max) = round_trip(&g, n, RateMode::Lossless, budget);
        println!(
            "{w}x{h} N={n}: budget {budget}, peak {}, reads of {max_rows} rows",
            enc.peak_buffer_bytes
        );
        assert_eq!(max, 0.0, "{w}x{h} N={n}");
        if h >= 200 {
            // The tall hole spans several chunks.
            assert!(
                3 * h / 5 > 2 * max_rows,
                "{w}x{h}: chunks of {max_rows} rows"
            );
        }
    }
}

#[test]
fn odd_sizes_meet_a_max_error_bound() {
    for (w, h) in [(300, 200), (37, 1000)] {
        let g = with_holes(synthetic(w, h, 3), 5);
        for e in [0.5, 2.5] {
            let (_, _, max) = round_trip(&g, 32, RateMode::MaxErrorM(e), 1_000_000);
            assert!(max <= e + 1e-9, "{w}x{h} e={e} max={max}");
        }
    }
}

#[test]
fn float_data_off_any_grid_is_refused_losslessly_and_bounded_in_max_error() {
    let mut g = synthetic(90, 70, 9);
    for (k, v) in g.values_m.iter_mut().enumerate() {
        *v += (k as f64 * 0.7548776662).fract() * 0.37;
    }
    g.quantum_m = None;
    let mut sink = Blobs::new(&g, 32);
    let err = encode_streaming(
        &mut GridSource::new(&g),
        StreamOptions {
            n: 32,
            mode: RateMode::Lossless,
            memory_budget_bytes: 1 << 20,
            sparse: false,
            rdo: Default::default(),
        },
        &mut sink,
    )
    .unwrap_err();
    assert_eq!(err, EncodeError::NotOnGrid);
    let (_, _, max) = round_trip(&g, 32, RateMode::MaxErrorM(0.25), 1 << 20);
    assert!(max <= 0.25 + 1e-9, "max={max}");
}

#[test]
fn a_failing_source_or_sink_is_an_error_not_a_panic() {
    let g = synthetic(300, 200, 2);
    let opts = StreamOptions {
        n: 32,
        mode: RateMode::Lossless,
        memory_budget_bytes: 1_000_000,
        sparse: false,
        rdo: Default::default(),
    };
    for fail_at_row in [1, 100, 199] {
        let mut src = GridSource::new(&g);
        src.fail_at_row = Some(fail_at_row);
        let err = encode_streaming(&mut src, opts, &mut Blobs::new(&g, 32)).unwrap_err();
        assert!(
            matches!(err, EncodeError::Source(ref m) if m.to_string().contains("disk on fire")),
            "{err}"
        );
    }
    let mut sink = Blobs::new(&g, 32);
    sink.fail_after = Some(5);
    let err = encode_streaming(&mut GridSource::new(&g), opts, &mut sink).unwrap_err();
    assert_eq!(err, EncodeError::writing("store is full".into()));
    // The sink's error is the cause, not part of the message.
    assert_eq!(err.to_string(), "writing blobs");
    let cause = std::error::Error::source(&err).map(ToString::to_string);
    assert_eq!(cause.as_deref(), Some("store is full"));
}

#[test]
fn bad_tolerances_and_tiny_budgets_are_refused_clearly() {
    let g = synthetic(100, 100, 4);
    let run = |mode, budget| {
        encode_streaming(
            &mut GridSource::new(&g),
            StreamOptions {
                n: 32,
                mode,
                memory_budget_bytes: budget,
                sparse: false,
                rdo: Default::default(),
            },
            &mut Blobs::new(&g, 32),
        )
    };
    assert!(matches!(
        run(RateMode::RmsM(-1.0), 1 << 20),
        Err(EncodeError::BadTolerance(_))
    ));
    assert!(matches!(
        run(RateMode::Lossless, 1000),
        Err(EncodeError::Budget { .. })
    ));
    assert!(matches!(
        run(RateMode::MaxErrorM(-1.0), 1 << 20),
        Err(EncodeError::BadTolerance(_))
    ));
    let nodata = Grid {
        values_m: vec![f64::NAN; 100 * 100],
        ..g.clone()
    };
    let err = encode_streaming(
        &mut GridSource::new(&nodata),
        StreamOptions {
            n: 32,
            mode: RateMode::Lossless,
            memory_budget_bytes: 1 << 20,
            sparse: false,
            rdo: Default::default(),
        },
        &mut Blobs::new(&g, 32),
    )
    .unwrap_err();
    assert_eq!(err, EncodeError::AllNodata);
}

#[test]
fn shared_korea_4097_streams_losslessly_in_bounded_memory() {
    let test = "shared_korea_4097_streams_losslessly_in_bounded_memory";
    let Some(path) = shared_file(test, "korea_srtm3_4097.json") else {
        return;
    };
    let g = grid(&path);
    let budget = 8_000_000;
    let (enc, streamed, max_rows, max) = timed_round_trip(&g, 32, RateMode::Lossless, budget);
    assert_eq!(max, 0.0);
    let (mem, in_memory) = timed_in_memory_lossless(&g);
    println!(
        "korea_srtm3_4097 lossless: streaming {} blobs {} bytes, peak {} bytes of a {budget} \
         budget (input {} bytes as f64), reads of {max_rows} rows, {streamed:.2?}; in memory {} blobs {} bytes, {in_memory:.2?}",
        enc.report.blob_count,
        enc.report.blob_bytes,
        enc.peak_buffer_bytes,
        g.values_m.len() * 8,
        mem.report.blob_count,
        mem.report.blob_bytes,
    );
    let ratio = enc.report.blob_bytes as f64 / mem.report.blob_bytes as f64;
    assert!((0.97..=1.03).contains(&ratio), "bytes ratio {ratio}");
}

/// Decodes `enc` a band of rows at a time and compares with the in-memory decoder.
fn rows_match_the_in_memory_decode(enc: &quincunx_codec::encode::Encoded, what: &str) {
    let geom = match &enc.coverage {
        Some(c) => RasterGeometry::with_coverage(enc.width, enc.height, enc.n, c),
        None => RasterGeometry::new(enc.width, enc.height, enc.n),
    }
    .unwrap();
    let want = decode_integers(enc).unwrap();
    let mut got = Vec::with_capacity(want.len());
    let mut next = 0;
    decode_rows(
        RowDecode {
            geom: &geom,
            root: &enc.root,
            steps: &enc.steps,
            model: &enc.model,
        },
        &|l, i| Ok(enc.blobs[l][i].clone()),
        &mut |row, values| {
            assert_eq!(row, next, "{what}: rows in order");
            assert_eq!(values.len(), enc.width);
            next += 1;
            got.extend_from_slice(values);
            Ok(())
        },
    )
    .unwrap();
    assert_eq!(next, enc.height, "{what}: every row");
    let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
    assert_eq!(diff, 0, "{what}: {diff} samples differ");
}

#[test]
fn rows_decoded_out_of_core_equal_the_in_memory_decode_bit_for_bit() {
    let korea = grid(&bundled_korea());
    let cases: Vec<(&str, Grid, RateMode, bool)> = vec![
        ("korea RMS 2", korea.clone(), RateMode::RmsM(2.0), false),
        ("korea RMS 9", korea.clone(), RateMode::RmsM(9.0), false),
        ("korea lossless", korea, RateMode::Lossless, false),
        (
            "300x200 holes, RMS 1",
            with_holes(synthetic(300, 200, 5), 9),
            RateMode::RmsM(1.0),
            false,
        ),
        (
            "300x200 sparse, max 1",
            with_block_holes(synthetic(300, 200, 3)),
            RateMode::MaxErrorM(1.0),
            true,
        ),
        (
            "37x1000 RMS 3",
            synthetic(37, 1000, 2),
            RateMode::RmsM(3.0),
            false,
        ),
        (
            "129x65 RMS 0.5",
            synthetic(129, 65, 4),
            RateMode::RmsM(0.5),
            false,
        ),
        (
            "2x2 lossless",
            synthetic(2, 2, 4),
            RateMode::Lossless,
            false,
        ),
    ];
    for (what, g, mode, sparse) in cases {
        let enc = encode(
            &g,
            EncodeOptions {
                n: 32,
                mode,
                sparse,
                rdo: Default::default(),
            },
        )
        .unwrap();
        rows_match_the_in_memory_decode(&enc, what);
    }
}

/// Streams at an RMS target and checks the output against the in-memory encoder's.
fn rms_matches_in_memory(g: &Grid, target: f64, budget: usize, rdo: RdoMode, what: &str) {
    let (enc, sink, max_rows) = stream_with(
        g,
        StreamOptions {
            n: 32,
            mode: RateMode::RmsM(target),
            memory_budget_bytes: budget,
            sparse: false,
            rdo,
        },
    );
    let mem = encode(
        g,
        EncodeOptions {
            n: 32,
            mode: RateMode::RmsM(target),
            sparse: false,
            rdo,
        },
    )
    .unwrap();
    println!(
        "{what}: {} rows a read, {} decodes, rdo {}, rms {:.4}, {:.4} bits/sample, peak {} bytes",
        max_rows,
        enc.report.verification_decodes,
        enc.report.rdo,
        enc.report.rms_m,
        enc.report.bits_per_sample,
        enc.peak_buffer_bytes
    );
    assert!(enc.report.rms_m <= target, "{what}");
    assert_eq!(enc.steps, mem.steps, "{what}");
    assert_eq!(enc.root, mem.root, "{what}");
    assert_eq!(enc.model, mem.model, "{what}");
    assert_eq!(sink.blobs, mem.blobs, "{what}");
    assert_eq!(enc.report, mem.report, "{what}");
    let decoded = decode(&enc.clone().into_encoded(sink.blobs)).unwrap();
    let (mut sum, mut count) = (0.0, 0);
    for (v, d) in g.values_m.iter().zip(&decoded) {
        if v.is_finite() {
            sum += (v - d) * (v - d);
            count += 1;
        }
    }
    let rms = (sum / count as f64).sqrt();
    assert!(
        (rms - enc.report.rms_m).abs() < 1e-9,
        "{what}: decoded rms {rms}"
    );
}

#[test]
fn rms_mode_streams_to_the_in_memory_encoders_bytes() {
    // Several chunks and no nodata: every byte must agree (the search, the
    // rate-distortion quantiser, the side information and the model).
    let g = synthetic(300, 200, 11);
    let budget = smallest_budget(&g, 32, 100_000);
    for (target, rdo) in [
        (2.0, RdoMode::Auto),
        (8.0, RdoMode::Auto),
        (8.0, RdoMode::On),
        (0.6, RdoMode::Off),
    ] {
        rms_matches_in_memory(
            &g,
            target,
            budget,
            rdo,
            &format!("300x200 rms {target} {rdo:?}"),
        );
    }
    let korea = grid(&bundled_korea());
    rms_matches_in_memory(
        &korea,
        2.0,
        64 << 20,
        RdoMode::Auto,
        "korea_srtm3_1025 rms 2, one chunk",
    );
    rms_matches_in_memory(
        &korea,
        9.0,
        64 << 20,
        RdoMode::Auto,
        "korea_srtm3_1025 rms 9, one chunk",
    );
}

/// A spill whose reads or writes fail.
struct BrokenSpill {
    inner: MemorySpill,
    fail_reads: bool,
}

impl IndexSpill for BrokenSpill {
    fn clear(&mut self, slot: usize) -> Result<(), IoError> {
        self.inner.clear(slot)
    }
    fn append(&mut self, slot: usize, bytes: &[u8]) -> Result<u64, IoError> {
        if self.fail_reads {
            self.inner.append(slot, bytes)
        } else {
            Err("disk full".into())
        }
    }
    fn read(&self, slot: usize, offset: u64, len: usize) -> Result<Vec<u8>, IoError> {
        if self.fail_reads {
            Err("bad sector".into())
        } else {
            self.inner.read(slot, offset, len)
        }
    }
    fn held(&self) -> usize {
        0
    }
}

#[test]
fn a_failing_index_spill_is_an_error_not_a_panic() {
    let g = synthetic(300, 200, 11);
    for fail_reads in [true, false] {
        let mut spill = BrokenSpill {
            inner: MemorySpill::default(),
            fail_reads,
        };
        let err = encode_streaming_with(
            &mut GridSource::new(&g),
            StreamOptions {
                n: 32,
                mode: RateMode::RmsM(2.0),
                memory_budget_bytes: 1 << 20,
                sparse: false,
                rdo: RdoMode::Auto,
            },
            &mut Blobs::new(&g, 32),
            &mut spill,
        )
        .unwrap_err();
        // The spill's error is the cause, with what was being done.
        let mut err_chain = err.to_string();
        let mut cause = std::error::Error::source(&err);
        while let Some(c) = cause {
            err_chain = format!("{err_chain}: {c}");
            cause = c.source();
        }
        let err = err_chain;
        let want = if fail_reads {
            "bad sector"
        } else {
            "disk full"
        };
        assert!(err.contains(want), "{err}");
    }
}
