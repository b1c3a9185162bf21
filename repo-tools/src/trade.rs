//! `quincunx trade`: what each screen-space tolerance costs (triangles, milliseconds,
//! bytes, seconds to full quality) and what it buys (image error against a
//! full-resolution reference of the same view), measured on the user's own data.
//!
//! For each tolerance a fresh client session flies the same path in real time through its
//! own emulated link (`--link`, default 4 Mbit/s and 100 ms), checking its cut for cracks;
//! the renderer then replays the flight frame by frame (as `quincunx fly --render` does)
//! and, at the last frame of each chosen leg, rasterises the view and reads back its
//! pixels and depth. Afterwards:
//! - the *needed set* of each tolerance: for every leg's final view, a fresh session over
//!   the server directly (no link, no prefetch, look-ahead or packages) refines the view
//!   to full quality, and the blobs of its cut are united over the views
//!   ([`quincunx_client::flight::needed_for_views`]); `fetched_over_needed` is the flight's
//!   fetched bytes over that set's. The same is done ignoring the blobs' side
//!   information (`flat_fraction` 0): what the side information saves on flat ground;
//! - the *reference* of each view: a fresh session refines it at tolerance 0 (every
//!   visible diamond down to the finest coded level; only frustum culling stays), drawn
//!   with a large GPU budget. PSNR compares shaded frames; the geometric error
//!   (`quincunx_render::error`) is, per pixel, the screen distance between the surface
//!   point the pixel shows and the reference surface along the local vertical. Pixels
//!   over the tolerance are re-measured at the exact first hit of their ray on the
//!   drawn cut's triangles (`quincunx_render::error::recheck`): a rasteriser can store,
//!   for a crest triangle seen edge-on, a depth off the surface.
//!
//! `--path extremes` (planets): views 1 m above the ground (oblique and straight down),
//! 100,000 km away, over the north pole and over a cube corner. Each view is also
//! rendered with the camera moved 1 mm (`jitter_psnr_db`), and straight-down views that
//! the ground fills are counted for background pixels (cracks).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_client::dag::PatchChanges;
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::flight::{self, BuiltinFlights, Flight, Leg, NeededSet, Pose};
use quincunx_client::refine::{Metric, RefineConfig};
use quincunx_client::session::{Session, SessionConfig, SessionError};
use quincunx_client::view::View;
use quincunx_codec::incremental::{PlanarRefiner, SphereRefiner};
use quincunx_render::domain::RenderDomain;
use quincunx_render::error::{error_map, psnr_db, recheck};
use quincunx_render::ground::SurfaceIndex;
use quincunx_render::offscreen::{DepthImage, Gpu, Image, OFFSCREEN_FORMAT, Offscreen};
use quincunx_render::scene::{Place, Shot, stream_to};
use quincunx_render::{Camera, RendererConfig, TerrainRenderer};
use serde::{Deserialize, Serialize};

use crate::args::{EmulatedLink, RefineArgs, ServerArgs};
use crate::fly::{FlyArgs, fly_options, parse_viewport, session_config, start_link};
use crate::fly_render::FrameDrawer;
use crate::plot::{Chart, Series};

/// The clear colour of every trade frame.
const BACKGROUND: [u8; 3] = [135, 170, 210];

/// `quincunx trade` options.
#[derive(Args, Debug, Clone)]
pub struct TradeArgs {
    /// Where to stream from.
    #[command(flatten)]
    pub server: ServerArgs,
    /// Tolerances to measure, pixels (0: the reference's refinement, every visible
    /// diamond at the finest level).
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2,4,8")]
    pub tolerances: Vec<f64>,
    /// Refinement metrics to measure, each at every tolerance (`geometric`, `sampling`):
    /// one curve per metric in the charts.
    #[arg(long, value_delimiter = ',', default_value = "geometric,sampling")]
    pub metrics: Vec<Metric>,
    /// `jump`, `approach`, `low-flight`, `extremes` (planets) or a JSON flight file.
    #[arg(long, default_value = "jump")]
    pub path: String,
    /// Emulated link of each flight, `KBIT_S,RTT_MS`, or `none`.
    #[arg(long, default_value = "4000,100", value_parser = crate::args::parse_link_or_none)]
    pub link: EmulatedLink,
    /// Views compared with the reference: this many legs' final views, spread over the
    /// flight (all legs when it has fewer).
    #[arg(long, default_value_t = 6)]
    pub views: usize,
    /// Write the report as `<label>.json` into this directory and PNG charts of every
    /// report there (one line per label).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Name of this repository's line in the charts (default: the repository's name,
    /// `+colour` with a colour layer).
    #[arg(long)]
    pub label: Option<String>,
    /// One JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Viewport `WIDTHxHEIGHT` (refinement and images).
    #[arg(long, default_value = "1920x1080", value_parser = parse_viewport)]
    pub viewport: [u32; 2],
    /// Seed of the `jump` places.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// GPU memory budget of the flights' renderer, MB.
    #[arg(long, default_value_t = 128.0)]
    pub gpu_budget_mb: f64,
    /// GPU memory budget of the reference renders, MB.
    #[arg(long, default_value_t = 4096.0)]
    pub reference_gpu_budget_mb: f64,
    /// Seconds a reference or needed-set view may take to reach full quality.
    #[arg(long, default_value_t = 300.0)]
    pub reference_wait_s: f64,
    /// Seconds each flight's session may spend refining its overviews before the flight
    /// (0: none, the first jump starts from nothing).
    #[arg(long, default_value_t = 0.0)]
    pub warm_up_s: f64,
    /// Check each flight's cut for cracks every this many frames (0 never).
    #[arg(long, default_value_t = 10)]
    pub check_every: usize,
    /// Flights per tolerance, each a new session through a new link starting from
    /// nothing: the times to full quality pool the jumps of every run; the other
    /// figures (frames, bytes, images) are the first run's. So many cold starts too,
    /// at each jump's view.
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Metres between samples (default: from the georeference).
    #[arg(long)]
    pub spacing_m: Option<f64>,
}

/// One tolerance's figures. Field names are those of `quincunx trade --json`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct TradePoint {
    /// Refinement metric (what the tolerance bounds).
    #[serde(default = "older_metric")]
    pub metric: Metric,
    /// Tolerance, pixels.
    pub tolerance_px: f64,
    /// Triangles drawn per frame, median and largest.
    pub triangles_median: f64,
    /// Largest.
    pub triangles_max: f64,
    /// Patches (cut halves) drawn per frame, median and largest.
    pub patches_median: f64,
    /// Largest.
    pub patches_max: f64,
    /// Refinement time per frame, ms: median and 99th percentile.
    pub refine_ms_median: f64,
    /// 99th percentile.
    pub refine_ms_p99: f64,
    /// Renderer CPU per frame (cut changes, uploads, draws, encoding, submitting), ms.
    pub render_ms_median: f64,
    /// 99th percentile.
    pub render_ms_p99: f64,
    /// Rasterisation per frame on the device (timestamp queries on the rasterised
    /// frames), ms; `None` without timestamps.
    pub render_gpu_ms_median: Option<f64>,
    /// 99th percentile.
    pub render_gpu_ms_p99: Option<f64>,
    /// Frames flown, and their rate.
    pub frames: usize,
    /// Frames per second the client kept.
    pub frames_per_s: f64,
    /// Body bytes fetched over the flight.
    pub bytes_fetched: u64,
    /// Of them, the colour layer's (0 without one).
    pub colour_bytes_fetched: u64,
    /// `bytes_fetched` over the flight's seconds.
    pub bytes_per_s: f64,
    /// Time to full quality after each jump of every run: median and largest (s).
    pub time_to_full_quality_s_median: Option<f64>,
    /// Largest.
    pub time_to_full_quality_s_max: Option<f64>,
    /// Mean time to full quality over the jumps that reached it (s).
    pub time_to_full_quality_s_mean: Option<f64>,
    /// Flights pooled into the time-to-full-quality figures (`--runs`).
    pub runs: usize,
    /// Each run's seconds to full quality, one per jump leg in flight order (`None`:
    /// the leg ended first).
    pub jump_times_s: Vec<Vec<Option<f64>>>,
    /// Jumps, over every run, whose leg ended before full quality.
    pub jumps_unfinished: usize,
    /// Time to full quality from a cold start at each jump's view: a new session through
    /// a new link flies that leg alone, so nothing an earlier view fetched helps it.
    /// Median and largest over every view of every run (s).
    pub time_to_full_quality_cold_s_median: Option<f64>,
    /// Largest.
    pub time_to_full_quality_cold_s_max: Option<f64>,
    /// Each run's cold-start seconds, one per jump leg in flight order.
    pub cold_times_s: Vec<Vec<Option<f64>>>,
    /// Cold starts, over every run, that did not reach full quality within the leg.
    pub cold_unfinished: usize,
    /// Jumps, over every run, whose cut the GPU budget held coarser than the tolerance
    /// (their time is to the best cut the pool holds).
    pub jumps_budget_limited: usize,
    /// The most halves (patches) the flight's cut could hold: the patch slots the
    /// `--gpu-budget-mb` pool has.
    pub cut_budget_halves: usize,
    /// PSNR of the shaded views against the references, over all compared pixels
    /// (`None`: every view identical, infinite).
    pub psnr_db: Option<f64>,
    /// Geometric error in pixels (see the module docs) over every measured pixel of
    /// every view: median, 99th percentile (nearest rank) and largest.
    pub geometric_error_px_p50: f64,
    /// 99th percentile.
    pub geometric_error_px_p99: f64,
    /// Largest.
    pub geometric_error_px_max: f64,
    /// Pixels measured, and those with no reference surface on their vertical.
    pub geometric_pixels: usize,
    /// Pixels without a reference surface.
    pub geometric_pixels_without_reference: usize,
    /// The largest geometric error before re-measuring pixels over the tolerance at
    /// their ray's exact hit (the depth attachment's points).
    pub geometric_error_px_max_depth_buffer: f64,
    /// Pixels over the tolerance whose depth-attachment point lay off the drawn surface
    /// (re-measured at their ray's hit), over every view.
    pub geometric_pixels_depth_off_surface: usize,
    /// Pixels over the tolerance left as measured, over every view (must be 0).
    pub geometric_pixels_not_rechecked: usize,
    /// Body bytes of the blobs of the final cuts (the cut at each leg's last frame).
    pub bytes_in_final_cuts: u64,
    /// Body bytes of the smallest blob set whose cuts meet the tolerance in the final
    /// views.
    pub bytes_needed: u64,
    /// `bytes_fetched / bytes_needed`.
    pub fetched_over_needed: f64,
    /// Whether every needed-set view reached full quality.
    pub needed_full_quality: bool,
    /// Largest projected error left in a needed-set cut (px; within the tolerance).
    pub needed_max_error_px: f64,
    /// Cut halves of the needed-set views, summed.
    pub needed_halves: usize,
    /// The needed set refined ignoring the blobs' side information (the sampling metric
    /// without its flat-ground rule, whatever the point's metric): bytes and halves.
    pub needed_bytes_ignoring_side_info: u64,
    /// Halves.
    pub needed_halves_ignoring_side_info: usize,
    /// `needed_halves_ignoring_side_info / needed_halves`: how much finer the surface is
    /// refined without the side information than the point's metric refines it.
    pub side_info_halves_saved: f64,
    /// Peak GPU bytes of the flight's renderer, and its budget.
    pub gpu_bytes_peak: u64,
    /// The budget (whole slots).
    pub gpu_bytes_budget: u64,
    /// Frames whose drawn cut lagged the client's (upload cap or GPU budget).
    pub frames_not_current: usize,
    /// Cracks and coverage errors over the checked frames of every flight and cold start
    /// (must be 0).
    pub cracks: usize,
    /// Coverage errors.
    pub coverage_errors: usize,
    /// Per compared view.
    pub views: Vec<ViewError>,
}

/// One view of one tolerance against its reference.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct ViewError {
    /// Leg whose final view it is.
    pub leg: usize,
    /// PSNR (`None`: identical).
    pub psnr_db: Option<f64>,
    /// Geometric error: median, 99th percentile, largest (px).
    pub geometric_error_px_p50: f64,
    /// 99th percentile.
    pub geometric_error_px_p99: f64,
    /// Largest.
    pub geometric_error_px_max: f64,
    /// Pixels whose geometric error is above 1 px.
    #[serde(default)]
    pub geometric_pixels_over_1px: usize,
    /// Pixels showing terrain.
    pub pixels: usize,
    /// Of them, pixels with no reference surface on their vertical.
    pub pixels_without_reference: usize,
    /// Background pixels (views that the ground fills: cracks; else the sky).
    pub background_px: usize,
    /// PSNR of the view against the same cut rendered with the camera moved 1 mm
    /// (`None`: identical). Only with `--path extremes`.
    pub jitter_psnr_db: Option<f64>,
    /// Every depth and error value was finite.
    pub finite: bool,
    /// Patches of the cut the renderer's GPU budget left out (drawn as holes).
    pub patches_missing: usize,
    /// The largest error as the depth attachment places each pixel's point, before
    /// pixels over the tolerance were re-measured at their ray's exact hit on the drawn
    /// triangles ([`quincunx_render::error::recheck`]).
    pub geometric_error_px_max_depth_buffer: f64,
    /// Pixels re-measured (their error over the tolerance).
    pub pixels_rechecked: usize,
    /// Of them, pixels whose depth-attachment point lay off the drawn surface.
    pub pixels_depth_off_surface: usize,
    /// Of them, pixels whose ray meets no drawn triangle (kept as measured).
    pub pixels_recheck_no_hit: usize,
    /// Pixels over the tolerance not re-measured (over the limit).
    pub pixels_not_rechecked: usize,
}

/// The reference of one view.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct ReferenceView {
    /// Leg.
    pub leg: usize,
    /// Whether it reached full quality (every visible diamond at the finest level).
    pub full_quality: bool,
    /// Seconds it took.
    pub seconds: f64,
    /// Cut halves.
    pub cut_halves: usize,
    /// Triangles drawn.
    pub triangles: u64,
}

/// What `quincunx trade --json` prints.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct TradeReport {
    /// Line name in the charts.
    pub label: String,
    /// Elevation repository.
    pub repo: String,
    /// Colour repository.
    pub colour: Option<String>,
    /// Flight.
    pub path: String,
    /// Emulated link (`None`: none).
    pub link: Option<[f64; 2]>,
    /// Viewport.
    pub viewport: [u32; 2],
    /// Adapter of the renders.
    pub adapter: String,
    /// One per tolerance, in the order given.
    pub points: Vec<TradePoint>,
    /// The references.
    pub references: Vec<ReferenceView>,
    /// Wall-clock seconds of the whole study.
    pub seconds: f64,
}

/// The metric of a report written before there was a choice.
fn older_metric() -> Metric {
    Metric::Sampling
}

/// A view captured at the end of a leg.
struct Capture {
    leg: usize,
    view: View,
    image: Image,
    depth: DepthImage,
    jitter: Option<Image>,
    missing: usize,
    /// The cut drawn, as triangles: pixels over the tolerance are re-measured on it.
    drawn: SurfaceIndex,
    tolerance_px: f64,
}

/// The domains a trade study runs on.
pub trait TradeDomain: BuiltinFlights + RenderDomain {
    /// Opens `repo` (and `colour`) at `url`.
    fn open(
        url: &str,
        repo: &str,
        colour: Option<&str>,
        config: SessionConfig,
    ) -> Result<Session<Self>, SessionError> {
        match colour {
            Some(c) => Session::open_with_colour(url, repo, c, config),
            None => Session::open(url, repo, config),
        }
    }

    /// The shots of `--path extremes`, or an error for this domain.
    fn extremes(size: [u32; 2]) -> Result<Vec<Shot>>;
}

impl TradeDomain for PlanarRefiner {
    fn extremes(_: [u32; 2]) -> Result<Vec<Shot>> {
        bail!("--path extremes is for planets (a planar repository has no poles or cube corners)")
    }
}

impl TradeDomain for SphereRefiner {
    fn extremes(size: [u32; 2]) -> Result<Vec<Shot>> {
        let shot = |lat, lon, height_m, pitch_deg| Shot {
            place: Place::LatLon(lat, lon),
            height_m,
            heading_deg: 30.0,
            pitch_deg,
            size,
            ..Shot::default()
        };
        // The cube corner (1, 1, 1): latitude asin(1/sqrt 3), longitude 45.
        let corner = (1.0f64 / 3f64.sqrt()).asin().to_degrees();
        Ok(vec![
            shot(36.0, 128.0, 1.0, -20.0),
            shot(36.0, 128.0, 1.0, -90.0),
            shot(0.0, 0.0, 1e8, -90.0),
            shot(90.0, 0.0, 2_000.0, -90.0),
            shot(corner, 45.0, 2_000.0, -90.0),
        ])
    }
}

/// Runs `quincunx trade`.
pub fn run(args: &TradeArgs) -> Result<()> {
    if args.tolerances.is_empty() {
        bail!("--tolerances: give at least one");
    }
    if args.metrics.is_empty() {
        bail!("--metrics: give at least one");
    }
    if let Some(t) = args
        .tolerances
        .iter()
        .find(|t| !(t.is_finite() && **t >= 0.0))
    {
        bail!("--tolerances: {t} is not a tolerance (0 or more pixels)");
    }
    if args.views == 0 {
        bail!("--views must be at least 1");
    }
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    for (name, v) in [
        ("--gpu-budget-mb", args.gpu_budget_mb),
        ("--reference-gpu-budget-mb", args.reference_gpu_budget_mb),
        ("--reference-wait-s", args.reference_wait_s),
    ] {
        if !(v.is_finite() && v > 0.0) {
            bail!("{name} must be positive");
        }
    }
    if !(args.warm_up_s.is_finite() && (0.0..=600.0).contains(&args.warm_up_s)) {
        bail!("--warm-up-s must be within 0..=600 seconds");
    }
    let link = args.link.0;
    let probe = quincunx_client::session::AnySession::open_with_colour(
        &args.server.url,
        &args.server.repo,
        args.server.colour.as_deref(),
        SessionConfig {
            connect: crate::fly::link_options(args.server.ca_cert.as_ref(), None),
            ..SessionConfig::default()
        },
    )
    .with_context(|| format!("opening {} at {}", args.server.repo, args.server.url))?;
    let report = match probe {
        quincunx_client::session::AnySession::Planar(s) => study(s, args, link)?,
        quincunx_client::session::AnySession::Planet(s) => study(s, args, link)?,
    };
    // The report first: a chart that cannot be drawn must not lose it.
    let printed = print(&report, args);
    if let Some(dir) = &args.plot {
        write_plots(dir, &report)?;
    }
    printed
}

/// The flight-like settings of one tolerance.
fn fly_args(args: &TradeArgs, url: &str, metric: Metric, tolerance_px: f64) -> FlyArgs {
    FlyArgs {
        server: ServerArgs {
            url: url.into(),
            ..args.server.clone()
        },
        refine: RefineArgs {
            tolerance_px,
            metric,
        },
        viewport: args.viewport,
        seed: args.seed,
        check_every: args.check_every,
        spacing_m: args.spacing_m,
        render: true,
        gpu_budget_mb: args.gpu_budget_mb,
        ..FlyArgs::new(url, args.server.repo.clone(), args.path.clone())
    }
}

/// Settings of the needed-set and reference sessions: the data without a link, and
/// only what refinement asks for; the needed sets under the flight's cut budget.
fn exact_config(
    args: &TradeArgs,
    metric: Metric,
    flat_fraction: Option<f64>,
    max_cut_halves: Option<usize>,
) -> SessionConfig {
    let mut refine = RefineConfig {
        metric,
        max_cut_halves,
        ..RefineConfig::default()
    };
    if let Some(f) = flat_fraction {
        refine.flat_fraction = f;
    }
    SessionConfig {
        connect: crate::fly::link_options(args.server.ca_cert.as_ref(), None),
        prefetch_ahead: Duration::ZERO,
        lookahead_levels: 0,
        package_factor: None,
        spacing_m: args.spacing_m,
        refine,
        ..SessionConfig::default()
    }
}

/// The whole study over one domain.
fn study<R: TradeDomain>(
    mut probe: Session<R>,
    args: &TradeArgs,
    link: Option<(f64, f64)>,
) -> Result<TradeReport> {
    let started = Instant::now();
    let extremes = args.path == "extremes";
    // One flight for every tolerance.
    let flight = if extremes {
        extremes_flight(&mut probe, &R::extremes(args.viewport)?)?
    } else {
        crate::fly::load_flight(&args.path, &mut probe, args.seed)?
    };
    drop(probe);
    let legs = flight.legs.len();
    let chosen: Vec<usize> = if legs <= args.views {
        (0..legs).collect()
    } else {
        (0..args.views)
            .map(|k| (k * legs + legs / 2) / args.views)
            .collect()
    };
    let mut points = Vec::new();
    let mut captures: Vec<Vec<Capture>> = Vec::new();
    let mut adapter = String::new();
    for &metric in &args.metrics {
        for &t in &args.tolerances {
            tracing::info!(%metric, tolerance_px = t, "flying");
            let (point, caps, name) =
                fly_point::<R>(args, &flight, link, metric, t, &chosen, extremes)
                    .with_context(|| format!("{metric} metric, tolerance {t} px"))?;
            adapter = name;
            points.push(point);
            captures.push(caps);
        }
    }
    // References, one view at a time (each holds a full-resolution cut).
    let gpu = Gpu::headless().context("starting the renderer")?;
    let mut references = Vec::new();
    let first = captures.first().map_or(&[][..], |c| c.as_slice());
    let views: Vec<(usize, View)> = first.iter().map(|c| (c.leg, c.view)).collect();
    let mut per_view: Vec<Vec<ViewError>> = vec![Vec::new(); points.len()];
    let mut pooled: Vec<Vec<f32>> = vec![Vec::new(); points.len()];
    for (vi, (leg, view)) in views.iter().enumerate() {
        tracing::info!(leg, "reference");
        let (reference, ref_image, ref_depth, index) = reference_view::<R>(args, &gpu, *leg, view)?;
        references.push(reference);
        for (pi, caps) in captures.iter().enumerate() {
            let Some(cap) = caps.get(vi) else { continue };
            let (v, errors) = compare(cap, &ref_image, &ref_depth, &index)?;
            per_view[pi].push(v);
            pooled[pi].extend(errors);
        }
    }
    for ((point, views), errors) in points.iter_mut().zip(per_view).zip(pooled) {
        aggregate(point, views, errors);
    }
    Ok(TradeReport {
        label: args
            .label
            .clone()
            .unwrap_or_else(|| match &args.server.colour {
                Some(c) => format!("{}+{c}", args.server.repo),
                None => args.server.repo.clone(),
            }),
        repo: args.server.repo.clone(),
        colour: args.server.colour.clone(),
        path: flight.name.clone(),
        link: link.map(|(k, r)| [k, r]),
        viewport: args.viewport,
        adapter,
        points,
        references,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// `--path extremes`: a hold leg per shot, the camera placed over the streamed terrain.
fn extremes_flight<R: TradeDomain>(probe: &mut Session<R>, shots: &[Shot]) -> Result<Flight> {
    let mut legs = Vec::new();
    for shot in shots {
        let (view, _) = stream_to(probe, shot, Duration::from_secs(60), None)?;
        legs.push(Leg {
            duration_s: 20.0,
            from: Pose {
                eye: view.eye.to_array(),
                target: view.target.to_array(),
            },
            to: None,
            jump: true,
            settle_s: Some(0.5),
        });
    }
    Ok(Flight {
        name: "extremes".into(),
        legs,
    })
}

/// Flies one tolerance and captures the chosen legs' final views.
fn fly_point<R: TradeDomain>(
    args: &TradeArgs,
    flight: &Flight,
    link: Option<(f64, f64)>,
    metric: Metric,
    tolerance_px: f64,
    chosen: &[usize],
    jitter: bool,
) -> Result<(TradePoint, Vec<Capture>, String)> {
    let (proxy, mut session, fa) = flight_session::<R>(args, link, metric, tolerance_px, None)?;
    let opts = fly_options(&fa);
    let mut drawer = FrameDrawer::new(&mut session, &fa)?;
    let mut frames = Vec::new();
    let report = flight::fly_with(&mut session, flight, &opts, |s, view, rec| {
        let t = Instant::now();
        let changes = s.cut_changes();
        frames.push((changes, *view, t.elapsed().as_secs_f64() * 1e3, rec.leg));
    })?;
    if let Some(why) = crate::fly::fetch_failure(
        report.bytes_fetched,
        report.requests,
        report.fetch_errors,
        report.fetch_timeouts,
    ) {
        bail!("the flight at {tolerance_px} px: {why}");
    }
    // The last frame of each chosen leg.
    let last: Vec<usize> = (0..frames.len())
        .filter(|&k| frames.get(k + 1).is_none_or(|f| f.3 != frames[k].3))
        .filter(|&k| chosen.contains(&frames[k].3))
        .collect();
    let mut captures = Vec::new();
    let dag = session.dag();
    let world = dag.refiner().world_frame(&session.world(), 0);
    // The drawn cut, replayed alongside the renderer.
    let mut cut = std::collections::HashMap::new();
    for (k, (changes, view, take_ms, leg)) in frames.into_iter().enumerate() {
        for key in &changes.left {
            cut.remove(key);
        }
        for p in &changes.entered {
            cut.insert((p.id, p.half), p.clone());
        }
        drawer
            .frame(dag.refiner(), dag.colour(), changes, &view, take_ms, k)
            .context("rendering the flight")?;
        if last.contains(&k) {
            let (image, depth, stats) = drawer.capture(&view, BACKGROUND)?;
            let jitter = if jitter {
                // The same cut, the camera 1 mm along the view's right.
                let right = (view.target - view.eye).cross(view.up).normalize_or_zero();
                let moved = View {
                    eye: view.eye + right * 1e-3,
                    target: view.target + right * 1e-3,
                    ..view
                };
                Some(drawer.capture(&moved, BACKGROUND)?.0)
            } else {
                None
            };
            let drawn = SurfaceIndex::from_patches(
                world,
                cut.values().filter_map(|p| {
                    let affine = dag.refiner().affine(p.id, &p.corners, p.half)?;
                    Some((affine, p.half, std::sync::Arc::clone(&p.grid)))
                }),
            );
            captures.push(Capture {
                leg,
                view,
                image,
                depth,
                jitter,
                missing: stats.missing,
                drawn,
                tolerance_px,
            });
        }
    }
    let render = drawer.summary();
    let bound = session.max_cut_halves();
    let cut_budget_halves = bound.unwrap_or(0);
    drop(drawer);
    drop(session);
    drop(proxy);
    // The other runs: only their jumps' times are kept.
    let mut runs = vec![report.jumps.clone()];
    // Cracks and coverage errors of every flight, the first's and those below.
    let (mut cracks, mut coverage_errors) = (report.cracks, report.coverage_errors);
    for run in 1..args.runs {
        let again = fly_again::<R>(args, flight, link, metric, tolerance_px, bound)
            .with_context(|| format!("run {}", run + 1))?;
        cracks += again.cracks;
        coverage_errors += again.coverage_errors;
        runs.push(again.jumps);
    }
    let jumps = pool_jumps(&runs);
    // Cold starts at each jump's view.
    let mut colds = Vec::new();
    for run in 0..args.runs {
        let mut one_run = Vec::new();
        for leg in flight.legs.iter().filter(|l| l.jump) {
            let alone = Flight {
                name: format!("{} (one leg)", flight.name),
                legs: vec![leg.clone()],
            };
            let r = fly_again::<R>(args, &alone, link, metric, tolerance_px, bound)
                .with_context(|| format!("cold start {} of run {}", one_run.len() + 1, run + 1))?;
            cracks += r.cracks;
            coverage_errors += r.coverage_errors;
            one_run.extend(r.jumps);
        }
        colds.push(one_run);
    }
    let cold = pool_jumps(&colds);
    // The needed set, with and without the side information (the sampling metric
    // without its flat-ground rule).
    let wait = Duration::from_secs_f64(args.reference_wait_s);
    let needed = |metric: Metric, flat: Option<f64>| -> Result<NeededSet> {
        Ok(flight::needed_for_views(
            || {
                R::open(
                    &args.server.url,
                    &args.server.repo,
                    args.server.colour.as_deref(),
                    exact_config(args, metric, flat, Some(cut_budget_halves)),
                )
            },
            &report.final_views,
            wait,
        )?)
    };
    let with = needed(metric, None)?;
    let without = needed(Metric::Sampling, Some(0.0))?;
    let needed_halves: usize = with.views.iter().map(|v| v.cut_halves).sum();
    let halves_without: usize = without.views.iter().map(|v| v.cut_halves).sum();
    let point = TradePoint {
        metric,
        tolerance_px,
        triangles_median: render.triangles_p50,
        triangles_max: render.triangles_max,
        patches_median: render.patches_p50,
        patches_max: render.patches_max,
        refine_ms_median: report.refine_ms_p50,
        refine_ms_p99: report.refine_ms_p99,
        render_ms_median: render.cpu_ms_p50,
        render_ms_p99: render.cpu_ms_p99,
        render_gpu_ms_median: render.gpu_ms_p50,
        render_gpu_ms_p99: render.gpu_ms_p99,
        frames: report.frames,
        frames_per_s: report.frames_per_s,
        bytes_fetched: report.bytes_fetched,
        colour_bytes_fetched: report.colour_bytes_fetched,
        bytes_per_s: if report.seconds > 0.0 {
            report.bytes_fetched as f64 / report.seconds
        } else {
            0.0
        },
        time_to_full_quality_s_median: jumps.median_s,
        time_to_full_quality_s_max: jumps.max_s,
        time_to_full_quality_s_mean: jumps.mean_s,
        runs: runs.len(),
        jump_times_s: runs
            .iter()
            .map(|r| r.iter().map(|j| j.time_to_full_quality_s).collect())
            .collect(),
        jumps_unfinished: jumps.unfinished,
        jumps_budget_limited: jumps.budget_limited,
        time_to_full_quality_cold_s_median: cold.median_s,
        time_to_full_quality_cold_s_max: cold.max_s,
        cold_times_s: colds
            .iter()
            .map(|r| r.iter().map(|j| j.time_to_full_quality_s).collect())
            .collect(),
        cold_unfinished: cold.unfinished,
        cut_budget_halves,
        bytes_in_final_cuts: report.bytes_in_final_cuts,
        bytes_needed: with.bytes,
        fetched_over_needed: if with.bytes > 0 {
            report.bytes_fetched as f64 / with.bytes as f64
        } else {
            0.0
        },
        needed_full_quality: with.views.iter().all(|v| v.full_quality),
        needed_max_error_px: with
            .views
            .iter()
            .map(|v| v.max_error_px)
            .fold(0.0, f64::max),
        needed_halves,
        needed_bytes_ignoring_side_info: without.bytes,
        needed_halves_ignoring_side_info: halves_without,
        side_info_halves_saved: if needed_halves > 0 {
            halves_without as f64 / needed_halves as f64
        } else {
            0.0
        },
        gpu_bytes_peak: render.gpu_bytes_peak,
        gpu_bytes_budget: render.gpu_bytes_budget,
        frames_not_current: render.frames_not_current,
        cracks,
        coverage_errors,
        ..TradePoint::default()
    };
    Ok((point, captures, render.adapter))
}

/// An emulated link and its URL.
type Link = (LinkProxy, String);

/// A new session for a flight at `tolerance_px` through a new link (open while the
/// returned proxy lives), its cut bounded by `bound` if given (else by the renderer).
/// With `--warm-up-s` 0 the first jump starts from nothing, as a client does that opens
/// a repository and goes to a view; else the session first refines its overviews (as
/// `quincunx fly` does), whose bytes count as fetched.
fn flight_session<R: TradeDomain>(
    args: &TradeArgs,
    link: Option<(f64, f64)>,
    metric: Metric,
    tolerance_px: f64,
    bound: Option<Option<usize>>,
) -> Result<(Option<Link>, Session<R>, FlyArgs)> {
    let proxy = link.map(|l| start_link(&args.server.url, l)).transpose()?;
    let url = proxy
        .as_ref()
        .map_or(args.server.url.as_str(), |(_, u)| u.as_str());
    let fa = fly_args(args, url, metric, tolerance_px);
    let mut config = session_config(&fa);
    config.connect =
        crate::fly::link_options(args.server.ca_cert.as_ref(), proxy.as_ref().map(|(p, _)| p));
    let mut session = R::open(
        url,
        &args.server.repo,
        args.server.colour.as_deref(),
        config,
    )?;
    if let Some(bound) = bound {
        session.set_max_cut_halves(bound);
    }
    if args.warm_up_s > 0.0 && !session.warm_up(Duration::from_secs_f64(args.warm_up_s))? {
        tracing::warn!("the roots did not arrive within --warm-up-s");
    }
    Ok((proxy, session, fa))
}

/// A flight of `tolerance_px` as the first run flew it (a new session through a new
/// link, its cut bounded as the renderer bounded the first's), without rendering.
fn fly_again<R: TradeDomain>(
    args: &TradeArgs,
    flight: &Flight,
    link: Option<(f64, f64)>,
    metric: Metric,
    tolerance_px: f64,
    bound: Option<usize>,
) -> Result<flight::FlightReport> {
    let (_proxy, mut session, fa) =
        flight_session::<R>(args, link, metric, tolerance_px, Some(bound))?;
    let opts = fly_options(&fa);
    // The same per-frame work as the first run: its cut changes are taken (and dropped).
    Ok(flight::fly_with(&mut session, flight, &opts, |s, _, _| {
        drop(s.cut_changes());
    })?)
}

/// Times to full quality pooled over runs.
#[derive(Debug, Default, PartialEq)]
struct PooledJumps {
    median_s: Option<f64>,
    max_s: Option<f64>,
    mean_s: Option<f64>,
    unfinished: usize,
    budget_limited: usize,
}

/// Median (nearest rank), largest and mean over every jump of every run that reached
/// full quality, and the counts of the others.
fn pool_jumps(runs: &[Vec<flight::JumpResult>]) -> PooledJumps {
    let all = runs.iter().flatten();
    let mut t: Vec<f64> = all
        .clone()
        .filter_map(|j| j.time_to_full_quality_s)
        .collect();
    t.sort_by(f64::total_cmp);
    PooledJumps {
        median_s: (!t.is_empty()).then(|| flight::percentile(&t, 0.5)),
        max_s: t.last().copied(),
        mean_s: (!t.is_empty()).then(|| t.iter().sum::<f64>() / t.len() as f64),
        unfinished: all
            .clone()
            .filter(|j| j.time_to_full_quality_s.is_none())
            .count(),
        budget_limited: all.filter(|j| j.budget_limited).count(),
    }
}

/// The full-resolution reference of `view`: refined at tolerance 0, drawn, read back.
fn reference_view<R: TradeDomain>(
    args: &TradeArgs,
    gpu: &Gpu,
    leg: usize,
    view: &View,
) -> Result<(ReferenceView, Image, DepthImage, SurfaceIndex)> {
    let mut session = R::open(
        &args.server.url,
        &args.server.repo,
        args.server.colour.as_deref(),
        // Sampling at 0 px: every visible diamond to the finest coded level, whatever
        // its bound says.
        exact_config(args, Metric::Sampling, None, None),
    )?;
    let view = View {
        tolerance_px: 0.0,
        ..*view
    };
    let start = Instant::now();
    let wait = Duration::from_secs_f64(args.reference_wait_s);
    let frame = loop {
        let frame = session.update(&view, start.elapsed(), Duration::from_millis(100))?;
        if frame.refine.full_quality || start.elapsed() >= wait {
            break frame;
        }
        if frame.refine.refined == 0 {
            std::thread::sleep(Duration::from_millis(2));
        }
    };
    if !frame.refine.full_quality {
        tracing::warn!(
            leg,
            "the reference did not reach full quality within --reference-wait-s"
        );
    }
    let seconds = start.elapsed().as_secs_f64();
    let config = RendererConfig {
        gpu_budget_bytes: (args.reference_gpu_budget_mb * 1_048_576.0) as u64,
        colour_format: OFFSCREEN_FORMAT,
        ..RendererConfig::default()
    };
    // The whole cut, drawn in parts of at most one pool's capacity, each depth-tested over
    // the last: a full-resolution cut can need more slots than the budget or one storage
    // binding holds (colour layers of large diamonds). A part gets a renderer of its own,
    // so nothing of the last part is kept resident beside it.
    let camera = Camera::from_view(&view);
    let offscreen = Offscreen::new(gpu, view.viewport_px)?;
    session.restart_cut_changes();
    let cut = session.cut_changes().entered;
    let mut first = Some(TerrainRenderer::for_session(
        &gpu.device,
        &session,
        config.clone(),
    )?);
    let capacity = first.as_ref().map_or(1, TerrainRenderer::capacity);
    let dag = session.dag();
    let mut triangles = 0;
    for (k, part) in cut.chunks(capacity.max(1) as usize).enumerate() {
        // The last part's renderer is dropped before the next one's pool is made.
        let mut renderer = match first.take() {
            Some(r) => r,
            None => TerrainRenderer::for_session(&gpu.device, &session, config.clone())?,
        };
        renderer.apply(
            dag.refiner(),
            dag.colour(),
            PatchChanges {
                entered: part.to_vec(),
                left: Vec::new(),
            },
        )?;
        let mut stats = renderer.prepare(&gpu.queue, &camera);
        while stats.pending > 0 {
            stats = renderer.prepare(&gpu.queue, &camera);
        }
        if stats.missing > 0 {
            bail!(
                "the reference of leg {leg}: {} patches of a part of {} did not fit a pool of \
                 {capacity} slots (--reference-gpu-budget-mb {})",
                stats.missing,
                part.len(),
                args.reference_gpu_budget_mb,
            );
        }
        triangles += stats.triangles;
        if k == 0 {
            offscreen.render(gpu, BACKGROUND, |pass| renderer.draw(pass))?;
        } else {
            offscreen.render_over(gpu, |pass| renderer.draw(pass))?;
        }
    }
    if cut.is_empty() {
        offscreen.render(gpu, BACKGROUND, |_| {})?;
    }
    let image = offscreen.read(gpu)?;
    let depth = offscreen.read_depth(gpu)?;
    let index = SurfaceIndex::new(&session);
    Ok((
        ReferenceView {
            leg,
            full_quality: frame.refine.full_quality,
            seconds,
            cut_halves: frame.refine.cut_halves,
            triangles,
        },
        image,
        depth,
        index,
    ))
}

/// Pixels over the tolerance re-measured per view, at most.
const RECHECK_LIMIT: usize = 10_000;

/// One captured view against its reference, and its measured pixels' errors.
fn compare(
    cap: &Capture,
    ref_image: &Image,
    ref_depth: &DepthImage,
    index: &SurfaceIndex,
) -> Result<(ViewError, Vec<f32>)> {
    let camera = Camera::from_view(&cap.view);
    let mut map = error_map(&camera, &cap.depth, Some(ref_depth), index)?;
    let depth_buffer_max = map.summary().max_px;
    let rechecked = recheck(
        &mut map,
        &camera,
        &cap.depth,
        index,
        &cap.drawn,
        cap.tolerance_px,
        RECHECK_LIMIT,
    )?;
    let g = map.summary();
    let errors: Vec<f32> = map
        .error_px
        .iter()
        .filter(|e| e.is_finite())
        .map(|&e| e as f32)
        .collect();
    let finite_psnr = |v: f64| v.is_finite().then_some(v);
    let psnr = psnr_db(&cap.image, ref_image)?;
    let jitter = match &cap.jitter {
        Some(j) => finite_psnr(psnr_db(&cap.image, j)?),
        None => None,
    };
    let background_px = cap.depth.data.iter().filter(|d| **d == 0.0).count();
    let finite = cap.depth.data.iter().all(|d| d.is_finite())
        && g.p99_px.is_finite()
        && g.max_px.is_finite();
    Ok((
        ViewError {
            leg: cap.leg,
            psnr_db: finite_psnr(psnr),
            geometric_error_px_p50: g.p50_px,
            geometric_error_px_p99: g.p99_px,
            geometric_error_px_max: g.max_px,
            geometric_pixels_over_1px: g.over_1px,
            pixels: g.pixels,
            pixels_without_reference: g.pixels_without_reference,
            background_px,
            jitter_psnr_db: jitter,
            finite,
            patches_missing: cap.missing,
            geometric_error_px_max_depth_buffer: depth_buffer_max,
            pixels_rechecked: rechecked.checked,
            pixels_depth_off_surface: rechecked.moved,
            pixels_recheck_no_hit: rechecked.no_hit,
            pixels_not_rechecked: rechecked.unchecked,
        },
        errors,
    ))
}

/// A tolerance's image figures from its views and their measured pixels' errors.
fn aggregate(point: &mut TradePoint, views: Vec<ViewError>, mut errors: Vec<f32>) {
    // PSNR over all pixels: the views' mean squared errors, averaged.
    let mse: Vec<f64> = views
        .iter()
        .map(|v| {
            v.psnr_db
                .map_or(0.0, |p| 255f64.powi(2) / 10f64.powf(p / 10.0))
        })
        .collect();
    let mean = mse.iter().sum::<f64>() / mse.len().max(1) as f64;
    point.psnr_db = (mean > 0.0).then(|| 10.0 * (255f64.powi(2) / mean).log10());
    // Percentiles over every measured pixel of every view (nearest rank).
    errors.sort_unstable_by(f32::total_cmp);
    let rank = |p: usize| {
        let n = errors.len();
        if n == 0 {
            0.0
        } else {
            f64::from(errors[(p * n).div_ceil(100).clamp(1, n) - 1])
        }
    };
    point.geometric_error_px_p50 = rank(50);
    point.geometric_error_px_p99 = rank(99);
    point.geometric_error_px_max = views
        .iter()
        .map(|v| v.geometric_error_px_max)
        .fold(0.0, f64::max);
    point.geometric_pixels = views.iter().map(|v| v.pixels).sum();
    point.geometric_pixels_without_reference =
        views.iter().map(|v| v.pixels_without_reference).sum();
    point.geometric_error_px_max_depth_buffer = views
        .iter()
        .map(|v| v.geometric_error_px_max_depth_buffer)
        .fold(0.0, f64::max);
    point.geometric_pixels_depth_off_surface =
        views.iter().map(|v| v.pixels_depth_off_surface).sum();
    point.geometric_pixels_not_rechecked = views.iter().map(|v| v.pixels_not_rechecked).sum();
    point.views = views;
}

fn print(report: &TradeReport, args: &TradeArgs) -> Result<()> {
    if args.json {
        outln!("{}", serde_json::to_string(report)?);
    } else {
        outln!(
            "trade study of {} ({} flight, {} views, {}x{}, {})",
            report.label,
            report.path,
            report.references.len(),
            report.viewport[0],
            report.viewport[1],
            report.link.map_or("no link".to_string(), |[k, r]| format!(
                "{k} kbit/s, {r} ms"
            )),
        );
        outln!(
            "{:>9} {:>6} {:>10} {:>8} {:>8} {:>12} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
            "metric",
            "tol px",
            "triangles",
            "refine",
            "render",
            "bytes",
            "ttfq s",
            "cold s",
            "PSNR dB",
            "geo p99",
            "geo max",
            "f/need"
        );
        for p in &report.points {
            outln!(
                "{:>9} {:>6} {:>10.0} {:>8.3} {:>8.3} {:>12} {:>8} {:>8} {:>8} {:>8.3} {:>8.3} {:>8.3}",
                p.metric.name(),
                p.tolerance_px,
                p.triangles_median,
                p.refine_ms_median,
                p.render_ms_median,
                p.bytes_fetched,
                p.time_to_full_quality_s_median
                    .map_or("-".into(), |t| format!("{t:.2}")),
                p.time_to_full_quality_cold_s_median
                    .map_or("-".into(), |t| format!("{t:.2}")),
                p.psnr_db.map_or("inf".into(), |v| format!("{v:.2}")),
                p.geometric_error_px_p99,
                p.geometric_error_px_max,
                p.fetched_over_needed
            );
        }
    }
    let cracks: usize = report
        .points
        .iter()
        .map(|p| p.cracks + p.coverage_errors)
        .sum();
    if cracks > 0 {
        bail!("the flights' cuts were inconsistent: {cracks} cracks and coverage errors");
    }
    Ok(())
}

/// Writes `report` as `<label>.json` into `dir` and charts every report there.
fn write_plots(dir: &Path, report: &TradeReport) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let file = dir.join(format!("{}.json", sanitize(&report.label)));
    std::fs::write(&file, serde_json::to_string_pretty(report)?)
        .with_context(|| format!("writing {}", file.display()))?;
    replot(dir)
}

/// Draws the charts of every report in `dir` (the `<label>.json` files `--plot` wrote),
/// measuring nothing: for reports gathered from several runs or machines.
pub fn replot(dir: &Path) -> Result<()> {
    let mut reports = Vec::new();
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    entries.sort();
    for p in entries {
        let text =
            std::fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
        match serde_json::from_str::<TradeReport>(&text) {
            Ok(r) if !r.points.is_empty() => reports.push(r),
            _ => tracing::warn!(file = %p.display(), "not a trade report: left out of the charts"),
        }
    }
    type Get = fn(&TradePoint) -> Option<f64>;
    let charts: [(&str, &str, &str, bool, Get); 9] = [
        (
            "triangles",
            "Triangles per frame (median)",
            "triangles",
            true,
            |p| Some(p.triangles_median),
        ),
        (
            "refine-ms",
            "Refinement per frame (median)",
            "ms",
            true,
            |p| Some(p.refine_ms_median),
        ),
        (
            "render-ms",
            "Renderer CPU per frame (median)",
            "ms",
            true,
            |p| Some(p.render_ms_median),
        ),
        (
            "render-gpu-ms",
            "Rasterisation per frame (median, lavapipe)",
            "ms",
            true,
            |p| p.render_gpu_ms_median,
        ),
        (
            "bytes",
            "Bytes fetched over the flight",
            "bytes",
            true,
            |p| Some(p.bytes_fetched as f64),
        ),
        (
            "ttfq",
            "Time to full quality after a jump (median)",
            "s",
            true,
            |p| p.time_to_full_quality_s_median,
        ),
        (
            "ttfq-cold",
            "Time to full quality from a cold start at each view (median)",
            "s",
            true,
            |p| p.time_to_full_quality_cold_s_median,
        ),
        (
            "psnr",
            "PSNR against the full-resolution reference",
            "dB",
            false,
            |p| p.psnr_db,
        ),
        (
            "geometric",
            "Geometric error, p99 over every pixel of the views",
            "px",
            false,
            |p| Some(p.geometric_error_px_p99),
        ),
    ];
    for (name, title, y_label, log_y, get) in charts {
        // One curve per report and metric.
        let series: Vec<Series> = reports
            .iter()
            .flat_map(|r| {
                let mut metrics: Vec<Metric> = r.points.iter().map(|p| p.metric).collect();
                metrics.dedup();
                metrics.into_iter().map(move |m| (r, m))
            })
            .map(|(r, metric)| Series {
                name: format!("{} ({metric})", r.label),
                points: r
                    .points
                    .iter()
                    .filter(|p| p.metric == metric && p.tolerance_px > 0.0)
                    .filter_map(|p| get(p).map(|y| (p.tolerance_px, y)))
                    .filter(|&(_, y)| y.is_finite() && (!log_y || y > 0.0))
                    .collect(),
            })
            .filter(|s| !s.points.is_empty())
            .collect();
        if series.is_empty() {
            continue;
        }
        let chart = Chart {
            title,
            x_label: "tolerance (px)",
            y_label,
            log_x: true,
            log_y,
            series: &series,
        };
        let out = dir.join(format!("trade-{name}.png"));
        crate::plot::write_png(&out, &chart, (900, 600))
            .with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

/// A label as a file name.
fn sanitize(label: &str) -> String {
    label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '+' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn jumps_pool_over_runs() {
        let j = |leg, t: Option<f64>, limited| flight::JumpResult {
            leg,
            time_to_full_quality_s: t,
            budget_limited: limited,
            bytes_fetched: 0,
        };
        // Seven finished jumps over three runs; the median is the 4th smallest.
        let runs = vec![
            vec![
                j(0, Some(0.5), false),
                j(2, Some(0.1), false),
                j(4, None, false),
            ],
            vec![
                j(0, Some(0.7), true),
                j(2, Some(0.3), false),
                j(4, Some(0.2), false),
            ],
            vec![
                j(0, Some(0.4), false),
                j(2, Some(0.6), false),
                j(4, None, false),
            ],
        ];
        let p = pool_jumps(&runs);
        assert_eq!(p.median_s, Some(0.4));
        assert_eq!(p.max_s, Some(0.7));
        assert!((p.mean_s.unwrap() - 2.8 / 7.0).abs() < 1e-12);
        assert_eq!((p.unfinished, p.budget_limited), (2, 1));
        assert_eq!(
            pool_jumps(&[vec![j(0, None, false)]]),
            PooledJumps {
                unfinished: 1,
                ..PooledJumps::default()
            }
        );
    }

    #[test]
    fn aggregate_pools_psnr_and_takes_the_worst_view() {
        let mut p = TradePoint::default();
        let v = |psnr: Option<f64>, p99: f64| ViewError {
            psnr_db: psnr,
            geometric_error_px_p50: p99 / 2.0,
            geometric_error_px_p99: p99,
            geometric_error_px_max: 2.0 * p99,
            pixels: 10,
            ..ViewError::default()
        };
        // MSE 65.025 and 0 (identical): mean 32.5125, PSNR = 30 + 10 log10 2.
        // 200 pixels: 0.01, 0.02, ..., 2.0; p99 = the 198th.
        let errors: Vec<f32> = (1..=200).map(|k| k as f32 / 100.0).collect();
        aggregate(&mut p, vec![v(Some(30.0), 1.0), v(None, 0.5)], errors);
        assert!((p.psnr_db.unwrap() - (30.0 + 10.0 * 2f64.log10())).abs() < 1e-9);
        assert!((p.geometric_error_px_p99 - 1.98).abs() < 1e-6);
        assert!((p.geometric_error_px_p50 - 1.0).abs() < 1e-6);
        assert_eq!((p.geometric_error_px_max, p.geometric_pixels), (2.0, 20));
        let mut same = TradePoint::default();
        aggregate(&mut same, vec![v(None, 0.0)], vec![0.0; 4]);
        assert_eq!(same.psnr_db, None);
    }
}
