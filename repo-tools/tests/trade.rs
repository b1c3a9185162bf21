//! End to end: `quincunx trade` on the bundled repositories, served by `quincunx serve`
//! over loopback and rendered on the GPU (lavapipe in CI). Skipped without a GPU unless
//! `REQUIRE_GPU=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};

use common::{bin, build, serve};
use serde_json::Value;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

fn gpu_or_skip(test: &str) -> bool {
    // Prints `SKIP` itself when there is no adapter; `REQUIRE_GPU=1` makes that fail.
    quincunx_render::offscreen::gpu_for_test(test)
        .unwrap()
        .is_some()
}

fn trade(url: &str, extra: &[&str]) -> Value {
    let o = bin()
        .args(["trade", "--url", url, "--json", "--viewport", "480x270"])
        .args(extra)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(o.status.success(), "trade failed: {stderr}");
    serde_json::from_slice(&o.stdout).unwrap()
}

const FIELDS: [&str; 10] = [
    "tolerance_px",
    "triangles_median",
    "refine_ms_median",
    "render_ms_median",
    "bytes_fetched",
    "time_to_full_quality_s_median",
    "psnr_db",
    "geometric_error_px_p99",
    "geometric_error_px_max",
    "fetched_over_needed",
];

fn f(p: &Value, k: &str) -> f64 {
    p[k].as_f64()
        .unwrap_or_else(|| panic!("{k} is not a number: {p}"))
}

/// The properties every trade point must have.
fn check_points(points: &[Value]) {
    for p in points {
        for k in FIELDS {
            assert!(p.get(k).is_some(), "no {k} in {p}");
        }
        let t = f(p, "tolerance_px");
        // What was fetched covers the smallest set that meets the tolerance...
        assert!(f(p, "fetched_over_needed") >= 1.0, "{p}");
        assert!(f(p, "bytes_needed") > 0.0, "{p}");
        // ... and that set's cuts do meet it.
        assert_eq!(p["needed_full_quality"], true, "{p}");
        assert!(f(p, "needed_max_error_px") <= t, "{p}");
        assert_eq!(f(p, "cracks") + f(p, "coverage_errors"), 0.0, "{p}");
        assert!(f(p, "bytes_in_final_cuts") <= f(p, "bytes_fetched"), "{p}");
        for v in p["views"].as_array().unwrap() {
            assert_eq!(v["finite"], true, "{v}");
        }
    }
}

/// Checks `p[times]` (runs of per-jump seconds, `null` unfinished) against its pooled
/// figures `<figure>_median`, `<figure>_max` and the count `p[unfinished]`.
fn pooled(p: &Value, times: &str, unfinished: &str, figure: &str) {
    let runs = p[times].as_array().unwrap();
    assert_eq!(runs.len() as f64, f(p, "runs"), "{p}");
    let legs = runs[0].as_array().unwrap().len();
    assert!(legs > 0, "{p}");
    assert!(runs.iter().all(|r| r.as_array().unwrap().len() == legs));
    let mut t: Vec<f64> = runs
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().filter_map(|v| v.as_f64()))
        .collect();
    t.sort_by(f64::total_cmp);
    assert_eq!(
        f(p, unfinished),
        (runs.len() * legs - t.len()) as f64,
        "{p}"
    );
    if let Some(max) = t.last() {
        assert_eq!(f(p, &format!("{figure}_max")), *max, "{p}");
        let mid = t[((t.len() - 1) as f64 * 0.5).round() as usize];
        assert_eq!(f(p, &format!("{figure}_median")), mid, "{p}");
    }
}

/// The bundled korea crop at 2 m, built in `dir` and served.
fn served_korea(dir: &Path) -> common::Server {
    let korea = dir.join("korea");
    build(
        &["--max-error-m", "2"],
        &data("korea_srtm3_1025.json"),
        &korea,
    );
    serve(&[("korea", &korea)])
}

#[test]
fn trade_on_the_bundled_korea_crop() {
    if !gpu_or_skip("trade_on_the_bundled_korea_crop") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let server = served_korea(dir.path());
    let plots = dir.path().join("plots");
    let r = trade(
        &server.url,
        &[
            "--repo",
            "korea",
            "--tolerances",
            "0,1,4",
            "--metrics",
            "sampling,geometric",
            "--views",
            "3",
            "--runs",
            "2",
            // A faster link than the default 4 Mbit/s, 100 ms: the study waits for
            // every leg of every flight; nothing checked here depends on the link.
            "--link",
            "20000,20",
            "--plot",
            plots.to_str().unwrap(),
        ],
    );
    let points = r["points"].as_array().unwrap();
    assert_eq!(points.len(), 6);
    check_points(points);
    let metric = |p: &Value| p["metric"].as_str().unwrap().to_string();
    assert!(points[..3].iter().all(|p| metric(p) == "sampling"));
    assert!(points[3..].iter().all(|p| metric(p) == "geometric"));
    // The geometric metric keeps its promise: no measured pixel above the tolerance,
    // and a coarser tolerance still costs less.
    for p in &points[4..] {
        assert!(
            f(p, "geometric_error_px_max") <= f(p, "tolerance_px"),
            "{p}"
        );
    }
    assert!(f(&points[4], "triangles_median") > f(&points[5], "triangles_median"));
    let (zero, one, four) = (&points[0], &points[1], &points[2]);
    // The reference's own refinement matches the reference exactly.
    assert!(zero["psnr_db"].is_null(), "{zero}");
    assert_eq!(f(zero, "geometric_error_px_max"), 0.0, "{zero}");
    // Coarser tolerance: fewer triangles and bytes, more image error.
    assert!(f(one, "triangles_median") > f(four, "triangles_median"));
    assert!(f(one, "bytes_fetched") > f(four, "bytes_fetched"));
    assert!(f(one, "psnr_db") > f(four, "psnr_db"));
    assert!(f(one, "geometric_error_px_p99") <= f(four, "geometric_error_px_p99"));
    // Times to full quality after the jumps and from cold starts at their views pool
    // both runs: each run lists one time per jump, and the median and largest are those
    // of the pooled finished ones.
    for p in points {
        assert_eq!(f(p, "runs"), 2.0, "{p}");
        pooled(
            p,
            "jump_times_s",
            "jumps_unfinished",
            "time_to_full_quality_s",
        );
        pooled(
            p,
            "cold_times_s",
            "cold_unfinished",
            "time_to_full_quality_cold_s",
        );
        let legs = |k: &str| p[k].as_array().unwrap()[0].as_array().unwrap().len();
        assert_eq!(legs("cold_times_s"), legs("jump_times_s"), "{p}");
    }
    // The charts and the report the charts came from.
    for name in [
        "trade-triangles.png",
        "trade-psnr.png",
        "trade-geometric.png",
        "trade-ttfq-cold.png",
        "korea.json",
    ] {
        assert!(plots.join(name).is_file(), "no {name}");
    }
}

#[test]
fn trade_on_the_bundled_planet_with_colour_at_the_extremes() {
    if !gpu_or_skip("trade_on_the_bundled_planet_with_colour_at_the_extremes") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let earth = dir.path().join("earth");
    let colour = dir.path().join("earth_colour");
    build(
        &["--planet", "--max-error-m", "2"],
        &data("etopo20_global.json"),
        &earth,
    );
    build(
        &["--planet", "--colour", "--rms-m", "4"],
        &data("bmng_global_1080x540.jpg"),
        &colour,
    );
    let server = serve(&[("earth", &earth), ("earth_colour", &colour)]);
    // Two jumps 15,000 and 4,000 km out, looking past the centre: where the tolerance
    // matters on a 37 km grid at 480 x 270.
    let jumps = dir.path().join("far.json");
    std::fs::write(
        &jumps,
        r#"{"legs": [
          {"duration_s": 20, "jump": true, "settle_s": 0.5,
           "from": {"eye": [21371000, 0, 0], "target": [0, 0, 1000000]}},
          {"duration_s": 20, "jump": true, "settle_s": 0.5,
           "from": {"eye": [0, 8000000, 6600000], "target": [0, 1000000, 0]}}]}"#,
    )
    .unwrap();
    let r = trade(
        &server.url,
        &[
            "--repo",
            "earth",
            "--colour",
            "earth_colour",
            "--tolerances",
            "1,4",
            "--path",
            jumps.to_str().unwrap(),
            "--views",
            "3",
            "--link",
            "none",
            "--runs",
            "1",
        ],
    );
    let points = r["points"].as_array().unwrap();
    check_points(points);
    let (one, four) = (&points[0], &points[1]);
    assert!(
        f(one, "triangles_median") > f(four, "triangles_median"),
        "{r}"
    );
    assert!(f(one, "bytes_needed") > f(four, "bytes_needed"), "{r}");
    assert!(f(one, "needed_halves") > f(four, "needed_halves"), "{r}");
    // The extremes: 1 m above the ground, 100,000 km away, a pole, a cube corner.
    let r = trade(
        &server.url,
        &[
            "--repo",
            "earth",
            "--colour",
            "earth_colour",
            "--tolerances",
            "1",
            "--path",
            "extremes",
            "--views",
            "5",
            "--link",
            "none",
            "--runs",
            "1",
        ],
    );
    let points = r["points"].as_array().unwrap();
    check_points(points);
    for p in points {
        let views = p["views"].as_array().unwrap();
        assert_eq!(views.len(), 5, "{p}");
        for (k, v) in views.iter().enumerate() {
            // Straight down (all but the oblique view at 1 m and the 100,000 km one):
            // the ground fills the frame, so a background pixel is a crack.
            if ![0, 2].contains(&k) {
                assert_eq!(f(v, "background_px"), 0.0, "view {k}: {v}");
            }
            // A millimetre's move changes the picture by little: no jitter.
            let jitter = v["jitter_psnr_db"].as_f64().unwrap_or(f64::INFINITY);
            assert!(jitter > 30.0, "view {k}: {v}");
        }
    }
}

#[test]
fn fly_render_draws_every_frame_and_reports_the_renderers_figures() {
    if !gpu_or_skip("fly_render_draws_every_frame") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let server = served_korea(dir.path());
    let o = bin()
        .args([
            "fly",
            "--url",
            &server.url,
            "--repo",
            "korea",
            "--path",
            "jump",
        ])
        .args(["--render", "--render-size", "320x180", "--json"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "fly --render failed: {stderr}");
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(f(&r, "cracks"), 0.0, "{r}");
    let render = &r["render"];
    // Every frame of the flight went through the renderer, with patches and triangles.
    assert_eq!(f(render, "frames"), f(&r, "frames"), "{r}");
    assert!(f(render, "frames_rasterised") >= 1.0, "{render}");
    assert!(f(render, "triangles_max") > 0.0, "{render}");
    assert!(f(render, "pool_uploads") > 0.0, "{render}");
    assert!(
        f(render, "gpu_bytes_peak") <= f(render, "gpu_bytes_budget"),
        "{render}"
    );
    assert_eq!(render["size"], serde_json::json!([320, 180]), "{render}");
}
