//! `quincunx loadtest --mode fly`: N simulated clients, each a real streaming session
//! (its own network thread, DAG and refinement) flying a built-in flight in real time
//! against the server. Reports what the clients experienced (time to full quality, cut
//! consistency, refinement time, frame rate) and what they cost: requests and bytes, and
//! the CPU of the load generator, of the server (`--server-pid`) and of the whole machine,
//! which together tell whether the server or the box running everything is the limit.
//!
//! With `--link` each client has an emulated link of its own (its own [`LinkProxy`]), so
//! the clients do not share one pipe. With `--sweep` the test runs once per client count
//! and reports one point per count; `--plot` draws them.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::flight::{self, BuiltinFlights, Flight, FlightReport, FlyOptions, percentile};
use quincunx_client::session::{AnySession, Session, SessionConfig};

use super::{LoadtestArgs, SPARE_FDS};
#[cfg(feature = "charts")]
use crate::plot::{self, Chart, Series};

/// What a fly load test measured, over all clients (one point of a sweep).
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
    /// Median over clients of the body bytes each fetched.
    pub bytes_fetched_per_client_p50: f64,
    /// Requests per second over the test: what the server answered.
    pub rps: f64,
    /// Fetch errors counted by the clients' network threads.
    pub fetch_errors: u64,
    /// Of those, attempts that timed out.
    pub fetch_timeouts: u64,
    /// Jumps over all clients, and those that did not reach full quality in their leg.
    pub jumps: usize,
    /// Jumps not at full quality when their leg ended.
    pub jumps_unfinished: usize,
    /// Time to full quality after a jump over all clients' jumps: median, p90, p95, max.
    pub time_to_full_quality_s_p50: Option<f64>,
    /// 90th percentile.
    pub time_to_full_quality_s_p90: Option<f64>,
    /// 95th percentile.
    pub time_to_full_quality_s_p95: Option<f64>,
    /// Largest.
    pub time_to_full_quality_s_max: Option<f64>,
    /// Median over clients of the frames per second each kept up (the flight clock, checks
    /// excluded; the flight aims at 60).
    pub frames_per_s_p50: f64,
    /// Median over clients of their median refinement time per frame (ms).
    pub refine_ms_p50: f64,
    /// Largest per-client 99th percentile (ms).
    pub refine_ms_p99_max: f64,
    /// Largest DAG memory of a client, bytes.
    pub dag_bytes_max: usize,
    /// Cracks and coverage errors over every checked frame of every client (must be 0).
    pub cracks: usize,
    /// Coverage errors.
    pub coverage_errors: usize,
    /// Frames checked.
    pub frames_checked: usize,
    /// The emulated link each client had (`--link`), or `null`.
    pub link: Option<LinkSpec>,
    /// Bytes the clients' links carried towards them (responses, headers included).
    pub link_bytes_down: Option<u64>,
    /// The fastest client's link: bytes carried towards it per second of its session
    /// (opening to the end of its flight); at most the link rate.
    pub link_bytes_per_s_max: Option<f64>,
    /// Cores this machine offers (load generator and, on one box, the server share them).
    pub cores: usize,
    /// CPU seconds (user + system) of the load generator over the point: the clients'
    /// sessions, their links and their cut checks.
    pub loadgen_cpu_s: f64,
    /// `loadgen_cpu_s / seconds`: cores' worth the load generator kept busy.
    pub loadgen_cpu_share: f64,
    /// The server's process id (`--server-pid`), or `null`.
    pub server_pid: Option<u32>,
    /// CPU seconds of the server process over the point.
    pub server_cpu_s: Option<f64>,
    /// `server_cpu_s / seconds`: cores' worth the server kept busy (1.0 = one core).
    pub server_cpu_share: Option<f64>,
    /// Share of all the machine's cores busy over the point (every process, others
    /// included; 1.0 = all cores busy), from `/proc/stat`.
    pub machine_cpu_share: Option<f64>,
    /// Errors of the failed clients.
    pub errors: Vec<String>,
}

/// An emulated link, as in the JSON.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LinkSpec {
    /// Rate each way, kilobits per second.
    pub kbit_s: f64,
    /// Round trip, milliseconds.
    pub rtt_ms: f64,
}

/// `--sweep`: the points, in order.
#[derive(Debug, Clone, Serialize)]
pub struct FlySweepReport {
    /// Always `"fly"`.
    pub mode: &'static str,
    /// Client counts, in the order run.
    pub sweep: Vec<usize>,
    /// One report per count.
    pub points: Vec<FlyLoadReport>,
}

/// Largest client count of one point.
pub const MAX_CLIENTS: usize = 100_000;

/// File descriptors one client may hold: its connection, its link's listener and two
/// sockets, and the two runtimes' event descriptors, with room to spare.
const FDS_PER_CLIENT: u64 = 16;

/// Checks `--sweep`: client counts, each in `1..=MAX_CLIENTS`.
fn check_sweep(counts: &[usize]) -> Result<()> {
    if counts.is_empty() {
        bail!("--sweep: give at least one client count");
    }
    if let Some(n) = counts.iter().find(|n| !(1..=MAX_CLIENTS).contains(*n)) {
        bail!("--sweep: {n} is not a client count in 1..={MAX_CLIENTS}");
    }
    Ok(())
}

/// Flies built-in flight `path` with `session` (its first `legs` legs only, if given).
fn fly_builtin<R: BuiltinFlights>(
    mut session: Session<R>,
    path: &str,
    legs: Option<usize>,
    seed: u64,
    opts: &FlyOptions,
) -> Result<FlightReport> {
    let mut f = Flight::builtin_for(path, &mut session, seed)?;
    if let Some(n) = legs {
        f.legs.truncate(n);
    }
    Ok(flight::fly(&mut session, &f, opts, |_| {})?)
}

/// What one client's thread hands back.
struct ClientRun {
    report: FlightReport,
    /// Bytes its link carried towards it and the seconds it ran, with `--link`.
    link: Option<(u64, f64)>,
}

/// Runs the fly load test: one point, or one per `--sweep` count.
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
    if args.legs == Some(0) {
        bail!("--legs must be at least 1");
    }
    if !(args.check_max_share.is_finite() && args.check_max_share >= 0.0) {
        bail!(
            "--check-max-share {} must be 0 (no limit) or a positive share",
            args.check_max_share
        );
    }
    if let Some(mb) = args.dag_budget_mb
        && !(mb.is_finite() && mb > 0.0)
    {
        bail!("--dag-budget-mb {mb} must be a positive number of MiB");
    }
    if let Some(pid) = args.server_pid {
        process_cpu_s(pid).with_context(|| format!("--server-pid {pid}"))?;
    }
    if let Some(dir) = &args.plot {
        if !cfg!(feature = "charts") {
            bail!("--plot needs quincunx built with the `charts` feature (the default)");
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("--plot: creating {}", dir.display()))?;
    }
    let counts = args.sweep.clone().unwrap_or_else(|| vec![args.connections]);
    check_sweep(&counts)?;
    let most = counts.iter().copied().max().unwrap_or(1) as u64;
    let fd_limit = rlimit::increase_nofile_limit(u64::MAX)
        .context("raising the open file limit (RLIMIT_NOFILE)")?;
    let needed = most * FDS_PER_CLIENT + SPARE_FDS;
    if needed > fd_limit {
        bail!(
            "{most} clients need about {needed} file descriptors but the limit is {fd_limit} \
             (raise the hard limit, e.g. `ulimit -Hn`, or run fewer clients)"
        );
    }
    let mut points = Vec::with_capacity(counts.len());
    for &clients in &counts {
        if !args.quiet {
            eprintln!("{clients} clients flying {path}...");
        }
        let point = run_point(args, &path, clients)?;
        if !args.quiet {
            eprintln!("  {}", summary_line(&point));
        }
        points.push(point);
    }
    if args.json {
        if args.sweep.is_some() {
            let sweep = FlySweepReport {
                mode: "fly",
                sweep: counts,
                points,
            };
            outln!("{}", serde_json::to_string(&sweep)?);
            points = sweep.points;
        } else {
            outln!("{}", serde_json::to_string(&points[0])?);
        }
    } else {
        for p in &points {
            print_text(p);
        }
    }
    #[cfg(feature = "charts")]
    if let Some(dir) = &args.plot {
        write_charts(dir, &points)?;
    }
    let (failed, cracks, coverage) = points.iter().fold((0, 0, 0), |(a, b, c), p| {
        (a + p.clients_failed, b + p.cracks, c + p.coverage_errors)
    });
    if failed > 0 || cracks > 0 || coverage > 0 {
        bail!("{failed} clients failed, {cracks} cracks, {coverage} coverage errors");
    }
    for p in &points {
        if let Some(why) = crate::fly::fetch_failure(
            p.bytes_fetched,
            p.requests,
            p.fetch_errors,
            p.fetch_timeouts,
        ) {
            bail!("{} clients: {why}", p.clients);
        }
    }
    Ok(())
}

/// Runs `clients` sessions in parallel threads, each with its own link under `--link`.
fn run_point(args: &LoadtestArgs, path: &str, clients: usize) -> Result<FlyLoadReport> {
    let opts = FlyOptions {
        tolerance_px: args.refine.tolerance_px,
        check_every: args.check_every,
        check_max_share: (args.check_max_share > 0.0).then_some(args.check_max_share),
        ..FlyOptions::default()
    };
    let cpu_before = CpuSample::take(args.server_pid)?;
    let start = Instant::now();
    let results: Vec<Result<ClientRun>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..clients)
            .map(|i| {
                let opts = &opts;
                std::thread::Builder::new()
                    .name(format!("fly-client-{i}"))
                    .spawn_scoped(s, move || fly_client(args, path, i, opts))
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
    let cpu_after = CpuSample::take(args.server_pid)?;
    let mut report = FlyLoadReport {
        mode: "fly",
        clients,
        clients_failed: 0,
        flight: path.to_string(),
        seconds,
        frames: 0,
        requests: 0,
        bytes_fetched: 0,
        bytes_fetched_per_client_p50: 0.0,
        rps: 0.0,
        fetch_errors: 0,
        fetch_timeouts: 0,
        jumps: 0,
        jumps_unfinished: 0,
        time_to_full_quality_s_p50: None,
        time_to_full_quality_s_p90: None,
        time_to_full_quality_s_p95: None,
        time_to_full_quality_s_max: None,
        frames_per_s_p50: 0.0,
        refine_ms_p50: 0.0,
        refine_ms_p99_max: 0.0,
        dag_bytes_max: 0,
        cracks: 0,
        coverage_errors: 0,
        frames_checked: 0,
        link: args
            .link
            .map(|(kbit_s, rtt_ms)| LinkSpec { kbit_s, rtt_ms }),
        link_bytes_down: args.link.map(|_| 0),
        link_bytes_per_s_max: args.link.map(|_| 0.0),
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        loadgen_cpu_s: 0.0,
        loadgen_cpu_share: 0.0,
        server_pid: args.server_pid,
        server_cpu_s: None,
        server_cpu_share: None,
        machine_cpu_share: None,
        errors: Vec::new(),
    };
    let (mut ttfq, mut medians, mut bytes, mut fps) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for r in results {
        match r {
            Ok(ClientRun { report: f, link }) => {
                report.frames += f.frames;
                report.requests += f.requests;
                report.bytes_fetched += f.bytes_fetched;
                report.fetch_errors += f.fetch_errors;
                report.fetch_timeouts += f.fetch_timeouts;
                report.jumps += f.jumps.len();
                report.jumps_unfinished += f.jumps_unfinished;
                report.cracks += f.cracks;
                report.coverage_errors += f.coverage_errors;
                report.frames_checked += f.frames_checked;
                report.refine_ms_p99_max = report.refine_ms_p99_max.max(f.refine_ms_p99);
                report.dag_bytes_max = report.dag_bytes_max.max(f.dag_bytes_max);
                medians.push(f.refine_ms_p50);
                bytes.push(f.bytes_fetched as f64);
                fps.push(f.frames_per_s);
                ttfq.extend(f.jumps.iter().filter_map(|j| j.time_to_full_quality_s));
                if let (Some((down, secs)), Some(total), Some(max)) = (
                    link,
                    report.link_bytes_down.as_mut(),
                    report.link_bytes_per_s_max.as_mut(),
                ) {
                    *total += down;
                    *max = max.max(down as f64 / secs.max(1e-9));
                }
            }
            Err(e) => {
                report.clients_failed += 1;
                report.errors.push(format!("{e:#}"));
            }
        }
    }
    report.rps = report.requests as f64 / seconds.max(1e-9);
    for v in [&mut ttfq, &mut medians, &mut bytes, &mut fps] {
        v.sort_by(f64::total_cmp);
    }
    if !ttfq.is_empty() {
        report.time_to_full_quality_s_p50 = Some(percentile(&ttfq, 0.5));
        report.time_to_full_quality_s_p90 = Some(percentile(&ttfq, 0.9));
        report.time_to_full_quality_s_p95 = Some(percentile(&ttfq, 0.95));
        report.time_to_full_quality_s_max = ttfq.last().copied();
    }
    report.refine_ms_p50 = percentile(&medians, 0.5);
    report.bytes_fetched_per_client_p50 = percentile(&bytes, 0.5);
    report.frames_per_s_p50 = percentile(&fps, 0.5);
    report.loadgen_cpu_s = cpu_after.own_s - cpu_before.own_s;
    report.loadgen_cpu_share = report.loadgen_cpu_s / seconds.max(1e-9);
    if let (Some(a), Some(b)) = (cpu_before.server_s, cpu_after.server_s) {
        report.server_cpu_s = Some(b - a);
        report.server_cpu_share = Some((b - a) / seconds.max(1e-9));
    }
    if let (Some((busy0, all0)), Some((busy1, all1))) = (cpu_before.machine, cpu_after.machine)
        && all1 > all0
    {
        report.machine_cpu_share = Some((busy1 - busy0) as f64 / (all1 - all0) as f64);
    }
    Ok(report)
}

/// One client: its own link (with `--link`), its session and its flight.
fn fly_client(args: &LoadtestArgs, path: &str, i: usize, opts: &FlyOptions) -> Result<ClientRun> {
    let started = Instant::now();
    let link: Option<(LinkProxy, String)> = args
        .link
        .map(|l| crate::fly::start_link(&args.server.url, l))
        .transpose()
        .with_context(|| format!("client {i}"))?;
    let url = link
        .as_ref()
        .map_or(args.server.url.as_str(), |(_, u)| u.as_str());
    let config = SessionConfig {
        connect: crate::fly::link_options(
            args.server.ca_cert.as_ref(),
            link.as_ref().map(|(p, _)| p),
        ),
        connections: 1,
        timeout: Duration::from_secs_f64(args.timeout_s),
        refine: quincunx_client::refine::RefineConfig {
            metric: args.refine.metric,
            max_dag_bytes: args.dag_budget_mb.map(|mb| (mb * 1_048_576.0) as usize),
            ..Default::default()
        },
        ..SessionConfig::default()
    };
    let session = AnySession::open_with_colour(
        url,
        &args.server.repo,
        args.server.colour.as_deref(),
        config,
    )
    .with_context(|| format!("client {i}: opening {}", args.server.repo))?;
    let seed = args.seed + i as u64;
    // The session (and its connection) ends with `fly_builtin`, before the link is read.
    let report = match session {
        AnySession::Planar(s) => fly_builtin(s, path, args.legs, seed, opts),
        AnySession::Planet(s) => fly_builtin(s, path, args.legs, seed, opts),
    }
    .with_context(|| format!("client {i}"))?;
    let link = link.map(|(proxy, _)| (proxy.bytes_down(), started.elapsed().as_secs_f64()));
    Ok(ClientRun { report, link })
}

/// CPU counters at one instant.
struct CpuSample {
    /// This process, seconds.
    own_s: f64,
    /// The server process, seconds.
    server_s: Option<f64>,
    /// The machine: busy and all jiffies over all cores.
    machine: Option<(u64, u64)>,
}

impl CpuSample {
    fn take(server_pid: Option<u32>) -> Result<CpuSample> {
        let own_s = read_cpu_s(Path::new("/proc/self/stat"))
            .context("reading the load generator's CPU time")?;
        let server_s = server_pid
            .map(|pid| process_cpu_s(pid).with_context(|| format!("--server-pid {pid}")))
            .transpose()?;
        let machine = std::fs::read_to_string("/proc/stat")
            .ok()
            .and_then(|s| machine_jiffies(&s));
        Ok(CpuSample {
            own_s,
            server_s,
            machine,
        })
    }
}

/// `/proc` counts CPU time in USER_HZ ticks, 100 a second on Linux whatever the kernel's
/// own tick (`getconf CLK_TCK`).
const USER_HZ: f64 = 100.0;

/// User plus system CPU seconds of process `pid`.
pub fn process_cpu_s(pid: u32) -> Result<f64> {
    let path = format!("/proc/{pid}/stat");
    if !Path::new(&path).exists() {
        bail!("no process {pid} ({path} does not exist)");
    }
    read_cpu_s(Path::new(&path))
}

fn read_cpu_s(path: &Path) -> Result<f64> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    stat_cpu_s(&text).with_context(|| format!("{}: not a process stat line", path.display()))
}

/// `utime + stime` of a `/proc/PID/stat` line, seconds. The command name (field 2) is in
/// parentheses and may hold spaces and parentheses itself: fields are counted after the
/// last `)`.
fn stat_cpu_s(line: &str) -> Result<f64> {
    let rest = line
        .rsplit_once(')')
        .map(|(_, r)| r)
        .context("no command name")?;
    // After the name: state (field 3), ..., utime (14), stime (15).
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| -> Result<u64> {
        fields
            .get(i)
            .context("too few fields")?
            .parse::<u64>()
            .context("a CPU time field is not a number")
    };
    Ok((tick(11)? + tick(12)?) as f64 / USER_HZ)
}

/// Busy and all jiffies of the `cpu` line of `/proc/stat` (idle and iowait are not busy).
fn machine_jiffies(stat: &str) -> Option<(u64, u64)> {
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .map(|t| t.parse().ok())
        .collect::<Option<_>>()?;
    // user nice system idle iowait irq softirq steal (guest time is within user).
    let all: u64 = v.iter().take(8).sum();
    let idle = v.get(3)? + v.get(4).copied().unwrap_or(0);
    Some((all - idle, all))
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.digits$}"))
}

/// One line per point: what the sweep table shows.
fn summary_line(r: &FlyLoadReport) -> String {
    format!(
        "{} clients: ttfq p50 {} s p95 {} s, {:.0} req/s, server CPU {} cores, load \
         generator {:.2} cores, machine {}% busy, {:.1} frames/s, {} fetch errors, {} cracks, \
         {} failed",
        r.clients,
        opt(r.time_to_full_quality_s_p50, 2),
        opt(r.time_to_full_quality_s_p95, 2),
        r.rps,
        opt(r.server_cpu_share, 2),
        r.loadgen_cpu_share,
        opt(r.machine_cpu_share.map(|s| s * 100.0), 0),
        r.frames_per_s_p50,
        r.fetch_errors,
        r.cracks,
        r.clients_failed
    )
}

fn print_text(report: &FlyLoadReport) {
    outln!(
        "{} clients flying {} for {:.1} s: {} frames ({:.1}/s per client), {} requests \
         ({:.0}/s), {} bytes ({:.0} per client)",
        report.clients,
        report.flight,
        report.seconds,
        report.frames,
        report.frames_per_s_p50,
        report.requests,
        report.rps,
        report.bytes_fetched,
        report.bytes_fetched_per_client_p50
    );
    outln!(
        "time to full quality after {} jumps: p50 {} s, p95 {} s, max {} s ({} unfinished)",
        report.jumps,
        opt(report.time_to_full_quality_s_p50, 3),
        opt(report.time_to_full_quality_s_p95, 3),
        opt(report.time_to_full_quality_s_max, 3),
        report.jumps_unfinished
    );
    outln!(
        "refine ms p50 {:.3} (worst client p99 {:.3}); cracks {}, coverage errors {} over {} \
         checked frames; {} fetch errors; {} clients failed",
        report.refine_ms_p50,
        report.refine_ms_p99_max,
        report.cracks,
        report.coverage_errors,
        report.frames_checked,
        report.fetch_errors,
        report.clients_failed
    );
    outln!(
        "CPU over {} cores: load generator {:.1} s ({:.2} cores), server {} s ({} cores), \
         machine {}% busy",
        report.cores,
        report.loadgen_cpu_s,
        report.loadgen_cpu_share,
        opt(report.server_cpu_s, 1),
        opt(report.server_cpu_share, 2),
        opt(report.machine_cpu_share.map(|s| s * 100.0), 0)
    );
    for e in &report.errors {
        outln!("  {e}");
    }
}

/// Chart size, pixels.
#[cfg(feature = "charts")]
const CHART_PX: (u32, u32) = (1000, 600);

/// `clients_ttfq.png`, `clients_rps.png`, `clients_cpu.png` and `clients_jumps.png` in
/// `dir`.
#[cfg(feature = "charts")]
fn write_charts(dir: &Path, points: &[FlyLoadReport]) -> Result<()> {
    let series = |name: &str, f: &dyn Fn(&FlyLoadReport) -> Option<f64>| Series {
        name: name.to_string(),
        points: points
            .iter()
            .map(|p| (p.clients as f64, f(p).unwrap_or(f64::NAN)))
            .collect(),
    };
    let link = match points.first().and_then(|p| p.link) {
        Some(l) => format!(", {} kbit/s {} ms link each", l.kbit_s, l.rtt_ms),
        None => String::new(),
    };
    let ttfq_title = format!("time to full quality after a jump{link}");
    // Over the jumps that reached full quality: `clients_jumps.png` says how many did not.
    let ttfq = [
        series("p50 (jumps that finished)", &|p| {
            p.time_to_full_quality_s_p50
        }),
        series("p95 (jumps that finished)", &|p| {
            p.time_to_full_quality_s_p95
        }),
    ];
    let unfinished = [series(
        "jumps not at full quality when their leg ended",
        &|p| (p.jumps > 0).then(|| 100.0 * p.jumps_unfinished as f64 / p.jumps as f64),
    )];
    let rps = [series("requests/s", &|p| Some(p.rps))];
    let cores = points.first().map_or(1, |p| p.cores);
    let cpu = [
        series("server", &|p| p.server_cpu_share),
        series("load generator (clients)", &|p| Some(p.loadgen_cpu_share)),
        series(&format!("whole machine ({cores} cores)"), &|p| {
            p.machine_cpu_share.map(|s| s * cores as f64)
        }),
    ];
    // (file, title, y axis, series, of jumps)
    let charts = [
        (
            "clients_ttfq.png",
            ttfq_title.as_str(),
            "seconds",
            &ttfq[..],
            true,
        ),
        (
            "clients_rps.png",
            "server requests per second",
            "requests/s",
            &rps[..],
            false,
        ),
        ("clients_cpu.png", "CPU used", "cores busy", &cpu[..], false),
        (
            "clients_jumps.png",
            "unfinished jumps",
            "% of jumps",
            &unfinished[..],
            true,
        ),
    ];
    let any_jump = points.iter().any(|p| p.jumps > 0);
    for (file, title, y_label, series, of_jumps) in charts {
        if of_jumps && !any_jump {
            eprintln!("--plot: {file} not drawn: the flight has no jumps");
            continue;
        }
        let path = dir.join(file);
        let chart = Chart {
            title,
            x_label: "clients",
            y_label,
            log_x: true,
            log_y: false,
            series,
        };
        plot::write_png(&path, &chart, CHART_PX)
            .with_context(|| format!("--plot: writing {}", path.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn stat_lines_are_read_after_the_last_parenthesis() {
        // Fields from a real `/proc/PID/stat`, with a name that holds ") (".
        let line = "4242 (we ird) (name) S 1 4242 4242 0 -1 4194560 1234 0 0 0 250 75 0 0 20 \
                    0 3 0 123456 100000000 2000 18446744073709551615";
        assert_eq!(stat_cpu_s(line).unwrap(), 3.25);
        assert!(stat_cpu_s("4242 (x) S 1 2").is_err());
        assert!(stat_cpu_s("no name").is_err());
        // This process's own line parses.
        assert!(read_cpu_s(Path::new("/proc/self/stat")).unwrap() >= 0.0);
        assert!(process_cpu_s(u32::MAX).is_err());
    }

    #[test]
    fn machine_busy_share_excludes_idle_and_iowait() {
        let stat = "cpu  100 0 50 800 50 0 0 0 0 0\ncpu0 50 0 25 400 25 0 0 0 0 0\n";
        assert_eq!(machine_jiffies(stat), Some((150, 1000)));
        assert_eq!(machine_jiffies("intr 1 2 3"), None);
    }

    #[test]
    fn sweeps_are_positive_counts() {
        assert!(check_sweep(&[1, 4, 16]).is_ok());
        for bad in [&[][..], &[0], &[1, 0, 2], &[MAX_CLIENTS + 1]] {
            assert!(check_sweep(bad).is_err(), "{bad:?}");
        }
    }
}
