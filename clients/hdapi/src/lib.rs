//! libHD for omnid: the C ABI of the OpenHaptics HD API (the 36 functions of docs/HDAPI.md)
//! over `omnid serve`, so haptics programs written for the vendor's SDK run unmodified.
//! Installed as `libHD.so.3.4.0` (`clients/hdapi/install.sh`). Every entry point catches
//! panics and checks its pointers: nothing unwinds into C.

pub mod consts;
mod device;
mod error;
mod kin;
mod link;
mod params;
mod registry;
mod scheduler;

use consts::*;
use device::{Device, DeviceError};
use error::{HDErrorInfo, Internal};
use registry::REGISTRY;
use std::collections::HashMap;
use std::ffi::{c_char, c_void, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::sync::{LazyLock, Mutex};

pub use error::HDErrorInfo as ErrorInfo;

/// Run `f`, turning a panic into an HD error and `fallback`.
fn guard<T>(fallback: T, f: impl FnOnce() -> T) -> T {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|_| {
        error::push(HD_INVALID_OPERATION, Internal::Panic, HD_INVALID_HANDLE);
        fallback
    })
}

fn push(code: u32, internal: Internal) {
    error::push(code, internal, REGISTRY.current_handle());
}

fn device_error(e: &DeviceError) -> (u32, Internal) {
    match e {
        DeviceError::NoDaemon(_) => (HD_COMM_ERROR, Internal::NoDaemon),
        DeviceError::Closed => (HD_COMM_ERROR, Internal::Refused),
        DeviceError::Timeout => (HD_COMM_ERROR, Internal::Timeout),
        DeviceError::Refused(_) => (HD_COMM_CONFIG_ERROR, Internal::Refused),
    }
}

/// Whether `OMNID_HD_DEBUG` asks for the reasons behind errors on stderr.
fn debug(message: &str) {
    if std::env::var_os("OMNID_HD_DEBUG").is_some() {
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), "libHD (omnid): {message}");
    }
}

// ---------------------------------------------------------------------------------------
// Devices

/// `HHD hdInitDevice(const char* name)`: connect to the daemon (docs/HDAPI.md, Devices).
///
/// # Safety
/// `name` is NULL or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn hdInitDevice(name: *const c_char) -> u32 {
    let name = if name.is_null() {
        None
    } else {
        // SAFETY: the caller passes a NUL-terminated string (checked non-null above).
        Some(
            unsafe { CStr::from_ptr(name) }
                .to_string_lossy()
                .into_owned(),
        )
    };
    guard(HD_INVALID_HANDLE, || {
        let socket = match device::socket_for(name.as_deref()) {
            Ok(s) => s,
            Err(why) => {
                debug(&why);
                error::push(HD_COMM_ERROR, Internal::NoDaemon, HD_INVALID_HANDLE);
                return HD_INVALID_HANDLE;
            }
        };
        if REGISTRY.all().iter().any(|d| d.socket == socket) {
            error::push(
                HD_DEVICE_ALREADY_INITIATED,
                Internal::None,
                HD_INVALID_HANDLE,
            );
            return HD_INVALID_HANDLE;
        }
        match Device::open(REGISTRY.next_handle(), &socket) {
            Ok(d) => {
                let hhd = REGISTRY.add(d);
                REGISTRY.set_current(hhd);
                if REGISTRY.scheduler.is_running() {
                    take_lease(hhd);
                }
                hhd
            }
            Err(e) => {
                debug(&format!("{}: {e}", socket.display()));
                let (code, internal) = device_error(&e);
                error::push(code, internal, HD_INVALID_HANDLE);
                HD_INVALID_HANDLE
            }
        }
    })
}

/// `void hdDisableDevice(HHD)`: idempotent.
#[no_mangle]
pub extern "C" fn hdDisableDevice(hhd: u32) {
    guard((), || {
        if let Some(d) = REGISTRY.remove(hhd) {
            d.close();
        }
    })
}

#[no_mangle]
pub extern "C" fn hdMakeCurrentDevice(hhd: u32) {
    guard((), || {
        if REGISTRY.get(hhd).is_some() {
            REGISTRY.set_current(hhd);
        } else {
            error::push(HD_BAD_HANDLE, Internal::None, hhd);
        }
    })
}

#[no_mangle]
pub extern "C" fn hdGetCurrentDevice() -> u32 {
    guard(HD_INVALID_HANDLE, || REGISTRY.current_handle())
}

// ---------------------------------------------------------------------------------------
// Frames

#[no_mangle]
pub extern "C" fn hdBeginFrame(hhd: u32) {
    guard((), || match REGISTRY.get(hhd) {
        Some(d) => {
            if !d.begin_frame() {
                error::push(HD_COMM_ERROR, Internal::Refused, hhd);
            }
        }
        None => error::push(HD_BAD_HANDLE, Internal::None, hhd),
    })
}

#[no_mangle]
pub extern "C" fn hdEndFrame(hhd: u32) {
    guard((), || {
        let Some(d) = REGISTRY.get(hhd) else {
            return error::push(HD_BAD_HANDLE, Internal::None, hhd);
        };
        let force_output = REGISTRY.caps.load(Ordering::Relaxed) & 1 != 0;
        match d.end_frame(force_output) {
            Ok(true) => {
                if d.take_too_slow().is_some() {
                    error::push(HD_TIMER_ERROR, Internal::SlowFrames, hhd);
                }
                for (code, internal) in d.take_limit_errors() {
                    error::push(code, internal, hhd);
                }
            }
            Ok(false) => error::push(HD_ILLEGAL_END, Internal::None, hhd),
            Err(e) => {
                let (code, internal) = device_error(&e);
                error::push(code, internal, hhd)
            }
        }
    })
}

// ---------------------------------------------------------------------------------------
// Errors

#[no_mangle]
pub extern "C" fn hdGetError() -> HDErrorInfo {
    guard(
        HDErrorInfo {
            error_code: HD_SUCCESS,
            internal_error_code: 0,
            h_hd: HD_INVALID_HANDLE,
        },
        error::pop,
    )
}

#[no_mangle]
pub extern "C" fn hdGetErrorString(code: u32) -> *const c_char {
    error::describe(code).as_ptr().cast()
}

// ---------------------------------------------------------------------------------------
// Capabilities

fn cap_bit(cap: u32) -> Option<u32> {
    (HD_FORCE_OUTPUT..=HD_ONE_FRAME_LIMIT)
        .contains(&cap)
        .then(|| 1 << (cap - HD_FORCE_OUTPUT))
}

#[no_mangle]
pub extern "C" fn hdEnable(cap: u32) {
    guard((), || match cap_bit(cap) {
        Some(b) => {
            REGISTRY.caps.fetch_or(b, Ordering::Relaxed);
        }
        None => push(HD_INVALID_ENUM, Internal::None),
    })
}

#[no_mangle]
pub extern "C" fn hdDisable(cap: u32) {
    guard((), || match cap_bit(cap) {
        Some(b) => {
            REGISTRY.caps.fetch_and(!b, Ordering::Relaxed);
        }
        None => push(HD_INVALID_ENUM, Internal::None),
    })
}

#[no_mangle]
pub extern "C" fn hdIsEnabled(cap: u32) -> u8 {
    guard(HD_FALSE, || match cap_bit(cap) {
        Some(b) => u8::from(REGISTRY.caps.load(Ordering::Relaxed) & b != 0),
        None => {
            push(HD_INVALID_ENUM, Internal::None);
            HD_FALSE
        }
    })
}

// ---------------------------------------------------------------------------------------
// State

/// The numbers of `param` on the current device, or push the error.
fn get_nums(param: u32) -> Option<Vec<f64>> {
    let Some(d) = REGISTRY.current() else {
        push(HD_BAD_HANDLE, Internal::None);
        return None;
    };
    match params::get(&d, param) {
        Ok(params::Value::Nums(v)) => Some(v),
        Ok(params::Value::Str(_)) => {
            push(HD_INVALID_INPUT_TYPE, Internal::None);
            None
        }
        Err(HD_INVALID_ENUM) => {
            refuse_once(param, Access::Read);
            None
        }
        Err(code) => {
            push(code, Internal::None);
            None
        }
    }
}

/// Which way a program used a parameter.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
enum Access {
    Read,
    Write,
}

/// Parameters already refused as unsupported, each way.
static REFUSED: LazyLock<Mutex<std::collections::HashSet<(u32, Access)>>> =
    LazyLock::new(Default::default);

/// An unsupported parameter is an `HD_INVALID_ENUM` the first time a program reads it and the
/// first time it writes it, and left alone after that (an output untouched, a write dropped):
/// a servo callback that reads or writes it every tick, as the SDK's CommandMotorDAC writes
/// DAC values, gets one error each way, not a thousand a second (docs/HDAPI.md, Parameters).
fn refuse_once(param: u32, access: Access) {
    let first = REFUSED
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .insert((param, access));
    if first {
        push(HD_INVALID_ENUM, Internal::None);
    }
}

/// Write `param`'s values, converted by `conv`, to the caller's array `out`.
///
/// # Safety
/// `out` is NULL or has room for all of the parameter's values.
unsafe fn get_into<T>(param: u32, out: *mut T, conv: impl Fn(f64) -> T) {
    if out.is_null() {
        return push(HD_INVALID_VALUE, Internal::NullPointer);
    }
    guard((), || {
        if let Some(v) = get_nums(param) {
            for (k, x) in v.into_iter().enumerate() {
                // SAFETY: the caller's array holds the parameter's values (docs/HDAPI.md).
                unsafe { out.add(k).write(conv(x)) };
            }
        }
    })
}

/// # Safety
/// `out` is NULL or has room for the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdGetBooleanv(param: u32, out: *mut u8) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { get_into(param, out, |x| u8::from(x != 0.0)) }
}

/// # Safety
/// `out` is NULL or has room for the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdGetIntegerv(param: u32, out: *mut i32) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { get_into(param, out, |x| x.round() as i32) }
}

/// # Safety
/// `out` is NULL or has room for the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdGetFloatv(param: u32, out: *mut f32) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { get_into(param, out, |x| x as f32) }
}

/// # Safety
/// `out` is NULL or has room for the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdGetDoublev(param: u32, out: *mut f64) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { get_into(param, out, |x| x) }
}

/// # Safety
/// `out` is NULL or has room for the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdGetLongv(param: u32, out: *mut i64) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { get_into(param, out, |x| x.round() as i64) }
}

/// Strings handed out stay alive (and unchanged) for the process: one per (device, param).
static STRINGS: LazyLock<Mutex<HashMap<(u32, u32), CString>>> = LazyLock::new(Default::default);

#[no_mangle]
pub extern "C" fn hdGetString(param: u32) -> *const c_char {
    guard(std::ptr::null(), || {
        let Some(d) = REGISTRY.current() else {
            push(HD_BAD_HANDLE, Internal::None);
            return std::ptr::null();
        };
        match params::get(&d, param) {
            Ok(params::Value::Str(s)) => {
                let mut strings = STRINGS.lock().unwrap_or_else(|e| e.into_inner());
                let c = strings
                    .entry((d.hhd, param))
                    .or_insert_with(|| CString::new(s.replace('\0', "")).unwrap_or_default());
                c.as_ptr()
            }
            Ok(params::Value::Nums(_)) => {
                push(HD_INVALID_INPUT_TYPE, Internal::None);
                std::ptr::null()
            }
            Err(code) => {
                push(code, Internal::None);
                std::ptr::null()
            }
        }
    })
}

/// Read `param`'s values from the caller's array `v` and set them.
///
/// # Safety
/// `v` is NULL or holds the parameter's values.
unsafe fn set_from<T: Copy>(param: u32, v: *const T, conv: impl Fn(T) -> f64) {
    let Some(n) = params::set_count(param) else {
        return refuse_once(param, Access::Write);
    };
    if v.is_null() {
        return push(HD_INVALID_VALUE, Internal::NullPointer);
    }
    // SAFETY: the caller's array holds the parameter's `n` values (docs/HDAPI.md).
    let values: Vec<f64> = (0..n).map(|k| conv(unsafe { v.add(k).read() })).collect();
    guard((), || {
        let Some(d) = REGISTRY.current() else {
            return push(HD_BAD_HANDLE, Internal::None);
        };
        match params::set(&d, param, &values) {
            Ok(()) => {}
            Err(HD_INVALID_ENUM) => refuse_once(param, Access::Write),
            Err(code) => push(code, Internal::None),
        }
    })
}

/// # Safety
/// `v` is NULL or holds the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdSetBooleanv(param: u32, v: *const u8) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { set_from(param, v, f64::from) }
}

/// # Safety
/// `v` is NULL or holds the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdSetIntegerv(param: u32, v: *const i32) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { set_from(param, v, f64::from) }
}

/// # Safety
/// `v` is NULL or holds the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdSetFloatv(param: u32, v: *const f32) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { set_from(param, v, f64::from) }
}

/// # Safety
/// `v` is NULL or holds the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdSetDoublev(param: u32, v: *const f64) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { set_from(param, v, |x| x) }
}

/// # Safety
/// `v` is NULL or holds the parameter's values.
#[no_mangle]
pub unsafe extern "C" fn hdSetLongv(param: u32, v: *const i64) {
    // SAFETY: forwarded from our caller's contract.
    unsafe { set_from(param, v, |x| x as f64) }
}

// ---------------------------------------------------------------------------------------
// Calibration (docs/HDAPI.md, Calibration: the Omni's inkwell)

#[no_mangle]
pub extern "C" fn hdCheckCalibration() -> u32 {
    guard(HD_CALIBRATION_NEEDS_MANUAL_INPUT, || {
        let Some(d) = REGISTRY.current() else {
            push(HD_BAD_HANDLE, Internal::None);
            return HD_CALIBRATION_NEEDS_MANUAL_INPUT;
        };
        if d.calibrated.load(Ordering::Relaxed) {
            HD_CALIBRATION_OK
        } else if d.inkwell_seen() {
            HD_CALIBRATION_NEEDS_UPDATE
        } else {
            HD_CALIBRATION_NEEDS_MANUAL_INPUT
        }
    })
}

#[no_mangle]
pub extern "C" fn hdCheckCalibrationStyle(style: i32) -> u8 {
    u8::from(style as u32 & HD_CALIBRATION_INKWELL != 0)
}

#[no_mangle]
pub extern "C" fn hdUpdateCalibration(style: u32) {
    guard((), || {
        let Some(d) = REGISTRY.current() else {
            return push(HD_BAD_HANDLE, Internal::None);
        };
        if style & HD_CALIBRATION_INKWELL == 0 {
            return push(HD_INVALID_VALUE, Internal::None);
        }
        // omnid zeroed the encoders at the inkwell before serving: once the stylus has been
        // seen docked there is nothing left to do.
        if d.inkwell_seen() {
            d.calibrated.store(true, Ordering::Relaxed);
        }
    })
}

#[no_mangle]
pub extern "C" fn hdUpdateCalibrationMessage(_style: u32) {}

// ---------------------------------------------------------------------------------------
// Scheduler

fn take_lease(hhd: u32) {
    if let Some(d) = REGISTRY.get(hhd) {
        if let Err(e) = d.take_lease() {
            debug(&format!("cannot command {}: {e}", d.socket.display()));
            let code = match e {
                DeviceError::Refused(_) => HD_DEVICE_ALREADY_INITIATED,
                _ => HD_COMM_ERROR,
            };
            error::push(code, Internal::LeaseHeld, hhd);
        }
    }
}

#[no_mangle]
pub extern "C" fn hdStartScheduler() {
    guard((), || {
        if REGISTRY.scheduler.is_running() {
            return;
        }
        for d in REGISTRY.all() {
            take_lease(d.hhd);
        }
        if REGISTRY.scheduler.start(&*REGISTRY).is_err() {
            push(HD_TIMER_ERROR, Internal::None);
        }
    })
}

#[no_mangle]
pub extern "C" fn hdStopScheduler() {
    guard((), || {
        REGISTRY.scheduler.stop();
        for d in REGISTRY.all() {
            d.stand_down();
        }
    })
}

#[no_mangle]
pub extern "C" fn hdSetSchedulerRate(rate: u64) {
    guard((), || {
        if rate == 0 {
            return push(HD_INVALID_VALUE, Internal::None);
        }
        // The daemon streams at its device rate divided by a whole number.
        for d in REGISTRY.all() {
            if let Err(e) = d.request(serde_json::json!({"op": "stream", "rate_hz": rate as f64})) {
                let (code, internal) = device_error(&e);
                error::push(code, internal, d.hhd);
            }
        }
    })
}

/// # Safety
/// `callback` is a function that may be called with `data` from the scheduler's thread.
#[no_mangle]
pub unsafe extern "C" fn hdScheduleAsynchronous(
    callback: Option<scheduler::Callback>,
    data: *mut c_void,
    priority: u16,
) -> u64 {
    guard(0, || match callback {
        Some(cb) => REGISTRY.scheduler.schedule(cb, data, priority),
        None => {
            push(HD_INVALID_VALUE, Internal::NullPointer);
            0
        }
    })
}

/// # Safety
/// `callback` is a function that may be called with `data` from the scheduler's thread.
#[no_mangle]
pub unsafe extern "C" fn hdScheduleSynchronous(
    callback: Option<scheduler::Callback>,
    data: *mut c_void,
    priority: u16,
) {
    guard((), || match callback {
        Some(cb) => REGISTRY.scheduler.run_sync(cb, data, priority),
        None => push(HD_INVALID_VALUE, Internal::NullPointer),
    })
}

#[no_mangle]
pub extern "C" fn hdUnschedule(handle: u64) {
    guard((), || {
        REGISTRY.scheduler.unschedule(handle);
    })
}

#[no_mangle]
pub extern "C" fn hdWaitForCompletion(handle: u64, wait: u32) -> u8 {
    guard(HD_FALSE, || match wait {
        HD_WAIT_CHECK_STATUS => u8::from(REGISTRY.scheduler.is_scheduled(handle)),
        HD_WAIT_INFINITE => {
            let scheduled = REGISTRY.scheduler.is_scheduled(handle);
            REGISTRY.scheduler.wait(handle);
            u8::from(scheduled)
        }
        _ => {
            push(HD_INVALID_ENUM, Internal::None);
            HD_FALSE
        }
    })
}

#[no_mangle]
pub extern "C" fn hdGetSchedulerTimeStamp() -> f64 {
    guard(0.0, || REGISTRY.scheduler.timestamp())
}

// ---------------------------------------------------------------------------------------
// Not supported (exported so programs link and load)

/// # Safety
/// Never reads or writes `angles`.
#[no_mangle]
pub unsafe extern "C" fn hdScaleGimbalAngles(
    _sx: f64,
    _sy: f64,
    _sz: f64,
    _nt: f64,
    _angles: *mut f64,
) {
    push(HD_INVALID_ENUM, Internal::None);
}

/// No licence is needed: always true.
#[no_mangle]
pub extern "C" fn hdDeploymentLicense(
    _vendor: *const c_char,
    _application: *const c_char,
    _password: *const c_char,
) -> u8 {
    HD_TRUE
}
