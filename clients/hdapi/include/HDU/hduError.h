/* omnid libHD: error helpers (docs/HDAPI.md, HDU helpers). Header-only, C and C++. */
#ifndef OMNID_HDU_ERROR_H
#define OMNID_HDU_ERROR_H

#include <stdio.h>
#include <HD/hd.h>

/* Print "message: description (error code, internal code)" to `stream`. */
static inline void hduPrintError(FILE *stream, const HDErrorInfo *error, const char *message)
{
    if (stream == NULL || error == NULL)
        return;
    fprintf(stream, "HD Error: %s\n%s\nHD error code 0x%04x, internal error code %d\n",
            message ? message : "", hdGetErrorString(error->errorCode), error->errorCode,
            error->internalErrorCode);
}

/* True for errors that mean the servo loop cannot go on (communication, device, timer). */
static inline HDboolean hduIsSchedulerError(const HDErrorInfo *error)
{
    if (error == NULL)
        return HD_FALSE;
    switch (error->errorCode) {
    case HD_COMM_ERROR:
    case HD_COMM_CONFIG_ERROR:
    case HD_TIMER_ERROR:
    case HD_DEVICE_FAULT:
    case HD_INVALID_PRIORITY:
    case HD_SCHEDULER_FULL:
        return HD_TRUE;
    default:
        return HD_FALSE;
    }
}

static inline HDboolean hduIsForceError(const HDErrorInfo *error)
{
    if (error == NULL)
        return HD_FALSE;
    return (error->errorCode >= HD_WARM_MOTORS && error->errorCode <= HD_FORCE_ERROR) ? HD_TRUE
                                                                                      : HD_FALSE;
}

#endif
