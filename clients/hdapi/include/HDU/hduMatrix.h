/* omnid libHD: a 4x4 transform for HD programs (docs/HDAPI.md, HDU helpers). C++ only.
 * Stored as HD_CURRENT_TRANSFORM is: 16 doubles, column-major, m[col][row] with the
 * translation in m[3][0..2]. */
#ifndef OMNID_HDU_MATRIX_H
#define OMNID_HDU_MATRIX_H

#ifdef __cplusplus
#include <HDU/hduVector.h>

class hduMatrix {
public:
    hduMatrix() { makeIdentity(); }
    explicit hduMatrix(const double *p) { set(p); }
    hduMatrix(const double m[4][4]) { set(&m[0][0]); }
    /* Sixteen values in storage order: a00 a01 a02 a03 is m[0][0..3] (the first column). */
    hduMatrix(double a00, double a01, double a02, double a03, double a10, double a11, double a12,
              double a13, double a20, double a21, double a22, double a23, double a30, double a31,
              double a32, double a33)
    {
        const double p[16] = {a00, a01, a02, a03, a10, a11, a12, a13,
                              a20, a21, a22, a23, a30, a31, a32, a33};
        set(p);
    }

    void set(const double *p) { for (int i = 0; i < 16; ++i) (&m_[0][0])[i] = p[i]; }
    void get(double *p) const { for (int i = 0; i < 16; ++i) p[i] = (&m_[0][0])[i]; }
    void makeIdentity() { for (int c = 0; c < 4; ++c) for (int r = 0; r < 4; ++r) m_[c][r] = (c == r); }

    double *operator[](int c) { return m_[c]; }
    const double *operator[](int c) const { return m_[c]; }
    operator double *() { return &m_[0][0]; }
    operator const double *() const { return &m_[0][0]; }

    hduMatrix operator*(const hduMatrix &o) const
    {
        hduMatrix out;
        for (int c = 0; c < 4; ++c)
            for (int r = 0; r < 4; ++r) {
                double s = 0;
                for (int k = 0; k < 4; ++k) s += m_[k][r] * o.m_[c][k];
                out.m_[c][r] = s;
            }
        return out;
    }

    /* Transform a point (rotation and translation). */
    void multVecMatrix(const hduVector3Dd &in, hduVector3Dd &out) const
    {
        hduVector3Dd t;
        for (int r = 0; r < 3; ++r) t[r] = m_[0][r] * in[0] + m_[1][r] * in[1] + m_[2][r] * in[2] + m_[3][r];
        out = t;
    }
    /* Transform a direction (rotation only). */
    void multDirMatrix(const hduVector3Dd &in, hduVector3Dd &out) const
    {
        hduVector3Dd t;
        for (int r = 0; r < 3; ++r) t[r] = m_[0][r] * in[0] + m_[1][r] * in[1] + m_[2][r] * in[2];
        out = t;
    }
    void getTranslation(hduVector3Dd &t) const { t.set(m_[3][0], m_[3][1], m_[3][2]); }
    /* This matrix without its translation (the rotation part alone). */
    void getRotationMatrix(hduMatrix &r) const
    {
        hduMatrix out(*this);
        out.m_[3][0] = out.m_[3][1] = out.m_[3][2] = 0.0;
        out.m_[0][3] = out.m_[1][3] = out.m_[2][3] = 0.0;
        out.m_[3][3] = 1.0;
        r = out;
    }

private:
    double m_[4][4];
};

#endif
#endif
