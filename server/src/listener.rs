//! Accepting and driving connections: one acceptor and event loop per worker thread
//! (`SO_REUSEPORT` listeners, like nginx's worker processes: no work stealing, no
//! cross-thread wake-ups), the connection limit, HTTP/1.1 (keep-alive, pipelining with
//! aggregated writes) or HTTP/2 (prior knowledge) per connection, the slow-loris and
//! idle timeouts, and graceful shutdown.

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulConnection;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{Semaphore, watch};

use crate::config::Limits;
use crate::state::AppState;

/// What an over-limit connection is told before it is closed.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain\r\ncontent-length: 32\r\nretry-after: 1\r\nconnection: close\r\n\r\ntoo many connections, try again\n";

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

/// What every worker shares.
pub(crate) struct Shared {
    pub(crate) app: Router,
    pub(crate) state: AppState,
    pub(crate) limits: Limits,
    pub(crate) permits: Arc<Semaphore>,
    pub(crate) shutdown: watch::Receiver<bool>,
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
    drain(&shared).await;
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

/// Waits until every connection closed or the grace period is over.
async fn drain(shared: &Shared) {
    let limits = &shared.limits;
    let all = u32::try_from(limits.max_connections).unwrap_or(u32::MAX);
    if tokio::time::timeout(limits.shutdown_grace(), shared.permits.acquire_many(all))
        .await
        .is_err()
    {
        tracing::warn!(
            "shutdown grace period over; closing {} connections",
            limits
                .max_connections
                .saturating_sub(shared.permits.available_permits())
        );
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
        let stream = match accepted {
            Ok((stream, _peer)) => stream,
            Err(e) => {
                // Out of descriptors or memory: back off instead of spinning.
                tracing::warn!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(20)).await;
                continue;
            }
        };
        let Ok(permit) = shared.permits.clone().try_acquire_owned() else {
            metrics.connections_rejected.fetch_add(1, Relaxed);
            let _ = stream.try_write(BUSY);
            continue;
        };
        metrics.connections_accepted.fetch_add(1, Relaxed);
        metrics.connections_open.fetch_add(1, Relaxed);
        let shared = shared.clone();
        tokio::spawn(async move {
            connection(stream, &shared).await;
            shared.state.metrics.connections_open.fetch_sub(1, Relaxed);
            drop(permit);
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
    let mut buf = [0u8; 4];
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

/// When bytes last moved on a connection, and since when a request head has been
/// arriving (0 = none), on the [`now_ms`] clock.
#[derive(Default)]
struct Clock {
    activity_ms: AtomicU64,
    head_since_ms: AtomicU64,
}

async fn connection(stream: TcpStream, shared: &Shared) {
    let (state, limits) = (&shared.state, &shared.limits);
    let _ = stream.set_nodelay(true);
    let protocol = match tokio::time::timeout(limits.header_timeout(), detect(&stream)).await {
        Ok(Ok(Some(p))) => p,
        Ok(Ok(None) | Err(_)) => return,
        Err(_) => {
            state
                .metrics
                .connections_header_timeout
                .fetch_add(1, Relaxed);
            return;
        }
    };
    let clock = Arc::new(Clock::default());
    clock.activity_ms.store(now_ms(), Relaxed);
    let io = TokioIo::new(Tracked::new(
        stream,
        clock.clone(),
        state.clone(),
        matches!(protocol, Protocol::Http1),
    ));
    let service = TowerToHyperService::new(shared.app.clone());
    match protocol {
        Protocol::Http1 => {
            // Head and idle timeouts are enforced by `drive` from `Clock`: no timer is
            // armed per request.
            let conn = hyper::server::conn::http1::Builder::new()
                .header_read_timeout(None)
                .max_buf_size(limits.max_header_bytes.max(8192))
                .max_headers(limits.max_headers)
                .keep_alive(true)
                .serve_connection(io, service);
            drive(conn, &clock, shared).await;
        }
        Protocol::Http2 => {
            state.metrics.connections_h2.fetch_add(1, Relaxed);
            let conn = hyper::server::conn::http2::Builder::new(TokioExecutor::new())
                .timer(TokioTimer::new())
                .max_concurrent_streams(limits.max_concurrent_streams)
                .max_header_list_size(u32::try_from(limits.max_header_bytes).unwrap_or(u32::MAX))
                .serve_connection(io, service);
            drive(conn, &clock, shared).await;
        }
    }
}

/// Runs a connection to its end. A watchdog closes it when nothing moved for the idle
/// timeout or a request head has been arriving for longer than the header timeout
/// (slow-loris), and a graceful close starts when the server shuts down.
async fn drive<C>(conn: C, clock: &Clock, shared: &Shared)
where
    C: GracefulConnection,
    C::Error: std::fmt::Display,
{
    let (metrics, limits) = (&shared.state.metrics, &shared.limits);
    let mut shutdown = shared.shutdown.clone();
    tokio::pin!(conn);
    let idle_ms = limits.idle_timeout().as_millis() as u64;
    let head_ms = limits.header_timeout().as_millis() as u64;
    let period = (limits.idle_timeout().min(limits.header_timeout()) / 4)
        .clamp(Duration::from_millis(10), Duration::from_secs(5));
    let mut watchdog = tokio::time::interval(period);
    watchdog.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut closing = false;
    loop {
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::trace!("connection ended: {e}");
                }
                return;
            }
            _ = shutdown.wait_for(|stop| *stop), if !closing => {
                closing = true;
                conn.as_mut().graceful_shutdown();
            }
            _ = watchdog.tick() => {
                let now = now_ms();
                if now.saturating_sub(clock.activity_ms.load(Relaxed)) >= idle_ms {
                    metrics.connections_idle_closed.fetch_add(1, Relaxed);
                    return;
                }
                let since = clock.head_since_ms.load(Relaxed);
                if since != 0 && now.saturating_sub(since) >= head_ms {
                    metrics.connections_header_timeout.fetch_add(1, Relaxed);
                    return;
                }
            }
        }
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

/// Finds the blank line that ends a request head, across reads.
#[derive(Default)]
struct HeadScanner {
    /// Bytes of `\r\n\r\n` matched at the end of what was fed so far.
    matched: usize,
}

impl HeadScanner {
    /// The length of `bytes` through the first head end in them, if any.
    fn feed(&mut self, bytes: &[u8]) -> Option<usize> {
        const END: &[u8; 4] = b"\r\n\r\n";
        for (i, &b) in bytes.iter().enumerate() {
            self.matched = if b == END[self.matched] {
                self.matched + 1
            } else if b == b'\r' {
                1
            } else {
                0
            };
            if self.matched == END.len() {
                self.matched = 0;
                return Some(i + 1);
            }
        }
        None
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
    stream: TcpStream,
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
    fn new(stream: TcpStream, clock: Arc<Clock>, state: AppState, aggregate: bool) -> Self {
        Tracked {
            stream,
            clock,
            state,
            aggregate,
            scanner: HeadScanner::default(),
            in_head: false,
            input: Vec::new(),
            consumed: 0,
            out: Vec::new(),
        }
    }

    fn wrote(&self, n: usize) {
        if n > 0 {
            self.clock.activity_ms.store(now_ms(), Relaxed);
            let m = &self.state.metrics;
            m.socket_writes.fetch_add(1, Relaxed);
            m.socket_bytes_written.fetch_add(n as u64, Relaxed);
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
                Poll::Pending => return Poll::Pending,
            }
        }
        if self.out.capacity() > OUT_CAP {
            // Idle connections keep no large buffers.
            self.out = Vec::new();
        }
        Poll::Ready(Ok(()))
    }

    /// Hands hyper at most one request head from `input`.
    fn give_input(&mut self, buf: &mut ReadBuf<'_>) {
        let rest = &self.input[self.consumed..];
        let avail = rest.len().min(buf.remaining());
        let end = self.scanner.feed(&rest[..avail]);
        let take = end.unwrap_or(avail);
        buf.put_slice(&rest[..take]);
        self.consumed += take;
        self.handed(end == Some(take));
        if self.consumed == self.input.len() {
            self.input = Vec::new();
            self.consumed = 0;
        }
    }
}

impl AsyncRead for Tracked {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if this.has_input() {
            this.give_input(buf);
            return Poll::Ready(Ok(()));
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
        this.clock.activity_ms.store(now_ms(), Relaxed);
        this.state.metrics.socket_reads.fetch_add(1, Relaxed);
        if this.aggregate {
            // Hand over the first request head; keep the rest for later reads.
            let end = this.scanner.feed(&buf.filled()[before..]);
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
            if let Poll::Ready(Ok(n)) = poll {
                this.wrote(n);
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
        assert_eq!(s.feed(b"GET / HTTP/1.1\r\nHost: a\r\n\r"), None);
        assert_eq!(s.feed(b"\nGET /x"), Some(1));
        assert_eq!(s.feed(b" HTTP/1.1\r\n\r\n"), Some(13));
        assert_eq!(s.feed(b"\r\r\n\r\n"), Some(5));
        assert_eq!(s.feed(b"a\r\na\r\n"), None);
        assert_eq!(s.feed(b"\r\n"), Some(2));
    }
}
