//! The transports behind one interface: requests go in with a key and a path, completions
//! come back on a channel with the slot they used.

mod pipelined;
mod reqwest_client;

use bytes::Bytes;
use tokio::sync::mpsc::UnboundedSender;

use super::{FetchConfig, FetchError, Key, Transport};

/// One GET to make.
#[derive(Clone, Debug)]
pub(crate) struct Request {
    pub key: Key,
    /// Absolute path (with the endpoint's prefix).
    pub path: String,
}

/// How a request ended.
#[derive(Debug)]
pub(crate) struct Completion {
    pub key: Key,
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
}

impl Driver {
    /// Starts the transport's tasks; call within the fetch runtime's context.
    pub fn new(
        config: &FetchConfig,
        done: UnboundedSender<Completion>,
    ) -> Result<Driver, FetchError> {
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
        }
    }

    /// Sends `request` on a free slot; `false` (and nothing sent) if there is none.
    pub fn send(&mut self, request: Request) -> bool {
        match self {
            Driver::Pipelined(p) => p.send(request),
            Driver::Reqwest(r) => r.send(request),
        }
    }

    /// Frees the slot of a completion.
    pub fn finished(&mut self, slot: usize) {
        match self {
            Driver::Pipelined(p) => p.finished(slot),
            Driver::Reqwest(r) => r.finished(),
        }
    }
}
