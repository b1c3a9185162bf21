//! Repositories the web crate's tests build with the codec: rasters and planets of
//! smooth terrain with hashed noise, and holes where a test wants nodata.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{
    CubeGrid, EncodeOptions, Encoded, EncodedDomain, FromEncoded, Grid, RateMode,
};
use quincunx_codec::incremental::{PlanarRefiner, Refiner, SphereRefiner};
use quincunx_codec::sphere_raster::SphereGeometry;
use quincunx_meta::{
    Attribute, AttributeKind, ChannelCoding, Domain, Metadata, NodataHandling, NodataPolicy,
};

/// Encoder options: diamond size `n`, rate `mode`, `sparse` coverage.
pub fn options(n: usize, mode: RateMode, sparse: bool) -> EncodeOptions {
    EncodeOptions {
        n,
        mode,
        sparse,
        rdo: Default::default(),
    }
}

/// A smooth integer raster with hashed noise; `hole` marks nodata.
pub fn raster(w: usize, h: usize, seed: u64, hole: impl Fn(usize, usize) -> bool) -> Grid {
    let values_m = (0..w * h)
        .map(|k| {
            let (x, y) = (k % w, k / w);
            if hole(x, y) {
                return f64::NAN;
            }
            let (fx, fy) = (x as f64, y as f64);
            let noise = ((k as u64 + seed) * 7919 % 13) as f64;
            // `+ 0.0`: no negative zeros.
            (300.0 * (fx / 17.0 + seed as f64).sin() * (fy / 23.0).cos() + 0.5 * fx + noise).round()
                + 0.0
        })
        .collect();
    Grid {
        width: w,
        height: h,
        values_m,
        quantum_m: Some(1.0),
    }
}

/// A planet of smooth continents plus hashed noise (a function of the cube point, so
/// edge copies agree); NaN where `hole` says so of the unit direction; `shift` varies the
/// values (colour channels).
pub fn planet(face_side: usize, n: usize, shift: f64, hole: impl Fn([f64; 3]) -> bool) -> CubeGrid {
    let geom = SphereGeometry::new(face_side, n).unwrap();
    let w = face_side + 1;
    let mut values_m = vec![0.0; geom.cube_len()];
    for face in 0..6u8 {
        for v in 0..w {
            for u in 0..w {
                let p = geom.sample_position(face, u, v);
                let q = cube_to_unit_sphere(p.map(|c| c as f64));
                let [x, y, z] = q;
                let hash = (p[0].wrapping_mul(73_856_093)
                    ^ p[1].wrapping_mul(19_349_663)
                    ^ p[2].wrapping_mul(83_492_791))
                .rem_euclid(17);
                let smooth = 2500.0 * (3.0 * x + 1.0 + shift).sin() * (2.0 * y).cos()
                    + 900.0 * (5.0 * z + 0.5).sin();
                values_m[geom.cube_index(face, u, v)] = if hole(q) {
                    f64::NAN
                } else {
                    (smooth * (1.0 + shift) + hash as f64).round() + 0.0
                };
            }
        }
    }
    CubeGrid {
        face_side,
        values_m,
        quantum_m: Some(1.0),
    }
}

/// Metadata of a repository (the fields a build writes; blob statistics filled in by
/// the test).
#[allow(clippy::too_many_arguments)]
pub fn metadata(
    domain: Domain,
    m: u32,
    n: usize,
    levels: usize,
    extent: [u64; 2],
    channels: Vec<ChannelCoding>,
    coverage: Option<Vec<u8>>,
    inline_max_bytes: Option<u32>,
) -> Metadata {
    let colour = channels.len() == 3;
    Metadata {
        format_version: 6,
        complete: true,
        content_hash: "ab".repeat(32),
        domain,
        m,
        n: n as u32,
        levels: levels as u32,
        attribute: Attribute {
            kind: if colour {
                AttributeKind::Colour
            } else {
                AttributeKind::Elevation
            },
            units: if colour { "srgb8" } else { "m" }.into(),
        },
        extent,
        nodata: NodataPolicy {
            source_count: 0,
            handling: NodataHandling::None,
        },
        georef: None,
        radius_m: (domain == Domain::Sphere).then_some(6.371e6),
        channels,
        build: serde_json::json!({}),
        level_stats: Vec::new(),
        coverage,
        inline_max_bytes,
        static_export: false,
    }
}

/// The domain, `m`, detail levels and extent of an encoded channel.
pub fn geometry_of(e: &Encoded) -> (Domain, u32, usize, [u64; 2]) {
    match e.domain {
        EncodedDomain::Planar { width, height } => {
            let r = PlanarRefiner::from_encoded(e).unwrap();
            let extent = [width as u64, height as u64];
            (Domain::Planar, r.domain().m(), r.detail_levels(), extent)
        }
        EncodedDomain::Sphere { face_side } => {
            let r = SphereRefiner::from_encoded(e).unwrap();
            let extent = [face_side as u64; 2];
            (Domain::Sphere, r.domain().m(), r.detail_levels(), extent)
        }
    }
}

/// The wall clock, for calls that time themselves.
pub struct Wall(pub std::time::Instant);

impl quincunx_client_core::refine::Clock for Wall {
    fn now(&self) -> std::time::Duration {
        self.0.elapsed()
    }
}
