//! Transports over an emulated link: how fast each one pulls a repository's blobs through
//! a narrow, high-latency link. Prints one JSON object.
//!
//! ```text
//! cargo run --release -p quincunx-client --example link_throughput -- \
//!     --repo korea=/tmp/korea4097 [--blobs 3000] [--kbit-s 4000] [--rtt-ms 100] \
//!     [--connections 2] [--depth 64] [--max-in-flight 256] [--transports pipelined,plain,h2]
//! ```
//!
//! It starts a quincunx server on the repository, puts an emulated link (`fetch::link`) in
//! front of it, queues the first N blobs of the repository (coarse to fine, as stored) as
//! one frame's wants and fetches them with each transport in turn, re-submitting the
//! still-open wants every 16 ms like a frame loop. Per transport: payload `bytes`,
//! `seconds` from the first submit to the last answer, payload `mbit_s`, and
//! `link_utilisation` = every byte the link carried downstream (status lines, headers and
//! HTTP/2 framing included) / (seconds x link rate). The `steady_` figures are the same
//! between the moments 10% and 90% of the blobs had arrived (no ramp-up, no tail).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::fetch::{FetchConfig, Fetched, Fetcher, Key, Remote, Transport};
use quincunx_diamond::{PlanarDomain, SphereDomain};
use quincunx_server::{RepoConfig, Server, ServerConfig};
use quincunx_store::Repository;

struct Args {
    name: String,
    path: PathBuf,
    blobs: usize,
    kbit_s: f64,
    rtt: Duration,
    connections: usize,
    depth: usize,
    max_in_flight: usize,
    transports: Vec<Transport>,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        name: String::new(),
        path: PathBuf::new(),
        blobs: 3000,
        kbit_s: 4000.0,
        rtt: Duration::from_millis(100),
        connections: 2,
        depth: 64,
        max_in_flight: 256,
        transports: Transport::ALL.to_vec(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        let num = |v: String| v.parse::<f64>().map_err(|e| format!("{v}: {e}"));
        match flag.as_str() {
            "--repo" => {
                let v = value()?;
                let (n, p) = v.split_once('=').ok_or("--repo NAME=PATH")?;
                args.name = n.to_string();
                args.path = PathBuf::from(p);
            }
            "--blobs" => args.blobs = num(value()?)? as usize,
            "--kbit-s" => args.kbit_s = num(value()?)?,
            "--rtt-ms" => args.rtt = Duration::from_secs_f64(num(value()?)? / 1000.0),
            "--connections" => args.connections = num(value()?)? as usize,
            "--depth" => args.depth = num(value()?)? as usize,
            "--max-in-flight" => args.max_in_flight = num(value()?)? as usize,
            "--transports" => {
                args.transports = value()?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if args.name.is_empty() {
        return Err("--repo NAME=PATH is required".into());
    }
    Ok(args)
}

/// The first `n` blob keys of the repository, in storage order (level-major: coarse to
/// fine), as diamond centres.
fn blob_keys(path: &PathBuf, n: usize) -> Vec<Key> {
    let repo = Repository::open(path).expect("open repository");
    let meta = repo.metadata().clone();
    let mut keys = Vec::new();
    for entry in repo.blobs().take(n) {
        let (key, _) = entry.expect("read repository");
        let centre = if meta.domain == quincunx_store::Domain::Sphere {
            SphereDomain::new(meta.m)
                .unwrap()
                .id_from_key(&key)
                .unwrap()
                .c
        } else {
            let id = PlanarDomain::new(meta.m)
                .unwrap()
                .id_from_key(&key)
                .unwrap();
            [id.x, id.y, 0]
        };
        keys.push(centre);
    }
    keys
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("link_throughput: {e}");
            std::process::exit(2);
        }
    };
    // Read the keys before the server opens the repository (one opener per process).
    let keys = blob_keys(&args.path, args.blobs);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let config = ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        repos: vec![RepoConfig {
            name: args.name.clone(),
            path: args.path.clone(),
        }],
        workers: 1,
        ..Default::default()
    };
    let server = runtime
        .block_on(Server::bind(config))
        .expect("start server");
    let server_addr = server.local_addr().unwrap();
    runtime.spawn(server.run(std::future::pending()));

    let mut results = serde_json::Map::new();
    let mut mbit = std::collections::HashMap::new();
    for &transport in &args.transports {
        let link = LinkProxy::start(server_addr, args.kbit_s, args.rtt).expect("link");
        let base = format!("http://{}", link.local_addr());
        let (remote, _) =
            Remote::open(&base, &args.name, Duration::from_secs(30)).expect("metadata");
        let metadata_bytes = link.bytes_down();
        let mut c = FetchConfig::new(remote);
        c.transport = transport;
        c.connections = args.connections;
        c.pipeline_depth = args.depth;
        c.max_in_flight = args.max_in_flight;
        c.request_timeout = Duration::from_secs(30);
        let fetcher: Fetcher<bytes::Bytes> =
            Fetcher::spawn(c, Arc::new(|_k, b| Ok(b))).expect("fetcher");
        let n = keys.len();
        let wants: Vec<(Key, f32)> = keys
            .iter()
            .enumerate()
            .map(|(i, k)| (*k, (n - i) as f32))
            .collect();
        let mut open: HashSet<Key> = keys.iter().copied().collect();
        let mut failed = 0u64;
        let start = Instant::now();
        let mut last = start;
        // (time, link bytes down, payload bytes, answered) after each frame.
        let mut trace: Vec<(Instant, u64, u64, usize)> = Vec::new();
        while !open.is_empty() && start.elapsed() < Duration::from_secs(600) {
            fetcher.submit(
                wants
                    .iter()
                    .filter(|(k, _)| open.contains(k))
                    .copied()
                    .collect(),
            );
            std::thread::sleep(Duration::from_millis(16));
            for (k, r) in fetcher.poll() {
                if matches!(r, Fetched::Failed(_)) {
                    failed += 1;
                } else if open.remove(&k) {
                    last = Instant::now();
                }
            }
            trace.push((
                Instant::now(),
                link.bytes_down(),
                fetcher.stats().bytes_fetched,
                n - open.len(),
            ));
        }
        // Steady state: between 10% and 90% of the blobs answered (no ramp-up, no tail).
        let at = |fraction: f64| {
            trace
                .iter()
                .find(|t| t.3 as f64 >= fraction * n as f64)
                .copied()
                .unwrap_or((last, 0, 0, 0))
        };
        let (t10, l10, p10, _) = at(0.1);
        let (t90, l90, p90, _) = at(0.9);
        let steady_s = (t90 - t10).as_secs_f64().max(1e-9);
        let steady_mbit_s = (p90 - p10) as f64 * 8.0 / steady_s / 1e6;
        let steady_utilisation = (l90 - l10) as f64 * 8.0 / steady_s / (args.kbit_s * 1000.0);
        let seconds = (last - start).as_secs_f64();
        let stats = fetcher.stats();
        drop(fetcher);
        let link_bytes = link.bytes_down() - metadata_bytes;
        let mbit_s = stats.bytes_fetched as f64 * 8.0 / seconds / 1e6;
        mbit.insert(transport, (mbit_s, steady_mbit_s));
        results.insert(
            transport.name().into(),
            serde_json::json!({
                "blobs": n - open.len(),
                "bytes": stats.bytes_fetched,
                "link_bytes_down": link_bytes,
                "link_bytes_up": link.bytes_up(),
                "connections": link.connections() - 1,
                "requests": stats.requests,
                "failed_reports": failed,
                "seconds": (seconds * 1000.0).round() / 1000.0,
                "mbit_s": (mbit_s * 1000.0).round() / 1000.0,
                "link_utilisation": ((link_bytes as f64 * 8.0 / seconds / (args.kbit_s * 1000.0)) * 1000.0).round() / 1000.0,
                "steady_mbit_s": (steady_mbit_s * 1000.0).round() / 1000.0,
                "steady_link_utilisation": (steady_utilisation * 1000.0).round() / 1000.0,
                "mean_blob_bytes": stats.mean_blob_bytes.round(),
                "final_window": stats.window,
                "estimated_bandwidth_mbit_s": (stats.bandwidth_bit_s / 1e4).round() / 100.0,
            }),
        );
        eprintln!(
            "{}: {:.3} Mbit/s in {seconds:.2} s",
            transport.name(),
            mbit_s
        );
    }
    let ratio = |t: Transport, steady: bool| {
        let pick = |v: &(f64, f64)| if steady { v.1 } else { v.0 };
        match (mbit.get(&t), mbit.get(&Transport::Plain)) {
            (Some(a), Some(b)) if pick(b) > 0.0 => {
                serde_json::json!((pick(a) / pick(b) * 100.0).round() / 100.0)
            }
            _ => serde_json::Value::Null,
        }
    };
    let out = serde_json::json!({
        "repo": args.name,
        "blobs_queued": keys.len(),
        "link_kbit_s": args.kbit_s,
        "rtt_ms": args.rtt.as_secs_f64() * 1000.0,
        "connections": args.connections,
        "pipeline_depth": args.depth,
        "max_in_flight": args.max_in_flight,
        "transports": results,
        "ratio_pipelined_plain": ratio(Transport::Pipelined, false),
        "ratio_h2_plain": ratio(Transport::H2, false),
        "steady_ratio_pipelined_plain": ratio(Transport::Pipelined, true),
        "steady_ratio_h2_plain": ratio(Transport::H2, true),
    });
    println!("{out}");
}
