//! The repository file on disk: the layout of [`quincunx_meta::pack`] (format 8), read
//! with positioned reads and written in one pass.
//!
//! Reading keeps the header, the root directory and the tiling in memory, and the leaf
//! directories of the tiles read lately (a bounded cache); each blob read is one `pread`
//! of the blob and its CRC-32.

use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::sync::{Arc, Mutex, PoisonError};

use bytes::Bytes;

pub use quincunx_meta::pack::*;

/// Leaf directories kept in memory at most (each is at most [`LEAF_MAX`] entries).
const LEAF_CACHE: usize = 256;

/// Bytes a walk reads at once (more when one blob is larger).
const WALK_READ_BYTES: u64 = 1 << 20;

/// Why one read failed: the file could not be read, or what it read is damaged.
#[derive(Debug)]
pub(crate) enum ReadError {
    Io(std::io::Error),
    Damaged(PackError),
}

/// An open repository file: header, root directory, tiling and recent leaf directories.
pub(crate) struct PackFile {
    file: File,
    pub header: Header,
    pub root: RootDir,
    pub tiling: Tiling,
    leaves: Mutex<HashMap<usize, Arc<Entries>>>,
}

impl PackFile {
    pub fn new(file: File, header: Header, root: RootDir, tiling: Tiling) -> PackFile {
        PackFile {
            file,
            header,
            root,
            tiling,
            leaves: Mutex::new(HashMap::new()),
        }
    }

    fn read(&self, at: Section) -> Result<Vec<u8>, ReadError> {
        let len = usize::try_from(at.len)
            .map_err(|_| ReadError::Damaged(PackError::Damaged("section too large".into())))?;
        let mut buf = vec![0; len];
        self.file
            .read_exact_at(&mut buf, at.offset)
            .map_err(ReadError::Io)?;
        Ok(buf)
    }

    /// The entries of tile `i` (cached).
    pub fn leaf(&self, i: usize) -> Result<Arc<Entries>, ReadError> {
        let mut cache = self.leaves.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(e) = cache.get(&i) {
            return Ok(Arc::clone(e));
        }
        drop(cache);
        let tile = self.root.tiles[i];
        let bytes = self.read(tile.dir)?;
        let entries = Arc::new(parse_leaf(&tile, &bytes).map_err(ReadError::Damaged)?);
        cache = self.leaves.lock().unwrap_or_else(PoisonError::into_inner);
        if cache.len() >= LEAF_CACHE {
            cache.clear();
        }
        cache.insert(i, Arc::clone(&entries));
        Ok(entries)
    }

    /// Where `key`'s blob is, if it has one; a failure names the offset of the leaf
    /// directory that could not be read.
    pub fn locate(&self, key: &[u8]) -> Result<Option<BlobRef>, (u64, ReadError)> {
        Ok(match self.root.lookup(&self.tiling, key) {
            Lookup::Blob(b) => Some(b),
            Lookup::Absent => None,
            Lookup::Tile(i) => {
                let entries = self
                    .leaf(i)
                    .map_err(|e| (self.root.tiles[i].dir.offset, e))?;
                find(&entries, key)
            }
        })
    }

    /// The blob at `b`, checked.
    pub fn blob(&self, b: BlobRef) -> Result<Bytes, ReadError> {
        let framed = self.read(b.framed())?;
        b.check(&framed).map_err(ReadError::Damaged)?;
        let mut framed = Bytes::from(framed);
        framed.truncate(b.len as usize);
        Ok(framed)
    }

    /// Every blob in file order: the root's, then tile by tile. Each blob is checked; a
    /// damaged blob or leaf directory is one error and the walk goes on.
    pub fn walk(&self) -> Walk<'_> {
        Walk {
            pack: self,
            root_at: 0,
            tile: 0,
            tile_entries: None,
            tile_at: 0,
            ready: VecDeque::new(),
        }
    }

    /// Reads `entries` (contiguous in the file) in one read and checks each blob.
    fn read_run(&self, entries: &[(Vec<u8>, BlobRef)], out: &mut VecDeque<WalkItem>) {
        let (Some((_, first)), Some((_, last))) = (entries.first(), entries.last()) else {
            return;
        };
        let span = Section {
            offset: first.offset,
            len: last.framed().end() - first.offset,
        };
        match self.read(span) {
            Err(e) => out.push_back(Err((entries[0].0.clone(), first.offset, e))),
            Ok(bytes) => {
                let bytes = Bytes::from(bytes);
                for (key, b) in entries {
                    let at = (b.offset - span.offset) as usize;
                    let framed = bytes.slice(at..at + b.framed().len as usize);
                    out.push_back(match b.check(&framed) {
                        Ok(_) => Ok((key.clone(), framed.slice(..b.len as usize))),
                        Err(e) => Err((key.clone(), b.offset, ReadError::Damaged(e))),
                    });
                }
            }
        }
    }
}

/// One blob of a walk, or the key and offset where reading failed.
pub(crate) type WalkItem = Result<(Vec<u8>, Bytes), (Vec<u8>, u64, ReadError)>;

/// The blobs of a file in file order (see [`PackFile::walk`]).
pub(crate) struct Walk<'a> {
    pack: &'a PackFile,
    root_at: usize,
    tile: usize,
    tile_entries: Option<Arc<Entries>>,
    tile_at: usize,
    ready: VecDeque<WalkItem>,
}

/// How many of `entries` (from the start) one read takes.
fn batch(entries: &[(Vec<u8>, BlobRef)]) -> usize {
    let Some((_, first)) = entries.first() else {
        return 0;
    };
    let n = entries.partition_point(|(_, b)| b.framed().end() - first.offset <= WALK_READ_BYTES);
    n.max(1)
}

impl Iterator for Walk<'_> {
    type Item = WalkItem;

    fn next(&mut self) -> Option<WalkItem> {
        loop {
            if let Some(item) = self.ready.pop_front() {
                return Some(item);
            }
            let root = &self.pack.root.entries.list;
            if self.root_at < root.len() {
                let n = batch(&root[self.root_at..]);
                self.pack
                    .read_run(&root[self.root_at..self.root_at + n], &mut self.ready);
                self.root_at += n;
                continue;
            }
            if let Some(entries) = &self.tile_entries {
                if self.tile_at < entries.len() {
                    let n = batch(&entries.list[self.tile_at..]);
                    let entries = Arc::clone(entries);
                    self.pack.read_run(
                        &entries.list[self.tile_at..self.tile_at + n],
                        &mut self.ready,
                    );
                    self.tile_at += n;
                    continue;
                }
                self.tile_entries = None;
                self.tile += 1;
            }
            let tile = self.pack.root.tiles.get(self.tile)?;
            match self.pack.leaf(self.tile) {
                Ok(entries) => {
                    self.tile_entries = Some(entries);
                    self.tile_at = 0;
                }
                Err(e) => {
                    self.tile += 1;
                    return Some(Err((Vec::new(), tile.dir.offset, e)));
                }
            }
        }
    }
}

/// The sections of a file to write, in order, once its blobs' order and lengths are
/// known: header, root, metadata, leaves; the blobs follow ([`write_blob`]).
pub(crate) fn write_head<W: Write>(
    out: &mut W,
    dirs: &Dirs,
    tiling: &Tiling,
    metadata_json: &[u8],
) -> std::io::Result<Header> {
    let metadata = deflate(metadata_json);
    let header = Header::for_sections(
        dirs,
        tiling,
        metadata.len() as u64,
        crc32fast::hash(&metadata),
    );
    out.write_all(&header.to_bytes())?;
    out.write_all(&dirs.root)?;
    out.write_all(&metadata)?;
    out.write_all(&dirs.leaves)?;
    Ok(header)
}

/// Writes one blob and its CRC-32.
pub(crate) fn write_blob<W: Write>(out: &mut W, blob: &[u8]) -> std::io::Result<()> {
    out.write_all(blob)?;
    out.write_all(&crc32fast::hash(blob).to_le_bytes())
}
