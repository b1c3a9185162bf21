//! `quincunx loadtest`: simulated view-dependent clients against a blob server.
//!
//! Each of N clients keeps one persistent HTTP/1.1 connection and replays a request stream
//! generated before timing starts ([`flight`]): the diamonds a client needs while a camera
//! flies over the domain, parents first. Requests go out in batches of `--pipeline-depth`
//! in one write (wrk-style); a request's latency runs from its batch's write to the end of
//! its response. The URLs are those of `quincunx export`, so the same run works against our
//! server and against any static web server serving an export.
//!
//! `--idle` instead opens N connections, makes one request on each and holds them idle, to
//! measure what idle connections cost the server.
//!
//! `--mode fly` runs N real client sessions instead ([`sessions`]): each has its own
//! network thread, DAG and time-budgeted refinement and flies a built-in flight in real
//! time, so the load is what real clients would make (requests only for what their views
//! need, when their bandwidth allows).
//!
//! Streams are shared between clients through a pool of `--flights` distinct flights
//! (client `i` flies flight `i mod flights`), which bounds memory and start-up time for
//! thousands of clients.

pub mod flight;
pub mod latency;
pub mod sessions;

use std::collections::BTreeMap;
use std::io::IsTerminal as _;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_store::Metadata;
use rayon::prelude::*;
use serde::Serialize;

use flight::{FlightPlan, Rng, Stream};
use latency::Histogram;
use quincunx_client::fetch::http1::{self, Connection, Endpoint, GetTemplate, Http1Error, Limits};

/// Options of `quincunx loadtest`.
#[derive(Args, Debug, Clone)]
pub struct LoadtestArgs {
    /// Where to stream from (`--colour`: with `--mode fly`, a colour repository each
    /// session streams with the elevation).
    #[command(flatten)]
    pub server: crate::args::ServerArgs,
    /// `requests` (replayed request streams, the default) or `fly` (real client
    /// sessions flying a built-in flight).
    #[arg(long, default_value = "requests", value_parser = ["requests", "fly"])]
    pub mode: String,
    /// Concurrent clients, one persistent connection each (`--clients` is the same).
    #[arg(long, visible_alias = "clients", default_value_t = 64)]
    pub connections: usize,
    /// `--mode fly`: the built-in flight (`approach`, `low-flight`, `jump`; default
    /// `jump`), seeded per client.
    #[arg(long)]
    pub path: Option<String>,
    /// `--mode fly`: what the tolerance bounds.
    #[command(flatten)]
    pub refine: crate::args::RefineArgs,
    /// `--mode fly`: check each client's cut for cracks every this many frames (0 never).
    #[arg(long, default_value_t = 10)]
    pub check_every: usize,
    /// How long to run, in seconds (with `--requests`, whichever ends first).
    #[arg(long, default_value_t = 10.0)]
    pub duration_s: f64,
    /// Stop after this many requests in total.
    #[arg(long)]
    pub requests: Option<u64>,
    /// Requests written per batch on each connection (1 = no pipelining).
    #[arg(long, default_value_t = 1)]
    pub pipeline_depth: usize,
    /// Tokio worker threads (default: the available cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Seed of the flights.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Distinct flights generated and shared round-robin by the clients.
    #[arg(long, default_value_t = 64)]
    pub flights: usize,
    /// Longest request stream of one flight.
    #[arg(long, default_value_t = 20_000)]
    pub max_stream: usize,
    /// A batch (or, with `--idle`, a connection's first request) not answered within this
    /// many seconds fails and its connection is replaced.
    #[arg(long, default_value_t = 10.0)]
    pub timeout_s: f64,
    /// Open the connections, make one request on each, then hold them idle for the
    /// duration and report how many are still open (`idle_open`).
    #[arg(long)]
    pub idle: bool,
    /// `--mode fly`: largest share of a client's flight time its checks may take: a frame
    /// due for a check is skipped while they exceed it (as `quincunx fly`). 0: no limit.
    #[arg(long, default_value_t = 0.0)]
    pub check_max_share: f64,
    /// `--mode fly`: memory budget of each client's DAG in MiB (default: only the view
    /// bounds it; a korea cut at 1 px holds about 95 MB).
    #[arg(long)]
    pub dag_budget_mb: Option<f64>,
    /// `--mode fly`: fly only the first this many legs of the flight (a shorter run).
    #[arg(long)]
    pub legs: Option<usize>,
    /// `--mode fly`: an emulated link `KBIT_S,RTT_MS` of its own for each client (an
    /// in-process throttling proxy in front of the server, as `quincunx fly --link`).
    #[arg(long, value_parser = crate::args::parse_link)]
    pub link: Option<(f64, f64)>,
    /// `--mode fly`: run once per client count, in order (e.g. `1,4,16,64,256`), and
    /// report one point per count (`points` in the JSON) instead of `--clients`.
    #[arg(long, value_delimiter = ',', num_args = 1)]
    pub sweep: Option<Vec<usize>>,
    /// `--mode fly`: the server's process id, to report the CPU it used in each point
    /// (`server_cpu_s`, `server_cpu_share`; Linux `/proc`).
    #[arg(long)]
    pub server_pid: Option<u32>,
    /// `--mode fly`: write charts of the points into this directory (`clients_ttfq.png`,
    /// `clients_rps.png`, `clients_cpu.png`, `clients_jumps.png`).
    #[arg(long)]
    pub plot: Option<std::path::PathBuf>,
    /// One JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// No progress line on stderr.
    #[arg(long)]
    pub quiet: bool,
}

/// File descriptors kept free for the process itself (stdio, runtime, metadata fetch).
const SPARE_FDS: u64 = 64;

/// Most connections opening at once in `--idle` mode (keeps SYN queues from overflowing).
const IDLE_CONNECT_CONCURRENCY: usize = 256;

/// What a run measured.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// `"load"` or `"idle"`.
    pub mode: &'static str,
    /// Responses received (any status).
    pub requests: u64,
    /// Non-200 responses plus requests lost to connection, protocol or timeout failures.
    pub errors: u64,
    /// `requests / duration_s`.
    pub rps: f64,
    /// Median latency, milliseconds.
    pub p50_ms: f64,
    /// 90th percentile latency, milliseconds.
    pub p90_ms: f64,
    /// 99th percentile latency, milliseconds.
    pub p99_ms: f64,
    /// Largest latency, milliseconds.
    pub max_ms: f64,
    /// Body bytes received.
    pub bytes: u64,
    /// 200 responses with an empty body (leaves).
    pub empty_bodies: u64,
    /// Clients (connections).
    pub connections: usize,
    /// Requests per batch.
    pub pipeline_depth: usize,
    /// Wall time from the first request to the last response, seconds.
    pub duration_s: f64,
    /// Responses by status code.
    pub statuses: BTreeMap<String, u64>,
    /// Failed requests by class (`connect`, `closed`, `reset`, `io`, `protocol`,
    /// `timeout`, `tls`, `status`; each status code is in `statuses`).
    pub error_kinds: BTreeMap<String, u64>,
    /// 429 answers that came from the server's per-address connection cap.
    pub per_ip_cap_429: u64,
    /// The causes of the errors, where known, with what lifts them.
    pub causes: Vec<String>,
    /// Tokio worker threads.
    pub threads: usize,
    /// Distinct flights in the pool (client `i` flies flight `i mod flights`).
    pub flights: usize,
    /// Mean stream length, requests.
    pub stream_len_mean: f64,
    /// `--idle`: connections still open at the end.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub idle_open: Option<u64>,
}

/// Runs `quincunx loadtest`.
pub fn run(args: &LoadtestArgs) -> Result<()> {
    check_args(args)?;
    if args.mode == "fly" {
        return sessions::run(args);
    }
    let fd_limit = rlimit::increase_nofile_limit(u64::MAX)
        .context("raising the open file limit (RLIMIT_NOFILE)")?;
    let needed = args.connections as u64 + SPARE_FDS;
    if needed > fd_limit {
        bail!(
            "--connections {} needs about {needed} file descriptors but the limit is {fd_limit} \
             (raise the hard limit, e.g. `ulimit -Hn`, or use fewer connections)",
            args.connections
        );
    }
    let options = crate::fly::link_options(args.server.ca_cert.as_ref(), None);
    let endpoint = Endpoint::from_url_with(&args.server.url, &options)
        .with_context(|| format!("--url {:?}", args.server.url))?;
    let threads = args.threads.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    });
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads)
        .enable_io()
        .enable_time()
        .build()
        .context("starting the tokio runtime")?;
    let meta = runtime.block_on(fetch_metadata(&endpoint, &args.server.repo))?;
    tracing::info!(domain = %meta.domain, m = meta.m, levels = meta.levels, "metadata");
    let flights = generate_flights(args, &meta)?;
    let stream_len_mean =
        flights.iter().map(|s| s.len() as f64).sum::<f64>() / flights.len() as f64;
    let hash16 = &meta.content_hash[..meta.content_hash.len().min(16)];
    let template = GetTemplate::new(
        &endpoint.host,
        &format!(
            "{}/repos/{}/v/{hash16}/d/",
            endpoint.prefix, args.server.repo
        ),
    );
    let ctx = Arc::new(Ctx {
        endpoint: endpoint.clone(),
        template,
        flights,
        depth: args.pipeline_depth,
        timeout: Duration::from_secs_f64(args.timeout_s),
        budget: args.requests.map(AtomicU64::new),
        done: AtomicU64::new(0),
        failed: AtomicU64::new(0),
        open: AtomicU64::new(0),
        finished: AtomicBool::new(false),
        live: std::sync::Mutex::new(Live::default()),
    });
    let duration = Duration::from_secs_f64(args.duration_s);
    let progress = (!args.quiet).then(|| std::io::stderr().is_terminal());
    let (stats, elapsed_s) = runtime.block_on(async {
        let ticker = progress.map(|tty| tokio::spawn(print_progress(ctx.clone(), args.idle, tty)));
        let result = if args.idle {
            drive_idle(ctx.clone(), args.connections, duration).await
        } else {
            drive_load(ctx.clone(), args.connections, duration).await
        };
        ctx.finished.store(true, Ordering::Relaxed);
        if let Some(t) = ticker {
            let _ = t.await;
        }
        result
    })?;
    let report = make_report(args, threads, &ctx, &stats, elapsed_s, stream_len_mean);
    if args.json {
        outln!("{}", serde_json::to_string(&report)?);
    } else {
        print_text(&report);
    }
    Ok(())
}

fn check_args(args: &LoadtestArgs) -> Result<()> {
    if args.connections == 0 {
        bail!("--connections must be at least 1");
    }
    if args.server.colour.is_some() && args.mode != "fly" {
        bail!("--color needs --mode fly (replayed request streams are of one repository)");
    }
    if args.mode != "fly" {
        for (given, name) in [
            (args.legs.is_some(), "--legs"),
            (args.check_max_share != 0.0, "--check-max-share"),
            (args.dag_budget_mb.is_some(), "--dag-budget-mb"),
            (args.link.is_some(), "--link"),
            (args.sweep.is_some(), "--sweep"),
            (args.server_pid.is_some(), "--server-pid"),
            (args.plot.is_some(), "--plot"),
        ] {
            if given {
                bail!("{name} needs --mode fly");
            }
        }
    }
    if !(1..=1024).contains(&args.pipeline_depth) {
        bail!("--pipeline-depth must be between 1 and 1024");
    }
    args.refine.check().map_err(anyhow::Error::msg)?;
    for (name, v) in [
        ("--duration-s", args.duration_s),
        ("--timeout-s", args.timeout_s),
    ] {
        check_seconds(name, v)?;
    }
    if args.threads == Some(0) || args.flights == 0 || args.max_stream == 0 {
        bail!("--threads, --flights and --max-stream must be at least 1");
    }
    let name = &args.server.repo;
    if name.is_empty()
        || name.starts_with('.')
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
    {
        bail!("--repo {name:?} must be ASCII letters, digits, '-', '_' or '.'");
    }
    Ok(())
}

/// Largest `--duration-s` / `--timeout-s`: about 31 years.
pub const MAX_SECONDS: f64 = 1e9;

/// A number of seconds within `(0, MAX_SECONDS)`, each way out named as what it is.
fn check_seconds(name: &str, v: f64) -> Result<()> {
    if v.is_nan() {
        bail!("{name} is not a number; give seconds between 0 and {MAX_SECONDS:e}");
    }
    if v <= 0.0 {
        bail!("{name} {v} must be more than 0 seconds");
    }
    if v >= MAX_SECONDS {
        // `1e300`, not three hundred digits.
        bail!(
            "{name} {v:e} is too large: give fewer than {MAX_SECONDS:e} seconds (about 31 years)"
        );
    }
    Ok(())
}

async fn fetch_metadata(endpoint: &Endpoint, repo: &str) -> Result<Metadata> {
    let path = format!("/repos/{repo}/metadata.json");
    let (status, body) = http1::get(endpoint, &path)
        .await
        .with_context(|| format!("fetching {}{path}", endpoint.prefix))?;
    if status != 200 {
        bail!("GET {}{path}: status {status}", endpoint.prefix);
    }
    let meta: Metadata =
        serde_json::from_slice(&body).with_context(|| format!("parsing {path}"))?;
    if meta.content_hash.len() < 16 || !meta.content_hash.bytes().all(|b| b.is_ascii_hexdigit()) {
        bail!("{path}: content_hash {:?} is not hex", meta.content_hash);
    }
    Ok(meta)
}

/// The flight pool, generated in parallel before any timing.
fn generate_flights(args: &LoadtestArgs, meta: &Metadata) -> Result<Vec<Arc<Stream>>> {
    // Idle clients make one request each: a root is all they need.
    let max_requests = if args.idle { 1 } else { args.max_stream };
    let plan = FlightPlan::for_metadata(meta, max_requests)?;
    let count = args.flights.min(args.connections);
    let started = Instant::now();
    let flights: Vec<Arc<Stream>> = (0..count as u64)
        .into_par_iter()
        .map(|i| Arc::new(plan.generate(Rng::client_seed(args.seed, i))))
        .collect();
    if flights.iter().any(|s| s.is_empty()) {
        bail!("a flight requested nothing (repository without levels?)");
    }
    tracing::info!(
        flights = count,
        seconds = started.elapsed().as_secs_f64(),
        "flights generated"
    );
    Ok(flights)
}

/// What every client shares; counters are touched once per batch, not per request.
struct Ctx {
    endpoint: Endpoint,
    template: GetTemplate,
    flights: Vec<Arc<Stream>>,
    depth: usize,
    timeout: Duration,
    /// Requests left to start (`--requests`), `None` when only the duration limits.
    budget: Option<AtomicU64>,
    /// Responses received so far (for the progress line).
    done: AtomicU64,
    /// Errors so far (for the progress line).
    failed: AtomicU64,
    /// `--idle`: connections currently established.
    open: AtomicU64,
    finished: AtomicBool,
    /// Errors by class so far (for the progress line), updated only when there are some.
    live: std::sync::Mutex<Live>,
}

/// Errors by class so far.
#[derive(Debug, Default)]
struct Live {
    kinds: [u64; ERROR_KINDS.len()],
    statuses: BTreeMap<u16, u64>,
}

impl Ctx {
    /// Adds what a client counted since `before` to the live counts.
    fn record(&self, before: &ErrorSnapshot, now: &Stats) {
        if now.errors == before.errors {
            return;
        }
        let mut live = self.live.lock().unwrap_or_else(|e| e.into_inner());
        for (i, n) in now.kinds.iter().enumerate() {
            live.kinds[i] += n - before.kinds[i];
        }
        for &(code, n) in &now.other_statuses {
            let old = before
                .statuses
                .iter()
                .find(|(c, _)| *c == code)
                .map_or(0, |(_, m)| *m);
            if n > old {
                *live.statuses.entry(code).or_insert(0) += n - old;
            }
        }
    }

    /// `429: 12, closed: 3` (empty without errors).
    fn live_line(&self) -> String {
        let live = self.live.lock().unwrap_or_else(|e| e.into_inner());
        let mut parts: Vec<String> = live
            .statuses
            .iter()
            .map(|(c, n)| format!("{c}: {n}"))
            .collect();
        for (k, n) in ERROR_KINDS.iter().zip(live.kinds) {
            if n > 0 && *k != "status" {
                parts.push(format!("{k}: {n}"));
            }
        }
        parts.join(", ")
    }
}

/// A client's error counts at the start of a batch.
struct ErrorSnapshot {
    errors: u64,
    kinds: [u64; ERROR_KINDS.len()],
    statuses: Vec<(u16, u64)>,
}

impl Stats {
    fn snapshot(&self) -> ErrorSnapshot {
        ErrorSnapshot {
            errors: self.errors,
            kinds: self.kinds,
            statuses: self.other_statuses.clone(),
        }
    }
}

impl Ctx {
    /// Takes up to `want` requests from the budget; 0 when it is spent.
    fn claim(&self, want: u64) -> u64 {
        let Some(budget) = &self.budget else {
            return want;
        };
        let mut left = budget.load(Ordering::Relaxed);
        loop {
            let take = want.min(left);
            if take == 0 {
                return 0;
            }
            match budget.compare_exchange_weak(
                left,
                left - take,
                Ordering::Relaxed,
                Ordering::Relaxed,
            ) {
                Ok(_) => return take,
                Err(now) => left = now,
            }
        }
    }
}

/// Causes of failed requests, in report order.
const ERROR_KINDS: [&str; 8] = [
    "connect", "closed", "io", "protocol", "timeout", "status", "reset", "tls",
];

/// One client's (or the merged) counts.
#[derive(Debug, Default)]
struct Stats {
    responses: u64,
    errors: u64,
    bytes: u64,
    empty: u64,
    ok: u64,
    /// Non-200 statuses (rare: a short list beats a map).
    other_statuses: Vec<(u16, u64)>,
    kinds: [u64; ERROR_KINDS.len()],
    latency: Histogram,
    idle_open: u64,
    /// 429s of the server's per-address cap, and the cap they named.
    per_ip_429: u64,
    per_ip_limit: Option<u64>,
}

impl Stats {
    fn response(&mut self, status: u16, body_len: usize, latency: Duration) {
        self.responses += 1;
        self.latency.record(latency.as_micros() as u64);
        if status == 200 {
            self.ok += 1;
            self.bytes += body_len as u64;
            self.empty += u64::from(body_len == 0);
        } else {
            self.fail(1, 5);
            match self.other_statuses.iter_mut().find(|(s, _)| *s == status) {
                Some((_, n)) => *n += 1,
                None => self.other_statuses.push((status, 1)),
            }
        }
    }

    fn fail(&mut self, n: u64, kind: usize) {
        self.errors += n;
        self.kinds[kind] += n;
    }

    fn merge(&mut self, o: &Stats) {
        self.responses += o.responses;
        self.errors += o.errors;
        self.bytes += o.bytes;
        self.empty += o.empty;
        self.ok += o.ok;
        for &(s, n) in &o.other_statuses {
            match self.other_statuses.iter_mut().find(|(t, _)| *t == s) {
                Some((_, m)) => *m += n,
                None => self.other_statuses.push((s, n)),
            }
        }
        for (a, b) in self.kinds.iter_mut().zip(o.kinds) {
            *a += b;
        }
        self.latency.merge(&o.latency);
        self.idle_open += o.idle_open;
        self.per_ip_429 += o.per_ip_429;
        self.per_ip_limit = self.per_ip_limit.or(o.per_ip_limit);
    }
}

fn error_kind(e: &Http1Error) -> usize {
    match e {
        Http1Error::Closed => 1,
        Http1Error::Io(io)
            if matches!(
                io.kind(),
                std::io::ErrorKind::ConnectionReset | std::io::ErrorKind::ConnectionAborted
            ) =>
        {
            6
        }
        Http1Error::Io(_) => 2,
        Http1Error::Tls(_) => 7,
        _ => 3,
    }
}

/// The class of a failed connect: TLS failures are `tls`, the rest `connect`.
fn connect_kind(e: &Http1Error) -> usize {
    match e {
        Http1Error::Tls(_) => 7,
        _ => 0,
    }
}

/// Whether a 429's body says it comes from the per-address connection cap, and the cap.
fn per_ip_cap(body: &[u8]) -> Option<Option<u64>> {
    let text = std::str::from_utf8(body).ok()?;
    if !text.contains("max_connections_per_ip") {
        return None;
    }
    let limit = text
        .split_once("allows ")
        .and_then(|(_, rest)| rest.split(' ').next())
        .and_then(|n| n.parse().ok());
    Some(limit)
}

async fn join_all(handles: Vec<tokio::task::JoinHandle<Stats>>) -> Result<Stats> {
    let mut total = Stats::default();
    for h in handles {
        total.merge(&h.await.context("a client task failed")?);
    }
    Ok(total)
}

async fn drive_load(ctx: Arc<Ctx>, clients: usize, duration: Duration) -> Result<(Stats, f64)> {
    let start = Instant::now();
    let deadline = start + duration;
    let handles = (0..clients)
        .map(|i| tokio::spawn(load_client(ctx.clone(), i, deadline)))
        .collect();
    let stats = join_all(handles).await?;
    Ok((stats, start.elapsed().as_secs_f64()))
}

/// One client: batches of pipelined requests on a persistent connection, replaced after
/// any failure, until the deadline or the request budget.
async fn load_client(ctx: Arc<Ctx>, index: usize, deadline: Instant) -> Stats {
    let stream = ctx.flights[index % ctx.flights.len()].clone();
    let mut next = 0;
    let mut stats = Stats::default();
    let mut conn: Option<Connection> = None;
    let mut batch = Vec::with_capacity(ctx.depth * 128);
    while Instant::now() < deadline {
        let n = ctx.claim(ctx.depth as u64);
        if n == 0 {
            break;
        }
        batch.clear();
        for _ in 0..n {
            ctx.template.push(&mut batch, stream.get(next));
            next = (next + 1) % stream.len();
        }
        let (done_before, errors_before) = (stats.responses, stats.errors);
        let c = match conn.as_mut() {
            Some(c) => c,
            None => match tokio::time::timeout(
                ctx.timeout,
                Connection::open(&ctx.endpoint, Limits::default()),
            )
            .await
            {
                Ok(Ok(c)) => conn.insert(c),
                Ok(Err(e)) => {
                    tracing::debug!(error = %e, "connect failed");
                    let before = stats.snapshot();
                    stats.fail(n, connect_kind(&e));
                    ctx.record(&before, &stats);
                    ctx.failed.fetch_add(n, Ordering::Relaxed);
                    // Do not spin against a server that refuses connections.
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                }
                Err(_) => {
                    let before = stats.snapshot();
                    stats.fail(n, 4);
                    ctx.record(&before, &stats);
                    ctx.failed.fetch_add(n, Ordering::Relaxed);
                    continue;
                }
            },
        };
        let before = stats.snapshot();
        let result = tokio::time::timeout(ctx.timeout, exchange(c, &batch, n, &mut stats)).await;
        let answered = stats.responses - done_before;
        let keep = match result {
            Ok(Ok(())) => !c.closing(),
            Ok(Err(e)) => {
                tracing::debug!(error = %e, "connection failed");
                stats.fail(n - answered, error_kind(&e));
                false
            }
            Err(_) => {
                stats.fail(n - answered, 4);
                false
            }
        };
        if !keep {
            conn = None;
        }
        ctx.done.fetch_add(answered, Ordering::Relaxed);
        ctx.failed
            .fetch_add(stats.errors - errors_before, Ordering::Relaxed);
        ctx.record(&before, &stats);
    }
    stats
}

/// Writes one batch and reads its `n` responses.
async fn exchange(
    conn: &mut Connection,
    batch: &[u8],
    n: u64,
    stats: &mut Stats,
) -> Result<(), Http1Error> {
    let sent = Instant::now();
    conn.send(batch).await?;
    for _ in 0..n {
        let r = conn.read_response().await?;
        stats.response(r.status, r.body.len(), sent.elapsed());
        if r.status == 429
            && let Some(limit) = per_ip_cap(r.body)
        {
            stats.per_ip_429 += 1;
            stats.per_ip_limit = stats.per_ip_limit.or(limit);
        }
    }
    Ok(())
}

async fn drive_idle(ctx: Arc<Ctx>, clients: usize, duration: Duration) -> Result<(Stats, f64)> {
    let start = Instant::now();
    let ready = Arc::new(tokio::sync::Barrier::new(clients + 1));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let gate = Arc::new(tokio::sync::Semaphore::new(IDLE_CONNECT_CONCURRENCY));
    let handles = (0..clients)
        .map(|i| {
            tokio::spawn(idle_client(
                ctx.clone(),
                i,
                ready.clone(),
                gate.clone(),
                stop_rx.clone(),
            ))
        })
        .collect();
    ready.wait().await;
    tracing::info!(
        seconds = start.elapsed().as_secs_f64(),
        open = ctx.open.load(Ordering::Relaxed),
        "idle connections established"
    );
    tokio::time::sleep(duration).await;
    let _ = stop_tx.send(true);
    let stats = join_all(handles).await?;
    Ok((stats, start.elapsed().as_secs_f64()))
}

/// One idle client: connect, one request, then wait for the stop signal or the server
/// closing the connection.
async fn idle_client(
    ctx: Arc<Ctx>,
    index: usize,
    ready: Arc<tokio::sync::Barrier>,
    gate: Arc<tokio::sync::Semaphore>,
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> Stats {
    let mut stats = Stats::default();
    let stream = &ctx.flights[index % ctx.flights.len()];
    let mut request = Vec::new();
    ctx.template.push(&mut request, stream.get(0));
    let opened = {
        let _permit = gate.acquire().await;
        tokio::time::timeout(ctx.timeout, async {
            let mut conn = Connection::open(&ctx.endpoint, Limits::default())
                .await
                .map_err(|e| (0, e))?;
            let sent = Instant::now();
            conn.send(&request).await.map_err(|e| (1, e))?;
            let r = conn.read_response().await.map_err(|e| (1, e))?;
            stats.response(r.status, r.body.len(), sent.elapsed());
            Ok::<_, (usize, Http1Error)>(conn)
        })
        .await
    };
    let mut conn = match opened {
        Ok(Ok(c)) => {
            ctx.done.fetch_add(1, Ordering::Relaxed);
            ctx.open.fetch_add(1, Ordering::Relaxed);
            Some(c)
        }
        Ok(Err((stage, e))) => {
            tracing::debug!(error = %e, "idle connection failed");
            let kind = if stage == 0 {
                connect_kind(&e)
            } else {
                error_kind(&e)
            };
            let before = stats.snapshot();
            stats.fail(1, kind);
            ctx.record(&before, &stats);
            ctx.failed.fetch_add(1, Ordering::Relaxed);
            None
        }
        Err(_) => {
            stats.fail(1, 4);
            ctx.failed.fetch_add(1, Ordering::Relaxed);
            None
        }
    };
    ready.wait().await;
    if let Some(c) = conn.as_mut() {
        tokio::select! {
            _ = c.wait_closed() => {
                ctx.open.fetch_sub(1, Ordering::Relaxed);
            }
            _ = stop.wait_for(|s| *s) => stats.idle_open = 1,
        }
    }
    stats
}

/// Prints a status line once a second until the run finishes: in place on a terminal,
/// one line per second otherwise.
async fn print_progress(ctx: Arc<Ctx>, idle: bool, tty: bool) {
    let start = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.tick().await;
    let mut last = (0u64, Instant::now());
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = wait_finished(&ctx) => break,
        }
        let done = ctx.done.load(Ordering::Relaxed);
        let failed = ctx.failed.load(Ordering::Relaxed);
        let now = Instant::now();
        let rate = (done - last.0) as f64 / (now - last.1).as_secs_f64();
        last = (done, now);
        let elapsed = start.elapsed().as_secs_f64();
        let line = if idle {
            format!(
                "{elapsed:6.1} s  {} open  {done} answered  {failed} errors",
                ctx.open.load(Ordering::Relaxed)
            )
        } else {
            format!("{elapsed:6.1} s  {done} requests  {rate:.0} req/s  {failed} errors")
        };
        let classes = ctx.live_line();
        let line = if classes.is_empty() {
            line
        } else {
            format!("{line} ({classes})")
        };
        if tty {
            eprint!("\r{line}\x1b[K");
        } else {
            eprintln!("{line}");
        }
    }
    if tty {
        eprint!("\r\x1b[K");
    }
}

async fn wait_finished(ctx: &Ctx) {
    while !ctx.finished.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn make_report(
    args: &LoadtestArgs,
    threads: usize,
    ctx: &Ctx,
    s: &Stats,
    duration_s: f64,
    stream_len_mean: f64,
) -> Report {
    let ms = |us: u64| us as f64 / 1000.0;
    let mut statuses = BTreeMap::new();
    if s.ok > 0 {
        statuses.insert("200".to_string(), s.ok);
    }
    for (code, n) in &s.other_statuses {
        statuses.insert(code.to_string(), *n);
    }
    let error_kinds = ERROR_KINDS
        .iter()
        .zip(s.kinds)
        .filter(|(_, n)| *n > 0)
        .map(|(k, n)| (k.to_string(), n))
        .collect();
    let mut causes = Vec::new();
    if s.per_ip_429 > 0 {
        let cap = s
            .per_ip_limit
            .map_or_else(|| "its limit".to_string(), |n| n.to_string());
        causes.push(format!(
            "{} answers 429 (and the requests pipelined behind them, closed) come from the \
             server's per-address connection cap (max_connections_per_ip = {cap}): {} \
             connections from one address exceed it; raise it with `quincunx serve \
             --max-connections-per-ip N` (0 = no limit), or exempt this address with \
             limits.per_ip_exempt",
            s.per_ip_429, args.connections
        ));
    }
    if s.kinds[7] > 0 {
        causes.push(format!(
            "{} requests failed in the TLS handshake (see the log with RUST_LOG=debug; an \
             unknown issuer needs --ca-cert)",
            s.kinds[7]
        ));
    }
    Report {
        mode: if args.idle { "idle" } else { "load" },
        requests: s.responses,
        errors: s.errors,
        rps: if duration_s > 0.0 {
            s.responses as f64 / duration_s
        } else {
            0.0
        },
        p50_ms: ms(s.latency.quantile_us(0.50)),
        p90_ms: ms(s.latency.quantile_us(0.90)),
        p99_ms: ms(s.latency.quantile_us(0.99)),
        max_ms: ms(s.latency.max_us()),
        bytes: s.bytes,
        empty_bodies: s.empty,
        connections: args.connections,
        pipeline_depth: args.pipeline_depth,
        duration_s,
        statuses,
        error_kinds,
        per_ip_cap_429: s.per_ip_429,
        causes,
        threads,
        flights: ctx.flights.len(),
        stream_len_mean,
        idle_open: args.idle.then_some(s.idle_open),
    }
}

fn print_text(r: &Report) {
    outln!(
        "{} connections, pipeline depth {}, {} threads, {:.2} s ({} mode)",
        r.connections,
        r.pipeline_depth,
        r.threads,
        r.duration_s,
        r.mode
    );
    outln!(
        "requests {}  errors {}  {:.0} req/s  {} body bytes ({} empty bodies)",
        r.requests,
        r.errors,
        r.rps,
        r.bytes,
        r.empty_bodies
    );
    outln!(
        "latency ms: p50 {:.3}  p90 {:.3}  p99 {:.3}  max {:.3}",
        r.p50_ms,
        r.p90_ms,
        r.p99_ms,
        r.max_ms
    );
    let join = |m: &BTreeMap<String, u64>| {
        m.iter()
            .map(|(k, v)| format!("{k}: {v}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    outln!("statuses: {}", join(&r.statuses));
    if !r.error_kinds.is_empty() {
        outln!("errors by class: {}", join(&r.error_kinds));
    }
    for cause in &r.causes {
        outln!("cause: {cause}");
    }
    outln!(
        "{} flights, {:.0} requests per stream on average",
        r.flights,
        r.stream_len_mean
    );
    if let Some(open) = r.idle_open {
        outln!("idle connections still open at the end: {open}");
    }
}
