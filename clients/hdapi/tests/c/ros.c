/* The ROS driver's call order (docs/HDAPI.md, Behaviours): init, enable forces, start the
 * scheduler, calibrate on the main thread (inkwell style; start-up blocks until OK), then
 * schedule the state callback after the start. */
#include "hdtest.h"
/* The ROS driver includes HL/hl.h and calls nothing of HL: the opt-in that lets it build. */
#define OMNID_HL_INCLUDE_ONLY
#include <HL/hl.h>

#define TICKS 200

static volatile int ticks;
static Sample last;
static HDErrorInfo servo_error;

static HDCallbackCode HDCALLBACK state_callback(void *data)
{
    (void)data;
    hdBeginFrame(hdGetCurrentDevice());
    read_sample(&last);
    HDdouble force[3] = {0, 0, 0};
    hdSetDoublev(HD_CURRENT_FORCE, force);
    hdEndFrame(hdGetCurrentDevice());
    HDErrorInfo e = hdGetError();
    if (HD_DEVICE_ERROR(e)) {
        servo_error = e;
        if (hduIsSchedulerError(&e))
            return HD_CALLBACK_DONE;
    }
    ticks++;
    return HD_CALLBACK_CONTINUE;
}

int main(void)
{
    HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    printf("model %s\nvendor %s\nserial %s\ndriver %s\n", hdGetString(HD_DEVICE_MODEL_TYPE),
           hdGetString(HD_DEVICE_VENDOR), hdGetString(HD_DEVICE_SERIAL_NUMBER),
           hdGetString(HD_DEVICE_DRIVER_VERSION));
    hdEnable(HD_FORCE_OUTPUT);
    hdStartScheduler();
    check("hdStartScheduler");

    HDint styles;
    hdGetIntegerv(HD_CALIBRATION_STYLE, &styles);
    HDenum style = (styles & HD_CALIBRATION_AUTO)      ? HD_CALIBRATION_AUTO
                   : (styles & HD_CALIBRATION_INKWELL) ? HD_CALIBRATION_INKWELL
                                                       : HD_CALIBRATION_ENCODER_RESET;
    printf("calibration-style %u\n", style);
    HDenum status = hdCheckCalibration();
    printf("calibration-first %#x\n", status);
    for (int i = 0; i < 400 && hdCheckCalibration() != HD_CALIBRATION_OK; i++) {
        if (hdCheckCalibration() == HD_CALIBRATION_NEEDS_UPDATE)
            hdUpdateCalibration(style);
        else
            sleep_ms(10); /* "Please place the device into the inkwell" */
    }
    printf("calibration-final %#x\n", hdCheckCalibration());
    check("calibration");

    HDdouble rate, max_force, workspace[6];
    hdGetDoublev(HD_UPDATE_RATE, &rate);
    hdGetDoublev(HD_NOMINAL_MAX_FORCE, &max_force);
    hdGetDoublev(HD_USABLE_WORKSPACE_DIMENSIONS, workspace);
    printf("rate %.1f max-force %.2f workspace %.1f %.1f\n", rate, max_force, workspace[0],
           workspace[3]);

    HDSchedulerHandle h = hdScheduleAsynchronous(state_callback, NULL, HD_MAX_SCHEDULER_PRIORITY);
    check("hdScheduleAsynchronous");
    for (int i = 0; i < 2000 && ticks < TICKS; i++)
        sleep_ms(5);
    hdStopScheduler();
    hdUnschedule(h);
    print_sample("sample", &last);
    printf("ticks %d servo-error %#x\n", ticks, servo_error.errorCode);
    hdDisableDevice(hhd);
    hdDisableDevice(hhd); /* idempotent */
    check("hdDisableDevice");
    printf("done\n");
    return 0;
}
