/* omnid libHDU: a 4x4 transform for HD programs (docs/HDAPI.md, libHDU). C++ only (empty
 * in C); the larger functions are in libHDU.a.
 *
 * Convention (docs/HDAPI.md, libHDU): points are row vectors multiplied on the left,
 * p' = p M, so m[row][col] holds the rotation in rows 0..2 and the translation in
 * m[3][0..2]. The 16 doubles in memory are therefore laid out as HD_CURRENT_TRANSFORM and
 * OpenGL's matrices are. A * B applies A first, then B. */
#ifndef OMNID_HDU_MATRIX_H
#define OMNID_HDU_MATRIX_H

#include <HD/hdDefines.h>

#ifdef __cplusplus
#include <ostream>
#include <HDU/hduVector.h>

class hduMatrix {
public:
    hduMatrix() { makeIdentity(); }
    explicit hduMatrix(const double *p) { set(p); }
    hduMatrix(const double m[4][4]) { set(m); }
    /* Sixteen values in storage order: a00 a01 a02 a03 is m[0][0..3] (the first row). */
    hduMatrix(double a00, double a01, double a02, double a03, double a10, double a11, double a12,
              double a13, double a20, double a21, double a22, double a23, double a30, double a31,
              double a32, double a33)
    {
        const double p[16] = {a00, a01, a02, a03, a10, a11, a12, a13,
                              a20, a21, a22, a23, a30, a31, a32, a33};
        set(p);
    }

    /* Transforms. Angles in radians; a rotation turns counter-clockwise looking down `axis`
     * (right-handed): createRotation((0,0,1), pi/2) maps (1,0,0) to (0,1,0). */
    static hduMatrix createTranslation(double x, double y, double z);
    static hduMatrix createTranslation(const hduVector3Dd &t) { return createTranslation(t[0], t[1], t[2]); }
    static hduMatrix createScale(double sx, double sy, double sz);
    static hduMatrix createScale(const hduVector3Dd &s) { return createScale(s[0], s[1], s[2]); }
    static hduMatrix createRotation(const hduVector3Dd &axis, double radians);
    static hduMatrix createRotationAroundX(double radians);
    static hduMatrix createRotationAroundY(double radians);
    static hduMatrix createRotationAroundZ(double radians);

    void set(const double *p) { for (int i = 0; i < 16; ++i) (&m_[0][0])[i] = p[i]; }
    void set(const double m[4][4]) { set(&m[0][0]); }
    void get(double *p) const { for (int i = 0; i < 16; ++i) p[i] = (&m_[0][0])[i]; }
    void get(double m[4][4]) const { get(&m[0][0]); }
    void getValue(double *p) const { get(p); }
    void getValue(double m[4][4]) const { get(&m[0][0]); }
    const double *getValue() const { return &m_[0][0]; }
    void makeIdentity() { for (int r = 0; r < 4; ++r) for (int c = 0; c < 4; ++c) m_[r][c] = (r == c); }
    bool isIdentity() const { return *this == hduMatrix(); }

    double *operator[](int row) { return m_[row]; }
    const double *operator[](int row) const { return m_[row]; }
    double &operator()(int row, int col) { return m_[row][col]; }
    double operator()(int row, int col) const { return m_[row][col]; }
    operator double *() { return &m_[0][0]; }
    operator const double *() const { return &m_[0][0]; }

    /* The product this * o (this applied first, then o). */
    hduMatrix operator*(const hduMatrix &o) const;
    hduMatrix &operator*=(const hduMatrix &o) { return *this = *this * o; }
    /* this = this * m, and this = m * this. */
    hduMatrix &multRight(const hduMatrix &m) { return *this = *this * m; }
    hduMatrix &multLeft(const hduMatrix &m) { return *this = m * *this; }
    bool operator==(const hduMatrix &o) const
    {
        for (int i = 0; i < 16; ++i)
            if ((&m_[0][0])[i] != (&o.m_[0][0])[i]) return false;
        return true;
    }
    bool operator!=(const hduMatrix &o) const { return !(*this == o); }

    hduMatrix transpose() const
    {
        hduMatrix t;
        for (int r = 0; r < 4; ++r) for (int c = 0; c < 4; ++c) t.m_[r][c] = m_[c][r];
        return t;
    }
    double determinant() const;
    /* The inverse; a singular matrix gives the identity (getInverse, invert say so). */
    hduMatrix inverse() const { hduMatrix i; getInverse(i); return i; }
    bool getInverse(hduMatrix &inv) const;
    bool invert() { hduMatrix i; bool ok = getInverse(i); *this = i; return ok; }

    /* Transform a point (rotation, scale and translation): out = in M. `out` may be `in`. */
    template <typename T> void multVecMatrix(const hduVector3D<T> &in, hduVector3D<T> &out) const
    {
        double t[4];
        for (int c = 0; c < 4; ++c) t[c] = m_[0][c] * in[0] + m_[1][c] * in[1] + m_[2][c] * in[2] + m_[3][c];
        double w = (t[3] != 0.0) ? t[3] : 1.0;
        out.set(T(t[0] / w), T(t[1] / w), T(t[2] / w));
    }
    /* Transform a direction (no translation). `out` may be `in`. */
    template <typename T> void multDirMatrix(const hduVector3D<T> &in, hduVector3D<T> &out) const
    {
        double t[3];
        for (int c = 0; c < 3; ++c) t[c] = m_[0][c] * in[0] + m_[1][c] * in[1] + m_[2][c] * in[2];
        out.set(T(t[0]), T(t[1]), T(t[2]));
    }
    void getTranslation(hduVector3Dd &t) const { t.set(m_[3][0], m_[3][1], m_[3][2]); }
    hduVector3Dd getTranslation() const { return hduVector3Dd(m_[3][0], m_[3][1], m_[3][2]); }
    void setTranslation(const hduVector3Dd &t) { m_[3][0] = t[0]; m_[3][1] = t[1]; m_[3][2] = t[2]; }
    /* This matrix without its translation (the rotation part alone). */
    void getRotationMatrix(hduMatrix &r) const
    {
        hduMatrix out(*this);
        out.m_[3][0] = out.m_[3][1] = out.m_[3][2] = 0.0;
        out.m_[0][3] = out.m_[1][3] = out.m_[2][3] = 0.0;
        out.m_[3][3] = 1.0;
        r = out;
    }
    hduMatrix getRotationMatrix() const { hduMatrix r; getRotationMatrix(r); return r; }

private:
    double m_[4][4];
};

/* Four rows of four numbers. */
inline std::ostream &operator<<(std::ostream &os, const hduMatrix &m)
{
    for (int r = 0; r < 4; ++r)
        os << m[r][0] << " " << m[r][1] << " " << m[r][2] << " " << m[r][3] << (r < 3 ? "\n" : "");
    return os;
}

#endif
#endif
