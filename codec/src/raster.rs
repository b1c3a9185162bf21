//! The whole-raster transform: a planar raster of any size placed in a diamond hierarchy.
//!
//! The raster (`width x height`, sample `(row, col)` at id point `(x, y) = (col, row)`)
//! sits in the planar domain `[0, S]^2` with `S = N 2^k` the smallest such square that
//! holds it; id units are raster samples, so the finest data lattice is the integer grid
//! and levels `0 ..= 2k - 1` carry details. Points outside the raster are *invalid*: they
//! are never read, never coded, and cost nothing (no padding is coded). Lifting runs in
//! place on the raster, one level at a time, one diamond at a time.

use rayon::prelude::*;

use crate::blob::BlobContext;
use crate::coverage::Coverage;
use crate::diamond::PlanarId;
use crate::lifting::{self, DiamondMask};
use quincunx_decoder::lattice::{Lattice, read_lattice, write_lattice};
#[doc(inline)]
pub use quincunx_decoder::raster::{DiamondSlot, RasterError, RasterFrame};
use quincunx_decoder::raster::{apply_coverage, check_coverage, slot};

/// The hierarchy a raster is placed in: domain, diamond size and, per detail level, the
/// diamonds that meet the raster.
#[derive(Clone, Debug)]
pub struct RasterGeometry {
    frame: RasterFrame,
    levels: Vec<Vec<DiamondSlot>>,
}

/// The geometry answers everything its frame does (placement of the raster and of single
/// diamonds); its own methods are those that need the tables.
impl std::ops::Deref for RasterGeometry {
    type Target = RasterFrame;

    fn deref(&self) -> &RasterFrame {
        &self.frame
    }
}

impl RasterGeometry {
    /// Places a `width x height` raster in the smallest hierarchy of `N x N` diamonds.
    pub fn new(width: usize, height: usize, n: usize) -> Result<Self, RasterError> {
        let frame = RasterFrame::new(width, height, n, None)?;
        let domain = frame.domain();
        let detail_levels = frame.detail_levels() as u32;
        let rect = [0, width as i64 - 1, 0, height as i64 - 1];
        let mut levels: Vec<Vec<DiamondSlot>> = (0..detail_levels)
            .map(|level| {
                domain
                    .diamonds_meeting(level, rect)
                    .into_par_iter()
                    .filter_map(|id| slot(&domain, id, n, width, height))
                    .collect()
            })
            .collect();
        for level in 0..levels.len().saturating_sub(1) {
            let index: std::collections::HashMap<PlanarId, usize> = levels[level + 1]
                .iter()
                .enumerate()
                .map(|(k, s)| (s.id, k))
                .collect();
            levels[level].par_iter_mut().for_each(|s| {
                for child in domain.children(s.id).unwrap_or_default() {
                    if let Some(&k) = index.get(&child) {
                        s.children.push(k);
                        if domain.parents(child).ok().and_then(|p| p.first().copied()) == Some(s.id)
                        {
                            s.owned.push(k);
                        }
                    }
                }
            });
        }
        Ok(RasterGeometry { frame, levels })
    }

    /// Like [`RasterGeometry::new`], with the points outside the covered blocks of
    /// `coverage` invalid too (sparse mode, see [`crate::coverage`]): diamonds that meet
    /// uncovered blocks get masks. The diamonds are those of [`RasterGeometry::new`].
    pub fn with_coverage(
        width: usize,
        height: usize,
        n: usize,
        coverage: &Coverage,
    ) -> Result<Self, RasterError> {
        let mut g = Self::new(width, height, n)?;
        check_coverage(width, height, coverage)?;
        let empty = DiamondMask::none(n);
        for level in &mut g.levels {
            level.par_iter_mut().for_each(|s| {
                apply_coverage(s, n, width, height, coverage, &empty);
            });
        }
        g.frame.set_coverage(Some(coverage.clone()));
        Ok(g)
    }

    /// Whether raster sample `(x, y)` is a valid point: inside the raster and, with a
    /// coverage, in a covered block.
    pub fn is_valid(&self, x: usize, y: usize) -> bool {
        x < self.frame.width()
            && y < self.frame.height()
            && self
                .frame
                .coverage()
                .is_none_or(|c| c.covers_point(0, x, y))
    }

    /// The diamonds of a detail level that meet the raster.
    pub fn level(&self, level: usize) -> &[DiamondSlot] {
        &self.levels[level]
    }

    /// What the blob decoder must know about diamond `index` of detail level `level`.
    pub fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_> {
        let s = &self.levels[level][index];
        self.frame.slot_context(level, s, s.owned.len())
    }

    /// The root diamond's slot (level 0), used for the root grid.
    pub fn root_slot(&self) -> DiamondSlot {
        // The root always meets the raster.
        slot(
            &self.frame.domain(),
            self.frame.domain().root(),
            self.frame.n(),
            self.frame.width(),
            self.frame.height(),
        )
        .unwrap_or_else(|| unreachable!())
    }

    /// Reads the root vertex grid (invalid vertices read as 0).
    pub fn gather_root(&self, raster: &[i32]) -> Vec<i32> {
        let root = self.root_slot();
        let mut v = vec![0; (self.frame.n() + 1) * (self.frame.n() + 1)];
        self.gather_vertices(&root, raster, &mut v);
        v
    }

    /// Writes the root vertex grid into the raster.
    pub fn scatter_root(&self, root_grid: &[i32], raster: &mut [i32]) {
        let root = self.root_slot();
        self.scatter_vertices(&root, root_grid, raster, 0, 0);
    }

    fn index(&self, (x, y): (i64, i64)) -> Option<usize> {
        if x >= 0
            && y >= 0
            && (x as usize) < self.frame.width()
            && (y as usize) < self.frame.height()
        {
            Some(y as usize * self.frame.width() + x as usize)
        } else {
            None
        }
    }

    fn gather_vertices(&self, s: &DiamondSlot, raster: &[i32], v: &mut [i32]) {
        let n = self.frame.n();
        if let Some([v0, _, si, sj]) = s.lin {
            read_lattice(raster, n + 1, v0, si, sj, v);
            return;
        }
        for i in 0..=n {
            for j in 0..=n {
                v[i * (n + 1) + j] = self.index(s.vertex_xy(i, j)).map_or(0, |k| raster[k]);
            }
        }
    }

    fn gather_cells(&self, s: &DiamondSlot, raster: &[i32], c: &mut [i32]) {
        let n = self.frame.n();
        if let Some([_, c0, si, sj]) = s.lin {
            read_lattice(raster, n, c0, si, sj, c);
            return;
        }
        for i in 0..n {
            for j in 0..n {
                c[i * n + j] = self.index(s.cell_xy(i, j)).map_or(0, |k| raster[k]);
            }
        }
    }

    /// Writes vertices `margin..=n - margin` of each row and column: margin 0 writes the
    /// whole grid, margin 1 only the interior, which is all lifting ever changes
    /// (boundary vertices are never updated). Only raster indices inside `part`
    /// (`raster[start..start + part.len()]`) are written.
    fn scatter_vertices(
        &self,
        s: &DiamondSlot,
        v: &[i32],
        part: &mut [i32],
        start: usize,
        margin: usize,
    ) {
        let n = self.frame.n();
        if let Some([v0, _, si, sj]) = s.lin {
            write_lattice(part, start, n + 1, margin, v0, si, sj, v);
            return;
        }
        for i in margin..=n - margin {
            for j in margin..=n - margin {
                if let Some(x) = self.part_entry(s.vertex_xy(i, j), part, start) {
                    *x = v[i * (n + 1) + j];
                }
            }
        }
    }

    /// Writes the cell centres that fall inside `part` (see [`Self::scatter_vertices`]).
    fn scatter_cells(&self, s: &DiamondSlot, c: &[i32], part: &mut [i32], start: usize) {
        let n = self.frame.n();
        if let Some([_, c0, si, sj]) = s.lin {
            write_lattice(part, start, n, 0, c0, si, sj, c);
            return;
        }
        for i in 0..n {
            for j in 0..n {
                if let Some(x) = self.part_entry(s.cell_xy(i, j), part, start) {
                    *x = c[i * n + j];
                }
            }
        }
    }

    /// The entry of `part` (raster indices from `start`) at a raster position, if both
    /// are inside.
    fn part_entry<'p>(
        &self,
        xy: (i64, i64),
        part: &'p mut [i32],
        start: usize,
    ) -> Option<&'p mut i32> {
        let k = self.index(xy)?.checked_sub(start)?;
        part.get_mut(k)
    }

    /// Forward transform in place: on return the raster holds the root-level values and
    /// the result holds one `N x N` detail matrix per diamond per level (zeros at
    /// invalid cells). Diamonds of a level are processed in parallel.
    pub fn analyze(&self, raster: &mut [i32]) -> Result<Vec<Vec<Vec<i32>>>, RasterError> {
        check_len(self, raster)?;
        Ok(analyze_levels(self, raster))
    }

    /// Inverse transform in place: the raster holds the root-level values on entry (see
    /// [`RasterGeometry::scatter_root`]) and the full-resolution values on exit.
    /// `details(level, index, h)` fills the detail matrix `h` of a diamond and returns
    /// `Ok(false)` when the diamond has none (zeros). Runs on the calling thread.
    pub fn synthesize<E>(
        &self,
        raster: &mut [i32],
        details: impl FnMut(usize, usize, &mut [i32]) -> Result<bool, E>,
    ) -> Result<(), E>
    where
        E: From<RasterError>,
    {
        synthesize_checked(self, raster, details)
    }

    /// Like [`RasterGeometry::synthesize`] with the diamonds of a level in parallel, calling
    /// `visit(level, index, coarse_vertices, fine_vertices, cells)` for each diamond
    /// (used by the encoder to measure side information).
    pub fn synthesize_par<F, R>(
        &self,
        raster: &mut [i32],
        details: &[Vec<Vec<i32>>],
        visit: F,
    ) -> Result<Vec<Vec<R>>, RasterError>
    where
        F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
        R: Send,
    {
        synthesize_par_checked(self, raster, details, visit)
    }
}

/// Checks that `raster` has the geometry's sample count.
pub(crate) fn check_len<G: Layout>(g: &G, raster: &[i32]) -> Result<(), RasterError> {
    if raster.len() == g.raster_len() {
        Ok(())
    } else {
        Err(RasterError::WrongLength {
            expected: g.raster_len(),
            got: raster.len(),
        })
    }
}

/// The public `synthesize` of both geometries: length check, then [`synthesize_levels`].
pub(crate) fn synthesize_checked<G: Layout, E: From<RasterError>>(
    g: &G,
    raster: &mut [i32],
    details: impl FnMut(usize, usize, &mut [i32]) -> Result<bool, E>,
) -> Result<(), E> {
    check_len(g, raster)?;
    synthesize_levels(g, raster, details)
}

/// The public `synthesize_par` of both geometries: length checks, then
/// [`synthesize_levels_par`] over the given detail matrices.
pub(crate) fn synthesize_par_checked<G, F, R>(
    g: &G,
    raster: &mut [i32],
    details: &[Vec<Vec<i32>>],
    visit: F,
) -> Result<Vec<Vec<R>>, RasterError>
where
    G: Layout,
    F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
    R: Send,
{
    check_len(g, raster)?;
    check_details(g, details)?;
    synthesize_levels_par(
        g,
        raster,
        |l, i, h| {
            h.copy_from_slice(&details[l][i]);
            h.iter().any(|&x| x != 0)
        },
        visit,
    )
}

/// A placement of diamonds in a flat sample array (a planar raster, or the six face arrays
/// of a cube raster): everything the level-by-level transform and the encoder need to
/// know about a geometry. Implemented by [`RasterGeometry`] and
/// [`crate::sphere_raster::SphereGeometry`].
pub(crate) trait Layout: Sync {
    /// Where one diamond's samples live.
    type Slot: Sync;
    /// Diamond size `N`.
    fn n(&self) -> usize;
    /// The diamonds of each detail level, coarsest first.
    fn slot_levels(&self) -> &[Vec<Self::Slot>];
    /// Length of the sample array.
    fn raster_len(&self) -> usize;
    /// Valid points of a diamond (`None` = all).
    fn mask<'s>(&self, s: &'s Self::Slot) -> Option<&'s DiamondMask>;
    /// Indices (next level) of a diamond's children.
    fn children<'s>(&self, s: &'s Self::Slot) -> &'s [usize];
    /// Indices (next level) of the children whose side information its blob carries.
    fn owned<'s>(&self, s: &'s Self::Slot) -> &'s [usize];
    /// Reads the `(N+1)^2` vertex grid.
    fn gather_vertices(&self, s: &Self::Slot, raster: &[i32], v: &mut [i32]);
    /// Reads the `N^2` cell centres.
    fn gather_cells(&self, s: &Self::Slot, raster: &[i32], c: &mut [i32]);
    /// Writes the interior vertices (all lifting ever changes) to every copy of each
    /// point, as far as they fall in `part`, the raster entries from index `start` (so
    /// disjoint parts of the raster are written in parallel).
    fn scatter_interior_part(&self, s: &Self::Slot, v: &[i32], part: &mut [i32], start: usize);
    /// Writes the cell centres to every copy of each point inside `part` (see
    /// [`Layout::scatter_interior_part`]).
    fn scatter_cells_part(&self, s: &Self::Slot, c: &[i32], part: &mut [i32], start: usize);
    /// Lowest and highest raster index a diamond's scatters can write (a bound).
    fn index_span(&self, s: &Self::Slot) -> (usize, usize);
    /// [`Layout::scatter_interior_part`] into the whole raster.
    fn scatter_interior(&self, s: &Self::Slot, v: &[i32], raster: &mut [i32]) {
        self.scatter_interior_part(s, v, raster, 0);
    }
    /// [`Layout::scatter_cells_part`] into the whole raster.
    fn scatter_cells(&self, s: &Self::Slot, c: &[i32], raster: &mut [i32]) {
        self.scatter_cells_part(s, c, raster, 0);
    }
    /// What the blob decoder must know about a diamond.
    fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_>;
    /// Reads the root vertex grids, in root order.
    fn gather_roots(&self, raster: &[i32]) -> Vec<Vec<i32>>;
    /// Writes the root vertex grids; errors if their number or sizes are wrong.
    fn scatter_roots(&self, roots: &[Vec<i32>], raster: &mut [i32]) -> Result<(), RasterError>;
    /// Clears `mask[k]` (a whole sample array) wherever entry `k` is not the one copy of
    /// its point that error measurements count.
    fn clear_duplicates(&self, mask: &mut [bool]);
    /// Number of distinct points.
    fn distinct_len(&self) -> usize;
    /// Writes `to_int(fill)` into `out[k]` wherever `valid[k]` is false, the fill being a
    /// smooth continuation of the valid `values` around it (so holes make no spikes);
    /// `false` if nothing is valid.
    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool;
    /// The coverage that makes points invalid (sparse mode), if any.
    fn coverage(&self) -> Option<&Coverage>;
    /// Per array entry, whether it is a valid point; `None` when every entry is.
    fn point_validity(&self) -> Option<Vec<bool>>;
}

/// Diamonds transformed in parallel, then written back together ([`scatter_chunk`]):
/// large enough to keep both cores busy, small enough that the lattices stay in a reused
/// buffer.
const CHUNK: usize = 1024;

/// Parts a chunk's raster range is split into for [`scatter_chunk`] (a few per thread).
const SCATTER_PARTS: usize = 8;

/// Writes a chunk of transformed diamonds back: interior vertices of diamond `k` when
/// `interior[k]`, and cells when `cells` is given. Diamonds of one level write disjoint
/// entries, so the chunk's raster range is cut into parts written in parallel, each by
/// the diamonds that reach into it.
fn scatter_chunk<G: Layout>(
    g: &G,
    raster: &mut [i32],
    chunk: &[G::Slot],
    vbuf: &[i32],
    cells: Option<&[i32]>,
    interior: &[bool],
) {
    let n = g.n();
    let (vlen, clen) = ((n + 1) * (n + 1), n * n);
    let spans: Vec<(usize, usize)> = chunk.iter().map(|s| g.index_span(s)).collect();
    let lo = spans.iter().map(|s| s.0).min().unwrap_or(0);
    let hi = spans
        .iter()
        .map(|s| s.1)
        .max()
        .unwrap_or(0)
        .min(raster.len().saturating_sub(1));
    if lo > hi {
        return;
    }
    let part_len = (hi + 1 - lo).div_ceil(SCATTER_PARTS);
    raster[lo..=hi]
        .par_chunks_mut(part_len)
        .enumerate()
        .for_each(|(p, part)| {
            let start = lo + p * part_len;
            let end = start + part.len();
            for (k, s) in chunk.iter().enumerate() {
                if spans[k].1 < start || spans[k].0 >= end {
                    continue;
                }
                if interior[k] {
                    g.scatter_interior_part(s, &vbuf[k * vlen..(k + 1) * vlen], part, start);
                }
                if let Some(c) = cells {
                    g.scatter_cells_part(s, &c[k * clen..(k + 1) * clen], part, start);
                }
            }
        });
}

/// Forward transform of every level, fine to coarse, diamonds of a level in parallel.
pub(crate) fn analyze_levels<G: Layout>(g: &G, raster: &mut [i32]) -> Vec<Vec<Vec<i32>>> {
    analyze_levels_with(g, raster, |_, _, _, _, _| ()).0
}

/// [`analyze_levels`], calling `visit(level, index, coarse_vertices, fine_vertices, cells)`
/// for each diamond (the lattice after and before its analysis: what synthesis will turn
/// back into each other), in parallel within a level.
pub(crate) fn analyze_levels_with<G: Layout, F, R>(
    g: &G,
    raster: &mut [i32],
    visit: F,
) -> (Vec<Vec<Vec<i32>>>, Vec<Vec<R>>)
where
    F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
    R: Send,
{
    let n = g.n();
    let (vlen, clen) = ((n + 1) * (n + 1), n * n);
    let levels = g.slot_levels();
    let mut details = vec![Vec::new(); levels.len()];
    let mut visits: Vec<Vec<R>> = (0..levels.len()).map(|_| Vec::new()).collect();
    // Coarse vertex lattices of a chunk of diamonds, reused (no per-level allocation).
    let mut vbuf = vec![0; CHUNK * vlen];
    for level in (0..levels.len()).rev() {
        let slots = &levels[level];
        let mut hs = Vec::with_capacity(slots.len());
        let mut rs = Vec::with_capacity(slots.len());
        for start in (0..slots.len()).step_by(CHUNK) {
            let chunk = &slots[start..(start + CHUNK).min(slots.len())];
            let shared: &[i32] = raster;
            let results: Vec<(Vec<i32>, R)> = vbuf
                .par_chunks_mut(vlen)
                .zip(chunk.par_iter())
                .enumerate()
                .map(|(k, (v, s))| {
                    let mut c = vec![0; clen];
                    let mut h = vec![0; clen];
                    g.gather_vertices(s, shared, v);
                    g.gather_cells(s, shared, &mut c);
                    let fine = v.to_vec();
                    lifting::analyze(n, v, &c, &mut h, g.mask(s));
                    let r = visit(level, start + k, v, &fine, &c);
                    (h, r)
                })
                .collect();
            scatter_chunk(g, raster, chunk, &vbuf, None, &vec![true; chunk.len()]);
            for (h, r) in results {
                hs.push(h);
                rs.push(r);
            }
        }
        details[level] = hs;
        visits[level] = rs;
    }
    (details, visits)
}

pub(crate) fn synthesize_levels<G: Layout, E>(
    g: &G,
    raster: &mut [i32],
    mut details: impl FnMut(usize, usize, &mut [i32]) -> Result<bool, E>,
) -> Result<(), E> {
    let n = g.n();
    let mut h = vec![0; n * n];
    let mut v = vec![0; (n + 1) * (n + 1)];
    let mut c = vec![0; n * n];
    for (level, slots) in g.slot_levels().iter().enumerate() {
        for (index, s) in slots.iter().enumerate() {
            let has = details(level, index, &mut h)?;
            g.gather_vertices(s, raster, &mut v);
            if has {
                lifting::synthesize(n, &mut v, &h, &mut c, g.mask(s));
                g.scatter_interior(s, &v, raster);
            } else {
                // No details: the vertices stay as they are, the cells are predicted.
                lifting::synthesize_zero(n, &v, &mut c, g.mask(s));
            }
            g.scatter_cells(s, &c, raster);
        }
    }
    Ok(())
}

/// Inverse transform with the diamonds of a level in parallel and a per-diamond visitor.
/// Checks that `details` has one `N x N` matrix per diamond of every level.
pub(crate) fn check_details<G: Layout>(
    g: &G,
    details: &[Vec<Vec<i32>>],
) -> Result<(), RasterError> {
    let levels = g.slot_levels();
    let nn = g.n() * g.n();
    if details.len() != levels.len()
        || details
            .iter()
            .zip(levels)
            .any(|(d, s)| d.len() != s.len() || d.iter().any(|h| h.len() != nn))
    {
        return Err(RasterError::WrongLength {
            expected: levels.iter().map(Vec::len).sum(),
            got: details.iter().map(Vec::len).sum(),
        });
    }
    Ok(())
}

/// Inverse transform with the diamonds of a level in parallel: `details(level, index, h)`
/// fills a diamond's details and says whether any is nonzero (a diamond without details
/// skips the update and the vertex write-back); `visit(level, index, coarse, fine, cells)`
/// sees each diamond's lattices before and after.
pub(crate) fn synthesize_levels_par<G, D, F, R>(
    g: &G,
    raster: &mut [i32],
    details: D,
    visit: F,
) -> Result<Vec<Vec<R>>, RasterError>
where
    G: Layout,
    D: Fn(usize, usize, &mut [i32]) -> bool + Sync,
    F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
    R: Send,
{
    let n = g.n();
    let (vlen, clen) = ((n + 1) * (n + 1), n * n);
    let levels = g.slot_levels();
    let mut out = Vec::with_capacity(levels.len());
    // Refined lattices of a chunk of diamonds, reused (no per-level allocation).
    let mut vbuf = vec![0; CHUNK * vlen];
    let mut cbuf = vec![0; CHUNK * clen];
    let mut hbuf = vec![0; CHUNK * clen];
    for (level, slots) in levels.iter().enumerate() {
        let mut rs = Vec::with_capacity(slots.len());
        for start in (0..slots.len()).step_by(CHUNK) {
            let chunk = &slots[start..(start + CHUNK).min(slots.len())];
            let shared: &[i32] = raster;
            let results: Vec<(R, bool)> = vbuf
                .par_chunks_mut(vlen)
                .zip(cbuf.par_chunks_mut(clen))
                .zip(hbuf.par_chunks_mut(clen))
                .zip(chunk.par_iter())
                .enumerate()
                .map(|(k, (((v, c), h), s))| {
                    let has = details(level, start + k, h);
                    g.gather_vertices(s, shared, v);
                    if has {
                        let coarse = v.to_vec();
                        lifting::synthesize(n, v, h, c, g.mask(s));
                        (visit(level, start + k, &coarse, v, c), true)
                    } else {
                        // No details: the vertices stay, the cells are the prediction.
                        lifting::synthesize_zero(n, v, c, g.mask(s));
                        (visit(level, start + k, v, v, c), false)
                    }
                })
                .collect();
            let has: Vec<bool> = results.iter().map(|r| r.1).collect();
            scatter_chunk(g, raster, chunk, &vbuf, Some(&cbuf), &has);
            rs.extend(results.into_iter().map(|r| r.0));
        }
        out.push(rs);
    }
    Ok(out)
}

impl Layout for RasterGeometry {
    type Slot = DiamondSlot;

    fn n(&self) -> usize {
        self.frame.n()
    }

    fn slot_levels(&self) -> &[Vec<DiamondSlot>] {
        &self.levels
    }

    fn raster_len(&self) -> usize {
        self.frame.width() * self.frame.height()
    }

    fn mask<'s>(&self, s: &'s DiamondSlot) -> Option<&'s DiamondMask> {
        s.mask.as_ref()
    }

    fn children<'s>(&self, s: &'s DiamondSlot) -> &'s [usize] {
        &s.children
    }

    fn owned<'s>(&self, s: &'s DiamondSlot) -> &'s [usize] {
        &s.owned
    }

    fn gather_vertices(&self, s: &DiamondSlot, raster: &[i32], v: &mut [i32]) {
        RasterGeometry::gather_vertices(self, s, raster, v);
    }

    fn gather_cells(&self, s: &DiamondSlot, raster: &[i32], c: &mut [i32]) {
        RasterGeometry::gather_cells(self, s, raster, c);
    }

    fn index_span(&self, s: &DiamondSlot) -> (usize, usize) {
        match s.lin {
            Some([v0, _, si, sj]) => {
                let (lo, hi) =
                    Lattice::new(self.frame.n() + 1, 0, self.frame.n() + 1, v0, si, sj).span();
                (lo.max(0) as usize, hi.max(0) as usize)
            }
            None => (0, self.raster_len().saturating_sub(1)),
        }
    }

    fn scatter_interior_part(&self, s: &DiamondSlot, v: &[i32], part: &mut [i32], start: usize) {
        self.scatter_vertices(s, v, part, start, 1);
    }

    fn scatter_cells_part(&self, s: &DiamondSlot, c: &[i32], part: &mut [i32], start: usize) {
        RasterGeometry::scatter_cells(self, s, c, part, start);
    }

    fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_> {
        RasterGeometry::blob_context(self, level, index)
    }

    fn gather_roots(&self, raster: &[i32]) -> Vec<Vec<i32>> {
        vec![self.gather_root(raster)]
    }

    fn scatter_roots(&self, roots: &[Vec<i32>], raster: &mut [i32]) -> Result<(), RasterError> {
        let side = (self.frame.n() + 1) * (self.frame.n() + 1);
        match roots {
            [root] if root.len() == side => {
                self.scatter_root(root, raster);
                Ok(())
            }
            _ => Err(RasterError::WrongLength {
                expected: side,
                got: roots.iter().map(Vec::len).sum(),
            }),
        }
    }

    fn clear_duplicates(&self, _mask: &mut [bool]) {}

    fn distinct_len(&self) -> usize {
        self.frame.width() * self.frame.height()
    }

    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool {
        crate::fill::fill_into(
            self.frame.width(),
            self.frame.height(),
            values,
            valid,
            out,
            to_int,
        )
    }

    fn coverage(&self) -> Option<&Coverage> {
        self.frame.coverage()
    }

    fn point_validity(&self) -> Option<Vec<bool>> {
        self.frame.coverage()?;
        Some(
            (0..self.frame.width() * self.frame.height())
                .into_par_iter()
                .map(|k| self.is_valid(k % self.frame.width(), k / self.frame.width()))
                .collect(),
        )
    }
}
#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> Vec<i32> {
        (0..w * h)
            .map(|k| (k % w) as i32 * 7 - (k / w) as i32 * 3 + ((k * 2654435761) % 97) as i32)
            .collect()
    }

    #[test]
    fn lattice_lines_cover_each_point_once_in_every_orientation() {
        let w_raster = 1000isize;
        // Axis-aligned, transposed and both 45-degree rotations, at several spacings.
        for (si, sj) in [
            (w_raster, 1),
            (1, w_raster),
            (2 * w_raster, -2),
            (w_raster + 1, -w_raster + 1),
            (w_raster + 1, w_raster - 1),
            (-w_raster - 1, w_raster - 1),
            (2 * w_raster - 2, -2 * w_raster - 2),
        ] {
            for (m, o, w) in [(33, 0, 33), (32, 0, 32), (31, 1, 33), (1, 0, 1), (2, 0, 2)] {
                let base = 400 * w_raster + 400;
                let mut seen = Vec::new();
                Lattice::new(m, o, w, base, si, sj).lines(|r, rs, b, bs, len| {
                    for t in 0..len {
                        seen.push((r + t as isize * rs, b + t * bs));
                    }
                });
                let mut want: Vec<(isize, usize)> = (o..o + m)
                    .flat_map(|i| {
                        (o..o + m)
                            .map(move |j| (base + i as isize * si + j as isize * sj, i * w + j))
                    })
                    .collect();
                seen.sort_unstable();
                want.sort_unstable();
                assert_eq!(seen, want, "si {si} sj {sj} m {m} o {o}");
                // Written part by part (cut anywhere), the raster is what one write gives.
                let lat = Lattice::new(m, o, w, base, si, sj);
                let buf: Vec<i32> = (0..(w * w) as i32).map(|x| x + 1).collect();
                let len = (1000 * w_raster) as usize;
                let mut whole = vec![0; len];
                lat.write_part(&buf, &mut whole, 0);
                for part_len in [1usize, 7, 999, 1000, 4093, 65536] {
                    let mut parts = vec![0; len];
                    for (p, part) in parts.chunks_mut(part_len).enumerate() {
                        lat.write_part(&buf, part, p * part_len);
                    }
                    assert!(parts == whole, "si {si} sj {sj} m {m} parts of {part_len}");
                }
                let (lo, hi) = lat.span();
                assert_eq!(whole.iter().position(|&x| x != 0), usize::try_from(lo).ok());
                assert_eq!(
                    whole.iter().rposition(|&x| x != 0),
                    usize::try_from(hi).ok()
                );
            }
        }
    }

    #[test]
    fn lossless_round_trip_for_odd_sizes() {
        for (w, h, n) in [
            (1, 1, 4),
            (5, 3, 4),
            (33, 33, 32),
            (100, 37, 8),
            (65, 129, 32),
            (300, 200, 32),
        ] {
            let g = RasterGeometry::new(w, h, n).unwrap();
            let orig = ramp(w, h);
            let mut r = orig.clone();
            let details = g.analyze(&mut r).unwrap();
            let root = g.gather_root(&r);
            let mut out = vec![0; w * h];
            g.scatter_root(&root, &mut out);
            g.synthesize::<RasterError>(&mut out, |l, i, h| {
                h.copy_from_slice(&details[l][i]);
                Ok(true)
            })
            .unwrap();
            assert_eq!(out, orig, "{w}x{h} N={n}");
        }
    }
}
