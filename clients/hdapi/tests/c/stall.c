/* A servo callback running while the daemon's servo loop stalls (omnid serve --inject
 * slow@T:MS): the stall must come back as a scheduler error (HD_TIMER_ERROR, internal code 9,
 * hduIsSchedulerError) at the end of a frame, with a readable string. Runs until it sees one
 * or the time runs out (argument: s, default 30). */
#include "hdtest.h"
#include <stdlib.h>

static volatile int ticks, timer, other, done;
static volatile HDErrorInfo got;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    hdBeginFrame(hdGetCurrentDevice());
    HDdouble p[3];
    hdGetDoublev(HD_CURRENT_POSITION, p);
    hdEndFrame(hdGetCurrentDevice());
    ticks++;
    HDErrorInfo e;
    while (HD_DEVICE_ERROR(e = hdGetError())) {
        if (hduIsSchedulerError(&e)) {
            timer++;
            got = e;
            done = 1;
            return HD_CALLBACK_DONE; /* as the SDK's examples end on a scheduler error */
        }
        other++;
    }
    return HD_CALLBACK_CONTINUE;
}

int main(int argc, char **argv)
{
    int seconds = argc > 1 ? atoi(argv[1]) : 30;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdScheduleAsynchronous(servo, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    for (int waited = 0; !done && waited < seconds * 1000; waited += 10)
        sleep_ms(10);
    hdStopScheduler();
    HDErrorInfo e = got;
    printf("ticks %d\nscheduler-errors %d\nother-errors %d\n", ticks, timer, other);
    printf("error 0x%x internal %d scheduler-error %d\n", e.errorCode, e.internalErrorCode,
           hduIsSchedulerError(&e));
    printf("string %s\n", hdGetErrorString(e.errorCode));
    return 0;
}
