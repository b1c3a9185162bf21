//! Out-of-core encoder of planar rasters: bounded memory, rows read on demand, blobs handed
//! out as they are coded. The output decodes with the ordinary decoder
//! ([`StreamEncoded::into_encoded`] + [`crate::encode::decode`]): same [`RasterGeometry`],
//! blob format, model and root grid as [`crate::encode::encode`] would use.
//!
//! Why it works: the finest detail level `2k - 1` refines the quincunx lattice
//! `{x + y even}` into every integer point and level `2k - 2` refines `2Z^2` into the
//! quincunx, so once that *octave* is analysed only the even rows and columns matter to the
//! coarser levels, and they form a raster half the size whose levels are the same problem
//! one octave smaller. Rows flow through a chain of octave processors, each holding a
//! rolling window of about three diamond heights; a diamond is analysed as soon as the rows
//! it spans are final (diamonds of one level never touch each other's points, so any order
//! works within a level), and no detail matrix outlives its diamond.
//!
//! Lossless and max-error modes: the steps are all 1 (256/256) and the decoder reproduces
//! the integerised values exactly, so the errors and the side information are computed
//! during analysis, without a verification decode. Passes over the source: (0) range,
//! quantum and valid count; (1) analysis, measuring errors, side information (bottom-up,
//! children always come first) and training counts; (2) the identical analysis again,
//! coding each diamond's blob into the sink as soon as its details exist.
//!
//! RMS mode: the in-memory rate control's search over passes of the analysis and of its
//! inverse, the synthesis, a band of rows at a time (`rms.rs`, `synth.rs`).
//!
//! Sparse mode: pass 0 also finds the coverage ([`RasterCoverage`], one row at a time),
//! and the geometry masks the blocks without data as the in-memory sparse encoder does.
//!
//! Nodata is filled chunk by chunk with push-pull ([`crate::fill`]) over the new rows plus
//! the last [`CONTEXT_ROWS`] filled rows as fixed context, so holes that span chunks have
//! no cliffs at the seams; the chunking depends only on the dimensions and the budget, so
//! passes 1 and 2 see identical values. When one chunk holds the whole raster the fills,
//! and so every byte, equal the in-memory encoder's; with more chunks the voids' fills
//! (not the data) may differ.

use std::ops::Range;
use std::sync::Arc;

use rayon::prelude::*;

use crate::blob;
use crate::coverage::{Coverage, RasterCoverage};
use crate::encode::{
    EncodeError, EncodeReport, Encoded, EncodedDomain, Measure, RateMode, RdoMode, Tally, ValueMap,
    check_tolerance, measure, native_quantum, on_quantum, side_info,
};
use crate::entropy::{self, CodecModel, ContextCounts};
use crate::lifting::{self, DiamondMask};
use crate::raster::{DiamondSlot, RasterGeometry};
use quincunx_decoder::lattice::{read_lattice, write_lattice};

mod cube;
mod rms;
mod shard;
mod synth;

pub use cube::{
    CUBE_PHASES, CubeEncoded, CubeMerge, CubeOptions, CubeSource, DecodedTiles, MemoryTiles,
    TileStore, encode_cube, encode_cube_shard,
};
pub use shard::{Merge, ShardFigures, ShardPart, ShardSpec, encode_shard};

/// What the streaming encoders' sources, sinks and stores fail with: any error (an
/// `std::io::Error`, a message), kept as the cause of [`EncodeError::Source`] or
/// [`EncodeError::Sink`].
pub type IoError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// An [`IoError`] that says what was being done when `source` happened.
#[derive(Debug, thiserror::Error)]
#[error("{what}")]
pub struct IoContext {
    /// What was being done.
    pub what: String,
    /// What went wrong.
    #[source]
    pub source: IoError,
}

/// `source`, saying what was being done.
pub fn io_context(what: impl Into<String>, source: IoError) -> IoError {
    Box::new(IoContext {
        what: what.into(),
        source,
    })
}

/// An [`IoError`], shared so that [`EncodeError`] stays `Clone`: the cause of
/// [`EncodeError::Source`] and [`EncodeError::Sink`]. It shows as the error it holds, whose
/// cause is its cause; two compare equal when their messages do.
#[derive(Clone, Debug)]
pub struct IoCause(pub Arc<dyn std::error::Error + Send + Sync + 'static>);

impl std::fmt::Display for IoCause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

impl std::error::Error for IoCause {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.0.source()
    }
}

impl PartialEq for IoCause {
    fn eq(&self, other: &IoCause) -> bool {
        self.to_string() == other.to_string()
    }
}

impl From<IoError> for IoCause {
    fn from(e: IoError) -> IoCause {
        IoCause(Arc::from(e))
    }
}

impl EncodeError {
    /// [`EncodeError::Source`] of `e`.
    pub fn reading(e: IoError) -> EncodeError {
        EncodeError::Source(e.into())
    }

    /// [`EncodeError::Sink`] of `e`.
    pub fn writing(e: IoError) -> EncodeError {
        EncodeError::Sink(e.into())
    }
}

/// Rows of a planar raster, read on demand (row 0 = north). May be called several times
/// over the same rows (the encoder makes more than one pass).
pub trait RowSource {
    /// Samples per row.
    fn width(&self) -> usize;
    /// Rows.
    fn height(&self) -> usize;
    /// Fills `out` (len = width * count) with rows `first .. first + count` in metres,
    /// NaN = nodata.
    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError>;
    /// Known quantum (1 m for int16), like [`crate::encode::Grid::quantum_m`].
    fn quantum_m(&self) -> Option<f64>;
}

/// Receives blobs as they are coded (any order).
pub trait BlobSink {
    /// Stores the blob of diamond `index` of detail level `level` (storage key `key`).
    fn put(&mut self, level: usize, index: usize, key: &[u8], blob: &[u8]) -> Result<(), IoError>;
}

/// Settings of the streaming encoder.
#[derive(Clone, Copy, Debug)]
pub struct StreamOptions {
    /// Diamond size `N` (cells per side; a power of two).
    pub n: usize,
    /// Rate mode: [`RateMode::Lossless`] or [`RateMode::MaxErrorM`].
    pub mode: RateMode,
    /// Bound on the sample buffers the encoder holds at once (rows read, rolling octave
    /// windows, in-flight diamonds). Per-diamond bookkeeping (the geometry and a few bytes
    /// of side information per diamond, `O(width x height / N^2)`) comes on top.
    pub memory_budget_bytes: usize,
    /// Sparse mode ([`crate::encode::EncodeOptions::sparse`]): blocks without data are
    /// holes. The coverage is found in the first pass, one row at a time.
    pub sparse: bool,
    /// The rate-distortion quantiser (RMS mode), as [`crate::encode::EncodeOptions::rdo`].
    pub rdo: RdoMode,
}

/// Everything a decoder needs besides the blobs (which went to the [`BlobSink`]).
#[derive(Clone, Debug)]
pub struct StreamEncoded {
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Diamond size.
    pub n: usize,
    /// Metres per integer unit.
    pub value_scale_m: f64,
    /// Metres at integer 0.
    pub value_offset_m: f64,
    /// Quantiser step per detail level, in 1/256 integer units (all 256).
    pub steps: Vec<u32>,
    /// Root vertex grid, `(N+1)^2` (zeros at invalid vertices).
    pub root: Vec<i32>,
    /// Trained starting probabilities.
    pub model: CodecModel,
    /// Measured results (errors over valid samples, exact in these rate modes).
    pub report: EncodeReport,
    /// Largest number of bytes of sample buffers held at once (at most the budget).
    pub peak_buffer_bytes: usize,
    /// The coverage (sparse mode).
    pub coverage: Option<Coverage>,
}

impl StreamEncoded {
    /// The in-memory form, with the blobs the sink received (`blobs[level][index]`), for
    /// [`crate::encode::decode`].
    pub fn into_encoded(self, blobs: Vec<Vec<Option<Vec<u8>>>>) -> Encoded {
        Encoded {
            domain: EncodedDomain::Planar {
                width: self.width,
                height: self.height,
            },
            width: self.width,
            height: self.height,
            n: self.n,
            value_scale_m: self.value_scale_m,
            value_offset_m: self.value_offset_m,
            steps: self.steps,
            root: self.root.clone(),
            roots: vec![self.root],
            model: self.model,
            blobs,
            coverage: self.coverage,
            report: self.report,
        }
    }
}

/// Filled rows kept as context for the next chunk's nodata fill.
pub const CONTEXT_ROWS: usize = 16;
/// Diamonds analysed at once (in parallel); bounds the in-flight matrices.
const BATCH: usize = 16;
/// Bytes of push-pull's own work arrays per sample filled over (pyramid and passes).
const FILL_BYTES_PER_SAMPLE: usize = 10;

/// Encodes a planar raster out of core. See the module docs. In RMS mode the quantised
/// indices of two attempts are kept in memory ([`MemorySpill`], about 0.02-0.4 bytes a
/// sample); [`encode_streaming_with`] takes another [`IndexSpill`].
pub fn encode_streaming(
    source: &mut dyn RowSource,
    opts: StreamOptions,
    sink: &mut dyn BlobSink,
) -> Result<StreamEncoded, EncodeError> {
    encode_streaming_with(source, opts, sink, &mut MemorySpill::default())
}

/// Storage for detail and index matrices between passes: three slots (0 to 2), each
/// appended to and read back by offset. The planar encoder uses it in RMS mode (slots 0
/// and 1: two attempts); the planet encoder keeps its details in slot 0 and, in RMS mode,
/// two attempts in slots 1 and 2.
pub trait IndexSpill: Sync {
    /// Empties slot `slot`.
    fn clear(&mut self, slot: usize) -> Result<(), IoError>;
    /// Appends `bytes` to slot `slot`; their offset in it.
    fn append(&mut self, slot: usize, bytes: &[u8]) -> Result<u64, IoError>;
    /// Reads `len` bytes at `offset` of slot `slot`.
    fn read(&self, slot: usize, offset: u64, len: usize) -> Result<Vec<u8>, IoError>;
    /// Bytes held in memory (for the encoder's accounting).
    fn held(&self) -> usize;
}

/// An [`IndexSpill`] in memory.
#[derive(Debug, Default)]
pub struct MemorySpill {
    slots: [Vec<u8>; 3],
}

impl IndexSpill for MemorySpill {
    fn clear(&mut self, slot: usize) -> Result<(), IoError> {
        self.slots
            .get_mut(slot)
            .ok_or_else(|| format!("no spill slot {slot}"))?
            .clear();
        Ok(())
    }

    fn append(&mut self, slot: usize, bytes: &[u8]) -> Result<u64, IoError> {
        let s = self
            .slots
            .get_mut(slot)
            .ok_or_else(|| format!("no spill slot {slot}"))?;
        let at = s.len() as u64;
        s.extend_from_slice(bytes);
        Ok(at)
    }

    fn read(&self, slot: usize, offset: u64, len: usize) -> Result<Vec<u8>, IoError> {
        let s = self
            .slots
            .get(slot)
            .ok_or_else(|| format!("no spill slot {slot}"))?;
        let start = usize::try_from(offset)?;
        s.get(start..start + len)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| {
                format!("spill slot {slot} has no bytes {start}..{}", start + len).into()
            })
    }

    fn held(&self) -> usize {
        self.slots.iter().map(Vec::capacity).sum()
    }
}

/// [`encode_streaming`] with the RMS mode's indices in `spill`.
pub fn encode_streaming_with(
    source: &mut dyn RowSource,
    opts: StreamOptions,
    sink: &mut dyn BlobSink,
    spill: &mut dyn IndexSpill,
) -> Result<StreamEncoded, EncodeError> {
    let Prepared {
        geom,
        plan,
        mut meter,
        coverage,
        valid,
        map,
        fill,
        ..
    } = prepare(source, &opts)?;
    let (width, height, n) = (plan.width, plan.height, plan.n);
    if let RateMode::RmsM(target) = opts.mode {
        let passes = rms::Passes {
            source,
            plan: &plan,
            geom: &geom,
            map: &map,
            fill: &fill,
            meter: &mut meter,
        };
        let enc = rms::encode_rms(passes, target, opts.rdo, valid, (sink, spill))?;
        return Ok(StreamEncoded { coverage, ..enc });
    }

    // Pass 1: errors, side information, training counts.
    let mut side = Side::new(&geom);
    let mut errors = Errors::default();
    let root = run_pass(
        source,
        &plan,
        &geom,
        &map,
        &fill,
        &mut Work::Analyse {
            side: &mut side,
            errors: &mut errors,
            keep: None,
        },
        &mut meter,
    )?;
    let levels = geom.detail_levels();
    let model = side.model(&geom);

    // Pass 2: code every blob.
    let mut coded = Coded::default();
    let root2 = run_pass(
        source,
        &plan,
        &geom,
        &map,
        &fill,
        &mut Work::Code {
            side: &side,
            model: &model,
            sink,
            coded: &mut coded,
        },
        &mut meter,
    )?;
    if root2 != root {
        return Err(EncodeError::Internal(
            "passes disagree (non-deterministic source?)",
        ));
    }

    let steps = vec![256u32; levels];
    let report = EncodeReport::tally(Tally {
        samples: width * height,
        valid_samples: valid,
        blobs: (coded.count, coded.bytes),
        roots: std::slice::from_ref(&root),
        model: &model,
        steps: steps.len(),
        errors: ((errors.sum2 / valid as f64).sqrt(), errors.max),
        rdo: false,
        decodes: 0,
    });
    Ok(StreamEncoded {
        width,
        height,
        n,
        value_scale_m: map.scale,
        value_offset_m: map.offset,
        steps,
        root,
        model,
        report,
        peak_buffer_bytes: meter.peak,
        coverage,
    })
}

/// What every streamed build starts from: the geometry (masked by the coverage in sparse
/// mode), the plan, and what pass 0 (the scan) found.
struct Prepared {
    geom: RasterGeometry,
    plan: Plan,
    meter: Meter,
    coverage: Option<Coverage>,
    valid: usize,
    map: ValueMap,
    fill: Fill,
    /// The scan's range and sum (a shard's parts must agree on them).
    scan: [f64; 3],
}

fn prepare(source: &mut dyn RowSource, opts: &StreamOptions) -> Result<Prepared, EncodeError> {
    check_tolerance(opts.mode)?;
    let (width, height, n) = (source.width(), source.height(), opts.n);
    let geom = RasterGeometry::new(width, height, n)?;
    let plan = Plan::new(&geom, opts.memory_budget_bytes)?;
    let mut meter = Meter::default();

    let mut coverage = opts.sparse.then(|| RasterCoverage::new(width, height, n));
    let scan = scan(source, &plan, coverage.as_mut(), &mut meter)?;
    if scan.valid == 0 {
        return Err(EncodeError::AllNodata);
    }
    // Sparse: the same diamonds, masked where blocks hold no data (the plan's buffers
    // depend on the dimensions only).
    let coverage = coverage.map(RasterCoverage::finish);
    let geom = match &coverage {
        Some(c) => RasterGeometry::with_coverage(width, height, n, c)?,
        None => geom,
    };
    let (map, fill) = scan.mapping(source.quantum_m(), opts.mode)?;
    Ok(Prepared {
        geom,
        plan,
        meter,
        coverage,
        valid: scan.valid,
        map,
        fill,
        scan: [scan.lo, scan.hi, scan.sum],
    })
}

/// Receives decoded rows in order: `(row, values)`.
pub type RowSink<'a> = dyn FnMut(usize, &[i32]) -> Result<(), IoError> + 'a;

/// What [`decode_rows`] decodes: a planar encoding without its blobs.
#[derive(Clone, Copy, Debug)]
pub struct RowDecode<'a> {
    /// The geometry (with the encoding's coverage, if any).
    pub geom: &'a RasterGeometry,
    /// Root vertex grid.
    pub root: &'a [i32],
    /// Quantiser step per detail level (1/256 units).
    pub steps: &'a [u32],
    /// The entropy model.
    pub model: &'a CodecModel,
}

/// Decodes a planar encoding to integers a band of rows at a time, in memory bounded by a
/// few diamond heights of rows per octave: `blob(level, index)` gives a diamond's blob
/// (`None`: no blob), `emit(row, values)` receives the rows in order, invalid points 0,
/// the same integers as [`crate::encode::decode_integers`].
pub fn decode_rows(
    d: RowDecode<'_>,
    blob: &(dyn Fn(usize, usize) -> Result<Option<Vec<u8>>, IoError> + Sync),
    emit: &mut RowSink<'_>,
) -> Result<(), EncodeError> {
    let n = d.geom.n();
    let details = |l: usize, i: usize, h: &mut [i32]| -> Result<bool, EncodeError> {
        let Some(bytes) = blob(l, i).map_err(EncodeError::reading)? else {
            return Ok(false);
        };
        let step = d.steps.get(l).copied().unwrap_or(256);
        let ctx = blob::BlobContext {
            step,
            ..d.geom.blob_context(l, i)
        };
        let mut q = Vec::with_capacity(n * n);
        blob::decode_into(&bytes, &ctx, d.model, &mut q)
            .map_err(|e| EncodeError::reading(io_context(format!("blob ({l}, {i})"), e.into())))?;
        let mut any = false;
        for (dst, &x) in h.iter_mut().zip(q.iter()) {
            any |= x != 0;
            *dst = crate::encode::dequantize(x, step);
        }
        Ok(any)
    };
    let mut row = 0;
    let mut line = Vec::new();
    synth::synthesize_rows(d.geom, d.root, &details, &mut |_| {}, &mut |r: &[i32]| {
        line.clear();
        line.extend(
            r.iter()
                .enumerate()
                .map(|(x, &v)| if d.geom.is_valid(x, row) { v } else { 0 }),
        );
        emit(row, &line).map_err(EncodeError::writing)?;
        row += 1;
        Ok(())
    })
}

/// Samples per parallel piece of the per-sample passes (fixed, so sums do not depend
/// on the thread count).
const PIECE: usize = 1 << 14;

/// Buffer sizes, fixed from the dimensions and the budget.
pub(crate) struct Plan {
    width: usize,
    height: usize,
    n: usize,
    /// Rows read (and filled) at once.
    chunk_rows: usize,
    /// `(width, height)` of the octave rasters `R_0 ..= R_k` (`R_o`: every `2^o`-th row
    /// and column).
    pub(crate) dims: Vec<(usize, usize)>,
    /// Row capacity of each octave's window.
    caps: Vec<usize>,
}

impl Plan {
    pub(crate) fn new(geom: &RasterGeometry, budget: usize) -> Result<Self, EncodeError> {
        let (width, height, n) = (geom.width(), geom.height(), geom.n());
        let octaves = geom.detail_levels() / 2;
        let mut dims = vec![(width, height)];
        for o in 0..octaves {
            let (w, h) = dims[o];
            dims.push((w.div_ceil(2), h.div_ceil(2)));
        }
        let mut plan = Plan {
            width,
            height,
            n,
            chunk_rows: 1,
            dims,
            caps: Vec::new(),
        };
        let needed = plan.bytes(1);
        if needed > budget {
            return Err(EncodeError::Budget { needed, budget });
        }
        let (mut lo, mut hi) = (1, height);
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            if plan.bytes(mid) <= budget {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        plan.chunk_rows = lo;
        plan.caps = plan.windows(lo);
        Ok(plan)
    }

    /// Row capacity of each octave window when `chunk` rows are read at once: a window
    /// keeps at most `3N` rows between pushes (a band of level-`2k-2` diamonds spans `2N`
    /// rows and waits for the level-`2k-1` diamonds `N` rows below it) plus one push.
    fn windows(&self, chunk: usize) -> Vec<usize> {
        let n3 = 3 * self.n;
        let mut push = chunk;
        (0..self.dims.len() - 1)
            .map(|o| {
                let cap = (n3 + push + 2).min(self.dims[o].1);
                push = (n3 + push) / 2 + 2;
                cap
            })
            .collect()
    }

    /// Upper bound of the sample buffers held with `chunk` rows read at once.
    fn bytes(&self, chunk: usize) -> usize {
        let fill_rows = CONTEXT_ROWS + chunk;
        let reader = fill_rows * self.width * (8 + 1 + FILL_BYTES_PER_SAMPLE);
        let windows: usize = self
            .windows(chunk)
            .iter()
            .zip(&self.dims)
            .map(|(rows, (w, _))| rows * w * 4)
            .sum();
        let (wk, hk) = self.dims[self.dims.len() - 1];
        let n = self.n;
        // Per diamond in flight: fine and coarse vertices, cells, details, a blob.
        let batch = BATCH * 4 * (2 * (n + 1) * (n + 1) + 3 * n * n);
        reader + windows + wk * hk * 4 + batch
    }
}

/// Peak of the sample buffers held.
#[derive(Default)]
struct Meter {
    peak: usize,
}

impl Meter {
    fn note(&mut self, bytes: usize) {
        self.peak = self.peak.max(bytes);
    }
}

/// What pass 0 learns about the valid samples.
struct Scan {
    valid: usize,
    lo: f64,
    hi: f64,
    sum: f64,
    /// Whether every valid value is on each candidate quantum.
    quanta: Vec<(f64, bool)>,
}

impl Scan {
    /// Nothing seen yet; the candidate quanta are `known` (when given) and the decimal
    /// ones.
    fn new(known: Option<f64>) -> Self {
        let mut candidates: Vec<f64> = crate::encode::DECIMAL_QUANTA.to_vec();
        if let Some(q) = known.filter(|&q| q > 0.0) {
            candidates.insert(0, q);
        }
        Scan {
            valid: 0,
            lo: f64::INFINITY,
            hi: f64::NEG_INFINITY,
            sum: 0.0,
            quanta: candidates.into_iter().map(|q| (q, true)).collect(),
        }
    }

    fn integral(&self, q: f64) -> bool {
        self.quanta.iter().any(|&(c, ok)| c == q && ok)
    }

    /// How the values map to integers (`known`: the source's quantum, asked now, after
    /// the pass) and how nodata is filled.
    fn mapping(&self, known: Option<f64>, mode: RateMode) -> Result<(ValueMap, Fill), EncodeError> {
        let native = native_quantum(known, |q| self.integral(q));
        let map = ValueMap::new(self.lo, self.hi, native, mode)?;
        let fill = Fill {
            lo: self.lo,
            hi: self.hi,
            mean: self.sum / self.valid as f64,
        };
        Ok((map, fill))
    }

    /// Adds the values of a band: fixed pieces in parallel, merged in order (the same
    /// results with any thread count); the sum in value order, as the in-memory planet
    /// encoder adds it for its mean fill.
    fn add(&mut self, band: &[f64]) {
        let quanta: Vec<f64> = self.quanta.iter().map(|&(q, _)| q).collect();
        let pieces: Vec<Scan> = band
            .par_chunks(PIECE)
            .map(|c| {
                let mut p = Scan::new(None);
                p.quanta = quanta.iter().map(|&q| (q, true)).collect();
                for &v in c.iter().filter(|v| v.is_finite()) {
                    p.valid += 1;
                    p.lo = p.lo.min(v);
                    p.hi = p.hi.max(v);
                    for (q, ok) in &mut p.quanta {
                        *ok = *ok && on_quantum(v, *q);
                    }
                }
                p
            })
            .collect();
        self.sum = band
            .iter()
            .filter(|v| v.is_finite())
            .fold(self.sum, |s, &v| s + v);
        for p in pieces {
            self.valid += p.valid;
            self.lo = self.lo.min(p.lo);
            self.hi = self.hi.max(p.hi);
            for (a, b) in self.quanta.iter_mut().zip(&p.quanta) {
                a.1 = a.1 && b.1;
            }
        }
    }
}

fn scan(
    source: &mut dyn RowSource,
    plan: &Plan,
    mut coverage: Option<&mut RasterCoverage>,
    meter: &mut Meter,
) -> Result<Scan, EncodeError> {
    let w = plan.width;
    let mut s = Scan::new(source.quantum_m());
    let mut buf = vec![0.0; plan.chunk_rows * w];
    meter.note(buf.capacity() * 8);
    let mut first = 0;
    while first < plan.height {
        let count = plan.chunk_rows.min(plan.height - first);
        let out = &mut buf[..count * w];
        source
            .read_rows(first, count, out)
            .map_err(EncodeError::reading)?;
        if let Some(cov) = coverage.as_deref_mut() {
            for (r, row) in out.chunks_exact(w).enumerate() {
                cov.mark_row(first + r, |x| row[x].is_finite());
            }
        }
        s.add(out);
        first += count;
    }
    Ok(s)
}

/// How nodata is filled: push-pull, clamped to the valid range, the valid mean where a
/// chunk and its context hold nothing valid.
struct Fill {
    lo: f64,
    hi: f64,
    mean: f64,
}

impl Fill {
    /// Fills the invalid samples of `vals` (rows of `w`, the first `context` of them
    /// filled context) with push-pull over all of them, clamped to the valid range, or
    /// the valid mean where nothing is valid; the bytes of push-pull's work arrays (0 when
    /// nothing needed filling).
    fn rows(&self, w: usize, context: usize, vals: &mut [f64], valid: &[bool]) -> usize {
        if valid[context * w..].iter().all(|&b| b) {
            return 0;
        }
        let clamp = crate::fill::push_pull(w, vals.len() / w, vals, valid);
        for (v, _) in vals.iter_mut().zip(valid).filter(|(_, b)| !**b) {
            *v = if clamp {
                v.clamp(self.lo, self.hi)
            } else {
                self.mean
            };
        }
        vals.len() * FILL_BYTES_PER_SAMPLE
    }
}

/// A piece's error sum with the offset of its first sample.
type Piece = (u64, f64);

/// Receives the details of a shard's diamonds: `(level, index, details)`.
pub type DetailsOut<'a> = dyn FnMut(usize, usize, &[i32]) -> Result<(), IoError> + 'a;

/// Errors of the integerised values against the source, over valid samples.
#[derive(Default)]
struct Errors {
    sum2: f64,
    max: f64,
    /// Shards: only the pieces whose first sample is in these rows count, each piece's
    /// sum kept with its first sample's offset, for the merge to add them in order.
    pieces: Option<(Range<usize>, Vec<Piece>)>,
}

/// Side information of every diamond, from pass 1.
struct Side {
    gamma: Vec<Vec<u64>>,
    has_data: Vec<Vec<bool>>,
    bounds: Vec<Vec<(i64, i64)>>,
    /// Training counts of the detail matrices (the side information is counted after
    /// pass 1, when every class is known).
    counts: ContextCounts,
}

impl Side {
    fn new(geom: &RasterGeometry) -> Self {
        let lens: Vec<usize> = (0..geom.detail_levels())
            .map(|l| geom.level(l).len())
            .collect();
        Side {
            gamma: lens.iter().map(|&k| vec![0; k]).collect(),
            has_data: lens.iter().map(|&k| vec![false; k]).collect(),
            bounds: lens.iter().map(|&k| vec![(0, 0); k]).collect(),
            counts: ContextCounts::default(),
        }
    }

    /// Whether a diamond's blob is part of the training sample (as the in-memory encoder
    /// chooses it: every blob of the small levels, every 4th diamond of the large ones).
    fn trains(&self, geom: &RasterGeometry, l: usize, i: usize) -> bool {
        let len = geom.level(l).len();
        self.has_data[l][i] && crate::encode::trains_on(len, i)
    }

    /// The trained model: the detail counts and the side information's, now that every
    /// class is known.
    fn model(&self, geom: &RasterGeometry) -> CodecModel {
        let levels = geom.detail_levels();
        let mut counts = self.counts.clone();
        for l in 0..levels {
            for i in 0..geom.level(l).len() {
                if self.trains(geom, l, i) {
                    let group = entropy::group(levels - 1 - l);
                    entropy::write_gammas(&mut counts, group, &self.classes(geom, l, i));
                }
            }
        }
        CodecModel::from_counts(&counts)
    }

    fn classes(&self, geom: &RasterGeometry, l: usize, i: usize) -> Vec<u8> {
        geom.level(l)[i]
            .owned
            .iter()
            .map(|&k| crate::encode::side_entry(self.gamma[l + 1][k], self.has_data[l + 1][k]))
            .collect()
    }
}

/// Blobs coded so far.
#[derive(Default)]
struct Coded {
    count: usize,
    bytes: usize,
}

/// What a pass does with each analysed diamond.
enum Work<'a> {
    /// Pass 1: measure errors and side information, count for training.
    Analyse {
        side: &'a mut Side,
        errors: &'a mut Errors,
        /// Shards: which diamonds are theirs, and where their details go.
        keep: Option<Keep<'a>>,
    },
    /// Pass 2: code blobs into the sink.
    Code {
        side: &'a Side,
        model: &'a CodecModel,
        sink: &'a mut dyn BlobSink,
        coded: &'a mut Coded,
    },
    /// Hands every batch of details to a visitor (the RMS rate control's passes).
    Visit(&'a mut dyn DetailVisitor),
}

/// What a shard keeps of its analysis: the side information and training counts of the
/// diamonds it owns (it analyses others, in its halo, only for their effect on its own),
/// and their details.
pub(crate) struct Keep<'a> {
    /// Whether diamond `(level, index)` is the shard's.
    pub(crate) owns: &'a (dyn Fn(usize, usize) -> bool + Sync),
    /// Receives the details of each owned diamond with data.
    pub(crate) details: &'a mut DetailsOut<'a>,
    /// Diamonds analysed, per level (an owned diamond's children must be).
    pub(crate) analysed: Vec<Vec<bool>>,
}

/// Receives the details of every diamond of a streamed analysis, a batch at a time.
pub(crate) trait DetailVisitor {
    /// Diamonds `batch` of `level` and their details (same order).
    fn visit(
        &mut self,
        geom: &RasterGeometry,
        level: usize,
        batch: &[usize],
        details: &[&[i32]],
    ) -> Result<(), EncodeError>;
}

/// One streaming analysis of the whole raster; returns the root grid.
fn run_pass(
    source: &mut dyn RowSource,
    plan: &Plan,
    geom: &RasterGeometry,
    map: &ValueMap,
    fill: &Fill,
    work: &mut Work<'_>,
    meter: &mut Meter,
) -> Result<Vec<i32>, EncodeError> {
    let octaves = plan.dims.len() - 1;
    let feed = Feed::Source {
        source,
        map,
        fill,
        window: None,
    };
    let last = run_octaves(feed, plan, geom, 0..octaves, work, meter)?;
    Ok(root_grid(plan, geom, &last))
}

/// The root grid, from the last octave raster `R_k`.
fn root_grid(plan: &Plan, geom: &RasterGeometry, last: &[i32]) -> Vec<i32> {
    let octaves = plan.dims.len() - 1;
    let wk = plan.dims[octaves].0;
    let root = geom.root_slot();
    let f = Frame::of(&root, octaves as u32);
    let mut v = vec![0; (plan.n + 1) * (plan.n + 1)];
    f.gather_vertices(plan.n, root.mask.as_ref(), last, 0, wk, &mut v);
    v
}

/// Where the rows of an octave chain come from.
enum Feed<'a> {
    /// The source, a chunk at a time (`R_0`).
    Source {
        source: &'a mut dyn RowSource,
        map: &'a ValueMap,
        fill: &'a Fill,
        /// Shards: what they read and analyse.
        window: Option<&'a Window>,
    },
    /// An octave raster in memory, all at once (the merge's `R_m`).
    Rows(&'a [i32]),
}

/// What a shard reads and analyses of the chain: the chunks starting in `read` are read
/// and filled (from a chunk whose fill context needs no earlier fill), the others are
/// zeros; each octave analyses only its `allow`ed groups; of the last raster only the
/// rows `keep` are kept.
struct Window {
    read: Range<usize>,
    allow: Vec<(Range<usize>, Range<usize>)>,
    keep: Range<usize>,
}

/// Runs octaves `range` of the chain over `feed` (rows of `R_{range.start}`); returns
/// `R_{range.end}` (with a window, only its kept rows).
fn run_octaves(
    feed: Feed<'_>,
    plan: &Plan,
    geom: &RasterGeometry,
    range: Range<usize>,
    work: &mut Work<'_>,
    meter: &mut Meter,
) -> Result<Vec<i32>, EncodeError> {
    let mut octs: Vec<Octave> = range
        .clone()
        .map(|o| Octave::new(geom, plan, o))
        .collect::<Result<_, _>>()?;
    let (wk, hk) = plan.dims[range.end];
    // The whole last raster, allocated once (shards keep only their rows of it).
    let whole = matches!(feed, Feed::Source { window: None, .. }) as usize;
    let mut last: Vec<i32> = Vec::with_capacity(whole * wk * hk);
    let held = |octs: &[Octave], last: &Vec<i32>, reader: &Reader| {
        reader.bytes() + last.capacity() * 4 + octs.iter().map(Octave::bytes).sum::<usize>()
    };
    let advance = |octs: &mut Vec<Octave>,
                   last: &mut Vec<i32>,
                   reader: &Reader,
                   work: &mut Work<'_>,
                   meter: &mut Meter|
     -> Result<(), EncodeError> {
        for o in 0..octs.len() {
            let base = held(octs, last, reader);
            let (head, tail) = octs.split_at_mut(o + 1);
            let out = match tail.first_mut() {
                Some(next) => &mut next.rows,
                None => &mut *last,
            };
            head[o].advance(geom, out, work, meter, base)?;
        }
        meter.note(held(octs, last, reader));
        Ok(())
    };
    let (source, map, fill, window) = match feed {
        Feed::Rows(rows) => {
            let reader = Reader::empty();
            match octs.first_mut() {
                Some(o) => o.rows.extend_from_slice(rows),
                None => last.extend_from_slice(rows),
            }
            advance(&mut octs, &mut last, &reader, work, meter)?;
            if octs.iter().any(|o| !o.done()) || last.len() != wk * hk {
                return Err(EncodeError::Internal("rows left unprocessed"));
            }
            return Ok(last);
        }
        Feed::Source {
            source,
            map,
            fill,
            window,
        } => (source, map, fill, window),
    };
    if let Some(w) = window {
        for (o, allow) in octs.iter_mut().zip(&w.allow) {
            o.allow = Some(allow.clone());
        }
    }
    // Shards: rows of the last raster emitted so far, and those kept.
    let (mut emitted, mut kept) = (0, Vec::new());
    let mut reader = Reader::new(plan);
    let mut first = 0;
    while first < plan.height {
        let count = plan.chunk_rows.min(plan.height - first);
        let base = held(&octs, &last, &reader);
        let errors = match work {
            Work::Analyse { errors, .. } => Some(&mut **errors),
            Work::Code { .. } | Work::Visit(_) => None,
        };
        let target = match octs.first_mut() {
            Some(o) => &mut o.rows,
            None => &mut last,
        };
        if window.is_none_or(|w| w.read.contains(&first)) {
            if let Some(w) = window
                && first == w.read.start
            {
                reader.prime(source, first).map_err(EncodeError::reading)?;
            }
            let fill_bytes = reader.load(source, first, count, map, fill, errors, target)?;
            meter.note(base + fill_bytes);
        } else {
            target.resize(target.len() + count * plan.width, 0);
        }
        first += count;
        advance(&mut octs, &mut last, &reader, work, meter)?;
        if let Some(w) = window {
            for row in last.chunks_exact(wk) {
                if w.keep.contains(&emitted) {
                    kept.extend_from_slice(row);
                }
                emitted += 1;
            }
            last.clear();
        }
    }
    if octs.iter().any(|o| !o.done()) {
        return Err(EncodeError::Internal("rows left unprocessed"));
    }
    match window {
        Some(w) if emitted == hk && kept.len() == w.keep.len() * wk => Ok(kept),
        None if last.len() == wk * hk => Ok(last),
        _ => Err(EncodeError::Internal("rows left unprocessed")),
    }
}

/// Reads chunks of rows, fills their nodata and integerises them.
struct Reader {
    width: usize,
    /// Context rows (already filled) followed by the chunk being read.
    vals: Vec<f64>,
    valid: Vec<bool>,
    context: usize,
}

impl Reader {
    /// A reader that reads nothing (chains fed from memory).
    fn empty() -> Self {
        Reader {
            width: 0,
            vals: Vec::new(),
            valid: Vec::new(),
            context: 0,
        }
    }

    /// Starts reading at row `first` as a reader that had read every row before it would:
    /// its context rows, which the caller has checked hold no nodata (so their fills are
    /// their values).
    fn prime(&mut self, source: &mut dyn RowSource, first: usize) -> Result<(), IoError> {
        let w = self.width;
        let k = CONTEXT_ROWS.min(first);
        source.read_rows(first - k, k, &mut self.vals[..k * w])?;
        if self.vals[..k * w].iter().any(|v| !v.is_finite()) {
            return Err("a shard's fill context holds nodata".into());
        }
        self.context = k;
        Ok(())
    }

    fn new(plan: &Plan) -> Self {
        let len = (CONTEXT_ROWS + plan.chunk_rows) * plan.width;
        Reader {
            width: plan.width,
            vals: vec![0.0; len],
            valid: vec![false; len],
            context: 0,
        }
    }

    fn bytes(&self) -> usize {
        self.vals.capacity() * 8 + self.valid.capacity()
    }

    /// Reads rows `first .. first + count`, appends their integers to `out`; returns the
    /// bytes of the fill's work arrays (0 when nothing needed filling).
    #[allow(clippy::too_many_arguments)]
    fn load(
        &mut self,
        source: &mut dyn RowSource,
        first: usize,
        count: usize,
        map: &ValueMap,
        fill: &Fill,
        errors: Option<&mut Errors>,
        out: &mut Vec<i32>,
    ) -> Result<usize, EncodeError> {
        let w = self.width;
        let (ctx, total) = (self.context * w, (self.context + count) * w);
        source
            .read_rows(first, count, &mut self.vals[ctx..total])
            .map_err(EncodeError::reading)?;
        let (vals, valid) = (&mut self.vals[..total], &mut self.valid[..total]);
        valid[..ctx].iter_mut().for_each(|b| *b = true);
        valid[ctx..]
            .par_chunks_mut(PIECE)
            .zip(vals[ctx..].par_chunks(PIECE))
            .for_each(|(bs, vs)| {
                for (b, v) in bs.iter_mut().zip(vs) {
                    *b = v.is_finite();
                }
            });
        if let Some(e) = errors {
            // Fixed pieces in parallel, summed in order (deterministic).
            let pieces: Vec<(f64, f64)> = vals[ctx..]
                .par_chunks(PIECE)
                .map(|vs| {
                    let (mut sum2, mut max) = (0.0, 0.0f64);
                    for &v in vs.iter().filter(|v| v.is_finite()) {
                        let d = (map.offset + map.int_of(v) as f64 * map.scale - v).abs();
                        sum2 += d * d;
                        max = max.max(d);
                    }
                    (sum2, max)
                })
                .collect();
            for (p, (sum2, max)) in pieces.into_iter().enumerate() {
                let at = first * w + p * PIECE;
                match &mut e.pieces {
                    None => {
                        e.sum2 += sum2;
                        e.max = e.max.max(max);
                    }
                    Some((rows, kept)) => {
                        if rows.contains(&(at / w)) {
                            kept.push((at as u64, sum2));
                            e.max = e.max.max(max);
                        }
                    }
                }
            }
        }
        let fill_bytes = fill.rows(w, self.context, vals, valid);
        out.par_extend(
            vals[ctx..]
                .par_iter()
                .with_min_len(PIECE)
                .map(|&v| map.int_of(v)),
        );
        let keep = CONTEXT_ROWS.min(self.context + count);
        let from = total - keep * w;
        self.vals.copy_within(from..total, 0);
        self.context = keep;
        Ok(fill_bytes)
    }
}

/// Where a diamond's points are in an octave raster `R_o` (point `(x, y)` of `R_o` is
/// raster point `(x 2^o, y 2^o)`): vertex `(i, j)` at `v0 + i a + j b`, cell `(i, j)` at
/// vertex `(i, j)` + `(a + b) / 2`.
pub(crate) struct Frame {
    v0: [i64; 2],
    a: [i64; 2],
    b: [i64; 2],
}

impl Frame {
    pub(crate) fn of(s: &DiamondSlot, shift: u32) -> Self {
        let f = 1i64 << shift;
        let (v0, a, b) = s.frame();
        Frame {
            v0: [v0[0] / f, v0[1] / f],
            a: [a[0] / f, a[1] / f],
            b: [b[0] / f, b[1] / f],
        }
    }

    /// Buffer index of vertex (0,0), of cell (0,0), and the steps along `i` and `j`, in a
    /// buffer of rows `base..` of width `w`.
    fn lin(&self, base: usize, w: usize) -> [isize; 4] {
        let w = w as i64;
        let v0 = (self.v0[1] - base as i64) * w + self.v0[0];
        let c0 = v0 + ((self.a[1] + self.b[1]) / 2) * w + (self.a[0] + self.b[0]) / 2;
        let si = self.a[1] * w + self.a[0];
        let sj = self.b[1] * w + self.b[0];
        [v0 as isize, c0 as isize, si as isize, sj as isize]
    }

    pub(crate) fn gather_vertices(
        &self,
        n: usize,
        mask: Option<&DiamondMask>,
        buf: &[i32],
        base: usize,
        w: usize,
        v: &mut [i32],
    ) {
        let [v0, _, si, sj] = self.lin(base, w);
        if mask.is_none() {
            return read_lattice(buf, n + 1, v0, si, sj, v);
        }
        gather_strided(
            n + 1,
            v0,
            si,
            sj,
            |i, j| mask.is_none_or(|m| m.vertex(i, j)),
            buf,
            v,
        );
    }

    pub(crate) fn gather_cells(
        &self,
        n: usize,
        mask: Option<&DiamondMask>,
        buf: &[i32],
        base: usize,
        w: usize,
        c: &mut [i32],
    ) {
        let [_, c0, si, sj] = self.lin(base, w);
        if mask.is_none() {
            return read_lattice(buf, n, c0, si, sj, c);
        }
        gather_strided(
            n,
            c0,
            si,
            sj,
            |i, j| mask.is_none_or(|m| m.cell(i, j)),
            buf,
            c,
        );
    }

    /// Writes the interior vertices (all lifting changes).
    pub(crate) fn scatter_interior(
        &self,
        n: usize,
        mask: Option<&DiamondMask>,
        v: &[i32],
        buf: &mut [i32],
        base: usize,
        w: usize,
    ) {
        let [v0, _, si, sj] = self.lin(base, w);
        if mask.is_none() {
            return write_lattice(buf, 0, n + 1, 1, v0, si, sj, v);
        }
        scatter_strided(
            n + 1,
            1,
            (v0, si, sj),
            |i, j| mask.is_none_or(|m| m.vertex(i, j)),
            v,
            buf,
        );
    }
}

impl Frame {
    /// Writes every vertex (valid ones, with a mask) into rows from 0 of width `w`.
    pub(crate) fn scatter_all(
        &self,
        n: usize,
        mask: Option<&DiamondMask>,
        v: &[i32],
        buf: &mut [i32],
        w: usize,
    ) {
        let [v0, _, si, sj] = self.lin(0, w);
        scatter_strided(
            n + 1,
            0,
            (v0, si, sj),
            |i, j| mask.is_none_or(|m| m.vertex(i, j)),
            v,
            buf,
        );
    }

    /// Writes the cells (valid ones, with a mask).
    pub(crate) fn scatter_cells(
        &self,
        n: usize,
        mask: Option<&DiamondMask>,
        c: &[i32],
        buf: &mut [i32],
        base: usize,
        w: usize,
    ) {
        let [_, c0, si, sj] = self.lin(base, w);
        if mask.is_none() {
            return write_lattice(buf, 0, n, 0, c0, si, sj, c);
        }
        scatter_strided(
            n,
            0,
            (c0, si, sj),
            |i, j| mask.is_none_or(|m| m.cell(i, j)),
            c,
            buf,
        );
    }
}

/// The diamonds of octave `o`'s two levels, grouped by rows of `R_o`: `(level_a,
/// level_b, a_groups, b_groups)` (see [`Octave`]).
pub(crate) type OctaveGroups = (usize, usize, Vec<Vec<usize>>, Vec<Vec<usize>>);

/// Writes points `margin .. side - margin` of a `side x side` grid `values` (row-major)
/// where `valid(i, j)`, point `(i, j)` at buffer index `start + i si + j sj`.
fn scatter_strided(
    side: usize,
    margin: usize,
    (start, si, sj): (isize, isize, isize),
    valid: impl Fn(usize, usize) -> bool,
    values: &[i32],
    buf: &mut [i32],
) {
    for i in margin..side - margin {
        let row = start + i as isize * si;
        for j in margin..side - margin {
            if valid(i, j) {
                buf[(row + j as isize * sj) as usize] = values[i * side + j];
            }
        }
    }
}

/// Reads a `side x side` lattice starting at buffer index `start` with steps `si`, `sj`
/// into `out` (row-major); points where `valid(i, j)` is false read as 0.
fn gather_strided(
    side: usize,
    start: isize,
    si: isize,
    sj: isize,
    valid: impl Fn(usize, usize) -> bool,
    buf: &[i32],
    out: &mut [i32],
) {
    for (i, row) in out.chunks_exact_mut(side).enumerate() {
        let row_start = start + i as isize * si;
        for (j, x) in row.iter_mut().enumerate() {
            *x = if valid(i, j) {
                buf[(row_start + j as isize * sj) as usize]
            } else {
                0
            };
        }
    }
}

/// Groups octave `o`'s diamonds by rows of `R_o` (see [`Octave`]) and checks that their
/// points lie on `R_o`.
pub(crate) fn octave_groups(
    geom: &RasterGeometry,
    n: usize,
    o: usize,
) -> Result<OctaveGroups, EncodeError> {
    let levels = geom.detail_levels();
    let (level_a, level_b) = (levels - 1 - 2 * o, levels - 2 - 2 * o);
    let f = 1i64 << o;
    let ni = n as i64;
    let mut a_groups: Vec<Vec<usize>> = Vec::new();
    for (i, s) in geom.level(level_a).iter().enumerate() {
        let cy = s.id.y / f;
        if cy < 0 || cy % ni != 0 {
            return Err(EncodeError::Internal("level A centre off its lattice"));
        }
        let g = (cy / ni) as usize;
        if a_groups.len() <= g {
            a_groups.resize(g + 1, Vec::new());
        }
        a_groups[g].push(i);
    }
    let mut b_groups: Vec<Vec<usize>> = Vec::new();
    for (i, s) in geom.level(level_b).iter().enumerate() {
        let cy = s.id.y / f;
        if cy < ni || (cy - ni) % (2 * ni) != 0 {
            return Err(EncodeError::Internal("level B centre off its lattice"));
        }
        let j = ((cy - ni) / (2 * ni)) as usize;
        if b_groups.len() <= j {
            b_groups.resize(j + 1, Vec::new());
        }
        b_groups[j].push(i);
    }
    // Every point of these levels must lie on the 2^o lattice, i.e. in `R_o`.
    let on_lattice = |s: &DiamondSlot| {
        let (v0, a, b) = s.frame();
        v0.iter()
            .chain(&a)
            .chain(&b)
            .chain(&[(a[0] + b[0]) / 2, (a[1] + b[1]) / 2])
            .all(|c| c % f == 0)
    };
    if !geom.level(level_a).iter().all(on_lattice) || !geom.level(level_b).iter().all(on_lattice) {
        return Err(EncodeError::Internal(
            "octave points off the decimated lattice",
        ));
    }
    Ok((level_a, level_b, a_groups, b_groups))
}

/// One octave of the chain: levels `A = 2k - 1 - 2o` (rotated, refines the quincunx of
/// `R_o` into all its points) and `B = A - 1` (axis-aligned, refines `2Z^2` into the
/// quincunx), over a rolling window of rows of `R_o`. Its output, the even rows and
/// columns, is `R_{o+1}`.
///
/// Row spans in `R_o` (`N` = diamond size): an `A` diamond centred on row `cy` (a multiple
/// of `N`, group `g = cy / N`) spans rows `cy - N ..= cy + N` and changes rows strictly
/// between; `B` diamonds of band `j` span rows `2Nj ..= 2N(j+1)` and need the `A` groups
/// `2j ..= 2j + 2` done first. After band `j`, rows up to `2N(j+1)` are final.
struct Octave {
    shift: u32,
    width: usize,
    height: usize,
    n: usize,
    level_a: usize,
    level_b: usize,
    a_groups: Vec<Vec<usize>>,
    b_groups: Vec<Vec<usize>>,
    next_a: usize,
    next_b: usize,
    /// Rows `base .. base + rows.len() / width` of `R_o`.
    rows: Vec<i32>,
    base: usize,
    /// Next row of `R_o` that may be emitted (even rows only are).
    next_emit: usize,
    /// Shards: the `A` groups and `B` bands analysed (the others are skipped: their rows
    /// are outside the shard's window or depend on rows that are).
    allow: Option<(Range<usize>, Range<usize>)>,
}

impl Octave {
    fn new(geom: &RasterGeometry, plan: &Plan, o: usize) -> Result<Self, EncodeError> {
        let n = plan.n;
        let (level_a, level_b, a_groups, b_groups) = octave_groups(geom, n, o)?;
        let (width, height) = plan.dims[o];
        Ok(Octave {
            shift: o as u32,
            width,
            height,
            n,
            level_a,
            level_b,
            a_groups,
            b_groups,
            next_a: 0,
            next_b: 0,
            rows: Vec::with_capacity(plan.caps[o] * width),
            base: 0,
            next_emit: 0,
            allow: None,
        })
    }

    fn bytes(&self) -> usize {
        self.rows.capacity() * 4
    }

    fn loaded(&self) -> usize {
        self.base + self.rows.len() / self.width
    }

    fn done(&self) -> bool {
        self.next_a == self.a_groups.len()
            && self.next_b == self.b_groups.len()
            && self.next_emit >= self.height
    }

    /// Analyses every diamond whose rows are final, emits the final even rows to `out`
    /// (the next octave's window, or `R_k`), and drops rows nothing needs any more.
    fn advance(
        &mut self,
        geom: &RasterGeometry,
        out: &mut Vec<i32>,
        work: &mut Work<'_>,
        meter: &mut Meter,
        held: usize,
    ) -> Result<(), EncodeError> {
        let n = self.n;
        loop {
            let loaded = self.loaded();
            if self.next_a < self.a_groups.len() {
                let g = self.next_a;
                if loaded >= (n * (g + 1) + 1).min(self.height) {
                    if self.allow.as_ref().is_none_or(|(a, _)| a.contains(&g)) {
                        let group = std::mem::take(&mut self.a_groups[g]);
                        self.run(geom, self.level_a, &group, work, meter, held)?;
                        self.a_groups[g] = group;
                    }
                    self.next_a += 1;
                    continue;
                }
            }
            if self.next_b < self.b_groups.len()
                && self.next_a >= (2 * self.next_b + 3).min(self.a_groups.len())
            {
                let j = self.next_b;
                if self.allow.as_ref().is_none_or(|(_, b)| b.contains(&j)) {
                    let group = std::mem::take(&mut self.b_groups[j]);
                    self.run(geom, self.level_b, &group, work, meter, held)?;
                    self.b_groups[j] = group;
                }
                self.next_b += 1;
                self.emit(out);
                continue;
            }
            break;
        }
        self.emit(out);
        // Keep the rows of the next A group and the next B band.
        let mut keep = self.loaded();
        if self.next_a < self.a_groups.len() {
            keep = keep.min((n * self.next_a).saturating_sub(n));
        }
        if self.next_b < self.b_groups.len() {
            keep = keep.min(2 * n * self.next_b);
        }
        if keep > self.base {
            self.rows.drain(..(keep - self.base) * self.width);
            self.base = keep;
        }
        Ok(())
    }

    /// Appends the final even rows (even columns) to `out`.
    fn emit(&mut self, out: &mut Vec<i32>) {
        let all = self.next_a == self.a_groups.len()
            && self.next_b == self.b_groups.len()
            && self.loaded() == self.height;
        let end = if all {
            self.height
        } else if self.next_b > 0 {
            (2 * self.n * self.next_b + 1).min(self.height)
        } else {
            0
        };
        while self.next_emit < end {
            let r = self.next_emit;
            if r.is_multiple_of(2) {
                let start = (r - self.base) * self.width;
                let row = &self.rows[start..start + self.width];
                out.extend(row.iter().step_by(2));
            }
            self.next_emit += 1;
        }
    }

    /// Analyses diamonds `group` of `level`, in batches of [`BATCH`] in parallel.
    fn run(
        &mut self,
        geom: &RasterGeometry,
        level: usize,
        group: &[usize],
        work: &mut Work<'_>,
        meter: &mut Meter,
        held: usize,
    ) -> Result<(), EncodeError> {
        let n = self.n;
        let slots = geom.level(level);
        let levels = geom.detail_levels();
        let coder: Option<(&Side, &CodecModel)> = match &*work {
            Work::Code { side, model, .. } => Some((*side, *model)),
            Work::Analyse { .. } | Work::Visit(_) => None,
        };
        let measuring = matches!(work, Work::Analyse { .. });
        for batch in group.chunks(BATCH) {
            let (rows, base, width, shift) = (&self.rows, self.base, self.width, self.shift);
            let results: Vec<Analysed> = batch
                .par_iter()
                .map(|&i| {
                    let s = &slots[i];
                    let mask = s.mask.as_ref();
                    let f = Frame::of(s, shift);
                    let mut v = vec![0; (n + 1) * (n + 1)];
                    let mut c = vec![0; n * n];
                    let mut h = vec![0; n * n];
                    f.gather_vertices(n, mask, rows, base, width, &mut v);
                    f.gather_cells(n, mask, rows, base, width, &mut c);
                    let fine = measuring.then(|| v.clone());
                    lifting::analyze(n, &mut v, &c, &mut h, mask);
                    let m = fine.map(|fine| measure(n, mask, &v, &fine, &c));
                    let blob = coder.and_then(|(side, model)| {
                        side.has_data[level][i].then(|| {
                            blob::encode(
                                &geom.blob_context(level, i),
                                model,
                                &side.classes(geom, level, i),
                                &h,
                            )
                        })
                    });
                    Analysed { v, h, m, blob }
                })
                .collect();
            let in_flight: usize = results
                .iter()
                .map(|r| {
                    4 * (r.v.len() + r.h.len() + (2 * (n + 1) * (n + 1) + n * n))
                        + r.blob.as_ref().map_or(0, Vec::len)
                })
                .sum();
            meter.note(held + in_flight);
            for (&i, r) in batch.iter().zip(&results) {
                let s = &slots[i];
                Frame::of(s, self.shift).scatter_interior(
                    n,
                    s.mask.as_ref(),
                    &r.v,
                    &mut self.rows,
                    self.base,
                    self.width,
                );
            }
            match work {
                Work::Analyse { side, keep, .. } => {
                    for (&i, r) in batch.iter().zip(&results) {
                        let m =
                            r.m.as_ref()
                                .ok_or(EncodeError::Internal("missing measure"))?;
                        let own = r.h.iter().any(|&x| x != 0);
                        let kids: &[usize] = if level + 1 < levels {
                            &slots[i].children
                        } else {
                            &[]
                        };
                        let (gamma, data, bound) = {
                            let side: &Side = side;
                            side_info(
                                m,
                                own,
                                kids.iter().map(|&k| {
                                    (
                                        side.gamma[level + 1][k],
                                        side.has_data[level + 1][k],
                                        side.bounds[level + 1][k],
                                    )
                                }),
                            )
                        };
                        side.gamma[level][i] = gamma;
                        side.has_data[level][i] = data;
                        side.bounds[level][i] = bound;
                        if let Some(keep) = keep.as_mut() {
                            keep.analysed[level][i] = true;
                            if (keep.owns)(level, i) {
                                if kids.iter().any(|&k| !keep.analysed[level + 1][k]) {
                                    return Err(EncodeError::Internal(
                                        "a shard's diamond lacks an analysed child (halo too small)",
                                    ));
                                }
                                if data {
                                    (keep.details)(level, i, &r.h).map_err(EncodeError::writing)?;
                                }
                            }
                        }
                    }
                    let group_ctx = entropy::group(levels - 1 - level);
                    let side_ref: &Side = side;
                    let owns = keep.as_ref().map(|k| k.owns);
                    let counts = batch
                        .par_iter()
                        .zip(&results)
                        .filter(|(i, _)| {
                            side_ref.trains(geom, level, **i) && owns.is_none_or(|o| o(level, **i))
                        })
                        .fold(ContextCounts::default, |mut acc, (&i, r)| {
                            entropy::write_matrix(
                                &mut acc,
                                group_ctx,
                                n,
                                &r.h,
                                slots[i].mask.as_ref().map(DiamondMask::cells),
                                // Exact modes only: no quantised level hides signs.
                                false,
                            );
                            acc
                        })
                        .reduce(ContextCounts::default, |mut a, b| {
                            a.merge(&b);
                            a
                        });
                    side.counts.merge(&counts);
                }
                Work::Code { sink, coded, .. } => {
                    for (&i, r) in batch.iter().zip(&results) {
                        if let Some(b) = &r.blob {
                            sink.put(level, i, &slots[i].key, b)
                                .map_err(EncodeError::writing)?;
                            coded.count += 1;
                            coded.bytes += b.len();
                        }
                    }
                }
                Work::Visit(visitor) => {
                    let details: Vec<&[i32]> = results.iter().map(|r| &r.h[..]).collect();
                    visitor.visit(geom, level, batch, &details)?;
                }
            }
        }
        Ok(())
    }
}

/// One analysed diamond.
struct Analysed {
    /// Coarse vertex values.
    v: Vec<i32>,
    /// Details.
    h: Vec<i32>,
    /// Side-information measure (pass 1).
    m: Option<Measure>,
    /// Coded blob (pass 2, diamonds with data).
    blob: Option<Vec<u8>>,
}
