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
//! This first version covers the planar domain and precomputes the slots of
//! [`RasterGeometry`]: memory is proportional to the repository's diamonds (about 60
//! bytes each plus masks at the raster border).

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
        "diamond {0:?} is not refinable in this repository (outside the raster or finer than its levels)"
    )]
    NotRefinable(PlanarId),
    /// A grid or lattice has the wrong size.
    #[error("expected {expected} values, got {got}")]
    WrongLength {
        /// Values expected.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// The lattices given are not those of the child's parents.
    #[error("{parent:?} is not a parent of {child:?}")]
    NotAParent {
        /// The child.
        child: PlanarId,
        /// The diamond passed as its parent.
        parent: PlanarId,
    },
    /// A valid vertex of the child lies in no given parent (a parent is missing).
    #[error("{missing} valid vertices of {child:?} are in none of the given parents")]
    MissingParent {
        /// The child.
        child: PlanarId,
        /// Valid vertices not covered.
        missing: usize,
    },
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
pub struct Refined {
    /// The diamond.
    pub id: PlanarId,
    /// Its `(N+1)^2` vertex values after synthesis (row-major `i * (N+1) + j`).
    pub vertices: Vec<i32>,
    /// Its `N^2` cell-centre values.
    pub cells: Vec<i32>,
    /// Side information of the children whose blobs' bounds this diamond carries: a class
    /// per owned child (see [`crate::entropy::class_bound`]); empty without a blob.
    pub child_classes: Vec<(PlanarId, u8)>,
}

/// A diamond's decoded blob: dequantised details and side information.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Details {
    /// The diamond.
    pub id: PlanarId,
    /// `N^2` dequantised details.
    pub h: Vec<i32>,
    /// Side information per owned child (see [`Refined::child_classes`]).
    pub child_classes: Vec<(PlanarId, u8)>,
    /// Owned children that have no blob, nor any descendant (their blobs need not be
    /// asked for: they are empty).
    pub empty_children: Vec<PlanarId>,
}

/// What a client needs to know about a diamond besides its grid.
#[derive(Clone, Debug)]
pub struct DiamondInfo<'a> {
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
    /// Its children that carry details too (finer than this level, inside the raster).
    pub children: Vec<PlanarId>,
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
        let n = self.n();
        let &(level, index) = self.slots.get(&id).ok_or(RefineError::NotRefinable(id))?;
        let slot = &self.geometry.level(level)[index];
        let mut q = Vec::with_capacity(n * n);
        let ctx = self.geometry.blob_context(level, index);
        let classes = blob::decode_into(blob, &ctx, &self.model, &mut q)?;
        let step = self.steps.get(level).copied().unwrap_or(256);
        let h = q.iter().map(|&x| dequantize(x, step)).collect();
        let next: &[_] = if level + 1 < self.geometry.detail_levels() {
            self.geometry.level(level + 1)
        } else {
            &[]
        };
        let mut child_classes = Vec::with_capacity(classes.len());
        let mut empty_children = Vec::new();
        for (&k, entry) in slot.owned.iter().zip(classes) {
            if let Some(c) = next.get(k) {
                let (class, no_data) = crate::entropy::split_side(entry);
                child_classes.push((c.id, class));
                if no_data {
                    empty_children.push(c.id);
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

    /// Refines `id` from its vertex `grid` and its decoded details (`None`: no blob, the
    /// zero refinement of a leaf).
    pub fn synthesize(
        &self,
        id: PlanarId,
        grid: &[i32],
        details: Option<&Details>,
    ) -> Result<Refined, RefineError> {
        let n = self.n();
        let &(level, index) = self.slots.get(&id).ok_or(RefineError::NotRefinable(id))?;
        if grid.len() != (n + 1) * (n + 1) {
            return Err(RefineError::WrongLength {
                expected: (n + 1) * (n + 1),
                got: grid.len(),
            });
        }
        if let Some(d) = details
            && (d.id != id || d.h.len() != n * n)
        {
            return Err(RefineError::WrongLength {
                expected: n * n,
                got: d.h.len(),
            });
        }
        let slot = &self.geometry.level(level)[index];
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
        lifting::synthesize(n, &mut vertices, h, &mut cells, slot.mask.as_ref());
        Ok(Refined {
            id,
            vertices,
            cells,
            child_classes: details.map(|d| d.child_classes.clone()).unwrap_or_default(),
        })
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
            if !true_parents.contains(&parent.id) {
                return Err(RefineError::NotAParent {
                    child,
                    parent: parent.id,
                });
            }
            if parent.vertices.len() != grid.len() || parent.cells.len() != n * n {
                return Err(RefineError::WrongLength {
                    expected: grid.len() + n * n,
                    got: parent.vertices.len() + parent.cells.len(),
                });
            }
            let map = lifting::child_half(&domain.corners(parent.id)?, &child_frame, n).ok_or(
                RefineError::NotAParent {
                    child,
                    parent: parent.id,
                },
            )?;
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
        let n = self.n();
        let (grid, written) = self.partial_child_grid(child, parents)?;
        let mask = self.info(child).and_then(|info| info.mask);
        let missing = (0..=n)
            .flat_map(|i| (0..=n).map(move |j| (i, j)))
            .filter(|&(i, j)| !written[i * (n + 1) + j] && mask.is_none_or(|m| m.vertex(i, j)))
            .count();
        if missing > 0 && self.slots.contains_key(&child) {
            return Err(RefineError::MissingParent { child, missing });
        }
        Ok(grid)
    }
}
