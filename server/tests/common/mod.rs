//! Test fixtures: small repositories of synthetic blobs (the server never decodes, so any
//! bytes do), a server on a loopback port, and a strict little HTTP/1.1 response reader.
#![allow(dead_code, unused_imports, clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::Duration;

use quincunx_diamond::PlanarId;
use quincunx_server::{AppState, RepoConfig, Server, ServerConfig};

pub use quincunx_testkit::{
    PLANAR_LEVELS, PLANAR_M, SPHERE_M, blob_for, planar_centres, sphere_centres,
};

/// A level-2 diamond of the planar fixture that has no blob (a leaf).
pub const PLANAR_LEAF: PlanarId = PlanarId {
    x: quincunx_testkit::PLANAR_LEAF[0],
    y: quincunx_testkit::PLANAR_LEAF[1],
};

/// Builds the planar (`plain`) and sphere (`globe`) fixtures under `dir`.
pub fn build_fixtures(dir: &Path) -> Vec<RepoConfig> {
    quincunx_testkit::build_fixtures(dir)
        .into_iter()
        .map(|(name, path)| RepoConfig { name, path })
        .collect()
}

/// The planar fixture's blob URL prefix.
pub fn planar_prefix(state: &AppState) -> String {
    let (_, served) = state.repo("plain").unwrap();
    format!("/repos/plain/v/{}/d", served.version)
}

/// The sphere fixture's blob URL prefix.
pub fn sphere_prefix(state: &AppState) -> String {
    let (_, served) = state.repo("globe").unwrap();
    format!("/repos/globe/v/{}/d", served.version)
}

/// A server on a loopback port, stopped when dropped (or by [`Running::stop`]).
pub struct Running {
    pub addr: SocketAddr,
    pub state: AppState,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    pub task: Option<tokio::task::JoinHandle<()>>,
    _dir: tempfile::TempDir,
    pub runtime: Option<tokio::runtime::Runtime>,
}

impl Running {
    /// Starts a server over fresh fixtures, on its own runtime, after `tweak`ing the config.
    pub fn start(tweak: impl FnOnce(&mut ServerConfig)) -> Running {
        let dir = tempfile::tempdir().unwrap();
        let mut config = ServerConfig {
            addr: "127.0.0.1:0".parse().unwrap(),
            repos: build_fixtures(dir.path()),
            ..Default::default()
        };
        tweak(&mut config);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let server = runtime.block_on(Server::bind(config)).unwrap();
        let addr = server.local_addr().unwrap();
        let state = server.state().clone();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = runtime.spawn(server.run(async {
            let _ = stopped.await;
        }));
        Running {
            addr,
            state,
            stop: Some(stop),
            task: Some(task),
            _dir: dir,
            runtime: Some(runtime),
        }
    }

    /// Starts graceful shutdown without waiting for it.
    pub fn begin_stop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }

    /// Shuts down and waits for the drain to finish.
    pub fn stop(mut self) {
        self.begin_stop();
        if let (Some(rt), Some(task)) = (self.runtime.take(), self.task.take()) {
            rt.block_on(task).unwrap();
        }
    }
}

pub use quincunx_testkit::http::Response;

/// Parses one response at the start of `buf`: `Ok(Some((response, used)))`, `Ok(None)` if
/// more bytes are needed.
pub fn parse_response(buf: &[u8], head_request: bool) -> Result<Option<(Response, usize)>, String> {
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut r = httparse::Response::new(&mut headers);
    let head = match r.parse(buf).map_err(|e| e.to_string())? {
        httparse::Status::Partial => return Ok(None),
        httparse::Status::Complete(n) => n,
    };
    let status = r.code.ok_or("no status")?;
    let headers: Vec<(String, String)> = r
        .headers
        .iter()
        .map(|h| {
            (
                h.name.to_string(),
                String::from_utf8_lossy(h.value).into_owned(),
            )
        })
        .collect();
    let len = if head_request || status == 304 || status == 204 {
        0
    } else {
        headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case("content-length"))
            .ok_or("no content-length")?
            .1
            .parse::<usize>()
            .map_err(|e| e.to_string())?
    };
    if buf.len() < head + len {
        return Ok(None);
    }
    Ok(Some((
        Response {
            status,
            headers,
            body: buf[head..head + len].to_vec(),
        },
        head + len,
    )))
}

/// Connects with a read timeout.
pub fn connect(addr: SocketAddr) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

/// Reads `count` responses from `stream` (bytes already read in `buf` are used first).
pub fn read_responses(stream: &mut TcpStream, count: usize) -> Vec<Response> {
    let mut buf = Vec::new();
    let mut out = Vec::new();
    let mut chunk = vec![0u8; 1 << 16];
    while out.len() < count {
        match parse_response(&buf, false).unwrap() {
            Some((r, used)) => {
                buf.drain(..used);
                out.push(r);
            }
            None => {
                let n = stream.read(&mut chunk).unwrap();
                assert!(n > 0, "connection closed after {} responses", out.len());
                buf.extend_from_slice(&chunk[..n]);
            }
        }
    }
    out
}

/// Sends `request` on a new connection and reads one response.
pub fn roundtrip(addr: SocketAddr, request: &str) -> Response {
    let mut s = connect(addr);
    s.write_all(request.as_bytes()).unwrap();
    read_responses(&mut s, 1).remove(0)
}

/// `GET path` on a new connection.
pub fn get(addr: SocketAddr, path: &str) -> Response {
    roundtrip(addr, &format!("GET {path} HTTP/1.1\r\nHost: t\r\n\r\n"))
}

/// Reads until the peer closes (or the read times out); returns everything read and
/// whether the peer closed.
pub fn read_to_close(stream: &mut TcpStream) -> (Vec<u8>, bool) {
    let mut out = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        match stream.read(&mut chunk) {
            Ok(0) => return (out, true),
            Ok(n) => out.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return (out, true),
            Err(_) => return (out, false),
        }
    }
}
