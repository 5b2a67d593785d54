/* VRPN's call order (docs/HDAPI.md, Testing): synchronous callbacks that read state without
 * a frame, and a read on the main thread outside the scheduler. Also requests to the daemon
 * while the scheduler's thread reads the socket (from the main thread and from a callback on
 * that thread), and the errors a program sees for calls it gets wrong. */
#include "hdtest.h"

static Sample in_sync;

static HDCallbackCode HDCALLBACK read_state(void *data)
{
    (void)data;
    read_sample(&in_sync);
    return HD_CALLBACK_DONE;
}

static HDerror rate_error_in_callback = 0x7fff;

static HDCallbackCode HDCALLBACK set_rate(void *data)
{
    hdSetSchedulerRate(*(HDulong *)data);
    rate_error_in_callback = hdGetError().errorCode;
    return HD_CALLBACK_DONE;
}

int main(void)
{
    HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    Sample outside;
    read_sample(&outside);
    check("read before the scheduler");
    print_sample("outside", &outside);
    hdStartScheduler();
    check("hdStartScheduler");
    for (int i = 0; i < 5; i++) {
        hdScheduleSynchronous(read_state, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
        check("hdScheduleSynchronous");
    }
    print_sample("sync", &in_sync);

    /* Each of these waits for the daemon's answer, which the scheduler's thread reads. */
    hdSetSchedulerRate(500);
    HDerror rate_error_on_main = hdGetError().errorCode;
    HDulong rate = 1000;
    hdScheduleSynchronous(set_rate, &rate, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdScheduleSynchronous(read_state, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    check("a tick after the requests");
    printf("rate %#x %#x\n", rate_error_on_main, rate_error_in_callback);

    /* Usage errors: each pushes its code, most recent first. */
    hdEndFrame(hhd);                      /* no frame begun */
    hdGetDoublev(0x7777, in_sync.gimbal); /* no such parameter */
    hdMakeCurrentDevice(42);              /* no such device */
    HDerror e1 = hdGetError().errorCode;
    HDerror e2 = hdGetError().errorCode;
    HDerror e3 = hdGetError().errorCode;
    HDerror e4 = hdGetError().errorCode;
    printf("errors %#x %#x %#x %#x\n", e1, e2, e3, e4);
    printf("string %s\n", hdGetErrorString(HD_COMM_ERROR));
    hdStopScheduler();
    hdDisableDevice(hhd);
    printf("done\n");
    return 0;
}
