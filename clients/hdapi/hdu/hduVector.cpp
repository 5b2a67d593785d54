// omnid libHDU: the C vector functions (docs/HDAPI.md, libHDU). Plain C arithmetic with C
// linkage and nothing of the C++ runtime, so C programs link them with a C compiler.
#include <HDU/hduVector.h>
#include <math.h>

extern "C" {

void hduVecSet(HDdouble *vec, HDdouble x, HDdouble y, HDdouble z)
{
    vec[0] = x;
    vec[1] = y;
    vec[2] = z;
}

void hduVecCopy(HDdouble *dst, const HDdouble *src)
{
    hduVecSet(dst, src[0], src[1], src[2]);
}

void hduVecAdd(HDdouble *res, const HDdouble *v1, const HDdouble *v2)
{
    hduVecSet(res, v1[0] + v2[0], v1[1] + v2[1], v1[2] + v2[2]);
}

void hduVecSubtract(HDdouble *res, const HDdouble *v1, const HDdouble *v2)
{
    hduVecSet(res, v1[0] - v2[0], v1[1] - v2[1], v1[2] - v2[2]);
}

void hduVecNegate(HDdouble *res, const HDdouble *v)
{
    hduVecSet(res, -v[0], -v[1], -v[2]);
}

void hduVecScale(HDdouble *res, const HDdouble *v, HDdouble s)
{
    hduVecSet(res, v[0] * s, v[1] * s, v[2] * s);
}

void hduVecScaleInPlace(HDdouble *v, HDdouble s)
{
    hduVecScale(v, v, s);
}

void hduVecScaleNonUniform(HDdouble *res, const HDdouble *v, const HDdouble *s)
{
    hduVecSet(res, v[0] * s[0], v[1] * s[1], v[2] * s[2]);
}

void hduVecScaleNonUniformInPlace(HDdouble *v, const HDdouble *s)
{
    hduVecScaleNonUniform(v, v, s);
}

HDdouble hduVecDotProduct(const HDdouble *v1, const HDdouble *v2)
{
    return v1[0] * v2[0] + v1[1] * v2[1] + v1[2] * v2[2];
}

HDdouble hduVecMagnitude(const HDdouble *v)
{
    return sqrt(hduVecDotProduct(v, v));
}

HDdouble hduVecDistance(const HDdouble *v1, const HDdouble *v2)
{
    HDdouble d[3];
    hduVecSubtract(d, v1, v2);
    return hduVecMagnitude(d);
}

void hduVecCrossProduct(HDdouble *res, const HDdouble *v1, const HDdouble *v2)
{
    hduVecSet(res, v1[1] * v2[2] - v1[2] * v2[1], v1[2] * v2[0] - v1[0] * v2[2],
              v1[0] * v2[1] - v1[1] * v2[0]);
}

void hduVecNormalize(HDdouble *res, const HDdouble *v)
{
    HDdouble m = hduVecMagnitude(v);
    if (m > 0.0)
        hduVecScale(res, v, 1.0 / m);
    else
        hduVecCopy(res, v);
}

void hduVecNormalizeInPlace(HDdouble *v)
{
    hduVecNormalize(v, v);
}

HDboolean hduVecIsEqual(const HDdouble *v1, const HDdouble *v2, HDdouble epsilon)
{
    for (int i = 0; i < 3; ++i)
        if (fabs(v1[i] - v2[i]) > epsilon)
            return HD_FALSE;
    return HD_TRUE;
}

} // extern "C"
