//! Fixed-bound histograms for per-tick timing: allocated once, updated without allocation.

use serde::Serialize;

/// Linear-bin histogram of nanosecond durations with an exact maximum.
#[derive(Debug, Clone)]
pub struct Histogram {
    bin_ns: u64,
    bins: Vec<u64>,
    overflow: u64,
    count: u64,
    max_ns: u64,
}

/// Percentiles in microseconds, as in the summary JSON.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
    pub p999: f64,
    pub max: f64,
}

impl Histogram {
    /// Bins of `bin_ns` up to `range_ns`; larger values land in an overflow bin (their maximum
    /// is still exact).
    pub fn new(bin_ns: u64, range_ns: u64) -> Self {
        let n = range_ns.div_ceil(bin_ns) as usize;
        Histogram {
            bin_ns,
            bins: vec![0; n],
            overflow: 0,
            count: 0,
            max_ns: 0,
        }
    }

    pub fn record(&mut self, ns: u64) {
        let i = (ns / self.bin_ns) as usize;
        match self.bins.get_mut(i) {
            Some(b) => *b += 1,
            None => self.overflow += 1,
        }
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }

    /// Upper edge of the bin holding quantile `p` (0..=1), ns; the exact max for overflow.
    pub fn quantile_ns(&self, p: f64) -> u64 {
        if self.count == 0 {
            return 0;
        }
        let rank = ((p * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (i, &b) in self.bins.iter().enumerate() {
            seen += b;
            if seen >= rank {
                return ((i as u64 + 1) * self.bin_ns).min(self.max_ns);
            }
        }
        self.max_ns
    }

    /// p50 / p99 / p99.9 / max in µs, or None when nothing was recorded.
    pub fn percentiles_us(&self) -> Option<Percentiles> {
        if self.count == 0 {
            return None;
        }
        let us = |ns: u64| ns as f64 / 1000.0;
        Some(Percentiles {
            p50: us(self.quantile_ns(0.50)),
            p99: us(self.quantile_ns(0.99)),
            p999: us(self.quantile_ns(0.999)),
            max: us(self.max_ns),
        })
    }
}

/// The three per-tick timings of the servo loop.
#[derive(Debug, Clone)]
pub struct TickTiming {
    /// Time between successive samples arriving.
    pub period: Histogram,
    /// How late a sample arrived against its ideal time (paced runs only).
    pub lateness: Histogram,
    /// Time from the sample's arrival to the command being ready.
    pub compute: Histogram,
    /// Ticks whose lateness plus compute exceeded one period.
    pub overruns: u64,
}

impl TickTiming {
    pub fn new(period_ns: u64) -> Self {
        TickTiming {
            period: Histogram::new(1_000, 20 * period_ns),
            lateness: Histogram::new(1_000, 20 * period_ns),
            compute: Histogram::new(50, period_ns.max(1_000_000)),
            overruns: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_of_a_uniform_ramp() {
        let mut h = Histogram::new(10, 100_000);
        for v in 1..=10_000u64 {
            h.record(v);
        }
        // Bins are 10 ns wide: quantiles are exact to one bin.
        assert!((h.quantile_ns(0.5) as i64 - 5_000).abs() <= 10);
        assert!((h.quantile_ns(0.99) as i64 - 9_900).abs() <= 10);
        assert_eq!(h.max_ns(), 10_000);
        assert_eq!(h.count(), 10_000);
    }

    #[test]
    fn overflow_keeps_exact_max() {
        let mut h = Histogram::new(1_000, 10_000);
        h.record(500);
        h.record(5_000_000);
        assert_eq!(h.quantile_ns(1.0), 5_000_000);
        assert_eq!(h.percentiles_us().unwrap().max, 5_000.0);
        assert!(Histogram::new(1, 10).percentiles_us().is_none());
    }
}
