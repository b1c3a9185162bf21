//! What a page opens: an elevation repository, an optional colour one, and settings, as
//! the JSON both the client and the decoding workers are created from.

use serde::Deserialize;

use quincunx_client_core::fetch::planner::PlannerConfig;
use quincunx_client_core::refine::Metric;
use quincunx_client_core::stream::StreamConfig;
use quincunx_meta::Metadata;

/// One repository: its name on the server and its `metadata.json`.
#[derive(Clone, Debug, Deserialize)]
pub struct LayerSpec {
    /// The repository's name.
    pub name: String,
    /// Its metadata.
    pub meta: Metadata,
}

/// A session's repositories and settings:
/// `{"elevation": {"name", "meta"}, "colour": {"name", "meta"} | null, "config": {...}}`.
#[derive(Clone, Debug, Deserialize)]
pub struct Open {
    /// The elevation repository.
    pub elevation: LayerSpec,
    /// The colour repository matched to it, if any.
    #[serde(default)]
    pub colour: Option<LayerSpec>,
    /// Settings (every field optional: the native client's defaults).
    #[serde(default)]
    pub config: WebConfig,
}

/// The settings a page may change; the rest are the native client's
/// (`SessionConfig::default`). Field names are camelCase in JSON.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default, rename_all = "camelCase", deny_unknown_fields)]
pub struct WebConfig {
    /// Most requests outstanding per repository (default 16: a browser runs at most six
    /// HTTP/1.1 connections per host, and requests beyond the window wait in its queue,
    /// outside the planner's priorities).
    pub max_in_flight: Option<usize>,
    /// The decoded-details cache of each layer, bytes (default 64 MiB).
    pub cache_bytes: Option<usize>,
    /// Levels of lookahead below wanted diamonds (default 2).
    pub lookahead_levels: Option<usize>,
    /// How far ahead the camera is predicted, ms (default 500; 0 disables prefetch).
    pub prefetch_ahead_ms: Option<f64>,
    /// Packages from this multiple of the tolerance (default 2; `0` asks for bare blobs).
    pub package_factor: Option<f64>,
    /// Sample spacing of a planar repository, metres (default: its georeferencing).
    pub spacing_m: Option<f64>,
    /// Most halves the cut may hold (a renderer's GPU pool).
    pub max_cut_halves: Option<usize>,
    /// The refinement metric (`"geometric"` or `"sampling"`; default: the native one).
    pub metric: Option<String>,
    /// The repository is a static export: a 404 is a leaf.
    pub static_export: bool,
}

/// Browsers' default window (see [`WebConfig::max_in_flight`]).
pub const DEFAULT_MAX_IN_FLIGHT: usize = 16;

impl WebConfig {
    /// The frame loop's settings.
    pub fn stream(&self) -> Result<StreamConfig, String> {
        let mut c = StreamConfig::default();
        if let Some(l) = self.lookahead_levels {
            c.lookahead_levels = l;
        }
        if let Some(ms) = self.prefetch_ahead_ms {
            c.prefetch_ahead = std::time::Duration::try_from_secs_f64(ms / 1000.0)
                .map_err(|_| format!("prefetchAheadMs {ms} is not a duration"))?;
        }
        if let Some(f) = self.package_factor {
            if !(f.is_finite() && f >= 0.0) {
                return Err(format!("packageFactor {f} is not a factor"));
            }
            c.package_factor = (f > 0.0).then_some(f);
        }
        c.refine.max_cut_halves = self.max_cut_halves;
        if let Some(m) = &self.metric {
            c.refine.metric = m.parse::<Metric>().map_err(|e| e.to_string())?;
        }
        Ok(c)
    }

    /// The request planner's settings.
    pub fn planner(&self) -> PlannerConfig {
        PlannerConfig {
            max_in_flight: self.max_in_flight.unwrap_or(DEFAULT_MAX_IN_FLIGHT).max(1),
            static_export: self.static_export,
            ..PlannerConfig::default()
        }
    }

    /// The cache budget of each layer.
    pub fn cache_bytes(&self) -> usize {
        self.cache_bytes.unwrap_or(64 << 20)
    }
}
