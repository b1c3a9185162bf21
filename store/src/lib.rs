//! The quincunx repository: one sled database (a directory) holding a metadata record and
//! one opaque blob per non-empty diamond, keyed by the codec's locality key (spec:
//! `docs/repository-format.md`).
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

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// Version of the repository layout (metadata record + blob tree).
pub const FORMAT_VERSION: u32 = 1;

const METADATA_KEY: &[u8] = b"metadata";
const BLOB_TREE: &[u8] = b"blobs";

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

fn open_db(path: &Path) -> Result<sled::Db> {
    sled::Config::new()
        .path(path)
        .mode(sled::Mode::LowSpace)
        .open()
        .map_err(sled_err(path))
}

/// An open, complete repository. Read-only: there is no way to write through it.
pub struct Repository {
    path: PathBuf,
    db: sled::Db,
    blobs: sled::Tree,
    metadata: Metadata,
}

impl Repository {
    /// Opens a published repository. Fails with [`StoreError::Incomplete`] for anything an
    /// interrupted build left behind.
    pub fn open(path: impl AsRef<Path>) -> Result<Repository> {
        let path = path.as_ref();
        if !path.join("db").exists() && !path.join("conf").exists() {
            return Err(StoreError::Missing(path.to_path_buf()));
        }
        let db = open_db(path)?;
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
        let blobs = db.open_tree(BLOB_TREE).map_err(sled_err(path))?;
        Ok(Repository {
            path: path.to_path_buf(),
            db,
            blobs,
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

    /// The blob stored under `key`, `None` when the diamond has no blob (a leaf).
    pub fn get(&self, key: &[u8]) -> Result<Option<sled::IVec>> {
        self.blobs.get(key).map_err(sled_err(&self.path))
    }

    /// Every `(key, blob)` in key order (level-major, then space-filling curve).
    pub fn blobs(&self) -> impl Iterator<Item = Result<(sled::IVec, sled::IVec)>> + '_ {
        self.blobs.iter().map(|r| r.map_err(sled_err(&self.path)))
    }

    /// Number of blobs.
    pub fn blob_count(&self) -> usize {
        self.blobs.len()
    }

    /// Bytes the database occupies on disk (all files in its directory).
    pub fn size_on_disk(&self) -> Result<u64> {
        dir_size(&self.path)
    }

    /// Recomputes the content hash from the stored blobs and metadata.
    pub fn compute_content_hash(&self) -> Result<String> {
        content_hash(&self.blobs, &self.metadata, &self.path)
    }

    /// sled's own opinion of its size (for the overhead report).
    pub fn sled_size_on_disk(&self) -> Result<u64> {
        self.db.size_on_disk().map_err(sled_err(&self.path))
    }
}

fn content_hash(blobs: &sled::Tree, metadata: &Metadata, path: &Path) -> Result<String> {
    let mut h = Sha256::new();
    for kv in blobs.iter() {
        let (k, v) = kv.map_err(sled_err(path))?;
        h.update((k.len() as u64).to_le_bytes());
        h.update(&k);
        h.update((v.len() as u64).to_le_bytes());
        h.update(&v);
    }
    let mut m = metadata.clone();
    m.content_hash.clear();
    m.complete = true;
    let json = serde_json::to_vec(&m).map_err(|e| StoreError::BadMetadata {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    h.update(&json);
    Ok(h
        .finalize()
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
pub struct RepositoryBuilder {
    final_path: PathBuf,
    partial: PathBuf,
    db: sled::Db,
    blobs: sled::Tree,
    stats: Vec<LevelStats>,
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
            drop(open_db(&partial)?);
            std::fs::remove_dir_all(&partial).map_err(io_err("removing", &partial))?;
        }
        if let Some(parent) = final_path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(io_err("creating", parent))?;
        }
        let db = open_db(&partial)?;
        let blobs = db.open_tree(BLOB_TREE).map_err(sled_err(&partial))?;
        Ok(RepositoryBuilder {
            final_path,
            partial,
            db,
            blobs,
            stats: Vec::new(),
        })
    }

    /// Stores the blob of a diamond of `level`. Keys are the codec's storage keys.
    pub fn put(&mut self, level: u32, key: &[u8], blob: &[u8]) -> Result<()> {
        let previous = self
            .blobs
            .insert(key, blob)
            .map_err(sled_err(&self.partial))?;
        if self.stats.len() <= level as usize {
            self.stats.resize_with(level as usize + 1, LevelStats::default);
            for (l, s) in self.stats.iter_mut().enumerate() {
                s.level = l as u32;
            }
        }
        let s = &mut self.stats[level as usize];
        if let Some(old) = previous {
            s.blobs -= 1;
            s.bytes -= old.len() as u64;
        }
        s.blobs += 1;
        s.bytes += blob.len() as u64;
        Ok(())
    }

    /// Blob count and bytes per level so far.
    pub fn level_stats(&self) -> &[LevelStats] {
        &self.stats
    }

    /// Writes the metadata record last, flushes, and renames the directory into place.
    /// With `overwrite`, an existing repository at the path is replaced (it stays intact
    /// until the new one is complete). Returns the published metadata.
    pub fn publish(self, mut metadata: Metadata, overwrite: bool) -> Result<Metadata> {
        if self.final_path.exists() && !overwrite {
            return Err(StoreError::Exists(self.final_path.clone()));
        }
        metadata.format_version = FORMAT_VERSION;
        metadata.level_stats = self.stats.clone();
        metadata.content_hash = content_hash(&self.blobs, &metadata, &self.partial)?;
        metadata.complete = true;
        let json = serde_json::to_vec(&metadata).map_err(|e| StoreError::BadMetadata {
            path: self.partial.clone(),
            reason: e.to_string(),
        })?;
        self.db
            .insert(METADATA_KEY, json)
            .map_err(sled_err(&self.partial))?;
        self.db.flush().map_err(sled_err(&self.partial))?;
        let RepositoryBuilder {
            final_path,
            partial,
            db,
            blobs,
            ..
        } = self;
        drop(blobs);
        drop(db);
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
        }
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
        assert_eq!(repo.blob_count(), 0, "the stale partial build was discarded");
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
}
