//! The byte layouts that cross the module's boundary: little-endian numbers, counts as
//! `u32`, ids as fetch keys. Whatever JavaScript hands in is untrusted: a short or
//! malformed buffer is a [`WireError`], never a panic.

use quincunx_client_core::colour::ColourDetails;
use quincunx_client_core::fetch::Key;
use quincunx_decoder::incremental::{Details, Refiner};

/// A buffer that does not hold what its reader expects.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("malformed buffer: {0}")]
pub struct WireError(pub String);

/// Reads numbers from the front of a buffer.
pub struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `bytes`.
    pub fn new(bytes: &'a [u8]) -> Self {
        Reader { bytes, at: 0 }
    }

    /// The next `len` bytes.
    pub fn take(&mut self, len: usize) -> Result<&'a [u8], WireError> {
        let end = self
            .at
            .checked_add(len)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| {
                WireError(format!(
                    "{len} bytes wanted at {} of {}",
                    self.at,
                    self.bytes.len()
                ))
            })?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], WireError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    /// A `u8`.
    pub fn u8(&mut self) -> Result<u8, WireError> {
        Ok(self.array::<1>()?[0])
    }

    /// A `u32`.
    pub fn u32(&mut self) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    /// An `f64`.
    pub fn f64(&mut self) -> Result<f64, WireError> {
        Ok(f64::from_le_bytes(self.array()?))
    }

    /// An `i64`.
    pub fn i64(&mut self) -> Result<i64, WireError> {
        Ok(i64::from_le_bytes(self.array()?))
    }

    /// A count of items of at least `min_item_bytes` each, checked against what is left
    /// (so a hostile count cannot ask for a huge allocation).
    pub fn count(&mut self, min_item_bytes: usize) -> Result<usize, WireError> {
        let n = self.u32()? as usize;
        let left = self.bytes.len() - self.at;
        if n.saturating_mul(min_item_bytes.max(1)) > left {
            return Err(WireError(format!("{n} items in {left} bytes")));
        }
        Ok(n)
    }

    /// A fetch key (three `i64`).
    pub fn key(&mut self) -> Result<Key, WireError> {
        Ok([self.i64()?, self.i64()?, self.i64()?])
    }

    /// A length-prefixed byte string.
    pub fn bytes(&mut self) -> Result<&'a [u8], WireError> {
        let n = self.count(1)?;
        self.take(n)
    }

    /// A length-prefixed, 4-byte aligned array of `i32` ([`Writer::i32s`]).
    pub fn i32s(&mut self) -> Result<Vec<i32>, WireError> {
        let n = self.count(4)?;
        self.take((4 - self.at % 4) % 4)?;
        let raw = self.take(n * 4)?;
        Ok(raw
            .chunks_exact(4)
            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    /// Bytes read so far.
    pub fn position(&self) -> usize {
        self.at
    }

    /// Whether everything was read.
    pub fn finish(&self) -> Result<(), WireError> {
        if self.at == self.bytes.len() {
            Ok(())
        } else {
            Err(WireError(format!(
                "{} bytes left over",
                self.bytes.len() - self.at
            )))
        }
    }
}

/// Appends numbers to a buffer.
#[derive(Default)]
pub struct Writer {
    /// What was written.
    pub out: Vec<u8>,
}

impl Writer {
    /// A `u8`.
    pub fn u8(&mut self, v: u8) {
        self.out.push(v);
    }

    /// A `u32`.
    pub fn u32(&mut self, v: u32) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }

    /// A count (saturating: no buffer here holds 2^32 items).
    pub fn count(&mut self, n: usize) {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX));
    }

    /// An `f64`.
    pub fn f64(&mut self, v: f64) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }

    /// An `i64`.
    pub fn i64(&mut self, v: i64) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }

    /// A length-prefixed byte string ([`Reader::bytes`]).
    pub fn bytes(&mut self, v: &[u8]) {
        self.count(v.len());
        self.out.extend_from_slice(v);
    }

    /// A fetch key.
    pub fn key(&mut self, k: Key) {
        for v in k {
            self.i64(v);
        }
    }

    /// Pads with zeros to a multiple of 4 bytes (so an `i32` array that follows can be
    /// viewed in place).
    pub fn align4(&mut self) {
        while !self.out.len().is_multiple_of(4) {
            self.out.push(0);
        }
    }

    /// A length-prefixed array of `i32`, 4-byte aligned.
    pub fn i32s(&mut self, v: &[i32]) {
        self.count(v.len());
        self.align4();
        for x in v {
            self.out.extend_from_slice(&x.to_le_bytes());
        }
    }
}

/// A decoded value that crosses from a decoding worker to the client, for refiner `R`:
/// ids as keys.
pub trait Wire<R: Refiner>: Sized {
    /// Appends the value.
    fn write(&self, w: &mut Writer);
    /// Reads the value of diamond `key`.
    fn read(key: Key, r: &mut Reader<'_>) -> Result<Self, WireError>;
}

impl<R: Refiner> Wire<R> for Details<R::Id> {
    fn write(&self, w: &mut Writer) {
        w.i32s(&self.h);
        w.count(self.child_classes.len());
        for &(c, class) in &self.child_classes {
            w.key(R::key_of(c));
            w.u8(class);
        }
        w.count(self.empty_children.len());
        for &c in &self.empty_children {
            w.key(R::key_of(c));
        }
        w.count(self.child_profiles.len());
        for (c, p) in &self.child_profiles {
            w.key(R::key_of(*c));
            w.bytes(p);
        }
    }

    fn read(key: Key, r: &mut Reader<'_>) -> Result<Self, WireError> {
        let h = r.i32s()?;
        let n = r.count(25)?;
        let mut child_classes = Vec::with_capacity(n);
        for _ in 0..n {
            child_classes.push((R::id_of(r.key()?), r.u8()?));
        }
        let n = r.count(24)?;
        let mut empty_children = Vec::with_capacity(n);
        for _ in 0..n {
            empty_children.push(R::id_of(r.key()?));
        }
        let n = r.count(28)?;
        let mut child_profiles = Vec::with_capacity(n);
        for _ in 0..n {
            child_profiles.push((R::id_of(r.key()?), r.bytes()?.to_vec()));
        }
        Ok(Details {
            id: R::id_of(key),
            h,
            child_classes,
            empty_children,
            child_profiles,
        })
    }
}

impl<R: Refiner> Wire<R> for ColourDetails<R::Id> {
    fn write(&self, w: &mut Writer) {
        w.count(self.channels.len());
        for c in &self.channels {
            match c {
                None => w.u8(0),
                Some(d) => {
                    w.u8(1);
                    <Details<R::Id> as Wire<R>>::write(d, w);
                }
            }
        }
    }

    fn read(key: Key, r: &mut Reader<'_>) -> Result<Self, WireError> {
        let n = r.count(1)?;
        let mut channels = Vec::with_capacity(n);
        for _ in 0..n {
            channels.push(match r.u8()? {
                0 => None,
                1 => Some(<Details<R::Id> as Wire<R>>::read(key, r)?),
                b => return Err(WireError(format!("channel flag {b}"))),
            });
        }
        Ok(ColourDetails {
            id: R::id_of(key),
            channels,
        })
    }
}
