//! The arm's kept weights are written off the host (docs/DESIGN.md §4.7, "Across the realtime
//! boundary"; docs/IDENTIFIER.md, "Kept per arm"): the host runs at SCHED_FIFO and serves
//! streams with a time to live of a few tens of ms, and a save waits on the disk (the write
//! is synced before its rename) for longer than that. So the host hands a copy of the weights
//! to this thread and goes on serving; the removal of `weights reset` goes the same way, so it
//! is done after every save asked before it.
//!
//! The hand-off is the wait-free ring of `crate::handoff` (the host never waits for this
//! thread). A save waiting behind a newer one is dropped (the newer holds more of what the arm
//! learned); a removal is never dropped. A failed save is said on stderr, as before; a removal's
//! outcome comes back to the host for the reset's answer.

use crate::handoff::{queue, Bell, Inlet, Outlet};
use crate::identifier::Identifier;
use crate::servo::Wake;
use crate::station::SessionId;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// Writes the kept weights: the store's whole-file save, or a test's stand-in.
pub type Writer =
    Box<dyn FnMut(&Path, &Identifier, &str, Option<&str>) -> Result<(), String> + Send>;

/// What the saver is asked to do, in order.
pub(crate) enum Job {
    /// Keep these weights.
    Save(Box<Identifier>),
    /// Remove the kept file (`weights_reset`, with its ticket and session).
    Remove { ticket: u64, session: SessionId },
}

/// A removal done: its ticket, session and outcome (`Ok(true)`: a file was removed).
pub(crate) struct Removed {
    pub ticket: u64,
    pub session: SessionId,
    pub result: Result<bool, String>,
}

/// The host's end of the saver thread.
pub(crate) struct Saver {
    inlet: Option<Inlet<Job>>,
    bell: Arc<Bell>,
    done: Outlet<Removed>,
    /// Jobs the ring had no room for yet (handed on at the next pump).
    backlog: VecDeque<Job>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Jobs in flight: saves come once a minute, so a full ring means a stuck disk.
const CAPACITY: usize = 4;

impl Saver {
    /// A saver of `path` for `arm` (with its `serial`), writing with the store.
    pub(crate) fn spawn(
        path: PathBuf,
        arm: String,
        serial: Option<String>,
        wake: Arc<Wake>,
    ) -> std::io::Result<Saver> {
        let writer: Writer = Box::new(crate::identifier::store::save);
        Saver::spawn_with(path, arm, serial, wake, writer)
    }

    /// A saver whose writes are `writer`'s (the store's, or a test's).
    pub(crate) fn spawn_with(
        path: PathBuf,
        arm: String,
        serial: Option<String>,
        wake: Arc<Wake>,
        mut writer: Writer,
    ) -> std::io::Result<Saver> {
        let bell = Arc::new(Bell::new()?);
        let (inlet, mut jobs) = queue::<Job>(CAPACITY);
        let (mut done_in, done) = queue::<Removed>(CAPACITY);
        let rung = bell.clone();
        let thread = std::thread::Builder::new()
            .name(format!("omnid-saver-{arm}"))
            .spawn(move || {
                normal_scheduler();
                let mut batch = Vec::new();
                loop {
                    while let Some(j) = jobs.pop() {
                        batch.push(j);
                    }
                    if batch.is_empty() {
                        if jobs.is_closed() {
                            break;
                        }
                        rung.wait(Duration::from_millis(500));
                        continue;
                    }
                    let n = batch.len();
                    for (i, job) in batch.drain(..).enumerate() {
                        match job {
                            // A later job overrides this save (a newer save, or a removal).
                            Job::Save(_) if i + 1 < n => {}
                            Job::Save(id) => {
                                if let Err(e) = writer(&path, &id, &arm, serial.as_deref()) {
                                    crate::errln!(
                                        "omnid: warning: arm {arm}: learned weights not kept: {e}"
                                    );
                                }
                            }
                            Job::Remove { ticket, session } => {
                                let mut r = Removed {
                                    ticket,
                                    session,
                                    result: remove_kept(&path),
                                };
                                // The host takes them at every pump: wait for room (this
                                // thread may wait; the host never does).
                                while let Err(back) = done_in.push_or_return(r) {
                                    if done_in.is_closed() {
                                        break;
                                    }
                                    r = back;
                                    std::thread::sleep(Duration::from_millis(5));
                                }
                                wake.notify();
                            }
                        }
                    }
                }
            })?;
        Ok(Saver {
            inlet: Some(inlet.ringing(bell.clone())),
            bell,
            done,
            backlog: VecDeque::new(),
            thread: Some(thread),
        })
    }

    /// Ask for `job` without waiting: a save still waiting here behind another is dropped.
    pub(crate) fn ask(&mut self, job: Job) {
        if matches!(job, Job::Save(_)) && matches!(self.backlog.back(), Some(Job::Save(_))) {
            self.backlog.pop_back();
        }
        self.backlog.push_back(job);
        self.hand_on();
    }

    /// Hand the backlog to the thread, as far as the ring has room.
    pub(crate) fn hand_on(&mut self) {
        let Some(inlet) = &mut self.inlet else {
            return;
        };
        while let Some(job) = self.backlog.pop_front() {
            if let Err(job) = inlet.push_or_return(job) {
                self.backlog.push_front(job);
                break;
            }
        }
    }

    /// A removal done, if one is.
    pub(crate) fn removed(&mut self) -> Option<Removed> {
        self.done.pop()
    }

    /// Hand on what is left, let the thread finish every job and end (the daemon's last save
    /// comes after this: docs/IDENTIFIER.md "Kept per arm"). The host's end waits here: the
    /// servo has ended and no stream is served any more.
    pub(crate) fn finish(&mut self) {
        while !self.backlog.is_empty() && self.thread.as_ref().is_some_and(|t| !t.is_finished()) {
            self.hand_on();
            if !self.backlog.is_empty() {
                while self.done.pop().is_some() {}
                std::thread::sleep(Duration::from_millis(5));
            }
        }
        self.inlet = None;
        self.bell.ring();
        if let Some(t) = self.thread.take() {
            // Removals done meanwhile are taken (nobody is left to answer), so that the
            // thread never waits for room to hand one back.
            while !t.is_finished() {
                while self.done.pop().is_some() {}
                std::thread::sleep(Duration::from_millis(1));
            }
            if t.join().is_err() {
                crate::errln!("omnid: warning: the weights saver thread panicked");
            }
        }
    }
}

impl Drop for Saver {
    fn drop(&mut self) {
        self.finish();
    }
}

/// Remove the kept weights at `path`: `Ok(true)` removed, `Ok(false)` there was none.
pub(crate) fn remove_kept(path: &Path) -> Result<bool, String> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(e.to_string()),
    }
}

/// This thread on the normal scheduler (it was spawned from the SCHED_FIFO host, whose policy
/// it inherits): it waits on the disk, and nothing waits for it.
fn normal_scheduler() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: a live sched_param for this thread; a failure leaves the policy as it was.
    let _ = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_OTHER, &param) };
}
