/* A servo callback that drives the arm too fast: a constant push until the daemon's safety
 * layer trips on the joints' speed, which must come back as HD_EXCEEDED_MAX_VELOCITY (a force
 * error, internal code 8) at the end of a frame, with a readable string. Argument: the push,
 * N along +x (default 2). */
#include "hdtest.h"
#include <stdlib.h>
#include <string.h>

static volatile int ticks, velocity, other, done;
static volatile HDErrorInfo got;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    HDdouble *push = (HDdouble *)data;
    hdBeginFrame(hdGetCurrentDevice());
    HDdouble force[3] = {*push, 0.0, 0.0};
    hdSetDoublev(HD_CURRENT_FORCE, force);
    hdEndFrame(hdGetCurrentDevice());
    ticks++;
    HDErrorInfo e;
    while (HD_DEVICE_ERROR(e = hdGetError())) {
        if (e.errorCode == HD_EXCEEDED_MAX_VELOCITY) {
            velocity++;
            got = e;
            done = 1;
            return HD_CALLBACK_DONE; /* as the SDK's examples stop rendering on a force error */
        }
        if (e.errorCode != HD_EXCEEDED_MAX_FORCE && e.errorCode != HD_WARM_MOTORS)
            other++;
    }
    return HD_CALLBACK_CONTINUE;
}

int main(int argc, char **argv)
{
    HDdouble push = argc > 1 ? atof(argv[1]) : 2.0;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdEnable(HD_FORCE_OUTPUT);
    hdScheduleAsynchronous(servo, &push, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    for (int waited = 0; !done && waited < 20000; waited += 10)
        sleep_ms(10);
    hdStopScheduler();
    HDErrorInfo e = got;
    printf("ticks %d\nvelocity-errors %d\nother-errors %d\n", ticks, velocity, other);
    printf("error 0x%x internal %d force-error %d scheduler-error %d\n", e.errorCode,
           e.internalErrorCode, hduIsForceError(&e), hduIsSchedulerError(&e));
    printf("string %s\n", hdGetErrorString(e.errorCode));
    return 0;
}
