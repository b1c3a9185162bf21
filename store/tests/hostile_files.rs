//! Hostile repository files at open: what is not a regular file is refused without
//! blocking, bytes appended after the file's end are named as such, and metadata outside its
//! limits is refused naming the field (so `serve`, which opens through the store, refuses
//! it too).

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

use quincunx_store::pack::encode_untiled;
use quincunx_store::{
    FORMAT_VERSION, Metadata, PACK_FILE, Repository, RepositoryBuilder, StoreError,
};

fn metadata() -> Metadata {
    Metadata {
        format_version: FORMAT_VERSION,
        complete: true,
        content_hash: "0123456789abcdef".repeat(4),
        levels: 2,
        build: serde_json::json!({}),
        ..common::metadata()
    }
}

/// Opens `dir` on another thread: a hang fails the test instead of blocking it.
fn open_within(dir: &Path, limit: Duration) -> Result<Repository, StoreError> {
    let (tx, rx) = mpsc::channel();
    let dir = dir.to_path_buf();
    std::thread::spawn(move || {
        let _ = tx.send(Repository::open(&dir));
    });
    rx.recv_timeout(limit)
        .unwrap_or_else(|_| panic!("opening blocked for more than {limit:?}"))
}

/// Makes `path` a FIFO, a link to `/dev/zero` or a Unix socket; `None` when the machine
/// cannot (no `mkfifo`).
fn special(kind: &str, path: &Path) -> Option<Box<dyn std::any::Any>> {
    match kind {
        "fifo" => {
            let made = std::process::Command::new("mkfifo")
                .arg(path)
                .status()
                .is_ok_and(|s| s.success());
            made.then(|| Box::new(()) as Box<dyn std::any::Any>)
        }
        "device" => {
            std::os::unix::fs::symlink("/dev/zero", path).unwrap();
            Some(Box::new(()))
        }
        "socket" => Some(Box::new(
            std::os::unix::net::UnixListener::bind(path).unwrap(),
        )),
        _ => unreachable!(),
    }
}

#[test]
fn a_fifo_a_device_or_a_socket_as_the_repository_file_is_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    for (kind, word) in [
        ("fifo", "FIFO"),
        ("device", "character device"),
        ("socket", "socket"),
    ] {
        let repo = dir.path().join(kind);
        std::fs::create_dir(&repo).unwrap();
        // mkfifo is coreutils: always there where this store runs.
        let Some(_keep) = special(kind, &repo.join(PACK_FILE)) else {
            panic!("{kind}: could not make one (mkfifo)");
        };
        let err = open_within(&repo, Duration::from_secs(5)).err().unwrap();
        assert!(matches!(err, StoreError::NotAFile(..)), "{kind}: {err}");
        let text = err.to_string();
        assert!(text.contains(word) && text.contains(PACK_FILE), "{text}");
    }
}

#[test]
fn a_byte_appended_after_the_end_is_called_trailing_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    let mut b = RepositoryBuilder::create(&path).unwrap();
    b.put(0, b"k", b"v").unwrap();
    let mut m = metadata();
    (m.format_version, m.complete, m.content_hash) = (0, false, String::new());
    b.publish(m, false).unwrap();
    let file = path.join(PACK_FILE);
    let mut bytes = std::fs::read(&file).unwrap();
    for extra in [1usize, 7, 1000] {
        let mut grown = bytes.clone();
        grown.extend(std::iter::repeat_n(0x5a, extra));
        std::fs::write(&file, &grown).unwrap();
        let text = Repository::open(&path).err().unwrap().to_string();
        assert!(
            text.contains(&format!("{extra} trailing byte(s) after its end")),
            "{text}"
        );
        assert!(!text.contains("truncated"), "{text}");
    }
    // A real truncation is still called one.
    bytes.pop();
    std::fs::write(&file, &bytes).unwrap();
    let err = Repository::open(&path).err().unwrap();
    assert!(matches!(err, StoreError::Incomplete(_)), "{err}");
}

/// Writes a repository file whose metadata record is `meta`, bypassing the builder.
fn craft(dir: &Path, meta: &serde_json::Value) {
    std::fs::create_dir_all(dir).unwrap();
    let bytes = encode_untiled(&serde_json::to_vec(meta).unwrap(), &[]).unwrap();
    std::fs::write(dir.join(PACK_FILE), bytes).unwrap();
}

#[test]
fn metadata_out_of_its_limits_is_refused_at_open_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let good = serde_json::to_value(metadata()).unwrap();
    craft(&dir.path().join("good"), &good);
    Repository::open(dir.path().join("good")).unwrap();
    let cases: Vec<(&str, serde_json::Value)> = vec![
        ("content_hash", "a".repeat(1_000_000).into()),
        ("content_hash", "xyz".into()),
        ("levels", 0.into()),
        ("levels", 4_000_000_000u32.into()),
        ("n", 0.into()),
        ("n", u32::MAX.into()),
        ("m", 0.into()),
        ("m", 60.into()),
        ("extent", serde_json::json!([1u64 << 63, 65])),
        ("extent", serde_json::json!([0, 0])),
        ("radius_m", (-5.0).into()),
    ];
    for (i, (field, value)) in cases.into_iter().enumerate() {
        let mut meta = good.clone();
        meta[field] = value;
        let path = dir.path().join(format!("bad{i}"));
        craft(&path, &meta);
        let text = Repository::open(&path).err().unwrap().to_string();
        assert!(text.contains(&format!("`{field}`")), "{field}: {text}");
        assert!(text.len() < 400, "{field}: the error stays short");
    }
    let mut meta = good.clone();
    meta["domain"] = "sphere".into();
    meta["extent"] = serde_json::json!([128, 128]);
    craft(&dir.path().join("planet"), &meta);
    let text = Repository::open(dir.path().join("planet"))
        .err()
        .unwrap()
        .to_string();
    assert!(text.contains("`radius_m`"), "{text}");
}
