/* omnid libHDU: 3-vectors for HD programs (docs/HDAPI.md, libHDU).
 *
 * In C a vector is an array of three numbers (hduVector3Dd is HDdouble[3]) handled by the
 * hduVec* functions of libHDU.a; in C++ it is the hduVector3D<T> class template (header-only),
 * which converts to T* so the C functions take it too. */
#ifndef OMNID_HDU_VECTOR_H
#define OMNID_HDU_VECTOR_H

#include <HD/hdDefines.h>

#ifdef __cplusplus
#include <cmath>
#include <istream>
#include <ostream>

template <typename T> class hduVector3D {
public:
    typedef T EltType;
#if __cplusplus >= 201103L
    /* constexpr: a function-local `static const hduVector3Dd v(1, 2, 3);` is then initialized
     * at compile time, with no guard variable, so a C++ program linked with gcc without the
     * C++ runtime (the SDK's CommandJointTorque) links. */
    constexpr hduVector3D() : v_{T(0), T(0), T(0)} {}
    constexpr hduVector3D(T x, T y, T z) : v_{x, y, z} {}
#else
    hduVector3D() { v_[0] = v_[1] = v_[2] = T(0); }
    hduVector3D(T x, T y, T z) { set(x, y, z); }
#endif
    explicit hduVector3D(const T *p) { set(p[0], p[1], p[2]); }
    template <typename U> hduVector3D(const hduVector3D<U> &o) { set(T(o[0]), T(o[1]), T(o[2])); }

    void set(T x, T y, T z) { v_[0] = x; v_[1] = y; v_[2] = z; }
    void set(const T *p) { set(p[0], p[1], p[2]); }
    T &operator[](int i) { return v_[i]; }
    const T &operator[](int i) const { return v_[i]; }
    operator T *() { return v_; }
    operator const T *() const { return v_; }

    hduVector3D &operator+=(const hduVector3D &o) { for (int i = 0; i < 3; ++i) v_[i] += o[i]; return *this; }
    hduVector3D &operator-=(const hduVector3D &o) { for (int i = 0; i < 3; ++i) v_[i] -= o[i]; return *this; }
    hduVector3D &operator*=(T s) { for (int i = 0; i < 3; ++i) v_[i] *= s; return *this; }
    hduVector3D &operator/=(T s) { for (int i = 0; i < 3; ++i) v_[i] /= s; return *this; }
    hduVector3D operator-() const { return hduVector3D(-v_[0], -v_[1], -v_[2]); }

    T dotProduct(const hduVector3D &o) const { return v_[0] * o[0] + v_[1] * o[1] + v_[2] * o[2]; }
    hduVector3D crossProduct(const hduVector3D &o) const
    {
        return hduVector3D(v_[1] * o[2] - v_[2] * o[1], v_[2] * o[0] - v_[0] * o[2],
                           v_[0] * o[1] - v_[1] * o[0]);
    }
    T magnitude() const { return T(std::sqrt(double(dotProduct(*this)))); }
    T magnitudeSquared() const { return dotProduct(*this); }
    T distance(const hduVector3D &o) const { hduVector3D d(*this); return (d -= o).magnitude(); }
    T distanceSqr(const hduVector3D &o) const { hduVector3D d(*this); return (d -= o).magnitudeSquared(); }
    /* Scale to length 1 (a zero vector stays zero); returns *this. */
    hduVector3D &normalize() { T m = magnitude(); if (m > T(0)) *this /= m; return *this; }
    bool isZero(T eps) const { return std::fabs(double(v_[0])) <= eps && std::fabs(double(v_[1])) <= eps && std::fabs(double(v_[2])) <= eps; }
    bool isEqual(const hduVector3D &o, T eps) const { hduVector3D d(*this); return (d -= o).isZero(eps); }

private:
    T v_[3];
};

template <typename T> hduVector3D<T> operator+(hduVector3D<T> a, const hduVector3D<T> &b) { return a += b; }
template <typename T> hduVector3D<T> operator-(hduVector3D<T> a, const hduVector3D<T> &b) { return a -= b; }
/* The scalar is not deduced, so `v * 3` and `v / 2` work for a vector of doubles. */
template <typename T> hduVector3D<T> operator*(hduVector3D<T> a, typename hduVector3D<T>::EltType s) { return a *= s; }
template <typename T> hduVector3D<T> operator*(typename hduVector3D<T>::EltType s, hduVector3D<T> a) { return a *= s; }
template <typename T> hduVector3D<T> operator/(hduVector3D<T> a, typename hduVector3D<T>::EltType s) { return a /= s; }
template <typename T> bool operator==(const hduVector3D<T> &a, const hduVector3D<T> &b)
{
    return a[0] == b[0] && a[1] == b[1] && a[2] == b[2];
}
template <typename T> bool operator!=(const hduVector3D<T> &a, const hduVector3D<T> &b) { return !(a == b); }

/* Free forms of the members. */
template <typename T> T dotProduct(const hduVector3D<T> &a, const hduVector3D<T> &b) { return a.dotProduct(b); }
template <typename T> hduVector3D<T> crossProduct(const hduVector3D<T> &a, const hduVector3D<T> &b) { return a.crossProduct(b); }
template <typename T> T magnitude(const hduVector3D<T> &a) { return a.magnitude(); }
template <typename T> T distance(const hduVector3D<T> &a, const hduVector3D<T> &b) { return a.distance(b); }
/* A unit vector along `a` (a zero vector stays zero); `a` is unchanged. */
template <typename T> hduVector3D<T> normalize(const hduVector3D<T> &a) { hduVector3D<T> n(a); return n.normalize(); }

/* Written as "x y z"; read back from three whitespace-separated numbers. */
template <typename T> std::ostream &operator<<(std::ostream &os, const hduVector3D<T> &v)
{
    return os << v[0] << " " << v[1] << " " << v[2];
}
template <typename T> std::istream &operator>>(std::istream &is, hduVector3D<T> &v)
{
    return is >> v[0] >> v[1] >> v[2];
}

typedef hduVector3D<double> hduVector3Dd;
typedef hduVector3D<float> hduVector3Df;
typedef hduVector3D<int> hduVector3Di;

#else /* C */

typedef HDdouble hduVector3Dd[3];
typedef HDfloat hduVector3Df[3];
typedef HDint hduVector3Di[3];

#endif

/* The C vector functions (libHDU.a, C linkage), for hduVector3Dd in C and, through its
 * conversion to HDdouble *, in C++. `res` may be one of the inputs. */
HD_BEGIN_DECLS
void hduVecSet(HDdouble *vec, HDdouble x, HDdouble y, HDdouble z);
void hduVecCopy(HDdouble *dst, const HDdouble *src);
void hduVecAdd(HDdouble *res, const HDdouble *v1, const HDdouble *v2);
void hduVecSubtract(HDdouble *res, const HDdouble *v1, const HDdouble *v2);
void hduVecNegate(HDdouble *res, const HDdouble *v);
void hduVecScale(HDdouble *res, const HDdouble *v, HDdouble s);
void hduVecScaleInPlace(HDdouble *v, HDdouble s);
void hduVecScaleNonUniform(HDdouble *res, const HDdouble *v, const HDdouble *s);
void hduVecScaleNonUniformInPlace(HDdouble *v, const HDdouble *s);
HDdouble hduVecMagnitude(const HDdouble *v);
HDdouble hduVecDistance(const HDdouble *v1, const HDdouble *v2);
HDdouble hduVecDotProduct(const HDdouble *v1, const HDdouble *v2);
void hduVecCrossProduct(HDdouble *res, const HDdouble *v1, const HDdouble *v2);
/* Scale to length 1; a zero vector stays zero. */
void hduVecNormalize(HDdouble *res, const HDdouble *v);
void hduVecNormalizeInPlace(HDdouble *v);
/* True when every component differs by at most `epsilon`. */
HDboolean hduVecIsEqual(const HDdouble *v1, const HDdouble *v2, HDdouble epsilon);
HD_END_DECLS

#endif
