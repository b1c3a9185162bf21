//! The codec on real terrain, through the public API only: lossless round trips, the rate
//! modes' promises measured on a real decode, blob decoding of hostile bytes, and golden
//! blobs that freeze the format.
//!
//! The bundled crop (`data/korea_srtm3_1025`) is always used; the shared datasets
//! (`$QUINCUNX_SHARED_DATA` or `../shared/data`) are used when present and skipped with a
//! `SKIP` line otherwise.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use proptest::prelude::*;
use quincunx_codec::blob::{self, BlobContext, DecodeError};
use quincunx_codec::encode::{self, EncodeOptions, Encoded, Grid, RateMode, RdoMode};
use quincunx_codec::entropy::{self, CodecModel};
use quincunx_codec::raster::RasterGeometry;

use common::{Errors, bundled_korea, errors, grid, shared_dir, shared_file};

const N: usize = 32;

fn encode_grid(g: &Grid, mode: RateMode) -> Encoded {
    encode_grid_with(g, mode, RdoMode::Auto)
}

fn encode_grid_with(g: &Grid, mode: RateMode, rdo: RdoMode) -> Encoded {
    encode::encode(
        g,
        EncodeOptions {
            n: N,
            mode,
            sparse: false,
            rdo,
        },
    )
    .unwrap_or_else(|e| panic!("encode {mode:?} failed: {e}"))
}

fn round_trip(g: &Grid, mode: RateMode) -> (Encoded, Errors) {
    let enc = encode_grid(g, mode);
    let decoded = encode::decode(&enc).expect("decoding what was just encoded");
    let err = errors(g, &decoded);
    (enc, err)
}

fn assert_lossless(name: &str, g: &Grid) {
    let (enc, err) = round_trip(g, RateMode::Lossless);
    println!(
        "{name}: lossless, {} valid samples, {:.3} bits/sample",
        err.valid, enc.report.bits_per_sample
    );
    assert!(err.valid > 0, "{name}: no valid samples");
    assert_eq!(
        err.inexact, 0,
        "{name}: {} of {} valid samples differ after a lossless round trip (max error {} m)",
        err.inexact, err.valid, err.max_abs_m
    );
    assert_eq!(
        enc.report.max_abs_m, 0.0,
        "{name}: encoder reports an error"
    );
}

#[test]
fn bundled_korea_crop_round_trips_bit_exactly() {
    assert_lossless("korea_srtm3_1025", &grid(&bundled_korea()));
}

#[test]
fn shared_korea_4097_round_trips_bit_exactly() {
    let test = "shared_korea_4097_round_trips_bit_exactly";
    let Some(path) = shared_file(test, "korea_srtm3_4097.json") else {
        return;
    };
    assert_lossless("korea_srtm3_4097", &grid(&path));
}

#[test]
fn shared_etopo5_round_trips_bit_exactly() {
    let test = "shared_etopo5_round_trips_bit_exactly";
    let Some(path) = shared_file(test, "etopo5_global.json") else {
        return;
    };
    assert_lossless("etopo5_global", &grid(&path));
}

/// Sidecars of the shared height grids (those with a `dtype`; image sidecars have none).
fn shared_height_grids() -> Vec<(String, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(shared_dir()) else {
        return Vec::new();
    };
    let mut out: Vec<(String, PathBuf)> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .filter(|p| {
            std::fs::read_to_string(p)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .is_some_and(|meta| meta.get("dtype").is_some())
        })
        .map(|p| {
            let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
            (stem, p)
        })
        .collect();
    out.sort();
    out
}

#[test]
fn max_error_mode_meets_its_bound_on_every_shared_grid() {
    let test = "max_error_mode_meets_its_bound_on_every_shared_grid";
    let grids = shared_height_grids();
    if grids.is_empty() {
        common::skip_without_shared_data(
            test,
            &format!("no height grids in {}", shared_dir().display()),
        );
        return;
    }
    let mut failures = Vec::new();
    for (name, path) in &grids {
        let g = grid(path);
        let tolerances: &[f64] = if name.starts_with("fixture_") {
            &[1.0, 0.5]
        } else {
            &[1.0]
        };
        for &tol in tolerances {
            let (enc, err) = round_trip(&g, RateMode::MaxErrorM(tol));
            println!(
                "{name}: max-error {tol} m -> measured max {:.6} m, rms {:.4} m, {:.3} bits/sample",
                err.max_abs_m, err.rms_m, enc.report.bits_per_sample
            );
            if err.max_abs_m > tol {
                failures.push(format!(
                    "{name}: requested max error {tol} m, measured {} m",
                    err.max_abs_m
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn rms_mode_meets_its_target_on_the_bundled_crop() {
    let g = grid(&bundled_korea());
    for target in [9.0, 1.0] {
        let (enc, err) = round_trip(&g, RateMode::RmsM(target));
        println!(
            "korea_srtm3_1025: rms {target} m -> measured rms {:.4} m, max {:.2} m, {:.3} bits/sample",
            err.rms_m, err.max_abs_m, enc.report.bits_per_sample
        );
        assert!(
            err.rms_m <= target,
            "rms target {target} m, measured {} m",
            err.rms_m
        );
    }
}

/// The rate-distortion quantiser on real terrain: at each RMS target, on and off both
/// meet it, and on costs fewer bits wherever the automatic choice turns it on.
#[test]
fn rate_distortion_quantisation_lowers_the_rate_at_the_same_rms() {
    let g = grid(&bundled_korea());
    for target in [9.0, 3.0, 1.0] {
        let run = |rdo| {
            let enc = encode_grid_with(&g, RateMode::RmsM(target), rdo);
            let err = errors(&g, &encode::decode(&enc).unwrap());
            assert!(
                err.rms_m <= target,
                "{rdo:?} at {target} m: rms {}",
                err.rms_m
            );
            enc.report
        };
        let (off, on, auto) = (run(RdoMode::Off), run(RdoMode::On), run(RdoMode::Auto));
        println!(
            "korea_srtm3_1025 rms {target} m: {:.4} bits/sample plain, {:.4} rate-distortion \
             ({:+.2} %), auto chose {}",
            off.bits_per_sample,
            on.bits_per_sample,
            100.0 * (on.bits_per_sample / off.bits_per_sample - 1.0),
            if auto.rdo { "it" } else { "plain" }
        );
        assert!(!off.rdo && on.rdo);
        if auto.rdo {
            assert!(
                on.bits_per_sample < 0.99 * off.bits_per_sample,
                "at {target} m: {} against {}",
                on.bits_per_sample,
                off.bits_per_sample
            );
        }
    }
}

// ---------------------------------------------------------------------------------------
// Hostile bytes.

/// A real masked (border) diamond of the bundled crop's hierarchy, for decoding contexts.
fn border_slot() -> (Vec<u8>, quincunx_codec::lifting::DiamondMask) {
    let geom = RasterGeometry::new(1025, 1025, N).unwrap();
    let last = geom.detail_levels() - 1;
    let s = geom
        .level(last)
        .iter()
        .find(|s| s.mask.is_some())
        .expect("a border diamond");
    (s.key.clone(), s.mask.clone().unwrap())
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 2000,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::WithSource("proptest-regressions"),
        )),
        ..ProptestConfig::default()
    })]

    /// Arbitrary bytes never panic the blob decoder: as they come (almost always a
    /// checksum error), and with a valid header and checksum patched in, so that the
    /// entropy decoder itself sees the garbage.
    #[test]
    fn blob_decoding_of_arbitrary_bytes_never_panics(
        bytes in proptest::collection::vec(any::<u8>(), 0..200),
        key in proptest::collection::vec(any::<u8>(), 1..12),
        group in 0..entropy::GROUPS,
        owned_children in 0usize..=4,
        masked in any::<bool>(),
        quantised in any::<bool>(),
    ) {
        let model = CodecModel::default();
        let (border_key, border_mask) = border_slot_cached();
        let ctx = BlobContext {
            key: if masked { border_key } else { &key },
            n: N,
            group,
            mask: masked.then_some(border_mask),
            owned_children,
            step: if quantised { 512 } else { 256 },
        };
        let _ = blob::decode(&bytes, &ctx, &model);

        let mut patched = bytes.clone();
        if patched.len() >= blob::HEADER_BYTES {
            patched[0] = (blob::VERSION << 4) | N.trailing_zeros() as u8;
            let crc = blob::crc16(&[ctx.key, &patched[..1], &patched[blob::HEADER_BYTES..]]);
            patched[1..3].copy_from_slice(&crc.to_le_bytes());
            if let Ok(content) = blob::decode(&patched, &ctx, &model) {
                prop_assert_eq!(content.q.len(), N * N);
                prop_assert_eq!(content.child_classes.len(), owned_children);
            }
        }
    }
}

fn border_slot_cached() -> (&'static [u8], &'static quincunx_codec::lifting::DiamondMask) {
    static SLOT: std::sync::OnceLock<(Vec<u8>, quincunx_codec::lifting::DiamondMask)> =
        std::sync::OnceLock::new();
    let (k, m) = SLOT.get_or_init(border_slot);
    (k, m)
}

/// Every blob of an encoding with its decoding context.
fn blobs_with_contexts(enc: &Encoded) -> Vec<(usize, usize, Vec<u8>)> {
    enc.blobs
        .iter()
        .enumerate()
        .flat_map(|(l, level)| {
            level
                .iter()
                .enumerate()
                .filter_map(move |(i, b)| b.clone().map(|b| (l, i, b)))
        })
        .collect()
}

#[test]
fn bit_flips_of_real_blobs_are_detected_or_decoded_without_panic() {
    let g = grid(&bundled_korea());
    let enc = encode_grid(&g, RateMode::RmsM(2.0));
    let geom = RasterGeometry::new(enc.width, enc.height, enc.n).unwrap();
    let all = blobs_with_contexts(&enc);
    assert!(!all.is_empty());
    // A spread of blobs: every 40th, which covers all levels and some border diamonds.
    let picked: Vec<_> = all.iter().step_by(40).collect();
    let (mut flips, mut patched_ok, mut masked) = (0usize, 0usize, 0usize);
    for (l, i, bytes) in picked {
        masked += usize::from(geom.level(*l)[*i].mask.is_some());
        let ctx = BlobContext {
            step: enc.steps[*l],
            ..geom.blob_context(*l, *i)
        };
        assert!(
            blob::decode(bytes, &ctx, &enc.model).is_ok(),
            "unmodified blob {l}_{i} must decode"
        );
        for bit in 0..bytes.len() * 8 {
            let mut b = bytes.clone();
            b[bit / 8] ^= 1 << (bit % 8);
            flips += 1;
            // CRC-16 detects every single-bit error.
            let r = blob::decode(&b, &ctx, &enc.model);
            assert!(
                matches!(
                    r,
                    Err(DecodeError::Checksum { .. }
                        | DecodeError::Version(_)
                        | DecodeError::Size { .. })
                ),
                "blob {l}_{i}, bit {bit}: a single bit flip was not detected: {r:?}"
            );
            // With the checksum patched the payload reaches the entropy decoder: any
            // result is fine, a panic is not.
            if bit >= 8 * blob::HEADER_BYTES {
                let crc = blob::crc16(&[ctx.key, &b[..1], &b[blob::HEADER_BYTES..]]);
                b[1..3].copy_from_slice(&crc.to_le_bytes());
                patched_ok += usize::from(blob::decode(&b, &ctx, &enc.model).is_ok());
            }
        }
        // Truncations too.
        for len in 0..bytes.len() {
            let _ = blob::decode(&bytes[..len], &ctx, &enc.model);
        }
    }
    println!(
        "{flips} single-bit flips all detected; {patched_ok} decoded after patching the checksum; {masked} border blobs among those tested"
    );
}

// ---------------------------------------------------------------------------------------
// Golden blobs.

/// A fixed, platform-independent synthetic terrain (integer arithmetic only).
fn golden_grid() -> Grid {
    let (w, h) = (65usize, 65usize);
    let values_m = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as i64, (k / w) as i64);
            let hill = 900 - ((x - 40) * (x - 40) + (y - 24) * (y - 24)) / 3;
            let ridge = 12 * ((x + 2 * y) % 17 - 8).abs();
            let noise = ((x * 73_856_093) ^ (y * 19_349_663)).rem_euclid(7);
            (hill.max(50) + ridge + noise) as f64
        })
        .collect();
    Grid {
        width: w,
        height: h,
        values_m,
        quantum_m: Some(1.0),
    }
}

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

/// Every file that freezes one encoding: blobs, model, root grid and parameters.
fn golden_files(enc: &Encoded, mode: &str) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<(String, Vec<u8>)> = blobs_with_contexts(enc)
        .into_iter()
        .map(|(l, i, b)| (format!("{l}_{i}.bin"), b))
        .collect();
    files.push(("model.bin".into(), enc.model.to_bytes()));
    files.push(("root.bin".into(), encode::root_grid_bytes(&enc.root)));
    let steps = serde_json::json!({
        "mode": mode,
        "width": enc.width,
        "height": enc.height,
        "n": enc.n,
        "blob_version": blob::UNPROFILED_VERSION,
        "value_scale_m": enc.value_scale_m,
        "value_offset_m": enc.value_offset_m,
        "steps": enc.steps,
    });
    let mut text = serde_json::to_string_pretty(&steps).unwrap();
    text.push('\n');
    files.push(("steps.json".into(), text.into_bytes()));
    files
}

/// Version 4 blobs (the same layout; their side-information classes were the largest
/// departure of any one level, not the sum) still decode: each to the detail matrix the
/// version 5 encoder codes for it, with classes never above version 5's.
#[test]
fn version_4_golden_blobs_still_decode() {
    let g = golden_grid();
    let enc = encode_grid_with(&g, RateMode::RmsM(2.0), RdoMode::Off);
    let geom = RasterGeometry::new(enc.width, enc.height, enc.n).unwrap();
    let dir = golden_dir().join("v4_rms_2m");
    let old_model = CodecModel::from_bytes(&std::fs::read(dir.join("model.bin")).unwrap()).unwrap();
    let mut checked = 0;
    for (l, i, bytes) in blobs_with_contexts(&enc) {
        let old = std::fs::read(dir.join(format!("{l}_{i}.bin"))).unwrap();
        assert_eq!(old[0] >> 4, 4, "{l}_{i}.bin is a version 4 blob");
        assert_eq!(bytes[0] >> 4, blob::UNPROFILED_VERSION);
        let ctx = BlobContext {
            step: enc.steps[l],
            ..geom.blob_context(l, i)
        };
        let old = blob::decode(&old, &ctx, &old_model).unwrap();
        let new = blob::decode(&bytes, &ctx, &enc.model).unwrap();
        assert_eq!(old.q, new.q, "{l}_{i}");
        assert_eq!(old.child_classes.len(), new.child_classes.len());
        for (a, b) in old.child_classes.iter().zip(&new.child_classes) {
            let ((a, _), (b, _)) = (entropy::split_side(*a), entropy::split_side(*b));
            assert!(a <= b, "{l}_{i}: version 4 class {a} above version 5's {b}");
        }
        checked += 1;
    }
    assert!(checked >= 4, "{checked} blobs compared");
}

#[test]
fn golden_blobs_are_unchanged() {
    let bless = std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1");
    let g = golden_grid();
    let mut problems = Vec::new();
    // The plain quantiser and the rate-distortion one each have their own golden files.
    for (mode_name, mode, rdo) in [
        ("lossless", RateMode::Lossless, RdoMode::Auto),
        ("rms_2m", RateMode::RmsM(2.0), RdoMode::Off),
        ("rms_2m_rdo", RateMode::RmsM(2.0), RdoMode::On),
    ] {
        let enc = encode_grid_with(&g, mode, rdo);
        assert_eq!(enc.report.rdo, rdo == RdoMode::On, "{mode_name}");
        // The frozen encoding must also be right, or we would freeze a bug.
        let err = errors(&g, &encode::decode(&enc).unwrap());
        match mode {
            RateMode::Lossless => assert_eq!(err.inexact, 0),
            _ => assert!(err.rms_m <= 2.0, "rms {}", err.rms_m),
        }
        let dir = golden_dir().join(mode_name);
        let files = golden_files(&enc, mode_name);
        if bless {
            std::fs::create_dir_all(&dir).unwrap();
            for entry in std::fs::read_dir(&dir).unwrap() {
                std::fs::remove_file(entry.unwrap().path()).unwrap();
            }
            for (name, bytes) in &files {
                std::fs::write(dir.join(name), bytes).unwrap();
            }
            println!("blessed {} files in {}", files.len(), dir.display());
            continue;
        }
        let on_disk: BTreeSet<String> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e} (bless with QUINCUNX_BLESS=1)", dir.display()))
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        let expected: BTreeSet<String> = files.iter().map(|(n, _)| n.clone()).collect();
        for name in on_disk.symmetric_difference(&expected) {
            let what = if expected.contains(name) {
                "is produced but not committed"
            } else {
                "is committed but no longer produced"
            };
            problems.push(format!("{mode_name}/{name} {what}"));
        }
        for (name, bytes) in &files {
            let Ok(golden) = std::fs::read(dir.join(name)) else {
                continue;
            };
            if &golden != bytes {
                let first = golden
                    .iter()
                    .zip(bytes)
                    .position(|(a, b)| a != b)
                    .unwrap_or(golden.len().min(bytes.len()));
                problems.push(format!(
                    "{mode_name}/{name}: {} bytes committed, {} produced, first difference at byte {first}",
                    golden.len(),
                    bytes.len()
                ));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "the encoder no longer reproduces the golden files in {}:\n  {}\n\
         Changing the blob format means bumping blob::VERSION (the encoder writes {}) and updating \
         docs/blob-format.md; then re-bless with `QUINCUNX_BLESS=1 cargo test -p quincunx-codec \
         --release --test real_data golden`.",
        golden_dir().display(),
        problems.join("\n  "),
        blob::UNPROFILED_VERSION
    );
}
