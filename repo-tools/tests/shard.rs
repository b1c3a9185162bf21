//! Sharded builds through the binary: `build --shard K/N` as N concurrent processes, then
//! `merge`, publish the content hash of one `build` with the same options (1, 2, 3 and 7
//! shards, lossless and max error, dense and sparse); a killed shard rerun alone gives
//! the same repository; parts of different builds, missing parts and damaged parts are
//! clear errors. Planets likewise: a global grid (1, 2, 3 and 7 shards) and mosaics,
//! dense and sparse.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_quincunx"))
}

fn korea() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json")
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
    serde_json::from_slice(&out.stdout).unwrap()
}

fn refused(cmd: &mut Command) -> String {
    let out = run(cmd);
    assert!(!out.status.success(), "succeeded: {cmd:?}");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The options every build here shares: out of core at 20 MB.
fn build(rate: &[&str]) -> Command {
    let mut c = bin();
    c.arg("build")
        .arg(korea())
        .args(rate)
        .args(["--memory-budget-mb", "20", "--json"]);
    c
}

/// One `build`; its JSON summary.
fn single(dir: &Path, rate: &[&str]) -> serde_json::Value {
    let s = ok_json(build(rate).arg("-o").arg(dir.join("single")));
    assert_eq!(s["out_of_core"], true, "{s}");
    s
}

/// `count` shards as concurrent processes, then `merge`; the merge's JSON summary.
fn sharded(dir: &Path, rate: &[&str], count: usize) -> serde_json::Value {
    sharded_with(dir, count, || build(rate))
}

/// `count` shards of the build `cmd` gives as concurrent processes, then `merge`; the
/// merge's JSON summary.
fn sharded_with(dir: &Path, count: usize, cmd: impl Fn() -> Command) -> serde_json::Value {
    let parts: Vec<PathBuf> = (0..count).map(|k| dir.join(format!("part{k}"))).collect();
    let children: Vec<_> = parts
        .iter()
        .enumerate()
        .map(|(k, p)| {
            cmd()
                .args(["--shard", &format!("{k}/{count}"), "-o"])
                .arg(p)
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for c in children {
        let out = c.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "shard failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let s: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert!(s["window_rows"].as_u64().unwrap() >= s["band_rows"].as_u64().unwrap());
    }
    // Any order.
    ok_json(
        bin()
            .arg("merge")
            .args(parts.iter().rev())
            .arg("-o")
            .arg(dir.join("merged"))
            .arg("--json"),
    )
}

#[test]
fn merged_shards_publish_the_single_builds_content_hash() {
    for rate in [
        &["--max-error-m", "2"][..],
        &["--lossless"][..],
        &["--max-error-m", "1", "--sparse"][..],
        &["--max-error-m", "2", "--bounds", "measured"][..],
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let one = single(tmp.path(), rate);
        let counts: &[usize] = if rate[0] == "--max-error-m" && rate.len() == 2 {
            &[1, 2, 3, 7]
        } else {
            &[3]
        };
        for &count in counts {
            let dir = tmp.path().join(format!("n{count}"));
            std::fs::create_dir(&dir).unwrap();
            let merged = sharded(&dir, rate, count);
            assert_eq!(
                merged["content_hash"], one["content_hash"],
                "{rate:?}, {count} shards"
            );
            assert_eq!(merged["blob_count"], one["blob_count"]);
        }
        if rate.contains(&"measured") {
            // The bound pass (its own process) keeps the budget too, and the in-memory
            // build publishes the same bytes.
            let peak = one["peak_rss_mb"].as_f64().unwrap();
            assert!(peak <= 20.0, "peak {peak} MB over a 20 MB budget: {one}");
            let mem = ok_json(
                bin()
                    .arg("build")
                    .arg(korea())
                    .args(rate)
                    .arg("--json")
                    .arg("-o")
                    .arg(tmp.path().join("in-memory")),
            );
            assert_eq!(mem["content_hash"], one["content_hash"]);
            let info = ok_json(
                bin()
                    .arg("info")
                    .arg(tmp.path().join("single"))
                    .arg("--json"),
            );
            assert_eq!(info["metadata"]["build"]["bounds"], "measured", "{info}");
        }
    }
}

#[test]
fn a_killed_shard_rerun_alone_gives_the_same_repository() {
    let rate = ["--max-error-m", "2"];
    let tmp = tempfile::tempdir().unwrap();
    let one = single(tmp.path(), &rate);
    kill_and_rerun(tmp.path(), &one, || build(&rate));
    // A planet's shard likewise.
    let tmp = tempfile::tempdir().unwrap();
    let etopo = bundled("etopo20_global.json");
    let planet_rate = ["--max-error-m", "10"];
    let one = ok_json(
        planet(&etopo, &planet_rate, 512)
            .arg("-o")
            .arg(tmp.path().join("single")),
    );
    kill_and_rerun(tmp.path(), &one, || planet(&etopo, &planet_rate, 512));
}

/// Shards 0 and 2 of 3 of the build `cmd` gives; shard 1 stalled and killed (the merge
/// refuses the missing part), then rerun alone: the merge gives `one`'s content hash.
fn kill_and_rerun(dir: &Path, one: &serde_json::Value, cmd: impl Fn() -> Command) {
    let parts: Vec<PathBuf> = (0..3).map(|k| dir.join(format!("part{k}"))).collect();
    for k in [0, 2] {
        ok_json(
            cmd()
                .args(["--shard", &format!("{k}/3"), "-o"])
                .arg(&parts[k]),
        );
    }
    // Shard 1 stalls after 50 diamonds' details and is killed.
    let mut child = cmd()
        .args(["--shard", "1/3", "--stall-after-blobs", "50", "-o"])
        .arg(&parts[1])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let partial = dir.join("part1.partial");
    for _ in 0..600 {
        if partial.join("details.bin").exists() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    std::thread::sleep(std::time::Duration::from_millis(500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "the shard ended before it was killed"
    );
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(partial.exists() && !parts[1].exists());
    // The merge refuses the missing part, naming it.
    let e = refused(
        bin()
            .arg("merge")
            .args(&parts)
            .arg("-o")
            .arg(dir.join("merged")),
    );
    assert!(
        e.contains("part1") && e.contains("finished shard part"),
        "{e}"
    );
    assert!(!dir.join("merged").exists());
    // Rerun alone.
    ok_json(cmd().args(["--shard", "1/3", "-o"]).arg(&parts[1]));
    assert!(!partial.exists());
    let merged = ok_json(
        bin()
            .arg("merge")
            .args(&parts)
            .arg("-o")
            .arg(dir.join("merged"))
            .arg("--json"),
    );
    assert_eq!(merged["content_hash"], one["content_hash"]);
    // A finished part is not overwritten without --overwrite.
    let e = refused(cmd().args(["--shard", "1/3", "-o"]).arg(&parts[1]));
    assert!(e.contains("already exists"), "{e}");
}

#[test]
fn parts_of_different_builds_and_damaged_parts_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let part = |rate: &[&str], k: usize, name: &str| {
        ok_json(
            build(rate)
                .args(["--shard", &format!("{k}/2"), "-o"])
                .arg(t.join(name)),
        );
        t.join(name)
    };
    let a0 = part(&["--max-error-m", "2"], 0, "a0");
    let a1 = part(&["--max-error-m", "2"], 1, "a1");
    let b1 = part(&["--max-error-m", "1"], 1, "b1");
    let merge =
        |parts: &[&PathBuf]| refused(bin().arg("merge").args(parts).arg("-o").arg(t.join("out")));
    let e = merge(&[&a0, &b1]);
    assert!(e.contains("not from the same build"), "{e}");
    let e = merge(&[&a0]);
    assert!(e.contains("missing part(s): 1"), "{e}");
    let e = merge(&[&a0, &a0]);
    assert!(e.contains("given twice"), "{e}");
    // A truncated part file, and truncated details.
    let cut = t.join("cut");
    std::fs::create_dir(&cut).unwrap();
    let bytes = std::fs::read(a1.join("part.bin")).unwrap();
    std::fs::write(cut.join("part.bin"), &bytes[..bytes.len() / 2]).unwrap();
    let e = merge(&[&a0, &cut]);
    assert!(e.contains("truncated") && e.contains("cut"), "{e}");
    std::fs::write(cut.join("part.bin"), &bytes).unwrap();
    let details = std::fs::read(a1.join("details.bin")).unwrap();
    std::fs::write(cut.join("details.bin"), &details[..details.len() - 3]).unwrap();
    let e = merge(&[&a0, &cut]);
    assert!(e.contains("details.bin") && e.contains("truncated"), "{e}");
    assert!(!t.join("out").exists() && !t.join("out.partial").exists());
    // Requests a shard cannot do.
    let shard = |extra: &[&str]| {
        let mut c = bin();
        c.arg("build")
            .arg(korea())
            .args(extra)
            .arg("-o")
            .arg(t.join("x"));
        refused(&mut c)
    };
    assert!(shard(&["--shard", "2/2", "--memory-budget-mb", "20"]).contains("K runs from 0"));
    assert!(shard(&["--shard", "0/2"]).contains("--memory-budget-mb"));
    let e = shard(&["--shard", "0/2", "--memory-budget-mb", "20", "--rms-m", "9"]);
    assert!(e.contains("RMS"), "{e}");
    let e = shard(&["--shard", "0/2", "--memory-budget-mb", "20", "--colour"]);
    assert!(e.contains("colour builds in one process"), "{e}");
    assert!(!t.join("x").exists());
}

#[test]
fn the_slurm_array_scripts_build_and_merge() {
    let tmp = tempfile::tempdir().unwrap();
    let one = single(tmp.path(), &["--max-error-m", "2"]);
    let deploy = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/slurm");
    let script = |name: &str| {
        let mut c = Command::new("bash");
        c.arg(deploy.join(name))
            .env("QUINCUNX", env!("CARGO_BIN_EXE_quincunx"))
            .env("SRC", korea())
            .env("PARTS", tmp.path().join("parts"))
            .env("OUT", tmp.path().join("repo"))
            .env("RATE", "--max-error-m 2")
            .env("BUDGET_MB", "20")
            .env("SLURM_ARRAY_TASK_COUNT", "3");
        c
    };
    // Task 1 twice (a rerun replaces its part), as Slurm would run a resubmitted task.
    for k in ["0", "1", "2", "1"] {
        ok_json(script("shard.sbatch").env("SLURM_ARRAY_TASK_ID", k));
    }
    let merged = ok_json(&mut script("merge.sbatch"));
    assert_eq!(merged["content_hash"], one["content_hash"]);
}

fn bundled(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

/// A planet build of `input` on a cube of face side `face_side` (512: 1.6 M samples, out
/// of core at 24 MB; 1024: 6.3 M samples, at 48 MB).
fn planet(input: &Path, rate: &[&str], face_side: usize) -> Command {
    let budget = if face_side > 512 { "48" } else { "24" };
    let mut c = bin();
    c.arg("build")
        .arg(input)
        .args(["--planet", "--face-side", &face_side.to_string()])
        .args(rate)
        .args(["--memory-budget-mb", budget, "--json"]);
    c
}

/// The single build (out of core) and `counts` sharded ones of `cmd` in `dir`: the same
/// content hash.
fn cases(dir: &Path, what: &str, counts: &[usize], cmd: impl Fn() -> Command) {
    let one = ok_json(cmd().arg("-o").arg(dir.join("single")));
    assert_eq!(one["out_of_core"], true, "{one}");
    for &count in counts {
        let sub = dir.join(format!("n{count}"));
        std::fs::create_dir(&sub).unwrap();
        let merged = sharded_with(&sub, count, &cmd);
        assert_eq!(
            merged["content_hash"], one["content_hash"],
            "{what}, {count} shards"
        );
        assert_eq!(merged["blob_count"], one["blob_count"], "{what}");
        assert_eq!(merged["samples"], one["samples"], "{what}");
    }
}

#[test]
fn planet_and_mosaic_shards_publish_the_single_builds_content_hash() {
    let tmp = tempfile::tempdir().unwrap();
    let etopo = bundled("etopo20_global.json");
    // A global grid.
    for (rate, counts, name) in [
        (&["--max-error-m", "10"][..], &[1, 2, 3, 7][..], "max"),
        (&["--lossless"][..], &[3][..], "lossless"),
    ] {
        let dir = tmp.path().join(name);
        std::fs::create_dir(&dir).unwrap();
        cases(&dir, name, counts, || planet(&etopo, rate, 512));
    }
    // Mosaics: the korea crop as four tiles and a copy of one over a cube corner (35.26N
    // 45E), over ETOPO 20' (dense), and alone (a sparse planet, holes elsewhere).
    let k = quincunx_repo_tools::input::read_heights(&korea()).unwrap();
    let tiles = tmp.path().join("tiles");
    std::fs::create_dir(&tiles).unwrap();
    let srtm3 = 1.0 / 1200.0;
    for (name, r, c) in [
        ("nw", 0, 0),
        ("ne", 0, 512),
        ("sw", 512, 0),
        ("se", 512, 512),
    ] {
        let tile = common::crop(&k.grid.values_m, 1025, r..=r + 512, c..=c + 512, 1);
        let (west, north) = (126.0 + c as f64 * srtm3, 38.0 - r as f64 * srtm3);
        common::write_raw(&tiles, name, &tile, west, north, srtm3);
    }
    let corner = common::crop(&k.grid.values_m, 1025, 0..=512, 0..=512, 1);
    common::write_raw(&tiles, "corner", &corner, 44.8, 35.5, srtm3);
    let names = "nw.json\nne.json\nsw.json\nse.json\ncorner.json\n";
    let dense = tiles.join("dense.txt");
    std::fs::write(&dense, format!("{}\n{names}", etopo.display())).unwrap();
    let sparse = tiles.join("sparse.txt");
    std::fs::write(&sparse, names).unwrap();
    for (list, name) in [(&dense, "dense mosaic"), (&sparse, "sparse mosaic")] {
        let dir = tmp.path().join(name.replace(' ', "-"));
        std::fs::create_dir(&dir).unwrap();
        cases(&dir, name, &[3], || {
            planet(list, &["--max-error-m", "2"], 1024)
        });
    }
    // A planar mosaic: the north-west tile and a copy of the south-east one a degree
    // away (a 2316 x 1716 grid, holes between them), 3 shards.
    let far = common::crop(&k.grid.values_m, 1025, 512..=1024, 512..=1024, 1);
    common::write_raw(&tiles, "far", &far, 127.4, 37.4, srtm3);
    let planar = tiles.join("planar.txt");
    std::fs::write(&planar, "nw.json\nfar.json\n").unwrap();
    let dir = tmp.path().join("planar-mosaic");
    std::fs::create_dir(&dir).unwrap();
    cases(&dir, "planar mosaic", &[3], || {
        let mut c = bin();
        c.arg("build")
            .arg(&planar)
            .args(["--max-error-m", "2", "--memory-budget-mb", "32"])
            .arg("--json");
        c
    });
    // Planet and planar parts do not merge together.
    let t = tmp.path();
    ok_json(
        planet(&etopo, &["--max-error-m", "10"], 512)
            .args(["--shard", "0/2", "-o"])
            .arg(t.join("p0")),
    );
    ok_json(
        build(&["--max-error-m", "2"])
            .args(["--shard", "1/2", "-o"])
            .arg(t.join("q1")),
    );
    let e = refused(
        bin()
            .arg("merge")
            .arg(t.join("p0"))
            .arg(t.join("q1"))
            .arg("-o")
            .arg(t.join("mixed")),
    );
    assert!(e.contains("not from the same build"), "{e}");
    assert!(!t.join("mixed").exists());
    let e = refused(
        planet(&etopo, &["--rms-m", "9"], 512)
            .args(["--shard", "0/2", "-o"])
            .arg(t.join("r0")),
    );
    assert!(e.contains("RMS"), "{e}");
}
