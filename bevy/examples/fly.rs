//! Fly over a quincunx repository in Bevy: a plane or a whole planet, streamed from a
//! `quincunx serve`, with a Bevy cube set on the ground by a height query.
//!
//! ```text
//! cargo run --release -p quincunx-bevy --example fly -- http://127.0.0.1:8080 korea
//! cargo run --release -p quincunx-bevy --example fly -- http://127.0.0.1:8080 earth --colour earth_colour
//! ```
//! (`quincunx demo` serves both; on Rust older than 1.97.1 add `--ignore-rust-version`
//! after `run`.)
//!
//! Keys: W/S forward and back, A/D left and right, E/Q up and down, Shift faster; drag
//! with the left mouse button to look around. The speed follows the height above the
//! ground. The window title shows the frame rate and the terrain's live figures.

use bevy::core_pipeline::tonemapping::Tonemapping;
use bevy::input::mouse::AccumulatedMouseMotion;
use bevy::prelude::*;
use bevy::window::{PresentMode, WindowResolution};
use quincunx_bevy::{QuincunxPlugin, Terrain, TerrainCamera, TerrainOrigin, TerrainState};

/// Marks the cube the height query places.
#[derive(Component)]
pub struct Marker;

/// Where the marker stands (Bevy coordinates, before the ground is known) and the
/// camera's yaw and pitch.
#[derive(Resource, Default)]
pub struct Fly {
    /// Whether the camera was placed over the terrain yet.
    pub placed: bool,
    /// Yaw and pitch (radians).
    pub yaw: f32,
    /// Pitch.
    pub pitch: f32,
    /// The marker's spot, quincunx coordinates.
    pub spot: Option<glam::DVec3>,
    /// Smoothed frame time, seconds.
    pub frame_s: f32,
}

/// The app: window, plugin, scene and controls (the tests add their own systems).
pub fn app(url: &str, repo: &str, colour: Option<&str>, size: (u32, u32)) -> App {
    let mut terrain = Terrain::new(url, repo);
    terrain.colour = colour.map(str::to_owned);
    let mut app = App::new();
    app.add_plugins((
        DefaultPlugins.set(WindowPlugin {
            primary_window: Some(Window {
                title: "quincunx in Bevy".into(),
                resolution: WindowResolution::new(size.0, size.1),
                present_mode: PresentMode::AutoNoVsync,
                ..default()
            }),
            ..default()
        }),
        QuincunxPlugin,
    ))
    .insert_resource(terrain)
    .insert_resource(ClearColor(Color::srgb(0.53, 0.67, 0.82)))
    .init_resource::<Fly>()
    .add_systems(Startup, setup)
    .add_systems(
        Update,
        (place_camera, controls, place_marker, title).chain(),
    );
    app
}

fn setup(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    commands.spawn((
        Camera3d::default(),
        TerrainCamera,
        Msaa::Off,
        // The terrain's colours as quincunx's own viewers show them (Bevy's default
        // tonemapper needs its LUT feature, and would tone the terrain on HDR cameras
        // only).
        Tonemapping::None,
        Transform::from_xyz(0.0, 10.0, 0.0),
    ));
    commands.spawn((
        DirectionalLight {
            illuminance: 8_000.0,
            ..default()
        },
        Transform::default().looking_to(Vec3::new(-0.4, -1.0, -0.3), Vec3::Y),
    ));
    commands.spawn((
        Marker,
        Mesh3d(meshes.add(Cuboid::new(1.0, 1.0, 1.0))),
        MeshMaterial3d(materials.add(StandardMaterial {
            base_color: Color::srgb(1.0, 0.0, 0.0),
            unlit: true,
            ..default()
        })),
        Transform::from_xyz(0.0, -1.0e6, 0.0),
    ));
}

/// Once the terrain is open: the origin at the data, the camera above it looking
/// across (a plane) or at the planet from three radii (a planet).
fn place_camera(
    state: Res<TerrainState>,
    mut origin: ResMut<TerrainOrigin>,
    mut fly: ResMut<Fly>,
    mut camera: Query<&mut Transform, With<TerrainCamera>>,
) {
    if fly.placed {
        return;
    }
    let (Some((min, max)), Ok(mut t)) = (state.bounds(), camera.single_mut()) else {
        return;
    };
    fly.placed = true;
    let centre = (min + max) / 2.0;
    match state.planet_radius_m() {
        Some(r) => {
            origin.origin = glam::DVec3::new(0.0, -3.0 * r, 0.0);
            *t = Transform::from_xyz(0.0, 0.0, 0.0)
                .looking_at(origin.to_bevy(glam::DVec3::ZERO), Vec3::Y);
            fly.spot = Some(glam::DVec3::new(0.0, -r, 0.0));
        }
        None => {
            origin.origin = glam::DVec3::new(min.x, min.y, max.z + 3_000.0);
            *t = Transform::from_xyz(0.0, 0.0, 0.0).looking_at(
                origin.to_bevy(glam::DVec3::new(centre.x, centre.y, min.z)),
                Vec3::Y,
            );
            fly.spot = Some(glam::DVec3::new(centre.x, centre.y, max.z));
        }
    }
    let (yaw, pitch, _) = t.rotation.to_euler(EulerRot::YXZ);
    (fly.yaw, fly.pitch) = (yaw, pitch);
}

#[allow(clippy::too_many_arguments)] // a Bevy system's parameters
fn controls(
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    motion: Res<AccumulatedMouseMotion>,
    time: Res<Time>,
    state: Res<TerrainState>,
    origin: Res<TerrainOrigin>,
    mut fly: ResMut<Fly>,
    mut camera: Query<&mut Transform, With<TerrainCamera>>,
) {
    let Ok(mut t) = camera.single_mut() else {
        return;
    };
    if buttons.pressed(MouseButton::Left) {
        fly.yaw -= motion.delta.x * 0.003;
        fly.pitch = (fly.pitch - motion.delta.y * 0.003).clamp(-1.55, 1.55);
        t.rotation = Quat::from_euler(EulerRot::YXZ, fly.yaw, fly.pitch, 0.0);
    }
    let mut go = Vec3::ZERO;
    for (key, dir) in [
        (KeyCode::KeyW, t.forward().as_vec3()),
        (KeyCode::KeyS, -t.forward().as_vec3()),
        (KeyCode::KeyD, t.right().as_vec3()),
        (KeyCode::KeyA, -t.right().as_vec3()),
        (KeyCode::KeyE, Vec3::Y),
        (KeyCode::KeyQ, Vec3::NEG_Y),
    ] {
        if keys.pressed(key) {
            go += dir;
        }
    }
    if go == Vec3::ZERO {
        return;
    }
    // A second to cross the height above the ground (or 100 m when it is unknown).
    let height = state
        .height_below(&origin, t.translation)
        .map_or(100.0, |g| (t.translation - g).length())
        .max(2.0);
    let boost = if keys.pressed(KeyCode::ShiftLeft) {
        5.0
    } else {
        1.0
    };
    t.translation += go.normalize() * height * boost * time.delta_secs();
}

/// Stands the cube on the drawn ground at its spot, sized to be seen from the camera.
fn place_marker(
    state: Res<TerrainState>,
    origin: Res<TerrainOrigin>,
    fly: Res<Fly>,
    camera: Query<&Transform, (With<TerrainCamera>, Without<Marker>)>,
    mut marker: Query<&mut Transform, With<Marker>>,
) {
    let (Some(spot), Ok(cam), Ok(mut m)) = (fly.spot, camera.single(), marker.single_mut()) else {
        return;
    };
    let at = origin.to_bevy(spot);
    let (Some(ground), Some(up)) = (state.height_below(&origin, at), state.up_at(&origin, at))
    else {
        return;
    };
    let side = ((cam.translation - ground).length() * 0.02).max(1.0);
    m.scale = Vec3::splat(side);
    m.rotation = Quat::from_rotation_arc(Vec3::Y, up);
    m.translation = ground + up * (side / 2.0);
}

fn title(
    time: Res<Time>,
    state: Res<TerrainState>,
    mut fly: ResMut<Fly>,
    mut windows: Query<&mut Window>,
) {
    fly.frame_s = if fly.frame_s == 0.0 {
        time.delta_secs()
    } else {
        0.95 * fly.frame_s + 0.05 * time.delta_secs()
    };
    let Ok(mut window) = windows.single_mut() else {
        return;
    };
    let s = state.stats();
    window.title = match state.error() {
        Some(e) => format!("quincunx: {e}"),
        None => format!(
            "quincunx | {:.0} fps | {} patches, {:.2} M triangles | cut {} halves{} | {:.1} MB fetched",
            1.0 / fly.frame_s.max(1e-6),
            s.patches_drawn,
            s.triangles_drawn as f64 / 1e6,
            s.cut_halves,
            if s.full_quality { ", full quality" } else { "" },
            s.bytes_fetched as f64 / 1e6,
        ),
    };
}

#[allow(dead_code)]
fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let url = args.first().map_or("http://127.0.0.1:8080", String::as_str);
    let repo = args.get(1).map_or("korea", String::as_str);
    let colour = args
        .iter()
        .position(|a| a == "--colour")
        .and_then(|k| args.get(k + 1))
        .map(String::as_str);
    app(url, repo, colour, (1280, 720)).run();
}
