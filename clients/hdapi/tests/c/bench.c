/* The benchmark's HD program (benches/hdapi.rs): a servo callback that renders a weak spring
 * around the start pose every frame for the given seconds, then stops. */
#include "hdtest.h"

static volatile long frames;
static double anchor[3];
static volatile int anchored;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    HHD hhd = hdGetCurrentDevice();
    hdBeginFrame(hhd);
    double p[3], f[3];
    hdGetDoublev(HD_CURRENT_POSITION, p);
    if (!anchored) {
        anchor[0] = p[0], anchor[1] = p[1], anchor[2] = p[2];
        anchored = 1;
    }
    for (int i = 0; i < 3; i++)
        f[i] = 0.02 * (anchor[i] - p[i]); /* N/mm */
    hdSetDoublev(HD_CURRENT_FORCE, f);
    hdEndFrame(hhd);
    frames++;
    return HD_CALLBACK_CONTINUE;
}

int main(int argc, char **argv)
{
    double seconds = argc > 1 ? atof(argv[1]) : 10.0;
    HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdEnable(HD_FORCE_OUTPUT);
    HDSchedulerHandle h = hdScheduleAsynchronous(servo, NULL, HD_MAX_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    printf("started\n");
    fflush(stdout);
    sleep_ms((long)(seconds * 1000.0));
    hdStopScheduler();
    hdUnschedule(h);
    hdDisableDevice(hhd);
    printf("frames %ld\n", frames);
    return 0;
}
