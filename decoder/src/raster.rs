//! Where a planar raster sits in the diamond hierarchy, one diamond at a time: the
//! raster's frame and each diamond's slot (placement, key, mask), derived from its id.
//!
//! The raster (`width x height`, sample `(row, col)` at id point `(x, y) = (col, row)`)
//! sits in the planar domain `[0, S]^2` with `S = N 2^k` the smallest such square that
//! holds it; id units are raster samples, so the finest data lattice is the integer grid
//! and levels `0 ..= 2k - 1` carry details. Points outside the raster are *invalid*: they
//! are never read, never coded, and cost nothing. [`RasterGeometry`] holds the tables of
//! every diamond, for the whole-raster transform ([`crate::layout`]).

use crate::blob::BlobContext;
use crate::coverage::{BlockState, Coverage};
use crate::diamond::{PlanarDomain, PlanarId, check_size};
use crate::lattice::{Lattice, read_lattice, write_lattice};
use crate::layout::{Layout, synthesize_levels};
use crate::lifting::DiamondMask;

/// Why a raster cannot be placed in a hierarchy.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
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

impl From<RasterError> for crate::blob::DecodeError {
    fn from(e: RasterError) -> Self {
        crate::blob::DecodeError::Entropy(crate::entropy::EntropyError::BadModel(match e {
            RasterError::WrongLength { .. } => "raster length",
            _ => "geometry",
        }))
    }
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
    pub lin: Option<[isize; 4]>,
}

impl DiamondSlot {
    /// Raster position of vertex `(i, j)`.
    pub fn vertex_xy(&self, i: usize, j: usize) -> (i64, i64) {
        let (i, j) = (i as i64, j as i64);
        (
            self.x0 + i * self.a[0] + j * self.b[0],
            self.y0 + i * self.a[1] + j * self.b[1],
        )
    }

    /// Raster position of cell `(i, j)`'s centre.
    pub fn cell_xy(&self, i: usize, j: usize) -> (i64, i64) {
        let (x, y) = self.vertex_xy(i, j);
        (
            x + (self.a[0] + self.b[0]) / 2,
            y + (self.a[1] + self.b[1]) / 2,
        )
    }

    /// Raster position of vertex `(0, 0)` and the steps along `i` and `j`.
    pub fn frame(&self) -> ([i64; 2], [i64; 2], [i64; 2]) {
        ([self.x0, self.y0], self.a, self.b)
    }

    /// Number of valid cells (the number of coded details).
    pub fn valid_cells(&self, n: usize) -> usize {
        self.mask.as_ref().map_or(n * n, DiamondMask::valid_cells)
    }
}

/// Checks that `coverage` is a block grid of a `width x height` raster.
pub fn check_coverage(width: usize, height: usize, coverage: &Coverage) -> Result<(), RasterError> {
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
pub fn apply_coverage(
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
/// `quincunx_codec::raster::RasterGeometry`: what is needed of one diamond is derived from its id, so a client
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
    /// of `quincunx_codec::raster::RasterGeometry::new`) and, for sparse repositories, its coverage.
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

    /// Sets the coverage (the encoder's geometry, once it has checked and applied it).
    pub fn set_coverage(&mut self, coverage: Option<Coverage>) {
        self.coverage = coverage;
    }

    /// The detail level of `id` if it is a diamond of a detail level.
    fn detail_level(&self, id: PlanarId) -> Option<usize> {
        let level = self.domain.level(id).ok()? as usize;
        (level < self.detail_levels).then_some(level)
    }

    /// Whether diamond `id` carries details: of a detail level, with a point in the
    /// raster (the diamonds of `quincunx_codec::raster::RasterGeometry::level`). Builds no mask.
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
pub fn slot(
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
                    .into_iter()
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
            levels[level].iter_mut().for_each(|s| {
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
            level.iter_mut().for_each(|s| {
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
        synthesize_levels(self, raster, details)
    }
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

    fn coverage(&self) -> Option<&Coverage> {
        self.frame.coverage()
    }

    fn point_validity(&self) -> Option<Vec<bool>> {
        self.frame.coverage()?;
        Some(
            (0..self.frame.width() * self.frame.height())
                .map(|k| self.is_valid(k % self.frame.width(), k / self.frame.width()))
                .collect(),
        )
    }
}
