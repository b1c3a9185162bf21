//! Accepting and driving connections: one acceptor and event loop per worker thread
//! (`SO_REUSEPORT` listeners, like nginx's worker processes: no work stealing, no
//! cross-thread wake-ups), the connection limits (global, per address, eviction when
//! full), HTTP/1.1 (keep-alive, pipelining with aggregated writes) or HTTP/2 (prior
//! knowledge, or ALPN over TLS) per connection, TLS termination (the handshake is due
//! within the header timeout, like a request head), the slow-client rules
//! (`docs/http-api.md`, "Slow clients"), and graceful shutdown.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::Router;
use axum::http::{HeaderValue, Method, Request, Response, StatusCode, Version, header};
use bytes::Bytes;
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulConnection;
use hyper_util::service::{TowerToHyperService, TowerToHyperServiceFuture};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{Semaphore, watch};

use crate::config::{IpNet, Limits, canonical_ip};
use crate::metrics::Route;
use crate::state::AppState;

/// What an over-limit connection is told before it is closed.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain\r\ncontent-length: 32\r\nretry-after: 1\r\nconnection: close\r\n\r\ntoo many connections, try again\n";

/// The header of a 429 that names the limit it comes from (`docs/http-api.md`).
pub const LIMIT_HEADER: &str = "x-quincunx-limit";

/// What a connection past its client's `max_connections_per_ip` (`limit`) is told before
/// it is closed: the limit in [`LIMIT_HEADER`], and in the body how to lift it.
fn busy_per_ip(limit: usize) -> Vec<u8> {
    let body = format!(
        "too many connections from your address: this server allows {limit} per address \
         (max_connections_per_ip; raise it with --max-connections-per-ip, 0 for no limit, \
         or exempt the address with limits.per_ip_exempt)\n"
    );
    format!(
        "HTTP/1.1 429 Too Many Requests\r\ncontent-type: text/plain\r\ncontent-length: {}\r\n\
         retry-after: 1\r\n{LIMIT_HEADER}: max-connections-per-ip={limit}\r\n\
         connection: close\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

/// The HTTP/2 connection preface; HTTP/1 requests never start with its first bytes.
const H2_PREFACE: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// Pending connections the kernel queues per listener.
const BACKLOG: u32 = 4096;

/// A listening socket that other workers can bind too (`SO_REUSEPORT`).
pub(crate) fn bind(addr: SocketAddr) -> io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    socket.set_reuseaddr(true)?;
    #[cfg(unix)]
    socket.set_reuseport(true)?;
    socket.bind(addr)?;
    socket.listen(BACKLOG)
}

/// Open connections per client address, for `max_connections_per_ip`.
pub(crate) struct PerIp {
    limit: usize,
    /// The 429 answer of a connection over the limit.
    busy: Vec<u8>,
    exempt: Vec<IpNet>,
    open: Mutex<HashMap<IpAddr, usize>>,
}

impl PerIp {
    pub(crate) fn new(limits: &Limits) -> Result<PerIp, crate::ServeError> {
        Ok(PerIp {
            limit: limits.max_connections_per_ip,
            busy: busy_per_ip(limits.max_connections_per_ip),
            exempt: limits.exempt_networks()?,
            open: Mutex::new(HashMap::new()),
        })
    }

    /// The key a client is counted under: its IPv4 address, or its IPv6 /64 (one
    /// subscriber's usual allocation, so rotating addresses within it does not help).
    fn key(ip: IpAddr) -> IpAddr {
        match canonical_ip(ip) {
            IpAddr::V6(v6) => IpAddr::V6(Ipv6Addr::from(u128::from(v6) & !(u64::MAX as u128))),
            v4 => v4,
        }
    }

    /// A slot for one more connection from `ip`, or `None` if it has its limit open.
    fn acquire(self: &Arc<Self>, ip: IpAddr) -> Option<IpSlot> {
        if self.limit == 0 || self.exempt.iter().any(|n| n.contains(ip)) {
            return Some(IpSlot(None));
        }
        let key = PerIp::key(ip);
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        let n = open.entry(key).or_insert(0);
        if *n >= self.limit {
            return None;
        }
        *n += 1;
        Some(IpSlot(Some((self.clone(), key))))
    }
}

/// One connection counted against its client's limit; released when dropped.
struct IpSlot(Option<(Arc<PerIp>, IpAddr)>);

impl Drop for IpSlot {
    fn drop(&mut self) {
        if let Some((per_ip, key)) = self.0.take() {
            let mut open = per_ip.open.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(n) = open.get_mut(&key) {
                *n -= 1;
                if *n == 0 {
                    open.remove(&key);
                }
            }
        }
    }
}

/// Every open connection's [`Clock`], so that a full server can close the least useful
/// one to make room for a new connection.
#[derive(Default)]
pub(crate) struct Registry {
    next: AtomicU64,
    conns: Mutex<HashMap<u64, Arc<Clock>>>,
}

impl Registry {
    fn insert(self: &Arc<Self>, clock: Arc<Clock>) -> Registered {
        let id = self.next.fetch_add(1, Relaxed);
        self.conns
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id, clock);
        Registered(self.clone(), id)
    }

    /// Tells the least useful connection to close: the oldest of those that never
    /// completed a request head (HTTP/1) or moved a response (HTTP/2), else the one that
    /// has gone longest without doing so, if that is at least `min_age_ms`. Whether one
    /// was told.
    fn evict_one(&self, now: u64, min_age_ms: u64) -> bool {
        let conns = self.conns.lock().unwrap_or_else(|e| e.into_inner());
        let victim = conns
            .values()
            .filter(|c| !c.evicted.load(Relaxed))
            .min_by_key(|c| (c.productive.load(Relaxed), c.useful_ms.load(Relaxed)));
        match victim {
            Some(c)
                if !c.productive.load(Relaxed)
                    || now.saturating_sub(c.useful_ms.load(Relaxed)) >= min_age_ms =>
            {
                c.evicted.store(true, Relaxed);
                c.evict.notify_one();
                true
            }
            _ => false,
        }
    }
}

/// A connection's entry in the [`Registry`], removed when dropped.
struct Registered(Arc<Registry>, u64);

impl Drop for Registered {
    fn drop(&mut self) {
        self.0
            .conns
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.1);
    }
}

/// How long a new connection waits for the slot of the connection evicted for it.
const EVICTION_WAIT: Duration = Duration::from_millis(500);

/// What every worker shares.
pub(crate) struct Shared {
    pub(crate) app: Router,
    pub(crate) state: AppState,
    pub(crate) limits: Limits,
    pub(crate) permits: Arc<Semaphore>,
    pub(crate) per_ip: Arc<PerIp>,
    pub(crate) registry: Arc<Registry>,
    pub(crate) shutdown: watch::Receiver<bool>,
    /// TLS termination (`https://`), offering `h2` and `http/1.1` by ALPN.
    pub(crate) tls: Option<tokio_rustls::TlsAcceptor>,
}

/// Serves `first` on the current runtime and `workers - 1` more listeners on the same
/// address, each on its own thread and single-threaded runtime, until shutdown; then
/// drains: open connections finish the request in hand (HTTP/1) or their open streams
/// (HTTP/2) and close, for at most the grace period.
pub(crate) async fn serve(first: TcpListener, workers: usize, shared: Arc<Shared>) {
    let mut threads = Vec::new();
    if let Ok(addr) = first.local_addr() {
        for i in 1..workers {
            let shared = shared.clone();
            let spawned = std::thread::Builder::new()
                .name(format!("quincunx-worker-{i}"))
                .spawn(move || worker(addr, shared));
            match spawned {
                Ok(handle) => threads.push(handle),
                Err(e) => tracing::warn!("could not start worker {i}: {e}"),
            }
        }
    }
    accept_loop(first, &shared).await;
    let left = drain(&shared).await;
    if left > 0 {
        tracing::warn!("shutdown grace period over; closing {left} connections");
    }
    let _ = tokio::task::spawn_blocking(move || {
        for t in threads {
            let _ = t.join();
        }
    })
    .await;
}

fn worker(addr: SocketAddr, shared: Arc<Shared>) {
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => return tracing::warn!("worker runtime: {e}"),
    };
    runtime.block_on(async {
        match bind(addr) {
            Ok(listener) => accept_loop(listener, &shared).await,
            Err(e) => tracing::warn!("worker could not listen on {addr}: {e}"),
        }
        drain(&shared).await;
    });
}

/// Waits until every connection (of every worker) closed or the grace period is over;
/// returns how many are still open.
async fn drain(shared: &Shared) -> u64 {
    let open = &shared.state.metrics.connections_open;
    let deadline = Instant::now() + shared.limits.shutdown_grace();
    loop {
        let n = open.load(Relaxed);
        if n == 0 || Instant::now() >= deadline {
            return n;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

async fn accept_loop(listener: TcpListener, shared: &Arc<Shared>) {
    let mut shutdown = shared.shutdown.clone();
    let metrics = &shared.state.metrics;
    loop {
        let accepted = tokio::select! {
            biased;
            _ = shutdown.wait_for(|stop| *stop) => break,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => accepted,
            Err(e) => {
                // Out of descriptors or memory: back off instead of spinning.
                tracing::warn!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(20)).await;
                continue;
            }
        };
        let accepted_ms = now_ms();
        let Some(slot) = shared.per_ip.acquire(peer.ip()) else {
            metrics.connections_rejected_per_ip.fetch_add(1, Relaxed);
            match &shared.tls {
                None => {
                    let _ = stream.try_write(&shared.per_ip.busy);
                }
                // Over TLS the 429 needs a handshake first, bounded by the header timeout.
                Some(tls) => {
                    let (tls, shared) = (tls.clone(), shared.clone());
                    tokio::spawn(async move {
                        let timeout = shared.limits.header_timeout();
                        let refuse = async {
                            let mut s = tls.accept(stream).await?;
                            tokio::io::AsyncWriteExt::write_all(&mut s, &shared.per_ip.busy)
                                .await?;
                            tokio::io::AsyncWriteExt::shutdown(&mut s).await
                        };
                        let _ = tokio::time::timeout(timeout, refuse).await;
                    });
                }
            }
            continue;
        };
        // Full: the least useful connection (see "Slow clients" in docs/http-api.md) is
        // closed to make room: one that never did anything useful, else one that did
        // nothing useful for a quarter of the header timeout; else the new one is refused.
        let permit = shared.permits.clone().try_acquire_owned().ok();
        let min_age_ms = shared.limits.header_timeout().as_millis() as u64 / 4;
        if permit.is_none() && !shared.registry.evict_one(accepted_ms, min_age_ms) {
            metrics.connections_rejected.fetch_add(1, Relaxed);
            let _ = stream.try_write(BUSY);
            continue;
        }
        let shared = shared.clone();
        tokio::spawn(async move {
            let permit = match permit {
                Some(p) => p,
                None => {
                    let freed = shared.permits.clone().acquire_owned();
                    match tokio::time::timeout(EVICTION_WAIT, freed).await {
                        Ok(Ok(p)) => p,
                        _ => {
                            let m = &shared.state.metrics;
                            m.connections_rejected.fetch_add(1, Relaxed);
                            let _ = stream.try_write(BUSY);
                            return;
                        }
                    }
                }
            };
            let m = &shared.state.metrics;
            m.connections_accepted.fetch_add(1, Relaxed);
            m.connections_open.fetch_add(1, Relaxed);
            connection(stream, accepted_ms, &shared).await;
            shared.state.metrics.connections_open.fetch_sub(1, Relaxed);
            drop(permit);
            drop(slot);
        });
    }
}

enum Protocol {
    Http1,
    Http2,
}

/// Waits for the first bytes of a connection and tells HTTP/2 prior knowledge from
/// HTTP/1.
async fn detect(stream: &TcpStream) -> io::Result<Option<Protocol>> {
    // The whole preface: an HTTP/1 request with method `PRI` shares its first bytes.
    let mut buf = [0u8; H2_PREFACE.len()];
    loop {
        let n = stream.peek(&mut buf).await?;
        if n == 0 {
            return Ok(None);
        }
        if buf[..n] != H2_PREFACE[..n] {
            return Ok(Some(Protocol::Http1));
        }
        if n == buf.len() {
            return Ok(Some(Protocol::Http2));
        }
        // A prefix of the preface: wait for more without spinning on peek.
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// What the watchdog of a connection reads, on the [`now_ms`] clock (0 = never / none).
struct Clock {
    /// When bytes last moved in either direction.
    activity_ms: AtomicU64,
    /// When bytes were last read.
    read_ms: AtomicU64,
    /// When response bytes were last written.
    write_ms: AtomicU64,
    /// HTTP/1: since when the request head being read has been due (the accept for a
    /// connection's first, else its first byte).
    head_since_ms: AtomicU64,
    /// Since when a write has been blocked (the client's receive window is full).
    blocked_since_ms: AtomicU64,
    /// HTTP/2: requests whose response has not been handed over in full.
    streams: AtomicU64,
    /// HTTP/2: when a request last arrived or a response last moved.
    progress_ms: AtomicU64,
    /// HTTP/2: whether a complete request has arrived yet.
    requested: AtomicBool,
    /// HTTP/2: since when bytes have been arriving with no request in flight.
    chatter_since_ms: AtomicU64,
    /// When the connection last did something useful: HTTP/1 completed a request head or
    /// wrote a response, HTTP/2 moved a response (the accept until then).
    useful_ms: AtomicU64,
    /// Whether it ever did something useful.
    productive: AtomicBool,
    /// Chosen for eviction.
    evicted: AtomicBool,
    /// Wakes the connection's task when it is evicted.
    evict: tokio::sync::Notify,
}

impl Clock {
    fn new(accepted_ms: u64) -> Clock {
        Clock {
            activity_ms: AtomicU64::new(accepted_ms),
            read_ms: AtomicU64::new(0),
            write_ms: AtomicU64::new(0),
            head_since_ms: AtomicU64::new(accepted_ms),
            blocked_since_ms: AtomicU64::new(0),
            streams: AtomicU64::new(0),
            progress_ms: AtomicU64::new(accepted_ms),
            requested: AtomicBool::new(false),
            chatter_since_ms: AtomicU64::new(0),
            useful_ms: AtomicU64::new(accepted_ms),
            productive: AtomicBool::new(false),
            evicted: AtomicBool::new(false),
            evict: tokio::sync::Notify::new(),
        }
    }

    fn useful(&self, now: u64) {
        self.useful_ms.store(now, Relaxed);
        if !self.productive.load(Relaxed) {
            self.productive.store(true, Relaxed);
        }
    }
}

async fn connection(stream: TcpStream, accepted_ms: u64, shared: &Shared) {
    let (state, limits) = (&shared.state, &shared.limits);
    let _ = stream.set_nodelay(true);
    let clock = Arc::new(Clock::new(accepted_ms));
    let _registered = shared.registry.insert(clock.clone());
    let head_ms = limits.header_timeout().as_millis() as u64;
    let left = head_ms.saturating_sub(now_ms().saturating_sub(accepted_ms));
    let (stream, protocol) = match &shared.tls {
        None => {
            let Some(protocol) = plain_protocol(&stream, left, &clock, state).await else {
                return;
            };
            (ServerStream::Plain(stream), protocol)
        }
        Some(tls) => {
            // The handshake, like a first request head, is due within the header timeout.
            let handshake = tokio::select! {
                done = tokio::time::timeout(Duration::from_millis(left), tls.accept(stream)) => done,
                _ = clock.evict.notified() => {
                    state.metrics.connections_evicted.fetch_add(1, Relaxed);
                    return;
                }
            };
            let tls = match handshake {
                Ok(Ok(tls)) => tls,
                Ok(Err(e)) => return tracing::debug!("TLS handshake: {e}"),
                Err(_) => {
                    state
                        .metrics
                        .connections_header_timeout
                        .fetch_add(1, Relaxed);
                    return;
                }
            };
            let protocol = match tls.get_ref().1.alpn_protocol() {
                Some(b"h2") => Protocol::Http2,
                _ => Protocol::Http1,
            };
            (ServerStream::Tls(Box::new(tls)), protocol)
        }
    };
    serve_connection(stream, protocol, clock, shared).await;
}

/// The protocol of a cleartext connection, from its first bytes (`None`: closed, evicted
/// or too slow, counted).
async fn plain_protocol(
    stream: &TcpStream,
    left: u64,
    clock: &Clock,
    state: &AppState,
) -> Option<Protocol> {
    let detected = tokio::select! {
        detected = tokio::time::timeout(Duration::from_millis(left), detect(stream)) => detected,
        _ = clock.evict.notified() => {
            state.metrics.connections_evicted.fetch_add(1, Relaxed);
            return None;
        }
    };
    match detected {
        Ok(Ok(Some(p))) => Some(p),
        Ok(Ok(None) | Err(_)) => None,
        Err(_) => {
            state
                .metrics
                .connections_header_timeout
                .fetch_add(1, Relaxed);
            None
        }
    }
}

async fn serve_connection(
    stream: ServerStream,
    protocol: Protocol,
    clock: Arc<Clock>,
    shared: &Shared,
) {
    let (state, limits) = (&shared.state, &shared.limits);
    let http1 = matches!(protocol, Protocol::Http1);
    let io = TokioIo::new(Tracked::new(stream, clock.clone(), state.clone(), http1));
    let service = Service {
        inner: TowerToHyperService::new(shared.app.clone()),
        clock: clock.clone(),
        state: state.clone(),
        http1,
    };
    match protocol {
        Protocol::Http1 => {
            // Head, write and idle timeouts are enforced by `drive` from `Clock`: no timer
            // is armed per request.
            let conn = hyper::server::conn::http1::Builder::new()
                .header_read_timeout(None)
                .max_buf_size(limits.max_header_bytes.max(8192))
                .max_headers(limits.max_headers)
                .keep_alive(true)
                .serve_connection(io, service);
            drive(conn, &clock, shared, false).await;
        }
        Protocol::Http2 => {
            state.metrics.connections_h2.fetch_add(1, Relaxed);
            let conn = hyper::server::conn::http2::Builder::new(TokioExecutor::new())
                .timer(TokioTimer::new())
                .max_concurrent_streams(limits.max_concurrent_streams)
                .max_header_list_size(u32::try_from(limits.max_header_bytes).unwrap_or(u32::MAX))
                // Streams a client opens and resets before they are answered (the "rapid
                // reset" flood), and streams reset for its protocol errors, at most:
                // past either the connection gets GOAWAY.
                .max_pending_accept_reset_streams(H2_MAX_PENDING_RESETS)
                .max_local_error_reset_streams(H2_MAX_LOCAL_ERROR_RESETS)
                .serve_connection(io, service);
            drive(conn, &clock, shared, true).await;
        }
    }
}

/// HTTP/2 streams opened and reset by the client before they were answered, at most.
const H2_MAX_PENDING_RESETS: usize = 20;
/// HTTP/2 streams the server resets for the client's protocol errors, at most.
const H2_MAX_LOCAL_ERROR_RESETS: usize = 64;
/// How long a connection closed by the watchdog has to flush its HTTP/2 GOAWAY.
const GOAWAY_FLUSH: Duration = Duration::from_millis(200);

/// Why the watchdog closes a connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Verdict {
    /// No complete request in time (slow-loris).
    Head,
    /// A response stopped moving.
    Write,
    /// Nothing moved for the idle timeout.
    Idle,
    /// Closed to make room for a new connection on a full server.
    Evicted,
}

/// The rules of "Slow clients" in `docs/http-api.md`, applied to one connection at `now`.
fn verdict(c: &Clock, now: u64, limits: &Limits, http2: bool) -> Option<Verdict> {
    let ms = |d: Duration| d.as_millis() as u64;
    let (head_ms, write_ms, idle_ms) = (
        ms(limits.header_timeout()),
        ms(limits.write_timeout()),
        ms(limits.idle_timeout()),
    );
    let blocked = c.blocked_since_ms.load(Relaxed);
    if blocked != 0 {
        // The server waits for the client to read: only the write timeout runs.
        return (now.saturating_sub(blocked) >= write_ms).then_some(Verdict::Write);
    }
    if http2 {
        if c.streams.load(Relaxed) > 0 {
            let progress = c.progress_ms.load(Relaxed);
            return (now.saturating_sub(progress) >= write_ms).then_some(Verdict::Write);
        }
        if !c.requested.load(Relaxed) {
            let since = c.head_since_ms.load(Relaxed);
            if now.saturating_sub(since) >= head_ms {
                return Some(Verdict::Head);
            }
        } else {
            let since = c.chatter_since_ms.load(Relaxed);
            if since != 0 {
                if now.saturating_sub(c.read_ms.load(Relaxed)) >= head_ms {
                    // Frames (a WINDOW_UPDATE, a PING) then silence: an idle connection.
                    let _ = c
                        .chatter_since_ms
                        .compare_exchange(since, 0, Relaxed, Relaxed);
                } else if now.saturating_sub(since) >= head_ms {
                    return Some(Verdict::Head);
                }
            }
        }
    } else {
        let since = c.head_since_ms.load(Relaxed);
        if since != 0 {
            // Time the server spent writing answers to this client is not the client's.
            let since = since.max(c.write_ms.load(Relaxed));
            if now.saturating_sub(since) >= head_ms {
                return Some(Verdict::Head);
            }
        }
    }
    (now.saturating_sub(c.activity_ms.load(Relaxed)) >= idle_ms).then_some(Verdict::Idle)
}

/// Runs a connection to its end. A watchdog closes it when [`verdict`] says so (HTTP/2
/// with a GOAWAY first), and a graceful close starts when the server shuts down.
async fn drive<C>(conn: C, clock: &Clock, shared: &Shared, http2: bool)
where
    C: GracefulConnection,
    C::Error: std::fmt::Display,
{
    let (metrics, limits) = (&shared.state.metrics, &shared.limits);
    let mut shutdown = shared.shutdown.clone();
    tokio::pin!(conn);
    let period = (limits
        .idle_timeout()
        .min(limits.header_timeout())
        .min(limits.write_timeout())
        / 4)
    .clamp(Duration::from_millis(10), Duration::from_secs(5));
    let mut watchdog = tokio::time::interval(period);
    watchdog.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut closing = false;
    let verdict = loop {
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::trace!("connection ended: {e}");
                }
                return;
            }
            stop = shutdown.wait_for(|stop| *stop), if !closing => {
                drop(stop);
                closing = true;
                conn.as_mut().graceful_shutdown();
            }
            _ = watchdog.tick() => {
                if let Some(v) = verdict(clock, now_ms(), limits, http2) {
                    break v;
                }
            }
            _ = clock.evict.notified() => break Verdict::Evicted,
        }
    };
    let counter = match verdict {
        Verdict::Head => &metrics.connections_header_timeout,
        Verdict::Write => &metrics.connections_write_timeout,
        Verdict::Idle => &metrics.connections_idle_closed,
        Verdict::Evicted => &metrics.connections_evicted,
    };
    counter.fetch_add(1, Relaxed);
    if http2 {
        // GOAWAY, then a moment to send it; the streams are not waited for.
        conn.as_mut().graceful_shutdown();
        let _ = tokio::time::timeout(GOAWAY_FLUSH, conn.as_mut()).await;
    }
}

/// The per-connection service: the router, plus what the watchdog needs to know about
/// requests (HTTP/2: arrivals and responses in flight), plus the HTTP/1 `Host` rules.
#[derive(Clone)]
struct Service {
    inner: TowerToHyperService<Router>,
    clock: Arc<Clock>,
    state: AppState,
    http1: bool,
}

impl hyper::service::Service<Request<Incoming>> for Service {
    type Response = Response<TrackedBody>;
    type Error = Infallible;
    type Future = ServiceFuture;

    fn call(&self, request: Request<Incoming>) -> ServiceFuture {
        if self.http1 {
            if let Err(reason) = check_host(&request).and_then(|()| check_framing(&request)) {
                self.state
                    .metrics
                    .observe(Route::Other, 400, reason.len() as u64, Duration::ZERO);
                return ServiceFuture::Rejected {
                    reason: Some(reason),
                };
            }
            return ServiceFuture::Routed {
                future: self.inner.call(request),
                clock: None,
            };
        }
        let c = &self.clock;
        let now = now_ms();
        c.streams.fetch_add(1, Relaxed);
        c.progress_ms.store(now, Relaxed);
        c.requested.store(true, Relaxed);
        c.chatter_since_ms.store(0, Relaxed);
        ServiceFuture::Routed {
            future: self.inner.call(request),
            clock: Some(StreamGuard(c.clone())),
        }
    }
}

/// HTTP/1 `Host` rules (RFC 9112 3.2): an HTTP/1.1 request has exactly one, any request
/// at most one, and its value is `host[:port]`.
fn check_host<B>(request: &Request<B>) -> Result<(), &'static str> {
    let mut hosts = request.headers().get_all(header::HOST).iter();
    match (hosts.next(), hosts.next()) {
        (Some(_), Some(_)) => Err("more than one Host header\n"),
        (None, _) if request.version() == Version::HTTP_11 => {
            Err("an HTTP/1.1 request needs a Host header\n")
        }
        (None, _) => Ok(()),
        (Some(v), None) if valid_host(v.as_bytes()) => Ok(()),
        (Some(_), None) => Err("the Host header is not host[:port]\n"),
    }
}

/// The authority-form request target is for `CONNECT` only (RFC 9112 3.2.3); hyper
/// parses `GET healthz` as one. (A request with both `Transfer-Encoding` and
/// `Content-Length` needs no check here: hyper drops the `Content-Length`, reads the body
/// as chunked and closes the connection after answering, as RFC 9112 6.3 asks.)
fn check_framing<B>(request: &Request<B>) -> Result<(), &'static str> {
    let uri = request.uri();
    if uri.scheme().is_none() && uri.authority().is_some() && request.method() != Method::CONNECT {
        return Err("the request target must start with '/'\n");
    }
    Ok(())
}

/// `uri-host [ ":" port ]` (RFC 9110 7.2, RFC 3986 3.2.2): a registered name (unreserved,
/// percent-encoded and sub-delimiter characters; may be empty), an IPv4 address or a
/// bracketed IPv6 address, then an optional port of at most 5 digits.
pub(crate) fn valid_host(v: &[u8]) -> bool {
    let (host, port): (&[u8], Option<&[u8]>) = if let Some(rest) = v.strip_prefix(b"[") {
        let Some(close) = rest.iter().position(|&b| b == b']') else {
            return false;
        };
        let literal = &rest[..close];
        let ok = std::str::from_utf8(literal)
            .ok()
            .and_then(|s| s.parse::<Ipv6Addr>().ok())
            .is_some();
        if !ok {
            return false;
        }
        match &rest[close + 1..] {
            [] => (&[], None),
            [b':', port @ ..] => (&[], Some(port)),
            _ => return false,
        }
    } else {
        match v.iter().rposition(|&b| b == b':') {
            Some(i) => (&v[..i], Some(&v[i + 1..])),
            None => (v, None),
        }
    };
    if let Some(port) = port
        && (port.len() > 5 || !port.iter().all(u8::is_ascii_digit))
    {
        return false;
    }
    let mut i = 0;
    while i < host.len() {
        let b = host[i];
        if b == b'%' {
            match host.get(i + 1..i + 3) {
                Some([h, l]) if h.is_ascii_hexdigit() && l.is_ascii_hexdigit() => i += 3,
                _ => return false,
            }
            continue;
        }
        if !(b.is_ascii_alphanumeric() || b"-._~!$&'()*+,;=".contains(&b)) {
            return false;
        }
        i += 1;
    }
    true
}

pin_project_lite::pin_project! {
    /// The response future of [`Service`].
    #[project = ServiceFutureProj]
    enum ServiceFuture {
        Rejected { reason: Option<&'static str> },
        Routed {
            #[pin]
            future: TowerToHyperServiceFuture<Router, Request<Incoming>>,
            clock: Option<StreamGuard>,
        },
    }
}

impl Future for ServiceFuture {
    type Output = Result<Response<TrackedBody>, Infallible>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        match self.project() {
            ServiceFutureProj::Rejected { reason } => {
                let body = axum::body::Body::from(reason.take().unwrap_or(""));
                let mut response = Response::new(TrackedBody { body, stream: None });
                *response.status_mut() = StatusCode::BAD_REQUEST;
                let h = response.headers_mut();
                h.insert(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static("text/plain; charset=utf-8"),
                );
                h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
                h.insert(header::CONNECTION, HeaderValue::from_static("close"));
                Poll::Ready(Ok(response))
            }
            ServiceFutureProj::Routed { future, clock } => {
                let response = match future.poll(cx) {
                    Poll::Ready(Ok(r)) => r,
                    Poll::Ready(Err(never)) => match never {},
                    Poll::Pending => return Poll::Pending,
                };
                let stream = clock.take();
                Poll::Ready(Ok(response.map(|body| TrackedBody { body, stream })))
            }
        }
    }
}

/// One HTTP/2 request in flight, for the watchdog; released when its response body is
/// dropped (hyper drops it once the last frame is handed over, or the stream is reset).
struct StreamGuard(Arc<Clock>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        let now = now_ms();
        self.0.progress_ms.store(now, Relaxed);
        self.0.streams.fetch_sub(1, Relaxed);
    }
}

/// A response body that tells the watchdog when it moves (HTTP/2).
struct TrackedBody {
    body: axum::body::Body,
    stream: Option<StreamGuard>,
}

impl http_body::Body for TrackedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        let this = self.get_mut();
        let poll = Pin::new(&mut this.body).poll_frame(cx);
        if let (Poll::Ready(_), Some(guard)) = (&poll, &this.stream) {
            let now = now_ms();
            guard.0.progress_ms.store(now, Relaxed);
            guard.0.useful(now);
        }
        poll
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

/// Milliseconds since the process started (at least 1), from a coarse clock that a
/// background thread advances every 5 ms: reading it costs an atomic load, not a system
/// call per socket operation.
fn now_ms() -> u64 {
    static CLOCK: std::sync::OnceLock<Arc<AtomicU64>> = std::sync::OnceLock::new();
    let clock = CLOCK.get_or_init(|| {
        let start = Instant::now();
        let clock = Arc::new(AtomicU64::new(1));
        let ticking = clock.clone();
        let spawned = std::thread::Builder::new()
            .name("quincunx-clock".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(Duration::from_millis(5));
                    ticking.store(start.elapsed().as_millis() as u64 + 1, Relaxed);
                }
            });
        if let Err(e) = spawned {
            tracing::warn!("clock thread: {e}; timeouts will not fire");
        }
        clock
    });
    clock.load(Relaxed)
}

/// Empty lines tolerated before a request line (RFC 9112 2.2 asks servers to ignore at
/// least one); a connection sending more is closed without an answer.
pub(crate) const MAX_EMPTY_LINES: u32 = 4;

/// Too many empty lines before a request line.
#[derive(Debug)]
struct TooManyEmptyLines;

/// Finds the empty line that ends a request head, across reads. Lines end in LF or CRLF
/// (as hyper parses them); empty lines before a request line are leading empty lines,
/// not a head.
#[derive(Default)]
struct HeadScanner {
    /// A non-empty line of this head has started.
    started: bool,
    /// The last byte was the LF ending a line (possibly followed by CRs).
    line_start: bool,
    /// Leading empty lines seen before this head.
    empty_lines: u32,
}

impl HeadScanner {
    /// The length of `bytes` through the first head end in them, if any.
    fn feed(&mut self, bytes: &[u8]) -> Result<Option<usize>, TooManyEmptyLines> {
        for (i, &b) in bytes.iter().enumerate() {
            if !self.started {
                match b {
                    b'\n' => {
                        self.empty_lines += 1;
                        if self.empty_lines > MAX_EMPTY_LINES {
                            return Err(TooManyEmptyLines);
                        }
                    }
                    b'\r' => {}
                    _ => {
                        self.started = true;
                        self.line_start = false;
                    }
                }
                continue;
            }
            match b {
                b'\n' if self.line_start => {
                    *self = HeadScanner::default();
                    return Ok(Some(i + 1));
                }
                b'\n' => self.line_start = true,
                b'\r' => {}
                _ => self.line_start = false,
            }
        }
        Ok(None)
    }
}

/// Bytes of responses collected before they are written even though more pipelined
/// requests are waiting (and the most a connection buffers when its client stops reading).
const OUT_CAP: usize = 64 << 10;

/// A client socket that records when bytes last moved and when a request head started,
/// counts system calls, and (for HTTP/1) aggregates the responses to pipelined requests
/// into few writes.
///
/// Aggregation: reads hand hyper one request head at a time, keeping the rest of what
/// arrived here; while more requests are waiting, responses are collected in `out` and
/// flushes deferred (up to [`OUT_CAP`]), so a pipeline of 16 requests is answered with one
/// write. Whenever the connection would wait for input, `out` is written first; with no
/// request waiting, responses are written straight from hyper's buffers. This replaces
/// hyper's own `pipeline_flush`, which keeps answering into its write buffer while the
/// socket is full (a client pipelining without reading grew it by gigabytes). Here a full
/// `out` makes writes wait, and hyper reads no further request until its response is
/// written.
struct Tracked {
    stream: ServerStream,
    clock: Arc<Clock>,
    state: AppState,
    /// HTTP/1: split reads per request, track heads, aggregate writes.
    aggregate: bool,
    scanner: HeadScanner,
    /// A request head has started and not ended.
    in_head: bool,
    /// Request bytes read from the socket and not yet handed to hyper (`input[consumed..]`).
    input: Vec<u8>,
    consumed: usize,
    /// Response bytes not yet written.
    out: Vec<u8>,
}

impl Tracked {
    fn new(stream: ServerStream, clock: Arc<Clock>, state: AppState, aggregate: bool) -> Self {
        Tracked {
            stream,
            clock,
            state,
            aggregate,
            scanner: HeadScanner::default(),
            // A connection's first head is due from the accept (`Clock::head_since_ms`).
            in_head: aggregate,
            input: Vec::new(),
            consumed: 0,
            out: Vec::new(),
        }
    }

    fn wrote(&self, n: usize) {
        if n > 0 {
            let now = now_ms();
            self.clock.activity_ms.store(now, Relaxed);
            self.clock.write_ms.store(now, Relaxed);
            self.clock.blocked_since_ms.store(0, Relaxed);
            if self.aggregate {
                // HTTP/1 writes only responses (HTTP/2 also PING and SETTINGS acks).
                self.clock.useful(now);
            }
            let m = &self.state.metrics;
            m.socket_writes.fetch_add(1, Relaxed);
            m.socket_bytes_written.fetch_add(n as u64, Relaxed);
        }
    }

    /// Notes that a write could not proceed: the client is not reading.
    fn blocked(&self) {
        if self.clock.blocked_since_ms.load(Relaxed) == 0 {
            self.clock.blocked_since_ms.store(now_ms(), Relaxed);
        }
    }

    fn has_input(&self) -> bool {
        self.consumed < self.input.len()
    }

    /// Records whether the bytes just handed to hyper ended a request head.
    fn handed(&mut self, head_ended: bool) {
        if head_ended {
            if self.in_head {
                self.in_head = false;
                self.clock.head_since_ms.store(0, Relaxed);
                self.clock.useful(now_ms());
            }
        } else if !self.in_head {
            self.in_head = true;
            self.clock.head_since_ms.store(now_ms(), Relaxed);
        }
    }

    /// Writes all of `out`.
    fn poll_drain(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while !self.out.is_empty() {
            match Pin::new(&mut self.stream).poll_write(cx, &self.out) {
                Poll::Ready(Ok(0)) => return Poll::Ready(Err(io::ErrorKind::WriteZero.into())),
                Poll::Ready(Ok(n)) => {
                    self.wrote(n);
                    self.out.drain(..n);
                }
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => {
                    self.blocked();
                    return Poll::Pending;
                }
            }
        }
        if self.out.capacity() > OUT_CAP {
            // Idle connections keep no large buffers.
            self.out = Vec::new();
        }
        if let ServerStream::Tls(_) = self.stream {
            // TLS may hold records back after accepting the bytes: out they go before the
            // connection waits for input.
            match Pin::new(&mut self.stream).poll_flush(cx) {
                Poll::Ready(r) => return Poll::Ready(r),
                Poll::Pending => {
                    self.blocked();
                    return Poll::Pending;
                }
            }
        }
        Poll::Ready(Ok(()))
    }

    /// Hands hyper at most one request head from `input`.
    fn give_input(&mut self, buf: &mut ReadBuf<'_>) -> io::Result<()> {
        let rest = &self.input[self.consumed..];
        let avail = rest.len().min(buf.remaining());
        let end = scan(&mut self.scanner, &self.state, &rest[..avail])?;
        let take = end.unwrap_or(avail);
        buf.put_slice(&rest[..take]);
        self.consumed += take;
        self.handed(end == Some(take));
        if self.consumed == self.input.len() {
            self.input = Vec::new();
            self.consumed = 0;
        }
        Ok(())
    }
}

/// A server connection: cleartext TCP or TLS over TCP.
enum ServerStream {
    Plain(TcpStream),
    Tls(Box<tokio_rustls::server::TlsStream<TcpStream>>),
}

impl AsyncRead for ServerStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            ServerStream::Plain(s) => Pin::new(s).poll_read(cx, buf),
            ServerStream::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for ServerStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            ServerStream::Plain(s) => Pin::new(s).poll_write(cx, buf),
            ServerStream::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            ServerStream::Plain(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            ServerStream::Tls(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            ServerStream::Plain(s) => s.is_write_vectored(),
            ServerStream::Tls(s) => s.is_write_vectored(),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            ServerStream::Plain(s) => Pin::new(s).poll_flush(cx),
            ServerStream::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            ServerStream::Plain(s) => Pin::new(s).poll_shutdown(cx),
            ServerStream::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

/// [`HeadScanner::feed`], counting connections closed for empty lines.
fn scan(scanner: &mut HeadScanner, state: &AppState, bytes: &[u8]) -> io::Result<Option<usize>> {
    scanner.feed(bytes).map_err(|TooManyEmptyLines| {
        state.metrics.connections_empty_lines.fetch_add(1, Relaxed);
        io::Error::new(io::ErrorKind::InvalidData, "too many empty lines")
    })
}

impl AsyncRead for Tracked {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if this.has_input() {
            return Poll::Ready(this.give_input(buf));
        }
        if this.aggregate {
            // About to wait for the client: first send what it is owed.
            match this.poll_drain(cx) {
                Poll::Ready(Ok(())) => {}
                other => return other,
            }
        }
        let before = buf.filled().len();
        match Pin::new(&mut this.stream).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {}
            other => return other,
        }
        let filled = buf.filled().len();
        if filled == before {
            return Poll::Ready(Ok(())); // end of stream
        }
        let now = now_ms();
        this.clock.activity_ms.store(now, Relaxed);
        this.clock.read_ms.store(now, Relaxed);
        this.state.metrics.socket_reads.fetch_add(1, Relaxed);
        if !this.aggregate {
            // HTTP/2: bytes with no request in flight start the chatter timer.
            let c = &this.clock;
            if c.streams.load(Relaxed) == 0 && c.chatter_since_ms.load(Relaxed) == 0 {
                c.chatter_since_ms.store(now, Relaxed);
            }
        }
        if this.aggregate {
            // Hand over the first request head; keep the rest for later reads.
            let end = match scan(&mut this.scanner, &this.state, &buf.filled()[before..]) {
                Ok(end) => end,
                Err(e) => return Poll::Ready(Err(e)),
            };
            if let Some(head) = end {
                let cut = before + head;
                if cut < filled {
                    this.input.extend_from_slice(&buf.filled()[cut..]);
                    this.consumed = 0;
                    buf.set_filled(cut);
                }
            }
            this.handed(end.is_some());
        }
        Poll::Ready(Ok(()))
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        self.poll_write_vectored(cx, &[io::IoSlice::new(buf)])
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        if !this.aggregate || (this.out.is_empty() && !this.has_input()) {
            // Nothing to aggregate with: write straight from hyper's buffers.
            let poll = Pin::new(&mut this.stream).poll_write_vectored(cx, bufs);
            match poll {
                Poll::Ready(Ok(n)) => this.wrote(n),
                Poll::Pending => this.blocked(),
                Poll::Ready(Err(_)) => {}
            }
            return poll;
        }
        if this.out.len() >= OUT_CAP {
            match this.poll_drain(cx) {
                Poll::Ready(Ok(())) => {}
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            }
        }
        let mut n = 0;
        for b in bufs {
            this.out.extend_from_slice(b);
            n += b.len();
        }
        Poll::Ready(Ok(n))
    }

    fn is_write_vectored(&self) -> bool {
        true
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        // More pipelined requests are already here: answer them before writing.
        if this.aggregate && this.has_input() && this.out.len() < OUT_CAP {
            return Poll::Ready(Ok(()));
        }
        match this.poll_drain(cx) {
            Poll::Ready(Ok(())) => Pin::new(&mut this.stream).poll_flush(cx),
            other => other,
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        match this.poll_drain(cx) {
            Poll::Ready(Ok(())) => Pin::new(&mut this.stream).poll_shutdown(cx),
            other => other,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn head_ends_are_found_across_reads() {
        let mut s = HeadScanner::default();
        let mut feed = |b: &[u8]| s.feed(b).unwrap();
        assert_eq!(feed(b"GET / HTTP/1.1\r\nHost: a\r\n\r"), None);
        assert_eq!(feed(b"\nGET /x"), Some(1));
        assert_eq!(feed(b" HTTP/1.1\r\n\r\n"), Some(13));
        assert_eq!(feed(b"a\r\na\r\n"), None);
        assert_eq!(feed(b"\r\n"), Some(2));
        // Bare LF line ends, as hyper accepts them.
        assert_eq!(feed(b"GET / HTTP/1.1\nHost: a\n\n"), Some(24));
        // Leading empty lines are not a head.
        assert_eq!(feed(b"\r\n\r\n\r\n"), None);
        assert_eq!(feed(b"GET / HTTP/1.1\r\n\r\n"), Some(18));
    }

    #[test]
    fn more_than_the_tolerated_empty_lines_are_an_error() {
        let mut s = HeadScanner::default();
        for _ in 0..MAX_EMPTY_LINES {
            assert_eq!(s.feed(b"\r\n").unwrap(), None);
        }
        assert!(s.feed(b"\r\n").is_err());
        let mut s = HeadScanner::default();
        assert!(s.feed(&b"\n".repeat(MAX_EMPTY_LINES as usize + 1)).is_err());
    }

    fn limits() -> Limits {
        Limits {
            header_timeout_s: 1.0,
            write_timeout_s: 5.0,
            idle_timeout_s: 100.0,
            ..Limits::default()
        }
    }

    #[test]
    fn a_head_waiting_behind_blocked_writes_is_timed_by_write_progress() {
        let l = limits();
        // A pipelined head partly handed to hyper at t = 1 s, the server blocked writing
        // answers to this client since 1.1 s.
        let c = Clock::new(1000);
        c.head_since_ms.store(1000, Relaxed);
        c.blocked_since_ms.store(1100, Relaxed);
        c.write_ms.store(1100, Relaxed);
        c.activity_ms.store(1100, Relaxed);
        assert_eq!(
            verdict(&c, 4000, &l, false),
            None,
            "head timer charged while blocked"
        );
        assert_eq!(verdict(&c, 6100, &l, false), Some(Verdict::Write));
        // Writes moving again: the head is due a header timeout after the last write.
        c.blocked_since_ms.store(0, Relaxed);
        c.write_ms.store(6000, Relaxed);
        c.activity_ms.store(6000, Relaxed);
        assert_eq!(verdict(&c, 6900, &l, false), None);
        assert_eq!(verdict(&c, 7000, &l, false), Some(Verdict::Head));
        // A connection's first head is due from the accept.
        let fresh = Clock::new(1000);
        assert_eq!(verdict(&fresh, 1999, &l, false), None);
        assert_eq!(verdict(&fresh, 2000, &l, false), Some(Verdict::Head));
    }

    #[test]
    fn http2_chatter_without_requests_is_a_slow_client_but_silence_is_idle() {
        let l = limits();
        let c = Clock::new(1000);
        // No request yet: due from the accept whatever arrives.
        c.read_ms.store(1900, Relaxed);
        assert_eq!(verdict(&c, 2000, &l, true), Some(Verdict::Head));
        c.requested.store(true, Relaxed);
        // Frames since 3 s, the last at 3.9 s: still chatter at 4 s.
        c.chatter_since_ms.store(3000, Relaxed);
        c.read_ms.store(3900, Relaxed);
        assert_eq!(verdict(&c, 4000, &l, true), Some(Verdict::Head));
        // One frame at 3 s, then silence for the header timeout: idle, timer cleared.
        c.read_ms.store(3000, Relaxed);
        c.activity_ms.store(3000, Relaxed);
        assert_eq!(verdict(&c, 4000, &l, true), None);
        assert_eq!(c.chatter_since_ms.load(Relaxed), 0);
        // A stream whose answer does not move is a write timeout, PINGs or not.
        c.streams.store(1, Relaxed);
        c.progress_ms.store(5000, Relaxed);
        c.read_ms.store(9900, Relaxed);
        c.activity_ms.store(9900, Relaxed);
        assert_eq!(verdict(&c, 9999, &l, true), None);
        assert_eq!(verdict(&c, 10_000, &l, true), Some(Verdict::Write));
    }

    #[test]
    fn eviction_prefers_connections_that_never_did_anything_useful() {
        let registry = Arc::new(Registry::default());
        let busy = Arc::new(Clock::new(1000));
        busy.useful(1500);
        let idle_new = Arc::new(Clock::new(3000));
        let _a = registry.insert(busy.clone());
        let _b = registry.insert(idle_new.clone());
        // The never-productive one goes first though it is younger, at any age.
        assert!(registry.evict_one(3001, 250));
        assert!(idle_new.evicted.load(Relaxed) && !busy.evicted.load(Relaxed));
        // A productive one only after min_age without doing anything useful.
        assert!(!registry.evict_one(1600, 250));
        assert!(registry.evict_one(1750, 250));
        assert!(busy.evicted.load(Relaxed));
        assert!(!registry.evict_one(9999, 250), "nothing left to evict");
    }

    #[test]
    fn host_values_follow_rfc_3986() {
        for ok in [
            &b"t"[..],
            b"example.com",
            b"example.com:8080",
            b"127.0.0.1:80",
            b"[::1]",
            b"[::1]:8080",
            b"",
            b"a-b_c~d.e%41",
        ] {
            assert!(valid_host(ok), "{:?}", String::from_utf8_lossy(ok));
        }
        for bad in [
            &b"a b"[..],
            b"a/b",
            b"a@b",
            b"[::1",
            b"[zz]",
            b"[::1]x",
            b"a:b",
            b"a:123456",
            b"a%4",
            b"a%zz",
            b"a\x01",
            b"a:80:90",
        ] {
            assert!(!valid_host(bad), "{:?}", String::from_utf8_lossy(bad));
        }
    }
}
