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
use crate::coverage::{BlockState, Coverage};
use crate::diamond::{PlanarDomain, PlanarId, check_size};
use crate::lifting::{self, DiamondMask};

/// Why a raster cannot be placed in a hierarchy.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RasterError {
    /// Zero width or height, or more samples than supported.
    #[error("raster of {0} x {1} samples is empty or too large")]
    BadDimensions(usize, usize),
    /// The diamond size is not supported.
    #[error(transparent)]
    Id(#[from] crate::diamond::IdError),
    /// A planet's face side is not `N` times a power of two (or is too small: `2 S >= 4`).
    #[error("face side {face_side} is not N = {n} times a power of two (and at least 4)")]
    FaceSide {
        /// samples per face side
        face_side: usize,
        /// diamond size
        n: usize,
    },
    /// The number of values does not match the dimensions.
    #[error("expected {expected} values, got {got}")]
    WrongLength {
        /// width x height
        expected: usize,
        /// values given
        got: usize,
    },
    /// A coverage's shape does not fit the geometry.
    #[error("the coverage does not fit the geometry: {0}")]
    Coverage(&'static str),
}

/// Where one diamond's samples live in the raster.
#[derive(Clone, Debug)]
pub struct DiamondSlot {
    /// The diamond.
    pub id: PlanarId,
    x0: i64,
    y0: i64,
    a: [i64; 2],
    b: [i64; 2],
    /// Valid points; `None` when every vertex and cell is valid.
    pub mask: Option<DiamondMask>,
    /// Storage key of the diamond.
    pub key: Vec<u8>,
    /// Indices (in the next detail level) of its children that carry details.
    pub children: Vec<usize>,
    /// The subset of `children` whose side information this diamond's blob carries
    /// (children whose first parent is this diamond), in side order.
    pub owned: Vec<usize>,
    /// For diamonds entirely inside the raster: raster index of vertex (0,0) and of cell
    /// (0,0), and the index steps along i and j.
    lin: Option<[isize; 4]>,
}

impl DiamondSlot {
    fn vertex_xy(&self, i: usize, j: usize) -> (i64, i64) {
        let (i, j) = (i as i64, j as i64);
        (
            self.x0 + i * self.a[0] + j * self.b[0],
            self.y0 + i * self.a[1] + j * self.b[1],
        )
    }

    fn cell_xy(&self, i: usize, j: usize) -> (i64, i64) {
        let (x, y) = self.vertex_xy(i, j);
        (
            x + (self.a[0] + self.b[0]) / 2,
            y + (self.a[1] + self.b[1]) / 2,
        )
    }

    /// Raster position of vertex `(0, 0)` and the steps along `i` and `j`.
    pub(crate) fn frame(&self) -> ([i64; 2], [i64; 2], [i64; 2]) {
        ([self.x0, self.y0], self.a, self.b)
    }

    /// Number of valid cells (the number of coded details).
    pub fn valid_cells(&self, n: usize) -> usize {
        self.mask.as_ref().map_or(n * n, DiamondMask::valid_cells)
    }
}

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
        let domain = frame.domain;
        let detail_levels = frame.detail_levels as u32;
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
        g.frame.coverage = Some(coverage.clone());
        Ok(g)
    }

    /// Whether raster sample `(x, y)` is a valid point: inside the raster and, with a
    /// coverage, in a covered block.
    pub fn is_valid(&self, x: usize, y: usize) -> bool {
        x < self.width
            && y < self.height
            && self
                .coverage
                .as_ref()
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
            &self.domain,
            self.domain.root(),
            self.n,
            self.width,
            self.height,
        )
        .unwrap_or_else(|| unreachable!())
    }

    /// Reads the root vertex grid (invalid vertices read as 0).
    pub fn gather_root(&self, raster: &[i32]) -> Vec<i32> {
        let root = self.root_slot();
        let mut v = vec![0; (self.n + 1) * (self.n + 1)];
        self.gather_vertices(&root, raster, &mut v);
        v
    }

    /// Writes the root vertex grid into the raster.
    pub fn scatter_root(&self, root_grid: &[i32], raster: &mut [i32]) {
        let root = self.root_slot();
        self.scatter_vertices(&root, root_grid, raster, 0, 0);
    }

    fn index(&self, (x, y): (i64, i64)) -> Option<usize> {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            Some(y as usize * self.width + x as usize)
        } else {
            None
        }
    }

    fn gather_vertices(&self, s: &DiamondSlot, raster: &[i32], v: &mut [i32]) {
        let n = self.n;
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
        let n = self.n;
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
        let n = self.n;
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
        let n = self.n;
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

/// The raster range holding `count` entries `base + j step` (`j = 0..count`), as
/// `(first, last)` indices in ascending order.
fn strided_span(base: isize, step: isize, count: usize) -> (usize, usize) {
    let end = base + (count as isize - 1) * step;
    (base.min(end) as usize, base.max(end) as usize)
}

/// The `m x m` sub-grid at `(o, o)` of a diamond's `w x w` lattice (buffer index
/// `i w + j`), whose point `(i, j)` is raster index `base + i si + j sj`.
///
/// [`Lattice::lines`] walks it along the lattice direction with the shortest raster
/// step. For a diamond rotated 45 degrees in the raster that is a diagonal of the
/// lattice, which runs along a raster row: its points are 2 (or 2^k) samples apart
/// instead of a raster row, so the accesses stream through cache lines and pages
/// instead of touching a new page per sample (korea RMS 9 m decoding went from 80 to
/// 89-93 M samples/s; docs/codec.md).
struct Lattice {
    m: usize,
    o: usize,
    w: usize,
    base: isize,
    si: isize,
    sj: isize,
}

impl Lattice {
    fn new(m: usize, o: usize, w: usize, base: isize, si: isize, sj: isize) -> Self {
        Lattice {
            m,
            o,
            w,
            base,
            si,
            sj,
        }
    }

    /// Calls `line(raster_start, raster_step, buffer_start, buffer_step, len)` for lines
    /// covering the sub-grid exactly once.
    fn lines(&self, mut line: impl FnMut(isize, isize, usize, usize, usize)) {
        let (m, w) = (self.m, self.w);
        if m == 0 {
            return;
        }
        let mut at = |i: usize, j: usize, rs: isize, bs: usize, len: usize| {
            let (i, j) = (self.o + i, self.o + j);
            line(
                self.base + i as isize * self.si + j as isize * self.sj,
                rs,
                i * w + j,
                bs,
                len,
            );
        };
        let (si, sj) = (self.si, self.sj);
        let steps = [sj, si, si + sj, si - sj].map(isize::unsigned_abs);
        let best = (0..4).min_by_key(|&k| steps[k]).unwrap_or(0);
        match best {
            0 => (0..m).for_each(|i| at(i, 0, sj, 1, m)),
            1 => (0..m).for_each(|j| at(0, j, si, w, m)),
            2 => {
                // Lines of constant j - i, from the corner (m - 1, 0) to (0, m - 1).
                for i in (1..m).rev() {
                    at(i, 0, si + sj, w + 1, m - i);
                }
                for j in 0..m {
                    at(0, j, si + sj, w + 1, m - j);
                }
            }
            _ => {
                // Lines of constant i + j, stepping (i + 1, j - 1).
                for j in 0..m {
                    at(0, j, si - sj, w - 1, j + 1);
                }
                for i in 1..m {
                    at(i, m - 1, si - sj, w - 1, m - i);
                }
            }
        }
    }
}

impl Lattice {
    /// Lowest and highest raster index of the sub-grid.
    fn span(&self) -> (isize, isize) {
        let e = self.m.saturating_sub(1) as isize;
        let b = self.base + self.o as isize * (self.si + self.sj);
        let c = [
            b,
            b + e * self.si,
            b + e * self.sj,
            b + e * (self.si + self.sj),
        ];
        (
            c.iter().copied().min().unwrap_or(b),
            c.iter().copied().max().unwrap_or(b),
        )
    }

    /// Writes the sub-grid of `buf` to the raster, as far as it falls in `part` (raster
    /// indices `start..start + part.len()`).
    fn write_part(&self, buf: &[i32], part: &mut [i32], start: usize) {
        let (lo, hi) = self.span();
        let (start, end) = (start as isize, (start + part.len()) as isize);
        if hi < start || lo >= end {
            return;
        }
        if lo >= start && hi < end {
            self.lines(|r, rs, b, bs, len| write_line(part, r - start, rs, buf, b, bs, len));
        } else {
            self.lines(|r, rs, b, bs, len| {
                let (t0, t1) = clip_line(r, rs, len, start, end);
                if t0 < t1 {
                    let r = r + t0 as isize * rs - start;
                    write_line(part, r, rs, buf, b + t0 * bs, bs, t1 - t0);
                }
            });
        }
    }
}

/// Reads the `side x side` lattice whose point `(i, j)` is `raster[base + i si + j sj]`
/// into `out` (row-major), walking the shortest raster step ([`Lattice`]).
pub(crate) fn read_lattice(
    raster: &[i32],
    side: usize,
    base: isize,
    si: isize,
    sj: isize,
    out: &mut [i32],
) {
    Lattice::new(side, 0, side, base, si, sj)
        .lines(|r, rs, b, bs, len| read_line(raster, r, rs, out, b, bs, len));
}

/// Writes rows and columns `margin..side - margin` of the `side x side` grid `v` back to
/// the lattice of [`read_lattice`], as far as it falls in `part`, the raster entries from
/// index `start` (the whole raster: `start` 0).
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_lattice(
    part: &mut [i32],
    start: usize,
    side: usize,
    margin: usize,
    base: isize,
    si: isize,
    sj: isize,
    v: &[i32],
) {
    Lattice::new(side - 2 * margin, margin, side, base, si, sj).write_part(v, part, start);
}

/// The range `t0..t1` of `t < len` with `start <= base + t step < end`.
fn clip_line(base: isize, step: isize, len: usize, start: isize, end: isize) -> (usize, usize) {
    let len = len as isize;
    let (lo, hi) = match step.signum() {
        0 if (start..end).contains(&base) => (0, len),
        0 => (0, 0),
        // ceil((start - base) / step) ..= floor((end - 1 - base) / step)
        1 => (
            -(base - start).div_euclid(step),
            (end - 1 - base).div_euclid(step) + 1,
        ),
        _ => (
            -(end - 1 - base).div_euclid(-step),
            (base - start).div_euclid(-step) + 1,
        ),
    };
    let (lo, hi) = (lo.clamp(0, len), hi.clamp(0, len));
    (lo as usize, hi.max(lo) as usize)
}

/// `buf[b0 + t bstep] = raster[base + t step]` for `t < len`: the raster bounds are
/// checked once per line (plain index loops: `step_by` divides to find its length, which
/// costs more than the copy on the short diagonal lines).
fn read_line(
    raster: &[i32],
    base: isize,
    step: isize,
    buf: &mut [i32],
    b0: usize,
    bstep: usize,
    len: usize,
) {
    if len == 0 {
        return;
    }
    let (lo, hi) = strided_span(base, step, len);
    let span = &raster[lo..=hi];
    let out = &mut buf[b0..=b0 + (len - 1) * bstep];
    let mut r = base - lo as isize;
    for t in 0..len {
        out[t * bstep] = span[r as usize];
        r += step;
    }
}

/// `raster[base + t step] = buf[b0 + t bstep]` for `t < len`.
fn write_line(
    raster: &mut [i32],
    base: isize,
    step: isize,
    buf: &[i32],
    b0: usize,
    bstep: usize,
    len: usize,
) {
    if len == 0 {
        return;
    }
    let (lo, hi) = strided_span(base, step, len);
    let span = &mut raster[lo..=hi];
    let src = &buf[b0..=b0 + (len - 1) * bstep];
    let mut r = base - lo as isize;
    for t in 0..len {
        span[r as usize] = src[t * bstep];
        r += step;
    }
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
        self.n
    }

    fn slot_levels(&self) -> &[Vec<DiamondSlot>] {
        &self.levels
    }

    fn raster_len(&self) -> usize {
        self.width * self.height
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
                let (lo, hi) = Lattice::new(self.n + 1, 0, self.n + 1, v0, si, sj).span();
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
        let side = (self.n + 1) * (self.n + 1);
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
        self.width * self.height
    }

    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool {
        crate::fill::fill_into(self.width, self.height, values, valid, out, to_int)
    }

    fn coverage(&self) -> Option<&Coverage> {
        self.coverage.as_ref()
    }

    fn point_validity(&self) -> Option<Vec<bool>> {
        self.coverage.as_ref()?;
        Some(
            (0..self.width * self.height)
                .into_par_iter()
                .map(|k| self.is_valid(k % self.width, k / self.width))
                .collect(),
        )
    }
}

/// Checks that `coverage` is a block grid of a `width x height` raster.
fn check_coverage(width: usize, height: usize, coverage: &Coverage) -> Result<(), RasterError> {
    let b = coverage.block_side();
    if coverage.faces() != 1
        || coverage.cols() != (width - 1) / b + 1
        || coverage.rows() != (height - 1) / b + 1
    {
        return Err(RasterError::Coverage("block grid of another raster size"));
    }
    Ok(())
}

/// Makes the points of slot `s` outside the covered blocks of `coverage` invalid.
fn apply_coverage(
    s: &mut DiamondSlot,
    n: usize,
    width: usize,
    height: usize,
    coverage: &Coverage,
    empty: &DiamondMask,
) {
    let (w, h) = (width as i64, height as i64);
    let inside = |(x, y): (i64, i64)| x >= 0 && y >= 0 && x < w && y < h;
    let covered =
        |(x, y): (i64, i64)| inside((x, y)) && coverage.covers_point(0, x as usize, y as usize);
    let corners = [(0, 0), (n, 0), (n, n), (0, n)].map(|(i, j)| s.vertex_xy(i, j));
    let range = |k: usize, hi: i64| {
        let lo = corners.iter().map(|c| [c.0, c.1][k]).min().unwrap_or(0);
        let up = corners.iter().map(|c| [c.0, c.1][k]).max().unwrap_or(0);
        [lo.max(0) as usize, up.min(hi - 1).max(0) as usize]
    };
    match coverage.state(0, range(0, w), range(1, h)) {
        BlockState::Full => {}
        BlockState::Empty => s.mask = Some(empty.clone()),
        BlockState::Mixed => {
            s.mask = Some(DiamondMask::from_fn(
                n,
                |i, j| covered(s.vertex_xy(i, j)),
                |i, j| covered(s.cell_xy(i, j)),
            ));
        }
    }
}

/// Where a raster sits in the hierarchy, without the per-diamond tables of
/// [`RasterGeometry`]: what is needed of one diamond is derived from its id, so a client
/// holds memory for the diamonds it looks at, not for the repository's.
#[derive(Clone, Debug)]
pub struct RasterFrame {
    width: usize,
    height: usize,
    n: usize,
    domain: PlanarDomain,
    detail_levels: usize,
    coverage: Option<Coverage>,
}

impl RasterFrame {
    /// The frame of a `width x height` raster coded with `N x N` diamonds (the hierarchy
    /// of [`RasterGeometry::new`]) and, for sparse repositories, its coverage.
    pub fn new(
        width: usize,
        height: usize,
        n: usize,
        coverage: Option<&Coverage>,
    ) -> Result<Self, RasterError> {
        check_size(n)?;
        if width == 0 || height == 0 || width > 1 << 24 || height > 1 << 24 {
            return Err(RasterError::BadDimensions(width, height));
        }
        let extent = (width.max(height) - 1).max(1) as u64;
        let mut k = 0u32;
        while ((n as u64) << k) < extent {
            k += 1;
        }
        let m = n.trailing_zeros() + k;
        let domain = PlanarDomain::new(m.max(1))?;
        if let Some(c) = coverage {
            check_coverage(width, height, c)?;
        }
        Ok(RasterFrame {
            width,
            height,
            n,
            domain,
            detail_levels: 2 * k as usize,
            coverage: coverage.cloned(),
        })
    }

    /// Raster width.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Raster height.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Diamond size `N`.
    pub fn n(&self) -> usize {
        self.n
    }

    /// The planar domain (id units = raster samples).
    pub fn domain(&self) -> PlanarDomain {
        self.domain
    }

    /// Number of levels that carry details.
    pub fn detail_levels(&self) -> usize {
        self.detail_levels
    }

    /// The coverage (sparse repositories).
    pub fn coverage(&self) -> Option<&Coverage> {
        self.coverage.as_ref()
    }

    /// The detail level of `id` if it is a diamond of a detail level.
    fn detail_level(&self, id: PlanarId) -> Option<usize> {
        let level = self.domain.level(id).ok()? as usize;
        (level < self.detail_levels).then_some(level)
    }

    /// Whether diamond `id` carries details: of a detail level, with a point in the
    /// raster (the diamonds of [`RasterGeometry::level`]). Builds no mask.
    pub fn is_coded(&self, id: PlanarId) -> bool {
        self.detail_level(id).is_some() && self.meets(id)
    }

    /// Whether a vertex or cell of diamond `id` lies in the raster.
    fn meets(&self, id: PlanarId) -> bool {
        let Some(s) = bare_slot(&self.domain, id, self.n) else {
            return false;
        };
        let (w, h) = (self.width as i64, self.height as i64);
        let inside = |(x, y): (i64, i64)| x >= 0 && y >= 0 && x < w && y < h;
        let n = self.n;
        // Every point lies in the box of the corners: a box outside the raster has none.
        let corners = [(0, 0), (n, 0), (n, n), (0, n)].map(|(i, j)| s.vertex_xy(i, j));
        let lo = |k: usize| corners.iter().map(|c| [c.0, c.1][k]).min().unwrap_or(0);
        let hi = |k: usize| corners.iter().map(|c| [c.0, c.1][k]).max().unwrap_or(-1);
        if lo(0) >= w || hi(0) < 0 || lo(1) >= h || hi(1) < 0 {
            return false;
        }
        corners.iter().any(|&c| inside(c))
            || (0..=n).any(|i| (0..=n).any(|j| inside(s.vertex_xy(i, j))))
            || (0..n).any(|i| (0..n).any(|j| inside(s.cell_xy(i, j))))
    }

    /// The slot of a diamond that carries details (its level, storage key and mask, the
    /// raster's edges and coverage applied; no child indices), `None` for others.
    pub fn slot(&self, id: PlanarId) -> Option<(usize, DiamondSlot)> {
        let level = self.detail_level(id)?;
        let mut s = slot(&self.domain, id, self.n, self.width, self.height)?;
        if let Some(c) = &self.coverage {
            apply_coverage(
                &mut s,
                self.n,
                self.width,
                self.height,
                c,
                &DiamondMask::none(self.n),
            );
        }
        Some((level, s))
    }

    /// The blob context of a coded diamond's slot at `level` with `owned` owned children.
    pub fn slot_context<'a>(
        &self,
        level: usize,
        s: &'a DiamondSlot,
        owned: usize,
    ) -> BlobContext<'a> {
        BlobContext::of_level(
            &s.key,
            self.n,
            self.detail_levels,
            level,
            s.mask.as_ref(),
            owned,
        )
    }
}

/// A diamond's frame as a slot (no key, mask or placement), `None` outside the domain.
fn bare_slot(domain: &PlanarDomain, id: PlanarId, n: usize) -> Option<DiamondSlot> {
    let c = domain.corners(id).ok()?;
    let ni = n as i64;
    let a = [(c[1][0] - c[0][0]) / ni, (c[1][1] - c[0][1]) / ni];
    let b = [(c[3][0] - c[0][0]) / ni, (c[3][1] - c[0][1]) / ni];
    Some(DiamondSlot {
        id,
        x0: c[0][0],
        y0: c[0][1],
        a,
        b,
        mask: None,
        key: Vec::new(),
        children: Vec::new(),
        owned: Vec::new(),
        lin: None,
    })
}

/// The raster placement of a diamond, `None` if none of its points is in the raster.
fn slot(
    domain: &PlanarDomain,
    id: PlanarId,
    n: usize,
    width: usize,
    height: usize,
) -> Option<DiamondSlot> {
    let mut s = bare_slot(domain, id, n)?;
    s.key = domain.key(id).ok()?;
    let inside =
        |(x, y): (i64, i64)| x >= 0 && y >= 0 && (x as usize) < width && (y as usize) < height;
    let all_corners = [(0, 0), (n, 0), (n, n), (0, n)]
        .iter()
        .all(|&(i, j)| inside(s.vertex_xy(i, j)));
    if !all_corners {
        let mask = DiamondMask::from_fn(
            n,
            |i, j| inside(s.vertex_xy(i, j)),
            |i, j| inside(s.cell_xy(i, j)),
        );
        if mask.valid_cells() == 0 && (0..=n).all(|i| (0..=n).all(|j| !mask.vertex(i, j))) {
            return None;
        }
        s.mask = Some(mask);
    } else {
        let w = width as isize;
        let at = |(x, y): (i64, i64)| y as isize * w + x as isize;
        let v0 = at(s.vertex_xy(0, 0));
        let c0 = at(s.cell_xy(0, 0));
        let si = at(s.vertex_xy(1, 0)) - v0;
        let sj = at(s.vertex_xy(0, 1)) - v0;
        s.lin = Some([v0, c0, si, sj]);
    }
    Some(s)
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
