//! Where a planar raster sits in the diamond hierarchy, one diamond at a time: the
//! raster's frame and each diamond's slot (placement, key, mask), derived from its id.
//!
//! The raster (`width x height`, sample `(row, col)` at id point `(x, y) = (col, row)`)
//! sits in the planar domain `[0, S]^2` with `S = N 2^k` the smallest such square that
//! holds it; id units are raster samples, so the finest data lattice is the integer grid
//! and levels `0 ..= 2k - 1` carry details. Points outside the raster are *invalid*: they
//! are never read, never coded, and cost nothing. The whole-raster tables and transform
//! (`RasterGeometry`) are the encoder's, in `quincunx-codec`.

use crate::blob::BlobContext;
use crate::coverage::{BlockState, Coverage};
use crate::diamond::{PlanarDomain, PlanarId, check_size};
use crate::lifting::DiamondMask;

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
