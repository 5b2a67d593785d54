//! The channel between a leader's and a follower's coupling (docs/TELEOP.md §3): one fixed-size
//! packet per tick each way through a bounded queue, and at the receiving end a delay line that
//! injects the configured delay, jitter and loss. Nothing allocates after construction: the
//! queues are crossbeam's array channels and the delay line a boxed ring filled up front.
//! Both endpoints of a pair in one daemon are joined directly; across daemons each endpoint's
//! far side is a network thread (zenoh) feeding the same queues.

use crate::handoff::{Inlet, Outlet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Packet flags.
pub mod packet_flags {
    /// The leader's clutch is pressed: the follower holds, the leader is free.
    pub const CLUTCH: u32 = 1;
    /// The sender's arm is not coupled (a fault, idle, or its coupling was stopped): the pair
    /// is disabled.
    pub const DOWN: u32 = 2;
}

/// What each side tells the other every tick (plain data, fixed size).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Packet {
    /// Counts the sender's packets.
    pub seq: u64,
    /// The sender's device time, s.
    pub t: f64,
    /// Leader: the engagement it is in (0: none). Follower: the engagement it has taken up.
    pub engage: u32,
    /// [`packet_flags`].
    pub flags: u32,
    /// Leader: its motion since it engaged, scaled into the follower's workspace, mm.
    /// Follower: its motion since it took up the engagement, mm.
    pub pos_mm: [f64; 3],
    /// The velocity of that motion, mm/s.
    pub vel_mm_s: [f64; 3],
    /// The outside's force on the sender's tip, estimated from its motors and model, N.
    pub force_n: [f64; 3],
    /// Energy that has entered the channel at the sender's port so far, J (time-domain
    /// passivity: the other side may put out at most this much).
    pub energy_in_j: f64,
    /// The sender's copy of the newest packet it has received from this end: that packet's
    /// `t` (this end's clock), or 0 before any. This end measures the round trip from it
    /// without the two clocks agreeing (docs/TELEOP.md §5).
    #[serde(default)]
    pub echo_t: f64,
}

/// Delay, jitter and loss injected at a receiving end (docs/TELEOP.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Impairment {
    /// One-way delay added to every packet, ms.
    pub delay_ms: f64,
    /// Each packet's delay varies uniformly by up to ± this, ms (packets stay in order, as on
    /// one TCP or zenoh stream).
    pub jitter_ms: f64,
    /// Fraction of packets lost, 0 ..= 1.
    pub loss: f64,
}

impl Default for Impairment {
    fn default() -> Self {
        Impairment {
            delay_ms: 0.0,
            jitter_ms: 0.0,
            loss: 0.0,
        }
    }
}

/// The longest one-way delay a delay line holds at 1 kHz with room to spare, ms.
pub const MAX_DELAY_MS: f64 = 1500.0;
/// Packets a delay line holds (two seconds at 1 kHz).
const LINE: usize = 2048;
/// Packets a queue holds between two ticks of the receiver.
const QUEUE: usize = 256;

/// Counters of one receiving end.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct ChannelStats {
    /// Packets sent from this end.
    pub sent: u64,
    /// Packets this end could not send (the queue was full).
    pub send_dropped: u64,
    /// Packets that reached this end.
    pub received: u64,
    /// Of those, lost by the injected loss.
    pub lost: u64,
    /// Of those, dropped because the delay line was full.
    pub overflowed: u64,
    /// Packets delivered (after their delay).
    pub delivered: u64,
}

/// One end of a channel.
pub struct Endpoint {
    tx: Inlet<Packet>,
    rx: Outlet<Packet>,
    impairment: Impairment,
    rng: ChaCha8Rng,
    /// Packets on their way, in delivery order: (due time, packet).
    line: Box<[(f64, Packet); LINE]>,
    head: usize,
    len: usize,
    /// When the last packet put in the line is due (delivery keeps order).
    last_due: f64,
    /// A playout buffer ([`Endpoint::set_playout`]): the delay every packet is delivered at,
    /// measured as arrival time less the sender's `t`, s; off while `None`, not yet known
    /// while NaN.
    playout: Option<f64>,
    stats: ChannelStats,
}

/// A playout buffer holds packets to this quantile of their delays: the rest arrive after
/// their time and are delivered late (the waves squeezed, which puts out less than came in)
/// rather than holding every packet to a spike.
pub const PLAYOUT_QUANTILE: f64 = 0.99;
/// How far one packet moves a playout buffer's delay, s (up by this times the quantile when
/// it came later, down by this times the rest when not): a delay rises to a new level at up
/// to a tenth of real time (the waves stretched by at most that) and comes down at 1 ms a
/// second at 1 kHz.
pub const PLAYOUT_STEP_S: f64 = 1e-4;

/// Two joined endpoints (the leader's, the follower's), each impaired as given on what it
/// receives.
pub fn pair(to_leader: Impairment, to_follower: Impairment, seed: u64) -> (Endpoint, Endpoint) {
    let (a_tx, a_rx) = crate::handoff::queue(QUEUE);
    let (b_tx, b_rx) = crate::handoff::queue(QUEUE);
    (
        Endpoint::new(a_tx, b_rx, to_leader, seed),
        Endpoint::new(b_tx, a_rx, to_follower, seed ^ 0x7E1E_0F00),
    )
}

impl Endpoint {
    /// An endpoint sending on `tx` and receiving from `rx` (a network thread's queues: the
    /// servo never waits on either, docs/DESIGN.md §4.7).
    pub fn new(
        tx: Inlet<Packet>,
        rx: Outlet<Packet>,
        impairment: Impairment,
        seed: u64,
    ) -> Endpoint {
        Endpoint {
            tx,
            rx,
            impairment,
            rng: ChaCha8Rng::seed_from_u64(seed),
            line: Box::new([(0.0, Packet::default()); LINE]),
            head: 0,
            len: 0,
            last_due: f64::NEG_INFINITY,
            playout: None,
            stats: ChannelStats::default(),
        }
    }

    /// Deliver every packet at one delay, tracked as the [`PLAYOUT_QUANTILE`] of the packets'
    /// arrival less their sender's time `t` (the two clocks' offset is the same in every
    /// packet and falls out). A jittery delay then reaches the receiver as a constant one
    /// near its largest — what wave variables need to stay passive (a delay that changes
    /// from packet to packet stretches and squeezes the waves: docs/TELEOP.md §5).
    pub fn set_playout(&mut self, on: bool) {
        self.playout = on.then_some(f64::NAN);
    }

    /// Send without waiting (a full queue drops the packet: the next one supersedes it).
    pub fn send(&mut self, p: Packet) {
        match self.tx.push(p) {
            Ok(()) => self.stats.sent += 1,
            Err(_) => self.stats.send_dropped += 1,
        }
    }

    /// At local time `now` (s): take what has arrived into the delay line, and return the
    /// newest packet whose delay has passed (older ones due at the same time are superseded).
    pub fn receive(&mut self, now: f64) -> Option<Packet> {
        while let Some(p) = self.rx.pop() {
            self.stats.received += 1;
            let imp = self.impairment;
            if imp.loss > 0.0 && self.rng.random::<f64>() < imp.loss {
                self.stats.lost += 1;
                continue;
            }
            if self.len == LINE {
                self.stats.overflowed += 1;
                continue;
            }
            let jitter = if imp.jitter_ms > 0.0 {
                self.rng.random_range(-imp.jitter_ms..=imp.jitter_ms)
            } else {
                0.0
            };
            let delay_s = (imp.delay_ms + jitter).max(0.0) * 1e-3;
            let mut due = (now + delay_s).max(self.last_due);
            if let Some(hold) = self.playout.as_mut() {
                let late = due - p.t;
                *hold = if hold.is_nan() {
                    late
                } else if late > *hold {
                    *hold + PLAYOUT_STEP_S * PLAYOUT_QUANTILE
                } else {
                    *hold - PLAYOUT_STEP_S * (1.0 - PLAYOUT_QUANTILE)
                };
                due = due.max(p.t + *hold);
            }
            self.last_due = due;
            let slot = (self.head + self.len) % LINE;
            self.line[slot] = (due, p);
            self.len += 1;
        }
        let mut newest = None;
        while self.len > 0 && self.line[self.head].0 <= now {
            newest = Some(self.line[self.head].1);
            self.head = (self.head + 1) % LINE;
            self.len -= 1;
            self.stats.delivered += 1;
        }
        newest
    }

    /// Forget everything queued and on its way (a fresh start: what a link check sent
    /// before a run is not delivered in it).
    pub fn clear(&mut self) {
        self.rx.clear();
        self.head = 0;
        self.len = 0;
        self.last_due = f64::NEG_INFINITY;
        self.playout = self.playout.map(|_| f64::NAN);
        self.stats = ChannelStats::default();
    }

    /// This end's counters.
    pub fn stats(&self) -> ChannelStats {
        self.stats
    }

    /// Change what is injected from now on (packets already on their way keep their delay).
    pub fn set_impairment(&mut self, impairment: Impairment) {
        self.impairment = impairment;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn packet(seq: u64) -> Packet {
        Packet {
            seq,
            ..Packet::default()
        }
    }

    #[test]
    fn a_packet_arrives_after_its_delay_and_the_newest_due_one_wins() {
        let delay = Impairment {
            delay_ms: 9.5,
            ..Impairment::default()
        };
        let (mut leader, mut follower) = pair(Impairment::default(), delay, 1);
        // The leader sends one packet a tick; the follower, looking once a tick, sees packet
        // k at tick k + 10 (due 9.5 ms after it arrived).
        let mut seen = Vec::new();
        for k in 0..40u64 {
            leader.send(packet(k));
            seen.push(follower.receive(k as f64 * 1e-3).map(|p| p.seq));
        }
        assert!(seen[..10].iter().all(Option::is_none), "{seen:?}");
        for (k, s) in seen.iter().enumerate().skip(10) {
            assert_eq!(*s, Some(k as u64 - 10), "tick {k}");
        }
        // Several due at once: only the newest is handed over.
        for k in 40..45 {
            leader.send(packet(k));
        }
        // Taken in at 0.5 s (due 9.5 ms later): only the last of the first forty is due.
        assert_eq!(follower.receive(0.5).map(|p| p.seq), Some(39));
        assert_eq!(follower.receive(1.0).map(|p| p.seq), Some(44));
    }

    #[test]
    fn loss_drops_about_its_fraction_and_jitter_keeps_the_order() {
        let imp = Impairment {
            delay_ms: 50.0,
            jitter_ms: 25.0,
            loss: 0.1,
        };
        let (mut leader, mut follower) = pair(Impairment::default(), imp, 7);
        let mut last = None;
        let n = 20_000u64;
        for k in 0..n {
            leader.send(packet(k));
            if let Some(p) = follower.receive(k as f64 * 1e-3) {
                assert!(last.is_none_or(|l| p.seq > l), "out of order");
                last = Some(p.seq);
            }
        }
        let s = follower.stats();
        let lost = s.lost as f64 / s.received as f64;
        // Binomial: σ = sqrt(0.1·0.9/20000) ≈ 0.002.
        assert!((lost - 0.1).abs() < 0.01, "{lost}");
        assert_eq!(s.received, n);
    }

    /// Issue #42: wave variables were unstable under a jittery delay (100 ms ±50 %); a
    /// playout buffer delivers every packet at one delay, about the largest seen.
    #[test]
    fn a_playout_buffer_turns_a_jittery_delay_into_a_constant_one_at_its_largest() {
        let imp = Impairment {
            delay_ms: 50.0,
            jitter_ms: 25.0,
            loss: 0.0,
        };
        let run = |playout: bool| {
            let (mut leader, mut follower) = pair(Impairment::default(), imp, 7);
            follower.set_playout(playout);
            // Each packet's delay as delivered, over the last of 5 s (after the first
            // seconds have shown the largest delay).
            let mut delays = Vec::new();
            for k in 0..5000u64 {
                let t = k as f64 * 1e-3;
                leader.send(Packet {
                    seq: k,
                    t,
                    ..Packet::default()
                });
                if let Some(p) = follower.receive(t) {
                    if k >= 4000 {
                        delays.push(t - p.t);
                    }
                }
            }
            let lo = delays.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = delays.iter().copied().fold(0.0, f64::max);
            (delays.len(), lo, hi)
        };
        // Without: the delay wanders over the jitter's span and packets come in bursts
        // (only the newest of a burst is handed over).
        let (n, lo, hi) = run(false);
        assert!(hi - lo > 0.02 && n < 900, "{n} {lo} {hi}");
        // With: one packet a tick, nearly all of them held to one delay near the largest
        // (the 99th percentile of 25–75 ms: 74.5 ms).
        let (n, lo, hi) = run(true);
        assert!(n >= 980, "{n}");
        assert!(lo > 0.070 && hi < 0.0765, "{lo} {hi}");
    }

    #[test]
    fn a_full_queue_drops_at_the_sender_and_says_so() {
        let (mut leader, mut follower) = pair(Impairment::default(), Impairment::default(), 1);
        for k in 0..(QUEUE as u64 + 10) {
            leader.send(packet(k));
        }
        assert_eq!(leader.stats().sent, QUEUE as u64);
        assert_eq!(leader.stats().send_dropped, 10);
        assert_eq!(follower.receive(0.0).map(|p| p.seq), Some(QUEUE as u64 - 1));
    }
}
