//! A camera placed the way people name views (a fraction of a raster or a latitude and
//! longitude, a height above the streamed terrain, heading and pitch), streamed to full
//! quality and drawn offscreen: what `quincunx render` does, as a library.

use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::session::Session;
use quincunx_client::view::View;

use crate::camera::Camera;
use crate::domain::{Geometry, RenderDomain};
use crate::ground::surface_height_m;
use crate::offscreen::{Gpu, GpuTiming, Image, Offscreen};
use crate::renderer::{RenderFrameStats, RendererConfig, TerrainRenderer};
use crate::{Lighting, Modes, RenderError};

/// Where the camera is over the ground.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Place {
    /// Fractions of a planar raster: `(0, 0)` = north-west corner, `(1, 1)` = south-east.
    Uv(f64, f64),
    /// Latitude and longitude on a planet, degrees.
    LatLon(f64, f64),
}

/// A named view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shot {
    /// Where.
    pub place: Place,
    /// Metres above the streamed terrain under the camera.
    pub height_m: f64,
    /// Degrees clockwise from north.
    pub heading_deg: f64,
    /// Degrees above the horizon (-90: straight down).
    pub pitch_deg: f64,
    /// Vertical field of view, degrees.
    pub fov_deg: f64,
    /// Image size, pixels.
    pub size: [u32; 2],
    /// Screen-space error tolerance, pixels.
    pub tolerance_px: f64,
}

impl Default for Shot {
    fn default() -> Self {
        Shot {
            place: Place::Uv(0.5, 0.5),
            height_m: 1000.0,
            heading_deg: 0.0,
            pitch_deg: -90.0,
            fov_deg: 60.0,
            size: [1920, 1080],
            tolerance_px: 1.0,
        }
    }
}

impl Shot {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |what: &str| Err(RenderError::Config(what.to_string()));
        match self.place {
            Place::Uv(u, v) if !(u.is_finite() && v.is_finite()) => {
                return bad("--uv must be finite");
            }
            Place::LatLon(lat, lon)
                if !(lat.is_finite()
                    && lon.is_finite()
                    && lat.abs() <= 90.0
                    && lon.abs() <= 360.0) =>
            {
                return bad("--lat-lon: latitude in -90..=90, longitude in -360..=360");
            }
            _ => {}
        }
        if !(self.height_m.is_finite() && self.height_m > 0.0 && self.height_m <= 1e10) {
            return bad("--height-m must be above 0 and at most 1e10");
        }
        if !(self.fov_deg.is_finite() && self.fov_deg > 0.5 && self.fov_deg < 179.0) {
            return bad("--fov-deg must be within 0.5..179");
        }
        if !(self.tolerance_px.is_finite() && self.tolerance_px > 0.0) {
            return bad("--tolerance-px must be positive");
        }
        if !(self.heading_deg.is_finite() && self.pitch_deg.is_finite()) {
            return bad("--heading-deg and --pitch-deg must be finite");
        }
        if !(-90.0..=90.0).contains(&self.pitch_deg) {
            return bad("--pitch-deg must be within -90..=90");
        }
        Ok(())
    }

    /// The point on the ground (height 0) under the camera, and the local up and north.
    fn ground<R: RenderDomain>(
        &self,
        session: &Session<R>,
    ) -> Result<(DVec3, DVec3, DVec3), RenderError> {
        let world = session.dag().refiner().world_frame(&session.world(), 0);
        match (self.place, world.geometry) {
            (
                Place::Uv(u, v),
                Geometry::Planar {
                    metres_per_fine,
                    extent_fine,
                },
            ) => {
                let x = u * extent_fine[0] as f64 * metres_per_fine;
                let y = v * extent_fine[1] as f64 * metres_per_fine;
                // Row 0 is the north edge: north is -y.
                Ok((DVec3::new(x, y, 0.0), DVec3::Z, DVec3::NEG_Y))
            }
            (Place::LatLon(lat, lon), Geometry::Planet { radius_m, .. }) => {
                let (la, lo) = (lat.to_radians(), lon.to_radians());
                let up = DVec3::new(la.cos() * lo.cos(), la.cos() * lo.sin(), la.sin());
                let mut north = (DVec3::Z - up * up.z).normalize_or_zero();
                if north == DVec3::ZERO {
                    // At a pole: north along the prime meridian's direction of travel.
                    north = DVec3::new(-lo.cos(), -lo.sin(), 0.0) * up.z.signum();
                }
                Ok((up * radius_m, up, north))
            }
            (Place::Uv(..), _) => Err(RenderError::Config(
                "--uv places a camera over a planar repository; this one is a planet (use --lat-lon)".into(),
            )),
            (Place::LatLon(..), _) => Err(RenderError::Config(
                "--lat-lon places a camera over a planet; this repository is planar (use --uv)".into(),
            )),
        }
    }

    /// The client view with the camera `height_m` above `ground_m`.
    pub fn view<R: RenderDomain>(
        &self,
        session: &Session<R>,
        ground_m: f64,
    ) -> Result<View, RenderError> {
        let (base, up, north) = self.ground(session)?;
        let east = up.cross(north);
        let (h, p) = (self.heading_deg.to_radians(), self.pitch_deg.to_radians());
        let horiz = north * h.cos() + east * h.sin();
        let forward = horiz * p.cos() + up * p.sin();
        let cam_up = -horiz * p.sin() + up * p.cos();
        let eye = base + up * (ground_m + self.height_m);
        Ok(View {
            eye,
            target: eye + forward * self.height_m.max(1.0),
            up: cam_up,
            fov_y_rad: self.fov_deg.to_radians(),
            viewport_px: self.size,
            tolerance_px: self.tolerance_px,
        })
    }
}

/// How streaming to a view went.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Streamed {
    /// The client reached full quality for the final view.
    pub full_quality: bool,
    /// The renderer's GPU pool (or the DAG budget) held the cut coarser than the
    /// tolerance: the view is the best cut that fits, not full quality.
    pub budget_limited: bool,
    /// Seconds from the start to full quality (or to giving up).
    pub seconds: f64,
    /// Frames run.
    pub frames: usize,
    /// Ground height under the camera (metres).
    pub ground_m: f64,
    /// Bytes the renderer uploaded while streaming.
    pub upload_bytes: u64,
}

/// Streams `session` towards `shot` until the cut is at full quality for the view whose
/// camera stands `height_m` above the streamed terrain, or until `wait`. The ground
/// height is re-read from the cut as it refines (the camera moves with it), and the
/// renderer (when given) takes each frame's changes, so its uploads spread over the wait.
pub fn stream_to<R: RenderDomain>(
    session: &mut Session<R>,
    shot: &Shot,
    wait: Duration,
    mut renderer: Option<(&mut TerrainRenderer<R>, &wgpu::Queue)>,
) -> Result<(View, Streamed), RenderError> {
    shot.validate()?;
    let start = Instant::now();
    let (lo, hi) = session.height_range();
    let mut ground = hi.max(lo);
    let mut view = shot.view(session, ground)?;
    let mut out = Streamed::default();
    let mut settled = 0;
    loop {
        let frame = session
            .update(&view, start.elapsed(), Duration::from_millis(8))
            .map_err(|e| RenderError::Config(e.to_string()))?;
        out.frames += 1;
        if let Some((r, q)) = renderer.as_mut() {
            r.sync(session)?;
            out.upload_bytes += r.prepare(q, &Camera::from_view(&view)).upload_bytes;
        }
        let full = frame.refine.settled() && frame.wanted == 0;
        if full {
            // The terrain under the camera may have changed as it refined: move the
            // camera to the new height and check again (twice in a row unchanged).
            let (base, up, _) = shot.ground(session)?;
            let g = surface_height_m(session, base + up * 1e-3).unwrap_or(ground);
            if (g - ground).abs() <= 1e-3 * shot.height_m.max(1.0) {
                settled += 1;
            } else {
                settled = 0;
                ground = g;
                view = shot.view(session, ground)?;
            }
            if settled >= 2 {
                out.full_quality = frame.refine.full_quality;
                out.budget_limited = !frame.refine.full_quality;
                break;
            }
        }
        if start.elapsed() >= wait {
            break;
        }
        if !full {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    out.seconds = start.elapsed().as_secs_f64();
    out.ground_m = ground;
    Ok((view, out))
}

/// One offscreen picture and its figures.
pub struct Picture {
    /// The pixels.
    pub image: Image,
    /// The renderer's last frame.
    pub stats: RenderFrameStats,
    /// The GPU time of the last frame.
    pub timing: GpuTiming,
    /// Bytes uploaded over all frames.
    pub upload_bytes: u64,
}

/// Options of [`picture`].
#[derive(Clone, Debug)]
pub struct PictureOptions {
    /// Renderer settings (the colour format is forced to the offscreen one).
    pub renderer: RendererConfig,
    /// Clear colour.
    pub background: [u8; 3],
    /// Lighting.
    pub lighting: Lighting,
    /// Modes.
    pub modes: Modes,
}

impl Default for PictureOptions {
    fn default() -> Self {
        PictureOptions {
            renderer: RendererConfig::default(),
            background: [135, 170, 210],
            lighting: Lighting::default(),
            modes: Modes::default(),
        }
    }
}

/// Streams `shot` to full quality (or `wait`) and renders it offscreen.
pub fn picture<R: RenderDomain>(
    gpu: &Gpu,
    session: &mut Session<R>,
    shot: &Shot,
    wait: Duration,
    options: &PictureOptions,
) -> Result<(Picture, Streamed, View), RenderError> {
    let config = RendererConfig {
        colour_format: crate::offscreen::OFFSCREEN_FORMAT,
        ..options.renderer.clone()
    };
    let mut renderer = TerrainRenderer::for_session(&gpu.device, session, config)?;
    if options.lighting.tint_m.is_none() {
        renderer.lighting = Lighting {
            tint_m: renderer.lighting.tint_m,
            ..options.lighting
        };
    } else {
        renderer.lighting = options.lighting;
    }
    renderer.set_modes(&gpu.device, options.modes);
    let (view, streamed) = stream_to(session, shot, wait, Some((&mut renderer, &gpu.queue)))?;
    let offscreen = Offscreen::new(gpu, shot.size)?;
    let camera = Camera::from_view(&view);
    renderer.sync(session)?;
    let mut upload_bytes = streamed.upload_bytes;
    let mut stats = renderer.prepare(&gpu.queue, &camera);
    upload_bytes += stats.upload_bytes;
    // Capped uploads: keep preparing until the drawn cut is the current one.
    while stats.pending > 0 {
        stats = renderer.prepare(&gpu.queue, &camera);
        upload_bytes += stats.upload_bytes;
    }
    let timing = offscreen.render(gpu, options.background, |pass| renderer.draw(pass))?;
    let image = offscreen.read(gpu)?;
    Ok((
        Picture {
            image,
            stats,
            timing,
            upload_bytes,
        },
        streamed,
        view,
    ))
}
