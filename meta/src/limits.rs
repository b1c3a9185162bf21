//! The one check of a metadata record, for every reader: the store at open (so the
//! server refuses to serve what fails it), the client after fetching it, and every tool.
//!
//! Two tiers. [`Metadata::check_limits`] is what the store (bytes only, it never decodes)
//! can check: every field within its stated limits, and the fields a server uses (content
//! hash, `m`, `n`, `extent`, `levels`, radius) sane and consistent. [`Metadata::validate`]
//! adds what a decoder needs: `m` and `levels` exactly those the extent and `N` imply, and
//! one channel per component of the attribute. Limits (`docs/repository-format.md`,
//! "Metadata limits"):
//!
//! - `content_hash`: exactly 64 lower-case hex digits (SHA-256).
//! - `m` in `1..=48` ([`quincunx_diamond::MAX_M`]); `n` a power of two in `2..=512`.
//! - `extent`: each side in `1..=2^24` ([`MAX_EXTENT`]); a sphere's is square, its side
//!   at least 2 and at most `2^(m+1)`; a planar side at most `2^m + 1`.
//! - `levels`: at most `2 m` (planar) or `2 m + 2` (sphere), and 0 only when the raster
//!   fits one diamond (the sides at most `N + 1`, a face side `N`).
//! - `radius_m`: a planet's is required, finite and in `1 .. 10^12` m; a planar one, if
//!   given, too.
//! - Channels: at most 3 ([`MAX_CHANNELS`]); each has finite value scale (> 0) and
//!   offset, `levels` positive quantiser steps, a model of at most [`MAX_MODEL_BYTES`],
//!   and one root grid (planar) or six (sphere) of `(N+1)^2` values each.
//! - ([`Metadata::validate`] only) `level_stats`: at most `levels` entries, each of a
//!   level below `levels`.

use crate::{AttributeKind, Domain, Metadata};
use quincunx_diamond::{MAX_M, MAX_N};

/// Largest raster side (samples), the codec's limit.
pub const MAX_EXTENT: u64 = 1 << 24;

/// Most channels a repository has (colour: Y, Co, Cg).
pub const MAX_CHANNELS: usize = 3;

/// Largest stored entropy model, bytes.
pub const MAX_MODEL_BYTES: usize = 1 << 20;

/// Smallest and largest planet radius, metres.
pub const RADIUS_RANGE_M: (f64, f64) = (1.0, 1e12);

/// Metadata that fails a check: the field and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("metadata field `{field}`: {reason}")]
pub struct MetadataError {
    /// The field, as named in the JSON (`channels[0].steps` for a channel's).
    pub field: String,
    /// What is wrong with it.
    pub reason: String,
}

fn bad(field: impl Into<String>, reason: impl Into<String>) -> MetadataError {
    MetadataError {
        field: field.into(),
        reason: reason.into(),
    }
}

/// What a raster's extent and `N` imply: `(m, detail levels)`.
fn implied(domain: Domain, extent: [u64; 2], n: u64) -> Result<(u32, u32), MetadataError> {
    match domain {
        Domain::Planar => {
            let e = (extent[0].max(extent[1]) - 1).max(1);
            let mut k = 0u32;
            while (n << k) < e {
                k += 1;
            }
            Ok(((n.trailing_zeros() + k).max(1), 2 * k))
        }
        Domain::Sphere => {
            let face = extent[0];
            if !face.is_multiple_of(n) || !(face / n).is_power_of_two() {
                return Err(bad(
                    "extent",
                    format!("a face side of {face} is not N = {n} times a power of two"),
                ));
            }
            let k = (face / n).trailing_zeros();
            Ok((face.trailing_zeros() - 1, 2 * k))
        }
    }
}

impl Metadata {
    /// Checks every field against its limits and the fields a server uses against each
    /// other (module docs); the error names the first field that fails.
    pub fn check_limits(&self) -> Result<(), MetadataError> {
        let hash = &self.content_hash;
        if hash.len() != 64 || !hash.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
            let shown: String = hash.chars().take(16).collect();
            return Err(bad(
                "content_hash",
                format!(
                    "{} characters ({shown:?}...), not 64 lower-case hex digits",
                    hash.chars().count()
                ),
            ));
        }
        if !(1..=MAX_M).contains(&self.m) {
            return Err(bad("m", format!("{} is outside 1..={MAX_M}", self.m)));
        }
        let n = u64::from(self.n);
        if !n.is_power_of_two() || !(2..=MAX_N as u64).contains(&n) {
            return Err(bad(
                "n",
                format!("{} is not a power of two in 2..={MAX_N}", self.n),
            ));
        }
        let [a, b] = self.extent;
        if !(1..=MAX_EXTENT).contains(&a) || !(1..=MAX_EXTENT).contains(&b) {
            return Err(bad(
                "extent",
                format!("{a} x {b}: each side must be in 1..={MAX_EXTENT}"),
            ));
        }
        let side = 1u64 << self.m;
        let (max_side, max_levels) = match self.domain {
            Domain::Planar => (side + 1, 2 * self.m),
            Domain::Sphere => (2 * side, 2 * self.m + 2),
        };
        if self.domain == Domain::Sphere && (a != b || a < 2) {
            return Err(bad(
                "extent",
                format!("{a} x {b}: a planet's faces are square, of side 2 or more"),
            ));
        }
        if a.max(b) > max_side {
            return Err(bad(
                "extent",
                format!(
                    "{a} x {b} does not fit the domain of m = {} (sides up to {max_side})",
                    self.m
                ),
            ));
        }
        if self.levels > max_levels {
            return Err(bad(
                "levels",
                format!(
                    "{} is deeper than the domain of m = {} allows ({max_levels})",
                    self.levels, self.m
                ),
            ));
        }
        let one_diamond = match self.domain {
            Domain::Planar => a.max(b) <= n + 1,
            Domain::Sphere => a == n,
        };
        if self.levels == 0 && !one_diamond {
            return Err(bad(
                "levels",
                format!("0, but a {a} x {b} raster does not fit one diamond of N = {n}"),
            ));
        }
        self.check_radius()?;
        self.check_channels()?;
        Ok(())
    }

    /// [`Metadata::check_limits`], and what a decoder needs besides: `m` and `levels`
    /// exactly those the extent and `N` imply, one channel for elevation and three for
    /// colour.
    pub fn validate(&self) -> Result<(), MetadataError> {
        self.check_limits()?;
        let (m, levels) = implied(self.domain, self.extent, u64::from(self.n))?;
        let [a, b] = self.extent;
        if m != self.m {
            return Err(bad(
                "m",
                format!(
                    "{}, but a {a} x {b} raster of N = {} gives m = {m}",
                    self.m, self.n
                ),
            ));
        }
        if levels != self.levels {
            return Err(bad(
                "levels",
                format!(
                    "{}, but a {a} x {b} raster of N = {} gives {levels} levels",
                    self.levels, self.n
                ),
            ));
        }
        if self.level_stats.len() > self.levels as usize {
            return Err(bad(
                "level_stats",
                format!(
                    "{} entries for {} levels",
                    self.level_stats.len(),
                    self.levels
                ),
            ));
        }
        if let Some(s) = self.level_stats.iter().find(|s| s.level >= self.levels) {
            return Err(bad(
                "level_stats",
                format!("an entry of level {} (levels {})", s.level, self.levels),
            ));
        }
        let want = match self.attribute.kind {
            AttributeKind::Elevation => 1,
            AttributeKind::Colour => 3,
        };
        if self.channels.len() != want {
            return Err(bad(
                "channels",
                format!(
                    "{} channels; {} has {want}",
                    self.channels.len(),
                    self.attribute.kind
                ),
            ));
        }
        Ok(())
    }

    fn check_radius(&self) -> Result<(), MetadataError> {
        let (lo, hi) = RADIUS_RANGE_M;
        match (self.domain, self.radius_m) {
            (Domain::Sphere, None) => Err(bad("radius_m", "a planet needs a radius")),
            (_, Some(r)) if !(r.is_finite() && (lo..=hi).contains(&r)) => Err(bad(
                "radius_m",
                format!("{r} is outside {lo} ..= {hi:e} metres"),
            )),
            _ => Ok(()),
        }
    }

    fn check_channels(&self) -> Result<(), MetadataError> {
        if self.channels.len() > MAX_CHANNELS {
            return Err(bad(
                "channels",
                format!("{} channels (at most {MAX_CHANNELS})", self.channels.len()),
            ));
        }
        let roots = match self.domain {
            Domain::Planar => 1,
            Domain::Sphere => 6,
        };
        let grid = (self.n as usize + 1).pow(2);
        for (c, ch) in self.channels.iter().enumerate() {
            let field = |name: &str| format!("channels[{c}].{name}");
            if !(ch.value_scale.is_finite() && ch.value_scale > 0.0) {
                return Err(bad(
                    field("value_scale"),
                    format!("{} is not a finite positive number", ch.value_scale),
                ));
            }
            if !ch.value_offset.is_finite() {
                return Err(bad(
                    field("value_offset"),
                    format!("{} is not finite", ch.value_offset),
                ));
            }
            if ch.steps.len() != self.levels as usize {
                return Err(bad(
                    field("steps"),
                    format!("{} entries for {} levels", ch.steps.len(), self.levels),
                ));
            }
            if ch.steps.contains(&0) {
                return Err(bad(field("steps"), "a step of 0"));
            }
            if ch.model.len() > MAX_MODEL_BYTES {
                return Err(bad(
                    field("model"),
                    format!("{} bytes (at most {MAX_MODEL_BYTES})", ch.model.len()),
                ));
            }
            if ch.roots.len() != roots {
                return Err(bad(
                    field("roots"),
                    format!(
                        "{} root grids; a {} repository has {roots}",
                        ch.roots.len(),
                        self.domain
                    ),
                ));
            }
            if let Some(r) = ch.roots.iter().find(|r| r.len() != grid) {
                return Err(bad(
                    field("roots"),
                    format!("a root grid of {} values, not (N+1)^2 = {grid}", r.len()),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::{Attribute, ChannelCoding, NodataHandling, NodataPolicy, Rate};

    /// A consistent 1025 x 1025 planar elevation record (N = 32: m = 10, 10 levels).
    fn good() -> Metadata {
        Metadata {
            format_version: 6,
            complete: true,
            content_hash: "ab".repeat(32),
            domain: Domain::Planar,
            m: 10,
            n: 32,
            levels: 10,
            attribute: Attribute {
                kind: AttributeKind::Elevation,
                units: "m".into(),
            },
            extent: [1025, 1025],
            nodata: NodataPolicy {
                source_count: 0,
                handling: NodataHandling::None,
            },
            georef: None,
            radius_m: None,
            channels: vec![ChannelCoding {
                name: "height".into(),
                value_scale: 0.5,
                value_offset: 0.0,
                steps: vec![256; 10],
                model: vec![1, 2, 3],
                roots: vec![vec![0; 33 * 33]],
                rate: Rate::Lossless,
            }],
            build: serde_json::json!({}),
            level_stats: vec![],
            coverage: None,
            inline_max_bytes: None,
            static_export: false,
        }
    }

    fn field_of(m: &Metadata) -> String {
        m.validate().unwrap_err().field
    }

    #[test]
    fn a_consistent_record_passes() {
        good().validate().unwrap();
        let mut planet = good();
        planet.domain = Domain::Sphere;
        planet.extent = [2048, 2048];
        planet.radius_m = Some(6.371e6);
        planet.channels[0].roots = vec![vec![0; 33 * 33]; 6];
        planet.levels = 12;
        planet.channels[0].steps = vec![256; 12];
        planet.validate().unwrap();
        let mut tiny = good();
        (tiny.extent, tiny.m, tiny.levels) = ([20, 20], 5, 0);
        tiny.channels[0].steps.clear();
        tiny.validate().unwrap();
    }

    #[test]
    fn each_field_out_of_range_is_named() {
        type Change = Box<dyn Fn(&mut Metadata)>;
        let cases: Vec<(&str, Change)> = vec![
            (
                "content_hash",
                Box::new(|m| m.content_hash = "a".repeat(1 << 20)),
            ),
            (
                "content_hash",
                Box::new(|m| m.content_hash = "G".repeat(64)),
            ),
            ("content_hash", Box::new(|m| m.content_hash.clear())),
            ("m", Box::new(|m| m.m = 0)),
            ("m", Box::new(|m| m.m = 49)),
            ("n", Box::new(|m| m.n = 0)),
            ("n", Box::new(|m| m.n = u32::MAX)),
            ("n", Box::new(|m| m.n = 24)),
            ("levels", Box::new(|m| m.levels = 0)),
            ("levels", Box::new(|m| m.levels = 4_000_000_000)),
            (
                "levels",
                Box::new(|m| {
                    m.levels = 12;
                    m.channels[0].steps = vec![256; 12];
                }),
            ),
            ("extent", Box::new(|m| m.extent = [0, 0])),
            ("extent", Box::new(|m| m.extent = [1 << 63, 1025])),
            ("extent", Box::new(|m| m.extent = [4097, 4097])),
            ("m", Box::new(|m| m.m = 11)),
            ("radius_m", Box::new(|m| m.radius_m = Some(f64::NAN))),
            ("radius_m", Box::new(|m| m.radius_m = Some(-1.0))),
            (
                "channels[0].steps",
                Box::new(|m| m.channels[0].steps.clear()),
            ),
            (
                "channels[0].steps",
                Box::new(|m| m.channels[0].steps = vec![256; 1_000_000]),
            ),
            (
                "channels[0].steps",
                Box::new(|m| m.channels[0].steps[3] = 0),
            ),
            (
                "channels[0].roots",
                Box::new(|m| m.channels[0].roots.clear()),
            ),
            (
                "channels[0].roots",
                Box::new(|m| m.channels[0].roots[0].truncate(5)),
            ),
            (
                "channels[0].value_scale",
                Box::new(|m| m.channels[0].value_scale = f64::NAN),
            ),
            (
                "channels[0].value_offset",
                Box::new(|m| m.channels[0].value_offset = f64::INFINITY),
            ),
            ("channels", Box::new(|m| m.channels.clear())),
            (
                "channels",
                Box::new(|m| m.channels = vec![m.channels[0].clone(); 4]),
            ),
            (
                "level_stats",
                Box::new(|m| m.level_stats = vec![Default::default(); 11]),
            ),
        ];
        for (field, change) in cases {
            let mut m = good();
            change(&mut m);
            assert_eq!(field_of(&m), field, "{:?}", m.validate());
            let text = m.validate().unwrap_err().to_string();
            assert!(text.contains(&format!("`{field}`")), "{text}");
            assert!(text.len() < 300, "the reason stays short: {}", text.len());
        }
        let mut planet = good();
        planet.domain = Domain::Sphere;
        planet.extent = [2048, 1024];
        assert_eq!(planet.check_limits().unwrap_err().field, "extent");
        planet.extent = [2048, 2048];
        planet.radius_m = None;
        assert_eq!(planet.check_limits().unwrap_err().field, "radius_m");
    }

    #[test]
    fn the_store_tier_leaves_codec_consistency_to_validate() {
        // The store's fixtures carry no channels and levels the codec would not derive.
        let mut m = good();
        m.channels.clear();
        m.levels = 3;
        m.check_limits().unwrap();
        assert_eq!(m.validate().unwrap_err().field, "levels");
    }
}
