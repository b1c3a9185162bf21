//! Pipelined HTTP/1.1 over K persistent connections, each a task on the fetch runtime.
//!
//! A connection writes every request as soon as it gets it (several in one write when they
//! come together) and matches responses to requests in order. When the connection fails
//! (refused, reset, closed, timed out, or a response that does not parse), every request
//! still outstanding on it completes with that error, so the scheduler re-issues them; the
//! connection reconnects when its next request arrives.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};
use tokio::time::Instant;

use super::{Completion, RangeMeta, Request};
use crate::fetch::http1::{Limits, ResponseDecoder, write_get_with};
use crate::fetch::tls::{TlsClient, tls_cause};
use crate::fetch::{FetchConfig, FetchError};

struct Settings {
    addr: SocketAddr,
    /// TLS for `https://` (ALPN `http/1.1`).
    tls: Option<TlsClient>,
    host: String,
    limits: Limits,
    timeout: Duration,
    deadline: Duration,
}

struct Conn {
    tx: UnboundedSender<Request>,
    in_flight: usize,
}

/// The connections and how many requests each has outstanding.
pub(crate) struct Pipelined {
    conns: Vec<Conn>,
    depth: usize,
}

impl Pipelined {
    /// Spawns `config.connections` connection tasks (they connect on their first request).
    pub fn new(config: &FetchConfig, done: UnboundedSender<Completion>) -> Self {
        let settings = Arc::new(Settings {
            addr: config.remote.endpoint.addr,
            tls: config.remote.endpoint.tls.clone(),
            host: config.remote.endpoint.host.clone(),
            limits: config.limits,
            timeout: config.request_timeout,
            deadline: config.request_deadline,
        });
        let conns = (0..config.connections.max(1))
            .map(|slot| {
                let (tx, rx) = unbounded_channel();
                tokio::spawn(run_connection(
                    slot,
                    Arc::clone(&settings),
                    rx,
                    done.clone(),
                ));
                Conn { tx, in_flight: 0 }
            })
            .collect();
        Pipelined {
            conns,
            depth: config.pipeline_depth.max(1),
        }
    }

    pub fn free_slots(&self) -> usize {
        self.conns
            .iter()
            .map(|c| self.depth.saturating_sub(c.in_flight))
            .sum()
    }

    /// Sends on the least loaded connection with room.
    pub fn send(&mut self, request: Request) -> bool {
        let depth = self.depth;
        let Some(conn) = self
            .conns
            .iter_mut()
            .filter(|c| c.in_flight < depth)
            .min_by_key(|c| c.in_flight)
        else {
            return false;
        };
        if conn.tx.send(request).is_err() {
            return false;
        }
        conn.in_flight += 1;
        true
    }

    pub fn finished(&mut self, slot: usize) {
        if let Some(c) = self.conns.get_mut(slot) {
            c.in_flight = c.in_flight.saturating_sub(1);
        }
    }
}

/// One connection's life: wait for a request, connect, exchange until failure, fail what
/// is outstanding, repeat. Ends when the driver is dropped.
async fn run_connection(
    slot: usize,
    settings: Arc<Settings>,
    mut rx: UnboundedReceiver<Request>,
    done: UnboundedSender<Completion>,
) {
    let mut pending: VecDeque<Request> = VecDeque::new();
    let mut out = Vec::new();
    loop {
        if pending.is_empty() {
            match rx.recv().await {
                Some(r) => pending.push_back(r),
                None => return,
            }
        }
        while let Ok(r) = rx.try_recv() {
            pending.push_back(r);
        }
        let error = match session(slot, &settings, &mut rx, &done, &mut pending, &mut out).await {
            Ok(()) => return,
            // The server answered and closed (announced, as nginx after `keepalive_requests`,
            // 1,000 by default, or at a response boundary, as nginx after an error answer):
            // what it did not answer goes out again on a new connection, not counted as
            // failures (RFC 9112 9.3.1: GETs are idempotent). It answered at least one on
            // this connection, so this makes progress.
            Err(e) if e == announced_close() => {
                tracing::debug!(
                    slot,
                    outstanding = pending.len(),
                    "server closed; reconnecting"
                );
                continue;
            }
            Err(e) => e,
        };
        if !pending.is_empty() {
            tracing::debug!(slot, %error, outstanding = pending.len(), "connection failed");
        }
        for r in pending.drain(..) {
            let _ = done.send(Completion {
                key: r.key,
                tag: r.tag,
                range: None,
                slot,
                result: Err(error.clone()),
            });
        }
    }
}

enum Event {
    Request(Option<Request>),
    Read(Result<usize, FetchError>),
    Timeout,
}

/// The error of a connection the server closed after announcing it (`Connection: close`).
fn announced_close() -> FetchError {
    FetchError::Connection("the server closed the connection".into())
}

fn conn_err(e: std::io::Error) -> FetchError {
    FetchError::Connection(e.to_string())
}

/// Reads what is available into the decoder.
async fn read_some<R: AsyncRead + Unpin>(
    rd: &mut R,
    decoder: &mut ResponseDecoder,
) -> Result<usize, FetchError> {
    let spare = decoder
        .spare()
        .map_err(|e| FetchError::Protocol(e.to_string()))?;
    let n = rd.read(spare).await.map_err(conn_err)?;
    decoder.filled(n);
    Ok(n)
}

async fn write_all<W: AsyncWrite + Unpin>(
    wr: &mut W,
    bytes: &[u8],
    timeout: Duration,
) -> Result<(), FetchError> {
    let write = async {
        wr.write_all(bytes).await?;
        // TLS buffers records: push them out now.
        wr.flush().await
    };
    match tokio::time::timeout(timeout, write).await {
        Ok(r) => r.map_err(conn_err),
        Err(_) => Err(FetchError::Timeout(timeout)),
    }
}

/// One connection (TCP, then TLS for `https://`): `Ok(())` when the request channel closed, else why it failed.
async fn session(
    slot: usize,
    s: &Settings,
    rx: &mut UnboundedReceiver<Request>,
    done: &UnboundedSender<Completion>,
    pending: &mut VecDeque<Request>,
    out: &mut Vec<u8>,
) -> Result<(), FetchError> {
    let stream = match tokio::time::timeout(s.timeout, TcpStream::connect(s.addr)).await {
        Err(_) => return Err(FetchError::Timeout(s.timeout)),
        Ok(Err(e)) => return Err(conn_err(e)),
        Ok(Ok(stream)) => stream,
    };
    stream.set_nodelay(true).map_err(conn_err)?;
    let Some(tls) = &s.tls else {
        let (rd, wr) = stream.into_split();
        return exchange(slot, s, rd, wr, rx, done, pending, out).await;
    };
    let host = tls.host();
    let stream = match tokio::time::timeout(s.timeout, tls.connect(stream)).await {
        Err(_) => return Err(FetchError::Timeout(s.timeout)),
        Ok(Err(e)) => {
            return Err(match tls_cause(&e, &host) {
                Some(msg) => FetchError::Tls(msg),
                None => FetchError::Tls(format!("TLS handshake with {host}: {e}")),
            });
        }
        Ok(Ok(stream)) => stream,
    };
    let (rd, wr) = tokio::io::split(stream);
    exchange(slot, s, rd, wr, rx, done, pending, out).await
}

/// Requests and responses on one connected stream, until the channel closes (`Ok`) or the
/// connection fails.
#[allow(clippy::too_many_arguments)]
async fn exchange<R: AsyncRead + Unpin, W: AsyncWrite + Unpin>(
    slot: usize,
    s: &Settings,
    mut rd: R,
    mut wr: W,
    rx: &mut UnboundedReceiver<Request>,
    done: &UnboundedSender<Completion>,
    pending: &mut VecDeque<Request>,
    out: &mut Vec<u8>,
) -> Result<(), FetchError> {
    let mut decoder = ResponseDecoder::new(s.limits);
    out.clear();
    for r in pending.iter() {
        write_get_with(out, &s.host, r.path.as_bytes(), r.headers.as_bytes());
    }
    write_all(&mut wr, out, s.timeout).await?;
    // When each outstanding request was written: the oldest must be answered within the
    // request deadline (responses come in order, so it is the one at the front).
    let mut written: VecDeque<Instant> = pending.iter().map(|_| Instant::now()).collect();
    // A connection with requests outstanding must make progress within the timeout.
    let mut deadline = Instant::now() + s.timeout;
    let mut answered = 0u64;
    loop {
        let oldest_due = written.front().map(|&t| t + s.deadline);
        let wake = oldest_due.map_or(deadline, |due| due.min(deadline));
        let event = tokio::select! {
            r = rx.recv() => Event::Request(r),
            n = read_some(&mut rd, &mut decoder) => Event::Read(n),
            () = tokio::time::sleep_until(wake), if !pending.is_empty() => Event::Timeout,
        };
        match event {
            Event::Request(None) => return Ok(()),
            Event::Request(Some(first)) => {
                if pending.is_empty() {
                    deadline = Instant::now() + s.timeout;
                }
                out.clear();
                write_get_with(
                    out,
                    &s.host,
                    first.path.as_bytes(),
                    first.headers.as_bytes(),
                );
                pending.push_back(first);
                while let Ok(r) = rx.try_recv() {
                    write_get_with(out, &s.host, r.path.as_bytes(), r.headers.as_bytes());
                    pending.push_back(r);
                }
                write_all(&mut wr, out, s.timeout).await?;
                let now = Instant::now();
                written.resize(pending.len(), now);
            }
            Event::Read(n) => {
                // Closed (or reset: nginx resets a connection it closes after an error
                // answer while requests are unread) between answers after answering
                // some: as if announced.
                let between = answered > 0 && decoder.buffered() == 0;
                match n {
                    Ok(0) if between => return Err(announced_close()),
                    Ok(0) => return Err(FetchError::Connection("closed by the server".into())),
                    Err(FetchError::Connection(_)) if between => return Err(announced_close()),
                    Err(e) => return Err(e),
                    Ok(_) => {}
                }
                deadline = Instant::now() + s.timeout;
                while let Some(resp) = decoder
                    .decode()
                    .map_err(|e| FetchError::Protocol(e.to_string()))?
                {
                    let Some(req) = pending.pop_front() else {
                        return Err(FetchError::Protocol("response to no request".into()));
                    };
                    written.pop_front();
                    answered += 1;
                    let close = resp.close;
                    let range = (!req.headers.is_empty()).then(|| RangeMeta {
                        content_range: resp.content_range,
                        etag: resp.etag.map(|e| String::from_utf8_lossy(e).into_owned()),
                    });
                    let _ = done.send(Completion {
                        key: req.key,
                        tag: req.tag,
                        range,
                        slot,
                        result: Ok((resp.status, Bytes::copy_from_slice(resp.body))),
                    });
                    if close {
                        return Err(announced_close());
                    }
                }
            }
            Event::Timeout => {
                return Err(match oldest_due {
                    Some(due) if Instant::now() >= due => FetchError::Deadline(s.deadline),
                    _ => FetchError::Timeout(s.timeout),
                });
            }
        }
    }
}
