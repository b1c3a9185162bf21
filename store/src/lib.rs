//! The quincunx repository: one sled database (a directory) holding a metadata record and
//! one opaque blob per non-empty diamond, keyed by the codec's locality key (spec:
//! `docs/repository-format.md`).
//!
//! Layout (format 2): blobs are packed in key order into pages of a few KiB (see
//! [`page`]), stored under their first key; runs of at most [`PAGES_PER_TREE`] consecutive
//! pages form one sled tree named `p` ‖ first key. The default tree holds the metadata. Why:
//! sled 0.34.7 writes a value once as a log fragment and again whenever it consolidates or
//! splits the node holding it, and does not reclaim the stale copies of a database that is
//! written once and then only read; a tree that receives fewer inserts than sled's
//! consolidation threshold is written exactly once. Measured in `examples/sled_space.rs`
//! and `docs/repository-format.md` ("Space overhead").
//!
//! Invariants:
//! - Keys and blobs are bytes here: this crate never decodes a blob (the server depends on
//!   it and must not depend on the codec).
//! - A repository is immutable once built. [`RepositoryBuilder`] writes into a sibling
//!   directory `<path>.partial`, writes the metadata record (with `complete = true` and the
//!   content hash) last, flushes, and only then renames the directory to `<path>`. A build
//!   that dies at any point leaves either nothing at `<path>` or the previous repository;
//!   [`Repository::open`] refuses anything without a complete metadata record.
//! - sled holds an exclusive lock on an open database, so one process at a time opens a
//!   repository; serve copies (or `quincunx export`) to scale out.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

pub mod answer;
pub mod channels;
pub mod page;

/// Version of the repository layout (metadata record + page trees) and of the blobs in
/// it: 4 holds version-3 blobs and their compact model; 3 held version 2 (the no-data
/// flags), format 2 version 1.
pub const FORMAT_VERSION: u32 = 5;

const METADATA_KEY: &[u8] = b"metadata";

/// Name prefix of the trees holding pages (the rest of the name is the tree's first key).
const PAGE_TREE_PREFIX: u8 = b'p';

/// Pages per sled tree. sled 0.34.7 consolidates a node (rewriting every value in it) when
/// it links its tenth update (`PAGE_CONSOLIDATION_THRESHOLD`), and splits leaves beyond 16
/// items: a fresh tree that receives nine inserts keeps each of them as the one copy
/// written.
pub const PAGES_PER_TREE: usize = 9;

/// sled segment size of new repositories: small enough that a small repository does not
/// round up to large segments (sled's log grows in whole segments), large enough that
/// default-sized pages stay inline in the log (sled moves a value larger than a quarter
/// segment to a file of its own).
const SEGMENT_BYTES: usize = 64 << 10;

/// Smallest target page size.
const MIN_PAGE_BYTES: usize = 4 << 10;

/// Largest target page size chosen automatically.
const MAX_PAGE_BYTES: usize = 1 << 20;

/// Page trees aimed for: sled rewrites its whole tree directory (names and roots) each time a
/// tree is created, so its write cost grows with the square of the tree count.
const TARGET_TREES: usize = 256;

/// Target page size for `total_bytes` of blobs: at least [`MIN_PAGE_BYTES`], larger when
/// that keeps the tree count near [`TARGET_TREES`].
fn default_page_bytes(total_bytes: u64) -> usize {
    let per_page = total_bytes / (PAGES_PER_TREE * TARGET_TREES) as u64;
    usize::try_from(per_page)
        .unwrap_or(MAX_PAGE_BYTES)
        .clamp(MIN_PAGE_BYTES, MAX_PAGE_BYTES)
}

/// Why a repository could not be opened, read or written.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database layer failed (I/O, corruption, lock held by another process).
    #[error("sled at {path}: {source}")]
    Sled {
        /// Database directory.
        path: PathBuf,
        /// Cause.
        source: sled::Error,
    },
    /// No repository at the path.
    #[error("no repository at {0}")]
    Missing(PathBuf),
    /// The directory is a database without a complete metadata record: an interrupted or
    /// unfinished build.
    #[error("{0} is not a complete repository (interrupted or unfinished build)")]
    Incomplete(PathBuf),
    /// The metadata record is unreadable.
    #[error("metadata of {path} is malformed: {reason}")]
    BadMetadata {
        /// Database directory.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The repository was written by an incompatible version.
    #[error("{path} has repository format {found}; this build reads format {FORMAT_VERSION}")]
    Version {
        /// Database directory.
        path: PathBuf,
        /// Version found.
        found: u32,
    },
    /// A stored page does not parse.
    #[error("{path}: page at key {key:02x?}: {source}")]
    Page {
        /// Database directory.
        path: PathBuf,
        /// The page's sled key.
        key: Vec<u8>,
        /// What is wrong.
        source: page::PageError,
    },
    /// Publishing would replace an existing repository and that was not asked for.
    #[error("{0} already exists (pass overwrite to replace it)")]
    Exists(PathBuf),
    /// Filesystem operation around the database failed.
    #[error("{context} {path}: {source}")]
    Io {
        /// What was being done.
        context: &'static str,
        /// Path involved.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

/// Whether `name` may name a repository in URLs and export folders: ASCII letters, digits,
/// `-`, `_` and `.`, not empty and not starting with `.` (so it is never a path step like
/// `..`).
pub fn is_valid_name(name: &str) -> bool {
    !name.is_empty()
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|c| c.is_ascii_alphanumeric() || b"-_.".contains(&c))
}

/// Shorthand.
pub type Result<T> = std::result::Result<T, StoreError>;

/// Everything a server or client needs to know about a repository, stored as one JSON
/// record. Codec-specific parts (model, steps, root grids) are opaque numbers here.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metadata {
    /// [`FORMAT_VERSION`] of the writer.
    pub format_version: u32,
    /// `true` only in the record written by [`RepositoryBuilder::publish`].
    pub complete: bool,
    /// SHA-256 (hex) over every key and blob in key order and the metadata with this
    /// field empty: changes whenever any content changes (used to version URLs).
    pub content_hash: String,
    /// `"planar"` or `"sphere"`.
    pub domain: String,
    /// Domain size exponent: planar side `2^m`, sphere cube `[-2^m, 2^m]^3` (id units).
    pub m: u32,
    /// Diamond size `N` (cells per side; vertex grids are `(N+1)^2`).
    pub n: u32,
    /// Levels that carry details (blobs exist for levels `0 .. levels`).
    pub levels: u32,
    /// What the samples are.
    pub attribute: Attribute,
    /// Planar: raster width and height in samples. Sphere: face side `2S` twice.
    pub extent: [u64; 2],
    /// How nodata in the source was handled.
    pub nodata: NodataPolicy,
    /// Where the samples are on Earth (or another body); `None` for plain height fields.
    pub georef: Option<serde_json::Value>,
    /// Planet radius in metres (sphere domain).
    pub radius_m: Option<f64>,
    /// One entry per channel (1 for elevation, 3 for colour: Y, Co, Cg).
    pub channels: Vec<ChannelCoding>,
    /// How the repository was built.
    pub build: serde_json::Value,
    /// Blob count and bytes per level.
    pub level_stats: Vec<LevelStats>,
    /// Sparse repositories: the codec's coverage bitmap (`Coverage::to_bytes`), which
    /// says where data exists; points elsewhere are invalid (holes). `None` = dense.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<Vec<u8>>,
    /// Inlining limit `T`: a diamond's package carries the packages of its owned children
    /// of at most `T` bytes ([`answer`]). `None`: no packages are served.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inline_max_bytes: Option<u32>,
}

/// The attribute a repository carries.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Attribute {
    /// `"elevation"` or `"colour"`.
    pub kind: String,
    /// Units of decoded values (`"m"` for elevation, `"srgb8"` for colour).
    pub units: String,
}

/// How source nodata was handled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodataPolicy {
    /// Nodata samples in the source.
    pub source_count: u64,
    /// `"none"` (no holes) or `"filled"` (holes filled smoothly; no spikes or cliffs).
    pub handling: String,
}

/// Decoder parameters of one channel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChannelCoding {
    /// Channel name (`"height"`, `"Y"`, `"Co"`, `"Cg"`).
    pub name: String,
    /// Value units per integer: decoded = offset + integer * scale.
    pub value_scale: f64,
    /// Value at integer 0.
    pub value_offset: f64,
    /// Quantiser step of each detail level, 1/256 integer units.
    pub steps: Vec<u32>,
    /// Trained entropy-model bytes.
    pub model: Vec<u8>,
    /// Root vertex grids (one per root diamond), row-major `(N+1)^2`.
    pub roots: Vec<Vec<i32>>,
    /// Rate mode the channel was coded with (`"lossless"`, `"rms_m=9"`, ...).
    pub rate: String,
}

/// Blobs of one level.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LevelStats {
    /// Level.
    pub level: u32,
    /// Blobs stored.
    pub blobs: u64,
    /// Bytes of those blobs.
    pub bytes: u64,
}

fn sled_err(path: &Path) -> impl FnOnce(sled::Error) -> StoreError + '_ {
    move |source| StoreError::Sled {
        path: path.to_path_buf(),
        source,
    }
}

fn io_err<'a>(
    context: &'static str,
    path: &'a Path,
) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io {
        context,
        path: path.to_path_buf(),
        source,
    }
}

fn open_db(path: &Path, segment_bytes: usize) -> Result<sled::Db> {
    sled::Config::new()
        .path(path)
        .mode(sled::Mode::LowSpace)
        .segment_size(segment_bytes)
        // No background flusher: it would also garbage-collect, rewriting pages of a
        // repository that is written once (publish flushes explicitly) and then only read.
        .flush_every_ms(None)
        // Pages are cached by the page reader and blobs by the server; sled's own cache
        // only needs the tree directory and recently read pages.
        .cache_capacity(SLED_CACHE_BYTES)
        .open()
        .map_err(sled_err(path))
}

/// sled's page cache per open repository (and per build).
const SLED_CACHE_BYTES: u64 = 4 << 20;

/// The segment size an existing database was created with (sled refuses to open it with
/// another), read from its `conf`; the current default when that is unreadable (sled then
/// reports what is wrong).
fn stored_segment_bytes(path: &Path) -> usize {
    std::fs::read(path.join("conf"))
        .ok()
        .and_then(|conf| {
            String::from_utf8_lossy(&conf)
                .lines()
                .find_map(|line| line.strip_prefix("segment_size: ")?.trim().parse().ok())
        })
        .unwrap_or(SEGMENT_BYTES)
}

/// An open, complete repository. Read-only: there is no way to write through it.
pub struct Repository {
    path: PathBuf,
    db: sled::Db,
    /// Page trees by first key, in key order.
    trees: Vec<PageTree>,
    metadata: Metadata,
}

/// One tree of at most [`PAGES_PER_TREE`] pages.
struct PageTree {
    first_key: Vec<u8>,
    tree: sled::Tree,
    /// The tree's page keys, loaded on first use: a point `get` of a known key is cheaper
    /// in sled than a reverse range scan.
    page_keys: std::sync::OnceLock<Vec<sled::IVec>>,
}

impl PageTree {
    fn page_keys(&self) -> sled::Result<&[sled::IVec]> {
        if let Some(keys) = self.page_keys.get() {
            return Ok(keys);
        }
        let keys = self.tree.iter().keys().collect::<sled::Result<Vec<_>>>()?;
        Ok(self.page_keys.get_or_init(|| keys))
    }
}

impl Repository {
    /// [`Repository::open`] right after this process closed the database: sled's I/O
    /// threads can hold the closed database's file lock for a moment, so lock conflicts
    /// are retried for up to two seconds.
    fn open_settling(path: &Path) -> Result<Repository> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(2);
        loop {
            match Repository::open(path) {
                Err(StoreError::Sled {
                    source: sled::Error::Io(e),
                    ..
                }) if e.to_string().contains("could not acquire lock")
                    && std::time::Instant::now() < deadline =>
                {
                    std::thread::sleep(std::time::Duration::from_millis(10));
                }
                other => return other,
            }
        }
    }

    /// Opens a published repository. Fails with [`StoreError::Incomplete`] for anything an
    /// interrupted build left behind.
    pub fn open(path: impl AsRef<Path>) -> Result<Repository> {
        let path = path.as_ref();
        if !path.join("db").exists() && !path.join("conf").exists() {
            return Err(StoreError::Missing(path.to_path_buf()));
        }
        let db = open_db(path, stored_segment_bytes(path))?;
        let raw = db
            .get(METADATA_KEY)
            .map_err(sled_err(path))?
            .ok_or_else(|| StoreError::Incomplete(path.to_path_buf()))?;
        let metadata: Metadata =
            serde_json::from_slice(&raw).map_err(|e| StoreError::BadMetadata {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?;
        if metadata.format_version != FORMAT_VERSION {
            return Err(StoreError::Version {
                path: path.to_path_buf(),
                found: metadata.format_version,
            });
        }
        if !metadata.complete {
            return Err(StoreError::Incomplete(path.to_path_buf()));
        }
        let mut trees = Vec::new();
        for name in db.tree_names() {
            if let Some((&PAGE_TREE_PREFIX, first_key)) = name.split_first() {
                trees.push(PageTree {
                    first_key: first_key.to_vec(),
                    tree: db.open_tree(&name).map_err(sled_err(path))?,
                    page_keys: std::sync::OnceLock::new(),
                });
            }
        }
        trees.sort_by(|a, b| a.first_key.cmp(&b.first_key));
        Ok(Repository {
            path: path.to_path_buf(),
            db,
            trees,
            metadata,
        })
    }

    /// The metadata record.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }

    /// Where the repository lives.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn page_err(&self, key: &[u8]) -> impl FnOnce(page::PageError) -> StoreError + '_ {
        let key = key.to_vec();
        move |source| StoreError::Page {
            path: self.path.clone(),
            key,
            source,
        }
    }

    /// The blob stored under `key`, `None` when the diamond has no blob (a leaf). The bytes
    /// are a view into the cached page (no copy).
    pub fn get(&self, key: &[u8]) -> Result<Option<sled::IVec>> {
        // The tree whose first key is the greatest one <= key, then the page likewise.
        let floor = |after: usize| after.checked_sub(1);
        let after = self
            .trees
            .partition_point(|t| t.first_key.as_slice() <= key);
        let Some(tree) = floor(after).and_then(|i| self.trees.get(i)) else {
            return Ok(None);
        };
        let page_keys = tree.page_keys().map_err(sled_err(&self.path))?;
        let after = page_keys.partition_point(|k| k.as_ref() <= key);
        let Some(page_key) = floor(after).and_then(|i| page_keys.get(i)) else {
            return Ok(None);
        };
        let Some(page) = tree.tree.get(page_key).map_err(sled_err(&self.path))? else {
            return Ok(None);
        };
        let found = page::find(page_key, &page, key).map_err(self.page_err(page_key))?;
        Ok(found.map(|range| page.subslice(range.start, range.len())))
    }

    /// Every `(key, blob)` in key order (level-major, then space-filling curve).
    pub fn blobs(&self) -> impl Iterator<Item = Result<(sled::IVec, sled::IVec)>> + '_ {
        self.trees
            .iter()
            .flat_map(|t| t.tree.iter())
            .flat_map(move |entry| match entry {
                Ok((page_key, page)) => self.page_entries(&page_key, &page),
                Err(e) => vec![Err(sled_err(&self.path)(e))],
            })
    }

    /// The pairs of one page (a malformed page ends in one error).
    fn page_entries(
        &self,
        page_key: &[u8],
        page: &sled::IVec,
    ) -> Vec<Result<(sled::IVec, sled::IVec)>> {
        let mut out = Vec::new();
        let reader = page::PageReader::new(page_key, page);
        let result = reader.and_then(|mut reader| {
            out.reserve(reader.remaining());
            while let Some((key, value)) = reader.next_entry()? {
                out.push(Ok((
                    sled::IVec::from(key),
                    page.subslice(value.start, value.len()),
                )));
            }
            Ok(())
        });
        if let Err(e) = result {
            out.push(Err(self.page_err(page_key)(e)));
        }
        out
    }

    /// Number of blobs.
    pub fn blob_count(&self) -> usize {
        // Counted from the page headers (no blob is touched); an unreadable page counts 0
        // here and surfaces as an error from `get` or `blobs`.
        self.trees
            .iter()
            .flat_map(|t| t.tree.iter())
            .filter_map(|entry| {
                let (page_key, page) = entry.ok()?;
                Some(page::PageReader::new(&page_key, &page).ok()?.remaining())
            })
            .sum()
    }

    /// Bytes the database occupies on disk (all files in its directory).
    pub fn size_on_disk(&self) -> Result<u64> {
        dir_size(&self.path)
    }

    /// Recomputes the content hash from the stored blobs and metadata.
    pub fn compute_content_hash(&self) -> Result<String> {
        let mut h = Sha256::new();
        for kv in self.blobs() {
            let (k, v) = kv?;
            hash_pair(&mut h, &k, &v);
        }
        finish_hash(h, &self.metadata, &self.path)
    }

    /// sled's own opinion of its size (for the overhead report).
    pub fn sled_size_on_disk(&self) -> Result<u64> {
        self.db.size_on_disk().map_err(sled_err(&self.path))
    }
}

fn hash_pair(h: &mut Sha256, key: &[u8], blob: &[u8]) {
    h.update((key.len() as u64).to_le_bytes());
    h.update(key);
    h.update((blob.len() as u64).to_le_bytes());
    h.update(blob);
}

fn finish_hash(mut h: Sha256, metadata: &Metadata, path: &Path) -> Result<String> {
    let mut m = metadata.clone();
    m.content_hash.clear();
    m.complete = true;
    let json = serde_json::to_vec(&m).map_err(|e| StoreError::BadMetadata {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    h.update(&json);
    Ok(h.finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<String>())
}

/// Total size of the regular files under `path`.
pub fn dir_size(path: &Path) -> Result<u64> {
    let mut total = 0;
    let entries = std::fs::read_dir(path).map_err(io_err("reading", path))?;
    for entry in entries {
        let entry = entry.map_err(io_err("reading", path))?;
        let meta = entry.metadata().map_err(io_err("stat", &entry.path()))?;
        if meta.is_dir() {
            total += dir_size(&entry.path())?;
        } else {
            total += meta.len();
        }
    }
    Ok(total)
}

/// Writes a new repository into `<path>.partial` and publishes it atomically.
///
/// Blobs are held in memory until [`RepositoryBuilder::publish`] (they are the compressed
/// output, a fraction of the input) and written there in one pass, in key order, packed into
/// pages; the partial database is created (and locked) at once so that a concurrent build
/// into the same path fails early.
pub struct RepositoryBuilder {
    final_path: PathBuf,
    partial: PathBuf,
    db: sled::Db,
    blobs: BTreeMap<Vec<u8>, Vec<u8>>,
    spill: Option<Spill>,
    stats: Vec<LevelStats>,
    page_bytes: Option<usize>,
}

/// Blobs held on disk instead of in memory until publication (out-of-core builds): an
/// append-only file beside the partial database and an in-memory index of where each
/// key's blob is (about 40 bytes per blob).
struct Spill {
    path: PathBuf,
    file: std::fs::File,
    end: u64,
    index: BTreeMap<Vec<u8>, (u64, usize)>,
}

/// Where an out-of-core build of `path` keeps its blobs until publication.
pub fn spill_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".spill");
    path.with_file_name(name)
}

/// Where a partial build of `path` is written.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    path.with_file_name(name)
}

impl RepositoryBuilder {
    /// Starts a build of the repository at `path`. A stale `<path>.partial` left by an
    /// interrupted build is removed; one held open by a running build is an error.
    pub fn create(path: impl AsRef<Path>) -> Result<RepositoryBuilder> {
        let final_path = path.as_ref().to_path_buf();
        let partial = partial_path(&final_path);
        if partial.exists() {
            // Fails while another process holds the database lock.
            drop(open_db(&partial, stored_segment_bytes(&partial))?);
            std::fs::remove_dir_all(&partial).map_err(io_err("removing", &partial))?;
        }
        if let Some(parent) = final_path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(io_err("creating", parent))?;
        }
        let db = open_db(&partial, SEGMENT_BYTES)?;
        // Under the partial database's lock: a stale spill is ours to remove.
        let spill = spill_path(&final_path);
        if spill.exists() {
            std::fs::remove_file(&spill).map_err(io_err("removing", &spill))?;
        }
        Ok(RepositoryBuilder {
            final_path,
            partial,
            db,
            blobs: BTreeMap::new(),
            spill: None,
            stats: Vec::new(),
            page_bytes: None,
        })
    }

    /// Keeps blobs on disk (in `<path>.spill`, removed at publication) instead of in
    /// memory, so a build's memory does not grow with its output. Call before any `put`.
    pub fn spill_to_disk(mut self) -> Result<RepositoryBuilder> {
        let path = spill_path(&self.final_path);
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(io_err("creating", &path))?;
        let mut spill = Spill {
            path,
            file,
            end: 0,
            index: BTreeMap::new(),
        };
        for (k, v) in std::mem::take(&mut self.blobs) {
            spill.insert(k, &v)?;
        }
        self.spill = Some(spill);
        Ok(self)
    }

    /// Sets the target page size in bytes (a page closes once it reaches it; a larger blob
    /// gets a page of its own). The default grows with the repository from 4 KiB so that
    /// the number of page trees stays near 256. For measurements; any value reads back the
    /// same.
    pub fn with_page_bytes(mut self, page_bytes: usize) -> RepositoryBuilder {
        self.page_bytes = Some(page_bytes.max(1));
        self
    }

    /// Stores the blob of a diamond of `level`. Keys are the codec's storage keys.
    pub fn put(&mut self, level: u32, key: &[u8], blob: &[u8]) -> Result<()> {
        let previous_len = match &mut self.spill {
            None => self
                .blobs
                .insert(key.to_vec(), blob.to_vec())
                .map(|old| old.len()),
            Some(spill) => spill.insert(key.to_vec(), blob)?,
        };
        if self.stats.len() <= level as usize {
            self.stats
                .resize_with(level as usize + 1, LevelStats::default);
            for (l, s) in self.stats.iter_mut().enumerate() {
                s.level = l as u32;
            }
        }
        let s = &mut self.stats[level as usize];
        if let Some(old_len) = previous_len {
            s.blobs -= 1;
            s.bytes -= old_len as u64;
        }
        s.blobs += 1;
        s.bytes += blob.len() as u64;
        Ok(())
    }

    /// Blob count and bytes per level so far.
    pub fn level_stats(&self) -> &[LevelStats] {
        &self.stats
    }

    /// Writes the pages, then the metadata record last, flushes, and renames the directory
    /// into place. With `overwrite`, an existing repository at the path is replaced (it
    /// stays intact until the new one is complete). Returns the published metadata.
    pub fn publish(self, mut metadata: Metadata, overwrite: bool) -> Result<Metadata> {
        if self.final_path.exists() && !overwrite {
            return Err(StoreError::Exists(self.final_path.clone()));
        }
        metadata.format_version = FORMAT_VERSION;
        metadata.level_stats = self.stats.clone();
        let mut h = Sha256::new();
        for kv in self.pending() {
            let (k, v) = kv?;
            hash_pair(&mut h, &k, &v);
        }
        metadata.content_hash = finish_hash(h, &metadata, &self.partial)?;
        metadata.complete = true;
        let json = serde_json::to_vec(&metadata).map_err(|e| StoreError::BadMetadata {
            path: self.partial.clone(),
            reason: e.to_string(),
        })?;
        let total: u64 = self.stats.iter().map(|s| s.bytes).sum();
        let page_bytes = self.page_bytes.unwrap_or_else(|| default_page_bytes(total));
        write_pages(&self.db, self.pending(), page_bytes, &self.partial)?;
        let RepositoryBuilder {
            final_path,
            partial,
            db,
            blobs,
            spill,
            ..
        } = self;
        drop(blobs);
        if let Some(spill) = spill {
            drop(spill.file);
            std::fs::remove_file(&spill.path).map_err(io_err("removing", &spill.path))?;
        }
        db.insert(METADATA_KEY, json).map_err(sled_err(&partial))?;
        db.flush().map_err(sled_err(&partial))?;
        drop(db);
        // Open and close it once the way readers do: recovery writes sled's snapshot and
        // settles the log, so the published directory is the size it will stay (and a
        // database that does not open is never published).
        drop(Repository::open_settling(&partial)?);
        let old = if final_path.exists() {
            let mut name = final_path.file_name().unwrap_or_default().to_os_string();
            name.push(".old");
            let old = final_path.with_file_name(name);
            if old.exists() {
                std::fs::remove_dir_all(&old).map_err(io_err("removing", &old))?;
            }
            std::fs::rename(&final_path, &old).map_err(io_err("moving aside", &final_path))?;
            Some(old)
        } else {
            None
        };
        std::fs::rename(&partial, &final_path).map_err(io_err("publishing", &final_path))?;
        if let Some(parent) = final_path.parent().filter(|p| !p.as_os_str().is_empty()) {
            // Make the rename durable.
            if let Ok(dir) = std::fs::File::open(parent) {
                let _ = dir.sync_all();
            }
        }
        if let Some(old) = old {
            std::fs::remove_dir_all(&old).map_err(io_err("removing", &old))?;
        }
        Ok(metadata)
    }
}

/// A key and its blob.
type KeyBlob = (Vec<u8>, Vec<u8>);

impl RepositoryBuilder {
    /// Every blob put so far, in key order.
    fn pending(&self) -> Box<dyn Iterator<Item = Result<KeyBlob>> + '_> {
        match &self.spill {
            None => Box::new(self.blobs.iter().map(|(k, v)| Ok((k.clone(), v.clone())))),
            Some(spill) => Box::new(spill.index.iter().map(|(k, &(at, len))| {
                use std::os::unix::fs::FileExt;
                let mut v = vec![0; len];
                spill
                    .file
                    .read_exact_at(&mut v, at)
                    .map_err(io_err("reading", &spill.path))?;
                Ok((k.clone(), v))
            })),
        }
    }
}

impl Spill {
    /// Appends a blob; returns the length of the blob it replaces, if any.
    fn insert(&mut self, key: Vec<u8>, blob: &[u8]) -> Result<Option<usize>> {
        use std::os::unix::fs::FileExt;
        self.file
            .write_all_at(blob, self.end)
            .map_err(io_err("writing", &self.path))?;
        let previous = self.index.insert(key, (self.end, blob.len()));
        self.end += blob.len() as u64;
        Ok(previous.map(|(_, len)| len))
    }
}

/// Packs `blobs` (in key order) into pages of about `page_bytes` and writes them,
/// [`PAGES_PER_TREE`] to a fresh tree, each with a single insert.
fn write_pages(
    db: &sled::Db,
    blobs: impl Iterator<Item = Result<KeyBlob>>,
    page_bytes: usize,
    path: &Path,
) -> Result<()> {
    let mut writer = page::PageWriter::default();
    let mut pending: Vec<(Vec<u8>, Vec<u8>)> = Vec::with_capacity(PAGES_PER_TREE);
    let write_tree = |pages: &mut Vec<(Vec<u8>, Vec<u8>)>| -> sled::Result<()> {
        let Some((first, _)) = pages.first() else {
            return Ok(());
        };
        let mut name = Vec::with_capacity(first.len() + 1);
        name.push(PAGE_TREE_PREFIX);
        name.extend_from_slice(first);
        let tree = db.open_tree(name)?;
        for (key, page) in pages.drain(..) {
            tree.insert(key, page)?;
        }
        // Written pages stay in sled's buffers until flushed: flush per tree so a large
        // repository's publication does not hold its pages in memory.
        db.flush()?;
        Ok(())
    };
    for kv in blobs {
        let (key, blob) = kv?;
        writer.push(&key, &blob);
        if writer.len() >= page_bytes
            && let Some(page) = writer.finish()
        {
            pending.push(page);
            if pending.len() == PAGES_PER_TREE {
                write_tree(&mut pending).map_err(sled_err(path))?;
            }
        }
    }
    if let Some(page) = writer.finish() {
        pending.push(page);
    }
    write_tree(&mut pending).map_err(sled_err(path))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn metadata() -> Metadata {
        Metadata {
            format_version: 0,
            complete: false,
            content_hash: String::new(),
            domain: "planar".into(),
            m: 6,
            n: 32,
            levels: 2,
            attribute: Attribute {
                kind: "elevation".into(),
                units: "m".into(),
            },
            extent: [65, 65],
            nodata: NodataPolicy {
                source_count: 0,
                handling: "none".into(),
            },
            georef: None,
            radius_m: None,
            channels: vec![],
            build: serde_json::json!({}),
            level_stats: vec![],
            coverage: None,
            inline_max_bytes: None,
        }
    }

    #[test]
    fn spilled_builds_publish_the_same_repository_and_leave_no_spill() {
        let dir = tempfile::tempdir().unwrap();
        let pairs: Vec<(Vec<u8>, Vec<u8>)> = (0u32..3000)
            .map(|i| {
                let key = [&[(i % 3) as u8][..], &(i * 7919 % 3001).to_be_bytes()].concat();
                (key, vec![(i % 251) as u8; (i % 97) as usize + 1])
            })
            .collect();
        let mut hashes = Vec::new();
        for spill in [false, true] {
            let path = dir.path().join(format!("repo{spill}"));
            let mut b = RepositoryBuilder::create(&path).unwrap();
            if spill {
                b.put(0, b"\x00early", b"kept").unwrap();
                b = b.spill_to_disk().unwrap();
            } else {
                b.put(0, b"\x00early", b"kept").unwrap();
            }
            for (k, v) in &pairs {
                b.put(u32::from(k[0]), k, v).unwrap();
            }
            let meta = b.publish(metadata(), false).unwrap();
            assert!(!spill_path(&path).exists());
            let repo = Repository::open(&path).unwrap();
            assert_eq!(repo.get(b"\x00early").unwrap().unwrap(), b"kept");
            for (k, v) in &pairs {
                assert_eq!(repo.get(k).unwrap().unwrap(), v.as_slice());
            }
            hashes.push((meta.content_hash, meta.level_stats));
        }
        assert_eq!(hashes[0], hashes[1]);
    }

    #[test]
    fn published_repository_reads_back_what_was_put() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        let mut b = RepositoryBuilder::create(&path).unwrap();
        b.put(0, b"\x00a", b"one").unwrap();
        b.put(1, b"\x01b", b"three").unwrap();
        b.put(1, b"\x01b", b"two").unwrap();
        let meta = b.publish(metadata(), false).unwrap();
        assert!(!partial_path(&path).exists());
        let repo = Repository::open(&path).unwrap();
        assert_eq!(repo.metadata(), &meta);
        assert_eq!(repo.get(b"\x00a").unwrap().unwrap(), b"one");
        assert_eq!(repo.get(b"\x01b").unwrap().unwrap(), b"two");
        assert!(repo.get(b"\x01c").unwrap().is_none());
        assert_eq!(repo.blob_count(), 2);
        assert_eq!(meta.level_stats[1].blobs, 1);
        assert_eq!(meta.level_stats[1].bytes, 3);
        assert_eq!(repo.compute_content_hash().unwrap(), meta.content_hash);
    }

    #[test]
    fn unfinished_build_never_opens_and_a_rerun_replaces_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        let mut b = RepositoryBuilder::create(&path).unwrap();
        b.put(0, b"k", b"v").unwrap();
        drop(b); // as if killed before publish
        assert!(matches!(
            Repository::open(&path),
            Err(StoreError::Missing(_))
        ));
        assert!(matches!(
            Repository::open(partial_path(&path)),
            Err(StoreError::Incomplete(_))
        ));
        let b = RepositoryBuilder::create(&path).unwrap();
        b.publish(metadata(), false).unwrap();
        let repo = Repository::open(&path).unwrap();
        assert_eq!(
            repo.blob_count(),
            0,
            "the stale partial build was discarded"
        );
    }

    #[test]
    fn content_hash_changes_with_content_and_existing_repositories_need_overwrite() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        let mut b = RepositoryBuilder::create(&path).unwrap();
        b.put(0, b"k", b"v1").unwrap();
        let first = b.publish(metadata(), false).unwrap();
        let mut b = RepositoryBuilder::create(&path).unwrap();
        b.put(0, b"k", b"v2").unwrap();
        assert!(matches!(
            b.publish(metadata(), false),
            Err(StoreError::Exists(_))
        ));
        let mut b = RepositoryBuilder::create(&path).unwrap();
        b.put(0, b"k", b"v2").unwrap();
        let second = b.publish(metadata(), true).unwrap();
        assert_ne!(first.content_hash, second.content_hash);
        let repo = Repository::open(&path).unwrap();
        assert_eq!(repo.get(b"k").unwrap().unwrap(), b"v2");
    }

    #[test]
    fn opening_garbage_is_an_error_not_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        assert!(Repository::open(dir.path().join("nothing")).is_err());
        let path = dir.path().join("junk");
        std::fs::create_dir_all(&path).unwrap();
        std::fs::write(path.join("conf"), b"garbage").unwrap();
        std::fs::write(path.join("db"), b"garbage").unwrap();
        assert!(Repository::open(&path).is_err());
    }

    fn build(
        path: &Path,
        pairs: &BTreeMap<Vec<u8>, Vec<u8>>,
        page_bytes: Option<usize>,
    ) -> (Metadata, Repository) {
        let mut b = RepositoryBuilder::create(path).unwrap();
        if let Some(n) = page_bytes {
            b = b.with_page_bytes(n);
        }
        for (k, v) in pairs {
            b.put(u32::from(k.first().copied().unwrap_or(0) % 4), k, v)
                .unwrap();
        }
        let meta = b.publish(metadata(), true).unwrap();
        (meta, Repository::open(path).unwrap())
    }

    fn check_against_model(repo: &Repository, meta: &Metadata, model: &BTreeMap<Vec<u8>, Vec<u8>>) {
        for (k, v) in model {
            assert_eq!(repo.get(k).unwrap().as_deref(), Some(v.as_slice()), "{k:?}");
        }
        let all: Vec<(Vec<u8>, Vec<u8>)> = repo
            .blobs()
            .map(|kv| {
                let (k, v) = kv.unwrap();
                (k.to_vec(), v.to_vec())
            })
            .collect();
        let want: Vec<(Vec<u8>, Vec<u8>)> =
            model.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        assert_eq!(all, want);
        assert_eq!(repo.blob_count(), model.len());
        assert_eq!(repo.compute_content_hash().unwrap(), meta.content_hash);
    }

    #[test]
    fn every_key_is_found_across_pages_and_trees_and_gaps_are_none() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        // Even keys only, so every odd key is a gap: before, between and after pages.
        let model: BTreeMap<Vec<u8>, Vec<u8>> = (0u32..400)
            .map(|i| {
                let key = [&[1u8][..], &(2 * i + 2).to_be_bytes()].concat();
                (key, vec![i as u8; (i % 50) as usize + 1])
            })
            .collect();
        let (meta, repo) = build(&path, &model, Some(100));
        assert!(repo.trees.len() > 3, "spans several page trees");
        check_against_model(&repo, &meta, &model);
        for i in 0u32..402 {
            let key = [&[1u8][..], &(2 * i + 1).to_be_bytes()].concat();
            assert!(repo.get(&key).unwrap().is_none(), "{key:?}");
        }
        for missing in [
            &b""[..],
            b"\x00",
            b"\x01",
            b"\x01\x00",
            b"\x02",
            b"\xff\xff\xff",
        ] {
            assert!(repo.get(missing).unwrap().is_none(), "{missing:?}");
        }
    }

    #[test]
    fn an_empty_repository_has_no_blobs() {
        let dir = tempfile::tempdir().unwrap();
        let (meta, repo) = build(&dir.path().join("repo"), &BTreeMap::new(), None);
        check_against_model(&repo, &meta, &BTreeMap::new());
        assert!(repo.get(b"\x00a").unwrap().is_none());
        assert!(repo.get(b"").unwrap().is_none());
    }

    #[test]
    fn blobs_bigger_than_a_page_and_keys_of_different_lengths_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let model: BTreeMap<Vec<u8>, Vec<u8>> = [
            (&b""[..], 3usize),
            (b"\x00", 0),
            (b"\x00\x01", 5),
            (b"\x00\x01\x02\x03\x04\x05\x06\x07\x08", 200_000),
            (b"\x01", 9000),
            (b"\x01\x00", 1),
            (b"\x02\xff\xff", 70_000),
        ]
        .into_iter()
        .map(|(k, n)| {
            (
                k.to_vec(),
                (0..n).map(|i| (i * 7 + k.len()) as u8).collect(),
            )
        })
        .collect();
        let (meta, repo) = build(&dir.path().join("repo"), &model, Some(4096));
        check_against_model(&repo, &meta, &model);
        assert!(repo.get(b"\x00\x01\x02").unwrap().is_none());
    }

    #[test]
    fn reopening_and_reading_everything_does_not_grow_the_directory() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        let model: BTreeMap<Vec<u8>, Vec<u8>> = (0u32..3000)
            .map(|i| (i.to_be_bytes().to_vec(), vec![(i % 251) as u8; 100]))
            .collect();
        let (_, repo) = build(&path, &model, None);
        drop(repo);
        let published = dir_size(&path).unwrap();
        let payload: usize = model.values().map(Vec::len).sum();
        assert!(
            published < payload as u64 * 13 / 10,
            "{published} for {payload}"
        );
        for _ in 0..2 {
            let repo = Repository::open(&path).unwrap();
            assert_eq!(repo.blobs().count(), model.len());
            drop(repo);
            assert_eq!(dir_size(&path).unwrap(), published);
        }
    }

    #[test]
    fn a_repository_of_another_format_version_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v1");
        {
            // Format 1: sled's default segment size, blobs in one tree.
            let db = sled::Config::new().path(&path).open().unwrap();
            db.open_tree("blobs").unwrap().insert("k", "v").unwrap();
            let mut m = metadata();
            m.format_version = 1;
            m.complete = true;
            db.insert(METADATA_KEY, serde_json::to_vec(&m).unwrap())
                .unwrap();
            db.flush().unwrap();
        }
        // sled's I/O threads may still hold the lock of the database just closed (seen
        // under load in CI): the same settling open the builder uses.
        assert!(matches!(
            Repository::open_settling(&path),
            Err(StoreError::Version { found: 1, .. })
        ));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(24))]
        #[test]
        fn random_repositories_read_back_like_a_map(
            model in proptest::collection::btree_map(
                proptest::collection::vec(0u8..4, 0..5),
                proptest::collection::vec(proptest::prelude::any::<u8>(), 0..300),
                0..120,
            ),
            probes in proptest::collection::vec(proptest::collection::vec(0u8..4, 0..6), 0..40),
            page_bytes in 1usize..2000,
        ) {
            let dir = tempfile::tempdir().unwrap();
            let (meta, repo) = build(&dir.path().join("repo"), &model, Some(page_bytes));
            check_against_model(&repo, &meta, &model);
            for p in &probes {
                let got = repo.get(p).unwrap();
                proptest::prop_assert_eq!(got.as_deref(), model.get(p).map(Vec::as_slice));
            }
        }
    }
}
