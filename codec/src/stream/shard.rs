//! Sharded builds of planar rasters: `N` processes each analyse a band of rows, a merge
//! finishes the coarse octaves and codes every blob, and the result is the single
//! process's out-of-core build byte for byte.
//!
//! Why it works. The analysis is integer lifting, diamond by diamond, and a diamond
//! changes only its own points, so a value after octave `o` depends only on values of
//! `R_o` near it. A shard owns the diamonds whose centre row is in its band `[a, b)` and
//! the rows of `R_m` there, where `m` is the *split* octave, the same for every shard. It
//! reads the band plus a halo, and at each octave analyses exactly the groups of diamonds
//! whose rows are all exact (read, or written only by exact diamonds); the halo is the
//! smallest for which every diamond it owns is exact ([`Layout`]). Everything a shard
//! analyses outside its band is analysed again by the owner; that redundancy is the
//! price of independence (korea, 4 shards: 1.2-1.6x the rows of a band).
//!
//! What is exact besides the analysis:
//! - Pass 0 (range, quantum, valid count, coverage, the mean fill's sum in value order)
//!   reads the whole source in every shard: it is cheap next to the analysis, and the
//!   value map must be global before any integer exists.
//! - Nodata fills are push-pull per read chunk with the previous chunk's filled rows as
//!   context. A shard starts filling at the latest chunk whose context rows hold no
//!   nodata (their fills are their values), so its fills are the single process's.
//! - Error sums are per fixed piece of a chunk; each shard keeps the sums of the pieces
//!   that start in its band with their offsets, and the merge adds them in sample order.
//! - Training counts are integers, summed; the side information of a shard's diamonds is
//!   bottom-up within the shard (their children are in the shard, or in its halo).
//!
//! The merge assembles `R_m` (a `4^-m` share of the samples), analyses the coarse octaves
//! in memory, trains the model, codes the coarse diamonds and then every shard's
//! diamonds from the details the shards wrote ([`Merge::code`]). Lossless and max-error
//! modes only: the RMS rate control searches over the whole analysis.

use std::ops::Range;

use rayon::prelude::*;

use super::{
    BlobSink, CONTEXT_ROWS, Coded, DetailsOut, Errors, Feed, Keep, Meter, Plan, RowSource, Side,
    StreamEncoded, StreamOptions, Window, Work, octave_groups, prepare, root_grid, run_octaves,
};
use crate::blob;
use crate::coverage::Coverage;
use crate::encode::{EncodeError, EncodeReport, RateMode, Tally};
use crate::entropy::{CodecModel, ContextCounts};
use crate::raster::RasterGeometry;

/// Which shard of how many: `index` in `0 .. count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardSpec {
    /// This shard, from 0 (Slurm's `SLURM_ARRAY_TASK_ID`, Kubernetes'
    /// `JOB_COMPLETION_INDEX`).
    pub index: usize,
    /// Shards in all.
    pub count: usize,
}

/// How a shard's work went.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ShardFigures {
    /// The split octave.
    pub split: usize,
    /// Rows the shard owns.
    pub band_rows: usize,
    /// Rows it reads and analyses (band and halo; planets: rows of which it holds a tile).
    pub window_rows: usize,
    /// Rows it turns into integers (the window, from where its fills start; planets: the
    /// runs of bands of [`crate::stream::encode_cube_shard`]'s pass 1).
    pub integer_rows: usize,
    /// Diamonds it analysed (its own and its halo's).
    pub analysed: usize,
    /// Diamonds it owns.
    pub owned: usize,
    /// Largest number of bytes of sample buffers held at once.
    pub peak_buffer_bytes: usize,
}

/// What every part of one build shares: the source's dimensions and scan, the options,
/// the split, and the caller's `extra` bytes (the CLI's description of the build). Parts
/// whose headers differ come from different builds.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Header {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) n: usize,
    pub(super) mode: RateMode,
    pub(super) sparse: bool,
    pub(super) budget: usize,
    pub(super) chunk_rows: usize,
    pub(super) shards: usize,
    pub(super) split: usize,
    pub(super) valid: usize,
    pub(super) scale: f64,
    pub(super) offset: f64,
    pub(super) scan: [f64; 3],
    pub(super) coverage: Option<Vec<u8>>,
    pub(super) extra: Vec<u8>,
    /// A planet's part (`width` is the face side plus one, `height` six times that,
    /// `chunk_rows` the tile side).
    pub(super) planet: bool,
}

/// The `A` groups and `B` bands an octave analyses.
type Allow = (Range<usize>, Range<usize>);

/// One side-information entry: `(level, index, gamma, has data, bounds)`.
pub(super) type SideEntry = (usize, usize, u64, bool, (i64, i64));

/// What a shard hands to the merge (besides the details it wrote as it went).
#[derive(Clone, Debug, PartialEq)]
pub struct ShardPart {
    pub(super) header: Header,
    pub(super) index: usize,
    /// Rows of `R_split` owned, and their values.
    pub(super) coarse_rows: Range<usize>,
    pub(super) coarse: Vec<i32>,
    pub(super) side: Vec<SideEntry>,
    pub(super) counts: Vec<[u64; 2]>,
    pub(super) pieces: Vec<(u64, f64)>,
    pub(super) max_error: f64,
    /// How the shard's work went (not part of what must agree).
    pub figures: ShardFigures,
}

/// How a build of `height` rows is split among shards: the split octave and, per
/// shard, the band of rows it owns and the window it reads.
struct Layout {
    split: usize,
    /// Ownership by a diamond's centre row (the last band runs to `usize::MAX`).
    bands: Vec<Range<usize>>,
    windows: Vec<Range<usize>>,
    allow: Vec<Vec<(Range<usize>, Range<usize>)>>,
}

/// The shape of one octave: rows of `R_o`, its `A` groups and `B` bands.
struct Shape {
    rows: usize,
    a_len: usize,
    b_len: usize,
}

impl Shape {
    /// Rows `A` group `g` spans (clipped).
    fn a_span(&self, n: usize, g: usize) -> (usize, usize) {
        ((n * g).saturating_sub(n), (n * (g + 1)).min(self.rows - 1))
    }

    /// Rows `B` band `j` spans (clipped).
    fn b_span(&self, n: usize, j: usize) -> (usize, usize) {
        (2 * n * j, (2 * n * (j + 1)).min(self.rows - 1))
    }

    /// Given the exact rows `e` of `R_o`: the groups and bands whose every input is
    /// exact, and the rows of `R_o` exact after the octave (every diamond spanning them
    /// was analysed). `None` when nothing is exact.
    fn propagate(&self, n: usize, e: &Range<usize>) -> Option<(Allow, Range<usize>)> {
        let inside = |(s0, s1): (usize, usize)| s0 >= e.start && s1 < e.end;
        let a_ok: Vec<bool> = (0..self.a_len).map(|g| inside(self.a_span(n, g))).collect();
        let b_ok: Vec<bool> = (0..self.b_len)
            .map(|j| {
                inside(self.b_span(n, j))
                    && (2 * j..=2 * j + 2)
                        .filter(|&g| g < self.a_len)
                        .all(|g| a_ok[g])
            })
            .collect();
        let a = run_of(&a_ok)?;
        let b = run_of(&b_ok).unwrap_or(0..0);
        let row_ok: Vec<bool> = (0..self.rows)
            .map(|r| {
                e.contains(&r)
                    && ((r / n).saturating_sub(1)..=r / n + 1)
                        .filter(|&g| g < self.a_len)
                        .filter(|&g| {
                            let (s0, s1) = self.a_span(n, g);
                            s0 <= r && r <= s1
                        })
                        .all(|g| a_ok[g])
                    && ((r / (2 * n)).saturating_sub(1)..=r / (2 * n))
                        .filter(|&j| j < self.b_len)
                        .filter(|&j| {
                            let (s0, s1) = self.b_span(n, j);
                            s0 <= r && r <= s1
                        })
                        .all(|j| b_ok[j])
            })
            .collect();
        Some(((a, b), run_of(&row_ok)?))
    }
}

/// The indices of the one run of `true` in `flags` (`None`: no `true`, or more than one
/// run, which the octave's structure rules out).
fn run_of(flags: &[bool]) -> Option<Range<usize>> {
    let first = flags.iter().position(|&f| f)?;
    let end = first + flags[first..].iter().take_while(|&&f| f).count();
    flags[end..].iter().all(|&f| !f).then_some(first..end)
}

impl Layout {
    fn new(
        geom: &RasterGeometry,
        plan: &Plan,
        count: usize,
        budget: usize,
    ) -> Result<Layout, EncodeError> {
        let (height, n) = (plan.height, plan.n);
        if count == 0 || count > height.div_ceil(2 * n) {
            return Err(EncodeError::Shard(format!(
                "{count} shards for {height} rows: give 1 to {} (one per {} rows at least)",
                height.div_ceil(2 * n),
                2 * n
            )));
        }
        let octaves = plan.dims.len() - 1;
        let shapes: Vec<Shape> = (0..octaves)
            .map(|o| {
                let (_, _, a, b) = octave_groups(geom, n, o)?;
                Ok(Shape {
                    rows: plan.dims[o].1,
                    a_len: a.len(),
                    b_len: b.len(),
                })
            })
            .collect::<Result<_, EncodeError>>()?;
        let bands: Vec<Range<usize>> = (0..count)
            .map(|k| {
                let end = if k + 1 == count {
                    usize::MAX
                } else {
                    (k + 1) * height / count
                };
                k * height / count..end
            })
            .collect();
        let mut best: Option<(f64, Layout)> = None;
        for split in 1..=octaves {
            // The merge holds `R_split` and a copy of it.
            let (w, h) = plan.dims[split];
            if 8 * w * h > budget.max(1 << 20) && split < octaves {
                continue;
            }
            let mut layout = Layout {
                split,
                bands: bands.clone(),
                windows: Vec::new(),
                allow: Vec::new(),
            };
            for band in &bands {
                let (window, allow) = window_for(&shapes, plan, split, band)?;
                layout.windows.push(window);
                layout.allow.push(allow);
            }
            // Critical path in rows analysed: the widest shard's fine octaves, then the
            // merge's coarse ones twice (analysis, coding).
            let widest = layout.windows.iter().map(|w| w.len()).max().unwrap_or(0);
            let keep = 0.25f64.powi(split as i32);
            let cost = widest as f64 * (1.0 - keep) + 2.0 * height as f64 * keep;
            if best.as_ref().is_none_or(|(c, _)| cost < *c) {
                best = Some((cost, layout));
            }
        }
        best.map(|(_, l)| l)
            .ok_or(EncodeError::Internal("no split octave fits"))
    }
}

/// The smallest window (band plus halo) from which a shard analyses every diamond it
/// owns at octaves below `split` and every row of `R_split` it owns; the groups it
/// analyses at each octave.
#[allow(clippy::type_complexity)]
fn window_for(
    shapes: &[Shape],
    plan: &Plan,
    split: usize,
    band: &Range<usize>,
) -> Result<(Range<usize>, Vec<(Range<usize>, Range<usize>)>), EncodeError> {
    let (height, n) = (plan.height, plan.n);
    let end = band.end.min(height);
    let try_halo = |halo: usize| -> Option<Vec<(Range<usize>, Range<usize>)>> {
        let mut e = band.start.saturating_sub(halo)..(end + halo).min(height);
        let mut allows = Vec::new();
        for (o, shape) in shapes.iter().enumerate().take(split) {
            let ((a, b), after) = shape.propagate(n, &e)?;
            let step = n << o;
            let owned = |centre: usize| band.contains(&centre);
            if (0..shape.a_len).any(|g| owned(g * step) && !a.contains(&g))
                || (0..shape.b_len).any(|j| owned((2 * j + 1) * step) && !b.contains(&j))
            {
                return None;
            }
            allows.push((a, b));
            e = after.start.div_ceil(2)..after.end.div_ceil(2);
        }
        let rows = plan.dims[split].1;
        (0..rows)
            .filter(|&r| band.contains(&(r << split)))
            .all(|r| e.contains(&r))
            .then_some(allows)
    };
    let (mut lo, mut hi) = (0, height);
    if try_halo(hi).is_none() {
        return Err(EncodeError::Internal(
            "a shard's window cannot cover its band",
        ));
    }
    while lo < hi {
        let mid = (lo + hi) / 2;
        if try_halo(mid).is_some() {
            hi = mid;
        } else {
            lo = mid + 1;
        }
    }
    let allow = try_halo(lo).ok_or(EncodeError::Internal("halo search"))?;
    Ok((band.start.saturating_sub(lo)..(end + lo).min(height), allow))
}

/// A shard's request: an exact rate mode and an index below the count.
pub(super) fn check_request(mode: RateMode, spec: ShardSpec) -> Result<(), EncodeError> {
    if matches!(mode, RateMode::RmsM(_)) {
        return Err(EncodeError::Shard(
            "sharded builds take --lossless or --max-error-m: the RMS rate control searches \
             over the whole analysis"
                .into(),
        ));
    }
    if spec.count == 0 {
        return Err(EncodeError::Shard("0 shards: give 1 or more".into()));
    }
    if spec.index >= spec.count {
        return Err(EncodeError::Shard(format!(
            "shard {} of {}: the index runs from 0 to {}",
            spec.index,
            spec.count,
            spec.count.saturating_sub(1)
        )));
    }
    Ok(())
}

/// Analyses shard `spec` of a planar raster: reads the whole source once (pass 0) and
/// the shard's window once (the analysis), hands the details of each diamond it owns
/// (with data) to `details` as `(level, index, details)`, and returns what the merge
/// needs besides. `extra` is stored in the part and must be equal in every part of a
/// build. Lossless and max-error modes.
pub fn encode_shard(
    source: &mut dyn RowSource,
    opts: StreamOptions,
    spec: ShardSpec,
    extra: Vec<u8>,
    details: &mut DetailsOut<'_>,
) -> Result<ShardPart, EncodeError> {
    check_request(opts.mode, spec)?;
    let prep = prepare(source, &opts)?;
    let (geom, plan, mut meter) = (prep.geom, prep.plan, prep.meter);
    let layout = Layout::new(&geom, &plan, spec.count, opts.memory_budget_bytes)?;
    let k = spec.index;
    let (band, window) = (layout.bands[k].clone(), layout.windows[k].clone());
    let split = layout.split;
    // Fill from the latest chunk at or before the window whose context has no nodata.
    let chunk = plan.chunk_rows;
    let mut from = window.start / chunk * chunk;
    let mut ctx = vec![0.0; CONTEXT_ROWS * plan.width];
    while from > 0 {
        let rows = CONTEXT_ROWS.min(from);
        let buf = &mut ctx[..rows * plan.width];
        source
            .read_rows(from - rows, rows, buf)
            .map_err(EncodeError::reading)?;
        if buf.iter().all(|v| v.is_finite()) {
            break;
        }
        from -= chunk;
    }
    drop(ctx);
    let coarse_rows = {
        let rows = plan.dims[split].1;
        let owned: Vec<usize> = (0..rows)
            .filter(|&r| band.contains(&(r << split)))
            .collect();
        match (owned.first(), owned.last()) {
            (Some(&f), Some(&l)) => f..l + 1,
            _ => 0..0,
        }
    };
    let win = Window {
        read: from..window.end,
        allow: layout.allow[k].clone(),
        keep: coarse_rows.clone(),
    };
    let levels = geom.detail_levels();
    let fine_from = levels - 2 * split;
    let owns = |l: usize, i: usize| {
        l >= fine_from && band.contains(&usize::try_from(geom.level(l)[i].id.y).unwrap_or(0))
    };
    let mut side = Side::new(&geom);
    let mut errors = Errors {
        pieces: Some((band.start..band.end.min(plan.height), Vec::new())),
        ..Errors::default()
    };
    let keep = Keep {
        owns: &owns,
        details,
        analysed: (0..levels)
            .map(|l| vec![false; geom.level(l).len()])
            .collect(),
    };
    let feed = Feed::Source {
        source,
        map: &prep.map,
        fill: &prep.fill,
        window: Some(&win),
    };
    let mut work = Work::Analyse {
        side: &mut side,
        errors: &mut errors,
        keep: Some(keep),
    };
    let coarse = run_octaves(feed, &plan, &geom, 0..split, &mut work, &mut meter)?;
    let Work::Analyse {
        keep: Some(keep), ..
    } = work
    else {
        return Err(EncodeError::Internal("the shard's work changed kind"));
    };
    let analysed_flags = keep.analysed;
    let mut entries = Vec::new();
    let (mut analysed, mut owned) = (0, 0);
    for (l, flags) in analysed_flags.iter().enumerate().skip(fine_from) {
        for (i, &done) in flags.iter().enumerate() {
            analysed += usize::from(done);
            if owns(l, i) {
                if !done {
                    return Err(EncodeError::Internal(
                        "a shard's own diamond was not analysed",
                    ));
                }
                owned += 1;
                entries.push((
                    l,
                    i,
                    side.gamma[l][i],
                    side.has_data[l][i],
                    side.bounds[l][i],
                ));
            }
        }
    }
    let header = Header {
        width: plan.width,
        height: plan.height,
        n: plan.n,
        mode: opts.mode,
        sparse: opts.sparse,
        budget: opts.memory_budget_bytes,
        chunk_rows: plan.chunk_rows,
        shards: spec.count,
        split,
        valid: prep.valid,
        scale: prep.map.scale,
        offset: prep.map.offset,
        scan: prep.scan,
        coverage: prep.coverage.as_ref().map(Coverage::to_bytes),
        extra,
        planet: false,
    };
    let pieces = errors.pieces.take().map(|(_, p)| p).unwrap_or_default();
    Ok(ShardPart {
        header,
        index: k,
        coarse_rows,
        coarse,
        side: entries,
        counts: side.counts.to_pairs(),
        pieces,
        max_error: errors.max,
        figures: ShardFigures {
            split,
            band_rows: band.end.min(plan.height) - band.start,
            window_rows: window.len(),
            integer_rows: window.end - from,
            analysed,
            owned,
            peak_buffer_bytes: meter.peak,
        },
    })
}

/// The merge of a sharded build's parts: [`Merge::new`] checks and assembles them and
/// analyses the coarse octaves, [`Merge::code`] codes the shards' diamonds from their
/// details, [`Merge::finish`] codes the coarse diamonds and reports.
pub struct Merge {
    header: Header,
    geom: RasterGeometry,
    plan: Plan,
    side: Side,
    model: CodecModel,
    coarse: Vec<i32>,
    root: Vec<i32>,
    coverage: Option<Coverage>,
    /// Fine diamonds with data coded so far, per level from `fine_from`.
    seen: Vec<Vec<bool>>,
    fine_from: usize,
    coded: Coded,
    sum2: f64,
    max: f64,
    meter: Meter,
}

impl Merge {
    /// Checks that `parts` are every shard of one build, each once, and assembles them.
    pub fn new(parts: Vec<ShardPart>) -> Result<Merge, EncodeError> {
        let (header, parts) = check_parts(parts, false)?;
        let coverage = header
            .coverage
            .as_deref()
            .map(Coverage::from_bytes)
            .transpose()
            .map_err(|e| EncodeError::Shard(format!("bad coverage in the parts: {e}")))?;
        let geom = match &coverage {
            Some(c) => RasterGeometry::with_coverage(header.width, header.height, header.n, c)?,
            None => RasterGeometry::new(header.width, header.height, header.n)?,
        };
        let plan = Plan::new(&geom, header.budget)?;
        let levels = geom.detail_levels();
        let octaves = plan.dims.len() - 1;
        if header.split == 0 || header.split > octaves || plan.chunk_rows != header.chunk_rows {
            return Err(EncodeError::Shard(
                "the parts' split does not fit the raster".into(),
            ));
        }
        let fine_from = levels - 2 * header.split;
        let (wm, hm) = plan.dims[header.split];
        let mut side = Side::new(&geom);
        let lens: Vec<usize> = (0..levels).map(|l| geom.level(l).len()).collect();
        let joined = join_parts(parts, (wm, wm * hm), (&lens, fine_from), |l, i, g, d, b| {
            side.gamma[l][i] = g;
            side.has_data[l][i] = d;
            side.bounds[l][i] = b;
        })?;
        side.counts = joined.counts;
        let (coarse, sum2, max) = (joined.coarse, joined.sum2, joined.max);
        let mut meter = Meter::default();
        let mut unused = Errors::default();
        let last = run_octaves(
            Feed::Rows(&coarse),
            &plan,
            &geom,
            header.split..octaves,
            &mut Work::Analyse {
                side: &mut side,
                errors: &mut unused,
                keep: None,
            },
            &mut meter,
        )?;
        let root = root_grid(&plan, &geom, &last);
        let model = side.model(&geom);
        let seen = (fine_from..levels)
            .map(|l| vec![false; geom.level(l).len()])
            .collect();
        Ok(Merge {
            header,
            geom,
            plan,
            side,
            model,
            coarse,
            root,
            coverage,
            seen,
            fine_from,
            coded: Coded::default(),
            sum2,
            max,
            meter,
        })
    }

    /// Codes the blobs of shard diamonds `(level, index, details)` (in parallel) into
    /// `sink`. Each diamond with data must come exactly once.
    pub fn code(
        &mut self,
        items: &[(usize, usize, Vec<i32>)],
        sink: &mut dyn BlobSink,
    ) -> Result<(), EncodeError> {
        for (l, i, h) in items {
            check_detail(
                (*l, *i, h),
                (self.header.n, self.fine_from),
                &self.side.has_data,
                &mut self.seen,
            )?;
        }
        let (geom, side, model) = (&self.geom, &self.side, &self.model);
        let blobs: Vec<Vec<u8>> = items
            .par_iter()
            .map(|(l, i, h)| {
                blob::encode(
                    &geom.blob_context(*l, *i),
                    model,
                    &side.classes(geom, *l, *i),
                    h,
                )
            })
            .collect();
        for ((l, i, _), b) in items.iter().zip(&blobs) {
            sink.put(*l, *i, &geom.level(*l)[*i].key, b)
                .map_err(EncodeError::writing)?;
            self.coded.count += 1;
            self.coded.bytes += b.len();
        }
        Ok(())
    }

    /// Codes the coarse diamonds into `sink` and reports; every shard diamond with data
    /// must have been coded.
    pub fn finish(mut self, sink: &mut dyn BlobSink) -> Result<StreamEncoded, EncodeError> {
        for (k, seen) in self.seen.iter().enumerate() {
            let l = self.fine_from + k;
            if let Some(i) = (0..seen.len()).find(|&i| self.side.has_data[l][i] && !seen[i]) {
                return Err(EncodeError::Shard(format!(
                    "the parts' details lack diamond {i} of level {l}"
                )));
            }
        }
        let octaves = self.plan.dims.len() - 1;
        let last = run_octaves(
            Feed::Rows(&self.coarse),
            &self.plan,
            &self.geom,
            self.header.split..octaves,
            &mut Work::Code {
                side: &self.side,
                model: &self.model,
                sink,
                coded: &mut self.coded,
            },
            &mut self.meter,
        )?;
        if root_grid(&self.plan, &self.geom, &last) != self.root {
            return Err(EncodeError::Internal("merge passes disagree"));
        }
        let h = &self.header;
        let steps = vec![256u32; self.geom.detail_levels()];
        let report = EncodeReport::tally(Tally {
            samples: h.width * h.height,
            valid_samples: h.valid,
            blobs: (self.coded.count, self.coded.bytes),
            roots: std::slice::from_ref(&self.root),
            model: &self.model,
            steps: steps.len(),
            errors: ((self.sum2 / h.valid as f64).sqrt(), self.max),
            rdo: false,
            decodes: 0,
        });
        Ok(StreamEncoded {
            width: h.width,
            height: h.height,
            n: h.n,
            value_scale_m: h.scale,
            value_offset_m: h.offset,
            steps,
            root: self.root,
            model: self.model,
            report,
            peak_buffer_bytes: self.meter.peak,
            coverage: self.coverage,
        })
    }
}

/// Checks that `parts` are every shard of one build (of a planet or not), each once;
/// their shared header and the parts in shard order.
pub(super) fn check_parts(
    mut parts: Vec<ShardPart>,
    planet: bool,
) -> Result<(Header, Vec<ShardPart>), EncodeError> {
    let first = parts
        .first()
        .ok_or_else(|| EncodeError::Shard("no parts to merge".into()))?;
    let header = first.header.clone();
    if header.planet != planet {
        return Err(EncodeError::Shard(if planet {
            "the parts are of a planar build, not a planet's".into()
        } else {
            "the parts are of a planet's build, not a planar one".into()
        }));
    }
    header.check()?;
    if let Some((p, field)) = parts
        .iter()
        .find_map(|p| header.differing_field(&p.header).map(|f| (p, f)))
    {
        return Err(EncodeError::Shard(format!(
            "part {} is not from the same build as part {}: their {field} differs",
            p.index, first.index
        )));
    }
    parts.sort_by_key(|p| p.index);
    for w in parts.windows(2) {
        if w[0].index == w[1].index {
            return Err(EncodeError::Shard(format!(
                "part {} is given twice",
                w[0].index
            )));
        }
    }
    let missing: Vec<String> = (0..header.shards)
        .filter(|k| !parts.iter().any(|p| p.index == *k))
        .take(16)
        .map(|k| k.to_string())
        .collect();
    if !missing.is_empty() || parts.len() != header.shards {
        return Err(EncodeError::Shard(format!(
            "the build has {} shards; missing part(s): {}",
            header.shards,
            missing.join(", ")
        )));
    }
    // The geometry is sized from the header's raster size: the parts must carry side
    // information of most of its diamonds (they cover every diamond of the fine levels),
    // so nothing is allocated beyond a small multiple of the parts' own bytes.
    let side: usize = parts.iter().map(|p| p.side.len()).sum();
    let cells = (header.width / header.n).saturating_mul(header.height / header.n);
    if side.saturating_mul(8) < cells {
        return Err(EncodeError::Shard(format!(
            "the parts describe a {} x {} raster but carry side information of only {side} \
             diamonds",
            header.width, header.height
        )));
    }
    Ok((header, parts))
}

/// Checks one diamond's details `(level, index, details)` given to a merge: a diamond of
/// the levels from `fine_from` with data, `N^2` values, not seen before (`seen`, per level
/// from `fine_from`, records it).
pub(super) fn check_detail(
    (l, i, h): (usize, usize, &[i32]),
    (n, fine_from): (usize, usize),
    has_data: &[Vec<bool>],
    seen: &mut [Vec<bool>],
) -> Result<(), EncodeError> {
    let ok = l >= fine_from
        && l < has_data.len()
        && i < has_data[l].len()
        && has_data[l][i]
        && h.len() == n * n;
    if !ok {
        return Err(EncodeError::Shard(format!(
            "details of diamond {i} of level {l} do not belong to the build"
        )));
    }
    if std::mem::replace(&mut seen[l - fine_from][i], true) {
        return Err(EncodeError::Shard(format!(
            "details of diamond {i} of level {l} come twice"
        )));
    }
    Ok(())
}

/// What the parts of a build hold together (see [`join_parts`]).
pub(super) struct Joined {
    /// `R_split`, the parts' rows in order.
    pub(super) coarse: Vec<i32>,
    /// The summed training counts.
    pub(super) counts: ContextCounts,
    /// The parts' error sums added in sample order, as one process adds them.
    pub(super) sum2: f64,
    /// The largest error.
    pub(super) max: f64,
}

/// Joins checked `parts` (in shard order): their rows of `R_split` (`row` values a row,
/// `total` in all) must follow each other, their side entries (each given to `side` as
/// `(level, index, gamma, has data, bounds)`) cover every diamond of the levels from
/// `fine_from` (of `lens` diamonds) once, and their error pieces each sample once.
pub(super) fn join_parts(
    parts: Vec<ShardPart>,
    (row, total): (usize, usize),
    (lens, fine_from): (&[usize], usize),
    mut side: impl FnMut(usize, usize, u64, bool, (i64, i64)),
) -> Result<Joined, EncodeError> {
    let mut joined = Joined {
        coarse: Vec::with_capacity(total),
        counts: ContextCounts::default(),
        sum2: 0.0,
        max: 0.0,
    };
    let mut pieces = Vec::new();
    let mut filled: Vec<Vec<bool>> = lens[fine_from..].iter().map(|&n| vec![false; n]).collect();
    for p in parts {
        let bad = |what: &str| EncodeError::Shard(format!("part {}: {what}", p.index));
        if p.coarse_rows.start != joined.coarse.len() / row.max(1)
            || p.coarse.len() != p.coarse_rows.len() * row
        {
            return Err(bad(
                "its rows of the coarse raster do not follow the previous part's",
            ));
        }
        joined.coarse.extend_from_slice(&p.coarse);
        for &(l, i, gamma, data, bounds) in &p.side {
            if l < fine_from || l >= lens.len() || i >= lens[l] {
                return Err(bad("side information of a diamond that is not a shard's"));
            }
            if std::mem::replace(&mut filled[l - fine_from][i], true) {
                return Err(bad("side information of a diamond another part has"));
            }
            side(l, i, gamma, data, bounds);
        }
        // A planet's merge trains the model itself, from every diamond's details.
        if p.header.planet != p.counts.is_empty() {
            return Err(bad("bad training counts"));
        }
        if !p.header.planet {
            let counts = ContextCounts::from_pairs(p.counts);
            joined
                .counts
                .merge(&counts.ok_or_else(|| bad("bad training counts"))?);
        }
        pieces.extend(p.pieces);
        joined.max = joined.max.max(p.max_error);
    }
    if joined.coarse.len() != total {
        return Err(EncodeError::Shard(
            "the parts do not cover the coarse raster".into(),
        ));
    }
    if filled.iter().any(|l| l.iter().any(|&f| !f)) {
        return Err(EncodeError::Shard("the parts miss some diamonds".into()));
    }
    pieces.sort_by_key(|&(at, _)| at);
    if pieces.windows(2).any(|w| w[0].0 == w[1].0) {
        return Err(EncodeError::Shard(
            "two parts measured the same samples".into(),
        ));
    }
    joined.sum2 = pieces.iter().fold(0.0, |s, &(_, x)| s + x);
    Ok(joined)
}

/// Most shards a build is split into.
pub const MAX_SHARDS: usize = 1 << 16;

/// Largest raster side a part may describe (the codec's limit).
const MAX_SIDE: usize = 1 << 24;

impl Header {
    /// Checks each field against sane limits before anything is sized from it; the error
    /// names the field.
    fn check(&self) -> Result<(), EncodeError> {
        let bad =
            |field: &str, why: String| Err(EncodeError::Shard(format!("the part's {field} {why}")));
        if !(1..=MAX_SHARDS).contains(&self.shards) {
            return bad(
                "shard count",
                format!("{} is outside 1..={MAX_SHARDS}", self.shards),
            );
        }
        let max_height = if self.planet {
            6 * (MAX_SIDE + 1)
        } else {
            MAX_SIDE
        };
        if !(1..=MAX_SIDE + 1).contains(&self.width) || !(1..=max_height).contains(&self.height) {
            return bad(
                "raster size",
                format!("{} x {} is out of range", self.width, self.height),
            );
        }
        if !self.n.is_power_of_two() || !(2..=512).contains(&self.n) {
            return bad(
                "diamond size N",
                format!("{} is not a power of two in 2..=512", self.n),
            );
        }
        if self.split > 48 {
            return bad("split", format!("{} is out of range", self.split));
        }
        if self.valid > self.width.saturating_mul(self.height) {
            return bad(
                "valid sample count",
                format!("{} exceeds the raster", self.valid),
            );
        }
        if let RateMode::MaxErrorM(v) | RateMode::RmsM(v) = self.mode
            && !(v.is_finite() && v > 0.0)
        {
            return bad("rate value", format!("{v} is not a finite positive number"));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return bad(
                "value scale",
                format!("{} is not a finite positive number", self.scale),
            );
        }
        if !self.offset.is_finite() {
            return bad("value offset", format!("{} is not finite", self.offset));
        }
        if let Some(v) = self.scan.iter().find(|v| !v.is_finite()) {
            return bad("source scan", format!("holds {v}, not a finite number"));
        }
        Ok(())
    }

    /// The first field in which two parts' headers differ.
    fn differing_field(&self, other: &Header) -> Option<&'static str> {
        let bits = |v: f64| v.to_bits();
        [
            (
                self.width != other.width || self.height != other.height,
                "raster size",
            ),
            (self.n != other.n, "diamond size N"),
            (self.mode != other.mode, "rate mode"),
            (self.sparse != other.sparse, "sparse flag"),
            (self.budget != other.budget, "memory budget"),
            (self.chunk_rows != other.chunk_rows, "chunk rows"),
            (self.shards != other.shards, "shard count"),
            (self.split != other.split, "split"),
            (self.valid != other.valid, "valid sample count"),
            (bits(self.scale) != bits(other.scale), "value scale"),
            (bits(self.offset) != bits(other.offset), "value offset"),
            (self.scan.map(bits) != other.scan.map(bits), "source scan"),
            (self.coverage != other.coverage, "coverage"),
            (self.extra != other.extra, "build description"),
            (self.planet != other.planet, "planet flag"),
        ]
        .into_iter()
        .find_map(|(differs, field)| differs.then_some(field))
    }
}

/// Bytes of a part: little-endian fields after a magic and version.
const MAGIC: &[u8; 8] = b"QXPART02";

struct Out(Vec<u8>);

impl Out {
    fn u(&mut self, x: usize) {
        self.0.extend_from_slice(&(x as u64).to_le_bytes());
    }
    fn f(&mut self, x: f64) {
        self.0.extend_from_slice(&x.to_bits().to_le_bytes());
    }
    fn bytes(&mut self, b: &[u8]) {
        self.u(b.len());
        self.0.extend_from_slice(b);
    }
}

struct In<'a>(&'a [u8]);

impl In<'_> {
    fn take(&mut self, k: usize) -> Result<&[u8], EncodeError> {
        if self.0.len() < k {
            return Err(EncodeError::Shard("the part is truncated".into()));
        }
        let (a, b) = self.0.split_at(k);
        self.0 = b;
        Ok(a)
    }
    fn u64(&mut self) -> Result<u64, EncodeError> {
        let b = self.take(8)?;
        Ok(u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
    }
    fn u(&mut self) -> Result<usize, EncodeError> {
        usize::try_from(self.u64()?)
            .map_err(|_| EncodeError::Shard("a count in the part is too large".into()))
    }
    /// A count of items of `size` bytes each, checked against what is left.
    fn count(&mut self, size: usize) -> Result<usize, EncodeError> {
        let k = self.u()?;
        if k.checked_mul(size).is_none_or(|b| b > self.0.len()) {
            return Err(EncodeError::Shard("the part is truncated".into()));
        }
        Ok(k)
    }
    fn f(&mut self) -> Result<f64, EncodeError> {
        Ok(f64::from_bits(self.u64()?))
    }
    fn bytes(&mut self) -> Result<Vec<u8>, EncodeError> {
        let k = self.count(1)?;
        Ok(self.take(k)?.to_vec())
    }
}

impl ShardPart {
    /// This part's shard index.
    pub fn index(&self) -> usize {
        self.index
    }

    /// Shards in the build.
    pub fn shards(&self) -> usize {
        self.header.shards
    }

    /// Whether the part is of a planet's build ([`crate::stream::CubeMerge`] merges
    /// those, [`Merge`] the others).
    pub fn is_planet(&self) -> bool {
        self.header.planet
    }

    /// The caller's bytes given to the shard.
    pub fn extra(&self) -> &[u8] {
        &self.header.extra
    }

    /// Replaces the caller's bytes given to the shard (for what is known only once the
    /// source has been read, such as what a mosaic's tiles held).
    pub fn set_extra(&mut self, extra: Vec<u8>) {
        self.header.extra = extra;
    }

    /// The part as bytes ([`ShardPart::from_bytes`] reads them).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut o = Out(MAGIC.to_vec());
        let h = &self.header;
        for x in [h.width, h.height, h.n] {
            o.u(x);
        }
        let (tag, value) = match h.mode {
            RateMode::Lossless => (0, 0.0),
            RateMode::MaxErrorM(e) => (1, e),
            RateMode::RmsM(t) => (2, t),
        };
        o.u(tag);
        o.f(value);
        for x in [
            usize::from(h.sparse),
            h.budget,
            h.chunk_rows,
            h.shards,
            h.split,
            h.valid,
        ] {
            o.u(x);
        }
        for x in [h.scale, h.offset, h.scan[0], h.scan[1], h.scan[2]] {
            o.f(x);
        }
        o.u(usize::from(h.coverage.is_some()));
        o.bytes(h.coverage.as_deref().unwrap_or(&[]));
        o.bytes(&h.extra);
        o.u(usize::from(h.planet));
        o.u(self.index);
        o.u(self.coarse_rows.start);
        o.u(self.coarse_rows.end);
        o.u(self.coarse.len());
        for &v in &self.coarse {
            o.0.extend_from_slice(&v.to_le_bytes());
        }
        o.u(self.side.len());
        for &(l, i, gamma, data, (lo, hi)) in &self.side {
            o.u(l);
            o.u(i);
            o.0.extend_from_slice(&gamma.to_le_bytes());
            o.u(usize::from(data));
            o.0.extend_from_slice(&lo.to_le_bytes());
            o.0.extend_from_slice(&hi.to_le_bytes());
        }
        o.u(self.counts.len());
        for &[a, b] in &self.counts {
            o.0.extend_from_slice(&a.to_le_bytes());
            o.0.extend_from_slice(&b.to_le_bytes());
        }
        o.u(self.pieces.len());
        for &(at, s) in &self.pieces {
            o.0.extend_from_slice(&at.to_le_bytes());
            o.f(s);
        }
        o.f(self.max_error);
        let f = &self.figures;
        for x in [
            f.split,
            f.band_rows,
            f.window_rows,
            f.integer_rows,
            f.analysed,
            f.owned,
            f.peak_buffer_bytes,
        ] {
            o.u(x);
        }
        o.0
    }

    /// Reads [`ShardPart::to_bytes`]'s output; a clear error for anything else.
    pub fn from_bytes(bytes: &[u8]) -> Result<ShardPart, EncodeError> {
        let mut r = In(bytes);
        if r.take(MAGIC.len()).ok() != Some(&MAGIC[..]) {
            return Err(EncodeError::Shard(
                "not a shard part of this version (bad magic)".into(),
            ));
        }
        let (width, height, n) = (r.u()?, r.u()?, r.u()?);
        let (tag, value) = (r.u()?, r.f()?);
        let mode = match tag {
            0 => RateMode::Lossless,
            1 => RateMode::MaxErrorM(value),
            2 => RateMode::RmsM(value),
            _ => return Err(EncodeError::Shard("bad rate mode in the part".into())),
        };
        let sparse = r.u()? != 0;
        let (budget, chunk_rows, shards, split, valid) = (r.u()?, r.u()?, r.u()?, r.u()?, r.u()?);
        let (scale, offset) = (r.f()?, r.f()?);
        let scan = [r.f()?, r.f()?, r.f()?];
        let has_coverage = r.u()? != 0;
        let coverage = r.bytes()?;
        let extra = r.bytes()?;
        let planet = r.u()? != 0;
        let header = Header {
            width,
            height,
            n,
            mode,
            sparse,
            budget,
            chunk_rows,
            shards,
            split,
            valid,
            scale,
            offset,
            scan,
            coverage: has_coverage.then_some(coverage),
            extra,
            planet,
        };
        let index = r.u()?;
        let coarse_rows = r.u()?..r.u()?;
        let k = r.count(4)?;
        let coarse = r
            .take(4 * k)?
            .chunks_exact(4)
            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let k = r.count(48)?;
        let mut side = Vec::with_capacity(k);
        for _ in 0..k {
            let (l, i, gamma, data) = (r.u()?, r.u()?, r.u64()?, r.u()? != 0);
            let (lo, hi) = (r.u64()? as i64, r.u64()? as i64);
            side.push((l, i, gamma, data, (lo, hi)));
        }
        let k = r.count(16)?;
        let mut counts = Vec::with_capacity(k);
        for _ in 0..k {
            counts.push([r.u64()?, r.u64()?]);
        }
        let k = r.count(16)?;
        let mut pieces = Vec::with_capacity(k);
        for _ in 0..k {
            pieces.push((r.u64()?, r.f()?));
        }
        let max_error = r.f()?;
        let figures = ShardFigures {
            split: r.u()?,
            band_rows: r.u()?,
            window_rows: r.u()?,
            integer_rows: r.u()?,
            analysed: r.u()?,
            owned: r.u()?,
            peak_buffer_bytes: r.u()?,
        };
        if !r.0.is_empty() {
            return Err(EncodeError::Shard("the part has trailing bytes".into()));
        }
        header.check()?;
        if index >= shards {
            return Err(EncodeError::Shard(format!(
                "the part says it is shard {index} of {shards}"
            )));
        }
        let rows = if header.planet {
            header.height
        } else {
            header.height.div_ceil(1 << header.split.min(47)) + 1
        };
        if coarse_rows.start > coarse_rows.end || coarse_rows.end > rows {
            return Err(EncodeError::Shard(format!(
                "the part's coarse rows {}..{} are outside the raster",
                coarse_rows.start, coarse_rows.end
            )));
        }
        if !(max_error.is_finite() && max_error >= 0.0) {
            return Err(EncodeError::Shard(format!(
                "the part's largest error is {max_error}, not a finite number >= 0"
            )));
        }
        if let Some((_, x)) = pieces.iter().find(|(_, x)| !(x.is_finite() && *x >= 0.0)) {
            return Err(EncodeError::Shard(format!(
                "the part's error sums hold {x}, not a finite number >= 0"
            )));
        }
        Ok(ShardPart {
            header,
            index,
            coarse_rows,
            coarse,
            side,
            counts,
            pieces,
            max_error,
            figures,
        })
    }
}
