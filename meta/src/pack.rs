//! The repository file's layout (format 8), without I/O: the header, the directories that
//! map diamond keys to the exact byte range of each blob, the blob framing, and the order
//! of blobs that makes a package one range. The store writes and reads files with it; the
//! client reads the same file over HTTP range requests (spec:
//! `docs/repository-format.md`).
//!
//! ```text
//! file   := header root metadata leaves blobs
//! header := fixed 128 bytes (below), its own CRC-32 last
//! root   := deflate(entries tiles)               the root directory
//! leaves := (deflate(entries) crc:u32)*          one leaf directory per tile, tile order
//! blobs  := (blob crc:u32)*                      the root's blobs, then each tile's
//! entries := count:varint (shared:varint suffix_len:varint suffix len:varint carried:varint){count}
//! tiles   := count:varint (tile_delta:varint128 dir_len:varint blobs_len:varint count:varint){count}
//! ```
//!
//! - **One read opens a file**: the header, the root directory and the metadata (deflated
//!   JSON) come first; a client reads [`OPEN_BYTES`] and has all three when they fit, and
//!   at most one more range when they do not.
//! - **Directories give exact ranges**: an entry is a key (prefix-compressed against the
//!   previous entry's) and its blob's length; offsets are implied, since blobs follow each
//!   other in directory order, each followed by the CRC-32 of its bytes.
//! - **A package is one range.** A served package ([`crate::answer`]) is a diamond's blob
//!   with the packages of its small owned children (at most the metadata's
//!   `inline_max_bytes` each). Here every package whose members share a directory is
//!   contiguous: the diamond, then each carried child's package in child order; `carried`
//!   is how many entries after a blob its package holds (0: none). A client asks for the
//!   range `offset .. package end` and has the same package the server would answer,
//!   with one request and one round trip. Packages nobody carries follow each other in
//!   key order (level-major, Z-order within a level), so the packages a view needs lie in
//!   few ranges.
//! - **Small repositories have one directory** (up to [`ROOT_ALL_MAX`] blobs): every blob
//!   is in the root.
//! - **Large ones are split**: the levels below `split_level` (the ones every view reads)
//!   stay in the root; deeper blobs are grouped by **tile**, a square of side
//!   `2^tile_shift` id units (on a planet, of one cube face) holding every diamond centre
//!   inside it, of every deeper level. Each tile has a leaf directory and one contiguous
//!   run of blobs, so a view reads a tile's directory once and its blobs as a few ranges,
//!   coarse levels first. The root lists the tiles that hold blobs (a missing tile holds
//!   none). A package never spans two directories: a child in another one is not carried.
//! - A diamond that no directory lists has no blob: it is a leaf.
//!
//! Everything here parses bytes that may be damaged or hostile: every length is checked
//! against its section before anything is allocated, inflation is bounded, and damage is a
//! [`PackError`], never a panic.

use std::collections::HashMap;

use crate::answer::IdSpace;

/// First bytes of a repository file (the CR LF catches text-mode transfers).
pub const MAGIC: &[u8; 8] = b"QXREPO\r\n";

/// The layout version this module reads and writes.
pub const LAYOUT_VERSION: u32 = 8;

/// Bytes of the header.
pub const HEADER_BYTES: u64 = 128;

/// What a range reader fetches first: the header, and the root directory and metadata
/// when they fit (PMTiles' figure).
pub const OPEN_BYTES: u64 = 16 << 10;

/// Bytes of the CRC-32 after each blob and leaf directory.
pub const CRC_BYTES: u64 = 4;

/// Repositories of at most this many blobs keep every entry in the root directory (about
/// 3 bytes an entry once deflated, so 24 KB at most).
pub const ROOT_ALL_MAX: usize = 8192;

/// Blobs the root keeps of the levels below the split, at most (all of level 0 always).
pub const ROOT_SPLIT_MAX: usize = 4096;

/// Entries a tile's leaf directory holds at most (unless one point holds more).
pub const LEAF_MAX: usize = 8192;

/// Largest inflated root or leaf directory accepted.
const MAX_DIR_BYTES: usize = 64 << 20;

/// Largest inflated metadata record accepted.
pub const MAX_METADATA_BYTES: usize = 256 << 20;

/// Why bytes are not a readable repository file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PackError {
    /// Not a repository file at all.
    #[error("not a quincunx repository file (its first bytes are not \"QXREPO\")")]
    NotAPack,
    /// A repository file of another layout version.
    #[error("repository file format {0}; this build reads format {LAYOUT_VERSION}")]
    Version(u32),
    /// Shorter than its header says: an interrupted build or a truncated copy.
    #[error("{0} (an interrupted build or a truncated copy)")]
    Incomplete(String),
    /// Structurally damaged.
    #[error("damaged: {0}")]
    Damaged(String),
}

impl PackError {
    /// What is wrong, without the kind's prefix (for messages that name the part read).
    pub fn reason(self) -> String {
        match self {
            PackError::Damaged(r) | PackError::Incomplete(r) => r,
            e => e.to_string(),
        }
    }
}

fn damaged(what: impl Into<String>) -> PackError {
    PackError::Damaged(what.into())
}

/// A byte range of the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Section {
    /// First byte.
    pub offset: u64,
    /// Length in bytes.
    pub len: u64,
}

impl Section {
    /// One past the last byte.
    pub fn end(&self) -> u64 {
        self.offset + self.len
    }

    fn checked_end(&self) -> Option<u64> {
        self.offset.checked_add(self.len)
    }
}

/// The fixed header at the start of the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Layout version ([`LAYOUT_VERSION`]).
    pub version: u32,
    /// Bytes in the whole file: a shorter file is truncated, a longer one has bytes
    /// appended.
    pub file_len: u64,
    /// The root directory (deflated).
    pub root: Section,
    /// The metadata record (deflated JSON).
    pub metadata: Section,
    /// The leaf directories, back to back in tile order.
    pub leaves: Section,
    /// The blobs, each followed by its CRC-32.
    pub blobs: Section,
    /// CRC-32 of the root directory's bytes.
    pub root_crc: u32,
    /// CRC-32 of the metadata's bytes.
    pub metadata_crc: u32,
    /// Levels below this one are listed in the root; deeper ones in tiles.
    pub split_level: u32,
    /// Tiles are squares of side `2^tile_shift` id units.
    pub tile_shift: u32,
    /// Blobs in the file.
    pub blob_count: u64,
}

impl Header {
    /// The header's bytes.
    pub fn to_bytes(&self) -> [u8; HEADER_BYTES as usize] {
        let mut out = [0u8; HEADER_BYTES as usize];
        out[..8].copy_from_slice(MAGIC);
        let mut at = 8;
        let mut put = |bytes: &[u8]| {
            out[at..at + bytes.len()].copy_from_slice(bytes);
            at += bytes.len();
        };
        put(&self.version.to_le_bytes());
        put(&0u32.to_le_bytes());
        put(&self.file_len.to_le_bytes());
        for s in [self.root, self.metadata, self.leaves, self.blobs] {
            put(&s.offset.to_le_bytes());
            put(&s.len.to_le_bytes());
        }
        put(&self.root_crc.to_le_bytes());
        put(&self.metadata_crc.to_le_bytes());
        put(&self.split_level.to_le_bytes());
        put(&self.tile_shift.to_le_bytes());
        put(&self.blob_count.to_le_bytes());
        let crc = crc32fast::hash(&out[..HEADER_BYTES as usize - 4]);
        out[HEADER_BYTES as usize - 4..].copy_from_slice(&crc.to_le_bytes());
        out
    }

    /// Parses and checks a header: magic, version, checksum, and sections that follow each
    /// other in order and end exactly at `file_len`. Whether the file has that length is
    /// the caller's check ([`Header::check_len`]).
    pub fn parse(bytes: &[u8]) -> Result<Header, PackError> {
        if bytes.len() < MAGIC.len() {
            return Err(if MAGIC.starts_with(bytes) {
                PackError::Incomplete("shorter than its header".into())
            } else {
                PackError::NotAPack
            });
        }
        if &bytes[..8] != MAGIC {
            return Err(PackError::NotAPack);
        }
        if bytes.len() < 12 {
            return Err(PackError::Incomplete("shorter than its header".into()));
        }
        let u32_at = |at: usize| u32::from_le_bytes(array(&bytes[at..at + 4]));
        let version = u32_at(8);
        if version != LAYOUT_VERSION {
            return Err(PackError::Version(version));
        }
        let bytes: &[u8; HEADER_BYTES as usize] = bytes
            .get(..HEADER_BYTES as usize)
            .and_then(|b| b.try_into().ok())
            .ok_or_else(|| PackError::Incomplete("shorter than its header".into()))?;
        let u32_at = |at: usize| u32::from_le_bytes(array(&bytes[at..at + 4]));
        let u64_at = |at: usize| u64::from_le_bytes(array(&bytes[at..at + 8]));
        if crc32fast::hash(&bytes[..HEADER_BYTES as usize - 4]) != u32_at(124) {
            return Err(damaged("header checksum mismatch"));
        }
        if u32_at(12) != 0 {
            return Err(damaged("reserved header bytes are not zero"));
        }
        let section = |at: usize| Section {
            offset: u64_at(at),
            len: u64_at(at + 8),
        };
        let header = Header {
            version,
            file_len: u64_at(16),
            root: section(24),
            metadata: section(40),
            leaves: section(56),
            blobs: section(72),
            root_crc: u32_at(88),
            metadata_crc: u32_at(92),
            split_level: u32_at(96),
            tile_shift: u32_at(100),
            blob_count: u64_at(104),
        };
        if bytes[112..124].iter().any(|&b| b != 0) {
            return Err(damaged("reserved header bytes are not zero"));
        }
        let mut end = HEADER_BYTES;
        for (name, s) in [
            ("root directory", header.root),
            ("metadata", header.metadata),
            ("leaf directories", header.leaves),
            ("blobs", header.blobs),
        ] {
            if s.offset != end || s.checked_end().is_none() {
                return Err(damaged(format!(
                    "the {name} (at {}, {} bytes) does not follow the section before it \
                     (which ends at {end})",
                    s.offset, s.len
                )));
            }
            end = s.end();
        }
        if end != header.file_len {
            return Err(damaged(format!(
                "sections end at {end}, the header says the file has {} bytes",
                header.file_len
            )));
        }
        if header.split_level > 255 || header.tile_shift > 127 {
            return Err(damaged("split level or tile size out of range"));
        }
        Ok(header)
    }

    /// Checks that a file (or an object) of `len` bytes is the one this header describes.
    pub fn check_len(&self, len: u64) -> Result<(), PackError> {
        match len.cmp(&self.file_len) {
            std::cmp::Ordering::Equal => Ok(()),
            std::cmp::Ordering::Less => Err(PackError::Incomplete(format!(
                "{len} of its {} bytes",
                self.file_len
            ))),
            std::cmp::Ordering::Greater => Err(damaged(format!(
                "{} trailing byte(s) after its end (something was appended to the file)",
                len - self.file_len
            ))),
        }
    }

    /// The bytes a reader needs before its first blob: header, root and metadata.
    pub fn open_len(&self) -> u64 {
        self.metadata.end()
    }

    /// Inflates and checks the metadata section's bytes (`bytes` = exactly the section).
    pub fn metadata_json(&self, bytes: &[u8]) -> Result<Vec<u8>, PackError> {
        if crc32fast::hash(bytes) != self.metadata_crc {
            return Err(damaged("metadata checksum mismatch"));
        }
        inflate(bytes, MAX_METADATA_BYTES).map_err(|e| damaged(format!("metadata: {e}")))
    }
}

fn array<const N: usize>(bytes: &[u8]) -> [u8; N] {
    let mut out = [0u8; N];
    out.copy_from_slice(bytes);
    out
}

/// Raw deflate at the default level.
pub fn deflate(raw: &[u8]) -> Vec<u8> {
    miniz_oxide::deflate::compress_to_vec(raw, 6)
}

/// Inflates raw deflate, refusing output over `limit` bytes.
pub fn inflate(bytes: &[u8], limit: usize) -> Result<Vec<u8>, String> {
    miniz_oxide::inflate::decompress_to_vec_with_limit(bytes, limit).map_err(|e| match e.status {
        miniz_oxide::inflate::TINFLStatus::HasMoreOutput => {
            format!("inflates to more than {limit} bytes")
        }
        status => format!("not valid deflate data ({status:?})"),
    })
}

/// Where a blob is: its bytes at `offset .. offset + len`, then its CRC-32; its package
/// ends at `package_end`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BlobRef {
    /// First byte of the blob.
    pub offset: u64,
    /// Length of the blob (without its CRC).
    pub len: u64,
    /// End of its package: the blob and the carried blobs after it, each with its CRC
    /// (the blob's own framed end when it carries none).
    pub package_end: u64,
}

impl BlobRef {
    /// The blob and its CRC: what a reader fetches.
    pub fn framed(&self) -> Section {
        Section {
            offset: self.offset,
            len: self.len + CRC_BYTES,
        }
    }

    /// The blob and the blobs it carries, each with its CRC: what a reader fetches for
    /// a package.
    pub fn package(&self) -> Section {
        Section {
            offset: self.offset,
            len: self.package_end - self.offset,
        }
    }

    /// The blob out of `framed`, its bytes and CRC as read, after checking the CRC.
    pub fn check<'a>(&self, framed: &'a [u8]) -> Result<&'a [u8], PackError> {
        let len = usize::try_from(self.len).map_err(|_| damaged("blob too large"))?;
        if framed.len() as u64 != self.len + CRC_BYTES {
            return Err(damaged(format!(
                "read as {} bytes, its directory says {} and a checksum",
                framed.len(),
                self.len
            )));
        }
        let (blob, crc) = framed.split_at(len);
        if crc32fast::hash(blob).to_le_bytes() != crc {
            return Err(damaged("checksum mismatch"));
        }
        Ok(blob)
    }
}

/// A tile the root lists: where its leaf directory and its blobs are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileRef {
    /// Tile id ([`Tiling::tile`]).
    pub tile: u128,
    /// Its leaf directory (deflated entries, then their CRC-32).
    pub dir: Section,
    /// Its blobs, back to back.
    pub blobs: Section,
    /// Blobs in it.
    pub count: u64,
}

/// A decoded directory's entries: keys and where their blobs are, in file order, with
/// an index by key.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Entries {
    /// Keys and blobs, in file order.
    pub list: Vec<(Vec<u8>, BlobRef)>,
    /// Positions in `list`, in key order.
    by_key: Vec<u32>,
}

impl Entries {
    /// Entries from a list in file order; duplicate keys are damage.
    fn new(list: Vec<(Vec<u8>, BlobRef)>) -> Result<Entries, PackError> {
        let mut by_key: Vec<u32> = (0..list.len() as u32).collect();
        by_key.sort_unstable_by(|&a, &b| list[a as usize].0.cmp(&list[b as usize].0));
        if by_key
            .windows(2)
            .any(|w| list[w[0] as usize].0 == list[w[1] as usize].0)
        {
            return Err(damaged("a key listed twice"));
        }
        Ok(Entries { list, by_key })
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// The blob of `key`, if listed.
    pub fn find(&self, key: &[u8]) -> Option<BlobRef> {
        self.by_key
            .binary_search_by(|&i| self.list[i as usize].0.as_slice().cmp(key))
            .ok()
            .map(|i| self.list[self.by_key[i] as usize].1)
    }
}

/// The root directory.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RootDir {
    /// Blobs of the levels below the split (all of them when there are no tiles).
    pub entries: Entries,
    /// Tiles holding deeper blobs, in tile order.
    pub tiles: Vec<TileRef>,
}

/// What a directory lookup found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lookup {
    /// The blob is here.
    Blob(BlobRef),
    /// No blob: the diamond is a leaf (or outside the repository).
    Absent,
    /// The key is in this tile (index into [`RootDir::tiles`]): read its directory.
    Tile(usize),
}

impl RootDir {
    /// Parses the root section's bytes (checksum, inflation, entries and tiles that tile
    /// the blob and leaf sections exactly).
    pub fn parse(header: &Header, bytes: &[u8]) -> Result<RootDir, PackError> {
        if crc32fast::hash(bytes) != header.root_crc {
            return Err(damaged("root directory checksum mismatch"));
        }
        let raw =
            inflate(bytes, MAX_DIR_BYTES).map_err(|e| damaged(format!("root directory: {e}")))?;
        let mut r = Reader::new(&raw);
        let entries = read_entries(&mut r, header.blobs.offset, header.blobs.end())
            .map_err(|e| damaged(format!("root directory: {e}")))?;
        let mut blob_end = entries
            .list
            .last()
            .map_or(header.blobs.offset, |(_, b)| b.framed().end());
        let count = r.count(1 + 1 + 1 + 1)?;
        let mut tiles = Vec::with_capacity(count);
        let (mut dir_end, mut tile) = (header.leaves.offset, None::<u128>);
        let mut total = entries.len() as u64;
        for _ in 0..count {
            let delta = r.varint128()?;
            let id = match tile {
                None => delta,
                Some(prev) => prev
                    .checked_add(delta)
                    .filter(|_| delta > 0)
                    .ok_or_else(|| damaged("root directory: tiles out of order"))?,
            };
            let dir_len = r.varint()?;
            let blobs_len = r.varint()?;
            let n = r.varint()?;
            let t = TileRef {
                tile: id,
                dir: Section {
                    offset: dir_end,
                    len: dir_len,
                },
                blobs: Section {
                    offset: blob_end,
                    len: blobs_len,
                },
                count: n,
            };
            let fits =
                |s: Section, region: Section| s.checked_end().is_some_and(|e| e <= region.end());
            if !fits(t.dir, header.leaves)
                || !fits(t.blobs, header.blobs)
                || dir_len < CRC_BYTES
                || n == 0
                || blobs_len < n * CRC_BYTES
            {
                return Err(damaged("root directory: a tile runs past its section"));
            }
            total += n;
            dir_end = t.dir.end();
            blob_end = t.blobs.end();
            tile = Some(id);
            tiles.push(t);
        }
        if !r.done() {
            return Err(damaged("root directory: bytes after its last tile"));
        }
        if dir_end != header.leaves.end() || blob_end != header.blobs.end() {
            return Err(damaged(
                "root directory: its entries and tiles do not cover the file's blobs",
            ));
        }
        if total != header.blob_count {
            return Err(damaged(format!(
                "root directory: lists {total} blobs, the header says {}",
                header.blob_count
            )));
        }
        Ok(RootDir { entries, tiles })
    }

    /// Where `key`'s blob is, or which tile to read; `tiling` maps deep keys to tiles.
    pub fn lookup(&self, tiling: &Tiling, key: &[u8]) -> Lookup {
        // Keys without a tile (shallow ones, or all of them in an untiled file) are in
        // the root, as [`Plan::order_key`] put them.
        let tile = (!self.tiles.is_empty()).then(|| tiling.tile(key)).flatten();
        let Some(tile) = tile else {
            return find(&self.entries, key).map_or(Lookup::Absent, Lookup::Blob);
        };
        match self.tiles.binary_search_by(|t| t.tile.cmp(&tile)) {
            Ok(i) => Lookup::Tile(i),
            Err(_) => Lookup::Absent,
        }
    }

    /// Bytes in the root: number of entries and of tiles, for reports.
    pub fn sizes(&self) -> (usize, usize) {
        (self.entries.len(), self.tiles.len())
    }
}

/// The entries of a tile's leaf directory out of its section's bytes (deflated entries,
/// CRC-32), checked against the tile: count, and blobs that tile its run exactly.
pub fn parse_leaf(tile: &TileRef, bytes: &[u8]) -> Result<Entries, PackError> {
    let bad = |what: &str| damaged(what);
    if bytes.len() as u64 != tile.dir.len {
        return Err(bad("read short"));
    }
    let (body, crc) = bytes.split_at(bytes.len() - CRC_BYTES as usize);
    if crc32fast::hash(body).to_le_bytes() != crc {
        return Err(bad("checksum mismatch"));
    }
    let raw = inflate(body, MAX_DIR_BYTES).map_err(|e| bad(&e))?;
    let mut r = Reader::new(&raw);
    let entries = read_entries(&mut r, tile.blobs.offset, tile.blobs.end()).map_err(|e| {
        let PackError::Damaged(e) = e else {
            return e;
        };
        bad(&e)
    })?;
    if !r.done() {
        return Err(bad("bytes after its entries"));
    }
    let end = entries
        .list
        .last()
        .map_or(tile.blobs.offset, |(_, b)| b.framed().end());
    if entries.len() as u64 != tile.count || end != tile.blobs.end() {
        return Err(bad("its entries do not match the tile the root lists"));
    }
    Ok(entries)
}

/// The blob of `key` in `entries`.
pub fn find(entries: &Entries, key: &[u8]) -> Option<BlobRef> {
    entries.find(key)
}

fn read_entries(r: &mut Reader<'_>, start: u64, limit: u64) -> Result<Entries, PackError> {
    let count = r.count(1 + 1 + 1 + 1)?;
    let mut out: Vec<(Vec<u8>, BlobRef)> = Vec::with_capacity(count);
    let mut carried = Vec::with_capacity(count);
    let mut at = start;
    for i in 0..count {
        let shared = usize::try_from(r.varint()?).map_err(|_| damaged("key too long"))?;
        let suffix_len = usize::try_from(r.varint()?).map_err(|_| damaged("key too long"))?;
        let suffix = r.take(suffix_len)?;
        let prev: &[u8] = out.last().map_or(&[], |(k, _)| k);
        if shared > prev.len() || shared + suffix_len > 64 {
            return Err(damaged(
                "a key shares more bytes than the one before it has",
            ));
        }
        let key = [&prev[..shared], suffix].concat();
        let len = r.varint()?;
        let n = r.varint()?;
        if n >= (count - i) as u64 {
            return Err(damaged("a package runs past its directory"));
        }
        carried.push(n as usize);
        let end = len
            .checked_add(CRC_BYTES)
            .and_then(|l| at.checked_add(l))
            .filter(|&e| e <= limit)
            .ok_or_else(|| damaged("a blob runs past its section"))?;
        out.push((
            key,
            BlobRef {
                offset: at,
                len,
                package_end: end,
            },
        ));
        at = end;
    }
    for (i, n) in carried.into_iter().enumerate() {
        out[i].1.package_end = out[i + n].1.framed().end();
    }
    Entries::new(out)
}

/// Encodes directory entries: keys, their blobs' lengths and the entries each package
/// carries, in file order.
fn write_entries(out: &mut Vec<u8>, entries: &[Placed]) {
    put_varint(out, entries.len() as u128);
    let mut prev: &[u8] = &[];
    for p in entries {
        let key = p.key.as_slice();
        let shared = prev.iter().zip(key).take_while(|(a, b)| a == b).count();
        put_varint(out, shared as u128);
        put_varint(out, (key.len() - shared) as u128);
        out.extend_from_slice(&key[shared..]);
        put_varint(out, u128::from(p.len));
        put_varint(out, u128::from(p.carried));
        prev = key;
    }
}

fn put_varint(out: &mut Vec<u8>, mut v: u128) {
    loop {
        let b = (v & 0x7F) as u8;
        v >>= 7;
        if v == 0 {
            out.push(b);
            return;
        }
        out.push(b | 0x80);
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Reader { bytes, at: 0 }
    }

    fn done(&self) -> bool {
        self.at == self.bytes.len()
    }

    fn varint128(&mut self) -> Result<u128, PackError> {
        let mut v: u128 = 0;
        for shift in (0..128).step_by(7) {
            let b = *self
                .bytes
                .get(self.at)
                .ok_or_else(|| damaged("directory ends inside a number"))?;
            self.at += 1;
            v |= u128::from(b & 0x7F)
                .checked_shl(shift)
                .filter(|_| shift < 126 || b & 0x7F < 4)
                .ok_or_else(|| damaged("number too large"))?;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(damaged("number too large"))
    }

    fn varint(&mut self) -> Result<u64, PackError> {
        u64::try_from(self.varint128()?).map_err(|_| damaged("number too large"))
    }

    /// A count of items of at least `min_bytes` each, bounded by what is left.
    fn count(&mut self, min_bytes: usize) -> Result<usize, PackError> {
        let n = self.varint()?;
        usize::try_from(n)
            .ok()
            .filter(|&n| n.saturating_mul(min_bytes) <= self.bytes.len() - self.at)
            .ok_or_else(|| damaged(format!("a count of {n} items does not fit its directory")))
    }

    fn take(&mut self, len: usize) -> Result<&'a [u8], PackError> {
        let end = self
            .at
            .checked_add(len)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| damaged("directory ends inside a key"))?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }
}

/// How deep keys map to tiles: a key's level, face (planets) and Morton code at its
/// level's step give its centre; the tile is that centre's square of side
/// `2^tile_shift`, as a Morton code (the face in the top bits).
#[derive(Debug, Clone)]
pub struct Tiling {
    /// Levels below it are in the root.
    pub split_level: u32,
    /// Tile side exponent.
    pub tile_shift: u32,
    sphere: bool,
    /// The coordinate step exponent of each level.
    exponents: Vec<u32>,
}

impl Tiling {
    /// The tiling of a repository's id space.
    pub fn new(space: &IdSpace, split_level: u32, tile_shift: u32) -> Tiling {
        let (sphere, exponents) = match space {
            IdSpace::Planar(d) => (
                false,
                (0..=d.max_level()).map(|l| d.level_exponent(l)).collect(),
            ),
            IdSpace::Sphere(d) => (
                true,
                (0..=d.max_level()).map(|l| d.level_exponent(l)).collect(),
            ),
        };
        Tiling {
            split_level,
            tile_shift,
            sphere,
            exponents,
        }
    }

    /// The tile of a key at or below the split level; `None` for shallower keys and
    /// malformed ones (which no directory lists).
    pub fn tile(&self, key: &[u8]) -> Option<u128> {
        let (&level, rest) = key.split_first()?;
        if u32::from(level) < self.split_level {
            return None;
        }
        let t = *self.exponents.get(usize::from(level))?;
        let (face, code) = if self.sphere {
            let (&face, code) = rest.split_first()?;
            (u128::from(face), code)
        } else {
            (0, rest)
        };
        if code.len() > 13 {
            return None;
        }
        let code = code.iter().fold(0u128, |v, &b| (v << 8) | u128::from(b));
        // The centre's Morton code at full resolution, then its tile's.
        let full = code.checked_shl(2 * t)?;
        let cell = full.checked_shr(2 * self.tile_shift).unwrap_or(0);
        Some((face << 120) | cell)
    }
}

/// How a build lays out its blobs: the split level and tile size chosen for its keys.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The tiling (split level and tile size).
    pub tiling: Tiling,
    /// Whether deep levels go to tiles (`false`: every blob is in the root).
    pub tiled: bool,
    /// The id space (`None`: no packages are laid out).
    pub space: Option<IdSpace>,
}

/// A blob's place in a file: its key, length, and how many entries after it its package
/// holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Placed {
    /// Storage key.
    pub key: Vec<u8>,
    /// Blob length (without its CRC).
    pub len: u64,
    /// Entries after it in its package.
    pub carried: u64,
}

/// The thresholds a [`Plan`] follows ([`Limits::default`]: [`ROOT_ALL_MAX`],
/// [`ROOT_SPLIT_MAX`], [`LEAF_MAX`]); tests use small ones to exercise tiles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Up to this many blobs, every entry is in the root.
    pub root_all_max: usize,
    /// The root keeps at most this many blobs of the levels above the split.
    pub root_split_max: usize,
    /// A tile holds at most this many blobs.
    pub leaf_max: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            root_all_max: ROOT_ALL_MAX,
            root_split_max: ROOT_SPLIT_MAX,
            leaf_max: LEAF_MAX,
        }
    }
}

impl Plan {
    /// Chooses the layout for `keys` (every stored key, any order) of a repository with
    /// id space `space`: everything in the root up to `limits.root_all_max` blobs;
    /// otherwise the root keeps the deepest split whose shallower levels hold at most
    /// `limits.root_split_max` blobs (level 0 always), and tiles are the largest squares
    /// that hold at most `limits.leaf_max` blobs each.
    pub fn choose<'a>(
        space: &IdSpace,
        keys: impl Iterator<Item = &'a [u8]> + Clone,
        limits: Limits,
    ) -> Plan {
        let total = keys.clone().count();
        let max_level = match space {
            IdSpace::Planar(d) => d.max_level(),
            IdSpace::Sphere(d) => d.max_level(),
        };
        if total <= limits.root_all_max {
            return Plan {
                tiling: Tiling::new(space, max_level + 1, 0),
                tiled: false,
                space: Some(*space),
            };
        }
        let last = max_level as usize + 1;
        let mut per_level = vec![0usize; last + 1];
        for k in keys.clone() {
            if let Some(&l) = k.first() {
                per_level[usize::from(l).min(last)] += 1;
            }
        }
        let mut split = 1;
        let mut above = per_level[0];
        while (split as usize) < last && above + per_level[split as usize] <= limits.root_split_max
        {
            above += per_level[split as usize];
            split += 1;
        }
        // The largest tiles under the cap: the biggest tile's count only falls as tiles
        // shrink, so search the shift.
        let top = space_bits(space);
        let biggest = |shift: u32| {
            let tiling = Tiling::new(space, split, shift);
            let mut counts: HashMap<u128, usize> = HashMap::new();
            for k in keys.clone() {
                if let Some(t) = tiling.tile(k) {
                    *counts.entry(t).or_default() += 1;
                }
            }
            counts.into_values().max().unwrap_or(0)
        };
        let (mut lo, mut hi) = (0, top);
        if biggest(hi) <= limits.leaf_max {
            lo = hi;
        }
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            if biggest(mid) <= limits.leaf_max {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        Plan {
            tiling: Tiling::new(space, split, lo),
            tiled: true,
            space: Some(*space),
        }
    }

    /// The section of a key, as it orders in the file: `(0, 0)` for the root, then
    /// `(tile, 1)` by tile.
    pub fn order_key(&self, key: &[u8]) -> (u128, u8) {
        match self.tiled.then(|| self.tiling.tile(key)).flatten() {
            None => (0, 0),
            Some(t) => (t, 1),
        }
    }

    /// The file's order of `blobs` (keys and lengths, any order, each key once): the
    /// root's, then each tile's; within one, packages (see the module docs) for a
    /// repository whose answers carry children up to `inline_max_bytes` each, in key
    /// order of the diamonds nobody carries. Without a limit, or an id space, key order.
    /// A key that is no diamond of the id space is an error.
    pub fn arrange(
        &self,
        mut blobs: Vec<(Vec<u8>, u64)>,
        inline_max_bytes: Option<u32>,
    ) -> Result<Vec<Placed>, String> {
        blobs.sort_unstable();
        blobs.sort_by_cached_key(|(k, _)| self.order_key(k));
        let mut out = Vec::with_capacity(blobs.len());
        let mut start = 0;
        while start < blobs.len() {
            let section = self.order_key(&blobs[start].0);
            let end = start + blobs[start..].partition_point(|(k, _)| self.order_key(k) == section);
            let part = &blobs[start..end];
            match (self.space.as_ref(), inline_max_bytes) {
                (Some(space), Some(limit)) => arrange_packages(space, part, limit, &mut out)?,
                _ => out.extend(part.iter().map(|(key, len)| Placed {
                    key: key.clone(),
                    len: *len,
                    carried: 0,
                })),
            }
            start = end;
        }
        Ok(out)
    }
}

/// Lays out one directory's blobs (`part`, in key order) as packages: a diamond's package
/// is its blob, then the packages of its owned children in `part` whose package (framed
/// as a server answers it) is at most `limit` bytes, in child order.
fn arrange_packages(
    space: &IdSpace,
    part: &[(Vec<u8>, u64)],
    limit: u32,
    out: &mut Vec<Placed>,
) -> Result<(), String> {
    use crate::answer::varint_len;
    let index: HashMap<&[u8], usize> = part
        .iter()
        .enumerate()
        .map(|(i, (k, _))| (k.as_slice(), i))
        .collect();
    // Each blob's owned children that are in this directory, in child order.
    let mut kids: Vec<Vec<usize>> = Vec::with_capacity(part.len());
    for (key, _) in part {
        let centre = space.centre(key)?;
        let mut mine = Vec::new();
        for c in space.owned_children(centre)? {
            let (k, _) = space.key_level(c)?;
            if let Some(&j) = index.get(k.as_slice()) {
                mine.push(j);
            }
        }
        kids.push(mine);
    }
    // Package sizes, deepest first (key order is level-major; children are one level
    // deeper than their owner).
    let mut size = vec![0usize; part.len()];
    let mut carried = vec![false; part.len()];
    for i in (0..part.len()).rev() {
        let len = usize::try_from(part[i].1).map_err(|_| "blob too large")?;
        let mut s = 1 + varint_len(len) + len;
        for &j in &kids[i] {
            if size[j] <= limit as usize {
                s += varint_len(size[j]) + size[j];
                carried[j] = true;
            }
        }
        size[i] = s;
    }
    fn emit(
        i: usize,
        part: &[(Vec<u8>, u64)],
        kids: &[Vec<usize>],
        carried: &[bool],
        out: &mut Vec<Placed>,
    ) {
        let at = out.len();
        out.push(Placed {
            key: part[i].0.clone(),
            len: part[i].1,
            carried: 0,
        });
        for &j in &kids[i] {
            if carried[j] {
                emit(j, part, kids, carried, out);
            }
        }
        out[at].carried = (out.len() - at - 1) as u64;
    }
    for i in 0..part.len() {
        if !carried[i] {
            emit(i, part, &kids, &carried, out);
        }
    }
    Ok(())
}

/// Bits of the widest full-resolution coordinate: one tile covers a domain (or a face).
fn space_bits(space: &IdSpace) -> u32 {
    match space {
        IdSpace::Planar(d) => d.m() + 1,
        IdSpace::Sphere(d) => d.m() + 2,
    }
}

/// Writes directories for blobs given in file order ([`Plan::arrange`]): collects the
/// root's entries and each tile's, then gives the root's and the leaves' bytes.
#[derive(Debug)]
pub struct DirWriter {
    plan: Plan,
    root: Vec<Placed>,
    tiles: Vec<(u128, Vec<Placed>)>,
}

/// The directories of a file, ready to write.
#[derive(Debug, Clone)]
pub struct Dirs {
    /// The root section (deflated).
    pub root: Vec<u8>,
    /// The leaf directories' section (each deflated, then its CRC-32).
    pub leaves: Vec<u8>,
    /// Bytes of all blobs with their CRCs.
    pub blobs_len: u64,
    /// Blobs listed.
    pub blob_count: u64,
}

impl DirWriter {
    /// An empty writer for `plan`.
    pub fn new(plan: Plan) -> DirWriter {
        DirWriter {
            plan,
            root: Vec::new(),
            tiles: Vec::new(),
        }
    }

    /// Adds the next blob, in file order (a section out of that order, or a package
    /// running past its section, is a caller's bug, reported as an error).
    pub fn push(&mut self, placed: Placed) -> Result<(), String> {
        let (tile, tiled) = self.plan.order_key(&placed.key);
        let list = if tiled == 0 {
            if !self.tiles.is_empty() {
                return Err("a root key after the tiles".into());
            }
            &mut self.root
        } else {
            match self.tiles.last_mut() {
                Some((t, list)) if *t == tile => list,
                Some((t, _)) if *t > tile => return Err("tiles out of order".into()),
                _ => {
                    if let Some((_, list)) = self.tiles.last() {
                        open_package(list)?;
                    } else {
                        open_package(&self.root)?;
                    }
                    self.tiles.push((tile, Vec::new()));
                    &mut self.tiles.last_mut().ok_or("no tile")?.1
                }
            }
        };
        list.push(placed);
        Ok(())
    }

    /// The sections.
    pub fn finish(self) -> Result<Dirs, String> {
        open_package(self.tiles.last().map_or(&self.root, |(_, l)| l))?;
        let framed = |list: &[Placed]| -> u64 { list.iter().map(|p| p.len + CRC_BYTES).sum() };
        let mut raw = Vec::new();
        write_entries(&mut raw, &self.root);
        let mut leaves = Vec::new();
        let mut table = Vec::new();
        put_varint(&mut table, self.tiles.len() as u128);
        let mut blobs_len = framed(&self.root);
        let mut blob_count = self.root.len() as u64;
        let mut prev = None;
        for (tile, list) in &self.tiles {
            let mut entries = Vec::new();
            write_entries(&mut entries, list);
            let body = deflate(&entries);
            let start = leaves.len();
            leaves.extend_from_slice(&body);
            leaves.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
            put_varint(&mut table, prev.map_or(*tile, |p| tile - p));
            put_varint(&mut table, (leaves.len() - start) as u128);
            put_varint(&mut table, u128::from(framed(list)));
            put_varint(&mut table, list.len() as u128);
            blobs_len += framed(list);
            blob_count += list.len() as u64;
            prev = Some(*tile);
        }
        raw.extend_from_slice(&table);
        Ok(Dirs {
            root: deflate(&raw),
            leaves,
            blobs_len,
            blob_count,
        })
    }
}

/// An error if a package of `list` (one directory's entries) runs past its end.
fn open_package(list: &[Placed]) -> Result<(), String> {
    match list
        .iter()
        .enumerate()
        .any(|(i, p)| i as u64 + p.carried >= list.len() as u64)
    {
        true => Err("a package runs past its directory".into()),
        false => Ok(()),
    }
}

impl Header {
    /// The header of a file of these directories, deflated metadata of `metadata_len`
    /// bytes (CRC `metadata_crc`) and the blobs the directories list, laid out in order.
    pub fn for_sections(
        dirs: &Dirs,
        tiling: &Tiling,
        metadata_len: u64,
        metadata_crc: u32,
    ) -> Header {
        let root = Section {
            offset: HEADER_BYTES,
            len: dirs.root.len() as u64,
        };
        let metadata = Section {
            offset: root.end(),
            len: metadata_len,
        };
        let leaves = Section {
            offset: metadata.end(),
            len: dirs.leaves.len() as u64,
        };
        let blobs = Section {
            offset: leaves.end(),
            len: dirs.blobs_len,
        };
        Header {
            version: LAYOUT_VERSION,
            file_len: blobs.end(),
            root,
            metadata,
            leaves,
            blobs,
            root_crc: crc32fast::hash(&dirs.root),
            metadata_crc,
            split_level: tiling.split_level,
            tile_shift: tiling.tile_shift,
            blob_count: dirs.blob_count,
        }
    }
}

/// The bytes of a whole file laid out by `plan` ([`Plan::arrange`], packages as
/// `inline_max_bytes` says): `pairs` (any order, each key once) and the metadata record
/// `json` (written as given, unchecked). For tools and tests that craft files; builds
/// write through the store, which streams its blobs.
pub fn encode(
    plan: Plan,
    json: &[u8],
    pairs: &[(Vec<u8>, Vec<u8>)],
    inline_max_bytes: Option<u32>,
) -> Result<Vec<u8>, String> {
    let tiling = plan.tiling.clone();
    let blobs: HashMap<&[u8], &[u8]> = pairs
        .iter()
        .map(|(k, v)| (k.as_slice(), v.as_slice()))
        .collect();
    let order = plan.arrange(
        pairs
            .iter()
            .map(|(k, v)| (k.clone(), v.len() as u64))
            .collect(),
        inline_max_bytes,
    )?;
    let mut dirs = DirWriter::new(plan);
    for p in &order {
        dirs.push(p.clone())?;
    }
    let dirs = dirs.finish()?;
    let metadata = deflate(json);
    let header = Header::for_sections(
        &dirs,
        &tiling,
        metadata.len() as u64,
        crc32fast::hash(&metadata),
    );
    let mut out = header.to_bytes().to_vec();
    out.extend_from_slice(&dirs.root);
    out.extend_from_slice(&metadata);
    out.extend_from_slice(&dirs.leaves);
    for p in &order {
        let v = blobs.get(p.key.as_slice()).copied().unwrap_or_default();
        out.extend_from_slice(v);
        out.extend_from_slice(&crc32fast::hash(v).to_le_bytes());
    }
    Ok(out)
}

/// [`encode`] with every blob in the root directory, in key order, no packages.
pub fn encode_untiled(json: &[u8], pairs: &[(Vec<u8>, Vec<u8>)]) -> Result<Vec<u8>, String> {
    let plan = Plan {
        tiling: Tiling {
            split_level: 255,
            tile_shift: 0,
            sphere: false,
            exponents: Vec::new(),
        },
        tiled: false,
        space: None,
    };
    encode(plan, json, pairs, None)
}

/// The package of blob `b` (key `key`, in a directory that `find` searches) out of
/// `bytes`, the file's bytes of [`BlobRef::package`]: its blob and each carried child's
/// package, every blob checked against its CRC, framed as a server answers it
/// ([`crate::answer::write`]). Bytes that do not hold the package the directory
/// describes are an error.
pub fn package_from(
    space: &IdSpace,
    key: &[u8],
    b: BlobRef,
    bytes: &[u8],
    find: &dyn Fn(&[u8]) -> Option<BlobRef>,
) -> Result<Vec<u8>, PackError> {
    if bytes.len() as u64 != b.package_end.saturating_sub(b.offset) {
        return Err(damaged(format!(
            "read as {} bytes, its package is {}",
            bytes.len(),
            b.package_end.saturating_sub(b.offset)
        )));
    }
    package_within(space, key, b, b.offset, bytes, find, 0)
}

fn package_within(
    space: &IdSpace,
    key: &[u8],
    b: BlobRef,
    base: u64,
    bytes: &[u8],
    find: &dyn Fn(&[u8]) -> Option<BlobRef>,
    depth: u32,
) -> Result<Vec<u8>, PackError> {
    let slice = |s: Section| {
        s.offset
            .checked_sub(base)
            .and_then(|at| bytes.get(at as usize..(at + s.len) as usize))
            .ok_or_else(|| damaged("a carried blob lies outside its package"))
    };
    let blob = b.check(slice(b.framed())?)?;
    let mut children = Vec::new();
    let mut pos = b.framed().end();
    if pos < b.package_end {
        if depth > 64 {
            return Err(damaged("packages nest too deep"));
        }
        let centre = space.centre(key).map_err(damaged)?;
        let owned = space.owned_children(centre).map_err(damaged)?;
        for (i, c) in owned.into_iter().enumerate() {
            if pos == b.package_end {
                break;
            }
            let (k, _) = space.key_level(c).map_err(damaged)?;
            let Some(cb) = find(&k).filter(|cb| cb.offset == pos) else {
                continue;
            };
            if cb.package_end > b.package_end {
                return Err(damaged("a carried package runs past its owner's"));
            }
            children.push((
                i,
                package_within(space, &k, cb, base, bytes, find, depth + 1)?,
            ));
            pos = cb.package_end;
        }
        if pos != b.package_end {
            return Err(damaged(
                "a package holds blobs that are not its owned children's",
            ));
        }
    }
    Ok(crate::answer::write(blob, &children, true))
}

/// `file` with its metadata record replaced by `json` (written as given, unchecked): the
/// directories and blobs are kept, the sections after the metadata move. For tools and
/// tests that craft files.
pub fn replace_metadata(file: &[u8], json: &[u8]) -> Result<Vec<u8>, PackError> {
    let header = Header::parse(file)?;
    header.check_len(file.len() as u64)?;
    let metadata = deflate(json);
    let shift = metadata.len() as i128 - header.metadata.len as i128;
    let moved = |s: Section| Section {
        offset: (i128::from(s.offset) + shift) as u64,
        len: s.len,
    };
    let new = Header {
        metadata: Section {
            offset: header.metadata.offset,
            len: metadata.len() as u64,
        },
        leaves: moved(header.leaves),
        blobs: moved(header.blobs),
        file_len: (i128::from(header.file_len) + shift) as u64,
        metadata_crc: crc32fast::hash(&metadata),
        ..header
    };
    let mut out = new.to_bytes().to_vec();
    out.extend_from_slice(&file[header.root.offset as usize..header.root.end() as usize]);
    out.extend_from_slice(&metadata);
    out.extend_from_slice(&file[header.leaves.offset as usize..]);
    Ok(out)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use quincunx_diamond::{PlanarDomain, PlanarId};

    /// Every centre of the first `levels` levels of a planar domain.
    fn keys(d: &PlanarDomain, levels: u32) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        let side = 1i64 << d.m();
        for x in 0..=side {
            for y in 0..=side {
                let id = PlanarId::new(x, y);
                if d.level(id).is_ok_and(|l| l < levels) {
                    out.push(d.key(id).unwrap());
                }
            }
        }
        out.sort();
        out
    }

    fn file(space: &IdSpace, keys: &[Vec<u8>]) -> (Header, RootDir, Vec<u8>, Plan) {
        let plan = Plan::choose(space, keys.iter().map(Vec::as_slice), Limits::default());
        let pairs: Vec<(Vec<u8>, Vec<u8>)> = keys
            .iter()
            .map(|k| {
                (
                    k.clone(),
                    vec![k[k.len() - 1]; k.len() + (k[0] as usize % 5)],
                )
            })
            .collect();
        let out = encode(plan.clone(), b"{}", &pairs, Some(40)).unwrap();
        let header = Header::parse(&out).unwrap();
        header.check_len(out.len() as u64).unwrap();
        let root = RootDir::parse(
            &header,
            &out[header.root.offset as usize..header.root.end() as usize],
        )
        .unwrap();
        (header, root, out, plan)
    }

    /// The blob of `key` in `file`, whose leaf directories are `leaves`.
    fn read<'a>(
        root: &RootDir,
        leaves: &[Entries],
        plan: &Plan,
        file: &'a [u8],
        key: &[u8],
    ) -> Result<Option<&'a [u8]>, PackError> {
        let at = |s: Section| &file[s.offset as usize..s.end() as usize];
        let b = match root.lookup(&plan.tiling, key) {
            Lookup::Blob(b) => b,
            Lookup::Absent => return Ok(None),
            Lookup::Tile(i) => match find(&leaves[i], key) {
                Some(b) => b,
                None => return Ok(None),
            },
        };
        b.check(at(b.framed())).map(Some)
    }

    fn leaves(root: &RootDir, file: &[u8]) -> Vec<Entries> {
        root.tiles
            .iter()
            .map(|t| parse_leaf(t, &file[t.dir.offset as usize..t.dir.end() as usize]).unwrap())
            .collect()
    }

    #[test]
    fn small_and_tiled_files_give_every_blob_back() {
        for (m, levels) in [(4, 6), (8, 15)] {
            let d = PlanarDomain::new(m).unwrap();
            let all = keys(&d, levels);
            let space = IdSpace::Planar(d);
            let (_, root, out, plan) = file(&space, &all);
            let leaves = leaves(&root, &out);
            assert_eq!(plan.tiled, all.len() > ROOT_ALL_MAX, "{m}");
            if plan.tiled {
                assert!(root.entries.len() <= ROOT_SPLIT_MAX && !root.tiles.is_empty());
                assert!(root.tiles.iter().all(|t| t.count as usize <= LEAF_MAX));
            }
            for k in &all {
                let blob = read(&root, &leaves, &plan, &out, k).unwrap().unwrap();
                assert_eq!(blob.len(), k.len() + (k[0] as usize % 5));
            }
            // Keys without blobs: a deeper level, and a missing one.
            let deeper = keys(&d, levels + 1)
                .into_iter()
                .find(|k| u32::from(k[0]) == levels)
                .unwrap();
            assert_eq!(read(&root, &leaves, &plan, &out, &deeper), Ok(None));
            // Damage in a blob is found by its CRC.
            let k = &all[all.len() / 2];
            let b = match root.lookup(&plan.tiling, k) {
                Lookup::Blob(b) => b,
                Lookup::Tile(i) => find(&leaves[i], k).unwrap(),
                Lookup::Absent => unreachable!(),
            };
            let mut bad = out.clone();
            bad[b.offset as usize] ^= 1;
            let err = read(&root, &leaves, &plan, &bad, k).unwrap_err();
            assert!(err.to_string().contains("checksum mismatch"), "{err}");
        }
    }

    /// A served package by the server's rule (`quincunx_store::Repository::package`),
    /// children limited to those `same` accepts.
    fn served(
        space: &IdSpace,
        blobs: &HashMap<Vec<u8>, Vec<u8>>,
        key: &[u8],
        limit: usize,
        same: &dyn Fn(&[u8]) -> bool,
    ) -> Vec<u8> {
        let owned = space.owned_children(space.centre(key).unwrap()).unwrap();
        let mut children = Vec::new();
        for (i, c) in owned.into_iter().enumerate() {
            let (k, _) = space.key_level(c).unwrap();
            if blobs.contains_key(&k) && same(&k) {
                let p = served(space, blobs, &k, limit, same);
                if p.len() <= limit {
                    children.push((i, p));
                }
            }
        }
        crate::answer::write(&blobs[key], &children, true)
    }

    #[test]
    fn every_package_is_one_range_holding_what_a_server_answers() {
        for (m, levels) in [(4, 8), (8, 15)] {
            let d = PlanarDomain::new(m).unwrap();
            let all = keys(&d, levels);
            let space = IdSpace::Planar(d);
            let (_, root, out, plan) = file(&space, &all);
            let blobs: HashMap<Vec<u8>, Vec<u8>> = all
                .iter()
                .map(|k| {
                    (
                        k.clone(),
                        vec![k[k.len() - 1]; k.len() + (k[0] as usize % 5)],
                    )
                })
                .collect();
            let at = |s: Section| &out[s.offset as usize..s.end() as usize];
            let leaves = leaves(&root, &out);
            let (mut carrying, mut carried) = (0, 0);
            for k in &all {
                let (b, dir) = match root.lookup(&plan.tiling, k) {
                    Lookup::Blob(b) => (b, &root.entries),
                    Lookup::Tile(i) => (find(&leaves[i], k).unwrap(), &leaves[i]),
                    Lookup::Absent => unreachable!(),
                };
                let tile = plan.order_key(k);
                let same = |c: &[u8]| plan.order_key(c) == tile;
                let want = served(&space, &blobs, k, 40, &same);
                let got = package_from(&space, k, b, at(b.package()), &|c| dir.find(c)).unwrap();
                assert_eq!(got, want, "{k:?}");
                if b.package_end > b.framed().end() {
                    carrying += 1;
                    carried += crate::answer::parse(&got, true).unwrap().children.len();
                }
                // A byte changed anywhere in the package is an error.
                let mut bad = at(b.package()).to_vec();
                let i = bad.len() / 2;
                bad[i] ^= 4;
                assert!(package_from(&space, k, b, &bad, &|c| dir.find(c)).is_err());
            }
            assert!(
                carrying > all.len() / 8 && carried > carrying,
                "{carrying} {carried}"
            );
        }
    }

    #[test]
    fn headers_refuse_damage_truncation_and_other_files() {
        let d = PlanarDomain::new(4).unwrap();
        let all = keys(&d, 6);
        let (header, _, out, _) = file(&IdSpace::Planar(d), &all);
        assert_eq!(Header::parse(b"GIF89a"), Err(PackError::NotAPack));
        assert!(matches!(
            Header::parse(&out[..40]),
            Err(PackError::Incomplete(_))
        ));
        assert!(matches!(
            Header::parse(&out[..5]),
            Err(PackError::Incomplete(_))
        ));
        for i in 12..HEADER_BYTES as usize {
            let mut bad = out.clone();
            bad[i] ^= 0x10;
            assert!(Header::parse(&bad).is_err(), "byte {i}");
        }
        let mut v7 = out.clone();
        v7[8] = 7;
        assert_eq!(Header::parse(&v7), Err(PackError::Version(7)));
        assert!(matches!(
            header.check_len(out.len() as u64 - 1),
            Err(PackError::Incomplete(_))
        ));
        assert!(matches!(
            header.check_len(out.len() as u64 + 3),
            Err(PackError::Damaged(_))
        ));
        // A damaged root directory.
        let mut bad = out.clone();
        bad[HEADER_BYTES as usize + 2] ^= 1;
        let root = &bad[header.root.offset as usize..header.root.end() as usize];
        assert!(RootDir::parse(&header, root).is_err());
    }

    #[test]
    fn hostile_directories_are_errors() {
        // Counts larger than the bytes, keys sharing too much, lengths past the end.
        for raw in [
            vec![0xFF, 0xFF, 0xFF, 0x0F],
            vec![1, 5, 0, 3],
            vec![1, 0, 1, 7, 0xFF, 0xFF, 0x03],
            vec![0x80; 30],
        ] {
            let comp = deflate(&raw);
            let header = Header {
                version: LAYOUT_VERSION,
                file_len: 0,
                root: Section::default(),
                metadata: Section::default(),
                leaves: Section::default(),
                blobs: Section {
                    offset: 200,
                    len: 10,
                },
                root_crc: crc32fast::hash(&comp),
                metadata_crc: 0,
                split_level: 0,
                tile_shift: 0,
                blob_count: 0,
            };
            assert!(RootDir::parse(&header, &comp).is_err(), "{raw:?}");
        }
        // A deflate bomb.
        let bomb = deflate(&vec![0u8; MAX_DIR_BYTES + 10]);
        assert!(
            inflate(&bomb, MAX_DIR_BYTES)
                .unwrap_err()
                .contains("more than")
        );
    }

    #[test]
    fn tiles_group_centres_by_square_across_levels() {
        let d = PlanarDomain::new(6).unwrap();
        let space = IdSpace::Planar(d);
        let (split, shift) = (4, 3);
        let tiling = Tiling::new(&space, split, shift);
        let deep: Vec<(Vec<u8>, (i64, i64))> = keys(&d, 12)
            .into_iter()
            .filter(|k| u32::from(k[0]) >= split)
            .map(|k| {
                let id = d.id_from_key(&k).unwrap();
                (k, (id.x >> shift, id.y >> shift))
            })
            .collect();
        assert!(deep.len() > 1000);
        for (ka, sa) in deep.iter().step_by(7) {
            for (kb, sb) in deep.iter().step_by(13) {
                assert_eq!(
                    tiling.tile(ka) == tiling.tile(kb),
                    sa == sb,
                    "{sa:?} {sb:?}"
                );
            }
        }
        let shallow = keys(&d, split).pop().unwrap();
        assert_eq!(tiling.tile(&shallow), None);
    }
}
