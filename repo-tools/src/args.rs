//! Argument groups shared by the subcommands that stream from a server (`fly`,
//! `loadtest`, `render`, `view`, `trade`): one definition, one help text and one parser
//! per flag, flattened into each command (`#[command(flatten)]`).

use clap::Args;
use quincunx_client::refine::Metric;

use crate::fly::{CaCert, parse_ca_cert};

/// Where to stream from: `--url`, `--ca-cert`, `--repo` and `--colour`.
#[derive(Args, Debug, Clone)]
pub struct ServerArgs {
    /// Server base URL, e.g. `http://127.0.0.1:8080` or `https://tiles.example.org`.
    #[arg(long)]
    pub url: String,
    /// A PEM file of CA certificates trusted for `https://` besides the system's.
    #[arg(long, value_parser = parse_ca_cert)]
    pub ca_cert: Option<CaCert>,
    /// Elevation repository name.
    #[arg(long)]
    pub repo: String,
    /// Colour repository matched to the elevation (same domain; depths and diamond sizes
    /// may differ).
    #[arg(long, visible_alias = "color")]
    pub colour: Option<String>,
}

impl ServerArgs {
    /// Repository `repo` at `url`, over the system's certificates, without colour.
    pub fn new(url: impl Into<String>, repo: impl Into<String>) -> ServerArgs {
        ServerArgs {
            url: url.into(),
            ca_cert: None,
            repo: repo.into(),
            colour: None,
        }
    }
}

/// What the tolerance bounds: `--tolerance-px` and `--metric`.
#[derive(Args, Debug, Clone, Copy)]
pub struct RefineArgs {
    /// Screen-space tolerance, pixels.
    #[arg(long, default_value_t = 1.0)]
    pub tolerance_px: f64,
    /// What the tolerance bounds: `geometric` (the projected error bound of the data: no
    /// point drawn more than about the tolerance from the full-resolution surface; with
    /// colour, texels at most the tolerance too) or `sampling` (projected grid spacing).
    #[arg(long, default_value_t = Metric::Geometric)]
    pub metric: Metric,
}

impl Default for RefineArgs {
    fn default() -> RefineArgs {
        RefineArgs {
            tolerance_px: 1.0,
            metric: Metric::Geometric,
        }
    }
}

impl RefineArgs {
    /// `Err` unless the tolerance is a positive number.
    pub fn check(&self) -> Result<(), String> {
        if self.tolerance_px.is_finite() && self.tolerance_px > 0.0 {
            Ok(())
        } else {
            Err(format!(
                "--tolerance-px {} must be positive",
                self.tolerance_px
            ))
        }
    }
}

/// Where one camera is and where it looks: `--lat-lon` or `--uv`, `--heading-deg`,
/// `--pitch-deg` and `--fov-deg` (its height is each command's own: `render` needs
/// one, `view` has a default).
#[derive(Args, Debug, Clone, Copy)]
pub struct CameraArgs {
    /// Planet: the point under the camera, `LAT,LON` in degrees (default 0,0).
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, conflicts_with = "uv")]
    pub lat_lon: Option<(f64, f64)>,
    /// Planar: the point under the camera, `U,V` fractions of the raster (0,0 = the
    /// north-west corner; default 0.5,0.5).
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true)]
    pub uv: Option<(f64, f64)>,
    /// Degrees clockwise from north.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub heading_deg: f64,
    /// Degrees above the horizon (-90 = straight down).
    #[arg(long, default_value_t = -90.0, allow_hyphen_values = true)]
    pub pitch_deg: f64,
    /// Vertical field of view, degrees.
    #[arg(long, default_value_t = 60.0)]
    pub fov_deg: f64,
}

/// Parses `A,B` (two numbers): `--uv`, `--lat-lon`.
pub fn parse_pair(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?} is not two numbers A,B"))?;
    let p = |t: &str| t.trim().parse::<f64>().map_err(|e| format!("{t:?}: {e}"));
    Ok((p(a)?, p(b)?))
}

/// Parses an emulated link `KBIT_S,RTT_MS` (a positive rate, a non-negative round trip).
pub fn parse_link(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?} is not KBIT_S,RTT_MS"))?;
    let parse = |t: &str| -> Result<f64, String> {
        let v: f64 = t.trim().parse().map_err(|e| format!("{t:?}: {e}"))?;
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(format!("{t:?} must be a non-negative number"))
        }
    };
    let (kbit, rtt) = (parse(a)?, parse(b)?);
    if kbit <= 0.0 {
        return Err("the link rate must be positive".into());
    }
    Ok((kbit, rtt))
}

/// An emulated link or none: what `--link` takes where it has a default (`trade`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EmulatedLink(pub Option<(f64, f64)>);

/// Parses `KBIT_S,RTT_MS` ([`parse_link`]) or `none`.
pub fn parse_link_or_none(s: &str) -> Result<EmulatedLink, String> {
    if s.trim().eq_ignore_ascii_case("none") {
        return Ok(EmulatedLink(None));
    }
    parse_link(s)
        .map(|l| EmulatedLink(Some(l)))
        .map_err(|e| format!("{e} (or none)"))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn links_parse_or_say_why_not() {
        assert_eq!(parse_link("4000,100"), Ok((4000.0, 100.0)));
        assert_eq!(parse_link_or_none("none"), Ok(EmulatedLink(None)));
        assert_eq!(
            parse_link_or_none(" 20000, 20"),
            Ok(EmulatedLink(Some((20000.0, 20.0))))
        );
        assert!(parse_link("0,100").unwrap_err().contains("positive"));
        assert!(parse_link("4000,-1").unwrap_err().contains("non-negative"));
        assert!(parse_link_or_none("fast").unwrap_err().contains("or none"));
        for bad in ["", "4000", "0,100", "-1,5", "x,1", "1,inf"] {
            assert!(parse_link_or_none(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_tolerance_is_checked() {
        assert!(RefineArgs::default().check().is_ok());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let r = RefineArgs {
                tolerance_px: bad,
                ..RefineArgs::default()
            };
            assert!(r.check().unwrap_err().contains("--tolerance-px"), "{bad}");
        }
    }
}
