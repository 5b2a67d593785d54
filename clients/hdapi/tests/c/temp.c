/* What the daemon knows, answered: HD_MOTOR_TEMPERATURE from the thermal model while a force
 * is pushed, and unsupported parameters read or written every tick refused once each, not
 * every tick (as the SDK's CommandMotorDAC writes DAC values every tick). */
#include "hdtest.h"

static volatile int ticks, invalid_enum, other_errors, limit_errors, last_other;
static HDdouble temp_first[3] = {-1, -1, -1}, temp_last[3];

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    hdBeginFrame(hdGetCurrentDevice());
    HDdouble force[3] = {0.0, 0.6, 0.0};
    hdSetDoublev(HD_CURRENT_FORCE, force);
    HDdouble t[3], v[3] = {0, 0, 0};
    hdGetDoublev(HD_MOTOR_TEMPERATURE, t);
    hdGetDoublev(HD_SOFTWARE_VELOCITY_LIMIT, v);
    HDlong dac[6] = {0, 0, 0, 0, 0, 0};
    hdGetLongv(HD_CURRENT_MOTOR_DAC_VALUES, dac);
    hdSetLongv(HD_CURRENT_MOTOR_DAC_VALUES, dac);
    hdEndFrame(hdGetCurrentDevice());
    HDErrorInfo e;
    while (HD_DEVICE_ERROR(e = hdGetError())) {
        if (e.errorCode == HD_INVALID_ENUM)
            invalid_enum++;
        else if (e.errorCode >= HD_WARM_MOTORS && e.errorCode <= HD_EXCEEDED_MAX_VELOCITY)
            limit_errors++; /* the daemon's safety layer acting: raised once per episode */
        else {
            other_errors++;
            last_other = e.errorCode;
        }
    }
    if (temp_first[0] < 0)
        for (int i = 0; i < 3; i++)
            temp_first[i] = t[i];
    for (int i = 0; i < 3; i++)
        temp_last[i] = t[i];
    ticks++;
    return HD_CALLBACK_CONTINUE;
}

int main(void)
{
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdEnable(HD_FORCE_OUTPUT);
    hdScheduleAsynchronous(servo, NULL, HD_DEFAULT_SCHEDULER_PRIORITY);
    hdStartScheduler();
    check("hdStartScheduler");
    sleep_ms(1500);
    hdStopScheduler();
    printf("ticks %d\ninvalid-enum %d\nlimit-errors %d\nother-errors %d\nlast-other 0x%x\n", ticks,
           invalid_enum, limit_errors, other_errors, last_other);
    printf("temp-first %.6f %.6f %.6f\ntemp-last %.6f %.6f %.6f\n", temp_first[0], temp_first[1],
           temp_first[2], temp_last[0], temp_last[1], temp_last[2]);
    return 0;
}
