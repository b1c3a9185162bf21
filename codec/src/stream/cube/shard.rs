//! Sharded builds of planets: `N` processes each analyse the fine octaves of a band of
//! the cube raster's rows, a merge finishes the coarse octaves and codes every blob, and
//! the result is the single process's out-of-core build ([`super::encode_cube`]) byte
//! for byte.
//!
//! Why it works: as for planar rasters ([`crate::stream::encode_shard`]), the analysis
//! is integer lifting diamond by diamond, and a diamond changes only its own points. A
//! shard owns the diamonds whose centre lies in its band of rows (face by face, rows in
//! order: global row `face (2S + 1) + v`) and the rows of `R_m` there, `m` the split
//! octave. The cube's faces meet along edges that are far apart in that order, so the
//! halo is not a band of rows: it is the set of tiles from which the shard's diamonds
//! come out exact, found backwards from the top ([`Closure`]). Before each level, the
//! tiles that must be exact after it need every diamond of the level touching them
//! (each diamond's tiles over all its pieces, across cube edges); those diamonds' tiles
//! must be exact before it. Between octaves a tile of `R_{o+1}` needs the four tiles of
//! `R_o` it is compacted from. The shard analyses exactly the diamonds found, which are
//! then exact by induction, and holds only the tiles found.
//!
//! Each shard scans the whole source (the value map, coverage and canonical edge values
//! must be global), then turns into integers only the bands of rows it needs
//! ([`pass_one_bands`]): fills are band by band of a face with the rows before as
//! context, so a face's run starts where those rows hold no nodata. It writes only its
//! tiles. Error sums are per fixed piece of the cube raster; each shard keeps those
//! starting in its band, and the merge adds them in sample order.

use std::collections::HashMap;
use std::ops::Range;

use super::super::shard::{
    Header, ShardPart, SideEntry, check_detail, check_parts, check_request, join_parts,
};
use super::super::{DetailsOut, IndexSpill, Meter};
use super::{
    BlobSink, Borders, CONTEXT_ROWS, CubeEncoded, CubeOptions, CubeSource, Lattice, Only, Partial,
    Scanned, Side, Spill, TileStore, analyse_octaves, analysis_state, code_blobs, compact,
    detail_spill, diamond_tiles, gather_roots, lattice_at, scan_cube, write_integers,
};
use crate::coverage::Coverage;
use crate::encode::{EncodeError, EncodeReport, PASS_CHUNK, SideInfo, Tally, rms_of_pieces};
use crate::raster::{EncodeLayout, Layout};
use crate::sphere_raster::SphereGeometry;
use crate::stream::{ShardFigures, ShardSpec};

/// The diamonds of one level grouped by what the closure asks of them: the tiles (of
/// their octave's raster) they touch and the shard that owns them.
struct Groups {
    tiles: Vec<Vec<usize>>,
    owner: Vec<usize>,
    /// Each diamond's group.
    of: Vec<u32>,
}

/// How a planet's build is split: the side of the blocks exactness is tracked in (the
/// diamond size, or the tile side if smaller: blocks nest in tiles), the bands of global
/// rows, the split octave, and each level's groups.
struct CubeLayout {
    b: usize,
    bands: Vec<Range<usize>>,
    split: usize,
    groups: Vec<Option<Groups>>,
}

/// What one shard holds and analyses for one split: blocks per octave `0 ..= split`,
/// groups per level (the levels of octaves below the split).
struct Closure {
    blocks: Vec<Vec<bool>>,
    groups: Vec<Option<Vec<bool>>>,
}

impl CubeLayout {
    /// The layout of `count` shards, and what shard `k` holds and analyses.
    fn new(
        geom: &SphereGeometry,
        b: usize,
        (k, count): (usize, usize),
    ) -> Result<(CubeLayout, Closure), EncodeError> {
        let (face_side, n) = (geom.face_side(), geom.n());
        let w = face_side + 1;
        let most = 6 * (face_side / (2 * n)).max(1);
        if count == 0 || count > most {
            return Err(EncodeError::Shard(format!(
                "{count} shards for a planet of face side {face_side}: give 1 to {most} (one \
                 per {} rows of the cube raster at least)",
                2 * n
            )));
        }
        let levels = geom.slot_levels().len();
        let octaves = levels / 2;
        if octaves < 2 {
            return Err(EncodeError::Shard(
                "the planet has one octave: build it in one process".into(),
            ));
        }
        let rows = 6 * w;
        let bands: Vec<Range<usize>> = (0..count)
            .map(|k| k * rows / count..(k + 1) * rows / count)
            .collect();
        let owner_of = |row: usize| bands.partition_point(|b| b.end <= row);
        let mut groups: Vec<Option<Groups>> = (0..levels).map(|_| None).collect();
        // The levels of octaves 0 .. octaves - 1 (the merge keeps at least the last).
        for o in 0..octaves - 1 {
            let lattice = Lattice::new(face_side, b, o, 0);
            for level in [levels - 1 - 2 * o, levels - 2 - 2 * o] {
                let mut index: HashMap<(Vec<usize>, usize), u32> = HashMap::new();
                let mut g = Groups {
                    tiles: Vec::new(),
                    owner: Vec::new(),
                    of: Vec::with_capacity(geom.level(level).len()),
                };
                let mut own = Vec::new();
                for s in geom.level(level) {
                    own.clear();
                    diamond_tiles(&lattice, &s.piece_corners(n), &mut own);
                    own.sort_unstable();
                    own.dedup();
                    let owner = owner_of(s.vertex_index(n / 2, n / 2) / w);
                    let key = (own.clone(), owner);
                    let next = g.tiles.len() as u32;
                    let id = *index.entry(key).or_insert_with(|| {
                        g.tiles.push(own.clone());
                        g.owner.push(owner);
                        next
                    });
                    g.of.push(id);
                }
                groups[level] = Some(g);
            }
        }
        let mut layout = CubeLayout {
            b,
            bands,
            split: 0,
            groups,
        };
        // The split octave: the least critical path in blocks analysed, the widest
        // shard's fine octaves then the merge's coarse ones twice (analysis, coding).
        let total = Lattice::new(face_side, b, 0, 0).tiles() as f64;
        let mut best: Option<(f64, usize, Closure)> = None;
        for split in 1..octaves {
            let mut widest = 0;
            let mut mine = None;
            for shard in 0..count {
                let c = layout.closure(geom, shard, split)?;
                widest = widest.max(c.blocks[0].iter().filter(|&&x| x).count());
                if shard == k {
                    mine = Some(c);
                }
            }
            let keep = 0.25f64.powi(split as i32);
            let cost = widest as f64 * (1.0 - keep) + 2.0 * total * keep;
            if best.as_ref().is_none_or(|(c, ..)| cost < *c)
                && let Some(mine) = mine
            {
                best = Some((cost, split, mine));
            }
        }
        let (_, split, closure) = best.ok_or(EncodeError::Internal("no split octave"))?;
        layout.split = split;
        Ok((layout, closure))
    }

    /// Rows of `R_split` (global: `face ((S >> split) + 1) + y`) whose first entry is in
    /// shard `k`'s band.
    fn coarse_rows(&self, face_side: usize, k: usize, split: usize) -> Range<usize> {
        let (w, ws) = (face_side + 1, (face_side >> split) + 1);
        let band = &self.bands[k];
        let owned: Vec<usize> = (0..6 * ws)
            .filter(|&r| band.contains(&((r / ws) * w + ((r % ws) << split))))
            .collect();
        match (owned.first(), owned.last()) {
            (Some(&f), Some(&l)) => f..l + 1,
            _ => 0..0,
        }
    }

    /// What shard `k` must hold and analyse for a split at `split` (see the module docs).
    fn closure(
        &self,
        geom: &SphereGeometry,
        k: usize,
        split: usize,
    ) -> Result<Closure, EncodeError> {
        let (face_side, b) = (geom.face_side(), self.b);
        let levels = geom.slot_levels().len();
        let top = Lattice::new(face_side, b, split, 0);
        let ws = top.side();
        let mut blocks = vec![Vec::new(); split + 1];
        blocks[split] = vec![false; top.tiles()];
        for r in self.coarse_rows(face_side, k, split) {
            for bu in 0..top.per {
                blocks[split][top.tile_no(r / ws, (r % ws) / b, bu)] = true;
            }
        }
        let mut groups: Vec<Option<Vec<bool>>> = (0..levels).map(|_| None).collect();
        for o in (0..split).rev() {
            let (up, here) = (
                Lattice::new(face_side, b, o + 1, 0),
                Lattice::new(face_side, b, o, 0),
            );
            let req = &blocks[o + 1];
            let mut after = vec![false; here.tiles()];
            for face in 0..6 {
                for tv in 0..up.per {
                    for tu in 0..up.per {
                        if !req[up.tile_no(face, tv, tu)] {
                            continue;
                        }
                        for (sv, su) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                            let (sv, su) = (2 * tv + sv, 2 * tu + su);
                            if sv < here.per && su < here.per {
                                after[here.tile_no(face, sv, su)] = true;
                            }
                        }
                    }
                }
            }
            // The octave's levels in reverse analysis order.
            for level in [levels - 2 - 2 * o, levels - 1 - 2 * o] {
                let g = self.groups[level]
                    .as_ref()
                    .ok_or(EncodeError::Internal("a shard level without groups"))?;
                let need: Vec<bool> = g
                    .tiles
                    .iter()
                    .zip(&g.owner)
                    .map(|(ts, &owner)| owner == k || ts.iter().any(|&x| after[x]))
                    .collect();
                for (ts, _) in g.tiles.iter().zip(&need).filter(|(_, n)| **n) {
                    for &x in ts {
                        after[x] = true;
                    }
                }
                groups[level] = Some(need);
            }
            blocks[o] = after;
        }
        Ok(Closure { blocks, groups })
    }
}

/// Analyses shard `spec` of a planet out of core: scans the whole source, turns the bands
/// it needs into integers, holds and analyses only what its diamonds need (see the module
/// docs),
/// hands the details of each diamond it owns (with data) to `details` as `(level,
/// index, details)`, and returns what the merge needs besides. `extra` is stored in the
/// part and must be equal in every part of a build. Lossless and max-error modes.
pub fn encode_cube_shard(
    source: &mut dyn CubeSource,
    opts: CubeOptions,
    spec: ShardSpec,
    extra: Vec<u8>,
    details: &mut DetailsOut<'_>,
    (spill, tiles): (&mut dyn IndexSpill, &mut dyn TileStore),
) -> Result<ShardPart, EncodeError> {
    check_request(opts.mode, spec)?;
    let (face_side, n) = (source.face_side(), opts.n);
    let w = face_side + 1;
    let mut meter = Meter::default();
    let Scanned {
        geom,
        borders,
        tile: t,
        coverage,
        map,
        fill,
        range,
        canon,
        counted: valid,
    } = scan_cube(source, opts, &mut meter)?;
    let block = if n < t && t.is_multiple_of(n) { n } else { t };
    let (layout, closure) = CubeLayout::new(&geom, block, (spec.index, spec.count))?;
    let (k, split) = (spec.index, layout.split);
    let band = layout.bands[k].clone();
    let levels = geom.slot_levels().len();
    let fine_from = levels - 2 * split;
    let mut owned = vec![Vec::new(); levels];
    let mut diamonds = vec![Vec::new(); levels];
    for l in fine_from..levels {
        let (Some(g), Some(need)) = (&layout.groups[l], &closure.groups[l]) else {
            return Err(EncodeError::Internal("a shard level without groups"));
        };
        diamonds[l] = g.of.iter().map(|&x| need[x as usize]).collect();
        owned[l] = g.of.iter().map(|&x| g.owner[x as usize] == k).collect();
    }
    // The tiles holding the blocks.
    let tiles_of = |o: usize, blocks: &[bool]| -> Vec<bool> {
        let (fine, coarse) = (
            Lattice::new(face_side, layout.b, o, 0),
            Lattice::new(face_side, t, o, 0),
        );
        let mut held = vec![false; coarse.tiles()];
        let ratio = t / layout.b;
        for (k, _) in blocks.iter().enumerate().filter(|&(_, &x)| x) {
            let (face, rest) = (k / (fine.per * fine.per), k % (fine.per * fine.per));
            let (bv, bu) = (rest / fine.per, rest % fine.per);
            held[coarse.tile_no(face, bv / ratio, bu / ratio)] = true;
        }
        held
    };
    let only = Only {
        tiles: closure
            .blocks
            .iter()
            .enumerate()
            .map(|(o, b)| tiles_of(o, b))
            .collect(),
        diamonds,
    };

    // Pass 1 over the bands the shard needs, writing its tiles only.
    let lattice = Lattice::new(face_side, t, 0, 0);
    let partial = Partial {
        bands: pass_one_bands(source, &borders, (&canon, &only.tiles[0]), &band, (w, t))?,
        canon,
    };
    let (pieces, _) = write_integers(
        source,
        &geom,
        &borders,
        (&map, &fill),
        (&lattice, Some(&only.tiles[0]), Some(&partial)),
        tiles,
        &mut meter,
    )?;

    // The fine octaves, then `R_split`'s owned rows.
    let (mut store, mut side) = analysis_state(&geom, spill)?;
    let cache_bytes = opts.memory_budget_bytes / 2;
    let second = lattice.len();
    let last = analyse_octaves(
        &geom,
        (0..split, lattice, (second, cache_bytes)),
        tiles,
        (&mut store, &mut *spill),
        (&mut side, None),
        Some(&only),
        &mut meter,
    )?;
    let top = lattice_at(face_side, t, split, second);
    compact(
        &last,
        &top,
        tiles,
        &mut meter,
        Some((&only.tiles[split - 1], &only.tiles[split])),
    )?;
    let coarse_rows = layout.coarse_rows(face_side, k, split);
    let coarse = read_rows(&top, coarse_rows.clone(), tiles)?;

    let mut entries: Vec<SideEntry> = Vec::new();
    let mut h = vec![0i32; n * n];
    let mut counted = (0usize, 0usize);
    for (l, own) in owned.iter().enumerate().skip(fine_from) {
        for (i, &mine) in own.iter().enumerate() {
            counted.0 += usize::from(only.diamonds[l][i]);
            if !mine {
                continue;
            }
            if !only.diamonds[l][i] {
                return Err(EncodeError::Internal(
                    "a shard's own diamond was not analysed",
                ));
            }
            counted.1 += 1;
            let bounds = if l == fine_from {
                side.bounds[i]
            } else {
                (0, 0)
            };
            let data = side.has_data[l][i];
            entries.push((l, i, side.gamma[l][i], data, bounds));
            if data {
                store.get(spill, l, i, &mut h)?;
                details(l, i, &h).map_err(EncodeError::writing)?;
            }
        }
    }
    let start = band.start * w;
    let end = band.end * w;
    let mut kept = Vec::new();
    let mut max_error = 0.0f64;
    for &(p, (sum2, max)) in &pieces {
        let at = p * PASS_CHUNK;
        if (start..end).contains(&at) {
            kept.push((at as u64, sum2));
            max_error = max_error.max(max);
        }
    }
    // Rows of the cube raster of which the shard holds any tile.
    let per = w.div_ceil(t);
    let window_rows: usize = only.tiles[0]
        .chunks(per)
        .enumerate()
        .filter(|(_, row)| row.iter().any(|&x| x))
        .map(|(r, _)| t.min(w - (r % per) * t))
        .sum();
    let header = Header {
        width: w,
        height: 6 * w,
        n,
        mode: opts.mode,
        sparse: opts.sparse,
        budget: opts.memory_budget_bytes,
        chunk_rows: t,
        shards: spec.count,
        split,
        valid,
        scale: map.scale,
        offset: map.offset,
        scan: range,
        coverage: coverage.as_ref().map(Coverage::to_bytes),
        extra,
        planet: true,
    };
    Ok(ShardPart {
        header,
        index: k,
        coarse_rows,
        coarse,
        side: entries,
        counts: Vec::new(),
        pieces: kept,
        max_error,
        figures: ShardFigures {
            split,
            band_rows: band.len(),
            window_rows,
            integer_rows: partial
                .bands
                .iter()
                .map(|b| (b.end * t).min(w).saturating_sub(b.start * t))
                .sum(),
            analysed: counted.0,
            owned: counted.1,
            peak_buffer_bytes: meter.peak,
        },
    })
}

/// The bands of rows (rows of tiles, `t` rows) of each face a shard's pass 1 runs over:
/// those holding its tiles of `R_0` (`present`), its rows, and the rest of the last error
/// piece starting in them; each face's run begins at the latest band whose previous
/// [`CONTEXT_ROWS`] rows hold no nodata (so its fills are the single process's), and
/// takes in the bands holding the canonical copies of its edge points that are nodata
/// (whose integers are fills).
fn pass_one_bands(
    source: &mut dyn CubeSource,
    borders: &Borders,
    (canon, present): (&HashMap<usize, f64>, &[bool]),
    band: &Range<usize>,
    (w, t): (usize, usize),
) -> Result<Vec<Range<usize>>, EncodeError> {
    let per = w.div_ceil(t);
    let mut need: Vec<Option<(usize, usize)>> = vec![None; 6];
    let mut add = |face: usize, b: usize| {
        let r = need[face].get_or_insert((b, b));
        *r = (r.0.min(b), r.1.max(b));
    };
    for (k, _) in present.iter().enumerate().filter(|&(_, &x)| x) {
        add(k / (per * per), (k / per) % per);
    }
    if band.start < band.end {
        let last_piece = (band.end * w - 1) / PASS_CHUNK;
        let end = ((last_piece + 1) * PASS_CHUNK).min(6 * w * w);
        for row in band.start..end.div_ceil(w) {
            add(row / w, (row % w) / t);
        }
    }
    let mut known = canon.clone();
    let mut rows = vec![0.0; CONTEXT_ROWS * w];
    let mut bands = vec![0..0; 6];
    for face in (0..6).rev() {
        let Some((lo, hi)) = need[face] else {
            continue;
        };
        let mut start = lo;
        while start > 0 {
            let first = start * t;
            let c = CONTEXT_ROWS.min(first);
            let buf = &mut rows[..c * w];
            source
                .read_face_rows(face, first - c, c, buf)
                .map_err(EncodeError::reading)?;
            borders.apply(face, (first - c, c), buf, &mut known, false)?;
            if buf.iter().all(|v| v.is_finite()) {
                break;
            }
            start -= 1;
        }
        bands[face] = start..hi + 1;
        // Nodata canonical copies of this run's edge points: their faces come first.
        let run = start * t..((hi + 1) * t).min(w);
        for &(v, _, k) in &borders.copies[face] {
            if run.contains(&v) && !canon.get(&k).is_some_and(|x| x.is_finite()) {
                let (g, row) = (k / (w * w), (k / w) % w);
                let r = need[g].get_or_insert((row / t, row / t));
                *r = (r.0.min(row / t), r.1.max(row / t));
            }
        }
    }
    Ok(bands)
}

/// Global rows `rows` of `R_o` (`lattice`: `face (side) + y`) from the tiles.
fn read_rows(
    lattice: &Lattice,
    rows: Range<usize>,
    tiles: &mut dyn TileStore,
) -> Result<Vec<i32>, EncodeError> {
    let ws = lattice.side();
    let mut out = vec![0i32; rows.len() * ws];
    let mut r = rows.start;
    while r < rows.end {
        // The rest of this face's rows.
        let (face, y) = (r / ws, r % ws);
        let count = (ws - y).min(rows.end - r);
        let o = (r - rows.start) * ws;
        lattice
            .read_rows(tiles, (face, y, count), &mut out[o..o + count * ws])
            .map_err(EncodeError::reading)?;
        r += count;
    }
    Ok(out)
}

/// The merge of a planet's sharded build: [`CubeMerge::new`] checks and assembles the
/// parts (`R_split` into the tiles), [`CubeMerge::add`] takes the shards' details into
/// the spill, [`CubeMerge::finish`] analyses the coarse octaves, trains the model on
/// every diamond and codes every blob, as [`super::encode_cube`] does.
pub struct CubeMerge {
    header: Header,
    geom: SphereGeometry,
    coverage: Option<Coverage>,
    side: Side,
    store: Spill,
    fine_from: usize,
    seen: Vec<Vec<bool>>,
    /// The integerisation's summed squared errors (in sample order) and largest error.
    errors: (f64, f64),
    meter: Meter,
}

impl CubeMerge {
    /// Checks that `parts` are every shard of one planet's build, each once, and writes
    /// their rows of `R_split` into `tiles`.
    pub fn new(
        parts: Vec<ShardPart>,
        spill: &mut dyn IndexSpill,
        tiles: &mut dyn TileStore,
    ) -> Result<CubeMerge, EncodeError> {
        let (header, parts) = check_parts(parts, true)?;
        let w = header.width;
        if w < 2 || header.height != 6 * w {
            return Err(EncodeError::Shard("the parts' cube has a bad shape".into()));
        }
        let face_side = w - 1;
        let coverage = header
            .coverage
            .as_deref()
            .map(Coverage::from_bytes)
            .transpose()
            .map_err(|e| EncodeError::Shard(format!("bad coverage in the parts: {e}")))?;
        let geom = SphereGeometry::new(face_side, header.n)?;
        let geom = match &coverage {
            Some(c) => geom.covered(c)?,
            None => geom,
        };
        let levels = geom.slot_levels().len();
        let (t, split) = (header.chunk_rows, header.split);
        if ![32, 64, 128, 256].contains(&t) || split == 0 || 2 * split >= levels {
            return Err(EncodeError::Shard(
                "the parts' tiles or split do not fit the planet".into(),
            ));
        }
        let fine_from = levels - 2 * split;
        let ws = (face_side >> split) + 1;
        let mut side = Side {
            gamma: (0..levels).map(|l| vec![0; geom.level(l).len()]).collect(),
            has_data: (0..levels)
                .map(|l| vec![false; geom.level(l).len()])
                .collect(),
            bounds: vec![(0, 0); geom.level(fine_from).len()],
        };
        let lens: Vec<usize> = (0..levels).map(|l| geom.level(l).len()).collect();
        // Details seen, per level from `fine_from`.
        let seen: Vec<Vec<bool>> = lens[fine_from..].iter().map(|&k| vec![false; k]).collect();
        let joined = join_parts(
            parts,
            (ws, 6 * ws * ws),
            (&lens, fine_from),
            |l, i, g, d, b| {
                side.gamma[l][i] = g;
                side.has_data[l][i] = d;
                if l == fine_from {
                    side.bounds[i] = b;
                }
            },
        )?;
        let mut meter = Meter::default();
        meter.note(joined.coarse.len() * 4);
        let second = Lattice::new(face_side, t, 0, 0).len();
        let top = lattice_at(face_side, t, split, second);
        for (face, rows) in joined.coarse.chunks_exact(ws * ws).enumerate() {
            top.write_face(tiles, face, rows)
                .map_err(EncodeError::writing)?;
        }
        let store = detail_spill(&geom, spill)?;
        Ok(CubeMerge {
            header,
            geom,
            coverage,
            side,
            store,
            fine_from,
            seen,
            errors: (joined.sum2, joined.max),
            meter,
        })
    }

    /// Takes the details of shard diamonds `(level, index, details)` into the spill.
    /// Each diamond with data must come exactly once.
    pub fn add(
        &mut self,
        items: &[(usize, usize, Vec<i32>)],
        spill: &mut dyn IndexSpill,
    ) -> Result<(), EncodeError> {
        let levels = self.geom.slot_levels().len();
        let mut by_level: Vec<Vec<(usize, &[i32])>> = vec![Vec::new(); levels];
        for &(l, i, ref h) in items {
            check_detail(
                (l, i, h),
                (self.header.n, self.fine_from),
                &self.side.has_data,
                &mut self.seen,
            )?;
            if h.iter().any(|&x| x != 0) {
                by_level[l].push((i, h));
            }
        }
        for (l, batch) in by_level.iter().enumerate() {
            if !batch.is_empty() {
                self.store.put_batch(spill, l, batch)?;
            }
        }
        Ok(())
    }

    /// Analyses the coarse octaves from the tiles, trains the model, codes every blob
    /// into `sink` and reports; every shard diamond with data must have been added.
    pub fn finish(
        mut self,
        sink: &mut dyn BlobSink,
        spill: &mut dyn IndexSpill,
        tiles: &mut dyn TileStore,
    ) -> Result<CubeEncoded, EncodeError> {
        let geom = &self.geom;
        let levels = geom.slot_levels().len();
        for (k, seen) in self.seen.iter().enumerate() {
            let l = self.fine_from + k;
            if let Some(i) = (0..seen.len()).find(|&i| self.side.has_data[l][i] && !seen[i]) {
                return Err(EncodeError::Shard(format!(
                    "the parts' details lack diamond {i} of level {l}"
                )));
            }
        }
        let h = &self.header;
        let (face_side, t, split) = (h.width - 1, h.chunk_rows, h.split);
        let cache_bytes = h.budget / 2;
        let second = Lattice::new(face_side, t, 0, 0).len();
        let top = lattice_at(face_side, t, split, second);
        let last = analyse_octaves(
            geom,
            (split..levels / 2, top, (second, cache_bytes)),
            tiles,
            (&mut self.store, &mut *spill),
            (&mut self.side, None),
            None,
            &mut self.meter,
        )?;
        let roots = gather_roots(geom, &last, cache_bytes, tiles, &mut self.meter)?;
        let side = SideInfo::from_parts(self.side.gamma, self.side.has_data);
        let steps = vec![256u32; levels];
        let (model, count, bytes) = code_blobs(geom, &steps, &side, &self.store, spill, sink)?;
        let report = EncodeReport::tally(Tally {
            samples: geom.distinct_len(),
            valid_samples: h.valid,
            blobs: (count, bytes),
            roots: &roots,
            model: &model,
            steps: steps.len(),
            errors: rms_of_pieces(&[self.errors], h.valid),
            rdo: false,
            decodes: 0,
        });
        Ok(CubeEncoded {
            face_side,
            n: h.n,
            value_scale_m: h.scale,
            value_offset_m: h.offset,
            steps,
            roots,
            model,
            report,
            peak_buffer_bytes: self.meter.peak,
            tile_store_bytes: (second + lattice_at(face_side, t, 1, 0).len()) as u64 * 4,
            coverage: self.coverage,
            decoded: None,
        })
    }
}
