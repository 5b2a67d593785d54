// omnid libHDU, internal: the name of an HD error code (docs/HDAPI.md, Constants).
#ifndef OMNID_HDU_ERROR_NAME_H
#define OMNID_HDU_ERROR_NAME_H

#include <HD/hd.h>

// "HD_COMM_ERROR" for 0x302; "HD_UNKNOWN_ERROR" for a code the HD API does not define.
static inline const char *hduErrorName(HDerror code)
{
    switch (code) {
#define HDU_NAME(c) \
    case c:         \
        return #c;
        HDU_NAME(HD_SUCCESS)
        HDU_NAME(HD_INVALID_ENUM)
        HDU_NAME(HD_INVALID_VALUE)
        HDU_NAME(HD_INVALID_OPERATION)
        HDU_NAME(HD_INVALID_INPUT_TYPE)
        HDU_NAME(HD_BAD_HANDLE)
        HDU_NAME(HD_WARM_MOTORS)
        HDU_NAME(HD_EXCEEDED_MAX_FORCE)
        HDU_NAME(HD_EXCEEDED_MAX_FORCE_IMPULSE)
        HDU_NAME(HD_EXCEEDED_MAX_VELOCITY)
        HDU_NAME(HD_FORCE_ERROR)
        HDU_NAME(HD_DEVICE_FAULT)
        HDU_NAME(HD_DEVICE_ALREADY_INITIATED)
        HDU_NAME(HD_COMM_ERROR)
        HDU_NAME(HD_COMM_CONFIG_ERROR)
        HDU_NAME(HD_TIMER_ERROR)
        HDU_NAME(HD_ILLEGAL_BEGIN)
        HDU_NAME(HD_ILLEGAL_END)
        HDU_NAME(HD_FRAME_ERROR)
        HDU_NAME(HD_INVALID_PRIORITY)
        HDU_NAME(HD_SCHEDULER_FULL)
        HDU_NAME(HD_INVALID_LICENSE)
#undef HDU_NAME
    default:
        return "HD_UNKNOWN_ERROR";
    }
}

#endif
