/* The JHU driver's call order (docs/HDAPI.md, Behaviours): callbacks are scheduled before
 * the scheduler starts and unscheduled after it stopped; the servo callback ends on any
 * error. Also checks priorities and hdWaitForCompletion. */
#include "hdtest.h"

#define TICKS 300

static volatile int ticks, low_ticks, order_ok = 1, stopped_on_error;
static volatile int last_seen; /* 1: high ran last, 2: low ran last */
static Sample last;

static HDCallbackCode HDCALLBACK high(void *data)
{
    HHD hhd = *(HHD *)data;
    hdMakeCurrentDevice(hhd);
    hdBeginFrame(hhd);
    read_sample(&last);
    hdEndFrame(hhd);
    if (HD_DEVICE_ERROR(hdGetError())) {
        stopped_on_error = 1;
        return HD_CALLBACK_DONE;
    }
    if (last_seen == 1)
        order_ok = 0; /* two highs without a low between: low skipped a tick */
    last_seen = 1;
    ticks++;
    return HD_CALLBACK_CONTINUE;
}

static HDCallbackCode HDCALLBACK low(void *data)
{
    (void)data;
    if (last_seen != 1)
        order_ok = 0; /* the higher priority must run first in every tick */
    last_seen = 2;
    low_ticks++;
    return HD_CALLBACK_CONTINUE;
}

static HDCallbackCode HDCALLBACK once(void *data)
{
    (*(int *)data)++;
    return HD_CALLBACK_DONE;
}

int main(void)
{
    HHD hhd = hdInitDevice("Default Device");
    check("hdInitDevice");
    HDSchedulerHandle hl = hdScheduleAsynchronous(low, NULL, HD_MIN_SCHEDULER_PRIORITY);
    HDSchedulerHandle hh = hdScheduleAsynchronous(high, &hhd, HD_MAX_SCHEDULER_PRIORITY);
    check("schedule before start");
    hdStartScheduler();
    check("hdStartScheduler");
    for (int i = 0; i < 4000 && ticks < TICKS; i++)
        sleep_ms(5);
    int calls = 0;
    HDSchedulerHandle ho = hdScheduleAsynchronous(once, &calls, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdWaitForCompletion(ho, HD_WAIT_INFINITE);
    printf("once %d\n", calls);
    printf("scheduled-while-running %d\n", hdWaitForCompletion(hh, HD_WAIT_CHECK_STATUS));
    hdStopScheduler();
    hdUnschedule(hh);
    hdUnschedule(hl);
    check("unschedule after stop");
    printf("scheduled-after-unschedule %d\n", hdWaitForCompletion(hh, HD_WAIT_CHECK_STATUS));
    print_sample("sample", &last);
    printf("ticks %d low %d order %d stopped-on-error %d\n", ticks, low_ticks, order_ok,
           stopped_on_error);
    hdDisableDevice(hhd);
    printf("done\n");
    return 0;
}
