//! A client's cost follows its view, not the repository: `quincunx fly` of the same
//! distant view of two planets built here from the bundled ETOPO20 grid, one with 256
//! times the other's samples (128 and 2048 per cube face side), served by
//! `quincunx serve`, peaks at the same resident memory with about the same DAG.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};

use common::{bin, build, serve};
use serde_json::Value;

fn build_planet(face_side: usize, out: &Path) {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/etopo20_global.json");
    let side = face_side.to_string();
    let args = [
        "--planet",
        "--max-error-m",
        "50",
        "--face-side",
        side.as_str(),
    ];
    build(&args, &input, out);
}

/// One held view of the whole Earth from 40,000 km.
fn distant_view(dir: &Path) -> PathBuf {
    let r = 6_371_008.8 + 4.0e7;
    let d = [1.0f64, 0.3, 0.5];
    let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
    let eye: Vec<f64> = d.iter().map(|x| x / len * r).collect();
    let flight = serde_json::json!({
        "legs": [{
            "duration_s": 10,
            "jump": true,
            "settle_s": 0.5,
            "from": { "eye": eye, "target": [0.0, 0.0, 0.0] }
        }]
    });
    let path = dir.join("distant.json");
    std::fs::write(&path, flight.to_string()).unwrap();
    path
}

fn fly(url: &str, repo: &str, path: &Path) -> Value {
    let o = bin()
        .args(["fly", "--json", "--url", url, "--repo", repo, "--path"])
        .arg(path)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(o.status.success(), "fly failed: {stderr}");
    serde_json::from_slice(&o.stdout).unwrap()
}

fn f(v: &Value, k: &str) -> f64 {
    v[k].as_f64()
        .unwrap_or_else(|| panic!("{k} is not a number: {v}"))
}

#[test]
fn a_planet_256_times_larger_costs_its_client_the_same_memory() {
    let dir = tempfile::tempdir().unwrap();
    let (small, big) = (dir.path().join("small"), dir.path().join("big"));
    build_planet(128, &small);
    build_planet(2048, &big);
    let server = serve(&[("small", &small), ("big", &big)]);
    let path = distant_view(dir.path());
    let a = fly(&server.url, "small", &path);
    let b = fly(&server.url, "big", &path);
    for r in [&a, &b] {
        assert_eq!(f(r, "jumps_unfinished"), 0.0, "{r}");
        assert_eq!(f(r, "cracks"), 0.0, "{r}");
    }
    let (rss_a, rss_b) = (f(&a, "client_peak_rss_mb"), f(&b, "client_peak_rss_mb"));
    eprintln!(
        "client peak RSS {rss_a:.1} MB (128 per face side) vs {rss_b:.1} MB (2048); \
         session open {:.1} vs {:.1} ms; diamonds {} vs {}, DAG bytes {} vs {}",
        f(&a, "session_open_ms"),
        f(&b, "session_open_ms"),
        a["diamonds_per_frame_max"],
        b["diamonds_per_frame_max"],
        a["dag_bytes_max"],
        b["dag_bytes_max"]
    );
    // The view wants about the same cut of both (the distant Earth is coarser than
    // either's finest level; the builds' side information differs a little).
    let (da, db) = (f(&a, "dag_bytes_max"), f(&b, "dag_bytes_max"));
    assert!(
        (da - db).abs() <= 0.1 * da.max(db),
        "DAG {da} vs {db} bytes"
    );
    // Tables of the big planet's 130,000 diamonds would add tens of MB (measured with
    // them: see docs/streaming.md); allocator noise is a few MB.
    assert!(
        (rss_b - rss_a).abs() < 4.0,
        "client peak RSS {rss_a:.1} MB vs {rss_b:.1} MB"
    );
}
