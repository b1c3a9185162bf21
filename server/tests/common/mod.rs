//! Test fixtures: small repositories of synthetic blobs (the server never decodes, so any
//! bytes do), a server on a loopback port, and a strict little HTTP/1.1 response reader.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::Duration;

use quincunx_diamond::{PlanarDomain, PlanarId, SphereDomain, SphereId};
use quincunx_server::{AppState, RepoConfig, Server, ServerConfig};
use quincunx_store::{Attribute, Metadata, NodataPolicy, RepositoryBuilder};

/// Planar fixture: m = 6, blobs on levels 0..PLANAR_LEVELS except [`PLANAR_LEAF`].
pub const PLANAR_M: u32 = 6;
/// Levels of the planar fixture.
pub const PLANAR_LEVELS: u32 = 4;
/// A level-2 diamond of the planar fixture that has no blob (a leaf).
pub const PLANAR_LEAF: PlanarId = PlanarId { x: 16, y: 16 };
/// Sphere fixture: m = 3, blobs on levels 0..2.
pub const SPHERE_M: u32 = 3;

/// The bytes stored for a centre: distinct per diamond, 1..2000 bytes.
pub fn blob_for(c: [i64; 3]) -> Vec<u8> {
    let seed = (c[0] * 31 + c[1] * 1009 + c[2] * 7919).unsigned_abs();
    let len = 1 + (seed % 1999) as usize;
    (0..len).map(|i| (seed as usize + i * 7) as u8).collect()
}

fn metadata(domain: &str, m: u32, levels: u32) -> Metadata {
    Metadata {
        format_version: 0,
        complete: false,
        content_hash: String::new(),
        domain: domain.into(),
        m,
        n: 32,
        levels,
        attribute: Attribute {
            kind: "elevation".into(),
            units: "m".into(),
        },
        extent: [1 << m, 1 << m],
        nodata: NodataPolicy {
            source_count: 0,
            handling: "none".into(),
        },
        georef: None,
        radius_m: (domain == "sphere").then_some(6_371_000.0),
        channels: vec![],
        build: serde_json::json!({"fixture": true}),
        level_stats: vec![],
        coverage: None,
    }
}

/// Every planar diamond above `levels`, by centre.
pub fn planar_centres(m: u32, levels: u32) -> BTreeMap<[i64; 3], u32> {
    let d = PlanarDomain::new(m).unwrap();
    let mut out = BTreeMap::new();
    let mut frontier = vec![d.root()];
    while let Some(id) = frontier.pop() {
        let level = d.level(id).unwrap();
        if level >= levels || out.insert([id.x, id.y, 0], level).is_some() {
            continue;
        }
        frontier.extend(d.children(id).unwrap());
    }
    out
}

/// Every sphere diamond above `levels`, by centre.
pub fn sphere_centres(m: u32, levels: u32) -> BTreeMap<[i64; 3], u32> {
    let d = SphereDomain::new(m).unwrap();
    let mut out = BTreeMap::new();
    let mut frontier: Vec<SphereId> = d.roots().to_vec();
    while let Some(id) = frontier.pop() {
        let level = d.level(id).unwrap();
        if level >= levels || out.insert(id.c, level).is_some() {
            continue;
        }
        frontier.extend(d.children(id).unwrap());
    }
    out
}

/// Builds the planar (`plain`) and sphere (`globe`) fixtures under `dir`.
pub fn build_fixtures(dir: &Path) -> Vec<RepoConfig> {
    let planar = dir.join("plain");
    let d = PlanarDomain::new(PLANAR_M).unwrap();
    let mut b = RepositoryBuilder::create(&planar).unwrap();
    for (c, level) in planar_centres(PLANAR_M, PLANAR_LEVELS) {
        let id = PlanarId { x: c[0], y: c[1] };
        if id != PLANAR_LEAF {
            b.put(level, &d.key(id).unwrap(), &blob_for(c)).unwrap();
        }
    }
    b.publish(metadata("planar", PLANAR_M, PLANAR_LEVELS), false)
        .unwrap();
    let sphere = dir.join("globe");
    let d = SphereDomain::new(SPHERE_M).unwrap();
    let mut b = RepositoryBuilder::create(&sphere).unwrap();
    for (c, level) in sphere_centres(SPHERE_M, 2) {
        b.put(level, &d.key(SphereId { c }).unwrap(), &blob_for(c))
            .unwrap();
    }
    b.publish(metadata("sphere", SPHERE_M, 2), false).unwrap();
    vec![
        RepoConfig {
            name: "plain".into(),
            path: planar,
        },
        RepoConfig {
            name: "globe".into(),
            path: sphere,
        },
    ]
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

/// One parsed response.
#[derive(Debug)]
pub struct Response {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Response {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

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
