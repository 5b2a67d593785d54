/* Two devices in one program, as the vendor's dual-device examples open them: by their
 * configured names ("PHANToM 1", "PHANToM 2": `[[arm]] aliases`), forces rendered on both in
 * one scheduler callback that makes each current in turn. */
#include "hdtest.h"

#define TICKS 1500

static HHD left, right;
static volatile int ticks;
static Sample last_left, last_right;

static HDCallbackCode HDCALLBACK both(void *data)
{
    (void)data;
    /* Left: a push along +x; right: along -x. */
    const HHD devices[2] = {left, right};
    const HDdouble push[2] = {0.5, -0.5};
    for (int k = 0; k < 2; k++) {
        hdMakeCurrentDevice(devices[k]);
        hdBeginFrame(devices[k]);
        read_sample(k == 0 ? &last_left : &last_right);
        HDdouble force[3] = {push[k], 0, 0};
        hdSetDoublev(HD_CURRENT_FORCE, force);
        hdEndFrame(devices[k]);
    }
    HDErrorInfo e = hdGetError();
    if (HD_DEVICE_ERROR(e)) {
        hduPrintError(stderr, &e, "frame");
        return HD_CALLBACK_DONE;
    }
    ticks++;
    return ticks < TICKS ? HD_CALLBACK_CONTINUE : HD_CALLBACK_DONE;
}

int main(void)
{
    left = hdInitDevice("PHANToM 1");
    check("hdInitDevice PHANToM 1");
    hdEnable(HD_FORCE_OUTPUT);
    right = hdInitDevice("PHANToM 2");
    check("hdInitDevice PHANToM 2");
    hdEnable(HD_FORCE_OUTPUT);
    printf("handles %u %u\n", left, right);
    hdScheduleAsynchronous(both, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    while (ticks < TICKS)
        sleep_ms(10);
    print_sample("left", &last_left);
    print_sample("right", &last_right);
    hdStopScheduler();
    hdDisableDevice(right);
    hdDisableDevice(left);
    printf("done %d\n", ticks);
    return 0;
}
