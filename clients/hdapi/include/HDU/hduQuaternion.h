/* omnid libHD: a unit quaternion for HD programs (docs/HDAPI.md, HDU helpers). C++ only. */
#ifndef OMNID_HDU_QUATERNION_H
#define OMNID_HDU_QUATERNION_H

#ifdef __cplusplus
#include <cmath>
#include <HDU/hduMatrix.h>

class hduQuaternion {
public:
    hduQuaternion() : s_(1.0), v_(0.0, 0.0, 0.0) {}
    hduQuaternion(double s, const hduVector3Dd &v) : s_(s), v_(v) {}
    /* The rotation part of a transform (column-major, as HD_CURRENT_TRANSFORM). */
    explicit hduQuaternion(const hduMatrix &m) { fromMatrix(m); }

    double &s() { return s_; }
    double s() const { return s_; }
    hduVector3Dd &v() { return v_; }
    const hduVector3Dd &v() const { return v_; }

    void fromMatrix(const hduMatrix &m)
    {
        /* R(row, col) = m[col][row] */
        double r00 = m[0][0], r11 = m[1][1], r22 = m[2][2];
        double tr = r00 + r11 + r22;
        if (tr > 0) {
            double k = std::sqrt(tr + 1.0) * 2.0;
            s_ = 0.25 * k;
            v_.set((m[1][2] - m[2][1]) / k, (m[2][0] - m[0][2]) / k, (m[0][1] - m[1][0]) / k);
        } else if (r00 > r11 && r00 > r22) {
            double k = std::sqrt(1.0 + r00 - r11 - r22) * 2.0;
            s_ = (m[1][2] - m[2][1]) / k;
            v_.set(0.25 * k, (m[1][0] + m[0][1]) / k, (m[2][0] + m[0][2]) / k);
        } else if (r11 > r22) {
            double k = std::sqrt(1.0 + r11 - r00 - r22) * 2.0;
            s_ = (m[2][0] - m[0][2]) / k;
            v_.set((m[1][0] + m[0][1]) / k, 0.25 * k, (m[2][1] + m[1][2]) / k);
        } else {
            double k = std::sqrt(1.0 + r22 - r00 - r11) * 2.0;
            s_ = (m[0][1] - m[1][0]) / k;
            v_.set((m[2][0] + m[0][2]) / k, (m[2][1] + m[1][2]) / k, 0.25 * k);
        }
    }

    double norm() const { return std::sqrt(s_ * s_ + v_.dotProduct(v_)); }
    void normalize() { double n = norm(); if (n > 0) { s_ /= n; v_ /= n; } }

private:
    double s_;
    hduVector3Dd v_;
};

#endif
#endif
