//! Sharded builds against the single-process out-of-core build: the same blobs, root,
//! model and report for 1, 2, 3 and 7 shards, dense and sparse, lossless and max error,
//! with nodata across shard boundaries; and merges of parts that do not belong together,
//! and damaged parts, are clear errors.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{bundled_korea, grid};
use quincunx_codec::encode::{EncodeError, Grid, RateMode};
use quincunx_codec::stream::{
    BlobSink, IoError, Merge, RowSource, ShardPart, ShardSpec, StreamEncoded, StreamOptions,
    encode_shard, encode_streaming,
};

struct GridSource<'a>(&'a Grid);

impl RowSource for GridSource<'_> {
    fn width(&self) -> usize {
        self.0.width
    }
    fn height(&self) -> usize {
        self.0.height
    }
    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError> {
        let w = self.0.width;
        out.copy_from_slice(&self.0.values_m[first * w..(first + count) * w]);
        Ok(())
    }
    fn quantum_m(&self) -> Option<f64> {
        self.0.quantum_m
    }
}

/// Blobs by `(level, index)`; a second put of one diamond fails the test.
#[derive(Default, PartialEq, Debug)]
struct Blobs(std::collections::BTreeMap<(usize, usize), Vec<u8>>);

impl BlobSink for Blobs {
    fn put(&mut self, level: usize, index: usize, _key: &[u8], blob: &[u8]) -> Result<(), IoError> {
        assert!(
            self.0.insert((level, index), blob.to_vec()).is_none(),
            "blob ({level}, {index}) put twice"
        );
        Ok(())
    }
}

fn opts(mode: RateMode, budget: usize, sparse: bool) -> StreamOptions {
    StreamOptions {
        n: 32,
        mode,
        memory_budget_bytes: budget,
        sparse,
        rdo: Default::default(),
    }
}

/// One shard: its part (through bytes, as a file would carry it) and its details.
fn shard(
    g: &Grid,
    o: StreamOptions,
    k: usize,
    count: usize,
) -> (ShardPart, Vec<(usize, usize, Vec<i32>)>) {
    let mut details = Vec::new();
    let part = encode_shard(
        &mut GridSource(g),
        o,
        ShardSpec { index: k, count },
        b"build A".to_vec(),
        &mut |l, i, h| {
            details.push((l, i, h.to_vec()));
            Ok(())
        },
    )
    .unwrap();
    let back = ShardPart::from_bytes(&part.to_bytes()).unwrap();
    assert_eq!(back, part);
    (back, details)
}

fn sharded(g: &Grid, o: StreamOptions, count: usize) -> (StreamEncoded, Blobs) {
    let (parts, details): (Vec<_>, Vec<_>) = (0..count).map(|k| shard(g, o, k, count)).unzip();
    for p in &parts {
        let f = &p.figures;
        println!(
            "  shard {}/{count}: split {}, band {} rows, window {} rows, analysed {} of which own {}",
            p.index(),
            f.split,
            f.band_rows,
            f.window_rows,
            f.analysed,
            f.owned
        );
    }
    let mut merge = Merge::new(parts).unwrap();
    let mut sink = Blobs::default();
    for d in details.iter().rev() {
        merge.code(d, &mut sink).unwrap();
    }
    (merge.finish(&mut sink).unwrap(), sink)
}

fn single(g: &Grid, o: StreamOptions) -> (StreamEncoded, Blobs) {
    let mut sink = Blobs::default();
    let enc = encode_streaming(&mut GridSource(g), o, &mut sink).unwrap();
    (enc, sink)
}

fn assert_same(a: &(StreamEncoded, Blobs), b: &(StreamEncoded, Blobs), what: &str) {
    assert!(a.1 == b.1, "{what}: blobs differ");
    assert_eq!(a.0.root, b.0.root, "{what}: root");
    assert_eq!(a.0.model.to_bytes(), b.0.model.to_bytes(), "{what}: model");
    assert_eq!(
        a.0.value_scale_m.to_bits(),
        b.0.value_scale_m.to_bits(),
        "{what}"
    );
    assert_eq!(
        a.0.value_offset_m.to_bits(),
        b.0.value_offset_m.to_bits(),
        "{what}"
    );
    assert_eq!(a.0.steps, b.0.steps, "{what}: steps");
    assert_eq!(a.0.coverage, b.0.coverage, "{what}: coverage");
    let (ra, rb) = (&a.0.report, &b.0.report);
    assert_eq!(ra.rms_m.to_bits(), rb.rms_m.to_bits(), "{what}: rms");
    assert_eq!(
        ra.max_abs_m.to_bits(),
        rb.max_abs_m.to_bits(),
        "{what}: max"
    );
    assert_eq!(
        (ra.blob_count, ra.blob_bytes),
        (rb.blob_count, rb.blob_bytes),
        "{what}"
    );
}

/// The bundled korea crop with scattered voids and a tall hole across every shard
/// boundary, so fills cross chunks and shards.
fn korea_with_holes() -> Grid {
    let mut g = grid(&bundled_korea());
    let w = g.width;
    let mut s = 7u64;
    for _ in 0..2000 {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        g.values_m[(s >> 33) as usize % (w * g.height)] = f64::NAN;
    }
    for y in 100..900 {
        for x in 400..430 {
            g.values_m[y * w + x] = f64::NAN;
        }
    }
    g
}

#[test]
fn shards_give_the_single_process_build_byte_for_byte() {
    let g = korea_with_holes();
    let budget = 3_000_000;
    for mode in [RateMode::Lossless, RateMode::MaxErrorM(2.0)] {
        let o = opts(mode, budget, false);
        let one = single(&g, o);
        for count in [1, 2, 3, 7] {
            println!("{mode:?}, {count} shards:");
            let what = format!("{mode:?}, {count} shards");
            assert_same(&sharded(&g, o, count), &one, &what);
        }
    }
}

#[test]
fn sparse_shards_give_the_single_process_build() {
    // A quarter and a band without data: holes in the coverage.
    let mut g = grid(&bundled_korea());
    let (w, h) = (g.width, g.height);
    for y in 0..h {
        for x in 0..w {
            if (x < w / 2 && y < h / 2) || (300..420).contains(&y) {
                g.values_m[y * w + x] = f64::NAN;
            }
        }
    }
    let o = opts(RateMode::MaxErrorM(1.0), 2_000_000, true);
    let one = single(&g, o);
    assert!(one.0.coverage.is_some());
    for count in [2, 3] {
        assert_same(
            &sharded(&g, o, count),
            &one,
            &format!("sparse, {count} shards"),
        );
    }
}

fn shard_error(e: EncodeError) -> String {
    match e {
        EncodeError::Shard(m) => m,
        other => panic!("expected a shard error, got {other}"),
    }
}

#[test]
fn parts_of_other_builds_missing_or_repeated_parts_are_refused() {
    let g = grid(&bundled_korea());
    let o = opts(RateMode::MaxErrorM(2.0), 3_000_000, false);
    let (a0, _) = shard(&g, o, 0, 3);
    let (a1, _) = shard(&g, o, 1, 3);
    let (a2, _) = shard(&g, o, 2, 3);
    // Another rate: another build.
    let (b1, _) = shard(&g, opts(RateMode::MaxErrorM(1.0), 3_000_000, false), 1, 3);
    let e = shard_error(Merge::new(vec![a0.clone(), b1, a2.clone()]).err().unwrap());
    assert!(e.contains("not from the same build"), "{e}");
    let e = shard_error(Merge::new(vec![a0.clone(), a2.clone()]).err().unwrap());
    assert!(e.contains("missing part(s): 1"), "{e}");
    let e = shard_error(
        Merge::new(vec![a0.clone(), a1.clone(), a1.clone()])
            .err()
            .unwrap(),
    );
    assert!(e.contains("given twice"), "{e}");
    // Details that are not the build's, or twice.
    let (_, d0) = shard(&g, o, 0, 3);
    let mut m = Merge::new(vec![a0, a1, a2]).unwrap();
    let mut sink = Blobs::default();
    m.code(&d0[..1], &mut sink).unwrap();
    let e = shard_error(m.code(&d0[..1], &mut sink).err().unwrap());
    assert!(e.contains("come twice"), "{e}");
    let e = shard_error(m.finish(&mut sink).err().unwrap());
    assert!(e.contains("lack diamond"), "{e}");
}

#[test]
fn damaged_parts_and_bad_requests_are_clear_errors() {
    let g = grid(&bundled_korea());
    let o = opts(RateMode::Lossless, 3_000_000, false);
    let (p, _) = shard(&g, o, 1, 2);
    let bytes = p.to_bytes();
    for cut in [0, 7, 8, 100, bytes.len() / 2, bytes.len() - 1] {
        let e = shard_error(ShardPart::from_bytes(&bytes[..cut]).err().unwrap());
        assert!(
            e.contains("truncated") || e.contains("magic"),
            "cut {cut}: {e}"
        );
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(shard_error(ShardPart::from_bytes(&longer).err().unwrap()).contains("trailing"));
    let bad = |o: StreamOptions, k: usize, count: usize| {
        shard_error(
            encode_shard(
                &mut GridSource(&g),
                o,
                ShardSpec { index: k, count },
                Vec::new(),
                &mut |_, _, _| Ok(()),
            )
            .err()
            .unwrap(),
        )
    };
    assert!(bad(o, 2, 2).contains("index runs from 0 to 1"));
    assert!(bad(o, 0, 0).contains("0 shards"));
    assert!(bad(o, 0, 1000).contains("1000 shards"));
    assert!(bad(opts(RateMode::RmsM(9.0), 3_000_000, false), 0, 2).contains("RMS"));
}
