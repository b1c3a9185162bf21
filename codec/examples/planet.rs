//! Encode/decode timing and rate of a synthetic planet (the shared `synthetic_planet`).
//!
//! ```text
//! cargo run --release -p quincunx-codec --example planet -- [face_side] [n] [--rms-m X | --max-error-m X]
//! ```
//! Prints distinct samples, bits per sample, errors, encode time (all cores) and decode
//! time (entropy decoding + synthesis to full resolution, one thread).

use std::time::Instant;

use quincunx_codec::encode::{self, EncodeOptions, RateMode};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    if let Err(e) = run() {
        eprintln!("planet: {e}");
        std::process::exit(2);
    }
}

fn run() -> Result<(), String> {
    let mut numbers = Vec::new();
    let mut mode = RateMode::Lossless;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || -> Result<f64, String> {
            args.next()
                .and_then(|v| v.parse().ok())
                .ok_or(format!("{a} needs a number"))
        };
        match a.as_str() {
            "--rms-m" => mode = RateMode::RmsM(value()?),
            "--max-error-m" => mode = RateMode::MaxErrorM(value()?),
            _ => numbers.push(a.parse::<usize>().map_err(|e| format!("{a}: {e}"))?),
        }
    }
    let face_side = numbers.first().copied().unwrap_or(1024);
    let n = numbers.get(1).copied().unwrap_or(32);
    let grid = common::synthetic_planet(face_side, n)?;
    let t0 = Instant::now();
    let enc = encode::encode_sphere(
        &grid,
        EncodeOptions {
            n,
            mode,
            sparse: false,
            rdo: Default::default(),
        },
    )
    .map_err(|e| e.to_string())?;
    let encode_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let dec = encode::decode(&enc).map_err(|e| e.to_string())?;
    let decode_s = t1.elapsed().as_secs_f64();
    let exact = dec == grid.values_m;
    let r = &enc.report;
    println!(
        "face_side {face_side} N {n} {mode:?}: {} distinct samples ({} stored), {} blobs, {:.3} bits/sample, rms {:.3} m, max {:.3} m, bit-exact {exact}",
        r.samples,
        grid.values_m.len(),
        r.blob_count,
        r.bits_per_sample,
        r.rms_m,
        r.max_abs_m
    );
    println!(
        "encode {encode_s:.2} s ({:.1} MS/s), decode {decode_s:.2} s ({:.1} MS/s, one thread)",
        r.samples as f64 / encode_s / 1e6,
        r.samples as f64 / decode_s / 1e6
    );
    Ok(())
}
