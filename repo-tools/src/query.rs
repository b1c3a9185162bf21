//! `quincunx query`: heights (or colours) at latitude/longitude points of a planet.

use std::path::Path;

use anyhow::{Context, Result, bail};
use quincunx_store::Repository;

use crate::layout::Geometry;
use crate::{planet, verify};

/// Checks a query point: the latitude within -90..=90 degrees, the longitude finite (any
/// value: it wraps). The message names the coordinate that is wrong.
pub fn check_point(lat: f64, lon: f64) -> Result<(), String> {
    if !(-90.0..=90.0).contains(&lat) {
        return Err(format!(
            "latitude {lat} is out of range: give -90 to 90 degrees"
        ));
    }
    if !lon.is_finite() {
        return Err(format!("longitude {lon} is not a finite number of degrees"));
    }
    Ok(())
}

/// Runs `quincunx query`: one line (or JSON object) per point.
pub fn run(repo: &Path, points: &[(f64, f64)], json: bool) -> Result<()> {
    for &(lat, lon) in points {
        check_point(lat, lon).map_err(anyhow::Error::msg)?;
    }
    let repo = Repository::open(repo).with_context(|| format!("opening {}", repo.display()))?;
    let decoded = verify::decode_repository(&repo)?;
    let Geometry::Sphere(geom) = &decoded.geom else {
        bail!("latitude/longitude queries need a planet repository");
    };
    let channels: Vec<Vec<f64>> = (0..decoded.values.len())
        .map(|c| decoded.channel(c))
        .collect();
    let units = &repo.metadata().attribute.units;
    let mut out = Vec::new();
    for &(lat, lon) in points {
        let values: Vec<f64> = channels
            .iter()
            .map(|c| planet::query(geom, c, lat, lon))
            .collect();
        if json {
            out.push(serde_json::json!({"lat": lat, "lon": lon, "values": values, "units": units}));
        } else {
            outln!("{lat:.5} {lon:.5} {values:?} {units}");
        }
    }
    if json {
        outln!("{}", serde_json::Value::Array(out));
    }
    Ok(())
}
