//! Colour layers: a colour repository (YCoCg-R, three channels) matched at run time to an
//! elevation repository of the same domain, even when their depths and diamond sizes
//! differ (the paper's section 4.2).
//!
//! - **Ids.** Both repositories cover the same domain; their id spaces differ by a power
//!   of two (`2^shift`, from their `m`). A diamond of level `l` in one is the diamond of
//!   level `l` in the other with its centre scaled by `2^shift`, so the DAG keeps the
//!   elevation ids and maps each to its colour id exactly ([`ColourLayer::colour_id`]).
//! - **Depths.** The DAG refines to the deeper layer's depth. The shallower layer is
//!   extended by procedural levels ([`Procedural`]): zero details (the lifting's smooth
//!   interpolation) or zero-centred noise, made up on the client, never fetched.
//! - **Sizes.** Each diamond carries an `(Nc+1)^2` colour grid per channel next to its
//!   `(Ne+1)^2` heights (by default `Nc = 2 Ne`: two texels per triangle edge); refinement
//!   synthesises both, and its error is `max(edge, texel)` in pixels.
//! - **Blobs.** One request per diamond fetches its three channel blobs, framed
//!   ([`quincunx_meta::channels`]); a channel without details has length 0.

use quincunx_decoder::colour::ycocg_r_to_rgb;
use quincunx_decoder::incremental::{Details, Procedural, RefineError, Refined};
use quincunx_meta::Metadata;
use quincunx_meta::channels::split_channels;

use crate::domain::Domain;
use crate::fetch::Weigh;
use crate::open::SessionError;

/// Channels of a colour repository (Y, Co, Cg).
pub const CHANNELS: usize = 3;

/// The decoded details of one diamond's colour: per channel, `None` when that channel has
/// no details there (zero details).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ColourDetails<I> {
    /// The diamond (colour id).
    pub id: I,
    /// Y, Co, Cg.
    pub channels: Vec<Option<Details<I>>>,
}

impl<I: Copy + Eq> ColourDetails<I> {
    /// Children whose colour is empty below them in every channel: a channel without
    /// details here has none below; one with details lists its empty children.
    pub fn empty_children(&self, children: &[I]) -> Vec<I> {
        children
            .iter()
            .copied()
            .filter(|c| {
                self.channels
                    .iter()
                    .all(|d| d.as_ref().is_none_or(|d| d.empty_children.contains(c)))
            })
            .collect()
    }
}

impl<I: Send + Sync + 'static> Weigh for ColourDetails<I> {
    fn weight_bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + self
                .channels
                .iter()
                .flatten()
                .map(Weigh::weight_bytes)
                .sum::<usize>()
    }
}

/// A diamond's colour in the DAG: per channel its `(Nc+1)^2` vertex grid, and its
/// refined lattices while it is refined.
#[derive(Clone, Debug)]
pub struct ColourNode<I> {
    /// The diamond's colour id.
    pub id: I,
    /// Y, Co, Cg vertex grids (entries of absent halves are 0).
    pub grids: std::sync::Arc<Vec<Vec<i32>>>,
    /// Y, Co, Cg refinements while refined (side information; the lattices themselves
    /// are not kept once the children have their halves).
    pub refined: Option<Vec<Refined<I>>>,
}

/// A colour repository matched to an elevation DAG.
#[derive(Debug)]
pub struct ColourLayer<R: Domain> {
    /// One refiner per channel (same geometry; own steps, model and roots), extended by
    /// procedural levels to the DAG's depth.
    channels: Vec<R>,
    /// Colour id = elevation id `* 2^shift`.
    shift: i32,
    /// Per channel `(value_scale, value_offset)`: decoded = offset + integer * scale.
    scales: Vec<(f64, f64)>,
    /// Levels the colour repository codes.
    coded_levels: usize,
}

/// Both layers' refiners once matched: the elevation refiner is extended too when the
/// colour is deeper.
pub type Matched<R> = (R, ColourLayer<R>);

impl<R: Domain> ColourLayer<R> {
    /// Matches colour repository `name` (`meta`) to the elevation refiner of `elevation`
    /// (`elevation_meta`): checks they cover the same domain, and extends whichever is
    /// shallower with procedural levels (`detail`) so both refine to the deeper depth.
    pub fn match_to(
        elevation: R,
        elevation_meta: &Metadata,
        name: &str,
        meta: &Metadata,
        detail: Procedural,
    ) -> Result<Matched<R>, SessionError> {
        let mismatch = |reason: String| SessionError::Metadata {
            name: name.to_string(),
            reason,
        };
        if meta.attribute.kind != quincunx_meta::AttributeKind::Colour
            || meta.channels.len() != CHANNELS
        {
            return Err(mismatch(format!(
                "a colour layer needs a colour repository of {CHANNELS} channels, not {} ({} channels)",
                meta.attribute.kind,
                meta.channels.len()
            )));
        }
        if meta.domain != elevation_meta.domain {
            return Err(mismatch(format!(
                "domain {:?} does not match the elevation's {:?}",
                meta.domain, elevation_meta.domain
            )));
        }
        let channels: Vec<R> = (0..CHANNELS)
            .map(|k| R::channel_from_metadata(name, meta, k))
            .collect::<Result<_, _>>()?;
        let shift = channels[0].id_exponent() as i32 - elevation.id_exponent() as i32;
        check_same_domain(elevation_meta, meta, shift).map_err(mismatch)?;
        let coded_levels = channels[0].detail_levels();
        let depth = coded_levels.max(elevation.detail_levels());
        let extend = |r: R, coded: usize| {
            r.with_procedural_levels(depth - coded, detail)
                .map_err(|e| mismatch(e.to_string()))
        };
        let elevation_levels = elevation.detail_levels();
        let elevation = extend(elevation, elevation_levels)?;
        let channels = channels
            .into_iter()
            .map(|c| extend(c, coded_levels))
            .collect::<Result<Vec<_>, _>>()?;
        let scales = meta
            .channels
            .iter()
            .map(|c| (c.value_scale, c.value_offset))
            .collect();
        Ok((
            elevation,
            ColourLayer {
                channels,
                shift,
                scales,
                coded_levels,
            },
        ))
    }

    /// Colour diamond size `Nc`.
    pub fn n(&self) -> usize {
        self.channels[0].n()
    }

    /// The channel refiners (Y, Co, Cg).
    pub fn channels(&self) -> &[R] {
        &self.channels
    }

    /// Levels the colour repository codes (deeper ones are procedural).
    pub fn coded_levels(&self) -> usize {
        self.coded_levels
    }

    /// The colour id of an elevation id.
    pub fn colour_id(&self, id: R::Id) -> Option<R::Id> {
        R::scale_id(id, self.shift)
    }

    /// The elevation id of a colour id.
    pub fn elevation_id(&self, id: R::Id) -> Option<R::Id> {
        R::scale_id(id, -self.shift)
    }

    /// Whether the colour diamond `colour` has a blob to fetch (coded, not procedural).
    pub fn is_coded(&self, colour: R::Id) -> bool {
        self.channels[0].is_coded(colour)
    }

    /// Whether the colour diamond `colour` can be refined (coded or procedural).
    pub fn is_refinable(&self, colour: R::Id) -> bool {
        self.channels[0].is_refinable(colour)
    }

    /// The roots' colour grids, keyed by elevation root.
    pub fn root_grids(&self, root: R::Id) -> Option<ColourNode<R::Id>> {
        let id = self.colour_id(root)?;
        let grids = self
            .channels
            .iter()
            .map(|c| {
                c.roots()
                    .into_iter()
                    .find(|(r, _)| *r == id)
                    .map(|(_, g)| g.to_vec())
            })
            .collect::<Option<Vec<_>>>()?;
        Some(ColourNode {
            id,
            grids: std::sync::Arc::new(grids),
            refined: None,
        })
    }

    /// Decodes a diamond's framed colour blob (colour id).
    pub fn decode(&self, id: R::Id, bytes: &[u8]) -> Result<ColourDetails<R::Id>, String> {
        let parts = split_channels(bytes, CHANNELS).map_err(|e| e.to_string())?;
        let channels = parts
            .into_iter()
            .zip(&self.channels)
            .map(|(part, r)| part.map(|b| r.decode(id, b)).transpose())
            .collect::<Result<Vec<_>, RefineError>>()
            .map_err(|e| e.to_string())?;
        Ok(ColourDetails { id, channels })
    }

    /// Refines a diamond's colour from its grids and details (`None`: zero, or
    /// procedural below the colour repository's depth).
    pub fn synthesize(
        &self,
        node: &ColourNode<R::Id>,
        details: Option<&ColourDetails<R::Id>>,
    ) -> Result<Vec<Refined<R::Id>>, RefineError> {
        self.channels
            .iter()
            .enumerate()
            .map(|(k, r)| {
                let d = details
                    .and_then(|d| d.channels.get(k))
                    .and_then(Option::as_ref);
                r.synthesize(node.id, &node.grids[k], d)
            })
            .collect()
    }

    /// The part of a child's colour grids (colour id) that lies in one refined parent
    /// (its Y, Co, Cg lattices), and which vertices that is.
    pub fn child_half(
        &self,
        child: R::Id,
        lattices: &[Refined<R::Id>],
    ) -> Result<(Vec<Vec<i32>>, Vec<bool>), RefineError> {
        let mut written = Vec::new();
        let grids = self
            .channels
            .iter()
            .zip(lattices)
            .map(|(r, lattice)| {
                let (g, w) = r.partial_child_grid(child, &[lattice])?;
                written = w;
                Ok(g)
            })
            .collect::<Result<Vec<_>, RefineError>>()?;
        Ok((grids, written))
    }

    /// The sRGB colour of vertex `k` of a diamond's colour grids (YCoCg-R inverted,
    /// clamped to bytes); `None` when the grids have no vertex `k`.
    pub fn rgb(&self, grids: &[Vec<i32>], k: usize) -> Option<[u8; 3]> {
        let [y, co, cg] = self.ycocg(grids, k)?;
        let (r, g, b) = ycocg_r_to_rgb(y, co, cg);
        Some([r, g, b].map(|x| x.clamp(0, 255) as u8))
    }

    /// The YCoCg-R integers `[Y, Co, Cg]` of vertex `k` (each channel's integers scaled
    /// back to colour units): what a shader decodes with the inverse transform.
    pub fn ycocg(&self, grids: &[Vec<i32>], k: usize) -> Option<[i32; 3]> {
        let v = |c: usize| {
            let (scale, offset) = *self.scales.get(c)?;
            let x = *grids.get(c)?.get(k)?;
            Some((offset + f64::from(x) * scale).round() as i32)
        };
        Some([v(0)?, v(1)?, v(2)?])
    }
}

/// Checks that two repositories of one domain cover the same ground: planets of one
/// radius; planar rasters whose extents correspond at the id scale `2^shift` and whose
/// georeferences (when both have one) agree.
fn check_same_domain(elevation: &Metadata, colour: &Metadata, shift: i32) -> Result<(), String> {
    if elevation.domain == quincunx_meta::Domain::Sphere {
        if let (Some(a), Some(b)) = (elevation.radius_m, colour.radius_m)
            && (a - b).abs() > 1e-9 * a.abs().max(b.abs())
        {
            return Err(format!(
                "planet radius {b} m does not match the elevation's {a} m"
            ));
        }
        return Ok(());
    }
    for axis in 0..2 {
        let (e, c) = (elevation.extent[axis], colour.extent[axis]);
        let (e, c) = (e.saturating_sub(1) as i128, c.saturating_sub(1) as i128);
        let same = if shift >= 0 {
            e << shift == c
        } else {
            c << -shift == e
        };
        if !same {
            return Err(format!(
                "extent {:?} does not line up with the elevation's {:?} (id scale 2^{shift}): \
                 the rasters must span the same ground, node to node",
                colour.extent, elevation.extent
            ));
        }
    }
    if let (Some(a), Some(b)) = (&elevation.georef, &colour.georef) {
        for (k, x, y) in [
            ("west", a.west, b.west),
            ("east", a.east, b.east),
            ("north", a.north, b.north),
            ("south", a.south, b.south),
        ] {
            if (x - y).abs() > 1e-6 * (1.0 + x.abs()) {
                return Err(format!(
                    "georeference {k} {y} does not match the elevation's {x}"
                ));
            }
        }
    }
    Ok(())
}
