//! The request queue: wanted keys in priority order, what is in flight, and per-key
//! backoff after failures. Pure: time is passed in, as the time since an origin the
//! caller chooses (its start, say), so the queue runs wherever a clock can be read.

use std::collections::HashMap;
use std::time::Duration;

use super::Key;

/// Whether a key is needed for the current frame or only predicted to be.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Class {
    /// Needed now.
    Want,
    /// Predicted (camera ahead): requested only when every eligible want is in flight.
    Prefetch,
}

#[derive(Clone, Copy, Debug)]
struct Retry {
    failures: u32,
    not_before: Duration,
}

/// Backoff settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Backoff {
    /// Delay before the third attempt (the second is immediate); doubles after each failure.
    pub base: Duration,
    /// Longest delay.
    pub max: Duration,
}

impl Backoff {
    /// The delay after `failures` failures in a row.
    pub fn delay(&self, failures: u32) -> Duration {
        if failures <= 1 {
            return Duration::ZERO;
        }
        let doublings = (failures - 2).min(20);
        self.base.saturating_mul(1 << doublings).min(self.max)
    }
}

/// The wanted keys and the requests in flight.
///
/// Invariants: a key is in flight at most once; [`Scheduler::next`] never returns a key in
/// flight, backing off, or not wanted.
#[derive(Debug, Default)]
pub struct Scheduler {
    wants: HashMap<Key, (Class, f32)>,
    /// Wanted keys, most urgent first (wants before prefetches, then by priority).
    order: Vec<Key>,
    in_flight: HashMap<Key, (Duration, Class)>,
    retry: HashMap<Key, Retry>,
}

impl Scheduler {
    /// An empty queue.
    pub fn new() -> Self {
        Self::default()
    }

    /// Replaces the wanted keys. A key in both lists is a want; the last priority given to
    /// a key wins. Keys not listed are dropped from the queue (requests in flight carry on).
    pub fn set_wants(&mut self, wants: &[(Key, f32)], prefetch: &[(Key, f32)], now: Duration) {
        self.wants.clear();
        for &(k, p) in prefetch {
            self.wants.insert(k, (Class::Prefetch, p));
        }
        for &(k, p) in wants {
            self.wants.insert(k, (Class::Want, p));
        }
        self.order.clear();
        self.order.extend(self.wants.keys().copied());
        let wants = &self.wants;
        self.order.sort_unstable_by(|a, b| {
            let (ca, pa) = wants[a];
            let (cb, pb) = wants[b];
            ca.cmp(&cb).then(pb.total_cmp(&pa)).then(a.cmp(b))
        });
        // Backoff is remembered only for keys still wanted or still backing off.
        self.retry
            .retain(|k, r| wants.contains_key(k) || r.not_before > now);
    }

    /// The class of a wanted key.
    pub fn class(&self, key: Key) -> Option<Class> {
        self.wants.get(&key).map(|w| w.0)
    }

    /// The priority of a wanted key.
    pub fn priority(&self, key: Key) -> Option<f32> {
        self.wants.get(&key).map(|w| w.1)
    }

    /// Stops wanting `key` until the next [`Scheduler::set_wants`] (it was answered).
    pub fn unwant(&mut self, key: Key) {
        self.wants.remove(&key);
    }

    /// Up to `max` keys to request now, most urgent first, leaving out keys in flight,
    /// backing off, or for which `skip` is true (cached, known leaves).
    pub fn next(&self, now: Duration, max: usize, mut skip: impl FnMut(Key) -> bool) -> Vec<Key> {
        let mut out = Vec::new();
        for &k in &self.order {
            if out.len() >= max {
                break;
            }
            if !self.wants.contains_key(&k)
                || self.in_flight.contains_key(&k)
                || self.retry.get(&k).is_some_and(|r| r.not_before > now)
                || skip(k)
            {
                continue;
            }
            out.push(k);
        }
        out
    }

    /// Records that `key` was requested.
    pub fn issued(&mut self, key: Key, now: Duration) {
        let class = self.class(key).unwrap_or(Class::Want);
        self.in_flight.insert(key, (now, class));
    }

    /// Records that `key`'s request ended: its latency and the class it was issued as.
    pub fn finished(&mut self, key: Key, now: Duration) -> Option<(Duration, Class)> {
        self.in_flight
            .remove(&key)
            .map(|(at, class)| (now.saturating_sub(at), class))
    }

    /// Forgets `key`'s failures (it was answered).
    pub fn succeeded(&mut self, key: Key) {
        self.retry.remove(&key);
    }

    /// Counts a failure of `key` and schedules its next attempt; returns the failures in a
    /// row so far.
    pub fn failed(&mut self, key: Key, now: Duration, backoff: Backoff) -> u32 {
        let failures = self.retry.get(&key).map_or(0, |r| r.failures) + 1;
        let not_before = now + backoff.delay(failures);
        self.retry.insert(
            key,
            Retry {
                failures,
                not_before,
            },
        );
        failures
    }

    /// Holds `key` back for `delay` (after a permanent failure).
    pub fn hold(&mut self, key: Key, now: Duration, delay: Duration) {
        let failures = self.retry.get(&key).map_or(0, |r| r.failures);
        self.retry.insert(
            key,
            Retry {
                failures,
                not_before: now + delay,
            },
        );
    }

    /// When the earliest wanted key now backing off may be requested.
    pub fn next_retry(&self, now: Duration) -> Option<Duration> {
        self.retry
            .iter()
            .filter(|(k, r)| {
                r.not_before > now
                    && self.wants.contains_key(*k)
                    && !self.in_flight.contains_key(*k)
            })
            .map(|(_, r)| r.not_before)
            .min()
    }

    /// Requests in flight.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Whether `key` is in flight.
    pub fn is_in_flight(&self, key: Key) -> bool {
        self.in_flight.contains_key(&key)
    }

    /// Wanted keys not in flight.
    pub fn queued(&self) -> usize {
        self.wants
            .keys()
            .filter(|k| !self.in_flight.contains_key(*k))
            .count()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn k(i: i64) -> Key {
        [i, 0, 0]
    }

    const B: Backoff = Backoff {
        base: Duration::from_millis(100),
        max: Duration::from_secs(1),
    };

    #[test]
    fn keys_come_out_by_priority_and_wants_before_prefetch() {
        let now = Duration::from_secs(1000);
        let mut s = Scheduler::new();
        s.set_wants(
            &[(k(1), 1.0), (k(2), 3.0), (k(3), 2.0)],
            &[(k(9), 100.0), (k(1), 50.0)],
            now,
        );
        assert_eq!(s.next(now, 10, |_| false), vec![k(2), k(3), k(1), k(9)]);
        assert_eq!(s.next(now, 2, |_| false), vec![k(2), k(3)]);
        assert_eq!(s.next(now, 10, |x| x == k(3)), vec![k(2), k(1), k(9)]);
    }

    #[test]
    fn in_flight_keys_are_not_issued_twice_and_dropped_wants_are_not_issued() {
        let now = Duration::from_secs(1000);
        let mut s = Scheduler::new();
        s.set_wants(&[(k(1), 1.0), (k(2), 2.0)], &[], now);
        s.issued(k(2), now);
        assert_eq!(s.next(now, 10, |_| false), vec![k(1)]);
        s.set_wants(&[(k(2), 2.0)], &[], now);
        assert!(s.next(now, 10, |_| false).is_empty());
        assert_eq!(s.queued(), 0);
        let later = now + Duration::from_millis(30);
        assert_eq!(
            s.finished(k(2), later),
            Some((Duration::from_millis(30), Class::Want))
        );
        assert_eq!(s.next(later, 10, |_| false), vec![k(2)]);
        s.unwant(k(2));
        assert!(s.next(later, 10, |_| false).is_empty());
    }

    #[test]
    fn failures_back_off_exponentially_up_to_the_cap() {
        let now = Duration::from_secs(1000);
        let mut s = Scheduler::new();
        s.set_wants(&[(k(1), 1.0)], &[], now);
        assert_eq!(s.failed(k(1), now, B), 1);
        assert_eq!(
            s.next(now, 1, |_| false),
            vec![k(1)],
            "the first retry is immediate"
        );
        assert_eq!(s.failed(k(1), now, B), 2);
        assert!(s.next(now, 1, |_| false).is_empty());
        assert_eq!(s.next_retry(now), Some(now + Duration::from_millis(100)));
        assert_eq!(
            s.next(now + Duration::from_millis(100), 1, |_| false),
            vec![k(1)]
        );
        let delays: Vec<_> = (1..8).map(|f| B.delay(f).as_millis()).collect();
        assert_eq!(delays, vec![0, 100, 200, 400, 800, 1000, 1000]);
        s.succeeded(k(1));
        assert_eq!(s.failed(k(1), now, B), 1);
    }
}
