// libHDU from C++ as the SDK's examples and the open drivers use it (docs/HDAPI.md, libHDU):
// hduVector3Dd's operators, hduMatrix transforms, hduQuaternion, hduLineSegment, the error
// stream. Built with the examples' "-lHDU -lHD -lrt -lncurses"; every result is printed as
// "key values..." and checked against Rust's own computation (nalgebra) in tests/hdapi.rs.
#include <HDU/hdu.h>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>

static void pv(const char *key, const hduVector3Dd &v)
{
    std::printf("%s %.17g %.17g %.17g\n", key, v[0], v[1], v[2]);
}

static void pm(const char *key, const hduMatrix &m)
{
    std::printf("%s", key);
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) std::printf(" %.17g", m[r][c]);
    std::printf("\n");
}

// Largest |a - b| over the 16 elements.
static double diff(const hduMatrix &a, const hduMatrix &b)
{
    double d = 0;
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) d = std::fmax(d, std::fabs(a[r][c] - b[r][c]));
    return d;
}

static double diff(const hduVector3Dd &a, const hduVector3Dd &b)
{
    return std::fmax(std::fabs(a[0] - b[0]), std::fmax(std::fabs(a[1] - b[1]), std::fabs(a[2] - b[2])));
}

int main()
{
    // Vectors: the operators of the examples (FrictionlessSphere, CommandJointTorque).
    hduVector3Dd a(1, 2, 3), b(-4, 0.5, 2);
    pv("ops", (a + b) * 2.0 - b / 4.0);
    pv("neg", -a);
    pv("cross", a.crossProduct(b));
    pv("cross-free", crossProduct(a, b));
    std::printf("dot %.17g %.17g\n", a.dotProduct(b), dotProduct(a, b));
    std::printf("magnitude %.17g\n", a.magnitude());
    std::printf("distance %.17g\n", a.distance(b));
    pv("normalize-free", normalize(b));
    std::printf("unchanged %d\n", b == hduVector3Dd(-4, 0.5, 2));
    {
        hduVector3Dd n(b);
        n.normalize();
        pv("normalize", n);
    }
    {
        std::ostringstream os;
        os << a;
        hduVector3Dd back;
        std::istringstream is(os.str());
        is >> back;
        std::printf("stream %d\n", back == a && !(back != a));
    }
    {
        // The C functions take the class too (it converts to HDdouble *).
        hduVector3Dd r;
        hduVecAdd(r, a, b);
        pv("c-add", r);
    }

    // Matrices.
    const double pi = HDU_PI;
    hduVector3Dd x(1, 0, 0), out;
    hduMatrix rz = hduMatrix::createRotation(hduVector3Dd(0, 0, 1), pi / 2);
    rz.multVecMatrix(x, out);
    pv("rz-x", out);
    hduMatrix::createRotationAroundX(pi / 2).multVecMatrix(hduVector3Dd(0, 1, 0), out);
    pv("rx-y", out);
    hduMatrix::createRotationAroundY(pi / 2).multVecMatrix(hduVector3Dd(0, 0, 1), out);
    pv("ry-z", out);

    const hduVector3Dd axis(1, 2, 3), p(0.3, -1, 2);
    const double angle = 0.7;
    hduMatrix rot = hduMatrix::createRotation(axis, angle);
    pm("rot", rot);
    rot.multVecMatrix(p, out);
    pv("rot-p", out);
    hduMatrix t = hduMatrix::createTranslation(10, 20, 30);
    hduMatrix s = hduMatrix::createScale(hduVector3Dd(2, 3, 4));
    hduMatrix m = s * rot * t; // scale, then rotate, then translate
    m.multVecMatrix(p, out);
    pv("srt-p", out);
    m.multDirMatrix(p, out);
    pv("srt-dir", out);
    {
        hduMatrix left = rot;
        left.multLeft(s);
        hduMatrix right = s;
        right.multRight(rot);
        hduMatrix times = s;
        times *= rot;
        std::printf("mult %.3g %.3g\n", diff(left, s * rot), std::fmax(diff(right, s * rot), diff(times, s * rot)));
    }
    std::printf("inverse %.3g %.3g\n", diff(m * m.inverse(), hduMatrix()), diff(m.inverse() * m, hduMatrix()));
    {
        hduMatrix inv = m;
        bool ok = inv.invert() && diff(inv, m.inverse()) == 0;
        hduMatrix singular = hduMatrix::createScale(1, 0, 1), si;
        bool sok = singular.getInverse(si);
        std::printf("invert %d %d %d\n", ok, sok, si.isIdentity());
    }
    std::printf("transpose %.3g %.3g\n", diff(rot.transpose(), rot.inverse()), diff(m.transpose().transpose(), m));
    std::printf("determinant %.17g %.17g\n", m.determinant(), rot.determinant());
    {
        // Storage: HD_CURRENT_TRANSFORM's layout, translation at [12..14].
        double flat[16], grid[4][4];
        t.get(flat);
        t.get(grid);
        m.getValue(flat);
        hduMatrix fromFlat(flat);
        std::printf("storage %g %g %g %g %d\n", t.getValue()[12], t.getValue()[13], grid[3][2], t(3, 0),
                    fromFlat == m);
        hduVector3Dd tr;
        m.getTranslation(tr);
        pv("translation", tr);
        hduMatrix r;
        m.getRotationMatrix(r);
        pv("rotation-part", r.getTranslation());
    }
    {
        std::ostringstream os;
        os << t;
        std::printf("matrix-stream %d\n", os.str() == "1 0 0 0\n0 1 0 0\n0 0 1 0\n10 20 30 1");
    }

    // Quaternions.
    hduQuaternion q(axis, angle);
    std::printf("q %.17g %.17g %.17g %.17g norm %.17g\n", q.s(), q.v()[0], q.v()[1], q.v()[2], q.norm());
    std::printf("q-matrix %.3g\n", diff(q.toMatrix(), rot));
    std::printf("q-rotate %.3g\n", [&] { hduVector3Dd o; rot.multVecMatrix(p, o); return diff(q.rotate(p), o); }());
    {
        hduQuaternion back(rot);
        double d = std::fmin(std::fabs(back.s() - q.s()) + diff(back.v(), q.v()),
                             std::fabs(back.s() + q.s()) + diff(back.v(), -q.v()));
        std::printf("q-from-matrix %.3g\n", d);
        // The large-angle branches of the conversion: half turns about each axis, and near one.
        double worst = 0;
        const hduVector3Dd axes[4] = {hduVector3Dd(1, 0, 0), hduVector3Dd(0, 1, 0), hduVector3Dd(0, 0, 1),
                                      hduVector3Dd(1, -1, 0.5)};
        for (int i = 0; i < 4; ++i)
            for (double ang = 2.5; ang < 3.2; ang += 0.3) {
                hduMatrix r = hduMatrix::createRotation(axes[i], ang);
                worst = std::fmax(worst, diff(hduQuaternion(r).toMatrix(), r));
            }
        std::printf("q-round-trip %.3g\n", worst);
    }
    {
        hduVector3Dd ax;
        double ang;
        q.toAxisAngle(ax, ang);
        std::printf("q-axis-angle %.3g %.17g\n", diff(ax, normalize(axis)), ang);
        hduQuaternion q2(hduVector3Dd(0, 1, 0), 0.4);
        std::printf("q-compose %.3g\n", diff((q * q2).toMatrix(), q2.toMatrix() * q.toMatrix()));
        std::printf("q-inverse %.3g\n", diff((q * q.inverse()).toMatrix(), hduMatrix()));
        hduQuaternion half = hduQuaternion().slerp(q, 0.5);
        std::printf("q-slerp %.3g\n", diff(half.toMatrix(), hduMatrix::createRotation(axis, angle / 2)));
    }

    // Line segments.
    hduLineSegmentd seg(hduVector3Dd(0, 0, 0), hduVector3Dd(10, 0, 0));
    double u;
    pv("seg-project", seg.projectPoint(hduVector3Dd(5, 3, 0), u));
    std::printf("seg-t %.17g distance %.17g %.17g length %.17g\n", u, seg.distance(hduVector3Dd(5, 3, 0)),
                seg.distance(hduVector3Dd(-2, 1, 0)), seg.length());
    pv("seg-beyond", seg.projectPoint(hduVector3Dd(14, -1, 2)));

    // hduMath in C++.
    std::printf("math %d %.17g %.17g %d\n", hduClamp(7, 0, 5), hduDegToRad(180.0), hduClamp(0.5, 0.0, 1.0),
                hduIsEqual(1.0, 1.0 + 1e-12, 1e-9));

    // The error on a stream.
    {
        HDErrorInfo e = {HD_TIMER_ERROR, 7, 0};
        std::ostringstream os;
        os << e;
        std::printf("error-stream %s\n", os.str().find("HD_TIMER_ERROR") != std::string::npos ? "names" : os.str().c_str());
        std::printf("error-kind %d %d %d\n", hduIsSchedulerError(&e), hduIsForceError(&e), hduIsComError(&e));
    }
    std::printf("done\n");
    return 0;
}
