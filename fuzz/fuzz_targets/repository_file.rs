//! A repository file of arbitrary bytes (`quincunx_store::Repository`) never panics, hangs
//! or allocates from an unchecked length: `open` fails cleanly or gives a repository whose
//! full walk yields at most one error per blob or leaf directory and whose `get`s return
//! blobs the walk saw.
//!
//! Input: the bytes of `repository.pack`. Seeds worth adding: a real repository file (e.g.
//! `store/tests/golden/format8.pack`).

#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use quincunx_store::{PACK_FILE, Repository};

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("quincunx-fuzz-pack-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("scratch directory");
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let dir = dir();
    std::fs::write(dir.join(PACK_FILE), data).expect("write the input");
    let Ok(repo) = Repository::open(dir) else {
        return;
    };
    let mut seen = Vec::new();
    let mut errors = 0;
    for kv in repo.blobs() {
        match kv {
            Ok((k, v)) => seen.push((k, v)),
            Err(_) => errors += 1,
        }
    }
    assert!(seen.len() <= repo.blob_count());
    assert!(errors <= data.len());
    for (k, v) in seen.iter().take(64) {
        assert_eq!(repo.get(k).ok().flatten().as_deref(), Some(&v[..]));
    }
    let _ = repo.compute_content_hash();
});
