//! The planet transform: a *cube raster* (six square face arrays) placed in the sphere
//! hierarchy ([`crate::diamond::sphere`]).
//!
//! # Storage
//! A planet of `face_side = 2S` samples per face side is a `Vec<i32>` of
//! `6 (2S+1)^2` values: face `f`'s sample `(u, v)` (that face's chart coordinates, see the
//! table in [`crate::diamond::sphere`]) at index `(f (2S+1) + v) (2S+1) + u`. Points on cube
//! edges (corners) exist in 2 (3) face arrays. The *canonical* copy is the one on the lowest
//! face index; every read of the transform takes the canonical copy and every write goes
//! to all copies, so each face array stays complete and consistent on its own.
//!
//! # Units and levels
//! Id units are samples: the domain is the cube `[-S, S]^3` (`m = log2 S`), and the sample
//! `(f, u, v)` is the cube point [`SphereFrame::sample_position`]. Positions returned by
//! [`SphereDomain::vertex_position`] are in id units x `2N`. `face_side = N 2^k`, so the
//! face roots (level 0) have a vertex spacing of `2^k` samples and the `2k` detail levels
//! `0 ..= 2k - 1` end with rotated diamonds of half-diagonal `N` whose cells land exactly
//! on the samples (the same choice as the planar [`crate::raster`]). With `k = 0` the six
//! root grids hold every sample and there are no details. Every diamond of every level is
//! present. Without a coverage the sphere has no invalid points, so no masks; with one
//! ([`SphereGeometry::with_coverage`], sparse mode) the points outside covered blocks are
//! invalid and the diamonds that meet uncovered blocks get masks.
//!
//! [`SphereFrame`] places one diamond at a time; [`SphereGeometry`] holds every diamond's
//! tables, for the whole-planet transform ([`crate::layout`]).

use crate::blob::BlobContext;
use crate::coverage::{BlockState, Coverage};
use crate::diamond::sphere::{axes, chart_of};
use crate::diamond::{SphereDomain, SphereId, check_size};
use crate::lattice::{read_lattice, write_lattice};
use crate::layout::{Layout, check_len, synthesize_levels};
use crate::lifting::DiamondMask;
use crate::raster::RasterError;

/// An affine index map: vertex `(i, j)` at `v0 + i si + j sj`, cell `(i, j)` at
/// `c0 + i si + j sj` (indices into the cube raster).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Placement {
    v0: isize,
    c0: isize,
    si: isize,
    sj: isize,
}

impl Placement {
    #[inline]
    fn at(&self, base: isize, i: usize, j: usize) -> usize {
        (base + i as isize * self.si + j as isize * self.sj) as usize
    }

    #[inline]
    fn base(&self, cell: bool) -> isize {
        if cell { self.c0 } else { self.v0 }
    }

    /// Lowest and highest index of a `side x side` grid from `base`.
    fn span(&self, base: isize, side: usize) -> (isize, isize) {
        let e = side.saturating_sub(1) as isize;
        let c = [
            base,
            base + e * self.si,
            base + e * self.sj,
            base + e * (self.si + self.sj),
        ];
        (
            c.iter().copied().min().unwrap_or(base),
            c.iter().copied().max().unwrap_or(base),
        )
    }
}

/// Where one diamond's samples live in the cube raster.
#[derive(Clone, Debug)]
pub struct SphereSlot {
    /// The diamond.
    pub id: SphereId,
    /// Storage key of the diamond ([`SphereDomain::key`]).
    pub key: Vec<u8>,
    /// Indices (in the next detail level) of its children.
    pub children: Kids,
    /// The subset of `children` whose side information this diamond's blob carries
    /// (children whose first parent is this diamond), in side order.
    pub owned: Kids,
    /// Points with `i >= j` (all points of a diamond inside one face): `P1`'s face.
    lower: Placement,
    /// Edge diamonds: points with `i <= j`, on `P2`'s face (boxed: few diamonds straddle
    /// an edge, and a planet's geometry holds one slot per diamond).
    upper: Option<Box<Placement>>,
    /// Whether the canonical copy of a diagonal point is the `upper` one.
    diag_upper: bool,
    /// Valid points; `None` when every vertex and cell is valid (always without a
    /// coverage).
    pub mask: Option<DiamondMask>,
}

/// Up to four diamond indices (a diamond has at most four children), held inline: a
/// planet's geometry holds two of these per diamond, where two `Vec`s took 144 bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Kids {
    ids: [usize; 4],
    len: u8,
}

impl Kids {
    /// Appends `k`; ignored past four (a diamond never has more children).
    pub fn push(&mut self, k: usize) {
        if let Some(slot) = self.ids.get_mut(self.len as usize) {
            *slot = k;
            self.len += 1;
        }
    }
}

impl<'a> IntoIterator for &'a Kids {
    type Item = &'a usize;
    type IntoIter = std::slice::Iter<'a, usize>;

    fn into_iter(self) -> Self::IntoIter {
        self.iter()
    }
}

impl std::ops::Deref for Kids {
    type Target = [usize];

    fn deref(&self) -> &[usize] {
        &self.ids[..self.len as usize]
    }
}

impl SphereSlot {
    fn pick(&self, i: usize, j: usize) -> &Placement {
        match &self.upper {
            Some(up) if j > i || (j == i && self.diag_upper) => up,
            _ => &self.lower,
        }
    }

    /// The lowest and highest cube-raster index of any copy of the slot's vertices and
    /// cells (diamond size `n`).
    pub fn index_span(&self, n: usize) -> (usize, usize) {
        let (mut lo, mut hi) = (isize::MAX, isize::MIN);
        for p in std::iter::once(&self.lower).chain(self.upper.as_deref()) {
            for (base, side) in [(p.v0, n + 1), (p.c0, n)] {
                let (l, h) = p.span(base, side);
                (lo, hi) = (lo.min(l), hi.max(h));
            }
        }
        (lo.max(0) as usize, hi.max(0) as usize)
    }

    /// Cube-raster index of the canonical copy of vertex `(i, j)`, `0 <= i, j <= N`.
    pub fn vertex_index(&self, i: usize, j: usize) -> usize {
        let p = self.pick(i, j);
        p.at(p.v0, i, j)
    }

    /// Cube-raster index of the canonical copy of cell `(i, j)`, `0 <= i, j < N`.
    pub fn cell_index(&self, i: usize, j: usize) -> usize {
        let p = self.pick(i, j);
        p.at(p.c0, i, j)
    }

    /// Whether the diamond straddles a cube edge (one triangle on each of two faces).
    pub fn is_edge(&self) -> bool {
        self.upper.is_some()
    }

    /// Cube-raster indices of the copies of interior vertex `(i, j)` that analysis
    /// writes: one, or two for an edge diamond's diagonal points (as the encoder's `Layout`'s
    /// `scatter_interior_part`).
    pub fn vertex_copies(&self, i: usize, j: usize) -> (usize, Option<usize>) {
        self.copies(false, i, j)
    }

    /// Cube-raster indices of the copies of cell `(i, j)` that synthesis writes (as
    /// the encoder's `Layout`'s `scatter_cells_part`).
    pub fn cell_copies(&self, i: usize, j: usize) -> (usize, Option<usize>) {
        self.copies(true, i, j)
    }

    fn copies(&self, cell: bool, i: usize, j: usize) -> (usize, Option<usize>) {
        let lo = self.lower.at(self.lower.base(cell), i, j);
        match &self.upper {
            None => (lo, None),
            Some(up) => {
                let u = up.at(up.base(cell), i, j);
                match j.cmp(&i) {
                    std::cmp::Ordering::Less => (lo, None),
                    std::cmp::Ordering::Greater => (u, None),
                    std::cmp::Ordering::Equal => (lo, Some(u)),
                }
            }
        }
    }

    /// The cube-raster indices of the corners of the flat pieces the `N`-diamond's points
    /// lie in: its square on one face, or an edge diamond's triangle on each of two faces.
    /// Every vertex and cell lies in the bounding box (in its face's chart) of one piece.
    pub fn piece_corners(&self, n: usize) -> Vec<Vec<usize>> {
        let at = |p: &Placement, i: usize, j: usize| p.at(p.v0, i, j);
        match &self.upper {
            None => vec![
                (0..4)
                    .map(|k| at(&self.lower, (k & 1) * n, (k >> 1) * n))
                    .collect(),
            ],
            Some(up) => vec![
                vec![
                    at(&self.lower, 0, 0),
                    at(&self.lower, n, 0),
                    at(&self.lower, n, n),
                ],
                vec![at(up, 0, 0), at(up, 0, n), at(up, n, n)],
            ],
        }
    }

    /// Reads a `side x side` grid (vertices: `N + 1`, cells: `N`), canonical copies.
    pub fn gather(&self, side: usize, cell: bool, raster: &[i32], out: &mut [i32]) {
        let lo = &self.lower;
        let Some(up) = &self.upper else {
            read_lattice(raster, side, lo.base(cell), lo.si, lo.sj, out);
            return;
        };
        let diag = if self.diag_upper { up } else { lo };
        let (bl, bu, bd) = (lo.base(cell), up.base(cell), diag.base(cell));
        for (i, row) in out.chunks_exact_mut(side).enumerate() {
            let (left, rest) = row.split_at_mut(i);
            for (j, x) in left.iter_mut().enumerate() {
                *x = raster[lo.at(bl, i, j)];
            }
            if let Some((d, right)) = rest.split_first_mut() {
                *d = raster[diag.at(bd, i, i)];
                for (j, x) in right.iter_mut().enumerate() {
                    *x = raster[up.at(bu, i, i + 1 + j)];
                }
            }
        }
    }

    /// Writes points `margin..side - margin` of a `side x side` grid to every copy. Only
    /// diagonal points of edge diamonds have two copies among those ever written (interior
    /// vertices and cells); other edge points are boundary vertices, never written here.
    /// Only raster indices inside `part` (`raster[start..start + part.len()]`) are written.
    pub fn scatter(
        &self,
        side: usize,
        margin: usize,
        cell: bool,
        values: &[i32],
        part: &mut [i32],
        start: usize,
    ) {
        let end = start + part.len();
        let misses = |p: &Placement| {
            let (lo, hi) = p.span(p.base(cell), side);
            hi < start as isize || lo >= end as isize
        };
        if misses(&self.lower) && self.upper.as_deref().is_none_or(misses) {
            return;
        }
        let lo = &self.lower;
        let bl = lo.base(cell);
        let Some(up) = &self.upper else {
            write_lattice(part, start, side, margin, bl, lo.si, lo.sj, values);
            return;
        };
        let mut put = |k: usize, x: i32| {
            if let Some(e) = k.checked_sub(start).and_then(|k| part.get_mut(k)) {
                *e = x;
            }
        };
        let bu = up.base(cell);
        for i in margin..side - margin {
            for j in margin..side - margin {
                let x = values[i * side + j];
                if j <= i {
                    put(lo.at(bl, i, j), x);
                }
                if j >= i {
                    put(up.at(bu, i, j), x);
                }
            }
        }
    }
}

/// Where a planet sits in the sphere hierarchy, without the per-diamond tables of
/// `quincunx_codec::sphere_raster::SphereGeometry`: what is needed of one diamond (its placement in the cube raster,
/// key and mask) is derived from its id, so a client holds memory for the diamonds it
/// looks at, not for the planet's.
#[derive(Clone, Debug)]
pub struct SphereFrame {
    face_side: usize,
    n: usize,
    domain: SphereDomain,
    detail_levels: usize,
    coverage: Option<Coverage>,
}

impl SphereFrame {
    /// The frame of a planet of `face_side` samples per face side (`N 2^k`, `k >= 0`)
    /// coded with `N x N` diamonds and, for sparse planets, its coverage.
    pub fn new(
        face_side: usize,
        n: usize,
        coverage: Option<&Coverage>,
    ) -> Result<Self, RasterError> {
        check_size(n)?;
        if face_side == 0 || face_side > 1 << 24 {
            return Err(RasterError::BadDimensions(face_side, face_side));
        }
        if !face_side.is_multiple_of(n) || !(face_side / n).is_power_of_two() {
            return Err(RasterError::FaceSide { face_side, n });
        }
        let k = (face_side / n).trailing_zeros();
        // S = face_side / 2 = 2^m.
        let m = face_side.trailing_zeros() - 1;
        if m == 0 {
            return Err(RasterError::FaceSide { face_side, n });
        }
        if let Some(c) = coverage {
            check_coverage(face_side, c)?;
        }
        Ok(SphereFrame {
            face_side,
            n,
            domain: SphereDomain::new(m)?,
            detail_levels: 2 * k as usize,
            coverage: coverage.cloned(),
        })
    }

    /// Number of levels that carry details.
    pub fn detail_levels(&self) -> usize {
        self.detail_levels
    }

    /// The detail level of `id` if it is a diamond of a detail level (on a planet every
    /// diamond of those levels carries details).
    pub fn coded_level(&self, id: SphereId) -> Option<usize> {
        let level = self.domain.level(id).ok()? as usize;
        (level < self.detail_levels).then_some(level)
    }

    /// Whether `id` has a slot ([`SphereFrame::coded_slot`] is `Some`), without working
    /// out its mask.
    pub fn has_slot(&self, id: SphereId) -> bool {
        self.coded_level(id).is_some() && self.slot(id).is_ok()
    }

    /// The slot of a diamond that carries details (its level, placement, key and, with a
    /// coverage, mask; no child indices), `None` for others.
    pub fn coded_slot(&self, id: SphereId) -> Option<(usize, SphereSlot)> {
        let level = self.coded_level(id)?;
        let mut s = self.slot(id).ok()?;
        if let Some(c) = &self.coverage {
            s.mask = self.coverage_mask(c, &s, &DiamondMask::none(self.n));
        }
        Some((level, s))
    }

    /// The blob context of a coded diamond's slot at `level` with `owned` owned children.
    pub fn slot_context<'a>(
        &self,
        level: usize,
        s: &'a SphereSlot,
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

    /// The mask a coverage gives a diamond (`None`: all valid).
    pub fn coverage_mask(
        &self,
        coverage: &Coverage,
        s: &SphereSlot,
        empty: &DiamondMask,
    ) -> Option<DiamondMask> {
        let n = self.n;
        let two_n = 2 * n as i64;
        let corners: Vec<[i64; 3]> = [(0, 0), (n, 0), (n, n), (0, n)]
            .iter()
            .filter_map(|&(i, j)| self.domain.vertex_position(s.id, n, i, j).ok())
            .map(|p| p.map(|x| x / two_n))
            .collect();
        // Every point of the diamond lies in the box of its corners (each half is a flat
        // triangle of three of them); the blocks met on every face the box touches decide.
        let half = self.half();
        let lo: [i64; 3] = std::array::from_fn(|k| corners.iter().map(|p| p[k]).min().unwrap_or(0));
        let hi: [i64; 3] = std::array::from_fn(|k| corners.iter().map(|p| p[k]).max().unwrap_or(0));
        let clamp = |x: i64| (x + half).clamp(0, 2 * half) as usize;
        let mut state: Option<BlockState> = None;
        for f in 0..6u8 {
            let ax = axes(f);
            if !(lo[ax.a]..=hi[ax.a]).contains(&(ax.s * half)) {
                continue;
            }
            let here = coverage.state(
                f as usize,
                [clamp(lo[ax.b]), clamp(hi[ax.b])],
                [clamp(lo[ax.c]), clamp(hi[ax.c])],
            );
            state = Some(match (state, here) {
                (None, x) => x,
                (Some(a), b) if a == b => a,
                _ => BlockState::Mixed,
            });
        }
        match state.unwrap_or(BlockState::Mixed) {
            BlockState::Full => None,
            BlockState::Empty => Some(empty.clone()),
            BlockState::Mixed => Some(DiamondMask::from_fn(
                n,
                |i, j| self.is_valid_index(coverage, s.vertex_index(i, j)),
                |i, j| self.is_valid_index(coverage, s.cell_index(i, j)),
            )),
        }
    }

    /// Whether cube-raster entry `index` is a valid point under `coverage`.
    pub fn is_valid_index(&self, coverage: &Coverage, index: usize) -> bool {
        let w = self.width();
        let (face, rest) = (index / (w * w), index % (w * w));
        let (u, v) = (rest % w, rest / w);
        if (1..w - 1).contains(&u) && (1..w - 1).contains(&v) {
            return coverage.covers_point(face, u, v);
        }
        let p = self.sample_position(face as u8, u, v);
        let s = self.half();
        (0..6u8).any(|f| {
            let ax = axes(f);
            p[ax.a] == ax.s * s && {
                let [u, v] = chart_of(f, p, s);
                coverage.covers_point(f as usize, u as usize, v as usize)
            }
        })
    }

    /// The coverage the geometry was built with (`quincunx_codec::sphere_raster::SphereGeometry::with_coverage`).
    pub fn coverage(&self) -> Option<&Coverage> {
        self.coverage.as_ref()
    }

    /// Sets the coverage (the encoder's geometry, once it has checked and applied it).
    pub fn set_coverage(&mut self, coverage: Option<Coverage>) {
        self.coverage = coverage;
    }

    /// Whether cube-raster entry `index` is a valid point (always, without a coverage).
    pub fn is_valid(&self, index: usize) -> bool {
        index < self.cube_len()
            && self
                .coverage
                .as_ref()
                .is_none_or(|c| self.is_valid_index(c, index))
    }

    /// Samples per face side (`2S`).
    pub fn face_side(&self) -> usize {
        self.face_side
    }

    /// Diamond size `N`.
    pub fn n(&self) -> usize {
        self.n
    }

    /// The sphere domain (id units = samples, `S = face_side / 2`).
    pub fn domain(&self) -> SphereDomain {
        self.domain
    }

    /// Length of the cube raster: `6 (2S+1)^2`.
    pub fn cube_len(&self) -> usize {
        6 * self.width() * self.width()
    }

    /// Number of distinct points of the cube surface: `6 (2S)^2 + 2`.
    pub fn distinct_points(&self) -> usize {
        6 * self.face_side * self.face_side + 2
    }

    /// Samples per face array side, `face_side + 1`.
    pub fn width(&self) -> usize {
        self.face_side + 1
    }

    /// Half the face side, `S`, in id units.
    pub fn half(&self) -> i64 {
        (self.face_side / 2) as i64
    }

    /// Index of face `face`'s sample `(u, v)`, `u, v <= face_side`.
    pub fn cube_index(&self, face: u8, u: usize, v: usize) -> usize {
        let w = self.width();
        (face as usize * w + v) * w + u
    }

    /// The cube point (id units, coordinates in `[-S, S]`) of face `face`'s sample `(u, v)`.
    pub fn sample_position(&self, face: u8, u: usize, v: usize) -> [i64; 3] {
        let ax = axes(face);
        let s = self.half();
        let mut p = [0; 3];
        p[ax.a] = ax.s * s;
        p[ax.b] = u as i64 - s;
        p[ax.c] = v as i64 - s;
        p
    }

    /// Cube-raster indices of every copy of the surface point `p` (id units), canonical
    /// (lowest face) first: one inside a face, two on an edge, three at a corner, none off
    /// the surface.
    pub fn point_indices(&self, p: [i64; 3]) -> impl Iterator<Item = usize> + '_ {
        let s = self.half();
        let inside = p.iter().all(|x| (-s..=s).contains(x));
        (0..6u8).filter_map(move |f| {
            let ax = axes(f);
            (inside && p[ax.a] == ax.s * s).then(|| {
                let [u, v] = chart_of(f, p, s);
                self.cube_index(f, u as usize, v as usize)
            })
        })
    }

    /// Whether cube-raster entry `index` is the canonical copy of its point.
    pub fn is_canonical(&self, index: usize) -> bool {
        let w = self.width();
        let (face, rest) = (index / (w * w), index % (w * w));
        let (u, v) = (rest % w, rest / w);
        if (1..w - 1).contains(&u) && (1..w - 1).contains(&v) {
            return true;
        }
        self.point_indices(self.sample_position(face as u8, u, v))
            .next()
            == Some(index)
    }

    /// The cube-raster placement of a diamond.
    pub fn slot(&self, id: SphereId) -> Result<SphereSlot, RasterError> {
        let d = &self.domain;
        let n = self.n;
        let two_n = 2 * n as i64;
        // Every vertex and cell of a diamond down to the finest detail level is a sample.
        let at = |i: usize, j: usize| -> Result<[i64; 3], RasterError> {
            Ok(d.vertex_position(id, n, i, j)?.map(|x| x / two_n))
        };
        let cell = d.cell_position(id, n, 0, 0)?.map(|x| x / two_n);
        let (v00, v10, v01) = (at(0, 0)?, at(1, 0)?, at(0, 1)?);
        let s = self.half();
        let w = self.width() as isize;
        let lin = |f: u8, p: [i64; 3]| -> isize {
            let [u, v] = chart_of(f, p, s);
            (f as isize * w + v as isize) * w + u as isize
        };
        // On face f: `i` steps from a to b, `j` from c to e. Folding across a cube edge is
        // an isometry of each half, so each half is affine in its own face's chart.
        let place = |f: u8, a: [i64; 3], b: [i64; 3], c: [i64; 3], e: [i64; 3]| Placement {
            v0: lin(f, v00),
            c0: lin(f, cell),
            si: lin(f, b) - lin(f, a),
            sj: lin(f, e) - lin(f, c),
        };
        let (face, other) = d.faces(id)?;
        let (lower, upper, diag_upper) = match other {
            None => (place(face, v00, v10, v00, v01), None, false),
            Some(g) => {
                let v11 = at(1, 1)?;
                let p1 = at(n, 0)?;
                let ax = axes(face);
                let lower_face = if p1[ax.a] == ax.s * s { face } else { g };
                let upper_face = if lower_face == face { g } else { face };
                (
                    place(lower_face, v00, v10, v10, v11),
                    Some(place(upper_face, v01, v11, v00, v01)),
                    upper_face == face,
                )
            }
        };
        Ok(SphereSlot {
            id,
            key: d.key(id)?,
            children: Kids::default(),
            owned: Kids::default(),
            lower,
            upper: upper.map(Box::new),
            diag_upper,
            mask: None,
        })
    }
}

/// Checks that `coverage` is a block grid of a planet of `face_side`.
pub fn check_coverage(face_side: usize, coverage: &Coverage) -> Result<(), RasterError> {
    let b = coverage.block_side();
    if coverage.faces() != 6
        || coverage.cols() != coverage.rows()
        || coverage.cols().checked_mul(b) != Some(face_side)
    {
        return Err(RasterError::Coverage("block grid of another planet size"));
    }
    Ok(())
}

/// The sphere hierarchy a cube raster is placed in: domain, diamond size, the six face
/// roots and, per detail level, every diamond.
#[derive(Clone, Debug)]
pub struct SphereGeometry {
    frame: SphereFrame,
    roots: Vec<SphereSlot>,
    levels: Vec<Vec<SphereSlot>>,
}

/// The geometry answers everything its frame does (placement of samples and of single
/// diamonds); its own methods are those that need the tables.
impl std::ops::Deref for SphereGeometry {
    type Target = SphereFrame;

    fn deref(&self) -> &SphereFrame {
        &self.frame
    }
}

impl SphereGeometry {
    /// Places a planet of `face_side` samples per face side (`N 2^k`, `k >= 0`) in the
    /// sphere hierarchy of `N x N` diamonds.
    pub fn new(face_side: usize, n: usize) -> Result<Self, RasterError> {
        let frame = SphereFrame::new(face_side, n, None)?;
        let (domain, detail_levels) = (frame.domain(), frame.detail_levels() as u32);
        let mut geom = SphereGeometry {
            frame,
            roots: Vec::new(),
            levels: Vec::new(),
        };
        geom.roots = domain
            .roots()
            .into_iter()
            .map(|id| geom.slot(id))
            .collect::<Result<_, _>>()?;
        let s2 = face_side as i64;
        for level in 0..detail_levels {
            let step = 1usize << domain.level_exponent(level);
            let ids: Vec<SphereId> = (0..6u8)
                .flat_map(|f| {
                    (0..=s2).step_by(step).flat_map(move |v| {
                        (0..=s2)
                            .step_by(step)
                            .filter_map(move |u| domain.from_face_chart(f, [u, v]).ok())
                            .filter(move |&id| {
                                domain.level(id).ok() == Some(level)
                                    && domain.faces(id).ok().map(|x| x.0) == Some(f)
                            })
                    })
                })
                .collect();
            let mut slots: Vec<SphereSlot> = ids
                .into_iter()
                .map(|id| geom.slot(id))
                .collect::<Result<_, _>>()?;
            slots.sort_by(|a, b| a.key.cmp(&b.key));
            geom.levels.push(slots);
        }
        for level in 0..geom.levels.len().saturating_sub(1) {
            let (coarse, fine) = geom.levels.split_at_mut(level + 1);
            let fine = &fine[0];
            let find = |id: SphereId| {
                let key = domain.key(id).ok()?;
                fine.binary_search_by(|s| s.key.as_slice().cmp(&key)).ok()
            };
            coarse[level].iter_mut().for_each(|s| {
                for child in domain.children(s.id).unwrap_or_default() {
                    if let Some(k) = find(child) {
                        s.children.push(k);
                        if domain.parents(child).ok().and_then(|p| p.first().copied()) == Some(s.id)
                        {
                            s.owned.push(k);
                        }
                    }
                }
            });
        }
        Ok(geom)
    }

    /// Like [`SphereGeometry::new`], with the points outside the covered blocks of
    /// `coverage` invalid (sparse mode, see [`crate::coverage`]): diamonds that meet
    /// uncovered blocks get masks. Both copies of a cube edge point agree: a point is
    /// valid when a covered block of any face holding a copy contains it.
    pub fn with_coverage(
        face_side: usize,
        n: usize,
        coverage: &Coverage,
    ) -> Result<Self, RasterError> {
        Self::new(face_side, n)?.covered(coverage)
    }

    /// This geometry with `coverage` applied (see [`SphereGeometry::with_coverage`]).
    pub fn covered(mut self, coverage: &Coverage) -> Result<Self, RasterError> {
        let g = &mut self;
        let n = g.frame.n();
        check_coverage(g.frame.face_side(), coverage)?;
        g.frame.set_coverage(Some(coverage.clone()));
        let mut levels = std::mem::take(&mut g.levels);
        let empty = DiamondMask::none(n);
        for level in &mut levels {
            level.iter_mut().for_each(|s| {
                s.mask = g.coverage_mask(coverage, s, &empty);
            });
        }
        g.levels = levels;
        Ok(self)
    }

    /// The diamonds of a detail level, sorted by key.
    pub fn level(&self, level: usize) -> &[SphereSlot] {
        &self.levels[level]
    }

    /// The six face roots' slots, in face order.
    pub fn root_slots(&self) -> &[SphereSlot] {
        &self.roots
    }

    /// `(level, index)` of a diamond with details, `None` for ids outside the detail
    /// levels (or not of this domain).
    pub fn locate(&self, id: SphereId) -> Option<(usize, usize)> {
        self.locate_key(&self.frame.domain().key(id).ok()?)
    }

    /// `(level, index)` of the diamond with storage key `key`, `None` if no diamond with
    /// details has that key.
    pub fn locate_key(&self, key: &[u8]) -> Option<(usize, usize)> {
        let level = *key.first()? as usize;
        let slots = self.levels.get(level)?;
        let index = slots.binary_search_by(|s| s.key.as_slice().cmp(key)).ok()?;
        Some((level, index))
    }

    /// What the blob decoder must know about diamond `index` of detail level `level`.
    pub fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_> {
        let s = &self.levels[level][index];
        self.frame.slot_context(level, s, s.owned.len())
    }

    /// Copies the canonical copy of every cube edge and corner point to its other copies;
    /// `values` must be a whole cube raster.
    pub fn make_consistent<T: Copy>(&self, values: &mut [T]) -> Result<(), RasterError> {
        if values.len() != self.cube_len() {
            return Err(RasterError::WrongLength {
                expected: self.cube_len(),
                got: values.len(),
            });
        }
        let w = self.frame.width();
        for face in 0..6u8 {
            for v in 0..w {
                let step = if v == 0 || v == w - 1 { 1 } else { w - 1 };
                for u in (0..w).step_by(step) {
                    let here = self.cube_index(face, u, v);
                    let pos = self.sample_position(face, u, v);
                    if let Some(first) = self.point_indices(pos).next()
                        && first != here
                    {
                        values[here] = values[first];
                    }
                }
            }
        }
        Ok(())
    }

    /// Reads the six root vertex grids (`(N+1)^2` each, canonical copies), in face order.
    pub fn gather_roots(&self, raster: &[i32]) -> Vec<Vec<i32>> {
        self.gather_roots_with(|k| raster[k])
    }

    /// [`SphereGeometry::gather_roots`] from any store of the cube raster: `read(index)`
    /// is the value of cube-raster entry `index`.
    pub fn gather_roots_with(&self, read: impl Fn(usize) -> i32) -> Vec<Vec<i32>> {
        let side = self.frame.n() + 1;
        self.roots
            .iter()
            .map(|s| {
                (0..side * side)
                    .map(|k| {
                        let (i, j) = (k / side, k % side);
                        let here = s.vertex_index(i, j);
                        // Border vertices lie on cube edges: read their canonical copies.
                        if i == 0 || j == 0 || i == self.frame.n() || j == self.frame.n() {
                            read(self.canonical_of(here).unwrap_or(here))
                        } else {
                            read(here)
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn canonical_of(&self, index: usize) -> Option<usize> {
        let w = self.frame.width();
        let (face, rest) = (index / (w * w), index % (w * w));
        self.point_indices(self.sample_position(face as u8, rest % w, rest / w))
            .next()
    }

    /// Writes the six root vertex grids into the cube raster, every copy of each point (a
    /// point on a cube edge takes the value of its canonical face's root).
    pub fn scatter_roots(&self, roots: &[Vec<i32>], raster: &mut [i32]) -> Result<(), RasterError> {
        check_len(self, raster)?;
        self.scatter_roots_with(roots, |k, x| raster[k] = x)
    }

    /// [`SphereGeometry::scatter_roots`] through `put(cube_index, value)`.
    pub fn scatter_roots_with(
        &self,
        roots: &[Vec<i32>],
        mut put: impl FnMut(usize, i32),
    ) -> Result<(), RasterError> {
        let side = self.frame.n() + 1;
        if roots.len() != 6 || roots.iter().any(|r| r.len() != side * side) {
            return Err(RasterError::WrongLength {
                expected: 6 * side * side,
                got: roots.iter().map(Vec::len).sum(),
            });
        }
        for (s, grid) in self.roots.iter().zip(roots) {
            for i in 1..self.frame.n() {
                for j in 1..self.frame.n() {
                    let (k, other) = s.vertex_copies(i, j);
                    put(k, grid[i * side + j]);
                    if let Some(k) = other {
                        put(k, grid[i * side + j]);
                    }
                }
            }
            for i in 0..side {
                for j in 0..side {
                    if i != 0 && j != 0 && i != self.frame.n() && j != self.frame.n() {
                        continue;
                    }
                    let here = s.vertex_index(i, j);
                    let w = self.frame.width();
                    let (face, rest) = (here / (w * w), here % (w * w));
                    let pos = self.sample_position(face as u8, rest % w, rest / w);
                    let mut copies = self.point_indices(pos);
                    if copies.next() == Some(here) {
                        put(here, grid[i * side + j]);
                        for k in copies {
                            put(k, grid[i * side + j]);
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Inverse transform in place: the cube raster holds the root-level values on entry
    /// (see [`SphereGeometry::scatter_roots`]) and the full-resolution values on exit.
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

impl Layout for SphereGeometry {
    type Slot = SphereSlot;

    fn n(&self) -> usize {
        self.frame.n()
    }

    fn slot_levels(&self) -> &[Vec<SphereSlot>] {
        &self.levels
    }

    fn raster_len(&self) -> usize {
        self.cube_len()
    }

    fn mask<'s>(&self, s: &'s SphereSlot) -> Option<&'s DiamondMask> {
        s.mask.as_ref()
    }

    fn children<'s>(&self, s: &'s SphereSlot) -> &'s [usize] {
        &s.children
    }

    fn owned<'s>(&self, s: &'s SphereSlot) -> &'s [usize] {
        &s.owned
    }

    fn gather_vertices(&self, s: &SphereSlot, raster: &[i32], v: &mut [i32]) {
        s.gather(self.frame.n() + 1, false, raster, v);
    }

    fn gather_cells(&self, s: &SphereSlot, raster: &[i32], c: &mut [i32]) {
        s.gather(self.frame.n(), true, raster, c);
    }

    fn index_span(&self, s: &SphereSlot) -> (usize, usize) {
        s.index_span(self.frame.n())
    }

    fn scatter_interior_part(&self, s: &SphereSlot, v: &[i32], part: &mut [i32], start: usize) {
        s.scatter(self.frame.n() + 1, 1, false, v, part, start);
    }

    fn scatter_cells_part(&self, s: &SphereSlot, c: &[i32], part: &mut [i32], start: usize) {
        s.scatter(self.frame.n(), 0, true, c, part, start);
    }

    fn blob_context(&self, level: usize, index: usize) -> BlobContext<'_> {
        SphereGeometry::blob_context(self, level, index)
    }

    fn gather_roots(&self, raster: &[i32]) -> Vec<Vec<i32>> {
        SphereGeometry::gather_roots(self, raster)
    }

    fn scatter_roots(&self, roots: &[Vec<i32>], raster: &mut [i32]) -> Result<(), RasterError> {
        SphereGeometry::scatter_roots(self, roots, raster)
    }

    fn coverage(&self) -> Option<&Coverage> {
        self.frame.coverage()
    }

    fn point_validity(&self) -> Option<Vec<bool>> {
        let c = self.frame.coverage()?;
        Some(
            (0..self.cube_len())
                .map(|k| self.is_valid_index(c, k))
                .collect(),
        )
    }
}
