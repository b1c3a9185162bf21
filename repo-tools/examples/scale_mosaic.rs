//! Writes a seeded synthetic planet mosaic for the scale benchmark (`benches/scale/`):
//! ETOPO5 refined with fractal detail, as one-degree raw `int16` tiles (+ JSON sidecars)
//! between 56°S and 60°N, SRTM's limits, so the polar caps are holes.
//!
//! ```sh
//! cargo run --release -p quincunx-repo-tools --example scale_mosaic -- \
//!     ../shared/data/etopo5_global.json <out-dir> <samples-per-degree> [seed]
//! ```
//!
//! Heights: ETOPO5's bilinear surface plus value-noise fBm (seven octaves, wavelengths
//! from 1/2 degree down by halves, amplitude 300 m at the coarsest falling by 0.55 an
//! octave), a pure function of the latitude, longitude and seed: tiles share their edge
//! samples exactly, and the same arguments write the same bytes. Prints one JSON line:
//! tiles, samples, bytes, seconds.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use quincunx_repo_tools::input;
use quincunx_repo_tools::planet::Equirect;
use rayon::prelude::*;

/// SRTM's latitude limits: tiles' south edges from 56°S to 59°N.
const SOUTH: i32 = -56;
const NORTH: i32 = 60;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: scale_mosaic <etopo5.json> <out-dir> <samples-per-degree> [seed]");
        std::process::exit(2);
    }
    let source = input::read_heights(Path::new(&args[1])).unwrap();
    let out = PathBuf::from(&args[2]);
    let per_degree: usize = args[3].parse().expect("samples per degree");
    let seed: u64 = args.get(4).map_or(1, |s| s.parse().expect("seed"));
    assert!(per_degree >= 2, "at least 2 samples per degree");
    std::fs::create_dir_all(&out).unwrap();
    let g = &source.grid;
    let base = Equirect::new(
        g.width,
        g.height,
        &g.values_m,
        source.georef.as_ref().unwrap(),
    )
    .unwrap();
    let started = Instant::now();
    let tiles: Vec<(i32, i32)> = (SOUTH..NORTH)
        .flat_map(|lat| (-180..180).map(move |lon| (lat, lon)))
        .collect();
    let side = per_degree + 1;
    let bytes: u64 = tiles
        .par_iter()
        .map(|&(lat, lon)| write_tile(&out, &base, lat, lon, per_degree, seed))
        .sum();
    let samples = tiles.len() * side * side;
    println!(
        "{{\"tiles\":{},\"tile_side\":{side},\"samples\":{samples},\"bytes\":{bytes},\"seconds\":{:.2},\"seed\":{seed}}}",
        tiles.len(),
        started.elapsed().as_secs_f64()
    );
}

/// Writes the tile whose south-west corner is (`lat`, `lon`); returns its bytes.
fn write_tile(out: &Path, base: &Equirect<'_>, lat: i32, lon: i32, k: usize, seed: u64) -> u64 {
    let side = k + 1;
    let mut data = Vec::with_capacity(side * side * 2);
    for r in 0..side {
        let y = f64::from(lat + 1) - r as f64 / k as f64;
        for c in 0..side {
            let x = f64::from(lon) + c as f64 / k as f64;
            let h = base.sample(y, x) + fbm(y, x, seed);
            let v = h.round().clamp(-32767.0, 32767.0) as i16;
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let name = format!(
        "{}{:02}{}{:03}",
        if lat < 0 { 'S' } else { 'N' },
        lat.unsigned_abs(),
        if lon < 0 { 'W' } else { 'E' },
        lon.unsigned_abs()
    );
    std::fs::write(out.join(format!("{name}.i16")), &data).unwrap();
    let sidecar = serde_json::json!({
        "file": format!("{name}.i16"),
        "width": side,
        "height": side,
        "dtype": "int16",
        "nodata": null,
        "crs": "EPSG:4326",
        "registration": "node",
        "georef": {"west": lon, "east": lon + 1, "south": lat, "north": lat + 1},
        "source": "quincunx scale_mosaic: ETOPO5 bilinear + value-noise fBm",
    });
    std::fs::write(out.join(format!("{name}.json")), sidecar.to_string()).unwrap();
    data.len() as u64
}

/// Fractal detail in metres at a latitude/longitude (degrees).
fn fbm(lat: f64, lon: f64, seed: u64) -> f64 {
    let (mut sum, mut amplitude, mut frequency) = (0.0, 300.0, 2.0);
    for octave in 0..7u64 {
        // Lattice cells per 360 degrees of longitude: the noise wraps the antimeridian.
        let period = (360.0 * frequency) as i64;
        sum += amplitude
            * value_noise(
                lat * frequency,
                lon * frequency,
                period,
                seed ^ (octave << 56),
            );
        amplitude *= 0.55;
        frequency *= 2.0;
    }
    sum
}

/// Smooth value noise in [-1, 1] on the unit lattice, periodic in `x` with `period`.
fn value_noise(y: f64, x: f64, period: i64, seed: u64) -> f64 {
    let (y0, x0) = (y.floor(), x.floor());
    let (fy, fx) = (smooth(y - y0), smooth(x - x0));
    let (iy, ix) = (y0 as i64, x0 as i64);
    let at = |dy: i64, dx: i64| lattice(iy + dy, (ix + dx).rem_euclid(period), seed);
    let top = at(0, 0) * (1.0 - fx) + at(0, 1) * fx;
    let bottom = at(1, 0) * (1.0 - fx) + at(1, 1) * fx;
    top * (1.0 - fy) + bottom * fy
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// A lattice value in [-1, 1] (splitmix64 of the point and seed).
fn lattice(y: i64, x: i64, seed: u64) -> f64 {
    let mut z = seed
        .wrapping_add((y as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
        .wrapping_add((x as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}
