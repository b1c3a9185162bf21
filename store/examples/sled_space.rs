//! Measures the space sled needs for a repository's blobs under different write strategies
//! (how `RepositoryBuilder` was chosen; see "Space overhead" in
//! `docs/repository-format.md`).
//!
//! Usage: `cargo run --release -p quincunx-store --example sled_space -- <repo>...`
//!
//! Each repository (current format, or format 1 with one sled value per blob) is copied to a
//! scratch directory first (opening a sled database writes to it), its blobs are read, and
//! every strategy writes them into a fresh database, closes it, opens it again the way
//! readers do, reads every blob, closes it, and measures. One JSON line per strategy:
//! `value_bytes` is the sum of blob sizes, `disk_bytes` the directory's total file size
//! after that reopen (`quincunx_store::dir_size`), `overhead` their ratio,
//! `disk_bytes_second_reopen` the size after one more open (with the timing) and close,
//! `alloc_bytes`
//! what the filesystem allocated (`st_blocks`), `files` the directory's file count and
//! `get_median_us` the median of 20,000 random `get`s of stored keys on a warm cache.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::time::Instant;

use quincunx_store::{Metadata, Repository, RepositoryBuilder, StoreError, dir_size};

type Pairs = Vec<(Vec<u8>, Vec<u8>)>;

fn main() {
    let inputs: Vec<String> = std::env::args().skip(1).collect();
    assert!(!inputs.is_empty(), "usage: sled_space <repo>...");
    for input in &inputs {
        let (metadata, blobs) = read_any(Path::new(input));
        measure_all(input, &metadata, &blobs);
    }
}

/// Blobs and metadata of a repository of the current format or of format 1.
fn read_any(input: &Path) -> (Option<Metadata>, Pairs) {
    let scratch = tempfile::tempdir().unwrap();
    let copy = scratch.path().join("repo");
    copy_dir(input, &copy);
    match Repository::open(&copy) {
        Ok(repo) => {
            let blobs = repo
                .blobs()
                .map(|kv| {
                    let (k, v) = kv.unwrap();
                    (k.to_vec(), v.to_vec())
                })
                .collect();
            (Some(repo.metadata().clone()), blobs)
        }
        Err(StoreError::Version { found: 1, .. }) => {
            let db = legacy_config(&copy, segment_bytes(&copy)).open().unwrap();
            let blobs = db
                .open_tree("blobs")
                .unwrap()
                .iter()
                .map(|kv| {
                    let (k, v) = kv.unwrap();
                    (k.to_vec(), v.to_vec())
                })
                .collect();
            let metadata = serde_json::from_slice(&db.get("metadata").unwrap().unwrap()).ok();
            (metadata, blobs)
        }
        Err(e) => panic!("{}: {e}", input.display()),
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

fn segment_bytes(path: &Path) -> usize {
    let conf = std::fs::read(path.join("conf")).unwrap();
    String::from_utf8_lossy(&conf)
        .lines()
        .find_map(|l| l.strip_prefix("segment_size: ")?.trim().parse().ok())
        .unwrap()
}

/// How format 1 opened its database.
fn legacy_config(path: &Path, segment: usize) -> sled::Config {
    sled::Config::new()
        .path(path)
        .mode(sled::Mode::LowSpace)
        .segment_size(segment)
}

#[derive(Clone, Copy)]
enum Strategy {
    /// Format 1: one sled value per blob, one insert each.
    PerBlobInserts { segment: usize },
    /// One sled value per blob, all in one `apply_batch`.
    PerBlobBatch { segment: usize },
    /// Pages (the store's page format) as values of a single tree.
    PagesOneTree { page: usize, segment: usize },
    /// The store: pages, at most 9 per tree (`page` 0 = its default page size).
    Store { page: usize },
}

impl Strategy {
    fn name(self) -> String {
        match self {
            Strategy::PerBlobInserts { segment } => {
                format!("per_blob_inserts_seg{}k", segment >> 10)
            }
            Strategy::PerBlobBatch { segment } => format!("per_blob_batch_seg{}k", segment >> 10),
            Strategy::PagesOneTree { page, segment } => {
                format!("pages{}k_one_tree_seg{}k", page >> 10, segment >> 10)
            }
            Strategy::Store { page: 0 } => "store_default".into(),
            Strategy::Store { page } => format!("store_pages{}k", page >> 10),
        }
    }
}

fn measure_all(input: &str, metadata: &Option<Metadata>, blobs: &Pairs) {
    let strategies = [
        Strategy::PerBlobInserts { segment: 512 << 10 },
        Strategy::PerBlobBatch { segment: 512 << 10 },
        Strategy::PerBlobBatch { segment: 64 << 10 },
        Strategy::PagesOneTree {
            page: 4 << 10,
            segment: 64 << 10,
        },
        Strategy::PagesOneTree {
            page: 64 << 10,
            segment: 64 << 10,
        },
        Strategy::Store { page: 2 << 10 },
        Strategy::Store { page: 8 << 10 },
        Strategy::Store { page: 16 << 10 },
        Strategy::Store { page: 0 },
    ];
    let value_bytes: u64 = blobs.iter().map(|(_, v)| v.len() as u64).sum();
    for strategy in strategies {
        let scratch = tempfile::tempdir().unwrap();
        let path = scratch.path().join("repo");
        let (reader, disk_bytes) = write(strategy, &path, metadata, blobs);
        let get_median_us = get_median_us(&reader, blobs);
        drop(reader);
        let disk_bytes_second_reopen = dir_size(&path).unwrap();
        println!(
            "{}",
            serde_json::json!({
                "repo": input,
                "strategy": strategy.name(),
                "blobs": blobs.len(),
                "value_bytes": value_bytes,
                "disk_bytes": disk_bytes,
                "overhead": (disk_bytes as f64 / value_bytes as f64 * 1000.0).round() / 1000.0,
                "disk_bytes_second_reopen": disk_bytes_second_reopen,
                "alloc_bytes": alloc_bytes(&path),
                "files": files(&path),
                "get_median_us": (get_median_us * 1000.0).round() / 1000.0,
            })
        );
    }
}

/// A reader of the written database, open for the `get` timing.
enum Reader {
    // The `Db` is held so that dropping the reader shuts sled down (a lone `Tree` does not).
    Tree(sled::Tree, #[allow(dead_code)] sled::Db),
    PagesOneTree(sled::Tree, #[allow(dead_code)] sled::Db),
    Store(Box<Repository>),
}

impl Reader {
    fn get(&self, key: &[u8]) -> Option<sled::IVec> {
        match self {
            Reader::Tree(t, _) => t.get(key).unwrap(),
            Reader::PagesOneTree(t, _) => {
                let (page_key, page) = t.range(..=key).next_back()?.unwrap();
                let range = quincunx_store::page::find(&page_key, &page, key).unwrap()?;
                Some(page.subslice(range.start, range.len()))
            }
            Reader::Store(repo) => repo.get(key).unwrap(),
        }
    }
}

/// Writes `blobs`, closes, reopens for reading, reads everything, closes, and returns a
/// reader opened once more and the size before that second open.
fn write(
    strategy: Strategy,
    path: &Path,
    metadata: &Option<Metadata>,
    blobs: &Pairs,
) -> (Reader, u64) {
    let metadata_json = serde_json::to_vec(metadata).unwrap();
    match strategy {
        Strategy::PerBlobInserts { segment } | Strategy::PerBlobBatch { segment } => {
            {
                let db = legacy_config(path, segment).open().unwrap();
                let tree = db.open_tree("blobs").unwrap();
                if matches!(strategy, Strategy::PerBlobBatch { .. }) {
                    let mut batch = sled::Batch::default();
                    for (k, v) in blobs {
                        batch.insert(k.as_slice(), v.as_slice());
                    }
                    tree.apply_batch(batch).unwrap();
                } else {
                    for (k, v) in blobs {
                        tree.insert(k.as_slice(), v.as_slice()).unwrap();
                    }
                }
                db.insert("metadata", metadata_json).unwrap();
                db.flush().unwrap();
            }
            let open = || {
                let db = legacy_config(path, segment).open().unwrap();
                let tree = db.open_tree("blobs").unwrap();
                assert_eq!(tree.iter().count(), blobs.len());
                Reader::Tree(tree, db)
            };
            reopened(path, open)
        }
        Strategy::PagesOneTree { page, segment } => {
            {
                let db = legacy_config(path, segment).open().unwrap();
                let tree = db.open_tree("pages").unwrap();
                let mut writer = quincunx_store::page::PageWriter::default();
                for (k, v) in blobs {
                    writer.push(k, v);
                    if writer.len() >= page {
                        let (key, value) = writer.finish().unwrap();
                        tree.insert(key, value).unwrap();
                    }
                }
                if let Some((key, value)) = writer.finish() {
                    tree.insert(key, value).unwrap();
                }
                db.insert("metadata", metadata_json).unwrap();
                db.flush().unwrap();
            }
            let open = || {
                let db = legacy_config(path, segment).open().unwrap();
                let tree = db.open_tree("pages").unwrap();
                tree.iter().for_each(|kv| drop(kv.unwrap()));
                Reader::PagesOneTree(tree, db)
            };
            reopened(path, open)
        }
        Strategy::Store { page } => {
            let mut builder = RepositoryBuilder::create(path).unwrap();
            if page > 0 {
                builder = builder.with_page_bytes(page);
            }
            for (k, v) in blobs {
                builder.put(u32::from(k[0]), k, v).unwrap();
            }
            let metadata = metadata.clone().expect("the store strategy needs metadata");
            builder.publish(metadata, false).unwrap();
            let open = || {
                let repo = Repository::open(path).unwrap();
                assert_eq!(repo.blobs().count(), blobs.len());
                Reader::Store(Box::new(repo))
            };
            reopened(path, open)
        }
    }
}

/// Opens, reads all, closes; then opens again for the timing, and returns that reader and
/// the directory size between the two opens.
fn reopened(path: &Path, open: impl Fn() -> Reader) -> (Reader, u64) {
    drop(open());
    let settled = dir_size(path).unwrap();
    (open(), settled)
}

fn get_median_us(reader: &Reader, blobs: &Pairs) -> f64 {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut times = Vec::with_capacity(20_000);
    for _ in 0..20_000 {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let (key, value) = &blobs[(state % blobs.len() as u64) as usize];
        let start = Instant::now();
        let got = reader.get(key);
        let elapsed = start.elapsed();
        assert_eq!(got.as_deref(), Some(value.as_slice()));
        times.push(elapsed.as_secs_f64() * 1e6);
    }
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn alloc_bytes(path: &Path) -> u64 {
    use std::os::unix::fs::MetadataExt;
    walk(path).iter().map(|m| m.blocks() * 512).sum()
}

fn files(path: &Path) -> usize {
    walk(path).len()
}

fn walk(path: &Path) -> Vec<std::fs::Metadata> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(path).unwrap() {
        let entry = entry.unwrap();
        let meta = entry.metadata().unwrap();
        if meta.is_dir() {
            out.extend(walk(&entry.path()));
        } else {
            out.push(meta);
        }
    }
    out
}
