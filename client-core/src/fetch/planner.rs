//! The data access layer's decisions, without the network: which keys to request and how
//! many at once (the bandwidth window), under which cap, whether as packages, and what
//! each answer means (a leaf, a body to decode, a retry after a backoff, a failure to
//! report). Time and answers go in; requests and what to deliver come out. The native
//! network thread (`quincunx_client::fetch::Fetcher`) drives it with its transports and
//! the system clock; anything else that can send requests and read a clock can too.
//!
//! One request's life: [`Planner::plan`] picks it, the caller sends it and says so
//! ([`Planner::sent`], or [`Planner::unsent`] if the transport refused it), and its answer
//! goes to [`Planner::complete`]. A body is decoded by the caller; what it carried goes to
//! [`Planner::carried`], a refusal to [`Planner::decode_failed`].

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;

use super::bandwidth::{Bandwidth, Cap};
use super::cache::DecodedCache;
use super::schedule::{Backoff, Class, Scheduler};
use super::{FetchError, FetchStats, Key, Weigh};

/// The settings the decisions follow (the native client's `FetchConfig` holds them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlannerConfig {
    /// Requests outstanding before there is a bandwidth estimate.
    pub initial_in_flight: usize,
    /// Most requests outstanding.
    pub max_in_flight: usize,
    /// Bandwidth cap (bit/s) on requested bytes, if any.
    pub bandwidth_cap_bit_s: Option<f64>,
    /// Attempts before a transient failure is reported.
    pub max_attempts: u32,
    /// Backoff before the third attempt; doubles after each failure.
    pub retry_backoff: Duration,
    /// Longest backoff (and how long a permanent failure is held).
    pub max_backoff: Duration,
    /// A static export: a 404 is a leaf (no file for an empty blob).
    pub static_export: bool,
}

impl Default for PlannerConfig {
    /// The native client's defaults (`FetchConfig::new`): 8 requests before a bandwidth
    /// estimate, at most 256, four attempts, backoff from 50 ms to 2 s.
    fn default() -> Self {
        PlannerConfig {
            initial_in_flight: 8,
            max_in_flight: 256,
            bandwidth_cap_bit_s: None,
            max_attempts: 4,
            retry_backoff: Duration::from_millis(50),
            max_backoff: Duration::from_secs(2),
            static_export: false,
        }
    }
}

/// A request to send.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Planned {
    /// The key.
    pub key: Key,
    /// Ask for it as a package (its answer carries small owned children).
    pub packaged: bool,
}

/// What an answer asks of the caller.
#[derive(Debug)]
pub enum Answer {
    /// Not a request in flight (a late answer to a key already settled): nothing to do.
    Stale,
    /// The key is a leaf (an empty body, or a static export's 404): remember it, and tell
    /// the frame loop if `report`.
    Leaf {
        /// The frame loop still wants it.
        report: bool,
    },
    /// A body to decode; then [`Planner::carried`] for each value it carried, or
    /// [`Planner::decode_failed`].
    Body {
        /// The answer's body.
        body: Bytes,
        /// It was asked for as a package.
        packaged: bool,
        /// The frame loop still wants it.
        report: bool,
    },
    /// The attempt failed: `Some` is a failure to report to the frame loop (permanent, or
    /// transient too many times); `None`, a retry after a backoff or a key no longer wanted.
    Failed(Option<FetchError>),
}

/// The decisions of one network thread (one repository).
///
/// Invariants: a key is in flight at most once; a key is requested only while wanted
/// and not backing off; the cap's bucket is charged for exactly the requests in flight.
#[derive(Debug)]
pub struct Planner {
    config: PlannerConfig,
    sched: Scheduler,
    bandwidth: Bandwidth,
    cap: Option<Cap>,
    /// Bytes taken from the cap's bucket per request in flight, settled on completion.
    charged: HashMap<Key, f64>,
    stats: FetchStats,
    /// Priority from which keys are asked for as packages (latest submit).
    package_above: Option<f32>,
    /// Keys in flight asked for as packages.
    packaged: HashSet<Key>,
}

impl Planner {
    /// Nothing wanted yet; `now` starts the cap's bucket.
    pub fn new(config: PlannerConfig, now: Duration) -> Self {
        Planner {
            cap: config.bandwidth_cap_bit_s.map(|c| Cap::new(c, now)),
            config,
            sched: Scheduler::new(),
            bandwidth: Bandwidth::new(),
            charged: HashMap::new(),
            stats: FetchStats::default(),
            package_above: None,
            packaged: HashSet::new(),
        }
    }

    /// A frame's wants (and predicted keys), replacing the last frame's; keys from
    /// priority `package_above` up are asked for as packages.
    pub fn submit(
        &mut self,
        wants: &[(Key, f32)],
        prefetch: &[(Key, f32)],
        package_above: Option<f32>,
        now: Duration,
    ) {
        self.package_above = package_above;
        self.bandwidth.on_submit(now);
        self.sched.set_wants(wants, prefetch, now);
    }

    /// The most urgent keys the window, the cap and `free_slots` (what the transport can
    /// take) allow now, leaving out keys for which `skip` is true (cached, known leaves).
    /// Each is charged to the cap: report each as [`Planner::sent`] or [`Planner::unsent`].
    pub fn plan(
        &mut self,
        now: Duration,
        free_slots: usize,
        skip: impl FnMut(Key) -> bool,
    ) -> Vec<Planned> {
        self.bandwidth.advance(now, self.sched.in_flight());
        let window = self.bandwidth.window(
            self.config.initial_in_flight,
            self.config.max_in_flight,
            self.config.bandwidth_cap_bit_s,
        );
        self.stats.window = window;
        let room = window
            .saturating_sub(self.sched.in_flight())
            .min(free_slots);
        if room == 0 {
            return Vec::new();
        }
        let keys = self.sched.next(now, room, skip);
        let expected = self.bandwidth.mean_bytes().max(1.0);
        let mut planned = Vec::with_capacity(keys.len());
        for key in keys {
            if let Some(cap) = &mut self.cap {
                if !cap.try_take(now, expected) {
                    break;
                }
                self.charged.insert(key, expected);
            }
            let packaged = self
                .package_above
                .is_some_and(|t| self.sched.priority(key).is_some_and(|p| p >= t));
            planned.push(Planned { key, packaged });
        }
        planned
    }

    /// A planned request was sent at `now`.
    pub fn sent(&mut self, request: Planned, now: Duration) {
        if request.packaged {
            self.packaged.insert(request.key);
        }
        self.sched.issued(request.key, now);
        self.stats.requests += 1;
    }

    /// A planned key was handed to a transport that counts its own requests (a range
    /// reader: one request carries many keys, a leaf none): in flight, not counted, and
    /// answered as [`Planned::packaged`] says, like [`Planner::sent`].
    pub fn sent_uncounted(&mut self, request: Planned, now: Duration) {
        if request.packaged {
            self.packaged.insert(request.key);
        }
        self.sched.issued(request.key, now);
    }

    /// Requests and body bytes a transport spent besides keys' bodies (a range reader's:
    /// directories, gaps between blobs, checksums; opening the file).
    pub fn spent(&mut self, requests: u64, bytes: u64) {
        self.stats.requests += requests;
        self.stats.bytes_fetched += bytes;
        self.stats.overhead_bytes += bytes;
    }

    /// `key` (in flight) turned out to have no blob without any answer from the network
    /// (a range reader's directory does not list it): a leaf, no latency measured.
    pub fn leaf_known(&mut self, key: Key, now: Duration) -> Answer {
        self.packaged.remove(&key);
        let Some((_, issued_as)) = self.sched.finished(key, now) else {
            return Answer::Stale;
        };
        if let (Some(cap), Some(charged)) = (&mut self.cap, self.charged.remove(&key)) {
            cap.correct(charged, 0.0);
        }
        let report = issued_as == Class::Want || self.sched.class(key) == Some(Class::Want);
        self.sched.succeeded(key);
        self.sched.unwant(key);
        self.stats.leaves += 1;
        Answer::Leaf { report }
    }

    /// A planned request was not sent (the transport refused it): its charge is returned.
    pub fn unsent(&mut self, key: Key) {
        if let (Some(cap), Some(charged)) = (&mut self.cap, self.charged.remove(&key)) {
            cap.correct(charged, 0.0);
        }
    }

    /// The answer to `key` at `now`: a status and body, or why there is none.
    pub fn complete(
        &mut self,
        key: Key,
        result: Result<(u16, Bytes), FetchError>,
        now: Duration,
    ) -> Answer {
        let in_flight_before = self.sched.in_flight();
        let packaged = self.packaged.remove(&key);
        let Some((latency, issued_as)) = self.sched.finished(key, now) else {
            return Answer::Stale;
        };
        if let (Some(cap), Some(charged)) = (&mut self.cap, self.charged.remove(&key)) {
            let actual = match &result {
                Ok((_, body)) => body.len() as f64,
                Err(_) => 0.0,
            };
            cap.correct(charged, actual);
        }
        // Report to the frame loop what it asked for (not prefetches it no longer wants).
        let report = issued_as == Class::Want || self.sched.class(key) == Some(Class::Want);
        let answer = match result {
            Ok((200, body)) => Ok(body),
            Ok((404, _)) if self.config.static_export => Ok(Bytes::new()),
            Ok((status, _)) => Err(FetchError::Status(status)),
            Err(e) => Err(e),
        };
        let body = match answer {
            Ok(body) => body,
            Err(error) => {
                self.bandwidth.advance(now, in_flight_before);
                return Answer::Failed(self.fail(key, error, now, report));
            }
        };
        let len = body.len();
        self.stats.responses += 1;
        self.stats.bytes_fetched += len as u64;
        self.bandwidth.on_answer(len, Some(latency));
        self.sched.succeeded(key);
        self.sched.unwant(key);
        self.bandwidth.advance(now, in_flight_before);
        if body.is_empty() {
            self.stats.leaves += 1;
            return Answer::Leaf { report };
        }
        Answer::Body {
            body,
            packaged,
            report,
        }
    }

    /// A decoded answer carried `key`'s value: it is no longer wanted from the network.
    /// Returns whether the frame loop wanted it (deliver it then).
    pub fn carried(&mut self, key: Key) -> bool {
        self.stats.carried += 1;
        let wanted = self.sched.class(key) == Some(Class::Want);
        self.sched.unwant(key);
        wanted
    }

    /// Caches what decoding `key`'s body gave: the values it carried first (so that once
    /// `key` is cached, so is everything it carried), then its own; each goes to
    /// `deliver` when the frame loop wants it (`report`: as [`Answer::Body`] said).
    pub fn store_decoded<T: Weigh>(
        &mut self,
        cache: &mut DecodedCache<T>,
        key: Key,
        value: T,
        carried: Vec<(Key, T)>,
        report: bool,
        mut deliver: impl FnMut(Key, Arc<T>),
    ) {
        for (k, v) in carried {
            let wanted = self.carried(k);
            let v = Arc::new(v);
            cache.insert(k, Arc::clone(&v));
            if wanted {
                deliver(k, v);
            }
        }
        let value = Arc::new(value);
        cache.insert(key, Arc::clone(&value));
        if report {
            deliver(key, value);
        }
    }

    /// The decoder refused `key`'s body (`report`: as [`Answer::Body`] said): the failure
    /// to report, if any (decode errors are permanent).
    pub fn decode_failed(
        &mut self,
        key: Key,
        reason: String,
        now: Duration,
        report: bool,
    ) -> Option<FetchError> {
        self.fail(key, FetchError::Decode(reason), now, report)
    }

    /// A failed attempt: retried after a backoff if transient; given up (and returned for
    /// reporting, if `report`) if permanent or after `max_attempts` failures in a row.
    fn fail(
        &mut self,
        key: Key,
        error: FetchError,
        now: Duration,
        report: bool,
    ) -> Option<FetchError> {
        self.stats.errors.count(&error);
        let backoff = Backoff {
            base: self.config.retry_backoff,
            max: self.config.max_backoff,
        };
        let give_up = if error.is_transient() {
            let failures = self.sched.failed(key, now, backoff);
            tracing::debug!(?key, failures, %error, "transient failure");
            failures >= self.config.max_attempts
        } else {
            tracing::debug!(?key, %error, "permanent failure");
            self.sched.hold(key, now, backoff.max);
            true
        };
        if !give_up {
            return None;
        }
        self.sched.unwant(key);
        report.then_some(error)
    }

    /// When something may be requested again without a new submit or answer: the
    /// earliest end of a backoff, or of the cap's debt.
    pub fn wake_at(&self, now: Duration) -> Option<Duration> {
        [
            self.sched.next_retry(now),
            self.cap.as_ref().and_then(Cap::ready_at),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// The counters and estimates now (`cache_hits` is the caller's to count).
    pub fn stats(&mut self) -> &FetchStats {
        self.stats.in_flight = self.sched.in_flight();
        self.stats.queued = self.sched.queued();
        self.stats.bandwidth_bit_s = self.bandwidth.rate_bit_s();
        self.stats.rtt = self.bandwidth.rtt();
        self.stats.latency = self.bandwidth.latency();
        self.stats.mean_blob_bytes = self.bandwidth.mean_bytes();
        &self.stats
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn config() -> PlannerConfig {
        PlannerConfig {
            initial_in_flight: 2,
            max_in_flight: 16,
            bandwidth_cap_bit_s: None,
            max_attempts: 2,
            retry_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(1),
            static_export: false,
        }
    }

    fn at(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    fn keys(p: &[Planned]) -> Vec<Key> {
        p.iter().map(|r| r.key).collect()
    }

    #[test]
    fn the_window_and_the_transport_bound_what_is_planned_most_urgent_first() {
        let mut p = Planner::new(config(), at(0));
        let wants = [([1, 0, 0], 1.0), ([2, 0, 0], 3.0), ([3, 0, 0], 2.0)];
        p.submit(&wants, &[], None, at(0));
        // Two before any estimate, the most urgent first; one when the transport has one.
        assert_eq!(keys(&p.plan(at(0), 1, |_| false)), vec![[2, 0, 0]]);
        let planned = p.plan(at(0), 8, |_| false);
        assert_eq!(keys(&planned), vec![[2, 0, 0], [3, 0, 0]]);
        for r in planned {
            p.sent(r, at(0));
        }
        // The window is full: nothing more until an answer.
        assert!(p.plan(at(1), 8, |_| false).is_empty());
        let body = Bytes::from_static(b"blob");
        match p.complete([2, 0, 0], Ok((200, body.clone())), at(50)) {
            Answer::Body {
                body: b, report, ..
            } => assert!(report && b == body),
            other => panic!("{other:?}"),
        }
        assert_eq!(keys(&p.plan(at(50), 8, |_| false)), vec![[1, 0, 0]]);
        // Skipped keys (cached, leaves) are never planned.
        let mut q = Planner::new(config(), at(0));
        q.submit(&wants, &[], None, at(0));
        assert_eq!(
            keys(&q.plan(at(0), 8, |k| k == [2, 0, 0])),
            vec![[3, 0, 0], [1, 0, 0]]
        );
        let stats = p.stats();
        assert_eq!(
            (stats.requests, stats.responses, stats.in_flight),
            (2, 1, 1)
        );
        assert_eq!(stats.bytes_fetched, 4);
    }

    #[test]
    fn transient_failures_retry_then_report_and_permanent_ones_report_at_once() {
        let mut p = Planner::new(config(), at(0));
        let key = [7, 0, 0];
        p.submit(&[(key, 1.0)], &[], None, at(0));
        let send = |p: &mut Planner, now| {
            let r = p.plan(now, 8, |_| false);
            assert_eq!(keys(&r), vec![key]);
            p.sent(r[0], now);
        };
        send(&mut p, at(0));
        let refused = Err(FetchError::Connection("reset".into()));
        assert!(matches!(
            p.complete(key, refused.clone(), at(10)),
            Answer::Failed(None)
        ));
        // The second attempt is immediate; its failure is the last (max_attempts 2).
        send(&mut p, at(10));
        match p.complete(key, refused, at(20)) {
            Answer::Failed(Some(FetchError::Connection(_))) => {}
            other => panic!("{other:?}"),
        }
        assert!(p.plan(at(5000), 8, |_| false).is_empty(), "given up");
        // A 404 is permanent (and a leaf only in a static export); a late answer is stale.
        let other = [8, 0, 0];
        p.submit(&[(other, 1.0)], &[], None, at(30));
        let r = p.plan(at(30), 8, |_| false);
        p.sent(r[0], at(30));
        assert!(matches!(
            p.complete(other, Ok((404, Bytes::new())), at(40)),
            Answer::Failed(Some(FetchError::Status(404)))
        ));
        assert!(matches!(
            p.complete(other, Ok((200, Bytes::new())), at(41)),
            Answer::Stale
        ));
        let mut s = Planner::new(
            PlannerConfig {
                static_export: true,
                ..config()
            },
            at(0),
        );
        s.submit(&[(other, 1.0)], &[], None, at(0));
        let r = s.plan(at(0), 8, |_| false);
        s.sent(r[0], at(0));
        assert!(matches!(
            s.complete(other, Ok((404, Bytes::new())), at(5)),
            Answer::Leaf { report: true }
        ));
        assert_eq!(s.stats().leaves, 1);
        assert_eq!(p.stats().errors.total(), 3);
    }

    #[test]
    fn a_backoff_holds_a_key_until_its_wake_time() {
        let mut p = Planner::new(
            PlannerConfig {
                max_attempts: 5,
                ..config()
            },
            at(0),
        );
        let key = [9, 0, 0];
        p.submit(&[(key, 1.0)], &[], None, at(0));
        for (attempt, now) in [(1, 0), (2, 10)] {
            let r = p.plan(at(now), 8, |_| false);
            assert_eq!(keys(&r), vec![key], "attempt {attempt}");
            p.sent(r[0], at(now));
            let failed = p.complete(key, Ok((503, Bytes::new())), at(now + 5));
            assert!(matches!(failed, Answer::Failed(None)));
        }
        // After the second failure: 100 ms of backoff, and a wake time that says so.
        assert!(p.plan(at(20), 8, |_| false).is_empty());
        assert_eq!(p.wake_at(at(20)), Some(at(115)));
        assert_eq!(keys(&p.plan(at(115), 8, |_| false)), vec![key]);
    }

    #[test]
    fn the_cap_charges_planned_requests_and_returns_unsent_ones() {
        let mut p = Planner::new(
            PlannerConfig {
                // 8 kbit/s: 1,000 B/s, a 1,500-byte bucket; answers expected at 1 byte.
                bandwidth_cap_bit_s: Some(8_000.0),
                ..config()
            },
            at(0),
        );
        let wants: Vec<(Key, f32)> = (0..4).map(|k| ([k, 0, 0], k as f32)).collect();
        p.submit(&wants, &[], None, at(0));
        let r = p.plan(at(0), 8, |_| false);
        assert_eq!(r.len(), 2);
        // The transport refuses both: the bucket is whole again, so the same two plan.
        for q in &r {
            p.unsent(q.key);
        }
        assert_eq!(p.plan(at(0), 8, |_| false), r);
        for q in r {
            p.sent(q, at(0));
        }
        // A 3,000-byte answer puts the bucket in debt: nothing until it refills.
        let first = [3, 0, 0];
        let body = Bytes::from(vec![1u8; 3000]);
        assert!(matches!(
            p.complete(first, Ok((200, body)), at(10)),
            Answer::Body { .. }
        ));
        assert!(p.plan(at(10), 8, |_| false).is_empty());
        let wake = p.wake_at(at(10)).unwrap();
        assert!(wake > at(10) && wake <= at(1600), "{wake:?}");
        assert_eq!(p.plan(wake, 8, |_| false).len(), 1);
    }

    #[test]
    fn urgent_keys_are_asked_for_as_packages_and_carried_keys_leave_the_queue() {
        let mut p = Planner::new(config(), at(0));
        p.submit(
            &[([1, 0, 0], 1.0), ([2, 0, 0], 5.0)],
            &[([3, 0, 0], 0.5)],
            Some(2.0),
            at(0),
        );
        let r = p.plan(at(0), 8, |_| false);
        assert_eq!(
            r,
            vec![
                Planned {
                    key: [2, 0, 0],
                    packaged: true
                },
                Planned {
                    key: [1, 0, 0],
                    packaged: false
                },
            ]
        );
        for q in r {
            p.sent(q, at(0));
        }
        match p.complete([2, 0, 0], Ok((200, Bytes::from_static(b"x"))), at(5)) {
            Answer::Body { packaged, .. } => assert!(packaged),
            other => panic!("{other:?}"),
        }
        // The package carried the prefetched key: not wanted by the frame loop, and
        // never requested.
        assert!(!p.carried([3, 0, 0]));
        assert!(p.plan(at(6), 8, |_| false).is_empty());
        assert_eq!(p.stats().carried, 1);
    }
}
