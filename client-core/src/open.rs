//! Opening a repository: why it can fail ([`SessionError`]) and what its metadata gives
//! (the incremental decoders and world mappings of planar repositories and planets).
//! Sessions, domains and colour layers all depend on this; it depends on none of them.

use quincunx_decoder::coverage::Coverage;
use quincunx_decoder::entropy::CodecModel;
use quincunx_decoder::incremental::{PlanarRefiner, RefineError, Refiner, SphereRefiner};
use quincunx_meta::{ChannelCoding, Domain, Metadata, Registration};

use crate::fetch::FetchError;
use crate::view::{PlanarWorld, SphereWorld};

/// Why the DAG refused an operation.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DagError {
    /// Not in the DAG, not complete (a parent is unrefined), already refined, or finer
    /// than the repository.
    #[error("{0} cannot be refined now")]
    NotRefinable(String),
    /// Not refined, or a child is refined.
    #[error("{0} cannot be coarsened now")]
    NotCoarsenable(String),
    /// Synthesis failed (bad details).
    #[error(transparent)]
    Refine(#[from] RefineError),
}

/// Mean Earth radius (metres), for sample spacings of latitude/longitude grids.
pub const EARTH_RADIUS_M: f64 = 6_371_008.8;

/// Why a session could not start or continue.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SessionError {
    /// Fetching the metadata or starting the network thread failed.
    #[error(transparent)]
    Fetch(#[from] FetchError),
    /// The repository's metadata is unusable for this client.
    #[error("repository {name:?}: {reason}")]
    Metadata {
        /// Repository name.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// The repository is of a kind this client does not stream yet.
    #[error("repository {name:?}: {reason}")]
    Unsupported {
        /// Repository name.
        name: String,
        /// What is missing.
        reason: String,
    },
    /// The DAG refused an operation (a bug, or details inconsistent with the metadata).
    #[error(transparent)]
    Dag(#[from] DagError),
}

/// A [`SessionError::Metadata`] naming repository `name`.
pub(crate) fn metadata_error(name: &str, reason: impl Into<String>) -> SessionError {
    SessionError::Metadata {
        name: name.to_string(),
        reason: reason.into(),
    }
}

/// Errors unless the repository has exactly one channel (elevation).
fn single_channel(name: &str, meta: &Metadata) -> Result<(), SessionError> {
    if meta.channels.len() > 1 {
        return Err(SessionError::Unsupported {
            name: name.to_string(),
            reason: format!(
                "{} channels ({}): open it as a colour layer of an elevation session",
                meta.channels.len(),
                meta.attribute.kind
            ),
        });
    }
    Ok(())
}

/// The coding of channel `channel` of a repository of `domain`, its entropy model and
/// coverage, after the checks every session needs.
fn channel<'m>(
    name: &str,
    meta: &'m Metadata,
    domain: Domain,
    channel: usize,
) -> Result<(&'m ChannelCoding, CodecModel, Option<Coverage>), SessionError> {
    if meta.domain != domain {
        return Err(SessionError::Unsupported {
            name: name.to_string(),
            reason: format!(
                "domain {:?}: open it with the {} session",
                meta.domain.name(),
                if meta.domain == Domain::Sphere {
                    "planet"
                } else {
                    "planar"
                }
            ),
        });
    }
    if !meta.complete {
        return Err(metadata_error(name, "the build did not complete"));
    }
    if meta.channels.is_empty() {
        return Err(metadata_error(name, "no channels"));
    }
    // The one check every reader makes (`quincunx_meta::limits`): hostile metadata from a
    // server is refused here, naming the field, before anything is sized from it.
    meta.validate()
        .map_err(|e| metadata_error(name, e.to_string()))?;
    let coding = meta.channels.get(channel).ok_or_else(|| {
        metadata_error(
            name,
            format!("no channel {channel} ({} channels)", meta.channels.len()),
        )
    })?;
    let model = CodecModel::from_bytes(&coding.model)
        .map_err(|e| metadata_error(name, format!("entropy model: {e}")))?;
    let coverage = meta
        .coverage
        .as_deref()
        .map(Coverage::from_bytes)
        .transpose()
        .map_err(|e| metadata_error(name, format!("coverage: {e}")))?;
    Ok((coding, model, coverage))
}

fn dim(name: &str, v: u64) -> Result<usize, SessionError> {
    usize::try_from(v).map_err(|_| metadata_error(name, "extent too large"))
}

/// Checks that the metadata's levels and `m` are what the geometry says.
fn check_levels(name: &str, meta: &Metadata, levels: usize, m: u32) -> Result<(), SessionError> {
    if levels != meta.levels as usize || m != meta.m {
        return Err(metadata_error(
            name,
            format!(
                "levels {} and m {} disagree with the extent and N (levels {levels}, m {m})",
                meta.levels, meta.m,
            ),
        ));
    }
    Ok(())
}

/// The incremental decoder of a planar single-channel repository from its metadata.
pub fn planar_refiner(name: &str, meta: &Metadata) -> Result<PlanarRefiner, SessionError> {
    single_channel(name, meta)?;
    planar_channel_refiner(name, meta, 0)
}

/// The incremental decoder of channel `index` of a planar repository.
pub fn planar_channel_refiner(
    name: &str,
    meta: &Metadata,
    index: usize,
) -> Result<PlanarRefiner, SessionError> {
    let (coding, model, coverage) = channel(name, meta, Domain::Planar, index)?;
    let [root] = coding.roots.as_slice() else {
        return Err(metadata_error(
            name,
            "a planar repository has one root grid",
        ));
    };
    let refiner = PlanarRefiner::new(
        dim(name, meta.extent[0])?,
        dim(name, meta.extent[1])?,
        meta.n as usize,
        coverage.as_ref(),
        coding.steps.clone(),
        model,
        root.clone(),
    )
    .map_err(|e| metadata_error(name, e.to_string()))?;
    check_levels(name, meta, refiner.detail_levels(), refiner.domain().m())?;
    Ok(refiner)
}

/// The incremental decoder of a single-channel planet from its metadata.
pub fn sphere_refiner(name: &str, meta: &Metadata) -> Result<SphereRefiner, SessionError> {
    single_channel(name, meta)?;
    sphere_channel_refiner(name, meta, 0)
}

/// The incremental decoder of channel `index` of a planet.
pub fn sphere_channel_refiner(
    name: &str,
    meta: &Metadata,
    index: usize,
) -> Result<SphereRefiner, SessionError> {
    let (coding, model, coverage) = channel(name, meta, Domain::Sphere, index)?;
    if coding.roots.len() != 6 {
        return Err(metadata_error(
            name,
            format!("a planet has 6 root grids, not {}", coding.roots.len()),
        ));
    }
    let refiner = SphereRefiner::new(
        dim(name, meta.extent[0])?,
        meta.n as usize,
        coverage.as_ref(),
        coding.steps.clone(),
        model,
        coding.roots.clone(),
    )
    .map_err(|e| metadata_error(name, e.to_string()))?;
    check_levels(name, meta, refiner.detail_levels(), refiner.domain().m())?;
    Ok(refiner)
}

/// The world mapping of a planet: its radius (metadata; required) and channel coding.
pub fn sphere_world(
    name: &str,
    meta: &Metadata,
    half_side: i64,
) -> Result<SphereWorld, SessionError> {
    let radius_m = meta
        .radius_m
        .filter(|r| r.is_finite() && *r > 0.0)
        .ok_or_else(|| metadata_error(name, "a planet needs a positive radius"))?;
    let (value_scale_m, value_offset_m) = meta
        .channels
        .first()
        .map_or((1.0, 0.0), |c| (c.value_scale, c.value_offset));
    Ok(SphereWorld {
        radius_m,
        half_side: half_side as f64,
        value_scale_m,
        value_offset_m,
        occluder_radius_m: 0.0,
    })
}

/// The world mapping of a planar repository: spacing from the georeference (or
/// `spacing_m`), values from its channel coding.
pub fn planar_world(meta: &Metadata, spacing_m: Option<f64>) -> PlanarWorld {
    let (value_scale_m, value_offset_m) = meta
        .channels
        .first()
        .map_or((1.0, 0.0), |c| (c.value_scale, c.value_offset));
    PlanarWorld {
        spacing_m: spacing_m
            .filter(|s| s.is_finite() && *s > 0.0)
            .or_else(|| georef_spacing_m(meta))
            .unwrap_or(1.0),
        value_scale_m,
        value_offset_m,
    }
}

/// Metres between rows from a georeference `{crs, west, east, north, south,
/// registration}`: degrees on the Earth for geographic grids, the grid's units otherwise.
fn georef_spacing_m(meta: &Metadata) -> Option<f64> {
    let g = meta.georef.as_ref()?;
    let (west, east, north, south) = (g.west, g.east, g.north, g.south);
    let rows = meta.extent[1] as f64;
    let node = g.registration == Registration::Node;
    let intervals = if node { rows - 1.0 } else { rows };
    let crs = g.crs.as_deref().unwrap_or("");
    let geographic = crs.contains("4326")
        || (crs.is_empty() || crs.to_ascii_lowercase().contains("lat"))
            && [west, east].iter().all(|v| v.abs() <= 360.0)
            && [north, south].iter().all(|v| v.abs() <= 90.0);
    let per_row = (north - south).abs() / intervals.max(1.0);
    let spacing = if geographic {
        per_row.to_radians() * EARTH_RADIUS_M
    } else {
        per_row
    };
    (spacing.is_finite() && spacing > 0.0).then_some(spacing)
}
