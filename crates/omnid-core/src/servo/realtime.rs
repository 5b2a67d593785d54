//! Realtime set-up of the servo thread (docs/DESIGN.md §4.7): SCHED_FIFO, locked memory, optional
//! CPU pinning, a prefaulted stack, and SIGINT/SIGTERM blocked so the Ctrl-C handler never runs
//! on this thread. Each step is configurable; a step that is not permitted gives one warning
//! naming the fix and the run goes on.

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// The `[realtime]` section: the realtime steps taken on the servo thread of a paced run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RealtimeConfig {
    /// SCHED_FIFO priority of the servo thread (1..=99); 0 leaves the normal scheduler.
    pub fifo_priority: i32,
    /// Lock all current and future memory (mlockall) so no page fault hits the loop.
    pub lock_memory: bool,
    /// Pin the servo thread to this CPU (-1: no pinning).
    pub cpu: i32,
    /// Touch this much stack before the first tick, KiB.
    pub prefault_stack_kib: usize,
}

impl Default for RealtimeConfig {
    fn default() -> Self {
        RealtimeConfig {
            fifo_priority: 80,
            lock_memory: true,
            cpu: -1,
            prefault_stack_kib: 256,
        }
    }
}

impl RealtimeConfig {
    /// Check every value; the first problem names its field (`realtime.…`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(0..=99).contains(&self.fifo_priority) {
            return Err(check::invalid(
                "realtime.fifo_priority",
                self.fifo_priority.to_string(),
                "0 ..= 99",
            ));
        }
        let cpus = std::thread::available_parallelism()
            .map(|n| n.get() as i32)
            .unwrap_or(1);
        if self.cpu < -1 || self.cpu >= cpus.max(1024) {
            return Err(check::invalid(
                "realtime.cpu",
                self.cpu.to_string(),
                "-1 or a CPU number",
            ));
        }
        if self.prefault_stack_kib > 1024 {
            return Err(check::invalid(
                "realtime.prefault_stack_kib",
                self.prefault_stack_kib.to_string(),
                "0 ..= 1024 (the servo thread's stack is 2 MiB)",
            ));
        }
        Ok(())
    }
}

/// Which steps took effect, for the summary.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RealtimeReport {
    /// The SCHED_FIFO priority the thread got (null: normal scheduler).
    pub fifo_priority: Option<i32>,
    /// Whether memory was locked.
    pub memory_locked: bool,
    /// The CPU the thread was pinned to (null: not pinned).
    pub cpu: Option<i32>,
    /// Stack touched before the first tick, KiB.
    pub stack_prefaulted_kib: usize,
    /// Whether SIGINT and SIGTERM were blocked on the thread.
    pub signals_blocked: bool,
    /// One line per step that was asked for but not permitted.
    pub warnings: Vec<String>,
}

use omnid_client::realtime::LIMITS_HINT;

#[inline(never)]
fn prefault_stack(kib: usize) {
    // Touch each page of a stack buffer so later calls find it mapped.
    let mut buf = [0u8; 1024 * 1024];
    let n = (kib * 1024).min(buf.len());
    let mut i = 0;
    while i < n {
        // SAFETY: i < buf.len(); volatile keeps the writes from being optimised away.
        unsafe { std::ptr::write_volatile(buf.as_mut_ptr().add(i), 1) };
        i += 4096;
    }
    std::hint::black_box(&buf);
}

/// Lock the process's memory: every page mapped now, populated at once (the servo's, built
/// before its first tick), and every page mapped later as it is first touched
/// (`MCL_ONFAULT`). Not `MCL_FUTURE` alone: then each later `mmap`, heap growth or thread
/// stack of any thread (zenoh's, a client's arrival) is filled page by page while that thread
/// holds the process's memory-map lock, and a thread of the normal scheduler preempted there
/// by a busy CPU kept an arm's SCHED_FIFO host waiting in its own heap growth for tens of ms
/// (docs/DESIGN.md §4.7). A kernel without `MCL_ONFAULT` (before 4.4) locks future memory as
/// before.
fn lock_memory() -> std::io::Result<()> {
    // SAFETY: mlockall has no memory-safety preconditions.
    if unsafe { libc::mlockall(libc::MCL_CURRENT) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    // MCL_FUTURE without MCL_CURRENT leaves the mappings just locked as they are.
    // SAFETY: as above.
    if unsafe { libc::mlockall(libc::MCL_FUTURE | libc::MCL_ONFAULT) } == 0 {
        return Ok(());
    }
    let e = std::io::Error::last_os_error();
    if e.raw_os_error() != Some(libc::EINVAL) {
        return Err(e);
    }
    // SAFETY: as above.
    if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Apply the configured steps to the calling thread (the servo thread, before its first tick).
pub fn apply(cfg: &RealtimeConfig) -> RealtimeReport {
    let mut r = RealtimeReport::default();

    // Signals: Ctrl-C and SIGTERM are handled by the ctrlc thread, never in the loop.
    // SAFETY: plain libc calls on a zeroed, then initialised, sigset_t.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigaddset(&mut set, libc::SIGTERM);
        libc::sigaddset(&mut set, libc::SIGHUP);
        r.signals_blocked = libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut()) == 0;
    }

    if cfg.lock_memory {
        match lock_memory() {
            Ok(()) => r.memory_locked = true,
            Err(e) => r
                .warnings
                .push(format!("memory lock not permitted ({e}): {LIMITS_HINT}")),
        }
    }

    if cfg.cpu >= 0 {
        // SAFETY: cpu_set_t is plain data; CPU_SET is bounds-checked by the check below.
        let ok = unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            if (cfg.cpu as usize) < 8 * std::mem::size_of::<libc::cpu_set_t>() {
                libc::CPU_SET(cfg.cpu as usize, &mut set);
                libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) == 0
            } else {
                false
            }
        };
        if ok {
            r.cpu = Some(cfg.cpu);
        } else {
            r.warnings.push(format!(
                "pinning to CPU {} failed ({}): set realtime.cpu to an online CPU or -1",
                cfg.cpu,
                std::io::Error::last_os_error()
            ));
        }
    }

    if cfg.prefault_stack_kib > 0 {
        prefault_stack(cfg.prefault_stack_kib);
        r.stack_prefaulted_kib = cfg.prefault_stack_kib;
    }

    // Priority last, once everything that may block or allocate is done.
    if cfg.fifo_priority > 0 {
        match set_fifo_priority(cfg.fifo_priority) {
            Ok(()) => r.fifo_priority = Some(cfg.fifo_priority),
            Err(w) => r.warnings.push(w),
        }
    }
    r
}

pub use omnid_client::realtime::set_fifo_priority;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_that_are_off_do_nothing_and_signals_are_blocked() {
        let cfg = RealtimeConfig {
            fifo_priority: 0,
            lock_memory: false,
            cpu: -1,
            prefault_stack_kib: 64,
        };
        let r = std::thread::spawn(move || apply(&cfg)).join().unwrap();
        assert_eq!(r.fifo_priority, None);
        assert!(!r.memory_locked && r.cpu.is_none() && r.warnings.is_empty());
        assert!(r.signals_blocked);
        assert_eq!(r.stack_prefaulted_kib, 64);
    }

    /// A field of /proc/self/status, kB.
    fn status_kb(field: &str) -> u64 {
        let text = std::fs::read_to_string("/proc/self/status").unwrap();
        text.lines()
            .find_map(|l| l.strip_prefix(field))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap()
    }

    /// The child's half of the test below, in a process of its own (the lock is the whole
    /// process's): lock, map 32 MiB, say how much of it was resident before and after touching
    /// it and how much of it was locked after.
    fn lock_then_map() {
        let cfg = RealtimeConfig {
            fifo_priority: 0,
            cpu: -1,
            prefault_stack_kib: 0,
            lock_memory: true,
        };
        let r = apply(&cfg);
        if !r.memory_locked {
            println!("MLOCK not permitted: {:?}", r.warnings);
            return;
        }
        let len = 32 << 20;
        let (rss0, lck0) = (status_kb("VmRSS:"), status_kb("VmLck:"));
        // SAFETY: a fresh private anonymous mapping, checked before use and unmapped here.
        let p = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                len,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        assert_ne!(p, libc::MAP_FAILED);
        let mapped = status_kb("VmRSS:").saturating_sub(rss0);
        for i in (0..len).step_by(4096) {
            // SAFETY: inside the mapping.
            unsafe { std::ptr::write_volatile(p.cast::<u8>().add(i), 1) };
        }
        let touched = status_kb("VmRSS:").saturating_sub(rss0);
        let locked = status_kb("VmLck:").saturating_sub(lck0);
        // SAFETY: the mapping made above.
        unsafe { libc::munmap(p, len) };
        println!("MLOCK mapped={mapped} touched={touched} locked={locked}");
    }

    /// docs/DESIGN.md §4.7: memory a thread maps after the servo locked the process is not
    /// filled at `mmap` (which a thread does holding the process's memory-map lock, where the
    /// normal scheduler may preempt it while an arm's SCHED_FIFO host waits on that lock), but
    /// it is locked once touched.
    #[test]
    fn memory_mapped_after_the_lock_is_locked_as_it_is_touched_not_filled_at_mmap() {
        if std::env::var_os("OMNID_TEST_LOCK_THEN_MAP").is_some() {
            lock_then_map();
            return;
        }
        let out = std::process::Command::new(std::env::current_exe().unwrap())
            .args([
                "--exact",
                "servo::realtime::tests::memory_mapped_after_the_lock_is_locked_as_it_is_touched_not_filled_at_mmap",
                "--nocapture",
                "--test-threads=1",
            ])
            .env("OMNID_TEST_LOCK_THEN_MAP", "1")
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}");
        let line = text
            .lines()
            .find_map(|l| l.find("MLOCK").map(|i| &l[i..]))
            .unwrap_or_else(|| panic!("the child said nothing: {text}"));
        if line.contains("not permitted") {
            eprintln!("skipped, loudly: {line}");
            return;
        }
        let kb = |k: &str| -> u64 {
            let v = line.split(&format!("{k}=")).nth(1).unwrap();
            v.split_whitespace().next().unwrap().parse().unwrap()
        };
        // 32 MiB = 32768 kB; other threads of the child may move RSS a little.
        assert!(kb("mapped") < 8192, "filled at mmap: {line}");
        assert!(kb("touched") >= 30000, "{line}");
        assert!(kb("locked") >= 30000, "locked as touched: {line}");
    }

    #[test]
    fn pinning_to_cpu_zero_works_or_warns() {
        let cfg = RealtimeConfig {
            fifo_priority: 0,
            lock_memory: false,
            cpu: 0,
            prefault_stack_kib: 0,
        };
        let r = std::thread::spawn(move || apply(&cfg)).join().unwrap();
        assert!(r.cpu == Some(0) || r.warnings.len() == 1);
    }

    #[test]
    fn validation_names_the_field() {
        let e = RealtimeConfig {
            fifo_priority: 120,
            ..Default::default()
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("realtime.fifo_priority") && e.contains("0 ..= 99"),
            "{e}"
        );
    }
}
