//! Incremental decoding, one diamond at a time, as a streaming client refines its cut.
//!
//! A client holds the vertex grids of the diamonds in its cut. Refining a diamond means:
//! 1. decode its blob (or no blob: zero details);
//! 2. synthesise, turning its `(N+1)^2` vertex grid into its refined lattice (updated
//!    vertices plus `N^2` cell centres);
//! 3. once *both* parents of a child are refined, assemble the child's vertex grid from
//!    the halves of their lattices ([`PlanarRefiner::child_grid`]).
//!
//! Every value a diamond's grid receives comes from exactly one parent lattice point.
//! Shared edges are unfiltered boundary vertices that both parents carry identically.
//! Neighbouring grids in any cut therefore agree bit for bit, and the values equal those
//! of the whole-raster decoder ([`crate::encode::decode_integers`]); the tests check
//! both.
//!
//! [`PlanarRefiner`] covers the planar domain, [`SphereRefiner`] planets; both precompute
//! the slots of their geometry ([`RasterGeometry`], [`crate::sphere_raster::SphereGeometry`]):
//! memory is proportional to the repository's diamonds (about 60 bytes each plus masks
//! where the data ends). [`Refiner`] is what a client needs of either.

mod sphere;

pub use sphere::SphereRefiner;

use crate::blob::{self, DecodeError};
use crate::coverage::Coverage;
use crate::diamond::{IdError, PlanarDomain, PlanarId};
use crate::encode::{Encoded, dequantize};
use crate::entropy::CodecModel;
use crate::lifting::{self, DiamondMask};
use crate::raster::{RasterError, RasterGeometry};

/// Why a diamond could not be refined or assembled.
#[derive(Debug, thiserror::Error)]
pub enum RefineError {
    /// The id is not a diamond of this repository that carries details.
    #[error(
        "diamond {0} is not refinable in this repository (outside the data or finer than its levels)"
    )]
    NotRefinable(String),
    /// A grid or lattice has the wrong size.
    #[error("expected {expected} values, got {got}")]
    WrongLength {
        /// Values expected.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// The lattices given are not those of the child's parents.
    #[error("{parent} is not a parent of {child}")]
    NotAParent {
        /// The child.
        child: String,
        /// The diamond passed as its parent.
        parent: String,
    },
    /// A valid vertex of the child lies in no given parent (a parent is missing).
    #[error("{missing} valid vertices of {child} are in none of the given parents")]
    MissingParent {
        /// The child.
        child: String,
        /// Valid vertices not covered.
        missing: usize,
    },
    /// The encoding or metadata is of the other domain (planar vs planet).
    #[error("the encoding is not of this refiner's domain")]
    WrongDomain,
    /// The blob does not decode.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The id is malformed.
    #[error(transparent)]
    Id(#[from] IdError),
    /// The repository parameters are inconsistent.
    #[error(transparent)]
    Raster(#[from] RasterError),
}

/// A refined diamond: its lattice, from which its children's grids are cut.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Refined<I = PlanarId> {
    /// The diamond.
    pub id: I,
    /// Its `(N+1)^2` vertex values after synthesis (row-major `i * (N+1) + j`).
    pub vertices: Vec<i32>,
    /// Its `N^2` cell-centre values.
    pub cells: Vec<i32>,
    /// Side information of the children whose blobs' bounds this diamond carries: a class
    /// per owned child (see [`crate::entropy::class_bound`]); empty without a blob.
    pub child_classes: Vec<(I, u8)>,
}

/// A diamond's decoded blob: dequantised details and side information.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Details<I = PlanarId> {
    /// The diamond.
    pub id: I,
    /// `N^2` dequantised details.
    pub h: Vec<i32>,
    /// Side information per owned child (see [`Refined::child_classes`]).
    pub child_classes: Vec<(I, u8)>,
    /// Owned children that have no blob, nor any descendant (their blobs need not be
    /// asked for: they are empty).
    pub empty_children: Vec<I>,
}

/// What a client needs to know about a diamond besides its grid.
#[derive(Clone, Debug)]
pub struct DiamondInfo<'a, I = PlanarId> {
    /// Detail level (0 = the root).
    pub level: usize,
    /// Position among its level's diamonds in the encoder's output
    /// ([`Encoded::blobs`]`[level][index]`).
    pub index: usize,
    /// Storage key (the blob's key in the repository).
    pub key: &'a [u8],
    /// Valid points (`None` = all): vertices outside the raster or its coverage are
    /// invalid and carry no meaningful value.
    pub mask: Option<&'a DiamondMask>,
    /// Its children (inside the data; at the finest detail level, the full-resolution
    /// leaves).
    pub children: Vec<I>,
}

/// What a streaming client needs of a repository's hierarchy, whatever its domain: the
/// roots, the shape of the DAG, decoding, synthesis and assembling children's grids.
pub trait Refiner: Send + Sync + std::fmt::Debug + 'static {
    /// The domain's diamond id.
    type Id: Copy + Eq + Ord + std::hash::Hash + std::fmt::Debug + Send + Sync + 'static;
    /// Diamond size `N`.
    fn n(&self) -> usize;
    /// Levels that carry details.
    fn detail_levels(&self) -> usize;
    /// The roots (one planar root, six planet face roots) and their vertex grids.
    fn roots(&self) -> Vec<(Self::Id, &[i32])>;
    /// What a client needs to know about a refinable diamond (`None` for leaves).
    fn info(&self, id: Self::Id) -> Option<DiamondInfo<'_, Self::Id>>;
    /// Whether `id` carries details here.
    fn is_refinable(&self, id: Self::Id) -> bool;
    /// The parents of `id` inside the domain (none for roots).
    fn parents(&self, id: Self::Id) -> Vec<Self::Id>;
    /// The ids centred at the frame corners `P1` and `P2`: the parents whose lattices hold
    /// the lower and the upper half (they may lie outside the domain).
    fn side_parents(&self, id: Self::Id) -> [Self::Id; 2];
    /// Frame corners `[E1, P1, E2, P2]` in id units (planar: `z = 0`; planets: points on
    /// the cube surface).
    fn corners(&self, id: Self::Id) -> [[i64; 3]; 4];
    /// Decodes the blob of `id`.
    fn decode(&self, id: Self::Id, blob: &[u8]) -> Result<Details<Self::Id>, RefineError>;
    /// Refines `id` from its vertex grid and decoded details (`None`: zero details).
    fn synthesize(
        &self,
        id: Self::Id,
        grid: &[i32],
        details: Option<&Details<Self::Id>>,
    ) -> Result<Refined<Self::Id>, RefineError>;
    /// The part of `child`'s grid that lies in the given refined parents, and which
    /// vertices were written.
    fn partial_child_grid(
        &self,
        child: Self::Id,
        parents: &[&Refined<Self::Id>],
    ) -> Result<(Vec<i32>, Vec<bool>), RefineError>;
    /// The id as a fetch key (its centre; planar `z = 0`).
    fn key_of(id: Self::Id) -> [i64; 3];
    /// The id of a fetch key.
    fn id_of(key: [i64; 3]) -> Self::Id;
}

/// Dequantises a diamond's blob and splits its side information over the owned children
/// (`next[k]` is the id of the next level's diamond `k`).
pub(crate) fn decode_details<I: Copy>(
    id: I,
    blob: &[u8],
    ctx: &crate::blob::BlobContext<'_>,
    model: &CodecModel,
    step: u32,
    owned: &[usize],
    next: impl Fn(usize) -> Option<I>,
) -> Result<Details<I>, RefineError> {
    let mut q = Vec::with_capacity(ctx.n * ctx.n);
    let classes = blob::decode_into(blob, ctx, model, &mut q)?;
    let h = q.iter().map(|&x| dequantize(x, step)).collect();
    let mut child_classes = Vec::with_capacity(classes.len());
    let mut empty_children = Vec::new();
    for (&k, entry) in owned.iter().zip(classes) {
        if let Some(c) = next(k) {
            let (class, no_data) = crate::entropy::split_side(entry);
            child_classes.push((c, class));
            if no_data {
                empty_children.push(c);
            }
        }
    }
    Ok(Details {
        id,
        h,
        child_classes,
        empty_children,
    })
}

/// Lifting synthesis of one diamond from its vertex grid and details (`None`: zeros).
pub(crate) fn synthesize_one<I: Copy>(
    n: usize,
    id: I,
    grid: &[i32],
    details: Option<&Details<I>>,
    mask: Option<&DiamondMask>,
) -> Result<Refined<I>, RefineError> {
    if grid.len() != (n + 1) * (n + 1) {
        return Err(RefineError::WrongLength {
            expected: (n + 1) * (n + 1),
            got: grid.len(),
        });
    }
    if let Some(d) = details
        && d.h.len() != n * n
    {
        return Err(RefineError::WrongLength {
            expected: n * n,
            got: d.h.len(),
        });
    }
    let zeros;
    let h = match details {
        Some(d) => &d.h,
        None => {
            zeros = vec![0; n * n];
            &zeros
        }
    };
    let mut vertices = grid.to_vec();
    let mut cells = vec![0; n * n];
    lifting::synthesize(n, &mut vertices, h, &mut cells, mask);
    Ok(Refined {
        id,
        vertices,
        cells,
        child_classes: details.map(|d| d.child_classes.clone()).unwrap_or_default(),
    })
}

/// Checks a refined parent's lattice sizes.
pub(crate) fn check_lattice<I>(r: &Refined<I>, n: usize) -> Result<(), RefineError> {
    if r.vertices.len() != (n + 1) * (n + 1) || r.cells.len() != n * n {
        return Err(RefineError::WrongLength {
            expected: (n + 1) * (n + 1) + n * n,
            got: r.vertices.len() + r.cells.len(),
        });
    }
    Ok(())
}

/// Errors when a valid vertex of `child`'s grid was not written (a parent is missing).
pub(crate) fn check_complete<I: std::fmt::Debug>(
    child: I,
    n: usize,
    written: &[bool],
    mask: Option<&DiamondMask>,
) -> Result<(), RefineError> {
    let missing = (0..=n)
        .flat_map(|i| (0..=n).map(move |j| (i, j)))
        .filter(|&(i, j)| !written[i * (n + 1) + j] && mask.is_none_or(|m| m.vertex(i, j)))
        .count();
    if missing > 0 {
        return Err(RefineError::MissingParent {
            child: id_text(child),
            missing,
        });
    }
    Ok(())
}

/// An id in error messages.
pub(crate) fn id_text(id: impl std::fmt::Debug) -> String {
    format!("{id:?}")
}

/// Refines planar diamonds one at a time for a repository's parameters.
#[derive(Debug)]
pub struct PlanarRefiner {
    geometry: RasterGeometry,
    slots: crate::diamond::IdMap<(usize, usize)>,
    steps: Vec<u32>,
    model: CodecModel,
    root: Vec<i32>,
}

impl PlanarRefiner {
    /// The refiner for a raster of `width x height` samples coded with `N x N` diamonds,
    /// the given quantiser steps (1/256 units per detail level), entropy model, root grid
    /// and (sparse repositories) coverage.
    pub fn new(
        width: usize,
        height: usize,
        n: usize,
        coverage: Option<&Coverage>,
        steps: Vec<u32>,
        model: CodecModel,
        root: Vec<i32>,
    ) -> Result<PlanarRefiner, RefineError> {
        let geometry = match coverage {
            Some(c) => RasterGeometry::with_coverage(width, height, n, c)?,
            None => RasterGeometry::new(width, height, n)?,
        };
        let side = (n + 1) * (n + 1);
        if root.len() != side {
            return Err(RefineError::WrongLength {
                expected: side,
                got: root.len(),
            });
        }
        let slots = (0..geometry.detail_levels())
            .flat_map(|level| {
                geometry
                    .level(level)
                    .iter()
                    .enumerate()
                    .map(move |(index, s)| (s.id, (level, index)))
            })
            .collect();
        Ok(PlanarRefiner {
            geometry,
            slots,
            steps,
            model,
            root,
        })
    }

    /// The refiner of an in-memory planar encoding.
    pub fn from_encoded(enc: &Encoded) -> Result<PlanarRefiner, RefineError> {
        PlanarRefiner::new(
            enc.width,
            enc.height,
            enc.n,
            enc.coverage.as_ref(),
            enc.steps.clone(),
            enc.model.clone(),
            enc.root.clone(),
        )
    }

    /// Diamond size `N`.
    pub fn n(&self) -> usize {
        self.geometry.n()
    }

    /// Raster width and height in samples (id units: sample `(x, y)` is at point `(x, y)`).
    pub fn raster_size(&self) -> (usize, usize) {
        (self.geometry.width(), self.geometry.height())
    }

    /// The id space.
    pub fn domain(&self) -> PlanarDomain {
        self.geometry.domain()
    }

    /// Levels that carry details (diamonds of these levels can be refined).
    pub fn detail_levels(&self) -> usize {
        self.geometry.detail_levels()
    }

    /// The root diamond and its vertex grid (from the repository metadata).
    pub fn root(&self) -> (PlanarId, &[i32]) {
        (self.geometry.domain().root(), &self.root)
    }

    /// What a client needs to know about a refinable diamond; `None` for diamonds
    /// outside the raster or finer than the detail levels (those are leaves).
    pub fn info(&self, id: PlanarId) -> Option<DiamondInfo<'_>> {
        let &(level, index) = self.slots.get(&id)?;
        let s = &self.geometry.level(level)[index];
        let children = if self.geometry.detail_levels() > level + 1 {
            s.children
                .iter()
                .map(|&k| self.geometry.level(level + 1)[k].id)
                .collect()
        } else {
            // Children of the finest detail level are full-resolution leaves: no slots.
            let domain = self.geometry.domain();
            domain
                .children(id)
                .unwrap_or_default()
                .into_iter()
                .filter(|&c| self.meets_raster(c))
                .collect()
        };
        Some(DiamondInfo {
            level,
            index,
            key: &s.key,
            mask: s.mask.as_ref(),
            children,
        })
    }

    /// Whether `id` carries details here (can be refined): cheaper than [`Self::info`].
    pub fn is_refinable(&self, id: PlanarId) -> bool {
        self.slots.contains_key(&id)
    }

    /// Whether any point of diamond `id` lies inside the raster.
    fn meets_raster(&self, id: PlanarId) -> bool {
        let Ok(c) = self.geometry.domain().corners(id) else {
            return false;
        };
        let (w, h) = (self.geometry.width() as i64, self.geometry.height() as i64);
        let min = |k: usize| c.iter().map(|p| p[k]).min().unwrap_or(0);
        let max = |k: usize| c.iter().map(|p| p[k]).max().unwrap_or(-1);
        min(0) < w && max(0) >= 0 && min(1) < h && max(1) >= 0
    }

    /// Decodes the blob of `id` (checksum over key and content, the repository's model,
    /// dequantisation): the part of refinement that can run off the frame loop.
    pub fn decode(&self, id: PlanarId, blob: &[u8]) -> Result<Details, RefineError> {
        let &(level, index) = self
            .slots
            .get(&id)
            .ok_or_else(|| RefineError::NotRefinable(id_text(id)))?;
        let slot = &self.geometry.level(level)[index];
        let ctx = self.geometry.blob_context(level, index);
        let step = self.steps.get(level).copied().unwrap_or(256);
        let next: &[_] = if level + 1 < self.geometry.detail_levels() {
            self.geometry.level(level + 1)
        } else {
            &[]
        };
        decode_details(id, blob, &ctx, &self.model, step, &slot.owned, |k| {
            next.get(k).map(|c| c.id)
        })
    }

    /// Refines `id` from its vertex `grid` and its decoded details (`None`: no blob, the
    /// zero refinement of a leaf).
    pub fn synthesize(
        &self,
        id: PlanarId,
        grid: &[i32],
        details: Option<&Details>,
    ) -> Result<Refined, RefineError> {
        let &(level, index) = self
            .slots
            .get(&id)
            .ok_or_else(|| RefineError::NotRefinable(id_text(id)))?;
        if details.is_some_and(|d| d.id != id) {
            return Err(RefineError::NotRefinable(id_text(id)));
        }
        let slot = &self.geometry.level(level)[index];
        synthesize_one(self.n(), id, grid, details, slot.mask.as_ref())
    }

    /// [`PlanarRefiner::decode`] then [`PlanarRefiner::synthesize`].
    pub fn refine(
        &self,
        id: PlanarId,
        grid: &[i32],
        blob: Option<&[u8]>,
    ) -> Result<Refined, RefineError> {
        let details = blob.map(|b| self.decode(id, b)).transpose()?;
        self.synthesize(id, grid, details.as_ref())
    }

    /// The part of `child`'s vertex grid that lies in the given refined parents: the grid
    /// (unwritten vertices are 0) and which vertices were written. A client holds one
    /// half of a child as soon as one of its parents is refined.
    pub fn partial_child_grid(
        &self,
        child: PlanarId,
        parents: &[&Refined],
    ) -> Result<(Vec<i32>, Vec<bool>), RefineError> {
        let n = self.n();
        let domain = self.geometry.domain();
        let child_frame = domain.corners(child)?;
        let true_parents = domain.parents(child)?;
        let mut grid = vec![0; (n + 1) * (n + 1)];
        let mut written = vec![false; (n + 1) * (n + 1)];
        for parent in parents {
            let not_a_parent = || RefineError::NotAParent {
                child: id_text(child),
                parent: id_text(parent.id),
            };
            if !true_parents.contains(&parent.id) {
                return Err(not_a_parent());
            }
            check_lattice(parent, n)?;
            let map = lifting::child_half(&domain.corners(parent.id)?, &child_frame, n)
                .ok_or_else(not_a_parent)?;
            lifting::scatter_to_child(
                &map,
                n,
                &parent.vertices,
                &parent.cells,
                &mut grid,
                Some(&mut written),
            );
        }
        Ok((grid, written))
    }

    /// The vertex grid of `child`, cut from its refined parents' lattices. Every valid
    /// vertex must lie in one of `parents` (pass both parents; border half diamonds have
    /// one). Invalid vertices are 0.
    pub fn child_grid(
        &self,
        child: PlanarId,
        parents: &[&Refined],
    ) -> Result<Vec<i32>, RefineError> {
        let (grid, written) = self.partial_child_grid(child, parents)?;
        if self.slots.contains_key(&child) {
            let mask = self.info(child).and_then(|info| info.mask);
            check_complete(child, self.n(), &written, mask)?;
        }
        Ok(grid)
    }
}

impl Refiner for PlanarRefiner {
    type Id = PlanarId;

    fn n(&self) -> usize {
        self.geometry.n()
    }

    fn detail_levels(&self) -> usize {
        self.geometry.detail_levels()
    }

    fn roots(&self) -> Vec<(PlanarId, &[i32])> {
        vec![self.root()]
    }

    fn info(&self, id: PlanarId) -> Option<DiamondInfo<'_>> {
        PlanarRefiner::info(self, id)
    }

    fn is_refinable(&self, id: PlanarId) -> bool {
        self.slots.contains_key(&id)
    }

    fn parents(&self, id: PlanarId) -> Vec<PlanarId> {
        self.geometry.domain().parents(id).unwrap_or_default()
    }

    fn side_parents(&self, id: PlanarId) -> [PlanarId; 2] {
        let c = self.geometry.domain().corners(id).unwrap_or_default();
        [
            PlanarId::new(c[1][0], c[1][1]),
            PlanarId::new(c[3][0], c[3][1]),
        ]
    }

    fn corners(&self, id: PlanarId) -> [[i64; 3]; 4] {
        let c = self.geometry.domain().corners(id).unwrap_or_default();
        c.map(|p| [p[0], p[1], 0])
    }

    fn decode(&self, id: PlanarId, blob: &[u8]) -> Result<Details, RefineError> {
        PlanarRefiner::decode(self, id, blob)
    }

    fn synthesize(
        &self,
        id: PlanarId,
        grid: &[i32],
        details: Option<&Details>,
    ) -> Result<Refined, RefineError> {
        PlanarRefiner::synthesize(self, id, grid, details)
    }

    fn partial_child_grid(
        &self,
        child: PlanarId,
        parents: &[&Refined],
    ) -> Result<(Vec<i32>, Vec<bool>), RefineError> {
        PlanarRefiner::partial_child_grid(self, child, parents)
    }

    fn key_of(id: PlanarId) -> [i64; 3] {
        [id.x, id.y, 0]
    }

    fn id_of(key: [i64; 3]) -> PlanarId {
        PlanarId::new(key[0], key[1])
    }
}
