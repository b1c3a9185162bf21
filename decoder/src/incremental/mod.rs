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
//! of the whole-raster decoder (`quincunx_codec::encode::decode_integers`); the tests check
//! both.
//!
//! [`PlanarRefiner`] covers the planar domain, [`SphereRefiner`] planets. Neither holds
//! tables of the repository's diamonds: what refining one needs (level, key, mask,
//! children) is derived from its id ([`RasterFrame`],
//! [`crate::sphere_raster::SphereFrame`]), so a client's memory follows its view, not
//! the repository's size. [`Refiner`] is what a client needs of either.

mod sphere;

pub use sphere::SphereRefiner;

use crate::blob::{self, DecodeError};
use crate::coverage::Coverage;
use crate::dequantize;
use crate::diamond::{IdError, PlanarDomain, PlanarId};
use crate::entropy::CodecModel;
use crate::layout::ChannelCoding;
use crate::lifting::{self, DiamondMask};
use crate::raster::{RasterError, RasterFrame};

/// Why a diamond could not be refined or assembled.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
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
    /// Procedural levels asked for beyond what the id space holds, or on a sparse
    /// repository (whose holes procedural detail cannot respect).
    #[error("procedural levels: {0}")]
    Procedural(String),
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
    /// Bound profiles of owned children with nothing below them (see
    /// [`Details::child_profiles`]).
    pub child_profiles: Vec<(I, Vec<u8>)>,
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
    /// Of those, the ones whose bounds below them the blob gives (version 6): per level
    /// below the child, from its children down, a class bounding every descendant of that
    /// level; below a profile's end, nothing is said.
    pub child_profiles: Vec<(I, Vec<u8>)>,
}

/// What a client needs to know about a diamond besides its grid.
#[derive(Clone, Debug)]
pub struct DiamondInfo<I = PlanarId> {
    /// Detail level (0 = the root).
    pub level: usize,
    /// Storage key (the blob's key in the repository; `quincunx_codec::encode::Encoded::blobs_by_key` finds it
    /// in an encoder's output).
    pub key: Vec<u8>,
    /// Valid points (`None` = all): vertices outside the raster or its coverage are
    /// invalid and carry no meaningful value. (Cheap to clone: shared storage.)
    pub mask: Option<DiamondMask>,
    /// Its children (inside the data; at the finest level, the leaves).
    pub children: Vec<I>,
    /// Below the repository's finest level: no blob exists, synthesis makes its details
    /// up ([`Procedural`]); `key` is then empty.
    pub procedural: bool,
}

/// Detail a client makes up where a repository has none: on levels below its finest, so
/// that the graph can refine on to a deeper layer's depth (colour deeper than elevation,
/// or the reverse; the paper's section 4.2).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Procedural {
    /// Zero details: the lifting's smooth interpolation of the coarser samples.
    #[default]
    Zero,
    /// Zero-centred uniform noise in `-amplitude ..= amplitude` (integer units), a
    /// function of the diamond and the seed alone: the same diamond always gets the same
    /// detail, so a cut depends on the view and not on the path to it.
    Noise {
        /// Largest detail magnitude (integer units; 0 = [`Procedural::Zero`]).
        amplitude: i32,
        /// Seed mixed with the diamond's centre.
        seed: u64,
    },
}

impl Procedural {
    /// The made-up details of the diamond centred at `key` (`None`: zeros).
    pub(crate) fn details<I: Copy>(self, id: I, key: [i64; 3], n: usize) -> Option<Details<I>> {
        let Procedural::Noise { amplitude, seed } = self else {
            return None;
        };
        if amplitude <= 0 {
            return None;
        }
        let mut state = key.iter().fold(seed ^ 0x9E37_79B9_7F4A_7C15, |h, &x| {
            splitmix64(h ^ (x as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9))
        });
        let span = 2 * amplitude as u64 + 1;
        let h = (0..n * n)
            .map(|_| {
                state = splitmix64(state);
                // The high bits are uniform; the tiny modulo bias is irrelevant here.
                ((state >> 16) % span) as i32 - amplitude
            })
            .collect();
        Some(Details {
            id,
            h,
            child_classes: Vec::new(),
            empty_children: Vec::new(),
            child_profiles: Vec::new(),
        })
    }
}

fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Procedural levels below a refiner's coded ones: how many and with what detail.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Extension {
    extra: usize,
    detail: Procedural,
}

impl Extension {
    /// `extra` procedural levels below `coded`, checked against the id space
    /// (`max_level`: the domain's deepest level; the last procedural level needs
    /// children) and the data (a sparse repository cannot be extended).
    pub(crate) fn new(
        coded: usize,
        extra: usize,
        detail: Procedural,
        max_level: u32,
        sparse: bool,
    ) -> Result<Extension, RefineError> {
        if extra > 0 && sparse {
            return Err(RefineError::Procedural(
                "a sparse repository (holes) cannot be extended procedurally".into(),
            ));
        }
        if extra > 0 && coded + extra > max_level as usize {
            return Err(RefineError::Procedural(format!(
                "{coded} coded + {extra} procedural levels exceed the id space's {max_level}"
            )));
        }
        Ok(Extension { extra, detail })
    }

    /// Levels added.
    pub(crate) fn extra(&self) -> usize {
        self.extra
    }

    /// The made-up details.
    pub(crate) fn detail(&self) -> Procedural {
        self.detail
    }

    /// The procedural level of a diamond of `level` below `coded` ones (`None` when it
    /// is not procedural).
    pub(crate) fn level(&self, coded: usize, level: Option<u32>) -> Option<usize> {
        if self.extra == 0 {
            return None;
        }
        let level = level? as usize;
        (coded..coded + self.extra)
            .contains(&level)
            .then_some(level)
    }
}

/// What a streaming client needs of a repository's hierarchy, whatever its domain: the
/// roots, the shape of the DAG, decoding, synthesis and assembling children's grids.
pub trait Refiner: Send + Sync + std::fmt::Debug + 'static {
    /// The domain's diamond id.
    type Id: Copy + Eq + Ord + std::hash::Hash + std::fmt::Debug + Send + Sync + 'static;
    /// Diamond size `N`.
    fn n(&self) -> usize;
    /// Levels that carry details in the repository (blobs).
    fn detail_levels(&self) -> usize;
    /// Levels that can be refined: the coded ones and the procedural ones below them.
    fn levels(&self) -> usize;
    /// Whether `id` is refined from a blob of the repository (refinable and not
    /// procedural): only such diamonds are ever fetched.
    fn is_coded(&self, id: Self::Id) -> bool;
    /// The roots (one planar root, six planet face roots) and their vertex grids.
    fn roots(&self) -> Vec<(Self::Id, &[i32])>;
    /// What a client needs to know about a refinable diamond (`None` for leaves).
    fn info(&self, id: Self::Id) -> Option<DiamondInfo<Self::Id>>;
    /// [`Refiner::info`]'s children alone (a sparse planet's mask, which `info` also
    /// works out, costs far more).
    fn children(&self, id: Self::Id) -> Option<Vec<Self::Id>> {
        self.info(id).map(|i| i.children)
    }
    /// Whether `id` can be refined here (coded or procedural).
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
    /// The blob of `id` (version 6) with new side information and the same details
    /// (`None`: a blob of zero details, which refines as no blob does): `entry` gives the
    /// side entry of each child `id` owns (a class, flagged [`crate::entropy::NO_DATA`]
    /// where nothing below it has a blob, and then its bound profile, see
    /// [`crate::blob::encode_profiled`]). What a build's bound pass writes; blobs older
    /// than version 5 are not coded again.
    fn recode(
        &self,
        id: Self::Id,
        blob: Option<&[u8]>,
        entry: &dyn Fn(Self::Id) -> (u8, Vec<u8>),
    ) -> Result<Vec<u8>, RefineError>;
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

/// Dequantises a diamond's blob and splits its side information over its `owned`
/// children (in side order).
pub(crate) fn decode_details<I: Copy>(
    id: I,
    blob: &[u8],
    ctx: &crate::blob::BlobContext<'_>,
    model: &CodecModel,
    step: u32,
    owned: &[I],
) -> Result<Details<I>, RefineError> {
    let mut q = Vec::with_capacity(ctx.n * ctx.n);
    // The level's step decides sign hiding.
    let ctx = crate::blob::BlobContext { step, ..*ctx };
    let (classes, profiles) = blob::decode_profiled_into(blob, &ctx, model, &mut q)?;
    let h = q.iter().map(|&x| dequantize(x, step)).collect();
    let mut child_classes = Vec::with_capacity(classes.len());
    let mut empty_children = Vec::new();
    for (&c, entry) in owned.iter().zip(classes) {
        let (class, no_data) = crate::entropy::split_side(entry);
        child_classes.push((c, class));
        if no_data {
            empty_children.push(c);
        }
    }
    let child_profiles = empty_children.iter().copied().zip(profiles).collect();
    Ok(Details {
        id,
        h,
        child_classes,
        empty_children,
        child_profiles,
    })
}

/// [`Refiner::recode`] once the context is known: the blob's quantised details (zeros
/// without one) coded again (version 6) with the same context and model, `entries` (one
/// per owned child) and `profiles` (one per entry flagged no-data).
pub(crate) fn recode_details(
    blob: Option<&[u8]>,
    ctx: &crate::blob::BlobContext<'_>,
    model: &CodecModel,
    step: u32,
    entries: &[u8],
    profiles: &[Vec<u8>],
) -> Result<Vec<u8>, RefineError> {
    let ctx = crate::blob::BlobContext { step, ..*ctx };
    let mut q = vec![0; ctx.n * ctx.n];
    if let Some(blob) = blob {
        if let Some(&head) = blob.first()
            && head >> 4 < blob::UNPROFILED_VERSION
        {
            return Err(DecodeError::Version(head >> 4).into());
        }
        blob::decode_into(blob, &ctx, model, &mut q)?;
    }
    if entries.len() != ctx.owned_children {
        return Err(RefineError::WrongLength {
            expected: ctx.owned_children,
            got: entries.len(),
        });
    }
    Ok(blob::encode_profiled(&ctx, model, entries, &q, profiles))
}

/// Side entries and the profiles of those flagged no-data, from `(entry, profile)` pairs.
pub(crate) fn split_entries(pairs: impl Iterator<Item = (u8, Vec<u8>)>) -> (Vec<u8>, Vec<Vec<u8>>) {
    let mut entries = Vec::new();
    let mut profiles = Vec::new();
    for (e, p) in pairs {
        if crate::entropy::split_side(e).1 {
            profiles.push(p);
        }
        entries.push(e);
    }
    (entries, profiles)
}

/// The `children` of `id` whose side information its blob carries: those whose first
/// parent it is (the encoder's rule, `RasterGeometry::new`), in the children's order.
pub(crate) fn owned_by<I: Copy + PartialEq>(
    id: I,
    children: Vec<I>,
    parents: impl Fn(I) -> Result<Vec<I>, IdError>,
) -> Vec<I> {
    children
        .into_iter()
        .filter(|&c| parents(c).ok().and_then(|p| p.first().copied()) == Some(id))
        .collect()
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
        child_profiles: details
            .map(|d| d.child_profiles.clone())
            .unwrap_or_default(),
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
    geometry: RasterFrame,
    steps: Vec<u32>,
    model: CodecModel,
    /// The root grid, alone (the layout [`ChannelCoding`] takes).
    roots: Vec<Vec<i32>>,
    /// Levels below the coded ones, refined with made-up details.
    extension: Extension,
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
        let geometry = RasterFrame::new(width, height, n, coverage)?;
        let side = (n + 1) * (n + 1);
        if root.len() != side {
            return Err(RefineError::WrongLength {
                expected: side,
                got: root.len(),
            });
        }
        Ok(PlanarRefiner {
            geometry,
            steps,
            model,
            roots: vec![root],
            extension: Extension::default(),
        })
    }

    /// The refiner extended by `extra` procedural levels below the coded ones, refined
    /// with `detail` (see [`Procedural`]). Errors for sparse repositories and beyond the
    /// id space.
    pub fn with_procedural_levels(
        mut self,
        extra: usize,
        detail: Procedural,
    ) -> Result<PlanarRefiner, RefineError> {
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
    fn procedural_level(&self, id: PlanarId) -> Option<usize> {
        let level = self.geometry.domain().level(id).ok();
        self.extension
            .level(self.geometry.detail_levels(), level)
            .filter(|_| self.meets_raster(id))
    }

    /// Valid points of a procedural diamond (`None`: all; the raster's points, as for
    /// coded diamonds, in units of `1/N` sample where its samples fall between).
    fn procedural_mask(&self, id: PlanarId) -> Option<DiamondMask> {
        let c = self.geometry.domain().corners(id).ok()?;
        let n = self.n() as i64;
        let (w, h) = (self.geometry.width() as i64, self.geometry.height() as i64);
        // Position times 2N of vertex (2i, 2j) / cell (2i+1, 2j+1), exact.
        let at = |i2: i64, j2: i64| {
            [0, 1].map(|k| 2 * n * c[0][k] + i2 * (c[1][k] - c[0][k]) + j2 * (c[3][k] - c[0][k]))
        };
        let inside = |p: [i64; 2]| {
            (0..=2 * n * (w - 1)).contains(&p[0]) && (0..=2 * n * (h - 1)).contains(&p[1])
        };
        let corners_in = [(0, 0), (2 * n, 0), (2 * n, 2 * n), (0, 2 * n)]
            .iter()
            .all(|&(i, j)| inside(at(i, j)));
        (!corners_in).then(|| {
            DiamondMask::from_fn(
                self.n(),
                |i, j| inside(at(2 * i as i64, 2 * j as i64)),
                |i, j| inside(at(2 * i as i64 + 1, 2 * j as i64 + 1)),
            )
        })
    }

    /// The placement of the raster and of single diamonds.
    pub fn frame(&self) -> &RasterFrame {
        &self.geometry
    }

    /// What the whole-raster decoder decodes this channel with: the root grid, the
    /// quantiser steps and the entropy model.
    pub fn coding(&self) -> ChannelCoding<'_> {
        ChannelCoding {
            roots: &self.roots,
            steps: &self.steps,
            model: &self.model,
        }
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
        (self.geometry.domain().root(), &self.roots[0])
    }

    /// What a client needs to know about a refinable diamond; `None` for diamonds
    /// outside the raster or finer than the detail levels (those are leaves).
    pub fn info(&self, id: PlanarId) -> Option<DiamondInfo> {
        let Some((level, slot)) = self.geometry.slot(id) else {
            let level = self.procedural_level(id)?;
            return Some(DiamondInfo {
                level,
                key: Vec::new(),
                mask: self.procedural_mask(id),
                children: self.children_in_raster(id),
                procedural: true,
            });
        };
        let children = if self.geometry.detail_levels() > level + 1 {
            self.coded_children(id)
        } else {
            // Children of the finest detail level carry no details: full-resolution
            // leaves, or the first procedural level.
            self.children_in_raster(id)
        };
        Some(DiamondInfo {
            level,
            key: slot.key,
            mask: slot.mask,
            children,
            procedural: false,
        })
    }

    /// The children of `id` that carry details, in the domain's order.
    fn coded_children(&self, id: PlanarId) -> Vec<PlanarId> {
        let domain = self.geometry.domain();
        domain
            .children(id)
            .unwrap_or_default()
            .into_iter()
            .filter(|&c| self.geometry.is_coded(c))
            .collect()
    }

    /// The coded children whose side information `id`'s blob carries, in side order.
    fn owned_children(&self, id: PlanarId, level: usize) -> Vec<PlanarId> {
        if level + 1 >= self.geometry.detail_levels() {
            return Vec::new();
        }
        owned_by(id, self.coded_children(id), |c| {
            self.geometry.domain().parents(c)
        })
    }

    fn children_in_raster(&self, id: PlanarId) -> Vec<PlanarId> {
        self.geometry
            .domain()
            .children(id)
            .unwrap_or_default()
            .into_iter()
            .filter(|&c| self.meets_raster(c))
            .collect()
    }

    /// Whether `id` can be refined here (coded or procedural): cheaper than
    /// [`Self::info`].
    pub fn is_refinable(&self, id: PlanarId) -> bool {
        self.geometry.is_coded(id) || self.procedural_level(id).is_some()
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
        self.with_context(id, |ctx, step, owned| {
            decode_details(id, blob, ctx, &self.model, step, &owned)
        })
    }

    /// Runs `f` with the blob context of `id`, its level's step and its owned children.
    fn with_context<T>(
        &self,
        id: PlanarId,
        f: impl FnOnce(&crate::blob::BlobContext<'_>, u32, Vec<PlanarId>) -> Result<T, RefineError>,
    ) -> Result<T, RefineError> {
        let (level, slot) = self
            .geometry
            .slot(id)
            .ok_or_else(|| RefineError::NotRefinable(id_text(id)))?;
        let owned = self.owned_children(id, level);
        let ctx = self.geometry.slot_context(level, &slot, owned.len());
        let step = self.steps.get(level).copied().unwrap_or(256);
        f(&ctx, step, owned)
    }

    /// Refines `id` from its vertex `grid` and its decoded details (`None`: no blob, the
    /// zero refinement of a leaf).
    pub fn synthesize(
        &self,
        id: PlanarId,
        grid: &[i32],
        details: Option<&Details>,
    ) -> Result<Refined, RefineError> {
        if details.is_some_and(|d| d.id != id) {
            return Err(RefineError::NotRefinable(id_text(id)));
        }
        let Some((_, slot)) = self.geometry.slot(id) else {
            if details.is_some() || self.procedural_level(id).is_none() {
                return Err(RefineError::NotRefinable(id_text(id)));
            }
            let made_up = self
                .extension
                .detail()
                .details(id, [id.x, id.y, 0], self.n());
            let mask = self.procedural_mask(id);
            return synthesize_one(self.n(), id, grid, made_up.as_ref(), mask.as_ref());
        };
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
        if self.is_refinable(child) {
            let mask = self.info(child).and_then(|info| info.mask);
            check_complete(child, self.n(), &written, mask.as_ref())?;
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

    fn levels(&self) -> usize {
        self.geometry.detail_levels() + self.extension.extra()
    }

    fn is_coded(&self, id: PlanarId) -> bool {
        self.geometry.is_coded(id)
    }

    fn roots(&self) -> Vec<(PlanarId, &[i32])> {
        vec![self.root()]
    }

    fn info(&self, id: PlanarId) -> Option<DiamondInfo> {
        PlanarRefiner::info(self, id)
    }

    fn is_refinable(&self, id: PlanarId) -> bool {
        PlanarRefiner::is_refinable(self, id)
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

    fn recode(
        &self,
        id: PlanarId,
        blob: Option<&[u8]>,
        entry: &dyn Fn(PlanarId) -> (u8, Vec<u8>),
    ) -> Result<Vec<u8>, RefineError> {
        self.with_context(id, |ctx, step, owned| {
            let (entries, profiles) = split_entries(owned.into_iter().map(entry));
            recode_details(blob, ctx, &self.model, step, &entries, &profiles)
        })
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
