//! The repository file through the public API: a golden file freezes the format; every kind
//! of damage is one clear error (never a loop, a panic or wrong bytes); readers write
//! nothing; a replaced repository stays readable by those who opened it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::metadata;
use quincunx_diamond::{PlanarDomain, PlanarId};
use quincunx_store::pack::{Header, Limits};
use quincunx_store::{Metadata, PACK_FILE, Repository, RepositoryBuilder, StoreError};

/// Blobs of 1-120 bytes for every diamond of levels 0-8 of the record's domain (m = 6).
fn pairs() -> BTreeMap<Vec<u8>, Vec<u8>> {
    let d = PlanarDomain::new(6).unwrap();
    let mut keys: Vec<Vec<u8>> = (0..=64)
        .flat_map(|x| (0..=64).map(move |y| PlanarId::new(x, y)))
        .filter(|&id| d.level(id).is_ok_and(|l| l < 9))
        .map(|id| d.key(id).unwrap())
        .collect();
    keys.sort();
    keys.into_iter()
        .enumerate()
        .map(|(i, key)| {
            let i = i as u32;
            let blob = (0..(i % 120) + 1).map(|j| (i * 31 + j) as u8).collect();
            (key, blob)
        })
        .collect()
}

/// Small limits, so the golden file has root entries and a few dozen tiles.
const LIMITS: Limits = Limits {
    root_all_max: 0,
    root_split_max: 16,
    leaf_max: 64,
};

fn build(path: &Path, overwrite: bool) -> Metadata {
    let mut b = RepositoryBuilder::create(path)
        .unwrap()
        .with_layout_limits(LIMITS);
    for (k, v) in &pairs() {
        b.put(u32::from(k[0]), k, v).unwrap();
    }
    // Packages of children up to 100 bytes: the golden file lays them out.
    let meta = Metadata {
        inline_max_bytes: Some(100),
        ..metadata()
    };
    b.publish(meta, overwrite).unwrap()
}

fn golden() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/format8.pack")
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
    let (root, tiles) = repo.directory_sizes();
    assert!(
        root > 0 && root <= 16 && tiles > 5,
        "{root} root entries, {tiles} tiles"
    );
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
    /// `open` works; this many blobs read and this many errors in a full walk.
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
    let header = Header::parse(&file).unwrap();
    let at = |offset: u64| offset as usize;
    let flip = |at: usize| -> Vec<u8> {
        let mut b = file.clone();
        for x in &mut b[at..(at + 16).min(len)] {
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
            "magic only",
            Some(file[..8].to_vec()),
            |s| *s == Seen::OpenFails,
            "not a complete",
        ),
        (
            "header only",
            Some(file[..128].to_vec()),
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
            "1 trailing byte(s) after its end",
        ),
        (
            "magic flipped",
            Some(flip(0)),
            |s| *s == Seen::OpenFails,
            "not a quincunx repository",
        ),
        (
            "header flipped",
            Some(flip(40)),
            |s| *s == Seen::OpenFails,
            "header checksum",
        ),
        (
            "root directory flipped",
            Some(flip(at(header.root.offset))),
            |s| *s == Seen::OpenFails,
            "root directory checksum",
        ),
        (
            "metadata flipped",
            Some(flip(at(header.metadata.offset))),
            |s| *s == Seen::OpenFails,
            "metadata checksum",
        ),
        (
            "a leaf directory flipped",
            Some(flip(at(header.leaves.offset + header.leaves.len / 2))),
            |s| matches!(s, Seen::Walk { ok, errors: 1 } if *ok < pairs().len()),
            "leaf directory at offset",
        ),
        (
            "a blob flipped",
            Some(flip(at(header.blobs.offset + header.blobs.len / 2))),
            |s| matches!(s, Seen::Walk { ok, errors } if *errors >= 1 && *ok + *errors == pairs().len()),
            "checksum mismatch",
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
    // Every cut in the header and the last blobs, every 61st in between.
    let cuts = (0..200).chain((200..n - 64).step_by(61)).chain(n - 64..n);
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
