/* A servo callback slower than a frame a millisecond (argument: ms per frame), pushing a small
 * force for about two seconds: between its frames the force must hold (the amplifiers must not
 * cycle), and frames further apart than the force can be held raise HD_TIMER_ERROR. */
#include "hdtest.h"
#include <stdlib.h>

static int frame_ms;
static volatile int frames, timer_errors;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    hdBeginFrame(hdGetCurrentDevice());
    HDdouble force[3] = {0.3, 0, 0};
    hdSetDoublev(HD_CURRENT_FORCE, force);
    hdEndFrame(hdGetCurrentDevice());
    HDErrorInfo e;
    while (HD_DEVICE_ERROR(e = hdGetError()))
        if (e.errorCode == HD_TIMER_ERROR)
            timer_errors++;
    frames++;
    sleep_ms(frame_ms);
    return HD_CALLBACK_CONTINUE;
}

int main(int argc, char **argv)
{
    frame_ms = argc > 1 ? atoi(argv[1]) : 40;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdEnable(HD_FORCE_OUTPUT);
    hdScheduleAsynchronous(servo, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    sleep_ms(2000);
    hdStopScheduler();
    printf("frames %d\ntimer-errors %d\n", frames, timer_errors);
    return 0;
}
