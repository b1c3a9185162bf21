//! Bandwidth estimation and the request allowance. Pure: time is passed in, as the time
//! since an origin the caller picks.
//!
//! The delivered rates (body bytes, and answers) are measured over *busy* time only (while
//! at least one request is outstanding), so an idle client does not read as a slow link.
//! The number of requests kept outstanding is the number of answers that arrive within one
//! RTT plus one frame at the estimated answer rate, times a small gain that lets the
//! estimate grow when the link is not yet full (each round trip the window can roughly
//! double, as in TCP slow start, until the link's queue starts to add latency). Counting
//! answers rather than body bytes keeps the window right when most answers are empty
//! leaves, which cost a round of headers but carry no body. Everything beyond the window
//! waits in the client's queue, where priorities can still change.

use std::time::Duration;

/// Busy time per rate sample.
const SAMPLE: Duration = Duration::from_millis(100);
/// EWMA weight of a new rate sample.
const RATE_ALPHA: f64 = 0.3;
/// EWMA weight of a new blob size.
const SIZE_ALPHA: f64 = 0.05;
/// EWMA weight of a new frame interval.
const FRAME_ALPHA: f64 = 0.2;
/// EWMA weight of a new answer latency.
const LATENCY_ALPHA: f64 = 0.2;
/// Headroom over the bandwidth-delay product.
const GAIN: f64 = 2.0;
/// Least size assumed per answer under a bandwidth cap (leaves are empty but still cost a
/// round of headers).
const MIN_ANSWER_BYTES: f64 = 256.0;
/// Longest frame interval taken into account (a stalled frame loop is not a frame).
const MAX_FRAME: Duration = Duration::from_millis(250);

/// EWMA estimates of the delivered rate, the answer size, the RTT and the frame interval.
#[derive(Clone, Debug, Default)]
pub struct Bandwidth {
    rate_bytes_s: Option<f64>,
    rate_answers_s: Option<f64>,
    mean_bytes: Option<f64>,
    rtt: Option<Duration>,
    latency_s: Option<f64>,
    frame: Option<Duration>,
    last_submit: Option<Duration>,
    last_advance: Option<Duration>,
    sample_bytes: u64,
    sample_answers: u64,
    sample_busy: Duration,
}

fn ewma(old: Option<f64>, new: f64, alpha: f64) -> f64 {
    match old {
        Some(old) => old + alpha * (new - old),
        None => new,
    }
}

impl Bandwidth {
    /// No estimate yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Accounts the time since the last call as busy if `in_flight > 0`. Call before every
    /// change of the number of requests in flight.
    pub fn advance(&mut self, now: Duration, in_flight: usize) {
        if let Some(last) = self.last_advance
            && in_flight > 0
        {
            self.sample_busy += now.saturating_sub(last);
        }
        self.last_advance = Some(now);
        if self.sample_busy >= SAMPLE {
            let busy = self.sample_busy.as_secs_f64();
            let rate = self.sample_bytes as f64 / busy;
            self.rate_bytes_s = Some(ewma(self.rate_bytes_s, rate, RATE_ALPHA));
            let answers = self.sample_answers as f64 / busy;
            self.rate_answers_s = Some(ewma(self.rate_answers_s, answers, RATE_ALPHA));
            self.sample_bytes = 0;
            self.sample_answers = 0;
            self.sample_busy = Duration::ZERO;
        }
    }

    /// A frame submitted its wants at `now`.
    pub fn on_submit(&mut self, now: Duration) {
        if let Some(last) = self.last_submit.replace(now) {
            let dt = now.saturating_sub(last).min(MAX_FRAME);
            self.frame = Some(match self.frame {
                Some(old) => old.mul_f64(1.0 - FRAME_ALPHA) + dt.mul_f64(FRAME_ALPHA),
                None => dt,
            });
        }
    }

    /// An answer of `body_bytes` arrived `latency` after its request was written.
    pub fn on_answer(&mut self, body_bytes: usize, latency: Option<Duration>) {
        self.sample_bytes += body_bytes as u64;
        self.sample_answers += 1;
        self.mean_bytes = Some(ewma(self.mean_bytes, body_bytes as f64, SIZE_ALPHA));
        if let Some(l) = latency {
            self.latency_s = Some(ewma(self.latency_s, l.as_secs_f64(), LATENCY_ALPHA));
            // The least latency ever seen: the path's RTT without queueing delay. Letting
            // it creep up would feed back (a fuller window queues more, which raises the
            // latency, which widens the window); a path that really got longer leaves the
            // link under-used rather than bloated.
            self.rtt = Some(self.rtt.map_or(l, |old| old.min(l)));
        }
    }

    /// Estimated delivered rate in bit/s (0 before the first estimate).
    pub fn rate_bit_s(&self) -> f64 {
        self.rate_bytes_s.unwrap_or(0.0) * 8.0
    }

    /// Estimated RTT.
    pub fn rtt(&self) -> Option<Duration> {
        self.rtt
    }

    /// Smoothed latency of recent answers: the RTT plus transfer and queueing time
    /// (`None` before the first answer).
    pub fn latency(&self) -> Option<Duration> {
        self.latency_s.map(Duration::from_secs_f64)
    }

    /// Mean answer body size in bytes (0 before the first answer).
    pub fn mean_bytes(&self) -> f64 {
        self.mean_bytes.unwrap_or(0.0)
    }

    /// Estimated answers per second (0 before the first estimate).
    pub fn answers_per_s(&self) -> f64 {
        self.rate_answers_s.unwrap_or(0.0)
    }

    /// How many requests may be outstanding: `initial` until there is an estimate, then
    /// `GAIN x answer rate x (RTT + frame)`, never below `initial` nor above `max`.
    /// `cap_bit_s` limits the answer rate used to `cap / answer size`.
    pub fn window(&self, initial: usize, max: usize, cap_bit_s: Option<f64>) -> usize {
        let lo = initial.min(max).max(1);
        let (Some(rate), Some(rtt)) = (self.rate_answers_s, self.rtt) else {
            return lo;
        };
        let rate = match cap_bit_s {
            Some(cap) => rate.min(cap / 8.0 / self.mean_bytes().max(MIN_ANSWER_BYTES)),
            None => rate,
        };
        let horizon = rtt + self.frame.unwrap_or(Duration::ZERO);
        let blobs = GAIN * rate * horizon.as_secs_f64();
        let blobs = if blobs.is_finite() { blobs.ceil() } else { 0.0 };
        (blobs as usize).clamp(lo, max.max(1))
    }
}

/// A token bucket on requested bytes, for the optional bandwidth cap: each request takes
/// the expected answer size, corrected when the answer arrives.
#[derive(Clone, Debug)]
pub struct Cap {
    rate_bytes_s: f64,
    burst_bytes: f64,
    tokens: f64,
    last: Duration,
}

impl Cap {
    /// A full bucket for `cap_bit_s`, holding 100 ms worth (at least one packet). The
    /// bucket may go into debt by one request, so any answer size gets through.
    pub fn new(cap_bit_s: f64, now: Duration) -> Self {
        let rate_bytes_s = (cap_bit_s / 8.0).max(1.0);
        let burst_bytes = (rate_bytes_s * 0.1).max(1500.0);
        Cap {
            rate_bytes_s,
            burst_bytes,
            tokens: burst_bytes,
            last: now,
        }
    }

    fn refill(&mut self, now: Duration) {
        let dt = now.saturating_sub(self.last).as_secs_f64();
        self.tokens = (self.tokens + dt * self.rate_bytes_s).min(self.burst_bytes);
        self.last = now;
    }

    /// Takes `bytes` if the bucket is not in debt.
    pub fn try_take(&mut self, now: Duration, bytes: f64) -> bool {
        self.refill(now);
        if self.tokens <= 0.0 {
            return false;
        }
        self.tokens -= bytes;
        true
    }

    /// Corrects the bucket by `actual - expected` bytes of an answer.
    pub fn correct(&mut self, expected: f64, actual: f64) {
        self.tokens -= actual - expected;
    }

    /// When the bucket is out of debt again, if it is in debt.
    pub fn ready_at(&self) -> Option<Duration> {
        (self.tokens <= 0.0)
            .then(|| self.last + Duration::from_secs_f64((-self.tokens + 1.0) / self.rate_bytes_s))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn the_window_is_the_bandwidth_delay_product_with_headroom() {
        let t0 = Duration::from_secs(1000);
        let mut b = Bandwidth::new();
        assert_eq!(b.window(8, 64, None), 8);
        // 500 kB/s of 2 kB answers, 100 ms latency, over busy time only.
        let mut t = t0;
        b.advance(t, 0);
        for _ in 0..50 {
            t += Duration::from_millis(4);
            b.on_answer(2000, Some(Duration::from_millis(100)));
            b.advance(t, 5);
        }
        // An idle second does not lower the rate.
        t += Duration::from_secs(1);
        b.advance(t, 0);
        assert!((b.rate_bit_s() - 4e6).abs() < 1e5, "{}", b.rate_bit_s());
        // 2 x 500 kB/s x 0.1 s / 2 kB = 50 answers.
        assert_eq!(b.window(8, 64, None), 50);
        assert_eq!(b.window(8, 30, None), 30);
        // A 2 Mbit/s cap halves it.
        assert_eq!(b.window(8, 64, Some(2e6)), 25);
        // A 16 ms frame adds to the horizon.
        b.on_submit(t);
        b.on_submit(t + Duration::from_millis(16));
        assert_eq!(b.window(8, 64, None), 58);
    }

    #[test]
    fn empty_answers_still_open_the_window() {
        // 1,000 empty leaves per second at 100 ms: the window follows the answer rate,
        // not the (zero) body rate.
        let t0 = Duration::from_secs(1000);
        let mut b = Bandwidth::new();
        let mut t = t0;
        b.advance(t, 0);
        for _ in 0..200 {
            t += Duration::from_millis(1);
            b.on_answer(0, Some(Duration::from_millis(100)));
            b.advance(t, 100);
        }
        assert_eq!(b.rate_bit_s(), 0.0);
        assert!(
            (b.answers_per_s() - 1000.0).abs() < 1.0,
            "{}",
            b.answers_per_s()
        );
        // 2 x 1000/s x 0.1 s = 200.
        assert_eq!(b.window(8, 256, None), 200);
    }

    #[test]
    fn the_rtt_is_the_least_latency_and_queueing_does_not_widen_the_window() {
        let mut b = Bandwidth::new();
        b.on_answer(0, Some(Duration::from_millis(200)));
        b.on_answer(0, Some(Duration::from_millis(100)));
        for _ in 0..1000 {
            b.on_answer(0, Some(Duration::from_millis(1100)));
        }
        assert_eq!(b.rtt(), Some(Duration::from_millis(100)));
    }

    #[test]
    fn the_cap_bucket_holds_requests_back_until_refilled() {
        let t0 = Duration::from_secs(1000);
        let mut c = Cap::new(8.0 * 100_000.0, t0); // 100 kB/s, 10 kB burst
        assert!(c.try_take(t0, 6_000.0));
        assert!(c.try_take(t0, 10_000.0));
        assert!(!c.try_take(t0, 10_000.0));
        let ready = c.ready_at().unwrap();
        assert!(ready > t0 && ready < t0 + Duration::from_millis(70));
        assert!(c.try_take(ready, 10_000.0));
        c.correct(10_000.0, 0.0);
        assert!(c.try_take(ready, 1.0));
    }
}
