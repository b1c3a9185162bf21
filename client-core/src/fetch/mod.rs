//! What the data access layer decides without doing any I/O: blob keys, why a fetch
//! failed, the decoded-value cache and the request schedule. The network thread that acts
//! on them is the native client's (`quincunx_client::fetch`).

pub mod cache;
pub mod schedule;

use std::time::Duration;

use bytes::Bytes;
use quincunx_decoder::incremental::Details;

/// A blob key: the diamond's centre. Planar ids use `[x, y, 0]`.
pub type Key = [i64; 3];

/// Why a key (or the set-up) failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
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
