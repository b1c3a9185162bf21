//! Sharded builds through the binary: `build --shard K/N` as N concurrent processes, then
//! `merge`, publish the content hash of one `build` with the same options (1, 2, 3 and 7
//! shards, lossless and max error, dense and sparse); a killed shard rerun alone gives
//! the same repository; parts of different builds, missing parts and damaged parts are
//! clear errors.

#![allow(clippy::unwrap_used, clippy::expect_used)]

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
    let parts: Vec<PathBuf> = (0..count).map(|k| dir.join(format!("part{k}"))).collect();
    let children: Vec<_> = parts
        .iter()
        .enumerate()
        .map(|(k, p)| {
            build(rate)
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
    }
}

#[test]
fn a_killed_shard_rerun_alone_gives_the_same_repository() {
    let tmp = tempfile::tempdir().unwrap();
    let rate = ["--max-error-m", "2"];
    let one = single(tmp.path(), &rate);
    let parts: Vec<PathBuf> = (0..3)
        .map(|k| tmp.path().join(format!("part{k}")))
        .collect();
    for k in [0, 2] {
        ok_json(
            build(&rate)
                .args(["--shard", &format!("{k}/3"), "-o"])
                .arg(&parts[k]),
        );
    }
    // Shard 1 stalls after 50 diamonds' details and is killed.
    let mut child = build(&rate)
        .args(["--shard", "1/3", "--stall-after-blobs", "50", "-o"])
        .arg(&parts[1])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let partial = tmp.path().join("part1.partial");
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
            .arg(tmp.path().join("merged")),
    );
    assert!(
        e.contains("part1") && e.contains("finished shard part"),
        "{e}"
    );
    assert!(!tmp.path().join("merged").exists());
    // Rerun alone.
    ok_json(build(&rate).args(["--shard", "1/3", "-o"]).arg(&parts[1]));
    assert!(!partial.exists());
    let merged = ok_json(
        bin()
            .arg("merge")
            .args(&parts)
            .arg("-o")
            .arg(tmp.path().join("merged"))
            .arg("--json"),
    );
    assert_eq!(merged["content_hash"], one["content_hash"]);
    // A finished part is not overwritten without --overwrite.
    let e = refused(build(&rate).args(["--shard", "1/3", "-o"]).arg(&parts[1]));
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
    let e = shard(&["--shard", "0/2", "--memory-budget-mb", "20", "--planet"]);
    assert!(e.contains("planar elevation"), "{e}");
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
