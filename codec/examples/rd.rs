//! Rate/distortion of the codec on a raw grid with a JSON sidecar.
//!
//! ```text
//! cargo run --release -p quincunx-codec --example rd -- <grid.json> [--lossless | --rms-m X | --max-error-m X] [--rdo auto|on|off] [--n 32] [--json]
//! ```
//! Encodes and decodes the grid and prints `samples`, `bits_per_sample`, `rms_m`,
//! `max_abs_m`, `encode_msamples_per_s`, `decode_msamples_per_s` (and whether the
//! rate-distortion quantiser ran, `rdo`; `--rdo` overrides the automatic choice). Decode is entropy
//! decoding plus synthesis of the whole grid to full resolution on one thread, into one
//! output buffer reused by every run (median of `--decode-runs`, default 3).

use std::path::PathBuf;
use std::time::Instant;

use quincunx_codec::encode::{self, EncodeOptions, RateMode, RdoMode};
use quincunx_codec::raster::RasterGeometry;

// The sidecar reader shared with the tests and benches (the codec itself does no I/O).
#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    if let Err(e) = run() {
        eprintln!("rd: {e}");
        std::process::exit(2);
    }
}

fn run() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let mut path = None;
    let mut mode = RateMode::Lossless;
    let mut json = false;
    let mut n = 32;
    let mut decode_runs = 3;
    let mut rdo = RdoMode::Auto;
    while let Some(a) = args.next() {
        let mut num = |name: &str| -> Result<f64, String> {
            args.next()
                .and_then(|v| v.parse().ok())
                .ok_or(format!("{name} needs a number"))
        };
        match a.as_str() {
            "--lossless" => mode = RateMode::Lossless,
            "--rms-m" => mode = RateMode::RmsM(num("--rms-m")?),
            "--max-error-m" => mode = RateMode::MaxErrorM(num("--max-error-m")?),
            "--n" => n = num("--n")? as usize,
            "--decode-runs" => decode_runs = num("--decode-runs")? as usize,
            "--rdo" => {
                rdo = match args.next().as_deref() {
                    Some("auto") => RdoMode::Auto,
                    Some("on") => RdoMode::On,
                    Some("off") => RdoMode::Off,
                    _ => return Err("--rdo needs auto, on or off".into()),
                }
            }
            "--json" => json = true,
            "-h" | "--help" => {
                println!(
                    "usage: rd <grid.json> [--lossless | --rms-m X | --max-error-m X] [--rdo auto|on|off] [--n 32] [--json]"
                );
                return Ok(());
            }
            p if !p.starts_with("--") => path = Some(PathBuf::from(p)),
            other => return Err(format!("unknown option {other}")),
        }
    }
    let path = path.ok_or(
        "usage: rd <grid.json> [--lossless | --rms-m X | --max-error-m X] [--rdo auto|on|off] [--n 32] [--json]",
    )?;
    let grid = common::load_grid(&path)?;
    let t0 = Instant::now();
    let enc = encode::encode(
        &grid,
        EncodeOptions {
            n,
            mode,
            sparse: false,
            rdo,
        },
    )
    .map_err(|e| e.to_string())?;
    let encode_s = t0.elapsed().as_secs_f64();
    // Decode: median of several single-thread runs.
    let mut times = Vec::new();
    let mut decoded = Vec::new();
    for _ in 0..decode_runs.max(1) {
        let t = Instant::now();
        let geom = RasterGeometry::new(enc.width, enc.height, enc.n).map_err(|e| e.to_string())?;
        // Into the same buffer every run, as a client decoding repeatedly would (the
        // first run's page faults are outside the median).
        encode::decode_integers_into(&geom, &enc, &mut decoded).map_err(|e| e.to_string())?;
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let decode_s = times[times.len() / 2];
    // Independent check of the reported errors.
    let (mut sum, mut max, mut count) = (0.0f64, 0.0f64, 0usize);
    for (&d, &v) in decoded.iter().zip(&grid.values_m) {
        if v.is_finite() {
            let e = (enc.value_offset_m + d as f64 * enc.value_scale_m - v).abs();
            sum += e * e;
            max = max.max(e);
            count += 1;
        }
    }
    let rms = (sum / count.max(1) as f64).sqrt();
    let r = &enc.report;
    let samples = r.samples as f64;
    let out = serde_json::json!({
        "grid": path.file_stem().and_then(|s| s.to_str()).unwrap_or(""),
        "mode": match mode { RateMode::Lossless => "lossless".to_string(), RateMode::RmsM(x) => format!("rms-m {x}"), RateMode::MaxErrorM(x) => format!("max-error-m {x}") },
        "n": n,
        "samples": r.samples,
        "valid_samples": r.valid_samples,
        "bits_per_sample": r.bits_per_sample,
        "rms_m": rms,
        "max_abs_m": max,
        "encode_msamples_per_s": samples / encode_s / 1e6,
        "decode_msamples_per_s": samples / decode_s / 1e6,
        "blob_count": r.blob_count,
        "blob_bytes": r.blob_bytes,
        "root_bytes": r.root_bytes,
        "model_bytes": r.model_bytes,
        "rdo": r.rdo,
        "verification_decodes": r.verification_decodes,
        "encode_threads": rayon::current_num_threads(),
    });
    if json {
        println!("{out}");
    } else {
        for (k, v) in out.as_object().into_iter().flatten() {
            println!("{k:>24}: {v}");
        }
    }
    if (rms - r.rms_m).abs() > 1e-9 {
        return Err(format!(
            "decoded RMS {rms} differs from the encoder's report {}",
            r.rms_m
        ));
    }
    Ok(())
}
