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
//! Inside the thread, every decision is the core's [`planner::Planner`] (no I/O; time is
//! passed in as a `Duration` since the thread started):
//! - a [`schedule::Scheduler`]: the wanted keys in priority order, what is in flight, and
//!   per-key retry backoff after transient failures;
//! - a [`bandwidth::Bandwidth`] estimator: EWMA of the delivered rate and of the blob size,
//!   and a minimum-latency RTT estimate. The number of requests outstanding is held to what
//!   can arrive within about one RTT plus one frame at the estimated rate, so the queue
//!   stays in the client, where priorities can still change.
//!
//! The thread adds the clock, a [`cache::DecodedCache`] of decoded values (LRU, byte
//! budget) and the set of known leaves, shared with the frame loop and consulted before
//! anything is requested, the decode function, and a [`Transport`]: pipelined HTTP/1.1
//! over K persistent connections ([`http1`], our own strict parser), plain HTTP/1.1 over K
//! connections, or HTTP/2 over one connection; each speaks TLS for `https://` URLs
//! ([`tls`]).
//!
//! [`link`] is an emulated narrow, high-latency link (an in-process throttling TCP proxy)
//! for tests and measurements.

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
pub use quincunx_client_core::fetch::{
    ErrorCounts, ErrorKind, FetchError, FetchStats, Key, Weigh, bandwidth, cache, planner, ranges,
    schedule,
};
pub use remote::{PackFile, Remote};
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
    /// How blob ranges are merged into requests when reading a repository file
    /// ([`Remote::pack`]).
    pub ranges: ranges::RangeConfig,
}

impl FetchConfig {
    /// Defaults: pipelined, 2 connections, depth 64, at most 256 in flight (the bandwidth
    /// window usually allows fewer), 10 s progress timeout, 30 s deadline per request,
    /// 4 attempts, 64 MiB cache.
    ///
    /// Blobs are small (hundreds of bytes), so a 4 Mbit/s, 100 ms link holds about a
    /// hundred answers in flight: depth and in-flight limits are set well above that.
    pub fn new(remote: Remote) -> Self {
        let planned = planner::PlannerConfig::default();
        FetchConfig {
            remote,
            transport: Transport::Pipelined,
            connections: 2,
            pipeline_depth: 64,
            max_in_flight: planned.max_in_flight,
            initial_in_flight: planned.initial_in_flight,
            bandwidth_cap_bit_s: planned.bandwidth_cap_bit_s,
            request_timeout: Duration::from_secs(10),
            request_deadline: DEFAULT_REQUEST_DEADLINE,
            max_attempts: planned.max_attempts,
            retry_backoff: planned.retry_backoff,
            max_backoff: planned.max_backoff,
            cache_bytes: 64 << 20,
            limits: http1::Limits::default(),
            ranges: ranges::RangeConfig::default(),
        }
    }

    /// The settings the core's [`planner::Planner`] decides with.
    pub fn planner(&self) -> planner::PlannerConfig {
        planner::PlannerConfig {
            initial_in_flight: self.initial_in_flight,
            max_in_flight: self.max_in_flight,
            bandwidth_cap_bit_s: self.bandwidth_cap_bit_s,
            max_attempts: self.max_attempts,
            retry_backoff: self.retry_backoff,
            max_backoff: self.max_backoff,
            static_export: self.remote.static_export,
        }
    }
}

/// Locks a mutex, ignoring poisoning: the data guarded here stays consistent even if a
/// holder panicked (every update is a single assignment or a cache operation).
pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}
