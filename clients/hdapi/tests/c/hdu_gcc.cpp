// C++ built and linked by gcc, not g++, so without the C++ runtime, as the SDK's
// CommandJointTorque example is ("gcc … x.cpp -lHDU -lHD -lrt"): hduVector3Dd, including a
// function-local static const one (C++11 and later: constexpr constructors), and the C
// functions must need nothing of libstdc++ (docs/HDAPI.md, libHDU); nor of libm, which is not
// linked either (so no magnitude() here: it calls sqrt). Checked in tests/hdapi.rs.
#include <HDU/hduError.h>
#include <HDU/hduVector.h>
#include <stdio.h>

static const hduVector3Dd maxTorque(188.0, 188.0, 48.0);

static hduVector3Dd spring(const hduVector3Dd &position)
{
    static const hduVector3Dd anchor(10.0, -20.0, 5.0);
    static const double k = 0.25;
    return (anchor - position) * k;
}

int main()
{
    hduVector3Dd f = spring(hduVector3Dd(12.0, -18.0, 4.0));
    hduVector3Dd c = f.crossProduct(maxTorque);
    double m[3];
    hduVecScale(m, f, 2.0);
    HDErrorInfo e = {HD_TIMER_ERROR, 0, 0};
    printf("gcc %g %g %g %g %g %g %g %d\n", f[0], f[1], f[2], f.dotProduct(maxTorque), c[2], m[0],
           hduVecMagnitude(f) * hduVecMagnitude(f), hduIsSchedulerError(&e));
    return 0;
}
