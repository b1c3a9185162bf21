//! Frame time of a Bevy app drawing quincunx terrain, on the view of
//! `render/examples/embed.rs` (960x540, 60 degrees, from above a corner of the data
//! towards its centre), after the cut reaches full quality; one JSON line.
//!
//! ```text
//! cargo run --release -p quincunx-bevy --example bench -- http://127.0.0.1:8080 korea [FRAMES] [--empty]
//! ```
//! `--empty` measures the same app without the terrain (the camera and the clear only):
//! what Bevy costs by itself.

use std::time::{Duration, Instant};

use bevy::core_pipeline::tonemapping::Tonemapping;
use bevy::prelude::*;
use bevy::window::{PresentMode, WindowResolution};
use bevy::winit::{UpdateMode, WinitSettings};
use glam::DVec3;
use quincunx_bevy::{QuincunxPlugin, Terrain, TerrainCamera, TerrainOrigin, TerrainState};

#[derive(Resource)]
struct Bench {
    empty: bool,
    frames: usize,
    settled: u32,
    placed: bool,
    times_ms: Vec<f64>,
    last: Option<Instant>,
    started: Instant,
    triangles: u64,
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let url = args.first().map_or("http://127.0.0.1:8080", String::as_str);
    let repo = args.get(1).map_or("korea", String::as_str);
    let frames = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(300);
    let empty = args.iter().any(|a| a == "--empty");
    let mut app = App::new();
    app.add_plugins((
        DefaultPlugins.set(WindowPlugin {
            primary_window: Some(Window {
                title: "quincunx bench".into(),
                resolution: WindowResolution::new(960, 540),
                present_mode: PresentMode::AutoNoVsync,
                ..default()
            }),
            ..default()
        }),
        QuincunxPlugin,
    ))
    // Frames as fast as they go, focused or not (an unfocused window, as under Xvfb,
    // otherwise updates at most 60 times a second).
    .insert_resource(WinitSettings {
        focused_mode: UpdateMode::Continuous,
        unfocused_mode: UpdateMode::Continuous,
    })
    .insert_resource(ClearColor(Color::srgb(0.25, 0.4, 0.65)))
    .insert_resource(TerrainOrigin {
        recentre_beyond_m: None,
        ..default()
    })
    .insert_resource(Bench {
        empty,
        frames,
        settled: 0,
        placed: false,
        times_ms: Vec::new(),
        last: None,
        started: Instant::now(),
        triangles: 0,
    })
    .add_systems(Startup, |mut commands: Commands| {
        commands.spawn((
            Camera3d::default(),
            TerrainCamera,
            Msaa::Off,
            // The terrain's colours as quincunx's own viewers show them (Bevy's default
            // tonemapper needs its LUT feature, and would tone the terrain on HDR
            // cameras only).
            Tonemapping::None,
            Projection::Perspective(PerspectiveProjection {
                fov: 60f32.to_radians(),
                ..default()
            }),
        ));
    })
    .add_systems(Update, measure);
    if !empty {
        app.insert_resource(Terrain::new(url, repo));
    }
    app.run();
}

fn measure(
    mut bench: ResMut<Bench>,
    state: Res<TerrainState>,
    mut origin: ResMut<TerrainOrigin>,
    mut camera: Query<&mut Transform, With<TerrainCamera>>,
    mut exit: MessageWriter<AppExit>,
) {
    if bench.started.elapsed() > Duration::from_secs(120) {
        eprintln!("bench: did not settle in 120 s: {:?}", state.stats());
        exit.write(AppExit::error());
        return;
    }
    if !bench.empty && !bench.placed {
        let (Some((min, max)), Ok(mut t)) = (state.bounds(), camera.single_mut()) else {
            return;
        };
        // embed.rs's view.
        let eye = DVec3::new(min.x, max.y, max.z + 8_000.0);
        let target = DVec3::new((min.x + max.x) / 2.0, (min.y + max.y) / 2.0, min.z);
        origin.origin = eye;
        *t = Transform::IDENTITY.looking_at(origin.to_bevy(target), Vec3::Y);
        bench.placed = true;
        return;
    }
    let s = state.stats();
    let current = bench.empty
        || (s.full_quality && s.patches_drawn == s.cut_halves && s.patches_missing == 0);
    if bench.settled < 60 {
        bench.settled = if current { bench.settled + 1 } else { 0 };
        return;
    }
    let now = Instant::now();
    if let Some(last) = bench.last {
        bench.times_ms.push((now - last).as_secs_f64() * 1e3);
    }
    bench.last = Some(now);
    bench.triangles = s.triangles_drawn;
    if bench.times_ms.len() >= bench.frames {
        let mut t = bench.times_ms.clone();
        t.sort_by(f64::total_cmp);
        let q = |p: f64| t[((t.len() - 1) as f64 * p).round() as usize];
        println!(
            "{{\"app\":\"bevy\",\"terrain\":{},\"frames\":{},\"frame_ms_median\":{:.3},\"frame_ms_p90\":{:.3},\"triangles\":{}}}",
            !bench.empty,
            t.len(),
            q(0.5),
            q(0.9),
            bench.triangles
        );
        exit.write(AppExit::Success);
    }
}
