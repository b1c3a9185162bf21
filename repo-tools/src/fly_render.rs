//! `quincunx fly --render`: each flight frame drawn offscreen with `quincunx-render`
//! (lavapipe or a GPU), with the renderer's figures.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use quincunx_client::flight::{self, Flight, FlightReport, FlyOptions, FrameRecord, percentile};
use quincunx_client::session::Session;
use quincunx_client::view::View;
use quincunx_render::domain::RenderDomain;
use quincunx_render::offscreen::{Gpu, Offscreen};
use quincunx_render::{Camera, RendererConfig, TerrainRenderer};

use crate::fly::{FlyArgs, FlyDomain, RASTER_EVERY, RenderSummary};

/// Flies `flight` with `session`, recording each frame's cut changes, then replays them
/// through the renderer.
pub(crate) fn fly_rendered<R: FlyDomain>(
    session: &mut Session<R>,
    flight: &Flight,
    opts: &FlyOptions,
    log: impl Fn(&FrameRecord),
    args: &FlyArgs,
) -> Result<(FlightReport, RenderSummary)> {
    if !(args.gpu_budget_mb.is_finite() && args.gpu_budget_mb > 0.0) {
        bail!("--gpu-budget-mb must be positive");
    }
    let mut drawer = FrameDrawer::new(session, args)?;
    // The flight runs at its real pace and records each frame's cut changes (the time
    // taking them is the first part of the renderer's frame); the renderer then replays
    // them frame by frame with real uploads and submissions (see `FrameDrawer::replay`).
    let mut frames = Vec::new();
    let report = flight::fly_with(session, flight, opts, |s, view, rec| {
        log(rec);
        let t = Instant::now();
        let changes = s.cut_changes();
        frames.push((changes, *view, t.elapsed().as_secs_f64() * 1e3));
    })?;
    let dag = session.dag();
    for (k, (changes, view, take_ms)) in frames.into_iter().enumerate() {
        drawer
            .frame(dag.refiner(), dag.colour(), changes, &view, take_ms, k)
            .context("rendering the flight")?;
    }
    Ok((report, drawer.summary()))
}

/// Draws each flight frame offscreen and keeps the figures.
pub(crate) struct FrameDrawer<R: RenderDomain> {
    gpu: Gpu,
    offscreen: Offscreen,
    renderer: TerrainRenderer<R>,
    cpu_ms: Vec<f64>,
    gpu_ms: Vec<f64>,
    uploads: Vec<f64>,
    upload_bytes: Vec<f64>,
    triangles: Vec<f64>,
    patches: Vec<f64>,
    draw_calls_max: usize,
    gpu_bytes_peak: u64,
    gpu_bytes_budget: u64,
    not_current: usize,
    size: [u32; 2],
}

impl<R: RenderDomain> FrameDrawer<R> {
    /// A drawer for `session`'s repository; bounds the session's cut by its pool.
    pub(crate) fn new(session: &mut Session<R>, args: &FlyArgs) -> Result<Self> {
        let gpu = Gpu::headless().context("starting the renderer")?;
        let size = args.render_size.unwrap_or(args.viewport);
        let offscreen = Offscreen::new(&gpu, size)?;
        let config = RendererConfig {
            gpu_budget_bytes: (args.gpu_budget_mb * 1_048_576.0) as u64,
            colour_format: quincunx_render::offscreen::OFFSCREEN_FORMAT,
            ..RendererConfig::default()
        };
        let renderer = TerrainRenderer::for_session(&gpu.device, session, config)?;
        renderer.bound_cut(session);
        Ok(FrameDrawer {
            gpu,
            offscreen,
            renderer,
            cpu_ms: Vec::new(),
            gpu_ms: Vec::new(),
            uploads: Vec::new(),
            upload_bytes: Vec::new(),
            triangles: Vec::new(),
            patches: Vec::new(),
            draw_calls_max: 0,
            gpu_bytes_peak: 0,
            gpu_bytes_budget: 0,
            not_current: 0,
            size,
        })
    }

    /// One recorded frame through the renderer: applying its cut changes, preparing
    /// (uploads, draws, uniforms), encoding the pass with the terrain draw and submitting
    /// are timed, added to `take_ms` (taking the changes during the flight). Every
    /// [`RASTER_EVERY`]th frame (and the first) the pass is submitted and rasterised, and
    /// waited for untimed; on the others the encoded pass is dropped after `finish` and
    /// an empty submission flushes the uploads, because lavapipe needs seconds per
    /// flight frame to rasterise on two cores. What a frame costs the host is the same
    /// either way: the device executes the commands.
    pub(crate) fn frame(
        &mut self,
        domain: &R,
        colour: Option<&quincunx_client::colour::ColourLayer<R>>,
        changes: quincunx_client::session::PatchChanges<R::Id>,
        view: &View,
        take_ms: f64,
        k: usize,
    ) -> Result<()> {
        let start = Instant::now();
        self.renderer.apply(domain, colour, changes)?;
        let stats = self
            .renderer
            .prepare(&self.gpu.queue, &Camera::from_view(view));
        let renderer = &self.renderer;
        let mut cpu_ms = 0.0;
        if k.is_multiple_of(RASTER_EVERY) {
            let timing = self.offscreen.render_timed(
                &self.gpu,
                [135, 170, 210],
                |pass| renderer.draw(pass),
                &mut cpu_ms,
                start,
            )?;
            if let Some(g) = timing.gpu_ms {
                self.gpu_ms.push(g);
            }
        } else {
            let encoded = self.offscreen.encode(&self.gpu, [135, 170, 210], |pass| {
                renderer.draw(pass);
            });
            self.gpu.queue.submit([]);
            cpu_ms = start.elapsed().as_secs_f64() * 1e3;
            drop(encoded);
        }
        self.cpu_ms.push(take_ms + cpu_ms);
        self.uploads.push(stats.uploads as f64);
        self.upload_bytes.push(stats.upload_bytes as f64);
        self.triangles.push(stats.triangles as f64);
        self.patches.push(stats.patches as f64);
        self.draw_calls_max = self.draw_calls_max.max(stats.draw_calls);
        self.gpu_bytes_peak = self.gpu_bytes_peak.max(stats.gpu_bytes_used);
        self.gpu_bytes_budget = stats.gpu_bytes_allocated;
        self.not_current += usize::from(!stats.current);
        Ok(())
    }

    /// The drawn cut for `view`, made current (capped uploads finished), rasterised
    /// and read back: the frame's pixels and depth, and the renderer's figures (patches
    /// the GPU budget left out are `missing`).
    pub(crate) fn capture(
        &mut self,
        view: &View,
        background: [u8; 3],
    ) -> Result<(
        quincunx_render::offscreen::Image,
        quincunx_render::offscreen::DepthImage,
        quincunx_render::RenderFrameStats,
    )> {
        let camera = Camera::from_view(view);
        let mut stats = self.renderer.prepare(&self.gpu.queue, &camera);
        while stats.pending > 0 {
            stats = self.renderer.prepare(&self.gpu.queue, &camera);
        }
        let renderer = &self.renderer;
        self.offscreen
            .render(&self.gpu, background, |pass| renderer.draw(pass))?;
        Ok((
            self.offscreen.read(&self.gpu)?,
            self.offscreen.read_depth(&self.gpu)?,
            stats,
        ))
    }

    pub(crate) fn summary(&self) -> RenderSummary {
        let sorted = |v: &[f64]| {
            let mut v = v.to_vec();
            v.sort_by(f64::total_cmp);
            v
        };
        let (cpu, up, ups) = (
            sorted(&self.cpu_ms),
            sorted(&self.upload_bytes),
            sorted(&self.uploads),
        );
        let pool = self.renderer.pool_stats();
        RenderSummary {
            adapter: self.gpu.describe(),
            frames: cpu.len(),
            cpu_ms_p50: percentile(&cpu, 0.5),
            cpu_ms_p99: percentile(&cpu, 0.99),
            cpu_ms_max: cpu.last().copied().unwrap_or(0.0),
            gpu_ms_p50: (!self.gpu_ms.is_empty()).then(|| percentile(&sorted(&self.gpu_ms), 0.5)),
            gpu_ms_p99: (!self.gpu_ms.is_empty()).then(|| percentile(&sorted(&self.gpu_ms), 0.99)),
            upload_bytes_p50: percentile(&up, 0.5),
            upload_bytes_p99: percentile(&up, 0.99),
            upload_bytes_max: up.last().copied().unwrap_or(0.0),
            upload_bytes_mean: up.iter().sum::<f64>() / up.len().max(1) as f64,
            uploads_p50: percentile(&ups, 0.5),
            uploads_max: ups.last().copied().unwrap_or(0.0),
            triangles_p50: percentile(&sorted(&self.triangles), 0.5),
            triangles_max: self.triangles.iter().copied().fold(0.0, f64::max),
            patches_max: self.patches.iter().copied().fold(0.0, f64::max),
            patches_p50: percentile(&sorted(&self.patches), 0.5),
            draw_calls_max: self.draw_calls_max,
            gpu_bytes_peak: self.gpu_bytes_peak,
            gpu_bytes_budget: self.gpu_bytes_budget,
            pool_uploads: pool.uploads,
            pool_cache_hits: pool.cache_hits,
            pool_evictions: pool.evictions,
            frames_not_current: self.not_current,
            frames_rasterised: self.cpu_ms.len().div_ceil(RASTER_EVERY),
            size: self.size,
        }
    }
}
