//! Encode and decode throughput on real terrain (samples per second).
//!
//! Uses `../shared/data/korea_srtm3_4097` (or `$QUINCUNX_SHARED_DATA`) when present, else
//! the bundled 1025 x 1025 crop. Decode is timed alone: the grid is encoded once outside
//! the measurement and [`encode::decode_integers`] (entropy decoding plus synthesis of the
//! whole grid, one thread) is timed.

#![allow(missing_docs, clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::time::Duration;

use criterion::measurement::WallTime;
use criterion::{
    BenchmarkGroup, BenchmarkId, Criterion, Throughput, criterion_group, criterion_main,
};
use quincunx_codec::encode::{self, EncodeOptions, Grid, RateMode};

#[path = "../tests/common/mod.rs"]
mod common;

const N: usize = 32;

/// The benchmark grid: the shared 4097 x 4097 Korea DEM when present, else the bundled crop.
fn bench_grid() -> (String, Grid) {
    let shared: PathBuf = common::shared_dir().join("korea_srtm3_4097.json");
    let path = if shared.is_file() {
        shared
    } else {
        eprintln!(
            "{} not found: benchmarking the bundled crop instead",
            shared.display()
        );
        common::bundled_korea()
    };
    let name = Path::new(&path)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    (name, common::grid(&path))
}

fn modes() -> [(&'static str, RateMode); 2] {
    [
        ("rms_9m", RateMode::RmsM(9.0)),
        ("lossless", RateMode::Lossless),
    ]
}

/// Few, long samples: one iteration codes the whole grid.
fn configure(group: &mut BenchmarkGroup<'_, WallTime>, samples: u64) {
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(samples));
}

fn codec(c: &mut Criterion) {
    let (name, grid) = bench_grid();
    let samples = (grid.width * grid.height) as u64;

    let mut group = c.benchmark_group(format!("encode/{name}"));
    configure(&mut group, samples);
    for (mode_name, mode) in modes() {
        group.bench_with_input(BenchmarkId::from_parameter(mode_name), &mode, |b, &mode| {
            b.iter(|| {
                encode::encode(
                    &grid,
                    EncodeOptions {
                        n: N,
                        mode,
                        sparse: false,
                        rdo: Default::default(),
                    },
                )
                .unwrap()
            })
        });
    }
    group.finish();

    let mut group = c.benchmark_group(format!("decode/{name}"));
    configure(&mut group, samples);
    for (mode_name, mode) in modes() {
        let enc = encode::encode(
            &grid,
            EncodeOptions {
                n: N,
                mode,
                sparse: false,
                rdo: Default::default(),
            },
        )
        .unwrap();
        group.bench_with_input(BenchmarkId::from_parameter(mode_name), &enc, |b, enc| {
            b.iter(|| encode::decode_integers(enc).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, codec);
criterion_main!(benches);
