//! `quincunx verify`: every blob checks and decodes; optionally, the full-resolution
//! reconstruction is measured against the source.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_codec::blob::{self, BlobContext};
use quincunx_codec::entropy::CodecModel;
use quincunx_store::Repository;
use serde::Serialize;

use crate::layout::Geometry;
use crate::{build, info, input, layout, planet, progress, rows};
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::stream::{RowDecode, RowSource};

/// Options of `quincunx verify`.
#[derive(Args, Debug, Clone)]
pub struct VerifyArgs {
    /// Repository directory.
    pub repo: PathBuf,
    /// The source the repository was built from (same formats as `build`).
    #[arg(long)]
    pub source: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Decode (and compare with a raw-grid source) a band of rows at a time instead of
    /// the whole raster in memory (planar repositories; chosen on its own when the
    /// whole raster would not fit in this machine's memory).
    #[arg(long)]
    pub stream: bool,
}

/// The `--json` report.
#[derive(Serialize, Debug, Default)]
pub struct VerifyReport {
    /// Samples the repository covers.
    pub samples: u64,
    /// `8 (blob bytes + roots/models/steps) / samples`.
    pub bits_per_sample: f64,
    /// Blobs checked (checksum + full entropy decode of every channel).
    pub blobs_checked: u64,
    /// Blobs that failed, or keys that belong to no diamond of the repository.
    pub blob_errors: u64,
    /// The content hash recomputed from the stored bytes matches the metadata.
    pub content_hash_ok: bool,
    /// Full-resolution decode (entropy decoding + synthesis, one thread), M samples/s.
    pub decode_msamples_per_s: f64,
    /// With `--source`: RMS error over valid samples (metres; colour: 8-bit RGB levels).
    /// For a planet, against the source resampled onto the cube (the codec's error).
    pub rms_m: Option<f64>,
    /// With `--source`: largest absolute error (same units).
    pub max_abs_m: Option<f64>,
    /// Sphere repositories: cube edge/corner samples whose face copies disagree.
    pub seam_mismatches: Option<u64>,
    /// SHA-256 (hex) of the full-resolution reconstruction in the canonical layout of
    /// `docs/blob-format.md` ("Reconstruction hash"): what `web-demo/tools/decode-repo.mjs`
    /// prints for the same repository's export.
    pub decoded_sha256: String,
}

/// The reconstruction hash of `docs/blob-format.md`: every point in the domain's sample
/// order, its channels' decoded integers one after another, each `i32` little-endian.
#[derive(Default)]
pub struct ReconstructionHash {
    sha: sha2::Sha256,
    bytes: Vec<u8>,
}

impl ReconstructionHash {
    /// Adds a run of points: `channels[c][k]` is channel `c` of the run's point `k`.
    pub fn add<V: AsRef<[i32]>>(&mut self, channels: &[V]) {
        use sha2::Digest;
        let len = channels.first().map_or(0, |c| c.as_ref().len());
        self.bytes.clear();
        self.bytes.reserve(len * 4 * channels.len());
        for k in 0..len {
            for c in channels {
                self.bytes.extend_from_slice(&c.as_ref()[k].to_le_bytes());
            }
        }
        self.sha.update(&self.bytes);
    }

    /// The hash, lower-case hex.
    pub fn finish(self) -> String {
        use sha2::Digest;
        self.sha
            .finalize()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }
}

/// Runs `quincunx verify`; fails (exit 1) when any check fails.
pub fn run(args: &VerifyArgs) -> Result<()> {
    let report = verify(args)?;
    if args.json {
        outln!("{}", serde_json::to_string(&report)?);
    } else {
        outln!(
            "{} blobs checked, {} errors, content hash {}; {:.4} bits/sample over {} samples; \
             decode {:.1} M samples/s{}",
            report.blobs_checked,
            report.blob_errors,
            if report.content_hash_ok {
                "ok"
            } else {
                "MISMATCH"
            },
            report.bits_per_sample,
            report.samples,
            report.decode_msamples_per_s,
            match (report.rms_m, report.max_abs_m) {
                (Some(r), Some(m)) => format!("; rms {r:.4}, max {m:.4}"),
                _ => String::new(),
            }
        );
    }
    if report.blob_errors > 0 || !report.content_hash_ok {
        bail!("verification failed");
    }
    Ok(())
}

/// Every channel's stored entropy model.
fn models(meta: &quincunx_store::Metadata) -> Result<Vec<CodecModel>> {
    meta.channels
        .iter()
        .map(|c| CodecModel::from_bytes(&c.model))
        .collect::<Result<Vec<_>, _>>()
        .context("stored entropy model")
}

fn check_blobs(repo: &Repository, geom: &Geometry) -> Result<(u64, u64)> {
    let meta = repo.metadata();
    let models = models(meta)?;
    let mut index = HashMap::new();
    for level in 0..geom.detail_levels() {
        for i in 0..geom.level_len(level) {
            index.insert(geom.key(level, i).to_vec(), (level, i));
        }
    }
    let pb = progress::bar(repo.blob_count() as u64, "checking", "blobs");
    let (mut checked, mut errors) = (0u64, 0u64);
    let mut q = Vec::new();
    for kv in repo.blobs() {
        let (key, bytes) = kv?;
        checked += 1;
        pb.inc(1);
        let Some(&(level, i)) = index.get(&key) else {
            tracing::error!(key = ?key, "stored key belongs to no diamond of the repository");
            errors += 1;
            continue;
        };
        let ctx = geom.blob_context(level, i);
        let parts = match layout::split_channels(&bytes, models.len()) {
            Ok(p) => p,
            Err(e) => {
                tracing::error!(level, index = i, "{e:#}");
                errors += 1;
                continue;
            }
        };
        for (c, part) in parts.iter().enumerate() {
            let ctx = BlobContext {
                step: meta.channels[c].steps.get(level).copied().unwrap_or(256),
                ..ctx
            };
            if let Some(part) = part
                && let Err(e) = blob::decode_into(part, &ctx, &models[c], &mut q)
            {
                tracing::error!(level, index = i, channel = c, "blob does not decode: {e}");
                errors += 1;
            }
        }
    }
    pb.finish_and_clear();
    Ok((checked, errors))
}

/// A repository decoded at full resolution: per channel, integers and their scale/offset.
pub struct Decoded {
    /// The geometry.
    pub geom: Geometry,
    /// Per channel: decoded integers in the domain's sample order.
    pub values: Vec<Vec<i32>>,
    /// Per channel: `(scale, offset)`.
    pub scales: Vec<(f64, f64)>,
    /// Seconds spent decoding (one thread).
    pub seconds: f64,
}

impl Decoded {
    /// Channel `c` in its units (metres; colour channels rounded to integers).
    pub fn channel(&self, c: usize) -> Vec<f64> {
        let (scale, offset) = self.scales[c];
        self.values[c]
            .iter()
            .map(|&v| offset + v as f64 * scale)
            .collect()
    }
}

/// Decodes every channel of a repository at full resolution.
pub fn decode_repository(repo: &Repository) -> Result<Decoded> {
    let meta = repo.metadata();
    let geom = Geometry::from_metadata(meta)?;
    let channels = (0..meta.channels.len())
        .map(|c| layout::load_channel(repo, &geom, c))
        .collect::<Result<Vec<_>>>()?;
    let spin = progress::spinner("decoding");
    let started = Instant::now();
    let values = channels
        .iter()
        .map(|e| geom.decode(e))
        .collect::<Result<Vec<_>>>()?;
    let seconds = started.elapsed().as_secs_f64();
    spin.finish_and_clear();
    Ok(Decoded {
        geom,
        values,
        scales: channels
            .iter()
            .map(|e| (e.value_scale_m, e.value_offset_m))
            .collect(),
        seconds,
    })
}

fn verify(args: &VerifyArgs) -> Result<VerifyReport> {
    let repo =
        Repository::open(&args.repo).with_context(|| format!("opening {}", args.repo.display()))?;
    let meta = repo.metadata().clone();
    let samples = info::samples(&meta);
    let blob_bytes: u64 = meta.level_stats.iter().map(|s| s.bytes).sum();
    let mut report = VerifyReport {
        samples,
        bits_per_sample: 8.0 * (blob_bytes + info::side_bytes(&meta)) as f64 / samples as f64,
        ..VerifyReport::default()
    };
    let geom = Geometry::from_metadata(&meta)?;
    (report.blobs_checked, report.blob_errors) = check_blobs(&repo, &geom)?;
    report.content_hash_ok = repo.compute_content_hash()? == meta.content_hash;
    if let Geometry::Planar(g) = &geom {
        let whole = samples.saturating_mul(16 * meta.channels.len() as u64);
        let fits = crate::layout::memory_total_bytes().is_none_or(|total| whole < total / 2);
        if args.stream || !fits {
            verify_rows(args, &repo, g, &mut report)?;
            return Ok(report);
        }
    }
    let decoded = decode_repository(&repo)?;
    report.decode_msamples_per_s =
        (samples * decoded.values.len() as u64) as f64 / decoded.seconds / 1e6;
    let mut hash = ReconstructionHash::default();
    hash.add(&decoded.values);
    report.decoded_sha256 = hash.finish();
    if let Geometry::Sphere(g) = &decoded.geom {
        report.seam_mismatches = Some(
            decoded
                .values
                .iter()
                .map(|v| planet::seam_mismatches(g, v))
                .sum(),
        );
    }

    let Some(source) = &args.source else {
        return Ok(report);
    };
    let (rms, max) = if meta.attribute.kind == quincunx_store::AttributeKind::Colour {
        let image =
            input::read_rgb(source).with_context(|| format!("reading {}", source.display()))?;
        let pixels = match &decoded.geom {
            Geometry::Sphere(g) => planet::resample_rgb(&image, g)?,
            Geometry::Planar(_) => {
                if [image.width as u64, image.height as u64] != meta.extent {
                    bail!(
                        "source is {} x {}, repository {:?}",
                        image.width,
                        image.height,
                        meta.extent
                    );
                }
                image.pixels
            }
        };
        let planes: Vec<Vec<i32>> = (0..3)
            .map(|c| {
                decoded
                    .channel(c)
                    .iter()
                    .map(|v| v.round() as i32)
                    .collect()
            })
            .collect();
        if planes.len() != 3 {
            bail!("a colour repository needs 3 channels");
        }
        build::rgb_error(&pixels, &planes[0], &planes[1], &planes[2])
    } else {
        let raster =
            input::read_heights(source).with_context(|| format!("reading {}", source.display()))?;
        let reference = match &decoded.geom {
            Geometry::Sphere(g) => planet::resample_heights(&raster, g)?.values_m,
            Geometry::Planar(_) => {
                let g = &raster.grid;
                if [g.width as u64, g.height as u64] != meta.extent {
                    bail!(
                        "source is {} x {}, repository {:?}",
                        g.width,
                        g.height,
                        meta.extent
                    );
                }
                raster.grid.values_m
            }
        };
        let (mut sum, mut max, mut count) = (0.0, 0.0f64, 0usize);
        for (d, v) in decoded.channel(0).into_iter().zip(reference) {
            if v.is_finite() {
                let e = (d - v).abs();
                sum += e * e;
                max = max.max(e);
                count += 1;
            }
        }
        ((sum / count.max(1) as f64).sqrt(), max)
    };
    report.rms_m = Some(rms);
    report.max_abs_m = Some(max);
    Ok(report)
}

/// The full-resolution part of `verify` a band of rows at a time (planar): every channel
/// decoded in step, compared row by row with the source (a raw grid read by rows; other
/// formats are read whole). The figures are the in-memory path's, summed in the same
/// order; the decode speed counts the comparison too.
fn verify_rows(
    args: &VerifyArgs,
    repo: &Repository,
    geom: &RasterGeometry,
    report: &mut VerifyReport,
) -> Result<()> {
    let meta = repo.metadata();
    let count = meta.channels.len();
    let models = models(meta)?;
    let n = meta.n as usize;
    for (c, coding) in meta.channels.iter().enumerate() {
        if coding.roots.len() != 1 || coding.roots[0].len() != (n + 1) * (n + 1) {
            bail!(
                "channel {c} needs 1 root grid of {} values",
                (n + 1) * (n + 1)
            );
        }
    }
    let fetchers: Vec<Box<rows::BlobOf<'_>>> = (0..count)
        .map(|c| {
            Box::new(move |l: usize, i: usize| {
                let Some(bytes) = repo.get(&geom.level(l)[i].key).map_err(|e| e.to_string())?
                else {
                    return Ok(None);
                };
                let parts = layout::split_channels(&bytes, count).map_err(|e| e.to_string())?;
                Ok(parts.get(c).copied().flatten().map(<[u8]>::to_vec))
            }) as Box<rows::BlobOf<'_>>
        })
        .collect();
    let channels: Vec<rows::StepChannel<'_>> = meta
        .channels
        .iter()
        .zip(&models)
        .zip(&fetchers)
        .map(|((coding, model), blob)| rows::StepChannel {
            decode: RowDecode {
                geom,
                root: &coding.roots[0],
                steps: &coding.steps,
                model,
            },
            blob: &**blob,
            scale: coding.value_scale,
            offset: coding.value_offset,
        })
        .collect();
    let h = geom.height();
    let check_size = |sw: usize, sh: usize| -> Result<()> {
        if [sw as u64, sh as u64] != meta.extent {
            bail!("source is {sw} x {sh}, repository {:?}", meta.extent);
        }
        Ok(())
    };
    let colour = meta.attribute.kind == quincunx_store::AttributeKind::Colour;
    let started = Instant::now();
    let mut hash = ReconstructionHash::default();
    match &args.source {
        None => rows::decode_in_step(&channels, h, &mut |_, ints| {
            hash.add(ints);
            Ok(())
        })?,
        Some(source) if colour => {
            let image =
                input::read_rgb(source).with_context(|| format!("reading {}", source.display()))?;
            check_size(image.width, image.height)?;
            let (rms, max) = rows::rgb_error_in_step(&channels, &image, Some(&mut hash))?;
            (report.rms_m, report.max_abs_m) = (Some(rms), Some(max));
        }
        Some(source) => {
            let mut reference = SourceRows::open(source)?;
            check_size(reference.width, reference.height)?;
            let (mut sum, mut max, mut valid) = (0.0, 0.0f64, 0usize);
            rows::decode_in_step(&channels, h, &mut |r, ints| {
                hash.add(ints);
                for (&d, &v) in channels[0].units(&ints[0]).iter().zip(reference.row(r)?) {
                    if v.is_finite() {
                        let e = (d - v).abs();
                        sum += e * e;
                        max = max.max(e);
                        valid += 1;
                    }
                }
                Ok(())
            })?;
            report.rms_m = Some((sum / valid.max(1) as f64).sqrt());
            report.max_abs_m = Some(max);
        }
    }
    report.decode_msamples_per_s =
        (report.samples * count as u64) as f64 / started.elapsed().as_secs_f64() / 1e6;
    report.decoded_sha256 = hash.finish();
    Ok(())
}

/// A height source read by rows: a raw grid in bands of 64 rows, other formats whole.
struct SourceRows {
    width: usize,
    height: usize,
    raw: Option<input::RawRows>,
    /// Rows `first ..` of the source.
    rows: Vec<f64>,
    first: usize,
}

impl SourceRows {
    fn open(path: &std::path::Path) -> Result<SourceRows> {
        let context = || format!("reading {}", path.display());
        if build::is_raw(path) {
            let raw = input::RawRows::open(path).with_context(context)?;
            let (width, height) = (raw.width(), raw.height());
            return Ok(SourceRows {
                width,
                height,
                raw: Some(raw),
                rows: Vec::new(),
                first: 0,
            });
        }
        let raster = input::read_heights(path).with_context(context)?;
        Ok(SourceRows {
            width: raster.grid.width,
            height: raster.grid.height,
            raw: None,
            rows: raster.grid.values_m,
            first: 0,
        })
    }

    fn row(&mut self, r: usize) -> Result<&[f64]> {
        let w = self.width;
        if let Some(raw) = &mut self.raw
            && !(self.first..self.first + self.rows.len() / w.max(1)).contains(&r)
        {
            let count = 64.min(self.height - r);
            self.rows.resize(count * w, 0.0);
            raw.read_rows(r, count, &mut self.rows)
                .map_err(|e| anyhow::anyhow!(e))?;
            self.first = r;
        }
        let k = r - self.first;
        self.rows
            .get(k * w..(k + 1) * w)
            .ok_or_else(|| anyhow::anyhow!("source row {r} missing"))
    }
}
