//! Rendered frames of the bundled repositories, streamed from a real server and drawn
//! offscreen by `quincunx-render` on the adapter the environment selects
//! (`WGPU_BACKEND`: lavapipe in `.ci/run`, llvmpipe GL in `.ci/gl-only`):
//!
//! - reference images (korea straight down and oblique, the planet whole and close with
//!   colour) compared with a tolerance: per channel `|diff| <= 2` on at least 99.5 % of
//!   the pixels and a mean `|diff|` of at most 0.5 (lavapipe is deterministic run to run);
//!   on failure the actual and difference images go to `<target>/render-failures/`; a
//!   missing reference fails (`QUINCUNX_BLESS=1` writes it);
//! - a crack detector: a magenta background (the terrain never has it), views where the
//!   f64 geometry says every ray meets the terrain (planar: the ray's stretch between the
//!   highest and the lowest height stays over the raster; planets: the ray meets the
//!   sphere of the lowest height), each pixel's 2 px neighbourhood included; 0 background
//!   pixels there, and the cut's own check clean; planets from 1 m to 100,000 km (the
//!   depth range GL without clip control loses);
//! - negative controls: past the raster's edge the background shows where the geometry
//!   says there is no terrain, and the same cut drawn without one patch shows a hole.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;

use common::stream::Served;
use glam::DVec3;
use quincunx_client::dag::Half;
use quincunx_client::session::{PatchChanges, PlanetSession, Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_render::domain::{Geometry, RenderDomain};
use quincunx_render::offscreen::{Gpu, Image, Offscreen, gpu_for_test};
use quincunx_render::renderer::{RendererConfig, TerrainRenderer};
use quincunx_render::scene::{Picture, PictureOptions, Place, Shot, Streamed, picture};
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_server::RepoConfig;

/// Frame size of every view here: small references.
const SIZE: [u32; 2] = [480, 270];
/// Streaming limit per view.
const WAIT: Duration = Duration::from_secs(120);
/// Pure magenta: no height tint or imagery colour is this.
const MAGENTA: [u8; 3] = [255, 0, 255];
/// Largest per-channel difference a pixel may have and still count as equal.
const PIXEL_TOLERANCE: u8 = 2;
/// Share of pixels that must be equal within [`PIXEL_TOLERANCE`].
const MIN_EQUAL_SHARE: f64 = 0.995;
/// Largest mean per-channel difference.
const MAX_MEAN_DIFF: f64 = 0.5;
/// Each pixel's neighbourhood (half side, pixels) that must lie on the terrain.
const MARGIN_PX: f64 = 2.0;

/// The bundled repositories, built as `quincunx demo` builds them, and their server.
struct Fixture {
    served: Served,
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let dir = target_dir().join("render-images-repos");
        let data = common::workspace_root().join("data");
        let korea = dir.join("korea");
        common::build_bundled_korea(&korea);
        let earth = dir.join("earth");
        build::run(&BuildArgs {
            planet: true,
            max_error_m: Some(2.0),
            overwrite: true,
            ..BuildArgs::new(data.join("etopo20_global.json"), &earth)
        })
        .unwrap();
        let earth_colour = dir.join("earth_colour");
        build::run(&BuildArgs {
            planet: true,
            colour: true,
            rms_m: Some(4.0),
            overwrite: true,
            ..BuildArgs::new(data.join("bmng_global_1080x540.jpg"), &earth_colour)
        })
        .unwrap();
        // The planar DEM + orthophoto pair (GSI, 256 x 256, no georeference: 1 m).
        let gsi = dir.join("gsi");
        build::run(&BuildArgs {
            max_error_m: Some(0.2),
            overwrite: true,
            ..BuildArgs::new(data.join("fixture_gsi_dem_256.json"), &gsi)
        })
        .unwrap();
        let gsi_colour = dir.join("gsi_colour");
        build::run(&BuildArgs {
            colour: true,
            rms_m: Some(4.0),
            overwrite: true,
            ..BuildArgs::new(data.join("fixture_gsi_color_256.jpg"), &gsi_colour)
        })
        .unwrap();
        let repos = [
            ("korea", korea),
            ("earth", earth),
            ("earth_colour", earth_colour),
            ("gsi", gsi),
            ("gsi_colour", gsi_colour),
        ]
        .into_iter()
        .map(|(name, path)| RepoConfig {
            name: name.into(),
            path,
        })
        .collect();
        Fixture {
            served: Served::start("127.0.0.1:0".parse().unwrap(), repos),
        }
    })
}

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| common::workspace_root().join("target"))
}

fn korea() -> Session {
    Session::open(&fixture().served.url(), "korea", SessionConfig::default()).unwrap()
}

fn gsi() -> Session {
    Session::open_with_colour(
        &fixture().served.url(),
        "gsi",
        "gsi_colour",
        SessionConfig::default(),
    )
    .unwrap()
}

fn earth() -> PlanetSession {
    PlanetSession::open_with_colour(
        &fixture().served.url(),
        "earth",
        "earth_colour",
        SessionConfig::default(),
    )
    .unwrap()
}

fn shot(place: Place, height_m: f64, pitch_deg: f64) -> Shot {
    Shot {
        place,
        height_m,
        pitch_deg,
        size: SIZE,
        ..Shot::default()
    }
}

/// Streams `shot` to full quality and draws it; checks the cut.
fn take<R: RenderDomain>(
    gpu: &Gpu,
    session: &mut Session<R>,
    shot: &Shot,
    background: [u8; 3],
) -> (Picture, Streamed, View) {
    let options = PictureOptions {
        background,
        ..PictureOptions::default()
    };
    let (pic, streamed, view) = picture(gpu, session, shot, WAIT, &options).unwrap();
    assert!(streamed.full_quality, "{shot:?}: not at full quality");
    assert_eq!(pic.stats.missing, 0, "{shot:?}: patches not drawn");
    let check = session.dag().check_cut();
    assert!(check.ok(), "{shot:?}: {check:?}");
    assert_eq!(check.cracks, 0);
    (pic, streamed, view)
}

/// [`take`] of `shot` on a new Earth session, and the radii of its lowest and highest
/// heights.
fn take_earth(gpu: &Gpu, shot: &Shot) -> (Picture, View, [f64; 2]) {
    let mut session = earth();
    let (pic, _, view) = take(gpu, &mut session, shot, MAGENTA);
    let world = session.dag().refiner().world_frame(&session.world(), 0);
    let Geometry::Planet { radius_m, .. } = world.geometry else {
        panic!("a planet")
    };
    let (low, high) = session.height_range();
    (pic, view, [radius_m + low, radius_m + high])
}

// ---------------------------------------------------------------- reference images

/// How far an image is from its reference.
#[derive(Debug)]
struct Difference {
    equal_share: f64,
    mean: f64,
    max: u8,
    image: Image,
}

fn difference(actual: &Image, reference: &Image) -> Difference {
    let mut image = actual.clone();
    let (mut equal, mut sum, mut max) = (0usize, 0u64, 0u8);
    for (k, (a, r)) in actual
        .rgba
        .chunks_exact(4)
        .zip(reference.rgba.chunks_exact(4))
        .enumerate()
    {
        let d = [0, 1, 2].map(|c| a[c].abs_diff(r[c]));
        let worst = d.into_iter().max().unwrap_or(0);
        equal += usize::from(worst <= PIXEL_TOLERANCE);
        sum += d.iter().map(|&x| u64::from(x)).sum::<u64>();
        max = max.max(worst);
        // Differences in red, amplified, over a dim grey of the reference.
        let grey = ((u16::from(r[0]) + u16::from(r[1]) + u16::from(r[2])) / 12) as u8;
        let red = grey.saturating_add(worst.saturating_mul(16));
        image.rgba[k * 4..k * 4 + 4].copy_from_slice(&[red, grey, grey, 255]);
    }
    let px = actual.rgba.len() / 4;
    Difference {
        equal_share: equal as f64 / px as f64,
        mean: sum as f64 / (3 * px) as f64,
        max,
        image,
    }
}

/// Compares `image` to `render_reference/<name>.png` (or writes it with
/// `QUINCUNX_BLESS=1`): `Err` with what failed and where the images went.
fn against_reference(name: &str, image: &Image) -> Result<String, String> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/render_reference");
    let path = dir.join(format!("{name}.png"));
    if std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1") {
        std::fs::create_dir_all(&dir).unwrap();
        image.write_png(&path).unwrap();
        return Ok(format!("{name}: wrote {}", path.display()));
    }
    if !path.exists() {
        return Err(format!(
            "{name}: no reference {} (run with QUINCUNX_BLESS=1 to write it)",
            path.display()
        ));
    }
    let reference = Image::read_png(&path).unwrap();
    let failures = target_dir().join("render-failures");
    let save = |why: String, diff: Option<&Image>| {
        std::fs::create_dir_all(&failures).unwrap();
        let actual = failures.join(format!("{name}.actual.png"));
        image.write_png(&actual).unwrap();
        let mut out = format!("{name}: {why}; actual image {}", actual.display());
        if let Some(diff) = diff {
            let d = failures.join(format!("{name}.diff.png"));
            diff.write_png(&d).unwrap();
            out.push_str(&format!(", difference {}", d.display()));
        }
        out
    };
    if (reference.width, reference.height) != (image.width, image.height) {
        let why = format!(
            "size {}x{}, reference {}x{}",
            image.width, image.height, reference.width, reference.height
        );
        return Err(save(why, None));
    }
    let d = difference(image, &reference);
    let summary = format!(
        "{:.4} % of pixels within {PIXEL_TOLERANCE}, mean |diff| {:.4}, max {}",
        d.equal_share * 100.0,
        d.mean,
        d.max
    );
    if d.equal_share < MIN_EQUAL_SHARE || d.mean > MAX_MEAN_DIFF {
        let why = format!(
            "{summary} (needs >= {} % and <= {MAX_MEAN_DIFF})",
            MIN_EQUAL_SHARE * 100.0
        );
        return Err(save(why, Some(&d.image)));
    }
    // Passing: images of an earlier failure are stale.
    for stale in ["actual", "diff"] {
        let _ = std::fs::remove_file(failures.join(format!("{name}.{stale}.png")));
    }
    Ok(format!("{name}: {summary}"))
}

#[test]
fn frames_match_their_references() {
    let Some(gpu) = gpu_for_test("frames_match_their_references").unwrap() else {
        return;
    };
    let sky = PictureOptions::default().background;
    let mut images = Vec::new();
    for (name, s) in [
        ("korea_down", shot(Place::Uv(0.5, 0.5), 40_000.0, -90.0)),
        ("korea_oblique", shot(Place::Uv(0.5, 0.75), 8_000.0, -30.0)),
    ] {
        images.push((name, take(&gpu, &mut korea(), &s, sky).0.image));
    }
    // A planar repository with colour: the GSI orthophoto on its DEM.
    let s = shot(Place::Uv(0.5, 0.5), 200.0, -90.0);
    images.push(("gsi_colour_down", take(&gpu, &mut gsi(), &s, sky).0.image));
    for (name, s) in [
        (
            "earth_whole",
            shot(Place::LatLon(30.0, 100.0), 15_000_000.0, -90.0),
        ),
        (
            "earth_close",
            shot(Place::LatLon(36.0, 128.0), 2_000_000.0, -50.0),
        ),
    ] {
        images.push((name, take(&gpu, &mut earth(), &s, sky).0.image));
    }
    let results: Vec<Result<String, String>> = images
        .iter()
        .map(|(name, image)| against_reference(name, image))
        .collect();
    for r in results.iter().flatten() {
        println!("{r}");
    }
    let failed: Vec<&String> = results.iter().filter_map(|r| r.as_ref().err()).collect();
    assert!(failed.is_empty(), "{failed:#?}");
}

// ---------------------------------------------------------------- the crack detector

/// The f64 ray through a point of the frame (pixels from the top-left corner).
fn ray(view: &View, x: f64, y: f64) -> DVec3 {
    let [w, h] = view.viewport_px.map(f64::from);
    let forward = (view.target - view.eye).normalize();
    let right = forward.cross(view.up).normalize();
    let up = right.cross(forward);
    let t = (view.fov_y_rad / 2.0).tan();
    let nx = 2.0 * x / w - 1.0;
    let ny = 1.0 - 2.0 * y / h;
    (forward + right * (nx * t * w / h) + up * (ny * t)).normalize()
}

/// What the geometry says a pixel shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Truth {
    /// The pixel and its neighbourhood see terrain.
    Terrain,
    /// The pixel and its neighbourhood see none.
    Nothing,
    /// Near an edge, or unknown.
    Unsure,
}

/// Whether a ray meets the terrain of a planar raster `[0, size]` (metres) whose heights
/// lie in `lo..=hi`: `Some(true)` when its stretch between the heights stays over the
/// raster (it must cross the surface there), `Some(false)` when the stretch lies beyond
/// one edge, `None` otherwise.
fn planar_ray(eye: DVec3, d: DVec3, size: [f64; 2], (lo, hi): (f64, f64)) -> Option<bool> {
    if d.z >= 0.0 {
        return Some(false).filter(|_| eye.z > hi);
    }
    let t_hi = ((hi - eye.z) / d.z).max(0.0);
    let t_lo = (lo - eye.z) / d.z;
    if t_lo <= 0.0 {
        return None;
    }
    let ends = [eye + d * t_hi, eye + d * t_lo];
    let inside = |p: &DVec3| p.x >= 0.0 && p.y >= 0.0 && p.x <= size[0] && p.y <= size[1];
    if ends.iter().all(inside) {
        return Some(true);
    }
    let beyond = [
        ends.iter().all(|p| p.x < 0.0),
        ends.iter().all(|p| p.y < 0.0),
        ends.iter().all(|p| p.x > size[0]),
        ends.iter().all(|p| p.y > size[1]),
    ];
    beyond.contains(&true).then_some(false).or(None)
}

/// Whether a ray from `eye` meets the sphere of radius `r` about the origin.
fn meets_sphere(eye: DVec3, d: DVec3, r: f64) -> bool {
    let along = eye.dot(d);
    along < 0.0 && (eye - d * along).length_squared() < r * r
}

/// The geometry's verdict for every pixel: `hit(ray)` for the ray through the pixel's
/// centre and the corners of the square [`MARGIN_PX`] around it (the terrain seen is
/// convex over such a square: a raster, a disc).
fn truth_map(view: &View, hit: impl Fn(DVec3) -> Option<bool>) -> Vec<Truth> {
    let [w, h] = view.viewport_px;
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let (cx, cy) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
            let m = MARGIN_PX;
            let verdicts: Vec<Option<bool>> = [(0.0, 0.0), (-m, -m), (m, -m), (-m, m), (m, m)]
                .iter()
                .map(|(dx, dy)| hit(ray(view, cx + dx, cy + dy)))
                .collect();
            out.push(if verdicts.iter().all(|v| *v == Some(true)) {
                Truth::Terrain
            } else if verdicts.iter().all(|v| *v == Some(false)) {
                Truth::Nothing
            } else {
                Truth::Unsure
            });
        }
    }
    out
}

fn is_background(px: &[u8]) -> bool {
    px[..3] == MAGENTA
}

/// Pixels of each kind, and the background ones among them.
#[derive(Debug, Default, PartialEq, Eq)]
struct Count {
    terrain: usize,
    background_in_terrain: usize,
    nothing: usize,
    background_in_nothing: usize,
}

fn count(image: &Image, truth: &[Truth]) -> Count {
    let mut c = Count::default();
    for (px, t) in image.rgba.chunks_exact(4).zip(truth) {
        match t {
            Truth::Terrain => {
                c.terrain += 1;
                c.background_in_terrain += usize::from(is_background(px));
            }
            Truth::Nothing => {
                c.nothing += 1;
                c.background_in_nothing += usize::from(is_background(px));
            }
            Truth::Unsure => {}
        }
    }
    c
}

/// The planar truth map of a session's view.
fn planar_truth(session: &Session, view: &View) -> Vec<Truth> {
    let world = session.dag().refiner().world_frame(&session.world(), 0);
    let Geometry::Planar {
        metres_per_fine,
        extent_fine,
    } = world.geometry
    else {
        panic!("planar")
    };
    let size = extent_fine.map(|e| e as f64 * metres_per_fine);
    let range = session.height_range();
    truth_map(view, |d| planar_ray(view.eye, d, size, range))
}

/// Planar views: the share of the frame the geometry says is terrain (at least), and
/// the view.
const PLANAR_VIEWS: [(f64, f64, f64, f64, f64); 6] = [
    // u, v, height (m), pitch (deg), least terrain share
    (0.3, 0.4, 2_000.0, -90.0, 1.0),
    (0.7, 0.6, 500.0, -90.0, 1.0),
    (0.5, 0.5, 20_000.0, -90.0, 1.0),
    (0.2, 0.8, 200.0, -90.0, 1.0),
    (0.5, 0.8, 3_000.0, -30.0, 0.3),
    (0.4, 0.9, 1_000.0, -20.0, 0.3),
];

#[test]
fn planar_views_show_no_background_inside_the_terrain() {
    let Some(gpu) = gpu_for_test("planar_views_show_no_background_inside_the_terrain").unwrap()
    else {
        return;
    };
    for (u, v, height_m, pitch_deg, least) in PLANAR_VIEWS {
        let s = shot(Place::Uv(u, v), height_m, pitch_deg);
        let mut session = korea();
        let (pic, _, view) = take(&gpu, &mut session, &s, MAGENTA);
        let c = count(&pic.image, &planar_truth(&session, &view));
        let px = (SIZE[0] * SIZE[1]) as usize;
        println!(
            "korea uv {u},{v} {height_m} m pitch {pitch_deg}: {} terrain pixels, {} background among them; {} patches",
            c.terrain, c.background_in_terrain, pic.stats.patches
        );
        assert!(
            c.terrain as f64 >= least * px as f64,
            "uv {u},{v}: only {} of {px} pixels are surely terrain",
            c.terrain
        );
        assert_eq!(c.background_in_terrain, 0, "uv {u},{v} {height_m} m: {c:?}");
    }
}

#[test]
fn a_gpu_budget_below_the_cut_draws_the_finest_cut_that_fits() {
    let Some(gpu) =
        gpu_for_test("a_gpu_budget_below_the_cut_draws_the_finest_cut_that_fits").unwrap()
    else {
        return;
    };
    // A low oblique view at half a pixel: thousands of patches with the default budget.
    let s = Shot {
        tolerance_px: 0.5,
        ..shot(Place::Uv(0.5, 0.8), 3_000.0, -30.0)
    };
    let (full, _, _) = take(&gpu, &mut korea(), &s, MAGENTA);
    // Slots for a third of that view's patches (the pool also holds cached ones): the
    // session's cut is bounded by the pool.
    let options = PictureOptions {
        background: MAGENTA,
        renderer: RendererConfig {
            gpu_budget_bytes: full.stats.slot_bytes * full.stats.patches as u64 / 3,
            ..RendererConfig::default()
        },
        ..PictureOptions::default()
    };
    let mut session = korea();
    let (pic, streamed, view) = picture(&gpu, &mut session, &s, WAIT, &options).unwrap();
    assert!(
        streamed.budget_limited && !streamed.full_quality,
        "{streamed:?}"
    );
    assert_eq!(pic.stats.missing, 0, "no patch left out");
    assert!(
        pic.stats.patches < full.stats.patches / 2,
        "{} of {}",
        pic.stats.patches,
        full.stats.patches
    );
    assert!(pic.stats.gpu_bytes_used <= pic.stats.gpu_bytes_allocated);
    assert!(session.dag().check_cut().ok());
    let c = count(&pic.image, &planar_truth(&session, &view));
    assert!(c.terrain > 0);
    assert_eq!(c.background_in_terrain, 0, "{c:?}");
}

#[test]
fn planet_views_show_no_background_inside_the_disc() {
    let Some(gpu) = gpu_for_test("planet_views_show_no_background_inside_the_disc").unwrap() else {
        return;
    };
    let places = [
        ("equator", 0.0, 10.0),
        ("pole", 90.0, 0.0),
        ("cube edge", 0.0, 45.0),
        ("cube corner", 35.264, 45.0),
    ];
    // From 100,000 km a 60 degree frame shows a disc of 20 px: look through a narrower one.
    for (height_m, fov_deg) in [(15_000_000.0, 60.0), (100_000_000.0, 10.0)] {
        for (what, lat, lon) in places {
            let s = Shot {
                fov_deg,
                ..shot(Place::LatLon(lat, lon), height_m, -90.0)
            };
            let (pic, view, [r, outer]) = take_earth(&gpu, &s);
            let truth = truth_map(&view, |d| Some(meets_sphere(view.eye, d, r)));
            let c = count(&pic.image, &truth);
            println!(
                "earth {what} ({lat},{lon}) from {height_m} m: {} disc pixels, {} background among them; {} outside, {} background; {} patches",
                c.terrain,
                c.background_in_terrain,
                c.nothing,
                c.background_in_nothing,
                pic.stats.patches
            );
            assert!(c.terrain > 500, "{what}: a disc of {} pixels", c.terrain);
            assert_eq!(
                c.background_in_terrain, 0,
                "{what} from {height_m} m: {c:?}"
            );
            // Around the disc the sky (the sphere of the highest height may reach a little
            // beyond the lowest one's, so only far outside it).
            let sky = truth_map(&view, |d| Some(meets_sphere(view.eye, d, outer)));
            let s = count(&pic.image, &sky);
            assert_eq!(
                s.background_in_nothing, s.nothing,
                "{what}: terrain off the disc"
            );
        }
    }
}

#[test]
fn a_planet_from_1_m_to_100_000_km_shows_no_background_inside_the_terrain() {
    let test = "a_planet_from_1_m_to_100_000_km_shows_no_background_inside_the_terrain";
    let Some(gpu) = gpu_for_test(test).unwrap() else {
        return;
    };
    // Straight down and oblique (the horizon in view: the widest depth range), from 1 m
    // to 100,000 km over a face centre on the equator. Without clip control a reversed-Z
    // depth near / distance rounds to the clear value from about 1,000 km up.
    for (height_m, pitch_deg, fov_deg) in [
        (1.0, -90.0, 60.0),
        (1.0, -10.0, 60.0),
        (100.0, -90.0, 60.0),
        (100.0, -20.0, 60.0),
        (10_000.0, -30.0, 60.0),
        (1_000_000.0, -60.0, 60.0),
        (15_000_000.0, -90.0, 60.0),
        (100_000_000.0, -90.0, 10.0),
    ] {
        let s = Shot {
            fov_deg,
            ..shot(Place::LatLon(0.0, 10.0), height_m, pitch_deg)
        };
        // Every ray that meets the sphere of the lowest height crosses the terrain.
        let (pic, view, [r, _]) = take_earth(&gpu, &s);
        let truth = truth_map(&view, |d| meets_sphere(view.eye, d, r).then_some(true));
        let c = count(&pic.image, &truth);
        println!(
            "earth from {height_m} m, pitch {pitch_deg}: {} terrain pixels, {} background among them; {} patches",
            c.terrain, c.background_in_terrain, pic.stats.patches
        );
        assert!(c.terrain > 10_000, "{height_m} m: {c:?}");
        assert_eq!(
            c.background_in_terrain, 0,
            "{height_m} m, pitch {pitch_deg}: {c:?}"
        );
    }
}

#[test]
fn the_detector_sees_background_past_the_raster_edge() {
    let Some(gpu) = gpu_for_test("the_detector_sees_background_past_the_raster_edge").unwrap()
    else {
        return;
    };
    // Straight down over the east edge: the right part of the frame is off the raster.
    let s = shot(Place::Uv(0.97, 0.5), 10_000.0, -90.0);
    let mut session = korea();
    let (pic, _, view) = take(&gpu, &mut session, &s, MAGENTA);
    let c = count(&pic.image, &planar_truth(&session, &view));
    println!("past the edge: {c:?}");
    assert!(c.terrain > 10_000 && c.nothing > 10_000, "{c:?}");
    assert_eq!(c.background_in_nothing, c.nothing, "{c:?}");
    assert_eq!(c.background_in_terrain, 0, "{c:?}");
}

/// The patch under the centre of a straight-down planar view.
fn patch_under<R: RenderDomain>(session: &Session<R>, ground: DVec3) -> (R::Id, Half) {
    let world = session.dag().refiner().world_frame(&session.world(), 0);
    let Geometry::Planar {
        metres_per_fine, ..
    } = world.geometry
    else {
        panic!("planar")
    };
    let p = ground / metres_per_fine;
    let n = world.n as usize;
    let snapshot = session.snapshot();
    snapshot
        .patches
        .iter()
        .find_map(|patch| {
            let a = session
                .dag()
                .refiner()
                .affine(patch.id, &patch.corners, patch.half)?;
            let corners = match patch.half {
                Half::Lower => [a.at(0, 0), a.at(n, 0), a.at(n, n)],
                Half::Upper => [a.at(0, 0), a.at(0, n), a.at(n, n)],
            }
            .map(|c| DVec3::new(c[0] as f64, c[1] as f64, 0.0));
            let side = |a: DVec3, b: DVec3| (b - a).cross(p - a).z;
            let s = [
                side(corners[0], corners[1]),
                side(corners[1], corners[2]),
                side(corners[2], corners[0]),
            ];
            let inside = s.iter().all(|&x| x > 0.0) || s.iter().all(|&x| x < 0.0);
            inside.then_some((patch.id, patch.half))
        })
        .expect("a patch under the camera")
}

/// Draws the session's cut, without `skip`, from `view` on a fresh renderer.
fn draw_cut<R: RenderDomain>(
    gpu: &Gpu,
    session: &Session<R>,
    view: &View,
    skip: Option<(R::Id, Half)>,
) -> Image {
    let config = RendererConfig {
        colour_format: quincunx_render::offscreen::OFFSCREEN_FORMAT,
        ..RendererConfig::default()
    };
    let mut renderer = TerrainRenderer::for_session(&gpu.device, session, config).unwrap();
    let entered = session
        .snapshot()
        .patches
        .into_iter()
        .filter(|p| Some((p.id, p.half)) != skip)
        .collect();
    let dag = session.dag();
    renderer
        .apply(
            dag.refiner(),
            dag.colour(),
            PatchChanges {
                entered,
                left: Vec::new(),
            },
        )
        .unwrap();
    let camera = quincunx_render::camera::Camera::from_view(view);
    for _ in 0..10_000 {
        if renderer.prepare(&gpu.queue, &camera).pending == 0 {
            break;
        }
    }
    let offscreen = Offscreen::new(gpu, view.viewport_px).unwrap();
    offscreen
        .render(gpu, MAGENTA, |pass| renderer.draw(pass))
        .unwrap();
    offscreen.read(gpu).unwrap()
}

#[test]
fn the_detector_sees_a_missing_patch() {
    let Some(gpu) = gpu_for_test("the_detector_sees_a_missing_patch").unwrap() else {
        return;
    };
    // Off the raster's centre, which is a corner of many patches.
    let s = shot(Place::Uv(0.43, 0.56), 20_000.0, -90.0);
    let mut session = korea();
    let (pic, _, view) = take(&gpu, &mut session, &s, MAGENTA);
    let truth = planar_truth(&session, &view);
    // The same cut drawn by hand: the picture again.
    let whole = draw_cut(&gpu, &session, &view, None);
    assert_eq!(
        whole, pic.image,
        "drawing the cut by hand changed the picture"
    );
    let ground = DVec3::new(view.eye.x, view.eye.y, 0.0);
    let hole = draw_cut(&gpu, &session, &view, Some(patch_under(&session, ground)));
    let c = count(&hole, &truth);
    println!("one patch left out: {c:?}");
    assert!(c.background_in_terrain > 0, "{c:?}");
    let centre = hole.pixel(SIZE[0] / 2, SIZE[1] / 2);
    assert!(is_background(&centre), "{centre:?}");
}
