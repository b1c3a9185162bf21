//! Incremental decoding of planets: [`SphereRefiner`].
//!
//! The same three steps as the planar refiner (decode, synthesise, assemble children's
//! grids from their parents' lattices). Assembly works in the unfolded chart of the
//! parent's canonical face: every point of a parent's square unfolds into it
//! ([`crate::diamond::sphere::unfold`]), so the child's half inside that parent maps onto
//! the parent's lattice by the same affine map as in the plane, also across cube edges.

use super::{
    Details, DiamondInfo, Extension, Procedural, RefineError, Refined, Refiner, check_complete,
    check_lattice, decode_details, id_text, owned_by, recode_details, split_entries,
    synthesize_one,
};
use crate::coverage::Coverage;
use crate::diamond::sphere::unfold;
use crate::diamond::{SphereDomain, SphereId};
use crate::entropy::CodecModel;
use crate::layout::ChannelCoding;
use crate::lifting;
use crate::sphere_raster::{SphereFrame, SphereSlot};

/// Refines planet diamonds one at a time for a repository's parameters.
#[derive(Debug)]
pub struct SphereRefiner {
    geometry: SphereFrame,
    steps: Vec<u32>,
    model: CodecModel,
    roots: Vec<Vec<i32>>,
    /// Levels below the coded ones, refined with made-up details.
    extension: Extension,
}

impl SphereRefiner {
    /// The refiner for a planet of `face_side` samples per face side coded with `N x N`
    /// diamonds, the quantiser steps, entropy model, the six face roots' vertex grids (face
    /// order) and (sparse repositories) coverage.
    pub fn new(
        face_side: usize,
        n: usize,
        coverage: Option<&Coverage>,
        steps: Vec<u32>,
        model: CodecModel,
        roots: Vec<Vec<i32>>,
    ) -> Result<SphereRefiner, RefineError> {
        let geometry = SphereFrame::new(face_side, n, coverage)?;
        let side = (n + 1) * (n + 1);
        if roots.len() != 6 {
            return Err(RefineError::WrongLength {
                expected: 6,
                got: roots.len(),
            });
        }
        if let Some(r) = roots.iter().find(|r| r.len() != side) {
            return Err(RefineError::WrongLength {
                expected: side,
                got: r.len(),
            });
        }
        Ok(SphereRefiner {
            geometry,
            steps,
            model,
            roots,
            extension: Extension::default(),
        })
    }

    /// The refiner extended by `extra` procedural levels below the coded ones, refined
    /// with `detail` (see [`Procedural`]). Errors for sparse planets and beyond the id
    /// space.
    pub fn with_procedural_levels(
        mut self,
        extra: usize,
        detail: Procedural,
    ) -> Result<SphereRefiner, RefineError> {
        self.extension = Extension::new(
            self.geometry.detail_levels(),
            extra,
            detail,
            self.geometry.domain().max_level(),
            self.geometry.coverage().is_some(),
        )?;
        Ok(self)
    }

    /// The level of a procedural diamond (`None` for others).
    fn procedural_level(&self, id: SphereId) -> Option<usize> {
        let level = self.geometry.domain().level(id).ok();
        self.extension.level(self.geometry.detail_levels(), level)
    }

    /// The id space.
    pub fn domain(&self) -> SphereDomain {
        self.geometry.domain()
    }

    /// The placement of the planet's samples (cube raster) and of single diamonds.
    pub fn frame(&self) -> &SphereFrame {
        &self.geometry
    }

    /// What the whole-raster decoder decodes this channel with: the six face roots'
    /// grids, the quantiser steps and the entropy model.
    pub fn coding(&self) -> ChannelCoding<'_> {
        ChannelCoding {
            roots: &self.roots,
            steps: &self.steps,
            model: &self.model,
        }
    }

    fn slot_of(&self, id: SphereId) -> Result<(usize, SphereSlot), RefineError> {
        self.geometry
            .coded_slot(id)
            .ok_or_else(|| RefineError::NotRefinable(id_text(id)))
    }

    /// The children of `id` that carry details below a detail level (all of them on a
    /// planet), `None` at the finest.
    fn coded_children(&self, id: SphereId, level: usize) -> Option<Vec<SphereId>> {
        (level + 1 < self.geometry.detail_levels())
            .then(|| self.geometry.domain().children(id).unwrap_or_default())
    }

    /// The coded children whose side information `id`'s blob carries, in side order.
    fn owned_children(&self, id: SphereId, level: usize) -> Vec<SphereId> {
        let children = self.coded_children(id, level).unwrap_or_default();
        owned_by(id, children, |c| self.geometry.domain().parents(c))
    }

    /// The vertex grid of `child`, cut from its refined parents' lattices (pass both:
    /// every diamond of a planet below the face roots has two). Invalid vertices are 0.
    pub fn child_grid(
        &self,
        child: SphereId,
        parents: &[&Refined<SphereId>],
    ) -> Result<Vec<i32>, RefineError> {
        let (grid, written) = self.partial_child_grid(child, parents)?;
        let mask = self.info(child).and_then(|info| info.mask);
        check_complete(child, self.geometry.n(), &written, mask.as_ref())?;
        Ok(grid)
    }
}

impl Refiner for SphereRefiner {
    type Id = SphereId;

    fn n(&self) -> usize {
        self.geometry.n()
    }

    fn detail_levels(&self) -> usize {
        self.geometry.detail_levels()
    }

    fn levels(&self) -> usize {
        self.geometry.detail_levels() + self.extension.extra()
    }

    fn is_coded(&self, id: SphereId) -> bool {
        self.geometry.coded_level(id).is_some()
    }

    fn roots(&self) -> Vec<(SphereId, &[i32])> {
        self.geometry
            .domain()
            .roots()
            .into_iter()
            .zip(&self.roots)
            .map(|(id, g)| (id, g.as_slice()))
            .collect()
    }

    fn info(&self, id: SphereId) -> Option<DiamondInfo<SphereId>> {
        let Some((level, slot)) = self.geometry.coded_slot(id) else {
            let level = self.procedural_level(id)?;
            return Some(DiamondInfo {
                level,
                key: Vec::new(),
                mask: None,
                children: self.geometry.domain().children(id).unwrap_or_default(),
                procedural: true,
            });
        };
        // Children of the finest detail level: full-resolution leaves, or the first
        // procedural level.
        let children = self
            .coded_children(id, level)
            .unwrap_or_else(|| self.geometry.domain().children(id).unwrap_or_default());
        Some(DiamondInfo {
            level,
            key: slot.key,
            mask: slot.mask,
            children,
            procedural: false,
        })
    }

    fn children(&self, id: SphereId) -> Option<Vec<SphereId>> {
        let domain_children = || self.geometry.domain().children(id).unwrap_or_default();
        match self.geometry.coded_level(id) {
            Some(level) if self.geometry.has_slot(id) => Some(
                self.coded_children(id, level)
                    .unwrap_or_else(domain_children),
            ),
            _ => {
                self.procedural_level(id)?;
                Some(domain_children())
            }
        }
    }

    fn is_refinable(&self, id: SphereId) -> bool {
        self.is_coded(id) || self.procedural_level(id).is_some()
    }

    fn parents(&self, id: SphereId) -> Vec<SphereId> {
        self.geometry.domain().parents(id).unwrap_or_default()
    }

    fn side_parents(&self, id: SphereId) -> [SphereId; 2] {
        let c = self.corners(id);
        [SphereId::new(c[1]), SphereId::new(c[3])]
    }

    fn corners(&self, id: SphereId) -> [[i64; 3]; 4] {
        self.geometry.domain().corners(id).unwrap_or_default()
    }

    fn decode(&self, id: SphereId, blob: &[u8]) -> Result<Details<SphereId>, RefineError> {
        let (level, slot) = self.slot_of(id)?;
        let owned = self.owned_children(id, level);
        let ctx = self.geometry.slot_context(level, &slot, owned.len());
        let step = self.steps.get(level).copied().unwrap_or(256);
        decode_details(id, blob, &ctx, &self.model, step, &owned)
    }

    fn recode(
        &self,
        id: SphereId,
        blob: Option<&[u8]>,
        entry: &dyn Fn(SphereId) -> (u8, Vec<u8>),
    ) -> Result<Vec<u8>, RefineError> {
        let (level, slot) = self.slot_of(id)?;
        let owned = self.owned_children(id, level);
        let ctx = self.geometry.slot_context(level, &slot, owned.len());
        let step = self.steps.get(level).copied().unwrap_or(256);
        let (entries, profiles) = split_entries(owned.into_iter().map(entry));
        recode_details(blob, &ctx, &self.model, step, &entries, &profiles)
    }

    fn synthesize(
        &self,
        id: SphereId,
        grid: &[i32],
        details: Option<&Details<SphereId>>,
    ) -> Result<Refined<SphereId>, RefineError> {
        if details.is_some_and(|d| d.id != id) {
            return Err(RefineError::NotRefinable(id_text(id)));
        }
        if !self.is_coded(id) && details.is_none() && self.procedural_level(id).is_some() {
            let made_up = self.extension.detail().details(id, id.c, self.n());
            return synthesize_one(self.n(), id, grid, made_up.as_ref(), None);
        }
        let (_, slot) = self.slot_of(id)?;
        synthesize_one(self.n(), id, grid, details, slot.mask.as_ref())
    }

    fn partial_child_grid(
        &self,
        child: SphereId,
        parents: &[&Refined<SphereId>],
    ) -> Result<(Vec<i32>, Vec<bool>), RefineError> {
        let n = self.n();
        let domain = self.geometry.domain();
        let s = domain.size();
        let frame = domain.corners(child)?;
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
            // The child's half inside this parent, in the parent's chart: E1, E2 and the
            // parent's centre (P1 or P2 of the child's frame); the fourth corner completes
            // the square.
            let (face, other, parent_frame) = domain.chart_frame(parent.id)?;
            let chart = |p: [i64; 3]| unfold(face, other, p, s).ok_or_else(not_a_parent);
            let (e1, e2, centre) = (chart(frame[0])?, chart(frame[2])?, chart(parent.id.c)?);
            let opposite = [e1[0] + e2[0] - centre[0], e1[1] + e2[1] - centre[1]];
            let child_frame = if parent.id.c == frame[1] {
                [e1, centre, e2, opposite]
            } else {
                [e1, opposite, e2, centre]
            };
            let map =
                lifting::child_half(&parent_frame, &child_frame, n).ok_or_else(not_a_parent)?;
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

    fn key_of(id: SphereId) -> [i64; 3] {
        id.c
    }

    fn id_of(key: [i64; 3]) -> SphereId {
        SphereId::new(key)
    }
}
