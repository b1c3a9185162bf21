//! The blob: one diamond's coded details plus side information (spec:
//! `docs/blob-format.md`).
//!
//! ```text
//! byte 0      version (high 4 bits) | log2(N) (low 4 bits)
//! bytes 1..3  CRC-16/CCITT (little-endian) over key ‖ byte 0 ‖ payload
//! bytes 3..   range-coded payload: side-information classes of the children this
//!             diamond owns, then the quantised detail matrix, then (version 6) one
//!             bound profile per owned child flagged no-data
//! ```
//! The payload length is the blob length minus 3: there is no length field, so no
//! allocation is ever sized from untrusted bytes. The key in the checksum makes a blob
//! served under the wrong id fail to decode.

use crate::entropy::{self, CodecModel, EntropyError, ModelDecoder, ModelEncoder};
use crate::lifting::DiamondMask;

/// Newest blob format version. Version 6 (what a build's bound pass writes: measured
/// bounds) adds, after the matrix, a bound profile for each owned child flagged
/// [`entropy::NO_DATA`]: the classes bounding its descendants level by level
/// ([`encode_profiled`]). Version 5 changed only what the side-information classes mean
/// (a true upper bound on the departure of the finest surface, monotone up the DAG:
/// `docs/blob-format.md`); the layout is version 4's.
pub const VERSION: u8 = 6;
/// The version [`encode`] writes (no profiles).
pub const UNPROFILED_VERSION: u8 = 5;
/// Oldest version still decoded: version 4 blobs have the same layout, and their classes
/// are the older, tighter estimate (largest departure of any one level, not the sum).
pub const MIN_VERSION: u8 = 4;
/// Bytes before the payload.
pub const HEADER_BYTES: usize = 3;

/// Why a blob could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// Fewer bytes than the header.
    #[error("blob of {0} bytes is shorter than its header")]
    TooShort(usize),
    /// Unknown format version.
    #[error("blob version {0} is not supported (expected {MIN_VERSION} to {VERSION})")]
    Version(u8),
    /// The blob's diamond size differs from the repository's.
    #[error("blob diamond size 2^{got} does not match the repository's N = {expected}")]
    Size {
        /// log2 N in the blob
        got: u8,
        /// the repository's N
        expected: usize,
    },
    /// Checksum mismatch: corrupted, truncated, or served for another id.
    #[error("checksum mismatch (stored {stored:#06x}, computed {computed:#06x})")]
    Checksum {
        /// stored CRC
        stored: u16,
        /// computed CRC
        computed: u16,
    },
    /// The coded payload is malformed.
    #[error(transparent)]
    Entropy(#[from] EntropyError),
}

/// What the decoder must know about a diamond besides its bytes (all derivable from the
/// id and the repository metadata).
#[derive(Clone, Copy, Debug)]
pub struct BlobContext<'a> {
    /// The diamond's storage key.
    pub key: &'a [u8],
    /// Diamond size `N`.
    pub n: usize,
    /// Level group (see [`entropy::group`]).
    pub group: usize,
    /// Valid cells (`None` = all).
    pub mask: Option<&'a DiamondMask>,
    /// Number of children whose side information this diamond carries.
    pub owned_children: usize,
    /// The quantiser step of the diamond's level (1/256 units, from the repository's
    /// metadata): above 256 (a quantised level, RMS mode) blocks hide a sign
    /// ([`entropy::HIDDEN_SIGN_MIN`]).
    pub step: u32,
}

impl<'a> BlobContext<'a> {
    /// The context of a diamond of detail level `level` of `detail_levels`, with storage
    /// key `key`, valid cells `mask` and `owned_children`; the step is 256 until a caller
    /// that knows the repository's steps sets it.
    pub fn of_level(
        key: &'a [u8],
        n: usize,
        detail_levels: usize,
        level: usize,
        mask: Option<&'a DiamondMask>,
        owned_children: usize,
    ) -> BlobContext<'a> {
        BlobContext {
            key,
            n,
            group: entropy::group(detail_levels - 1 - level),
            mask,
            owned_children,
            step: 256,
        }
    }

    /// Whether this diamond's blocks hide signs.
    pub fn hides_signs(&self) -> bool {
        self.step > 256
    }
}

/// A decoded blob.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BlobContent {
    /// Side-information class of each owned child (see [`entropy::class_bound`]): a bound
    /// on how far that child's finer surface departs from its own grid.
    pub child_classes: Vec<u8>,
    /// Quantised details, `N x N` row-major.
    pub q: Vec<i32>,
}

/// CRC-16/CCITT-FALSE of one byte value, for the table-driven [`crc16`].
const CRC_TABLE: [u16; 256] = {
    let mut t = [0u16; 256];
    let mut b = 0;
    while b < 256 {
        let mut crc = (b as u16) << 8;
        let mut k = 0;
        while k < 8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
            k += 1;
        }
        t[b] = crc;
        b += 1;
    }
    t
};

/// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), one table lookup per byte.
pub fn crc16(parts: &[&[u8]]) -> u16 {
    let mut crc: u16 = 0xFFFF;
    for part in parts {
        for &b in *part {
            crc = (crc << 8) ^ CRC_TABLE[usize::from((crc >> 8) as u8 ^ b)];
        }
    }
    crc
}

/// Encodes a blob (version 5: no bound profiles).
pub fn encode(
    ctx: &BlobContext<'_>,
    model: &CodecModel,
    child_classes: &[u8],
    q: &[i32],
) -> Vec<u8> {
    encode_version(ctx, model, child_classes, q, None)
}

/// Encodes a blob of version 6: besides [`encode`]'s content, `profiles` holds one bound
/// profile per entry of `entries` flagged [`entropy::NO_DATA`], in order. A profile's
/// `k`-th class bounds the departure of every descendant `k + 1` levels below that child
/// (nothing below it has a blob, so no blob will tell); it may stop early (below its
/// end, nothing is said).
pub fn encode_profiled(
    ctx: &BlobContext<'_>,
    model: &CodecModel,
    entries: &[u8],
    q: &[i32],
    profiles: &[Vec<u8>],
) -> Vec<u8> {
    encode_version(ctx, model, entries, q, Some(profiles))
}

fn encode_version(
    ctx: &BlobContext<'_>,
    model: &CodecModel,
    child_classes: &[u8],
    q: &[i32],
    profiles: Option<&[Vec<u8>]>,
) -> Vec<u8> {
    let mut e = ModelEncoder::new(model);
    entropy::write_gammas(&mut e, ctx.group, child_classes);
    entropy::write_matrix(
        &mut e,
        ctx.group,
        ctx.n,
        q,
        ctx.mask.map(DiamondMask::cells),
        ctx.hides_signs(),
    );
    let version = match profiles {
        Some(profiles) => {
            let mut profiles = profiles.iter();
            for &entry in child_classes {
                if entropy::split_side(entry).1 {
                    let p = profiles.next().map_or(&[][..], Vec::as_slice);
                    entropy::write_profile(&mut e, ctx.group, p);
                }
            }
            VERSION
        }
        None => UNPROFILED_VERSION,
    };
    let payload = e.finish();
    let head = (version << 4) | ctx.n.trailing_zeros() as u8;
    let crc = crc16(&[ctx.key, &[head], &payload]);
    let mut out = Vec::with_capacity(HEADER_BYTES + payload.len());
    out.push(head);
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(&payload);
    out
}

/// Decodes a blob into `q` (resized to `N x N`), returning the child classes.
pub fn decode_into(
    bytes: &[u8],
    ctx: &BlobContext<'_>,
    model: &CodecModel,
    q: &mut Vec<i32>,
) -> Result<Vec<u8>, DecodeError> {
    decode_profiled_into(bytes, ctx, model, q).map(|(classes, _)| classes)
}

/// [`decode_into`] with the bound profiles of version 6 (empty before): one per class
/// flagged [`entropy::NO_DATA`], in order.
pub fn decode_profiled_into(
    bytes: &[u8],
    ctx: &BlobContext<'_>,
    model: &CodecModel,
    q: &mut Vec<i32>,
) -> Result<(Vec<u8>, Vec<Vec<u8>>), DecodeError> {
    if bytes.len() < HEADER_BYTES {
        return Err(DecodeError::TooShort(bytes.len()));
    }
    let head = bytes[0];
    if !(MIN_VERSION..=VERSION).contains(&(head >> 4)) {
        return Err(DecodeError::Version(head >> 4));
    }
    if (head & 15) as u32 != ctx.n.trailing_zeros() {
        return Err(DecodeError::Size {
            got: head & 15,
            expected: ctx.n,
        });
    }
    let stored = u16::from_le_bytes([bytes[1], bytes[2]]);
    let payload = &bytes[HEADER_BYTES..];
    let computed = crc16(&[ctx.key, &[head], payload]);
    if stored != computed {
        return Err(DecodeError::Checksum { stored, computed });
    }
    let mut d = ModelDecoder::new(model, payload);
    let classes = entropy::read_gammas(&mut d, ctx.group, ctx.owned_children);
    q.resize(ctx.n * ctx.n, 0);
    entropy::read_matrix(
        &mut d,
        ctx.group,
        ctx.n,
        q,
        ctx.mask.map(DiamondMask::cells),
        ctx.hides_signs(),
    )?;
    let mut profiles = Vec::new();
    if head >> 4 >= 6 {
        for &entry in &classes {
            if entropy::split_side(entry).1 {
                profiles.push(entropy::read_profile(&mut d, ctx.group));
            }
        }
    }
    d.finish()?;
    Ok((classes, profiles))
}

/// Decodes a blob.
pub fn decode(
    bytes: &[u8],
    ctx: &BlobContext<'_>,
    model: &CodecModel,
) -> Result<BlobContent, DecodeError> {
    let mut q = Vec::new();
    let child_classes = decode_into(bytes, ctx, model, &mut q)?;
    Ok(BlobContent { child_classes, q })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn crc16_is_ccitt_false() {
        // The standard check value of CRC-16/CCITT-FALSE, and its split-input form.
        assert_eq!(crc16(&[b"123456789"]), 0x29B1);
        assert_eq!(crc16(&[b"1234", b"", b"56789"]), 0x29B1);
        assert_eq!(crc16(&[]), 0xFFFF);
    }

    #[test]
    fn blob_round_trips_and_rejects_a_foreign_key() {
        let model = CodecModel::default();
        let ctx = BlobContext {
            key: b"\x05abc",
            n: 32,
            group: 1,
            mask: None,
            owned_children: 2,
            step: 256,
        };
        let q: Vec<i32> = (0..1024)
            .map(|k: i32| if k % 37 == 0 { (k % 11) - 5 } else { 0 })
            .collect();
        let bytes = encode(&ctx, &model, &[3, 0], &q);
        let got = decode(&bytes, &ctx, &model).unwrap();
        assert_eq!(
            got,
            BlobContent {
                child_classes: vec![3, 0],
                q
            }
        );
        let other = BlobContext {
            key: b"\x05abd",
            ..ctx
        };
        assert!(matches!(
            decode(&bytes, &other, &model),
            Err(DecodeError::Checksum { .. })
        ));
        assert!(matches!(
            decode(&bytes[..2], &ctx, &model),
            Err(DecodeError::TooShort(2))
        ));
    }

    #[test]
    fn profiles_round_trip_in_version_6_and_version_5_has_none() {
        let model = CodecModel::default();
        let ctx = BlobContext {
            key: b"\x05abc",
            n: 32,
            group: 2,
            mask: None,
            owned_children: 4,
            step: 256,
        };
        let q: Vec<i32> = (0..1024)
            .map(|k: i32| if k % 29 == 0 { (k % 7) - 3 } else { 0 })
            .collect();
        let no_data = entropy::NO_DATA;
        // Two children flagged no-data (one with an empty profile), one plain, one class 0.
        let entries = [9 | no_data, 4, 0, 5 | no_data];
        let profiles = vec![vec![8, 6, 6, 3, 1, 0], vec![]];
        let bytes = encode_profiled(&ctx, &model, &entries, &q, &profiles);
        assert_eq!(bytes[0] >> 4, VERSION);
        let mut got_q = Vec::new();
        let (classes, got) = decode_profiled_into(&bytes, &ctx, &model, &mut got_q).unwrap();
        assert_eq!(
            (classes.as_slice(), got_q.as_slice()),
            (&entries[..], &q[..])
        );
        assert_eq!(got, profiles);
        // The same content without profiles is version 5 and decodes to none.
        let v5 = encode(&ctx, &model, &entries, &q);
        assert_eq!(v5[0] >> 4, UNPROFILED_VERSION);
        let (classes, got) = decode_profiled_into(&v5, &ctx, &model, &mut got_q).unwrap();
        assert_eq!((classes.as_slice(), got.len()), (&entries[..], 0));
        assert!(bytes.len() > v5.len());
        // A class above the largest a profile holds is clamped, never wrapped.
        let bytes = encode_profiled(&ctx, &model, &entries, &q, &[vec![200], vec![63]]);
        let (_, got) = decode_profiled_into(&bytes, &ctx, &model, &mut got_q).unwrap();
        assert_eq!(got, vec![vec![62], vec![62]]);
    }
}
