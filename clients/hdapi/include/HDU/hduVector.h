/* omnid libHD: a small 3-vector for HD programs (docs/HDAPI.md, HDU helpers). C++ only. */
#ifndef OMNID_HDU_VECTOR_H
#define OMNID_HDU_VECTOR_H

#ifdef __cplusplus
#include <cmath>
#include <ostream>

template <typename T> class hduVector3D {
public:
    typedef T EltType;
    hduVector3D() { v_[0] = v_[1] = v_[2] = T(0); }
    hduVector3D(T x, T y, T z) { set(x, y, z); }
    explicit hduVector3D(const T *p) { set(p[0], p[1], p[2]); }
    template <typename U> hduVector3D(const hduVector3D<U> &o) { set(T(o[0]), T(o[1]), T(o[2])); }

    void set(T x, T y, T z) { v_[0] = x; v_[1] = y; v_[2] = z; }
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
    T magnitude() const { return std::sqrt(dotProduct(*this)); }
    void normalize() { T m = magnitude(); if (m > T(0)) *this /= m; }
    bool isZero(T eps) const { return std::fabs(v_[0]) <= eps && std::fabs(v_[1]) <= eps && std::fabs(v_[2]) <= eps; }

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
template <typename T> std::ostream &operator<<(std::ostream &os, const hduVector3D<T> &v)
{
    return os << v[0] << " " << v[1] << " " << v[2];
}

typedef hduVector3D<double> hduVector3Dd;
typedef hduVector3D<float> hduVector3Df;
typedef hduVector3D<int> hduVector3Di;

#endif
#endif
