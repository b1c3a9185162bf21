//! The encoder's whole-raster transform: the forward transform (analysis) and the
//! parallel inverse the encoder measures side information with, over the geometries of
//! `quincunx-decoder` ([`RasterGeometry`], and the planet's
//! [`crate::sphere_raster::SphereGeometry`]).
//!
//! The geometries, the [`Layout`] trait and the serial inverse transform (the
//! whole-raster decoder) are the decoder's ([`quincunx_decoder::layout`]); lifting runs in
//! place on the raster, one level at a time, one diamond at a time.

use rayon::prelude::*;

use crate::lifting;
#[doc(inline)]
pub use quincunx_decoder::layout::Layout;
pub(crate) use quincunx_decoder::layout::check_len;
#[doc(inline)]
pub use quincunx_decoder::raster::{DiamondSlot, RasterError, RasterFrame, RasterGeometry};

/// The encoder's transform of a geometry: analysis, and synthesis with the diamonds of a
/// level in parallel. Implemented by [`RasterGeometry`] and
/// [`crate::sphere_raster::SphereGeometry`].
pub trait Transform {
    /// Forward transform in place: on return the raster holds the root-level values and
    /// the result holds one `N x N` detail matrix per diamond per level (zeros at
    /// invalid cells). Diamonds of a level are processed in parallel. A planet's edge
    /// copies are first made consistent (the canonical copy wins).
    fn analyze(&self, raster: &mut [i32]) -> Result<Vec<Vec<Vec<i32>>>, RasterError>;

    /// Like the geometry's serial `synthesize`, with the diamonds of a level in parallel,
    /// calling `visit(level, index, coarse_vertices, fine_vertices, cells)` for each
    /// diamond (used by the encoder to measure side information).
    fn synthesize_par<F, R>(
        &self,
        raster: &mut [i32],
        details: &[Vec<Vec<i32>>],
        visit: F,
    ) -> Result<Vec<Vec<R>>, RasterError>
    where
        F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
        R: Send;
}

impl Transform for RasterGeometry {
    fn analyze(&self, raster: &mut [i32]) -> Result<Vec<Vec<Vec<i32>>>, RasterError> {
        check_len(self, raster)?;
        Ok(analyze_levels(self, raster))
    }

    fn synthesize_par<F, R>(
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

/// What the encoder needs of a geometry beyond the transform: error measurement over
/// distinct points, and filling nodata before coding.
pub(crate) trait EncodeLayout: Layout {
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
}

impl EncodeLayout for RasterGeometry {
    fn clear_duplicates(&self, _mask: &mut [bool]) {}

    fn distinct_len(&self) -> usize {
        self.width() * self.height()
    }

    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool {
        crate::fill::fill_into(self.width(), self.height(), values, valid, out, to_int)
    }
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
