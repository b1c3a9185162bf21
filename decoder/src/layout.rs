//! The whole-raster inverse transform: every diamond of a placed raster (planar, or a
//! planet's cube raster) synthesised level by level, coarse to fine, in place.
//!
//! [`Layout`] is what the transform needs of a geometry; [`crate::raster::RasterGeometry`]
//! and [`crate::sphere_raster::SphereGeometry`] implement it. [`decode_levels`] decodes a
//! whole channel from its blobs (what `quincunx verify` and the browser's whole-repository
//! decode run); the encoder's forward transform and its parallel passes are built on the
//! same trait in `quincunx-codec`.

use crate::blob::{self, BlobContext, DecodeError};
use crate::coverage::Coverage;
use crate::entropy::CodecModel;
use crate::lifting::{self, DiamondMask};
use crate::raster::RasterError;

/// A placement of diamonds in a flat sample array (a planar raster, or the six face arrays
/// of a cube raster): everything the level-by-level transform needs to know about a
/// geometry.
pub trait Layout: Sync {
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
    /// disjoint parts of the raster can be written in parallel).
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
    /// The coverage that makes points invalid (sparse mode), if any.
    fn coverage(&self) -> Option<&Coverage>;
    /// Per array entry, whether it is a valid point; `None` when every entry is.
    fn point_validity(&self) -> Option<Vec<bool>>;
}

/// Checks that `raster` has the geometry's sample count.
pub fn check_len<G: Layout>(g: &G, raster: &[i32]) -> Result<(), RasterError> {
    if raster.len() == g.raster_len() {
        Ok(())
    } else {
        Err(RasterError::WrongLength {
            expected: g.raster_len(),
            got: raster.len(),
        })
    }
}

/// Inverse transform in place, on the calling thread: the raster holds the root-level
/// values on entry and the full-resolution values on exit. `details(level, index, h)`
/// fills the detail matrix `h` of a diamond and returns `Ok(false)` when the diamond has
/// none (zeros: the vertices stay, the cells are the prediction).
pub fn synthesize_levels<G: Layout, E: From<RasterError>>(
    g: &G,
    raster: &mut [i32],
    mut details: impl FnMut(usize, usize, &mut [i32]) -> Result<bool, E>,
) -> Result<(), E> {
    check_len(g, raster)?;
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
                lifting::synthesize_zero(n, &v, &mut c, g.mask(s));
            }
            g.scatter_cells(s, &c, raster);
        }
    }
    Ok(())
}

/// One channel's coding: what [`decode_levels`] decodes its blobs with.
#[derive(Clone, Copy, Debug)]
pub struct ChannelCoding<'a> {
    /// Every root vertex grid, in root order.
    pub roots: &'a [Vec<i32>],
    /// Quantiser step per detail level, in 1/256 integer units (256 past the end).
    pub steps: &'a [u32],
    /// The channel's trained starting probabilities.
    pub model: &'a CodecModel,
}

/// Decodes a channel at full resolution into `out` (resized to the raster, its allocation
/// reused), on the calling thread: the roots, then every level's blobs, synthesised in
/// place. `blob(level, index)` gives the diamond's blob (`None`: no data below it).
/// Invalid points of a sparse geometry decode to 0.
pub fn decode_levels<'b, G: Layout>(
    geom: &G,
    coding: ChannelCoding<'_>,
    mut blob: impl FnMut(usize, usize) -> Option<&'b [u8]>,
    out: &mut Vec<i32>,
) -> Result<(), DecodeError> {
    out.clear();
    out.resize(geom.raster_len(), 0);
    let raster = &mut out[..];
    geom.scatter_roots(coding.roots, raster)?;
    let mut q = Vec::with_capacity(geom.n() * geom.n());
    synthesize_levels::<G, DecodeError>(geom, raster, |l, i, h| {
        let Some(bytes) = blob(l, i) else {
            return Ok(false);
        };
        let step = coding.steps.get(l).copied().unwrap_or(256);
        let ctx = BlobContext {
            step,
            ..geom.blob_context(l, i)
        };
        blob::decode_into(bytes, &ctx, coding.model, &mut q)?;
        // A blob that only carries its children's side information has no nonzero
        // detail: synthesising it is the prediction alone (`lifting::synthesize_zero`).
        let mut any = false;
        for (dst, &x) in h.iter_mut().zip(q.iter()) {
            any |= x != 0;
            *dst = crate::dequantize(x, step);
        }
        Ok(any)
    })?;
    if let Some(valid) = geom.point_validity() {
        raster
            .iter_mut()
            .zip(&valid)
            .filter(|(_, ok)| !**ok)
            .for_each(|(x, _)| *x = 0);
    }
    Ok(())
}
