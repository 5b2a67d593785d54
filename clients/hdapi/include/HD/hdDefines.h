/* omnid libHD: types and constants of the HD API, written from the interoperability table in
 * omnid's docs/HDAPI.md (values and types only; no vendor text). */
#ifndef OMNID_HD_DEFINES_H
#define OMNID_HD_DEFINES_H

#include "hdCompilerConfig.h"
#include "hdExport.h"

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDerror;
typedef unsigned int HDCallbackCode;
typedef unsigned int HDWaitCode;
typedef unsigned char HDboolean;
typedef unsigned short HDushort;
typedef int HDint;
typedef unsigned int HDuint;
typedef long HDlong;
typedef unsigned long HDulong;
typedef float HDfloat;
typedef double HDdouble;
typedef const char *HDstring;
typedef unsigned long HDSchedulerHandle;

typedef struct {
    HDerror errorCode;
    int internalErrorCode;
    HHD hHD;
} HDErrorInfo;

/* Truth, callbacks, waits */
#define HD_TRUE 1
#define HD_FALSE 0
#define HD_CALLBACK_DONE 0
#define HD_CALLBACK_CONTINUE 1
#define HD_WAIT_CHECK_STATUS 0
#define HD_WAIT_INFINITE 1

/* Devices */
#define HD_DEFAULT_DEVICE NULL
#define HD_INVALID_HANDLE 0xFFFFFFFF

/* Scheduler priorities */
#define HD_MAX_SCHEDULER_PRIORITY 65535
#define HD_MIN_SCHEDULER_PRIORITY 0
#define HD_DEFAULT_SCHEDULER_PRIORITY ((HD_MAX_SCHEDULER_PRIORITY + HD_MIN_SCHEDULER_PRIORITY) / 2)

/* Stylus buttons */
#define HD_DEVICE_BUTTON_1 (1 << 0)
#define HD_DEVICE_BUTTON_2 (1 << 1)
#define HD_DEVICE_BUTTON_3 (1 << 2)
#define HD_DEVICE_BUTTON_4 (1 << 3)

/* Calibration */
#define HD_CALIBRATION_OK 0x5000
#define HD_CALIBRATION_NEEDS_UPDATE 0x5001
#define HD_CALIBRATION_NEEDS_MANUAL_INPUT 0x5002
#define HD_CALIBRATION_ENCODER_RESET (1 << 0)
#define HD_CALIBRATION_AUTO (1 << 1)
#define HD_CALIBRATION_INKWELL (1 << 2)

/* Errors */
#define HD_SUCCESS 0x0000
#define HD_INVALID_ENUM 0x0100
#define HD_INVALID_VALUE 0x0101
#define HD_INVALID_OPERATION 0x0102
#define HD_INVALID_INPUT_TYPE 0x0103
#define HD_BAD_HANDLE 0x0104
#define HD_WARM_MOTORS 0x0200
#define HD_EXCEEDED_MAX_FORCE 0x0201
#define HD_EXCEEDED_MAX_FORCE_IMPULSE 0x0202
#define HD_EXCEEDED_MAX_VELOCITY 0x0203
#define HD_FORCE_ERROR 0x0204
#define HD_DEVICE_FAULT 0x0300
#define HD_DEVICE_ALREADY_INITIATED 0x0301
#define HD_COMM_ERROR 0x0302
#define HD_COMM_CONFIG_ERROR 0x0303
#define HD_TIMER_ERROR 0x0304
#define HD_ILLEGAL_BEGIN 0x0400
#define HD_ILLEGAL_END 0x0401
#define HD_FRAME_ERROR 0x0402
#define HD_INVALID_PRIORITY 0x0500
#define HD_SCHEDULER_FULL 0x0501
#define HD_INVALID_LICENSE 0x0600

/* Current state */
#define HD_CURRENT_BUTTONS 0x2000
#define HD_CURRENT_SAFETY_SWITCH 0x2001
#define HD_CURRENT_INKWELL_SWITCH 0x2002
#define HD_CURRENT_ENCODER_VALUES 0x2010
#define HD_CURRENT_POSITION 0x2050
#define HD_CURRENT_VELOCITY 0x2051
#define HD_CURRENT_TRANSFORM 0x2052
#define HD_CURRENT_ANGULAR_VELOCITY 0x2053
#define HD_CURRENT_JACOBIAN 0x2054
#define HD_CURRENT_JOINT_ANGLES 0x2100
#define HD_CURRENT_GIMBAL_ANGLES 0x2150

/* Last frame's state: the current value's code + 0x200 */
#define HD_LAST_BUTTONS 0x2200
#define HD_LAST_SAFETY_SWITCH 0x2201
#define HD_LAST_INKWELL_SWITCH 0x2202
#define HD_LAST_ENCODER_VALUES 0x2210
#define HD_LAST_POSITION 0x2250
#define HD_LAST_VELOCITY 0x2251
#define HD_LAST_TRANSFORM 0x2252
#define HD_LAST_ANGULAR_VELOCITY 0x2253
#define HD_LAST_JACOBIAN 0x2254
#define HD_LAST_JOINT_ANGLES 0x2300
#define HD_LAST_GIMBAL_ANGLES 0x2350

/* Identification */
#define HD_VERSION 0x2500
#define HD_DEVICE_MODEL_TYPE 0x2501
#define HD_DEVICE_DRIVER_VERSION 0x2502
#define HD_DEVICE_VENDOR 0x2503
#define HD_DEVICE_SERIAL_NUMBER 0x2504
#define HD_DEVICE_FIRMWARE_VERSION 0x2505

/* Device description */
#define HD_MAX_WORKSPACE_DIMENSIONS 0x2550
#define HD_USABLE_WORKSPACE_DIMENSIONS 0x2551
#define HD_TABLETOP_OFFSET 0x2552
#define HD_INPUT_DOF 0x2553
#define HD_OUTPUT_DOF 0x2554
#define HD_CALIBRATION_STYLE 0x2555

/* Rates and limits */
#define HD_UPDATE_RATE 0x2600
#define HD_INSTANTANEOUS_UPDATE_RATE 0x2601
#define HD_NOMINAL_MAX_STIFFNESS 0x2602
#define HD_NOMINAL_MAX_FORCE 0x2603
#define HD_NOMINAL_MAX_CONTINUOUS_FORCE 0x2604
#define HD_MOTOR_TEMPERATURE 0x2605
#define HD_SOFTWARE_VELOCITY_LIMIT 0x2606
#define HD_SOFTWARE_FORCE_IMPULSE_LIMIT 0x2607
#define HD_FORCE_RAMPING_RATE 0x2608
#define HD_NOMINAL_MAX_DAMPING 0x2609

/* Output */
#define HD_CURRENT_FORCE 0x2700
#define HD_CURRENT_TORQUE 0x2701
#define HD_CURRENT_JOINT_TORQUE 0x2703
#define HD_CURRENT_GIMBAL_TORQUE 0x2704
#define HD_CURRENT_MOTOR_DAC_VALUES 0x2750
#define HD_LAST_FORCE 0x2800
#define HD_LAST_TORQUE 0x2801
#define HD_LAST_JOINT_TORQUE 0x2802
#define HD_LAST_GIMBAL_TORQUE 0x2803

/* Capabilities */
#define HD_FORCE_OUTPUT 0x4000
#define HD_MAX_FORCE_CLAMPING 0x4001
#define HD_FORCE_RAMPING 0x4002
#define HD_SOFTWARE_FORCE_LIMIT 0x4003
#define HD_ONE_FRAME_LIMIT 0x4004

/* An error code that names a device problem (not a usage error). */
#define HD_DEVICE_ERROR(X) (((X).errorCode) != HD_SUCCESS)

#endif
