//! The station's host: the one thread that owns an arm's station and runs the loop around it
//! (docs/ARCHITECTURE.md, The daemon). It waits in one `poll` on the servo's wake-up and on
//! whatever its ports wait on, lets each port serve what came in, hands the station's output
//! (states encoded once for every client of every port, events, late answers) to the ports,
//! and expires what waited too long. A transport is a [`Port`]: the Unix socket
//! (`transport::unix`) and zenoh (`transport::zenoh::port`) are two; a third is one more
//! implementation added where `cmd::serve` lists them.

use super::json;
use super::protocol::Request;
use crate::station::{Output, SessionId, Station, StationReport, StationSetup, Tap};
use serde_json::Value;
use std::collections::HashMap;
use std::io;
use std::os::fd::AsRawFd;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long `poll` waits when nothing happens: the stop flag is seen this soon.
const POLL_MS: i32 = 50;

/// How long the goodbye may take to leave at the end, never blocking on a stuck client.
const GOODBYE: Duration = Duration::from_millis(100);

/// A transport on the station: its clients become the station's sessions. Everything a port
/// does happens on the host's thread, between two `poll`s, and never blocks.
pub trait Port: Send {
    /// The descriptors this port waits on, appended to `fds` (their order is the port's own).
    fn interest(&self, fds: &mut Vec<libc::pollfd>);
    /// Serve what came in. `ready` is this port's part of `poll`'s answer, in the order
    /// [`Port::interest`] gave; a port may also look for work that no descriptor announced.
    fn serve(&mut self, ready: &[libc::pollfd], desk: &mut Desk<'_>);
    /// A state message (encoded once, shared): for its sessions that stream tick `seq`.
    fn state(&mut self, seq: u64, message: &Arc<[u8]>);
    /// An event message, for every greeted session.
    fn event(&mut self, message: &Arc<[u8]>);
    /// The late answer to a request of `session`, one of this port's.
    fn answer(&mut self, session: SessionId, message: Vec<u8>);
    /// Add this port's part to a `status` reply; `local` when the asker is on this PC.
    fn status(&self, _status: &mut Value, _local: bool) {}
    /// Whether this port's clients are on this PC (they may be shown local paths).
    fn local(&self) -> bool;
    /// Send what is queued; forget clients that are gone (their sessions close).
    fn flush(&mut self, desk: &mut Desk<'_>);
    /// Close what has waited too long.
    fn expire(&mut self, now: Instant, desk: &mut Desk<'_>);
    /// The servo has ended: say goodbye to every client.
    fn goodbye(&mut self, desk: &mut Desk<'_>);
    /// Messages are still queued (the goodbye has not left yet).
    fn pending(&self) -> bool {
        false
    }
    /// What must outlive the arm's end (the socket's connections close only after the final
    /// safe packet went out).
    fn close(self: Box<Self>) -> Box<dyn Send>;
}

/// A request the station answers later: who asked, and the id to echo.
struct Pending {
    port: usize,
    session: SessionId,
    id: Option<Value>,
}

/// What a port may use while it serves: the station, and where a late answer is awaited.
pub struct Desk<'a> {
    pub(crate) station: &'a mut Station,
    later: &'a mut HashMap<u64, Pending>,
    port: usize,
}

impl Desk<'_> {
    /// A greeted session's request (`json::serve`): what to send now; an answer the station
    /// gives later goes back to this port, to `session`.
    pub(crate) fn serve(&mut self, session: SessionId, request: Request) -> json::Served {
        let served = json::serve(self.station, session, request);
        if let Some((ticket, id)) = served.later.clone() {
            let port = self.port;
            self.later.insert(ticket, Pending { port, session, id });
        }
        served
    }
}

/// What the host saw, for the daemon's exit.
pub struct HostReport {
    /// The station's report (faults, dumps, the ring, the recording's end).
    pub(crate) station: StationReport,
    /// What the ports keep until the report is dropped (the clients' connections).
    _kept: Vec<Box<dyn Send>>,
}

/// The thread that owns one arm's station and serves it through its ports.
pub struct Host {
    station: Station,
    ports: Vec<Box<dyn Port>>,
    later: HashMap<u64, Pending>,
}

impl Host {
    /// A host for the arm's station that `cmd::serve::prepare_arm` set up.
    pub fn new(station: StationSetup) -> Host {
        Host {
            station: Station::new(station),
            ports: Vec::new(),
            later: HashMap::new(),
        }
    }

    /// Add a consumer of every tick and event of this arm (a recorder, another transport's
    /// feed) before serving.
    pub fn add_tap(&mut self, tap: Box<dyn Tap>) {
        self.station.add_tap(tap);
    }

    /// Serve the arm through `port` too.
    pub fn add_port(&mut self, port: Box<dyn Port>) {
        self.ports.push(port);
    }

    /// Serve until the servo thread has ended (its record channel closes).
    pub fn run(mut self) -> HostReport {
        let mut fds = Vec::new();
        loop {
            let servo_done = self.pump();
            self.each_port(|p, desk| p.flush(desk));
            if servo_done {
                break;
            }
            if let Err(e) = self.poll_once(&mut fds) {
                crate::errln!("omnid serve: poll: {e}");
                std::thread::sleep(Duration::from_millis(POLL_MS as u64));
            }
            let now = Instant::now();
            self.each_port(|p, desk| p.expire(now, desk));
        }
        self.finish()
    }

    /// Run `f` on every port with its desk.
    fn each_port(&mut self, mut f: impl FnMut(&mut dyn Port, &mut Desk<'_>)) {
        let Host {
            station,
            ports,
            later,
        } = self;
        for (port, p) in ports.iter_mut().enumerate() {
            let mut desk = Desk {
                station,
                later,
                port,
            };
            f(p.as_mut(), &mut desk);
        }
    }

    /// Hand what the station has to the ports: states to those streaming, events to all,
    /// late answers to who asked.
    fn pump(&mut self) -> bool {
        let Host {
            station,
            ports,
            later,
        } = self;
        station.pump(&mut |o| match o {
            Output::State(state) => {
                let message = json::state(state);
                for p in ports.iter_mut() {
                    p.state(state.seq, &message);
                }
            }
            Output::Event(e) => {
                let message = json::event(e);
                for p in ports.iter_mut() {
                    p.event(&message);
                }
            }
            Output::Done {
                ticket, op, result, ..
            } => {
                let Some(w) = later.remove(&ticket) else {
                    return;
                };
                let mut v = json::answer(op, w.id.as_ref(), result);
                if v["status"].is_object() {
                    let local = ports[w.port].local();
                    for p in ports.iter() {
                        p.status(&mut v["status"], local);
                    }
                }
                ports[w.port].answer(w.session, json::encode(&v));
            }
        })
    }

    /// Wait for the servo's wake-up or any port's descriptor, then let every port serve.
    fn poll_once(&mut self, fds: &mut Vec<libc::pollfd>) -> io::Result<()> {
        fds.clear();
        fds.push(libc::pollfd {
            fd: self.station.wake().fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        });
        let mut ends = Vec::with_capacity(self.ports.len());
        for p in &self.ports {
            p.interest(fds);
            ends.push(fds.len());
        }
        // SAFETY: `fds` is a live array of `fds.len()` pollfd structs.
        let rc = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, POLL_MS) };
        if rc < 0 {
            let e = io::Error::last_os_error();
            return if e.kind() == io::ErrorKind::Interrupted {
                Ok(())
            } else {
                Err(e)
            };
        }
        if fds[0].revents != 0 {
            self.station.wake().clear();
        }
        let mut start = 1;
        self.each_port(|p, desk| {
            let end = ends[desk.port];
            p.serve(&fds[start..end], desk);
            start = end;
        });
        Ok(())
    }

    /// The servo has ended: say goodbye, finish the station, hand back the report.
    fn finish(mut self) -> HostReport {
        self.each_port(|p, desk| p.goodbye(desk));
        let until = Instant::now() + GOODBYE;
        while self.ports.iter().any(|p| p.pending()) && Instant::now() < until {
            self.each_port(|p, desk| p.flush(desk));
            std::thread::sleep(Duration::from_millis(1));
        }
        let kept = std::mem::take(&mut self.ports)
            .into_iter()
            .map(|p| p.close())
            .collect();
        HostReport {
            station: self.station.finish(),
            _kept: kept,
        }
    }
}
