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
//! [`crate::diamond::SphereDomain::vertex_position`] are in id units x `2N`. `face_side = N 2^k`, so the
//! face roots (level 0) have a vertex spacing of `2^k` samples and the `2k` detail levels
//! `0 ..= 2k - 1` end with rotated diamonds of half-diagonal `N` whose cells land exactly
//! on the samples (the same choice as the planar [`crate::raster`]). With `k = 0` the six
//! root grids hold every sample and there are no details. Every diamond of every level is
//! present. Without a coverage the sphere has no invalid points, so no masks; with one
//! ([`SphereGeometry::with_coverage`], sparse mode) the points outside covered blocks are
//! invalid and the diamonds that meet uncovered blocks get masks.
//!
//! # Roots
//! Six root grids, one per face root, in face order: [`SphereGeometry::gather_roots`] /
//! [`SphereGeometry::scatter_roots`].

use rayon::prelude::*;

use crate::blob::BlobContext;
use crate::coverage::Coverage;
use crate::diamond::SphereId;
use crate::lifting::DiamondMask;
use crate::raster::{
    Layout, RasterError, analyze_levels, check_len, synthesize_checked, synthesize_par_checked,
};
use quincunx_decoder::sphere_raster::check_coverage;
#[doc(inline)]
pub use quincunx_decoder::sphere_raster::{Kids, SphereFrame, SphereSlot};

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
                .into_par_iter()
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
            coarse[level].par_iter_mut().for_each(|s| {
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
    pub(crate) fn covered(mut self, coverage: &Coverage) -> Result<Self, RasterError> {
        let g = &mut self;
        let n = g.frame.n();
        check_coverage(g.frame.face_side(), coverage)?;
        g.frame.set_coverage(Some(coverage.clone()));
        let mut levels = std::mem::take(&mut g.levels);
        let empty = DiamondMask::none(n);
        for level in &mut levels {
            level.par_iter_mut().for_each(|s| {
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
    pub(crate) fn gather_roots_with(&self, read: impl Fn(usize) -> i32) -> Vec<Vec<i32>> {
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
    pub(crate) fn scatter_roots_with(
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

    /// Forward transform in place: first makes the edge copies consistent (the canonical
    /// copy wins), then on return the cube raster holds the root-level values and the
    /// result one `N x N` detail matrix per diamond per level. Diamonds of a level run in
    /// parallel.
    pub fn analyze(&self, raster: &mut [i32]) -> Result<Vec<Vec<Vec<i32>>>, RasterError> {
        self.make_consistent(raster)?;
        Ok(analyze_levels(self, raster))
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
        synthesize_checked(self, raster, details)
    }

    /// Like [`SphereGeometry::synthesize`] with the diamonds of a level in parallel,
    /// calling `visit(level, index, coarse_vertices, fine_vertices, cells)` for each.
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

    fn clear_duplicates(&self, mask: &mut [bool]) {
        // Only points on a face's border have other copies: per row, its two ends, or all
        // of it on the face's first and last rows.
        let w = self.frame.width();
        mask.par_chunks_mut(w)
            .enumerate()
            .for_each(|(row, entries)| {
                let v = row % w;
                let (start, last) = (row * w, entries.len() - 1);
                let mut check = |u: usize| {
                    if entries[u] && !self.is_canonical(start + u) {
                        entries[u] = false;
                    }
                };
                if v == 0 || v + 1 == w {
                    (0..=last).for_each(&mut check);
                } else {
                    check(0);
                    check(last);
                }
            });
    }

    fn distinct_len(&self) -> usize {
        self.distinct_points()
    }

    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool {
        // Summed in order: a parallel reduction would make the mean, and so the
        // repository's bytes, depend on how the work was split.
        let (sum, count) = values
            .iter()
            .zip(valid)
            .filter(|(_, b)| **b)
            .fold((0.0, 0usize), |(s, c), (&x, _)| (s + x, c + 1));
        if count == 0 {
            return false;
        }
        let mean = sum / count as f64;
        let w = self.frame.width();
        out.par_chunks_exact_mut(w * w)
            .zip(values.par_chunks_exact(w * w))
            .zip(valid.par_chunks_exact(w * w))
            .for_each(|((out, face), ok)| {
                if !crate::fill::fill_into(w, w, face, ok, out, to_int) {
                    out.iter_mut().for_each(|x| *x = to_int(mean));
                }
            });
        self.make_consistent(out).is_ok()
    }

    fn coverage(&self) -> Option<&Coverage> {
        self.frame.coverage()
    }

    fn point_validity(&self) -> Option<Vec<bool>> {
        let c = self.frame.coverage()?;
        Some(
            (0..self.cube_len())
                .into_par_iter()
                .map(|k| self.is_valid_index(c, k))
                .collect(),
        )
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn every_slot_index_is_a_copy_of_its_sample_position() {
        for (face_side, n) in [(8, 8), (16, 4), (32, 8), (64, 8)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let d = g.domain();
            let two_n = 2 * n as i64;
            let all = g.root_slots().iter().chain(g.levels.iter().flatten());
            let mut checked = 0;
            for s in all {
                for i in 0..=n {
                    for j in 0..=n {
                        let p = d.vertex_position(s.id, n, i, j).unwrap().map(|x| x / two_n);
                        let copies: Vec<usize> = g.point_indices(p).collect();
                        assert!(
                            copies.contains(&s.vertex_index(i, j)),
                            "{face_side}/{n} {:?} vertex ({i},{j})",
                            s.id
                        );
                        if s.is_edge() && i == j && 0 < i && i < n {
                            assert_eq!(s.vertex_index(i, j), copies[0], "diagonal");
                        }
                        // Cells are samples only in diamonds that carry details.
                        if i < n && j < n && g.detail_levels() > 0 {
                            let p = d.cell_position(s.id, n, i, j).unwrap();
                            assert!(p.iter().all(|x| x % two_n == 0), "cell off the samples");
                            let copies: Vec<usize> =
                                g.point_indices(p.map(|x| x / two_n)).collect();
                            assert_eq!(s.cell_index(i, j), copies[0]);
                        }
                        checked += 1;
                    }
                }
            }
            assert!(checked > 0);
        }
    }

    #[test]
    fn finest_cells_and_roots_cover_every_point_once_per_level() {
        let (face_side, n) = (32, 4);
        let g = SphereGeometry::new(face_side, n).unwrap();
        assert_eq!(g.detail_levels(), 6);
        let mut hit = vec![0u32; g.cube_len()];
        for l in 0..g.detail_levels() {
            for s in g.level(l) {
                for i in 0..n {
                    for j in 0..n {
                        hit[s.cell_index(i, j)] += 1;
                    }
                }
            }
        }
        for s in g.root_slots() {
            for i in 0..=n {
                for j in 0..=n {
                    let k = s.vertex_index(i, j);
                    hit[k] += u32::from(g.is_canonical(k));
                }
            }
        }
        // Every distinct point is a root vertex or a cell of exactly one diamond (cells of
        // consecutive levels are the new lattice points).
        let mut distinct = 0;
        for (k, &h) in hit.iter().enumerate() {
            if g.is_canonical(k) {
                distinct += 1;
                assert_eq!(h, 1, "point {k}");
            } else {
                assert_eq!(h, 0);
            }
        }
        assert_eq!(distinct, g.distinct_points());
    }

    #[test]
    fn clearing_duplicates_keeps_exactly_the_canonical_copies() {
        for (face_side, n) in [(8, 8), (32, 4), (64, 16)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let mut mask = vec![true; g.cube_len()];
            // Entries already cleared stay cleared.
            mask[7] = false;
            g.clear_duplicates(&mut mask);
            for (k, &m) in mask.iter().enumerate() {
                assert_eq!(m, k != 7 && g.is_canonical(k), "{face_side} {n}: entry {k}");
            }
            let kept = mask.iter().filter(|&&m| m).count();
            assert_eq!(kept + usize::from(g.is_canonical(7)), g.distinct_points());
        }
    }

    #[test]
    fn analysis_and_synthesis_round_trip_with_consistent_copies() {
        for (face_side, n) in [(8, 8), (32, 4), (64, 16)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let mut orig: Vec<i32> = (0..g.cube_len())
                .map(|k| ((k * 2654435761) % 1013) as i32 - 300)
                .collect();
            g.make_consistent(&mut orig).unwrap();
            let mut r = orig.clone();
            let details = g.analyze(&mut r).unwrap();
            let roots = g.gather_roots(&r);
            let mut out = vec![0; g.cube_len()];
            g.scatter_roots(&roots, &mut out).unwrap();
            g.synthesize::<RasterError>(&mut out, |l, i, h| {
                h.copy_from_slice(&details[l][i]);
                Ok(true)
            })
            .unwrap();
            assert_eq!(out, orig, "{face_side} N={n}");
        }
    }

    #[test]
    fn bad_face_sides_are_rejected() {
        assert!(SphereGeometry::new(48, 16).is_err());
        assert!(SphereGeometry::new(8, 16).is_err());
        assert!(SphereGeometry::new(2, 2).is_err());
        assert!(SphereGeometry::new(0, 4).is_err());
        assert!(SphereGeometry::new(64, 3).is_err());
        assert!(SphereGeometry::new(4, 2).is_ok());
    }
}
