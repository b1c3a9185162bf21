//! `quincunx view`: the window under Xvfb saves a screenshot that shows terrain, and with
//! no display the command fails cleanly.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::HashSet;
use std::path::Path;
use std::process::{Command, Output};

use common::{bin, build, serve};
use quincunx_render::offscreen::Image;

/// The viewer's clear colour (`repo-tools/src/view.rs`).
const BACKGROUND: [u8; 3] = [135, 170, 210];

fn show(out: &Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn has_xvfb_run() -> bool {
    Command::new("sh")
        .args(["-c", "command -v xvfb-run"])
        .output()
        .is_ok_and(|o| o.status.success())
}

#[test]
fn view_under_xvfb_saves_a_screenshot_of_terrain() {
    if !has_xvfb_run() {
        quincunx_testkit::skip::skip(
            "view_under_xvfb",
            "REQUIRE_XVFB",
            "xvfb-run is not installed (apt-get install xvfb xauth)",
        );
        return;
    }
    // No adapter: SKIP, or fail with REQUIRE_GPU=1, like the other render tests.
    if quincunx_render::offscreen::gpu_for_test("view_under_xvfb")
        .unwrap()
        .is_none()
    {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("korea");
    let korea = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    build(&["--rms-m", "2"], &korea, &repo);
    let server = serve(&[("korea", &repo)]);
    let shot = dir.path().join("view.png");
    let xdg = dir.path().join("xdg");
    std::fs::create_dir(&xdg).unwrap();
    let out = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1024x768x24"])
        .arg(env!("CARGO_BIN_EXE_quincunx"))
        .args([
            "view",
            "--url",
            &server.url,
            "--repo",
            "korea",
            "--uv",
            "0.5,0.5",
            "--height-m",
            "20000",
            "--size",
            "640x480",
            "--frames",
            "40",
            "--screenshot",
        ])
        .arg(&shot)
        .env("XDG_RUNTIME_DIR", &xdg)
        .output()
        .unwrap();
    drop(server);
    assert!(
        out.status.success(),
        "quincunx view failed:\n{}",
        show(&out)
    );
    let image = Image::read_png(&shot).unwrap();
    assert_eq!((image.width, image.height), (640, 480), "{}", show(&out));
    let pixels: Vec<[u8; 3]> = image
        .rgba
        .chunks_exact(4)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    let distinct: HashSet<[u8; 3]> = pixels.iter().copied().collect();
    let background = pixels
        .iter()
        .filter(|p| p.iter().zip(BACKGROUND).all(|(&a, b)| a.abs_diff(b) <= 2))
        .count();
    let terrain_share = 1.0 - background as f64 / pixels.len() as f64;
    println!(
        "view_under_xvfb: {} distinct colours, {:.1}% not background",
        distinct.len(),
        100.0 * terrain_share
    );
    assert!(
        distinct.len() >= 300,
        "only {} distinct colours: a blank window?",
        distinct.len()
    );
    assert!(
        terrain_share > 0.9,
        "{:.1}% of the pixels are terrain (straight down from 20 km, it should fill the frame)",
        100.0 * terrain_share
    );
}

#[test]
fn view_without_a_display_exits_1_with_a_clear_message() {
    let out = bin()
        .args([
            "view",
            "--url",
            "http://127.0.0.1:9",
            "--repo",
            "korea",
            "--frames",
            "1",
        ])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .env_remove("WAYLAND_SOCKET")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", show(&out));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("error: cannot open a window") && stderr.contains("DISPLAY"),
        "unclear message:\n{}",
        show(&out)
    );
    assert!(!stderr.contains("panicked"), "{}", show(&out));
}
