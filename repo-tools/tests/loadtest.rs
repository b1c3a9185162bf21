//! End-to-end tests of `quincunx loadtest`: build the bundled korea crop, export it, serve the
//! export with a tiny static-file server written here (pipelining-capable, like nginx set up
//! to answer missing files with an empty 200), and check the load generator's accounting
//! against what the server actually sent.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_quincunx"))
}

fn run(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("run quincunx");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    out
}

fn ok_json(cmd: &mut Command) -> serde_json::Value {
    let out = run(cmd);
    assert!(
        out.status.success(),
        "failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("bad JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

/// Builds the bundled korea crop and exports it as `<dir>/www/repos/korea/...`.
fn exported_korea(dir: &Path) -> PathBuf {
    let input = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let repo = dir.join("korea");
    ok_json(
        bin()
            .args(["build", "--max-error-m", "2", "--json", "-o"])
            .arg(&repo)
            .arg(&input),
    );
    let www = dir.join("www");
    let out = run(bin().arg("export").arg(&repo).arg(&www));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    www
}

/// What the static server sent for blob requests (metadata excluded).
#[derive(Default)]
struct Served {
    requests: AtomicU64,
    body_bytes: AtomicU64,
    empty: AtomicU64,
    not_found: AtomicU64,
}

/// Serves files under `root`, in request order on each connection. A missing file is an
/// empty 200 (or a 404 with `missing_is_404`).
async fn serve(listener: TcpListener, root: PathBuf, missing_is_404: bool, served: Arc<Served>) {
    loop {
        let Ok((sock, _)) = listener.accept().await else {
            return;
        };
        tokio::spawn(connection(
            sock,
            root.clone(),
            missing_is_404,
            served.clone(),
        ));
    }
}

async fn connection(mut sock: TcpStream, root: PathBuf, missing_is_404: bool, served: Arc<Served>) {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    let mut out = Vec::new();
    loop {
        // Answer every complete request already buffered, then write them all at once.
        loop {
            let mut headers = [httparse::EMPTY_HEADER; 32];
            let mut req = httparse::Request::new(&mut headers);
            let Ok(httparse::Status::Complete(n)) = req.parse(&buf) else {
                break;
            };
            let path = req.path.unwrap().to_string();
            buf.drain(..n);
            assert!(!path.contains(".."));
            let file = root.join(path.trim_start_matches('/'));
            let (status, body) = match std::fs::read(&file) {
                Ok(b) => ("200 OK", b),
                Err(_) if missing_is_404 => ("404 Not Found", Vec::new()),
                Err(_) => ("200 OK", Vec::new()),
            };
            if !path.ends_with("metadata.json") {
                served.requests.fetch_add(1, Ordering::Relaxed);
                served
                    .not_found
                    .fetch_add(u64::from(status.starts_with("404")), Ordering::Relaxed);
                if status.starts_with("200") {
                    served
                        .body_bytes
                        .fetch_add(body.len() as u64, Ordering::Relaxed);
                    served
                        .empty
                        .fetch_add(u64::from(body.is_empty()), Ordering::Relaxed);
                }
            }
            out.extend_from_slice(
                format!(
                    "HTTP/1.1 {status}\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\r\n",
                    body.len()
                )
                .as_bytes(),
            );
            out.extend_from_slice(&body);
        }
        if !out.is_empty() {
            if sock.write_all(&out).await.is_err() {
                return;
            }
            out.clear();
        }
        match sock.read(&mut chunk).await {
            Ok(0) | Err(_) => return,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
        }
    }
}

/// Starts the server on a runtime of its own; returns the runtime (keep it alive), the URL
/// and the counters.
fn start_server(
    root: PathBuf,
    missing_is_404: bool,
) -> (tokio::runtime::Runtime, String, Arc<Served>) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let listener = rt
        .block_on(TcpListener::bind("127.0.0.1:0"))
        .expect("bind a local port");
    let url = format!("http://{}", listener.local_addr().unwrap());
    let served = Arc::new(Served::default());
    rt.spawn(serve(listener, root, missing_is_404, served.clone()));
    (rt, url, served)
}

fn loadtest(url: &str, extra: &[&str]) -> serde_json::Value {
    ok_json(
        bin()
            .args([
                "loadtest", "--url", url, "--repo", "korea", "--json", "--quiet",
            ])
            .args(extra),
    )
}

#[test]
fn pipelined_clients_receive_exactly_the_bytes_the_server_sent() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    let (_rt, url, served) = start_server(www, false);
    let report = loadtest(
        &url,
        &[
            "--requests",
            "2000",
            "--connections",
            "4",
            "--pipeline-depth",
            "8",
            "--duration-s",
            "120",
            "--threads",
            "2",
        ],
    );
    println!("{report}");
    assert_eq!(report["mode"], "load");
    assert_eq!(report["requests"], 2000);
    assert_eq!(report["errors"], 0);
    assert_eq!(report["statuses"]["200"], 2000);
    assert_eq!(report["connections"], 4);
    assert_eq!(report["pipeline_depth"], 8);
    let bytes = report["bytes"].as_u64().unwrap();
    assert!(bytes > 0);
    assert_eq!(served.requests.load(Ordering::Relaxed), 2000);
    assert_eq!(bytes, served.body_bytes.load(Ordering::Relaxed));
    assert_eq!(report["empty_bodies"], served.empty.load(Ordering::Relaxed));
    for key in ["rps", "p50_ms", "p90_ms", "p99_ms", "max_ms", "duration_s"] {
        assert!(report[key].as_f64().unwrap() >= 0.0, "{key}");
    }
    assert!(report["p50_ms"].as_f64() <= report["p99_ms"].as_f64());
    assert!(report["p99_ms"].as_f64() <= report["max_ms"].as_f64());
}

#[test]
fn non_200_statuses_are_counted_as_errors_by_code() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    // Leaves (sea, no blob) become 404s.
    let (_rt, url, served) = start_server(www, true);
    let report = loadtest(
        &url,
        &[
            "--requests",
            "1500",
            "--connections",
            "3",
            "--pipeline-depth",
            "4",
        ],
    );
    println!("{report}");
    let not_found = report["statuses"]["404"].as_u64().unwrap();
    assert!(not_found > 0, "the korea crop has leaves");
    assert_eq!(report["requests"], 1500);
    assert_eq!(report["errors"], not_found);
    assert_eq!(report["error_kinds"]["status"], not_found);
    assert_eq!(report["empty_bodies"], 0);
    assert_eq!(report["bytes"], served.body_bytes.load(Ordering::Relaxed));
}

#[test]
fn idle_connections_are_held_open_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    let (_rt, url, served) = start_server(www, false);
    let report = loadtest(
        &url,
        &["--idle", "--connections", "50", "--duration-s", "0.5"],
    );
    println!("{report}");
    assert_eq!(report["mode"], "idle");
    assert_eq!(report["idle_open"], 50);
    assert_eq!(report["requests"], 50);
    assert_eq!(report["errors"], 0);
    assert_eq!(served.requests.load(Ordering::Relaxed), 50);
}

#[test]
fn an_unreachable_server_or_impossible_options_fail_cleanly() {
    // Nothing listens on a port we just released.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}");
    for (args, needle) in [
        (vec!["--url", url.as_str()], "metadata.json"),
        (vec!["--url", "https://example.invalid"], "--url"),
        (
            vec!["--url", url.as_str(), "--connections", "2000000000"],
            "file descriptors",
        ),
        (
            vec!["--url", url.as_str(), "--pipeline-depth", "0"],
            "--pipeline-depth",
        ),
    ] {
        let out = run(bin().args(["loadtest", "--repo", "korea"]).args(&args));
        assert_eq!(out.status.code(), Some(1), "{args:?}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
    }
}

#[test]
fn fly_mode_runs_real_sessions_against_a_static_export() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    let (_rt, url, served) = start_server(www, false);
    let report = loadtest(
        &url,
        &[
            "--mode",
            "fly",
            "--clients",
            "2",
            "--path",
            "jump",
            "--tolerance-px",
            "2",
            "--check-every",
            "1",
        ],
    );
    assert_eq!(report["mode"], "fly");
    assert_eq!(report["clients"], 2);
    assert_eq!(report["clients_failed"], 0, "{report}");
    assert_eq!(report["jumps"], 12, "{report}");
    assert_eq!(report["jumps_unfinished"], 0, "{report}");
    assert_eq!(report["cracks"], 0);
    assert_eq!(report["coverage_errors"], 0);
    assert_eq!(report["frames_checked"], report["frames"]);
    // The clients' accounting is the server's: every blob request and body byte.
    assert_eq!(
        report["requests"].as_u64().unwrap(),
        served.requests.load(Ordering::Relaxed),
        "{report}"
    );
    assert_eq!(
        report["bytes_fetched"].as_u64().unwrap(),
        served.body_bytes.load(Ordering::Relaxed)
    );
    assert!(
        served.empty.load(Ordering::Relaxed) > 0,
        "no leaves requested"
    );

    // Only built-in flights.
    let out = run(bin().args([
        "loadtest", "--url", &url, "--repo", "korea", "--mode", "fly", "--path", "x.json",
    ]));
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("built-in flights"));
}

#[test]
fn quincunx_fly_takes_a_static_servers_404_as_a_leaf_and_reports_its_costs() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    // A leaf's missing file is a 404, as from any static server or object store.
    let (_rt, url, served) = start_server(www, true);
    let report = ok_json(bin().args([
        "fly",
        "--url",
        &url,
        "--repo",
        "korea",
        "--path",
        "jump",
        "--tolerance-px",
        "2",
        "--json",
    ]));
    assert_eq!(report["fetch_errors"], 0, "{report}");
    assert_eq!(report["jumps_unfinished"], 0, "{report}");
    assert_eq!(report["cracks"], 0);
    assert!(
        served.not_found.load(Ordering::Relaxed) > 0,
        "no leaf was asked for"
    );
    // What opening and flying cost the client process.
    let open_ms = report["session_open_ms"].as_f64().unwrap();
    assert!(
        open_ms > 0.0 && open_ms < report["seconds"].as_f64().unwrap() * 1e3,
        "{report}"
    );
    let rss = report["client_peak_rss_mb"].as_f64().unwrap();
    assert!(rss > 1.0 && rss < 4096.0, "{report}");
}

/// Every field of a fly point (`FlyLoadReport`), nullable ones included.
const FLY_POINT_FIELDS: [&str; 36] = [
    "mode",
    "clients",
    "clients_failed",
    "flight",
    "seconds",
    "frames",
    "requests",
    "bytes_fetched",
    "bytes_fetched_per_client_p50",
    "rps",
    "fetch_errors",
    "fetch_timeouts",
    "jumps",
    "jumps_unfinished",
    "time_to_full_quality_s_p50",
    "time_to_full_quality_s_p90",
    "time_to_full_quality_s_p95",
    "time_to_full_quality_s_max",
    "frames_per_s_p50",
    "refine_ms_p50",
    "refine_ms_p99_max",
    "dag_bytes_max",
    "cracks",
    "coverage_errors",
    "frames_checked",
    "link",
    "link_bytes_down",
    "link_bytes_per_s_max",
    "cores",
    "loadgen_cpu_s",
    "loadgen_cpu_share",
    "server_pid",
    "server_cpu_s",
    "server_cpu_share",
    "machine_cpu_share",
    "errors",
];

#[test]
fn a_fly_sweep_reports_every_point_through_a_link_per_client() {
    let dir = tempfile::tempdir().unwrap();
    let www = exported_korea(dir.path());
    let (_rt, url, served) = start_server(www, false);
    let plots = dir.path().join("plots");
    // 400 kbit/s = 50,000 bytes/s each way per client: less than the 70,000 bytes/s a
    // client averaged here through a 2000 kbit/s link, so this link binds.
    let rate_bytes_s = 400.0 * 1000.0 / 8.0;
    // The static server runs in this process: its CPU is this process's.
    let pid = std::process::id().to_string();
    let report = loadtest(
        &url,
        &[
            "--mode",
            "fly",
            "--sweep",
            "1,2",
            "--path",
            "jump",
            "--legs",
            "2",
            "--tolerance-px",
            "2",
            "--check-every",
            "5",
            "--link",
            "400,20",
            "--server-pid",
            &pid,
            "--plot",
            plots.to_str().unwrap(),
        ],
    );
    assert_eq!(report["mode"], "fly");
    assert_eq!(report["sweep"], serde_json::json!([1, 2]));
    let points = report["points"].as_array().unwrap();
    assert_eq!(points.len(), 2, "{report}");
    let mut requests = 0;
    for (p, clients) in points.iter().zip([1u64, 2]) {
        for key in FLY_POINT_FIELDS {
            assert!(p.get(key).is_some(), "no {key} in {p}");
        }
        assert_eq!(p["clients"], clients);
        assert_eq!(p["clients_failed"], 0, "{p}");
        assert_eq!(p["errors"], serde_json::json!([]));
        assert_eq!(p["fetch_errors"], 0, "{p}");
        assert_eq!(p["cracks"], 0, "{p}");
        assert_eq!(p["coverage_errors"], 0, "{p}");
        assert!(p["frames_checked"].as_u64().unwrap() > 0);
        // Two jump legs per client, each timed.
        assert_eq!(p["jumps"], 2 * clients, "{p}");
        assert_eq!(p["jumps_unfinished"], 0, "{p}");
        let t = |k: &str| p[k].as_f64().unwrap_or_else(|| panic!("{k} in {p}"));
        assert!(t("time_to_full_quality_s_p50") <= t("time_to_full_quality_s_p95"));
        assert!(t("time_to_full_quality_s_p95") <= t("time_to_full_quality_s_max"));
        // Paced at 60 frames/s: every frame holds the screen for a whole period, the last
        // of a leg too (the margin is the period's rounding to nanoseconds).
        assert!(
            t("frames_per_s_p50") > 0.0 && t("frames_per_s_p50") <= 60.001,
            "{p}"
        );
        assert!(t("rps") > 0.0);
        // Every byte went through the clients' own links (headers add to the bodies), and
        // no client's link carried more than its rate.
        assert_eq!(
            p["link"],
            serde_json::json!({"kbit_s": 400.0, "rtt_ms": 20.0})
        );
        let bytes = p["bytes_fetched"].as_u64().unwrap();
        assert!(bytes > 0);
        assert!(p["link_bytes_down"].as_u64().unwrap() > bytes, "{p}");
        let fastest = t("link_bytes_per_s_max");
        assert!(
            fastest > 0.0 && fastest <= rate_bytes_s,
            "{fastest} bytes/s over a {rate_bytes_s} bytes/s link: {p}"
        );
        let per_client = t("bytes_fetched_per_client_p50");
        assert!(per_client > 0.0 && per_client <= bytes as f64);
        // CPU: the load generator used some; shares are seconds over the point's time.
        assert_eq!(
            p["server_pid"].as_u64(),
            Some(u64::from(std::process::id()))
        );
        assert!(t("loadgen_cpu_s") > 0.0);
        let seconds = t("seconds");
        for (cpu, share) in [
            ("loadgen_cpu_s", "loadgen_cpu_share"),
            ("server_cpu_s", "server_cpu_share"),
        ] {
            assert!(t(cpu) >= 0.0, "{p}");
            assert!((t(share) * seconds - t(cpu)).abs() < 1e-6, "{p}");
        }
        let machine = t("machine_cpu_share");
        assert!((0.0..=1.0).contains(&machine), "{p}");
        requests += p["requests"].as_u64().unwrap();
    }
    assert_eq!(requests, served.requests.load(Ordering::Relaxed));
    for name in [
        "clients_ttfq.png",
        "clients_rps.png",
        "clients_cpu.png",
        "clients_jumps.png",
    ] {
        let file = std::fs::File::open(plots.join(name)).unwrap();
        let info = png::Decoder::new(file).read_info().unwrap().info().clone();
        assert_eq!((info.width, info.height), (1000, 600), "{name}");
    }

    // Bad options fail cleanly, naming the option.
    for (extra, needle) in [
        (
            vec!["--mode", "fly", "--server-pid", "4294967295"],
            "--server-pid",
        ),
        (vec!["--mode", "fly", "--sweep", "1,0"], "--sweep"),
        (vec!["--link", "2000,20"], "--link needs --mode fly"),
        (vec!["--mode", "fly", "--link", "0,20"], "link rate"),
        (vec!["--mode", "fly", "--legs", "0"], "--legs"),
    ] {
        let out = run(bin()
            .args(["loadtest", "--url", &url, "--repo", "korea", "--quiet"])
            .args(&extra));
        assert!(!out.status.success(), "{extra:?}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(needle), "{extra:?}: {stderr}");
    }
}
