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
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest value seen (exact).
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

    /// Become a copy of `other` without allocating (same range: the bins are reused).
    pub(crate) fn copy_from(&mut self, other: &Histogram) {
        self.bin_ns = other.bin_ns;
        self.bins.clone_from(&other.bins);
        self.overflow = other.overflow;
        self.count = other.count;
        self.max_ns = other.max_ns;
    }

    /// Count one duration, ns.
    pub fn record(&mut self, ns: u64) {
        let i = (ns / self.bin_ns) as usize;
        match self.bins.get_mut(i) {
            Some(b) => *b += 1,
            None => self.overflow += 1,
        }
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    /// Durations recorded.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Largest duration recorded, ns (exact).
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
    /// Ticks whose lateness plus compute exceeded the device's step (see `record`).
    pub overruns: u64,
    // (host ns, device s) of the first and the last tick recorded.
    first: Option<(u64, f64)>,
    last: (u64, f64),
    // Host ns when the last tick's command was ready.
    last_done: u64,
}

impl TickTiming {
    /// Histograms sized for a device step of `period_ns`.
    pub fn new(period_ns: u64) -> Self {
        TickTiming {
            period: Histogram::new(1_000, 20 * period_ns),
            lateness: Histogram::new(1_000, 20 * period_ns),
            compute: Histogram::new(50, period_ns.max(1_000_000)),
            overruns: 0,
            first: None,
            last: (0, 0.0),
            last_done: 0,
        }
    }

    /// Become a copy of `other` without allocating (built for the same period).
    pub(crate) fn copy_from(&mut self, other: &TickTiming) {
        self.period.copy_from(&other.period);
        self.lateness.copy_from(&other.lateness);
        self.compute.copy_from(&other.compute);
        self.overruns = other.overruns;
        self.first = other.first;
        self.last = other.last;
        self.last_done = other.last_done;
    }

    /// One tick: the sample arrived at `wake` and the command was ready at `done` (host clock,
    /// ns); `t_dev` is the sample's device time, s. Lateness (paced runs) is measured against
    /// the device's own schedule, the first wake plus the device time since the first sample
    /// (1 ms a tick on the simulator, the log's own steps on a replay, gaps included on
    /// hardware). An overrun is a tick whose work ends after the next sample is due, taking
    /// this tick's device step for the next one's.
    pub fn record(&mut self, wake: u64, done: u64, t_dev: f64, paced: bool) {
        let compute = done.saturating_sub(wake);
        self.compute.record(compute);
        let ns_between = |a: f64, b: f64| ((b - a) * 1e9).round().max(0.0) as u64;
        match self.first {
            None => self.first = Some((wake, t_dev)),
            Some((wake0, t0)) => {
                let (last_wake, last_t) = self.last;
                self.period.record(wake.saturating_sub(last_wake));
                if paced {
                    let late = wake.saturating_sub(wake0 + ns_between(t0, t_dev));
                    self.lateness.record(late);
                    if late + compute > ns_between(last_t, t_dev) {
                        self.overruns += 1;
                    }
                }
            }
        }
        self.last = (wake, t_dev);
        self.last_done = done;
    }

    /// Host time from the first sample's arrival to the last command, s (None before a tick).
    pub fn wall_s(&self) -> Option<f64> {
        let (wake0, _) = self.first?;
        Some(self.last_done.saturating_sub(wake0) as f64 * 1e-9)
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
    fn lateness_follows_the_device_schedule() {
        // A 100 Hz log replayed in a 1 kHz configuration, with jittered steps: each wake 30 µs
        // after its sample is due, work taking 20 µs, except one tick whose work runs past
        // the next sample.
        let mut t = TickTiming::new(1_000_000);
        let start = 5_000_000_000u64;
        let times: [f64; 6] = [0.0, 0.010, 0.0201, 0.0299, 0.040, 0.050];
        for (k, &t_dev) in times.iter().enumerate() {
            let due = start + (t_dev * 1e9).round() as u64;
            let wake = if k == 0 { start } else { due + 30_000 };
            let work = if k == 3 { 9_900_000 } else { 20_000 };
            t.record(wake, wake + work, t_dev, true);
        }
        assert_eq!(t.lateness.count(), 5);
        assert_eq!(t.lateness.max_ns(), 30_000);
        assert_eq!(t.overruns, 1);
        assert_eq!(t.period.count(), 5);
        assert_eq!(t.compute.max_ns(), 9_900_000);

        // Unpaced: no lateness, no overruns.
        let mut u = TickTiming::new(1_000_000);
        for k in 0..4u64 {
            u.record(k * 5_000, k * 5_000 + 4_000, k as f64 * 1e-3, false);
        }
        assert_eq!(
            (u.lateness.count(), u.overruns, u.period.count()),
            (0, 0, 3)
        );
        // First wake at 0, last command ready at 19 µs.
        assert_eq!(u.wall_s(), Some(19e-6));
        assert_eq!(TickTiming::new(1_000_000).wall_s(), None);
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
