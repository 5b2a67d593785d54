/* omnid libHDU: error helpers (docs/HDAPI.md, libHDU). C and C++; the functions are in
 * libHDU.a (link -lHDU -lHD). */
#ifndef OMNID_HDU_ERROR_H
#define OMNID_HDU_ERROR_H

#include <stdio.h>
#include <HD/hd.h>

HD_BEGIN_DECLS

/* Print `error` to `stream`: its code's name and number, the library's description of it,
 * the internal code and device handle, then `appendedMessage` (may be NULL). */
void hduPrintError(FILE *stream, const HDErrorInfo *error, const char *appendedMessage);

/* True for errors after which the servo loop cannot go on: communication, device fault,
 * timer, scheduler (HD_COMM_ERROR, HD_COMM_CONFIG_ERROR, HD_TIMER_ERROR, HD_DEVICE_FAULT,
 * HD_INVALID_PRIORITY, HD_SCHEDULER_FULL). */
HDboolean hduIsSchedulerError(const HDErrorInfo *error);

/* True for the force errors, HD_WARM_MOTORS to HD_FORCE_ERROR (0x200..0x204). */
HDboolean hduIsForceError(const HDErrorInfo *error);

/* True for HD_COMM_ERROR and HD_COMM_CONFIG_ERROR. */
HDboolean hduIsComError(const HDErrorInfo *error);

HD_END_DECLS

#ifdef __cplusplus
#include <iosfwd>
/* The same text as hduPrintError without an appended message. */
std::ostream &operator<<(std::ostream &os, const HDErrorInfo &error);
#endif

#endif
