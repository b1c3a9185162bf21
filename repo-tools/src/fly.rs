//! `quincunx fly`: a headless client session flying a camera path against a server, in
//! real time, optionally through an emulated narrow link; per-frame stats and a summary.

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_client::fetch::Transport;
use quincunx_client::fetch::http1::Endpoint;
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::flight::{self, BuiltinFlights, Flight, FlightReport, FlyOptions};
use quincunx_client::session::{AnySession, Session, SessionConfig};
use quincunx_codec::incremental::Procedural;

/// `quincunx fly` options.
#[derive(Args, Debug, Clone)]
pub struct FlyArgs {
    /// Server base URL, e.g. `http://127.0.0.1:8080`.
    #[arg(long)]
    pub url: String,
    /// Elevation repository name.
    #[arg(long)]
    pub repo: String,
    /// Colour repository matched to the elevation (same domain; depths and diamond sizes
    /// may differ).
    #[arg(long)]
    pub color: Option<String>,
    /// With `--color`: detail made up below the shallower layer's finest level, as
    /// zero-centred uniform noise of this amplitude (integer units of that layer; 0:
    /// zero detail, smooth interpolation).
    #[arg(long, default_value_t = 0)]
    pub procedural_noise: i32,
    /// `approach`, `low-flight`, `jump`, or a JSON flight file (see `docs/streaming.md`).
    #[arg(long, default_value = "jump")]
    pub path: String,
    /// Screen-space tolerance, pixels.
    #[arg(long, default_value_t = 1.0)]
    pub tolerance_px: f64,
    /// `pipelined`, `plain` or `h2`.
    #[arg(long, default_value = "pipelined")]
    pub transport: Transport,
    /// Emulated link `KBIT_S,RTT_MS` (an in-process throttling proxy in front of the
    /// server), e.g. `4000,100`.
    #[arg(long, value_parser = parse_link)]
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
}

impl FlyArgs {
    /// The command line's defaults for flying `path` over `repo` at `url` (1 px, pipelined,
    /// 1920x1080 at 60 frames/s, every frame checked, text output).
    pub fn new(url: impl Into<String>, repo: impl Into<String>, path: impl Into<String>) -> Self {
        FlyArgs {
            url: url.into(),
            repo: repo.into(),
            color: None,
            procedural_noise: 0,
            path: path.into(),
            tolerance_px: 1.0,
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
        }
    }
}

fn parse_link(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?} is not KBIT_S,RTT_MS"))?;
    let parse = |t: &str| -> Result<f64, String> {
        let v: f64 = t.trim().parse().map_err(|e| format!("{t:?}: {e}"))?;
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(format!("{t:?} must be a non-negative number"))
        }
    };
    let (kbit, rtt) = (parse(a)?, parse(b)?);
    if kbit <= 0.0 {
        return Err("the link rate must be positive".into());
    }
    Ok((kbit, rtt))
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
            max_dag_bytes: args
                .dag_budget_mb
                .map(|mb| (mb.max(0.0) * 1_048_576.0) as usize),
            ..Default::default()
        },
        timeout: Duration::from_secs_f64(args.timeout_s),
        request_deadline: Duration::from_secs_f64(args.deadline_s),
        ..SessionConfig::default()
    }
}

/// The run options `args` ask for.
pub fn fly_options(args: &FlyArgs) -> FlyOptions {
    FlyOptions {
        fps: args.fps,
        frame_budget: Duration::from_secs_f64(args.frame_budget_ms.max(0.0) / 1e3),
        viewport_px: args.viewport,
        tolerance_px: args.tolerance_px,
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

/// An emulated link in front of the server named by `url`, and the URL to use instead.
pub fn start_link(url: &str, link: (f64, f64)) -> Result<(LinkProxy, String)> {
    let endpoint = Endpoint::from_url(url).with_context(|| format!("server URL {url:?}"))?;
    let proxy = LinkProxy::start(endpoint.addr, link.0, Duration::from_secs_f64(link.1 / 1e3))
        .context("starting the emulated link")?;
    let url = format!("http://{}{}", proxy.local_addr(), endpoint.prefix);
    Ok((proxy, url))
}

/// Runs `quincunx fly`.
pub fn run(args: &FlyArgs) -> Result<()> {
    if !(args.tolerance_px.is_finite() && args.tolerance_px > 0.0) {
        bail!("--tolerance-px must be positive");
    }
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
    let link = args.link.map(|l| start_link(&args.url, l)).transpose()?;
    let url = link.as_ref().map_or(args.url.as_str(), |(_, u)| u.as_str());
    let session =
        AnySession::open_with_colour(url, &args.repo, args.color.as_deref(), session_config(args))
            .with_context(|| match &args.color {
                Some(c) => format!("opening {} with colour {c} at {}", args.repo, args.url),
                None => format!("opening {} at {}", args.repo, args.url),
            })?;
    let report = match session {
        AnySession::Planar(s) => fly_session(s, args)?,
        AnySession::Planet(s) => fly_session(s, args)?,
    };
    let link_bytes = link.as_ref().map(|(p, _)| p.bytes_down());
    print_report(&report, args, link_bytes)
}

/// Loads and flies the flight of `args` with `session`.
fn fly_session<R: BuiltinFlights>(mut session: Session<R>, args: &FlyArgs) -> Result<FlightReport> {
    let flight = load_flight(&args.path, &mut session, args.seed)?;
    let opts = fly_options(args);
    let per_frame = args.frames;
    Ok(flight::fly(&mut session, &flight, &opts, |f| {
        if per_frame && let Ok(line) = serde_json::to_string(f) {
            eprintln!("{line}");
        }
    })?)
}

fn print_report(r: &FlightReport, args: &FlyArgs, link_bytes_down: Option<u64>) -> Result<()> {
    if args.json {
        let mut v = serde_json::to_value(r)?;
        if let Some(obj) = v.as_object_mut() {
            obj.insert("repo".into(), args.repo.clone().into());
            obj.insert("color".into(), args.color.clone().into());
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
            args.repo,
            r.transport,
            r.seconds,
            r.frames,
            r.frames_per_s
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
    if r.bytes_fetched == 0 && r.fetch_errors > 0 {
        bail!(
            "the flight fetched nothing: {} fetch errors ({} timeouts: no progress within \
             --timeout-s {} or no whole answer within --deadline-s {})",
            r.fetch_errors,
            r.fetch_timeouts,
            args.timeout_s,
            args.deadline_s
        );
    }
    if r.cracks > 0 || r.coverage_errors > 0 {
        bail!(
            "the cut was inconsistent: {} cracks, {} coverage errors",
            r.cracks,
            r.coverage_errors
        );
    }
    Ok(())
}
