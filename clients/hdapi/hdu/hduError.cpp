// omnid libHDU: the C error helpers (docs/HDAPI.md, libHDU). C linkage and only stdio, so C
// programs link them with a C compiler; the C++ stream form is in hduErrorStream.cpp.
#include <HDU/hduError.h>
#include "hduErrorName.h"

extern "C" {

void hduPrintError(FILE *stream, const HDErrorInfo *error, const char *appendedMessage)
{
    if (stream == NULL || error == NULL)
        return;
    fprintf(stream, "HD Error: %s (0x%04x): %s\n", hduErrorName(error->errorCode),
            error->errorCode, hdGetErrorString(error->errorCode));
    fprintf(stream, "HHD: %u, internal error code: %d\n", error->hHD, error->internalErrorCode);
    if (appendedMessage != NULL && appendedMessage[0] != '\0')
        fprintf(stream, "%s\n", appendedMessage);
}

HDboolean hduIsSchedulerError(const HDErrorInfo *error)
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

HDboolean hduIsForceError(const HDErrorInfo *error)
{
    if (error == NULL)
        return HD_FALSE;
    return (error->errorCode >= HD_WARM_MOTORS && error->errorCode <= HD_FORCE_ERROR) ? HD_TRUE
                                                                                      : HD_FALSE;
}

HDboolean hduIsComError(const HDErrorInfo *error)
{
    if (error == NULL)
        return HD_FALSE;
    return (error->errorCode == HD_COMM_ERROR || error->errorCode == HD_COMM_CONFIG_ERROR)
               ? HD_TRUE
               : HD_FALSE;
}

} // extern "C"
