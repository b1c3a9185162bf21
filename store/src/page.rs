//! Pages: runs of consecutive `(key, blob)` pairs packed together (the repository file is a
//! sequence of pages, [`crate::pack`]).
//!
//! ```text
//! page  := count:varint entry{count}
//! entry := shared:varint suffix_len:varint suffix value_len:varint value
//! ```
//! An entry's key is the first `shared` bytes of the previous key followed by `suffix`; the
//! "previous key" of the first entry is the page's first key (kept in the page index), which is the first entry's key
//! (so the first entry costs two bytes of key). Keys are strictly increasing. Varints are
//! LEB128 (at most 10 bytes, values fit in `usize`).
//!
//! Pages come from disk: every length is checked against the bytes that remain, and a bad
//! page is a [`PageError`], never a panic or an allocation sized by a length field.

use std::cmp::Ordering;

/// Why a page could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("malformed page: {0}")]
pub struct PageError(&'static str);

/// Appends `value` as LEB128.
fn put_varint(out: &mut Vec<u8>, mut value: usize) {
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// Bytes `put_varint` writes for `value`.
fn varint_len(mut value: usize) -> usize {
    let mut n = 1;
    while value >= 0x80 {
        value >>= 7;
        n += 1;
    }
    n
}

/// Builds one page from pairs given in increasing key order.
#[derive(Debug, Default)]
pub struct PageWriter {
    first_key: Vec<u8>,
    previous_key: Vec<u8>,
    body: Vec<u8>,
    count: usize,
}

impl PageWriter {
    /// Appends a pair; `key` must be greater than every key appended before.
    pub fn push(&mut self, key: &[u8], value: &[u8]) {
        debug_assert!(self.count == 0 || key > self.previous_key.as_slice());
        if self.count == 0 {
            self.first_key = key.to_vec();
            self.previous_key = key.to_vec();
        }
        let shared = self
            .previous_key
            .iter()
            .zip(key)
            .take_while(|(a, b)| a == b)
            .count();
        put_varint(&mut self.body, shared);
        put_varint(&mut self.body, key.len() - shared);
        self.body.extend_from_slice(&key[shared..]);
        put_varint(&mut self.body, value.len());
        self.body.extend_from_slice(value);
        self.previous_key.clear();
        self.previous_key.extend_from_slice(key);
        self.count += 1;
    }

    /// Encoded size so far.
    pub fn len(&self) -> usize {
        varint_len(self.count) + self.body.len()
    }

    /// Pairs pushed since the last [`PageWriter::finish`].
    pub fn count(&self) -> usize {
        self.count
    }

    /// `true` before the first [`PageWriter::push`].
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The page's first key and bytes; `None` when empty. Resets the
    /// writer.
    pub fn finish(&mut self) -> Option<(Vec<u8>, Vec<u8>)> {
        if self.count == 0 {
            return None;
        }
        let mut page = Vec::with_capacity(self.len());
        put_varint(&mut page, self.count);
        page.append(&mut self.body);
        self.count = 0;
        self.previous_key.clear();
        Some((std::mem::take(&mut self.first_key), page))
    }
}

/// One entry of a page: its key and the byte range of its value in the page.
pub type Entry<'k> = (&'k [u8], std::ops::Range<usize>);

/// Reads a page entry by entry.
#[derive(Debug)]
pub struct PageReader<'a> {
    page: &'a [u8],
    at: usize,
    remaining: usize,
    key: Vec<u8>,
    started: bool,
}

impl<'a> PageReader<'a> {
    /// Starts reading `page` whose first key is `page_key`.
    pub fn new(page_key: &[u8], page: &'a [u8]) -> Result<PageReader<'a>, PageError> {
        let mut reader = PageReader {
            page,
            at: 0,
            remaining: 0,
            key: page_key.to_vec(),
            started: false,
        };
        reader.remaining = reader.varint()?;
        // Each entry takes at least three bytes: a count beyond that is corrupt.
        if reader.remaining > page.len() / 3 {
            return Err(PageError("entry count exceeds the page"));
        }
        Ok(reader)
    }

    /// Entries not yet read.
    pub fn remaining(&self) -> usize {
        self.remaining
    }

    fn varint(&mut self) -> Result<usize, PageError> {
        let mut value: usize = 0;
        for shift in (0..64).step_by(7) {
            let byte = *self
                .page
                .get(self.at)
                .ok_or(PageError("truncated length"))?;
            self.at += 1;
            let bits = usize::from(byte & 0x7f);
            if shift > 0 && bits.leading_zeros() < shift {
                return Err(PageError("length overflows"));
            }
            value |= bits << shift;
            if byte & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(PageError("length overflows"))
    }

    fn take(&mut self, len: usize) -> Result<std::ops::Range<usize>, PageError> {
        let end = self
            .at
            .checked_add(len)
            .filter(|&end| end <= self.page.len())
            .ok_or(PageError("entry runs past the end of the page"))?;
        let range = self.at..end;
        self.at = end;
        Ok(range)
    }

    /// The next entry: its key (valid until the next call) and the byte range of its value
    /// in the page; `None` after the last entry.
    pub fn next_entry(&mut self) -> Result<Option<Entry<'_>>, PageError> {
        if self.remaining == 0 {
            return if self.at == self.page.len() {
                Ok(None)
            } else {
                Err(PageError("trailing bytes after the last entry"))
            };
        }
        let first = !self.started;
        self.started = true;
        let shared = self.varint()?;
        let suffix_len = self.varint()?;
        if shared > self.key.len() {
            return Err(PageError("shared prefix longer than the previous key"));
        }
        let suffix = self.take(suffix_len)?;
        let previous_len = self.key.len();
        let in_order = if first {
            // The first entry repeats the page key.
            shared == previous_len && suffix.is_empty()
        } else {
            // Strictly increasing: the first new byte beats the previous key's byte there,
            // or the previous key is a proper prefix of this one.
            match self.page[suffix.clone()].first() {
                None => false,
                Some(&byte) => shared == previous_len || byte > self.key[shared],
            }
        };
        if !in_order {
            return Err(PageError("keys out of order"));
        }
        self.key.truncate(shared);
        self.key.extend_from_slice(&self.page[suffix]);
        let value_len = self.varint()?;
        let value = self.take(value_len)?;
        self.remaining -= 1;
        Ok(Some((&self.key, value)))
    }
}

/// Finds `key` in the page stored under `page_key`: the byte range of its value, `None`
/// when the page does not hold it.
///
/// Never builds a key: it tracks how many leading bytes the current entry shares with `key`
/// (the classic search over prefix-compressed keys). It checks bounds but not key order, so
/// a corrupt page may give a wrong answer here, never a panic; [`PageReader`] (used to walk
/// every blob, as `verify` does) checks everything.
pub fn find(
    page_key: &[u8],
    page: &[u8],
    key: &[u8],
) -> Result<Option<std::ops::Range<usize>>, PageError> {
    let common = |a: &[u8], b: &[u8]| a.iter().zip(b).take_while(|(x, y)| x == y).count();
    let mut cursor = PageReader {
        page,
        at: 0,
        remaining: 0,
        key: Vec::new(),
        started: true,
    };
    let count = cursor.varint()?;
    // `matched`: leading bytes the current entry's key shares with `key`; `len`: its length.
    let (mut matched, mut len) = (common(page_key, key), page_key.len());
    for i in 0..count {
        let shared = cursor.varint()?;
        let suffix = cursor.varint()?;
        let suffix = cursor.take(suffix)?;
        let value_len = cursor.varint()?;
        let value = cursor.take(value_len)?;
        // The byte of the current key at `matched`, if it has one.
        let next_byte = if i == 0 {
            if shared != page_key.len() || !suffix.is_empty() {
                return Err(PageError("first entry does not repeat the page key"));
            }
            page_key.get(matched).copied()
        } else {
            if shared > len {
                return Err(PageError("shared prefix longer than the previous key"));
            }
            len = shared + suffix.len();
            match shared.cmp(&matched) {
                // Same byte at `matched` as the previous key, which was smaller.
                Ordering::Greater => continue,
                // Larger than the previous key where that one equalled `key`.
                Ordering::Less => return Ok(None),
                Ordering::Equal => {
                    let suffix = &page[suffix];
                    matched += common(suffix, &key[matched..]);
                    suffix.get(matched - shared).copied()
                }
            }
        };
        match (next_byte, key.get(matched).copied()) {
            (None, None) => return Ok(Some(value)),
            (None, Some(_)) => {}
            (Some(_), None) => return Ok(None),
            (Some(ours), Some(theirs)) if ours < theirs => {}
            (Some(_), Some(_)) => return Ok(None),
        }
    }
    Ok(None)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn build(pairs: &[(&[u8], &[u8])]) -> (Vec<u8>, Vec<u8>) {
        let mut w = PageWriter::default();
        for (k, v) in pairs {
            w.push(k, v);
        }
        let len = w.len();
        let (key, page) = w.finish().unwrap();
        assert_eq!(page.len(), len);
        (key, page)
    }

    fn entries(key: &[u8], page: &[u8]) -> Vec<(Vec<u8>, Vec<u8>)> {
        let mut r = PageReader::new(key, page).unwrap();
        let mut out = vec![];
        while let Some((k, v)) = r.next_entry().unwrap() {
            out.push((k.to_vec(), page[v].to_vec()));
        }
        out
    }

    #[test]
    fn a_page_reads_back_its_pairs_with_keys_of_different_lengths() {
        let pairs: Vec<(&[u8], &[u8])> = vec![
            (b"\x01", b"a"),
            (b"\x01\x00", b""),
            (b"\x01\x00\x05", b"ccc"),
            (b"\x01\x07", &[9; 300]),
            (b"\x02\x00\x00\x00\x00\x00\x00\x01", b"e"),
        ];
        let (key, page) = build(&pairs);
        assert_eq!(key, b"\x01");
        let got = entries(&key, &page);
        assert_eq!(got.len(), pairs.len());
        for ((k, v), (ek, ev)) in got.iter().zip(&pairs) {
            assert_eq!(k.as_slice(), *ek);
            assert_eq!(v.as_slice(), *ev);
        }
        for (k, v) in &pairs {
            assert_eq!(&page[find(&key, &page, k).unwrap().unwrap()], *v);
        }
        for missing in [
            &b"\x00"[..],
            b"\x01\x00\x04",
            b"\x01\x06",
            b"\x03",
            b"\x01\x00\x05\x00",
        ] {
            assert_eq!(find(&key, &page, missing).unwrap(), None, "{missing:?}");
        }
    }

    #[test]
    fn an_empty_writer_finishes_to_nothing() {
        assert!(PageWriter::default().finish().is_none());
    }

    #[test]
    fn malformed_pages_are_errors() {
        let (key, page) = build(&[(b"ab", b"xyz"), (b"ac", b"uvw")]);
        for cut in 0..page.len() {
            let r = PageReader::new(&key, &page[..cut]).and_then(|mut r| {
                while r.next_entry()?.is_some() {}
                Ok(())
            });
            assert!(r.is_err(), "truncated at {cut}");
        }
        // The first entry must repeat the page key.
        assert!(find(b"a", &page, b"ac").is_err());
        let mut long = page.clone();
        long.push(0);
        let mut r = PageReader::new(&key, &long).unwrap();
        assert!((0..3).any(|_| r.next_entry().is_err()), "trailing bytes");
        assert!(PageReader::new(&key, &[0xff; 12]).is_err());
    }

    proptest! {
        #[test]
        fn any_page_decodes_to_what_was_written(
            pairs in proptest::collection::btree_map(
                proptest::collection::vec(any::<u8>(), 0..6),
                proptest::collection::vec(any::<u8>(), 0..40),
                1..30,
            ),
            probes in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..6), 0..20),
        ) {
            let mut w = PageWriter::default();
            for (k, v) in &pairs {
                w.push(k, v);
            }
            let (key, page) = w.finish().unwrap();
            let got = entries(&key, &page);
            let want: Vec<_> = pairs.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
            prop_assert_eq!(got, want);
            for p in probes.iter().filter(|p| p.as_slice() >= key.as_slice()) {
                let found = find(&key, &page, p).unwrap().map(|r| page[r].to_vec());
                prop_assert_eq!(found.as_ref(), pairs.get(p));
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(key in proptest::collection::vec(any::<u8>(), 0..4),
                                       page in proptest::collection::vec(any::<u8>(), 0..64),
                                       probe in proptest::collection::vec(any::<u8>(), 0..4)) {
            let _ = find(&key, &page, &probe);
        }
    }
}
