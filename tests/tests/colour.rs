//! Colour layers streamed end to end: an elevation and a colour repository built from the
//! bundled data, served over loopback, matched at run time by one session.
//!
//! - the planar GSI pair (elevation 33x33 diamonds, colour 65x65: the colour is two
//!   levels shallower, so the graph refines it procedurally below its finest level): every
//!   frame of a jump flight is crack-free in heights and in colour, and every colour
//!   sample the cut holds at full resolution equals the whole-raster decode of the colour
//!   repository;
//! - the planet (ETOPO20 elevation, Blue Marble colour on a four times finer cube): the
//!   elevation is the shallower layer, and a low view refines beyond its deepest level;
//! - the error is `max(edge, texel)`: a colour layer with more texels per edge than the
//!   elevation has vertices refines the same view further;
//! - repositories that do not match are clear errors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::stream::{Served, converge, view_of};
use glam::DVec3;
use quincunx_client::domain::{Domain, World};
use quincunx_client::flight::Flight;
use quincunx_client::refine::{Metric, RefineConfig};
use quincunx_client::session::{PlanetSession, Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_codec::diamond::{PlanarDomain, SphereDomain};
use quincunx_codec::incremental::{PlanarRefiner, Refiner, SphereRefiner};
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_repo_tools::layout::{Geometry, load_channel};
use quincunx_server::RepoConfig;
use quincunx_store::Repository;

fn data(name: &str) -> PathBuf {
    common::workspace_root().join("data").join(name)
}

/// Builds `input` into `dir/name` with `args` on top of the defaults.
fn build(
    dir: &Path,
    name: &str,
    input: &str,
    args: impl FnOnce(BuildArgs) -> BuildArgs,
) -> PathBuf {
    let out = dir.join(name);
    build::run(&args(BuildArgs {
        overwrite: true,
        ..BuildArgs::new(data(input), &out)
    }))
    .unwrap();
    out
}

fn serve(repos: &[(&str, &Path)]) -> Served {
    Served::start(
        "127.0.0.1:0".parse().unwrap(),
        repos
            .iter()
            .map(|(name, path)| RepoConfig {
                name: (*name).into(),
                path: path.to_path_buf(),
            })
            .collect(),
    )
}

/// The colour repository decoded at full resolution: its geometry and Y, Co, Cg.
fn decode_colour(path: &Path) -> (Geometry, Vec<Vec<i32>>) {
    let repo = Repository::open(path).unwrap();
    let geom = Geometry::from_metadata(repo.metadata()).unwrap();
    let channels = (0..3)
        .map(|c| {
            geom.decode(&load_channel(&repo, &geom, c).unwrap())
                .unwrap()
        })
        .collect();
    (geom, channels)
}

/// Checks the colour every cut diamond at or below the colour repository's finest level
/// holds against the full decode, at each of its vertices that is a colour sample (the
/// procedural levels in between interpolate, keeping the samples). Returns the samples
/// compared.
fn colour_samples_match<R: Domain>(
    session: &Session<R>,
    decoded: &[Vec<i32>],
    index: impl Fn(R::Id, usize, usize) -> Option<usize>,
) -> usize {
    let dag = session.dag();
    let layer = dag.colour().expect("a colour layer");
    let channel = &layer.channels()[0];
    let nc = layer.n();
    let mut compared = 0;
    for (id, half) in dag.cut() {
        let node = dag.node(id).unwrap();
        let colour = node.colour.as_ref().expect("every cut diamond has colour");
        let final_values = channel.info(colour.id).is_none_or(|i| i.procedural);
        if !final_values {
            continue;
        }
        let mask = channel.info(colour.id).and_then(|i| i.mask);
        for i in 0..=nc {
            for j in 0..=nc {
                if !half.contains(i, j) || mask.as_ref().is_some_and(|m| !m.vertex(i, j)) {
                    continue;
                }
                let Some(k) = index(colour.id, i, j) else {
                    continue;
                };
                for (c, channel) in decoded.iter().enumerate() {
                    assert_eq!(
                        colour.grids[c][i * (nc + 1) + j],
                        channel[k],
                        "{id:?} colour {:?} ({i},{j}) channel {c}",
                        colour.id
                    );
                }
                compared += 1;
            }
        }
    }
    compared
}

#[test]
fn planar_colour_streams_crack_free_and_equals_the_decoded_imagery() {
    let dir = tempfile::tempdir().unwrap();
    let dem = build(dir.path(), "gsi", "fixture_gsi_dem_256.json", |a| {
        BuildArgs {
            max_error_m: Some(0.05),
            ..a
        }
    });
    let colour = build(dir.path(), "gsi_colour", "fixture_gsi_color_256.jpg", |a| {
        BuildArgs {
            colour: true,
            max_error_m: Some(4.0),
            ..a
        }
    });
    let (geom, decoded) = decode_colour(&colour);
    let Geometry::Planar(raster) = &geom else {
        panic!("planar")
    };
    let width = raster.width();
    let server = serve(&[("gsi", &dem), ("gsi_colour", &colour)]);
    let config = SessionConfig {
        spacing_m: Some(5.0),
        ..SessionConfig::default()
    };
    let mut session: Session =
        Session::open_with_colour(&server.url(), "gsi", "gsi_colour", config).unwrap();
    let layer = session.dag().colour().unwrap();
    assert_eq!(layer.n(), 64);
    // Same ground and size: the colour's 65x65 diamonds are two levels shallower.
    assert_eq!(
        layer.coded_levels() + 2,
        session.dag().refiner().detail_levels()
    );
    let domain = PlanarDomain::new(layer.channels()[0].domain().m()).unwrap();
    assert_eq!(session.colour().unwrap().0, "gsi_colour");
    // Positions come in id units times 2N: samples are the multiples of 2N.
    let index = |id, i, j| {
        let p = domain.vertex_position(id, 64, i, j).ok()?;
        if p.iter().any(|c| c % 128 != 0) {
            return None;
        }
        let (x, y) = (
            usize::try_from(p[0] / 128).ok()?,
            usize::try_from(p[1] / 128).ok()?,
        );
        (x < width && y < raster.height()).then_some(y * width + x)
    };
    let flight = Flight::builtin_for("jump", &mut session, 3).unwrap();
    let world = session.world();
    let start = Instant::now();
    let mut compared = 0;
    for leg in flight.legs.iter().filter(|l| l.jump).take(3) {
        let view = view_of(&leg.from, &world);
        // `converge` checks every frame's cut, colour included.
        converge(&mut session, &view, start, Duration::from_secs(60));
        let check = session.dag().check_cut();
        assert!(check.colour_shared > 0, "{check:?}");
        compared += colour_samples_match(&session, &decoded, index);
    }
    assert!(compared > 1000, "{compared} samples compared");
    // Both repositories were fetched and used.
    assert!(session.bytes_used() > 0);
    let snap = session.snapshot();
    assert_eq!(snap.colour_n, 64);
    assert!(snap.patches.iter().all(|p| p.colour.is_some()));
    let p = &snap.patches[0];
    let rgb = session
        .dag()
        .colour()
        .unwrap()
        .rgb(p.colour.as_ref().unwrap(), 0)
        .unwrap();
    assert!(rgb.iter().any(|&c| c > 0), "{rgb:?}");
    assert!(
        session
            .dag()
            .colour()
            .unwrap()
            .rgb(p.colour.as_ref().unwrap(), 65 * 65)
            .is_none()
    );
}

#[test]
fn a_planet_refines_its_elevation_procedurally_down_to_the_colour_depth() {
    let dir = tempfile::tempdir().unwrap();
    let earth = build(dir.path(), "earth", "etopo20_global.json", |a| BuildArgs {
        planet: true,
        rms_m: Some(10.0),
        ..a
    });
    // The colour on a cube four times finer: two levels deeper than the elevation.
    let colour = build(
        dir.path(),
        "earth_colour",
        "bmng_global_1080x540.jpg",
        |a| BuildArgs {
            planet: true,
            colour: true,
            face_side: Some(1024),
            rms_m: Some(4.0),
            ..a
        },
    );
    let (geom, decoded) = decode_colour(&colour);
    let Geometry::Sphere(cube) = &geom else {
        panic!("sphere")
    };
    let server = serve(&[("earth", &earth), ("earth_colour", &colour)]);
    let mut session: PlanetSession = Session::open_with_colour(
        &server.url(),
        "earth",
        "earth_colour",
        SessionConfig::default(),
    )
    .unwrap();
    let coded = 6; // ETOPO20 on 256-sample faces of 33x33 diamonds
    assert_eq!(session.dag().refiner().detail_levels(), coded);
    assert_eq!(session.dag().refiner().levels(), coded + 2);
    let layer = session.dag().colour().unwrap();
    assert_eq!(layer.coded_levels(), coded + 2);
    let domain = SphereDomain::new(layer.channels()[0].domain().m()).unwrap();
    let _ = layer;
    let index = |id, i, j| {
        let p = domain.vertex_position(id, 64, i, j).ok()?;
        if p.iter().any(|c| c % 128 != 0) {
            return None;
        }
        cube.point_indices(p.map(|c| c / 128)).next()
    };
    let start = Instant::now();
    assert!(session.warm_up(Duration::from_secs(20)).unwrap());
    // Low over the Himalaya, looking along the surface.
    let world = session.world();
    let dir = DVec3::new(0.0, 1.0, 0.55).normalize();
    let (_, high) = session.height_range_near(dir);
    let eye = dir * (world.radius_m + high + 2_000.0);
    let target = DVec3::new(0.2, 1.0, 0.5).normalize() * world.radius_m;
    let view = View {
        eye,
        target,
        up: world.up(eye),
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    };
    converge(&mut session, &view, start, Duration::from_secs(90));
    let dag = session.dag();
    let mut by_level: HashMap<usize, usize> = HashMap::new();
    for (id, _) in dag.cut() {
        let level = dag.refiner().info(id).map_or(coded + 2, |i| i.level);
        *by_level.entry(level).or_default() += 1;
    }
    let procedural: usize = by_level
        .iter()
        .filter(|(l, _)| **l > coded)
        .map(|(_, c)| c)
        .sum();
    assert!(
        procedural > 0,
        "the cut stays within the elevation's levels: {by_level:?}"
    );
    let compared = colour_samples_match(&session, &decoded, index);
    assert!(compared > 1000, "{compared} samples compared");
    let check = dag.check_cut();
    assert!(check.ok() && check.colour_shared > 0, "{check:?}");
}

/// Halves of the converged cut for `view`.
fn converged_halves(mut session: Session, view: &View) -> usize {
    converge(&mut session, view, Instant::now(), Duration::from_secs(60));
    session.dag().cut_len()
}

#[test]
fn texels_coarser_than_the_edges_refine_further() {
    let dir = tempfile::tempdir().unwrap();
    let dem = build(dir.path(), "gsi", "fixture_gsi_dem_256.json", |a| {
        BuildArgs {
            max_error_m: Some(0.05),
            ..a
        }
    });
    // 17x17 colour diamonds: one texel per two elevation edges, so the texels decide.
    let colour = build(
        dir.path(),
        "gsi_colour17",
        "fixture_gsi_color_256.jpg",
        |a| BuildArgs {
            colour: true,
            diamond_size: Some(17),
            max_error_m: Some(4.0),
            ..a
        },
    );
    let server = serve(&[("gsi", &dem), ("gsi_colour17", &colour)]);
    let view = View {
        eye: DVec3::new(128.0, 128.0, 600.0),
        target: DVec3::new(128.0, 129.0, 0.0),
        up: DVec3::Y,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 4.0,
    };
    let halves = |metric: Metric| {
        let config = SessionConfig {
            spacing_m: Some(1.0),
            refine: RefineConfig {
                metric,
                ..RefineConfig::default()
            },
            ..SessionConfig::default()
        };
        let plain: Session = Session::open(&server.url(), "gsi", config.clone()).unwrap();
        let coloured: Session =
            Session::open_with_colour(&server.url(), "gsi", "gsi_colour17", config).unwrap();
        assert_eq!(coloured.dag().texels_per_edge(), 0.5);
        (
            converged_halves(plain, &view),
            converged_halves(coloured, &view),
        )
    };
    // Sampling: halving the error scale needs two more levels, about four times the halves.
    let (a, b) = halves(Metric::Sampling);
    assert!(b >= 3 * a, "sampling: {a} halves without colour, {b} with");
    // Geometric: the texel rule refines where the heights alone would not.
    let (a, b) = halves(Metric::Geometric);
    assert!(b >= 2 * a, "geometric: {a} halves without colour, {b} with");
}

#[test]
fn repositories_that_do_not_match_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let dem = build(dir.path(), "gsi", "fixture_gsi_dem_256.json", |a| {
        BuildArgs {
            max_error_m: Some(0.5),
            ..a
        }
    });
    let colour = build(dir.path(), "gsi_colour", "fixture_gsi_color_256.jpg", |a| {
        BuildArgs {
            colour: true,
            max_error_m: Some(8.0),
            ..a
        }
    });
    let korea = dir.path().join("korea");
    common::build_bundled_korea(&korea);
    let earth = build(dir.path(), "earth", "etopo20_global.json", |a| BuildArgs {
        planet: true,
        rms_m: Some(20.0),
        ..a
    });
    let server = serve(&[
        ("gsi", &dem),
        ("gsi_colour", &colour),
        ("korea", &korea),
        ("earth", &earth),
    ]);
    let url = server.url();
    let open = |name: &str, colour: &str| {
        Session::<PlanarRefiner>::open_with_colour(&url, name, colour, SessionConfig::default())
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
    };
    let e = open("korea", "gsi_colour");
    assert!(e.contains("does not line up"), "{e}");
    let e = open("gsi", "gsi");
    assert!(e.contains("needs a colour repository"), "{e}");
    let e = Session::<SphereRefiner>::open_with_colour(
        &url,
        "earth",
        "gsi_colour",
        SessionConfig::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("domain"), "{e}");
    let e = Session::<PlanarRefiner>::open(&url, "gsi_colour", SessionConfig::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("colour layer"), "{e}");
}
