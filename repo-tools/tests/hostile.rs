//! Hostile files and servers against the real `quincunx` binary (issue 40): special files
//! where repository and part files belong, crafted shard parts under a 100 MB data limit,
//! metadata outside its limits at the store and from a fake server. Every run is killed
//! after a deadline: a hang fails the test instead of blocking it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{bin, run_within};

/// Runs `cmd`, which must fail within 5 s with `needle` in its error.
fn refused(cmd: &mut Command, needle: &str) -> String {
    let run = run_within(cmd, Duration::from_secs(5));
    assert!(!run.success, "{cmd:?} succeeded: {}", run.stdout);
    assert!(
        run.stderr.contains(needle),
        "{cmd:?}: {:?} lacks {needle:?}",
        run.stderr
    );
    run.stderr
}

/// `quincunx <args>` with its data segment limited to 100 MB (`prlimit`, no `unsafe`):
/// an allocation beyond it fails the run (abort), which [`run_within`] reports.
fn limited(args: &[&std::ffi::OsStr]) -> Command {
    let mut c = Command::new("prlimit");
    c.arg("--data=100000000")
        .arg(env!("CARGO_BIN_EXE_quincunx"));
    c.args(args);
    c
}

fn has_prlimit() -> bool {
    Command::new("prlimit")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Puts a FIFO, a link to `/dev/zero` or a Unix socket at `path`; the listener of a socket
/// is returned to keep it.
fn special(kind: &str, path: &Path) -> Option<std::os::unix::net::UnixListener> {
    match kind {
        "fifo" => {
            let ok = Command::new("mkfifo").arg(path).status().unwrap().success();
            assert!(ok, "mkfifo {}", path.display());
            None
        }
        "device" => {
            std::os::unix::fs::symlink("/dev/zero", path).unwrap();
            None
        }
        _ => Some(std::os::unix::net::UnixListener::bind(path).unwrap()),
    }
}

const KINDS: [(&str, &str); 3] = [
    ("fifo", "a FIFO"),
    ("device", "a character device"),
    ("socket", "a socket"),
];

#[test]
fn special_files_as_the_repository_file_end_every_tool_at_once() {
    let dir = tempfile::tempdir().unwrap();
    for (kind, words) in KINDS {
        let repo = dir.path().join(kind);
        std::fs::create_dir(&repo).unwrap();
        let _keep = special(kind, &repo.join("repository.pack"));
        let r = repo.as_os_str();
        let out = dir.path().join(format!("{kind}-out"));
        let png = dir.path().join(format!("{kind}.png"));
        let spec = format!("k={}", repo.display());
        let cases: Vec<Vec<&std::ffi::OsStr>> = vec![
            vec!["info".as_ref(), r],
            vec!["verify".as_ref(), r],
            vec!["export".as_ref(), r, out.as_os_str()],
            vec!["query".as_ref(), r, "--at".as_ref(), "1,2".as_ref()],
            vec!["preview".as_ref(), r, "-o".as_ref(), png.as_os_str()],
            vec![
                "serve".as_ref(),
                "--addr".as_ref(),
                "127.0.0.1:0".as_ref(),
                "--repo".as_ref(),
                spec.as_ref(),
            ],
        ];
        for args in cases {
            let text = refused(bin().args(&args), words);
            assert!(text.contains("not a regular file"), "{args:?}: {text}");
        }
    }
}

/// Bytes of a shard part (`QXPART02`): the header fields given, then an empty body of
/// `side` side entries.
#[derive(Clone)]
struct Part {
    width: u64,
    height: u64,
    n: u64,
    shards: u64,
    index: u64,
    scale: f64,
    side: u64,
}

impl Part {
    fn planar() -> Part {
        Part {
            width: 1025,
            height: 1025,
            n: 32,
            shards: 2,
            index: 0,
            scale: 1.0,
            side: 0,
        }
    }

    fn bytes(&self) -> Vec<u8> {
        let mut o = b"QXPART02".to_vec();
        let mut u = |x: u64| o.extend_from_slice(&x.to_le_bytes());
        for x in [self.width, self.height, self.n, 1] {
            u(x);
        }
        u(1f64.to_bits()); // max error 1
        for x in [0, 20 << 20, 64, self.shards, 2, self.width * self.height] {
            u(x);
        }
        for x in [self.scale, 0.0, 0.0, 0.0, 0.0] {
            u(x.to_bits());
        }
        u(0); // no coverage
        u(0); // empty coverage bytes
        let extra = br#"{"input":"x.json","lossless":false,"max_error_m":1.0,"diamond_size":null,"rdo":"off","inline_bytes":0,"memory_budget_mb":20,"source":{"units":"m","source_samples":1,"nodata_count":0,"georef":null},"radius_m":null,"face_side":null,"sparse":false}"#;
        u(extra.len() as u64);
        o.extend_from_slice(extra);
        let mut u = |x: u64| o.extend_from_slice(&x.to_le_bytes());
        u(0); // planar
        u(self.index);
        for x in [0, 0, 0] {
            u(x); // coarse rows 0..0, no values
        }
        u(self.side);
        for k in 0..self.side {
            for x in [20, k, 1, 1, 0, 0] {
                u(x);
            }
        }
        for x in [0, 0] {
            u(x); // no counts, no pieces
        }
        u(0f64.to_bits());
        for _ in 0..7 {
            u(0);
        }
        o
    }

    fn write(&self, dir: &Path) -> PathBuf {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("part.bin"), self.bytes()).unwrap();
        std::fs::write(dir.join("details.bin"), b"").unwrap();
        dir.to_path_buf()
    }
}

fn merge(dir: &Path, parts: &[PathBuf]) -> Command {
    let out = dir.join("merged");
    let mut args: Vec<&std::ffi::OsStr> = vec!["merge".as_ref()];
    args.extend(parts.iter().map(|p| p.as_os_str()));
    args.extend(["-o".as_ref(), out.as_os_str(), "--overwrite".as_ref()]);
    if has_prlimit() {
        limited(&args)
    } else {
        let mut c = bin();
        c.args(args);
        c
    }
}

#[test]
fn special_files_as_a_part_end_merge_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let good = Part::planar().write(&dir.path().join("good"));
    for (kind, words) in KINDS {
        let part = dir.path().join(kind);
        std::fs::create_dir(&part).unwrap();
        let _keep = special(kind, &part.join("part.bin"));
        let text = refused(&mut merge(dir.path(), &[good.clone(), part]), words);
        assert!(text.contains("part.bin"), "{text}");
    }
}

#[test]
fn crafted_parts_are_clear_errors_within_100_mb() {
    if !has_prlimit() {
        quincunx_testkit::skip::skip(
            "crafted_parts_are_clear_errors_within_100_mb",
            "REQUIRE_PRLIMIT",
            "prlimit (util-linux) is missing",
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let p = Part::planar();
    let two = |name: &str, a: Part, b: Part| {
        vec![
            a.write(&d.join(name).join("0")),
            b.write(&d.join(name).join("1")),
        ]
    };
    // Both parts agree on 2^62 shards.
    let huge = Part {
        shards: 1 << 62,
        ..p.clone()
    };
    let parts = two("huge", huge.clone(), Part { index: 1, ..huge });
    refused(
        &mut merge(d, &parts),
        "shard count 4611686018427387904 is outside",
    );
    // A NaN value scale names the field.
    let nan = Part {
        scale: f64::NAN,
        ..p.clone()
    };
    let parts = two("nan", nan.clone(), Part { index: 1, ..nan });
    let text = refused(&mut merge(d, &parts), "value scale NaN");
    assert!(!text.contains("same build as part 0"), "{text}");
    // Parts of builds with different shard counts.
    let parts = two(
        "mismatch",
        p.clone(),
        Part {
            index: 1,
            shards: 3,
            ..p.clone()
        },
    );
    refused(&mut merge(d, &parts), "their shard count differs");
    // The largest raster with no side information to back it.
    let big = Part {
        width: 1 << 24,
        height: 1 << 24,
        n: 2,
        ..p.clone()
    };
    let parts = two("big", big.clone(), Part { index: 1, ..big });
    refused(&mut merge(d, &parts), "carry side information of only");
    // A count of side entries beyond the file's bytes.
    let mut bytes = p.bytes();
    let at = bytes.len() - 8 * 11; // the side count: counts, pieces, error, 7 figures follow
    bytes[at..at + 8].copy_from_slice(&(1u64 << 60).to_le_bytes());
    let lying = d.join("lying");
    std::fs::create_dir(&lying).unwrap();
    std::fs::write(lying.join("part.bin"), bytes).unwrap();
    refused(&mut merge(d, &[lying]), "truncated");
}

/// A small real repository's metadata record, as JSON.
fn real_metadata(dir: &Path) -> serde_json::Value {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/jacksboro.json");
    let repo = dir.join("jacksboro");
    common::build(&["--max-error-m", "2"], &fixture, &repo);
    let run = run_within(
        bin().arg("info").arg(&repo).arg("--json"),
        Duration::from_secs(60),
    );
    assert!(run.success, "{}", run.stderr);
    let info: serde_json::Value = serde_json::from_str(&run.stdout).unwrap();
    info["metadata"].clone()
}

/// Each field out of range, and what the error must name.
fn hostile_variants(good: &serde_json::Value) -> Vec<(&'static str, serde_json::Value)> {
    let levels = good["levels"].as_u64().unwrap() as usize;
    let edit = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut m = good.clone();
        f(&mut m);
        m
    };
    vec![
        (
            "content_hash",
            edit(&|m| m["content_hash"] = "ab".repeat(500_000).into()),
        ),
        ("levels", edit(&|m| m["levels"] = 0.into())),
        ("levels", edit(&|m| m["levels"] = 4_000_000_000u32.into())),
        ("n", edit(&|m| m["n"] = 0.into())),
        ("n", edit(&|m| m["n"] = u32::MAX.into())),
        (
            "extent",
            edit(&|m| m["extent"] = serde_json::json!([1u64 << 63, 150])),
        ),
        ("extent", edit(&|m| m["extent"] = serde_json::json!([0, 0]))),
        (
            "channels[0].steps",
            edit(&|m| m["channels"][0]["steps"] = serde_json::json!([])),
        ),
        (
            "channels[0].steps",
            edit(&|m| m["channels"][0]["steps"] = vec![256; 1_000_000 + levels].into()),
        ),
        (
            "channels[0].roots",
            edit(&|m| m["channels"][0]["roots"] = serde_json::json!([[1, 2, 3]])),
        ),
    ]
}

/// Writes a repository whose metadata record is `meta`: the real repository's file with
/// the record replaced (directories and blobs kept).
fn with_metadata(real: &Path, out: &Path, meta: &serde_json::Value) {
    let file = std::fs::read(real.join("repository.pack")).unwrap();
    let record = serde_json::to_vec(meta).unwrap();
    let bytes = quincunx_store::pack::replace_metadata(&file, &record).unwrap();
    std::fs::create_dir_all(out).unwrap();
    std::fs::write(out.join("repository.pack"), bytes).unwrap();
}

/// A fake server answering every request with `body` (200, JSON), on a thread.
fn fake_server(body: Vec<u8>) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut s) = stream else { continue };
            let body = body.clone();
            std::thread::spawn(move || {
                let mut buf = [0u8; 8192];
                let mut seen = Vec::new();
                while let Ok(k) = s.read(&mut buf) {
                    if k == 0 {
                        break;
                    }
                    seen.extend_from_slice(&buf[..k]);
                    while let Some(end) = seen.windows(4).position(|w| w == b"\r\n\r\n") {
                        seen.drain(..end + 4);
                        let head = format!(
                            "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n\
                             content-length: {}\r\n\r\n",
                            body.len()
                        );
                        if s.write_all(head.as_bytes()).is_err() || s.write_all(&body).is_err() {
                            return;
                        }
                    }
                }
            });
        }
    });
    url
}

#[test]
fn metadata_out_of_its_limits_is_refused_by_serve_verify_fly_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let good = real_metadata(dir.path());
    let real = dir.path().join("jacksboro");
    for (i, (field, meta)) in hostile_variants(&good).into_iter().enumerate() {
        let named = format!("`{field}`");
        // At the store: serve and verify.
        let repo = dir.path().join(format!("bad{i}"));
        with_metadata(&real, &repo, &meta);
        let spec = format!("bad={}", repo.display());
        refused(
            bin().args(["serve", "--addr", "127.0.0.1:0", "--repo", &spec]),
            &named,
        );
        refused(bin().arg("verify").arg(&repo), &named);
        // From a fake server: fly and render (before any GPU is needed).
        let url = fake_server(serde_json::to_vec(&meta).unwrap());
        refused(
            bin().args(["fly", "--url", &url, "--repo", "bad", "--json"]),
            &named,
        );
        refused(
            bin()
                .args([
                    "render",
                    "--url",
                    &url,
                    "--repo",
                    "bad",
                    "--uv",
                    "0.5,0.5",
                    "--height-m",
                    "5000",
                    "-o",
                ])
                .arg(dir.path().join("bad.png")),
            &named,
        );
    }
}

/// The status line `quincunx serve` answers `request` with.
fn status_line(url: &str, request: &[u8]) -> String {
    let addr = url.trim_start_matches("http://");
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.write_all(request).unwrap();
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).unwrap();
    String::from_utf8_lossy(&buf[..n])
        .lines()
        .next()
        .unwrap_or("")
        .to_string()
}

#[test]
fn connect_and_an_http1_pri_request_are_method_not_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/jacksboro.json");
    let repo = dir.path().join("j");
    common::build(&["--max-error-m", "2"], &fixture, &repo);
    let server = common::serve(&[("j", &repo)]);
    for request in [
        &b"CONNECT example.com:443 HTTP/1.1\r\nHost: example.com:443\r\n\r\n"[..],
        b"PRI / HTTP/1.1\r\nHost: x\r\n\r\n",
        b"PRI * HTTP/1.1\r\nHost: x\r\n\r\n",
    ] {
        let line = status_line(&server.url, request);
        assert_eq!(
            line,
            "HTTP/1.1 405 Method Not Allowed",
            "{}",
            String::from_utf8_lossy(request)
        );
    }
}
