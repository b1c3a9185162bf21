//! What the data access layer decides without doing any I/O: blob keys, why a fetch
//! failed, the decoded-value cache and the request schedule. The network thread that acts
//! on them is the native client's (`quincunx_client::fetch`).

pub mod bandwidth;
pub mod cache;
pub mod planner;
pub mod range_answer;
pub mod ranges;
pub mod schedule;

use std::time::Duration;

use bytes::Bytes;
use quincunx_decoder::incremental::Details;

/// A blob key: the diamond's centre. Planar ids use `[x, y, 0]`.
pub type Key = [i64; 3];

/// Why a key (or the set-up) failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FetchError {
    /// The server answered with a status other than 200.
    #[error("HTTP status {0}")]
    Status(u16),
    /// Connecting, writing or reading failed, or the server closed the connection early
    /// (including truncated bodies).
    #[error("connection: {0}")]
    Connection(String),
    /// The response could not be parsed or broke a limit.
    #[error("malformed response: {0}")]
    Protocol(String),
    /// No progress within the request timeout.
    #[error("no response within {0:?}")]
    Timeout(Duration),
    /// The response did not complete within the request deadline, however steadily its
    /// bytes came (a server trickling a byte at a time). Counted as a timeout.
    #[error("no complete response within the {0:?} request deadline")]
    Deadline(Duration),
    /// The decode function refused the blob.
    #[error("decode: {0}")]
    Decode(String),
    /// The TLS handshake failed: the certificate was refused (the message names the
    /// cause: unknown issuer, wrong host name, expired) or the server does not speak TLS.
    /// Permanent: retrying cannot fix a certificate.
    #[error("{0}")]
    Tls(String),
    /// The base URL is not `http://` or `https://host[:port][/prefix]`.
    #[error("bad URL: {0}")]
    BadUrl(String),
    /// The repository's metadata could not be used.
    #[error("metadata: {0}")]
    Metadata(String),
    /// The network thread could not start or has stopped.
    #[error("fetch thread: {0}")]
    Thread(String),
    /// The repository file read with range requests is not the one opened (another
    /// `ETag` or length, a 412 or 416): permanent, never a mix of two builds.
    #[error("{0}")]
    Changed(String),
}

/// Coarse classes of [`FetchError`], for counting.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// 4xx status (permanent).
    ClientStatus,
    /// 5xx or any other non-200 status (transient).
    ServerStatus,
    /// Connection refused, reset or closed early (transient).
    Connection,
    /// Malformed response (transient: a new connection may do better).
    Protocol,
    /// Request timeout or deadline (transient).
    Timeout,
    /// Decode error (permanent).
    Decode,
    /// TLS handshake or certificate failure (permanent).
    Tls,
    /// Set-up errors.
    Other,
}

impl FetchError {
    /// The error's class.
    pub fn kind(&self) -> ErrorKind {
        match self {
            FetchError::Status(s) if (400..500).contains(s) && *s != 408 && *s != 429 => {
                ErrorKind::ClientStatus
            }
            FetchError::Status(_) => ErrorKind::ServerStatus,
            FetchError::Changed(_) => ErrorKind::ClientStatus,
            FetchError::Connection(_) => ErrorKind::Connection,
            FetchError::Protocol(_) => ErrorKind::Protocol,
            FetchError::Timeout(_) | FetchError::Deadline(_) => ErrorKind::Timeout,
            FetchError::Decode(_) => ErrorKind::Decode,
            FetchError::Tls(_) => ErrorKind::Tls,
            FetchError::BadUrl(_) | FetchError::Metadata(_) | FetchError::Thread(_) => {
                ErrorKind::Other
            }
        }
    }

    /// Whether retrying (on a new connection, after a backoff) may succeed.
    pub fn is_transient(&self) -> bool {
        matches!(
            self.kind(),
            ErrorKind::ServerStatus
                | ErrorKind::Connection
                | ErrorKind::Protocol
                | ErrorKind::Timeout
        )
    }
}

/// Memory a decoded value holds, for the cache's byte budget.
pub trait Weigh {
    /// Approximate heap plus inline size in bytes.
    fn weight_bytes(&self) -> usize;
}

impl<E> Weigh for Vec<E> {
    fn weight_bytes(&self) -> usize {
        std::mem::size_of::<Self>() + self.capacity() * std::mem::size_of::<E>()
    }
}

impl Weigh for Bytes {
    fn weight_bytes(&self) -> usize {
        std::mem::size_of::<Self>() + self.len()
    }
}

/// A decoded blob's details.
impl<I: Send + Sync + 'static> Weigh for Details<I> {
    fn weight_bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + self.h.capacity() * std::mem::size_of::<i32>()
            + self.child_classes.capacity() * std::mem::size_of::<(I, u8)>()
            + self.empty_children.capacity() * std::mem::size_of::<I>()
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
    /// Body bytes of 200 answers (and 206 answers of range reads).
    pub bytes_fetched: u64,
    /// Of them, what was not a blob or package: opening a repository file and reading
    /// its directories, the gaps and checksums between coalesced blobs (range reads;
    /// 0 from a server).
    pub overhead_bytes: u64,
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
        self.overhead_bytes += o.overhead_bytes;
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
