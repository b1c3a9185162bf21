//! How the codec's output maps onto a repository, and back.
//!
//! - One stored blob per diamond that has one, under the codec's storage key.
//! - Elevation repositories store the codec blob itself. Colour repositories (Y, Co, Cg)
//!   frame the three channel blobs of a diamond as `len0 blob0 len1 blob1 len2 blob2`
//!   (LEB128 lengths; length 0 = that channel has no details there), so one request
//!   fetches a diamond's colour.
//! - The metadata record carries per channel the value scale/offset, quantiser steps,
//!   trained model and root grid: with the id alone a client can decode any blob.

use anyhow::{Context, Result, bail};
use quincunx_codec::encode::{EncodeReport, Encoded, RateMode};
use quincunx_codec::entropy::CodecModel;
use quincunx_codec::raster::RasterGeometry;
use quincunx_store::{ChannelCoding, Metadata, Repository};

/// Names of the colour channels, in blob order.
pub const COLOUR_CHANNELS: [&str; 3] = ["Y", "Co", "Cg"];

/// The rate mode as stored in metadata.
pub fn rate_label(mode: RateMode) -> String {
    match mode {
        RateMode::Lossless => "lossless".into(),
        RateMode::RmsM(t) => format!("rms={t}"),
        RateMode::MaxErrorM(e) => format!("max_error={e}"),
    }
}

/// The metadata description of one coded channel.
pub fn channel_coding(name: &str, enc: &Encoded, mode: RateMode) -> ChannelCoding {
    ChannelCoding {
        name: name.into(),
        value_scale: enc.value_scale_m,
        value_offset: enc.value_offset_m,
        steps: enc.steps.clone(),
        model: enc.model.to_bytes(),
        roots: vec![enc.root.clone()],
        rate: rate_label(mode),
    }
}

fn push_leb128(out: &mut Vec<u8>, mut v: usize) {
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
        push_leb128(&mut out, p.len());
        out.extend_from_slice(p);
    }
    Some(out)
}

/// Splits a stored blob into its `count` channel blobs (`None` = channel has no details).
pub fn split_channels(bytes: &[u8], count: usize) -> Result<Vec<Option<&[u8]>>> {
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
                bail!("colour blob truncated in the length of channel {c}");
            };
            rest = tail;
            if shift > 28 {
                bail!("colour blob has an overlong length for channel {c}");
            }
            len |= ((b & 0x7F) as usize) << shift;
            shift += 7;
            if b & 0x80 == 0 {
                break;
            }
        }
        if len > rest.len() {
            bail!(
                "colour blob channel {c} claims {len} bytes, {} remain",
                rest.len()
            );
        }
        let (part, tail) = rest.split_at(len);
        out.push((len > 0).then_some(part));
        rest = tail;
    }
    if !rest.is_empty() {
        bail!("colour blob has {} trailing bytes", rest.len());
    }
    Ok(out)
}

/// The raster geometry a planar repository was built on.
pub fn planar_geometry(meta: &Metadata) -> Result<RasterGeometry> {
    if meta.domain != "planar" {
        bail!("domain {:?} is not planar", meta.domain);
    }
    let [w, h] = meta.extent;
    let geom = RasterGeometry::new(w as usize, h as usize, meta.n as usize)
        .context("repository extent or diamond size is invalid")?;
    if geom.detail_levels() != meta.levels as usize || geom.domain().m() != meta.m {
        bail!(
            "metadata says m = {}, {} levels; extent {w} x {h} with N = {} gives m = {}, {} levels",
            meta.m,
            meta.levels,
            meta.n,
            geom.domain().m(),
            geom.detail_levels()
        );
    }
    Ok(geom)
}

/// Reassembles channel `channel` of a planar repository as the codec's in-memory form
/// (blobs read from the store), ready to decode.
pub fn load_channel(repo: &Repository, geom: &RasterGeometry, channel: usize) -> Result<Encoded> {
    let meta = repo.metadata();
    let coding = meta
        .channels
        .get(channel)
        .with_context(|| format!("repository has no channel {channel}"))?;
    let model = CodecModel::from_bytes(&coding.model).context("stored entropy model")?;
    let root = coding
        .roots
        .first()
        .cloned()
        .context("channel has no root grid")?;
    let n = meta.n as usize;
    if root.len() != (n + 1) * (n + 1) {
        bail!(
            "root grid has {} values, expected {}",
            root.len(),
            (n + 1) * (n + 1)
        );
    }
    let count = meta.channels.len();
    let mut blobs = Vec::with_capacity(geom.detail_levels());
    for level in 0..geom.detail_levels() {
        let mut row = Vec::with_capacity(geom.level(level).len());
        for slot in geom.level(level) {
            let blob = match repo.get(&slot.key)? {
                None => None,
                Some(bytes) => split_channels(&bytes, count)
                    .with_context(|| format!("blob of {:?}", slot.id))?[channel]
                    .map(<[u8]>::to_vec),
            };
            row.push(blob);
        }
        blobs.push(row);
    }
    Ok(Encoded {
        width: geom.width(),
        height: geom.height(),
        n,
        value_scale_m: coding.value_scale,
        value_offset_m: coding.value_offset,
        steps: coding.steps.clone(),
        root,
        model,
        blobs,
        report: EncodeReport::default(),
    })
}

/// Peak resident memory of this process so far, MB (Linux; 0 elsewhere).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn channel_framing_round_trips_and_rejects_truncation() {
        let a = vec![7u8; 200];
        let parts = [Some(&a[..]), None, Some(&b"xyz"[..])];
        let framed = frame_channels(&parts).unwrap();
        assert_eq!(split_channels(&framed, 3).unwrap(), parts.to_vec());
        for cut in 0..framed.len() {
            assert!(split_channels(&framed[..cut], 3).is_err(), "cut {cut}");
        }
        assert!(frame_channels(&[None, None, None]).is_none());
        assert!(split_channels(&[0xFF; 8], 3).is_err());
    }
}
