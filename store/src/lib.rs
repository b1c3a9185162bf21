//! The quincunx repository: a directory holding one immutable file, `repository.pack`, with
//! a metadata record and one opaque blob per non-empty diamond, keyed by the codec's
//! locality key (spec: `docs/repository-format.md`).
//!
//! Layout (format 6): blobs are packed in key order into pages of a few KiB (see [`page`]),
//! the pages written back to back, followed by a page index (first key, length, blob count
//! and CRC-32 of each page), the metadata record and a footer ([`pack`]). Readers open the
//! file read-only, load the index and metadata, and read pages with positioned reads.
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
//! - Every damage to the file is an error naming the repository: head, footer, index and
//!   metadata are checked at open, each page's CRC when it is read.

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
pub mod page;

/// Version of the repository layout (the pack file) and of the blobs in it: 6 is the pack
/// file with version-4 blobs; 5 held the same blobs in a sled database, 4 version-3 blobs.
pub const FORMAT_VERSION: u32 = 6;

/// The file in a repository directory that holds the repository.
pub const PACK_FILE: &str = "repository.pack";

/// Smallest target page size.
const MIN_PAGE_BYTES: usize = 4 << 10;

/// Largest target page size chosen automatically.
const MAX_PAGE_BYTES: usize = 64 << 10;

/// Pages aimed for at most: the index is held in memory by every reader (about 20 bytes a
/// page), so large repositories get larger pages.
const TARGET_PAGES: u64 = 1 << 16;

/// Target page size for `total_bytes` of blobs: 4 KiB (one filesystem block: a `get` reads
/// one), larger when that keeps the index under [`TARGET_PAGES`] entries.
fn default_page_bytes(total_bytes: u64) -> usize {
    usize::try_from(total_bytes / TARGET_PAGES)
        .unwrap_or(MAX_PAGE_BYTES)
        .clamp(MIN_PAGE_BYTES, MAX_PAGE_BYTES)
}

/// Why a repository could not be opened, read or written.
#[derive(Debug, thiserror::Error)]
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
    #[error("{path} has repository format {found}; this build reads format {FORMAT_VERSION}")]
    Version {
        /// Repository path.
        path: PathBuf,
        /// Version found.
        found: u32,
    },
    /// A stored page is damaged.
    #[error("{path}: page at key {key:02x?} (offset {offset}): {reason}")]
    Page {
        /// The repository file.
        path: PathBuf,
        /// The page's first key.
        key: Vec<u8>,
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
    file: File,
    /// The page index, in key order.
    pages: Vec<pack::PageRef>,
    metadata: Metadata,
}

impl Repository {
    /// Opens a published repository (the directory `path`). Reads the head, footer, index
    /// and metadata and checks them; pages are checked when read.
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
        let pack_err = |reason| StoreError::Pack {
            path: file_path.clone(),
            reason,
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
        let head = read(0, pack::HEAD_BYTES.min(file_len))?;
        if head.len() < pack::HEAD_BYTES as usize
            && pack::HEAD_MAGIC.starts_with(&head[..head.len().min(pack::HEAD_MAGIC.len())])
        {
            return Err(StoreError::Incomplete(path.to_path_buf()));
        }
        let head_version = pack::parse_head(&head).map_err(pack_err)?;
        if head_version != FORMAT_VERSION {
            return Err(StoreError::Version {
                path: path.to_path_buf(),
                found: head_version,
            });
        }
        if file_len < pack::HEAD_BYTES + pack::FOOTER_BYTES {
            return Err(StoreError::Incomplete(path.to_path_buf()));
        }
        let footer_bytes = read(file_len - pack::FOOTER_BYTES, pack::FOOTER_BYTES)?;
        let footer = match pack::Footer::parse(&footer_bytes, file_len) {
            Err(pack::PackError::Incomplete(_)) => {
                let tail_len = file_len.min(pack::TRAILING_SEARCH_BYTES);
                let tail = read(file_len - tail_len, tail_len)?;
                return Err(match pack::trailing_bytes(&tail, file_len) {
                    Some(extra) => pack_err(pack::PackError::Damaged(format!(
                        "{extra} trailing byte(s) after the footer (something was appended \
                         to the file)"
                    ))),
                    None => StoreError::Incomplete(path.to_path_buf()),
                });
            }
            other => other.map_err(pack_err)?,
        };
        if footer.format_version != head_version {
            return Err(pack_err(pack::PackError::Damaged(format!(
                "head says format {head_version}, footer {}",
                footer.format_version
            ))));
        }
        let index = read(footer.index_offset, footer.index_len)?;
        if crc32fast::hash(&index) != footer.index_crc {
            return Err(pack_err(pack::PackError::Damaged(
                "page index checksum mismatch".into(),
            )));
        }
        let raw = read(footer.index_offset + footer.index_len, footer.metadata_len)?;
        if crc32fast::hash(&raw) != footer.metadata_crc {
            return Err(pack_err(pack::PackError::Damaged(
                "metadata checksum mismatch".into(),
            )));
        }
        let pages = pack::decode_index(&index, footer.index_offset).map_err(pack_err)?;
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
        metadata
            .check_limits()
            .map_err(|e| StoreError::BadMetadata {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?;
        Ok(Repository {
            path: path.to_path_buf(),
            file_path,
            file,
            pages,
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

    fn page_err(&self, page: &pack::PageRef, reason: String) -> StoreError {
        StoreError::Page {
            path: self.file_path.clone(),
            key: page.first_key.to_vec(),
            offset: page.offset,
            reason,
        }
    }

    /// Reads a page and checks its CRC.
    fn read_page(&self, page: &pack::PageRef) -> Result<Bytes> {
        let mut buf = vec![0; page.len as usize];
        self.file
            .read_exact_at(&mut buf, page.offset)
            .map_err(io_err("reading", &self.file_path))?;
        if crc32fast::hash(&buf) != page.crc {
            return Err(self.page_err(page, "checksum mismatch".into()));
        }
        Ok(Bytes::from(buf))
    }

    /// The blob stored under `key`, `None` when the diamond has no blob (a leaf). The bytes
    /// are copied out of the page read, so whoever keeps them (the server's hot cache)
    /// holds the blob, not its page: as views, 24,000 cached blobs of about 100 bytes
    /// held over 100 MB of 4 KiB pages under an 8 MiB cache budget.
    pub fn get(&self, key: &[u8]) -> Result<Option<Bytes>> {
        // The page whose first key is the greatest one <= key.
        let after = self.pages.partition_point(|p| &*p.first_key <= key);
        let Some(page_ref) = after.checked_sub(1).and_then(|i| self.pages.get(i)) else {
            return Ok(None);
        };
        let page = self.read_page(page_ref)?;
        let found = page::find(&page_ref.first_key, &page, key)
            .map_err(|e| self.page_err(page_ref, e.to_string()))?;
        Ok(found.map(|range| Bytes::copy_from_slice(&page[range])))
    }

    /// Every `(key, blob)` in key order (level-major, then space-filling curve). Each page
    /// is checked fully (checksum, lengths, key order, blob count); a damaged page is one
    /// error, and the walk goes on with the next page.
    pub fn blobs(&self) -> impl Iterator<Item = Result<(Vec<u8>, Bytes)>> + '_ {
        self.pages.iter().enumerate().flat_map(move |(i, p)| {
            let next = self.pages.get(i + 1).map(|n| &*n.first_key);
            match self.page_entries(p, next) {
                Ok(entries) => entries.into_iter().map(Ok).collect::<Vec<_>>(),
                Err(e) => vec![Err(e)],
            }
        })
    }

    /// The pairs of one page, whose keys must stay below the next page's first key.
    fn page_entries(
        &self,
        page_ref: &pack::PageRef,
        next: Option<&[u8]>,
    ) -> Result<Vec<(Vec<u8>, Bytes)>> {
        let page = self.read_page(page_ref)?;
        let bad = |e: page::PageError| self.page_err(page_ref, e.to_string());
        let mut reader = page::PageReader::new(&page_ref.first_key, &page).map_err(bad)?;
        if reader.remaining() != page_ref.blobs as usize {
            return Err(self.page_err(
                page_ref,
                format!(
                    "holds {} blobs, the index says {}",
                    reader.remaining(),
                    page_ref.blobs
                ),
            ));
        }
        let mut out = Vec::with_capacity(reader.remaining());
        while let Some((key, value)) = reader.next_entry().map_err(bad)? {
            out.push((key.to_vec(), page.slice(value)));
        }
        if let (Some((last, _)), Some(next)) = (out.last(), next)
            && last.as_slice() >= next
        {
            return Err(self.page_err(page_ref, "keys run past the next page's first key".into()));
        }
        Ok(out)
    }

    /// Number of blobs (from the index: no page is read).
    pub fn blob_count(&self) -> usize {
        self.pages.iter().map(|p| p.blobs as usize).sum()
    }

    /// Bytes the repository occupies on disk (all files in its directory).
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
/// output, a fraction of the input) and written there in one pass, in key order, packed into
/// pages; the partial repository file is created and locked at once, so a concurrent build
/// into the same path fails early instead of deleting the running build's files.
pub struct RepositoryBuilder {
    final_path: PathBuf,
    partial: PathBuf,
    /// The repository file being written (locked while this builder lives).
    file: File,
    blobs: BTreeMap<Vec<u8>, Vec<u8>>,
    spill: Option<Spill>,
    stats: Vec<LevelStats>,
    page_bytes: Option<usize>,
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
    /// gets a page of its own). The default is 4 KiB, more for repositories of over 256 MB
    /// (see [`TARGET_PAGES`]). For measurements; any value reads back the same.
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

    /// Writes the pages, the index and the metadata record, then the footer, syncs, and
    /// publishes with one rename. With `overwrite`, an existing repository at the path is
    /// replaced: the new file is renamed onto the old one, so the path holds a complete
    /// repository at every instant. Returns the published metadata.
    pub fn publish(self, mut metadata: Metadata, overwrite: bool) -> Result<Metadata> {
        RepositoryBuilder::check_destination(&self.final_path, overwrite)?;
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
        let file_path = self.partial.join(PACK_FILE);
        let write_err = io_err("writing", &file_path);
        let out = std::io::BufWriter::with_capacity(1 << 20, &self.file);
        let mut pack = pack::PackWriter::new(out, FORMAT_VERSION).map_err(write_err)?;
        let mut writer = page::PageWriter::default();
        let write_page =
            |writer: &mut page::PageWriter, pack: &mut pack::PackWriter<_>| -> Result<()> {
                let count = writer.count();
                if let Some((first_key, page)) = writer.finish() {
                    pack.page(&first_key, &page, count)
                        .map_err(io_err("writing", &file_path))?;
                }
                Ok(())
            };
        for kv in self.pending() {
            let (key, blob) = kv?;
            writer.push(&key, &blob);
            if writer.len() >= page_bytes {
                write_page(&mut writer, &mut pack)?;
            }
        }
        write_page(&mut writer, &mut pack)?;
        abort_point("pages");
        let out = pack.finish(&json).map_err(io_err("writing", &file_path))?;
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
                    "the written index does not count every blob".into(),
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

/// A key and its blob.
type KeyBlob = (Vec<u8>, Vec<u8>);

impl RepositoryBuilder {
    /// Every blob put so far, in key order.
    fn pending(&self) -> Box<dyn Iterator<Item = Result<KeyBlob>> + '_> {
        match &self.spill {
            None => Box::new(self.blobs.iter().map(|(k, v)| Ok((k.clone(), v.clone())))),
            Some(spill) => Box::new(spill.index.iter().map(|(k, &(at, len))| {
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
    fn every_key_is_found_across_pages_and_gaps_are_none() {
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
        assert!(repo.pages.len() > 3, "spans several pages");
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
        bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
        std::fs::write(&file, &bytes).unwrap();
        assert!(matches!(
            Repository::open(&path),
            Err(StoreError::Version { found: 7, .. })
        ));
    }

    #[test]
    fn a_page_whose_keys_run_into_the_next_page_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crafted");
        std::fs::create_dir(&path).unwrap();
        let page = |pairs: &[(&[u8], &[u8])]| {
            let mut w = page::PageWriter::default();
            for (k, v) in pairs {
                w.push(k, v);
            }
            w.finish().unwrap()
        };
        let (k1, p1) = page(&[(b"a", b"1"), (b"c", b"3")]);
        let (k2, p2) = page(&[(b"b", b"2")]);
        let mut m = metadata();
        m.format_version = FORMAT_VERSION;
        m.complete = true;
        m.content_hash = "0".repeat(64);
        let mut w = pack::PackWriter::new(Vec::new(), FORMAT_VERSION).unwrap();
        w.page(&k1, &p1, 2).unwrap();
        w.page(&k2, &p2, 1).unwrap();
        let bytes = w.finish(&serde_json::to_vec(&m).unwrap()).unwrap();
        std::fs::write(path.join(PACK_FILE), bytes).unwrap();
        let repo = Repository::open(&path).unwrap();
        let walk: Vec<_> = repo.blobs().collect();
        assert_eq!(
            walk.len(),
            2,
            "one error for the first page, one blob from the second"
        );
        assert!(
            walk[0]
                .as_ref()
                .err()
                .unwrap()
                .to_string()
                .contains("next page")
        );
        assert_eq!(&walk[1].as_ref().unwrap().1[..], b"2");
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
