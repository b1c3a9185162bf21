//! `quincunx build`: source raster -> codec -> repository file, published atomically.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use quincunx_codec::colour::rgb_to_ycocg_r;
use quincunx_codec::encode::{self, CubeGrid, EncodeOptions, Encoded, Grid, RateMode, RdoMode};
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::sphere_raster::SphereFrame;
use quincunx_codec::sphere_raster::SphereGeometry;
use quincunx_codec::stream::{
    self, BlobSink, CubeOptions, CubeSource, IndexSpill, IoError, RowSource, StreamOptions,
    TileStore, io_context,
};
use quincunx_store::{
    Attribute, AttributeKind, ChannelCoding, Metadata, NodataHandling, NodataPolicy,
    RepositoryBuilder,
};
use rayon::prelude::*;
use serde::Serialize;

use crate::input::{self, Georef};
use crate::layout::{self, COLOUR_CHANNELS, Geometry};
use crate::rows;
use crate::{info, mosaic, planet, progress};

/// What the program itself is assumed to keep resident during an out-of-core build.
const PROGRAM_BYTES: usize = 10 << 20;

/// What glibc's per-thread malloc arenas keep of a worker thread's freed buffers, counted
/// in planar colour builds out of core: the bundled Blue Marble at RMS 4 under 32 MB
/// peaked at 30.8-34.1 MB with other work running and at 22.3-26.4 MB with
/// `MALLOC_ARENA_MAX=1`. Six such builds at once peaked at 28.7-33.0 MB counting
/// rayon's threads only, and at 26.0-28.4 MB counting the three threads that measure the
/// error too (2026-12-04). Other builds measured within their budgets.
const ARENA_BYTES_PER_THREAD: usize = 2 << 20;

/// Options of `quincunx build`.
#[derive(Args, Debug, Clone)]
pub struct BuildArgs {
    /// Source: raw grid (`.i16`/`.f32` or its `.json` sidecar), GeoTIFF, 16-bit PNG, SRTM
    /// `.hgt`; with `--colour`, JPEG or PNG imagery. Or a mosaic of georeferenced height
    /// tiles: a directory, a list file (`.txt`/`.list`, one path per line) or a quoted
    /// pattern (`'tiles/N3*.hgt'`); the finer tile wins where tiles overlap, then the first
    /// in order, and what no tile covers is a hole (mosaics are always `--sparse`).
    pub input: PathBuf,
    /// Repository directory to publish.
    #[arg(short, long)]
    pub output: PathBuf,
    /// The input is RGB imagery: build a colour repository (YCoCg-R, 3 channels).
    #[arg(long)]
    pub colour: bool,
    /// Build a planet: the input is a global latitude/longitude grid (node- or
    /// cell-registered, as its georeference says), resampled onto the cube-mapped sphere.
    #[arg(long)]
    pub planet: bool,
    /// Planet radius in metres (default: `--body`).
    #[arg(long, requires = "planet")]
    pub radius_m: Option<f64>,
    /// Named body for the radius: earth, mars (3396 km), moon, venus, mercury.
    #[arg(long, default_value = "earth", requires = "planet")]
    pub body: String,
    /// Sparse repository: large areas without data (whole coverage blocks of nodata) become
    /// holes that are not coded at all, instead of being filled and coded. For sources
    /// that cover part of a planet or raster.
    #[arg(long)]
    pub sparse: bool,
    /// Samples per cube face side (a power-of-two multiple of N; default: closest to the
    /// source resolution).
    #[arg(long, requires = "planet")]
    pub face_side: Option<usize>,
    /// Vertices per diamond side, `2^k + 1` (default 33 for elevation, 65 for colour).
    #[arg(long)]
    pub diamond_size: Option<usize>,
    /// Bit-exact (the default).
    #[arg(long, conflicts_with_all = ["rms_m", "max_error_m"])]
    pub lossless: bool,
    /// RMS error target in metres (colour: in 8-bit levels, per channel).
    #[arg(long, conflicts_with = "max_error_m")]
    pub rms_m: Option<f64>,
    /// Guaranteed absolute error bound in metres (colour: in 8-bit RGB levels).
    #[arg(long)]
    pub max_error_m: Option<f64>,
    /// RMS mode: choose detail indices by rate and distortion (fewer bits at the same
    /// RMS, slower encode). `auto` does where most indices are zero (korea: from about
    /// 3 m RMS up; there 3-4 % fewer bits for about 10-30 % more encode time).
    #[arg(long, value_enum, default_value_t = Rdo::Auto)]
    pub rdo: Rdo,
    /// Worker threads, 1 to 1024 (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Memory budget in MB: a build whose in-memory estimate exceeds it runs out of core
    /// (elevation from a raw grid + sidecar or a tile mosaic, planar or planet; colour
    /// images, planar or planet); other inputs over it are refused before they start.
    #[arg(long)]
    pub memory_budget_mb: Option<u64>,
    /// Replace an existing repository at the output path (atomically). Without it an
    /// existing output is an error before anything is read or encoded.
    #[arg(long)]
    pub overwrite: bool,
    /// Print one JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
    /// Inline small answers: a diamond's answer carries those of its owned children that
    /// are at most this many bytes, instead of one answer each (0: never). See
    /// `docs/blob-format.md`, "Answers".
    #[arg(long, default_value_t = DEFAULT_INLINE_BYTES)]
    pub inline_bytes: u64,
    /// Test hook: stop making progress after storing this many blobs (to be killed).
    #[arg(long, hide = true)]
    pub stall_after_blobs: Option<u64>,
    /// Build shard `K` of `N` (`K` from 0) into a part directory at `--output`, for
    /// `quincunx merge` to publish: planar elevation from a raw grid, lossless or max
    /// error, with `--memory-budget-mb` (docs/building.md, "Sharded builds").
    #[arg(long, value_parser = crate::shard::parse_spec, requires = "memory_budget_mb")]
    pub shard: Option<stream::ShardSpec>,
    /// The error bounds the blobs carry: `encoder` (a sum over levels, what the encoder
    /// knows as it goes) or `measured` (the default: `quincunx bounds` once the
    /// repository is published: each diamond's departure from the full-resolution
    /// decode, 0.35x the triangles at 1 px on korea; a tile at a time, within
    /// `--memory-budget-mb`; docs/building.md "Error bounds").
    #[arg(long, value_enum, default_value = "measured")]
    pub bounds: Bounds,
}

/// `--bounds`: which side-information bounds a build writes.
#[derive(
    ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Bounds {
    /// The encoder's (blob version 5).
    Encoder,
    /// Measured by `quincunx bounds` after publishing (blob version 6).
    #[default]
    Measured,
}

/// `--rdo`: the codec's [`RdoMode`].
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rdo {
    /// Where most indices are zero.
    Auto,
    /// Always (best rate).
    On,
    /// Never (fastest).
    Off,
}

impl Rdo {
    fn mode(self) -> RdoMode {
        match self {
            Rdo::Auto => RdoMode::Auto,
            Rdo::On => RdoMode::On,
            Rdo::Off => RdoMode::Off,
        }
    }

    pub(crate) fn label(self) -> &'static str {
        match self {
            Rdo::Auto => "auto",
            Rdo::On => "on",
            Rdo::Off => "off",
        }
    }

    /// The setting [`Rdo::label`] names (`auto` for anything else).
    pub(crate) fn from_label(label: &str) -> Rdo {
        [Rdo::On, Rdo::Off]
            .into_iter()
            .find(|r| r.label() == label)
            .unwrap_or(Rdo::Auto)
    }
}

/// Default of `--inline-bytes`: an answer a fraction of an HTTP/1.1 head (about 240 bytes
/// down, 90 up) costs more in heads and round trips than in bytes a client may not need
/// (measured in `docs/streaming.md`).
pub const DEFAULT_INLINE_BYTES: u64 = 512;

impl BuildArgs {
    /// The command line's defaults for `input` -> `output`: an elevation repository,
    /// lossless unless a rate is set, not overwriting, text output.
    pub fn new(input: impl Into<PathBuf>, output: impl Into<PathBuf>) -> BuildArgs {
        BuildArgs {
            input: input.into(),
            output: output.into(),
            colour: false,
            planet: false,
            radius_m: None,
            body: "earth".into(),
            sparse: false,
            face_side: None,
            diamond_size: None,
            lossless: false,
            rms_m: None,
            max_error_m: None,
            rdo: Rdo::Auto,
            threads: None,
            memory_budget_mb: None,
            overwrite: false,
            json: false,
            inline_bytes: DEFAULT_INLINE_BYTES,
            stall_after_blobs: None,
            shard: None,
            bounds: Bounds::Measured,
        }
    }
}

/// The `--json` summary.
#[derive(Serialize, Debug)]
pub struct BuildSummary {
    /// Output repository.
    pub output: String,
    /// `"elevation"` or `"colour"`.
    pub kind: String,
    /// Coded samples, no padding: the input's for planar builds, the cube raster's
    /// distinct points (`6 (2S)^2 + 2`) for planets. `bits_per_sample` is per coded sample.
    pub samples: usize,
    /// Samples (pixels for colour) of the input file: `samples` for planar builds, the
    /// latitude/longitude grid's for planets.
    pub source_samples: usize,
    /// `source_samples / seconds / 1e6`: how fast the input is turned into a repository.
    pub source_msamples_per_s: f64,
    /// Wall-clock seconds of the whole build (read, encode, write, publish).
    pub seconds: f64,
    /// `samples / seconds / 1e6`.
    pub msamples_per_s: f64,
    /// Seconds reading the input (for planets and mosaics, resampling it too), before
    /// encoding; 0 out of core, where reading is part of encoding.
    pub read_seconds: f64,
    /// Seconds spent encoding (transform, rate control, entropy coding).
    pub encode_seconds: f64,
    /// Seconds writing the blobs and publishing the repository.
    pub write_seconds: f64,
    /// Peak resident memory of the process, MB.
    pub peak_rss_mb: f64,
    /// Blobs stored.
    pub blob_count: usize,
    /// Bytes of all blobs.
    pub blob_bytes: u64,
    /// Bytes of root grids, models and steps (in the metadata).
    pub side_bytes: usize,
    /// `8 (blob_bytes + side_bytes) / samples`.
    pub bits_per_sample: f64,
    /// Bytes of the repository directory on disk.
    pub repository_bytes: u64,
    /// `repository_bytes / (blob_bytes + side_bytes)`: what the repository file adds (page
    /// framing, index, metadata record).
    pub storage_overhead: f64,
    /// Achieved RMS error over valid samples (elevation: metres; colour: 8-bit levels, RGB).
    pub rms: f64,
    /// Achieved largest absolute error (same units).
    pub max_abs: f64,
    /// Content hash of the published repository.
    pub content_hash: String,
    /// Whether the rate-distortion quantiser chose the indices (`--rdo`).
    pub rdo: bool,
    /// Built out of core (streaming, bounded memory) because the in-memory estimate
    /// exceeded `--memory-budget-mb`.
    pub out_of_core: bool,
    /// Out-of-core planet builds: each phase of the encoder (`stream::CUBE_PHASES`), its
    /// seconds and the peak resident memory sampled during it.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub phases: Vec<PhaseFigure>,
    /// Out-of-core planet builds: bytes of temporary files (tiles and index spill) at
    /// most, beside the output.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scratch_bytes: Option<u64>,
}

/// One phase of an out-of-core planet build.
#[derive(Serialize, Debug, Clone)]
pub struct PhaseFigure {
    /// Its name (`stream::CUBE_PHASES`).
    pub name: &'static str,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Peak resident memory sampled during it (every 50 ms), MB.
    pub peak_rss_mb: f64,
}

pub(crate) fn rate_mode(args: &BuildArgs) -> Result<RateMode> {
    let mode = match (args.rms_m, args.max_error_m) {
        (Some(t), _) => RateMode::RmsM(t),
        (_, Some(e)) => RateMode::MaxErrorM(e),
        _ => RateMode::Lossless,
    };
    match mode {
        RateMode::RmsM(t) | RateMode::MaxErrorM(t) if !(t.is_finite() && t > 0.0) => {
            bail!("tolerance {t} is not a positive number")
        }
        _ => Ok(mode),
    }
}

pub(crate) fn diamond_n(args: &BuildArgs) -> Result<usize> {
    let size = args
        .diamond_size
        .unwrap_or(if args.colour { 65 } else { 33 });
    let n = size.saturating_sub(1);
    if n < 2 || !n.is_power_of_two() || n > 512 {
        bail!("--diamond-size {size} must be 2^k + 1 between 3 and 513");
    }
    Ok(n)
}

/// Bytes per coded sample and channel the in-memory build needs at its peak (values,
/// integers, transform workspace, detail matrices, blobs), with a fifth to spare: measured
/// on korea_srtm3_4097 14.0 (lossless, max error 1 m) and 19.6 (RMS 9 m, whose
/// verification decodes keep the source) and, with the source grid's 8 bytes a sample on
/// top, 21.8-22.1 per cube sample on the ETOPO5 planet.
pub(crate) const BUILD_BYTES_PER_SAMPLE: u64 = 24;

/// Source samples a planet build holds while resampling, in coded samples' worth (8 bytes
/// of the source grid against [`BUILD_BYTES_PER_SAMPLE`]).
const SOURCE_SAMPLES_PER_CODED: usize = 3;

pub(crate) fn in_memory_mb(samples: usize, channels: usize) -> u64 {
    (samples as u64 * BUILD_BYTES_PER_SAMPLE * channels as u64).div_ceil(1 << 20)
}

pub(crate) fn is_raw(path: &Path) -> bool {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    matches!(ext.as_str(), "json" | "i16" | "f32")
}

fn check_budget(args: &BuildArgs, samples: usize, channels: usize) -> Result<()> {
    let Some(budget) = args.memory_budget_mb else {
        return Ok(());
    };
    let need_mb = in_memory_mb(samples, channels);
    if need_mb > budget {
        bail!(
            "this build needs about {need_mb} MB in memory but --memory-budget-mb is {budget}; \
             out-of-core builds cover elevation (planar or planet) from a raw grid + JSON \
             sidecar or a tile mosaic, and planar colour (convert other elevation formats \
             to raw, or raise the budget)"
        );
    }
    Ok(())
}

/// Receives blobs from the streaming encoder straight into the repository.
pub(crate) struct StoreSink<'a> {
    args: &'a BuildArgs,
    builder: &'a mut RepositoryBuilder,
    stored: u64,
    spin: indicatif::ProgressBar,
}

impl<'a> StoreSink<'a> {
    pub(crate) fn new(
        args: &'a BuildArgs,
        builder: &'a mut RepositoryBuilder,
        spin: &indicatif::ProgressBar,
    ) -> Self {
        StoreSink {
            args,
            builder,
            stored: 0,
            spin: spin.clone(),
        }
    }
}

impl BlobSink for StoreSink<'_> {
    fn put(&mut self, level: usize, _index: usize, key: &[u8], blob: &[u8]) -> Result<(), IoError> {
        self.builder.put(level as u32, key, blob)?;
        self.stored += 1;
        if self.stored.is_multiple_of(256) {
            self.spin.set_message(format!("{} blobs", self.stored));
        }
        stall_hook(self.args, self.stored);
        Ok(())
    }
}

/// The out-of-core build: rows are read from the file as the streaming encoder needs
/// them (three passes), so memory holds a few diamond-heights of rows per octave, the
/// per-diamond bookkeeping and the coded blobs, never the raster.
fn build_streaming<S: RowSource>(
    args: &BuildArgs,
    rows: &mut S,
    source_bytes: usize,
    facts: impl Fn(&S) -> StreamFacts,
    (n, mode, budget_mb): (usize, RateMode, u64),
    started: Instant,
) -> Result<BuildSummary> {
    let (width, height) = (rows.width(), rows.height());
    tracing::info!(width, height, budget_mb, "out-of-core build");
    // The budget covers the whole process: what is resident now (program, input
    // header), the per-diamond bookkeeping (geometry, side information and the spill
    // index: korea_srtm3_4097 at a 32 MB budget peaks at 23.8-26.8 MB in all, about 400
    // bytes per diamond once the program and the sample buffers are taken off), the
    // partial database's cache, and the encoder's sample buffers, which get the rest.
    // `tests/cli.rs` checks the measured peak against the budget.
    //
    // The encoder's share must not depend on what happens to be resident at this moment:
    // it fixes the chunking, and with it the nodata fills, so builds that subtracted the
    // measured size were not reproducible (the same command gave different content
    // hashes, and the shards of one sharded build chose different tiles). The program is
    // counted as `PROGRAM_BYTES` (7.8-7.9 MB resident here), and what the input holds
    // (a global grid, a decoded image, a mosaic's tiles) by its size.
    //
    // Checked before the partial database and the spill are created, so a budget that
    // is too small leaves nothing behind.
    let opts = stream_options(args, width * height, (n, mode, budget_mb), source_bytes)?;
    let (meta, description, encode_seconds) = with_builder(args, |builder| {
        let mut builder = builder
            .spill_to_disk()
            .with_context(|| format!("creating {}", args.output.display()))?;
        let encode_started = Instant::now();
        let spin = progress::spinner("streaming");
        spin.set_message(format!("{width} x {height} in {budget_mb} MB"));
        let mut sink = StoreSink::new(args, &mut builder, &spin);
        let mut spill = FileSpill::beside(&args.output)?;
        let enc = stream::encode_streaming_with(rows, opts, &mut sink, &mut spill)
            .context("encoding out of core")?;
        spin.finish_and_clear();
        let encode_seconds = encode_started.elapsed().as_secs_f64();
        tracing::info!(
            peak_buffer_bytes = enc.peak_buffer_bytes,
            peak_rss_mb = layout::peak_rss_mb(),
            "streamed"
        );
        let (meta, description) = publish_streamed(args, builder, enc, facts(rows), (n, mode))?;
        Ok((meta, description, encode_seconds))
    })?;
    let mut summary = summarise(args, &meta, &description, started, (0.0, encode_seconds))?;
    summary.out_of_core = true;
    Ok(summary)
}

/// Describes and publishes a streamed planar elevation build (`quincunx build` out of
/// core, `quincunx merge`).
pub(crate) fn publish_streamed(
    args: &BuildArgs,
    builder: RepositoryBuilder,
    enc: stream::StreamEncoded,
    facts: StreamFacts,
    (n, mode): (usize, RateMode),
) -> Result<(Metadata, Description)> {
    let StreamFacts {
        units,
        georef,
        source_samples,
    } = facts;
    let (width, height) = (enc.width, enc.height);
    let geometry = match &enc.coverage {
        Some(c) => RasterGeometry::with_coverage(width, height, n, c),
        None => RasterGeometry::new(width, height, n),
    }
    .context("raster geometry")?;
    let description = Description {
        coverage: enc.coverage.as_ref().map(|c| c.to_bytes()),
        geometry: Geometry::Planar(geometry),
        radius_m: None,
        kind: AttributeKind::Elevation,
        units,
        samples: enc.report.samples,
        source_samples,
        nodata_count: enc.report.samples - enc.report.valid_samples,
        georef,
        channels: vec![ChannelCoding {
            name: "height".into(),
            value_scale: enc.value_scale_m,
            value_offset: enc.value_offset_m,
            steps: enc.steps.clone(),
            model: enc.model.to_bytes(),
            roots: vec![enc.root.clone()],
            rate: layout::rate_label(mode),
        }],
        rms: enc.report.rms_m,
        max_abs: enc.report.max_abs_m,
        rdo_used: enc.report.rdo,
    };
    let meta = publish(args, builder, &description, n, mode)?;
    Ok((meta, description))
}

/// The out-of-core planet build: [`stream::encode_cube`] from `cube`, the tiles of the
/// cube raster in an unnamed temporary file beside the output, blobs straight into the
/// repository. `source_bytes` is what the source holds itself (the global grid, or a
/// mosaic's decoded tiles).
fn build_cube_streaming<S: CubeSource>(
    args: &BuildArgs,
    cube: &mut S,
    source_bytes: usize,
    facts: impl Fn(&S) -> Source,
    (n, mode, budget_mb, sparse): (usize, RateMode, u64, bool),
    started: Instant,
) -> Result<BuildSummary> {
    let face_side = cube.face_side();
    tracing::info!(face_side, budget_mb, "out-of-core planet build");
    let opts = cube_options(args, face_side, (n, mode, budget_mb, sparse), source_bytes)?;
    let radius = radius_m(args)?;
    let built = with_builder(args, |builder| {
        let mut builder = builder
            .spill_to_disk()
            .with_context(|| format!("creating {}", args.output.display()))?;
        let encode_started = Instant::now();
        let spin = progress::spinner("streaming");
        spin.set_message(format!(
            "6 faces of {face_side} x {face_side} in {budget_mb} MB"
        ));
        let mut sink = StoreSink::new(args, &mut builder, &spin);
        let mut spill = FileSpill::beside(&args.output)?;
        let mut tiles = FileTiles::beside(&args.output)?;
        let sampler = layout::RssSampler::start();
        let mut last = Instant::now();
        let mut phases = Vec::new();
        let mut phase = |name: &'static str| {
            phases.push(PhaseFigure {
                name,
                seconds: last.elapsed().as_secs_f64(),
                peak_rss_mb: sampler.take_peak_mb(),
            });
            last = Instant::now();
        };
        let enc = stream::encode_cube(cube, opts, &mut sink, &mut spill, &mut tiles, &mut phase)
            .context("encoding the planet out of core")?;
        tracing::info!(?phases, "phases");
        let scratch_bytes = enc.tile_store_bytes + spill.len();
        spin.finish_and_clear();
        let encode_seconds = encode_started.elapsed().as_secs_f64();
        tracing::info!(
            peak_buffer_bytes = enc.peak_buffer_bytes,
            tile_store_bytes = enc.tile_store_bytes,
            peak_rss_mb = layout::peak_rss_mb(),
            "streamed"
        );
        let (meta, description) = publish_cube(args, builder, enc, facts(cube), (radius, n, mode))?;
        Ok((meta, description, encode_seconds, phases, scratch_bytes))
    })?;
    let (meta, description, encode_seconds, phases, scratch_bytes) = built;
    let mut summary = summarise(args, &meta, &description, started, (0.0, encode_seconds))?;
    summary.out_of_core = true;
    summary.phases = phases;
    summary.scratch_bytes = Some(scratch_bytes);
    Ok(summary)
}

/// The streaming encoder's options for a planar elevation build of `samples` out of core
/// (one process, or a shard: the same budget, so the same chunking).
pub(crate) fn stream_options(
    args: &BuildArgs,
    samples: usize,
    (n, mode, budget_mb): (usize, RateMode, u64),
    source_bytes: usize,
) -> Result<StreamOptions> {
    Ok(StreamOptions {
        n,
        mode,
        memory_budget_bytes: encoder_budget(budget_mb, planar_diamonds(samples, n), source_bytes)?,
        sparse: args.sparse || mosaic::is_mosaic(&args.input),
        rdo: args.rdo.mode(),
    })
}

/// The out-of-core planet encoder's options for a planet of face side `face_side` (one
/// process, or a shard: the same budget, so the same tiles).
pub(crate) fn cube_options(
    args: &BuildArgs,
    face_side: usize,
    (n, mode, budget_mb, sparse): (usize, RateMode, u64, bool),
    source_bytes: usize,
) -> Result<CubeOptions> {
    let samples = 6 * (face_side + 1) * (face_side + 1);
    Ok(CubeOptions {
        n,
        mode,
        memory_budget_bytes: encoder_budget(
            budget_mb,
            cube_diamonds(samples, n, mode),
            source_bytes,
        )?,
        sparse,
        rdo: args.rdo.mode(),
        keep_decoded: false,
    })
}

/// The cube frame of face side `face_side`, or why it cannot be one.
fn cube_frame(face_side: usize, n: usize) -> Result<SphereFrame> {
    SphereFrame::new(face_side, n, None)
        .with_context(|| format!("--face-side {face_side} must be N x 2^k with N = {n}"))
}

/// `--face-side`, or the default for a mosaic's finest tiles.
fn mosaic_face_side(args: &BuildArgs, mosaic: &mosaic::Mosaic, n: usize) -> usize {
    args.face_side
        .unwrap_or_else(|| planet::default_face_side(mosaic.finest_spacing(), n))
}

/// What the metadata records of a mosaic's tiles once read (`assembled`).
fn mosaic_source(mosaic: &mosaic::Mosaic, a: mosaic::Assembled, georef: Option<Georef>) -> Source {
    Source {
        units: a.units,
        source_samples: mosaic.source_samples,
        nodata_count: a.nodata_count,
        georef,
    }
}

/// Publishes a planet's elevation encoded out of core (by one process, or by a sharded
/// build's merge).
pub(crate) fn publish_cube(
    args: &BuildArgs,
    builder: RepositoryBuilder,
    enc: stream::CubeEncoded,
    source: Source,
    (radius, n, mode): (f64, usize, RateMode),
) -> Result<(Metadata, Description)> {
    let description = elevation(source, enc.into_encoded(Vec::new()), Some(radius), mode)?.desc;
    let meta = publish(args, builder, &description, n, mode)?;
    Ok((meta, description))
}

/// A planet's elevation source as cube rows (a global grid, or a mosaic) for a sharded
/// build: runs `f` with it, the bytes it holds itself and whether the build is sparse
/// (mosaics always are); `f`'s result and what the metadata records of the source (once
/// `f` has read it all).
pub(crate) fn with_cube_source<T>(
    args: &BuildArgs,
    n: usize,
    f: impl FnOnce(&mut dyn CubeSource, usize, bool) -> Result<T>,
) -> Result<(T, Source)> {
    if mosaic::is_mosaic(&args.input) {
        let mosaic = mosaic::Mosaic::open(&args.input)?;
        mosaic.check_planet()?;
        let frame = cube_frame(mosaic_face_side(args, &mosaic, n), n)?;
        let mut cube = mosaic.cube_rows(&frame)?;
        let held = cube.held_bytes();
        let out = f(&mut cube, held, true)?;
        return Ok((out, mosaic_source(&mosaic, cube.assembled(), None)));
    }
    let raster = input::read_heights(&args.input)
        .with_context(|| format!("reading {}", args.input.display()))?;
    let g = &raster.grid;
    let face_side = planet_face_side(args, raster.georef.as_ref(), g.width, g.height, n)?;
    let mut cube = planet::EquirectRows::new(&raster, &cube_frame(face_side, n)?)?;
    let out = f(&mut cube, grid_bytes(&raster.grid), args.sparse)?;
    Ok((out, Source::of(&raster)))
}

/// What a global grid read into memory holds (its heights, 8 bytes a sample).
fn grid_bytes(grid: &Grid) -> usize {
    grid.values_m.len() * 8
}

/// An unnamed temporary file in the output's directory (on the disk the build writes to;
/// gone when the build ends, however it ends).
fn temp_beside(output: &Path) -> Result<std::fs::File> {
    let dir = output
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    tempfile::tempfile_in(dir)
        .with_context(|| format!("creating a temporary file in {}", dir.display()))
}

/// The out-of-core planet encoder's tiles: an unnamed temporary file beside the output
/// (gone when the build ends, however it ends).
pub(crate) struct FileTiles {
    file: std::fs::File,
    bytes: Vec<u8>,
}

impl FileTiles {
    pub(crate) fn beside(output: &Path) -> Result<FileTiles> {
        Ok(FileTiles {
            file: temp_beside(output)?,
            bytes: Vec::new(),
        })
    }
}

impl TileStore for FileTiles {
    fn read(&mut self, offset: u64, out: &mut [i32]) -> Result<(), IoError> {
        use std::os::unix::fs::FileExt;
        self.bytes.resize(out.len() * 4, 0);
        self.file
            .read_exact_at(&mut self.bytes, offset * 4)
            .map_err(|e| io_context("reading the planet's tiles", e.into()))?;
        for (x, b) in out.iter_mut().zip(self.bytes.chunks_exact(4)) {
            *x = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        }
        Ok(())
    }

    fn write(&mut self, offset: u64, data: &[i32]) -> Result<(), IoError> {
        use std::os::unix::fs::FileExt;
        self.bytes.clear();
        self.bytes.extend(data.iter().flat_map(|x| x.to_le_bytes()));
        self.file
            .write_all_at(&self.bytes, offset * 4)
            .map_err(|e| io_context("writing the planet's tiles", e.into()))
    }
}

/// One colour channel (YCoCg-R) of an image, as rows.
struct ChannelRows<'a> {
    image: &'a input::RgbImage,
    channel: usize,
}

impl RowSource for ChannelRows<'_> {
    fn width(&self) -> usize {
        self.image.width
    }
    fn height(&self) -> usize {
        self.image.height
    }
    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError> {
        let w = self.image.width;
        let pixels = self
            .image
            .pixels
            .get(first * w..(first + count) * w)
            .ok_or("rows past the image")?;
        for (o, &[r, g, b]) in out.iter_mut().zip(pixels) {
            let (y, co, cg) = rgb_to_ycocg_r(r as i32, g as i32, b as i32);
            *o = [y, co, cg][self.channel] as f64;
        }
        Ok(())
    }
    fn quantum_m(&self) -> Option<f64> {
        Some(1.0)
    }
}

/// Keeps one channel's blobs by diamond until the three are framed together.
#[derive(Default)]
struct ChannelBlobs {
    blobs: std::collections::HashMap<(usize, usize), Vec<u8>>,
}

impl BlobSink for ChannelBlobs {
    fn put(&mut self, level: usize, index: usize, _key: &[u8], blob: &[u8]) -> Result<(), IoError> {
        self.blobs.insert((level, index), blob.to_vec());
        Ok(())
    }
}

/// The out-of-core colour build (planar): each YCoCg-R channel streams from the decoded
/// image (3 bytes a pixel, against about 72 in memory), its blobs are kept (the coded
/// size) until the three are framed per diamond, and the RGB error is measured on the
/// three channels decoded a band of rows at a time in step.
fn build_colour_streaming(
    args: &BuildArgs,
    image: &input::RgbImage,
    (n, mode, budget_mb): (usize, RateMode, u64),
    started: Instant,
) -> Result<BuildSummary> {
    let (width, height) = (image.width, image.height);
    let channel_mode = colour_channel_mode(mode);
    let opts = StreamOptions {
        n,
        mode: channel_mode,
        // The decoded image stays in memory, and the allocator's per-thread arenas keep
        // what this build's worker threads free (see `ARENA_BYTES_PER_THREAD`): rayon's,
        // and the three that decode the channels in step to measure the error.
        memory_budget_bytes: encoder_budget(
            budget_mb,
            planar_diamonds(width * height, n),
            width * height * 3
                + (rayon::current_num_threads() + COLOUR_CHANNELS.len()) * ARENA_BYTES_PER_THREAD,
        )?,
        sparse: args.sparse,
        rdo: args.rdo.mode(),
    };
    tracing::info!(width, height, budget_mb, "out-of-core colour build");
    let encode_started = Instant::now();
    let pb = progress::bar(3, "encoding", "channels");
    let mut channels = Vec::new();
    for (c, name) in COLOUR_CHANNELS.iter().enumerate() {
        let mut rows = ChannelRows { image, channel: c };
        let mut sink = ChannelBlobs::default();
        let mut spill = FileSpill::beside(&args.output)?;
        let enc = stream::encode_streaming_with(&mut rows, opts, &mut sink, &mut spill)
            .with_context(|| format!("encoding colour channel {name} out of core"))?;
        channels.push((name.to_string(), enc, sink));
        pb.inc(1);
    }
    pb.finish_and_clear();
    let geom = match &channels[0].1.coverage {
        Some(c) => RasterGeometry::with_coverage(width, height, n, c),
        None => RasterGeometry::new(width, height, n),
    }
    .context("raster geometry")?;
    let (rms, max_abs) = streamed_rgb_error(image, &geom, &channels)?;
    let encode_seconds = encode_started.elapsed().as_secs_f64();
    let description = Description {
        coverage: channels[0].1.coverage.as_ref().map(|c| c.to_bytes()),
        geometry: Geometry::Planar(geom.clone()),
        radius_m: None,
        kind: AttributeKind::Colour,
        units: "srgb8".into(),
        samples: width * height,
        source_samples: width * height,
        nodata_count: 0,
        georef: image.georef.clone(),
        channels: channels
            .iter()
            .map(|(name, e, _)| ChannelCoding {
                name: name.clone(),
                value_scale: e.value_scale_m,
                value_offset: e.value_offset_m,
                steps: e.steps.clone(),
                model: e.model.to_bytes(),
                roots: vec![e.root.clone()],
                rate: layout::rate_label(channel_mode),
            })
            .collect(),
        rms,
        max_abs,
        rdo_used: channels.iter().any(|(_, e, _)| e.report.rdo),
    };
    let meta = with_builder(args, |mut builder| {
        let mut stored = 0u64;
        for level in 0..geom.detail_levels() {
            for index in 0..geom.level(level).len() {
                let parts: Vec<Option<&[u8]>> = channels
                    .iter()
                    .map(|(_, _, b)| b.blobs.get(&(level, index)).map(Vec::as_slice))
                    .collect();
                if let Some(blob) = layout::frame_channels(&parts) {
                    builder.put(level as u32, &geom.level(level)[index].key, &blob)?;
                    stored += 1;
                    stall_hook(args, stored);
                }
            }
        }
        publish(args, builder, &description, n, mode)
    })?;
    let read_seconds = encode_started.duration_since(started).as_secs_f64();
    let mut summary = summarise(
        args,
        &meta,
        &description,
        started,
        (read_seconds, encode_seconds),
    )?;
    summary.out_of_core = true;
    Ok(summary)
}

/// RMS and largest RGB error of streamed colour channels: the three decoded a band of
/// rows at a time in step, compared in pixel order as [`rgb_error`] does.
fn streamed_rgb_error(
    image: &input::RgbImage,
    geom: &RasterGeometry,
    channels: &[(String, stream::StreamEncoded, ChannelBlobs)],
) -> Result<(f64, f64)> {
    let fetchers: Vec<Box<rows::BlobOf<'_>>> = channels
        .iter()
        .map(|(_, _, blobs)| {
            Box::new(move |l: usize, i: usize| Ok(blobs.blobs.get(&(l, i)).cloned()))
                as Box<rows::BlobOf<'_>>
        })
        .collect();
    let steps: Vec<rows::StepChannel<'_>> = channels
        .iter()
        .zip(&fetchers)
        .map(|((_, enc, _), blob)| rows::StepChannel {
            decode: stream::RowDecode {
                geom,
                root: &enc.root,
                steps: &enc.steps,
                model: &enc.model,
            },
            blob: &**blob,
            scale: enc.value_scale_m,
            offset: enc.value_offset_m,
        })
        .collect();
    rows::rgb_error_in_step(&steps, image, None).context("decoding colour for measurement")
}

/// Detail and index matrices between passes (the RMS rate control's attempts, the planet
/// encoder's details), in three unnamed temporary files beside the output (gone when the build ends, however it ends).
pub(crate) struct FileSpill {
    files: [std::fs::File; 3],
    lens: [u64; 3],
}

impl FileSpill {
    pub(crate) fn beside(output: &Path) -> Result<FileSpill> {
        Ok(FileSpill {
            files: [
                temp_beside(output)?,
                temp_beside(output)?,
                temp_beside(output)?,
            ],
            lens: [0; 3],
        })
    }

    fn slot(&self, slot: usize) -> Result<&std::fs::File, String> {
        self.files
            .get(slot)
            .ok_or_else(|| format!("no spill slot {slot}"))
    }
}

impl IndexSpill for FileSpill {
    fn clear(&mut self, slot: usize) -> Result<(), IoError> {
        self.slot(slot)?.set_len(0)?;
        self.lens[slot] = 0;
        Ok(())
    }

    fn append(&mut self, slot: usize, bytes: &[u8]) -> Result<u64, IoError> {
        use std::os::unix::fs::FileExt;
        let at = self.lens[slot.min(2)];
        self.slot(slot)?
            .write_all_at(bytes, at)
            .map_err(|e| io_context("writing the index spill", e.into()))?;
        self.lens[slot] = at + bytes.len() as u64;
        Ok(at)
    }

    fn read(&self, slot: usize, offset: u64, len: usize) -> Result<Vec<u8>, IoError> {
        use std::os::unix::fs::FileExt;
        let mut buf = vec![0; len];
        self.slot(slot)?
            .read_exact_at(&mut buf, offset)
            .map_err(|e| io_context("reading the index spill", e.into()))?;
        Ok(buf)
    }

    fn held(&self) -> usize {
        0
    }
}

impl FileSpill {
    /// Bytes in the spill's files now.
    fn len(&self) -> u64 {
        self.lens.iter().sum()
    }
}

/// What the metadata says of an out-of-core build's input (asked once it has been read).
pub(crate) struct StreamFacts {
    pub(crate) units: String,
    pub(crate) georef: Option<Georef>,
    pub(crate) source_samples: usize,
}

/// What `--memory-budget-mb` leaves the streaming encoder's sample buffers once the
/// program, the per-diamond bookkeeping (`diamonds` at `per_diamond` bytes: the geometry,
/// side information and spill index), the blob spill's buffers and `source_bytes` the
/// input holds itself are counted (see `build_streaming`).
pub(crate) fn encoder_budget(
    budget_mb: u64,
    (diamonds, per_diamond): (usize, usize),
    source_bytes: usize,
) -> Result<usize> {
    let reserve = PROGRAM_BYTES + diamonds * per_diamond + (3 << 20) + source_bytes;
    let budget = (budget_mb as usize) << 20;
    if budget <= reserve {
        bail!(
            "out-of-core build: --memory-budget-mb {budget_mb} leaves nothing for sample buffers: the program, \
             the geometry of {diamonds} diamonds, the blob spill and the input's own buffers \
             ({} MB) already take about {} MB",
            source_bytes.div_ceil(1 << 20),
            reserve.div_ceil(1 << 20)
        );
    }
    Ok(budget - reserve)
}

/// Diamonds of a planar raster of `samples` (a bound) and the bookkeeping bytes each
/// costs the streaming encoder (korea_srtm3_4097 at a 32 MB budget: about 400).
pub(crate) fn planar_diamonds(samples: usize, n: usize) -> (usize, usize) {
    (2 * samples / (n * n) + 64, 400)
}

/// Diamonds of a planet of `samples` cube-raster entries (the levels hold about
/// `samples / N^2` together) and the bookkeeping bytes each costs the out-of-core planet
/// encoder: its geometry's slot (about 220 bytes, measured at face side 8192) and its
/// side information and spill index (about 60); in RMS mode also two attempts' spill
/// indexes and measures (about 130).
pub(crate) fn cube_diamonds(samples: usize, n: usize, mode: RateMode) -> (usize, usize) {
    let rms = if matches!(mode, RateMode::RmsM(_)) {
        130
    } else {
        0
    };
    (samples / (n * n) * 21 / 20 + 64, 280 + rms)
}

/// Runs `quincunx build`.
pub fn run(args: &BuildArgs) -> Result<()> {
    let mut builder = rayon::ThreadPoolBuilder::new();
    if let Some(t) = args.threads {
        // Before any thread starts (`check_args` repeats it for library callers).
        if !(1..=MAX_THREADS).contains(&t) {
            bail!(
                "--threads {t} is out of range: give 1 to {MAX_THREADS} (or leave it out for all cores)"
            );
        }
        builder = builder.num_threads(t);
    }
    let pool = builder.build().context("starting worker threads")?;
    if let Some(spec) = args.shard {
        return pool.install(|| crate::shard::build_part(args, spec));
    }
    let summary = pool.install(|| build(args))?;
    if args.json {
        outln!("{}", serde_json::to_string(&summary)?);
    } else {
        outln!(
            "built {} ({}): {} samples in {:.2} s ({:.2} M samples/s), {:.4} bits/sample, \
             rms {:.4}, max {:.4}, {} blobs, {:.2}x on disk, peak {:.0} MB",
            summary.output,
            summary.kind,
            summary.samples,
            summary.seconds,
            summary.msamples_per_s,
            summary.bits_per_sample,
            summary.rms,
            summary.max_abs,
            summary.blob_count,
            summary.storage_overhead,
            summary.peak_rss_mb
        );
    }
    Ok(())
}

/// What was encoded, ready to store: the description and each channel's codec output.
struct Coded {
    desc: Description,
    encoded: Vec<Encoded>,
}

/// Largest `--threads`: more threads than this only cost memory and start-up time (a
/// request for 100 000 spent 50 s spawning threads before failing).
pub const MAX_THREADS: usize = 1024;

/// Checks every option and the output path before anything is read, encoded or created,
/// so that a refused build leaves nothing behind (no `.partial`, no `.spill`).
fn check_args(args: &BuildArgs) -> Result<(RateMode, usize)> {
    if let Some(t) = args.threads
        && !(1..=MAX_THREADS).contains(&t)
    {
        bail!(
            "--threads {t} is out of range: give 1 to {MAX_THREADS} (or leave it out for all cores)"
        );
    }
    let mode = rate_mode(args)?;
    let n = diamond_n(args)?;
    if args.planet {
        radius_m(args)?;
    }
    if u32::try_from(args.inline_bytes).is_err() {
        bail!(
            "--inline-bytes {} is out of range: give 0 to {}",
            args.inline_bytes,
            u32::MAX
        );
    }
    check_output(args)?;
    Ok((mode, n))
}

/// The output must not exist unless `--overwrite` is given, and then it must be a
/// repository to replace, never a file or a directory holding anything else.
pub(crate) fn check_output(args: &BuildArgs) -> Result<()> {
    match RepositoryBuilder::check_destination(&args.output, args.overwrite) {
        Err(quincunx_store::StoreError::Exists(p)) => bail!(
            "{} already exists (pass --overwrite to replace it)",
            p.display()
        ),
        Err(quincunx_store::StoreError::Occupied(p)) => bail!(
            "{} exists and is not a repository directory: not replacing it",
            p.display()
        ),
        other => other.map_err(anyhow::Error::from),
    }
}

/// Creates the builder for the output, runs `f` with it, and removes what the failed
/// build wrote (`<output>.partial`, `<output>.spill`) if `f` fails. A builder that cannot
/// be created (another build holds the partial database) is left alone.
pub(crate) fn with_builder<T>(
    args: &BuildArgs,
    f: impl FnOnce(RepositoryBuilder) -> Result<T>,
) -> Result<T> {
    let builder = RepositoryBuilder::create(&args.output)
        .with_context(|| format!("creating {}", args.output.display()))?;
    let result = f(builder);
    if result.is_err() {
        // The builder is gone (consumed or dropped by `f`): its lock is released.
        for path in [
            quincunx_store::partial_path(&args.output),
            quincunx_store::spill_path(&args.output),
        ] {
            let removed = if path.is_dir() {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            };
            if let Err(e) = removed
                && e.kind() != std::io::ErrorKind::NotFound
            {
                tracing::warn!(path = %path.display(), error = %e, "could not remove a failed build's files");
            }
        }
    }
    result
}

fn build(args: &BuildArgs) -> Result<BuildSummary> {
    let started = Instant::now();
    let (mode, n) = check_args(args)?;
    if let Some(budget_mb) = args.memory_budget_mb
        && !args.colour
        && !args.planet
        && is_raw(&args.input)
    {
        let mut rows = input::RawRows::open(&args.input)
            .with_context(|| format!("reading {}", args.input.display()))?;
        let samples = rows.raw().width * rows.raw().height;
        if in_memory_mb(samples, 1) > budget_mb {
            let facts = |r: &input::RawRows| StreamFacts {
                units: r.raw().units.clone(),
                georef: r.raw().georef.clone(),
                source_samples: samples,
            };
            let held = 0;
            return build_streaming(args, &mut rows, held, facts, (n, mode, budget_mb), started);
        }
    }
    if mosaic::is_mosaic(&args.input) {
        return build_mosaic(args, n, mode, started);
    }
    let spin = progress::spinner("reading");
    spin.set_message(args.input.display().to_string());
    let encode_started;
    let coded = if args.colour {
        let image = input::read_rgb(&args.input)
            .with_context(|| format!("reading {}", args.input.display()))?;
        spin.finish_and_clear();
        if image.width * image.height == 0 {
            bail!("the image is empty");
        }
        let (pixels, domain) = if args.planet {
            let face_side =
                planet_face_side(args, image.georef.as_ref(), image.width, image.height, n)?;
            let frame = cube_frame(face_side, n)?;
            if let Some(budget_mb) = args.memory_budget_mb
                && in_memory_mb(frame.distinct_points(), 3) > budget_mb
            {
                encode_started = Instant::now();
                let mut coded = encode_colour_cube(args, &image, &frame, mode, budget_mb)?;
                coded.desc.radius_m = Some(radius_m(args)?);
                coded.desc.source_samples = image.width * image.height;
                let mut summary = store(args, &coded, n, mode, started, encode_started)?;
                summary.out_of_core = true;
                return Ok(summary);
            }
            let geom = planet_geometry(args, image.georef.as_ref(), image.width, image.height, n)?;
            (
                planet::resample_rgb(&image, &geom)?,
                ColourDomain::Sphere(geom),
            )
        } else {
            if let Some(budget_mb) = args.memory_budget_mb
                && in_memory_mb(image.width * image.height, 3) > budget_mb
            {
                return build_colour_streaming(args, &image, (n, mode, budget_mb), started);
            }
            (
                image.pixels,
                ColourDomain::Planar(image.width, image.height),
            )
        };
        encode_started = Instant::now();
        let mut coded = encode_colour(
            &pixels,
            &domain,
            n,
            mode,
            image.georef,
            args.sparse,
            args.rdo.mode(),
        )?;
        if args.planet {
            coded.desc.radius_m = Some(radius_m(args)?);
        }
        coded.desc.source_samples = image.width * image.height;
        coded
    } else {
        let raster = input::read_heights(&args.input)
            .with_context(|| format!("reading {}", args.input.display()))?;
        spin.finish_and_clear();
        tracing::info!(
            format = ?raster.format,
            width = raster.grid.width,
            height = raster.grid.height,
            nodata = raster.nodata_count,
            "read input"
        );
        if args.planet {
            let g = &raster.grid;
            let face_side = planet_face_side(args, raster.georef.as_ref(), g.width, g.height, n)?;
            let frame = cube_frame(face_side, n)?;
            let source = g.width * g.height / SOURCE_SAMPLES_PER_CODED;
            if let Some(budget_mb) = args.memory_budget_mb
                && in_memory_mb(frame.distinct_points() + source, 1) > budget_mb
            {
                let mut cube = planet::EquirectRows::new(&raster, &frame)?;
                let facts = |_: &planet::EquirectRows| Source::of(&raster);
                return build_cube_streaming(
                    args,
                    &mut cube,
                    grid_bytes(&raster.grid),
                    facts,
                    (n, mode, budget_mb, args.sparse),
                    started,
                );
            }
            check_budget(args, frame.distinct_points() + source, 1)?;
            let geom = SphereGeometry::new(face_side, n)?;
            let spin = progress::spinner("resampling");
            let resample_started = Instant::now();
            let cube = planet::resample_heights(&raster, &geom)?;
            spin.finish_and_clear();
            tracing::info!(
                seconds = resample_started.elapsed().as_secs_f64(),
                face_side = geom.face_side(),
                "resampled onto the cube"
            );
            let source = Source::of(&raster);
            drop(raster); // the cube holds what is coded
            encode_started = Instant::now();
            encode_planet(
                source,
                cube,
                n,
                mode,
                radius_m(args)?,
                args.sparse,
                args.rdo.mode(),
            )?
        } else {
            check_budget(args, raster.grid.width * raster.grid.height, 1)?;
            encode_started = Instant::now();
            let source = Source::of(&raster);
            encode_heights(raster.grid, source, n, mode, args.sparse, args.rdo.mode())?
        }
    };
    store(args, &coded, n, mode, started, encode_started)
}

/// Writes what was encoded, publishes it, and summarises the build.
fn store(
    args: &BuildArgs,
    coded: &Coded,
    n: usize,
    mode: RateMode,
    started: Instant,
    encode_started: Instant,
) -> Result<BuildSummary> {
    let encode_seconds = encode_started.elapsed().as_secs_f64();
    tracing::info!(
        seconds = encode_seconds,
        since_start = started.elapsed().as_secs_f64(),
        "encoded"
    );
    let write_started = Instant::now();
    let meta = with_builder(args, |mut builder| {
        write_blobs(args, &mut builder, coded)?;
        tracing::info!(
            seconds = write_started.elapsed().as_secs_f64(),
            "blobs written"
        );
        let publish_started = Instant::now();
        let meta = publish(args, builder, &coded.desc, n, mode)?;
        tracing::info!(
            seconds = publish_started.elapsed().as_secs_f64(),
            "published"
        );
        Ok(meta)
    })?;
    let read_seconds = encode_started.duration_since(started).as_secs_f64();
    summarise(
        args,
        &meta,
        &coded.desc,
        started,
        (read_seconds, encode_seconds),
    )
}

/// Builds from a tile mosaic (`mosaic.rs`): always sparse, so that what no tile covers is
/// not coded.
fn build_mosaic(
    args: &BuildArgs,
    n: usize,
    mode: RateMode,
    started: Instant,
) -> Result<BuildSummary> {
    if args.colour {
        bail!(
            "{}: colour mosaics are not supported; give one georeferenced image with --colour",
            args.input.display()
        );
    }
    let mosaic = mosaic::Mosaic::open(&args.input)?;
    tracing::info!(
        tiles = mosaic.tiles.len(),
        samples = mosaic.source_samples,
        "read mosaic headers"
    );
    let encode_started;
    let coded = if args.planet {
        mosaic.check_planet()?;
        let face_side = mosaic_face_side(args, &mosaic, n);
        // Before the geometry, whose tables grow with the face side too.
        let samples = 6 * (face_side as u64 + 1).pow(2);
        if let Some(budget_mb) = args.memory_budget_mb
            && in_memory_mb(samples as usize, 1) > budget_mb
        {
            let mut cube = mosaic.cube_rows(&cube_frame(face_side, n)?)?;
            let held = cube.held_bytes();
            let facts = |c: &mosaic::MosaicCube<'_>| mosaic_source(&mosaic, c.assembled(), None);
            let how = (n, mode, budget_mb, true);
            return build_cube_streaming(args, &mut cube, held, facts, how, started);
        }
        mosaic::check_memory(samples, &format!("choose a --face-side below {face_side}"))?;
        check_budget(args, samples as usize, 1)?;
        let geom = SphereGeometry::new(face_side, n)
            .with_context(|| format!("--face-side {face_side} must be N x 2^k with N = {n}"))?;
        let resample_started = Instant::now();
        let (cube, assembled) = mosaic.to_cube(&geom)?;
        tracing::info!(
            seconds = resample_started.elapsed().as_secs_f64(),
            face_side,
            "resampled the mosaic onto the cube"
        );
        let source = mosaic_source(&mosaic, assembled, None);
        encode_started = Instant::now();
        encode_planet(
            source,
            cube,
            n,
            mode,
            radius_m(args)?,
            true,
            args.rdo.mode(),
        )?
    } else {
        if let Some(budget_mb) = args.memory_budget_mb {
            let (mut rows, georef) = mosaic.rows()?;
            let samples = rows.width() * rows.height();
            if in_memory_mb(samples, 1) > budget_mb {
                let held = rows.held_bytes();
                let facts = |r: &mosaic::MosaicRows<'_>| StreamFacts {
                    units: r.assembled().units,
                    georef: Some(georef.clone()),
                    source_samples: mosaic.source_samples,
                };
                return build_streaming(
                    args,
                    &mut rows,
                    held,
                    facts,
                    (n, mode, budget_mb),
                    started,
                );
            }
        }
        let (grid, georef, assembled) = mosaic.to_grid()?;
        check_budget(args, grid.width * grid.height, 1)?;
        let source = mosaic_source(&mosaic, assembled, Some(georef));
        encode_started = Instant::now();
        encode_heights(grid, source, n, mode, true, args.rdo.mode())?
    };
    store(args, &coded, n, mode, started, encode_started)
}

/// What the metadata and summary say about the coded data (both build paths).
pub(crate) struct Description {
    /// Sparse builds: the coverage bitmap's bytes.
    coverage: Option<Vec<u8>>,
    geometry: Geometry,
    radius_m: Option<f64>,
    kind: AttributeKind,
    units: String,
    samples: usize,
    /// Samples of the input file.
    source_samples: usize,
    nodata_count: usize,
    georef: Option<Georef>,
    channels: Vec<ChannelCoding>,
    rms: f64,
    max_abs: f64,
    /// The rate-distortion quantiser ran (any channel).
    rdo_used: bool,
}

pub(crate) fn summarise(
    args: &BuildArgs,
    meta: &Metadata,
    d: &Description,
    started: Instant,
    (read_seconds, encode_seconds): (f64, f64),
) -> Result<BuildSummary> {
    let seconds = started.elapsed().as_secs_f64();
    let blob_bytes: u64 = meta.level_stats.iter().map(|s| s.bytes).sum();
    let blob_count = meta.level_stats.iter().map(|s| s.blobs).sum::<u64>() as usize;
    let side_bytes = info::side_bytes(meta) as usize;
    let repository_bytes = quincunx_store::dir_size(&args.output)?;
    let coded_bytes = blob_bytes + side_bytes as u64;
    Ok(BuildSummary {
        output: args.output.display().to_string(),
        kind: d.kind.name().into(),
        samples: d.samples,
        source_samples: d.source_samples,
        source_msamples_per_s: d.source_samples as f64 / seconds / 1e6,
        seconds,
        msamples_per_s: d.samples as f64 / seconds / 1e6,
        read_seconds,
        encode_seconds,
        write_seconds: (seconds - read_seconds - encode_seconds).max(0.0),
        peak_rss_mb: layout::peak_rss_mb(),
        blob_count,
        blob_bytes,
        side_bytes,
        bits_per_sample: 8.0 * coded_bytes as f64 / d.samples as f64,
        repository_bytes,
        storage_overhead: repository_bytes as f64 / coded_bytes.max(1) as f64,
        rms: d.rms,
        max_abs: d.max_abs,
        content_hash: meta.content_hash.clone(),
        rdo: d.rdo_used,
        out_of_core: false,
        phases: Vec::new(),
        scratch_bytes: None,
    })
}

fn encode_heights(
    grid: Grid,
    source: Source,
    n: usize,
    mode: RateMode,
    sparse: bool,
    rdo: RdoMode,
) -> Result<Coded> {
    let spin = progress::spinner("encoding");
    spin.set_message(format!("{} x {}", grid.width, grid.height));
    let enc = encode::encode_owned(
        grid,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo,
        },
    )
    .context("encoding the height grid")?;
    spin.finish_and_clear();
    elevation(source, enc, None, mode)
}

/// What the metadata records of an elevation build's source.
#[derive(Serialize, serde::Deserialize, Debug, Clone, PartialEq)]
pub(crate) struct Source {
    pub(crate) units: String,
    /// Samples read (all tiles' for a mosaic).
    pub(crate) source_samples: usize,
    /// Nodata samples the encoder was given.
    pub(crate) nodata_count: usize,
    pub(crate) georef: Option<Georef>,
}

impl Source {
    fn of(raster: &input::HeightRaster) -> Source {
        Source {
            units: raster.units.clone(),
            source_samples: raster.grid.width * raster.grid.height,
            nodata_count: raster.nodata_count,
            georef: raster.georef.clone(),
        }
    }
}

/// An elevation result: one `height` channel.
fn elevation(source: Source, enc: Encoded, radius_m: Option<f64>, mode: RateMode) -> Result<Coded> {
    Ok(Coded {
        desc: Description {
            coverage: enc.coverage.as_ref().map(|c| c.to_bytes()),
            geometry: Geometry::of(&enc)?,
            radius_m,
            kind: AttributeKind::Elevation,
            units: source.units,
            samples: enc.report.samples,
            source_samples: source.source_samples,
            nodata_count: source.nodata_count,
            georef: source.georef,
            channels: vec![layout::channel_coding("height", &enc, mode)],
            rms: enc.report.rms_m,
            max_abs: enc.report.max_abs_m,
            rdo_used: enc.report.rdo,
        },
        encoded: vec![enc],
    })
}

pub(crate) fn radius_m(args: &BuildArgs) -> Result<f64> {
    let r = match args.radius_m {
        Some(r) => r,
        None => planet::body_radius_m(&args.body)
            .with_context(|| format!("unknown body {:?}; pass --radius-m", args.body))?,
    };
    if !(r.is_finite() && r > 0.0) {
        bail!("radius {r} m is not a positive number");
    }
    Ok(r)
}

fn planet_geometry(
    args: &BuildArgs,
    georef: Option<&Georef>,
    width: usize,
    height: usize,
    n: usize,
) -> Result<SphereGeometry> {
    let face_side = planet_face_side(args, georef, width, height, n)?;
    SphereGeometry::new(face_side, n)
        .with_context(|| format!("--face-side {face_side} must be N x 2^k with N = {n}"))
}

/// `--face-side`, or the default for a global grid's spacing.
fn planet_face_side(
    args: &BuildArgs,
    georef: Option<&Georef>,
    width: usize,
    height: usize,
    n: usize,
) -> Result<usize> {
    let georef = georef.context(
        "planet builds need a georeferenced latitude/longitude grid (sidecar `georef`, GeoTIFF tags)",
    )?;
    let spacing = planet::Equirect::new(width, height, &[], georef)?.spacing_deg();
    Ok(args
        .face_side
        .unwrap_or_else(|| planet::default_face_side(spacing, n)))
}

fn encode_planet(
    source: Source,
    cube: CubeGrid,
    n: usize,
    mode: RateMode,
    radius_m: f64,
    sparse: bool,
    rdo: RdoMode,
) -> Result<Coded> {
    let spin = progress::spinner("encoding");
    spin.set_message(format!("6 faces of {0} x {0}", cube.face_side));
    let enc = encode::encode_sphere_owned(
        cube,
        EncodeOptions {
            n,
            mode,
            sparse,
            rdo,
        },
    )
    .context("encoding the planet")?;
    spin.finish_and_clear();
    elevation(source, enc, Some(radius_m), mode)
}

/// Where colour pixels live.
pub enum ColourDomain {
    /// A `width x height` image.
    Planar(usize, usize),
    /// A cube raster.
    Sphere(SphereGeometry),
}

/// Per-channel error bound that keeps every RGB component within `e` levels after the
/// inverse YCoCg-R (worst case `|dR| <= 2d + 2` for channel errors `<= d`).
pub fn colour_channel_bound(e: f64) -> Option<f64> {
    let d = ((e - 2.0) / 2.0).floor();
    (d >= 1.0).then_some(d)
}

fn encode_colour(
    pixels: &[[u8; 3]],
    domain: &ColourDomain,
    n: usize,
    mode: RateMode,
    georef: Option<Georef>,
    sparse: bool,
    rdo: RdoMode,
) -> Result<Coded> {
    let mut planes = [
        Vec::with_capacity(pixels.len()),
        Vec::with_capacity(pixels.len()),
        Vec::with_capacity(pixels.len()),
    ];
    for &[r, g, b] in pixels {
        let (y, co, cg) = rgb_to_ycocg_r(r as i32, g as i32, b as i32);
        planes[0].push(y as f64);
        planes[1].push(co as f64);
        planes[2].push(cg as f64);
    }
    let channel_mode = colour_channel_mode(mode);
    let pb = progress::bar(3, "encoding", "channels");
    let mut channels = Vec::new();
    for (name, values) in COLOUR_CHANNELS.iter().zip(planes) {
        let opts = EncodeOptions {
            n,
            mode: channel_mode,
            sparse,
            rdo,
        };
        let enc = match domain {
            ColourDomain::Planar(width, height) => encode::encode(
                &Grid {
                    width: *width,
                    height: *height,
                    values_m: values,
                    quantum_m: Some(1.0),
                },
                opts,
            ),
            ColourDomain::Sphere(geom) => encode::encode_sphere_owned(
                CubeGrid {
                    face_side: geom.face_side(),
                    values_m: values,
                    quantum_m: Some(1.0),
                },
                opts,
            ),
        }
        .with_context(|| format!("encoding colour channel {name}"))?;
        channels.push((name.to_string(), enc));
        pb.inc(1);
    }
    pb.finish_and_clear();
    // Each decode runs on one thread: the three channels in parallel.
    let decoded = channels
        .par_iter()
        .map(|(_, e)| encode::decode(e).map(|v| v.into_iter().map(|x| x.round() as i32).collect()))
        .collect::<Result<Vec<Vec<i32>>, _>>()
        .context("decoding colour for measurement")?;
    let errors = rgb_error(pixels, &decoded[0], &decoded[1], &decoded[2]);
    colour_coded(channels, channel_mode, georef, errors)
}

/// The colour channels' per-channel rate mode for a build's `mode`.
fn colour_channel_mode(mode: RateMode) -> RateMode {
    match mode {
        RateMode::MaxErrorM(e) => {
            colour_channel_bound(e).map_or(RateMode::Lossless, RateMode::MaxErrorM)
        }
        m => m,
    }
}

/// A colour repository's description and channels, with its measured RGB errors.
fn colour_coded(
    channels: Vec<(String, Encoded)>,
    channel_mode: RateMode,
    georef: Option<Georef>,
    (rms, max_abs): (f64, f64),
) -> Result<Coded> {
    Ok(Coded {
        desc: Description {
            coverage: channels[0].1.coverage.as_ref().map(|c| c.to_bytes()),
            geometry: Geometry::of(&channels[0].1)?,
            radius_m: None,
            kind: AttributeKind::Colour,
            units: "srgb8".into(),
            samples: channels[0].1.report.samples,
            source_samples: channels[0].1.report.samples,
            nodata_count: 0,
            georef,
            channels: channels
                .iter()
                .map(|(name, e)| layout::channel_coding(name, e, channel_mode))
                .collect(),
            rms,
            max_abs,
            rdo_used: channels.iter().any(|(_, e)| e.report.rdo),
        },
        encoded: channels.into_iter().map(|(_, e)| e).collect(),
    })
}

/// The out-of-core colour planet build: each YCoCg-R channel streams from the image
/// (`planet::EquirectRgbRows`, the in-memory resampling bit for bit) through the planet
/// encoder out of core, which leaves its decoded raster in its tiles; the channels'
/// blobs are kept (their coded size) until they are framed, and the RGB error is measured
/// on the three decoded rasters read in step with the pixels, a band of rows at a time,
/// as in memory.
fn encode_colour_cube(
    args: &BuildArgs,
    image: &input::RgbImage,
    frame: &SphereFrame,
    mode: RateMode,
    budget_mb: u64,
) -> Result<Coded> {
    let (face_side, n) = (frame.face_side(), frame.n());
    let channel_mode = colour_channel_mode(mode);
    let samples = 6 * (face_side + 1) * (face_side + 1);
    let opts = CubeOptions {
        n,
        mode: channel_mode,
        // The decoded image stays in memory.
        memory_budget_bytes: encoder_budget(
            budget_mb,
            cube_diamonds(samples, n, channel_mode),
            image.width * image.height * 3,
        )?,
        sparse: args.sparse,
        rdo: args.rdo.mode(),
        keep_decoded: true,
    };
    tracing::info!(face_side, budget_mb, "out-of-core colour planet build");
    let mut rows = planet::EquirectRgbRows::new(image, frame)?;
    let pb = progress::bar(3, "encoding", "channels");
    let mut channels = Vec::new();
    for (c, name) in COLOUR_CHANNELS.iter().enumerate() {
        rows.channel = c;
        let mut sink = ChannelBlobs::default();
        let mut spill = FileSpill::beside(&args.output)?;
        let mut tiles = FileTiles::beside(&args.output)?;
        let enc = stream::encode_cube(
            &mut rows,
            opts,
            &mut sink,
            &mut spill,
            &mut tiles,
            &mut |_| {},
        )
        .with_context(|| format!("encoding colour channel {name} out of core"))?;
        channels.push((name.to_string(), enc, sink, tiles));
        pb.inc(1);
    }
    pb.finish_and_clear();
    // The RGB error, a band of rows at a time in cube-raster order.
    let w = face_side + 1;
    let band = 64.min(w);
    let mut error = rows::RgbError::default();
    let mut pixels = vec![[0u8; 3]; band * w];
    let mut ints = vec![0i32; band * w];
    let mut decoded = vec![vec![0i32; band * w]; 3];
    for face in 0..6 {
        for first in (0..w).step_by(band) {
            let count = band.min(w - first);
            let len = count * w;
            rows.rgb_rows(face, (first, count), &mut pixels[..len])
                .map_err(|e| anyhow::anyhow!(e))?;
            for ((_, enc, _, tiles), out) in channels.iter_mut().zip(&mut decoded) {
                let layout = enc
                    .decoded
                    .context("the planet encoder left no decoded raster")?;
                layout
                    .read_rows(tiles, (face, first, count), &mut ints[..len])
                    .map_err(|e| anyhow::anyhow!(e))
                    .context("decoding colour for measurement")?;
                // As `encode::decode` and the in-memory measurement round them.
                for (o, &v) in out.iter_mut().zip(&ints[..len]) {
                    *o = (enc.value_offset_m + v as f64 * enc.value_scale_m).round() as i32;
                }
            }
            error.add(
                &pixels[..len],
                &decoded[0][..len],
                &decoded[1][..len],
                &decoded[2][..len],
            );
        }
    }
    let geom = match &channels[0].1.coverage {
        Some(c) => SphereGeometry::with_coverage(face_side, n, c)?,
        None => SphereGeometry::new(face_side, n)?,
    };
    let encoded = channels
        .into_iter()
        .map(|(name, enc, mut sink, _)| {
            let blobs = (0..geom.detail_levels())
                .map(|l| {
                    (0..geom.level(l).len())
                        .map(|i| sink.blobs.remove(&(l, i)))
                        .collect()
                })
                .collect();
            (name, enc.into_encoded(blobs))
        })
        .collect();
    colour_coded(encoded, channel_mode, image.georef.clone(), error.finish())
}

/// RMS and largest absolute error over all RGB components of decoded YCoCg-R planes
/// (clamped to 0..=255) against the source image.
pub fn rgb_error(pixels: &[[u8; 3]], y: &[i32], co: &[i32], cg: &[i32]) -> (f64, f64) {
    let mut error = rows::RgbError::default();
    error.add(pixels, y, co, cg);
    error.finish()
}

fn write_blobs(args: &BuildArgs, builder: &mut RepositoryBuilder, coded: &Coded) -> Result<()> {
    let geom = &coded.desc.geometry;
    let total: usize = (0..geom.detail_levels()).map(|l| geom.level_len(l)).sum();
    let pb = progress::bar(total as u64, "writing", "diamonds");
    let mut stored = 0u64;
    for level in 0..geom.detail_levels() {
        for index in 0..geom.level_len(level) {
            let parts: Vec<Option<&[u8]>> = coded
                .encoded
                .iter()
                .map(|e| e.blobs[level][index].as_deref())
                .collect();
            if let Some(blob) = layout::frame_channels(&parts) {
                builder.put(level as u32, geom.key(level, index), &blob)?;
                stored += 1;
                stall_hook(args, stored);
            }
            pb.inc(1);
        }
    }
    pb.finish_and_clear();
    Ok(())
}

/// Test hook (`--stall-after-blobs`): stop making progress so a test can kill the build
/// mid-way.
pub(crate) fn stall_hook(args: &BuildArgs, stored: u64) {
    if args.stall_after_blobs == Some(stored) {
        tracing::warn!("stalling after {stored} blobs (test hook)");
        loop {
            std::thread::sleep(std::time::Duration::from_secs(3600));
        }
    }
}

pub(crate) fn publish(
    args: &BuildArgs,
    builder: RepositoryBuilder,
    d: &Description,
    n: usize,
    mode: RateMode,
) -> Result<Metadata> {
    let geom = &d.geometry;
    let meta = Metadata {
        format_version: quincunx_store::FORMAT_VERSION,
        complete: false,
        content_hash: String::new(),
        domain: geom.domain(),
        m: geom.m(),
        n: n as u32,
        levels: geom.detail_levels() as u32,
        attribute: Attribute {
            kind: d.kind,
            units: d.units.clone(),
        },
        extent: geom.extent(),
        nodata: NodataPolicy {
            source_count: d.nodata_count as u64,
            handling: if d.nodata_count > 0 {
                NodataHandling::Filled
            } else {
                NodataHandling::None
            },
        },
        georef: d.georef.as_ref().map(Georef::stored),
        radius_m: d.radius_m,
        channels: d.channels.clone(),
        build: serde_json::json!({
            "tool": concat!("quincunx ", env!("CARGO_PKG_VERSION")),
            "input": file_name(&args.input),
            "rate": layout::rate_label(mode),
            "diamond_size": n + 1,
            "achieved_rms": d.rms,
            "achieved_max_abs": d.max_abs,
            "rdo": args.rdo.label(),
            "rdo_used": d.rdo_used,
        }),
        level_stats: Vec::new(),
        coverage: d.coverage.clone(),
        inline_max_bytes: u32::try_from(args.inline_bytes).ok().filter(|&t| t > 0),
        static_export: false,
    };
    let meta = builder
        .publish(meta, args.overwrite)
        .with_context(|| format!("publishing {}", args.output.display()))?;
    // The encoder's side information bounds by a sum over levels; the published file's
    // decode measures each diamond's own (`bounds`).
    if args.bounds == Bounds::Encoder {
        return Ok(meta);
    }
    let tile = crate::bounds::tile_for_budget(args.memory_budget_mb);
    let Some((meta, t, child_peak_mb)) = crate::bounds::tighten_for_build(&args.output, tile)
        .with_context(|| format!("measuring the bounds of {}", args.output.display()))?
    else {
        return Ok(meta);
    };
    crate::layout::note_child_peak_mb(child_peak_mb);
    tracing::info!(
        diamonds = t.diamonds,
        classes = t.classes,
        lowered = t.lowered,
        raised = t.raised,
        added = t.added,
        zero_detail_blobs = t.zero_detail_blobs,
        profiled = t.profiled,
        profile_classes = t.profile_classes,
        median_ratio = t.median_ratio,
        bytes_before = t.bytes.0,
        bytes_after = t.bytes.1,
        seconds = t.seconds,
        "bounds measured"
    );
    Ok(meta)
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}
