/* ABI of our headers (docs/HDAPI.md, Types and ABI): type sizes and HDErrorInfo's layout are
 * checked at compile time; every constant is printed as "NAME VALUE" for the table test in
 * tests/suite/hdapi.rs. Also compiled as C++ (the HDU helpers). */
#include <HD/hd.h>
#include <HDU/hduError.h>
#include <stddef.h>
#include <stdio.h>
#ifdef __cplusplus
#include <HDU/hduMatrix.h>
#include <HDU/hduQuaternion.h>
#include <HDU/hduVector.h>
#define STATIC_ASSERT static_assert
#else
#define STATIC_ASSERT _Static_assert
#endif

STATIC_ASSERT(sizeof(HHD) == 4, "HHD");
STATIC_ASSERT(sizeof(HDenum) == 4, "HDenum");
STATIC_ASSERT(sizeof(HDerror) == 4, "HDerror");
STATIC_ASSERT(sizeof(HDCallbackCode) == 4, "HDCallbackCode");
STATIC_ASSERT(sizeof(HDWaitCode) == 4, "HDWaitCode");
STATIC_ASSERT(sizeof(HDboolean) == 1, "HDboolean");
STATIC_ASSERT(sizeof(HDushort) == 2, "HDushort");
STATIC_ASSERT(sizeof(HDint) == 4, "HDint");
STATIC_ASSERT(sizeof(HDlong) == 8, "HDlong");
STATIC_ASSERT(sizeof(HDulong) == 8, "HDulong");
STATIC_ASSERT(sizeof(HDSchedulerHandle) == 8, "HDSchedulerHandle");
STATIC_ASSERT(sizeof(HDfloat) == 4, "HDfloat");
STATIC_ASSERT(sizeof(HDdouble) == 8, "HDdouble");
STATIC_ASSERT(sizeof(HDErrorInfo) == 12, "HDErrorInfo size");
STATIC_ASSERT(offsetof(HDErrorInfo, errorCode) == 0, "errorCode");
STATIC_ASSERT(offsetof(HDErrorInfo, internalErrorCode) == 4, "internalErrorCode");
STATIC_ASSERT(offsetof(HDErrorInfo, hHD) == 8, "hHD");

#define P(name) printf("%s %lu\n", #name, (unsigned long)(name))

int main(void)
{
    P(HD_TRUE); P(HD_FALSE); P(HD_CALLBACK_DONE); P(HD_CALLBACK_CONTINUE);
    P(HD_WAIT_CHECK_STATUS); P(HD_WAIT_INFINITE); P(HD_INVALID_HANDLE);
    P(HD_MAX_SCHEDULER_PRIORITY); P(HD_MIN_SCHEDULER_PRIORITY); P(HD_DEFAULT_SCHEDULER_PRIORITY);
    P(HD_DEVICE_BUTTON_1); P(HD_DEVICE_BUTTON_2); P(HD_DEVICE_BUTTON_3); P(HD_DEVICE_BUTTON_4);
    P(HD_CALIBRATION_OK); P(HD_CALIBRATION_NEEDS_UPDATE); P(HD_CALIBRATION_NEEDS_MANUAL_INPUT);
    P(HD_CALIBRATION_ENCODER_RESET); P(HD_CALIBRATION_AUTO); P(HD_CALIBRATION_INKWELL);
    P(HD_SUCCESS); P(HD_INVALID_ENUM); P(HD_INVALID_VALUE); P(HD_INVALID_OPERATION);
    P(HD_INVALID_INPUT_TYPE); P(HD_BAD_HANDLE); P(HD_WARM_MOTORS); P(HD_EXCEEDED_MAX_FORCE);
    P(HD_EXCEEDED_MAX_FORCE_IMPULSE); P(HD_EXCEEDED_MAX_VELOCITY); P(HD_FORCE_ERROR);
    P(HD_DEVICE_FAULT); P(HD_DEVICE_ALREADY_INITIATED); P(HD_COMM_ERROR); P(HD_COMM_CONFIG_ERROR);
    P(HD_TIMER_ERROR); P(HD_ILLEGAL_BEGIN); P(HD_ILLEGAL_END); P(HD_FRAME_ERROR);
    P(HD_INVALID_PRIORITY); P(HD_SCHEDULER_FULL); P(HD_INVALID_LICENSE);
    P(HD_CURRENT_BUTTONS); P(HD_CURRENT_SAFETY_SWITCH); P(HD_CURRENT_INKWELL_SWITCH);
    P(HD_CURRENT_ENCODER_VALUES); P(HD_CURRENT_POSITION); P(HD_CURRENT_VELOCITY);
    P(HD_CURRENT_TRANSFORM); P(HD_CURRENT_ANGULAR_VELOCITY); P(HD_CURRENT_JACOBIAN);
    P(HD_CURRENT_JOINT_ANGLES); P(HD_CURRENT_GIMBAL_ANGLES);
    P(HD_LAST_BUTTONS); P(HD_LAST_SAFETY_SWITCH); P(HD_LAST_INKWELL_SWITCH);
    P(HD_LAST_ENCODER_VALUES); P(HD_LAST_POSITION); P(HD_LAST_VELOCITY); P(HD_LAST_TRANSFORM);
    P(HD_LAST_ANGULAR_VELOCITY); P(HD_LAST_JACOBIAN); P(HD_LAST_JOINT_ANGLES);
    P(HD_LAST_GIMBAL_ANGLES);
    P(HD_VERSION); P(HD_DEVICE_MODEL_TYPE); P(HD_DEVICE_DRIVER_VERSION); P(HD_DEVICE_VENDOR);
    P(HD_DEVICE_SERIAL_NUMBER); P(HD_DEVICE_FIRMWARE_VERSION);
    P(HD_MAX_WORKSPACE_DIMENSIONS); P(HD_USABLE_WORKSPACE_DIMENSIONS); P(HD_TABLETOP_OFFSET);
    P(HD_INPUT_DOF); P(HD_OUTPUT_DOF); P(HD_CALIBRATION_STYLE);
    P(HD_UPDATE_RATE); P(HD_INSTANTANEOUS_UPDATE_RATE); P(HD_NOMINAL_MAX_STIFFNESS);
    P(HD_NOMINAL_MAX_FORCE); P(HD_NOMINAL_MAX_CONTINUOUS_FORCE); P(HD_MOTOR_TEMPERATURE);
    P(HD_SOFTWARE_VELOCITY_LIMIT); P(HD_SOFTWARE_FORCE_IMPULSE_LIMIT); P(HD_FORCE_RAMPING_RATE);
    P(HD_NOMINAL_MAX_DAMPING);
    P(HD_CURRENT_FORCE); P(HD_CURRENT_TORQUE); P(HD_CURRENT_JOINT_TORQUE);
    P(HD_CURRENT_GIMBAL_TORQUE); P(HD_CURRENT_MOTOR_DAC_VALUES); P(HD_LAST_FORCE);
    P(HD_LAST_TORQUE); P(HD_LAST_JOINT_TORQUE); P(HD_LAST_GIMBAL_TORQUE);
    P(HD_FORCE_OUTPUT); P(HD_MAX_FORCE_CLAMPING); P(HD_FORCE_RAMPING);
    P(HD_SOFTWARE_FORCE_LIMIT); P(HD_ONE_FRAME_LIMIT);
    printf("HD_DEFAULT_DEVICE_IS_NULL %d\n", HD_DEFAULT_DEVICE == NULL);
    {
        HDErrorInfo e;
        e.errorCode = HD_COMM_ERROR;
        printf("HD_DEVICE_ERROR %d\n", HD_DEVICE_ERROR(e) ? 1 : 0);
    }
#ifdef __cplusplus
    {
        hduVector3Dd a(1, 2, 3), b(4, 5, 6);
        double t[16] = {0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1, 0, 10, 20, 30, 1};
        hduMatrix m(t);
        hduVector3Dd p;
        m.multVecMatrix(a, p);
        hduQuaternion q(m);
        /* The ROS driver's uses: 16 scalars, the rotation part, integer scale, division. */
        hduMatrix offset(0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        hduMatrix rotation;
        m.getRotationMatrix(rotation);
        hduQuaternion r(offset * rotation);
        hduVector3Dd v = (a * 3 - 4 * b + a) / 0.002;
        printf("ROS %.1f %.3f %.1f\n", rotation[3][0], r.norm(), v[0]);
        printf("HDU %.1f %.1f %.1f %.1f %.3f\n", (a + b).magnitude() * 0 + a.dotProduct(b), p[0], p[1],
               p[2], q.norm());
    }
#endif
    return 0;
}
