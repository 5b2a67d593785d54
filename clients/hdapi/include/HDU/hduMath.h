/* omnid libHDU: small math helpers for HD programs (docs/HDAPI.md, libHDU). Header-only,
 * C and C++. */
#ifndef OMNID_HDU_MATH_H
#define OMNID_HDU_MATH_H

#include <HD/hdDefines.h>

#define HDU_PI 3.14159265358979323846
#define HDU_2PI (2.0 * HDU_PI)
#define HDU_PI_2 (0.5 * HDU_PI)
#define HDU_DEG_PER_RAD (180.0 / HDU_PI)
#define HDU_RAD_PER_DEG (HDU_PI / 180.0)
/* The tolerance the helpers below use when a caller gives none. */
#define HDU_EPSILON 1e-9

static inline HDdouble hduDegToRad(HDdouble degrees) { return degrees * HDU_RAD_PER_DEG; }
static inline HDdouble hduRadToDeg(HDdouble radians) { return radians * HDU_DEG_PER_RAD; }

#ifdef __cplusplus
template <typename T> inline T hduMin(T a, T b) { return b < a ? b : a; }
template <typename T> inline T hduMax(T a, T b) { return a < b ? b : a; }
template <typename T> inline T hduAbs(T a) { return a < T(0) ? -a : a; }
/* -1, 0 or 1. */
template <typename T> inline T hduSign(T a) { return a < T(0) ? T(-1) : (T(0) < a ? T(1) : T(0)); }
/* `value` limited to [lo, hi]. */
template <typename T> inline T hduClamp(T value, T lo, T hi) { return value < lo ? lo : (hi < value ? hi : value); }
template <typename T> inline bool hduIsEqual(T a, T b, T epsilon) { return hduAbs(a - b) <= epsilon; }
#else
static inline HDdouble hduMin(HDdouble a, HDdouble b) { return b < a ? b : a; }
static inline HDdouble hduMax(HDdouble a, HDdouble b) { return a < b ? b : a; }
static inline HDdouble hduAbs(HDdouble a) { return a < 0 ? -a : a; }
static inline HDdouble hduSign(HDdouble a) { return a < 0 ? -1.0 : (0 < a ? 1.0 : 0.0); }
static inline HDdouble hduClamp(HDdouble value, HDdouble lo, HDdouble hi)
{
    return value < lo ? lo : (hi < value ? hi : value);
}
static inline HDboolean hduIsEqual(HDdouble a, HDdouble b, HDdouble epsilon)
{
    return hduAbs(a - b) <= epsilon ? HD_TRUE : HD_FALSE;
}
#endif

#endif
