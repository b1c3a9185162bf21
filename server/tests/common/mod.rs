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

    /// The directory of fixture repository `name`.
    pub fn repo_dir(&self, name: &str) -> std::path::PathBuf {
        self._dir.path().join(name)
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

/// Connects from source address `from` (any of 127.0.0.0/8 on Linux), with a small
/// receive buffer if `recv_buffer` is given (set before connecting, so the window
/// advertised from the start is small).
pub fn connect_from(
    from: std::net::IpAddr,
    addr: SocketAddr,
    recv_buffer: Option<usize>,
) -> TcpStream {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::IPV4, Type::STREAM, Some(Protocol::TCP)).unwrap();
    if let Some(n) = recv_buffer {
        socket.set_recv_buffer_size(n).unwrap();
    }
    socket.bind(&SocketAddr::new(from, 0).into()).unwrap();
    socket.connect(&addr.into()).unwrap();
    let s: TcpStream = socket.into();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

/// Waits up to `within` for the peer to close `stream` (reading and discarding what it
/// sends); true if it did.
pub fn closed_within(stream: &mut TcpStream, within: Duration) -> bool {
    let deadline = std::time::Instant::now() + within;
    let mut chunk = [0u8; 4096];
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return false;
        }
        stream.set_read_timeout(Some(left)).unwrap();
        match stream.read(&mut chunk) {
            Ok(0) => return true,
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return true,
            Err(_) => return false,
        }
    }
}

/// A well-behaved client on its own keep-alive connection, making valid requests in a
/// loop on a thread until stopped; [`WellBehaved::stop`] returns (ok, failed).
pub struct WellBehaved {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<(u64, Vec<String>)>>,
}

impl WellBehaved {
    pub fn start(addr: SocketAddr, path: String) -> WellBehaved {
        use std::sync::atomic::Ordering::Relaxed;
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stopping = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut ok = 0;
            let mut failed = Vec::new();
            let mut s = connect(addr);
            let request = format!("GET {path} HTTP/1.1\r\nHost: t\r\n\r\n");
            while !stopping.load(Relaxed) {
                let sent = s.write_all(request.as_bytes());
                let got = sent
                    .map_err(|e| e.to_string())
                    .and_then(|_| read_one(&mut s));
                match got {
                    Ok(200) => ok += 1,
                    Ok(status) => failed.push(format!("status {status}")),
                    Err(e) => {
                        failed.push(e);
                        s = connect(addr);
                    }
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            (ok, failed)
        });
        WellBehaved {
            stop,
            thread: Some(thread),
        }
    }

    /// Stops the client; asserts it made requests and every one succeeded.
    pub fn stop(mut self) -> u64 {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let (ok, failed) = self.thread.take().unwrap().join().unwrap();
        assert!(
            failed.is_empty(),
            "the well-behaved client failed: {failed:?}"
        );
        assert!(ok > 0, "the well-behaved client made no request");
        ok
    }
}

/// Reads one response's status (its body read and discarded).
fn read_one(s: &mut TcpStream) -> Result<u16, String> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    loop {
        if let Some((r, _)) = parse_response(&buf, false)? {
            return Ok(r.status);
        }
        let n = s.read(&mut chunk).map_err(|e| e.to_string())?;
        if n == 0 {
            return Err("closed".into());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

/// HTTP/2 framing for tests that misbehave on purpose.
pub mod h2 {
    use super::*;

    pub const PREFACE: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";
    pub const DATA: u8 = 0;
    pub const HEADERS: u8 = 1;
    pub const RST_STREAM: u8 = 3;
    pub const SETTINGS: u8 = 4;
    pub const PING: u8 = 6;
    pub const GOAWAY: u8 = 7;
    pub const WINDOW_UPDATE: u8 = 8;
    pub const CONTINUATION: u8 = 9;
    pub const END_STREAM: u8 = 1;
    pub const END_HEADERS: u8 = 4;
    pub const ACK: u8 = 1;

    pub fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
        let len = payload.len() as u32;
        let mut f = vec![(len >> 16) as u8, (len >> 8) as u8, len as u8, kind, flags];
        f.extend_from_slice(&stream.to_be_bytes());
        f.extend_from_slice(payload);
        f
    }

    /// A SETTINGS frame with `(id, value)` pairs.
    pub fn settings(pairs: &[(u16, u32)]) -> Vec<u8> {
        let mut p = Vec::new();
        for (id, v) in pairs {
            p.extend_from_slice(&id.to_be_bytes());
            p.extend_from_slice(&v.to_be_bytes());
        }
        frame(SETTINGS, 0, 0, &p)
    }

    /// The HPACK block of `GET path` on authority `t` (no Huffman, no indexing).
    pub fn get_block(path: &str) -> Vec<u8> {
        let mut b = vec![0x82, 0x86, 0x04, path.len() as u8];
        b.extend_from_slice(path.as_bytes());
        b.extend_from_slice(&[0x01, 0x01, b't']);
        b
    }

    /// Preface, empty SETTINGS, and `GET path` on stream 1 (ended).
    pub fn hello(path: &str) -> Vec<u8> {
        let mut out = PREFACE.to_vec();
        out.extend(settings(&[]));
        out.extend(frame(
            HEADERS,
            END_HEADERS | END_STREAM,
            1,
            &get_block(path),
        ));
        out
    }

    /// The `:status` at the start of an HPACK block: indexed (`0x88` = 200, ... `0x8e` =
    /// 500) or a literal with the `:status` name index (`0x48`, `0x08`), no Huffman.
    pub fn status_of(block: &[u8]) -> u16 {
        const STATIC: [u16; 7] = [200, 204, 206, 304, 400, 404, 500];
        match block {
            [b @ 0x88..=0x8e, ..] => STATIC[usize::from(b - 0x88)],
            [0x48 | 0x08, 3, d @ ..] if d.len() >= 3 => std::str::from_utf8(&d[..3])
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(0),
            [0x48 | 0x08, n, d @ ..] if n & 0x80 != 0 => {
                let n = usize::from(n & 0x7f);
                huffman_digits(d.get(..n).unwrap_or(&[]))
            }
            _ => 0,
        }
    }

    /// Decodes a Huffman-coded string of decimal digits (RFC 7541 appendix B: '0'-'2'
    /// are 5-bit codes 0-2, '3'-'9' 6-bit codes 0x19-0x1f); 0 if it is anything else.
    fn huffman_digits(bytes: &[u8]) -> u16 {
        let bits: Vec<u8> = bytes
            .iter()
            .flat_map(|b| (0..8).rev().map(move |i| (b >> i) & 1))
            .collect();
        let take = |at: usize, n: usize| {
            bits.get(at..at + n)
                .map(|b| b.iter().fold(0u8, |v, &x| v << 1 | x))
        };
        let (mut at, mut value, mut digits) = (0, 0u16, 0);
        while digits < 3 {
            match (take(at, 5), take(at, 6)) {
                (Some(c), _) if c < 3 => {
                    value = value * 10 + u16::from(c);
                    at += 5;
                }
                (_, Some(c)) if (0x19..=0x1f).contains(&c) => {
                    value = value * 10 + u16::from(c - 0x19 + 3);
                    at += 6;
                }
                _ => return 0,
            }
            digits += 1;
        }
        value
    }

    /// What came back on a connection.
    #[derive(Debug, Default)]
    pub struct Seen {
        /// Frame types in order (SETTINGS, acks, ...).
        pub kinds: Vec<u8>,
        /// The `:status` of each HEADERS block, by stream (0 if not understood).
        pub statuses: Vec<(u32, u16)>,
        /// GOAWAY error code, if one came.
        pub goaway: Option<u32>,
        /// Streams reset, with their codes.
        pub resets: Vec<(u32, u32)>,
        pub closed: bool,
    }

    /// Reads frames until the peer closes, `within` passes or `stop` says enough.
    pub fn read_frames(s: &mut TcpStream, within: Duration, stop: impl Fn(&Seen) -> bool) -> Seen {
        let deadline = std::time::Instant::now() + within;
        let mut seen = Seen::default();
        let mut buf = Vec::new();
        let mut chunk = [0u8; 16384];
        loop {
            while buf.len() >= 9 {
                let len =
                    (usize::from(buf[0]) << 16) | (usize::from(buf[1]) << 8) | usize::from(buf[2]);
                if buf.len() < 9 + len {
                    break;
                }
                let (kind, stream) = (
                    buf[3],
                    u32::from_be_bytes([buf[5], buf[6], buf[7], buf[8]]) & 0x7fff_ffff,
                );
                let payload = &buf[9..9 + len];
                seen.kinds.push(kind);
                match kind {
                    HEADERS if !payload.is_empty() => {
                        seen.statuses.push((stream, status_of(payload)))
                    }
                    GOAWAY if len >= 8 => {
                        seen.goaway = Some(u32::from_be_bytes([
                            payload[4], payload[5], payload[6], payload[7],
                        ]))
                    }
                    RST_STREAM if len == 4 => seen.resets.push((
                        stream,
                        u32::from_be_bytes([payload[0], payload[1], payload[2], payload[3]]),
                    )),
                    _ => {}
                }
                buf.drain(..9 + len);
            }
            if stop(&seen) {
                return seen;
            }
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return seen;
            }
            s.set_read_timeout(Some(left)).unwrap();
            match s.read(&mut chunk) {
                Ok(0) => {
                    seen.closed = true;
                    return seen;
                }
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => {
                    seen.closed = true;
                    return seen;
                }
                Err(_) => return seen,
            }
        }
    }
}
