//! The `fly` example's app against `quincunx serve`, under Xvfb: screenshots of the bundled
//! korea crop and ETOPO20 planet, checked pixel by pixel.
//!
//! - korea straight down: terrain everywhere (0 background pixels), the cube the height
//!   query stood on the ground visible where the camera projects it;
//! - korea oblique, the cube in sight (every corner's ray reaches it): its pixels there,
//!   its lowest pixel where the ground point projects;
//! - korea low, the cube behind a ridge (every corner's ray hits the terrain first):
//!   none of its pixels;
//! - the planet 1 m above the ground, straight down: 0 background pixels; again with
//!   Bevy's origin 1 km from the camera (the camera's f32 translation 1 km): the same
//!   image within the translation's rounding;
//! - the planet from 100,000 km: every pixel inside its disk is terrain; again with the
//!   bundled Blue Marble colour layer: every pixel inside the disk terrain, most of them
//!   other than without it, oceans blue and land not.
//!
//! Winit needs the main thread and one event loop per process, so this is a
//! `harness = false` test that runs one app through every scene, and re-runs itself under
//! `xvfb-run` when it has no display.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "../examples/fly.rs"]
mod fly;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bevy::app::AppExit;
use bevy::prelude::*;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use glam::DVec3;
use quincunx_bevy::{DepthReadback, Terrain, TerrainCamera, TerrainOrigin, TerrainState};

const SIZE: (u32, u32) = (640, 400);
const CHILD: &str = "QUINCUNX_BEVY_APP_CHILD";

fn main() {
    if std::env::var_os(CHILD).is_some() {
        child();
        return;
    }
    let name = "bevy_app";
    let has_xvfb = Command::new("sh")
        .args(["-c", "command -v xvfb-run"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_xvfb {
        quincunx_testkit::skip::skip(name, "REQUIRE_XVFB", "xvfb-run is not installed");
        return;
    }
    match quincunx_render::offscreen::gpu_for_test(name) {
        Ok(Some(_)) => {}
        Ok(None) => return,
        Err(e) => panic!("{name}: {e}"),
    }
    let status = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1280x1024x24"])
        .arg(std::env::current_exe().unwrap())
        .env(CHILD, "1")
        .env_remove("WAYLAND_DISPLAY")
        .status()
        .unwrap();
    assert!(
        status.success(),
        "{name}: the app under Xvfb failed: {status}"
    );
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The `quincunx` binary: `$QUINCUNX_BIN`, else the one beside this test's target
/// directory (`cargo test --release` at the top builds it; CI's test build did), else
/// built now.
fn quincunx_bin() -> PathBuf {
    if let Some(bin) = std::env::var_os("QUINCUNX_BIN") {
        return bin.into();
    }
    let exe = std::env::current_exe().unwrap();
    let bin = exe.parent().unwrap().parent().unwrap().join("quincunx");
    if !bin.exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .args(["build", "--release", "--bin", "quincunx"])
            .current_dir(workspace_root())
            .status()
            .unwrap();
        assert!(status.success(), "building quincunx: {status}");
    }
    bin
}

/// A `quincunx serve` process, killed on drop.
struct Serve(std::process::Child);

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Builds the bundled korea crop and ETOPO20 planet (as `quincunx demo` does) and serves
/// them with `quincunx serve`.
fn serve(dir: &Path) -> (Serve, SocketAddr) {
    let bin = quincunx_bin();
    let root = workspace_root();
    for (input, name, flags) in [
        ("data/korea_srtm3_1025.json", "korea", &["--rms-m", "2"][..]),
        (
            "data/etopo20_global.json",
            "earth",
            &["--planet", "--max-error-m", "2"][..],
        ),
        (
            "data/bmng_global_1080x540.jpg",
            "earth_colour",
            &["--colour", "--planet", "--rms-m", "4"][..],
        ),
    ] {
        let status = Command::new(&bin)
            .arg("build")
            .arg(root.join(input))
            .arg("-o")
            .arg(dir.join(name))
            .args(flags)
            .status()
            .unwrap();
        assert!(status.success(), "quincunx build {input}: {status}");
    }
    let addr: SocketAddr = {
        let probe = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        probe.local_addr().unwrap()
    };
    let child = Command::new(&bin)
        .args(["serve", "--log", "warn", "--addr", &addr.to_string()])
        .arg("--repo")
        .arg(format!("korea={}", dir.join("korea").display()))
        .arg("--repo")
        .arg(format!("earth={}", dir.join("earth").display()))
        .arg("--repo")
        .arg(format!(
            "earth_colour={}",
            dir.join("earth_colour").display()
        ))
        .spawn()
        .unwrap();
    let served = Serve(child);
    let deadline = Instant::now() + Duration::from_secs(30);
    while std::net::TcpStream::connect(addr).is_err() {
        assert!(
            Instant::now() < deadline,
            "quincunx serve did not listen on {addr}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    (served, addr)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scene {
    KoreaDown,
    KoreaInSight,
    KoreaHidden,
    PlanetLow,
    PlanetLowShifted,
    PlanetFar,
    PlanetColour,
}

const SCENES: [Scene; 7] = [
    Scene::KoreaDown,
    Scene::KoreaInSight,
    Scene::KoreaHidden,
    Scene::PlanetLow,
    Scene::PlanetLowShifted,
    Scene::PlanetFar,
    Scene::PlanetColour,
];

/// A screenshot and what the scene expected of it.
struct Shot {
    scene: Scene,
    rgba: Vec<[u8; 4]>,
    width: u32,
    height: u32,
    /// The cube's centre and its ground point, projected (pixels).
    cube_px: Option<Vec2>,
    ground_px: Option<Vec2>,
    /// The planet's disk: centre and radius (pixels).
    disk: Option<(Vec2, f32)>,
    triangles: u64,
}

/// The depth read back in the in-sight view, against the queries, at a grid of pixels
/// showing terrain: the largest screen distance (px) between the depth buffer's point
/// and the ray's hit (their height difference, seen at the point), and between that
/// point and `height_below` it; and how many pixels.
#[derive(Clone, Copy, Debug, Default)]
struct DepthCheck {
    ray_px: f64,
    height_px: f64,
    pixels: usize,
}

#[derive(Resource)]
struct Script {
    scene: usize,
    /// Frames at full quality with the drawn cut current.
    settled: u32,
    /// Camera pose candidates tried in the scene.
    tries: usize,
    started: Instant,
    waiting_shot: bool,
    /// The in-sight view's depth read-back was asked for, and its check.
    depth_asked: bool,
    depth: Option<DepthCheck>,
    shots: Arc<Mutex<Vec<Shot>>>,
    /// The planet's low camera: its position, quincunx frame.
    low_eye: Option<DVec3>,
    failed: Option<String>,
    url: String,
}

fn child() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, addr) = serve(dir.path());
    let url = format!("http://{addr}");
    let shots = Arc::new(Mutex::new(Vec::new()));
    let failed = Arc::new(Mutex::new(None::<String>));
    let mut app = fly::app(&url, "korea", None, SIZE);
    let f2 = Arc::clone(&failed);
    let depth = Arc::new(Mutex::new(None::<DepthCheck>));
    let d2 = Arc::clone(&depth);
    app.insert_resource(Script {
        scene: 0,
        settled: 0,
        tries: 0,
        started: Instant::now(),
        waiting_shot: false,
        depth_asked: false,
        depth: None,
        shots: Arc::clone(&shots),
        low_eye: None,
        failed: None,
        url,
    })
    .insert_resource(TerrainOrigin {
        recentre_beyond_m: None,
        ..default()
    })
    .add_systems(Update, script)
    .add_systems(Last, move |script: Res<Script>| {
        if let Some(f) = &script.failed {
            *f2.lock().unwrap() = Some(f.clone());
        }
        if let Some(d) = script.depth {
            *d2.lock().unwrap() = Some(d);
        }
    });
    app.run();
    if let Some(f) = failed.lock().unwrap().take() {
        panic!("{f}");
    }
    let shots = std::mem::take(&mut *shots.lock().unwrap());
    assert_eq!(shots.len(), SCENES.len(), "every scene took its screenshot");
    // The screenshots, for a look when a check fails.
    let keep = std::env::temp_dir().join("quincunx-bevy-app");
    std::fs::create_dir_all(&keep).unwrap();
    for shot in &shots {
        let image = quincunx_render::Image {
            width: shot.width,
            height: shot.height,
            rgba: shot.rgba.iter().flatten().copied().collect(),
        };
        let path = keep.join(format!("{:?}.png", shot.scene));
        image.write_png(&path).unwrap();
    }
    eprintln!("screenshots in {}", keep.display());
    check(&shots);
    let d = depth
        .lock()
        .unwrap()
        .expect("the depth read-back of the in-sight view");
    eprintln!(
        "depth read-back against the queries at {} pixels: ray_hit within {:.4} px, \
         height_below within {:.4} px",
        d.pixels, d.ray_px, d.height_px
    );
    assert!(d.pixels > 200, "{d:?}");
    assert!(d.ray_px <= 1.0 && d.height_px <= 1.0, "{d:?}");
}

/// The background colour as the window stores it.
fn is_background(p: [u8; 4]) -> bool {
    let want = [135i32, 171, 209];
    (0..3).all(|c| (i32::from(p[c]) - want[c]).abs() <= 1)
}

fn is_red(p: [u8; 4]) -> bool {
    p[0] >= 200 && p[1] <= 40 && p[2] <= 40
}

#[allow(clippy::too_many_arguments)]
fn script(
    mut script: ResMut<Script>,
    mut commands: Commands,
    state: Res<TerrainState>,
    mut origin: ResMut<TerrainOrigin>,
    mut fly: ResMut<fly::Fly>,
    mut terrain: ResMut<Terrain>,
    mut camera: Query<(&mut Transform, &Camera, &GlobalTransform), With<TerrainCamera>>,
    marker: Query<&Transform, (With<fly::Marker>, Without<TerrainCamera>)>,
    mut camera3d: Query<&mut Camera3d, With<TerrainCamera>>,
    readback: Res<DepthReadback>,
    mut exit: MessageWriter<AppExit>,
) {
    // A depth attachment the read-back can copy from.
    if let Ok(mut c) = camera3d.single_mut() {
        let usages = bevy::render::render_resource::TextureUsages::RENDER_ATTACHMENT
            | bevy::render::render_resource::TextureUsages::COPY_SRC;
        if c.depth_texture_usages.0 != usages.bits() {
            c.depth_texture_usages = usages.into();
        }
    }
    if script.failed.is_some() {
        exit.write(AppExit::error());
        return;
    }
    if script.started.elapsed() > Duration::from_secs(120) {
        script.failed = Some(format!(
            "scene {:?} did not settle in 120 s: {:?}",
            SCENES.get(script.scene),
            state.stats()
        ));
        return;
    }
    if script.waiting_shot {
        if script.depth_asked && script.depth.is_none() {
            if let (Some(depth), Ok((_, cam, gt))) = (readback.take(), camera.single()) {
                script.depth = Some(depth_check(&state, &origin, cam, gt, &depth));
            }
            return;
        }
        if script.shots.lock().unwrap().len() > script.scene {
            script.waiting_shot = false;
            next_scene(&mut script);
            if script.scene == SCENES.len() {
                exit.write(AppExit::Success);
            }
        }
        return;
    }
    let Some(&scene) = SCENES.get(script.scene) else {
        return;
    };
    let planet = matches!(
        scene,
        Scene::PlanetLow | Scene::PlanetLowShifted | Scene::PlanetFar | Scene::PlanetColour
    );
    let colour = scene == Scene::PlanetColour;
    if planet && (terrain.repo != "earth" || terrain.colour.is_some() != colour) {
        let earth = Terrain::new(script.url.clone(), "earth");
        *terrain = if colour {
            earth.with_colour("earth_colour")
        } else {
            earth
        };
        fly.placed = false;
        return;
    }
    if !state.is_open() || !fly.placed || (planet != state.planet_radius_m().is_some()) {
        return;
    }
    let Ok((mut t, cam, gt)) = camera.single_mut() else {
        return;
    };
    let (Some((min, max)), Ok(m)) = (state.bounds(), marker.single()) else {
        return;
    };
    let s = state.stats();
    let current = s.full_quality && s.patches_drawn == s.cut_halves && s.patches_missing == 0;
    script.settled = if current { script.settled + 1 } else { 0 };
    // The first frame of a scene (tries == 0) poses the camera; once the cut settles,
    // the scene's expectation is checked on it, and the camera posed again if it fails
    // (the next candidate, or 1 m above the ground as now drawn: it refines as the
    // camera nears it).
    let cube = m.translation;
    let eye = gt.translation();
    let again = if script.tries == 0 {
        Some(0)
    } else if script.settled < 30 {
        return;
    } else {
        match scene {
            Scene::KoreaInSight | Scene::KoreaHidden => (sight(&state, &origin, eye, m)
                != Some(scene == Scene::KoreaInSight))
            .then_some(script.tries),
            Scene::PlanetLow | Scene::PlanetLowShifted => {
                let ground = state.height_below(&origin, eye).unwrap();
                let up = state.up_at(&origin, eye).unwrap();
                ((eye - ground).dot(up) - 1.0).abs().gt(&0.01).then_some(0)
            }
            _ => None,
        }
    };
    if let Some(k) = again {
        script.settled = 0;
        if script.tries > 400 {
            script.failed = Some(format!("scene {scene:?}: no camera pose found"));
            return;
        }
        pose(
            scene,
            &mut script,
            &state,
            &mut origin,
            &mut fly,
            &mut t,
            min,
            max,
            k,
        );
        script.tries = script.tries.max(1);
        return;
    }
    let project = |p: Vec3| cam.world_to_viewport(gt, p).ok();
    let ground = cube - m.rotation * Vec3::Y * (m.scale.y / 2.0);
    let disk = matches!(scene, Scene::PlanetFar | Scene::PlanetColour).then(|| {
        let centre = origin.to_bevy(DVec3::ZERO);
        let r = state.planet_radius_m().unwrap();
        let d = (centre - eye).length() as f64;
        let angle = (r / d).asin();
        // Bevy's default vertical field of view.
        let fov = std::f64::consts::FRAC_PI_4;
        let focal = f64::from(SIZE.1) / 2.0 / (fov / 2.0).tan();
        (project(centre).unwrap(), (focal * angle.tan()) as f32)
    });
    let pending = Some(Shot {
        scene,
        rgba: Vec::new(),
        width: 0,
        height: 0,
        cube_px: project(cube),
        ground_px: project(ground),
        disk,
        triangles: s.triangles_drawn,
    });
    script.waiting_shot = true;
    if scene == Scene::KoreaInSight {
        readback.request();
        script.depth_asked = true;
    }
    let shots = Arc::clone(&script.shots);
    let pending = Arc::new(Mutex::new(pending));
    commands
        .spawn(Screenshot::primary_window())
        .observe(move |shot: On<ScreenshotCaptured>| {
            let Some(mut p) = pending.lock().unwrap().take() else {
                return;
            };
            let image = &shot.image;
            let (w, h) = (image.width(), image.height());
            p.width = w;
            p.height = h;
            p.rgba = (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| image.get_color_at(x, y).unwrap().to_srgba().to_u8_array())
                .collect();
            shots.lock().unwrap().push(p);
        });
}

/// Whether every ray from `eye` to the cube's centre and the corners of its top face
/// reaches them (`Some(true)`), or every one meets the terrain first (`Some(false)`).
fn sight(
    state: &TerrainState,
    origin: &TerrainOrigin,
    eye: Vec3,
    cube: &Transform,
) -> Option<bool> {
    let points: Vec<Vec3> = [
        (0.0, 0.0, 0.0),
        (-0.45, 0.45, -0.45),
        (0.45, 0.45, -0.45),
        (-0.45, 0.45, 0.45),
        (0.45, 0.45, 0.45),
    ]
    .iter()
    .map(|&(x, y, z)| cube.transform_point(Vec3::new(x, y, z)))
    .collect();
    let blocked: Vec<bool> = points
        .iter()
        .map(|&c| {
            state
                .ray_hit(origin, eye, c - eye)
                .is_some_and(|h| (h - eye).length() < (c - eye).length() - 0.02 * cube.scale.x)
        })
        .collect();
    if blocked.iter().all(|b| !b) {
        Some(true)
    } else if blocked.iter().all(|b| *b) {
        Some(false)
    } else {
        None
    }
}

/// Compares the depth read back with `ray_hit` and `height_below` at a 32 x 20 grid of
/// pixel centres.
fn depth_check(
    state: &TerrainState,
    origin: &TerrainOrigin,
    cam: &Camera,
    gt: &GlobalTransform,
    depth: &quincunx_render::DepthImage,
) -> DepthCheck {
    let near = quincunx_render::camera::NEAR_M as f32;
    let forward = gt.forward().as_vec3();
    let eye = gt.translation();
    let project = |p: Vec3| cam.world_to_viewport(gt, p).ok();
    let mut out = DepthCheck::default();
    for gy in 0..20 {
        for gx in 0..32 {
            let x = (gx * depth.width / 32 + depth.width / 64) as f32 + 0.5;
            let y = (gy * depth.height / 20 + depth.height / 40) as f32 + 0.5;
            let d = depth.data[(y as u32 * depth.width + x as u32) as usize];
            if d <= 0.0 {
                continue;
            }
            let ray = cam.viewport_to_world(gt, Vec2::new(x, y)).unwrap();
            let dir = ray.direction.as_vec3();
            // Reversed Z, infinite far plane: depth = near / (distance along the axis).
            let point = eye + dir * (near / (d * dir.dot(forward)));
            let (Some(hit), Some(up), Some(ground)) = (
                state.ray_hit(origin, eye, dir),
                state.up_at(origin, point),
                state.height_below(origin, point),
            ) else {
                continue;
            };
            let (Some(p), Some(r), Some(g)) = (
                project(point),
                project(point + up * (hit - point).dot(up)),
                project(ground),
            ) else {
                continue;
            };
            out.ray_px = out.ray_px.max(f64::from(p.distance(r)));
            out.height_px = out.height_px.max(f64::from(p.distance(g)));
            out.pixels += 1;
        }
    }
    out
}

fn next_scene(script: &mut Script) {
    script.scene += 1;
    script.tries = 0;
    script.settled = 0;
    script.started = Instant::now();
}

/// Poses the camera for `scene`; `k` numbers the candidates of scenes that search.
#[allow(clippy::too_many_arguments)]
fn pose(
    scene: Scene,
    script: &mut Script,
    state: &TerrainState,
    origin: &mut TerrainOrigin,
    fly: &mut fly::Fly,
    t: &mut Transform,
    min: DVec3,
    max: DVec3,
    k: usize,
) {
    let centre = (min + max) / 2.0;
    match scene {
        Scene::KoreaDown => {
            // The highest of a 16 x 16 grid of ground points: land, with ridges around.
            let mut best = (f64::NEG_INFINITY, centre);
            for i in 0..16 {
                for j in 0..16 {
                    let (u, v) = ((f64::from(i) + 0.5) / 16.0, (f64::from(j) + 0.5) / 16.0);
                    let p = DVec3::new(
                        min.x + u * (max.x - min.x),
                        min.y + v * (max.y - min.y),
                        max.z + 100.0,
                    );
                    if let Some(g) = state.height_below(origin, origin.to_bevy(p)) {
                        let g = origin.to_quincunx(g);
                        if g.z > best.0 {
                            best = (g.z, g);
                        }
                    }
                }
            }
            fly.spot = Some(best.1);
            let centre = best.1;
            origin.origin = DVec3::new(centre.x + 300.0, centre.y + 200.0, max.z + 1_500.0);
            *t = Transform::IDENTITY.looking_to(Vec3::NEG_Y, Vec3::NEG_Z);
        }
        Scene::KoreaInSight | Scene::KoreaHidden => {
            // Around the spot: 16 headings, then farther and lower; the first candidate
            // from `k` on whose rays (on the cut as it is) say what the scene wants.
            let spot = fly.spot.unwrap();
            for k in k..k + 400 {
                script.tries = k + 1;
                let heading = (k % 16) as f64 * std::f64::consts::TAU / 16.0;
                let ring = (k / 16) % 5;
                let distance = [2_000.0, 4_000.0, 8_000.0, 3_000.0, 6_000.0][ring];
                let above = if scene == Scene::KoreaHidden {
                    [15.0, 40.0, 15.0, 80.0, 30.0][ring]
                } else {
                    [600.0, 900.0, 1_500.0, 800.0, 1_200.0][ring]
                };
                let xy = DVec3::new(
                    spot.x + distance * heading.cos(),
                    spot.y + distance * heading.sin(),
                    max.z + 1_000.0,
                );
                let Some(ground) = state.height_below(origin, origin.to_bevy(xy)) else {
                    continue;
                };
                let eye_q = DVec3::new(xy.x, xy.y, origin.to_quincunx(ground).z + above);
                let eye = origin.to_bevy(eye_q);
                // Where the cube will stand, as the example sizes it.
                let at = origin.to_bevy(spot);
                let (Some(g), Some(up)) = (state.height_below(origin, at), state.up_at(origin, at))
                else {
                    continue;
                };
                let side = ((eye - g).length() * 0.02).max(1.0);
                let cube = Transform::from_translation(g + up * (side / 2.0))
                    .with_rotation(Quat::from_rotation_arc(Vec3::Y, up))
                    .with_scale(Vec3::splat(side));
                if sight(state, origin, eye, &cube) == Some(scene == Scene::KoreaInSight) {
                    origin.origin = eye_q;
                    *t = Transform::IDENTITY.looking_at(origin.to_bevy(spot), Vec3::Y);
                    return;
                }
            }
        }
        Scene::PlanetLow | Scene::PlanetLowShifted => {
            let dir = DVec3::new(0.3, -0.8, 0.5).normalize();
            let r = state.planet_radius_m().unwrap();
            let eye = match script.low_eye {
                // Each pass stands the camera 1 m above the ground as drawn now.
                Some(e) => {
                    let ground = state
                        .height_below(origin, origin.to_bevy(e))
                        .map(|g| origin.to_quincunx(g));
                    ground.map_or(e, |g| g + dir * 1.0)
                }
                None => dir * (r + 10_000.0),
            };
            script.low_eye = Some(eye);
            fly.spot = Some(dir * r);
            // The shifted scene keeps Bevy's origin 1 km away from the camera.
            let offset = if scene == Scene::PlanetLowShifted {
                DVec3::new(1_000.0, 0.0, 0.0)
            } else {
                DVec3::ZERO
            };
            origin.origin = eye - offset;
            let down = quincunx_bevy::to_bevy(-dir).as_vec3();
            let side = down.any_orthonormal_vector();
            *t = Transform::from_translation(quincunx_bevy::to_bevy(offset).as_vec3())
                .looking_to(down, side);
        }
        Scene::PlanetFar | Scene::PlanetColour => {
            let r = state.planet_radius_m().unwrap();
            let dir = DVec3::new(0.3, -0.8, 0.5).normalize();
            fly.spot = Some(dir * r);
            origin.origin = dir * (r + 1.0e8);
            *t = Transform::IDENTITY.looking_to(quincunx_bevy::to_bevy(-dir).as_vec3(), Vec3::Y);
        }
    }
}

fn check(shots: &[Shot]) {
    for s in shots {
        let at = |p: Vec2| {
            let (x, y) = (p.x as u32, p.y as u32);
            (x < s.width && y < s.height).then(|| s.rgba[(y * s.width + x) as usize])
        };
        let background = s.rgba.iter().filter(|p| is_background(**p)).count();
        let red: Vec<(u32, u32)> = (0..s.height)
            .flat_map(|y| (0..s.width).map(move |x| (x, y)))
            .filter(|&(x, y)| is_red(s.rgba[(y * s.width + x) as usize]))
            .collect();
        eprintln!(
            "{:?}: {}x{}, {} triangles, {background} background pixels, {} cube pixels",
            s.scene,
            s.width,
            s.height,
            s.triangles,
            red.len()
        );
        assert!(s.triangles > 0, "{:?}: terrain drawn", s.scene);
        match s.scene {
            Scene::KoreaDown => {
                assert_eq!(background, 0, "straight down over korea: no background");
                let colours: std::collections::HashSet<[u8; 4]> = s.rgba.iter().copied().collect();
                assert!(
                    colours.len() > 100,
                    "shaded land: {} colours",
                    colours.len()
                );
                let c = s.cube_px.unwrap();
                assert!(is_red(at(c).unwrap()), "the cube at its projection {c}");
            }
            Scene::KoreaInSight => {
                assert!(red.len() > 20, "the cube in sight: {} pixels", red.len());
                let c = s.cube_px.unwrap();
                assert!(is_red(at(c).unwrap()), "the cube at its projection {c}");
                // Resting on the ground: its lowest pixel where the ground point projects.
                let g = s.ground_px.unwrap();
                let lowest = red.iter().map(|p| p.1).max().unwrap() as f32;
                assert!(
                    (lowest + 0.5 - g.y).abs() <= 2.0,
                    "the cube's lowest row {lowest} against its ground point's {g}"
                );
            }
            Scene::KoreaHidden => {
                assert_eq!(red.len(), 0, "the cube behind a ridge is hidden");
            }
            Scene::PlanetLow | Scene::PlanetLowShifted => {
                assert_eq!(background, 0, "1 m above the planet, straight down");
            }
            Scene::PlanetFar | Scene::PlanetColour => {
                let (c, r) = s.disk.unwrap();
                let mut inside = 0;
                for y in 0..s.height {
                    for x in 0..s.width {
                        let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                        if p.distance(c) < r - 2.0 {
                            inside += 1;
                            assert!(
                                !is_background(s.rgba[(y * s.width + x) as usize]),
                                "background at ({x}, {y}) inside the planet's disk ({c}, {r} px)"
                            );
                        }
                    }
                }
                assert!(inside > 1_000, "the disk holds {inside} pixels");
            }
        }
    }
    // The same view with the camera's f32 translation 1 km from Bevy's origin.
    let (a, b) = (&shots[3], &shots[4]);
    let diff: f64 = a
        .rgba
        .iter()
        .zip(&b.rgba)
        .map(|(p, q)| {
            (0..3)
                .map(|c| f64::from(p[c].abs_diff(q[c])).powi(2))
                .sum::<f64>()
        })
        .sum::<f64>()
        / (a.rgba.len() * 3) as f64;
    let psnr = 10.0 * (255f64.powi(2) / diff.max(1e-12)).log10();
    eprintln!("the planet 1 m up, origin at the camera against 1 km away: PSNR {psnr:.1} dB");
    assert!(psnr > 30.0, "PSNR {psnr} dB");

    // The same far view with the colour layer: inside the disk, most pixels other than
    // the shading without it; the imagery's oceans blue, its land not.
    let (plain, coloured) = (&shots[5], &shots[6]);
    let (c, r) = coloured.disk.unwrap();
    let (mut inside, mut changed, mut blue, mut land) = (0usize, 0usize, 0usize, 0usize);
    for y in 0..coloured.height {
        for x in 0..coloured.width {
            if Vec2::new(x as f32 + 0.5, y as f32 + 0.5).distance(c) >= r - 2.0 {
                continue;
            }
            let k = (y * coloured.width + x) as usize;
            let (p, q) = (coloured.rgba[k], plain.rgba[k]);
            // The cube stands on the disk in both.
            if is_red(p) {
                continue;
            }
            inside += 1;
            if (0..3).any(|i| p[i].abs_diff(q[i]) > 24) {
                changed += 1;
            }
            if i32::from(p[2]) > i32::from(p[0]) + 20 {
                blue += 1;
            } else if p[0] >= p[2] {
                land += 1;
            }
        }
    }
    let share = |n: usize| n as f64 / inside as f64;
    eprintln!(
        "the planet with colour: {inside} disk pixels, {:.0} % other than without colour, \
         {:.0} % blue, {:.0} % land",
        100.0 * share(changed),
        100.0 * share(blue),
        100.0 * share(land)
    );
    assert!(
        share(changed) > 0.5,
        "the colour layer drawn: {changed} of {inside}"
    );
    assert!(
        share(blue) > 0.2 && share(land) > 0.05,
        "{blue} blue, {land} land"
    );
}
