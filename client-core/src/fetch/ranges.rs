//! Reading a repository file (`repository.pack`, format 8) with HTTP range requests,
//! without I/O: what to request for a set of wanted keys, and what an answer means.
//!
//! The caller (the native network thread, or the browser) opens the file with
//! [`open_len`] and [`PackIndex::open`], then for each batch of keys the planner releases
//! calls [`RangeReader::plan`], sends the [`RangeRequest`]s it gives (one `Range` each),
//! and hands every answer to [`RangeReader::answered`].
//!
//! - Keys the directories do not list are leaves at once: no request.
//! - Keys of a tile whose leaf directory is not loaded wait for it; the directory is
//!   requested once, however many keys wait.
//! - **Packages are one range.** A key asked for as a package is read from its blob to
//!   the end of its package (the file lays a package out contiguously, see
//!   [`quincunx_meta::pack`]), and answered with the package a server would send: the
//!   same round trip brings the small owned children.
//! - Ranges are **coalesced**: sorted by offset, two neighbours go in one request when
//!   the gap between them is at most [`RangeConfig::max_gap`] bytes (an answer head
//!   costs more than that) and the request stays within [`RangeConfig::max_run`] bytes.
//! - Every blob is checked against its CRC-32 before it is handed on, so a wrong answer
//!   (a server that ignores the range, a changed file, a bad cache) is an error, never a
//!   wrong blob.

use std::collections::HashMap;
use std::sync::Arc;

use bytes::Bytes;
use quincunx_meta::Metadata;
use quincunx_meta::answer::IdSpace;
use quincunx_meta::pack::{
    self, BlobRef, Entries, Header, Lookup, OPEN_BYTES, PackError, RootDir, Section, Tiling,
};

use super::{FetchError, Key};

/// What a reader fetches first: [`OPEN_BYTES`] (or the whole file, if shorter).
pub const FIRST_READ: u64 = OPEN_BYTES;

/// How many bytes from the start of the file opening needs, from the first bytes read
/// (at least the header's 128). More than were read: fetch the rest, then
/// [`PackIndex::open`].
pub fn open_len(first: &[u8]) -> Result<u64, PackError> {
    Ok(Header::parse(first)?.open_len())
}

/// An opened repository file: its header, root directory and tiling.
#[derive(Debug)]
pub struct PackIndex {
    /// The header.
    pub header: Header,
    /// The root directory.
    pub root: RootDir,
    /// How deep keys map to tiles.
    pub tiling: Tiling,
    /// The repository's id space (centres to keys).
    pub space: IdSpace,
}

impl PackIndex {
    /// Opens a file of `file_len` bytes (the `Content-Range` total) from its first bytes
    /// (at least [`open_len`] of them): checks header, root directory and metadata, and
    /// gives the index and the metadata record.
    pub fn open(front: &[u8], file_len: u64) -> Result<(PackIndex, Metadata), PackError> {
        let header = Header::parse(front)?;
        header.check_len(file_len)?;
        let at = |s: Section| -> Result<&[u8], PackError> {
            front
                .get(s.offset as usize..s.end() as usize)
                .ok_or_else(|| PackError::Incomplete("read short of its metadata".into()))
        };
        let root = RootDir::parse(&header, at(header.root)?)?;
        let json = header.metadata_json(at(header.metadata)?)?;
        let meta: Metadata = serde_json::from_slice(&json)
            .map_err(|e| PackError::Damaged(format!("metadata: {e}")))?;
        if meta.format_version != pack::LAYOUT_VERSION || !meta.complete {
            return Err(PackError::Version(meta.format_version));
        }
        meta.check_limits()
            .map_err(|e| PackError::Damaged(format!("metadata: {e}")))?;
        let space = IdSpace::of(&meta).map_err(PackError::Damaged)?;
        let tiling = Tiling::new(&space, header.split_level, header.tile_shift);
        Ok((
            PackIndex {
                header,
                root,
                tiling,
                space,
            },
            meta,
        ))
    }
}

/// How blob ranges are merged into requests.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RangeConfig {
    /// Largest gap (bytes nobody asked for) read to join two ranges into one request.
    pub max_gap: u64,
    /// Largest request, in bytes (a single larger blob still gets its own).
    pub max_run: u64,
}

impl Default for RangeConfig {
    /// Gaps up to 128 bytes (a range answer's head is 250-500 bytes), requests up to
    /// 64 KiB (one request does not hold up the ones behind it for long).
    fn default() -> Self {
        RangeConfig {
            max_gap: 128,
            max_run: 64 << 10,
        }
    }
}

/// One range to request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RangeRequest {
    /// Names the request in [`RangeReader::answered`].
    pub tag: u64,
    /// The bytes to request.
    pub range: Section,
}

impl RangeRequest {
    /// The `Range` header's value.
    pub fn header_value(&self) -> String {
        format!(
            "bytes={}-{}",
            self.range.offset,
            self.range.end().saturating_sub(1)
        )
    }
}

/// A key to read: where its blob is, and whether it is read as a package.
#[derive(Clone, Copy, Debug)]
struct Wanted {
    key: Key,
    blob: BlobRef,
    packaged: bool,
    /// The directory listing it: the root (`None`) or a tile's.
    dir: Option<usize>,
}

impl Wanted {
    /// The bytes it needs.
    fn span(&self) -> Section {
        if self.packaged {
            self.blob.package()
        } else {
            self.blob.framed()
        }
    }
}

/// What a request is for.
#[derive(Debug)]
enum Pending {
    /// These keys, inside the request's range.
    Blobs(Section, Vec<Wanted>),
    /// The leaf directory of tile `i`.
    Dir(usize),
}

/// What to do after [`RangeReader::plan`] or [`RangeReader::answered`].
#[derive(Debug, Default)]
pub struct Step {
    /// Keys that have no blob: leaves.
    pub leaves: Vec<Key>,
    /// Keys' answers, checked, or why a key failed: the bare blob, or for a key asked
    /// for as a package, the package ([`quincunx_meta::answer`] framing).
    pub blobs: Vec<(Key, Result<Bytes, FetchError>)>,
    /// Requests to send.
    pub requests: Vec<RangeRequest>,
    /// Bytes read that no answer in `blobs` holds: directories, gaps, checksums (less
    /// the packages' framing).
    pub overhead_bytes: u64,
}

/// The directories read so far and the requests in flight.
#[derive(Debug)]
pub struct RangeReader {
    index: Arc<PackIndex>,
    config: RangeConfig,
    leaves: HashMap<usize, Arc<Entries>>,
    /// Tiles whose directory is being read, with the keys waiting for it.
    waiting: HashMap<usize, Vec<(Key, bool)>>,
    pending: HashMap<u64, Pending>,
    next_tag: u64,
}

impl RangeReader {
    /// A reader of an opened file.
    pub fn new(index: Arc<PackIndex>, config: RangeConfig) -> RangeReader {
        RangeReader {
            index,
            config,
            leaves: HashMap::new(),
            waiting: HashMap::new(),
            pending: HashMap::new(),
            next_tag: 1,
        }
    }

    /// Leaf directories loaded.
    pub fn loaded_tiles(&self) -> usize {
        self.leaves.len()
    }

    fn tag(&mut self, p: Pending) -> u64 {
        let tag = self.next_tag;
        self.next_tag += 1;
        self.pending.insert(tag, p);
        tag
    }

    /// What fetching `keys` takes (each with whether to read it as a package): leaves
    /// known at once, and requests (coalesced ranges, leaf directories not yet loaded
    /// or requested).
    pub fn plan(&mut self, keys: &[(Key, bool)]) -> Step {
        let mut step = Step::default();
        let mut found = Vec::new();
        for &(key, packaged) in keys {
            match self.locate(key) {
                Err(e) => step.blobs.push((key, Err(e))),
                Ok(Located::Absent) => step.leaves.push(key),
                Ok(Located::Blob(blob, dir)) => found.push(Wanted {
                    key,
                    blob,
                    packaged,
                    dir,
                }),
                Ok(Located::Tile(i)) => {
                    let waiting = self.waiting.entry(i).or_default();
                    waiting.push((key, packaged));
                    if waiting.len() == 1 {
                        let dir = self.index.root.tiles[i].dir;
                        let tag = self.tag(Pending::Dir(i));
                        step.requests.push(RangeRequest { tag, range: dir });
                    }
                }
            }
        }
        self.coalesce(found, &mut step);
        step
    }

    fn locate(&self, key: Key) -> Result<Located, FetchError> {
        let (k, _) = self
            .index
            .space
            .key_level(key)
            .map_err(|e| FetchError::Protocol(format!("key {key:?}: {e}")))?;
        Ok(match self.index.root.lookup(&self.index.tiling, &k) {
            Lookup::Blob(b) => Located::Blob(b, None),
            Lookup::Absent => Located::Absent,
            Lookup::Tile(i) => match self.leaves.get(&i) {
                Some(entries) => entries
                    .find(&k)
                    .map_or(Located::Absent, |b| Located::Blob(b, Some(i))),
                None => Located::Tile(i),
            },
        })
    }

    /// Groups ranges into requests (see the module docs).
    fn coalesce(&mut self, mut found: Vec<Wanted>, step: &mut Step) {
        found.sort_by_key(|w| (w.blob.offset, std::cmp::Reverse(w.span().end())));
        found.dedup_by_key(|w| w.blob.offset);

        let mut run: Vec<Wanted> = Vec::new();
        let mut end = 0;
        let mut flush = |run: &mut Vec<Wanted>, end: u64, reader: &mut RangeReader| {
            if let Some(first) = run.first() {
                let range = Section {
                    offset: first.blob.offset,
                    len: end - first.blob.offset,
                };
                let tag = reader.tag(Pending::Blobs(range, std::mem::take(run)));
                step.requests.push(RangeRequest { tag, range });
            }
        };
        for w in found {
            let span = w.span();
            if let Some(first) = run.first() {
                let gap = span.offset.saturating_sub(end);
                let len = span.end().max(end) - first.blob.offset;
                if gap > self.config.max_gap || len > self.config.max_run {
                    flush(&mut run, end, self);
                }
            }
            end = if run.is_empty() {
                span.end()
            } else {
                end.max(span.end())
            };
            run.push(w);
        }
        flush(&mut run, end, self);
    }

    /// The answer of `w` out of `body`, the bytes of `range`.
    fn read(&self, w: &Wanted, range: Section, body: &Bytes) -> Result<Bytes, String> {
        let span = w.span();
        let at = (span.offset - range.offset) as usize;
        let bytes = body.slice(at..at + span.len as usize);
        if !w.packaged {
            return match w.blob.check(&bytes) {
                Ok(_) => Ok(bytes.slice(..w.blob.len as usize)),
                Err(e) => Err(e.reason()),
            };
        }
        let (k, _) = self.index.space.key_level(w.key)?;
        let find = |c: &[u8]| match w.dir {
            None => self.index.root.entries.find(c),
            Some(i) => self.leaves.get(&i).and_then(|e| e.find(c)),
        };
        pack::package_from(&self.index.space, &k, w.blob, &bytes, &find)
            .map(Bytes::from)
            .map_err(PackError::reason)
    }

    /// The answer to request `tag`: the bytes of exactly its range (the caller has checked
    /// the status, `Content-Range` and the file's identity), or why there are none. A
    /// failed request fails each of its keys with that error (retry them by planning
    /// them again).
    pub fn answered(&mut self, tag: u64, answer: Result<Bytes, FetchError>) -> Step {
        let mut step = Step::default();
        let Some(pending) = self.pending.remove(&tag) else {
            return step;
        };
        match pending {
            Pending::Blobs(range, wanted) => {
                let body = match answer.and_then(|b| exact(b, range)) {
                    Ok(b) => b,
                    Err(e) => {
                        step.blobs = wanted
                            .into_iter()
                            .map(|w| (w.key, Err(e.clone())))
                            .collect();
                        return step;
                    }
                };
                let mut used = 0;
                for w in wanted {
                    let answer = match self.read(&w, range, &body) {
                        Ok(b) => {
                            used += b.len() as u64;
                            Ok(b)
                        }
                        Err(e) => Err(FetchError::Protocol(format!(
                            "blob at {} of the repository file: {e}",
                            w.blob.offset
                        ))),
                    };
                    step.blobs.push((w.key, answer));
                }
                step.overhead_bytes = (body.len() as u64).saturating_sub(used);
            }
            Pending::Dir(i) => {
                let keys = self.waiting.remove(&i).unwrap_or_default();
                let tile = self.index.root.tiles[i];
                let parsed = answer.and_then(|b| exact(b, tile.dir)).and_then(|b| {
                    pack::parse_leaf(&tile, &b).map_err(|e| {
                        FetchError::Protocol(format!(
                            "leaf directory at {} of the repository file: {}",
                            tile.dir.offset,
                            e.reason()
                        ))
                    })
                });
                match parsed {
                    Err(e) => {
                        step.blobs = keys.into_iter().map(|(k, _)| (k, Err(e.clone()))).collect();
                    }
                    Ok(entries) => {
                        step.overhead_bytes = tile.dir.len;
                        self.leaves.insert(i, Arc::new(entries));
                        let mut next = self.plan(&keys);
                        step.leaves.append(&mut next.leaves);
                        step.blobs.append(&mut next.blobs);
                        step.requests.append(&mut next.requests);
                    }
                }
            }
        }
        step
    }

    /// The bytes request `tag` asked for, while it is pending.
    pub fn range_of(&self, tag: u64) -> Option<Section> {
        match self.pending.get(&tag)? {
            Pending::Blobs(range, _) => Some(*range),
            Pending::Dir(i) => Some(self.index.root.tiles[*i].dir),
        }
    }
}

enum Located {
    /// Its blob, in the root's directory (`None`) or a tile's.
    Blob(BlobRef, Option<usize>),
    Absent,
    Tile(usize),
}

/// The answer's bytes if they are exactly `range`'s length.
fn exact(body: Bytes, range: Section) -> Result<Bytes, FetchError> {
    if body.len() as u64 == range.len {
        Ok(body)
    } else {
        Err(FetchError::Protocol(format!(
            "{} bytes for a range of {} (bytes {}-{})",
            body.len(),
            range.len,
            range.offset,
            range.end() - 1
        )))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use quincunx_diamond::{PlanarDomain, PlanarId};

    /// Packages carry children of at most this many bytes.
    const INLINE: u32 = 60;

    /// A file of every diamond of levels 0-9 of a 64-square (blob = 20 bytes of the key's
    /// last byte), tiled with small limits; returns it, its index and the keys as centres.
    fn file(tiled: bool) -> (Vec<u8>, Arc<PackIndex>, Vec<Key>) {
        file_with(tiled, Some(INLINE))
    }

    /// [`file`] with packages of children up to `inline` bytes (`None`: key order).
    fn file_with(tiled: bool, inline: Option<u32>) -> (Vec<u8>, Arc<PackIndex>, Vec<Key>) {
        let d = PlanarDomain::new(6).unwrap();
        let mut ids: Vec<(Vec<u8>, Key)> = (0..=64)
            .flat_map(|x| (0..=64).map(move |y| PlanarId::new(x, y)))
            .filter(|&id| d.level(id).is_ok_and(|l| l < 10))
            .map(|id| (d.key(id).unwrap(), [id.x, id.y, 0]))
            .collect();
        ids.sort();
        let space = IdSpace::Planar(d);
        let limits = if tiled {
            pack::Limits {
                root_all_max: 0,
                root_split_max: 8,
                leaf_max: 50,
            }
        } else {
            pack::Limits::default()
        };
        let plan = pack::Plan::choose(&space, ids.iter().map(|(k, _)| k.as_slice()), limits);
        let pairs: Vec<(Vec<u8>, Vec<u8>)> = ids
            .iter()
            .map(|(k, _)| (k.clone(), vec![k[k.len() - 1]; 20]))
            .collect();
        let json = serde_json::to_vec(&metadata()).unwrap();
        let out = pack::encode(plan, &json, &pairs, inline).unwrap();
        let (index, _) = PackIndex::open(&out, out.len() as u64).unwrap();
        (
            out,
            Arc::new(index),
            ids.into_iter().map(|(_, c)| c).collect(),
        )
    }

    fn metadata() -> Metadata {
        serde_json::from_value(serde_json::json!({
            "format_version": pack::LAYOUT_VERSION,
            "complete": true,
            "content_hash": "0123456789abcdef".repeat(4),
            "domain": "planar",
            "m": 6,
            "n": 32,
            "levels": 10,
            "attribute": {"kind": "elevation", "units": "m"},
            "extent": [65, 65],
            "nodata": {"source_count": 0, "handling": "none"},
            "georef": null,
            "radius_m": null,
            "channels": [],
            "build": {},
            "level_stats": [],
        }))
        .unwrap()
    }

    /// Serves every request from `file` until nothing is left; returns blobs, leaves,
    /// requests made and overhead bytes.
    fn drive(
        reader: &mut RangeReader,
        file: &[u8],
        keys: &[Key],
    ) -> (HashMap<Key, Bytes>, Vec<Key>, usize, u64) {
        drive_as(reader, file, keys, false)
    }

    /// [`drive`], asking for packages when `packaged`.
    fn drive_as(
        reader: &mut RangeReader,
        file: &[u8],
        keys: &[Key],
        packaged: bool,
    ) -> (HashMap<Key, Bytes>, Vec<Key>, usize, u64) {
        let keys: Vec<(Key, bool)> = keys.iter().map(|&k| (k, packaged)).collect();
        let mut step = reader.plan(&keys);
        let (mut blobs, mut leaves, mut requests, mut overhead) =
            (HashMap::new(), Vec::new(), 0, 0);
        loop {
            leaves.append(&mut step.leaves);
            for (k, b) in step.blobs.drain(..) {
                blobs.insert(k, b.unwrap());
            }
            overhead += step.overhead_bytes;
            let Some(r) = step.requests.pop() else { break };
            requests += 1;
            let body =
                Bytes::copy_from_slice(&file[r.range.offset as usize..r.range.end() as usize]);
            let mut next = reader.answered(r.tag, Ok(body));
            next.requests.append(&mut step.requests);
            step = next;
        }
        (blobs, leaves, requests, overhead)
    }

    #[test]
    fn every_key_reads_back_through_coalesced_ranges_and_directories() {
        for tiled in [false, true] {
            let (file, index, keys) = file(tiled);
            let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
            let (blobs, leaves, requests, overhead) = drive(&mut reader, &file, &keys);
            assert!(leaves.is_empty());
            assert_eq!(blobs.len(), keys.len());
            for (c, b) in &blobs {
                let (k, _) = index.space.key_level(*c).unwrap();
                assert_eq!(&b[..], &[k[k.len() - 1]; 20][..]);
            }
            // Everything is contiguous: one request per 64 KiB (plus directories).
            assert_eq!(reader.loaded_tiles(), index.root.tiles.len());
            assert!(
                requests <= 1 + index.root.tiles.len() * 2,
                "{tiled}: {requests} requests"
            );
            assert!(overhead >= 4 * keys.len() as u64);
            // Deeper keys (no blob) are leaves without a request.
            let deeper = [[1, 0, 0], [0, 1, 0]];
            let (b, l, r, _) = drive(&mut reader, &file, &deeper);
            assert!(b.is_empty() && r == 0 && l.len() == 2, "{b:?} {l:?} {r}");
        }
    }

    #[test]
    fn packages_read_as_one_range_carry_the_small_owned_children() {
        use quincunx_meta::answer;
        for tiled in [false, true] {
            let (file, index, keys) = file(tiled);
            // Shallow keys one at a time, as a viewer refining asks for them.
            let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
            let (mut requests, mut carried) = (0, 0);
            for &key in keys.iter().filter(|&&k| index.space.level(k).unwrap() < 7) {
                let (blobs, _, r, _) = drive_as(&mut reader, &file, &[key], true);
                requests += r;
                let (k, _) = index.space.key_level(key).unwrap();
                let parsed = answer::parse(&blobs[&key], true).unwrap();
                assert_eq!(parsed.blob, &[k[k.len() - 1]; 20][..]);
                let owned = index.space.owned_children(key).unwrap();
                for (i, child) in parsed.children {
                    let (ck, _) = index.space.key_level(owned[i]).unwrap();
                    let inner = answer::parse(child, true).unwrap();
                    assert_eq!(inner.blob, &[ck[ck.len() - 1]; 20][..]);
                    assert!(child.len() <= INLINE as usize);
                    carried += 1;
                }
            }
            assert!(carried > 30, "{tiled}: {carried} carried");
            // One request per package (and per leaf directory).
            let shallow = keys.iter().filter(|&&k| index.space.level(k).unwrap() < 7);
            assert!(requests <= shallow.count() + index.root.tiles.len());
            // A package answer with a byte changed fails that key only.
            let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
            let step = reader.plan(&[(keys[0], true), (keys[keys.len() - 1], false)]);
            for r in step.requests {
                let mut body = file[r.range.offset as usize..r.range.end() as usize].to_vec();
                body[0] ^= 1;
                let s = reader.answered(r.tag, Ok(Bytes::from(body)));
                assert!(s.blobs.iter().all(|(_, b)| b.is_err()), "{:?}", s.blobs);
            }
        }
    }

    #[test]
    fn gaps_over_the_limit_split_requests_and_wrong_answers_are_errors() {
        let (file, index, keys) = file_with(false, None);
        let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
        // Every 20th key: 24-byte blobs 456 bytes apart, so no two share a request.
        let sparse: Vec<Key> = keys.iter().step_by(20).copied().collect();
        let sparse: Vec<(Key, bool)> = sparse.into_iter().map(|k| (k, false)).collect();
        let sparse_step = reader.plan(&sparse);
        assert_eq!(sparse_step.requests.len(), sparse.len());
        // Every 5th: gaps of 96 bytes, joined.
        let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
        let dense: Vec<(Key, bool)> = keys.iter().step_by(5).map(|&k| (k, false)).collect();
        let step = reader.plan(&dense);
        assert!(
            step.requests.len() < dense.len() / 10,
            "{}",
            step.requests.len()
        );
        // A short answer, a changed byte: errors for the keys, never a wrong blob.
        let r = step.requests[0];
        let short =
            Bytes::copy_from_slice(&file[r.range.offset as usize..r.range.end() as usize - 1]);
        let s = reader.answered(r.tag, Ok(short));
        assert!(!s.blobs.is_empty() && s.blobs.iter().all(|(_, b)| b.is_err()));
        let r = sparse_step.requests[1];
        let mut bad = file[r.range.offset as usize..r.range.end() as usize].to_vec();
        bad[3] ^= 1;
        let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
        let r = reader.plan(&sparse).requests[1];
        let s = reader.answered(r.tag, Ok(Bytes::from(bad)));
        let errors: Vec<_> = s
            .blobs
            .iter()
            .filter_map(|(_, b)| b.as_ref().err())
            .collect();
        assert_eq!(errors.len(), 1, "{errors:?}");
        assert!(errors[0].to_string().contains("checksum mismatch"));
        // A late or unknown answer is ignored.
        assert!(reader.answered(r.tag, Ok(Bytes::new())).blobs.is_empty());
    }

    #[test]
    fn keys_of_one_tile_share_one_directory_request() {
        let (file, index, keys) = file(true);
        let mut reader = RangeReader::new(Arc::clone(&index), RangeConfig::default());
        let deep: Vec<(Key, bool)> = keys
            .iter()
            .filter(|&&c| index.space.level(c).unwrap() >= index.tiling.split_level)
            .map(|&k| (k, false))
            .collect();
        let step = reader.plan(&deep);
        assert!(step.blobs.is_empty() && step.leaves.is_empty());
        assert_eq!(step.requests.len(), index.root.tiles.len());
        // A failed directory read fails its keys; planning them again asks again.
        let r = step.requests[0];
        let s = reader.answered(r.tag, Err(FetchError::Status(503)));
        let failed: Vec<(Key, bool)> = s.blobs.iter().map(|(k, _)| (*k, false)).collect();
        assert!(!failed.is_empty());
        let again = reader.plan(&failed);
        assert_eq!(again.requests.len(), 1);
        let body = Bytes::copy_from_slice(
            &file[again.requests[0].range.offset as usize..again.requests[0].range.end() as usize],
        );
        let s = reader.answered(again.requests[0].tag, Ok(body));
        assert!(!s.requests.is_empty());
    }
}
