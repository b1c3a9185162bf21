//! The image-error measures (`quincunx_render::error`) on rendered frames of the bundled
//! repositories, streamed from a real server to full quality and drawn offscreen with
//! lavapipe: one planar view (korea, oblique, 1920 x 1080) and two of the planet (earth,
//! oblique with the limb in view, and the whole disc over a cube corner):
//!
//! - the depth read back is 0 exactly where the background shows, and each terrain
//!   pixel unprojects to a point within a small bound of the cut's surface
//!   (`SurfaceIndex::along`, which `surface_height_m` agrees with);
//! - a frame against its own cut with its own depth measures exactly 0, its PSNR is
//!   infinite; without the reference depth only the depth's quantisation is left
//!   (p99 < 1e-3 px);
//! - against the same cut raised by a known height, every pixel's error is the
//!   projection of that height step (within 1 %): a known answer on real terrain;
//! - the geometric refinement metric keeps its promise on screen: views refined at 1 and
//!   4 px measure a geometric error (against the full-resolution reference of the same
//!   view) of at most the tolerance, on korea and on the planet.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use common::stream::Served;
use glam::DVec3;
use quincunx_client::refine::{Metric, RefineConfig};
use quincunx_client::session::{PlanetSession, Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_render::domain::{Geometry, RenderDomain};
use quincunx_render::error::error_map;
use quincunx_render::ground::surface_height_m;
use quincunx_render::offscreen::{OFFSCREEN_FORMAT, gpu_for_test};
use quincunx_render::renderer::{RendererConfig, TerrainRenderer};
use quincunx_render::scene::{Place, Shot, stream_to};
use quincunx_render::{
    Camera, DepthImage, Gpu, Image, Offscreen, SurfaceIndex, geometric_error, psnr_db, unproject,
};
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_server::RepoConfig;

/// Streaming limit per view.
const WAIT: Duration = Duration::from_secs(180);
/// Pure magenta: no height tint is this.
const MAGENTA: [u8; 3] = [255, 0, 255];

fn served() -> &'static Served {
    static SERVED: OnceLock<Served> = OnceLock::new();
    SERVED.get_or_init(|| {
        let dir = target_dir().join("image-error-repos");
        let korea = dir.join("korea");
        common::build_bundled_korea(&korea);
        let earth = dir.join("earth");
        build::run(&BuildArgs {
            planet: true,
            max_error_m: Some(2.0),
            overwrite: true,
            bounds: build::Bounds::Measured,
            ..BuildArgs::new(
                common::workspace_root().join("data/etopo20_global.json"),
                &earth,
            )
        })
        .unwrap();
        // The geometric metric's promise is checked on measured bounds (what `--bounds
        // measured` and `quincunx demo` write).
        quincunx_repo_tools::bounds::tighten(&korea, quincunx_repo_tools::bounds::TILE_SAMPLES)
            .unwrap();
        let repos = [("korea", korea), ("earth", earth)]
            .into_iter()
            .map(|(name, path)| RepoConfig {
                name: name.into(),
                path,
            })
            .collect();
        Served::start("127.0.0.1:0".parse().unwrap(), repos)
    })
}

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| common::workspace_root().join("target"))
}

/// A frame streamed to full quality: its camera, pixels, depth, and the index of the
/// cut it drew.
struct Frame {
    view: View,
    camera: Camera,
    image: Image,
    depth: DepthImage,
    index: SurfaceIndex,
}

fn frame<R: RenderDomain>(gpu: &Gpu, session: &mut Session<R>, shot: &Shot) -> Frame {
    let config = RendererConfig {
        colour_format: OFFSCREEN_FORMAT,
        ..RendererConfig::default()
    };
    // A new renderer takes the whole cut.
    session.restart_cut_changes();
    let mut renderer = TerrainRenderer::for_session(&gpu.device, session, config).unwrap();
    let (view, streamed) =
        stream_to(session, shot, WAIT, Some((&mut renderer, &gpu.queue))).unwrap();
    assert!(streamed.full_quality, "{shot:?}: not at full quality");
    draw(gpu, session, renderer, &view, shot)
}

/// A frame of `view` streamed to convergence (every frame's cut checked).
fn frame_at<R: RenderDomain>(gpu: &Gpu, session: &mut Session<R>, view: &View) -> Frame {
    let config = RendererConfig {
        colour_format: OFFSCREEN_FORMAT,
        gpu_budget_bytes: 4 << 30,
        ..RendererConfig::default()
    };
    common::stream::converge(session, view, Instant::now(), WAIT);
    session.restart_cut_changes();
    let renderer = TerrainRenderer::for_session(&gpu.device, session, config).unwrap();
    let shot = Shot {
        size: view.viewport_px,
        ..Shot::default()
    };
    draw(gpu, session, renderer, view, &shot)
}

/// Draws the session's cut from `view` offscreen and reads back pixels and depth.
fn draw<R: RenderDomain>(
    gpu: &Gpu,
    session: &mut Session<R>,
    mut renderer: TerrainRenderer<R>,
    view: &View,
    shot: &Shot,
) -> Frame {
    let camera = Camera::from_view(view);
    renderer.sync(session).unwrap();
    let mut stats = renderer.prepare(&gpu.queue, &camera);
    while stats.pending > 0 {
        stats = renderer.prepare(&gpu.queue, &camera);
    }
    assert_eq!(stats.missing, 0, "{shot:?}: patches not drawn");
    let offscreen = Offscreen::new(gpu, shot.size).unwrap();
    offscreen
        .render(gpu, MAGENTA, |pass| renderer.draw(pass))
        .unwrap();
    let index = SurfaceIndex::new(session);
    assert_eq!(index.skipped(), 0);
    assert_eq!(
        index.patches(),
        stats.patches,
        "the index holds the drawn cut"
    );
    let depth = offscreen.read_depth(gpu).unwrap();
    // The one-off height query meets the same triangles as the index.
    let mut checked = 0;
    for k in (0..depth.data.len()).step_by(97) {
        let (x, y) = (k as u32 % shot.size[0], k as u32 / shot.size[0]);
        let Some(p) = unproject(&camera, shot.size, x, y, depth.data[k]) else {
            continue;
        };
        let r = index.along(p, index.up(p)).unwrap();
        let h = surface_height_m(session, p).unwrap();
        let want = match index.world().geometry {
            Geometry::Planet { radius_m, .. } => r.length() - radius_m,
            Geometry::Planar { .. } => r.z,
        };
        assert!(
            (h - want).abs() < 1e-6,
            "({x}, {y}): {h} m, the index {want} m"
        );
        checked += 1;
    }
    assert!(checked > 100);
    Frame {
        view: *view,
        camera,
        image: offscreen.read(gpu).unwrap(),
        depth,
        index,
    }
}

/// The checks of the module docs on one frame; `raise_m`: the known height step.
fn check(name: &str, f: &Frame, raise_m: f64) {
    let [w, h] = f.camera.viewport_px;
    assert_eq!((f.depth.width, f.depth.height), (w, h));
    // Depth 0 exactly where the background shows; terrain points on the cut's surface.
    let (mut terrain, mut off) = (0usize, Vec::new());
    for y in 0..h {
        for x in 0..w {
            let d = f.depth.at(x, y).unwrap();
            let background = f.image.pixel(x, y)[..3] == MAGENTA;
            assert_eq!(d == 0.0, background, "{name} ({x}, {y}): depth {d}");
            if background {
                continue;
            }
            terrain += 1;
            let p = unproject(&f.camera, [w, h], x, y, d).unwrap();
            let r = f.index.along(p, f.index.up(p)).unwrap_or_else(|| {
                panic!("{name} ({x}, {y}): no surface along the up through {p}")
            });
            off.push((p - r).length() / (p - f.camera.eye).length());
        }
    }
    off.sort_by(f64::total_cmp);
    let (p99, max) = (off[off.len() * 99 / 100], off[off.len() - 1]);
    println!(
        "{name}: {terrain} terrain pixels of {}, unprojected within {p99:.2e} (p99), \
         {max:.2e} (max) of their distance from the cut",
        w * h
    );
    assert!(terrain > (w * h / 4) as usize, "{name}: too little terrain");
    // Depth quantisation leaves about 1e-7 of the distance; the worst are silhouette
    // pixels, where the rasteriser (vertices snapped to its subpixel grid) lets a crest
    // cover a pixel centre that the f64 ray passes just above (korea: 0.6 m at 20 km).
    assert!(p99 < 1e-6 && max < 1e-3, "{name}: {p99:.3e} {max:.3e}");

    // Against itself.
    assert_eq!(psnr_db(&f.image, &f.image).unwrap(), f64::INFINITY);
    let same = geometric_error(&f.camera, &f.depth, Some(&f.depth), &f.index).unwrap();
    assert_eq!(same.pixels, terrain, "{name}: {same:?}");
    assert_eq!(same.pixels_without_reference, 0);
    assert_eq!((same.max_px, same.mean_px), (0.0, 0.0), "{name}: {same:?}");
    let start = Instant::now();
    let quantised = geometric_error(&f.camera, &f.depth, None, &f.index).unwrap();
    let seconds = start.elapsed().as_secs_f64();
    println!("{name}: without the reference depth {quantised:?} ({seconds:.3} s)");
    assert_eq!(quantised.pixels, terrain, "{name}: {quantised:?}");
    assert_eq!(quantised.pixels_without_reference, 0);
    assert!(quantised.p99_px < 1e-3, "{name}: {quantised:?}");

    // Against the cut raised by `raise_m`, pixel by pixel: the reference point moves by
    // that step along the up, so the error is the projection of `R0 + step - X` (`R0`
    // the unraised reference point), and, where X lies on the cut (all but silhouette
    // pixels, which the rasteriser's vertex snapping moves), that of the step itself.
    let quantised_px = error_map(&f.camera, &f.depth, None, &f.index).unwrap();
    let raised = f.index.clone().with_offset_m(raise_m).unwrap();
    let map = error_map(&f.camera, &f.depth, None, &raised).unwrap();
    let (mut worst_r0, mut worst_step, mut largest, mut off_cut) = (0.0f64, 0.0f64, 0.0f64, 0);
    for y in 0..h {
        for x in 0..w {
            let k = (y * w + x) as usize;
            let Some(p) = unproject(&f.camera, [w, h], x, y, f.depth.data[k]) else {
                assert!(map.error_px[k].is_nan());
                continue;
            };
            let up = f.index.up(p);
            let r0 = f.index.along(p, up).unwrap();
            let px = |q: DVec3| {
                let a = f.camera.project(p).unwrap();
                let b = f.camera.project(q).unwrap();
                (a[0] - b[0]).hypot(a[1] - b[1])
            };
            let got = map.error_px[k];
            assert!(got.is_finite(), "{name} ({x}, {y}): {got}");
            let want = px(r0 + up * raise_m);
            // Relative, or to 0.01 px where the step points at the camera (the nadir).
            worst_r0 = worst_r0.max((got - want).abs() / want.max(0.01));
            if quantised_px.error_px[k] < 1e-3 {
                let step = px(p + up * raise_m);
                worst_step = worst_step.max((got - step).abs() / step.max(0.01));
            } else {
                off_cut += 1;
            }
            largest = largest.max(want);
        }
    }
    let s = map.summary();
    println!(
        "{name}: raised {raise_m} m: {s:?}; steps up to {largest:.3} px; measured within \
         {:.2e} of the raised reference points' projection, within {:.2e} of the step's \
         ({off_cut} silhouette pixels left out)",
        worst_r0, worst_step
    );
    assert!(s.pixels == terrain && s.p50_px > 0.5, "{name}: {s:?}");
    assert!(worst_r0 < 0.01, "{name}: {worst_r0:.3e}");
    assert!(worst_step < 0.01, "{name}: {worst_step:.3e}");
    assert!(
        off_cut * 1000 < terrain,
        "{name}: {off_cut} pixels off the cut"
    );
}

#[test]
fn korea_oblique_errors_are_zero_against_itself_and_the_step_raised() {
    let Some(gpu) =
        gpu_for_test("korea_oblique_errors_are_zero_against_itself_and_the_step_raised").unwrap()
    else {
        return;
    };
    let mut session: Session =
        Session::open(&served().url(), "korea", SessionConfig::default()).unwrap();
    let shot = Shot {
        place: Place::Uv(0.5, 0.8),
        height_m: 3_000.0,
        pitch_deg: -25.0,
        size: [1920, 1080],
        ..Shot::default()
    };
    let f = frame(&gpu, &mut session, &shot);
    check("korea oblique", &f, 50.0);
}

#[test]
fn earth_errors_are_zero_against_itself_and_the_step_raised() {
    let Some(gpu) =
        gpu_for_test("earth_errors_are_zero_against_itself_and_the_step_raised").unwrap()
    else {
        return;
    };
    let mut session =
        PlanetSession::open(&served().url(), "earth", SessionConfig::default()).unwrap();
    for (name, place, height_m, pitch_deg, raise_m) in [
        (
            "earth oblique",
            Place::LatLon(36.0, 128.0),
            2_000_000.0,
            -50.0,
            20_000.0,
        ),
        // Over a cube corner: three faces meet under the camera.
        (
            "earth whole",
            Place::LatLon(35.264, 45.0),
            8_000_000.0,
            -90.0,
            200_000.0,
        ),
    ] {
        let shot = Shot {
            place,
            height_m,
            pitch_deg,
            size: [640, 360],
            ..Shot::default()
        };
        let f = frame(&gpu, &mut session, &shot);
        check(name, &f, raise_m);
    }
}

/// A session config with `metric` (tolerances come with the views).
fn with_metric(metric: Metric) -> SessionConfig {
    SessionConfig {
        refine: RefineConfig {
            metric,
            ..RefineConfig::default()
        },
        ..SessionConfig::default()
    }
}

/// Streams `shot` with the geometric metric, then its exact view at 0 px with the
/// sampling metric (every visible diamond at the finest coded level), and measures the
/// first against the second. Returns the geometric error summary.
fn geometric_against_reference<R: RenderDomain>(
    gpu: &Gpu,
    open: impl Fn(SessionConfig) -> Session<R>,
    shot: &Shot,
) -> quincunx_render::error::GeometricError {
    let mut session = open(with_metric(Metric::Geometric));
    let test = frame(gpu, &mut session, shot);
    let test_halves = session.dag().cut_len();
    drop(session);
    let view = test.view;
    let mut session = open(with_metric(Metric::Sampling));
    let reference = frame_at(
        gpu,
        &mut session,
        &View {
            tolerance_px: 0.0,
            ..view
        },
    );
    let e = geometric_error(
        &test.camera,
        &test.depth,
        Some(&reference.depth),
        &reference.index,
    )
    .unwrap();
    eprintln!(
        "geometric metric at {} px: {} halves (reference {}), error {e:?}",
        shot.tolerance_px,
        test_halves,
        session.dag().cut_len()
    );
    assert!(e.pixels > 1000, "{e:?}");
    e
}

/// A 960 x 540 shot.
fn half_hd(place: Place, height_m: f64, pitch_deg: f64, tolerance_px: f64) -> Shot {
    Shot {
        place,
        height_m,
        pitch_deg,
        size: [960, 540],
        tolerance_px,
        ..Shot::default()
    }
}

/// The geometric metric's promise on screen: no measured pixel further from the
/// full-resolution surface than the tolerance (the bound is projected at the nearest point
/// of each diamond's box, times the box's off-axis factor).
#[test]
fn geometric_metric_keeps_the_error_within_the_tolerance() {
    let Some(gpu) = gpu_for_test("geometric_metric_keeps_the_error_within_the_tolerance").unwrap()
    else {
        return;
    };
    let url = served().url();
    for tolerance_px in [1.0, 4.0] {
        for (place, height_m, pitch_deg) in [
            (Place::Uv(0.5, 0.8), 3_000.0, -25.0),
            (Place::Uv(0.3, 0.4), 15_000.0, -90.0),
        ] {
            let shot = half_hd(place, height_m, pitch_deg, tolerance_px);
            let e = geometric_against_reference(
                &gpu,
                |c| -> Session { Session::open(&url, "korea", c).unwrap() },
                &shot,
            );
            assert!(e.max_px <= tolerance_px, "korea {shot:?}: {e:?}");
        }
        for (place, height_m, pitch_deg) in [
            (Place::LatLon(36.0, 128.0), 2_000_000.0, -50.0),
            (Place::LatLon(27.9, 86.9), 300_000.0, -30.0),
        ] {
            let shot = half_hd(place, height_m, pitch_deg, tolerance_px);
            let e = geometric_against_reference(
                &gpu,
                |c| PlanetSession::open(&url, "earth", c).unwrap(),
                &shot,
            );
            assert!(e.max_px <= tolerance_px, "earth {shot:?}: {e:?}");
        }
    }
}
