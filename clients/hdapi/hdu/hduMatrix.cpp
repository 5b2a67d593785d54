// omnid libHDU: hduMatrix's larger functions (docs/HDAPI.md, libHDU, for the convention).
#include <HDU/hduMatrix.h>
#include <cmath>

hduMatrix hduMatrix::createTranslation(double x, double y, double z)
{
    hduMatrix t;
    t.m_[3][0] = x;
    t.m_[3][1] = y;
    t.m_[3][2] = z;
    return t;
}

hduMatrix hduMatrix::createScale(double sx, double sy, double sz)
{
    hduMatrix s;
    s.m_[0][0] = sx;
    s.m_[1][1] = sy;
    s.m_[2][2] = sz;
    return s;
}

// Rodrigues' formula for the column-vector rotation R = cI + s[u]x + (1 - c)uu^T, stored
// transposed (rows are the images of the axes): m[i][j] = R(j, i).
hduMatrix hduMatrix::createRotation(const hduVector3Dd &axis, double radians)
{
    hduMatrix r;
    double n = axis.magnitude();
    if (n == 0.0)
        return r;
    const double u[3] = {axis[0] / n, axis[1] / n, axis[2] / n};
    const double c = std::cos(radians), s = std::sin(radians), k = 1.0 - c;
    // [u]x(i, j): the matrix of u x (.)
    const double cross[3][3] = {{0.0, -u[2], u[1]}, {u[2], 0.0, -u[0]}, {-u[1], u[0], 0.0}};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r.m_[i][j] = (i == j ? c : 0.0) + k * u[i] * u[j] + s * cross[j][i];
    return r;
}

hduMatrix hduMatrix::createRotationAroundX(double radians)
{
    return createRotation(hduVector3Dd(1, 0, 0), radians);
}

hduMatrix hduMatrix::createRotationAroundY(double radians)
{
    return createRotation(hduVector3Dd(0, 1, 0), radians);
}

hduMatrix hduMatrix::createRotationAroundZ(double radians)
{
    return createRotation(hduVector3Dd(0, 0, 1), radians);
}

hduMatrix hduMatrix::operator*(const hduMatrix &o) const
{
    hduMatrix out;
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) {
            double sum = 0.0;
            for (int k = 0; k < 4; ++k)
                sum += m_[r][k] * o.m_[k][c];
            out.m_[r][c] = sum;
        }
    return out;
}

// Gaussian elimination with partial pivoting: the product of the pivots, sign-corrected.
double hduMatrix::determinant() const
{
    double a[4][4];
    get(a);
    double det = 1.0;
    for (int col = 0; col < 4; ++col) {
        int pivot = col;
        for (int r = col + 1; r < 4; ++r)
            if (std::fabs(a[r][col]) > std::fabs(a[pivot][col]))
                pivot = r;
        if (a[pivot][col] == 0.0)
            return 0.0;
        if (pivot != col) {
            for (int c = 0; c < 4; ++c) {
                double t = a[col][c];
                a[col][c] = a[pivot][c];
                a[pivot][c] = t;
            }
            det = -det;
        }
        det *= a[col][col];
        for (int r = col + 1; r < 4; ++r) {
            double f = a[r][col] / a[col][col];
            for (int c = col; c < 4; ++c)
                a[r][c] -= f * a[col][c];
        }
    }
    return det;
}

// Gauss-Jordan elimination with partial pivoting on [A | I].
bool hduMatrix::getInverse(hduMatrix &inv) const
{
    double a[4][4];
    get(a);
    hduMatrix out;
    for (int col = 0; col < 4; ++col) {
        int pivot = col;
        for (int r = col + 1; r < 4; ++r)
            if (std::fabs(a[r][col]) > std::fabs(a[pivot][col]))
                pivot = r;
        if (std::fabs(a[pivot][col]) < 1e-300) {
            inv.makeIdentity();
            return false;
        }
        if (pivot != col)
            for (int c = 0; c < 4; ++c) {
                double t = a[col][c];
                a[col][c] = a[pivot][c];
                a[pivot][c] = t;
                t = out.m_[col][c];
                out.m_[col][c] = out.m_[pivot][c];
                out.m_[pivot][c] = t;
            }
        const double p = a[col][col];
        for (int c = 0; c < 4; ++c) {
            a[col][c] /= p;
            out.m_[col][c] /= p;
        }
        for (int r = 0; r < 4; ++r) {
            if (r == col)
                continue;
            const double f = a[r][col];
            if (f == 0.0)
                continue;
            for (int c = 0; c < 4; ++c) {
                a[r][c] -= f * a[col][c];
                out.m_[r][c] -= f * out.m_[col][c];
            }
        }
    }
    inv = out;
    return true;
}
