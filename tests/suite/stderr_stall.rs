//! A daemon whose stderr nobody drains (a paused pager, a stalled log collector) keeps serving
//! its clients, and a stop signal still ends it within a bounded time.

use crate::common;

use common::omnid;
use omnid::transport::client::Client;
use serde_json::json;
use std::os::fd::{FromRawFd, OwnedFd};
use std::process::Stdio;
use std::time::{Duration, Instant};

#[test]
#[ignore = "paced"]
fn a_stderr_nobody_reads_blocks_neither_the_clients_nor_the_stop() {
    // A pipe of one page whose reading end is never read.
    let mut fds = [0; 2];
    // SAFETY: `fds` has room for the two descriptors.
    assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
    // SAFETY: both descriptors are new and owned here alone.
    let (_unread, write_end) =
        unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) };
    // SAFETY: plain fcntl on an owned descriptor.
    unsafe { libc::fcntl(fds[1], libc::F_SETPIPE_SZ, 4096) };
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("sim.sock");
    let mut child = omnid()
        .args(["serve", "--device", "sim", "--socket"])
        .arg(&socket)
        .env("OMNID_STATE_DIR", dir.path().join("state"))
        .stdout(Stdio::null())
        .stderr(Stdio::from(write_end))
        .spawn()
        .unwrap();
    // A daemon blocked on stderr would block these clients too: a watchdog ends it, so the
    // test fails instead of hanging.
    let pid = child.id() as i32;
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watching = done.clone();
    std::thread::spawn(move || {
        let until = Instant::now() + Duration::from_secs(90);
        while Instant::now() < until {
            if watching.load(std::sync::atomic::Ordering::SeqCst) {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        // SAFETY: kill with the child's pid (not yet waited for while not done).
        unsafe { libc::kill(pid, libc::SIGKILL) };
    });
    let until = Instant::now() + Duration::from_secs(20);
    let mut c = loop {
        match Client::connect(&socket, "steady") {
            Ok(c) => break c,
            Err(_) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => panic!("no daemon: {e}"),
        }
    };
    // Each client that asks and never reads is cut off with a line on stderr: far more than
    // the pipe holds.
    for k in 0..60 {
        let flood = Client::connect(&socket, "flood").unwrap();
        let mut sent = 0;
        while flood.send(&json!({"op": "status", "id": k})).is_ok() && sent < 20_000 {
            sent += 1;
        }
        assert!(sent < 20_000, "flood {k} was never cut off");
        // The steady client is served all along.
        c.request(json!({"op": "status"}))
            .unwrap_or_else(|e| panic!("after flood {k}: {e}"));
    }
    // SAFETY: kill with a live child's pid.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    let until = Instant::now() + Duration::from_secs(15);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("SIGTERM did not end a daemon whose stderr is full");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    done.store(true, std::sync::atomic::Ordering::SeqCst);
    assert_eq!(status.code(), Some(130));
    assert!(!socket.exists(), "socket removed");
}
