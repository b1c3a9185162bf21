//! `quincunx loadtest --mode fly`: N simulated clients, each a real streaming session
//! (its own network thread, DAG and refinement) flying a built-in flight in real time
//! against the server. Reports what the clients experienced (time to full quality, cut
//! consistency, refinement time) and what they cost the server (requests, bytes).

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use quincunx_client::flight::{self, BuiltinFlights, Flight, FlightReport, FlyOptions, percentile};
use quincunx_client::session::{AnySession, Session, SessionConfig};

use super::LoadtestArgs;

/// What a fly load test measured, over all clients.
#[derive(Debug, Clone, Serialize)]
pub struct FlyLoadReport {
    /// Always `"fly"`.
    pub mode: &'static str,
    /// Clients run and clients whose session failed (could not open, or errored).
    pub clients: usize,
    /// Clients that failed.
    pub clients_failed: usize,
    /// Flight each client flew (seeded per client).
    pub flight: String,
    /// Wall time of the whole test.
    pub seconds: f64,
    /// Frames over all clients.
    pub frames: usize,
    /// Requests and body bytes over all clients.
    pub requests: u64,
    /// Body bytes.
    pub bytes_fetched: u64,
    /// Requests per second over the test.
    pub rps: f64,
    /// Fetch errors counted by the clients' network threads.
    pub fetch_errors: u64,
    /// Jumps over all clients, and those that did not reach full quality in their leg.
    pub jumps: usize,
    /// Jumps not at full quality when their leg ended.
    pub jumps_unfinished: usize,
    /// Time to full quality after a jump over all clients' jumps: median, p90, max.
    pub time_to_full_quality_s_p50: Option<f64>,
    /// 90th percentile.
    pub time_to_full_quality_s_p90: Option<f64>,
    /// Largest.
    pub time_to_full_quality_s_max: Option<f64>,
    /// Median over clients of their median refinement time per frame (ms).
    pub refine_ms_p50: f64,
    /// Largest per-client 99th percentile (ms).
    pub refine_ms_p99_max: f64,
    /// Cracks and coverage errors over every checked frame of every client (must be 0).
    pub cracks: usize,
    /// Coverage errors.
    pub coverage_errors: usize,
    /// Frames checked.
    pub frames_checked: usize,
    /// Errors of the failed clients.
    pub errors: Vec<String>,
}

/// Flies built-in flight `path` with `session`.
fn fly_builtin<R: BuiltinFlights>(
    mut session: Session<R>,
    path: &str,
    seed: u64,
    opts: &FlyOptions,
) -> Result<FlightReport> {
    let f = Flight::builtin_for(path, &mut session, seed)?;
    Ok(flight::fly(&mut session, &f, opts, |_| {})?)
}

/// Runs N sessions in parallel threads.
pub fn run(args: &LoadtestArgs) -> Result<()> {
    if args.connections == 0 {
        bail!("--clients must be at least 1");
    }
    let path = args.path.clone().unwrap_or_else(|| "jump".into());
    if !flight::BUILTIN.contains(&path.as_str()) {
        bail!(
            "--path {path:?}: fly load tests use the built-in flights ({})",
            flight::BUILTIN.join(", ")
        );
    }
    let opts = FlyOptions {
        tolerance_px: args.tolerance_px,
        check_every: args.check_every,
        ..FlyOptions::default()
    };
    let start = Instant::now();
    let results: Vec<Result<FlightReport>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..args.connections)
            .map(|i| {
                let path = path.clone();
                std::thread::Builder::new()
                    .name(format!("fly-client-{i}"))
                    .spawn_scoped(s, move || -> Result<FlightReport> {
                        let config = SessionConfig {
                            connections: 1,
                            timeout: Duration::from_secs_f64(args.timeout_s),
                            ..SessionConfig::default()
                        };
                        let session = AnySession::open_with_colour(
                            &args.url,
                            &args.repo,
                            args.color.as_deref(),
                            config,
                        )
                        .with_context(|| format!("client {i}: opening {}", args.repo))?;
                        let seed = args.seed + i as u64;
                        match session {
                            AnySession::Planar(s) => fly_builtin(s, &path, seed, &opts),
                            AnySession::Planet(s) => fly_builtin(s, &path, seed, &opts),
                        }
                    })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| match h {
                Ok(h) => h
                    .join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("a client thread panicked"))),
                Err(e) => Err(anyhow::anyhow!("spawning a client thread: {e}")),
            })
            .collect()
    });
    let seconds = start.elapsed().as_secs_f64();
    let mut report = FlyLoadReport {
        mode: "fly",
        clients: args.connections,
        clients_failed: 0,
        flight: path,
        seconds,
        frames: 0,
        requests: 0,
        bytes_fetched: 0,
        rps: 0.0,
        fetch_errors: 0,
        jumps: 0,
        jumps_unfinished: 0,
        time_to_full_quality_s_p50: None,
        time_to_full_quality_s_p90: None,
        time_to_full_quality_s_max: None,
        refine_ms_p50: 0.0,
        refine_ms_p99_max: 0.0,
        cracks: 0,
        coverage_errors: 0,
        frames_checked: 0,
        errors: Vec::new(),
    };
    let (mut ttfq, mut medians) = (Vec::new(), Vec::new());
    for r in results {
        match r {
            Ok(f) => {
                report.frames += f.frames;
                report.requests += f.requests;
                report.bytes_fetched += f.bytes_fetched;
                report.fetch_errors += f.fetch_errors;
                report.jumps += f.jumps.len();
                report.jumps_unfinished += f.jumps_unfinished;
                report.cracks += f.cracks;
                report.coverage_errors += f.coverage_errors;
                report.frames_checked += f.frames_checked;
                report.refine_ms_p99_max = report.refine_ms_p99_max.max(f.refine_ms_p99);
                medians.push(f.refine_ms_p50);
                ttfq.extend(f.jumps.iter().filter_map(|j| j.time_to_full_quality_s));
            }
            Err(e) => {
                report.clients_failed += 1;
                report.errors.push(format!("{e:#}"));
            }
        }
    }
    report.rps = report.requests as f64 / seconds.max(1e-9);
    ttfq.sort_by(f64::total_cmp);
    medians.sort_by(f64::total_cmp);
    if !ttfq.is_empty() {
        report.time_to_full_quality_s_p50 = Some(percentile(&ttfq, 0.5));
        report.time_to_full_quality_s_p90 = Some(percentile(&ttfq, 0.9));
        report.time_to_full_quality_s_max = ttfq.last().copied();
    }
    report.refine_ms_p50 = percentile(&medians, 0.5);
    if args.json {
        outln!("{}", serde_json::to_string(&report)?);
    } else {
        outln!(
            "{} clients flying {} for {:.1} s: {} frames, {} requests ({:.0}/s), {} bytes",
            report.clients,
            report.flight,
            report.seconds,
            report.frames,
            report.requests,
            report.rps,
            report.bytes_fetched
        );
        outln!(
            "time to full quality after {} jumps: p50 {:?} s, p90 {:?} s, max {:?} s ({} unfinished)",
            report.jumps,
            report.time_to_full_quality_s_p50,
            report.time_to_full_quality_s_p90,
            report.time_to_full_quality_s_max,
            report.jumps_unfinished
        );
        outln!(
            "refine ms p50 {:.3} (worst client p99 {:.3}); cracks {}, coverage errors {} over {} checked frames; {} clients failed",
            report.refine_ms_p50,
            report.refine_ms_p99_max,
            report.cracks,
            report.coverage_errors,
            report.frames_checked,
            report.clients_failed
        );
        for e in &report.errors {
            outln!("  {e}");
        }
    }
    if report.clients_failed > 0 || report.cracks > 0 || report.coverage_errors > 0 {
        bail!(
            "{} clients failed, {} cracks, {} coverage errors",
            report.clients_failed,
            report.cracks,
            report.coverage_errors
        );
    }
    Ok(())
}
