//! Sharded builds: `quincunx build --shard K/N` writes a part directory, `quincunx merge`
//! publishes one repository from all `N` parts, the same bytes (and content hash) as one
//! `quincunx build` with the same options (docs/building.md, "Sharded builds").
//!
//! A part directory holds `part.bin` (what the merge needs besides the details:
//! [`stream::ShardPart`]) and `details.bin` (each owned diamond's details: level u32,
//! index u64, then `N^2` zigzag LEB128 integers, little-endian). A shard writes into
//! `<part>.partial` and renames it when complete, so a killed shard leaves no part, and
//! its rerun starts afresh.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_codec::encode::RateMode;
use quincunx_codec::stream::{self, CubeMerge, IoError, Merge, RowSource, ShardPart, ShardSpec};
use serde::{Deserialize, Serialize};

use crate::build::{self, BuildArgs, FileSpill, FileTiles, Rdo, StreamFacts};
use crate::input::{self, Georef};
use crate::{layout, mosaic, progress};

/// A planar source a shard reads: a raw grid's rows, or a mosaic's.
trait PlanarRows {
    fn rows(&mut self) -> &mut dyn RowSource;
    /// What the source holds itself (a mosaic's decoded tiles).
    fn held_bytes(&self) -> usize;
    /// What the metadata records of it, once read.
    fn facts(&self) -> build::Source;
}

impl PlanarRows for input::RawRows {
    fn rows(&mut self) -> &mut dyn RowSource {
        self
    }
    fn held_bytes(&self) -> usize {
        0
    }
    fn facts(&self) -> build::Source {
        let raw = self.raw();
        build::Source {
            units: raw.units.clone(),
            source_samples: raw.width * raw.height,
            nodata_count: 0,
            georef: raw.georef.clone(),
        }
    }
}

impl PlanarRows for (mosaic::MosaicRows<'_>, Georef, usize) {
    fn rows(&mut self) -> &mut dyn RowSource {
        &mut self.0
    }
    fn held_bytes(&self) -> usize {
        self.0.held_bytes()
    }
    fn facts(&self) -> build::Source {
        let a = self.0.assembled();
        build::Source {
            units: a.units,
            source_samples: self.2,
            nodata_count: a.nodata_count,
            georef: Some(self.1.clone()),
        }
    }
}

/// Parses `--shard K/N`.
pub fn parse_spec(s: &str) -> Result<ShardSpec, String> {
    let (k, n) = s
        .split_once('/')
        .ok_or_else(|| format!("--shard {s}: give K/N, e.g. 0/4"))?;
    let k: usize = k
        .trim()
        .parse()
        .map_err(|_| format!("--shard {s}: K is not a number"))?;
    let n: usize = n
        .trim()
        .parse()
        .map_err(|_| format!("--shard {s}: N is not a number"))?;
    if n == 0 || k >= n {
        return Err(format!(
            "--shard {s}: K runs from 0 to N - 1 and N from 1 (K/N = {k}/{n})"
        ));
    }
    Ok(ShardSpec { index: k, count: n })
}

/// What the merge needs to publish what `quincunx build` would: the parts carry it, and
/// parts whose descriptions differ are from different builds.
#[derive(Serialize, Deserialize, Debug, PartialEq)]
struct BuildFacts {
    input: String,
    lossless: bool,
    max_error_m: Option<f64>,
    diamond_size: Option<usize>,
    rdo: String,
    inline_bytes: u64,
    memory_budget_mb: u64,
    source: build::Source,
    /// Planets: the radius, `--face-side` and `--sparse` (a global grid's).
    radius_m: Option<f64>,
    face_side: Option<usize>,
    sparse: bool,
    /// `--bounds` (parts from before it: the encoder's, which they were built with; not
    /// the build's default, which is now measured).
    #[serde(default = "encoder_bounds")]
    bounds: build::Bounds,
}

/// What a part written before `BuildFacts::bounds` was built with.
fn encoder_bounds() -> build::Bounds {
    build::Bounds::Encoder
}

/// The `--json` summary of a shard.
#[derive(Serialize, Debug)]
pub struct ShardSummary {
    /// Part directory.
    pub output: String,
    /// This shard (from 0) and the shard count.
    pub shard: usize,
    /// Shards in all.
    pub shards: usize,
    /// The split octave (the merge analyses the octaves from it on).
    pub split: usize,
    /// Rows the shard owns.
    pub band_rows: usize,
    /// Rows it read and analysed (band and halo; planets: rows of which it holds a tile).
    pub window_rows: usize,
    /// Rows it turned into integers (planets: of the cube raster's `6 (2S + 1)`).
    pub integer_rows: usize,
    /// Diamonds analysed.
    pub analysed: usize,
    /// Diamonds owned.
    pub owned: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Peak resident memory, MB.
    pub peak_rss_mb: f64,
    /// Bytes of the part directory.
    pub part_bytes: u64,
}

const PART_FILE: &str = "part.bin";
const DETAILS_FILE: &str = "details.bin";

fn partial_dir(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".partial");
    PathBuf::from(s)
}

/// Runs `quincunx build --shard K/N`.
pub fn build_part(args: &BuildArgs, spec: ShardSpec) -> Result<()> {
    let started = Instant::now();
    let mode = build::rate_mode(args)?;
    let n = build::diamond_n(args)?;
    if args.colour {
        bail!("--shard builds elevation; colour builds in one process");
    }
    let planar_mosaic = !args.planet && mosaic::is_mosaic(&args.input);
    if !args.planet && !planar_mosaic && !build::is_raw(&args.input) {
        bail!(
            "--shard builds planar elevation from a raw grid (+ JSON sidecar) or a mosaic, and \
             planets from a global grid or a mosaic; other planar inputs build in one process"
        );
    }
    if matches!(mode, RateMode::RmsM(_)) {
        bail!(
            "--shard takes --lossless or --max-error-m: the RMS rate control searches over the \
             whole analysis"
        );
    }
    let Some(budget_mb) = args.memory_budget_mb else {
        bail!("--shard needs --memory-budget-mb (the merge's result equals one build with it)");
    };
    let radius_m = if args.planet {
        Some(build::radius_m(args)?)
    } else {
        None
    };
    let out = &args.output;
    if out.exists() && !args.overwrite {
        bail!(
            "{} already exists (pass --overwrite to replace it)",
            out.display()
        );
    }
    if out.exists() && !out.join(PART_FILE).is_file() {
        bail!(
            "{} exists and is not a shard part: not replacing it",
            out.display()
        );
    }
    let partial = partial_dir(out);
    if partial.exists() {
        // A killed run's leftovers: this run starts afresh.
        std::fs::remove_dir_all(&partial)
            .with_context(|| format!("removing {}", partial.display()))?;
    }
    std::fs::create_dir_all(&partial).with_context(|| format!("creating {}", partial.display()))?;
    let result = (|| -> Result<(ShardSummary, usize)> {
        let details_path = partial.join(DETAILS_FILE);
        let mut details = BufWriter::with_capacity(
            1 << 20,
            File::create(&details_path)
                .with_context(|| format!("creating {}", details_path.display()))?,
        );
        let spin = progress::spinner("shard");
        let mut record = Vec::new();
        let mut written = 0u64;
        let mut put = |level: usize, index: usize, h: &[i32]| -> Result<(), IoError> {
            record.clear();
            record.extend_from_slice(&(level as u32).to_le_bytes());
            record.extend_from_slice(&(index as u64).to_le_bytes());
            for &x in h {
                put_varint(&mut record, ((x << 1) ^ (x >> 31)) as u32);
            }
            details.write_all(&record)?;
            written += 1;
            build::stall_hook(args, written);
            Ok(())
        };
        let facts = |source: build::Source| BuildFacts {
            input: args
                .input
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            lossless: args.lossless,
            max_error_m: args.max_error_m,
            diamond_size: args.diamond_size,
            rdo: args.rdo.label().into(),
            inline_bytes: args.inline_bytes,
            memory_budget_mb: budget_mb,
            source,
            radius_m,
            face_side: args.face_side,
            sparse: args.sparse,
            bounds: args.bounds,
        };
        let (part, rows) = if args.planet {
            let ((mut part, rows), source) =
                build::with_cube_source(args, n, |cube, held, sparse| {
                    let face_side = cube.face_side();
                    spin.set_message(format!(
                        "{}/{} of 6 faces of {face_side} x {face_side}",
                        spec.index, spec.count
                    ));
                    // The same options as one out-of-core build of this input.
                    let how = (n, mode, budget_mb, sparse);
                    let opts = build::cube_options(args, face_side, how, held)?;
                    let mut spill = FileSpill::beside(&partial)?;
                    let mut tiles = FileTiles::beside(&partial)?;
                    let part = stream::encode_cube_shard(
                        cube,
                        opts,
                        spec,
                        Vec::new(),
                        &mut put,
                        (&mut spill, &mut tiles),
                    )
                    .context("encoding the shard")?;
                    Ok((part, 6 * (face_side + 1)))
                })?;
            part.set_extra(serde_json::to_vec(&facts(source))?);
            (part, rows)
        } else {
            // A planar source's rows, the bytes it holds, its facts once read, sparse.
            let mosaic = if planar_mosaic {
                Some(mosaic::Mosaic::open(&args.input)?)
            } else {
                None
            };
            let mut source: Box<dyn PlanarRows + '_> = match &mosaic {
                Some(m) => {
                    let (rows, georef) = m.rows()?;
                    Box::new((rows, georef, m.source_samples))
                }
                None => Box::new(
                    input::RawRows::open(&args.input)
                        .with_context(|| format!("reading {}", args.input.display()))?,
                ),
            };
            let (width, height) = (source.rows().width(), source.rows().height());
            spin.set_message(format!(
                "{}/{} of {width} x {height}",
                spec.index, spec.count
            ));
            // The same options as one out-of-core build of this input.
            let how = (n, mode, budget_mb);
            let opts = build::stream_options(args, width * height, how, source.held_bytes())?;
            let mut part = stream::encode_shard(source.rows(), opts, spec, Vec::new(), &mut put)
                .context("encoding the shard")?;
            part.set_extra(serde_json::to_vec(&facts(source.facts()))?);
            (part, height)
        };
        spin.finish_and_clear();
        let details = details
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("writing {}", details_path.display()))?;
        details.sync_all()?;
        let part_path = partial.join(PART_FILE);
        let mut f = File::create(&part_path)
            .with_context(|| format!("creating {}", part_path.display()))?;
        f.write_all(&part.to_bytes())
            .and_then(|()| f.sync_all())
            .with_context(|| format!("writing {}", part_path.display()))?;
        let fig = &part.figures;
        let summary = ShardSummary {
            output: out.display().to_string(),
            shard: spec.index,
            shards: spec.count,
            split: fig.split,
            band_rows: fig.band_rows,
            window_rows: fig.window_rows,
            integer_rows: fig.integer_rows,
            analysed: fig.analysed,
            owned: fig.owned,
            seconds: 0.0,
            peak_rss_mb: 0.0,
            part_bytes: quincunx_store::dir_size(&partial)?,
        };
        Ok((summary, rows))
    })();
    let (mut summary, height) = match result {
        Ok(s) => s,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
    };
    if out.exists() {
        std::fs::remove_dir_all(out).with_context(|| format!("replacing {}", out.display()))?;
    }
    std::fs::rename(&partial, out).with_context(|| format!("publishing {}", out.display()))?;
    summary.seconds = started.elapsed().as_secs_f64();
    summary.peak_rss_mb = layout::peak_rss_mb();
    if args.json {
        outln!("{}", serde_json::to_string(&summary)?);
    } else {
        outln!(
            "shard {}/{} -> {}: {} rows of {} read (split octave {}), {} diamonds analysed, \
             {} own, {:.2} s, peak {:.0} MB, part {:.1} MB",
            summary.shard,
            summary.shards,
            summary.output,
            summary.window_rows,
            height,
            summary.split,
            summary.analysed,
            summary.owned,
            summary.seconds,
            summary.peak_rss_mb,
            summary.part_bytes as f64 / 1e6
        );
    }
    Ok(())
}

fn put_varint(out: &mut Vec<u8>, mut x: u32) {
    while x >= 0x80 {
        out.push((x as u8) | 0x80);
        x >>= 7;
    }
    out.push(x as u8);
}

/// Options of `quincunx merge`.
#[derive(Args, Debug, Clone)]
pub struct MergeArgs {
    /// Every part directory of the build (`quincunx build --shard K/N`), in any order.
    #[arg(required = true)]
    pub parts: Vec<PathBuf>,
    /// Repository directory to publish.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Replace an existing repository at the output path (atomically).
    #[arg(long)]
    pub overwrite: bool,
    /// Print one JSON summary on stdout (as `quincunx build --json`).
    #[arg(long)]
    pub json: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

/// One diamond's details: `(level, index, details)`.
type Record = (usize, usize, Vec<i32>);

/// Reads the details of a part, `batch` diamonds at a time.
struct Details {
    path: PathBuf,
    r: BufReader<File>,
    n2: usize,
}

impl Details {
    fn open(dir: &Path, n2: usize) -> Result<Details> {
        let path = dir.join(DETAILS_FILE);
        let f = quincunx_store::open_regular_file(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        Ok(Details {
            path,
            r: BufReader::with_capacity(1 << 20, f),
            n2,
        })
    }

    fn byte(&mut self) -> Result<Option<u8>> {
        let mut b = [0u8];
        match self.r.read(&mut b) {
            Ok(0) => Ok(None),
            Ok(_) => Ok(Some(b[0])),
            Err(e) => Err(e).with_context(|| format!("reading {}", self.path.display())),
        }
    }

    fn truncated(&self) -> anyhow::Error {
        anyhow::anyhow!("{} is truncated or corrupt", self.path.display())
    }

    /// The next record, or `None` at the end.
    fn next(&mut self) -> Result<Option<Record>> {
        let mut head = [0u8; 12];
        let mut got = 0;
        while got < head.len() {
            match self.byte()? {
                Some(b) => head[got] = b,
                None if got == 0 => return Ok(None),
                None => return Err(self.truncated()),
            }
            got += 1;
        }
        let level = u32::from_le_bytes(head[..4].try_into()?) as usize;
        let index = usize::try_from(u64::from_le_bytes(head[4..].try_into()?))
            .map_err(|_| self.truncated())?;
        let mut h = Vec::with_capacity(self.n2);
        for _ in 0..self.n2 {
            let mut x = 0u32;
            let mut shift = 0;
            loop {
                let b = self.byte()?.ok_or_else(|| self.truncated())?;
                if shift > 28 {
                    return Err(self.truncated());
                }
                x |= u32::from(b & 0x7f) << shift;
                shift += 7;
                if b & 0x80 == 0 {
                    break;
                }
            }
            h.push(((x >> 1) as i32) ^ -((x & 1) as i32));
        }
        Ok(Some((level, index, h)))
    }
}

/// A part file's bytes: a regular file only (a FIFO or device fails at once), read up to
/// its length at open (a file growing meanwhile is an error, not an endless read).
fn read_part(path: &Path) -> Result<Vec<u8>> {
    let file = quincunx_store::open_regular_file(path)?;
    let len = file.metadata()?.len();
    let mut bytes = Vec::with_capacity(usize::try_from(len)?);
    file.take(len + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 != len {
        bail!("the file changed size while it was read");
    }
    Ok(bytes)
}

/// Runs `quincunx merge`.
pub fn merge(args: &MergeArgs) -> Result<()> {
    let mut pool = rayon::ThreadPoolBuilder::new();
    if let Some(t) = args.threads {
        if !(1..=build::MAX_THREADS).contains(&t) {
            bail!(
                "--threads {t} is out of range: give 1 to {}",
                build::MAX_THREADS
            );
        }
        pool = pool.num_threads(t);
    }
    let pool = pool.build().context("starting worker threads")?;
    let summary = pool.install(|| merge_parts(args))?;
    if args.json {
        outln!("{}", serde_json::to_string(&summary)?);
    } else {
        outln!(
            "merged {} parts into {}: {} samples in {:.2} s, {:.4} bits/sample, rms {:.4}, \
             max {:.4}, {} blobs, peak {:.0} MB, content hash {}",
            args.parts.len(),
            summary.output,
            summary.samples,
            summary.seconds,
            summary.bits_per_sample,
            summary.rms,
            summary.max_abs,
            summary.blob_count,
            summary.peak_rss_mb,
            summary.content_hash
        );
    }
    Ok(())
}

fn merge_parts(args: &MergeArgs) -> Result<build::BuildSummary> {
    let started = Instant::now();
    let mut parts = Vec::new();
    for dir in &args.parts {
        let path = dir.join(PART_FILE);
        let bytes = read_part(&path).with_context(|| {
            format!(
                "reading {} (is {} a finished shard part?)",
                path.display(),
                dir.display()
            )
        })?;
        let part = ShardPart::from_bytes(&bytes).with_context(|| format!("{}", path.display()))?;
        parts.push((part.index(), dir.clone(), part));
    }
    parts.sort_by_key(|p| p.0);
    let dirs: Vec<PathBuf> = parts.iter().map(|p| p.1.clone()).collect();
    let parts: Vec<ShardPart> = parts.into_iter().map(|p| p.2).collect();
    let planet = parts.first().is_some_and(ShardPart::is_planet);
    let facts: BuildFacts = serde_json::from_slice(
        parts
            .first()
            .map(|p| p.extra())
            .context("no parts to merge")?,
    )
    .context("the parts' build description")?;
    let mut bargs = BuildArgs::new(&facts.input, &args.output);
    bargs.lossless = facts.lossless;
    bargs.max_error_m = facts.max_error_m;
    bargs.diamond_size = facts.diamond_size;
    bargs.rdo = Rdo::from_label(&facts.rdo);
    bargs.inline_bytes = facts.inline_bytes;
    bargs.memory_budget_mb = Some(facts.memory_budget_mb);
    bargs.overwrite = args.overwrite;
    bargs.planet = planet;
    bargs.radius_m = facts.radius_m;
    bargs.face_side = facts.face_side;
    bargs.sparse = facts.sparse;
    bargs.bounds = facts.bounds;
    let mode = build::rate_mode(&bargs)?;
    let n = build::diamond_n(&bargs)?;
    build::check_output(&bargs)?;
    let (meta, description) = build::with_builder(&bargs, |builder| {
        let mut builder = builder
            .spill_to_disk()
            .with_context(|| format!("creating {}", args.output.display()))?;
        let spin = progress::spinner("merging");
        let mut sink = build::StoreSink::new(&bargs, &mut builder, &spin);
        // Every part's details, a batch at a time.
        let each = |f: &mut dyn FnMut(&[Record]) -> Result<()>| -> Result<()> {
            let mut batch = Vec::new();
            for dir in &dirs {
                let mut details = Details::open(dir, n * n)?;
                while let Some(rec) = details.next()? {
                    batch.push(rec);
                    if batch.len() == 1024 {
                        f(&batch).with_context(|| format!("coding {}", details.path.display()))?;
                        batch.clear();
                    }
                }
                f(&batch).with_context(|| format!("coding {}", details.path.display()))?;
                batch.clear();
            }
            Ok(())
        };
        if planet {
            let mut spill = FileSpill::beside(&args.output)?;
            let mut tiles = FileTiles::beside(&args.output)?;
            let mut merge =
                CubeMerge::new(parts, &mut spill, &mut tiles).context("merging the parts")?;
            each(&mut |batch| Ok(merge.add(batch, &mut spill)?))?;
            let enc = merge
                .finish(&mut sink, &mut spill, &mut tiles)
                .context("merging the parts")?;
            spin.finish_and_clear();
            let radius = facts
                .radius_m
                .context("a planet's parts without a radius")?;
            build::publish_cube(
                &bargs,
                builder,
                enc,
                facts.source.clone(),
                (radius, n, mode),
            )
        } else {
            let mut merge = Merge::new(parts).context("merging the parts")?;
            each(&mut |batch| Ok(merge.code(batch, &mut sink)?))?;
            let enc = merge.finish(&mut sink).context("merging the parts")?;
            spin.finish_and_clear();
            let source = &facts.source;
            let facts = StreamFacts {
                units: source.units.clone(),
                georef: source.georef.clone(),
                source_samples: source.source_samples,
            };
            build::publish_streamed(&bargs, builder, enc, facts, (n, mode))
        }
    })?;
    let seconds = started.elapsed().as_secs_f64();
    let mut summary = build::summarise(&bargs, &meta, &description, started, (0.0, seconds))?;
    summary.out_of_core = true;
    Ok(summary)
}
