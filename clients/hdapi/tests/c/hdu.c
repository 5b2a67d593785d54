/* libHDU from C as the SDK's HD console examples use it (docs/HDAPI.md, libHDU): vectors as
 * HDdouble[3] through the hduVec* functions, the error helpers on a real error (no daemon),
 * hduMath. Built with exactly the examples' "-lHDU -lHD -lrt -lncurses"; every result is
 * printed as "key values..." and checked against Rust's own computation in tests/suite/hdapi.rs. */
#include <HDU/hdu.h>
#include <stdio.h>

_Static_assert(sizeof(hduVector3Dd) == 3 * sizeof(HDdouble), "hduVector3Dd is HDdouble[3]");
_Static_assert(sizeof(hduVector3Df) == 3 * sizeof(HDfloat), "hduVector3Df is HDfloat[3]");

static void pv(const char *key, const hduVector3Dd v)
{
    printf("%s %.17g %.17g %.17g\n", key, v[0], v[1], v[2]);
}

int main(void)
{
    hduVector3Dd a = {1, 2, 3}, b, r;
    hduVecSet(b, -4, 0.5, 2);

    hduVecAdd(r, a, b);
    pv("add", r);
    hduVecSubtract(r, a, b);
    pv("sub", r);
    hduVecScale(r, a, 2.5);
    pv("scale", r);
    hduVecCopy(r, b);
    hduVecScaleInPlace(r, -3);
    pv("scale-in-place", r);
    hduVecScaleNonUniform(r, a, b);
    pv("scale-non-uniform", r);
    hduVecCopy(r, a);
    hduVecScaleNonUniformInPlace(r, b);
    pv("scale-non-uniform-in-place", r);
    hduVecNegate(r, b);
    pv("negate", r);
    hduVecCrossProduct(r, a, b);
    pv("cross", r);
    /* res aliasing an input */
    hduVecCopy(r, a);
    hduVecCrossProduct(r, r, b);
    pv("cross-aliased", r);
    hduVecNormalize(r, b);
    pv("normalize", r);
    hduVecCopy(r, a);
    hduVecNormalizeInPlace(r);
    pv("normalize-in-place", r);
    hduVecSet(r, 0, 0, 0);
    hduVecNormalizeInPlace(r);
    pv("normalize-zero", r);
    printf("magnitude %.17g\n", hduVecMagnitude(a));
    printf("dot %.17g\n", hduVecDotProduct(a, b));
    printf("distance %.17g\n", hduVecDistance(a, b));
    {
        hduVector3Dd near = {1 + 1e-7, 2 - 1e-7, 3};
        printf("equal %d %d %d\n", hduVecIsEqual(a, near, 1e-6), hduVecIsEqual(a, near, 1e-8),
               hduVecIsEqual(a, b, 1e-6));
    }

    /* AnchoredSpringForce's spring: F = k (anchor - position). */
    {
        hduVector3Dd anchor = {10, -20, 5}, position = {12, -18, 4}, force;
        hduVecSubtract(force, anchor, position);
        hduVecScaleInPlace(force, 0.25);
        pv("spring", force);
    }

    /* hduMath */
    printf("math %.17g %.17g %.17g %.17g %.17g %.17g\n", hduDegToRad(90), hduRadToDeg(HDU_PI / 4),
           hduClamp(5, 0, 3), hduClamp(-1, 0, 3), hduMin(2, -7), hduMax(2, -7));

    /* The error helpers on every code the HD API defines. */
    {
        static const HDerror codes[] = {0x000, 0x100, 0x101, 0x102, 0x103, 0x104, 0x200, 0x201,
                                        0x202, 0x203, 0x204, 0x300, 0x301, 0x302, 0x303, 0x304,
                                        0x400, 0x401, 0x402, 0x500, 0x501, 0x600};
        for (unsigned i = 0; i < sizeof codes / sizeof codes[0]; i++) {
            HDErrorInfo e = {codes[i], 0, 0};
            printf("kind %u %d %d %d\n", codes[i], hduIsSchedulerError(&e), hduIsForceError(&e),
                   hduIsComError(&e));
        }
        printf("kind-null %d %d %d\n", hduIsSchedulerError(NULL), hduIsForceError(NULL),
               hduIsComError(NULL));
    }

    /* A real error, as every example reports it. */
    {
        HDErrorInfo error;
        HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
        if (HD_DEVICE_ERROR(error = hdGetError())) {
            printf("print-begin\n");
            fflush(stdout);
            hduPrintError(stdout, &error, "Failed to initialize haptic device");
            printf("print-end\n");
            printf("init-error %u %d\n", error.errorCode, hduIsSchedulerError(&error));
        } else {
            printf("init-ok %u\n", hhd);
        }
        hduPrintError(stdout, NULL, "no error given");
        hduPrintError(NULL, &error, "no stream");
        {
            HDErrorInfo unknown = {0x777, 0, 0};
            printf("print-begin\n");
            hduPrintError(stdout, &unknown, NULL);
            printf("print-end\n");
        }
    }
    printf("done\n");
    return 0;
}
