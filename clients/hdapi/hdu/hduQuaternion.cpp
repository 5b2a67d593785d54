// omnid libHDU: hduQuaternion's conversions (docs/HDAPI.md, libHDU, for the convention).
// The column-vector rotation R of q is stored transposed in an hduMatrix: m[i][j] = R(j, i).
#include <HDU/hduQuaternion.h>
#include <cmath>

void hduQuaternion::fromMatrix(const hduMatrix &m)
{
    // R(row, col) = m[col][row]; the branch on the largest diagonal term keeps k away from 0.
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

void hduQuaternion::toMatrix(hduMatrix &m) const
{
    hduQuaternion q(*this);
    q.normalize();
    const double w = q.s_, x = q.v_[0], y = q.v_[1], z = q.v_[2];
    const double R[3][3] = {
        {1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
        {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
        {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)},
    };
    m.makeIdentity();
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            m[i][j] = R[j][i];
}

void hduQuaternion::fromAxisAngle(const hduVector3Dd &axis, double radians)
{
    double n = axis.magnitude();
    if (n == 0.0) {
        s_ = 1.0;
        v_.set(0.0, 0.0, 0.0);
        return;
    }
    s_ = std::cos(radians / 2);
    v_ = axis * (std::sin(radians / 2) / n);
}

void hduQuaternion::toAxisAngle(hduVector3Dd &axis, double &radians) const
{
    hduQuaternion q(*this);
    q.normalize();
    double s = q.s_ > 1.0 ? 1.0 : (q.s_ < -1.0 ? -1.0 : q.s_);
    double half_sin = std::sqrt(1.0 - s * s);
    if (half_sin < 1e-12) {
        axis.set(1.0, 0.0, 0.0);
        radians = 0.0;
        return;
    }
    axis = q.v_ / half_sin;
    radians = 2.0 * std::acos(s);
}

hduQuaternion hduQuaternion::slerp(const hduQuaternion &to, double t) const
{
    hduQuaternion a(*this), b(to);
    a.normalize();
    b.normalize();
    double cosine = a.dotProduct(b);
    if (cosine < 0.0) {
        b = -b;
        cosine = -cosine;
    }
    double wa, wb;
    if (cosine > 0.9995) { // nearly equal: linear, then normalized
        wa = 1.0 - t;
        wb = t;
    } else {
        double angle = std::acos(cosine), sine = std::sin(angle);
        wa = std::sin((1.0 - t) * angle) / sine;
        wb = std::sin(t * angle) / sine;
    }
    hduQuaternion r = a * wa + b * wb;
    return r.normalize();
}
