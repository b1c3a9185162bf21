//! Test fixtures: small repositories of synthetic blobs (the fetch layer never decodes, so
//! any bytes do), a real quincunx server on a loopback port that can be killed and
//! restarted on the same port, a raw-TCP fake server with faults, and a frame-loop driver.
#![allow(dead_code, unused_imports, clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::Bytes;
use quincunx_client::fetch::http1::Endpoint;
use quincunx_client::fetch::{FetchConfig, Fetched, Fetcher, Key, Remote, Transport};
use quincunx_server::{RepoConfig, Server, ServerConfig};

pub use quincunx_testkit::{
    PLANAR_LEAF, PLANAR_LEVELS, PLANAR_M, SPHERE_M, blob_for, planar_centres, sphere_centres,
};

/// Builds the planar (`plain`) and sphere (`globe`) fixtures under `dir`. The content is
/// deterministic, so two builds have the same version.
pub fn build_fixtures(dir: &Path) -> Vec<RepoConfig> {
    quincunx_testkit::build_fixtures(dir)
        .into_iter()
        .map(|(name, path)| RepoConfig { name, path })
        .collect()
}

/// The planar fixture's wants: every diamond, coarse to fine (priority = -level).
pub fn planar_wants() -> Vec<(Key, f32)> {
    planar_centres(PLANAR_M, PLANAR_LEVELS)
        .into_iter()
        .map(|(k, level)| (k, -(level as f32)))
        .collect()
}

/// The sphere fixture's wants, coarse to fine.
pub fn sphere_wants() -> Vec<(Key, f32)> {
    sphere_centres(SPHERE_M, 2)
        .into_iter()
        .map(|(k, level)| (k, -(level as f32)))
        .collect()
}

/// A real server on a loopback port over its own fixture copy. Dropping it kills it
/// abruptly: its runtime goes, and with it every connection.
pub struct TestServer {
    pub addr: SocketAddr,
    runtime: Option<tokio::runtime::Runtime>,
    _dir: tempfile::TempDir,
}

impl TestServer {
    /// Starts on `addr` (port 0 for any).
    pub fn start_on(addr: SocketAddr) -> TestServer {
        let dir = tempfile::tempdir().unwrap();
        let config = ServerConfig {
            addr,
            repos: build_fixtures(dir.path()),
            // One worker: everything runs on this runtime, so dropping it kills the server.
            workers: 1,
            ..Default::default()
        };
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let server = runtime.block_on(Server::bind(config)).unwrap();
        let addr = server.local_addr().unwrap();
        runtime.spawn(server.run(std::future::pending()));
        TestServer {
            addr,
            runtime: Some(runtime),
            _dir: dir,
        }
    }

    /// Starts on any free port.
    pub fn start() -> TestServer {
        Self::start_on("127.0.0.1:0".parse().unwrap())
    }

    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Kills the server now (connections are dropped, nothing is drained).
    pub fn kill(mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_timeout(Duration::from_secs(2));
        }
    }

    /// `GET /metrics`, parsed into `name{labels} -> value`.
    pub fn metrics(&self) -> HashMap<String, f64> {
        let endpoint = Endpoint::from_url(&self.url()).unwrap();
        let (status, body) = quincunx_client::fetch::http1::get_blocking(
            &endpoint,
            "/metrics",
            Duration::from_secs(5),
        )
        .unwrap();
        assert_eq!(status, 200);
        String::from_utf8(body)
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .filter_map(|l| {
                let (name, value) = l.rsplit_once(' ')?;
                Some((name.to_string(), value.parse().ok()?))
            })
            .collect()
    }

    /// Blob requests answered so far, whatever the status.
    pub fn blob_requests(&self) -> f64 {
        self.metrics()
            .iter()
            .filter(|(k, _)| k.starts_with("quincunx_http_requests_total{route=\"blob\""))
            .map(|(_, v)| v)
            .sum()
    }

    /// A metric's value (0 if absent).
    pub fn metric(&self, name: &str) -> f64 {
        self.metrics().get(name).copied().unwrap_or(0.0)
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_timeout(Duration::from_secs(2));
        }
    }
}

/// The identity decode: blobs as bytes.
pub fn raw() -> quincunx_client::fetch::Decode<Bytes> {
    Arc::new(|_key, bytes| Ok(bytes))
}

/// A fetch configuration for `repo` at `base` (metadata fetched from the server).
pub fn config(base: &str, repo: &str, transport: Transport) -> FetchConfig {
    let (remote, _) = Remote::open(base, repo, Duration::from_secs(5)).unwrap();
    let mut c = FetchConfig::new(remote);
    c.transport = transport;
    c.request_timeout = Duration::from_secs(5);
    c
}

/// Final answers by key.
pub type Answers = HashMap<Key, Fetched<Bytes>>;

/// A frame loop: submits the still-unanswered wants every 5 ms and collects results until
/// every key has a final answer (Data or Leaf; with `retry_failed`, Failed keys are wanted
/// again) or `limit` passes. Returns the final answers and every Failed seen.
pub fn drive(
    fetcher: &Fetcher<Bytes>,
    wants: &[(Key, f32)],
    limit: Duration,
    retry_failed: bool,
) -> (Answers, Vec<(Key, String)>) {
    let start = Instant::now();
    let mut answers: Answers = HashMap::new();
    let mut failures = Vec::new();
    while start.elapsed() < limit {
        let open: Vec<(Key, f32)> = wants
            .iter()
            .filter(|(k, _)| !answers.contains_key(k))
            .copied()
            .collect();
        if open.is_empty() {
            break;
        }
        fetcher.submit(open);
        std::thread::sleep(Duration::from_millis(5));
        for (k, r) in fetcher.poll() {
            match r {
                Fetched::Failed(e) => {
                    failures.push((k, e.to_string()));
                    if !retry_failed {
                        answers.insert(k, Fetched::Failed(e));
                    }
                }
                other => {
                    answers.insert(k, other);
                }
            }
        }
    }
    (answers, failures)
}

/// Checks that every key got its exact bytes (or Leaf for [`PLANAR_LEAF`]).
pub fn assert_exact(answers: &HashMap<Key, Fetched<Bytes>>, wants: &[(Key, f32)]) {
    assert_eq!(answers.len(), wants.len(), "keys answered");
    for (k, _) in wants {
        match &answers[k] {
            Fetched::Data(b) => {
                assert_ne!(*k, PLANAR_LEAF);
                assert_eq!(b.as_ref(), &blob_for(*k)[..], "{k:?}");
            }
            Fetched::Leaf => assert_eq!(*k, PLANAR_LEAF, "{k:?} is not a leaf"),
            Fetched::Failed(e) => panic!("{k:?} failed: {e}"),
        }
    }
}

/// What the fake server does with each request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Fault {
    /// Answers with the fixture bytes (empty for the leaf).
    Good = 0,
    /// Announces the whole body, sends half, closes.
    Truncate = 1,
    /// A status line that does not parse.
    CorruptStatus = 2,
    /// 404 with a short body.
    NotFound = 3,
    /// 500 with a short body.
    ServerError = 4,
    /// Reads requests, never answers.
    Stall = 5,
    /// Like `Good`, but the leaf is a 404, as a static file server answers the missing
    /// file of an exported leaf.
    LeafNotFound = 6,
}

/// A raw-TCP HTTP/1.1 server whose behaviour can be switched at run time.
pub struct FakeServer {
    pub addr: SocketAddr,
    fault: Arc<AtomicU8>,
    stop: Arc<AtomicBool>,
    pub requests: Arc<AtomicU64>,
    pub connections: Arc<AtomicU64>,
}

impl FakeServer {
    pub fn start(fault: Fault) -> FakeServer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let server = FakeServer {
            addr,
            fault: Arc::new(AtomicU8::new(fault as u8)),
            stop: Arc::new(AtomicBool::new(false)),
            requests: Arc::new(AtomicU64::new(0)),
            connections: Arc::new(AtomicU64::new(0)),
        };
        let (f, stop, requests, connections) = (
            server.fault.clone(),
            server.stop.clone(),
            server.requests.clone(),
            server.connections.clone(),
        );
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((s, _)) => {
                        connections.fetch_add(1, Ordering::Relaxed);
                        let (f, stop, requests) = (f.clone(), stop.clone(), requests.clone());
                        std::thread::spawn(move || serve_fake(s, &f, &stop, &requests));
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(2)),
                }
            }
        });
        server
    }

    pub fn set(&self, fault: Fault) {
        self.fault.store(fault as u8, Ordering::Relaxed);
    }

    /// A remote naming the planar fixture's blobs on this server.
    pub fn remote(&self) -> Remote {
        let base = format!("http://{}", self.addr);
        Remote {
            endpoint: Endpoint::from_url(&base).unwrap(),
            base_url: base,
            name: "plain".into(),
            version: "0123456789abcdef".into(),
            sphere: false,
            static_export: false,
            pack: None,
        }
    }
}

impl Drop for FakeServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

fn serve_fake(mut s: TcpStream, fault: &AtomicU8, stop: &AtomicBool, requests: &AtomicU64) {
    s.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    while !stop.load(Ordering::Relaxed) {
        // Answer every complete request in the buffer.
        loop {
            let mut headers = [httparse::EMPTY_HEADER; 16];
            let mut req = httparse::Request::new(&mut headers);
            let Ok(httparse::Status::Complete(n)) = req.parse(&buf) else {
                break;
            };
            let path = req.path.unwrap_or("").to_string();
            buf.drain(..n);
            requests.fetch_add(1, Ordering::Relaxed);
            let key = path
                .rsplit('/')
                .take(2)
                .collect::<Vec<_>>()
                .iter()
                .rev()
                .map(|p| p.parse::<i64>().unwrap_or(0))
                .collect::<Vec<_>>();
            let key: Key = [key[0], key[1], 0];
            let blob = if key == PLANAR_LEAF {
                Vec::new()
            } else {
                blob_for(key)
            };
            let ok = |body: &[u8]| {
                let mut r = format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n", body.len())
                    .into_bytes();
                r.extend_from_slice(body);
                r
            };
            let reply = match fault.load(Ordering::Relaxed) {
                0 => ok(&blob),
                6 if key == PLANAR_LEAF => {
                    b"HTTP/1.1 404 Not Found\r\nContent-Length: 4\r\n\r\nnope".to_vec()
                }
                6 => ok(&blob),
                1 => {
                    let mut r = ok(&blob);
                    r.truncate(r.len() - blob.len() / 2 - 1);
                    let _ = s.write_all(&r);
                    return;
                }
                2 => b"HTTP/1.1 2x0 OK\r\nContent-Length: 0\r\n\r\n".to_vec(),
                3 => b"HTTP/1.1 404 Not Found\r\nContent-Length: 4\r\n\r\nnope".to_vec(),
                4 => {
                    b"HTTP/1.1 500 Internal Server Error\r\nContent-Length: 4\r\n\r\noops".to_vec()
                }
                _ => Vec::new(),
            };
            if s.write_all(&reply).is_err() {
                return;
            }
        }
        match s.read(&mut chunk) {
            Ok(0) => return,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return,
        }
    }
}
