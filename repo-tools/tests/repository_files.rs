//! Repositories as immutable, shareable artifacts, through the real binary: every kind of
//! damage is a clear error from every tool within 10 s; any number of readers (two servers,
//! verify, export, info) share one repository at once, also from read-only files of another
//! user, and leave its bytes and times as they were; a build killed at any step of an
//! `--overwrite` publication leaves a readable repository at the path.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

const PACK: &str = "repository.pack";

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_quincunx"))
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// Runs `cmd` for at most `limit`; `None` if it had to be killed.
fn run_within(cmd: &mut Command, limit: Duration) -> Option<Output> {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run quincunx");
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            child.kill().unwrap();
            child.wait().unwrap();
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    Some(out)
}

fn ok(cmd: &mut Command) -> Output {
    let out = run_within(cmd, Duration::from_secs(120)).expect("finishes");
    assert!(
        out.status.success(),
        "failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn json(out: &Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A small lossless repository (Jacksboro fault fixture) at `path`.
fn build(path: &Path, extra: &[&str]) -> serde_json::Value {
    json(&ok(bin()
        .args(["build", "--lossless", "--json", "-o"])
        .arg(path)
        .args(extra)
        .arg(fixture("jacksboro.json"))))
}

fn content_hash(path: &Path) -> String {
    let v = json(&ok(bin().arg("info").arg(path).arg("--json")));
    v["metadata"]["content_hash"].as_str().unwrap().to_string()
}

/// A running `quincunx serve` of one repository named `r`.
struct Server {
    child: Child,
    addr: String,
}

impl Server {
    /// Starts it; `Err` with its stderr if it exits instead (within 10 s).
    fn start(repo: &Path) -> Result<Server, String> {
        let mut child = bin()
            .args(["serve", "--addr", "127.0.0.1:0", "--repo"])
            .arg(format!("r={}", repo.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                if let Some(rest) = line.split("http://").nth(1) {
                    let _ = tx.send(rest.split('/').next().unwrap_or("").to_string());
                }
            }
        });
        match rx.recv_timeout(Duration::from_secs(10)) {
            Ok(addr) => Ok(Server { child, addr }),
            Err(_) => {
                let _ = child.kill();
                let out = child.wait_with_output().unwrap();
                Err(String::from_utf8_lossy(&out.stderr).into_owned())
            }
        }
    }

    /// Status of `GET path` on a fresh connection.
    fn status(&self, path: &str) -> u16 {
        let mut s = std::net::TcpStream::connect(&self.addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n\r\n",
            self.addr
        )
        .unwrap();
        let mut answer = Vec::new();
        s.read_to_end(&mut answer).unwrap();
        let head = String::from_utf8_lossy(&answer[..answer.len().min(12)]).into_owned();
        head.get(9..12)
            .and_then(|c| c.parse().ok())
            .unwrap_or_else(|| panic!("no status in {head:?}"))
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Blob URL paths of a repository named `r` (from a static export of it).
fn blob_paths(repo: &Path) -> Vec<String> {
    let dir = tempfile::tempdir().unwrap();
    ok(bin()
        .arg("export")
        .arg(repo)
        .arg(dir.path())
        .args(["--name", "r"]));
    let mut out = Vec::new();
    let mut stack = vec![dir.path().to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.components().any(|c| c.as_os_str() == "d") {
                let rel = p.strip_prefix(dir.path()).unwrap();
                out.push(format!("/{}", rel.display()));
            }
        }
    }
    out.sort();
    out
}

/// Names, bytes and modification times of the files of a repository directory.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>, std::time::SystemTime)> {
    let mut out: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            let modified = std::fs::metadata(&p).unwrap().modified().unwrap();
            (p.clone(), std::fs::read(&p).unwrap(), modified)
        })
        .collect();
    out.sort();
    out
}

#[test]
fn every_kind_of_damage_is_a_clear_error_from_every_tool_within_10_s() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good");
    build(&good, &[]);
    let paths = blob_paths(&good);
    let clean = std::fs::read(good.join(PACK)).unwrap();
    let n = clean.len();
    let header = quincunx_store::pack::Header::parse(&clean).unwrap();
    let at = |offset: u64| offset as usize;
    let invert = |at: usize| {
        let mut b = clean.clone();
        for x in &mut b[at..at + 16] {
            *x = !*x;
        }
        Some(b)
    };
    // (kind, file bytes (None: no file), damage that `open` finds (false: only blob reads))
    let kinds: Vec<(&str, Option<Vec<u8>>, bool)> = vec![
        (
            "16 bytes inverted amid the blobs",
            invert(at(header.blobs.offset + header.blobs.len / 2)),
            false,
        ),
        (
            "root directory inverted",
            invert(at(header.root.offset)),
            true,
        ),
        (
            "metadata inverted",
            invert(at(header.metadata.offset + header.metadata.len / 2)),
            true,
        ),
        ("header inverted", invert(40), true),
        ("magic inverted", invert(0), true),
        ("truncated to half", Some(clean[..n / 2].to_vec()), true),
        ("empty file", Some(Vec::new()), true),
        ("no repository file", None, true),
    ];
    let limit = Duration::from_secs(10);
    for (kind, bytes, at_open) in kinds {
        let slug: String = kind
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        let repo = dir.path().join(&slug);
        std::fs::create_dir(&repo).unwrap();
        if let Some(b) = &bytes {
            std::fs::write(repo.join(PACK), b).unwrap();
        }
        let out_dir = dir.path().join(format!("{slug}-export"));
        let preview = dir.path().join(format!("{slug}.png"));
        let tools: Vec<(&str, Command)> = vec![
            ("info", {
                let mut c = bin();
                c.arg("info").arg(&repo);
                c
            }),
            ("verify", {
                let mut c = bin();
                c.arg("verify").arg(&repo);
                c
            }),
            ("export", {
                let mut c = bin();
                c.arg("export").arg(&repo).arg(&out_dir);
                c
            }),
            ("preview", {
                let mut c = bin();
                c.arg("preview").arg(&repo).arg("-o").arg(&preview);
                c
            }),
        ];
        for (tool, mut cmd) in tools {
            let out = run_within(&mut cmd, limit)
                .unwrap_or_else(|| panic!("{tool} on {kind}: still running after 10 s"));
            let stderr = String::from_utf8_lossy(&out.stderr);
            if tool == "info" && !at_open {
                // info reads the header, root directory and metadata, not the blobs.
                assert!(out.status.success(), "info on {kind}: {stderr}");
                continue;
            }
            assert_eq!(out.status.code(), Some(1), "{tool} on {kind}: {stderr}");
            assert!(stderr.starts_with("error:"), "{tool} on {kind}: {stderr}");
            assert!(
                stderr.contains(&*repo.to_string_lossy()),
                "{tool} on {kind}: the error does not name the repository: {stderr}"
            );
        }
        let started = Instant::now();
        match Server::start(&repo) {
            Err(stderr) => {
                assert!(at_open, "serve refused {kind}: {stderr}");
                assert!(
                    stderr.contains(&*repo.to_string_lossy()),
                    "serve on {kind}: {stderr}"
                );
                assert!(
                    started.elapsed() < limit,
                    "serve took {:?}",
                    started.elapsed()
                );
            }
            Ok(server) => {
                assert!(!at_open, "serve started on {kind}");
                // The damaged blobs answer 500, every other one 200.
                let statuses: Vec<u16> = paths.iter().map(|p| server.status(p)).collect();
                let failed = statuses.iter().filter(|&&s| s == 500).count();
                assert!(failed > 0, "no damaged blob failed");
                assert_eq!(
                    failed + statuses.iter().filter(|&&s| s == 200).count(),
                    statuses.len(),
                    "{statuses:?}"
                );
                assert!(
                    failed < statuses.len() / 2,
                    "{failed} of {}",
                    statuses.len()
                );
                assert_eq!(server.status("/repos/r/metadata.json"), 200);
            }
        }
    }
}

#[test]
fn two_servers_and_every_tool_read_one_repository_at_once_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("repo");
    build(&repo, &[]);
    let paths = blob_paths(&repo);
    let before = snapshot(&repo);
    std::thread::sleep(Duration::from_millis(20));
    let servers = [Server::start(&repo).unwrap(), Server::start(&repo).unwrap()];
    let export = dir.path().join("export");
    let mut readers: Vec<Child> = [
        vec!["verify".into(), repo.display().to_string()],
        vec![
            "export".into(),
            repo.display().to_string(),
            export.display().to_string(),
        ],
        vec!["info".into(), repo.display().to_string()],
        vec!["info".into(), repo.display().to_string(), "--json".into()],
    ]
    .into_iter()
    .map(|args| {
        bin()
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    })
    .collect();
    for server in &servers {
        for p in paths.iter().step_by(7) {
            assert_eq!(server.status(p), 200, "{p}");
        }
    }
    for r in &mut readers {
        let status = r.wait().unwrap();
        let mut stderr = String::new();
        r.stderr
            .take()
            .unwrap()
            .read_to_string(&mut stderr)
            .unwrap();
        assert!(status.success(), "{stderr}");
    }
    for server in &servers {
        assert_eq!(server.status("/repos/r/metadata.json"), 200);
    }
    drop(servers);
    assert_eq!(snapshot(&repo), before, "a reader changed the repository");
}

#[test]
fn a_read_only_repository_of_another_user_is_read_and_left_as_it_was() {
    use std::os::unix::fs::PermissionsExt;
    let test = "a_read_only_repository_of_another_user_is_read_and_left_as_it_was";
    let dir = tempfile::tempdir().unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let repo = dir.path().join("repo");
    build(&repo, &[]);
    let pack = repo.join(PACK);
    std::fs::set_permissions(&pack, std::fs::Permissions::from_mode(0o444)).unwrap();
    std::fs::set_permissions(&repo, std::fs::Permissions::from_mode(0o555)).unwrap();
    let before = snapshot(&repo);
    // Root reads anything: run the tools as `nobody` when we are root, so the files belong
    // to another user and their modes apply.
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.starts_with(b"0\n"));
    let as_reader = |args: &[&std::ffi::OsStr]| -> Command {
        if root {
            let mut c = Command::new("setpriv");
            c.args(["--reuid=65534", "--regid=65534", "--clear-groups", "--"])
                .arg(env!("CARGO_BIN_EXE_quincunx"))
                .args(args);
            c
        } else {
            let mut c = bin();
            c.args(args);
            c
        }
    };
    if root {
        let probe = as_reader(&["--version".as_ref()]).output();
        if !probe.is_ok_and(|o| o.status.success()) {
            quincunx_testkit::skip::skip(
                test,
                "REQUIRE_SETPRIV",
                "user nobody cannot run the test binary here (setpriv)",
            );
            return;
        }
    } else {
        println!("{test}: not root, so the repository is read-only but our own");
    }
    let export = dir.path().join("export");
    std::fs::create_dir(&export).unwrap();
    std::fs::set_permissions(&export, std::fs::Permissions::from_mode(0o777)).unwrap();
    for args in [
        vec!["info".as_ref(), repo.as_os_str()],
        vec!["verify".as_ref(), repo.as_os_str()],
        vec!["export".as_ref(), repo.as_os_str(), export.as_os_str()],
    ] {
        ok(&mut as_reader(&args));
    }
    assert_eq!(snapshot(&repo), before, "a reader changed the repository");
    if root {
        // A directory its reader may not enter is a permission error, not "no repository".
        std::fs::set_permissions(&repo, std::fs::Permissions::from_mode(0o000)).unwrap();
        let out = run_within(
            &mut as_reader(&["info".as_ref(), repo.as_os_str()]),
            Duration::from_secs(10),
        )
        .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(stderr.contains("Permission denied"), "{stderr}");
        assert!(!stderr.contains("no repository"), "{stderr}");
    }
    std::fs::set_permissions(&repo, std::fs::Permissions::from_mode(0o755)).unwrap();
}

#[test]
fn a_build_killed_at_any_step_of_publishing_leaves_a_readable_repository() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("repo");
    let old = build(&repo, &[]);
    let old_hash = content_hash(&repo);
    assert_eq!(old["content_hash"].as_str(), Some(old_hash.as_str()));
    // Encoder bounds: one publish. (Measured bounds publish twice, the second time
    // from `quincunx bounds` through the same steps, and a kill after the first swap
    // leaves the encoder-bounds repository.)
    let new_args = ["--overwrite", "--max-error-m", "2", "--bounds", "encoder"];
    let mut new_hash = None;
    for (step, published) in [("blobs", false), ("synced", false), ("swapped", true)] {
        let out = run_within(
            bin()
                .env("QUINCUNX_PUBLISH_ABORT_AT", step)
                .args(["build", "--json", "-o"])
                .arg(&repo)
                .args(new_args)
                .arg(fixture("jacksboro.json")),
            Duration::from_secs(120),
        )
        .unwrap();
        assert!(!out.status.success(), "the build was not stopped at {step}");
        // A complete repository at the path at every step: the old one before the swap.
        let hash = content_hash(&repo);
        if published {
            assert_ne!(hash, old_hash, "killed after the swap: the new repository");
            new_hash = Some(hash);
        } else {
            assert_eq!(hash, old_hash, "killed at {step}: the old repository");
        }
        ok(bin().arg("verify").arg(&repo));
    }
    // The next build clears what the killed ones left and publishes.
    let built = json(&ok(bin()
        .args(["build", "--json", "-o"])
        .arg(&repo)
        .args(new_args)
        .arg(fixture("jacksboro.json"))));
    assert_eq!(built["content_hash"].as_str(), new_hash.as_deref());
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, vec!["repo".to_string()], "nothing left beside it");
    // A first build killed before its rename leaves nothing at the path.
    let fresh = dir.path().join("fresh");
    let out = run_within(
        bin()
            .env("QUINCUNX_PUBLISH_ABORT_AT", "synced")
            .args(["build", "--lossless", "-o"])
            .arg(&fresh)
            .arg(fixture("jacksboro.json")),
        Duration::from_secs(120),
    )
    .unwrap();
    assert!(!out.status.success());
    let info = run_within(bin().arg("info").arg(&fresh), Duration::from_secs(10)).unwrap();
    assert!(String::from_utf8_lossy(&info.stderr).contains("no repository"));
}
