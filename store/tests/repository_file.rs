//! The repository file through the public API: a golden file freezes the format; every kind
//! of damage is one clear error (never a loop, a panic or wrong bytes); readers write
//! nothing; a replaced repository stays readable by those who opened it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::metadata;
use quincunx_store::{Metadata, PACK_FILE, Repository, RepositoryBuilder, StoreError};

/// 600 blobs of 1-120 bytes over three levels: a few dozen 1 KiB pages.
fn pairs() -> BTreeMap<Vec<u8>, Vec<u8>> {
    (0u32..600)
        .map(|i| {
            let key = [&[(i % 3) as u8][..], &(i * 7919 % 6007).to_be_bytes()].concat();
            let blob = (0..(i % 120) + 1).map(|j| (i * 31 + j) as u8).collect();
            (key, blob)
        })
        .collect()
}

fn build(path: &Path, overwrite: bool) -> Metadata {
    let mut b = RepositoryBuilder::create(path)
        .unwrap()
        .with_page_bytes(1024);
    for (k, v) in &pairs() {
        b.put(u32::from(k[0]), k, v).unwrap();
    }
    b.publish(metadata(), overwrite).unwrap()
}

fn golden() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/format6.pack")
}

#[test]
fn the_repository_file_is_byte_for_byte_the_golden_one_and_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    build(&path, false);
    let bytes = std::fs::read(path.join(PACK_FILE)).unwrap();
    if std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1") {
        std::fs::write(golden(), &bytes).unwrap();
    }
    let want = std::fs::read(golden()).unwrap();
    assert!(
        bytes == want,
        "the repository file changed: bump FORMAT_VERSION, then bless with QUINCUNX_BLESS=1"
    );
    // The committed file, opened where it lies in the source tree, reads back every pair.
    let copy = dir.path().join("golden");
    std::fs::create_dir(&copy).unwrap();
    std::fs::copy(golden(), copy.join(PACK_FILE)).unwrap();
    let repo = Repository::open(&copy).unwrap();
    let got: BTreeMap<Vec<u8>, Vec<u8>> = repo
        .blobs()
        .map(|kv| {
            let (k, v) = kv.unwrap();
            (k, v.to_vec())
        })
        .collect();
    assert_eq!(got, pairs());
    assert_eq!(
        repo.compute_content_hash().unwrap(),
        repo.metadata().content_hash
    );
}

/// What a reader sees of a damaged repository.
#[derive(Debug, PartialEq)]
enum Seen {
    /// `open` fails.
    OpenFails,
    /// `open` works; this many blobs read and this many page errors in a full walk.
    Walk { ok: usize, errors: usize },
}

fn walk(path: &Path) -> (Seen, Option<String>) {
    let repo = match Repository::open(path) {
        Ok(r) => r,
        Err(e) => return (Seen::OpenFails, Some(e.to_string())),
    };
    let (mut ok, mut errors, mut message) = (0, 0, None);
    let pairs = pairs();
    // Bounded: a walk that repeated an error forever would end here, counted.
    for kv in repo.blobs().take(pairs.len() + 100) {
        match kv {
            Ok((k, v)) => {
                assert_eq!(pairs.get(&k), Some(&v.to_vec()), "wrong bytes served");
                ok += 1;
            }
            Err(e) => {
                errors += 1;
                message = Some(e.to_string());
            }
        }
    }
    // Every get gives the right bytes or an error, never other bytes.
    for (k, v) in &pairs {
        if let Ok(got) = repo.get(k) {
            assert_eq!(got.as_deref(), Some(v.as_slice()));
        }
    }
    (Seen::Walk { ok, errors }, message)
}

/// A damage kind: name, file bytes (`None`: no file), what a reader must see, and words the
/// error must say.
type DamageCase = (
    &'static str,
    Option<Vec<u8>>,
    fn(&Seen) -> bool,
    &'static str,
);

#[test]
fn every_kind_of_damage_is_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good");
    build(&good, false);
    let file = std::fs::read(good.join(PACK_FILE)).unwrap();
    let len = file.len();
    let footer_at = len - 48;
    let index_at = u64::from_le_bytes(file[footer_at..footer_at + 8].try_into().unwrap()) as usize;
    let metadata_at = index_at
        + u64::from_le_bytes(file[footer_at + 8..footer_at + 16].try_into().unwrap()) as usize;
    let flip = |at: usize| -> Vec<u8> {
        let mut b = file.clone();
        for x in &mut b[at..at + 16] {
            *x = !*x;
        }
        b
    };
    // (name, file bytes or None for no file, what a reader must see, words the error says)
    let cases: Vec<DamageCase> = vec![
        (
            "empty file",
            Some(vec![]),
            |s| *s == Seen::OpenFails,
            "not a complete",
        ),
        (
            "head only",
            Some(file[..16].to_vec()),
            |s| *s == Seen::OpenFails,
            "not a complete",
        ),
        (
            "half the file",
            Some(file[..len / 2].to_vec()),
            |s| *s == Seen::OpenFails,
            "not a complete",
        ),
        (
            "all but one byte",
            Some(file[..len - 1].to_vec()),
            |s| *s == Seen::OpenFails,
            "not a complete",
        ),
        (
            "one byte appended",
            Some([&file[..], b"x"].concat()),
            |s| *s == Seen::OpenFails,
            "1 trailing byte(s) after the footer",
        ),
        (
            "head flipped",
            Some(flip(0)),
            |s| *s == Seen::OpenFails,
            "not a quincunx repository",
        ),
        (
            "a page flipped (offset 500)",
            Some(flip(500)),
            |s| matches!(s, Seen::Walk { ok, errors: 1 } if *ok < 600),
            "checksum",
        ),
        (
            "index flipped",
            Some(flip(index_at)),
            |s| *s == Seen::OpenFails,
            "index checksum",
        ),
        (
            "metadata flipped",
            Some(flip(metadata_at)),
            |s| *s == Seen::OpenFails,
            "metadata checksum",
        ),
        (
            "footer flipped",
            Some(flip(footer_at)),
            |s| *s == Seen::OpenFails,
            "footer",
        ),
        (
            "zeros of the same length",
            Some(vec![0; len]),
            |s| *s == Seen::OpenFails,
            "not a quincunx repository",
        ),
        (
            "text of another program",
            Some(b"SQLite format 3\0 and more bytes here".to_vec()),
            |s| *s == Seen::OpenFails,
            "not a quincunx repository",
        ),
        (
            "no repository file",
            None,
            |s| *s == Seen::OpenFails,
            "without a repository",
        ),
    ];
    for (name, bytes, expect, words) in cases {
        let path = dir.path().join(name.replace(' ', "_"));
        std::fs::create_dir(&path).unwrap();
        if let Some(bytes) = bytes {
            std::fs::write(path.join(PACK_FILE), bytes).unwrap();
        }
        let (seen, message) = walk(&path);
        assert!(expect(&seen), "{name}: {seen:?}");
        let message = message.unwrap_or_default();
        assert!(
            message.contains(words),
            "{name}: {message:?} lacks {words:?}"
        );
        assert!(
            message.contains(&*path.to_string_lossy()),
            "{name}: {message:?} does not name the repository"
        );
    }
    // The repository file is a directory; the path is a file; the path does not exist.
    let odd = dir.path().join("pack_is_a_dir");
    std::fs::create_dir_all(odd.join(PACK_FILE)).unwrap();
    assert!(Repository::open(&odd).is_err());
    let plain = dir.path().join("plain_file");
    std::fs::write(&plain, b"x").unwrap();
    assert!(matches!(
        Repository::open(&plain),
        Err(StoreError::NotARepository(_))
    ));
    assert!(matches!(
        Repository::open(dir.path().join("absent")),
        Err(StoreError::Missing(_))
    ));
}

#[test]
fn every_truncation_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good");
    build(&good, false);
    let file = std::fs::read(good.join(PACK_FILE)).unwrap();
    let cut = dir.path().join("cut");
    std::fs::create_dir(&cut).unwrap();
    let n = file.len();
    // Every cut in the head and the footer, every 61st in between.
    let cuts = (0..64).chain((64..n - 64).step_by(61)).chain(n - 64..n);
    for at in cuts {
        std::fs::write(cut.join(PACK_FILE), &file[..at]).unwrap();
        assert!(Repository::open(&cut).is_err(), "cut at {at}");
    }
}

/// Names, bytes and modification times of the files under `dir`.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>, std::time::SystemTime)> {
    let mut out: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            let m = std::fs::metadata(&p).unwrap();
            (p.clone(), std::fs::read(&p).unwrap(), m.modified().unwrap())
        })
        .collect();
    out.sort();
    out
}

#[test]
fn readers_write_nothing_and_read_read_only_files_together() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    build(&path, false);
    let perms = |p: &Path, mode| std::fs::set_permissions(p, std::fs::Permissions::from_mode(mode));
    perms(&path.join(PACK_FILE), 0o444).unwrap();
    perms(&path, 0o555).unwrap();
    let before = snapshot(&path);
    std::thread::sleep(std::time::Duration::from_millis(20));
    // Many readers at once, each reading everything.
    let readers: Vec<Repository> = (0..8).map(|_| Repository::open(&path).unwrap()).collect();
    std::thread::scope(|s| {
        for r in &readers {
            s.spawn(|| {
                assert_eq!(r.blobs().filter(Result::is_ok).count(), pairs().len());
                for (k, v) in pairs() {
                    assert_eq!(r.get(&k).unwrap().as_deref(), Some(v.as_slice()));
                }
            });
        }
    });
    drop(readers);
    assert_eq!(snapshot(&path), before, "reading changed the repository");
    perms(&path, 0o755).unwrap();
}

#[test]
fn a_replaced_repository_stays_readable_by_those_who_opened_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    let mut b = RepositoryBuilder::create(&path).unwrap();
    b.put(0, b"\x00k", b"old").unwrap();
    let old = b.publish(metadata(), false).unwrap();
    let reader = Repository::open(&path).unwrap();
    let new = build(&path, true);
    assert_ne!(old.content_hash, new.content_hash);
    // The reader that opened the old file keeps reading it, consistently.
    assert_eq!(&reader.get(b"\x00k").unwrap().unwrap()[..], b"old");
    assert_eq!(reader.compute_content_hash().unwrap(), old.content_hash);
    // New readers see the new one.
    let fresh = Repository::open(&path).unwrap();
    assert_eq!(fresh.metadata().content_hash, new.content_hash);
    assert!(fresh.get(b"\x00k").unwrap().is_none());
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "nothing beside the repository"
    );
}

#[test]
fn a_second_build_of_the_same_path_is_refused_while_the_first_runs() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    let first = RepositoryBuilder::create(&path).unwrap();
    let err = RepositoryBuilder::create(&path).err().unwrap();
    assert!(matches!(err, StoreError::Busy(..)), "{err}");
    drop(first); // as if killed: the stale partial build is removed by the next one
    let b = RepositoryBuilder::create(&path).unwrap();
    b.publish(metadata(), false).unwrap();
    assert!(Repository::open(&path).is_ok());
}

#[test]
fn publishing_over_something_that_is_not_a_repository_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("home");
    std::fs::create_dir(&path).unwrap();
    std::fs::write(path.join("notes.txt"), b"mine").unwrap();
    for overwrite in [false, true] {
        assert!(matches!(
            RepositoryBuilder::check_destination(&path, overwrite),
            Err(StoreError::Occupied(_))
        ));
        let b = RepositoryBuilder::create(&path).unwrap();
        assert!(matches!(
            b.publish(metadata(), overwrite),
            Err(StoreError::Occupied(_))
        ));
    }
    assert_eq!(std::fs::read(path.join("notes.txt")).unwrap(), b"mine");
    assert!(!path.join(PACK_FILE).exists());
}

#[test]
fn a_sled_repository_is_replaced_whole_on_overwrite() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("repo");
    std::fs::create_dir(&path).unwrap();
    for f in ["db", "conf", "snap.0000000000001234"] {
        std::fs::write(path.join(f), b"sled").unwrap();
    }
    std::fs::create_dir(path.join("blobs")).unwrap();
    assert!(matches!(
        Repository::open(&path),
        Err(StoreError::Legacy(_))
    ));
    assert!(matches!(
        RepositoryBuilder::check_destination(&path, false),
        Err(StoreError::Exists(_))
    ));
    build(&path, true);
    let names: Vec<_> = std::fs::read_dir(&path)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from(PACK_FILE)]);
    assert_eq!(Repository::open(&path).unwrap().blob_count(), pairs().len());
}
