//! The repository file (`repository.pack`): pages of blobs, a page index and the metadata
//! record in one immutable file, read with positioned reads (spec:
//! `docs/repository-format.md`).
//!
//! ```text
//! file     := head page* index metadata footer
//! head     := "QXREPO\r\n" format_version:u32 0:u32                      (16 bytes)
//! index    := count:varint entry{count}
//! entry    := shared:varint suffix_len:varint suffix page_len:varint blobs:varint crc:u32
//! footer   := index_offset:u64 index_len:u64 metadata_len:u64 index_crc:u32
//!             metadata_crc:u32 format_version:u32 footer_crc:u32 "QXEND\0\0\n"  (48 bytes)
//! ```
//! Integers are little-endian, varints LEB128. Pages ([`crate::page`]) follow the head back
//! to back in key order; an index entry's key is its page's first key, prefix-compressed
//! against the previous entry's; its offset is implied (the sum of the lengths before it).
//! `crc` is CRC-32 (IEEE) of the page, `index_crc` and `metadata_crc` of those sections,
//! `footer_crc` of the footer's first 36 bytes. The footer is written last: a file without a
//! valid footer is an unfinished build or a truncated copy.
//!
//! Everything here parses bytes from disk: lengths are checked against the file before
//! anything is allocated or read, and damage is a [`PackError`], never a panic.

use std::io::Write;

/// First bytes of a repository file (the CR LF catches text-mode transfers).
pub const HEAD_MAGIC: &[u8; 8] = b"QXREPO\r\n";

/// Last bytes of a complete repository file.
pub const FOOTER_MAGIC: &[u8; 8] = b"QXEND\0\0\n";

/// Bytes of the head.
pub const HEAD_BYTES: u64 = 16;

/// Bytes of the footer.
pub const FOOTER_BYTES: u64 = 48;

/// Why a repository file could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PackError {
    /// Not a repository file at all.
    #[error("not a quincunx repository file (its first bytes are not \"QXREPO\")")]
    NotAPack,
    /// A head but no valid footer: an interrupted build or a truncated copy.
    #[error("{0} (an interrupted build or a truncated copy)")]
    Incomplete(&'static str),
    /// Structurally damaged.
    #[error("damaged: {0}")]
    Damaged(String),
}

fn damaged(what: impl Into<String>) -> PackError {
    PackError::Damaged(what.into())
}

/// Where the sections of a repository file are, read from its footer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Footer {
    /// Offset of the index (= end of the pages).
    pub index_offset: u64,
    /// Length of the index.
    pub index_len: u64,
    /// Length of the metadata record (it follows the index).
    pub metadata_len: u64,
    /// CRC-32 of the index.
    pub index_crc: u32,
    /// CRC-32 of the metadata record.
    pub metadata_crc: u32,
    /// Format version (equals the head's).
    pub format_version: u32,
}

impl Footer {
    /// The footer's bytes.
    pub fn to_bytes(&self) -> [u8; FOOTER_BYTES as usize] {
        let mut out = [0u8; FOOTER_BYTES as usize];
        out[0..8].copy_from_slice(&self.index_offset.to_le_bytes());
        out[8..16].copy_from_slice(&self.index_len.to_le_bytes());
        out[16..24].copy_from_slice(&self.metadata_len.to_le_bytes());
        out[24..28].copy_from_slice(&self.index_crc.to_le_bytes());
        out[28..32].copy_from_slice(&self.metadata_crc.to_le_bytes());
        out[32..36].copy_from_slice(&self.format_version.to_le_bytes());
        let crc = crc32fast::hash(&out[..36]);
        out[36..40].copy_from_slice(&crc.to_le_bytes());
        out[40..48].copy_from_slice(FOOTER_MAGIC);
        out
    }

    /// Parses and checks a footer of a file of `file_len` bytes whose head said
    /// `head_version`: the sections must tile the file exactly.
    pub fn parse(bytes: &[u8], file_len: u64) -> Result<Footer, PackError> {
        let bytes: &[u8; FOOTER_BYTES as usize] = bytes
            .try_into()
            .map_err(|_| PackError::Incomplete("no footer"))?;
        if &bytes[40..48] != FOOTER_MAGIC {
            return Err(PackError::Incomplete("no footer at the end of the file"));
        }
        let u64_at = |at: usize| u64::from_le_bytes(array(&bytes[at..at + 8]));
        let u32_at = |at: usize| u32::from_le_bytes(array(&bytes[at..at + 4]));
        if crc32fast::hash(&bytes[..36]) != u32_at(36) {
            return Err(damaged("footer checksum mismatch"));
        }
        let footer = Footer {
            index_offset: u64_at(0),
            index_len: u64_at(8),
            metadata_len: u64_at(16),
            index_crc: u32_at(24),
            metadata_crc: u32_at(28),
            format_version: u32_at(32),
        };
        let end = footer
            .index_offset
            .checked_add(footer.index_len)
            .and_then(|e| e.checked_add(footer.metadata_len))
            .and_then(|e| e.checked_add(FOOTER_BYTES));
        if footer.index_offset < HEAD_BYTES || end != Some(file_len) {
            return Err(damaged(format!(
                "sections (index at {}, {} + {} bytes) do not fit a file of {file_len} bytes",
                footer.index_offset, footer.index_len, footer.metadata_len
            )));
        }
        Ok(footer)
    }
}

/// How far from the end [`trailing_bytes`] looks for a footer.
pub const TRAILING_SEARCH_BYTES: u64 = 64 << 10;

/// When the last bytes of a file are not a footer: how many bytes follow the last valid
/// footer (magic and checksum) within `tail`, the file's last bytes (`file_len` in all),
/// if there is one. Tells bytes appended to a complete file from an unfinished one.
pub fn trailing_bytes(tail: &[u8], file_len: u64) -> Option<u64> {
    let footer = FOOTER_BYTES as usize;
    (footer..=tail.len()).rev().find_map(|end| {
        let bytes = &tail[end - footer..end];
        let footer_end = file_len - (tail.len() - end) as u64;
        (&bytes[40..48] == FOOTER_MAGIC && Footer::parse(bytes, footer_end).is_ok())
            .then_some((tail.len() - end) as u64)
    })
}

fn array<const N: usize>(bytes: &[u8]) -> [u8; N] {
    let mut out = [0u8; N];
    out.copy_from_slice(bytes);
    out
}

/// The head's bytes.
pub fn head(format_version: u32) -> [u8; HEAD_BYTES as usize] {
    let mut out = [0u8; HEAD_BYTES as usize];
    out[..8].copy_from_slice(HEAD_MAGIC);
    out[8..12].copy_from_slice(&format_version.to_le_bytes());
    out
}

/// The format version a head names.
pub fn parse_head(bytes: &[u8]) -> Result<u32, PackError> {
    if bytes.len() < HEAD_BYTES as usize || &bytes[..8] != HEAD_MAGIC {
        return Err(PackError::NotAPack);
    }
    if bytes[12..16] != [0; 4] {
        return Err(damaged("reserved head bytes are not zero"));
    }
    Ok(u32::from_le_bytes(array(&bytes[8..12])))
}

/// One page as the index describes it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PageRef {
    /// The page's first key.
    pub first_key: Box<[u8]>,
    /// Offset in the file.
    pub offset: u64,
    /// Length in bytes.
    pub len: u32,
    /// Blobs in the page.
    pub blobs: u32,
    /// CRC-32 of the page.
    pub crc: u32,
}

/// Appends `value` as LEB128.
pub(crate) fn put_varint(out: &mut Vec<u8>, mut value: u64) {
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// Serialises the index of `pages` (which must follow each other from the head on, in key
/// order).
pub fn encode_index(pages: &[PageRef]) -> Vec<u8> {
    let mut out = Vec::with_capacity(pages.len() * 16);
    put_varint(&mut out, pages.len() as u64);
    let mut previous: &[u8] = &[];
    for p in pages {
        let shared = previous
            .iter()
            .zip(p.first_key.iter())
            .take_while(|(a, b)| a == b)
            .count();
        put_varint(&mut out, shared as u64);
        put_varint(&mut out, (p.first_key.len() - shared) as u64);
        out.extend_from_slice(&p.first_key[shared..]);
        put_varint(&mut out, u64::from(p.len));
        put_varint(&mut out, u64::from(p.blobs));
        out.extend_from_slice(&p.crc.to_le_bytes());
        previous = &p.first_key;
    }
    out
}

/// Parses an index whose pages must exactly fill `HEAD_BYTES .. pages_end`, keys strictly
/// increasing.
pub fn decode_index(bytes: &[u8], pages_end: u64) -> Result<Vec<PageRef>, PackError> {
    let mut r = Cursor { bytes, at: 0 };
    let count = r.varint()?;
    // An entry takes at least 8 bytes.
    if count > (bytes.len() / 8) as u64 {
        return Err(damaged("index entry count exceeds the index"));
    }
    let mut pages: Vec<PageRef> = Vec::with_capacity(count as usize);
    let mut offset = HEAD_BYTES;
    let mut key: Vec<u8> = Vec::new();
    for _ in 0..count {
        let shared = r.varint()? as usize;
        let suffix_len = r.varint()? as usize;
        if shared > key.len() {
            return Err(damaged("index key shares more than the previous key"));
        }
        let suffix = r.take(suffix_len)?;
        let in_order = pages.is_empty()
            || suffix
                .first()
                .is_some_and(|&b| shared == key.len() || b > key[shared]);
        if !in_order {
            return Err(damaged("index keys out of order"));
        }
        key.truncate(shared);
        key.extend_from_slice(suffix);
        let len = u32::try_from(r.varint()?).map_err(|_| damaged("page length overflows"))?;
        let blobs = u32::try_from(r.varint()?).map_err(|_| damaged("blob count overflows"))?;
        let crc = u32::from_le_bytes(array(r.take(4)?));
        if len == 0 || blobs == 0 {
            return Err(damaged("empty page in the index"));
        }
        pages.push(PageRef {
            first_key: key.clone().into_boxed_slice(),
            offset,
            len,
            blobs,
            crc,
        });
        offset += u64::from(len);
        if offset > pages_end {
            return Err(damaged("index pages run past the index"));
        }
    }
    if r.at != bytes.len() {
        return Err(damaged("trailing bytes after the index"));
    }
    if offset != pages_end {
        return Err(damaged("index pages do not reach the index"));
    }
    Ok(pages)
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn varint(&mut self) -> Result<u64, PackError> {
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let byte = *self
                .bytes
                .get(self.at)
                .ok_or_else(|| damaged("index truncated"))?;
            self.at += 1;
            let bits = u64::from(byte & 0x7f);
            if shift > 0 && bits.leading_zeros() < shift {
                return Err(damaged("index length overflows"));
            }
            value |= bits << shift;
            if byte & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(damaged("index length overflows"))
    }

    fn take(&mut self, len: usize) -> Result<&'a [u8], PackError> {
        let end = self
            .at
            .checked_add(len)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| damaged("index truncated"))?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }
}

/// Writes a repository file front to back: [`PackWriter::page`] for each page in key order,
/// then [`PackWriter::finish`].
pub struct PackWriter<W: Write> {
    out: W,
    at: u64,
    pages: Vec<PageRef>,
    format_version: u32,
}

impl<W: Write> PackWriter<W> {
    /// Writes the head.
    pub fn new(mut out: W, format_version: u32) -> std::io::Result<PackWriter<W>> {
        out.write_all(&head(format_version))?;
        Ok(PackWriter {
            out,
            at: HEAD_BYTES,
            pages: Vec::new(),
            format_version,
        })
    }

    /// Appends a page holding `blobs` blobs whose first key is `first_key`.
    pub fn page(&mut self, first_key: &[u8], page: &[u8], blobs: usize) -> std::io::Result<()> {
        let invalid = |what| std::io::Error::new(std::io::ErrorKind::InvalidInput, what);
        let len = u32::try_from(page.len()).map_err(|_| invalid("page over 4 GiB"))?;
        let blobs = u32::try_from(blobs).map_err(|_| invalid("too many blobs in a page"))?;
        self.out.write_all(page)?;
        self.pages.push(PageRef {
            first_key: first_key.into(),
            offset: self.at,
            len,
            blobs,
            crc: crc32fast::hash(page),
        });
        self.at += u64::from(len);
        Ok(())
    }

    /// Writes the index, the metadata record and the footer; returns the writer.
    pub fn finish(mut self, metadata: &[u8]) -> std::io::Result<W> {
        let index = encode_index(&self.pages);
        self.out.write_all(&index)?;
        self.out.write_all(metadata)?;
        let footer = Footer {
            index_offset: self.at,
            index_len: index.len() as u64,
            metadata_len: metadata.len() as u64,
            index_crc: crc32fast::hash(&index),
            metadata_crc: crc32fast::hash(metadata),
            format_version: self.format_version,
        };
        self.out.write_all(&footer.to_bytes())?;
        Ok(self.out)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn pages(keys: &[&[u8]]) -> Vec<PageRef> {
        let mut offset = HEAD_BYTES;
        keys.iter()
            .enumerate()
            .map(|(i, k)| {
                let p = PageRef {
                    first_key: (*k).into(),
                    offset,
                    len: 10 + i as u32,
                    blobs: 1 + i as u32,
                    crc: 0xdead_beef ^ i as u32,
                };
                offset += u64::from(p.len);
                p
            })
            .collect()
    }

    #[test]
    fn an_index_reads_back_with_offsets_and_every_cut_is_an_error() {
        let p = pages(&[b"\x00", b"\x00\x01", b"\x01\x00\x05", b"\x01\x07", b"\x02"]);
        let end = p.last().map(|p| p.offset + u64::from(p.len)).unwrap();
        let bytes = encode_index(&p);
        assert_eq!(decode_index(&bytes, end).unwrap(), p);
        for cut in 0..bytes.len() {
            assert!(decode_index(&bytes[..cut], end).is_err(), "cut at {cut}");
        }
        assert!(
            decode_index(&bytes, end + 1).is_err(),
            "pages short of the index"
        );
        assert!(
            decode_index(&bytes, end - 1).is_err(),
            "pages past the index"
        );
        let swapped = pages(&[b"\x01", b"\x00"]);
        assert!(decode_index(&encode_index(&swapped), HEAD_BYTES + 21).is_err());
    }

    #[test]
    fn a_footer_must_tile_the_file_and_carry_its_checksum() {
        let f = Footer {
            index_offset: 100,
            index_len: 20,
            metadata_len: 30,
            index_crc: 1,
            metadata_crc: 2,
            format_version: 6,
        };
        let bytes = f.to_bytes();
        assert_eq!(Footer::parse(&bytes, 198).unwrap(), f);
        assert!(matches!(
            Footer::parse(&bytes, 199),
            Err(PackError::Damaged(_))
        ));
        for i in 0..40 {
            let mut b = bytes;
            b[i] ^= 0x10;
            assert!(
                matches!(Footer::parse(&b, 198), Err(PackError::Damaged(_))),
                "{i}"
            );
        }
        let mut b = bytes;
        b[47] = 0;
        assert!(matches!(
            Footer::parse(&b, 198),
            Err(PackError::Incomplete(_))
        ));
    }

    proptest::proptest! {
        #[test]
        fn arbitrary_index_bytes_never_panic(
            bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..200),
            end in 0u64..10_000,
        ) {
            let _ = decode_index(&bytes, end);
        }
    }
}
