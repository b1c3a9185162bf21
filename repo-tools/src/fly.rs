//! `quincunx fly`: a headless client session flying a camera path against a server, in
//! real time, optionally through an emulated narrow link; per-frame stats and a summary.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_client::fetch::Transport;
use quincunx_client::fetch::http1::Endpoint;
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::fetch::tls::ConnectOptions;
use quincunx_client::flight::{
    self, BuiltinFlights, Flight, FlightReport, FlyOptions, FrameRecord,
};
use quincunx_client::session::{AnySession, Session, SessionConfig};
use quincunx_codec::incremental::Procedural;

use crate::args::{RefineArgs, ServerArgs};

/// `quincunx fly` options.
#[derive(Args, Debug, Clone)]
pub struct FlyArgs {
    /// Where to stream from.
    #[command(flatten)]
    pub server: ServerArgs,
    /// With `--colour`: detail made up below the shallower layer's finest level, as
    /// zero-centred uniform noise of this amplitude (integer units of that layer; 0:
    /// zero detail, smooth interpolation).
    #[arg(long, default_value_t = 0)]
    pub procedural_noise: i32,
    /// `approach`, `low-flight`, `jump`, or a JSON flight file (see `docs/streaming.md`).
    #[arg(long, default_value = "jump")]
    pub path: String,
    /// What the tolerance bounds.
    #[command(flatten)]
    pub refine: RefineArgs,
    /// `pipelined`, `plain` or `h2`.
    #[arg(long, default_value = "pipelined")]
    pub transport: Transport,
    /// Emulated link `KBIT_S,RTT_MS` (an in-process throttling proxy in front of the
    /// server), e.g. `4000,100`.
    #[arg(long, value_parser = crate::args::parse_link)]
    pub link: Option<(f64, f64)>,
    /// Persistent connections (pipelined and plain).
    #[arg(long, default_value_t = 2)]
    pub connections: usize,
    /// Refinement budget per frame, milliseconds.
    #[arg(long, default_value_t = 4.0)]
    pub frame_budget_ms: f64,
    /// Frames per second.
    #[arg(long, default_value_t = 60.0)]
    pub fps: f64,
    /// Viewport `WIDTHxHEIGHT`.
    #[arg(long, default_value = "1920x1080", value_parser = parse_viewport)]
    pub viewport: [u32; 2],
    /// Prefetch horizon in seconds (0 disables prefetch).
    #[arg(long, default_value_t = 0.5)]
    pub prefetch_s: f64,
    /// Levels below each wanted diamond requested ahead (see `SessionConfig`).
    #[arg(long, default_value_t = 2)]
    pub lookahead_levels: usize,
    /// Ask for packages (a blob with its small owned children's) when a diamond's
    /// projected error is above this many times the tolerance; 0: bare blobs only.
    #[arg(long, default_value_t = 2.0)]
    pub package_factor: f64,
    /// Memory budget of the client's DAG in MiB (default: only the view bounds it).
    #[arg(long)]
    pub dag_budget_mb: Option<f64>,
    /// Metres between samples (default: from the georeference).
    #[arg(long)]
    pub spacing_m: Option<f64>,
    /// Seed of the `jump` places.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Check the cut for cracks every this many frames (0 = never). The checks are kept
    /// off the flight's clock and their cost reported separately (`check_ms_*`).
    #[arg(long, default_value_t = 1)]
    pub check_every: usize,
    /// Largest share of the flight's time the checks may take in wall-clock time: a
    /// frame due for a check is skipped while they exceed it (`frames_checked` says how
    /// many were). 0: no limit, every due frame is checked however long it takes.
    #[arg(long, default_value_t = 0.25)]
    pub check_max_share: f64,
    /// Seconds the metadata request may take in all, and a blob request may go without
    /// progress.
    #[arg(long, default_value_t = 10.0)]
    pub timeout_s: f64,
    /// Seconds a blob request may take in all, however steadily its bytes come (a
    /// server trickling a byte at a time): then it fails, is counted as a timeout and
    /// retried.
    #[arg(long, default_value_t = 30.0)]
    pub deadline_s: f64,
    /// One JSON object (the summary) on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Per-frame JSON lines on stderr.
    #[arg(long)]
    pub frames: bool,
    /// Draw every frame offscreen with `quincunx-render` (lavapipe or a GPU) and report
    /// the renderer's CPU time per frame (changes to submitted commands), upload bytes
    /// and GPU memory (`render` in the JSON).
    #[arg(long)]
    pub render: bool,
    /// With `--render`: the offscreen image size (default: the viewport; the cut is
    /// always refined for the viewport).
    #[arg(long, value_parser = parse_viewport)]
    pub render_size: Option<[u32; 2]>,
    /// With `--render`: GPU memory budget for patches, MB.
    #[arg(long, default_value_t = 128.0)]
    pub gpu_budget_mb: f64,
    /// Exit 0 even when some jumps never reach full quality within their leg (for
    /// measuring links too slow for the path's legs). Without it such a run exits 1.
    #[arg(long)]
    pub allow_unfinished: bool,
}

impl FlyArgs {
    /// The command line's defaults for flying `path` over `repo` at `url` (1 px, pipelined,
    /// 1920x1080 at 60 frames/s, every frame checked, text output).
    pub fn new(url: impl Into<String>, repo: impl Into<String>, path: impl Into<String>) -> Self {
        FlyArgs {
            server: ServerArgs::new(url, repo),
            procedural_noise: 0,
            path: path.into(),
            refine: RefineArgs::default(),
            transport: Transport::Pipelined,
            link: None,
            connections: 2,
            frame_budget_ms: 4.0,
            fps: 60.0,
            viewport: [1920, 1080],
            prefetch_s: 0.5,
            lookahead_levels: 2,
            package_factor: 2.0,
            dag_budget_mb: None,
            spacing_m: None,
            seed: 1,
            check_every: 1,
            check_max_share: 0.25,
            timeout_s: 10.0,
            deadline_s: 30.0,
            json: false,
            frames: false,
            render: false,
            render_size: None,
            gpu_budget_mb: 128.0,
            allow_unfinished: false,
        }
    }
}

/// Why the requests of one or more flights (`bytes` fetched, `requests` written,
/// `errors` failed attempts, `timeouts` of them) did not stream the repository, or `None`:
/// nothing fetched but errors, or most attempts failed (answers that were garbage,
/// truncated or under the wrong key fail to decode; a server that went away fails to
/// connect).
pub fn fetch_failure(bytes: u64, requests: u64, errors: u64, timeouts: u64) -> Option<String> {
    let attempts = requests.max(errors);
    if bytes == 0 && errors > 0 {
        let hint = if timeouts > 0 {
            ": no progress within --timeout-s or no whole answer within --deadline-s"
        } else {
            ""
        };
        Some(format!(
            "the flight fetched nothing: {errors} fetch errors ({timeouts} timeouts{hint})"
        ))
    } else if errors > 0 && errors * 2 > attempts {
        Some(format!(
            "most requests failed: {errors} of {attempts} attempts ({timeouts} timeouts): the \
             server answered what is not the repository's blobs, or went away"
        ))
    } else {
        None
    }
}

/// Why a flight did not do what it was asked, in one line, or `None`: its fetches failed
/// ([`fetch_failure`]), a cut was inconsistent, or (with `full_quality`) a jump never
/// reached full quality in its leg.
pub fn flight_failure(r: &FlightReport, full_quality: bool) -> Option<String> {
    if let Some(why) = fetch_failure(
        r.bytes_fetched,
        r.requests,
        r.fetch_errors,
        r.fetch_timeouts,
    ) {
        Some(why)
    } else if r.cracks > 0 || r.coverage_errors > 0 {
        Some(format!(
            "the cut was inconsistent: {} cracks, {} coverage errors",
            r.cracks, r.coverage_errors
        ))
    } else if full_quality && r.jumps_unfinished > 0 {
        Some(format!(
            "{} of {} jumps never reached full quality within their leg ({} requests \
             failed); --allow-unfinished accepts that",
            r.jumps_unfinished,
            r.jumps.len(),
            r.fetch_errors
        ))
    } else {
        None
    }
}

/// Parses `WxH` (each side 1..=16384).
pub fn parse_viewport(s: &str) -> Result<[u32; 2], String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("{s:?} is not WIDTHxHEIGHT"))?;
    let p = |t: &str| match t.parse::<u32>() {
        Ok(v) if (1..=16_384).contains(&v) => Ok(v),
        _ => Err(format!("{t:?} is not a size in 1..=16384")),
    };
    Ok([p(w)?, p(h)?])
}

/// The session settings `args` ask for.
pub fn session_config(args: &FlyArgs) -> SessionConfig {
    SessionConfig {
        transport: args.transport,
        connections: args.connections,
        prefetch_ahead: Duration::from_secs_f64(args.prefetch_s.max(0.0)),
        spacing_m: args.spacing_m,
        lookahead_levels: args.lookahead_levels,
        package_factor: (args.package_factor > 0.0).then_some(args.package_factor),
        procedural: match args.procedural_noise {
            a if a > 0 => Procedural::Noise {
                amplitude: a,
                seed: args.seed,
            },
            _ => Procedural::Zero,
        },
        refine: quincunx_client::refine::RefineConfig {
            metric: args.refine.metric,
            max_dag_bytes: args
                .dag_budget_mb
                .map(|mb| (mb.max(0.0) * 1_048_576.0) as usize),
            ..Default::default()
        },
        timeout: Duration::from_secs_f64(args.timeout_s),
        request_deadline: Duration::from_secs_f64(args.deadline_s),
        connect: link_options(args.server.ca_cert.as_ref(), None),
        ..SessionConfig::default()
    }
}

/// The run options `args` ask for.
pub fn fly_options(args: &FlyArgs) -> FlyOptions {
    FlyOptions {
        fps: args.fps,
        frame_budget: Duration::from_secs_f64(args.frame_budget_ms.max(0.0) / 1e3),
        viewport_px: args.viewport,
        tolerance_px: args.refine.tolerance_px,
        check_every: args.check_every,
        check_max_share: (args.check_max_share > 0.0).then_some(args.check_max_share),
        ..FlyOptions::default()
    }
}

/// A built-in flight or one read from a file, over the session's world.
pub fn load_flight<R: BuiltinFlights>(
    path: &str,
    session: &mut Session<R>,
    seed: u64,
) -> Result<Flight> {
    if flight::BUILTIN.contains(&path) {
        return Ok(Flight::builtin_for(path, session, seed)?);
    }
    let p = Path::new(path);
    if !p.exists() {
        bail!(
            "no flight {path:?}: built-in flights are {} (or give a JSON file)",
            flight::BUILTIN.join(", ")
        );
    }
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {path}"))?;
    Ok(Flight::from_json(path, &text)?)
}

/// An emulated link in front of the server named by `url`, and the URL to use instead:
/// the proxy's for `http://`; for `https://` the same URL (the certificate names its host),
/// reached through the proxy by [`ConnectOptions::connect_to`] (see [`link_options`]).
///
/// A bucket URL (`s3://...`) keeps its URL; the proxy stands in front of its `http://`
/// endpoint (`AWS_ENDPOINT_URL` or `AWS_ENDPOINT`, an S3-protocol server on this network).
pub fn start_link(url: &str, link: (f64, f64)) -> Result<(LinkProxy, String)> {
    if url.starts_with("s3://") || url.starts_with("s3a://") {
        let endpoint = ["AWS_ENDPOINT_URL", "AWS_ENDPOINT"]
            .iter()
            .find_map(|k| std::env::var(k).ok())
            .filter(|e| e.starts_with("http://"))
            .context("--link with an s3:// URL needs an http:// endpoint in AWS_ENDPOINT_URL")?;
        let endpoint =
            Endpoint::from_url(&endpoint).with_context(|| format!("endpoint {endpoint:?}"))?;
        let proxy = LinkProxy::start(endpoint.addr, link.0, Duration::from_secs_f64(link.1 / 1e3))
            .context("starting the emulated link")?;
        return Ok((proxy, url.to_string()));
    }
    let endpoint = Endpoint::from_url(url).with_context(|| format!("server URL {url:?}"))?;
    let proxy = LinkProxy::start(endpoint.addr, link.0, Duration::from_secs_f64(link.1 / 1e3))
        .context("starting the emulated link")?;
    let url = match endpoint.tls {
        Some(_) => url.to_string(),
        None => format!("http://{}{}", proxy.local_addr(), endpoint.prefix),
    };
    Ok((proxy, url))
}

/// The connection settings of a session: `--ca-cert`, and through `link` if there is one.
pub fn link_options(ca_cert: Option<&CaCert>, link: Option<&LinkProxy>) -> ConnectOptions {
    ConnectOptions {
        ca_cert_pem: ca_cert.map(|c| c.pem.clone()),
        connect_to: link.map(LinkProxy::local_addr),
        ..ConnectOptions::default()
    }
}

/// The certificates of `--ca-cert`, read when the flag is parsed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CaCert {
    /// The file named.
    pub path: PathBuf,
    /// Its PEM text.
    pub pem: Vec<u8>,
}

/// Reads a `--ca-cert` file.
pub fn parse_ca_cert(s: &str) -> Result<CaCert, String> {
    let pem = std::fs::read(s).map_err(|e| format!("cannot read {s}: {e}"))?;
    if !pem.windows(27).any(|w| w == b"-----BEGIN CERTIFICATE-----") {
        return Err(format!("{s} holds no PEM certificate"));
    }
    Ok(CaCert {
        path: PathBuf::from(s),
        pem,
    })
}

/// Runs `quincunx fly`.
pub fn run(args: &FlyArgs) -> Result<()> {
    if args.render && !cfg!(feature = "render") {
        bail!(RENDER_MISSING);
    }
    args.refine.check().map_err(anyhow::Error::msg)?;
    if !(args.check_max_share.is_finite() && args.check_max_share >= 0.0) {
        bail!(
            "--check-max-share {} must be 0 (no limit) or a positive share",
            args.check_max_share
        );
    }
    for (name, v) in [
        ("--timeout-s", args.timeout_s),
        ("--deadline-s", args.deadline_s),
    ] {
        if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
            bail!("{name} {v} is out of range: give more than 0 and at most 86400 seconds");
        }
    }
    let link = args
        .link
        .map(|l| start_link(&args.server.url, l))
        .transpose()?;
    let url = link
        .as_ref()
        .map_or(args.server.url.as_str(), |(_, u)| u.as_str());
    let opened = Instant::now();
    let mut config = session_config(args);
    config.connect = link_options(args.server.ca_cert.as_ref(), link.as_ref().map(|(p, _)| p));
    let session = AnySession::open_with_colour(
        url,
        &args.server.repo,
        args.server.colour.as_deref(),
        config,
    )
    .with_context(|| match &args.server.colour {
        Some(c) => format!(
            "opening {} with colour {c} at {}",
            args.server.repo, args.server.url
        ),
        None => format!("opening {} at {}", args.server.repo, args.server.url),
    })?;
    let session_open_ms = opened.elapsed().as_secs_f64() * 1e3;
    let (report, render) = match session {
        AnySession::Planar(s) => fly_session(s, args)?,
        AnySession::Planet(s) => fly_session(s, args)?,
    };
    let process = ProcessFigures {
        session_open_ms,
        client_peak_rss_mb: crate::layout::peak_rss_mb(),
    };
    let link_bytes = link.as_ref().map(|(p, _)| p.bytes_down());
    print_report(&report, args, link_bytes, render.as_ref(), &process)
}

/// What the flight cost the process itself.
struct ProcessFigures {
    /// Opening the session: metadata, the colour layer's and the roots' tables (ms).
    session_open_ms: f64,
    /// The process's peak resident memory (`VmHWM`) at the end of the flight, the
    /// renderer's included with `--render` (MB).
    client_peak_rss_mb: f64,
}

/// Loads and flies the flight of `args` with `session` (rendering each frame with
/// `--render`).
fn fly_session<R: FlyDomain>(
    mut session: Session<R>,
    args: &FlyArgs,
) -> Result<(FlightReport, Option<RenderSummary>)> {
    let flight = load_flight(&args.path, &mut session, args.seed)?;
    let opts = fly_options(args);
    let per_frame = args.frames;
    let log = |f: &FrameRecord| {
        if per_frame && let Ok(line) = serde_json::to_string(f) {
            eprintln!("{line}");
        }
    };
    if !args.render {
        return Ok((flight::fly(&mut session, &flight, &opts, log)?, None));
    }
    #[cfg(feature = "render")]
    {
        let (report, summary) =
            crate::fly_render::fly_rendered(&mut session, &flight, &opts, log, args)?;
        Ok((report, Some(summary)))
    }
    #[cfg(not(feature = "render"))]
    bail!(RENDER_MISSING)
}

/// `--render` in a build without the renderer.
const RENDER_MISSING: &str =
    "--render needs quincunx built with the `render` feature (the default)";

/// What a domain needs to be flown: built-in flights, and drawing with `--render`.
#[cfg(feature = "render")]
pub trait FlyDomain: BuiltinFlights + quincunx_render::domain::RenderDomain {}
#[cfg(feature = "render")]
impl<R: BuiltinFlights + quincunx_render::domain::RenderDomain> FlyDomain for R {}
/// What a domain needs to be flown: built-in flights.
#[cfg(not(feature = "render"))]
pub trait FlyDomain: BuiltinFlights {}
#[cfg(not(feature = "render"))]
impl<R: BuiltinFlights> FlyDomain for R {}

/// `quincunx fly --render`: the renderer's figures over the flight.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RenderSummary {
    /// Adapter.
    pub adapter: String,
    /// Frames drawn.
    pub frames: usize,
    /// Renderer CPU per frame (taking the cut changes, apply, prepare, encoding the pass,
    /// submitting), ms.
    pub cpu_ms_p50: f64,
    /// 99th percentile.
    pub cpu_ms_p99: f64,
    /// Largest.
    pub cpu_ms_max: f64,
    /// GPU time per frame (timestamp queries), ms; `None` without them.
    pub gpu_ms_p50: Option<f64>,
    /// 99th percentile.
    pub gpu_ms_p99: Option<f64>,
    /// Bytes uploaded per frame: median.
    pub upload_bytes_p50: f64,
    /// 99th percentile.
    pub upload_bytes_p99: f64,
    /// Largest.
    pub upload_bytes_max: f64,
    /// Mean.
    pub upload_bytes_mean: f64,
    /// Patches uploaded per frame, median and largest.
    pub uploads_p50: f64,
    /// Largest.
    pub uploads_max: f64,
    /// Triangles per frame, median.
    pub triangles_p50: f64,
    /// Largest.
    pub triangles_max: f64,
    /// Patches drawn per frame, median.
    pub patches_p50: f64,
    /// Largest.
    pub patches_max: f64,
    /// Draw calls per frame, largest.
    pub draw_calls_max: usize,
    /// Peak GPU bytes held by patches (drawn and cached).
    pub gpu_bytes_peak: u64,
    /// The pool's allocation (the budget in whole slots).
    pub gpu_bytes_budget: u64,
    /// Uploads, cache hits and evictions over the flight.
    pub pool_uploads: u64,
    /// Patches that re-entered the cut from the cache, without an upload.
    pub pool_cache_hits: u64,
    /// Cached patches evicted.
    pub pool_evictions: u64,
    /// Frames whose drawn cut lagged the client's (upload cap or budget).
    pub frames_not_current: usize,
    /// Frames rasterised (every `RASTER_EVERY`th; all are encoded and timed).
    pub frames_rasterised: usize,
    /// Image size.
    pub size: [u32; 2],
}

/// Frames of `quincunx fly --render` rasterised and waited for (the others are encoded,
/// flushed and timed the same way).
pub const RASTER_EVERY: usize = 60;

fn print_report(
    r: &FlightReport,
    args: &FlyArgs,
    link_bytes_down: Option<u64>,
    render: Option<&RenderSummary>,
    process: &ProcessFigures,
) -> Result<()> {
    let failure = flight_failure(r, !args.allow_unfinished);
    if args.json {
        let mut v = serde_json::to_value(r)?;
        if let Some(obj) = v.as_object_mut() {
            obj.insert("failure".into(), failure.clone().into());
            obj.insert("session_open_ms".into(), process.session_open_ms.into());
            obj.insert(
                "client_peak_rss_mb".into(),
                process.client_peak_rss_mb.into(),
            );
            if let Some(render) = render {
                obj.insert("render".into(), serde_json::to_value(render)?);
            }
            obj.insert("repo".into(), args.server.repo.clone().into());
            obj.insert("color".into(), args.server.colour.clone().into());
            obj.insert(
                "link".into(),
                args.link.map_or(
                    serde_json::Value::Null,
                    |(k, rtt)| serde_json::json!({"kbit_s": k, "rtt_ms": rtt}),
                ),
            );
            obj.insert("link_bytes_down".into(), link_bytes_down.into());
            // The field the issue names: the jump legs' times, in order.
            obj.insert(
                "time_to_full_quality_s".into(),
                r.jumps
                    .iter()
                    .map(|j| j.time_to_full_quality_s)
                    .collect::<Vec<_>>()
                    .into(),
            );
            obj.insert(
                "diamonds_per_frame".into(),
                serde_json::json!({"p50": r.diamonds_per_frame_p50, "max": r.diamonds_per_frame_max}),
            );
        }
        outln!("{}", serde_json::to_string(&v)?);
    } else {
        outln!(
            "flight {} over {} ({}), {:.1} s, {} frames ({:.1} frames/s)",
            r.flight,
            args.server.repo,
            r.transport,
            r.seconds,
            r.frames,
            r.frames_per_s
        );
        outln!(
            "session opened in {:.1} ms; peak resident memory {:.1} MB",
            process.session_open_ms,
            process.client_peak_rss_mb
        );
        for j in &r.jumps {
            match j.time_to_full_quality_s {
                Some(t) => outln!(
                    "  jump {}: full quality after {t:.3} s ({} bytes)",
                    j.leg,
                    j.bytes_fetched
                ),
                None => outln!("  jump {}: not at full quality when the leg ended", j.leg),
            }
        }
        outln!(
            "fetched {} bytes, used {} bytes (waste {:.3}), {} requests, {} failures, \
             {} fetch errors ({} timeouts)",
            r.bytes_fetched,
            r.bytes_in_final_cuts,
            r.fetch_waste,
            r.requests,
            r.failures,
            r.fetch_errors,
            r.fetch_timeouts
        );
        outln!(
            "diamonds per frame p50 {} max {}; refine ms p50 {:.3} p99 {:.3}",
            r.diamonds_per_frame_p50,
            r.diamonds_per_frame_max,
            r.refine_ms_p50,
            r.refine_ms_p99
        );
        if let Some(g) = render {
            outln!(
                "rendered {} frames ({}x{}, {}): renderer CPU ms p50 {:.3} p99 {:.3}, \
                 uploads p50 {:.0} B max {:.0} B per frame, GPU memory peak {} of {} bytes",
                g.frames,
                g.size[0],
                g.size[1],
                g.adapter,
                g.cpu_ms_p50,
                g.cpu_ms_p99,
                g.upload_bytes_p50,
                g.upload_bytes_max,
                g.gpu_bytes_peak,
                g.gpu_bytes_budget
            );
        }
        outln!(
            "cracks {} and coverage errors {} over {} checked frames; the checks took \
             {:.1} s (median {:.1} ms, max {:.1} ms), not counted in the flight's {:.1} s \
             ({:.1} s wall clock)",
            r.cracks,
            r.coverage_errors,
            r.frames_checked,
            r.check_ms_total / 1e3,
            r.check_ms_p50,
            r.check_ms_max,
            r.seconds,
            r.wall_seconds
        );
    }
    match failure {
        Some(why) => bail!("{why}"),
        None => Ok(()),
    }
}
