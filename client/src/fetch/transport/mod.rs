//! The transports behind one interface: requests go in with a key and a path, completions
//! come back on a channel with the slot they used.

#[cfg(feature = "object-store")]
pub(crate) mod object_store;
mod pipelined;
mod reqwest_client;

use bytes::Bytes;
use tokio::sync::mpsc::UnboundedSender;

use super::{FetchConfig, FetchError, Key, Transport};

/// What a range answer says about itself.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct RangeMeta {
    /// `Content-Range`: first, last, total (see [`super::http1::Response::content_range`]).
    pub content_range: Option<[u64; 3]>,
    /// `ETag`.
    pub etag: Option<String>,
}

/// Requests in flight against a fixed number of slots (one driver's window).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Slots {
    max: usize,
    used: usize,
}

impl Slots {
    /// `max` slots (at least one).
    pub fn new(max: usize) -> Slots {
        Slots {
            max: max.max(1),
            used: 0,
        }
    }

    pub fn free(&self) -> usize {
        self.max.saturating_sub(self.used)
    }

    /// Takes a slot; false when all are taken.
    pub fn take(&mut self) -> bool {
        if self.used >= self.max {
            return false;
        }
        self.used += 1;
        true
    }

    /// Gives back a slot a request took.
    pub fn release(&mut self) {
        self.used = self.used.saturating_sub(1);
    }
}

/// One GET to make.
#[derive(Clone, Debug)]
pub(crate) struct Request {
    pub key: Key,
    /// Names a range request (0 for a blob or package URL).
    pub tag: u64,
    /// Absolute path (with the endpoint's prefix).
    pub path: String,
    /// More header lines, each ending in CR LF (a `Range` and an `If-Match`), or empty.
    pub headers: String,
}

impl Request {
    /// A GET of a blob or package URL.
    pub fn get(key: Key, path: String) -> Request {
        Request {
            key,
            tag: 0,
            path,
            headers: String::new(),
        }
    }
}

/// How a request ended.
#[derive(Debug)]
pub(crate) struct Completion {
    pub key: Key,
    /// The request's tag.
    pub tag: u64,
    /// `Content-Range` (first, last, total) and `ETag`, read for requests with extra
    /// headers only.
    pub range: Option<RangeMeta>,
    /// The slot (pipelined: connection index) that carried it; freed by
    /// [`Driver::finished`].
    pub slot: usize,
    /// Status and body, or why there is none.
    pub result: Result<(u16, Bytes), FetchError>,
}

/// A transport driving its connections on the current tokio runtime.
pub(crate) enum Driver {
    Pipelined(pipelined::Pipelined),
    Reqwest(reqwest_client::ReqwestDriver),
    /// A repository file in a bucket, whatever [`Transport`] says.
    #[cfg(feature = "object-store")]
    ObjectStore(self::object_store::ObjectStoreDriver),
}

impl Driver {
    /// Starts the transport's tasks; call within the fetch runtime's context.
    pub fn new(
        config: &FetchConfig,
        done: UnboundedSender<Completion>,
    ) -> Result<Driver, FetchError> {
        #[cfg(feature = "object-store")]
        if let Some(source) = config.remote.pack.as_ref().and_then(|p| p.object.as_ref()) {
            let driver = self::object_store::ObjectStoreDriver::new(config, source, done)?;
            return Ok(Driver::ObjectStore(driver));
        }
        Ok(match config.transport {
            Transport::Pipelined => Driver::Pipelined(pipelined::Pipelined::new(config, done)),
            Transport::Plain | Transport::H2 => {
                Driver::Reqwest(reqwest_client::ReqwestDriver::new(config, done)?)
            }
        })
    }

    /// Requests that can be sent now.
    pub fn free_slots(&self) -> usize {
        match self {
            Driver::Pipelined(p) => p.free_slots(),
            Driver::Reqwest(r) => r.free_slots(),
            #[cfg(feature = "object-store")]
            Driver::ObjectStore(o) => o.free_slots(),
        }
    }

    /// Sends `request` on a free slot; `false` (and nothing sent) if there is none.
    pub fn send(&mut self, request: Request) -> bool {
        match self {
            Driver::Pipelined(p) => p.send(request),
            Driver::Reqwest(r) => r.send(request),
            #[cfg(feature = "object-store")]
            Driver::ObjectStore(o) => o.send(request),
        }
    }

    /// Frees the slot of a completion.
    pub fn finished(&mut self, slot: usize) {
        match self {
            Driver::Pipelined(p) => p.finished(slot),
            Driver::Reqwest(r) => r.finished(),
            #[cfg(feature = "object-store")]
            Driver::ObjectStore(o) => o.finished(),
        }
    }
}
