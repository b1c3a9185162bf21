//! The `docker/` topology without Docker: two quincunx servers, each on its own copy of a
//! repository built from the bundled data, behind nginx running the shipped
//! `docker/nginx-cache.conf` (only host names, ports and paths are replaced). Also runs the
//! image's health check script, `docker/healthcheck.sh`, against the replicas.
//!
//! And `quincunx fly` against a static export (`quincunx export`) that nginx serves as
//! plain files, with no rule for missing files: a leaf's 404 is a leaf.
//!
//! Prints `SKIP nginx_cache: ...` and passes when nginx is not installed.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use common::nginx::{Nginx, find_nginx, free_port};
use common::{get, metric, workspace_root};
use quincunx_client::flight::{self, Flight, FlyOptions};
use quincunx_client::session::Session;
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_repo_tools::args::RefineArgs;
use quincunx_repo_tools::fly::{self, FlyArgs};
use quincunx_server::{RepoConfig, Server, ServerConfig};
use quincunx_testkit::skip::skip;

const REPO: &str = "korea";
const IMMUTABLE: &str = "public, max-age=31536000, immutable";
const BLOB_200: &str = "quincunx_http_requests_total{route=\"blob\",status=\"200\"}";
const BLOB_400: &str = "quincunx_http_requests_total{route=\"blob\",status=\"400\"}";

#[test]
fn nginx_caches_blobs_across_two_replicas_and_survives_losing_one() {
    let Some(nginx) = find_nginx("nginx_cache") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();

    // One build that both replicas serve and this test reads the expected blobs from, all
    // at once (readers share a repository).
    let built = root.join("built").join(REPO);
    common::build_bundled_korea(&built);
    let (version, blobs) = sample_blobs(&built, 24);
    assert!(blobs.len() >= 20, "only {} blobs", blobs.len());

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let mut a = Replica::start(&runtime, &built, &version);
    let mut b = Replica::start(&runtime, &built, &version);

    let proxy = start_cache(&nginx, &root.join("nginx"), [a.addr, b.addr]);
    let via = proxy.addr;

    // The health check script of the image: healthy replicas pass.
    let healthcheck = workspace_root().join("docker/healthcheck.sh");
    let healthy = |addr: SocketAddr| {
        Command::new("bash")
            .arg(&healthcheck)
            .arg(addr.ip().to_string())
            .arg(addr.port().to_string())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .map(|s| s.success())
    };
    let bash_found = healthy(a.addr).is_ok();
    if bash_found {
        assert!(healthy(a.addr).unwrap() && healthy(b.addr).unwrap());
    } else {
        skip(
            "nginx_cache (health check part)",
            "REQUIRE_NGINX",
            "bash not found",
        );
    }

    // A blob: MISS, then HIT; the bytes, ETag and Cache-Control of the replicas.
    let (path, bytes) = &blobs[0];
    let direct = get(a.addr, path, &[]);
    assert_eq!(direct.status, 200);
    assert_eq!(&direct.body, bytes);
    let etag = direct
        .header("etag")
        .expect("blobs carry an ETag")
        .to_string();
    assert!(etag.starts_with('"'), "strong ETag: {etag}");
    let first = get(via, path, &[]);
    assert_eq!(first.status, 200, "{}", first.text());
    assert_eq!(first.header("x-cache-status"), Some("MISS"));
    let second = get(via, path, &[]);
    assert_eq!(second.status, 200);
    assert_eq!(second.header("x-cache-status"), Some("HIT"));
    for r in [&first, &second] {
        assert_eq!(&r.body, bytes);
        assert_eq!(r.header("etag"), Some(etag.as_str()));
        assert_eq!(r.header("cache-control"), Some(IMMUTABLE));
    }

    // Conditional requests: answered 304 from the cache, and on a cache miss too.
    let conditional = get(via, path, &[&format!("If-None-Match: {etag}")]);
    assert_eq!(conditional.status, 304);
    assert!(conditional.body.is_empty());
    assert_eq!(conditional.header("etag"), Some(etag.as_str()));
    let (fresh_path, _) = &blobs[1];
    let fresh_etag = get(b.addr, fresh_path, &[])
        .header("etag")
        .unwrap()
        .to_string();
    let conditional = get(via, fresh_path, &[&format!("If-None-Match: {fresh_etag}")]);
    assert_eq!(conditional.status, 304);
    assert_eq!(conditional.header("x-cache-status"), Some("MISS"));

    // metadata.json and the listing pass through, uncached.
    let metadata = get(via, &format!("/repos/{REPO}/metadata.json"), &[]);
    assert_eq!(metadata.status, 200);
    assert_eq!(metadata.header("x-cache-status"), None);
    assert_eq!(
        metadata.body,
        get(b.addr, &format!("/repos/{REPO}/metadata.json"), &[]).body
    );
    let json: serde_json::Value = serde_json::from_slice(&metadata.body).unwrap();
    assert!(json["content_hash"].as_str().unwrap().starts_with(&version));
    assert_eq!(json["domain"], "planar");
    let listing = get(via, "/repos", &[]);
    assert_eq!(listing.status, 200);
    assert!(listing.text().contains(REPO), "{}", listing.text());
    assert_eq!(get(via, "/metrics", &[]).status, 404);

    // An invalid id is a 400 that is not cached: both requests reach a replica.
    let invalid = format!("/repos/{REPO}/v/{version}/d/01/2");
    let blob_400_before = blob_requests(&[a.addr, b.addr], BLOB_400);
    for _ in 0..2 {
        let r = get(via, &invalid, &[]);
        assert_eq!(r.status, 400);
        assert_ne!(r.header("x-cache-status"), Some("HIT"));
    }
    assert_eq!(
        blob_requests(&[a.addr, b.addr], BLOB_400),
        blob_400_before + 2
    );

    // Distinct blobs are spread over both replicas, each fetched once from upstream.
    let before = blob_requests(&[a.addr, b.addr], BLOB_200);
    for (path, bytes) in &blobs[2..12] {
        let r = get(via, path, &[]);
        assert_eq!((r.status, r.header("x-cache-status")), (200, Some("MISS")));
        assert_eq!(&r.body, bytes);
    }
    for (path, _) in &blobs[2..12] {
        assert_eq!(get(via, path, &[]).header("x-cache-status"), Some("HIT"));
    }
    assert_eq!(blob_requests(&[a.addr, b.addr], BLOB_200), before + 10);
    let served_by_a = blob_requests(&[a.addr], BLOB_200);
    let served_by_b = blob_requests(&[b.addr], BLOB_200);
    assert!(
        served_by_a > 0 && served_by_b > 0,
        "blob requests per replica: a {served_by_a}, b {served_by_b}"
    );

    // Replica A stops: cached blobs are still hits, the others come from B.
    a.stop(&runtime);
    if bash_found {
        assert!(!healthy(a.addr).unwrap(), "a stopped replica is unhealthy");
    }
    for (path, bytes) in blobs[..1].iter().chain(&blobs[2..12]) {
        let r = get(via, path, &[]);
        assert_eq!((r.status, r.header("x-cache-status")), (200, Some("HIT")));
        assert_eq!(&r.body, bytes);
    }
    let b_before = blob_requests(&[b.addr], BLOB_200);
    for (path, bytes) in &blobs[12..] {
        let r = get(via, path, &[]);
        assert_eq!(r.status, 200, "{path} without replica a: {}", r.text());
        assert_eq!(r.header("x-cache-status"), Some("MISS"));
        assert_eq!(&r.body, bytes);
    }
    assert_eq!(
        blob_requests(&[b.addr], BLOB_200),
        b_before + (blobs.len() - 12) as u64
    );
    println!(
        "nginx_cache: {} blobs via nginx {via} over replicas {} (stopped) and {}; \
         upstream blob 200s: a {served_by_a}, b {}",
        blobs.len(),
        a.addr,
        b.addr,
        blob_requests(&[b.addr], BLOB_200)
    );

    drop(proxy);
    b.stop(&runtime);
}

#[test]
fn quincunx_fly_streams_a_static_export_from_plain_nginx() {
    let Some(nginx) = find_nginx("nginx_static") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let built = root.join("built").join(REPO);
    common::build_bundled_korea(&built);
    let www = root.join("www");
    quincunx_repo_tools::export::run(&built, &www, Some(REPO)).unwrap();
    let addr = free_port();
    // Files, nothing else: a missing file is nginx's 404.
    let log = root.join("nginx/access.log");
    let snippet = format!(
        "access_log {};\nserver {{ listen {addr}; root {}; }}",
        log.display(),
        www.display()
    );
    let metadata = format!("/repos/{REPO}/metadata.json");
    let server = Nginx::run(&nginx, &root.join("nginx"), addr, &snippet, &metadata);
    let url = format!("http://{addr}");
    let not_found = || {
        std::fs::read_to_string(&log)
            .unwrap()
            .lines()
            .filter(|l| l.contains("/v/") && l.contains("\" 404 "))
            .count()
    };

    // `quincunx fly` itself, then the same session and flight with its report.
    let args = FlyArgs {
        refine: RefineArgs {
            tolerance_px: 2.0,
            ..RefineArgs::default()
        },
        ..FlyArgs::new(&url, REPO, "jump")
    };
    fly::run(&args).unwrap();
    let fly = || {
        let mut session =
            Session::<PlanarRefiner>::open(&url, REPO, fly::session_config(&args)).unwrap();
        let flight = Flight::builtin_for("jump", &mut session, args.seed).unwrap();
        let opts = FlyOptions {
            check_every: 1,
            ..fly::fly_options(&args)
        };
        flight::fly(&mut session, &flight, &opts, |_| {}).unwrap()
    };
    let before = not_found();
    let report = fly();
    let leaves_404 = not_found() - before;
    assert!(leaves_404 > 0, "no leaf was asked for: {report:?}");
    assert_eq!(report.fetch_errors, 0, "{report:?}");
    assert_eq!(report.failures, 0, "{report:?}");
    assert_eq!(report.jumps_unfinished, 0, "{report:?}");
    assert_eq!((report.cracks, report.coverage_errors), (0, 0));
    let requests = report.requests;

    // The same files without `static_export` in the metadata (as `quincunx serve` answers
    // it): a 404 is then an error, not a leaf.
    let meta_file = www.join(&metadata[1..]);
    let mut meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&meta_file).unwrap()).unwrap();
    assert_eq!(meta["static_export"], true);
    meta.as_object_mut().unwrap().remove("static_export");
    std::fs::write(&meta_file, meta.to_string()).unwrap();
    let report = fly();
    assert!(report.fetch_errors > 0, "{report:?}");
    println!(
        "nginx_static: {requests} requests, {leaves_404} leaves answered 404, 0 fetch errors; \
         {} fetch errors without static_export",
        report.fetch_errors
    );
    drop(server);
}

/// Copies a directory tree (files and directories only: what a repository holds).
/// The URL version (`hash16`) of a repository and `count` of its blobs spread over the
/// key space: (URL path, bytes).
fn sample_blobs(repo: &Path, count: usize) -> (String, Vec<(String, Vec<u8>)>) {
    let repo = quincunx_store::Repository::open(repo).unwrap();
    let meta = repo.metadata().clone();
    let total = repo.blob_count();
    let step = (total / count).max(1);
    let blobs = repo
        .blobs()
        .step_by(step)
        .take(count)
        .map(|item| {
            let (key, blob) = item.unwrap();
            let path = quincunx_repo_tools::export::blob_path(&meta, REPO, &key).unwrap();
            (format!("/{path}"), blob.to_vec())
        })
        .collect();
    (meta.content_hash[..16].to_string(), blobs)
}

/// The sum of a request counter over replicas' `/metrics`.
fn blob_requests(replicas: &[SocketAddr], sample: &str) -> u64 {
    replicas
        .iter()
        .map(|&addr| {
            let r = get(addr, "/metrics", &[]);
            assert_eq!(r.status, 200);
            metric(&r.text(), sample)
        })
        .sum()
}

/// A server on a loopback port, on the shared runtime.
struct Replica {
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl Replica {
    fn start(runtime: &tokio::runtime::Runtime, repo: &Path, version: &str) -> Replica {
        let config = ServerConfig {
            addr: "127.0.0.1:0".parse().unwrap(),
            repos: vec![RepoConfig {
                name: REPO.into(),
                path: repo.to_path_buf(),
            }],
            ..Default::default()
        };
        let server = runtime.block_on(Server::bind(config)).unwrap();
        let addr = server.local_addr().unwrap();
        // The URLs the test computed with `quincunx export`'s mapping are the server's.
        assert_eq!(server.state().repo(REPO).unwrap().1.version, version);
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = runtime.spawn(server.run(async {
            let _ = stopped.await;
        }));
        Replica {
            addr,
            stop: Some(stop),
            task: Some(task),
        }
    }

    /// Shuts down gracefully and waits until the socket is closed.
    fn stop(&mut self, runtime: &tokio::runtime::Runtime) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(task) = self.task.take() {
            runtime
                .block_on(async { tokio::time::timeout(Duration::from_secs(60), task).await })
                .expect("the server drains within a minute")
                .unwrap();
        }
    }
}

/// nginx running the shipped `docker/nginx-cache.conf` in front of `replicas`.
fn start_cache(binary: &Path, dir: &Path, replicas: [SocketAddr; 2]) -> Nginx {
    let shipped =
        std::fs::read_to_string(workspace_root().join("docker/nginx-cache.conf")).unwrap();
    let addr = free_port();
    let d = dir.display();
    let mut snippet = shipped;
    for (from, to) in [
        ("listen 80;", format!("listen {addr};")),
        ("server-a:8080", replicas[0].to_string()),
        ("server-b:8080", replicas[1].to_string()),
        ("/var/cache/nginx/quincunx", format!("{d}/cache")),
        ("/var/log/nginx/access.log", format!("{d}/access.log")),
    ] {
        assert_eq!(
            snippet.matches(from).count(),
            1,
            "docker/nginx-cache.conf must contain {from:?} once (the test replaces it)"
        );
        snippet = snippet.replace(from, &to);
    }
    Nginx::run(binary, dir, addr, &snippet, "/healthz")
}
