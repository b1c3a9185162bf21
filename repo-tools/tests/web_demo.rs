//! The web demo's tests, run from `cargo test`: the `node --test` suite of the WebAssembly
//! module and the page's client on the bundled repositories (their exports and `verify
//! --json` reference hashes), and the browser test: headless Chromium on the demo page
//! against `quincunx render`.
//!
//! Needs `node` (and, for the browser test, `/usr/bin/chromium` and
//! `web-demo/node_modules/playwright-core`, which `.ci/run` installs); without them the
//! tests print `SKIP`. `REQUIRE_BROWSER=1` (set by `.ci/run`) turns a missing browser or
//! package into a failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use common::bin;
use quincunx_render::{Image, psnr_db};
use quincunx_testkit::skip::skip;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn has_node() -> bool {
    Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
}

/// The bundled repositories (`quincunx demo --build-only`) and their exports, built once
/// per run: `(demo dir, export dir)`.
fn bundled() -> &'static (PathBuf, PathBuf) {
    static DIRS: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    DIRS.get_or_init(|| {
        let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-demo");
        let _ = std::fs::remove_dir_all(&root);
        let (demo, export) = (root.join("demo"), root.join("export"));
        let o = bin()
            .args(["demo", "--build-only", "--dir"])
            .arg(&demo)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        for name in ["korea", "earth", "earth_colour"] {
            let o = bin()
                .arg("export")
                .arg(demo.join(name))
                .arg(&export)
                .args(["--name", name])
                .output()
                .unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        (demo, export)
    })
}

/// `node --test web-demo/test/`: the module's golden and hostile-input tests, the
/// reconstruction of every bundled repository against `quincunx verify --json`, corrupt
/// and truncated blobs, and the client against a real server.
#[test]
fn node_test_suite() {
    if !has_node() {
        skip("node_test_suite", "REQUIRE_NODE", "node not found");
        return;
    }
    let (demo, export) = bundled();
    let o = Command::new("node")
        .arg("--test")
        .arg("--test-reporter=spec")
        .arg("web-demo/test/")
        .current_dir(workspace())
        .env("QUINCUNX_BIN", env!("CARGO_BIN_EXE_quincunx"))
        .env("QUINCUNX_DEMO_DIR", demo)
        .env("QUINCUNX_EXPORT_DIR", export)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    println!("{stdout}");
    assert!(
        o.status.success(),
        "node --test failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// `verify --json`'s `decoded_sha256` is the same through the in-memory and the streaming
/// (band of rows) decoder, on elevation and on colour.
#[test]
fn decoded_hash_in_memory_equals_streaming() {
    let (demo, _) = bundled();
    let hash = |repo: &Path, stream: bool| -> String {
        let mut cmd = bin();
        cmd.arg("verify").arg(repo).arg("--json");
        if stream {
            cmd.arg("--stream");
        }
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        v["decoded_sha256"].as_str().unwrap().to_string()
    };
    let korea = demo.join("korea");
    let h = hash(&korea, false);
    assert_eq!(h.len(), 64);
    assert_eq!(h, hash(&korea, true));
    let colour = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-demo-colour");
    common::build(
        &["--colour", "--rms-m", "4"],
        &workspace().join("data/fixture_gsi_color_256.jpg"),
        &colour,
    );
    assert_eq!(hash(&colour, false), hash(&colour, true));
    assert_ne!(hash(&colour, false), h);
}

/// A view of the browser test.
struct View {
    name: &'static str,
    repo: &'static str,
    colour: Option<&'static str>,
    /// `quincunx render`'s place flags and the page's query parameters, in pairs.
    place: &'static [(&'static str, &'static str)],
    /// Straight down inside the data: every pixel must be terrain.
    down: bool,
    /// Then fly (keys held for ms), and open the URL the page wrote in a new page.
    fly: Option<(&'static [&'static str], u32)>,
}

const VIEWS: [View; 3] = [
    View {
        name: "korea_down",
        repo: "korea",
        colour: None,
        place: &[
            ("uv", "0.5,0.5"),
            ("height_m", "20000"),
            ("pitch_deg", "-90"),
        ],
        down: true,
        fly: None,
    },
    View {
        name: "korea_oblique",
        repo: "korea",
        colour: None,
        place: &[
            ("uv", "0.5,0.5"),
            ("height_m", "2000"),
            ("pitch_deg", "-30"),
            ("heading_deg", "30"),
        ],
        down: false,
        fly: Some((&["KeyD", "KeyW"], 700)),
    },
    View {
        name: "earth_colour_down",
        repo: "earth",
        colour: Some("earth_colour"),
        place: &[
            ("lat_lon", "36,128"),
            ("height_m", "1000000"),
            ("pitch_deg", "-90"),
        ],
        down: true,
        fly: Some((&["KeyA"], 700)),
    },
];

/// Size of the compared images.
const SIZE: [u32; 2] = [640, 360];
/// The smallest PSNR (dB, RGB, peak 255) a browser screenshot may have against
/// `quincunx render`'s image of the same view.
const MIN_PSNR_DB: f64 = 40.0;
/// The smallest PSNR of a flown view against the same page's URL opened anew.
const MIN_SHARED_PSNR_DB: f64 = 40.0;
/// `quincunx render`'s default background.
const BACKGROUND: [u8; 3] = [135, 170, 210];

fn background_pixels(image: &Image) -> usize {
    image
        .rgba
        .chunks_exact(4)
        .filter(|p| p[..3] == BACKGROUND)
        .count()
}

/// Headless Chromium opens the demo page on each view, waits for full quality and
/// screenshots it; each screenshot is compared with `quincunx render`'s PNG of the same
/// view (PSNR >= [`MIN_PSNR_DB`]), straight-down views show no background pixel (no
/// crack, no hole), and no page logs an error.
#[test]
fn browser_views_match_render() {
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let playwright = workspace().join("web-demo/node_modules/playwright-core");
    let missing = if !has_node() {
        Some("node not found")
    } else if !Path::new(&chromium).exists() {
        Some("chromium not found (apt-get install chromium)")
    } else if !playwright.exists() {
        Some("web-demo/node_modules/playwright-core missing (npm ci in web-demo)")
    } else {
        None
    };
    if let Some(why) = missing {
        skip("browser_views_match_render", "REQUIRE_BROWSER", why);
        return;
    }
    let (demo, _) = bundled();
    let server = common::serve(&[
        ("korea", &demo.join("korea")),
        ("earth", &demo.join("earth")),
        ("earth_colour", &demo.join("earth_colour")),
    ]);
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-demo-browser");
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).unwrap();
    let size = format!("{}x{}", SIZE[0], SIZE[1]);

    // The references.
    let mut references = Vec::new();
    for v in &VIEWS {
        let png = out.join(format!("{}.render.png", v.name));
        let mut cmd = bin();
        cmd.args([
            "render",
            "--url",
            &server.url,
            "--repo",
            v.repo,
            "--size",
            &size,
        ])
        .arg("-o")
        .arg(&png)
        .arg("--json");
        if let Some(c) = v.colour {
            cmd.args(["--colour", c]);
        }
        for (k, val) in v.place {
            cmd.arg(format!("--{}={val}", k.replace('_', "-")));
        }
        let o = cmd.output().unwrap();
        if !o.status.success() {
            skip(
                &format!("comparison with quincunx render ({})", v.name),
                "REQUIRE_GPU",
                &format!(
                    "quincunx render: {}",
                    String::from_utf8_lossy(&o.stderr).trim()
                ),
            );
            references.push(None);
            continue;
        }
        println!(
            "render {}: {}",
            v.name,
            String::from_utf8_lossy(&o.stdout).trim()
        );
        references.push(Some(Image::read_png(&png).unwrap()));
    }

    // The browser.
    let views: Vec<serde_json::Value> = VIEWS
        .iter()
        .map(|v| {
            let mut query = format!("repo={}", v.repo);
            if let Some(c) = v.colour {
                query.push_str(&format!("&colour={c}"));
            }
            for (k, val) in v.place {
                query.push_str(&format!("&{k}={val}"));
            }
            let mut view = serde_json::json!({"name": v.name, "query": query, "size": SIZE});
            if let Some((keys, ms)) = v.fly {
                view["fly"] = serde_json::json!({"keys": keys, "ms": ms});
            }
            view
        })
        .collect();
    let views_file = out.join("views.json");
    std::fs::write(&views_file, serde_json::to_vec(&views).unwrap()).unwrap();
    let o = Command::new("node")
        .arg(workspace().join("web-demo/tools/browser-views.mjs"))
        .arg(&server.url)
        .arg(&out)
        .arg(&views_file)
        .env("CHROMIUM", &chromium)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(
        o.status.success(),
        "browser.mjs failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let results: Vec<serde_json::Value> = stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(results.len(), VIEWS.len(), "{stdout}");
    for ((v, r), reference) in VIEWS.iter().zip(&results).zip(&references) {
        let errors = r["console_errors"].as_array().unwrap();
        assert!(errors.is_empty(), "{}: console errors {errors:?}", v.name);
        let shot = Image::read_png(&out.join(format!("{}.png", v.name))).unwrap();
        assert_eq!([shot.width, shot.height], SIZE, "{}", v.name);
        let background = background_pixels(&shot);
        let psnr = reference
            .as_ref()
            .map(|reference| psnr_db(&shot, reference).unwrap());
        println!(
            "{}",
            serde_json::json!({
                "view": v.name,
                "psnr_db": psnr,
                "background_pixels": background,
                "time_to_full_quality_ms": r["stats"]["timeToFullQualityMs"],
                "wall_ms": r["wall_ms"],
                "triangles": r["stats"]["triangles"],
                "bytes": r["stats"]["bytesReceived"],
            })
        );
        if v.down {
            assert_eq!(
                background, 0,
                "{}: background pixels in a straight-down view",
                v.name
            );
        }
        if let Some(psnr) = psnr {
            assert!(
                psnr >= MIN_PSNR_DB,
                "{}: PSNR {psnr:.2} dB < {MIN_PSNR_DB}",
                v.name
            );
        }
        if v.fly.is_some() {
            // The URL the page wrote after flying names the view it shows: opened in a
            // new page, it looks the same, and more like the flown view than the start.
            let url = r["flown_url"].as_str().unwrap();
            assert!(url.contains("/view?"), "{}: {url}", v.name);
            let flown = Image::read_png(&out.join(format!("{}.flown.png", v.name))).unwrap();
            let shared = Image::read_png(&out.join(format!("{}.shared.png", v.name))).unwrap();
            let same = psnr_db(&flown, &shared).unwrap();
            let moved = psnr_db(&flown, &shot).unwrap();
            println!(
                "{}",
                serde_json::json!({"view": v.name, "flown_url": url, "shared_psnr_db": same,
                    "flown_vs_start_psnr_db": moved})
            );
            assert!(
                same >= MIN_SHARED_PSNR_DB,
                "{}: the shared URL's view differs: PSNR {same:.2} dB",
                v.name
            );
            assert!(
                same > moved + 3.0,
                "{}: flying did not move the view ({moved:.2} dB)",
                v.name
            );
        }
    }
}
