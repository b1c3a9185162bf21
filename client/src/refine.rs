//! Refinement: the core's ([`quincunx_client_core::refine`], re-exported whole) and the
//! system clock a native frame loop reads it with.

use std::time::Duration;

pub use quincunx_client_core::refine::*;

/// The real clock: time since the instant it holds.
#[derive(Clone, Copy, Debug)]
pub struct SystemClock(pub std::time::Instant);

impl Clock for SystemClock {
    fn now(&self) -> Duration {
        self.0.elapsed()
    }
}
