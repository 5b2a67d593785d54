/* omnid libHDU: quaternions for HD programs (docs/HDAPI.md, libHDU). C++ only (empty in
 * C); the conversions are in libHDU.a.
 *
 * q = s + v (scalar s, vector v). A unit quaternion is a rotation; its matrix (toMatrix,
 * the hduMatrix(q) of fromMatrix) follows hduMatrix's convention, so
 * q.toMatrix(m); m.multVecMatrix(p, out) rotates p as q.rotate(p) does, and the matrix of
 * q1 * q2 is M(q2) * M(q1) (q2 applied first). */
#ifndef OMNID_HDU_QUATERNION_H
#define OMNID_HDU_QUATERNION_H

#include <HD/hdDefines.h>

#ifdef __cplusplus
#include <cmath>
#include <ostream>
#include <HDU/hduMatrix.h>

class hduQuaternion {
public:
    hduQuaternion() : s_(1.0), v_(0.0, 0.0, 0.0) {}
    hduQuaternion(double s, const hduVector3Dd &v) : s_(s), v_(v) {}
    hduQuaternion(double s, double x, double y, double z) : s_(s), v_(x, y, z) {}
    /* The rotation by `radians` about `axis` (need not be unit length). */
    hduQuaternion(const hduVector3Dd &axis, double radians) { fromAxisAngle(axis, radians); }
    /* The rotation part of a transform (hduMatrix's convention). */
    explicit hduQuaternion(const hduMatrix &m) { fromMatrix(m); }

    double &s() { return s_; }
    double s() const { return s_; }
    hduVector3Dd &v() { return v_; }
    const hduVector3Dd &v() const { return v_; }
    /* Element i: 0 is s, 1..3 are v. */
    double &operator[](int i) { return i == 0 ? s_ : v_[i - 1]; }
    double operator[](int i) const { return i == 0 ? s_ : v_[i - 1]; }

    void fromMatrix(const hduMatrix &m);
    void toMatrix(hduMatrix &m) const;
    hduMatrix toMatrix() const { hduMatrix m; toMatrix(m); return m; }
    void fromAxisAngle(const hduVector3Dd &axis, double radians);
    /* The axis (unit) and angle (radians, 0..2 pi) of a unit quaternion; the identity gives
     * the axis (1, 0, 0) and angle 0. */
    void toAxisAngle(hduVector3Dd &axis, double &radians) const;

    double dotProduct(const hduQuaternion &o) const { return s_ * o.s_ + v_.dotProduct(o.v_); }
    double norm() const { return std::sqrt(dotProduct(*this)); }
    hduQuaternion &normalize() { double n = norm(); if (n > 0) { s_ /= n; v_ /= n; } return *this; }
    hduQuaternion conjugate() const { return hduQuaternion(s_, -v_); }
    hduQuaternion inverse() const
    {
        double n2 = dotProduct(*this);
        hduQuaternion c = conjugate();
        if (n2 > 0) { c.s_ /= n2; c.v_ /= n2; }
        return c;
    }
    /* The Hamilton product: the rotation o, then this. */
    hduQuaternion operator*(const hduQuaternion &o) const
    {
        return hduQuaternion(s_ * o.s_ - v_.dotProduct(o.v_), o.v_ * s_ + v_ * o.s_ + v_.crossProduct(o.v_));
    }
    hduQuaternion &operator*=(const hduQuaternion &o) { return *this = *this * o; }
    hduQuaternion operator*(double k) const { return hduQuaternion(s_ * k, v_ * k); }
    hduQuaternion operator+(const hduQuaternion &o) const { return hduQuaternion(s_ + o.s_, v_ + o.v_); }
    hduQuaternion operator-(const hduQuaternion &o) const { return hduQuaternion(s_ - o.s_, v_ - o.v_); }
    hduQuaternion operator-() const { return hduQuaternion(-s_, -v_); }
    bool operator==(const hduQuaternion &o) const { return s_ == o.s_ && v_ == o.v_; }
    bool operator!=(const hduQuaternion &o) const { return !(*this == o); }

    /* p rotated by this (unit) quaternion: q p q*. */
    hduVector3Dd rotate(const hduVector3Dd &p) const
    {
        hduQuaternion r = *this * hduQuaternion(0.0, p) * conjugate();
        return r.v_;
    }
    /* Spherical interpolation from this (t = 0) to `to` (t = 1), the short way round. */
    hduQuaternion slerp(const hduQuaternion &to, double t) const;

private:
    double s_;
    hduVector3Dd v_;
};

inline std::ostream &operator<<(std::ostream &os, const hduQuaternion &q)
{
    return os << q.s() << " " << q.v();
}

#endif
#endif
