//! Out-of-core encoder of planets: the cube raster lives in tiles of a [`TileStore`]
//! (a file, for `quincunx build`), a bounded cache of them in memory.
//!
//! Why it works: a detail level's diamonds never touch each other's written points (their
//! interiors are disjoint; they only read shared borders), so a level can be analysed in
//! any order, a batch of diamonds at a time, each batch reading and writing only the tiles
//! its diamonds' points lie in. The batches follow the tiles (row of tiles by row of
//! tiles, face by face), so the cache holds about two rows of tiles of a face, plus the
//! tiles beside the cube edges that the diamonds straddling them reach on the other face.
//! After the two levels of an octave only every second point of every second row is read
//! again, so the tiles are compacted into a raster of a quarter the size (`R_o`), and
//! every octave's diamonds span about `2N` points of its own raster.
//!
//! Passes over the source, face by face, rows in order: (0) range, quantum, coverage and
//! the canonical copies of the cube-edge points; (1) the integers, written as tiles, with
//! the errors of the integerisation. Then the analysis (details to an [`IndexSpill`],
//! side information as it goes up the levels), the model, every blob to the sink, and
//! on request ([`CubeOptions::keep_decoded`]) the decoded raster left in the tiles.
//!
//! RMS mode runs the in-memory encoder's search ([`crate::encode::search_scale`]) with a
//! verifier out of core (`CubeVerifier`): the analysis' details stay in slot 0 of the
//! spill; each verification decode quantises them into its own slot while it synthesises
//! through the tiles coarse to fine (each octave's raster expanded from the next coarser
//! one, the inverse of the compaction), measures every diamond, and reads the source once
//! more to measure the decoded integers against it. The kept attempt's indices and
//! measures give the side information and the blobs.
//!
//! The bytes equal the in-memory planet encoder's ([`crate::encode::encode_sphere`]) in
//! every rate mode when the source has no nodata inside covered blocks: the same
//! integers, the same diamonds, the same errors summed in the same pieces and order, the
//! same model. Nodata is filled band by band of a face with push-pull (as the planar
//! streaming encoder does), where the in-memory encoder fills whole faces, so voids'
//! fills may differ.

use crate::stream::IoError;
use std::borrow::Cow;
use std::collections::HashMap;
use std::ops::Range;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use super::rms::{Histograms, Spill};
use super::{BlobSink, Fill, IndexSpill, Meter, Scan};
use crate::coverage::{Coverage, CubeCoverage};
use crate::encode::{
    Attempt, EncodeError, EncodeReport, Encoded, EncodedDomain, Measure, PASS_CHUNK, Quantise,
    RateMode, RdoMode, SideInfo, Tally, ValueMap, Verifier, blob_model, check_tolerance, code_blob,
    dequantize, measure, rms_of_pieces, search_scale, side_info, side_information, train_model,
};
use crate::entropy::CodecModel;
use crate::lifting;
use crate::raster::{EncodeLayout, Layout};
use crate::sphere_raster::SphereGeometry;

mod shard;
pub use shard::{CubeMerge, encode_cube_shard};

/// A planet's heights, read a band of rows of one face at a time. Faces are read in
/// order, rows in order within a face; a source is read more than once (two passes, and
/// one more per verification decode in RMS mode).
pub trait CubeSource {
    /// Samples per face side `2S` (`N 2^k`).
    fn face_side(&self) -> usize;
    /// Fills `out` (`count x (face_side + 1)`) with face `face`'s rows
    /// `first .. first + count` in metres (cube-raster order, see
    /// [`crate::sphere_raster`]), NaN = nodata. Copies of cube-edge points need not agree:
    /// the lowest face's copy is used.
    fn read_face_rows(
        &mut self,
        face: usize,
        first: usize,
        count: usize,
        out: &mut [f64],
    ) -> Result<(), IoError>;
    /// Known quantum, like [`crate::encode::CubeGrid::quantum_m`].
    fn quantum_m(&self) -> Option<f64>;
}

/// Where the encoder keeps the cube raster's tiles: `i32` values at offsets counted in
/// values. Reads only what was written.
pub trait TileStore: Send {
    /// Reads `out.len()` values from `offset`.
    fn read(&mut self, offset: u64, out: &mut [i32]) -> Result<(), IoError>;
    /// Writes `data` at `offset`.
    fn write(&mut self, offset: u64, data: &[i32]) -> Result<(), IoError>;
}

/// Tiles in memory (tests; small planets).
#[derive(Default)]
pub struct MemoryTiles(Vec<i32>);

impl TileStore for MemoryTiles {
    fn read(&mut self, offset: u64, out: &mut [i32]) -> Result<(), IoError> {
        let start = offset as usize;
        let src = self
            .0
            .get(start..start + out.len())
            .ok_or("read past the tiles written")?;
        out.copy_from_slice(src);
        Ok(())
    }

    fn write(&mut self, offset: u64, data: &[i32]) -> Result<(), IoError> {
        let start = offset as usize;
        if self.0.len() < start + data.len() {
            self.0.resize(start + data.len(), 0);
        }
        self.0[start..start + data.len()].copy_from_slice(data);
        Ok(())
    }
}

/// Settings of the out-of-core planet encoder.
#[derive(Clone, Copy, Debug)]
pub struct CubeOptions {
    /// Diamond size `N`.
    pub n: usize,
    /// Any rate mode.
    pub mode: RateMode,
    /// Bound on the sample buffers held at once (row bands, the tile cache, diamonds in
    /// flight). The geometry's tables and a few bytes per diamond come on top.
    pub memory_budget_bytes: usize,
    /// Sparse mode: blocks without data are holes.
    pub sparse: bool,
    /// Rate-distortion quantisation in the RMS mode.
    pub rdo: RdoMode,
    /// Leave the decoded cube raster in the [`TileStore`] at the end (one more synthesis;
    /// see [`CubeEncoded::decoded`]).
    pub keep_decoded: bool,
}

/// Everything a decoder needs besides the blobs (which went to the [`BlobSink`]).
#[derive(Clone, Debug)]
pub struct CubeEncoded {
    /// Samples per face side.
    pub face_side: usize,
    /// Diamond size.
    pub n: usize,
    /// Metres per integer unit.
    pub value_scale_m: f64,
    /// Metres at integer 0.
    pub value_offset_m: f64,
    /// Quantiser step per detail level (1/256 units; all 256 in the exact modes).
    pub steps: Vec<u32>,
    /// The six root vertex grids.
    pub roots: Vec<Vec<i32>>,
    /// Trained starting probabilities.
    pub model: CodecModel,
    /// Measured results.
    pub report: EncodeReport,
    /// Largest number of bytes of sample buffers held at once.
    pub peak_buffer_bytes: usize,
    /// Bytes of tiles written to the [`TileStore`] at most (its size).
    pub tile_store_bytes: u64,
    /// The coverage (sparse mode).
    pub coverage: Option<Coverage>,
    /// With [`CubeOptions::keep_decoded`]: where the decoded integers are.
    pub decoded: Option<DecodedTiles>,
}

/// The decoded integers of a planet, left by [`encode_cube`] in its [`TileStore`] (what a
/// decoder of the blobs gives, every copy of every point).
#[derive(Clone, Copy, Debug)]
pub struct DecodedTiles {
    face_side: usize,
    t: usize,
}

impl DecodedTiles {
    /// Reads face `face`'s rows `first .. first + count` (`count x (face_side + 1)`
    /// integers, cube-raster order) from `tiles`.
    pub fn read_rows(
        &self,
        tiles: &mut dyn TileStore,
        (face, first, count): (usize, usize, usize),
        out: &mut [i32],
    ) -> Result<(), IoError> {
        let w = self.face_side + 1;
        if face >= 6 || first + count > w || out.len() != count * w {
            return Err(format!(
                "rows {first}..{} of face {face} into {} values: outside a cube of face side {}",
                first + count,
                out.len(),
                self.face_side
            )
            .into());
        }
        Lattice::new(self.face_side, self.t, 0, 0).read_rows(tiles, (face, first, count), out)
    }
}

impl CubeEncoded {
    /// The in-memory form, with the blobs the sink received (`blobs[level][index]`).
    pub fn into_encoded(self, blobs: Vec<Vec<Option<Vec<u8>>>>) -> Encoded {
        Encoded {
            domain: EncodedDomain::Sphere {
                face_side: self.face_side,
            },
            width: self.face_side + 1,
            height: 6 * (self.face_side + 1),
            n: self.n,
            value_scale_m: self.value_scale_m,
            value_offset_m: self.value_offset_m,
            steps: self.steps,
            root: Vec::new(),
            roots: self.roots,
            model: self.model,
            blobs,
            coverage: self.coverage,
            report: self.report,
        }
    }
}

/// Diamonds analysed in one batch at most.
const BATCH: usize = 256;
/// Filled rows of a face kept as context for the next band's fill.
const CONTEXT_ROWS: usize = super::CONTEXT_ROWS;

/// The phases [`encode_cube`] reports as it ends each: pass 0, pass 1, the analysis, the
/// RMS rate control's search (nothing in the exact modes), and the side information,
/// model and blobs.
pub const CUBE_PHASES: [&str; 5] = ["scan", "integers", "analysis", "rate control", "coding"];

/// Encodes a planet out of core (see the module docs). `phase(name)` is called as each
/// of [`CUBE_PHASES`] ends (for a caller's timings).
pub fn encode_cube(
    source: &mut dyn CubeSource,
    opts: CubeOptions,
    sink: &mut dyn BlobSink,
    spill: &mut dyn IndexSpill,
    tiles: &mut dyn TileStore,
    phase: &mut dyn FnMut(&'static str),
) -> Result<CubeEncoded, EncodeError> {
    let (face_side, n) = (source.face_side(), opts.n);
    let mut meter = Meter::default();
    let Scanned {
        geom,
        borders,
        tile,
        coverage,
        map,
        fill,
        ..
    } = scan_cube(source, opts, &mut meter)?;
    phase(CUBE_PHASES[0]);

    // Pass 1: the integers, as tiles of R_0, and the integerisation's errors.
    let lattice = Lattice::new(face_side, tile, 0, 0);
    let errors = write_integers(
        source,
        &geom,
        &borders,
        (&map, &fill),
        (&lattice, None, None),
        tiles,
        &mut meter,
    )?;
    let tile_store_bytes = (lattice.len() + Lattice::new(face_side, tile, 1, 0).len()) * 4;
    phase(CUBE_PHASES[1]);

    // The analysis, octave by octave.
    let levels = geom.slot_levels().len();
    let (mut store, mut side) = analysis_state(&geom, spill)?;
    let mut hist = matches!(opts.mode, RateMode::RmsM(_)).then(|| Histograms::new(levels));
    let cache_bytes = opts.memory_budget_bytes / 2;
    let second = lattice.len();
    let lattice = analyse_octaves(
        &geom,
        (0..levels / 2, lattice, (second, cache_bytes)),
        tiles,
        (&mut store, &mut *spill),
        (&mut side, hist.as_mut()),
        None,
        &mut meter,
    )?;
    let roots = gather_roots(&geom, &lattice, cache_bytes, tiles, &mut meter)?;

    phase(CUBE_PHASES[2]);

    // The RMS rate control: the search of the in-memory encoder, each verification
    // decode a synthesis through the tiles (see `CubeVerifier`).
    let (pieces, valid_count) = errors;
    let pieces: Vec<(f64, f64)> = pieces.into_iter().map(|p| p.1).collect();
    let mut rate = Rate {
        steps: vec![256u32; levels],
        errors: rms_of_pieces(&pieces, valid_count),
        rdo: false,
        decodes: 0,
    };
    let (side, kept) = match (opts.mode, hist) {
        (RateMode::RmsM(target), Some(hist)) => {
            let mut verifier = CubeVerifier {
                synth: Synth {
                    geom: &geom,
                    roots: &roots,
                    tiles: &mut *tiles,
                    spill: &mut *spill,
                    shape: (tile, second),
                    cache_bytes,
                    meter: &mut meter,
                },
                source,
                borders: &borders,
                map: &map,
                details: &store,
                last: Spill::with_levels(n, 1, (0..levels).map(|l| geom.level(l).len())),
                kept: Spill::with_levels(n, 2, (0..levels).map(|l| geom.level(l).len())),
                valid_count,
            };
            let unit = verifier.source.quantum_m().unwrap_or(map.scale);
            let out = search_scale(
                n,
                &hist.finish(),
                (target, unit, map.scale),
                valid_count,
                opts.rdo,
                &mut verifier,
            )?;
            let kept = verifier.kept;
            let side = side_information(&geom, |l, i| kept.has(l, i), &out.measures);
            rate = Rate {
                steps: out.steps,
                errors: out.errors,
                rdo: out.rdo_used,
                decodes: out.decodes,
            };
            (side, kept)
        }
        _ => (SideInfo::from_parts(side.gamma, side.has_data), store),
    };
    phase(CUBE_PHASES[3]);

    // The model and the blobs.
    let steps = rate.steps;
    let (model, count, bytes) = code_blobs(&geom, &steps, &side, &kept, spill, sink)?;
    let decoded = if opts.keep_decoded {
        let mut synth = Synth {
            geom: &geom,
            roots: &roots,
            tiles,
            spill,
            shape: (tile, second),
            cache_bytes,
            meter: &mut meter,
        };
        synth.run(&steps, Indices::Coded(&kept))?;
        Some(DecodedTiles { face_side, t: tile })
    } else {
        None
    };
    phase(CUBE_PHASES[4]);
    let report = EncodeReport::tally(Tally {
        samples: geom.distinct_len(),
        valid_samples: valid_count,
        blobs: (count, bytes),
        roots: &roots,
        model: &model,
        steps: steps.len(),
        errors: rate.errors,
        rdo: rate.rdo,
        decodes: rate.decodes,
    });
    Ok(CubeEncoded {
        face_side,
        n,
        value_scale_m: map.scale,
        value_offset_m: map.offset,
        steps,
        roots,
        model,
        report,
        peak_buffer_bytes: meter.peak,
        tile_store_bytes: tile_store_bytes as u64,
        coverage,
        decoded,
    })
}

/// What pass 0 learns: the geometry (with the coverage in sparse mode), the value map,
/// the fill, the range and sum (which a shard's parts must agree on), the canonical
/// copies of the edge points, and the valid canonical entries (the samples counted).
struct Scanned {
    geom: SphereGeometry,
    borders: Borders,
    /// The tile side.
    tile: usize,
    coverage: Option<Coverage>,
    map: ValueMap,
    fill: Fill,
    range: [f64; 3],
    canon: HashMap<usize, f64>,
    counted: usize,
}

/// Checks the settings and runs pass 0: range, quanta, coverage, the canonical copies
/// of edge points.
fn scan_cube(
    source: &mut dyn CubeSource,
    opts: CubeOptions,
    meter: &mut Meter,
) -> Result<Scanned, EncodeError> {
    check_tolerance(opts.mode)?;
    let face_side = source.face_side();
    let geom = SphereGeometry::new(face_side, opts.n)?;
    let w = face_side + 1;
    let tile = tile_side(w, opts.memory_budget_bytes)?;
    let borders = Borders::new(&geom);
    let mut coverage = opts.sparse.then(|| CubeCoverage::new(face_side, opts.n));
    let mut scan = Scan::new(source.quantum_m());
    let mut canon = HashMap::new();
    let mut vals = vec![0.0; tile * w];
    meter.note(vals.len() * 8);
    for face in 0..6 {
        for first in (0..w).step_by(tile) {
            let count = tile.min(w - first);
            let band = &mut vals[..count * w];
            read_band(source, &borders, &mut canon, (face, first, count), band)?;
            if let Some(cov) = coverage.as_mut() {
                for (r, row) in band.chunks_exact(w).enumerate() {
                    cov.mark_row(face, first + r, |u| row[u].is_finite());
                }
            }
            scan.add(band);
        }
    }
    if scan.valid == 0 {
        return Err(EncodeError::AllNodata);
    }
    // The valid samples, one copy of each edge point: a copy is valid when its canonical
    // one is, whose value it took.
    let copies = borders.copies.iter().flatten();
    let counted = scan.valid
        - copies
            .filter(|&&(_, _, k)| canon.get(&k).is_some_and(|v| v.is_finite()))
            .count();
    let coverage = coverage.map(CubeCoverage::finish);
    let geom = match &coverage {
        Some(c) => geom.covered(c)?,
        None => geom,
    };
    let (map, fill) = scan.mapping(source.quantum_m(), opts.mode)?;
    Ok(Scanned {
        geom,
        borders,
        tile,
        coverage,
        map,
        fill,
        range: [scan.lo, scan.hi, scan.sum],
        canon,
        counted,
    })
}

/// An empty spill of every diamond's details of `geom` (slot 0 of `spill`, cleared).
fn detail_spill(geom: &SphereGeometry, spill: &mut dyn IndexSpill) -> Result<Spill, EncodeError> {
    let lens = (0..geom.slot_levels().len()).map(|l| geom.level(l).len());
    let mut store = Spill::with_levels(geom.n(), 0, lens);
    store.clear(spill)?;
    Ok(store)
}

/// An empty spill of details (slot 0 of `spill`, cleared) and side information, for an
/// analysis of `geom`.
fn analysis_state(
    geom: &SphereGeometry,
    spill: &mut dyn IndexSpill,
) -> Result<(Spill, Side), EncodeError> {
    let levels = geom.slot_levels().len();
    let store = detail_spill(geom, spill)?;
    let side = Side {
        gamma: vec![Vec::new(); levels],
        has_data: vec![Vec::new(); levels],
        bounds: Vec::new(),
    };
    Ok((store, side))
}

/// The raster `R_o` of octave `o` in the tile store: even octaves from offset 0, odd
/// ones from `second` (each is compacted from the previous one).
fn lattice_at(face_side: usize, t: usize, o: usize, second: usize) -> Lattice {
    Lattice::new(face_side, t, o, if o % 2 == 1 { second } else { 0 })
}

/// What a shard analyses (see [`shard`]): per octave, the tiles of `R_o` it holds; per
/// level, the diamonds.
struct Only {
    tiles: Vec<Vec<bool>>,
    diamonds: Vec<Vec<bool>>,
}

/// Analyses `octaves` (a range of them, `R_start` in the tiles as `lattice`), compacting
/// each octave's raster into the next one's; the last octave's raster, flushed to the
/// tiles. With `only`, just the diamonds and tiles it names.
fn analyse_octaves(
    geom: &SphereGeometry,
    (octaves, mut lattice, (second, cache_bytes)): (Range<usize>, Lattice, (usize, usize)),
    tiles: &mut dyn TileStore,
    (store, spill): (&mut Spill, &mut dyn IndexSpill),
    (side, mut hist): (&mut Side, Option<&mut Histograms>),
    only: Option<&Only>,
    meter: &mut Meter,
) -> Result<Lattice, EncodeError> {
    let levels = geom.slot_levels().len();
    let (face_side, t) = (geom.face_side(), lattice.t);
    let mut cache = Cache::new(&lattice, cache_bytes);
    for o in octaves.clone() {
        if o > octaves.start {
            let next = lattice_at(face_side, t, o, second);
            cache.flush(&lattice, tiles)?;
            let present = only.map(|w| (&w.tiles[o - 1][..], &w.tiles[o][..]));
            compact(&lattice, &next, tiles, meter, present)?;
            lattice = next;
            cache = Cache::new(&lattice, cache_bytes);
        }
        for level in [levels - 1 - 2 * o, levels - 2 - 2 * o] {
            analyse_level(
                geom,
                level,
                (&lattice, &mut cache, &mut *tiles),
                (&mut *store, &mut *spill),
                (&mut *side, hist.as_deref_mut()),
                only.map(|w| &w.diamonds[level][..]),
                meter,
            )?;
        }
    }
    cache.flush(&lattice, tiles)?;
    Ok(lattice)
}

/// The six root vertex grids from the last octave's raster (a few tiles per face).
fn gather_roots(
    geom: &SphereGeometry,
    lattice: &Lattice,
    cache_bytes: usize,
    tiles: &mut dyn TileStore,
    meter: &mut Meter,
) -> Result<Vec<Vec<i32>>, EncodeError> {
    let mut cache = Cache::new(lattice, cache_bytes);
    let all: Vec<usize> = (0..lattice.tiles()).collect();
    cache.ensure(lattice, &all, tiles)?;
    meter.note(cache.held_bytes());
    let missed = AtomicBool::new(false);
    let roots = geom.gather_roots_with(|k| cache.get(lattice, k, &missed));
    if missed.load(Ordering::Relaxed) {
        return Err(EncodeError::Internal(
            "a root vertex outside the loaded tiles",
        ));
    }
    Ok(roots)
}

/// Trains the model on every diamond's indices (in `kept`) and codes every blob into
/// `sink`, in level order: the model, the blobs coded and their bytes.
fn code_blobs(
    geom: &SphereGeometry,
    steps: &[u32],
    side: &SideInfo,
    kept: &Spill,
    spill: &dyn IndexSpill,
    sink: &mut dyn BlobSink,
) -> Result<(CodecModel, usize, usize), EncodeError> {
    let n = geom.n();
    let levels = geom.slot_levels().len();
    let failed: Mutex<Option<EncodeError>> = Mutex::new(None);
    let matrix = |l: usize, i: usize| -> Vec<i32> {
        kept.matrix(spill, l, i).unwrap_or_else(|e| {
            if let Ok(mut f) = failed.lock() {
                f.get_or_insert(e);
            }
            vec![0; n * n]
        })
    };
    let model = blob_model(geom, steps, &|l, i| Cow::Owned(matrix(l, i)), side);
    let (mut count, mut bytes) = (0usize, 0usize);
    for l in 0..levels {
        let len = geom.level(l).len();
        for start in (0..len).step_by(4 * BATCH) {
            let coded: Vec<(usize, Option<Vec<u8>>)> = (start..(start + 4 * BATCH).min(len))
                .into_par_iter()
                .map(|i| {
                    let blob = side.has_data[l][i]
                        .then(|| code_blob(geom, steps, &model, &matrix(l, i), side, l, i));
                    (i, blob.flatten())
                })
                .collect();
            for (i, blob) in coded {
                if let Some(b) = blob {
                    count += 1;
                    bytes += b.len();
                    sink.put(l, i, &geom.level(l)[i].key, &b)
                        .map_err(EncodeError::writing)?;
                }
            }
        }
    }
    if let Some(e) = failed.into_inner().ok().flatten() {
        return Err(e);
    }
    Ok((model, count, bytes))
}

/// The tile side: the largest of 256, 128, 64, 32 whose band of rows (values, validity,
/// fill context and integers, about 20 bytes a sample) takes at most a quarter of the
/// budget.
fn tile_side(w: usize, budget: usize) -> Result<usize, EncodeError> {
    let band = |t: usize| (t + CONTEXT_ROWS) * w * 20;
    [256, 128, 64, 32]
        .into_iter()
        .find(|&t| 4 * band(t) <= budget)
        .ok_or(EncodeError::Budget {
            needed: 4 * band(32),
            budget,
        })
}

/// The cube-edge points: every face's border entries, and which of them are not the
/// canonical (lowest face) copy of their point, with that copy's index.
struct Borders {
    /// Per face: `(row, column, canonical index)` of its non-canonical border entries.
    copies: Vec<Vec<(usize, usize, usize)>>,
    /// Per face: the cube indices of its border entries that are canonical.
    canonical: Vec<Vec<usize>>,
    w: usize,
}

impl Borders {
    fn new(geom: &SphereGeometry) -> Self {
        let w = geom.face_side() + 1;
        let mut copies = vec![Vec::new(); 6];
        let mut canonical = vec![Vec::new(); 6];
        for face in 0..6u8 {
            for v in 0..w {
                let step = if v == 0 || v == w - 1 { 1 } else { w - 1 };
                for u in (0..w).step_by(step) {
                    let here = geom.cube_index(face, u, v);
                    let first = geom
                        .point_indices(geom.sample_position(face, u, v))
                        .next()
                        .unwrap_or(here);
                    if first == here {
                        canonical[face as usize].push(here);
                    } else {
                        copies[face as usize].push((v, u, first));
                    }
                }
            }
        }
        Borders {
            copies,
            canonical,
            w,
        }
    }

    /// Gives the non-canonical entries of face `face`'s rows `first..first + count` (in
    /// `band`) their canonical copies' values from `known`, then records the band's
    /// canonical border entries in `known` (faces come in order, so every canonical copy
    /// is known before its copies are read).
    fn apply<T: Copy>(
        &self,
        face: usize,
        (first, count): (usize, usize),
        band: &mut [T],
        known: &mut HashMap<usize, T>,
        record: bool,
    ) -> Result<(), EncodeError> {
        let w = self.w;
        let rows = first..first + count;
        for &(v, u, canon) in &self.copies[face] {
            if rows.contains(&v) {
                band[(v - first) * w + u] = *known.get(&canon).ok_or(EncodeError::Internal(
                    "an edge point's canonical copy unread",
                ))?;
            }
        }
        if record {
            let base = (face * w + first) * w;
            for &k in &self.canonical[face] {
                if (base..base + count * w).contains(&k) {
                    known.insert(k, band[k - base]);
                }
            }
        }
        Ok(())
    }
}

/// Reads a band of rows and gives edge points their canonical copies' values (recording
/// the band's own canonical border values).
fn read_band(
    source: &mut dyn CubeSource,
    borders: &Borders,
    canon: &mut HashMap<usize, f64>,
    (face, first, count): (usize, usize, usize),
    band: &mut [f64],
) -> Result<(), EncodeError> {
    source
        .read_face_rows(face, first, count, band)
        .map_err(EncodeError::reading)?;
    borders.apply(face, (first, count), band, canon, true)
}

/// The integerisation's errors: `(sum of squares, max)` per [`PASS_CHUNK`] entries of
/// the cube raster (as the in-memory encoder sums them) with each piece's number, and
/// the samples counted.
type Errors = (Vec<(usize, (f64, f64))>, usize);

/// A shard's pass 1 (see [`shard`]): per face, the bands of rows (rows of tiles) to run
/// over, and every canonical copy of an edge point from pass 0.
struct Partial {
    bands: Vec<Range<usize>>,
    canon: HashMap<usize, f64>,
}

/// Pass 1: reads every face again, fills nodata band by band, writes the integers as the
/// tiles of `R_0`, and measures the integerisation's errors over the valid canonical
/// entries, in the in-memory encoder's pieces and order. With `partial`, only its bands
/// and the pieces they hold whole (and the samples counted in them).
#[allow(clippy::too_many_arguments)]
fn write_integers(
    source: &mut dyn CubeSource,
    geom: &SphereGeometry,
    borders: &Borders,
    (map, fill): (&ValueMap, &Fill),
    (lattice, present, partial): (&Lattice, Option<&[bool]>, Option<&Partial>),
    tiles: &mut dyn TileStore,
    meter: &mut Meter,
) -> Result<Errors, EncodeError> {
    let w = geom.face_side() + 1;
    let t = lattice.t;
    let mut canon = partial.map(|p| p.canon.clone()).unwrap_or_default();
    let mut canon_ints: HashMap<usize, i32> = canon
        .iter()
        .filter(|(_, v)| v.is_finite())
        .map(|(&k, &v)| (k, map.int_of(v)))
        .collect();
    let mut vals = vec![0.0; (CONTEXT_ROWS + t) * w];
    let mut valid = vec![false; (CONTEXT_ROWS + t) * w];
    let mut ints = vec![0i32; t * w];
    let mut tile = vec![0i32; t * t];
    let mut pieces = Vec::new();
    let mut current = (0.0, 0.0f64);
    let mut counted_total = 0usize;
    // Where the run of bands read without a gap began, and where the last band ended.
    let (mut run_from, mut last_end) = (0usize, 0usize);
    for face in 0..6 {
        let mut context = 0usize;
        for first in (0..w).step_by(t) {
            if partial.is_some_and(|p| !p.bands[face].contains(&(first / t))) {
                continue;
            }
            let count = t.min(w - first);
            if (face * w + first) * w != last_end {
                // A new run (a shard's): the piece in progress is not ours; the fill's
                // context is the rows before, which hold no nodata.
                (current, run_from) = ((0.0, 0.0), (face * w + first) * w);
                context = CONTEXT_ROWS.min(first);
                if context > 0 {
                    let rows = &mut vals[..context * w];
                    read_band(
                        source,
                        borders,
                        &mut canon,
                        (face, first - context, context),
                        rows,
                    )?;
                    if rows.iter().any(|v| !v.is_finite()) {
                        return Err(EncodeError::Internal("a shard's fill context holds nodata"));
                    }
                }
            }
            let (ctx, total) = (context * w, (context + count) * w);
            read_band(
                source,
                borders,
                &mut canon,
                (face, first, count),
                &mut vals[ctx..total],
            )?;
            let start = (face * w + first) * w;
            for (b, v) in valid[ctx..total].iter_mut().zip(&vals[ctx..total]) {
                *b = v.is_finite();
            }
            // Errors of the valid canonical entries, in pieces of the whole cube raster.
            let (band_pieces, band_counted) =
                piece_errors(geom, map, (start, &vals[ctx..total], None), &mut current);
            pieces.extend(
                band_pieces
                    .into_iter()
                    .enumerate()
                    .map(|(i, p)| (start / PASS_CHUNK + i, p))
                    .filter(|&(k, _)| k * PASS_CHUNK >= run_from),
            );
            counted_total += band_counted;
            valid[..ctx].iter_mut().for_each(|b| *b = true);
            let fill_bytes = fill.rows(w, context, &mut vals[..total], &valid[..total]);
            meter.note(
                (vals.len() + ints.len() / 2 + tile.len() / 2) * 8 + valid.len() + fill_bytes,
            );
            ints[..count * w]
                .par_chunks_mut(PASS_CHUNK)
                .zip(vals[ctx..total].par_chunks(PASS_CHUNK))
                .for_each(|(out, vs)| {
                    for (o, &v) in out.iter_mut().zip(vs) {
                        *o = map.int_of(v);
                    }
                });
            borders.apply(
                face,
                (first, count),
                &mut ints[..count * w],
                &mut canon_ints,
                true,
            )?;
            // The band is one row of tiles.
            let tv = first / t;
            for tu in 0..lattice.per {
                let k = lattice.tile_no(face, tv, tu);
                if present.is_some_and(|p| !p[k]) {
                    continue;
                }
                tile.iter_mut().for_each(|x| *x = 0);
                let (u0, u1) = (tu * t, ((tu + 1) * t).min(w));
                for r in 0..count {
                    tile[r * t..r * t + (u1 - u0)].copy_from_slice(&ints[r * w + u0..r * w + u1]);
                }
                tiles
                    .write(lattice.offset(k), &tile)
                    .map_err(EncodeError::writing)?;
            }
            let keep = CONTEXT_ROWS.min(context + count);
            vals.copy_within(total - keep * w..total, 0);
            context = keep;
            last_end = start + count * w;
        }
    }
    let k = 6 * w * w / PASS_CHUNK;
    if !(6 * w * w).is_multiple_of(PASS_CHUNK)
        && last_end == 6 * w * w
        && k * PASS_CHUNK >= run_from
    {
        pieces.push((k, current));
    }
    Ok((pieces, counted_total))
}

/// The error pieces completed by a band of the cube raster starting at entry `start`,
/// of the integerisation or of `decoded` (the band's decoded integers): `current` is the
/// piece in progress when the band begins (and when it ends). Each
/// piece sums its entries in order, as the in-memory encoder's does.
fn piece_errors(
    geom: &SphereGeometry,
    map: &ValueMap,
    (start, band, decoded): (usize, &[f64], Option<&[i32]>),
    current: &mut (f64, f64),
) -> (Vec<(f64, f64)>, usize) {
    let end = start + band.len();
    // Segments of the band split at piece boundaries.
    let mut cuts = vec![start];
    let mut next = (start / PASS_CHUNK + 1) * PASS_CHUNK;
    while next < end {
        cuts.push(next);
        next += PASS_CHUNK;
    }
    cuts.push(end);
    let first = *current;
    let sums: Vec<((f64, f64), usize)> = cuts
        .par_windows(2)
        .enumerate()
        .map(|(s, c)| {
            let mut acc = if s == 0 { first } else { (0.0, 0.0f64) };
            let mut counted = 0;
            for k in c[0]..c[1] {
                let v = band[k - start];
                if v.is_finite() && geom.is_canonical(k) {
                    let d = decoded.map_or_else(|| map.int_of(v), |d| d[k - start]);
                    let e = (map.offset + d as f64 * map.scale - v).abs();
                    acc = (acc.0 + e * e, acc.1.max(e));
                    counted += 1;
                }
            }
            (acc, counted)
        })
        .collect();
    let counted = sums.iter().map(|s| s.1).sum();
    let mut done: Vec<(f64, f64)> = sums.into_iter().map(|s| s.0).collect();
    // The last segment is complete only if the band ends on a piece boundary.
    *current = if end.is_multiple_of(PASS_CHUNK) {
        (0.0, 0.0)
    } else {
        done.pop().unwrap_or((0.0, 0.0))
    };
    (done, counted)
}

/// The tiled raster `R_o` of one octave: point `(x, y)` of face `f` is cube sample
/// `(x 2^o, y 2^o)`; tiles of `t x t` points, `per` to a face side, stored from value
/// offset `base`.
struct Lattice {
    t: usize,
    shift: u32,
    per: usize,
    base: u64,
    /// The full-resolution cube raster's width `2S + 1`.
    w: usize,
}

impl Lattice {
    fn new(face_side: usize, t: usize, o: usize, base: usize) -> Self {
        let side = (face_side >> o) + 1;
        Lattice {
            t,
            shift: o as u32,
            per: side.div_ceil(t),
            base: base as u64,
            w: face_side + 1,
        }
    }

    fn tiles(&self) -> usize {
        6 * self.per * self.per
    }

    /// Points to a side of a face of this raster.
    fn side(&self) -> usize {
        ((self.w - 1) >> self.shift) + 1
    }

    /// Reads face `face`'s rows `first .. first + count` of this raster (`count x side`
    /// values) from `tiles`.
    fn read_rows(
        &self,
        tiles: &mut dyn TileStore,
        (face, first, count): (usize, usize, usize),
        out: &mut [i32],
    ) -> Result<(), IoError> {
        let (t, w) = (self.t, self.side());
        let mut tile = vec![0i32; t * t];
        for tv in first / t..(first + count).div_ceil(t) {
            for tu in 0..self.per {
                tiles.read(self.offset(self.tile_no(face, tv, tu)), &mut tile)?;
                let (u0, u1) = (tu * t, ((tu + 1) * t).min(w));
                for y in (tv * t).max(first)..((tv + 1) * t).min(first + count) {
                    let (r, ty) = (y - first, y - tv * t);
                    out[r * w + u0..r * w + u1].copy_from_slice(&tile[ty * t..ty * t + (u1 - u0)]);
                }
            }
        }
        Ok(())
    }

    /// Writes every row of face `face` of this raster (`side x side` values) as its tiles.
    fn write_face(
        &self,
        tiles: &mut dyn TileStore,
        face: usize,
        rows: &[i32],
    ) -> Result<(), IoError> {
        let (t, w) = (self.t, self.side());
        let mut tile = vec![0i32; t * t];
        for tv in 0..self.per {
            for tu in 0..self.per {
                tile.iter_mut().for_each(|x| *x = 0);
                let (u0, u1) = (tu * t, ((tu + 1) * t).min(w));
                for y in tv * t..((tv + 1) * t).min(w) {
                    let ty = y - tv * t;
                    tile[ty * t..ty * t + (u1 - u0)].copy_from_slice(&rows[y * w + u0..y * w + u1]);
                }
                tiles.write(self.offset(self.tile_no(face, tv, tu)), &tile)?;
            }
        }
        Ok(())
    }

    /// Values the tiles take.
    fn len(&self) -> usize {
        self.tiles() * self.t * self.t
    }

    fn tile_no(&self, face: usize, tv: usize, tu: usize) -> usize {
        (face * self.per + tv) * self.per + tu
    }

    fn offset(&self, tile: usize) -> u64 {
        self.base + (tile * self.t * self.t) as u64
    }

    /// `(face, x, y)` of cube-raster entry `index` in this raster.
    #[inline]
    fn point(&self, index: usize) -> (usize, usize, usize) {
        let w2 = self.w * self.w;
        let (face, rest) = (index / w2, index % w2);
        let (v, u) = (rest / self.w, rest % self.w);
        (face, u >> self.shift, v >> self.shift)
    }

    /// Tile number and offset in the tile of cube-raster entry `index`.
    #[inline]
    fn locate(&self, index: usize) -> (usize, usize) {
        let (face, x, y) = self.point(index);
        let t = self.t;
        (self.tile_no(face, y / t, x / t), (y % t) * t + x % t)
    }
}

/// The tiles of one raster held in memory, least recently used dropped first.
struct Cache {
    slots: Vec<Option<Box<[i32]>>>,
    dirty: Vec<bool>,
    used: Vec<u64>,
    clock: u64,
    held: usize,
    cap: usize,
    tile_values: usize,
}

impl Cache {
    fn new(lattice: &Lattice, bytes: usize) -> Self {
        let tiles = lattice.tiles();
        let tile_values = lattice.t * lattice.t;
        Cache {
            slots: (0..tiles).map(|_| None).collect(),
            dirty: vec![false; tiles],
            used: vec![0; tiles],
            clock: 0,
            held: 0,
            cap: (bytes / (4 * tile_values)).max(16),
            tile_values,
        }
    }

    fn held_bytes(&self) -> usize {
        self.held * self.tile_values * 4 + self.slots.len() * 24
    }

    /// Loads the tiles `needed` (dropping others, least recently used first, to stay
    /// within the capacity when it can).
    fn ensure(
        &mut self,
        lattice: &Lattice,
        needed: &[usize],
        store: &mut dyn TileStore,
    ) -> Result<(), EncodeError> {
        self.clock += 1;
        for &k in needed {
            self.used[k] = self.clock;
        }
        let missing = needed.iter().filter(|&&k| self.slots[k].is_none()).count();
        if self.held + missing > self.cap {
            let mut held: Vec<usize> = (0..self.slots.len())
                .filter(|&k| self.slots[k].is_some() && self.used[k] < self.clock)
                .collect();
            held.sort_by_key(|&k| self.used[k]);
            for k in held.into_iter().take(self.held + missing - self.cap) {
                self.drop_tile(lattice, k, store)?;
            }
        }
        for &k in needed {
            if self.slots[k].is_none() {
                let mut data = vec![0i32; self.tile_values].into_boxed_slice();
                store
                    .read(lattice.offset(k), &mut data)
                    .map_err(EncodeError::reading)?;
                self.slots[k] = Some(data);
                self.held += 1;
            }
        }
        Ok(())
    }

    fn drop_tile(
        &mut self,
        lattice: &Lattice,
        k: usize,
        store: &mut dyn TileStore,
    ) -> Result<(), EncodeError> {
        if let Some(data) = self.slots[k].take() {
            if self.dirty[k] {
                store
                    .write(lattice.offset(k), &data)
                    .map_err(EncodeError::writing)?;
                self.dirty[k] = false;
            }
            self.held -= 1;
        }
        Ok(())
    }

    /// Writes every changed tile back.
    fn flush(&mut self, lattice: &Lattice, store: &mut dyn TileStore) -> Result<(), EncodeError> {
        for k in 0..self.slots.len() {
            if let (true, Some(data)) = (self.dirty[k], &self.slots[k]) {
                store
                    .write(lattice.offset(k), data)
                    .map_err(EncodeError::writing)?;
                self.dirty[k] = false;
            }
        }
        Ok(())
    }

    /// Cube-raster entry `index`; 0 and `missed` set if its tile is not loaded (a bug).
    #[inline]
    fn get(&self, lattice: &Lattice, index: usize, missed: &AtomicBool) -> i32 {
        let (tile, at) = lattice.locate(index);
        match self.slots.get(tile).and_then(|s| s.as_deref()) {
            Some(data) => data[at],
            None => {
                missed.store(true, Ordering::Relaxed);
                0
            }
        }
    }

    #[inline]
    fn set(&mut self, lattice: &Lattice, index: usize, x: i32) -> bool {
        let (tile, at) = lattice.locate(index);
        match self.slots.get_mut(tile).and_then(|s| s.as_deref_mut()) {
            Some(data) => {
                data[at] = x;
                self.dirty[tile] = true;
                true
            }
            None => false,
        }
    }
}

/// The tiles a diamond's points lie in.
fn diamond_tiles(lattice: &Lattice, corners: &[Vec<usize>], out: &mut Vec<usize>) {
    let t = lattice.t;
    for piece in corners {
        let pts: Vec<(usize, usize, usize)> = piece.iter().map(|&k| lattice.point(k)).collect();
        let face = pts[0].0;
        let (x0, x1) = (
            pts.iter().map(|p| p.1).min().unwrap_or(0),
            pts.iter().map(|p| p.1).max().unwrap_or(0),
        );
        let (y0, y1) = (
            pts.iter().map(|p| p.2).min().unwrap_or(0),
            pts.iter().map(|p| p.2).max().unwrap_or(0),
        );
        debug_assert!(pts.iter().all(|p| p.0 == face));
        for tv in y0 / t..=y1 / t {
            for tu in x0 / t..=x1 / t {
                out.push(lattice.tile_no(face, tv, tu));
            }
        }
    }
}

/// Every diamond's side information, computed as the analysis goes up the levels (the
/// children's before their parents'): the class and data flags for the blobs, and the
/// value bounds of the level below the one being analysed.
struct Side {
    gamma: Vec<Vec<u64>>,
    has_data: Vec<Vec<bool>>,
    bounds: Vec<(i64, i64)>,
}

/// One diamond's analysis: its details, its lifted vertex grid, whether any detail is
/// nonzero, and its side information `(class, has data, value bounds)`.
struct Analysed {
    index: usize,
    details: Vec<i32>,
    lifted: Vec<i32>,
    nonzero: bool,
    side: (u64, bool, (i64, i64)),
}

/// Analyses every diamond of `level` on the raster of its octave, batch by batch in tile
/// order: details to the spill, side information into `side`, the lifted vertices back
/// into the tiles.
fn analyse_level(
    geom: &SphereGeometry,
    level: usize,
    (lattice, cache, tiles): (&Lattice, &mut Cache, &mut dyn TileStore),
    (store, spill): (&mut Spill, &mut dyn IndexSpill),
    (side, mut hist): (&mut Side, Option<&mut Histograms>),
    only: Option<&[bool]>,
    meter: &mut Meter,
) -> Result<(), EncodeError> {
    let n = geom.n();
    let slots = geom.level(level);
    let finest = level + 1 == geom.slot_levels().len();
    let mut gamma = vec![0u64; slots.len()];
    let mut has_data = vec![false; slots.len()];
    let mut bounds = vec![(0i64, 0i64); slots.len()];
    let (vlen, clen) = ((n + 1) * (n + 1), n * n);
    for_each_batch(
        geom,
        level,
        (lattice, cache, tiles),
        only,
        |batch, cache| {
            let missed = AtomicBool::new(false);
            let shared: &Cache = cache;
            let results: Vec<Analysed> = batch
                .par_iter()
                .map(|&i| {
                    let s = &slots[i];
                    let mut v = vec![0; vlen];
                    let mut c = vec![0; clen];
                    let mut h = vec![0; clen];
                    gather_vertices(n, s, (lattice, shared), &missed, &mut v);
                    for a in 0..n {
                        for b in 0..n {
                            c[a * n + b] = shared.get(lattice, s.cell_index(a, b), &missed);
                        }
                    }
                    let fine = v.clone();
                    lifting::analyze(n, &mut v, &c, &mut h, geom.mask(s));
                    let m = measure(n, geom.mask(s), &v, &fine, &c);
                    let nonzero = h.iter().any(|&x| x != 0);
                    let children: &[usize] = if finest { &[] } else { geom.children(s) };
                    let info = side_info(
                        &m,
                        nonzero,
                        children.iter().map(|&k| {
                            (
                                side.gamma[level + 1][k],
                                side.has_data[level + 1][k],
                                side.bounds[k],
                            )
                        }),
                    );
                    Analysed {
                        index: i,
                        details: h,
                        lifted: v,
                        nonzero,
                        side: info,
                    }
                })
                .collect();
            if missed.load(Ordering::Relaxed) {
                return Err(EncodeError::Internal("a diamond point outside its tiles"));
            }
            meter.note(cache.held_bytes() + results.len() * (vlen + 2 * clen) * 4);
            let mut lost = false;
            for r in &results {
                let (s, v) = (&slots[r.index], &r.lifted);
                for a in 1..n {
                    for b in 1..n {
                        let x = v[a * (n + 1) + b];
                        let (k, other) = s.vertex_copies(a, b);
                        lost |= !cache.set(lattice, k, x);
                        if let Some(k) = other {
                            lost |= !cache.set(lattice, k, x);
                        }
                    }
                }
            }
            if lost {
                return Err(EncodeError::Internal("a lifted vertex outside its tiles"));
            }
            let matrices: Vec<(usize, &[i32])> = results
                .iter()
                .filter(|r| r.nonzero)
                .map(|r| (r.index, &r.details[..]))
                .collect();
            if !matrices.is_empty() {
                store.put_batch(spill, level, &matrices)?;
            }
            if let Some(h) = hist.as_deref_mut() {
                for r in &results {
                    h.add(level, &r.details);
                }
            }
            for r in results {
                let i = r.index;
                (gamma[i], has_data[i], bounds[i]) = r.side;
            }
            Ok(())
        },
    )?;
    side.gamma[level] = gamma;
    side.has_data[level] = has_data;
    side.bounds = bounds;
    Ok(())
}

/// Writes `R_{o+1}` (`to`) from `R_o` (`from`): every second point of every second row,
/// a row of output tiles from two rows of input tiles. With `present` (a shard's tiles
/// of `from` and `to`), only the tiles of `to` it flags, from those of `from` it flags
/// (the others read as zeros).
fn compact(
    from: &Lattice,
    to: &Lattice,
    store: &mut dyn TileStore,
    meter: &mut Meter,
    present: Option<(&[bool], &[bool])>,
) -> Result<(), EncodeError> {
    let has = |of: usize, k: usize| present.is_none_or(|p| if of == 0 { p.0[k] } else { p.1[k] });
    let t = from.t;
    let tv_len = t * t;
    let mut rows = vec![0i32; 2 * from.per * tv_len];
    let mut out = vec![0i32; tv_len];
    meter.note((rows.len() + out.len()) * 4);
    for face in 0..6 {
        for tv in 0..to.per {
            if !(0..to.per).any(|tu| has(1, to.tile_no(face, tv, tu))) {
                continue;
            }
            for r in 0..2 {
                let src = 2 * tv + r;
                for tu in 0..from.per {
                    let buf =
                        &mut rows[(r * from.per + tu) * tv_len..(r * from.per + tu + 1) * tv_len];
                    if src < from.per && has(0, from.tile_no(face, src, tu)) {
                        store
                            .read(from.offset(from.tile_no(face, src, tu)), buf)
                            .map_err(EncodeError::reading)?;
                    } else {
                        buf.iter_mut().for_each(|x| *x = 0);
                    }
                }
            }
            for tu in 0..to.per {
                if !has(1, to.tile_no(face, tv, tu)) {
                    continue;
                }
                for y in 0..t {
                    // Row 2y of the two input rows of tiles.
                    let (r, yy) = (2 * y / t, 2 * y % t);
                    for x in 0..t {
                        let sx = 2 * (tu * t + x);
                        let (stu, xx) = (sx / t, sx % t);
                        out[y * t + x] = if stu < from.per {
                            rows[(r * from.per + stu) * tv_len + yy * t + xx]
                        } else {
                            0
                        };
                    }
                }
                store
                    .write(to.offset(to.tile_no(face, tv, tu)), &out)
                    .map_err(EncodeError::writing)?;
            }
        }
    }
    Ok(())
}

/// Calls `f(batch, cache)` for the diamonds of `level` (those `only` flags, if given) a
/// batch at a time in tile order, each batch's tiles loaded: up to [`BATCH`] diamonds
/// whose tiles fit in half the cache.
fn for_each_batch(
    geom: &SphereGeometry,
    level: usize,
    (lattice, cache, tiles): (&Lattice, &mut Cache, &mut dyn TileStore),
    only: Option<&[bool]>,
    mut f: impl FnMut(&[usize], &mut Cache) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    let n = geom.n();
    let slots = geom.level(level);
    let mut order: Vec<(usize, usize)> = slots
        .par_iter()
        .enumerate()
        .filter(|&(i, _)| only.is_none_or(|o| o[i]))
        .map(|(i, s)| (lattice.locate(s.vertex_index(0, 0)).0, i))
        .collect();
    order.par_sort_unstable();
    let mut next = 0;
    let mut own = Vec::new();
    let mut batch = Vec::new();
    while next < order.len() {
        let mut needed: Vec<usize> = Vec::new();
        batch.clear();
        while next < order.len() && batch.len() < BATCH {
            let i = order[next].1;
            own.clear();
            diamond_tiles(lattice, &slots[i].piece_corners(n), &mut own);
            let mut merged: Vec<usize> = needed.iter().chain(&own).copied().collect();
            merged.sort_unstable();
            merged.dedup();
            if !batch.is_empty() && merged.len() > cache.cap / 2 {
                break;
            }
            needed = merged;
            batch.push(i);
            next += 1;
        }
        cache.ensure(lattice, &needed, tiles)?;
        f(&batch, cache)?;
    }
    Ok(())
}

/// A diamond's `(N + 1)^2` vertices from the loaded tiles.
fn gather_vertices(
    n: usize,
    s: &crate::sphere_raster::SphereSlot,
    (lattice, cache): (&Lattice, &Cache),
    missed: &AtomicBool,
    v: &mut [i32],
) {
    for a in 0..=n {
        for b in 0..=n {
            v[a * (n + 1) + b] = cache.get(lattice, s.vertex_index(a, b), missed);
        }
    }
}

/// What the rate control settled: steps, errors, and how it got there.
struct Rate {
    steps: Vec<u32>,
    errors: (f64, f64),
    rdo: bool,
    decodes: usize,
}

/// The RMS rate control's verifier out of core: every diamond's details are in slot 0
/// of the spill (from the analysis); an attempt quantises them into its own slot as a
/// synthesis goes through the tiles ([`Synth`]), measuring each diamond, then reads the
/// source once more and measures the decoded integers against it in the in-memory
/// encoder's pieces and order. The same indices, measures and errors as the in-memory
/// verifier's, so the same search.
struct CubeVerifier<'a> {
    synth: Synth<'a>,
    source: &'a mut dyn CubeSource,
    borders: &'a Borders,
    map: &'a ValueMap,
    details: &'a Spill,
    last: Spill,
    kept: Spill,
    valid_count: usize,
}

/// Where a synthesis takes each diamond's indices from.
enum Indices<'s> {
    /// Quantised from the analysis' details and stored into `into` (an attempt).
    Quantise {
        q: &'s Quantise,
        cost_model: Option<&'s CodecModel>,
        details: &'s Spill,
        into: &'s mut Spill,
    },
    /// Read from a spill of indices (the coded ones).
    Coded(&'s Spill),
}

/// A synthesis through the tiles, coarse to fine: the analysis' octaves in reverse, each
/// raster `R_o` expanded from `R_{o+1}`, the roots first; `R_0` is left in the tiles.
struct Synth<'a> {
    geom: &'a SphereGeometry,
    roots: &'a [Vec<i32>],
    tiles: &'a mut dyn TileStore,
    spill: &'a mut dyn IndexSpill,
    /// Tile side, and the value offset of the odd octaves' rasters.
    shape: (usize, usize),
    cache_bytes: usize,
    meter: &'a mut Meter,
}

impl Synth<'_> {
    fn lattice(&self, o: usize) -> Lattice {
        let (t, second) = self.shape;
        Lattice::new(
            self.geom.face_side(),
            t,
            o,
            if o % 2 == 1 { second } else { 0 },
        )
    }

    /// Synthesises every level with `steps`; the measures per diamond and whether any
    /// index is nonzero.
    fn run(
        &mut self,
        steps: &[u32],
        mut indices: Indices<'_>,
    ) -> Result<(Vec<Vec<Measure>>, bool), EncodeError> {
        let geom = self.geom;
        let n = geom.n();
        let levels = geom.slot_levels().len();
        let octaves = levels / 2;
        if let Indices::Quantise { into, .. } = &mut indices {
            into.clear(self.spill)?;
        }
        let mut measures: Vec<Vec<Option<Measure>>> = (0..levels)
            .map(|l| vec![None; geom.level(l).len()])
            .collect();
        let mut coded = false;
        // The coarsest raster: zeros, then the roots.
        let mut lattice = self.lattice(octaves - 1);
        let zeros = vec![0i32; lattice.t * lattice.t];
        for k in 0..lattice.tiles() {
            self.tiles
                .write(lattice.offset(k), &zeros)
                .map_err(EncodeError::writing)?;
        }
        let mut cache = Cache::new(&lattice, self.cache_bytes);
        let all: Vec<usize> = (0..lattice.tiles()).collect();
        cache.ensure(&lattice, &all, self.tiles)?;
        let mut lost = false;
        geom.scatter_roots_with(self.roots, |k, x| lost |= !cache.set(&lattice, k, x))?;
        if lost {
            return Err(EncodeError::Internal(
                "a root vertex outside the loaded tiles",
            ));
        }
        for o in (0..octaves).rev() {
            if o + 1 < octaves {
                let finer = self.lattice(o);
                cache.flush(&lattice, self.tiles)?;
                drop(cache);
                expand(&lattice, &finer, self.tiles, self.meter)?;
                lattice = finer;
                cache = Cache::new(&lattice, self.cache_bytes);
            }
            for level in [levels - 2 - 2 * o, levels - 1 - 2 * o] {
                let (slots, clen, vlen) = (geom.level(level), n * n, (n + 1) * (n + 1));
                let spill = &mut *self.spill;
                let indices = &mut indices;
                let meter = &mut *self.meter;
                let measures = &mut measures[level];
                for_each_batch(
                    geom,
                    level,
                    (&lattice, &mut cache, &mut *self.tiles),
                    None,
                    |batch, cache| {
                        let missed = AtomicBool::new(false);
                        let shared: &Cache = cache;
                        let store: &dyn IndexSpill = &*spill;
                        let from: &Indices<'_> = indices;
                        let results: Vec<Synthesised> = batch
                            .par_iter()
                            .map(|&i| -> Result<Synthesised, EncodeError> {
                                let s = &slots[i];
                                let mask = geom.mask(s);
                                let mut h = vec![0; clen];
                                let mut indices = vec![0; clen];
                                match from {
                                    Indices::Quantise {
                                        q,
                                        cost_model,
                                        details,
                                        ..
                                    } => {
                                        details.get(store, level, i, &mut h)?;
                                        q.matrix(
                                            *cost_model,
                                            &geom.blob_context(level, i),
                                            steps[level],
                                            &h,
                                            &mut indices,
                                        );
                                    }
                                    Indices::Coded(coded) => {
                                        coded.get(store, level, i, &mut indices)?;
                                    }
                                }
                                let nonzero = indices.iter().any(|&x| x != 0);
                                let mut v = vec![0; vlen];
                                let mut c = vec![0; clen];
                                gather_vertices(n, s, (&lattice, shared), &missed, &mut v);
                                let m = if nonzero {
                                    for (d, &x) in h.iter_mut().zip(&indices) {
                                        *d = dequantize(x, steps[level]);
                                    }
                                    let coarse = v.clone();
                                    lifting::synthesize(n, &mut v, &h, &mut c, mask);
                                    measure(n, mask, &coarse, &v, &c)
                                } else {
                                    lifting::synthesize_zero(n, &v, &mut c, mask);
                                    measure(n, mask, &v, &v, &c)
                                };
                                Ok(Synthesised {
                                    index: i,
                                    indices,
                                    fine: v,
                                    cells: c,
                                    nonzero,
                                    measure: m,
                                })
                            })
                            .collect::<Result<_, _>>()?;
                        if missed.load(Ordering::Relaxed) {
                            return Err(EncodeError::Internal("a diamond point outside its tiles"));
                        }
                        meter.note(cache.held_bytes() + results.len() * (vlen + 3 * clen) * 4);
                        let mut lost = false;
                        for r in &results {
                            let s = &slots[r.index];
                            let mut put = |(k, other): (usize, Option<usize>), x: i32| {
                                lost |= !cache.set(&lattice, k, x);
                                if let Some(k) = other {
                                    lost |= !cache.set(&lattice, k, x);
                                }
                            };
                            if r.nonzero {
                                for a in 1..n {
                                    for b in 1..n {
                                        put(s.vertex_copies(a, b), r.fine[a * (n + 1) + b]);
                                    }
                                }
                            }
                            for a in 0..n {
                                for b in 0..n {
                                    put(s.cell_copies(a, b), r.cells[a * n + b]);
                                }
                            }
                        }
                        if lost {
                            return Err(EncodeError::Internal(
                                "a synthesised point outside its tiles",
                            ));
                        }
                        let nonzero: Vec<(usize, &[i32])> = results
                            .iter()
                            .filter(|r| r.nonzero)
                            .map(|r| (r.index, &r.indices[..]))
                            .collect();
                        if !nonzero.is_empty() {
                            coded = true;
                            if let Indices::Quantise { into, .. } = indices {
                                into.put_batch(spill, level, &nonzero)?;
                            }
                        }
                        for r in results {
                            measures[r.index] = Some(r.measure);
                        }
                        Ok(())
                    },
                )?;
            }
        }
        cache.flush(&lattice, self.tiles)?;
        let measures = measures
            .into_iter()
            .map(|l| l.into_iter().collect::<Option<Vec<Measure>>>())
            .collect::<Option<Vec<_>>>()
            .ok_or(EncodeError::Internal("a diamond was not synthesised"))?;
        Ok((measures, coded))
    }
}

impl CubeVerifier<'_> {
    /// The decoded integers (the tiles of `R_0`) against the source, read again face by
    /// face: `(rms, max)` over the valid canonical entries.
    fn errors(&mut self) -> Result<(f64, f64), EncodeError> {
        let geom = self.synth.geom;
        let w = geom.face_side() + 1;
        let decoded = DecodedTiles {
            face_side: geom.face_side(),
            t: self.synth.shape.0,
        };
        let t = decoded.t;
        let mut canon = HashMap::new();
        let mut vals = vec![0.0; t * w];
        let mut ints = vec![0i32; t * w];
        self.synth
            .meter
            .note(vals.len() * 8 + (ints.len() + t * t) * 4);
        let mut pieces = Vec::new();
        let mut current = (0.0, 0.0f64);
        for face in 0..6 {
            for first in (0..w).step_by(t) {
                let count = t.min(w - first);
                let band = &mut vals[..count * w];
                read_band(
                    self.source,
                    self.borders,
                    &mut canon,
                    (face, first, count),
                    band,
                )?;
                decoded
                    .read_rows(
                        self.synth.tiles,
                        (face, first, count),
                        &mut ints[..count * w],
                    )
                    .map_err(EncodeError::reading)?;
                let start = (face * w + first) * w;
                let (done, _) = piece_errors(
                    geom,
                    self.map,
                    (start, &vals[..count * w], Some(&ints[..count * w])),
                    &mut current,
                );
                pieces.extend(done);
            }
        }
        if !(6 * w * w).is_multiple_of(PASS_CHUNK) {
            pieces.push(current);
        }
        Ok(rms_of_pieces(&pieces, self.valid_count))
    }
}

/// One diamond's synthesis: its indices, fine vertices, cells and measures.
struct Synthesised {
    index: usize,
    indices: Vec<i32>,
    fine: Vec<i32>,
    cells: Vec<i32>,
    nonzero: bool,
    measure: Measure,
}

impl Verifier for CubeVerifier<'_> {
    fn train_cost(&mut self, q: &Quantise, steps: &[u32]) -> Result<CodecModel, EncodeError> {
        let (geom, n) = (self.synth.geom, self.synth.geom.n());
        let store: &dyn IndexSpill = &*self.synth.spill;
        let details = self.details;
        let failed: Mutex<Option<EncodeError>> = Mutex::new(None);
        let model = train_model(
            geom,
            |_, _| true,
            |acc, l, i| {
                let mut h = details.matrix(store, l, i).unwrap_or_else(|e| {
                    if let Ok(mut f) = failed.lock() {
                        f.get_or_insert(e);
                    }
                    vec![0; n * n]
                });
                q.count_rounded(acc, geom, (l, i), steps[l], &mut h);
            },
        );
        match failed.into_inner().ok().flatten() {
            Some(e) => Err(e),
            None => Ok(model),
        }
    }

    fn attempt(
        &mut self,
        q: &Quantise,
        cost_model: Option<&CodecModel>,
        steps: &[u32],
    ) -> Result<Attempt, EncodeError> {
        let (measures, coded) = self.synth.run(
            steps,
            Indices::Quantise {
                q,
                cost_model,
                details: self.details,
                into: &mut self.last,
            },
        )?;
        let errors = self.errors()?;
        Ok((measures, coded, errors))
    }

    fn keep_last(&mut self) {
        std::mem::swap(&mut self.last, &mut self.kept);
    }
}

/// Writes `R_{o-1}` (`to`) from `R_o` (`from`), the inverse of [`compact`]: the points
/// of `R_o` at every second point of every second row, zeros between (the synthesis of
/// `to`'s octave writes them).
fn expand(
    from: &Lattice,
    to: &Lattice,
    store: &mut dyn TileStore,
    meter: &mut Meter,
) -> Result<(), EncodeError> {
    let t = from.t;
    let tv_len = t * t;
    let mut src = vec![0i32; from.per * tv_len];
    let mut out = vec![0i32; tv_len];
    meter.note((src.len() + out.len()) * 4);
    for face in 0..6 {
        for stv in 0..from.per {
            for tu in 0..from.per {
                store
                    .read(
                        from.offset(from.tile_no(face, stv, tu)),
                        &mut src[tu * tv_len..(tu + 1) * tv_len],
                    )
                    .map_err(EncodeError::reading)?;
            }
            // Output rows of tiles 2 stv and 2 stv + 1 take source rows of tiles stv.
            for r in 0..2 {
                let tv = 2 * stv + r;
                if tv >= to.per {
                    continue;
                }
                for tu in 0..to.per {
                    out.iter_mut().for_each(|x| *x = 0);
                    for y in (0..t).step_by(2) {
                        let sy = (tv * t + y) / 2 - stv * t;
                        for x in (0..t).step_by(2) {
                            let sx = (tu * t + x) / 2;
                            let (stu, xx) = (sx / t, sx % t);
                            if stu < from.per {
                                out[y * t + x] = src[stu * tv_len + sy * t + xx];
                            }
                        }
                    }
                    store
                        .write(to.offset(to.tile_no(face, tv, tu)), &out)
                        .map_err(EncodeError::writing)?;
                }
            }
        }
    }
    Ok(())
}
