//! Multi-channel blobs (colour: Y, Co, Cg): the channel blobs of one diamond framed as
//! `len0 blob0 len1 blob1 len2 blob2` (LEB128 lengths; length 0 = that channel has no
//! details there), so one request fetches a diamond's colour. Single-channel blobs are
//! stored as they are.

/// A framed blob that does not split (truncated, overlong lengths, trailing bytes).
#[derive(Debug, thiserror::Error)]
#[error("malformed channel frame: {0}")]
pub struct FrameError(String);

use crate::answer::write_varint;

/// Frames the channel blobs of one diamond (`None` when no channel has details).
pub fn frame_channels(parts: &[Option<&[u8]>]) -> Option<Vec<u8>> {
    if parts.len() == 1 {
        return parts[0].map(<[u8]>::to_vec);
    }
    if parts.iter().all(Option::is_none) {
        return None;
    }
    let mut out = Vec::new();
    for p in parts {
        let p = p.unwrap_or_default();
        write_varint(&mut out, p.len());
        out.extend_from_slice(p);
    }
    Some(out)
}

/// Splits a stored blob into its `count` channel blobs (`None` = channel has no details).
pub fn split_channels(bytes: &[u8], count: usize) -> Result<Vec<Option<&[u8]>>, FrameError> {
    if count == 1 {
        return Ok(vec![Some(bytes)]);
    }
    let mut out = Vec::with_capacity(count);
    let mut rest = bytes;
    for c in 0..count {
        let mut len = 0usize;
        let mut shift = 0;
        loop {
            let Some((&b, tail)) = rest.split_first() else {
                return Err(FrameError(format!(
                    "truncated in the length of channel {c}"
                )));
            };
            rest = tail;
            if shift > 28 {
                return Err(FrameError(format!("overlong length for channel {c}")));
            }
            len |= ((b & 0x7F) as usize) << shift;
            shift += 7;
            if b & 0x80 == 0 {
                break;
            }
        }
        if len > rest.len() {
            return Err(FrameError(format!(
                "channel {c} claims {len} bytes, {} remain",
                rest.len()
            )));
        }
        let (part, tail) = rest.split_at(len);
        out.push((len > 0).then_some(part));
        rest = tail;
    }
    if !rest.is_empty() {
        return Err(FrameError(format!("{} trailing bytes", rest.len())));
    }
    Ok(out)
}
