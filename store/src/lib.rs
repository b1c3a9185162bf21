//! The quincunx repository: a directory holding one immutable file, `repository.pack`, with
//! a metadata record and one opaque blob per non-empty diamond, keyed by the codec's
//! locality key (spec: `docs/repository-format.md`).
//!
//! Layout (format 8, [`pack`]): a header, the root directory and the metadata record at
//! the start of the file (one small read opens it, locally or over HTTP ranges), the
//! tiles' leaf directories, then the blobs, each followed by its CRC-32. Directories give
//! every blob's exact byte range. Readers open the file read-only, keep the header and
//! root directory in memory, and read leaf directories and blobs with positioned reads.
//!
//! Invariants:
//! - Keys and blobs are bytes here: this crate never decodes a blob (the server depends on
//!   it and must not depend on the codec).
//! - Reading never writes: [`Repository::open`] opens one file read-only, takes no lock and
//!   creates nothing, so any number of processes read a repository at once, from read-only
//!   files and filesystems, and its bytes and times stay as they are.
//! - A repository is immutable once built. [`RepositoryBuilder`] writes the file inside a
//!   sibling directory `<path>.partial`, footer last, syncs it, and publishes it with one
//!   rename: of the directory when nothing is at `<path>`, of the file onto
//!   `<path>/repository.pack` when replacing a repository (`overwrite`). At every instant
//!   `<path>` holds the old complete repository or the new one; processes that opened the
//!   old one keep reading it (its inode) until they close it.
//! - Every damage to the file is an error naming the repository: header, root directory
//!   and metadata are checked at open, a leaf directory's and a blob's CRC when read.

use std::collections::BTreeMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use bytes::Bytes;
use sha2::{Digest, Sha256};

pub mod answer;
pub use quincunx_meta::channels;
pub use quincunx_meta::{
    Attribute, AttributeKind, ChannelCoding, Domain, Georef, LevelStats, Metadata, NodataHandling,
    NodataPolicy, Rate, Registration,
};
pub mod pack;

/// Version of the repository layout (the pack file) and of the blobs in it: 7 is the
/// range-readable file (directories with exact blob ranges, [`pack`]) with version-4
/// blobs; 6 packed the same blobs into pages indexed at the end of the file; 5 held them
/// in a sled database, 4 version-3 blobs.
pub const FORMAT_VERSION: u32 = pack::LAYOUT_VERSION;

/// The file in a repository directory that holds the repository.
pub const PACK_FILE: &str = "repository.pack";

/// Why a repository could not be opened, read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// No repository at the path.
    #[error("no repository at {0}")]
    Missing(PathBuf),
    /// A directory, but no repository file in it.
    #[error("{0} is a directory without a repository (no {PACK_FILE} in it)")]
    NotARepository(PathBuf),
    /// The repository file is not a regular file (a FIFO, device, socket or directory).
    #[error("{1}: refusing to read it as a repository")]
    NotAFile(PathBuf, String),
    /// A repository of format 5 or older (a sled database directory).
    #[error(
        "{0} is a repository of format 5 or older (a sled database); this build reads format \
         {FORMAT_VERSION}: rebuild it with `quincunx build`"
    )]
    Legacy(PathBuf),
    /// The file is not a complete repository: an interrupted build or a truncated copy.
    #[error("{0} is not a complete repository (interrupted build or truncated copy)")]
    Incomplete(PathBuf),
    /// The repository file is damaged or not a repository file.
    #[error("{path}: {reason}")]
    Pack {
        /// The repository file.
        path: PathBuf,
        /// What is wrong.
        reason: pack::PackError,
    },
    /// The metadata record is unreadable.
    #[error("metadata of {path} is malformed: {reason}")]
    BadMetadata {
        /// Repository path.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The repository was written by an incompatible version.
    #[error(
        "{path} has repository format {found}; this build reads format {FORMAT_VERSION}: \
         rebuild it with `quincunx build`"
    )]
    Version {
        /// Repository path.
        path: PathBuf,
        /// Version found.
        found: u32,
    },
    /// A stored blob or leaf directory is damaged.
    #[error("{path}: {what} at offset {offset}: {reason}")]
    Damaged {
        /// The repository file.
        path: PathBuf,
        /// What was read: the blob of a key, or a leaf directory.
        what: String,
        /// Its offset in the file.
        offset: u64,
        /// What is wrong.
        reason: String,
    },
    /// Publishing would replace an existing repository and that was not asked for.
    #[error("{0} already exists (pass overwrite to replace it)")]
    Exists(PathBuf),
    /// Publishing would put a repository into a directory that holds something else.
    #[error("{0} exists and is not a repository: refusing to publish into it")]
    Occupied(PathBuf),
    /// Another build is writing the same repository.
    #[error("another build is writing {0} (its {1} is locked)")]
    Busy(PathBuf, PathBuf),
    /// Filesystem operation failed.
    #[error("{context} {path}: {cause}")]
    Io {
        /// What was being done.
        context: &'static str,
        /// Path involved.
        path: PathBuf,
        /// Cause (in the message, so not also a `source`: printed once in error chains).
        cause: std::io::Error,
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

fn io_err<'a>(
    context: &'static str,
    path: &'a Path,
) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |cause| StoreError::Io {
        context,
        path: path.to_path_buf(),
        cause,
    }
}

/// Whether anything (even a dangling link) is at `path`; errors other than "not found"
/// count as something being there.
fn occupied(path: &Path) -> bool {
    !matches!(std::fs::symlink_metadata(path), Err(e) if e.kind() == std::io::ErrorKind::NotFound)
}

/// What is at a path that is not a regular file, in words ("a FIFO", "a directory").
fn file_kind(m: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = m.file_type();
    if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else {
        "not a regular file"
    }
}

/// Opens `path` read-only if it is a regular file (after links), and fails without
/// blocking otherwise: the type is checked before `open` (which blocks on a FIFO without
/// a writer) and again on the open file (in case the path changed in between). Every tool
/// opens repository and part files through this.
pub fn open_regular_file(path: &Path) -> std::io::Result<File> {
    let not_regular = |m: &std::fs::Metadata| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} is {}, not a regular file", path.display(), file_kind(m)),
        )
    };
    let before = std::fs::metadata(path)?;
    if !before.is_file() {
        return Err(not_regular(&before));
    }
    let file = File::open(path)?;
    let after = file.metadata()?;
    if !after.is_file() {
        return Err(not_regular(&after));
    }
    Ok(file)
}

/// An open, complete repository. Read-only: there is no way to write through it, and
/// opening it writes nothing.
pub struct Repository {
    path: PathBuf,
    file_path: PathBuf,
    pack: pack::PackFile,
    metadata: Metadata,
}

impl Repository {
    /// Opens a published repository (the directory `path`). Reads the header, the root
    /// directory and the metadata and checks them; leaf directories and blobs are checked
    /// when read.
    pub fn open(path: impl AsRef<Path>) -> Result<Repository> {
        let path = path.as_ref();
        let file_path = path.join(PACK_FILE);
        let file = match open_regular_file(&file_path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(match std::fs::metadata(path) {
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        StoreError::Missing(path.to_path_buf())
                    }
                    Err(cause) => StoreError::Io {
                        context: "opening",
                        path: path.to_path_buf(),
                        cause,
                    },
                    Ok(m) if !m.is_dir() => StoreError::NotARepository(path.to_path_buf()),
                    Ok(_) if holds_sled_database(path) => StoreError::Legacy(path.to_path_buf()),
                    Ok(_) => StoreError::NotARepository(path.to_path_buf()),
                });
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotADirectory => {
                return Err(StoreError::NotARepository(path.to_path_buf()));
            }
            Err(e) if e.kind() == std::io::ErrorKind::InvalidInput => {
                return Err(StoreError::NotAFile(file_path, e.to_string()));
            }
            Err(cause) => {
                return Err(StoreError::Io {
                    context: "opening",
                    path: file_path,
                    cause,
                });
            }
        };
        let meta = file.metadata().map_err(io_err("reading", &file_path))?;
        if meta.is_dir() {
            return Err(StoreError::NotARepository(path.to_path_buf()));
        }
        let file_len = meta.len();
        let read = |at: u64, len: u64| -> Result<Vec<u8>> {
            let mut buf = vec![0; usize::try_from(len).unwrap_or(usize::MAX)];
            file.read_exact_at(&mut buf, at)
                .map_err(io_err("reading", &file_path))?;
            Ok(buf)
        };
        let pack_err = |reason| match reason {
            pack::PackError::Incomplete(_) => StoreError::Incomplete(path.to_path_buf()),
            pack::PackError::Version(found) => StoreError::Version {
                path: path.to_path_buf(),
                found,
            },
            reason => StoreError::Pack {
                path: file_path.clone(),
                reason,
            },
        };
        let head = read(0, pack::HEADER_BYTES.min(file_len))?;
        let header = pack::Header::parse(&head).map_err(pack_err)?;
        header.check_len(file_len).map_err(pack_err)?;
        let front = read(pack::HEADER_BYTES, header.open_len() - pack::HEADER_BYTES)?;
        let (root, raw) = front.split_at(header.root.len as usize);
        let root = pack::RootDir::parse(&header, root).map_err(pack_err)?;
        let raw = header.metadata_json(raw).map_err(pack_err)?;
        let bad_metadata = |reason: String| StoreError::BadMetadata {
            path: path.to_path_buf(),
            reason,
        };
        let metadata: Metadata =
            serde_json::from_slice(&raw).map_err(|e| bad_metadata(e.to_string()))?;
        if metadata.format_version != FORMAT_VERSION {
            return Err(StoreError::Version {
                path: path.to_path_buf(),
                found: metadata.format_version,
            });
        }
        if !metadata.complete {
            return Err(StoreError::Incomplete(path.to_path_buf()));
        }
        metadata
            .check_limits()
            .map_err(|e| bad_metadata(e.to_string()))?;
        let space = answer::IdSpace::of(&metadata).map_err(bad_metadata)?;
        let tiling = pack::Tiling::new(&space, header.split_level, header.tile_shift);
        Ok(Repository {
            path: path.to_path_buf(),
            file_path,
            pack: pack::PackFile::new(file, header, root, tiling),
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

    /// The file's header (where its sections are).
    pub fn header(&self) -> &pack::Header {
        &self.pack.header
    }

    /// Entries in the root directory and tiles it lists.
    pub fn directory_sizes(&self) -> (usize, usize) {
        self.pack.root.sizes()
    }

    fn read_err(
        &self,
        what: impl FnOnce() -> String,
        offset: u64,
        e: pack::ReadError,
    ) -> StoreError {
        match e {
            pack::ReadError::Io(cause) => StoreError::Io {
                context: "reading",
                path: self.file_path.clone(),
                cause,
            },
            pack::ReadError::Damaged(reason) => StoreError::Damaged {
                path: self.file_path.clone(),
                what: what(),
                offset,
                reason: reason.reason(),
            },
        }
    }

    /// The blob stored under `key`, `None` when the diamond has no blob (a leaf): a
    /// directory lookup (the root's, or a tile's leaf directory, cached), then one read of
    /// the blob and its CRC-32.
    pub fn get(&self, key: &[u8]) -> Result<Option<Bytes>> {
        let at = match self.pack.locate(key) {
            Ok(Some(at)) => at,
            Ok(None) => return Ok(None),
            Err((offset, e)) => return Err(self.read_err(|| "leaf directory".into(), offset, e)),
        };
        self.pack
            .blob(at)
            .map(Some)
            .map_err(|e| self.read_err(|| format!("blob of key {key:02x?}"), at.offset, e))
    }

    /// Every `(key, blob)` in file order: the root directory's blobs in key order
    /// (level-major, then space-filling curve), then tile by tile, each in key order.
    /// Each blob's CRC is checked; a damaged blob (or leaf directory) is one error, and
    /// the walk goes on with the next one.
    pub fn blobs(&self) -> impl Iterator<Item = Result<(Vec<u8>, Bytes)>> + '_ {
        self.pack.walk().map(move |item| {
            item.map_err(|(key, offset, e)| {
                let what = || {
                    if key.is_empty() {
                        "leaf directory".to_string()
                    } else {
                        format!("blob of key {key:02x?}")
                    }
                };
                self.read_err(what, offset, e)
            })
        })
    }

    /// Number of blobs (from the header: nothing else is read).
    pub fn blob_count(&self) -> usize {
        usize::try_from(self.pack.header.blob_count).unwrap_or(usize::MAX)
    }

    /// Bytes the repository occupies on disk (all files in its directory).
    pub fn size_on_disk(&self) -> Result<u64> {
        dir_size(&self.path)
    }

    /// Recomputes the content hash from the stored blobs (in file order) and metadata.
    pub fn compute_content_hash(&self) -> Result<String> {
        let mut h = Sha256::new();
        for kv in self.blobs() {
            let (k, v) = kv?;
            hash_pair(&mut h, &k, &v);
        }
        finish_hash(h, &self.metadata, &self.path)
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
    m.static_export = false;
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
/// output, a fraction of the input) and written there in one pass, in the file's order
/// ([`pack::Plan`]); the partial repository file is created and locked at once, so a concurrent build
/// into the same path fails early instead of deleting the running build's files.
pub struct RepositoryBuilder {
    final_path: PathBuf,
    partial: PathBuf,
    /// The repository file being written (locked while this builder lives).
    file: File,
    blobs: BTreeMap<Vec<u8>, Vec<u8>>,
    spill: Option<Spill>,
    stats: Vec<LevelStats>,
    limits: pack::Limits,
}

/// Blobs held on disk instead of in memory until publication (out-of-core builds): an
/// append-only file beside the partial repository and an in-memory index of where each
/// key's blob is (about 40 bytes per blob).
struct Spill {
    path: PathBuf,
    file: File,
    end: u64,
    index: BTreeMap<Vec<u8>, (u64, usize)>,
}

/// `path` with `suffix` appended to its file name.
fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(suffix);
    path.with_file_name(name)
}

/// Where an out-of-core build of `path` keeps its blobs until publication.
pub fn spill_path(path: &Path) -> PathBuf {
    sibling(path, ".spill")
}

/// Where a partial build of `path` is written.
pub fn partial_path(path: &Path) -> PathBuf {
    sibling(path, ".partial")
}

/// Files a repository of format 5 or older (a sled database) may hold.
fn is_legacy_entry(name: &std::ffi::OsStr) -> bool {
    let name = name.to_string_lossy();
    matches!(name.as_ref(), "db" | "conf" | "blobs") || name.starts_with("snap.")
}

/// Whether `path` is a directory holding a repository, of this format or an older one.
fn holds_repository(path: &Path) -> bool {
    occupied(&path.join(PACK_FILE)) || holds_sled_database(path)
}

/// Whether `path` holds a sled database (a repository of format 5 or older).
fn holds_sled_database(path: &Path) -> bool {
    occupied(&path.join("db")) || occupied(&path.join("conf"))
}

/// Test hook: `QUINCUNX_PUBLISH_ABORT_AT=<step>` aborts the process at that step of
/// [`RepositoryBuilder::publish`] (`pages`, `synced`, `swapped`), as a kill there would,
/// so tests can check what readers find after a crash at each step.
fn abort_point(step: &str) {
    if std::env::var_os("QUINCUNX_PUBLISH_ABORT_AT").is_some_and(|s| s == step) {
        eprintln!("QUINCUNX_PUBLISH_ABORT_AT={step}: aborting");
        std::process::abort();
    }
}

/// Makes a rename in `dir` durable.
fn sync_dir(dir: &Path) {
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

impl RepositoryBuilder {
    /// Starts a build of the repository at `path`. A stale `<path>.partial` left by an
    /// interrupted build is removed; one that a running build holds is an error
    /// ([`StoreError::Busy`]).
    pub fn create(path: impl AsRef<Path>) -> Result<RepositoryBuilder> {
        let final_path = path.as_ref().to_path_buf();
        let partial = partial_path(&final_path);
        let file_path = partial.join(PACK_FILE);
        if occupied(&partial) {
            if let Ok(f) = std::fs::OpenOptions::new().write(true).open(&file_path) {
                match f.try_lock() {
                    Ok(()) => {}
                    Err(std::fs::TryLockError::WouldBlock) => {
                        return Err(StoreError::Busy(final_path, file_path));
                    }
                    Err(std::fs::TryLockError::Error(e)) => {
                        return Err(io_err("locking", &file_path)(e));
                    }
                }
            }
            std::fs::remove_dir_all(&partial).map_err(io_err("removing", &partial))?;
        }
        if let Some(parent) = final_path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(io_err("creating", parent))?;
        }
        match std::fs::create_dir(&partial) {
            Ok(()) => {}
            // Another build created it since the check above.
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(StoreError::Busy(final_path, file_path));
            }
            Err(e) => return Err(io_err("creating", &partial)(e)),
        }
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&file_path)
            .map_err(io_err("creating", &file_path))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                return Err(StoreError::Busy(final_path, file_path));
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(io_err("locking", &file_path)(e));
            }
        }
        // Under the partial file's lock: a stale spill is ours to remove.
        let spill = spill_path(&final_path);
        if occupied(&spill) {
            std::fs::remove_file(&spill).map_err(io_err("removing", &spill))?;
        }
        Ok(RepositoryBuilder {
            final_path,
            partial,
            file,
            blobs: BTreeMap::new(),
            spill: None,
            stats: Vec::new(),
            limits: pack::Limits::default(),
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

    /// Sets the thresholds of the layout: when deep levels go to tiles, and how many
    /// blobs a tile holds. The defaults ([`pack::Limits::default`]) suit every
    /// repository; tests use small ones to give small repositories tiles.
    pub fn with_layout_limits(mut self, limits: pack::Limits) -> RepositoryBuilder {
        self.limits = limits;
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

    /// Whether publishing would need `overwrite`, or could not publish at all: call before
    /// starting work so a build is refused before it encodes anything.
    pub fn check_destination(path: &Path, overwrite: bool) -> Result<()> {
        if !occupied(path) {
            return Ok(());
        }
        if !path.is_dir() || !holds_repository(path) {
            return Err(StoreError::Occupied(path.to_path_buf()));
        }
        if !overwrite {
            return Err(StoreError::Exists(path.to_path_buf()));
        }
        Ok(())
    }

    /// Chooses the layout, writes the header, directories, metadata and blobs, syncs, and
    /// publishes with one rename. With `overwrite`, an existing repository at the path is
    /// replaced: the new file is renamed onto the old one, so the path holds a complete
    /// repository at every instant. Returns the published metadata.
    pub fn publish(self, mut metadata: Metadata, overwrite: bool) -> Result<Metadata> {
        RepositoryBuilder::check_destination(&self.final_path, overwrite)?;
        metadata.format_version = FORMAT_VERSION;
        metadata.level_stats = self.stats.clone();
        let bad_metadata = |reason: String| StoreError::BadMetadata {
            path: self.partial.clone(),
            reason,
        };
        let space = answer::IdSpace::of(&metadata).map_err(bad_metadata)?;
        let layout_err = |e: String| StoreError::Pack {
            path: self.partial.clone(),
            reason: pack::PackError::Damaged(e),
        };
        let (plan, placed) = self
            .file_order(&space, metadata.inline_max_bytes)
            .map_err(layout_err)?;
        let keys: Vec<Vec<u8>> = placed.iter().map(|p| p.key.clone()).collect();
        let mut h = Sha256::new();
        for kv in self.in_order(&keys) {
            let (k, v) = kv?;
            hash_pair(&mut h, k, &v);
        }
        metadata.content_hash = finish_hash(h, &metadata, &self.partial)?;
        metadata.complete = true;
        let json = serde_json::to_vec(&metadata).map_err(|e| bad_metadata(e.to_string()))?;
        let mut dirs = pack::DirWriter::new(plan.clone());
        for p in placed {
            dirs.push(p).map_err(layout_err)?;
        }
        let dirs = dirs.finish().map_err(layout_err)?;
        let file_path = self.partial.join(PACK_FILE);
        let write_err = io_err("writing", &file_path);
        let mut out = std::io::BufWriter::with_capacity(1 << 20, &self.file);
        pack::write_head(&mut out, &dirs, &plan.tiling, &json).map_err(write_err)?;
        for kv in self.in_order(&keys) {
            let (_, blob) = kv?;
            pack::write_blob(&mut out, &blob).map_err(io_err("writing", &file_path))?;
        }
        abort_point("blobs");
        out.into_inner()
            .map_err(|e| io_err("writing", &file_path)(e.into_error()))?
            .sync_all()
            .map_err(io_err("syncing", &file_path))?;
        // Read it back the way readers do: a file that does not open is never published.
        let check = Repository::open(&self.partial)?;
        if check.blob_count() as u64 != self.stats.iter().map(|s| s.blobs).sum::<u64>() {
            return Err(StoreError::Pack {
                path: file_path.clone(),
                reason: pack::PackError::Damaged(
                    "the written directories do not count every blob".into(),
                ),
            });
        }
        drop(check);
        abort_point("synced");
        let RepositoryBuilder {
            final_path,
            partial,
            file,
            spill,
            ..
        } = self;
        let parent = final_path.parent().unwrap_or(Path::new(""));
        if occupied(&final_path) {
            // Replacing: the new file onto the old one, in one rename.
            let target = final_path.join(PACK_FILE);
            std::fs::rename(&file_path, &target).map_err(io_err("publishing", &target))?;
            sync_dir(&final_path);
            abort_point("swapped");
            // What a sled repository (format 5 or older) held beside it.
            let entries = std::fs::read_dir(&final_path).map_err(io_err("reading", &final_path))?;
            for entry in entries.flatten() {
                if is_legacy_entry(&entry.file_name()) {
                    let p = entry.path();
                    let removed = if p.is_dir() {
                        std::fs::remove_dir_all(&p)
                    } else {
                        std::fs::remove_file(&p)
                    };
                    removed.map_err(io_err("removing", &p))?;
                }
            }
            std::fs::remove_dir(&partial).map_err(io_err("removing", &partial))?;
        } else {
            std::fs::rename(&partial, &final_path).map_err(io_err("publishing", &final_path))?;
        }
        sync_dir(parent);
        drop(file);
        if let Some(spill) = spill {
            drop(spill.file);
            std::fs::remove_file(&spill.path).map_err(io_err("removing", &spill.path))?;
        }
        Ok(metadata)
    }
}

impl RepositoryBuilder {
    /// The layout for the blobs put so far, and their keys in the file's order
    /// ([`pack::Plan::arrange`]: packages up to `inline_max_bytes`).
    fn file_order(
        &self,
        space: &answer::IdSpace,
        inline_max_bytes: Option<u32>,
    ) -> std::result::Result<(pack::Plan, Vec<pack::Placed>), String> {
        let lens: Vec<(Vec<u8>, u64)> = match &self.spill {
            None => self
                .blobs
                .iter()
                .map(|(k, v)| (k.clone(), v.len() as u64))
                .collect(),
            Some(spill) => spill
                .index
                .iter()
                .map(|(k, &(_, len))| (k.clone(), len as u64))
                .collect(),
        };
        let plan = pack::Plan::choose(space, lens.iter().map(|(k, _)| k.as_slice()), self.limits);
        let placed = plan.arrange(lens, inline_max_bytes)?;
        Ok((plan, placed))
    }

    /// The blobs of `keys`, in that order.
    fn in_order<'a>(
        &'a self,
        keys: &'a [Vec<u8>],
    ) -> impl Iterator<Item = Result<(&'a [u8], std::borrow::Cow<'a, [u8]>)>> + 'a {
        keys.iter().map(move |k| match &self.spill {
            None => Ok((
                k.as_slice(),
                std::borrow::Cow::Borrowed(self.blobs.get(k).map_or(&[][..], Vec::as_slice)),
            )),
            Some(spill) => {
                let &(at, len) = spill.index.get(k).unwrap_or(&(0, 0));
                let mut v = vec![0; len];
                spill
                    .file
                    .read_exact_at(&mut v, at)
                    .map_err(io_err("reading", &spill.path))?;
                Ok((k.as_slice(), std::borrow::Cow::Owned(v)))
            }
        })
    }
}

impl Spill {
    /// Appends a blob; returns the length of the blob it replaces, if any.
    fn insert(&mut self, key: Vec<u8>, blob: &[u8]) -> Result<Option<usize>> {
        self.file
            .write_all_at(blob, self.end)
            .map_err(io_err("writing", &self.path))?;
        let previous = self.index.insert(key, (self.end, blob.len()));
        self.end += blob.len() as u64;
        Ok(previous.map(|(_, len)| len))
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
            domain: crate::Domain::Planar,
            m: 6,
            n: 32,
            levels: 2,
            attribute: Attribute {
                kind: crate::AttributeKind::Elevation,
                units: "m".into(),
            },
            extent: [65, 65],
            nodata: NodataPolicy {
                source_count: 0,
                handling: crate::NodataHandling::None,
            },
            georef: None,
            radius_m: None,
            channels: vec![],
            build: serde_json::json!({}),
            level_stats: vec![],
            coverage: None,
            inline_max_bytes: None,
            static_export: false,
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
            assert_eq!(&repo.get(b"\x00early").unwrap().unwrap()[..], b"kept");
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
        assert_eq!(&repo.get(b"\x00a").unwrap().unwrap()[..], b"one");
        assert_eq!(&repo.get(b"\x01b").unwrap().unwrap()[..], b"two");
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
        assert_eq!(&repo.get(b"k").unwrap().unwrap()[..], b"v2");
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
        limits: Option<pack::Limits>,
    ) -> (Metadata, Repository) {
        let mut b = RepositoryBuilder::create(path).unwrap();
        if let Some(limits) = limits {
            b = b.with_layout_limits(limits);
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
        let walk: Vec<(Vec<u8>, Vec<u8>)> = repo
            .blobs()
            .map(|kv| {
                let (k, v) = kv.unwrap();
                (k.to_vec(), v.to_vec())
            })
            .collect();
        let all: BTreeMap<Vec<u8>, Vec<u8>> = walk.iter().cloned().collect();
        assert_eq!(walk.len(), all.len(), "each blob once");
        assert_eq!(&all, model);
        assert_eq!(repo.blob_count(), model.len());
        assert_eq!(repo.compute_content_hash().unwrap(), meta.content_hash);
    }

    /// Every centre of levels `0 .. levels` of the planar domain of [`metadata`] (m = 6),
    /// in key order.
    fn diamond_keys(levels: u32) -> Vec<Vec<u8>> {
        let d = quincunx_diamond::PlanarDomain::new(6).unwrap();
        let mut out: Vec<Vec<u8>> = (0..=64)
            .flat_map(|x| (0..=64).map(move |y| quincunx_diamond::PlanarId::new(x, y)))
            .filter(|&id| d.level(id).is_ok_and(|l| l < levels))
            .map(|id| d.key(id).unwrap())
            .collect();
        out.sort();
        out
    }

    /// Limits that give a few hundred blobs tiles.
    const SMALL_TILES: pack::Limits = pack::Limits {
        root_all_max: 0,
        root_split_max: 8,
        leaf_max: 40,
    };

    #[test]
    fn every_key_is_found_in_the_root_and_in_tiles_and_gaps_are_none() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        // Every other diamond has a blob, so the others are gaps everywhere.
        let keys = diamond_keys(10);
        let model: BTreeMap<Vec<u8>, Vec<u8>> = keys
            .iter()
            .step_by(2)
            .enumerate()
            .map(|(i, k)| (k.clone(), vec![i as u8; i % 50 + 1]))
            .collect();
        let (meta, repo) = build(&path, &model, Some(SMALL_TILES));
        let (root, tiles) = repo.directory_sizes();
        assert!(root <= 8 && tiles > 3, "{root} root entries, {tiles} tiles");
        check_against_model(&repo, &meta, &model);
        for k in keys.iter().skip(1).step_by(2) {
            assert!(repo.get(k).unwrap().is_none(), "{k:?}");
        }
        for missing in [
            &b""[..],
            b"\x00",
            b"\x01",
            b"\x01\x00",
            b"\x09",
            b"\xff\xff\xff",
        ] {
            assert!(repo.get(missing).unwrap().is_none(), "{missing:?}");
        }
        // The same blobs with the default limits: one directory, the same blobs.
        let (_, flat) = build(&dir.path().join("flat"), &model, None);
        assert_eq!(flat.directory_sizes(), (model.len(), 0));
    }

    #[test]
    fn a_damaged_blob_or_leaf_directory_is_one_error_and_the_walk_goes_on() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("repo");
        let model: BTreeMap<Vec<u8>, Vec<u8>> = diamond_keys(10)
            .into_iter()
            .map(|k| (k, vec![7; 30]))
            .collect();
        let (_, repo) = build(&path, &model, Some(SMALL_TILES));
        let header = *repo.header();
        let (_, tiles) = repo.directory_sizes();
        drop(repo);
        let file = path.join(PACK_FILE);
        let good = std::fs::read(&file).unwrap();
        // A byte of the last blob, then a byte of the first leaf directory.
        for (at, errors, missing) in [
            (header.file_len - 10, 1, 1),
            (header.leaves.offset + 2, 1, 0),
        ] {
            let mut bytes = good.clone();
            bytes[at as usize] ^= 0x40;
            std::fs::write(&file, &bytes).unwrap();
            let repo = Repository::open(&path).unwrap();
            let walk: Vec<_> = repo.blobs().collect();
            let failed: Vec<String> = walk
                .iter()
                .filter_map(|r| r.as_ref().err().map(ToString::to_string))
                .collect();
            assert_eq!(failed.len(), errors, "{failed:?}");
            assert!(failed[0].contains("checksum mismatch"), "{failed:?}");
            let read = walk.iter().filter(|r| r.is_ok()).count();
            if missing == 1 {
                assert_eq!(read, model.len() - 1);
            } else {
                // The first tile's blobs are lost, every other one is read.
                assert!(read < model.len() && read > model.len() / 2, "{read}");
                assert!(tiles > 1);
            }
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
        let (meta, repo) = build(&dir.path().join("repo"), &model, None);
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
    fn repositories_of_other_formats_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        // Format 5 and older: a sled database directory.
        let legacy = dir.path().join("v5");
        std::fs::create_dir_all(&legacy).unwrap();
        std::fs::write(legacy.join("conf"), b"segment_size: 65536\n").unwrap();
        std::fs::write(legacy.join("db"), [0u8; 64]).unwrap();
        let err = Repository::open(&legacy).err().unwrap();
        assert!(matches!(err, StoreError::Legacy(_)), "{err}");
        assert!(err.to_string().contains("rebuild"), "{err}");
        // A pack file of another version.
        let path = dir.path().join("repo");
        RepositoryBuilder::create(&path)
            .unwrap()
            .publish(metadata(), false)
            .unwrap();
        let file = path.join(PACK_FILE);
        let mut bytes = std::fs::read(&file).unwrap();
        bytes[8..12].copy_from_slice(&6u32.to_le_bytes());
        std::fs::write(&file, &bytes).unwrap();
        let err = Repository::open(&path).err().unwrap();
        assert!(matches!(err, StoreError::Version { found: 6, .. }), "{err}");
        assert!(err.to_string().contains("rebuild"), "{err}");
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
        ) {
            let dir = tempfile::tempdir().unwrap();
            let (meta, repo) = build(&dir.path().join("repo"), &model, None);
            check_against_model(&repo, &meta, &model);
            for p in &probes {
                let got = repo.get(p).unwrap();
                proptest::prop_assert_eq!(got.as_deref(), model.get(p).map(Vec::as_slice));
            }
        }
    }
}
