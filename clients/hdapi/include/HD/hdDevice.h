/* omnid libHD: device, frame, state, capability, error and calibration calls (docs/HDAPI.md). */
#ifndef OMNID_HD_DEVICE_H
#define OMNID_HD_DEVICE_H

#include "hdDefines.h"

HD_BEGIN_DECLS

HDAPI HHD HDAPIENTRY hdInitDevice(HDstring pConfigName);
HDAPI void HDAPIENTRY hdDisableDevice(HHD hHD);
HDAPI void HDAPIENTRY hdMakeCurrentDevice(HHD hHD);
HDAPI HHD HDAPIENTRY hdGetCurrentDevice(void);

HDAPI void HDAPIENTRY hdBeginFrame(HHD hHD);
HDAPI void HDAPIENTRY hdEndFrame(HHD hHD);

HDAPI HDErrorInfo HDAPIENTRY hdGetError(void);
HDAPI HDstring HDAPIENTRY hdGetErrorString(HDerror errorCode);

HDAPI void HDAPIENTRY hdEnable(HDenum cap);
HDAPI void HDAPIENTRY hdDisable(HDenum cap);
HDAPI HDboolean HDAPIENTRY hdIsEnabled(HDenum cap);

HDAPI void HDAPIENTRY hdGetBooleanv(HDenum pname, HDboolean *params);
HDAPI void HDAPIENTRY hdGetIntegerv(HDenum pname, HDint *params);
HDAPI void HDAPIENTRY hdGetFloatv(HDenum pname, HDfloat *params);
HDAPI void HDAPIENTRY hdGetDoublev(HDenum pname, HDdouble *params);
HDAPI void HDAPIENTRY hdGetLongv(HDenum pname, HDlong *params);
HDAPI HDstring HDAPIENTRY hdGetString(HDenum pname);

HDAPI void HDAPIENTRY hdSetBooleanv(HDenum pname, const HDboolean *params);
HDAPI void HDAPIENTRY hdSetIntegerv(HDenum pname, const HDint *params);
HDAPI void HDAPIENTRY hdSetFloatv(HDenum pname, const HDfloat *params);
HDAPI void HDAPIENTRY hdSetDoublev(HDenum pname, const HDdouble *params);
HDAPI void HDAPIENTRY hdSetLongv(HDenum pname, const HDlong *params);

HDAPI HDenum HDAPIENTRY hdCheckCalibration(void);
HDAPI HDboolean HDAPIENTRY hdCheckCalibrationStyle(HDint style);
HDAPI void HDAPIENTRY hdUpdateCalibration(HDenum style);
HDAPI void HDAPIENTRY hdUpdateCalibrationMessage(HDenum style);

HDAPI void HDAPIENTRY hdScaleGimbalAngles(HDdouble scaleX, HDdouble scaleY, HDdouble scaleZ,
                                          HDdouble nT, HDdouble *angles);
HDAPI HDboolean HDAPIENTRY hdDeploymentLicense(const char *vendorName, const char *applicationName,
                                               const char *password);

HD_END_DECLS

#endif
