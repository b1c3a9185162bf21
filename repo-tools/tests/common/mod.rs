//! Shared helpers of the `quincunx` binary's end-to-end tests: the binary, raw tiles
//! for mosaics, and `quincunx serve` on a free port.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The `quincunx` binary under test.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_quincunx"))
}

/// `quincunx build <args> --overwrite -o <out> <input>`, which must succeed.
pub fn build(args: &[&str], input: &Path, out: &Path) {
    let o = bin()
        .arg("build")
        .args(args)
        .arg("--overwrite")
        .arg("-o")
        .arg(out)
        .arg(input)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A rectangle of a grid, every `step`-th sample.
pub fn crop(
    values: &[f64],
    width: usize,
    rows: std::ops::RangeInclusive<usize>,
    cols: std::ops::RangeInclusive<usize>,
    step: usize,
) -> (usize, usize, Vec<f64>) {
    let rows: Vec<usize> = rows.step_by(step).collect();
    let cols: Vec<usize> = cols.step_by(step).collect();
    let mut out = Vec::with_capacity(rows.len() * cols.len());
    for &r in &rows {
        out.extend(cols.iter().map(|&c| values[r * width + c]));
    }
    (cols.len(), rows.len(), out)
}

/// Writes a node-registered raw `int16` tile (`NAME.i16` + `NAME.json`; NaN = -32768)
/// whose first sample is at (`west`, `north`) with spacing `d` degrees.
pub fn write_raw(
    dir: &Path,
    name: &str,
    tile: &(usize, usize, Vec<f64>),
    west: f64,
    north: f64,
    d: f64,
) {
    write_raw_crs(dir, name, tile, west, north, d, "EPSG:4326");
}

pub fn write_raw_crs(
    dir: &Path,
    name: &str,
    (w, h, values): &(usize, usize, Vec<f64>),
    west: f64,
    north: f64,
    d: f64,
    crs: &str,
) {
    let bytes: Vec<u8> = values
        .iter()
        .flat_map(|&v| (if v.is_nan() { -32768 } else { v as i16 }).to_le_bytes())
        .collect();
    std::fs::write(dir.join(format!("{name}.i16")), bytes).unwrap();
    let sidecar = serde_json::json!({
        "file": format!("{name}.i16"),
        "width": w,
        "height": h,
        "dtype": "int16",
        "nodata": -32768,
        "crs": crs,
        "registration": "node",
        "georef": {
            "west": west,
            "north": north,
            "east": west + (*w - 1) as f64 * d,
            "south": north - (*h - 1) as f64 * d,
        },
    });
    std::fs::write(dir.join(format!("{name}.json")), sidecar.to_string()).unwrap();
}

/// `quincunx serve` on a free port; killed on drop.
pub struct Server {
    child: Child,
    pub url: String,
}

impl Server {
    /// The server's resident memory now, in bytes (Linux `/proc`).
    pub fn rss_bytes(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let kb: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap_or_else(|| panic!("no VmRSS in {status}"));
        kb * 1024
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Serves each `(name, path)` repository.
pub fn serve(repos: &[(&str, &Path)]) -> Server {
    serve_with(repos, &[])
}

/// [`serve`] with more `quincunx serve` flags.
pub fn serve_with(repos: &[(&str, &Path)], flags: &[&str]) -> Server {
    let mut cmd = bin();
    cmd.args(["serve", "--addr", "127.0.0.1:0"]).args(flags);
    for (name, path) in repos {
        cmd.arg("--repo").arg(format!("{name}={}", path.display()));
    }
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    // "serving on http://127.0.0.1:PORT/  (...)"
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .trim_end_matches('/')
        .to_string();
    Server { child, url }
}

/// A run's exit and output.
pub struct Run {
    pub success: bool,
    pub stderr: String,
    pub stdout: String,
}

/// Runs `cmd` (stdin closed), killing it after `limit`: a run that needs the kill fails
/// the test.
pub fn run_within(cmd: &mut Command, limit: Duration) -> Run {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = child.stdout.take().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{cmd:?} did not end within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let run = Run {
        success: status.success(),
        stdout: out.join().unwrap(),
        stderr: err.join().unwrap(),
    };
    assert!(
        !run.stderr.contains("panicked") && status.code().is_some(),
        "{cmd:?} crashed ({status}): {}",
        run.stderr
    );
    run
}
