//! Streams quincunx terrain (a plane or a whole planet) into a Bevy app and draws it in
//! Bevy's main 3D pass, on Bevy's own wgpu device, into Bevy's colour and depth targets:
//! Bevy's meshes and the terrain occlude each other.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use quincunx_bevy::{QuincunxPlugin, Terrain, TerrainCamera};
//!
//! fn main() {
//!     App::new()
//!         .add_plugins((DefaultPlugins, QuincunxPlugin))
//!         .insert_resource(Terrain::new("http://127.0.0.1:8080", "korea"))
//!         .add_systems(Startup, |mut commands: Commands| {
//!             commands.spawn((
//!                 Camera3d::default(),
//!                 TerrainCamera,
//!                 Transform::from_xyz(0.0, 3_000.0, 0.0).looking_to(Vec3::NEG_Z, Vec3::Y),
//!             ));
//!         })
//!         .run();
//! }
//! ```
//!
//! # Frames and precision
//!
//! Quincunx positions are f64 metres in the repository's frame (planar: `x` east, `y`
//! north, `z` up, the raster's corner at the origin; planets: centred on the planet,
//! `z` through the north pole). Bevy's are f32 and `y` up. [`TerrainOrigin`] holds the
//! quincunx position of Bevy's origin; a quincunx point `q` is at Bevy position
//! [`to_bevy`]`(q - origin)`. The terrain is drawn relative to the camera in f64 (the
//! renderer's camera-relative path), so its precision does not depend on the origin; a
//! Bevy mesh's does (f32 relative to the origin: about 1e-7 of its distance from it).
//! With [`TerrainOrigin::recentre_beyond_m`] set, the plugin moves the origin to the
//! camera whenever the camera gets that far from it, shifting every root entity's
//! `Transform` by the same amount (a floating origin).
//!
//! # What the plugin requires of the camera
//!
//! - The terrain is refined for and drawn in the one camera marked [`TerrainCamera`].
//! - Its projection is perspective. Bevy's projection is reversed Z with an infinite far
//!   plane, as the renderer's; the plugin sets the camera's near plane to the renderer's
//!   ([`quincunx_render::camera::NEAR_M`], 5 cm) so that both write the same depth.
//! - Any MSAA sample count and colour format (HDR or not): the renderer's pipeline is
//!   made for the view's, and made again if they change.
//! - Tonemapping: the terrain's shader writes lit colours, not tonemapped ones. On an
//!   HDR camera Bevy's tonemapping pass tones them with everything else; on an LDR
//!   camera Bevy tones its meshes in their own shaders and the terrain not at all.
//!   `Tonemapping::None` (the example's) shows the terrain as quincunx's viewers do.
//!
//! # Queries
//!
//! [`TerrainState::height_below`] and [`TerrainState::ray_hit`] answer against the
//! client's current cut, the surface as drawn (not the full-resolution data): its
//! distance to the data is within the refinement's tolerance, projected for the
//! camera that refined it. They are exact (f64) for that surface.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

use bevy::camera::{Camera, Projection};
use bevy::core_pipeline::core_3d::{main_opaque_pass_3d, main_transparent_pass_3d};
use bevy::core_pipeline::{Core3d, Core3dSystems};
use bevy::prelude::*;
use bevy::render::render_resource::{RenderPassDescriptor, StoreOp};
use bevy::render::renderer::{RenderContext, RenderDevice, RenderQueue, ViewQuery};
use bevy::render::sync_world::MainEntity;
use bevy::render::view::{Msaa, ViewDepthStencilTexture, ViewTarget};
use bevy::render::{ExtractSchedule, MainWorld, RenderApp};
use bevy::transform::TransformSystems;
use glam::DVec3;
use quincunx_client::colour::ColourLayer;
use quincunx_client::fine::WorldFrame;
use quincunx_client::session::{AnySession, PatchChanges, Session, SessionConfig, SessionError};
use quincunx_client::view::View;
use quincunx_decoder::incremental::{PlanarRefiner, SphereRefiner};
use quincunx_render::camera::NEAR_M;
use quincunx_render::domain::RenderDomain;
use quincunx_render::ground::SurfaceIndex;
use quincunx_render::offscreen::{copy_for_readback, map_read_on, readback_buffer};
use quincunx_render::{RendererConfig, TerrainRenderer};

pub use quincunx_client;
pub use quincunx_render;

/// What to stream and how finely: insert it as a resource (changing it reopens the
/// terrain).
#[derive(Resource, Clone, Debug, PartialEq)]
pub struct Terrain {
    /// Server URL (`http://` or `https://`), or a repository file's URL.
    pub url: String,
    /// Elevation repository.
    pub repo: String,
    /// Colour repository matched to it, if any.
    pub colour: Option<String>,
    /// Screen-space tolerance, pixels (the client's default metric: no drawn point
    /// more than this far on screen from the data).
    pub tolerance_px: f64,
    /// GPU memory for patches, bytes: the cut is bounded to what fits.
    pub gpu_budget_bytes: u64,
    /// Refinement time per frame (the network runs on its own threads: no frame waits
    /// on it).
    pub refine_budget: Duration,
}

impl Terrain {
    /// Repository `repo` at `url`, 1 px tolerance, 128 MB of GPU memory, 4 ms of
    /// refinement per frame.
    pub fn new(url: impl Into<String>, repo: impl Into<String>) -> Terrain {
        Terrain {
            url: url.into(),
            repo: repo.into(),
            colour: None,
            tolerance_px: 1.0,
            gpu_budget_bytes: 128 << 20,
            refine_budget: Duration::from_millis(4),
        }
    }

    /// With colour repository `colour`.
    pub fn with_colour(mut self, colour: impl Into<String>) -> Terrain {
        self.colour = Some(colour.into());
        self
    }
}

/// Marks the camera the terrain is refined for and drawn in (one at a time).
#[derive(Component, Clone, Copy, Debug, Default)]
pub struct TerrainCamera;

/// The quincunx position (f64 metres, the repository's frame) of Bevy's origin, and
/// when to move it.
#[derive(Resource, Clone, Copy, Debug, PartialEq)]
pub struct TerrainOrigin {
    /// Quincunx position of Bevy's `(0, 0, 0)`.
    pub origin: DVec3,
    /// Move the origin to the camera once the camera is this far from it (metres),
    /// shifting root entities with it; `None`: never.
    pub recentre_beyond_m: Option<f32>,
}

impl Default for TerrainOrigin {
    fn default() -> Self {
        TerrainOrigin {
            origin: DVec3::ZERO,
            recentre_beyond_m: Some(1_000.0),
        }
    }
}

impl TerrainOrigin {
    /// The Bevy position of quincunx point `q` (f32, relative to the origin).
    pub fn to_bevy(&self, q: DVec3) -> Vec3 {
        to_bevy(q - self.origin).as_vec3()
    }

    /// The quincunx position (f64) of Bevy position `b`.
    pub fn to_quincunx(&self, b: Vec3) -> DVec3 {
        self.origin + from_bevy(b.as_dvec3())
    }
}

/// A quincunx direction or offset (`z` up) in Bevy's axes (`y` up): `(x, z, -y)`.
pub fn to_bevy(q: DVec3) -> DVec3 {
    DVec3::new(q.x, q.z, -q.y)
}

/// A Bevy direction or offset in quincunx axes: the inverse of [`to_bevy`].
pub fn from_bevy(b: DVec3) -> DVec3 {
    DVec3::new(b.x, -b.z, b.y)
}

/// Figures of the last frame, for a HUD or a window title.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TerrainStats {
    /// Halves in the client's cut.
    pub cut_halves: usize,
    /// Whether the cut meets the tolerance everywhere in view.
    pub full_quality: bool,
    /// Blob bytes fetched since the terrain opened.
    pub bytes_fetched: u64,
    /// Refinement time of the frame.
    pub refine_ms: f64,
    /// Patches and triangles the renderer drew (the last frame it drew).
    pub patches_drawn: usize,
    /// Triangles.
    pub triangles_drawn: u64,
    /// Patches the GPU budget left out (0 unless the budget is too small).
    pub patches_missing: usize,
}

/// A read-back of the terrain camera's depth attachment after the terrain pass (reversed
/// Z: `near / distance`, 0 where nothing was drawn), for tests and tools: it costs a copy
/// of the attachment and a wait for the GPU. [`DepthReadback::request`] asks for the
/// next frame's; [`DepthReadback::take`] gives it a frame or two later. The camera needs
/// `Msaa::Off` and a depth attachment that can be copied from (`Camera3d`'s
/// `depth_texture_usages` with `TextureUsages::COPY_SRC`).
#[derive(Resource, Clone, Default)]
pub struct DepthReadback(Arc<Mutex<Readback>>);

#[derive(Default)]
struct Readback {
    wanted: bool,
    /// The buffer the copy went into: width, height, padded row bytes.
    copied: Option<(wgpu::Buffer, u32, u32, u32)>,
    done: Option<quincunx_render::DepthImage>,
}

impl DepthReadback {
    /// Asks for the depth of the next frame drawn.
    pub fn request(&self) {
        if let Ok(mut r) = self.0.lock() {
            r.wanted = true;
            r.done = None;
        }
    }

    /// The depth read back, once it is there (rows top to bottom, as
    /// [`quincunx_render::DepthImage`]).
    pub fn take(&self) -> Option<quincunx_render::DepthImage> {
        self.0.lock().ok()?.done.take()
    }
}

/// The streaming terrain in the main world: its state, its figures and the gameplay
/// queries.
#[derive(Resource, Default)]
pub struct TerrainState {
    inner: Mutex<Inner>,
    shared: Arc<Shared>,
}

/// What the render world tells the main world.
#[derive(Default)]
struct Shared {
    /// Patch slots of the renderer's pool (0 until it exists).
    capacity: AtomicUsize,
    /// The renderer was made anew: the next changes must list the whole cut.
    resync: AtomicBool,
    patches_drawn: AtomicUsize,
    triangles_drawn: AtomicU64,
    patches_missing: AtomicUsize,
}

#[derive(Default)]
enum Status {
    #[default]
    Closed,
    Opening(Mutex<mpsc::Receiver<Result<AnySession, SessionError>>>),
    Open(Box<Streaming>),
    Failed(String),
}

#[derive(Default)]
struct Inner {
    status: Status,
    opened_for: Option<Terrain>,
    stats: TerrainStats,
    /// The last epoch handed out: a new one for each session opened and each time the
    /// renderer is made anew, so the render world never mixes cuts.
    epoch: u64,
}

struct Streaming {
    session: AnySession,
    started: Instant,
    /// The cut's surface for queries, and whether the cut changed since it was made.
    surface: Option<Arc<SurfaceIndex>>,
    cut_changed: bool,
    epoch: u64,
    /// The repository's world frame and land tint, once a batch needed them.
    frame_of: Option<(WorldFrame, (f64, f64))>,
}

impl TerrainState {
    /// Whether the terrain is open and streaming.
    pub fn is_open(&self) -> bool {
        self.lock(|i| matches!(i.status, Status::Open(_)))
    }

    /// Why opening the terrain failed, if it did.
    pub fn error(&self) -> Option<String> {
        self.lock(|i| match &i.status {
            Status::Failed(why) => Some(why.clone()),
            _ => None,
        })
    }

    /// The last frame's figures.
    pub fn stats(&self) -> TerrainStats {
        let mut s = self.lock(|i| i.stats);
        s.patches_drawn = self.shared.patches_drawn.load(Ordering::Relaxed);
        s.triangles_drawn = self.shared.triangles_drawn.load(Ordering::Relaxed);
        s.patches_missing = self.shared.patches_missing.load(Ordering::Relaxed);
        s
    }

    /// The repository's box in its own frame (metres: planar data, or a planet's
    /// sphere with its heights), once open.
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        self.lock(|i| match &i.status {
            Status::Open(s) => Some(match &s.session {
                AnySession::Planar(p) => {
                    let b = p.bounds();
                    (b.min, b.max)
                }
                AnySession::Planet(p) => {
                    let r = planet_radius(p) + p.height_range().1.max(0.0);
                    (DVec3::splat(-r), DVec3::splat(r))
                }
            }),
            _ => None,
        })
    }

    /// The planet's radius at height 0 (metres); `None` for a plane or before opening.
    pub fn planet_radius_m(&self) -> Option<f64> {
        self.lock(|i| match &i.status {
            Status::Open(s) => match &s.session {
                AnySession::Planet(p) => Some(planet_radius(p)),
                AnySession::Planar(_) => None,
            },
            _ => None,
        })
    }

    /// The point of the drawn surface straight below (or above) Bevy position `at`,
    /// along the local up (planes: Bevy's `+y`; planets: away from the centre), in Bevy
    /// coordinates; `None` before the terrain is open or off the data.
    pub fn height_below(&self, origin: &TerrainOrigin, at: Vec3) -> Option<Vec3> {
        let surface = self.surface()?;
        let q = origin.to_quincunx(at);
        let hit = surface.along(q, surface.up(q))?;
        Some(origin.to_bevy(hit))
    }

    /// The first point where the ray from Bevy position `from` along `dir` meets the
    /// drawn surface, in Bevy coordinates (picking, line of sight). Costs a pass over
    /// the cut's patch boxes: a few rays per frame, not one per pixel.
    pub fn ray_hit(&self, origin: &TerrainOrigin, from: Vec3, dir: Vec3) -> Option<Vec3> {
        let surface = self.surface()?;
        let hit = surface.first_hit(origin.to_quincunx(from), from_bevy(dir.as_dvec3()))?;
        Some(origin.to_bevy(hit))
    }

    /// The local up direction at Bevy position `at`, in Bevy axes.
    pub fn up_at(&self, origin: &TerrainOrigin, at: Vec3) -> Option<Vec3> {
        let surface = self.surface()?;
        Some(to_bevy(surface.up(origin.to_quincunx(at))).as_vec3())
    }

    fn surface(&self) -> Option<Arc<SurfaceIndex>> {
        self.lock(|i| {
            let Status::Open(s) = &mut i.status else {
                return None;
            };
            if s.cut_changed || s.surface.is_none() {
                s.surface = Some(Arc::new(match &s.session {
                    AnySession::Planar(p) => SurfaceIndex::new(p),
                    AnySession::Planet(p) => SurfaceIndex::new(p),
                }));
                s.cut_changed = false;
            }
            s.surface.clone()
        })
    }

    fn lock<T>(&self, f: impl FnOnce(&mut Inner) -> T) -> T {
        let mut guard = match self.inner.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        };
        f(&mut guard)
    }
}

fn planet_radius(p: &Session<SphereRefiner>) -> f64 {
    match p.core().refiner().world_frame(&p.world(), 0).geometry {
        quincunx_client::fine::Geometry::Planet { radius_m, .. } => radius_m,
        quincunx_client::fine::Geometry::Planar { .. } => 0.0,
    }
}

/// Streams the [`Terrain`] resource's repository and draws it in the
/// [`TerrainCamera`]'s main 3D pass.
pub struct QuincunxPlugin;

impl Plugin for QuincunxPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<TerrainState>()
            .init_resource::<TerrainOrigin>()
            .init_resource::<Outbox>()
            .init_resource::<DepthReadback>()
            .add_systems(
                PostUpdate,
                (
                    recentre.before(TransformSystems::Propagate),
                    (open, stream).chain().after(TransformSystems::Propagate),
                ),
            );
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            tracing::warn!("QuincunxPlugin without a render app: the terrain streams, undrawn");
            return;
        };
        render_app
            .init_resource::<Drawer>()
            .add_systems(ExtractSchedule, extract)
            .add_systems(
                Core3d,
                draw.after(main_opaque_pass_3d)
                    .before(main_transparent_pass_3d)
                    .in_set(Core3dSystems::MainPass),
            );
    }
}

/// Moves the origin to the camera when it strayed beyond `recentre_beyond_m`.
fn recentre(
    mut origin: ResMut<TerrainOrigin>,
    camera: Query<Entity, With<TerrainCamera>>,
    mut roots: Query<(Entity, &mut Transform), Without<ChildOf>>,
) {
    let (Some(beyond), Ok(cam)) = (origin.recentre_beyond_m, camera.single()) else {
        return;
    };
    let Ok((_, t)) = roots.get(cam) else { return };
    let shift = t.translation;
    if shift.length() <= beyond {
        return;
    }
    origin.origin += from_bevy(shift.as_dvec3());
    for (_, mut t) in &mut roots {
        t.translation -= shift;
    }
}

/// Opens (or reopens) the terrain when the [`Terrain`] resource appears or changes.
fn open(terrain: Option<Res<Terrain>>, state: Res<TerrainState>) {
    let Some(terrain) = terrain else { return };
    state.lock(|i| {
        if i.opened_for.as_ref() != Some(&*terrain) {
            i.opened_for = Some(terrain.clone());
            let (tx, rx) = mpsc::channel();
            let t = terrain.clone();
            let spawned = std::thread::Builder::new()
                .name("quincunx-open".into())
                .spawn(move || {
                    let config = SessionConfig::default();
                    let _ = tx.send(AnySession::open_with_colour(
                        &t.url,
                        &t.repo,
                        t.colour.as_deref(),
                        config,
                    ));
                });
            i.status = match spawned {
                Ok(_) => Status::Opening(Mutex::new(rx)),
                Err(e) => Status::Failed(format!("starting a thread: {e}")),
            };
        }
        if let Status::Opening(rx) = &i.status {
            let got = rx.lock().ok().and_then(|rx| rx.try_recv().ok());
            match got {
                Some(Ok(session)) => {
                    i.epoch += 1;
                    i.status = Status::Open(Box::new(Streaming {
                        session,
                        started: Instant::now(),
                        surface: None,
                        cut_changed: true,
                        epoch: i.epoch,
                        frame_of: None,
                    }))
                }
                Some(Err(e)) => {
                    tracing::error!("opening the terrain: {e}");
                    i.status = Status::Failed(e.to_string());
                }
                None => {}
            }
        }
    });
}

/// One layer's cut changes and what applying them needs, for the render world.
struct Batch<R: RenderDomain> {
    refiner: Arc<R>,
    colour: Option<Arc<ColourLayer<R>>>,
    world: WorldFrame,
    tint_m: (f64, f64),
    changes: PatchChanges<R::Id>,
}

enum AnyBatch {
    Planar(Batch<PlanarRefiner>),
    Planet(Batch<SphereRefiner>),
}

/// What the main world hands the render world at the next extraction.
#[derive(Resource, Default)]
struct Outbox {
    batches: Vec<(u64, AnyBatch)>,
    camera: Option<(Entity, quincunx_render::Camera)>,
    epoch: u64,
    shared: Option<Arc<Shared>>,
    gpu_budget_bytes: u64,
}

/// Refines the cut for the terrain camera and queues its changes for the renderer.
fn stream(
    terrain: Option<Res<Terrain>>,
    state: Res<TerrainState>,
    origin: Res<TerrainOrigin>,
    mut outbox: ResMut<Outbox>,
    mut cameras: Query<(Entity, &Camera, &GlobalTransform, &mut Projection), With<TerrainCamera>>,
) {
    let Some(terrain) = terrain else { return };
    let Ok((entity, camera, at, mut projection)) = cameras.single_mut() else {
        return;
    };
    let Projection::Perspective(p) = &mut *projection else {
        return;
    };
    if p.near != NEAR_M as f32 {
        p.near = NEAR_M as f32;
    }
    let fov = f64::from(p.fov);
    let Some(size) = camera.physical_viewport_size() else {
        return;
    };
    if size.x == 0 || size.y == 0 {
        return;
    }
    let eye = origin.to_quincunx(at.translation());
    let forward = from_bevy(at.forward().as_vec3().as_dvec3());
    let up = from_bevy(at.up().as_vec3().as_dvec3());
    let view = View {
        eye,
        target: eye + forward,
        up,
        fov_y_rad: fov,
        viewport_px: [size.x, size.y],
        tolerance_px: terrain.tolerance_px,
    };
    outbox.camera = Some((entity, quincunx_render::Camera::from_view(&view)));
    outbox.shared = Some(Arc::clone(&state.shared));
    outbox.gpu_budget_bytes = terrain.gpu_budget_bytes;
    let shared = Arc::clone(&state.shared);
    state.lock(|i| {
        let Status::Open(s) = &mut i.status else {
            return;
        };
        if shared.resync.swap(false, Ordering::AcqRel) {
            i.epoch += 1;
            s.epoch = i.epoch;
            match &mut s.session {
                AnySession::Planar(p) => p.restart_cut_changes(),
                AnySession::Planet(p) => p.restart_cut_changes(),
            }
        }
        outbox.epoch = s.epoch;
        let tick = Tick {
            view: &view,
            now: s.started.elapsed(),
            budget: terrain.refine_budget,
            capacity: shared.capacity.load(Ordering::Acquire),
        };
        let result = match &mut s.session {
            AnySession::Planar(p) => {
                step(p, &tick, &mut s.frame_of).map(|(f, b)| (f, b.map(AnyBatch::Planar)))
            }
            AnySession::Planet(p) => {
                step(p, &tick, &mut s.frame_of).map(|(f, b)| (f, b.map(AnyBatch::Planet)))
            }
        };
        match result {
            Ok((stats, batch)) => {
                i.stats = stats;
                if let Some(b) = batch {
                    s.cut_changed = true;
                    outbox.batches.push((s.epoch, b));
                }
            }
            Err(e) => tracing::warn!("terrain frame: {e}"),
        }
    });
}

/// What one session frame runs under: the view, the session's clock, the refinement
/// budget and the renderer's capacity in halves (0 until known).
struct Tick<'a> {
    view: &'a View,
    now: Duration,
    budget: Duration,
    capacity: usize,
}

/// One session frame: refine, and the cut's changes if any.
fn step<R: RenderDomain>(
    session: &mut Session<R>,
    tick: &Tick<'_>,
    frame_of: &mut Option<(WorldFrame, (f64, f64))>,
) -> Result<(TerrainStats, Option<Batch<R>>), SessionError> {
    let capacity = tick.capacity;
    if capacity > 0 && session.max_cut_halves().is_none_or(|m| m > capacity) {
        session.set_max_cut_halves(Some(capacity));
    }
    let frame = session.update(tick.view, tick.now, tick.budget)?;
    let stats = TerrainStats {
        cut_halves: frame.refine.cut_halves,
        full_quality: frame.refine.full_quality,
        bytes_fetched: session.fetch_stats().bytes_fetched
            + session.colour_fetch_stats().map_or(0, |c| c.bytes_fetched),
        refine_ms: frame.elapsed.as_secs_f64() * 1e3,
        ..TerrainStats::default()
    };
    let changes = session.cut_changes();
    if changes.entered.is_empty() && changes.left.is_empty() {
        return Ok((stats, None));
    }
    let core = session.core();
    let colour = core.colour_layer().cloned();
    // The world frame and land tint: the repository's, made once per session.
    let (world, tint_m) = *frame_of.get_or_insert_with(|| {
        let colour_n = colour.as_ref().map_or(0, |c| c.n());
        let world = core.refiner().world_frame(&session.world(), colour_n);
        (
            world,
            quincunx_render::renderer::land_tint_m(&**core.refiner(), &world),
        )
    });
    Ok((
        stats,
        Some(Batch {
            refiner: Arc::clone(core.refiner()),
            colour,
            world,
            tint_m,
            changes,
        }),
    ))
}

/// The renderer in the render world.
#[derive(Resource, Default)]
struct Drawer {
    renderer: Option<AnyRenderer>,
    /// Colour format and MSAA samples the renderer was made for.
    made_for: Option<(wgpu::TextureFormat, u32)>,
    pending: Vec<(u64, AnyBatch)>,
    /// The main world's epoch, and the one the renderer was made in.
    epoch: u64,
    renderer_epoch: u64,
    /// A resync was asked for in this epoch: its batches are deltas to drop.
    stale_epoch: Option<u64>,
    camera: Option<(Entity, quincunx_render::Camera)>,
    shared: Option<Arc<Shared>>,
    gpu_budget_bytes: u64,
    readback: Option<DepthReadback>,
}

enum AnyRenderer {
    Planar(Box<TerrainRenderer<PlanarRefiner>>),
    Planet(Box<TerrainRenderer<SphereRefiner>>),
}

/// Moves the main world's queued changes and camera into the render world.
fn extract(mut main: ResMut<MainWorld>, mut drawer: ResMut<Drawer>) {
    drawer.readback = main.get_resource::<DepthReadback>().cloned();
    let Some(mut outbox) = main.get_resource_mut::<Outbox>() else {
        return;
    };
    let batches = std::mem::take(&mut outbox.batches);
    drawer.epoch = outbox.epoch;
    drawer.camera = outbox.camera;
    drawer.shared.clone_from(&outbox.shared);
    drawer.gpu_budget_bytes = outbox.gpu_budget_bytes;
    drawer.pending.extend(batches);
}

/// Draws the terrain into the terrain camera's main pass, after Bevy's opaque meshes,
/// with Bevy's depth attachment.
fn draw(
    view: ViewQuery<(
        &ViewTarget,
        &ViewDepthStencilTexture,
        &MainEntity,
        Option<&Msaa>,
    )>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    mut drawer: ResMut<Drawer>,
    mut ctx: RenderContext,
) {
    let (target, depth, main_entity, msaa) = view.into_inner();
    let Some((camera_entity, camera)) = drawer.camera else {
        return;
    };
    if main_entity.id() != camera_entity {
        return;
    }
    if let Some(r) = &drawer.readback {
        finish_readback(device.wgpu_device(), r);
    }
    let drawer = &mut *drawer;
    let made_for = (target.main_texture_format(), msaa.map_or(1, Msaa::samples));
    let epoch = drawer.epoch;
    // A renderer per epoch (a session, or the whole cut again), made for the view's
    // targets with the epoch's first batch (it carries the world frame); when the
    // targets change, the main world is asked for the whole cut in a new epoch.
    if drawer.renderer.is_some()
        && (drawer.renderer_epoch != epoch || drawer.made_for != Some(made_for))
    {
        if drawer.renderer_epoch == epoch {
            drawer.stale_epoch = Some(epoch);
            if let Some(s) = &drawer.shared {
                s.resync.store(true, Ordering::Release);
            }
        }
        drawer.renderer = None;
    }
    let stale = drawer.stale_epoch;
    drawer
        .pending
        .retain(|(e, _)| *e == epoch && Some(*e) != stale);
    for (_, batch) in std::mem::take(&mut drawer.pending) {
        if drawer.renderer.is_none() {
            let config = RendererConfig {
                gpu_budget_bytes: drawer.gpu_budget_bytes,
                colour_format: made_for.0,
                sample_count: made_for.1,
                ..RendererConfig::default()
            };
            let made = match &batch {
                AnyBatch::Planar(b) => {
                    make(device.wgpu_device(), b, config).map(AnyRenderer::Planar)
                }
                AnyBatch::Planet(b) => {
                    make(device.wgpu_device(), b, config).map(AnyRenderer::Planet)
                }
            };
            match made {
                Ok(r) => {
                    let capacity = match &r {
                        AnyRenderer::Planar(r) => r.capacity(),
                        AnyRenderer::Planet(r) => r.capacity(),
                    };
                    if let Some(s) = &drawer.shared {
                        s.capacity.store(capacity as usize, Ordering::Release);
                    }
                    drawer.renderer = Some(r);
                    drawer.made_for = Some(made_for);
                    drawer.renderer_epoch = epoch;
                }
                Err(e) => {
                    tracing::error!("making the terrain renderer: {e}");
                    return;
                }
            }
        }
        let applied = match (&mut drawer.renderer, batch) {
            (Some(AnyRenderer::Planar(r)), AnyBatch::Planar(b)) => {
                r.apply(&b.refiner, b.colour.as_deref(), b.changes)
            }
            (Some(AnyRenderer::Planet(r)), AnyBatch::Planet(b)) => {
                r.apply(&b.refiner, b.colour.as_deref(), b.changes)
            }
            _ => Ok(()),
        };
        if let Err(e) = applied {
            tracing::error!("terrain cut changes: {e}");
        }
    }
    let Some(renderer) = &mut drawer.renderer else {
        return;
    };
    let stats = match renderer {
        AnyRenderer::Planar(r) => r.prepare(&queue, &camera),
        AnyRenderer::Planet(r) => r.prepare(&queue, &camera),
    };
    if let Some(s) = &drawer.shared {
        s.patches_drawn.store(stats.patches, Ordering::Relaxed);
        s.triangles_drawn.store(stats.triangles, Ordering::Relaxed);
        s.patches_missing.store(stats.missing, Ordering::Relaxed);
    }
    let colour = [Some(target.get_color_attachment())];
    let mut pass = ctx
        .command_encoder()
        .begin_render_pass(&RenderPassDescriptor {
            label: Some("quincunx terrain"),
            color_attachments: &colour,
            depth_stencil_attachment: Some(depth.get_attachment(StoreOp::Store)),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    match renderer {
        AnyRenderer::Planar(r) => r.draw(&mut pass),
        AnyRenderer::Planet(r) => r.draw(&mut pass),
    }
    drop(pass);
    if let Some(r) = &drawer.readback {
        start_readback(
            device.wgpu_device(),
            ctx.command_encoder(),
            depth.texture(),
            r,
        );
    }
}

/// Copies the depth attachment into a buffer when a read-back is wanted (mapped by
/// [`finish_readback`] once this frame's commands were submitted).
fn start_readback(
    device: &wgpu::Device,
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    readback: &DepthReadback,
) {
    let Ok(mut r) = readback.0.lock() else { return };
    if !r.wanted || r.copied.is_some() {
        return;
    }
    if texture.sample_count() != 1 || !texture.usage().contains(wgpu::TextureUsages::COPY_SRC) {
        tracing::error!(
            "depth read-back needs Msaa::Off and a depth attachment with COPY_SRC usage \
             (Camera3d::depth_texture_usages)"
        );
        r.wanted = false;
        return;
    }
    let (w, h) = (texture.width(), texture.height());
    let (buffer, padded) = readback_buffer(device, [w, h], "quincunx-bevy depth read-back");
    copy_for_readback(
        encoder,
        texture,
        wgpu::TextureAspect::DepthOnly,
        &buffer,
        padded,
    );
    r.wanted = false;
    r.copied = Some((buffer, w, h, padded));
}

/// Maps the buffer a previous frame copied the depth into and keeps its values.
fn finish_readback(device: &wgpu::Device, readback: &DepthReadback) {
    let Ok(mut r) = readback.0.lock() else { return };
    let Some((buffer, w, h, padded)) = r.copied.take() else {
        return;
    };
    match map_read_on(device, &buffer, |b| {
        quincunx_render::DepthImage::from_padded(b, w, h, padded)
    }) {
        Ok(depth) => r.done = Some(depth),
        Err(e) => tracing::error!("depth read-back: {e}"),
    }
}

/// A renderer for a batch's repository.
fn make<R: RenderDomain>(
    device: &wgpu::Device,
    batch: &Batch<R>,
    config: RendererConfig,
) -> Result<Box<TerrainRenderer<R>>, quincunx_render::RenderError> {
    let mut renderer = TerrainRenderer::new(device, batch.world, config)?;
    renderer.lighting.tint_m = Some(batch.tint_m);
    Ok(Box::new(renderer))
}
