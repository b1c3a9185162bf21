//! What a quincunx repository says about itself, shared by the store that writes and
//! serves it, the server, and the client that streams it: the metadata record
//! ([`Metadata`], one JSON document whose every field is typed), the answer framing
//! ([`answer`]: packages of a blob and its small owned children, with the id relations
//! they need), the multi-channel blob framing ([`channels`]) and the one check of a
//! record every reader makes ([`limits`]: [`Metadata::check_limits`], [`Metadata::validate`]).
//!
//! The JSON is part of the repository format (`docs/repository-format.md`): the content
//! hash is computed over it, so every type here serialises to exactly the text the
//! earlier string and JSON-value fields did (`"planar"`, `"rms=9"`, georeference keys in
//! alphabetical order); the store's golden files check that.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

pub mod answer;
pub mod channels;
pub mod crypto;
pub mod limits;
pub mod pack;

pub use limits::MetadataError;

/// Everything a server or client needs to know about a repository, stored as one JSON
/// record. Codec-specific parts (model, steps, root grids) are opaque numbers here.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metadata {
    /// `quincunx_store::FORMAT_VERSION` of the writer.
    pub format_version: u32,
    /// `true` only in the record written by `quincunx_store::RepositoryBuilder::publish`.
    pub complete: bool,
    /// SHA-256 (hex) over every key and blob in key order and the metadata with this
    /// field empty: changes whenever any content changes (used to version URLs).
    pub content_hash: String,
    /// Planar raster or cube-mapped sphere.
    pub domain: Domain,
    /// Domain size exponent: planar side `2^m`, sphere cube `[-2^m, 2^m]^3` (id units).
    pub m: u32,
    /// Diamond size `N` (cells per side; vertex grids are `(N+1)^2`).
    pub n: u32,
    /// Levels that carry details (blobs exist for levels `0 .. levels`).
    pub levels: u32,
    /// What the samples are.
    pub attribute: Attribute,
    /// Planar: raster width and height in samples. Sphere: face side `2S` twice.
    pub extent: [u64; 2],
    /// How nodata in the source was handled.
    pub nodata: NodataPolicy,
    /// Where the source's samples are on Earth (or another body); `None` for sources
    /// without one (plain height fields, planet mosaics).
    pub georef: Option<Georef>,
    /// Planet radius in metres (sphere domain).
    pub radius_m: Option<f64>,
    /// One entry per channel (1 for elevation, 3 for colour: Y, Co, Cg).
    pub channels: Vec<ChannelCoding>,
    /// How the repository was built: provenance for people (tool, input file name, rate,
    /// achieved errors), free-form JSON that no reader interprets.
    pub build: serde_json::Value,
    /// Blob count and bytes per level.
    pub level_stats: Vec<LevelStats>,
    /// Sparse repositories: the codec's coverage bitmap (`Coverage::to_bytes`), which
    /// says where data exists; points elsewhere are invalid (holes). `None` = dense.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<Vec<u8>>,
    /// Inlining limit `T`: a diamond's package carries the packages of its owned children
    /// of at most `T` bytes ([`answer`]). `None`: no packages are served.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inline_max_bytes: Option<u32>,
    /// `true` only in the `metadata.json` that `quincunx export` writes: the repository is
    /// a folder of static files, where a diamond without a blob (a leaf) has no file, so
    /// the web server or object store answers its URL with a 404. A client takes a 404
    /// on a blob or package URL of such a repository as a leaf; from `quincunx serve`
    /// (which answers a leaf with an empty 200 and never sets this) a 404 stays an error.
    /// Not part of the content hash, which is computed with it `false`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub static_export: bool,
}

/// The attribute a repository carries.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Attribute {
    /// Heights or colour.
    pub kind: AttributeKind,
    /// Units of decoded values (`"m"` for elevation, `"srgb8"` for colour).
    pub units: String,
}

/// How source nodata was handled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodataPolicy {
    /// Nodata samples in the source.
    pub source_count: u64,
    /// What became of it.
    pub handling: NodataHandling,
}

/// Decoder parameters of one channel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChannelCoding {
    /// Channel name (`"height"`, `"Y"`, `"Co"`, `"Cg"`).
    pub name: String,
    /// Value units per integer: decoded = offset + integer * scale.
    pub value_scale: f64,
    /// Value at integer 0.
    pub value_offset: f64,
    /// Quantiser step of each detail level, 1/256 integer units.
    pub steps: Vec<u32>,
    /// Trained entropy-model bytes.
    pub model: Vec<u8>,
    /// Root vertex grids (one per root diamond), row-major `(N+1)^2`.
    pub roots: Vec<Vec<i32>>,
    /// Rate mode the channel was coded with.
    pub rate: Rate,
}

/// Blobs of one level.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LevelStats {
    /// Level.
    pub level: u32,
    /// Blobs stored.
    pub blobs: u64,
    /// Bytes of those blobs.
    pub bytes: u64,
}

/// The id space a repository's diamonds live in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Domain {
    /// A planar raster, square `[0, 2^m]^2`.
    Planar,
    /// The cube-mapped sphere `[-2^m, 2^m]^3` of a planet.
    Sphere,
}

impl Domain {
    /// The name in the metadata and on the command line (`"planar"`, `"sphere"`).
    pub fn name(self) -> &'static str {
        match self {
            Domain::Planar => "planar",
            Domain::Sphere => "sphere",
        }
    }
}

impl fmt::Display for Domain {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// What the samples of a repository are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AttributeKind {
    /// Heights (one channel).
    Elevation,
    /// sRGB colour as YCoCg-R (three channels).
    Colour,
}

impl AttributeKind {
    /// The name in the metadata (`"elevation"`, `"colour"`).
    pub fn name(self) -> &'static str {
        match self {
            AttributeKind::Elevation => "elevation",
            AttributeKind::Colour => "colour",
        }
    }
}

impl fmt::Display for AttributeKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// What a build did with the source's nodata.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NodataHandling {
    /// The source had none.
    None,
    /// Filled smoothly (no spikes or cliffs); in a sparse repository, large areas are
    /// holes instead ([`Metadata::coverage`]).
    Filled,
}

/// The rate mode a channel was coded with; in the JSON, `"lossless"`, `"rms=<t>"` or
/// `"max_error=<e>"` (units of the attribute: metres, or 8-bit levels for colour).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Rate {
    /// Bit-exact.
    Lossless,
    /// An RMS error target.
    Rms(f64),
    /// A guaranteed largest absolute error.
    MaxError(f64),
}

impl fmt::Display for Rate {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rate::Lossless => f.write_str("lossless"),
            Rate::Rms(t) => write!(f, "rms={t}"),
            Rate::MaxError(e) => write!(f, "max_error={e}"),
        }
    }
}

/// A rate that does not parse.
#[derive(Debug, thiserror::Error)]
#[error("unknown rate {0:?}: expected \"lossless\", \"rms=<t>\" or \"max_error=<e>\"")]
pub struct RateError(String);

impl FromStr for Rate {
    type Err = RateError;

    fn from_str(s: &str) -> Result<Rate, RateError> {
        let number = |v: &str| {
            v.parse::<f64>()
                .ok()
                .filter(|t| t.is_finite() && *t > 0.0)
                .ok_or_else(|| RateError(s.to_owned()))
        };
        if s == "lossless" {
            Ok(Rate::Lossless)
        } else if let Some(t) = s.strip_prefix("rms=") {
            Ok(Rate::Rms(number(t)?))
        } else if let Some(e) = s.strip_prefix("max_error=") {
            Ok(Rate::MaxError(number(e)?))
        } else {
            Err(RateError(s.to_owned()))
        }
    }
}

impl Serialize for Rate {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Rate {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Rate, D::Error> {
        let s = String::deserialize(deserializer)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// How samples sit on a georeference's extent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Registration {
    /// Grid-registered: the extent passes through the outer samples.
    Node,
    /// Pixel-registered: the extent is the outer edge of the cells.
    Cell,
}

/// Where a planar repository's raster lies on the ground. The fields are in alphabetical
/// order, the order of the JSON object the format has always stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Georef {
    /// Coordinate reference system, `"EPSG:<code>"` or the source's description.
    pub crs: Option<String>,
    /// Eastern edge (longitude or easting).
    pub east: f64,
    /// Northern edge (latitude or northing).
    pub north: f64,
    /// Whether the edges pass through the outer samples or the outer cell edges.
    pub registration: Registration,
    /// Southern edge.
    pub south: f64,
    /// Western edge.
    pub west: f64,
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn rates_round_trip_through_their_text() {
        for (rate, text) in [
            (Rate::Lossless, "lossless"),
            (Rate::Rms(9.0), "rms=9"),
            (Rate::Rms(0.25), "rms=0.25"),
            (Rate::MaxError(2.0), "max_error=2"),
        ] {
            assert_eq!(rate.to_string(), text);
            assert_eq!(text.parse::<Rate>().unwrap(), rate);
            assert_eq!(serde_json::to_string(&rate).unwrap(), format!("\"{text}\""));
        }
        for bad in ["", "rms=", "rms=-1", "rms=nan", "max_error=x", "fast"] {
            assert!(bad.parse::<Rate>().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn enums_serialise_as_the_format_names() {
        let text = |v: serde_json::Result<String>| v.unwrap();
        assert_eq!(text(serde_json::to_string(&Domain::Planar)), "\"planar\"");
        assert_eq!(text(serde_json::to_string(&Domain::Sphere)), "\"sphere\"");
        assert_eq!(
            text(serde_json::to_string(&AttributeKind::Colour)),
            "\"colour\""
        );
        assert_eq!(
            text(serde_json::to_string(&NodataHandling::Filled)),
            "\"filled\""
        );
        assert!(serde_json::from_str::<Domain>("\"torus\"").is_err());
        let g = Georef {
            crs: None,
            east: 2.0,
            north: 3.0,
            registration: Registration::Node,
            south: 1.0,
            west: 0.0,
        };
        assert_eq!(
            serde_json::to_string(&g).unwrap(),
            r#"{"crs":null,"east":2.0,"north":3.0,"registration":"node","south":1.0,"west":0.0}"#
        );
    }
}
