//! `quincunx view`: a window over a served repository (winit 0.30 + wgpu), streaming as
//! the camera moves, with the live figures in the title.
//!
//! The camera orbits a target point: it is `distance` metres from the target, at a
//! heading and pitch measured in the local frame (up, north, east) at the target. Fly
//! keys move target and eye together; the eye is kept above the streamed ground.

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use clap::Args;
use glam::DVec3;
use quincunx_client::domain::World;
use quincunx_client::refine::RefineConfig;
use quincunx_client::session::{AnySession, Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_render::domain::RenderDomain;
use quincunx_render::ground::surface_height_m;
use quincunx_render::offscreen::{Gpu, Image, copy_for_readback, map_read, readback_buffer};
use quincunx_render::scene::{Place, Shot};
use quincunx_render::{Camera, DEPTH_FORMAT, Geometry, RendererConfig, TerrainRenderer};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop, OwnedDisplayHandle};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

const CONTROLS: &str = "\
Controls:
  left drag       orbit about the target point
  right drag      pan (move the target over the ground)
  wheel           zoom towards / away from the target
  W A S D         fly forward / left / back / right (speed grows with height above ground)
  Q E             fly down / up
  [ ]             halve / double the screen-space tolerance
  F               wireframe on / off
  L               colour by level on / off
  Esc             quit
The title shows fps, triangles, patches, tolerance (px) and bytes/s received, twice a second.

--screenshot saves the window's own image (the surface texture, copied before it is
presented) where the surface allows copies (COPY_SRC); otherwise the last frame is also
drawn into an offscreen texture of the same size and format, and that is saved. The
backend is Vulkan when it has an adapter (lavapipe under Xvfb), else any (WGPU_BACKEND
overrides).";

/// `quincunx view` options.
#[derive(Args, Debug, Clone)]
#[command(after_help = CONTROLS)]
pub struct ViewArgs {
    /// Where to stream from.
    #[command(flatten)]
    pub server: crate::args::ServerArgs,
    /// Where the camera is and where it looks.
    #[command(flatten)]
    pub camera: crate::args::CameraArgs,
    /// Metres above the streamed terrain (default: half the raster's width, or one and
    /// a half radii over a planet).
    #[arg(long)]
    pub height_m: Option<f64>,
    /// What the tolerance bounds.
    #[command(flatten)]
    pub refine: crate::args::RefineArgs,
    /// Window size `WxH` (physical pixels).
    #[arg(long, default_value = "1280x720", value_parser = crate::fly::parse_viewport)]
    pub size: [u32; 2],
    /// GPU memory budget for patches, MB.
    #[arg(long, default_value_t = 256.0)]
    pub gpu_budget_mb: f64,
    /// Wait for the display's refresh (default: present as fast as frames are drawn).
    #[arg(long)]
    pub vsync: bool,
    /// Quit after this many frames.
    #[arg(long)]
    pub frames: Option<u64>,
    /// With `--frames`: save the last frame's window image as a PNG.
    #[arg(long, requires = "frames")]
    pub screenshot: Option<PathBuf>,
}

/// Runs `quincunx view`.
pub fn run(args: &ViewArgs) -> Result<()> {
    args.refine.check().map_err(anyhow::Error::msg)?;
    if !(args.gpu_budget_mb.is_finite()
        && args.gpu_budget_mb > 0.0
        && args.gpu_budget_mb <= 65_536.0)
    {
        bail!(
            "--gpu-budget-mb {} must be above 0 and at most 65536",
            args.gpu_budget_mb
        );
    }
    if args.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    if let Some(h) = args.height_m
        && !(h.is_finite() && h > 0.0)
    {
        bail!("--height-m {h} must be above 0");
    }
    // The display first: without one there is nothing to do (and no reason to connect).
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow!(
            "cannot open a window: {e} (no display? `quincunx view` needs X11 or Wayland; \
             on a headless machine run it under `xvfb-run -a`)"
        )
    })?;
    let mut session = AnySession::open_with_colour(
        &args.server.url,
        &args.server.repo,
        args.server.colour.as_deref(),
        SessionConfig {
            connect: crate::fly::link_options(args.server.ca_cert.as_ref(), None),
            refine: RefineConfig {
                metric: args.refine.metric,
                ..RefineConfig::default()
            },
            ..SessionConfig::default()
        },
    )
    .with_context(|| format!("opening {} at {}", args.server.repo, args.server.url))?;
    match &mut session {
        AnySession::Planar(s) => {
            s.warm_up(Duration::from_secs(5))?;
        }
        AnySession::Planet(s) => {
            s.warm_up(Duration::from_secs(5))?;
        }
    }
    match session {
        AnySession::Planar(s) => run_app(event_loop, s, args),
        AnySession::Planet(s) => run_app(event_loop, s, args),
    }
}

fn run_app<R: RenderDomain>(
    event_loop: EventLoop<()>,
    session: Session<R>,
    args: &ViewArgs,
) -> Result<()> {
    let world = session.dag().refiner().world_frame(&session.world(), 0);
    let (place, default_height) = match world.geometry {
        Geometry::Planar {
            metres_per_fine,
            extent_fine,
        } => {
            let (u, v) = args.camera.uv.unwrap_or((0.5, 0.5));
            let width = extent_fine[0].max(extent_fine[1]) as f64 * metres_per_fine;
            (Place::Uv(u, v), 0.5 * width)
        }
        Geometry::Planet { radius_m, .. } => {
            let (lat, lon) = args.camera.lat_lon.unwrap_or((0.0, 0.0));
            (Place::LatLon(lat, lon), 1.5 * radius_m)
        }
    };
    let shot = Shot {
        place,
        height_m: args.height_m.unwrap_or(default_height),
        heading_deg: args.camera.heading_deg,
        pitch_deg: args.camera.pitch_deg,
        fov_deg: args.camera.fov_deg,
        size: args.size,
        tolerance_px: args.refine.tolerance_px,
    };
    shot.validate()?;
    let (lo, hi) = session.height_range();
    let view = shot.view(&session, hi.max(lo))?;
    let datum = match world.geometry {
        Geometry::Planar { .. } => Datum::Plane,
        Geometry::Planet { radius_m, .. } => Datum::Sphere(radius_m),
    };
    let rig = Rig {
        target: view.target,
        distance: (view.target - view.eye).length(),
        heading: args.camera.heading_deg.to_radians(),
        pitch: args
            .camera
            .pitch_deg
            .to_radians()
            .clamp(MIN_PITCH, MAX_PITCH),
        datum,
    };
    let display = event_loop.owned_display_handle();
    event_loop.set_control_flow(ControlFlow::Poll);
    let mut app = App {
        args: args.clone(),
        session,
        view,
        rig,
        ground_m: hi.max(lo),
        display,
        gfx: None,
        input: Input::default(),
        figures: Figures::default(),
        start: Instant::now(),
        last_frame: None,
        frames: 0,
        error: None,
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| anyhow!("the window's event loop failed: {e}"))?;
    if let Some(e) = app.error {
        return Err(e);
    }
    Ok(())
}

const MIN_PITCH: f64 = -89.9_f64.to_radians();
const MAX_PITCH: f64 = -1.0_f64.to_radians();
/// The least height of the eye above the streamed ground, metres.
const CLEARANCE_M: f64 = 2.0;

#[derive(Clone, Copy, Debug)]
enum Datum {
    Plane,
    Sphere(f64),
}

/// The orbit camera: everything in the local frame at the target.
#[derive(Clone, Copy, Debug)]
struct Rig {
    target: DVec3,
    distance: f64,
    heading: f64,
    pitch: f64,
    datum: Datum,
}

impl Rig {
    /// Up, north and east at `p`.
    fn frame(&self, p: DVec3) -> (DVec3, DVec3, DVec3) {
        match self.datum {
            Datum::Plane => (DVec3::Z, DVec3::NEG_Y, DVec3::X),
            Datum::Sphere(_) => {
                let up = p.normalize_or(DVec3::Z);
                let mut north = (DVec3::Z - up * up.z).normalize_or_zero();
                if north == DVec3::ZERO {
                    north = DVec3::X;
                }
                (up, north, up.cross(north))
            }
        }
    }

    /// Forward, camera up and the horizontal forward at the target.
    fn axes(&self) -> (DVec3, DVec3, DVec3) {
        let (up, north, east) = self.frame(self.target);
        let horiz = north * self.heading.cos() + east * self.heading.sin();
        let forward = horiz * self.pitch.cos() + up * self.pitch.sin();
        let cam_up = -horiz * self.pitch.sin() + up * self.pitch.cos();
        (forward, cam_up, horiz)
    }

    fn eye(&self) -> DVec3 {
        self.target - self.axes().0 * self.distance
    }

    /// Height of `p` above the datum (plane z = 0, or the sphere of height 0).
    fn altitude(&self, p: DVec3) -> f64 {
        match self.datum {
            Datum::Plane => p.z,
            Datum::Sphere(r) => p.length() - r,
        }
    }

    /// The screen's right and the horizontal forward, both tangent at the target.
    fn tangents(&self) -> (DVec3, DVec3) {
        let (forward, cam_up, horiz) = self.axes();
        let (up, _, _) = self.frame(self.target);
        let right = forward.cross(cam_up);
        let right = (right - up * right.dot(up)).normalize_or(DVec3::X);
        (right, horiz)
    }

    /// Moves target and eye together by `delta`.
    fn translate(&mut self, delta: DVec3) {
        self.target += delta;
    }
}

#[derive(Default)]
struct Input {
    keys: HashSet<KeyCode>,
    left: bool,
    right: bool,
    cursor: Option<(f64, f64)>,
}

#[derive(Default)]
struct Figures {
    since: Option<Instant>,
    frames: u64,
    bytes_at: u64,
}

struct Gfx<R: RenderDomain> {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    gpu: Gpu,
    config: wgpu::SurfaceConfiguration,
    depth: wgpu::TextureView,
    renderer: TerrainRenderer<R>,
    /// The surface texture can be copied (screenshots read it directly).
    surface_copies: bool,
}

struct App<R: RenderDomain> {
    args: ViewArgs,
    session: Session<R>,
    view: View,
    rig: Rig,
    ground_m: f64,
    display: OwnedDisplayHandle,
    gfx: Option<Gfx<R>>,
    input: Input,
    figures: Figures,
    start: Instant,
    last_frame: Option<Instant>,
    frames: u64,
    error: Option<anyhow::Error>,
}

fn depth_view(device: &wgpu::Device, w: u32, h: u32) -> wgpu::TextureView {
    device
        .create_texture(&wgpu::TextureDescriptor {
            label: Some("quincunx view depth"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        })
        .create_view(&Default::default())
}

/// A colour format the renderer draws as the offscreen frames do (8-bit, not sRGB),
/// else the surface's first.
fn pick_format(formats: &[wgpu::TextureFormat]) -> Option<wgpu::TextureFormat> {
    use wgpu::TextureFormat as F;
    formats
        .iter()
        .copied()
        .find(|f| matches!(f, F::Bgra8Unorm | F::Rgba8Unorm))
        .or_else(|| formats.first().copied())
}

impl<R: RenderDomain> App<R> {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: anyhow::Error) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        event_loop.exit();
    }

    fn start_gfx(&mut self, event_loop: &ActiveEventLoop) -> Result<Gfx<R>> {
        let [w, h] = self.args.size;
        let attrs = Window::default_attributes()
            .with_title(format!("quincunx view {}", self.args.server.repo))
            .with_inner_size(PhysicalSize::new(w, h));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .context("creating the window")?,
        );
        let backend_from_env = std::env::var_os("WGPU_BACKEND").is_some();
        let mut attempts = Vec::new();
        if !backend_from_env {
            attempts.push(Some(wgpu::Backends::VULKAN));
        }
        attempts.push(None);
        let mut last_error = None;
        let mut found = None;
        for backends in attempts {
            let mut desc = wgpu::InstanceDescriptor::new_with_display_handle_from_env(Box::new(
                self.display.clone(),
            ));
            if let Some(b) = backends {
                desc.backends = b;
            }
            let instance = wgpu::Instance::new(desc);
            let surface = match instance.create_surface(window.clone()) {
                Ok(s) => s,
                Err(e) => {
                    last_error = Some(anyhow!("creating the window's surface: {e}"));
                    continue;
                }
            };
            match Gpu::from_instance(&instance, Some(&surface)) {
                Ok(gpu) => {
                    found = Some((surface, gpu));
                    break;
                }
                Err(e) => last_error = Some(anyhow!("{e}")),
            }
        }
        let Some((surface, gpu)) = found else {
            return Err(last_error.unwrap_or_else(|| anyhow!("no GPU adapter")));
        };
        let caps = surface.get_capabilities(&gpu.adapter);
        let format = pick_format(&caps.formats).ok_or_else(|| {
            anyhow!(
                "the window's surface supports no format on {}",
                gpu.describe()
            )
        })?;
        let want_copy = self.args.screenshot.is_some();
        let surface_copies = want_copy && caps.usages.contains(wgpu::TextureUsages::COPY_SRC);
        let size = window.inner_size();
        let config = wgpu::SurfaceConfiguration {
            usage: if surface_copies {
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC
            } else {
                wgpu::TextureUsages::RENDER_ATTACHMENT
            },
            format,
            color_space: wgpu::SurfaceColorSpace::Auto,
            width: size.width.max(1),
            height: size.height.max(1),
            desired_maximum_frame_latency: 2,
            present_mode: if self.args.vsync {
                wgpu::PresentMode::AutoVsync
            } else {
                wgpu::PresentMode::AutoNoVsync
            },
            alpha_mode: caps
                .alpha_modes
                .first()
                .copied()
                .unwrap_or(wgpu::CompositeAlphaMode::Auto),
            view_formats: vec![],
        };
        surface.configure(&gpu.device, &config);
        let depth = depth_view(&gpu.device, config.width, config.height);
        let renderer = TerrainRenderer::for_session(
            &gpu.device,
            &self.session,
            RendererConfig {
                gpu_budget_bytes: (self.args.gpu_budget_mb * 1_048_576.0) as u64,
                colour_format: format,
                ..RendererConfig::default()
            },
        )?;
        // The first sync uploads the whole cut the warm-up refined.
        self.session.restart_cut_changes();
        tracing::info!(adapter = %gpu.describe(), ?format, surface_copies, "window ready");
        Ok(Gfx {
            window,
            surface,
            gpu,
            config,
            depth,
            renderer,
            surface_copies,
        })
    }

    fn resize(&mut self, size: PhysicalSize<u32>) {
        let Some(g) = self.gfx.as_mut() else { return };
        if size.width == 0 || size.height == 0 {
            return;
        }
        g.config.width = size.width;
        g.config.height = size.height;
        g.surface.configure(&g.gpu.device, &g.config);
        g.depth = depth_view(&g.gpu.device, size.width, size.height);
    }

    fn key(&mut self, event_loop: &ActiveEventLoop, code: KeyCode, pressed: bool) {
        if !pressed {
            self.input.keys.remove(&code);
            return;
        }
        if !self.input.keys.insert(code) {
            return; // key repeat
        }
        match code {
            KeyCode::Escape => event_loop.exit(),
            KeyCode::BracketLeft => {
                self.view.tolerance_px = (self.view.tolerance_px * 0.5).max(1.0 / 64.0);
            }
            KeyCode::BracketRight => {
                self.view.tolerance_px = (self.view.tolerance_px * 2.0).min(256.0);
            }
            KeyCode::KeyF => {
                if let Some(g) = self.gfx.as_mut() {
                    let mut modes = g.renderer.modes();
                    modes.wireframe = !modes.wireframe;
                    g.renderer.set_modes(&g.gpu.device, modes);
                }
            }
            KeyCode::KeyL => {
                if let Some(g) = self.gfx.as_mut() {
                    let mut modes = g.renderer.modes();
                    modes.colour_by_level = !modes.colour_by_level;
                    g.renderer.set_modes(&g.gpu.device, modes);
                }
            }
            _ => {}
        }
    }

    /// Metres per pixel at the target's distance.
    fn metres_per_px(&self) -> f64 {
        let h = f64::from(self.view.viewport_px[1].max(1));
        2.0 * self.rig.distance * (self.view.fov_y_rad * 0.5).tan() / h
    }

    fn drag(&mut self, dx: f64, dy: f64) {
        if self.input.left {
            self.rig.heading += dx * 0.005;
            self.rig.pitch = (self.rig.pitch - dy * 0.005).clamp(MIN_PITCH, MAX_PITCH);
        } else if self.input.right {
            let (right, horiz) = self.rig.tangents();
            let m = self.metres_per_px();
            self.rig.translate(-right * dx * m + horiz * dy * m);
        }
    }

    /// Applies held fly keys over `dt` seconds, then keeps the eye above the ground.
    fn fly(&mut self, dt: f64) {
        let eye = self.rig.eye();
        let above = (self.rig.altitude(eye) - self.ground_m).max(1.0);
        let step = above * dt;
        let (right, horiz) = self.rig.tangents();
        let (up, _, _) = self.rig.frame(self.rig.target);
        let keys = &self.input.keys;
        let mut delta = DVec3::ZERO;
        for (code, dir) in [
            (KeyCode::KeyW, horiz),
            (KeyCode::KeyS, -horiz),
            (KeyCode::KeyD, right),
            (KeyCode::KeyA, -right),
            (KeyCode::KeyE, up),
            (KeyCode::KeyQ, -up),
        ] {
            if keys.contains(&code) {
                delta += dir;
            }
        }
        if delta != DVec3::ZERO {
            self.rig.translate(delta.normalize() * step);
        }
        let eye = self.rig.eye();
        if let Some(g) = surface_height_m(&self.session, eye) {
            self.ground_m = g;
        }
        let low = self.ground_m + CLEARANCE_M - self.rig.altitude(eye);
        if low > 0.0 {
            let eye_up = self.session.world().up(eye);
            self.rig.translate(eye_up * low);
        }
        let eye = self.rig.eye();
        let (forward, cam_up, _) = self.rig.axes();
        self.view.eye = eye;
        self.view.target = eye + forward * self.rig.distance;
        self.view.up = cam_up;
    }

    fn frame(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let now = Instant::now();
        let dt = self
            .last_frame
            .map_or(0.0, |t| now.duration_since(t).as_secs_f64().min(0.25));
        self.last_frame = Some(now);
        let Some(g) = self.gfx.as_ref() else {
            return Ok(());
        };
        self.view.viewport_px = [g.config.width, g.config.height];
        self.fly(dt);
        self.session
            .update(&self.view, self.start.elapsed(), Duration::from_millis(4))
            .context("streaming")?;
        let Some(g) = self.gfx.as_mut() else {
            return Ok(());
        };
        g.renderer.sync(&mut self.session)?;
        let stats = g
            .renderer
            .prepare(&g.gpu.queue, &Camera::from_view(&self.view));
        let frame = match g.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t) => t,
            wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                g.surface.configure(&g.gpu.device, &g.config);
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                bail!("the window's surface texture failed validation")
            }
        };
        let last = self.args.frames.is_some_and(|n| self.frames + 1 >= n);
        let shoot = last && self.args.screenshot.is_some();
        let mut encoder = g
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        let surface_view = frame.texture.create_view(&Default::default());
        record_pass(&mut encoder, &surface_view, &g.depth, &g.renderer);
        // What a screenshot reads: the surface itself, or the same frame drawn again
        // offscreen when the surface cannot be copied.
        let capture = if shoot {
            let size = wgpu::Extent3d {
                width: g.config.width,
                height: g.config.height,
                depth_or_array_layers: 1,
            };
            let own = (!g.surface_copies).then(|| {
                let t = g.gpu.device.create_texture(&wgpu::TextureDescriptor {
                    label: Some("quincunx view capture"),
                    size,
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: g.config.format,
                    usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
                    view_formats: &[],
                });
                record_pass(
                    &mut encoder,
                    &t.create_view(&Default::default()),
                    &g.depth,
                    &g.renderer,
                );
                t
            });
            let texture = own.as_ref().unwrap_or(&frame.texture);
            Some(copy_to_buffer(&g.gpu, &mut encoder, texture))
        } else {
            None
        };
        g.gpu.queue.submit([encoder.finish()]);
        g.gpu.queue.present(frame);
        self.frames += 1;
        if let Some((buffer, padded_row)) = capture {
            let [w, h] = [g.config.width, g.config.height];
            let image = read_capture(&g.gpu, &buffer, padded_row, w, h, g.config.format)?;
            if let Some(path) = &self.args.screenshot {
                image
                    .write_png(path)
                    .with_context(|| format!("writing {}", path.display()))?;
                tracing::info!(path = %path.display(), from_surface = g.surface_copies, "screenshot");
            }
        }
        // Figures in the title, twice a second.
        let fig = &mut self.figures;
        fig.frames += 1;
        let since = *fig.since.get_or_insert(now);
        let elapsed = now.duration_since(since).as_secs_f64();
        if elapsed >= 0.5 {
            let bytes = self.session.fetch_stats().bytes_fetched;
            let rate = bytes.saturating_sub(fig.bytes_at) as f64 / elapsed;
            let fps = fig.frames as f64 / elapsed;
            let mut title = format!(
                "quincunx view {} | {fps:.1} fps | {} triangles | {} patches | {} px | {}/s",
                self.args.server.repo,
                stats.triangles,
                stats.patches,
                self.view.tolerance_px,
                human_bytes(rate)
            );
            if g.renderer.modes().wireframe {
                title.push_str(" | wireframe");
            }
            if g.renderer.modes().colour_by_level {
                title.push_str(" | levels");
            }
            g.window.set_title(&title);
            tracing::debug!(%title, "figures");
            *fig = Figures {
                since: Some(now),
                frames: 0,
                bytes_at: bytes,
            };
        }
        if last {
            event_loop.exit();
        } else {
            g.window.request_redraw();
        }
        Ok(())
    }
}

fn human_bytes(b: f64) -> String {
    if b >= 1e6 {
        format!("{:.1} MB", b / 1e6)
    } else if b >= 1e3 {
        format!("{:.1} kB", b / 1e3)
    } else {
        format!("{b:.0} B")
    }
}

const BACKGROUND: wgpu::Color = wgpu::Color {
    r: 135.0 / 255.0,
    g: 170.0 / 255.0,
    b: 210.0 / 255.0,
    a: 1.0,
};

fn record_pass<R: RenderDomain>(
    encoder: &mut wgpu::CommandEncoder,
    colour: &wgpu::TextureView,
    depth: &wgpu::TextureView,
    renderer: &TerrainRenderer<R>,
) {
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("quincunx view"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: colour,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: wgpu::LoadOp::Clear(BACKGROUND),
                store: wgpu::StoreOp::Store,
            },
        })],
        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
            view: depth,
            depth_ops: Some(wgpu::Operations {
                load: wgpu::LoadOp::Clear(0.0),
                store: wgpu::StoreOp::Discard,
            }),
            stencil_ops: None,
        }),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    renderer.draw(&mut pass);
}

fn copy_to_buffer(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
) -> (wgpu::Buffer, u32) {
    let size = [texture.width(), texture.height()];
    let (buffer, padded_row) = readback_buffer(&gpu.device, size, "quincunx view screenshot");
    copy_for_readback(
        encoder,
        texture,
        wgpu::TextureAspect::All,
        &buffer,
        padded_row,
    );
    (buffer, padded_row)
}

fn read_capture(
    gpu: &Gpu,
    buffer: &wgpu::Buffer,
    padded_row: u32,
    w: u32,
    h: u32,
    format: wgpu::TextureFormat,
) -> Result<Image> {
    use wgpu::TextureFormat as F;
    let bgra = match format {
        F::Bgra8Unorm | F::Bgra8UnormSrgb => true,
        F::Rgba8Unorm | F::Rgba8UnormSrgb => false,
        other => bail!("cannot save a screenshot of a {other:?} surface (8-bit RGBA or BGRA only)"),
    };
    let row = (w * 4) as usize;
    let padded = padded_row as usize;
    let rgba = map_read(gpu, buffer, |b| {
        let mut out = Vec::with_capacity(row * h as usize);
        for y in 0..h as usize {
            let line = &b[y * padded..y * padded + row];
            if bgra {
                out.extend(line.chunks_exact(4).flat_map(|p| [p[2], p[1], p[0], 255]));
            } else {
                out.extend(line.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2], 255]));
            }
        }
        out
    })?;
    Ok(Image {
        width: w,
        height: h,
        rgba,
    })
}

impl<R: RenderDomain> ApplicationHandler for App<R> {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        match self.start_gfx(event_loop) {
            Ok(g) => {
                g.window.request_redraw();
                self.gfx = Some(g);
            }
            Err(e) => self.fail(event_loop, e),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => self.resize(size),
            WindowEvent::KeyboardInput { event, .. } => {
                if let PhysicalKey::Code(code) = event.physical_key {
                    self.key(event_loop, code, event.state == ElementState::Pressed);
                }
            }
            WindowEvent::MouseInput { state, button, .. } => {
                let down = state == ElementState::Pressed;
                match button {
                    MouseButton::Left => self.input.left = down,
                    MouseButton::Right => self.input.right = down,
                    _ => {}
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let p = (position.x, position.y);
                if let Some(q) = self.input.cursor {
                    self.drag(p.0 - q.0, p.1 - q.1);
                }
                self.input.cursor = Some(p);
            }
            WindowEvent::CursorLeft { .. } => self.input.cursor = None,
            WindowEvent::MouseWheel { delta, .. } => {
                let lines = match delta {
                    MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                self.rig.distance = (self.rig.distance * 0.85f64.powf(lines)).clamp(1.0, 1e10);
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.frame(event_loop) {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }
}
