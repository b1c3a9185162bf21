//! Accepting and driving connections: the connection limit, HTTP/1.1 (keep-alive,
//! pipelining with aggregated flushes) or HTTP/2 (prior knowledge) per connection, the
//! slow-loris and idle timeouts, and graceful shutdown.

use std::io;
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
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};

use crate::config::Limits;
use crate::state::AppState;

/// What an over-limit connection is told before it is closed.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain\r\ncontent-length: 32\r\nretry-after: 1\r\nconnection: close\r\n\r\ntoo many connections, try again\n";

/// The HTTP/2 connection preface; HTTP/1 requests never start with its first bytes.
const H2_PREFACE: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// Accepts until `shutdown` turns true, then drains: open connections finish the request
/// in hand (HTTP/1) or their open streams (HTTP/2) and close, for at most the grace period.
pub(crate) async fn serve(
    listener: TcpListener,
    app: Router,
    state: AppState,
    limits: Limits,
    mut shutdown: watch::Receiver<bool>,
) {
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let limits = Arc::new(limits);
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
        let Ok(permit) = permits.clone().try_acquire_owned() else {
            state.metrics.connections_rejected.fetch_add(1, Relaxed);
            let _ = stream.try_write(BUSY);
            continue;
        };
        state.metrics.connections_accepted.fetch_add(1, Relaxed);
        state.metrics.connections_open.fetch_add(1, Relaxed);
        let (app, state, limits, shutdown) =
            (app.clone(), state.clone(), limits.clone(), shutdown.clone());
        tokio::spawn(async move {
            connection(stream, app, &state, &limits, shutdown).await;
            state.metrics.connections_open.fetch_sub(1, Relaxed);
            drop(permit);
        });
    }
    drop(listener);
    let all = u32::try_from(limits.max_connections).unwrap_or(u32::MAX);
    if tokio::time::timeout(limits.shutdown_grace(), permits.acquire_many(all))
        .await
        .is_err()
    {
        tracing::warn!(
            "shutdown grace period over; closing {} connections",
            limits.max_connections - permits.available_permits()
        );
    }
}

enum Protocol {
    Http1,
    Http2,
}

/// Waits for the first bytes of a connection (at most the header timeout) and tells
/// HTTP/2 prior knowledge from HTTP/1.
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

async fn connection(
    stream: TcpStream,
    app: Router,
    state: &AppState,
    limits: &Limits,
    shutdown: watch::Receiver<bool>,
) {
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
    let activity = Arc::new(AtomicU64::new(now_ms()));
    let io = TokioIo::new(Tracked::new(
        stream,
        activity.clone(),
        state.clone(),
        matches!(protocol, Protocol::Http1),
    ));
    let service = TowerToHyperService::new(app);
    match protocol {
        Protocol::Http1 => {
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout())
                .max_buf_size(limits.max_header_bytes.max(8192))
                .max_headers(limits.max_headers)
                .keep_alive(true)
                .serve_connection(io, service);
            drive(conn, &activity, state, limits, shutdown).await;
        }
        Protocol::Http2 => {
            state.metrics.connections_h2.fetch_add(1, Relaxed);
            let conn = hyper::server::conn::http2::Builder::new(TokioExecutor::new())
                .timer(TokioTimer::new())
                .max_concurrent_streams(limits.max_concurrent_streams)
                .max_header_list_size(u32::try_from(limits.max_header_bytes).unwrap_or(u32::MAX))
                .serve_connection(io, service);
            drive(conn, &activity, state, limits, shutdown).await;
        }
    }
}

/// Runs a connection to its end, closing it when nothing moved for the idle timeout and
/// starting a graceful close when the server shuts down.
async fn drive<C>(
    conn: C,
    activity: &AtomicU64,
    state: &AppState,
    limits: &Limits,
    mut shutdown: watch::Receiver<bool>,
) where
    C: GracefulConnection,
    C::Error: std::fmt::Display,
{
    tokio::pin!(conn);
    let idle_ms = limits.idle_timeout().as_millis() as u64;
    let idle = tokio::time::sleep(limits.idle_timeout());
    tokio::pin!(idle);
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
            _ = idle.as_mut() => {
                let last = activity.load(Relaxed);
                let quiet_ms = now_ms().saturating_sub(last);
                if quiet_ms >= idle_ms {
                    state.metrics.connections_idle_closed.fetch_add(1, Relaxed);
                    return;
                }
                idle.as_mut().reset(tokio::time::Instant::now() + Duration::from_millis(idle_ms - quiet_ms));
            }
        }
    }
}

/// Milliseconds on a process-wide monotonic clock.
fn now_ms() -> u64 {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    START.get_or_init(Instant::now).elapsed().as_millis() as u64
}

/// Bytes of responses collected before they are written even though more pipelined
/// requests are waiting (and the most a connection buffers when its client stops reading).
const OUT_CAP: usize = 64 << 10;

/// A client socket that records when bytes last moved, counts system calls, and (for
/// HTTP/1) aggregates the responses to pipelined requests into few writes.
///
/// Aggregation: reads hand hyper one request head at a time, keeping the rest of what
/// arrived here; responses are collected in `out`, and a flush is deferred while more
/// requests are already waiting (up to [`OUT_CAP`]), so a pipeline of 16 requests is
/// answered with one write. Whenever the connection would wait for input, `out` is
/// written first. This replaces hyper's own `pipeline_flush`, which never stops
/// answering into its write buffer while the socket is full: a client pipelining without
/// reading would grow it without bound. Here a full `out` makes writes wait, and hyper
/// reads no further request until its response is written.
struct Tracked {
    stream: TcpStream,
    activity: Arc<AtomicU64>,
    state: AppState,
    /// HTTP/1: split reads per request and aggregate writes.
    aggregate: bool,
    /// Request bytes read from the socket and not yet handed to hyper (`input[consumed..]`).
    input: Vec<u8>,
    consumed: usize,
    /// Response bytes not yet written.
    out: Vec<u8>,
}

/// Length of the first request head in `bytes` (through its blank line), if complete.
fn first_head_len(bytes: &[u8]) -> Option<usize> {
    bytes
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map(|p| p + 4)
}

impl Tracked {
    fn new(stream: TcpStream, activity: Arc<AtomicU64>, state: AppState, aggregate: bool) -> Self {
        Tracked {
            stream,
            activity,
            state,
            aggregate,
            input: Vec::new(),
            consumed: 0,
            out: Vec::new(),
        }
    }

    fn wrote(&self, n: usize) {
        if n > 0 {
            self.activity.store(now_ms(), Relaxed);
            let m = &self.state.metrics;
            m.socket_writes.fetch_add(1, Relaxed);
            m.socket_bytes_written.fetch_add(n as u64, Relaxed);
        }
    }

    fn has_input(&self) -> bool {
        self.consumed < self.input.len()
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
        let take = first_head_len(rest)
            .unwrap_or(rest.len())
            .min(buf.remaining());
        buf.put_slice(&rest[..take]);
        self.consumed += take;
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
        if !this.aggregate {
            let before = buf.filled().len();
            let poll = Pin::new(&mut this.stream).poll_read(cx, buf);
            if matches!(poll, Poll::Ready(Ok(()))) && buf.filled().len() > before {
                this.activity.store(now_ms(), Relaxed);
                this.state.metrics.socket_reads.fetch_add(1, Relaxed);
            }
            return poll;
        }
        if this.has_input() {
            this.give_input(buf);
            return Poll::Ready(Ok(()));
        }
        // About to wait for the client: first send what it is owed.
        match this.poll_drain(cx) {
            Poll::Ready(Ok(())) => {}
            other => return other,
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
        this.activity.store(now_ms(), Relaxed);
        this.state.metrics.socket_reads.fetch_add(1, Relaxed);
        // Keep everything after the first request head for later reads.
        if let Some(head) = first_head_len(&buf.filled()[before..]) {
            let end = before + head;
            if end < filled {
                this.input.extend_from_slice(&buf.filled()[end..]);
                this.consumed = 0;
                buf.set_filled(end);
            }
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
        if !this.aggregate {
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
