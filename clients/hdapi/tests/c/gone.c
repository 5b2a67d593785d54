/* The daemon stops under a running program: its servo callback sees HD_COMM_ERROR and ends
 * (as the ROS driver's does on a scheduler error), and a synchronous call still returns. */
#include "hdtest.h"

static volatile int ticks;
static volatile HDerror servo_error;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    hdBeginFrame(hdGetCurrentDevice());
    HDdouble force[3] = {0, 0, 0};
    hdSetDoublev(HD_CURRENT_FORCE, force);
    hdEndFrame(hdGetCurrentDevice());
    HDErrorInfo e = hdGetError();
    if (HD_DEVICE_ERROR(e) && hduIsSchedulerError(&e)) {
        servo_error = e.errorCode;
        return HD_CALLBACK_DONE;
    }
    ticks++;
    return HD_CALLBACK_CONTINUE;
}

static HDCallbackCode HDCALLBACK nothing(void *data)
{
    (void)data;
    return HD_CALLBACK_DONE;
}

int main(void)
{
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdStartScheduler();
    HDSchedulerHandle h = hdScheduleAsynchronous(servo, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    while (ticks < 100)
        sleep_ms(5);
    printf("running\n");
    fflush(stdout);
    hdWaitForCompletion(h, HD_WAIT_INFINITE); /* until the callback ends on the error */
    hdScheduleSynchronous(nothing, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    printf("servo-error %#x\n", servo_error);
    hdStopScheduler();
    return 0;
}
