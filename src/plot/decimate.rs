//! Streaming min/max decimation. A figure is ~1000 pixels wide, a log up to 600 k rows; drawing
//! every row is slow and hides nothing more than the per-column extremes do. Rows go into
//! buckets of equal row count; each bucket keeps, per channel, its minimum and maximum with
//! their times, so spikes survive. When the buckets reach twice the target, neighbours merge
//! and the bucket size doubles: memory stays bounded without knowing the row count ahead.

/// One extreme of a channel within a bucket: its time and value (NaN value: none yet).
#[derive(Debug, Clone, Copy)]
struct Extreme {
    t: f64,
    v: f64,
}

const NONE: Extreme = Extreme {
    t: f64::NAN,
    v: f64::NAN,
};

/// The decimated log: per channel, points in time order, non-finite values left out.
#[derive(Debug, Clone, PartialEq)]
pub struct Decimated {
    /// Rows read.
    pub rows: u64,
    /// First and last time seen (min and max, in case a log's clock is not monotonic).
    pub t_range: (f64, f64),
    /// Per channel, (time s, value) points: each kept bucket's minimum and maximum.
    pub channels: Vec<Vec<(f64, f64)>>,
}

/// The decimator's running state: bounded by twice the target bucket count, whatever the
/// number of rows.
pub struct Decimator {
    channels: usize,
    target: usize,
    rows_per_bucket: u64,
    rows_in_last: u64,
    rows: u64,
    t_range: (f64, f64),
    /// Bucket b, channel c: `[min, max]` at `(b * channels + c) * 2`.
    extremes: Vec<Extreme>,
}

impl Decimator {
    /// `target`: the fewest buckets kept once there are more rows than that (at most twice as
    /// many are kept).
    pub fn new(channels: usize, target: usize) -> Decimator {
        Decimator {
            channels,
            target: target.max(1),
            rows_per_bucket: 1,
            rows_in_last: 0,
            rows: 0,
            t_range: (f64::INFINITY, f64::NEG_INFINITY),
            extremes: Vec::new(),
        }
    }

    /// Rows pushed so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// One row: its time and one value per channel. `t` must be finite.
    pub fn push(&mut self, t: f64, values: &[f64]) {
        debug_assert_eq!(values.len(), self.channels);
        if self.rows_in_last == 0 {
            if self.buckets() == 2 * self.target {
                self.halve();
            }
            let len = self.extremes.len() + 2 * self.channels;
            self.extremes.resize(len, NONE);
        }
        let start = self.extremes.len() - 2 * self.channels;
        let bucket = &mut self.extremes[start..];
        for (pair, &v) in bucket.chunks_exact_mut(2).zip(values) {
            if !v.is_finite() {
                continue;
            }
            // An empty slot (NaN) takes the first value.
            if pair[0].v.is_nan() || v < pair[0].v {
                pair[0] = Extreme { t, v };
            }
            if pair[1].v.is_nan() || v > pair[1].v {
                pair[1] = Extreme { t, v };
            }
        }
        self.rows_in_last += 1;
        if self.rows_in_last == self.rows_per_bucket {
            self.rows_in_last = 0;
        }
        self.rows += 1;
        self.t_range = (self.t_range.0.min(t), self.t_range.1.max(t));
    }

    fn buckets(&self) -> usize {
        self.extremes.len() / (2 * self.channels).max(1)
    }

    /// Merge neighbouring buckets pairwise (called only on a full, even count).
    fn halve(&mut self) {
        let width = 2 * self.channels;
        let n = self.buckets() / 2;
        for b in 0..n {
            for k in 0..width {
                let a = self.extremes[2 * b * width + k];
                let c = self.extremes[(2 * b + 1) * width + k];
                let is_min = k % 2 == 0;
                let better = if is_min { c.v < a.v } else { c.v > a.v };
                let pick_c = a.v.is_nan() || better;
                self.extremes[b * width + k] = if pick_c { c } else { a };
            }
        }
        self.extremes.truncate(n * width);
        self.rows_per_bucket *= 2;
    }

    /// The kept points, per channel in time order.
    pub fn finish(self) -> Decimated {
        let width = 2 * self.channels;
        let mut channels = vec![Vec::with_capacity(2 * self.buckets()); self.channels];
        if width > 0 {
            for bucket in self.extremes.chunks_exact(width) {
                for (c, pair) in bucket.chunks_exact(2).enumerate() {
                    let (lo, hi) = (pair[0], pair[1]);
                    if lo.v.is_nan() {
                        continue;
                    }
                    // Both extremes, in the order they happened, once if they are one sample.
                    let (first, second) = if lo.t <= hi.t { (lo, hi) } else { (hi, lo) };
                    channels[c].push((first.t, first.v));
                    if first.t != second.t || first.v != second.v {
                        channels[c].push((second.t, second.v));
                    }
                }
            }
        }
        let t_range = if self.rows == 0 {
            (0.0, 0.0)
        } else {
            self.t_range
        };
        Decimated {
            rows: self.rows,
            t_range,
            channels,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(values: &[f64], target: usize) -> Decimated {
        let mut d = Decimator::new(1, target);
        for (i, &v) in values.iter().enumerate() {
            d.push(i as f64, &[v]);
        }
        d.finish()
    }

    #[test]
    fn few_rows_pass_through_unchanged() {
        let d = run(&[3.0, 1.0, 2.0], 10);
        assert_eq!(d.channels[0], vec![(0.0, 3.0), (1.0, 1.0), (2.0, 2.0)]);
        assert_eq!(d.rows, 3);
        assert_eq!(d.t_range, (0.0, 2.0));
    }

    #[test]
    fn many_rows_stay_bounded_and_keep_spikes() {
        let n = 600_000;
        let mut v: Vec<f64> = (0..n).map(|i| (i as f64 * 1e-3).sin()).collect();
        v[123_457] = 50.0;
        v[400_001] = -50.0;
        let d = run(&v, 1000);
        let pts = &d.channels[0];
        assert!(pts.len() <= 4 * 1000, "{} points", pts.len());
        assert!(pts.len() >= 1000, "{} points", pts.len());
        assert!(pts.contains(&(123_457.0, 50.0)));
        assert!(pts.contains(&(400_001.0, -50.0)));
        // Time order is kept.
        assert!(pts.windows(2).all(|w| w[0].0 <= w[1].0));
        assert_eq!(d.t_range, (0.0, (n - 1) as f64));
    }

    #[test]
    fn non_finite_values_are_left_out() {
        let d = run(&[f64::NAN, 1.0, f64::INFINITY, 2.0], 10);
        assert_eq!(d.channels[0], vec![(1.0, 1.0), (3.0, 2.0)]);
        let d = run(&[f64::NAN; 5], 2);
        assert!(d.channels[0].is_empty());
    }

    #[test]
    fn merged_buckets_keep_both_extremes_in_time_order() {
        // 8 rows into at most 4 buckets of 2: each bucket shows its max then min (falling).
        let v = [8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.0];
        let d = run(&v, 2);
        let pts = &d.channels[0];
        assert!(pts.windows(2).all(|w| w[0].0 < w[1].0), "{pts:?}");
        assert_eq!(pts.first(), Some(&(0.0, 8.0)));
        assert_eq!(pts.last(), Some(&(8.0, 0.0)));
    }
}
