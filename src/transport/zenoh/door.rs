//! The bounded pipes between an arm's host and its zenoh side: requests in (remote clients'
//! messages, their comings and goings, ROS 2 commands), and out (messages for remote clients
//! from the port, ticks from the tap). Neither side ever waits on the other: the host runs at
//! SCHED_FIFO and zenoh's threads do not, so the pipes are `handoff` queues (docs/DESIGN.md
//! §4.7), and a full pipe drops, and the drop is counted.

use crate::handoff::{self, Bell, Inlet, Outlet, Refused, SharedInlet};
use crate::servo::Wake;
use crate::station::Op;
use crate::telemetry::record::TickRecord;
use serde::Serialize;
use std::cell::RefCell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Messages and ticks queued toward the network per arm before new ones are dropped.
const OUT_QUEUE: usize = 4096;

/// What came from the network for the hub.
pub(crate) enum Inbound {
    /// A remote client's message, JSON as a socket client sends it, with the sample's
    /// attachment when it was an authentication tag's length (`bind`).
    Message {
        cid: Arc<str>,
        bytes: Vec<u8>,
        tag: Option<[u8; super::bind::TAG_LEN]>,
    },
    /// A remote client's liveliness token appeared.
    Joined(Arc<str>),
    /// It went away (the client closed, or its session died).
    Gone(Arc<str>),
    /// A ROS 2 command, already a station op.
    Ros(Op),
}

/// What goes to the network.
pub(crate) enum Outbound {
    /// One tick, for the ROS 2 topics.
    Tick(Box<TickRecord>),
    /// A message for one remote client.
    ToClient { cid: Arc<str>, bytes: Arc<[u8]> },
    /// A remote client has gone: its publisher is undeclared.
    Forget(Arc<str>),
}

/// What the zenoh side of one arm counted (in `status` as `zenoh`, and said at exit).
#[derive(Debug, Default)]
pub struct ZenohStats {
    /// Samples taken from the network (commands and client messages).
    pub received: AtomicU64,
    /// Samples refused: too large, not decodable, not a known client, not allowed.
    pub refused: AtomicU64,
    /// Samples dropped because the hub's inbox was full (a flood).
    pub dropped_in: AtomicU64,
    /// Samples put to the network.
    pub published: AtomicU64,
    /// Ticks or messages dropped because the network side was behind.
    pub dropped_out: AtomicU64,
    /// Remote clients' requests refused because the client already had its share of the
    /// arm's time waiting (`throttled_clients` in status says whose).
    pub throttled: AtomicU64,
    /// Requests on a bound remote client's id without its authentication code, or with a
    /// counter already taken: another session's, or replayed (docs/ZENOH.md); and hellos whose
    /// key was refused.
    pub forged: AtomicU64,
}

/// [`ZenohStats`] read once, for `status`.
#[derive(Debug, Clone, Copy, Serialize, PartialEq, Eq)]
pub struct StatsSnapshot {
    pub received: u64,
    pub refused: u64,
    pub dropped_in: u64,
    pub published: u64,
    pub dropped_out: u64,
    pub throttled: u64,
    pub forged: u64,
}

impl ZenohStats {
    pub(crate) fn count(c: &AtomicU64) {
        c.fetch_add(1, Ordering::Relaxed);
    }

    /// Every counter, now.
    pub fn snapshot(&self) -> StatsSnapshot {
        let r = |c: &AtomicU64| c.load(Ordering::Relaxed);
        StatsSnapshot {
            received: r(&self.received),
            refused: r(&self.refused),
            dropped_in: r(&self.dropped_in),
            published: r(&self.published),
            dropped_out: r(&self.dropped_out),
            throttled: r(&self.throttled),
            forged: r(&self.forged),
        }
    }
}

/// The hub's side of an arm's zenoh transport.
pub struct Door {
    pub(crate) inbox: Outlet<Inbound>,
    /// Messages for remote clients (the port's `&self` methods send too; one thread).
    out: RefCell<Inlet<Outbound>>,
    pub(crate) wake: Arc<Wake>,
    pub(crate) stats: Arc<ZenohStats>,
    /// Commands over zenoh are allowed (`[zenoh] allow_commands`).
    pub(crate) allow_commands: bool,
    /// A ROS 2 commander silent this long loses the lease, ms.
    pub(crate) lease_lapse_ms: f64,
}

/// The network's side (cloned into every zenoh callback of the arm).
#[derive(Clone)]
pub(crate) struct NetSide {
    inbox: Arc<SharedInlet<Inbound>>,
    wake: Arc<Wake>,
    pub(crate) stats: Arc<ZenohStats>,
    pub(crate) max_sample_bytes: usize,
}

/// The way out to the network: the tap's end for ticks, and what the network thread reads.
pub(crate) struct Outbox {
    pub(crate) ticks: Inlet<Outbound>,
    pub(crate) feed: Feed,
}

/// The network thread's end of the pipes out: it sleeps on a bell both producers ring.
pub(crate) struct Feed {
    messages: Outlet<Outbound>,
    ticks: Outlet<Outbound>,
    bell: Arc<Bell>,
    /// Which pipe is read first next time (each in turn, so neither starves the other).
    ticks_first: bool,
}

impl Feed {
    /// What to publish next, waiting for it; None once the tap has let go of its end and both
    /// pipes are drained (the arm has ended).
    pub(crate) fn next(&mut self) -> Option<Outbound> {
        loop {
            self.ticks_first = !self.ticks_first;
            let (a, b) = if self.ticks_first {
                (&mut self.ticks, &mut self.messages)
            } else {
                (&mut self.messages, &mut self.ticks)
            };
            if let Some(m) = a.pop().or_else(|| b.pop()) {
                return Some(m);
            }
            if self.ticks.is_closed() {
                return None;
            }
            self.bell.wait(Duration::from_millis(100));
        }
    }
}

impl Door {
    /// Both sides of one arm's door, the inbox holding `inbox` requests.
    pub(crate) fn pair(
        inbox: usize,
        allow_commands: bool,
        lease_lapse_ms: f64,
    ) -> std::io::Result<(Door, NetSide, Outbox)> {
        let (in_tx, in_rx) = handoff::queue(inbox);
        let bell = Arc::new(Bell::new()?);
        let (out_tx, out_rx) = handoff::queue(OUT_QUEUE);
        let (ticks_tx, ticks_rx) = handoff::queue(OUT_QUEUE);
        let wake = Arc::new(Wake::new()?);
        let stats = Arc::new(ZenohStats::default());
        Ok((
            Door {
                inbox: in_rx,
                out: RefCell::new(out_tx.ringing(bell.clone())),
                wake: wake.clone(),
                stats: stats.clone(),
                allow_commands,
                lease_lapse_ms,
            },
            NetSide {
                inbox: Arc::new(in_tx.shared()),
                wake,
                stats,
                max_sample_bytes: usize::MAX,
            },
            Outbox {
                ticks: ticks_tx.ringing(bell.clone()),
                feed: Feed {
                    messages: out_rx,
                    ticks: ticks_rx,
                    bell,
                    ticks_first: false,
                },
            },
        ))
    }

    /// Queue a message for a remote client (dropped and counted when the network is behind).
    pub(crate) fn to_client(&self, cid: &Arc<str>, bytes: Arc<[u8]>) {
        let m = Outbound::ToClient {
            cid: cid.clone(),
            bytes,
        };
        if self.out.borrow_mut().push(m).is_err() {
            ZenohStats::count(&self.stats.dropped_out);
        }
    }
}

impl Door {
    /// Remote client `cid` has gone: the network side drops what it kept for it (queued
    /// behind its last messages, so they still leave).
    pub(crate) fn forget(&self, cid: &Arc<str>) {
        if self
            .out
            .borrow_mut()
            .push(Outbound::Forget(cid.clone()))
            .is_err()
        {
            ZenohStats::count(&self.stats.dropped_out);
        }
    }
}

impl NetSide {
    /// Hand a request to the hub and wake it; a full inbox drops it (counted).
    pub(crate) fn send(&self, m: Inbound) {
        ZenohStats::count(&self.stats.received);
        match self.inbox.push(m) {
            Ok(()) => self.wake.notify(),
            Err(Refused::Full) => ZenohStats::count(&self.stats.dropped_in),
            Err(Refused::Closed) => {}
        }
    }

    /// Count a sample refused before it reached the hub.
    pub(crate) fn refuse(&self) {
        ZenohStats::count(&self.stats.received);
        ZenohStats::count(&self.stats.refused);
    }
}
