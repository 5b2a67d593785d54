//! The packet rate, measured (docs/FIREWIRE.md §5). No open source writes or reads the rate
//! register, so omnid never sets the rate: it measures the period between the device's
//! packets from the isochronous receive timestamps (the bus's cycle clock, 8000 cycles a
//! second, <linux/firewire-cdev.h>: "16 bits invalid, 3 bits cycleSeconds, 13 bits
//! cycleCount") and refuses a device that runs at another rate than `device.rate_hz`.

/// Bus cycles per second (IEEE 1394: 125 µs cycles).
pub(crate) const CYCLES_PER_S: u32 = 8000;
/// The cycle clock of a timestamp wraps after 8 s.
pub(crate) const CYCLE_WRAP: u32 = 8 * CYCLES_PER_S;
/// Packets measured at open.
pub(crate) const MEASURE_PACKETS: usize = 64;
/// Pairs of consecutive packets the measurement needs at least.
pub(crate) const MIN_PAIRS: usize = 8;
/// Relative difference between measured and configured rate that is refused.
pub(crate) const TOLERANCE: f64 = 0.02;

/// A receive timestamp as a cycle number within the 8 s wrap, or `None` when its cycle count
/// is out of range (not a timestamp).
pub(crate) fn cycle_index(timestamp: u16) -> Option<u32> {
    let seconds = u32::from(timestamp >> 13);
    let count = u32::from(timestamp & 0x1FFF);
    (count < CYCLES_PER_S).then_some(seconds * CYCLES_PER_S + count)
}

/// Cycles from timestamp `a` to timestamp `b` (forward, modulo the 8 s wrap).
pub(crate) fn cycles_between(a: u16, b: u16) -> Option<u32> {
    let (a, b) = (cycle_index(a)?, cycle_index(b)?);
    Some((b + CYCLE_WRAP - a) % CYCLE_WRAP)
}

/// What the device's stream looked like.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateMeasurement {
    /// Packets looked at.
    pub(crate) packets: usize,
    /// Consecutive pairs whose counter stepped by exactly one (the period is theirs).
    pub(crate) pairs: usize,
    /// Period between packets, s: the mean of the middle 80 % of the pairs (0 when none).
    pub(crate) period_s: f64,
    /// Median step of the per-packet counter (bytes 32..35) between consecutive packets.
    pub(crate) counter_step: i64,
}

impl RateMeasurement {
    pub(crate) fn rate_hz(&self) -> f64 {
        if self.period_s > 0.0 {
            1.0 / self.period_s
        } else {
            0.0
        }
    }

    /// Measure from consecutive packets' `(counter, timestamp)`.
    pub(crate) fn from_packets(packets: &[(u32, u16)]) -> Self {
        let mut steps: Vec<i64> = packets
            .windows(2)
            .map(|w| i64::from(w[1].0.wrapping_sub(w[0].0) as i32))
            .collect();
        steps.sort_unstable();
        let counter_step = steps.get(steps.len() / 2).copied().unwrap_or(0);
        // Cycles between consecutive packets (counter +1); the mean of the middle 80 %, so
        // that a burst at the start (packets queued before the first read) or a late packet
        // does not move it, while a rate between whole cycles (6, 7, 7, ...) still averages.
        let mut gaps: Vec<u32> = packets
            .windows(2)
            .filter(|w| w[1].0.wrapping_sub(w[0].0) == 1)
            .filter_map(|w| cycles_between(w[0].1, w[1].1))
            .collect();
        gaps.sort_unstable();
        let pairs = gaps.len();
        let trim = pairs / 10;
        let kept = &gaps[trim..pairs - trim];
        let period_s = if kept.is_empty() {
            0.0
        } else {
            kept.iter().map(|&c| f64::from(c)).sum::<f64>()
                / kept.len() as f64
                / f64::from(CYCLES_PER_S)
        };
        RateMeasurement {
            packets: packets.len(),
            pairs,
            period_s,
            counter_step,
        }
    }

    /// The refusal, when this stream does not fit `rate_hz` (the text names the numbers).
    pub(crate) fn mismatch(&self, rate_hz: f64) -> Option<String> {
        if self.packets <= MIN_PAIRS {
            return Some(format!(
                "only {} packets arrived while the packet rate was measured; at least {} are \
                 needed",
                self.packets,
                MIN_PAIRS + 1
            ));
        }
        if self.counter_step != 1 {
            return Some(format!(
                "the per-packet counter (state bytes 32..35) advanced by {} per packet (median \
                 over {} packets); omnid takes device time as counter / device.rate_hz and \
                 needs +1 per packet (docs/FIREWIRE.md §4)",
                self.counter_step, self.packets
            ));
        }
        if self.pairs < MIN_PAIRS {
            return Some(format!(
                "only {} of {} packets came one after another (counter +1) while the packet \
                 rate was measured; at least {MIN_PAIRS} are needed",
                self.pairs, self.packets
            ));
        }
        let rate = self.rate_hz();
        if ((rate - rate_hz) / rate_hz).abs() > TOLERANCE {
            return Some(format!(
                "it sends a packet every {:.3} ms ({rate:.1} Hz, from the isochronous \
                 timestamps of {} packets), but device.rate_hz = {rate_hz}: omnid does not set \
                 the device's rate (no open source shows how, docs/FIREWIRE.md §5), so set \
                 device.rate_hz = {:.0}",
                self.period_s * 1e3,
                self.packets,
                rate.round()
            ));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Timestamps of a device sending at `rate_hz` from cycle `start`.
    fn stream(rate_hz: f64, start: u32, n: usize, counter0: u32) -> Vec<(u32, u16)> {
        (0..n)
            .map(|k| {
                let c = (start + (k as f64 * 8000.0 / rate_hz).round() as u32) % CYCLE_WRAP;
                let ts = ((c / 8000) << 13 | (c % 8000)) as u16;
                (counter0.wrapping_add(k as u32), ts)
            })
            .collect()
    }

    #[test]
    fn timestamps_unwrap_across_the_8_second_clock() {
        assert_eq!(cycle_index(0x0000), Some(0));
        assert_eq!(cycle_index((1 << 13) | 7999), Some(15999));
        assert_eq!(cycle_index(8000), None);
        // 7 s 7996 → 0 s 4: 8 cycles.
        assert_eq!(cycles_between((7 << 13) | 7996, 4), Some(8));
    }

    #[test]
    fn measures_the_vendor_rates_and_refuses_a_mismatch_naming_numbers() {
        for rate in [500.0, 1000.0, 1600.0] {
            let m = RateMeasurement::from_packets(&stream(rate, 63_990, 64, u32::MAX - 3));
            assert!((m.rate_hz() - rate).abs() < 1.0, "{m:?}");
            assert_eq!(m.counter_step, 1);
            assert_eq!(m.mismatch(rate), None);
        }
        let m = RateMeasurement::from_packets(&stream(500.0, 0, 64, 7));
        let e = m.mismatch(1000.0).unwrap();
        assert!(
            e.contains("2.000 ms") && e.contains("500.0 Hz") && e.contains("device.rate_hz = 1000"),
            "{e}"
        );
    }

    #[test]
    fn a_burst_at_the_start_does_not_bias_the_period_and_fractional_rates_average() {
        let mut s = stream(1000.0, 100, 64, 0);
        // The first five packets arrived one cycle apart (queued before the first read).
        for k in 1..5 {
            s[k].1 = s[0].1 + k as u16;
        }
        let m = RateMeasurement::from_packets(&s);
        assert!((m.rate_hz() - 1000.0).abs() < 1.0, "{m:?}");
        // 1200 Hz: gaps of 6 and 7 cycles.
        let m = RateMeasurement::from_packets(&stream(1200.0, 0, 64, 0));
        assert!((m.rate_hz() - 1200.0).abs() < 12.0, "{m:?}");
        assert_eq!(m.mismatch(1200.0), None);
    }

    #[test]
    fn lost_packets_do_not_bias_the_period() {
        let mut s = stream(1000.0, 100, 64, 0);
        s.retain(|(c, _)| c % 5 != 3);
        let m = RateMeasurement::from_packets(&s);
        assert!((m.rate_hz() - 1000.0).abs() < 0.5, "{m:?}");
    }

    #[test]
    fn a_counter_that_is_not_per_packet_is_refused() {
        let s: Vec<(u32, u16)> = stream(1000.0, 0, 64, 0)
            .into_iter()
            .map(|(c, t)| (c * 2, t))
            .collect();
        let e = RateMeasurement::from_packets(&s).mismatch(1000.0).unwrap();
        assert!(e.contains("advanced by 2 per packet"), "{e}");
        assert!(RateMeasurement::from_packets(&[(1, 0)])
            .mismatch(1000.0)
            .unwrap()
            .contains("at least 9"));
    }
}
