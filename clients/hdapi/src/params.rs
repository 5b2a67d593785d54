//! `hdGet…`/`hdSet…`: every parameter the library answers, as numbers (converted to the
//! caller's type at the boundary) or a string, in the units of docs/HDAPI.md.

use crate::consts::*;
use crate::device::{Device, Frame};
use crate::kin;
use omnid_client::protocol::State;

/// Omni workspace boxes, mm (min xyz, then max xyz): docs/HDAPI.md, Device description.
const MAX_WORKSPACE_MM: [f64; 6] = [-210.0, -110.0, -85.0, 210.0, 205.0, 130.0];
const USABLE_WORKSPACE_MM: [f64; 6] = [-80.0, -60.0, -35.0, 80.0, 60.0, 35.0];
/// Nominal limits the clients scale their effects by (docs/HDAPI.md, Device description).
const NOMINAL_MAX_STIFFNESS_N_PER_MM: f64 = 1.02;
const NOMINAL_MAX_CONTINUOUS_FORCE_N: f64 = 0.88;
const NOMINAL_MAX_DAMPING: f64 = 0.005;

pub enum Value {
    Nums(Vec<f64>),
    Str(String),
}

fn nums<const N: usize>(v: [f64; N]) -> Result<Value, u32> {
    Ok(Value::Nums(v.to_vec()))
}

/// The sample a read sees: inside a frame its snapshot; outside a frame the scheduler's
/// tick's sample while it runs, else the latest.
fn sample(d: &Device, f: &Frame, last: bool) -> Result<State, u32> {
    let s = if last {
        f.last.clone().or_else(|| f.current.clone())
    } else if f.depth > 0 {
        f.current.clone()
    } else {
        f.tick.clone()
    };
    s.or_else(|| d.latest()).ok_or(HD_COMM_ERROR)
}

fn buttons(s: &State) -> f64 {
    f64::from(u8::from(s.buttons[0]) | (u8::from(s.buttons[1]) << 1))
}

/// The value of `param` on device `d`.
pub fn get(d: &Device, param: u32) -> Result<Value, u32> {
    let f = d.frame.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let h = &d.hello;
    // State: CURRENT_… and LAST_… (= CURRENT + 0x200).
    let (base, last) = match param {
        0x2200..=0x23FF => (param - LAST_OFFSET, true),
        _ => (param, false),
    };
    match base {
        HD_CURRENT_BUTTONS => return nums([buttons(&sample(d, &f, last)?)]),
        // The Omni has no safety switch: always closed.
        HD_CURRENT_SAFETY_SWITCH => return nums([1.0]),
        HD_CURRENT_INKWELL_SWITCH => {
            return nums([f64::from(u8::from(sample(d, &f, last)?.inkwell))])
        }
        HD_CURRENT_POSITION => return nums(sample(d, &f, last)?.tip_mm),
        HD_CURRENT_VELOCITY => {
            let s = sample(d, &f, last)?;
            return nums(kin::velocity_mm_s(&s.q, &s.qd));
        }
        HD_CURRENT_TRANSFORM => {
            let s = sample(d, &f, last)?;
            return nums(kin::transform(&s.q, &s.gimbal, &s.tip_mm));
        }
        // The gimbal's rates are not measured.
        HD_CURRENT_ANGULAR_VELOCITY => return nums([0.0; 3]),
        HD_CURRENT_JACOBIAN => return nums(kin::jacobian6(&sample(d, &f, last)?.q)),
        HD_CURRENT_JOINT_ANGLES => return nums(sample(d, &f, last)?.q),
        HD_CURRENT_GIMBAL_ANGLES => return nums(sample(d, &f, last)?.gimbal),
        // The daemon's thermal model: 0 cold, 1 at the steady state of the continuous torque,
        // where the safety layer starts holding the motor (docs/HDAPI.md, Parameters).
        HD_MOTOR_TEMPERATURE => return nums(sample(d, &f, false)?.heat.map(|h| h.clamp(0.0, 1.0))),
        _ => {}
    }
    match param {
        HD_VERSION => Ok(Value::Str("3.4.0".into())),
        HD_DEVICE_MODEL_TYPE => Ok(Value::Str(h.model.clone())),
        HD_DEVICE_DRIVER_VERSION => Ok(Value::Str(h.server.clone())),
        HD_DEVICE_VENDOR => Ok(Value::Str(h.vendor.clone())),
        HD_DEVICE_SERIAL_NUMBER => Ok(Value::Str(
            h.serial.clone().unwrap_or_else(|| h.device.clone()),
        )),
        HD_DEVICE_FIRMWARE_VERSION => Ok(Value::Str(
            h.firmware.clone().unwrap_or_else(|| "unknown".into()),
        )),
        HD_MAX_WORKSPACE_DIMENSIONS => nums(MAX_WORKSPACE_MM),
        HD_USABLE_WORKSPACE_DIMENSIONS => nums(USABLE_WORKSPACE_MM),
        HD_TABLETOP_OFFSET => nums([MAX_WORKSPACE_MM[1]]),
        HD_INPUT_DOF => nums([6.0]),
        HD_OUTPUT_DOF => nums([3.0]),
        HD_CALIBRATION_STYLE => nums([f64::from(HD_CALIBRATION_INKWELL)]),
        HD_UPDATE_RATE => nums([h.rate_hz]),
        HD_INSTANTANEOUS_UPDATE_RATE => nums([d.instantaneous_rate()]),
        HD_NOMINAL_MAX_STIFFNESS => nums([NOMINAL_MAX_STIFFNESS_N_PER_MM]),
        HD_NOMINAL_MAX_FORCE => nums([kin::MAX_FORCE_N]),
        HD_NOMINAL_MAX_CONTINUOUS_FORCE => nums([NOMINAL_MAX_CONTINUOUS_FORCE_N]),
        HD_NOMINAL_MAX_DAMPING => nums([NOMINAL_MAX_DAMPING]),
        HD_CURRENT_FORCE => nums(f.force),
        HD_CURRENT_TORQUE => nums(f.torque),
        HD_CURRENT_JOINT_TORQUE => nums(f.joint_torque),
        HD_CURRENT_GIMBAL_TORQUE => nums(f.gimbal_torque),
        HD_LAST_FORCE => nums(f.last_force),
        HD_LAST_TORQUE => nums(f.last_torque),
        HD_LAST_JOINT_TORQUE => nums(f.last_joint_torque),
        HD_LAST_GIMBAL_TORQUE => nums(f.last_gimbal_torque),
        _ => Err(HD_INVALID_ENUM),
    }
}

/// How many values `hdSet…` reads for `param`.
pub fn set_count(param: u32) -> Option<usize> {
    match param {
        HD_CURRENT_FORCE
        | HD_CURRENT_TORQUE
        | HD_CURRENT_JOINT_TORQUE
        | HD_CURRENT_GIMBAL_TORQUE => Some(3),
        _ => None,
    }
}

/// Set an output of the frame in progress. Outside a frame it is an error.
pub fn set(d: &Device, param: u32, v: &[f64]) -> Result<(), u32> {
    let mut f = d.frame.lock().unwrap_or_else(|e| e.into_inner());
    if f.depth == 0 {
        return Err(HD_INVALID_OPERATION);
    }
    let v3 = [v[0], v[1], v[2]];
    match param {
        HD_CURRENT_FORCE => f.force = v3,
        // No motors in the Omni's gimbal: accepted and reported back, never sent.
        HD_CURRENT_TORQUE => f.torque = v3,
        HD_CURRENT_JOINT_TORQUE => f.joint_torque = v3,
        HD_CURRENT_GIMBAL_TORQUE => f.gimbal_torque = v3,
        _ => return Err(HD_INVALID_ENUM),
    }
    Ok(())
}
