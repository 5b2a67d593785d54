//! The HD error stack: per thread (an error a call made on the main thread never ends the
//! servo callback of a client that stops on any error, docs/HDAPI.md, Behaviours), most
//! recent first, bounded.

use crate::consts::*;
use std::cell::RefCell;

/// `HDErrorInfo`: 12 bytes, fields at 0, 4 and 8 (docs/HDAPI.md, Types and ABI).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HDErrorInfo {
    pub error_code: u32,
    pub internal_error_code: i32,
    pub h_hd: u32,
}

/// Errors kept per thread; older ones are dropped past this.
const DEPTH: usize = 32;

thread_local! {
    static STACK: RefCell<Vec<HDErrorInfo>> = const { RefCell::new(Vec::new()) };
}

/// Push an error for `hhd` (`internal` is one of [`Internal`]'s codes).
pub fn push(code: u32, internal: Internal, hhd: u32) {
    let _ = STACK.try_with(|s| {
        let mut s = s.borrow_mut();
        if s.len() == DEPTH {
            s.remove(0);
        }
        s.push(HDErrorInfo {
            error_code: code,
            internal_error_code: internal as i32,
            h_hd: hhd,
        });
    });
}

/// Pop the most recent error; `HD_SUCCESS` when there is none.
pub fn pop() -> HDErrorInfo {
    STACK
        .try_with(|s| s.borrow_mut().pop())
        .ok()
        .flatten()
        .unwrap_or(HDErrorInfo {
            error_code: HD_SUCCESS,
            internal_error_code: 0,
            h_hd: HD_INVALID_HANDLE,
        })
}

/// What went wrong inside, as `internalErrorCode` (docs/HDAPI.md, Errors).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(i32)]
pub enum Internal {
    None = 0,
    /// No `omnid serve` at the socket.
    NoDaemon = 1,
    /// The daemon refused or closed the connection.
    Refused = 2,
    /// Another client holds the daemon's command lease.
    LeaseHeld = 3,
    /// A null pointer where the call needs one.
    NullPointer = 4,
    /// The daemon answered nothing in time.
    Timeout = 5,
    /// A panic inside the library, caught at the C boundary.
    Panic = 6,
    /// Frames that set a force come further apart than its longest time to live (100 ms): the
    /// force lapses between them (`HD_TIMER_ERROR`).
    SlowFrames = 7,
    /// The daemon's safety layer held the force or torque back (`HD_EXCEEDED_MAX_FORCE`,
    /// `HD_WARM_MOTORS`), once per episode, or tripped on a joint's speed
    /// (`HD_EXCEEDED_MAX_VELOCITY`).
    DaemonLimit = 8,
    /// The daemon's servo loop stalled past its deadline (`HD_TIMER_ERROR`).
    ServoStall = 9,
}

/// `hdGetErrorString`: a static, NUL-terminated description of `code`.
pub fn describe(code: u32) -> &'static [u8] {
    match code {
        HD_SUCCESS => b"No error\0",
        HD_INVALID_ENUM => b"Invalid enumerant (not supported by omnid's libHD)\0",
        HD_INVALID_VALUE => b"Invalid value\0",
        HD_INVALID_OPERATION => b"Invalid operation\0",
        HD_INVALID_INPUT_TYPE => b"Invalid input type\0",
        HD_BAD_HANDLE => b"Invalid device handle\0",
        HD_WARM_MOTORS => b"Motors are warm\0",
        HD_EXCEEDED_MAX_FORCE => b"Exceeded the maximum force\0",
        HD_EXCEEDED_MAX_FORCE_IMPULSE => b"Exceeded the maximum force impulse\0",
        HD_EXCEEDED_MAX_VELOCITY => {
            b"Exceeded the maximum velocity (omnid's safety layer stopped the arm: \
              safety.max_velocity_rad_s)\0"
        }
        HD_FORCE_ERROR => b"Force error\0",
        HD_DEVICE_FAULT => b"Device fault\0",
        HD_DEVICE_ALREADY_INITIATED => {
            b"Device already in use (another client holds omnid's command lease)\0"
        }
        HD_COMM_ERROR => {
            b"Communication error: no omnid serve daemon answered (is `omnid serve` running? \
              set OMNID_SOCKET to its socket)\0"
        }
        HD_COMM_CONFIG_ERROR => b"Communication configuration error\0",
        HD_TIMER_ERROR => {
            b"Scheduler timer error (the servo loop missed its deadline, or frames that push \
              came too far apart)\0"
        }
        HD_ILLEGAL_BEGIN => b"Illegal begin frame\0",
        HD_ILLEGAL_END => b"Illegal end frame (no frame begun)\0",
        HD_FRAME_ERROR => b"Frame error\0",
        HD_INVALID_PRIORITY => b"Invalid scheduler priority\0",
        HD_SCHEDULER_FULL => b"Scheduler full\0",
        HD_INVALID_LICENSE => b"Invalid license\0",
        _ => b"Unknown error\0",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stack_pops_most_recent_first_then_success() {
        push(HD_INVALID_ENUM, Internal::None, 1);
        push(HD_BAD_HANDLE, Internal::None, 2);
        assert_eq!(pop().error_code, HD_BAD_HANDLE);
        assert_eq!(pop().error_code, HD_INVALID_ENUM);
        assert_eq!(pop().error_code, HD_SUCCESS);
    }

    #[test]
    fn error_info_is_twelve_bytes() {
        assert_eq!(std::mem::size_of::<HDErrorInfo>(), 12);
    }
}
