//! Planets streamed end to end: the bundled ETOPO20 globe built as a planet repository,
//! served over loopback, streamed by `PlanetSession`.
//!
//! - a jump flight over the whole planet: every frame's cut is crack-free and covers all
//!   six faces once, every jump reaches full quality, and the final cut is bit-identical
//!   to refining with the repository read locally;
//! - the approach from two radii out down to a low view;
//! - numerical extremes: the camera 1 m above the surface (over a pole, a cube corner,
//!   a cube edge) and 100,000 km away: refinement converges with finite errors and a
//!   crack-free cut that reaches the repository's deepest level under the camera;
//! - `quincunx fly` on a planet.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::stream::{Local, Served, converge, cut_of, reference_cut, view_of};
use glam::DVec3;
use quincunx_client::dag::Dag;
use quincunx_client::domain::{Domain, World};
use quincunx_client::flight::{self, Flight, FlyOptions};
use quincunx_client::refine::{Refinement, SystemClock};
use quincunx_client::session::{PlanetSession, SessionConfig};
use quincunx_client::view::View;
use quincunx_codec::incremental::{Refiner, SphereRefiner};
use quincunx_repo_tools::args::RefineArgs;
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_repo_tools::fly::{self, FlyArgs};
use quincunx_store::Repository;

const REPO: &str = "earth";

/// Builds the bundled ETOPO20 grid as an Earth planet at 10 m RMS into
/// `dir/built/earth`, and a copy the test reads locally.
fn build_earth(dir: &Path) -> (PathBuf, PathBuf) {
    common::stream::built_and_local(dir, REPO, |built| {
        build::run(&BuildArgs {
            planet: true,
            rms_m: Some(10.0),
            overwrite: true,
            ..BuildArgs::new(
                common::workspace_root().join("data/etopo20_global.json"),
                built,
            )
        })
        .unwrap();
    })
}

#[test]
fn a_jump_flight_over_a_planet_is_crack_free_and_ends_on_the_local_cut() {
    let dir = tempfile::tempdir().unwrap();
    let (built, local) = build_earth(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let mut session = PlanetSession::open(&server.url(), REPO, SessionConfig::default()).unwrap();
    assert_eq!(session.dag().len(), 6, "six face roots");
    let flight = Flight::builtin_for("jump", &mut session, 5).unwrap();
    // Low views are above the planet's surface, within its height range: 300 m above a
    // conservative bound on its highest point (the warm-up's overview cut, refined by
    // sampling density, widened by its error bounds, which sum every level's departure:
    // 10.8 km here, against Everest's 8.8 km).
    let r = session.world().radius_m;
    let highest = session.height_range().1;
    for leg in &flight.legs {
        let alt = DVec3::from_array(leg.from.eye).length() - r;
        assert!((-11_000.0..15_000.0).contains(&alt), "{alt} ({highest} m)");
    }
    let opts = FlyOptions {
        check_every: 1,
        ..FlyOptions::default()
    };
    let report = flight::fly(&mut session, &flight, &opts, |f| {
        assert_eq!((f.cracks, f.coverage_errors), (0, 0), "{f:?}");
        assert!(f.max_error_px.is_finite());
    })
    .unwrap();
    assert_eq!(report.frames_checked, report.frames);
    assert_eq!((report.cracks, report.coverage_errors), (0, 0));
    assert_eq!(report.jumps.len(), 6);
    assert_eq!(report.jumps_unfinished, 0, "{report:?}");
    assert_eq!(report.failures, 0);
    assert!(report.bytes_in_final_cuts > 0 && report.bytes_fetched >= report.bytes_in_final_cuts);

    let last = view_of(&flight.legs.last().unwrap().from, &session.world());
    converge(&mut session, &last, Instant::now(), Duration::from_secs(30));
    let streamed = cut_of(session.dag());
    let snapshot = session.snapshot();
    assert_eq!(snapshot.patches.len(), streamed.len());
    let world = session.world();
    drop(session);
    server.kill();
    let expected = reference_cut::<SphereRefiner>(&local, REPO, &last, world);
    assert!(expected.len() > 50, "{}", expected.len());
    // Every half both cuts hold has the same grid, bit for bit. The cuts themselves may
    // differ slightly: a planet's bounding caps are not nested, so after other views a
    // refined diamond can stay refined for a visible child that wants refining while a
    // fresh refinement never reaches that child (docs/streaming.md).
    let n = snapshot.n;
    let mut common = 0;
    for (id, half, grid) in &streamed {
        if let Some(e) = expected.iter().find(|e| e.0 == *id && e.1 == *half) {
            let in_half = |g: &[i32]| -> Vec<i32> {
                (0..=n)
                    .flat_map(|i| (0..=n).map(move |j| (i, j)))
                    .filter(|&(i, j)| half.contains(i, j))
                    .map(|(i, j)| g[i * (n + 1) + j])
                    .collect()
            };
            assert_eq!(in_half(&e.2), in_half(grid), "{id:?} {half:?}");
            common += 1;
        }
    }
    assert!(
        common * 10 >= expected.len() * 8,
        "{common} of {} local halves streamed",
        expected.len()
    );
}

#[test]
fn the_approach_from_two_radii_out_reaches_full_quality_without_cracks() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _local) = build_earth(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let mut session = PlanetSession::open(&server.url(), REPO, SessionConfig::default()).unwrap();
    let flight = Flight::builtin_for("approach", &mut session, 2).unwrap();
    let r = session.world().radius_m;
    let first = DVec3::from_array(flight.legs[0].from.eye).length() - r;
    assert!(first > 1.5 * r, "{first}");
    let opts = FlyOptions {
        check_every: 4,
        ..FlyOptions::default()
    };
    let mut last_full = false;
    let report = flight::fly(&mut session, &flight, &opts, |f| {
        assert_eq!((f.cracks, f.coverage_errors), (0, 0), "{f:?}");
        last_full = f.full_quality;
    })
    .unwrap();
    assert!(report.frames_checked > 0);
    assert!(
        last_full,
        "the final low view is not at full quality: {report:?}"
    );
    server.kill();
}

/// Refines locally for `view` until converged (at most 200 frames of 50 ms).
fn converge_local(
    dag: &mut Dag<SphereRefiner>,
    local: &mut Local<SphereRefiner>,
    world: <SphereRefiner as Domain>::World,
    view: &View,
) -> usize {
    let mut refinement = Refinement::default();
    let clock = SystemClock(Instant::now());
    for frame in 0..200 {
        let s = refinement
            .update(dag, view, world, local, &clock, Duration::from_millis(50))
            .unwrap();
        assert!(s.max_error_px.is_finite(), "{s:?}");
        let check = dag.check_cut();
        assert!(check.ok(), "{check:?}");
        if s.converged {
            return frame;
        }
    }
    panic!("no convergence for {view:?}");
}

#[test]
fn numerical_extremes_one_metre_above_poles_corners_and_edges_and_far_away() {
    let dir = tempfile::tempdir().unwrap();
    let (_built, local_path) = build_earth(dir.path());
    let repo = Repository::open(&local_path).unwrap();
    let (refiner, world) = SphereRefiner::from_metadata(REPO, repo.metadata(), None).unwrap();
    // Horizon culling on, with a sphere below the deepest trench as the occluder.
    let world = SphereRefiner::with_lowest_height(world, -11_000.0);
    let refiner = Arc::new(refiner);
    let finest = refiner.detail_levels();
    let mut local = Local {
        repo,
        refiner: Arc::clone(&refiner),
    };
    let mut dag = Dag::new(Arc::clone(&refiner));
    let r = world.radius_m;
    let places = [
        ("north pole", DVec3::Z),
        ("south pole", DVec3::NEG_Z),
        ("cube corner", DVec3::ONE.normalize()),
        ("cube edge", DVec3::new(1.0, 0.0, -1.0).normalize()),
        ("Everest", lat_lon(27.99, 86.93)),
    ];
    for (name, d) in places {
        // 1 m above the highest the surface can be there, looking at the horizon.
        let ground = r + 9_000.0;
        let eye = d * (ground + 1.0);
        let tangent = d.any_orthonormal_vector();
        let view = View {
            eye,
            target: eye + tangent * 1_000.0 - d * 0.5,
            up: world.up(eye),
            fov_y_rad: 60f64.to_radians(),
            viewport_px: [1920, 1080],
            tolerance_px: 1.0,
        };
        converge_local(&mut dag, &mut local, world, &view);
        // The diamonds under the camera are the finest the repository has.
        let deepest = dag
            .nodes()
            .filter(|n| n.refined.is_some())
            .filter_map(|n| refiner.info(n.id).map(|i| i.level))
            .max()
            .unwrap();
        assert_eq!(deepest + 1, finest, "{name}");
        for node in dag.nodes() {
            let (bbox, spacing) =
                refiner.footprint(&world, node.id, &node.corners, (-11_000.0, 9_000.0));
            assert!(bbox.min.is_finite() && bbox.max.is_finite() && spacing > 0.0);
        }
    }
    // 100,000 km away: a handful of coarse diamonds, everything finite.
    let view = View {
        eye: DVec3::new(1.0, 2.0, 3.0).normalize() * 1e8,
        target: DVec3::ZERO,
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    };
    converge_local(&mut dag, &mut local, world, &view);
    assert!(dag.refined_len() <= 30, "{}", dag.refined_len());
    for p in dag.cut() {
        let node = dag.node(p.0).unwrap();
        let v = refiner
            .vertex_world(&world, p.0, 0, 0, node.grid[0])
            .unwrap();
        assert!(v.is_finite() && (v.length() - r).abs() < 12_000.0);
    }
}

fn lat_lon(lat: f64, lon: f64) -> DVec3 {
    let (lat, lon) = (lat.to_radians(), lon.to_radians());
    DVec3::new(lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin())
}

#[test]
fn quincunx_fly_streams_a_planet() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _local) = build_earth(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let args = FlyArgs {
        refine: RefineArgs {
            tolerance_px: 2.0,
            ..RefineArgs::default()
        },
        viewport: [1280, 720],
        check_every: 8,
        json: true,
        ..FlyArgs::new(server.url(), REPO, "low-flight")
    };
    fly::run(&args).unwrap();
    server.kill();
}
