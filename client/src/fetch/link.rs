//! An emulated narrow, high-latency link: an in-process TCP proxy on loopback.
//!
//! Every connection accepted on the proxy's port is forwarded to the upstream server.
//! Each direction is one shared link for all connections: bytes are read in packets of at
//! most [`PACKET_BYTES`], serialised at the link rate (a token bucket without burst, kept
//! as "the time the link is next free"), then held for half the RTT before they are
//! written on (store and forward; byte order is preserved per connection). Reading pauses
//! while the link is busy, so the sender feels the back-pressure of a slow link.
//!
//! ```no_run
//! use std::time::Duration;
//! use quincunx_client::fetch::link::LinkProxy;
//!
//! let upstream = "127.0.0.1:8080".parse().unwrap();
//! let link = LinkProxy::start(upstream, 4000.0, Duration::from_millis(100))?;
//! println!("a 4 Mbit/s, 100 ms link to the server: http://{}", link.local_addr());
//! # Ok::<(), std::io::Error>(())
//! ```

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc::{UnboundedReceiver, unbounded_channel};
use tokio::time::Instant;

use super::lock;

/// Largest packet forwarded at once (an Ethernet MSS).
pub const PACKET_BYTES: usize = 1460;

/// How far ahead of the link's schedule the proxy reads, so timer lateness does not leave
/// the link idle.
const READ_AHEAD: Duration = Duration::from_millis(5);

/// One direction of the link: when it is next free.
struct Direction {
    bytes_per_s: f64,
    next_free: std::sync::Mutex<Option<Instant>>,
    bytes: AtomicU64,
}

impl Direction {
    /// Schedules a packet of `len` bytes read at `now`: when its last bit has crossed.
    fn schedule(&self, now: Instant, len: usize) -> Instant {
        let mut next = lock(&self.next_free);
        let start = next.map_or(now, |t| t.max(now));
        let end = start + Duration::from_secs_f64(len as f64 / self.bytes_per_s);
        *next = Some(end);
        self.bytes.fetch_add(len as u64, Ordering::Relaxed);
        end
    }
}

struct Link {
    upstream: SocketAddr,
    one_way: Duration,
    down: Direction,
    up: Direction,
    connections: AtomicU64,
}

/// A running emulated link; stops when dropped.
pub struct LinkProxy {
    addr: SocketAddr,
    link: Arc<Link>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl LinkProxy {
    /// Listens on a loopback port and forwards to `upstream` over a link of `kbit_s`
    /// kilobits per second in each direction and a round trip of `rtt` (half each way).
    pub fn start(upstream: SocketAddr, kbit_s: f64, rtt: Duration) -> std::io::Result<LinkProxy> {
        if !(kbit_s.is_finite() && kbit_s > 0.0) {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("link rate {kbit_s} kbit/s"),
            ));
        }
        let direction = || Direction {
            bytes_per_s: kbit_s * 1000.0 / 8.0,
            next_free: std::sync::Mutex::new(None),
            bytes: AtomicU64::new(0),
        };
        let link = Arc::new(Link {
            upstream,
            one_way: rtt / 2,
            down: direction(),
            up: direction(),
            connections: AtomicU64::new(0),
        });
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()?;
        let std_listener = std::net::TcpListener::bind(("127.0.0.1", 0))?;
        std_listener.set_nonblocking(true)?;
        let addr = std_listener.local_addr()?;
        let listener = {
            let _entered = runtime.enter();
            TcpListener::from_std(std_listener)?
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let accept_link = Arc::clone(&link);
        let thread = std::thread::Builder::new()
            .name("quincunx-link".into())
            .spawn(move || {
                runtime.block_on(async move {
                    tokio::select! {
                        () = accept_loop(listener, accept_link) => {}
                        _ = stopped => {}
                    }
                });
            })?;
        Ok(LinkProxy {
            addr,
            link,
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// The proxy's address: connect here instead of to the upstream server.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Bytes forwarded towards the client (responses, headers included).
    pub fn bytes_down(&self) -> u64 {
        self.link.down.bytes.load(Ordering::Relaxed)
    }

    /// Bytes forwarded towards the server (requests).
    pub fn bytes_up(&self) -> u64 {
        self.link.up.bytes.load(Ordering::Relaxed)
    }

    /// Connections accepted so far.
    pub fn connections(&self) -> u64 {
        self.link.connections.load(Ordering::Relaxed)
    }
}

impl Drop for LinkProxy {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

async fn accept_loop(listener: TcpListener, link: Arc<Link>) {
    loop {
        let client = match listener.accept().await {
            Ok((s, _)) => s,
            Err(e) => {
                tracing::warn!(%e, "link proxy: accept failed");
                tokio::time::sleep(Duration::from_millis(10)).await;
                continue;
            }
        };
        link.connections.fetch_add(1, Ordering::Relaxed);
        let link = Arc::clone(&link);
        tokio::spawn(async move {
            let server = match TcpStream::connect(link.upstream).await {
                Ok(s) => s,
                Err(e) => {
                    tracing::debug!(%e, "link proxy: upstream refused");
                    return;
                }
            };
            let _ = client.set_nodelay(true);
            let _ = server.set_nodelay(true);
            let (client_rd, client_wr) = client.into_split();
            let (server_rd, server_wr) = server.into_split();
            let up = forward(client_rd, server_wr, Arc::clone(&link), false);
            let down = forward(server_rd, client_wr, link, true);
            tokio::join!(up, down);
        });
    }
}

/// A packet to write at `due`, or end of stream (`None`).
type Delayed = (Instant, Option<Vec<u8>>);

/// Pumps one direction of one connection through the link.
async fn forward(mut from: OwnedReadHalf, to: OwnedWriteHalf, link: Arc<Link>, down: bool) {
    let (tx, rx) = unbounded_channel::<Delayed>();
    let writer = tokio::spawn(deliver(to, rx));
    let direction = if down { &link.down } else { &link.up };
    let mut buf = vec![0u8; PACKET_BYTES];
    loop {
        let n = match from.read(&mut buf).await {
            Ok(0) | Err(_) => 0,
            Ok(n) => n,
        };
        let now = Instant::now();
        if n == 0 {
            let _ = tx.send((now + link.one_way, None));
            break;
        }
        let crossed = direction.schedule(now, n);
        if tx
            .send((crossed + link.one_way, Some(buf[..n].to_vec())))
            .is_err()
        {
            break;
        }
        // Back-pressure: read the next packet when the link is nearly free again.
        tokio::time::sleep_until(crossed.checked_sub(READ_AHEAD).unwrap_or(crossed)).await;
    }
    let _ = writer.await;
}

/// Writes packets when due, in order; shuts the write side down at end of stream.
async fn deliver(mut to: OwnedWriteHalf, mut rx: UnboundedReceiver<Delayed>) {
    while let Some((due, packet)) = rx.recv().await {
        tokio::time::sleep_until(due).await;
        match packet {
            Some(p) => {
                if to.write_all(&p).await.is_err() {
                    return;
                }
            }
            None => {
                let _ = to.shutdown().await;
                return;
            }
        }
    }
}
