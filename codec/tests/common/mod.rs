//! Shared helpers of the integration tests: where the data lives, how to read it, how to
//! measure errors.
//!
//! Bundled data (`data/` at the repository root) is always present. Shared data lives in
//! `$QUINCUNX_SHARED_DATA` or `../shared/data` beside the repository; tests that need it
//! print `SKIP <test>: <reason>` and return when it is absent.

// Each test crate uses a different subset of these helpers.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{CubeGrid, Grid, RawType};
use quincunx_codec::sphere_raster::SphereGeometry;

/// The bundled data directory (`<repo>/data`).
pub fn bundled_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data")
}

/// The bundled Korea crop's sidecar.
pub fn bundled_korea() -> PathBuf {
    bundled_dir().join("korea_srtm3_1025.json")
}

/// The shared data directory: `$QUINCUNX_SHARED_DATA`, else `<repo>/../shared/data`.
pub fn shared_dir() -> PathBuf {
    match std::env::var_os("QUINCUNX_SHARED_DATA") {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    }
}

/// A file of the shared data directory, or `None` after printing why the test is skipped
/// (a failure instead with `REQUIRE_SHARED_DATA=1`, which CI sets).
pub fn shared_file(test: &str, name: &str) -> Option<PathBuf> {
    let path = shared_dir().join(name);
    if path.is_file() {
        Some(path)
    } else {
        skip_without_shared_data(
            test,
            &format!(
                "{} not found (set QUINCUNX_SHARED_DATA to the shared data directory)",
                path.display()
            ),
        );
        None
    }
}

/// Prints `SKIP <test>: <why>`, or fails the test when `REQUIRE_SHARED_DATA=1`.
pub fn skip_without_shared_data(test: &str, why: &str) {
    quincunx_testkit::skip::skip(test, "REQUIRE_SHARED_DATA", why);
}

/// Reads a grid in the shared data format (raw little-endian int16/float32 + JSON sidecar).
/// Also used by `examples/rd.rs` and the benches.
pub fn load_grid(sidecar: &Path) -> Result<Grid, String> {
    let text =
        std::fs::read_to_string(sidecar).map_err(|e| format!("{}: {e}", sidecar.display()))?;
    let meta: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", sidecar.display()))?;
    let width = meta["width"].as_u64().ok_or("sidecar: missing width")? as usize;
    let height = meta["height"].as_u64().ok_or("sidecar: missing height")? as usize;
    let dtype = meta["dtype"].as_str().ok_or("sidecar: missing dtype")?;
    let file = meta["file"].as_str().ok_or("sidecar: missing file")?;
    let scale = meta["vertical_scale"].as_f64().unwrap_or(1.0);
    let offset = meta["vertical_offset"].as_f64().unwrap_or(0.0);
    let nodata = meta["nodata"].as_f64();
    let ty = RawType::from_dtype(dtype).ok_or(format!("unsupported dtype {dtype}"))?;
    let path = sidecar.with_file_name(file);
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    Grid::from_raw_le(width, height, ty, &bytes, scale, offset, nodata)
        .map_err(|e| format!("{}: {e}", path.display()))
}

/// Loads a grid, panicking with the reason (tests only).
pub fn grid(sidecar: &Path) -> Grid {
    load_grid(sidecar).unwrap_or_else(|e| panic!("cannot load {}: {e}", sidecar.display()))
}

/// The top-left `w x h` samples of the bundled Korea crop (sizes that are not a power of
/// two plus one give border diamonds masks).
pub fn bundled_korea_crop(w: usize, h: usize) -> Grid {
    let mut g = grid(&bundled_korea());
    g.values_m = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| g.values_m[y * g.width + x])
        .collect();
    g.width = w;
    g.height = h;
    g
}

/// Measured errors of a decode over the valid (non-NaN) samples of the original.
#[derive(Clone, Copy, Debug)]
pub struct Errors {
    /// Root-mean-square error, metres.
    pub rms_m: f64,
    /// Largest absolute error, metres.
    pub max_abs_m: f64,
    /// Valid samples whose decoded value is not bit-identical to the original.
    pub inexact: usize,
    /// Valid samples compared.
    pub valid: usize,
}

/// Compares decoded metres with the original grid on its valid samples.
pub fn errors(original: &Grid, decoded_m: &[f64]) -> Errors {
    assert_eq!(
        decoded_m.len(),
        original.values_m.len(),
        "decoded sample count"
    );
    let (mut sum, mut max, mut inexact, mut valid) = (0.0f64, 0.0f64, 0usize, 0usize);
    for (&d, &v) in decoded_m.iter().zip(&original.values_m) {
        if v.is_nan() {
            continue;
        }
        valid += 1;
        if d.to_bits() != v.to_bits() {
            inexact += 1;
        }
        let e = (d - v).abs();
        // A NaN decode must count as an error, not vanish in `max`.
        let e = if e.is_nan() { f64::INFINITY } else { e };
        sum += e * e;
        max = max.max(e);
    }
    Errors {
        rms_m: (sum / valid.max(1) as f64).sqrt(),
        max_abs_m: max,
        inexact,
        valid,
    }
}

/// A synthetic planet in integer metres: smooth continents and ridges on the sphere plus
/// up to 16 m of hashed noise. Values are a function of the cube point, so the copies of
/// edge and corner points agree.
pub fn synthetic_planet(face_side: usize, n: usize) -> Result<CubeGrid, String> {
    let geom = SphereGeometry::new(face_side, n).map_err(|e| e.to_string())?;
    let w = face_side + 1;
    let mut values_m = vec![0.0; geom.cube_len()];
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let p = geom.sample_position(face, u, v);
                let [x, y, z] = cube_to_unit_sphere(p.map(|c| c as f64));
                let smooth = 2500.0 * (3.0 * x + 1.0).sin() * (2.0 * y).cos()
                    + 900.0 * (5.0 * z + 0.5).sin()
                    + 350.0 * (13.0 * x * y + 7.0 * z).sin();
                let hash = (p[0].wrapping_mul(73_856_093)
                    ^ p[1].wrapping_mul(19_349_663)
                    ^ p[2].wrapping_mul(83_492_791))
                .rem_euclid(17);
                values_m[geom.cube_index(face, u, v)] = (smooth + hash as f64).round();
            }
        }
    }
    Ok(CubeGrid {
        face_side,
        values_m,
        quantum_m: Some(1.0),
    })
}

/// A planar refiner of a `w x h` raster for geometry queries: identity steps, the default
/// model and a zero root grid (frames, masks and ids, no real data).
#[allow(clippy::unwrap_used)]
pub fn planar_refiner(
    w: usize,
    h: usize,
    n: usize,
    coverage: Option<&quincunx_codec::coverage::Coverage>,
) -> quincunx_codec::incremental::PlanarRefiner {
    let levels = quincunx_codec::raster::RasterFrame::new(w, h, n, None)
        .unwrap()
        .detail_levels();
    quincunx_codec::incremental::PlanarRefiner::new(
        w,
        h,
        n,
        coverage,
        vec![256; levels],
        quincunx_codec::entropy::CodecModel::default(),
        vec![0; (n + 1) * (n + 1)],
    )
    .unwrap()
}
