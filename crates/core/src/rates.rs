//! [`RateWindow`]: per-second rates of monotone counters over a sliding window, and
//! [`TokenBucket`]: the per-actor message rate limit.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// The span status rates are averaged over.
pub const RATES_WINDOW: Duration = Duration::from_secs(10);

/// Rates of a fixed set of monotone counters over (about) the last `window`, sampled lazily:
/// every read records the totals it is given (at most one sample per tenth of the window) and
/// compares them with the oldest sample that is not older than needed. Nothing runs between
/// reads, so an idle status endpoint costs nothing; rarely read, a rate averages over the time
/// since the previous read instead (the span is returned with the rates).
#[derive(Debug, Clone)]
pub struct RateWindow {
    window: Duration,
    /// `(at, totals)`, oldest first; never empty.
    samples: VecDeque<(Instant, Vec<u64>)>,
}

impl RateWindow {
    /// A window over `width` counters that were all 0 at `start`.
    pub fn new(start: Instant, width: usize, window: Duration) -> Self {
        Self {
            window,
            samples: VecDeque::from([(start, vec![0; width])]),
        }
    }

    /// The rates per second of `totals` at `now`, and the span they are averaged over. Counters
    /// that went down (a reset) count as 0.
    pub fn rates(&mut self, now: Instant, totals: &[u64]) -> (Duration, Vec<f64>) {
        let window_start = now.checked_sub(self.window).unwrap_or(now);
        // Keep exactly one sample at or before the window's start as the base.
        while self.samples.len() > 1 && self.samples[1].0 <= window_start {
            self.samples.pop_front();
        }
        let (base_at, base) = self.samples.front().expect("never empty");
        let span = now.saturating_duration_since(*base_at);
        let secs = span.as_secs_f64();
        let rates = totals
            .iter()
            .zip(base.iter().chain(std::iter::repeat(&0)))
            .map(|(&now, &then)| {
                if secs > 0.0 {
                    now.saturating_sub(then) as f64 / secs
                } else {
                    0.0
                }
            })
            .collect();
        let last_at = self.samples.back().expect("never empty").0;
        if now.saturating_duration_since(last_at) >= self.window / 10 {
            self.samples.push_back((now, totals.to_vec()));
        }
        (span, rates)
    }
}

/// A token bucket: `rate` tokens per second, at most `burst` saved up. A taker that finds the
/// bucket empty goes into debt and is told how long to wait, so takers are served in order at
/// the configured rate.
#[derive(Debug, Clone)]
pub struct TokenBucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    at: Instant,
}

impl TokenBucket {
    /// A full bucket of `rate` tokens per second (at least 1 saved up) at `now`. `rate` must be
    /// positive and finite.
    pub fn new(rate: f64, now: Instant) -> Self {
        debug_assert!(rate.is_finite() && rate > 0.0, "rate {rate}");
        let burst = rate.max(1.0);
        Self {
            rate,
            burst,
            tokens: burst,
            at: now,
        }
    }

    /// Takes one token at `now`: how long the taker must wait before acting (zero if a token
    /// was there).
    pub fn take(&mut self, now: Instant) -> Duration {
        let elapsed = now.saturating_duration_since(self.at).as_secs_f64();
        self.at = self.at.max(now);
        self.tokens = (self.tokens + elapsed * self.rate).min(self.burst) - 1.0;
        if self.tokens >= 0.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(-self.tokens / self.rate)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SEC: Duration = Duration::from_secs(1);

    #[test]
    fn rates_average_over_the_window() {
        let t0 = Instant::now();
        let mut w = RateWindow::new(t0, 2, 10 * SEC);
        // Before any sample: since the start.
        let (span, r) = w.rates(t0 + 2 * SEC, &[20, 4]);
        assert_eq!(span, 2 * SEC);
        assert_eq!(r, [10.0, 2.0]);
        // A steady 10/s then a burst: samples every second for 30 s.
        for s in 3..=30 {
            w.rates(t0 + s * SEC, &[10 * s as u64, 4]);
        }
        let (span, r) = w.rates(t0 + 31 * SEC, &[310 + 100, 4]);
        // The base is the newest sample at or before 21 s.
        assert_eq!(span, 10 * SEC);
        assert_eq!(r, [(410.0 - 210.0) / 10.0, 0.0]);
        assert!(w.samples.len() <= 12, "{} samples", w.samples.len());
    }

    #[test]
    fn rare_reads_average_since_the_previous_read_and_resets_count_as_zero() {
        let t0 = Instant::now();
        let mut w = RateWindow::new(t0, 1, 10 * SEC);
        w.rates(t0 + 5 * SEC, &[50]);
        let (span, r) = w.rates(t0 + 105 * SEC, &[1050]);
        assert_eq!(span, 100 * SEC);
        assert_eq!(r, [10.0]);
        let (_, r) = w.rates(t0 + 106 * SEC, &[3]);
        assert_eq!(r, [0.0]);
        // Same instant as the start: no rate rather than a division by zero.
        let mut w = RateWindow::new(t0, 1, 10 * SEC);
        assert_eq!(w.rates(t0, &[7]).1, [0.0]);
    }

    #[test]
    fn a_bucket_allows_its_burst_then_spaces_takers_at_the_rate() {
        let t0 = Instant::now();
        let mut b = TokenBucket::new(4.0, t0);
        for _ in 0..4 {
            assert_eq!(b.take(t0), Duration::ZERO);
        }
        // Empty: the fifth waits a quarter second, the sixth half a second.
        assert_eq!(b.take(t0), Duration::from_millis(250));
        assert_eq!(b.take(t0), Duration::from_millis(500));
        // Two seconds later the debt (2 tokens) is paid and the bucket is full again (4).
        let t2 = t0 + 2 * SEC;
        for _ in 0..4 {
            assert_eq!(b.take(t2), Duration::ZERO);
        }
        assert!(b.take(t2) > Duration::ZERO);
        // Below one per second the bucket still holds one token.
        let mut slow = TokenBucket::new(0.5, t0);
        assert_eq!(slow.take(t0), Duration::ZERO);
        assert_eq!(slow.take(t0), 2 * SEC);
    }
}
