//! The data access layer: a network thread that fetches blobs by diamond key.
//!
//! The frame loop talks to a [`Fetcher`] through channels and never blocks on the network:
//! - each frame it [`Fetcher::submit`]s the keys it wants with priorities (higher = more
//!   urgent; the refinement code uses coarse-to-fine, projected error). Keys left out of a
//!   submit are dropped from the queue (a request already in flight is not cancelled);
//! - it [`Fetcher::poll`]s for results: [`Fetched::Data`] (decoded on the network thread),
//!   [`Fetched::Leaf`] (an empty blob: the diamond has no refinement data), or
//!   [`Fetched::Failed`].
//!
//! `fetch` sees keys and priorities, never the DAG. A key is a diamond centre `[x, y, z]`
//! (planar ids use `z = 0`), see [`Remote`].
//!
//! Inside the thread:
//! - a [`cache::DecodedCache`] of decoded values (LRU, byte budget) and the set of known
//!   leaves, shared with the frame loop and consulted before anything is requested;
//! - a [`schedule::Scheduler`]: the wanted keys in priority order, what is in flight, and
//!   per-key retry backoff after transient failures;
//! - a [`bandwidth::Bandwidth`] estimator: EWMA of the delivered rate and of the blob size,
//!   and a minimum-latency RTT estimate. The number of requests outstanding is held to what
//!   can arrive within about one RTT plus one frame at the estimated rate, so the queue
//!   stays in the client, where priorities can still change;
//! - a [`Transport`]: pipelined HTTP/1.1 over K persistent connections ([`http1`], our own
//!   strict parser), plain HTTP/1.1 over K connections, or HTTP/2 over one connection;
//!   each speaks TLS for `https://` URLs ([`tls`]).
//!
//! [`link`] is an emulated narrow, high-latency link (an in-process throttling TCP proxy)
//! for tests and measurements.

pub mod bandwidth;
pub mod http1;
pub mod link;
mod remote;
pub mod tls;
mod transport;
mod worker;

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use bytes::Bytes;

#[doc(inline)]
pub use quincunx_client_core::fetch::{ErrorKind, FetchError, Key, Weigh, cache, schedule};
pub use remote::Remote;
pub use worker::Fetcher;

/// Turns a blob's bytes into the value handed to the frame loop; runs on the network
/// thread. An `Err` is reported as [`FetchError::Decode`] and not retried.
pub type Decode<T> = Arc<dyn Fn(Key, Bytes) -> Result<T, String> + Send + Sync>;

/// What one answer decoded to: the requested key's value, and the values of the other
/// keys the answer carried (a package's owned children, `quincunx_meta::answer`).
#[derive(Debug)]
pub struct Decoded<T> {
    /// The value of the key asked for.
    pub value: T,
    /// Other keys the same answer brought, with their values.
    pub carried: Vec<(Key, T)>,
}

/// Like [`Decode`], for answers that may carry other keys' values: the flag says whether
/// the answer was asked for as a package ([`Remote::package_path`]).
pub type Unpack<T> = Arc<dyn Fn(Key, Bytes, bool) -> Result<Decoded<T>, String> + Send + Sync>;

/// What became of a wanted key.
#[derive(Debug)]
pub enum Fetched<T> {
    /// The decoded blob.
    Data(Arc<T>),
    /// The server answered with an empty blob: the diamond has no refinement data.
    Leaf,
    /// The key could not be fetched: a permanent failure (4xx, decode error), or a
    /// transient one that persisted for [`FetchConfig::max_attempts`] attempts in a row.
    /// Submitting the key again retries it (after its backoff).
    Failed(FetchError),
}

impl<T> Clone for Fetched<T> {
    fn clone(&self) -> Self {
        match self {
            Fetched::Data(v) => Fetched::Data(Arc::clone(v)),
            Fetched::Leaf => Fetched::Leaf,
            Fetched::Failed(e) => Fetched::Failed(e.clone()),
        }
    }
}

/// How blobs travel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Transport {
    /// Our pipelined HTTP/1.1 client: [`FetchConfig::connections`] persistent connections,
    /// up to [`FetchConfig::pipeline_depth`] requests outstanding on each, responses in
    /// order, strict parsing; requests of a dropped connection are re-issued.
    Pipelined,
    /// HTTP/1.1 without pipelining (reqwest): one request at a time on each of
    /// [`FetchConfig::connections`] connections.
    Plain,
    /// HTTP/2 with prior knowledge (reqwest): streams multiplexed on one connection.
    H2,
}

impl Transport {
    /// All transports, for comparisons.
    pub const ALL: [Transport; 3] = [Transport::Pipelined, Transport::Plain, Transport::H2];

    /// `pipelined`, `plain` or `h2`.
    pub fn name(self) -> &'static str {
        match self {
            Transport::Pipelined => "pipelined",
            Transport::Plain => "plain",
            Transport::H2 => "h2",
        }
    }
}

impl std::str::FromStr for Transport {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Transport::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| format!("unknown transport {s:?} (pipelined, plain or h2)"))
    }
}

/// Default [`FetchConfig::request_deadline`].
pub const DEFAULT_REQUEST_DEADLINE: Duration = Duration::from_secs(30);

/// Settings of a [`Fetcher`]. [`FetchConfig::new`] gives the defaults.
#[derive(Clone, Debug)]
pub struct FetchConfig {
    /// Where blobs come from.
    pub remote: Remote,
    /// How they travel.
    pub transport: Transport,
    /// Persistent connections (pipelined and plain; HTTP/2 uses one).
    pub connections: usize,
    /// Requests outstanding per pipelined connection.
    pub pipeline_depth: usize,
    /// Requests outstanding in total, whatever the bandwidth estimate says.
    pub max_in_flight: usize,
    /// Requests outstanding before there is a bandwidth estimate, and the least ever.
    pub initial_in_flight: usize,
    /// Optional cap on the rate blobs are requested at, in bit/s of body bytes.
    pub bandwidth_cap_bit_s: Option<f64>,
    /// A request (or connection) that makes no progress for this long fails.
    pub request_timeout: Duration,
    /// A request whose whole response has not arrived this long after it was written
    /// fails with [`FetchError::Deadline`], even if bytes keep coming: the progress
    /// timeout alone never ends a server that trickles a byte every 50 ms. It is a
    /// failed attempt like any timeout (counted in [`ErrorCounts::timeout`], retried,
    /// then reported). Default 30 s: a 64-deep pipeline of 512-byte answers takes 0.07 s
    /// at 4 Mbit/s, so only a broken server or link gets near it.
    pub request_deadline: Duration,
    /// Transient failures in a row before a key is reported [`Fetched::Failed`].
    pub max_attempts: u32,
    /// Backoff before the third attempt (the second is immediate); doubles each time.
    pub retry_backoff: Duration,
    /// Longest backoff.
    pub max_backoff: Duration,
    /// Byte budget of the decoded-value cache (by [`Weigh::weight_bytes`]).
    pub cache_bytes: usize,
    /// Response size limits (pipelined transport).
    pub limits: http1::Limits,
}

impl FetchConfig {
    /// Defaults: pipelined, 2 connections, depth 64, at most 256 in flight (the bandwidth
    /// window usually allows fewer), 10 s progress timeout, 30 s deadline per request,
    /// 4 attempts, 64 MiB cache.
    ///
    /// Blobs are small (hundreds of bytes), so a 4 Mbit/s, 100 ms link holds about a
    /// hundred answers in flight: depth and in-flight limits are set well above that.
    pub fn new(remote: Remote) -> Self {
        FetchConfig {
            remote,
            transport: Transport::Pipelined,
            connections: 2,
            pipeline_depth: 64,
            max_in_flight: 256,
            initial_in_flight: 8,
            bandwidth_cap_bit_s: None,
            request_timeout: Duration::from_secs(10),
            request_deadline: DEFAULT_REQUEST_DEADLINE,
            max_attempts: 4,
            retry_backoff: Duration::from_millis(50),
            max_backoff: Duration::from_secs(2),
            cache_bytes: 64 << 20,
            limits: http1::Limits::default(),
        }
    }
}

/// Errors counted by class.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ErrorCounts {
    /// 4xx answers.
    pub client_status: u64,
    /// 5xx (and other unexpected) answers.
    pub server_status: u64,
    /// Connection failures, resets and truncated responses.
    pub connection: u64,
    /// Malformed responses.
    pub protocol: u64,
    /// Timeouts.
    pub timeout: u64,
    /// Decode errors.
    pub decode: u64,
    /// TLS handshake and certificate failures.
    pub tls: u64,
}

impl ErrorCounts {
    /// Counts one error.
    pub fn count(&mut self, e: &FetchError) {
        match e.kind() {
            ErrorKind::ClientStatus => self.client_status += 1,
            ErrorKind::ServerStatus => self.server_status += 1,
            ErrorKind::Connection => self.connection += 1,
            ErrorKind::Protocol => self.protocol += 1,
            ErrorKind::Timeout => self.timeout += 1,
            ErrorKind::Decode => self.decode += 1,
            ErrorKind::Tls => self.tls += 1,
            ErrorKind::Other => {}
        }
    }

    /// Adds another set of counts.
    pub fn add(&mut self, o: &ErrorCounts) {
        self.client_status += o.client_status;
        self.server_status += o.server_status;
        self.connection += o.connection;
        self.protocol += o.protocol;
        self.timeout += o.timeout;
        self.decode += o.decode;
        self.tls += o.tls;
    }

    /// All errors.
    pub fn total(&self) -> u64 {
        self.client_status
            + self.server_status
            + self.connection
            + self.protocol
            + self.timeout
            + self.decode
            + self.tls
    }
}

/// A snapshot of the network thread's counters.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FetchStats {
    /// Requests written (including retries).
    pub requests: u64,
    /// Answers received with status 200 (leaves included).
    pub responses: u64,
    /// Body bytes of 200 answers.
    pub bytes_fetched: u64,
    /// Keys answered with an empty body.
    pub leaves: u64,
    /// Keys whose values came inside another key's answer.
    pub carried: u64,
    /// Wants answered from the cache or the leaf set, without a request.
    pub cache_hits: u64,
    /// Requests outstanding now.
    pub in_flight: usize,
    /// Wanted keys not yet requested.
    pub queued: usize,
    /// Requests the bandwidth estimate allows outstanding now.
    pub window: usize,
    /// Estimated delivered rate (body bytes), bit/s; 0 before the first estimate.
    pub bandwidth_bit_s: f64,
    /// Estimated round trip (the least request latency seen).
    pub rtt: Option<Duration>,
    /// Smoothed latency of recent answers (EWMA): the RTT plus transfer and queueing
    /// time. Well above [`FetchStats::rtt`], answers queue on the link.
    pub latency: Option<Duration>,
    /// Mean body size of fetched blobs (EWMA), bytes.
    pub mean_blob_bytes: f64,
    /// Errors by class (each failed attempt counts).
    pub errors: ErrorCounts,
}

impl FetchStats {
    /// Adds the counters of another network thread (a second layer's): counts, bytes,
    /// windows and rates add up; the round trip is the least; the mean blob size is
    /// weighted by responses.
    pub fn add(&mut self, o: &FetchStats) {
        let responses = self.responses + o.responses;
        if responses > 0 {
            self.mean_blob_bytes = (self.mean_blob_bytes * self.responses as f64
                + o.mean_blob_bytes * o.responses as f64)
                / responses as f64;
        }
        self.requests += o.requests;
        self.responses = responses;
        self.bytes_fetched += o.bytes_fetched;
        self.leaves += o.leaves;
        self.carried += o.carried;
        self.cache_hits += o.cache_hits;
        self.in_flight += o.in_flight;
        self.queued += o.queued;
        self.window += o.window;
        self.bandwidth_bit_s += o.bandwidth_bit_s;
        self.rtt = match (self.rtt, o.rtt) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        // The slower layer's: a queue on either link shows.
        self.latency = self.latency.max(o.latency);
        self.errors.add(&o.errors);
    }
}

/// Locks a mutex, ignoring poisoning: the data guarded here stays consistent even if a
/// holder panicked (every update is a single assignment or a cache operation).
pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}
