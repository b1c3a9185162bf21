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
use quincunx_codec::blob::BlobContext;
use quincunx_codec::coverage::Coverage;
use quincunx_codec::encode::{self, EncodeReport, Encoded, EncodedDomain, RateMode};
use quincunx_codec::entropy::CodecModel;
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::sphere_raster::SphereGeometry;
use quincunx_store::{ChannelCoding, Domain, Metadata, Rate, Repository};

/// Names of the colour channels, in blob order.
pub const COLOUR_CHANNELS: [&str; 3] = ["Y", "Co", "Cg"];

/// The rate mode as stored in metadata.
pub fn rate_label(mode: RateMode) -> Rate {
    match mode {
        RateMode::Lossless => Rate::Lossless,
        RateMode::RmsM(t) => Rate::Rms(t),
        RateMode::MaxErrorM(e) => Rate::MaxError(e),
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
        roots: enc.roots.clone(),
        rate: rate_label(mode),
    }
}

pub use quincunx_store::channels::{frame_channels, split_channels};

/// The hierarchy a repository was built on: a planar raster or a cube-mapped planet.
pub enum Geometry {
    /// Planar raster.
    Planar(RasterGeometry),
    /// Planet (cube raster).
    Sphere(SphereGeometry),
}

impl Geometry {
    /// The geometry of a codec result.
    pub fn of(enc: &Encoded) -> Result<Geometry> {
        Ok(match enc.domain {
            EncodedDomain::Planar { width, height } => {
                Geometry::Planar(RasterGeometry::new(width, height, enc.n)?)
            }
            EncodedDomain::Sphere { face_side } => {
                Geometry::Sphere(SphereGeometry::new(face_side, enc.n)?)
            }
        })
    }

    /// The geometry a repository's metadata describes, after the metadata's one check
    /// ([`Metadata::validate`]: limits, `m` and `levels` from the extent and `N`).
    pub fn from_metadata(meta: &Metadata) -> Result<Geometry> {
        meta.validate()?;
        let [a, b] = meta.extent;
        let (a, b) = (a as usize, b as usize);
        let n = meta.n as usize;
        let coverage = coverage(meta)?;
        let geom = match (meta.domain, &coverage) {
            (Domain::Planar, None) => Geometry::Planar(RasterGeometry::new(a, b, n)?),
            (Domain::Planar, Some(c)) => {
                Geometry::Planar(RasterGeometry::with_coverage(a, b, n, c)?)
            }
            (Domain::Sphere, None) if a == b => Geometry::Sphere(SphereGeometry::new(a, n)?),
            (Domain::Sphere, Some(c)) if a == b => {
                Geometry::Sphere(SphereGeometry::with_coverage(a, n, c)?)
            }
            (Domain::Sphere, _) => bail!("a sphere's extent must be square, not {a} x {b}"),
        };
        if geom.detail_levels() != meta.levels as usize || geom.m() != meta.m {
            // `validate` derives both as the codec does; reaching this is a bug.
            bail!("the metadata's levels and m disagree with the codec's geometry");
        }
        Ok(geom)
    }

    /// The metadata's domain.
    pub fn domain(&self) -> Domain {
        match self {
            Geometry::Planar(_) => Domain::Planar,
            Geometry::Sphere(_) => Domain::Sphere,
        }
    }

    /// Domain size exponent.
    pub fn m(&self) -> u32 {
        match self {
            Geometry::Planar(g) => g.domain().m(),
            Geometry::Sphere(g) => g.domain().m(),
        }
    }

    /// Metadata `extent`.
    pub fn extent(&self) -> [u64; 2] {
        match self {
            Geometry::Planar(g) => [g.width() as u64, g.height() as u64],
            Geometry::Sphere(g) => [g.face_side() as u64; 2],
        }
    }

    /// Levels carrying details.
    pub fn detail_levels(&self) -> usize {
        match self {
            Geometry::Planar(g) => g.detail_levels(),
            Geometry::Sphere(g) => g.detail_levels(),
        }
    }

    /// Diamonds of a level.
    pub fn level_len(&self, level: usize) -> usize {
        match self {
            Geometry::Planar(g) => g.level(level).len(),
            Geometry::Sphere(g) => g.level(level).len(),
        }
    }

    /// Storage key of diamond `index` of `level`.
    pub fn key(&self, level: usize, index: usize) -> &[u8] {
        match self {
            Geometry::Planar(g) => &g.level(level)[index].key,
            Geometry::Sphere(g) => &g.level(level)[index].key,
        }
    }

    /// Decoder context of diamond `index` of `level`.
    pub fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_> {
        match self {
            Geometry::Planar(g) => g.blob_context(level, index),
            Geometry::Sphere(g) => g.blob_context(level, index),
        }
    }

    /// Decodes a channel at full resolution (one thread) to integers.
    pub fn decode(&self, enc: &Encoded) -> Result<Vec<i32>> {
        match self {
            Geometry::Planar(g) => encode::decode_integers_with(g, enc),
            Geometry::Sphere(g) => encode::decode_sphere_integers_with(g, enc),
        }
        .context("decoding the repository")
    }
}

/// The coverage of a sparse repository (`None` = dense).
pub fn coverage(meta: &Metadata) -> Result<Option<Coverage>> {
    meta.coverage
        .as_deref()
        .map(Coverage::from_bytes)
        .transpose()
        .context("the repository's coverage bitmap is malformed")
}

/// Reassembles channel `channel` of a repository as the codec's in-memory form (blobs
/// read from the store), ready to decode.
pub fn load_channel(repo: &Repository, geom: &Geometry, channel: usize) -> Result<Encoded> {
    let meta = repo.metadata();
    let coding = meta
        .channels
        .get(channel)
        .with_context(|| format!("repository has no channel {channel}"))?;
    let model = CodecModel::from_bytes(&coding.model).context("stored entropy model")?;
    let n = meta.n as usize;
    let want_roots = match geom {
        Geometry::Planar(_) => 1,
        Geometry::Sphere(_) => 6,
    };
    if coding.roots.len() != want_roots || coding.roots.iter().any(|r| r.len() != (n + 1) * (n + 1))
    {
        bail!(
            "channel {channel} needs {want_roots} root grids of {} values",
            (n + 1) * (n + 1)
        );
    }
    let count = meta.channels.len();
    let mut blobs = Vec::with_capacity(geom.detail_levels());
    for level in 0..geom.detail_levels() {
        let mut row = Vec::with_capacity(geom.level_len(level));
        for index in 0..geom.level_len(level) {
            let blob = match repo.get(geom.key(level, index))? {
                None => None,
                Some(bytes) => split_channels(&bytes, count)
                    .with_context(|| format!("blob {index} of level {level}"))?[channel]
                    .map(<[u8]>::to_vec),
            };
            row.push(blob);
        }
        blobs.push(row);
    }
    let (domain, width, height, root) = match geom {
        Geometry::Planar(g) => (
            EncodedDomain::Planar {
                width: g.width(),
                height: g.height(),
            },
            g.width(),
            g.height(),
            coding.roots[0].clone(),
        ),
        Geometry::Sphere(g) => (
            EncodedDomain::Sphere {
                face_side: g.face_side(),
            },
            g.face_side() + 1,
            6 * (g.face_side() + 1),
            Vec::new(),
        ),
    };
    Ok(Encoded {
        domain,
        width,
        height,
        n,
        value_scale_m: coding.value_scale,
        value_offset_m: coding.value_offset,
        steps: coding.steps.clone(),
        root,
        roots: coding.roots.clone(),
        model,
        blobs,
        coverage: coverage(meta)?,
        report: EncodeReport::default(),
    })
}

fn proc_status_kb(field: &str) -> Option<f64> {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(field))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
}

/// The largest peak of a child process this one ran as part of its work (KB).
static CHILD_PEAK_KB: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Records the peak resident memory of a child process that did part of this one's work
/// (the build's bound pass), which [`peak_rss_mb`] then counts.
pub fn note_child_peak_mb(mb: f64) {
    let kb = (mb * 1024.0).ceil() as u64;
    CHILD_PEAK_KB.fetch_max(kb, std::sync::atomic::Ordering::Relaxed);
}

/// Peak resident memory of this process so far, or of a child that did part of its work
/// if that was larger, MB (Linux; 0 elsewhere).
pub fn peak_rss_mb() -> f64 {
    let own = proc_status_kb("VmHWM:").map_or(0.0, |kb| kb / 1024.0);
    let child = CHILD_PEAK_KB.load(std::sync::atomic::Ordering::Relaxed) as f64 / 1024.0;
    own.max(child)
}

/// Samples this process's resident memory every 50 ms on a thread of its own (reading
/// `/proc`, which does not disturb what is measured) and keeps the peak since the last
/// [`RssSampler::take_peak_mb`]. Stops when dropped.
pub struct RssSampler {
    peak_kb: std::sync::Arc<std::sync::atomic::AtomicU64>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl RssSampler {
    /// Starts sampling.
    pub fn start() -> RssSampler {
        use std::sync::atomic::Ordering;
        let peak_kb = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (p, s) = (peak_kb.clone(), stop.clone());
        std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                if let Some(kb) = proc_status_kb("VmRSS:") {
                    p.fetch_max(kb as u64, Ordering::Relaxed);
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
        });
        RssSampler { peak_kb, stop }
    }

    /// The peak since the last call (or the start), MB, including now.
    pub fn take_peak_mb(&self) -> f64 {
        use std::sync::atomic::Ordering;
        let now = proc_status_kb("VmRSS:").unwrap_or(0.0) as u64;
        self.peak_kb.swap(0, Ordering::Relaxed).max(now) as f64 / 1024.0
    }
}

impl Drop for RssSampler {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Physical memory of this machine, bytes (`MemTotal` of `/proc/meminfo`; `None` where
/// there is none).
pub fn memory_total_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kb: u64 = text
        .lines()
        .find(|l| l.starts_with("MemTotal:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()?;
    Some(kb * 1024)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn channel_framing_round_trips_and_rejects_truncation() {
        let a = [7u8; 200];
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
