//! A log-bucketed latency histogram (HDR-style): exact below 128 us, then 64 buckets per
//! power of two, i.e. values are known to within 1/64 (1.6 %). Memory is bounded by the
//! largest value recorded (at most a few thousand counters), whatever the request count.

/// Sub-buckets per power of two, as a bit count.
const SUB_BITS: u32 = 6;
const SUB: u64 = 1 << SUB_BITS;
/// Values below this are counted exactly.
const EXACT: u64 = 2 * SUB;

/// Counts of latencies in microseconds.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Histogram {
    counts: Vec<u64>,
    total: u64,
    max_us: u64,
}

fn bucket(us: u64) -> usize {
    if us < EXACT {
        return us as usize;
    }
    let e = 63 - us.leading_zeros();
    let shift = e - SUB_BITS;
    (EXACT + u64::from(e - SUB_BITS - 1) * SUB + ((us >> shift) - SUB)) as usize
}

/// The largest value that falls in bucket `i`.
fn bucket_high(i: usize) -> u64 {
    let i = i as u64;
    if i < EXACT {
        return i;
    }
    let e = (i - EXACT) / SUB + u64::from(SUB_BITS) + 1;
    let mantissa = SUB + (i - EXACT) % SUB;
    let shift = e - u64::from(SUB_BITS);
    let high = (u128::from(mantissa + 1) << shift) - 1;
    u64::try_from(high).unwrap_or(u64::MAX)
}

impl Histogram {
    /// Records one latency.
    pub fn record(&mut self, us: u64) {
        let b = bucket(us);
        if b >= self.counts.len() {
            self.counts.resize(b + 1, 0);
        }
        self.counts[b] += 1;
        self.total += 1;
        self.max_us = self.max_us.max(us);
    }

    /// Adds another histogram's counts.
    pub fn merge(&mut self, other: &Histogram) {
        if other.counts.len() > self.counts.len() {
            self.counts.resize(other.counts.len(), 0);
        }
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self.total += other.total;
        self.max_us = self.max_us.max(other.max_us);
    }

    /// Number of values recorded.
    pub fn count(&self) -> u64 {
        self.total
    }

    /// The largest value recorded (exact), 0 if none.
    pub fn max_us(&self) -> u64 {
        self.max_us
    }

    /// The `q`-quantile (`0 <= q <= 1`): the upper edge of the bucket holding it, never
    /// above the maximum. 0 if nothing was recorded.
    pub fn quantile_us(&self, q: f64) -> u64 {
        if self.total == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return bucket_high(i).min(self.max_us);
            }
        }
        self.max_us
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_monotone_and_tight() {
        let mut last = 0;
        for us in (0..200_000u64).chain([u32::MAX as u64, u64::MAX / 2, u64::MAX]) {
            let b = bucket(us);
            assert!(b >= last, "{us}");
            last = b;
            let high = bucket_high(b);
            assert!(high >= us, "{us} above its bucket's top {high}");
            assert!(
                (high - us) as f64 <= us as f64 / SUB as f64,
                "{us} -> {high}"
            );
        }
    }

    #[test]
    fn quantiles_of_a_uniform_spread() {
        let mut h = Histogram::default();
        for us in 1..=10_000 {
            h.record(us);
        }
        let mut other = Histogram::default();
        other.record(50_000);
        h.merge(&other);
        assert_eq!(h.count(), 10_001);
        assert_eq!(h.max_us(), 50_000);
        for (q, want) in [(0.5, 5_000.0), (0.9, 9_000.0), (0.99, 9_900.0)] {
            let got = h.quantile_us(q) as f64;
            assert!((got - want).abs() / want < 0.02, "q{q}: {got}");
        }
        assert_eq!(h.quantile_us(1.0), 50_000);
        assert_eq!(Histogram::default().quantile_us(0.5), 0);
    }
}
