//! Shared helpers of the `quincunx` binary's end-to-end tests: the binary, and
//! `quincunx serve` on a free port.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

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
