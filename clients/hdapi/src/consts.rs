//! The HD API's numeric constants the library acts on: the values of docs/HDAPI.md's table
//! (the C header `include/HD/hdDefines.h` carries the same values for clients).

pub const HD_TRUE: u8 = 1;
pub const HD_FALSE: u8 = 0;
pub const HD_CALLBACK_DONE: u32 = 0;
pub const HD_WAIT_CHECK_STATUS: u32 = 0;
pub const HD_WAIT_INFINITE: u32 = 1;
pub const HD_INVALID_HANDLE: u32 = 0xFFFF_FFFF;

pub const HD_CALIBRATION_OK: u32 = 0x5000;
pub const HD_CALIBRATION_NEEDS_UPDATE: u32 = 0x5001;
pub const HD_CALIBRATION_NEEDS_MANUAL_INPUT: u32 = 0x5002;
pub const HD_CALIBRATION_INKWELL: u32 = 4;

// Errors.
pub const HD_SUCCESS: u32 = 0;
pub const HD_INVALID_ENUM: u32 = 0x100;
pub const HD_INVALID_VALUE: u32 = 0x101;
pub const HD_INVALID_OPERATION: u32 = 0x102;
pub const HD_INVALID_INPUT_TYPE: u32 = 0x103;
pub const HD_BAD_HANDLE: u32 = 0x104;
pub const HD_WARM_MOTORS: u32 = 0x200;
pub const HD_EXCEEDED_MAX_FORCE: u32 = 0x201;
pub const HD_EXCEEDED_MAX_FORCE_IMPULSE: u32 = 0x202;
pub const HD_EXCEEDED_MAX_VELOCITY: u32 = 0x203;
pub const HD_FORCE_ERROR: u32 = 0x204;
pub const HD_DEVICE_FAULT: u32 = 0x300;
pub const HD_DEVICE_ALREADY_INITIATED: u32 = 0x301;
pub const HD_COMM_ERROR: u32 = 0x302;
pub const HD_COMM_CONFIG_ERROR: u32 = 0x303;
pub const HD_TIMER_ERROR: u32 = 0x304;
pub const HD_ILLEGAL_BEGIN: u32 = 0x400;
pub const HD_ILLEGAL_END: u32 = 0x401;
pub const HD_FRAME_ERROR: u32 = 0x402;
pub const HD_INVALID_PRIORITY: u32 = 0x500;
pub const HD_SCHEDULER_FULL: u32 = 0x501;
pub const HD_INVALID_LICENSE: u32 = 0x600;

// State (LAST_… = CURRENT_… + 0x200).
pub const LAST_OFFSET: u32 = 0x200;
pub const HD_CURRENT_BUTTONS: u32 = 0x2000;
pub const HD_CURRENT_SAFETY_SWITCH: u32 = 0x2001;
pub const HD_CURRENT_INKWELL_SWITCH: u32 = 0x2002;
pub const HD_CURRENT_ENCODER_VALUES: u32 = 0x2010;
pub const HD_CURRENT_POSITION: u32 = 0x2050;
pub const HD_CURRENT_VELOCITY: u32 = 0x2051;
pub const HD_CURRENT_TRANSFORM: u32 = 0x2052;
pub const HD_CURRENT_ANGULAR_VELOCITY: u32 = 0x2053;
pub const HD_CURRENT_JACOBIAN: u32 = 0x2054;
pub const HD_CURRENT_JOINT_ANGLES: u32 = 0x2100;
pub const HD_CURRENT_GIMBAL_ANGLES: u32 = 0x2150;

// Identification.
pub const HD_VERSION: u32 = 0x2500;
pub const HD_DEVICE_MODEL_TYPE: u32 = 0x2501;
pub const HD_DEVICE_DRIVER_VERSION: u32 = 0x2502;
pub const HD_DEVICE_VENDOR: u32 = 0x2503;
pub const HD_DEVICE_SERIAL_NUMBER: u32 = 0x2504;
pub const HD_DEVICE_FIRMWARE_VERSION: u32 = 0x2505;

// Device description.
pub const HD_MAX_WORKSPACE_DIMENSIONS: u32 = 0x2550;
pub const HD_USABLE_WORKSPACE_DIMENSIONS: u32 = 0x2551;
pub const HD_TABLETOP_OFFSET: u32 = 0x2552;
pub const HD_INPUT_DOF: u32 = 0x2553;
pub const HD_OUTPUT_DOF: u32 = 0x2554;
pub const HD_CALIBRATION_STYLE: u32 = 0x2555;

// Rates and limits.
pub const HD_UPDATE_RATE: u32 = 0x2600;
pub const HD_INSTANTANEOUS_UPDATE_RATE: u32 = 0x2601;
pub const HD_NOMINAL_MAX_STIFFNESS: u32 = 0x2602;
pub const HD_NOMINAL_MAX_FORCE: u32 = 0x2603;
pub const HD_NOMINAL_MAX_CONTINUOUS_FORCE: u32 = 0x2604;
pub const HD_MOTOR_TEMPERATURE: u32 = 0x2605;
pub const HD_SOFTWARE_VELOCITY_LIMIT: u32 = 0x2606;
pub const HD_SOFTWARE_FORCE_IMPULSE_LIMIT: u32 = 0x2607;
pub const HD_FORCE_RAMPING_RATE: u32 = 0x2608;
pub const HD_NOMINAL_MAX_DAMPING: u32 = 0x2609;

// Output.
pub const HD_CURRENT_FORCE: u32 = 0x2700;
pub const HD_CURRENT_TORQUE: u32 = 0x2701;
pub const HD_CURRENT_JOINT_TORQUE: u32 = 0x2703;
pub const HD_CURRENT_GIMBAL_TORQUE: u32 = 0x2704;
pub const HD_CURRENT_MOTOR_DAC_VALUES: u32 = 0x2750;
pub const HD_LAST_FORCE: u32 = 0x2800;
pub const HD_LAST_TORQUE: u32 = 0x2801;
pub const HD_LAST_JOINT_TORQUE: u32 = 0x2802;
pub const HD_LAST_GIMBAL_TORQUE: u32 = 0x2803;

// Capabilities.
pub const HD_FORCE_OUTPUT: u32 = 0x4000;
pub const HD_MAX_FORCE_CLAMPING: u32 = 0x4001;
pub const HD_FORCE_RAMPING: u32 = 0x4002;
pub const HD_SOFTWARE_FORCE_LIMIT: u32 = 0x4003;
pub const HD_ONE_FRAME_LIMIT: u32 = 0x4004;
