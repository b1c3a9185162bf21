//! End-to-end tests of the `quincunx` binary: build -> verify for every input format and
//! rate mode, colour, export, interrupted builds and bad input.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_quincunx"))
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn shared_data(test: &str, name: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("QUINCUNX_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    let p = dir.join(name);
    if p.exists() {
        Some(p)
    } else {
        quincunx_testkit::skip::skip(
            test,
            "REQUIRE_SHARED_DATA",
            &format!("{} not found", p.display()),
        );
        None
    }
}

fn run(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("run quincunx");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    out
}

fn ok_json(cmd: &mut Command) -> serde_json::Value {
    let out = run(cmd);
    assert!(
        out.status.success(),
        "failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("bad JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

/// `quincunx verify <repo> --source <source> --json`.
fn verify_json(repo: &Path, source: &Path) -> serde_json::Value {
    ok_json(
        bin()
            .arg("verify")
            .arg(repo)
            .arg("--source")
            .arg(source)
            .arg("--json"),
    )
}

fn build_and_verify(
    input: &Path,
    rate: &[&str],
    extra: &[&str],
) -> (serde_json::Value, serde_json::Value) {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("repo");
    let built = ok_json(
        bin()
            .arg("build")
            .arg(input)
            .arg("-o")
            .arg(&repo)
            .args(rate)
            .args(extra)
            .arg("--json"),
    );
    let verified = verify_json(&repo, input);
    assert_eq!(verified["blob_errors"], 0);
    assert_eq!(verified["content_hash_ok"], true);
    assert!(verified["blobs_checked"].as_u64().unwrap() > 0);
    assert_eq!(built["samples"], verified["samples"]);
    let (b, v) = (
        built["bits_per_sample"].as_f64().unwrap(),
        verified["bits_per_sample"].as_f64().unwrap(),
    );
    assert!(
        (b - v).abs() < 1e-9,
        "build says {b} bits/sample, verify {v}"
    );
    (built, verified)
}

fn check_bound(verified: &serde_json::Value, rate: &[&str]) {
    let rms = verified["rms_m"].as_f64().unwrap();
    let max = verified["max_abs_m"].as_f64().unwrap();
    match rate {
        ["--lossless"] => assert_eq!(max, 0.0),
        ["--rms-m", t] => assert!(rms <= t.parse::<f64>().unwrap() + 1e-9, "rms {rms} > {t}"),
        ["--max-error-m", e] => {
            assert!(max <= e.parse::<f64>().unwrap() + 1e-9, "max {max} > {e}")
        }
        _ => unreachable!(),
    }
}

const RATES: [&[&str]; 3] = [
    &["--lossless"],
    &["--rms-m", "2"],
    &["--max-error-m", "1.5"],
];

#[test]
fn every_input_format_builds_and_verifies_within_every_rate_mode() {
    for input in [
        "jacksboro.json",
        "jacksboro_stripped_i16.tif",
        "jacksboro_tiled_f32.tif",
        "jacksboro_u16.png",
    ] {
        for rate in RATES {
            let (built, verified) = build_and_verify(&fixture(input), rate, &[]);
            check_bound(&verified, rate);
            assert!(built["seconds"].as_f64().unwrap() > 0.0);
            assert!(built["peak_rss_mb"].as_f64().unwrap() > 0.0);
            assert_eq!(built["kind"], "elevation", "{input}");
        }
    }
}

#[test]
fn srtm_hgt_tiles_build_and_verify() {
    // A real-sized SRTM3 tile (1201 x 1201, big-endian) made from the bundled SRTM crop.
    let dir = tempfile::tempdir().unwrap();
    let src =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.i16"))
            .unwrap();
    let mut hgt = Vec::with_capacity(1201 * 1201 * 2);
    for row in 0..1201 {
        for col in 0..1201 {
            let (r, c) = (row % 1025, col % 1025);
            let v = i16::from_le_bytes([src[(r * 1025 + c) * 2], src[(r * 1025 + c) * 2 + 1]]);
            hgt.extend_from_slice(&v.to_be_bytes());
        }
    }
    let path = dir.path().join("N37E127.hgt");
    std::fs::write(&path, hgt).unwrap();
    for rate in [&["--lossless"][..], &["--max-error-m", "4"]] {
        let (built, verified) = build_and_verify(&path, rate, &[]);
        check_bound(&verified, rate);
        assert_eq!(built["samples"], 1201 * 1201);
    }
}

#[test]
fn colour_imagery_builds_within_the_requested_rgb_error() {
    let (_, lossless) = build_and_verify(
        &fixture("gsi_color_256.jpg"),
        &["--lossless"],
        &["--colour"],
    );
    assert_eq!(lossless["max_abs_m"], 0.0);
    let (lossy, bounded) = build_and_verify(
        &fixture("gsi_color_256.jpg"),
        &["--max-error-m", "8"],
        &["--colour"],
    );
    assert!(bounded["max_abs_m"].as_f64().unwrap() <= 8.0);
    assert!(lossy["bits_per_sample"].as_f64().unwrap() < 24.0);
    assert_eq!(lossy["kind"], "colour");
}

#[test]
fn info_and_export_describe_every_blob() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("jb");
    ok_json(
        bin()
            .args(["build", "--max-error-m", "1", "--json", "-o"])
            .arg(&repo)
            .arg(fixture("jacksboro.json")),
    );
    let info = ok_json(bin().arg("info").arg(&repo).arg("--json"));
    let blobs = info["blob_count"].as_u64().unwrap();
    assert!(blobs > 0);
    let hash = info["metadata"]["content_hash"]
        .as_str()
        .unwrap()
        .to_string();
    let out = dir.path().join("www");
    let status = run(bin().arg("export").arg(&repo).arg(&out));
    assert!(status.status.success());
    let base = out.join("repos/jb");
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(base.join("metadata.json")).unwrap()).unwrap();
    assert_eq!(meta["content_hash"], hash.as_str());
    let mut files = 0;
    let mut stack = vec![base.join("v").join(&hash[..16]).join("d")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(d).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                stack.push(e.path());
            } else {
                files += 1;
            }
        }
    }
    assert_eq!(files, blobs);
}

#[test]
fn a_killed_build_leaves_nothing_that_opens_and_a_rerun_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("repo");
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let mut child = bin()
        .args([
            "build",
            "--max-error-m",
            "2",
            "--stall-after-blobs",
            "100",
            "-o",
        ])
        .arg(&repo)
        .arg(&input)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let partial = dir.path().join("repo.partial");
    let marker = dir.path().join("repo.partial").join("repository.pack");
    for _ in 0..600 {
        if marker.exists() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    std::thread::sleep(std::time::Duration::from_millis(300));
    assert!(
        child.try_wait().unwrap().is_none(),
        "build ended before it was killed"
    );
    child.kill().unwrap(); // SIGKILL: no cleanup runs
    child.wait().unwrap();
    assert!(partial.exists());
    assert!(!repo.exists());
    for path in [&repo, &partial] {
        let out = run(bin().arg("info").arg(path));
        assert!(!out.status.success(), "{} opened", path.display());
        assert_eq!(out.status.code(), Some(1));
    }
    let out = run(bin().arg("verify").arg(&partial));
    assert!(String::from_utf8_lossy(&out.stderr).contains("not a complete repository"));
    let built = ok_json(
        bin()
            .args(["build", "--max-error-m", "2", "--json", "-o"])
            .arg(&repo)
            .arg(&input),
    );
    assert!(built["blob_count"].as_u64().unwrap() > 100);
    assert!(!partial.exists());
    let verified = ok_json(bin().arg("verify").arg(&repo).arg("--json"));
    assert_eq!(verified["blob_errors"], 0);
}

fn expect_failure(args: &[&str], inputs: &[&Path], needle: &str) {
    let dir = tempfile::tempdir().unwrap();
    let out = run(bin()
        .args(args)
        .args(inputs)
        .arg("-o")
        .arg(dir.path().join("repo")));
    let stderr = String::from_utf8_lossy(&out.stderr).to_lowercase();
    assert_eq!(out.status.code(), Some(1), "{args:?} {inputs:?}: {stderr}");
    assert!(
        stderr.contains(&needle.to_lowercase()),
        "{args:?} {inputs:?}: expected {needle:?} in {stderr}"
    );
    assert!(!dir.path().join("repo").exists());
}

#[test]
fn bad_input_is_a_clear_error_never_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Each raw case lives in its own folder: the sidecar names its data file.
    let case = |name: &str, data: &[u8], sidecar: &str| {
        let dir = d.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("jacksboro.i16"), data).unwrap();
        std::fs::write(dir.join("jacksboro.f32"), data).unwrap();
        std::fs::write(dir.join("jacksboro.json"), sidecar).unwrap();
        dir.join("jacksboro.json")
    };
    let raw = std::fs::read(fixture("jacksboro.i16")).unwrap();
    let sidecar = std::fs::read_to_string(fixture("jacksboro.json")).unwrap();
    // Truncated raw grid.
    let short = case("short", &raw[..raw.len() / 2], &sidecar);
    expect_failure(&["build"], &[&short], "bytes");
    // Sidecar whose dimensions do not match.
    let mut wrong: serde_json::Value = serde_json::from_str(&sidecar).unwrap();
    wrong["width"] = serde_json::json!(wrong["width"].as_u64().unwrap() + 1);
    let wrong = case("wrong", &raw, &wrong.to_string());
    expect_failure(&["build"], &[&wrong], "bytes");
    // NaN everywhere.
    let mut nan: serde_json::Value = serde_json::from_str(&sidecar).unwrap();
    nan["dtype"] = serde_json::json!("float32");
    nan["nodata"] = serde_json::json!("NaN");
    let nan_bytes: Vec<u8> = (0..raw.len() / 2)
        .flat_map(|_| f32::NAN.to_le_bytes())
        .collect();
    let nan = case("nan", &nan_bytes, &nan.to_string());
    expect_failure(&["build"], &[&nan], "no valid samples");
    // Truncated TIFF and a TIFF layout we do not read.
    let tif = std::fs::read(fixture("jacksboro_stripped_i16.tif")).unwrap();
    std::fs::write(d.join("cut.tif"), &tif[..tif.len() / 3]).unwrap();
    expect_failure(&["build"], &[&d.join("cut.tif")], "tif");
    let mut rgb_tif = std::io::Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut rgb_tif)
        .unwrap()
        .write_image::<tiff::encoder::colortype::RGB8>(4, 4, &[9u8; 48])
        .unwrap();
    std::fs::write(d.join("rgb.tif"), rgb_tif.into_inner()).unwrap();
    expect_failure(&["build"], &[&d.join("rgb.tif")], "bands");
    // Empty and truncated images.
    std::fs::write(d.join("empty.png"), b"").unwrap();
    expect_failure(&["build"], &[&d.join("empty.png")], "png");
    let jpg = std::fs::read(fixture("gsi_color_256.jpg")).unwrap();
    std::fs::write(d.join("cut.jpg"), &jpg[..jpg.len() / 4]).unwrap();
    expect_failure(&["build", "--colour"], &[&d.join("cut.jpg")], "jp");
    // Unknown format, missing file, bad options.
    std::fs::write(d.join("x.bmp"), b"BM").unwrap();
    expect_failure(&["build"], &[&d.join("x.bmp")], "bmp");
    expect_failure(&["build"], &[&d.join("missing.tif")], "missing.tif");
    expect_failure(
        &["build", "--diamond-size", "32"],
        &[&fixture("jacksboro.json")],
        "2^k + 1",
    );
    expect_failure(
        &["build", "--rms-m=-1"],
        &[&fixture("jacksboro.json")],
        "positive",
    );
    expect_failure(
        &["build", "--memory-budget-mb", "1"],
        &[&Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json")],
        "out-of-core",
    );
}

#[test]
fn korea_at_rms_9m_meets_its_error_target() {
    let Some(input) = shared_data(
        "korea_at_rms_9m_meets_its_error_target",
        "korea_srtm3_4097.json",
    ) else {
        return;
    };
    let (built, verified) = build_and_verify(&input, &["--rms-m", "9"], &[]);
    check_bound(&verified, &["--rms-m", "9"]);
    println!("korea rms 9: build {built}\nverify {verified}");
}

#[test]
fn rdo_is_chosen_by_the_option_and_recorded() {
    // The bundled korea crop at 3 m: `auto` and `on` run the rate-distortion quantiser
    // (few nonzero indices), `off` rounds; all meet the target, and the quantiser codes
    // fewer bits.
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let rate = ["--rms-m", "3"];
    let mut bits = Vec::new();
    for (choice, expect) in [("auto", true), ("on", true), ("off", false)] {
        let (built, verified) = build_and_verify(&input, &rate, &["--rdo", choice]);
        check_bound(&verified, &rate);
        assert_eq!(built["rdo"], expect, "--rdo {choice}");
        bits.push(built["bits_per_sample"].as_f64().unwrap());
    }
    assert_eq!(bits[0], bits[1]);
    assert!(
        bits[1] < 0.99 * bits[2],
        "rdo {} against rounding {}",
        bits[1],
        bits[2]
    );
    // Lossless ignores it.
    let (built, _) = build_and_verify(&input, &["--lossless"], &["--rdo", "on"]);
    assert_eq!(built["rdo"], false);
    assert_eq!(built["source_samples"], built["samples"]);
}

fn query(repo: &Path, points: &[(f64, f64)]) -> Vec<f64> {
    let mut cmd = bin();
    cmd.arg("query").arg(repo).arg("--json");
    for (lat, lon) in points {
        cmd.arg("--at").arg(format!("{lat},{lon}"));
    }
    let v = ok_json(&mut cmd);
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| p["values"][0].as_f64().unwrap_or(f64::NAN))
        .collect()
}

fn check_planet(repo: &Path, everest_min: f64, trench_max: f64) {
    let everest = (27.988, 86.925);
    let mariana = (11.35, 142.2);
    let h = query(
        repo,
        &[
            everest,
            mariana,
            (90.0, 0.0),
            (90.0, 123.0),
            (-90.0, 0.0),
            (-90.0, -77.0),
            (0.0, 180.0),
            (0.0, -180.0),
            (45.0, 45.0),
        ],
    );
    assert!(
        h[0] > everest_min && h[0] < 8849.0,
        "Everest area: {}",
        h[0]
    );
    assert!(
        h[1] < trench_max && h[1] > -11035.0,
        "Mariana trench: {}",
        h[1]
    );
    assert_eq!(h[2], h[3], "north pole depends on longitude");
    assert_eq!(h[4], h[5], "south pole depends on longitude");
    assert!(
        (-4500.0..-3500.0).contains(&h[2]),
        "north pole is Arctic ocean floor: {}",
        h[2]
    );
    assert!(
        (2000.0..3500.0).contains(&h[4]),
        "south pole is the ice sheet: {}",
        h[4]
    );
    assert!(
        (h[6] - h[7]).abs() < 1e-6,
        "antimeridian seam: {} vs {}",
        h[6],
        h[7]
    );
}

#[test]
fn bundled_planet_builds_without_seams_and_answers_point_queries() {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/etopo20_global.json");
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("earth");
    let built = ok_json(
        bin()
            .args(["build", "--planet", "--max-error-m", "2", "--json", "-o"])
            .arg(&repo)
            .arg(&input),
    );
    assert_eq!(
        built["samples"],
        6 * 256 * 256 + 2,
        "face side follows the 20' source"
    );
    let verified = verify_json(&repo, &input);
    assert_eq!(verified["seam_mismatches"], 0);
    assert_eq!(verified["blob_errors"], 0);
    assert!(verified["max_abs_m"].as_f64().unwrap() <= 2.0);
    let info = ok_json(bin().arg("info").arg(&repo).arg("--json"));
    assert_eq!(info["metadata"]["domain"], "sphere");
    assert_eq!(info["metadata"]["radius_m"], 6_371_000.0);
    check_planet(&repo, 4000.0, -6000.0);
    // Mars radius from the body name.
    let mars = dir.path().join("mars");
    ok_json(
        bin()
            .args([
                "build",
                "--planet",
                "--body",
                "mars",
                "--face-side",
                "64",
                "--json",
                "-o",
            ])
            .arg(&mars)
            .arg(&input),
    );
    let info = ok_json(bin().arg("info").arg(&mars).arg("--json"));
    assert_eq!(info["metadata"]["radius_m"], 3_396_000.0);
}

#[test]
fn etopo5_planet_is_lossless_and_seamless() {
    let Some(input) = shared_data(
        "etopo5_planet_is_lossless_and_seamless",
        "etopo5_global.json",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("earth");
    let built = ok_json(
        bin()
            .args(["build", "--planet", "--lossless", "--json", "-o"])
            .arg(&repo)
            .arg(&input),
    );
    let verified = verify_json(&repo, &input);
    println!("etopo5 planet: build {built}\nverify {verified}");
    assert_eq!(verified["seam_mismatches"], 0);
    assert_eq!(verified["max_abs_m"], 0.0);
    check_planet(&repo, 5000.0, -8000.0);
}

#[test]
fn blue_marble_colour_planet_is_within_the_requested_error() {
    let Some(input) = shared_data(
        "blue_marble_colour_planet_is_within_the_requested_error",
        "bmng_global_5400x2700.jpg",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("bmng");
    ok_json(
        bin()
            .args([
                "build",
                "--planet",
                "--colour",
                "--max-error-m",
                "8",
                "--json",
                "-o",
            ])
            .arg(&repo)
            .arg(&input),
    );
    let verified = verify_json(&repo, &input);
    assert_eq!(verified["seam_mismatches"], 0);
    assert!(verified["max_abs_m"].as_f64().unwrap() <= 8.0);
    let info = ok_json(bin().arg("info").arg(&repo).arg("--json"));
    assert_eq!(info["metadata"]["attribute"]["kind"], "colour");
    assert_eq!(info["metadata"]["channels"].as_array().unwrap().len(), 3);
}

#[test]
fn out_of_core_build_of_the_bundled_crop_is_lossless_within_its_budget() {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("ooc");
    let built = ok_json(
        bin()
            .args([
                "build",
                "--lossless",
                "--memory-budget-mb",
                "16",
                "--json",
                "-o",
            ])
            .arg(&repo)
            .arg(&input),
    );
    assert_eq!(
        built["out_of_core"], true,
        "the in-memory estimate exceeds 16 MB"
    );
    let peak = built["peak_rss_mb"].as_f64().unwrap();
    assert!(peak <= 16.0, "peak {peak} MB over a 16 MB budget");
    assert!(!dir.path().join("ooc.spill").exists());
    let verified = verify_json(&repo, &input);
    assert_eq!(verified["max_abs_m"], 0.0);
    assert_eq!(verified["blob_errors"], 0);
    // Same size as the in-memory build, give or take the nodata fill.
    let in_memory = ok_json(
        bin()
            .args(["build", "--lossless", "--json", "-o"])
            .arg(dir.path().join("mem"))
            .arg(&input),
    );
    let (a, b) = (
        built["bits_per_sample"].as_f64().unwrap(),
        in_memory["bits_per_sample"].as_f64().unwrap(),
    );
    assert!(
        (a - b).abs() / b < 0.01,
        "out of core {a} vs in memory {b} bits/sample"
    );
}

#[test]
fn sparse_out_of_core_build_codes_no_hole_within_its_budget() {
    // The bundled crop with its south-east quarter and a band in the west cut out (NaN).
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data");
    let raw = std::fs::read(data.join("korea_srtm3_1025.i16")).unwrap();
    let mut sidecar: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("korea_srtm3_1025.json")).unwrap())
            .unwrap();
    let w = 1025usize;
    let mut f32s = Vec::with_capacity(raw.len() * 2);
    for (k, v) in raw.chunks_exact(2).enumerate() {
        let (x, y) = (k % w, k / w);
        let hole = (x > 600 && y > 500) || (100..300).contains(&x) && (200..260).contains(&y);
        let v = i16::from_le_bytes([v[0], v[1]]);
        let v = if hole || v == -32768 {
            f32::NAN
        } else {
            v as f32
        };
        f32s.extend_from_slice(&v.to_le_bytes());
    }
    let dir = tempfile::tempdir().unwrap();
    sidecar["file"] = "cut.f32".into();
    sidecar["dtype"] = "float32".into();
    sidecar["nodata"] = "NaN".into();
    std::fs::write(dir.path().join("cut.f32"), f32s).unwrap();
    let input = dir.path().join("cut.json");
    std::fs::write(&input, sidecar.to_string()).unwrap();
    let build = |name: &str, flags: &[&str]| {
        let repo = dir.path().join(name);
        let built = ok_json(
            bin()
                .args(["build", "--max-error-m", "1", "--json"])
                .args(flags)
                .arg("-o")
                .arg(&repo)
                .arg(&input),
        );
        (repo, built)
    };
    let (ooc, built) = build("ooc", &["--sparse", "--memory-budget-mb", "16"]);
    let (_, in_memory) = build("mem", &["--sparse"]);
    let (_, dense) = build("dense", &["--memory-budget-mb", "16"]);
    println!("sparse out of core {built}\nsparse in memory {in_memory}\ndense out of core {dense}");
    assert_eq!(built["out_of_core"], true);
    assert_eq!(in_memory["out_of_core"], false);
    let peak = built["peak_rss_mb"].as_f64().unwrap();
    assert!(peak <= 16.0, "peak {peak} MB over a 16 MB budget");
    let verified = verify_json(&ooc, &input);
    assert!(verified["max_abs_m"].as_f64().unwrap() <= 1.0);
    assert_eq!(verified["blob_errors"], 0);
    let info = ok_json(bin().arg("info").arg(&ooc).arg("--json"));
    assert!(info["metadata"]["coverage"].is_array());
    // The holes are not coded: fewer blobs than dense. Voids inside covered blocks (the
    // hole borders, the SRTM voids) are filled chunk by chunk out of core and over the
    // whole raster in memory, so the bytes differ a little (byte-for-byte equality with
    // one chunk: codec/tests/stream.rs).
    assert!(built["blob_count"].as_u64().unwrap() < dense["blob_count"].as_u64().unwrap());
    let (a, b) = (
        built["bits_per_sample"].as_f64().unwrap(),
        in_memory["bits_per_sample"].as_f64().unwrap(),
    );
    assert!(
        (a - b).abs() / b < 0.01,
        "out of core {a} vs in memory {b} bits/sample"
    );
}

#[test]
fn rms_builds_stream_out_of_core_within_their_budget() {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let dir = tempfile::tempdir().unwrap();
    let build = |name: &str, flags: &[&str]| {
        let repo = dir.path().join(name);
        let built = ok_json(
            bin()
                .args(["build", "--rms-m", "2", "--json"])
                .args(flags)
                .arg("-o")
                .arg(&repo)
                .arg(&input),
        );
        (repo, built)
    };
    let (repo, ooc) = build("ooc", &["--memory-budget-mb", "16"]);
    let (_, mem) = build("mem", &[]);
    println!("RMS 2 m out of core {ooc}\nin memory {mem}");
    assert_eq!(ooc["out_of_core"], true);
    assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 16.0, "{ooc}");
    let verified = verify_json(&repo, &input);
    assert!(verified["rms_m"].as_f64().unwrap() <= 2.0, "{verified}");
    assert_eq!(verified["blob_errors"], 0);
    // The crop's 11 voids are filled per chunk out of core: within 1 % of the in-memory
    // rate (byte-for-byte equality where the fills agree: codec/tests/stream.rs and the
    // korea test below).
    let (a, b) = (
        ooc["bits_per_sample"].as_f64().unwrap(),
        mem["bits_per_sample"].as_f64().unwrap(),
    );
    assert!((a - b).abs() / b < 0.01, "out of core {a} vs in memory {b}");
}

#[test]
fn colour_builds_out_of_core_are_the_in_memory_repositories() {
    // The bundled Blue Marble as a planar image (about 42 MB to build in memory) and as
    // a planet of face side 512 (about 117 MB at RMS 4).
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/bmng_global_1080x540.jpg");
    let dir = tempfile::tempdir().unwrap();
    let planet = &["--planet", "--face-side", "512"][..];
    for domain in [&[][..], planet] {
        for rate in [
            &["--lossless"][..],
            &["--max-error-m", "8"],
            &["--rms-m", "4"],
        ] {
            let build = |name: &str, flags: &[&str]| {
                let repo = dir.path().join(name);
                let built = ok_json(
                    bin()
                        .args(["build", "--colour", "--json"])
                        .args(domain)
                        .args(rate)
                        .args(flags)
                        .arg("-o")
                        .arg(&repo)
                        .arg(&input),
                );
                (repo, built)
            };
            let tag = format!("{}{}", domain.len(), rate.join(""));
            let (repo, ooc) = build(&format!("ooc{tag}"), &["--memory-budget-mb", "32"]);
            let (_, mem) = build(&format!("mem{tag}"), &[]);
            println!("colour {domain:?} {rate:?} out of core {ooc}\nin memory {mem}");
            assert_eq!(ooc["out_of_core"], true, "{domain:?} {rate:?}");
            assert_eq!(mem["out_of_core"], false, "{domain:?} {rate:?}");
            assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 32.0, "{ooc}");
            for key in ["content_hash", "rms", "max_abs", "blob_count"] {
                assert_eq!(ooc[key], mem[key], "{domain:?} {rate:?}: {key}");
            }
            let verified = verify_json(&repo, &input);
            assert_eq!(verified["blob_errors"], 0, "{domain:?} {rate:?}");
            assert_eq!(verified["rms_m"], ooc["rms"], "{domain:?} {rate:?}");
        }
    }
}

#[test]
fn verify_by_rows_reports_what_verify_in_memory_does() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data");
    let dir = tempfile::tempdir().unwrap();
    let cases: [(&str, &[&str]); 4] = [
        ("korea_srtm3_1025.json", &["--rms-m", "2"]),
        ("korea_srtm3_1025.json", &["--lossless", "--sparse"]),
        ("fixture_gsi_dem_256.json", &["--max-error-m", "0.5"]),
        ("bmng_global_1080x540.jpg", &["--colour", "--rms-m", "4"]),
    ];
    for (k, (file, rate)) in cases.iter().enumerate() {
        let input = data.join(file);
        let repo = dir.path().join(format!("r{k}"));
        ok_json(
            bin()
                .arg("build")
                .args(*rate)
                .args(["--json", "-o"])
                .arg(&repo)
                .arg(&input),
        );
        let verify = |flags: &[&str]| {
            ok_json(
                bin()
                    .arg("verify")
                    .arg(&repo)
                    .arg("--source")
                    .arg(&input)
                    .arg("--json")
                    .args(flags),
            )
        };
        let (rows, whole) = (verify(&["--stream"]), verify(&[]));
        println!("{file} {rate:?}: by rows {rows}\nin memory {whole}");
        for key in [
            "rms_m",
            "max_abs_m",
            "blobs_checked",
            "blob_errors",
            "content_hash_ok",
        ] {
            assert_eq!(rows[key], whole[key], "{file} {rate:?}: {key}");
        }
        assert!(rows["rms_m"].as_f64().is_some(), "{file}: measured");
    }
}

#[test]
fn korea_at_rms_9_out_of_core_is_the_in_memory_repository() {
    let Some(input) = shared_data(
        "korea_at_rms_9_out_of_core_is_the_in_memory_repository",
        "korea_srtm3_4097.json",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let build = |name: &str, flags: &[&str]| {
        ok_json(
            bin()
                .args(["build", "--rms-m", "9", "--json"])
                .args(flags)
                .arg("-o")
                .arg(dir.path().join(name))
                .arg(&input),
        )
    };
    let ooc = build("ooc", &["--memory-budget-mb", "32"]);
    let mem = build("mem", &[]);
    println!("korea RMS 9 m out of core {ooc}\nin memory {mem}");
    assert_eq!(ooc["out_of_core"], true);
    assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 32.0, "{ooc}");
    assert_eq!(ooc["rdo"], true);
    assert_eq!(ooc["content_hash"], mem["content_hash"]);
}

#[test]
fn korea_builds_out_of_core_with_a_budget_below_its_input_size() {
    let Some(input) = shared_data(
        "korea_builds_out_of_core_with_a_budget_below_its_input_size",
        "korea_srtm3_4097.json",
    ) else {
        return;
    };
    let input_mb = std::fs::metadata(input.with_extension("i16"))
        .unwrap()
        .len() as f64
        / 1048576.0;
    let dir = tempfile::tempdir().unwrap();
    let build = |name: &str| {
        let repo = dir.path().join(name);
        let built = ok_json(
            bin()
                .args([
                    "build",
                    "--max-error-m",
                    "1",
                    "--memory-budget-mb",
                    "32",
                    "--json",
                    "-o",
                ])
                .arg(&repo)
                .arg(&input),
        );
        (repo, built)
    };
    let (repo, built) = build("korea");
    println!("korea out of core: {built} (input {input_mb:.1} MB)");
    assert!(32.0 < input_mb);
    assert_eq!(built["out_of_core"], true);
    assert!(built["peak_rss_mb"].as_f64().unwrap() <= 32.0);
    let verified = verify_json(&repo, &input);
    assert!(verified["max_abs_m"].as_f64().unwrap() <= 1.0);
    assert_eq!(verified["blob_errors"], 0);
    // Reproducible: the chunking (and so the nodata fills) depends on the arguments only,
    // not on what the process happened to have resident (it did: 4 hashes in 6 runs).
    for round in 0..2 {
        let (_, again) = build(&format!("again{round}"));
        assert_eq!(
            again["content_hash"], built["content_hash"],
            "round {round}"
        );
    }
}

/// The ETOPO5 planet at RMS 9 m fits a 256 MB budget in core: the budget's estimate
/// (24 bytes a cube sample, 8 a source sample) lets it build, within the budget, to the
/// repository an unbudgeted build makes.
#[test]
fn etopo5_planet_at_rms_9_builds_within_a_256_mb_budget() {
    let Some(input) = shared_data(
        "etopo5_planet_at_rms_9_builds_within_a_256_mb_budget",
        "etopo5_global.json",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let build = |name: &str, budget: &[&str]| {
        ok_json(
            bin()
                .args(["build", "--planet", "--rms-m", "9", "--json"])
                .args(budget)
                .arg("-o")
                .arg(dir.path().join(name))
                .arg(&input),
        )
    };
    let budgeted = build("budget", &["--memory-budget-mb", "256"]);
    let free = build("free", &[]);
    let peak = budgeted["peak_rss_mb"].as_f64().unwrap();
    println!("etopo5 planet RMS 9 m under a 256 MB budget: peak {peak:.1} MB");
    assert!(peak <= 256.0, "peak {peak} MB over the 256 MB budget");
    assert!(budgeted["rms"].as_f64().unwrap() <= 9.0);
    assert_eq!(budgeted["content_hash"], free["content_hash"]);
    // Under 128 MB it does not fit in memory: out of core, the same repository.
    let ooc = build("ooc", &["--memory-budget-mb", "128"]);
    let peak = ooc["peak_rss_mb"].as_f64().unwrap();
    println!("etopo5 planet RMS 9 m out of core under 128 MB: peak {peak:.1} MB");
    assert_eq!(ooc["out_of_core"], true);
    assert!(peak <= 128.0, "peak {peak} MB over the 128 MB budget");
    assert_eq!(ooc["content_hash"], free["content_hash"]);
    // Below what the program and the geometry take, it is refused before it starts.
    let out = run(bin()
        .args([
            "build",
            "--planet",
            "--rms-m",
            "9",
            "--memory-budget-mb",
            "64",
            "-o",
        ])
        .arg(dir.path().join("small"))
        .arg(&input));
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--memory-budget-mb 64 leaves nothing for sample buffers"),
        "{err}"
    );
    assert!(!dir.path().join("small").exists());
}

#[test]
fn demo_builds_and_verifies_the_bundled_samples_once() {
    let dir = tempfile::tempdir().unwrap();
    let repos = dir.path().join("demo");
    for round in 0..2 {
        // `--smoke`: serve on a free port, request the example URLs, stop.
        let out = run(bin().arg("demo").arg("--dir").arg(&repos).args([
            "--addr",
            "127.0.0.1:0",
            "--smoke",
        ]));
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        // Built and verified the first time only.
        assert_eq!(
            stdout.matches("0 errors, content hash ok").count(),
            if round == 0 { 3 } else { 0 },
            "{stdout}"
        );
        assert_eq!(stdout.contains("building"), round == 0, "{stdout}");
        assert!(
            stdout.contains("serving the sample repositories on http://127.0.0.1:"),
            "{stdout}"
        );
        assert!(stdout.contains("smoke check passed"), "{stdout}");
        // The planet streams with its colour.
        assert!(stdout.contains("colour from earth_colour"), "{stdout}");
    }
    assert!(repos.join("korea").exists() && repos.join("earth").exists());
    for (name, w, h) in [("earth", 64, 32), ("korea", 64, 64)] {
        let png = dir.path().join(format!("{name}.png"));
        let out = run(bin()
            .arg("preview")
            .arg(repos.join(name))
            .args(["--width", "64", "-o"])
            .arg(&png));
        assert!(out.status.success());
        let bytes = std::fs::read(&png).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let dims = (
            u32::from_be_bytes(bytes[16..20].try_into().unwrap()),
            u32::from_be_bytes(bytes[20..24].try_into().unwrap()),
        );
        assert_eq!(dims, (w, h), "{name}");
    }
}

#[test]
fn planets_out_of_core_are_the_in_memory_repositories() {
    // The bundled ETOPO20 on a cube of face side 512: about 42 MB to build in memory.
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/etopo20_global.json");
    let dir = tempfile::tempdir().unwrap();
    let build = |name: &str, rate: &[&str], flags: &[&str]| {
        let repo = dir.path().join(name);
        let mut cmd = bin();
        cmd.args(["build", "--planet", "--face-side", "512", "--json"])
            .args(rate)
            .args(flags)
            .arg("-o")
            .arg(&repo)
            .arg(&input);
        (repo, cmd)
    };
    for rate in [
        &["--lossless"][..],
        &["--max-error-m", "2"],
        &["--rms-m", "9"],
        &["--rms-m", "20", "--rdo", "on"],
    ] {
        let tag = rate.join("");
        let (repo, mut cmd) = build(&format!("ooc{tag}"), rate, &["--memory-budget-mb", "32"]);
        let ooc = ok_json(&mut cmd);
        let mem = ok_json(&mut build(&format!("mem{tag}"), rate, &[]).1);
        println!("planet {rate:?} out of core {ooc}\nin memory {mem}");
        assert_eq!(ooc["out_of_core"], true, "{rate:?}");
        assert_eq!(mem["out_of_core"], false, "{rate:?}");
        assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 32.0, "{ooc}");
        for key in ["content_hash", "rms", "max_abs", "blob_count"] {
            assert_eq!(ooc[key], mem[key], "{rate:?}: {key}");
        }
        let verified = verify_json(&repo, &input);
        assert_eq!(verified["blob_errors"], 0, "{rate:?}");
        assert_eq!(verified["seam_mismatches"], 0, "{rate:?}");
    }
}

#[test]
fn sparse_planet_codes_only_where_there_is_data() {
    // The bundled ETOPO20 cut to North America (20..60 N, 130..60 W), NaN elsewhere.
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data");
    let raw = std::fs::read(data.join("etopo20_global.i16")).unwrap();
    let mut sidecar: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("etopo20_global.json")).unwrap()).unwrap();
    let (w, h) = (1080usize, 540usize);
    let mut f32s = Vec::with_capacity(w * h * 4);
    for r in 0..h {
        let lat = 90.0 - (r as f64 + 0.5) / 3.0;
        for c in 0..w {
            let lon = -180.0 + (c as f64 + 0.5) / 3.0;
            let k = 2 * (r * w + c);
            let v = i16::from_le_bytes([raw[k], raw[k + 1]]) as f32;
            let inside = (20.0..60.0).contains(&lat) && (-130.0..-60.0).contains(&lon);
            f32s.extend_from_slice(&if inside { v } else { f32::NAN }.to_le_bytes());
        }
    }
    let dir = tempfile::tempdir().unwrap();
    sidecar["file"] = "na.f32".into();
    sidecar["dtype"] = "float32".into();
    sidecar["nodata"] = "NaN".into();
    std::fs::write(dir.path().join("na.f32"), f32s).unwrap();
    let input = dir.path().join("na.json");
    std::fs::write(&input, sidecar.to_string()).unwrap();
    let mut blobs = Vec::new();
    for sparse in [false, true] {
        let repo = dir.path().join(format!("na_{sparse}"));
        let mut cmd = bin();
        cmd.args(["build", "--planet", "--max-error-m", "0.5", "--json", "-o"])
            .arg(&repo)
            .arg(&input);
        if sparse {
            cmd.arg("--sparse");
        }
        let built = ok_json(&mut cmd);
        let verified = verify_json(&repo, &input);
        assert!(
            verified["max_abs_m"].as_f64().unwrap() <= 0.5,
            "bound on every data sample"
        );
        assert_eq!(verified["seam_mismatches"], 0);
        blobs.push(built["blob_count"].as_u64().unwrap());
        let heights = query(&repo, &[(40.0, -105.0), (-30.0, 20.0)]);
        assert!(heights[0] > 1000.0, "Rocky Mountains: {}", heights[0]);
        if sparse {
            assert!(
                heights[1].is_nan(),
                "no data in southern Africa: {}",
                heights[1]
            );
            let info = ok_json(bin().arg("info").arg(&repo).arg("--json"));
            assert!(info["metadata"]["coverage"].is_array());
        }
    }
    println!(
        "North America on ETOPO20: dense {} blobs, sparse {}",
        blobs[0], blobs[1]
    );
    assert!(
        blobs[1] * 2 < blobs[0],
        "sparse {} blobs vs dense {}",
        blobs[1],
        blobs[0]
    );
}

#[test]
fn a_corrupted_repository_fails_verification_without_panicking() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("jb");
    ok_json(
        bin()
            .args(["build", "--lossless", "--json", "-o"])
            .arg(&repo)
            .arg(fixture("jacksboro.json")),
    );
    let db = repo.join("repository.pack");
    let clean = std::fs::read(&db).unwrap();
    // Flip bytes at several places of the repository file (header, directories, metadata,
    // blobs):
    // every part is under a checksum, so every flip must be a clean failure (exit 1 with a
    // message naming the repository).
    let mut failures = 0;
    for k in 1..=16 {
        let mut bytes = clean.clone();
        let at = bytes.len() * k / 17;
        for b in &mut bytes[at..(at + 8).min(clean.len())] {
            *b ^= 0x5A;
        }
        std::fs::write(&db, &bytes).unwrap();
        let out = run(bin().arg("verify").arg(&repo).arg("--json"));
        match out.status.code() {
            Some(1) => {
                failures += 1;
                let stderr = String::from_utf8_lossy(&out.stderr);
                assert!(stderr.starts_with("error:"), "{stderr}");
                assert!(stderr.contains(&*repo.to_string_lossy()), "{stderr}");
            }
            other => panic!(
                "flip {k}: exit {other:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            ),
        }
    }
    assert_eq!(failures, 16, "every corruption is detected");
    std::fs::write(&db, &clean).unwrap();
    assert_eq!(
        ok_json(bin().arg("verify").arg(&repo).arg("--json"))["blob_errors"],
        0
    );
}

/// Every entry of `dir`, by name (to show that a refused build left nothing behind).
fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Runs `cmd` (a build with `--stall-after-blobs 1`, so one that reaches the store hangs)
/// and returns its output, killing it and failing if it has not ended within 120 s.
fn run_refused(cmd: &mut Command) -> Output {
    let mut child = cmd
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    for _ in 0..1200 {
        if child.try_wait().unwrap().is_some() {
            let out = child.wait_with_output().unwrap();
            let stderr = String::from_utf8_lossy(&out.stderr);
            assert!(!stderr.contains("panicked"), "panic: {stderr}");
            return out;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    panic!("the build was not refused before it started writing blobs");
}

#[test]
fn a_build_refused_for_its_output_or_options_refuses_first_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let korea = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    // An existing output without --overwrite: refused before the input is encoded (the
    // stall hook would hang a build that got as far as storing a blob), left untouched.
    let repo = dir.path().join("repo");
    std::fs::create_dir(&repo).unwrap();
    std::fs::write(repo.join("repository.pack"), b"mine").unwrap();
    let out = run_refused(
        bin()
            .args([
                "build",
                "--max-error-m",
                "2",
                "--stall-after-blobs",
                "1",
                "-o",
            ])
            .arg(&repo)
            .arg(&korea),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("already exists") && stderr.contains("--overwrite"),
        "{stderr}"
    );
    assert_eq!(entries(dir.path()), ["repo"]);
    assert_eq!(entries(&repo), ["repository.pack"]);
    // --overwrite never publishes into a directory that holds something else.
    let home = dir.path().join("home");
    std::fs::create_dir(&home).unwrap();
    std::fs::write(home.join("keep.txt"), b"mine").unwrap();
    let out = run_refused(
        bin()
            .args(["build", "--overwrite", "--stall-after-blobs", "1", "-o"])
            .arg(&home)
            .arg(&korea),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("not a repository directory"), "{stderr}");
    assert_eq!(entries(&home), ["keep.txt"]);
    // --overwrite never replaces a file that is not a repository directory.
    let file = dir.path().join("file");
    std::fs::write(&file, b"not a repository").unwrap();
    let out = run_refused(
        bin()
            .args(["build", "--overwrite", "--stall-after-blobs", "1", "-o"])
            .arg(&file)
            .arg(&korea),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("not a repository directory"), "{stderr}");
    assert_eq!(std::fs::read(&file).unwrap(), b"not a repository");
    // Memory budgets the out-of-core build cannot meet: no .partial, no .spill.
    for budget in ["0", "5"] {
        let fresh = tempfile::tempdir().unwrap();
        let out = run_refused(
            bin()
                .args(["build", "--lossless", "--stall-after-blobs", "1"])
                .args(["--memory-budget-mb", budget, "-o"])
                .arg(fresh.path().join("repo"))
                .arg(&korea),
        );
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "budget {budget}: {stderr}");
        assert!(stderr.contains("--memory-budget-mb"), "{stderr}");
        assert!(
            entries(fresh.path()).is_empty(),
            "budget {budget}: {:?}",
            entries(fresh.path())
        );
    }
    // Options that only a planet build reads are checked first too.
    let fresh = tempfile::tempdir().unwrap();
    let out = run_refused(
        bin()
            .args([
                "build",
                "--planet",
                "--body",
                "pluto",
                "--stall-after-blobs",
                "1",
                "-o",
            ])
            .arg(fresh.path().join("repo"))
            .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/etopo20_global.json")),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("pluto"), "{stderr}");
    assert!(entries(fresh.path()).is_empty());
}

#[test]
fn build_threads_are_bounded_with_a_clear_error() {
    for threads in ["0", "1025", "100000"] {
        let dir = tempfile::tempdir().unwrap();
        let out = run_refused(
            bin()
                .args([
                    "build",
                    "--threads",
                    threads,
                    "--stall-after-blobs",
                    "1",
                    "-o",
                ])
                .arg(dir.path().join("repo"))
                .arg(fixture("jacksboro.json")),
        );
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "--threads {threads}: {stderr}");
        assert!(
            stderr.contains(&format!("--threads {threads} is out of range"))
                && stderr.contains("1 to 1024"),
            "--threads {threads}: {stderr}"
        );
        assert!(entries(dir.path()).is_empty());
    }
    // The bound itself is accepted.
    let dir = tempfile::tempdir().unwrap();
    ok_json(
        bin()
            .args(["build", "--threads", "1024", "--json", "-o"])
            .arg(dir.path().join("repo"))
            .arg(fixture("jacksboro.json")),
    );
}

#[test]
fn bad_values_are_named_for_what_is_wrong_with_them() {
    let stderr_of = |args: &[&str]| {
        let out = run(bin().args(args));
        assert!(!out.status.success(), "{args:?} succeeded");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    // Query points: the coordinate that is wrong, and the range (checked before the
    // repository is even opened).
    let e = stderr_of(&["query", "/nonexistent", "--at", "91,0"]);
    assert!(
        e.contains("latitude 91 is out of range") && e.contains("-90 to 90"),
        "{e}"
    );
    assert!(!e.contains("longitude"), "{e}");
    let e = stderr_of(&["query", "/nonexistent", "--at", "-90.5,10"]);
    assert!(e.contains("latitude -90.5 is out of range"), "{e}");
    let e = stderr_of(&["query", "/nonexistent", "--at", "45,inf"]);
    assert!(e.contains("longitude inf is not a finite number"), "{e}");
    // Load test durations: too large is not "not positive".
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let lt = |d: &str| {
        stderr_of(&[
            "loadtest",
            "--url",
            &url,
            "--repo",
            "korea",
            "--duration-s",
            d,
        ])
    };
    let e = lt("1e300");
    assert!(
        e.contains("--duration-s 1e300 is too large") && e.contains("1e9"),
        "{e}"
    );
    assert!(!e.contains("positive"), "{e}");
    let e = lt("0");
    assert!(
        e.contains("--duration-s 0 must be more than 0 seconds"),
        "{e}"
    );
    // The shared refinement flags are checked alike by every command that takes them,
    // before anything is fetched.
    let at = [
        "--url",
        url.as_str(),
        "--repo",
        "korea",
        "--tolerance-px",
        "0",
    ];
    for cmd in [
        vec!["fly"],
        vec!["loadtest"],
        vec![
            "render",
            "--uv",
            "0.5,0.5",
            "--height-m",
            "100",
            "-o",
            "/nonexistent.png",
        ],
        vec!["view"],
    ] {
        let e = stderr_of(&[cmd.as_slice(), &at].concat());
        assert!(
            e.contains("--tolerance-px 0 must be positive"),
            "{cmd:?}: {e}"
        );
    }
    // A metadata request that times out says so, with the URL, not an OS error code.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let hold = std::thread::spawn(move || {
        // Accept and never answer (keep the sockets open until the test ends).
        let mut held = Vec::new();
        listener.set_nonblocking(true).unwrap();
        let until = std::time::Instant::now() + std::time::Duration::from_secs(30);
        while std::time::Instant::now() < until && held.len() < 4 {
            match listener.accept() {
                Ok((s, _)) => held.push(s),
                Err(_) => std::thread::sleep(std::time::Duration::from_millis(10)),
            }
        }
        held
    });
    let e = stderr_of(&[
        "fly",
        "--url",
        &format!("http://{addr}"),
        "--repo",
        "korea",
        "--timeout-s",
        "1",
    ]);
    let want = format!(
        "timed out after 1 s fetching the metadata from http://{addr}/repos/korea/metadata.json"
    );
    assert!(e.contains(&want), "{e}");
    assert!(!e.contains("os error"), "{e}");
    drop(hold);
}

/// The bundled ETOPO20 grid (or the Blue Marble mosaic with `colour`) in `dir`, its
/// sidecar's CRS text replaced by `crs`; returns the sidecar's path.
fn with_crs(dir: &Path, name: &str, crs: &str, colour: bool) -> PathBuf {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data");
    let (stem, ext) = if colour {
        ("bmng_global_1080x540", "jpg")
    } else {
        ("etopo20_global", "i16")
    };
    let case = dir.join(name);
    std::fs::create_dir_all(&case).unwrap();
    let mut sidecar: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join(format!("{stem}.json"))).unwrap()).unwrap();
    if colour {
        sidecar["georef"]["projection"] = crs.into();
    } else {
        sidecar["crs"] = crs.into();
    }
    std::fs::copy(
        data.join(format!("{stem}.{ext}")),
        case.join(format!("{stem}.{ext}")),
    )
    .unwrap();
    let json = case.join(format!("{stem}.json"));
    std::fs::write(&json, sidecar.to_string()).unwrap();
    if colour {
        case.join(format!("{stem}.{ext}"))
    } else {
        json
    }
}

#[test]
fn planet_builds_recognise_the_projection_not_its_wording() {
    let dir = tempfile::tempdir().unwrap();
    for (crs, colour) in [
        ("Simple Cylindrical", false),
        ("Simple Cylindrical", true),
        ("equirectangular", true),
        ("+proj=eqc +lat_ts=0 +R=6371000", false),
        ("EPSG:4269", false),
    ] {
        let input = with_crs(dir.path(), &format!("ok{}", crs.len()), crs, colour);
        let mut cmd = bin();
        cmd.args(["build", "--planet", "--face-side", "64", "--json", "-o"])
            .arg(dir.path().join(format!("repo-{}-{colour}", crs.len())))
            .arg(&input);
        if colour {
            cmd.args(["--colour", "--max-error-m", "8"]);
        } else {
            cmd.args(["--max-error-m", "20"]);
        }
        let built = ok_json(&mut cmd);
        assert_eq!(
            built["kind"],
            if colour { "colour" } else { "elevation" },
            "{crs}"
        );
    }
    for (crs, colour, named) in [
        ("UTM zone 33N", false, "UTM"),
        ("EPSG:32633", false, "UTM zone 33N"),
        ("Mercator", true, "Mercator"),
        ("+proj=eqc +lat_ts=30", false, "standard parallel 30"),
        ("+proj=merc +R=3396190", false, "Mercator"),
    ] {
        let input = with_crs(dir.path(), &format!("bad{}", crs.len()), crs, colour);
        let out_dir = dir.path().join(format!("refused-{}", crs.len()));
        let mut cmd = bin();
        cmd.args(["build", "--planet", "--face-side", "64", "-o"])
            .arg(&out_dir)
            .arg(&input);
        if colour {
            cmd.arg("--colour");
        }
        let out = run(&mut cmd);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{crs}: {stderr}");
        assert!(
            stderr.contains("latitude/longitude grid"),
            "{crs}: {stderr}"
        );
        assert!(
            stderr.contains(named),
            "{crs}: {stderr} should name {named}"
        );
        assert!(
            stderr.contains("Accepted") && stderr.contains("Simple"),
            "{crs}: {stderr}"
        );
        assert!(!out_dir.exists());
    }
}
