/* The SDK's QueryDevice way of waiting for a button: the main thread copies the device's state
 * with a synchronous call again and again, and stops once button 1 is down. Prints the
 * buttons it saw and how many polls it took; exits 1 if no button comes within the time given
 * (argument: seconds, default 20). */
#include "hdtest.h"
#include <stdlib.h>

typedef struct {
    HDint buttons;
    HDboolean inkwell;
    HDErrorInfo error;
} DeviceData;

static HDCallbackCode HDCALLBACK copy_state(void *data)
{
    DeviceData *d = (DeviceData *)data;
    hdBeginFrame(hdGetCurrentDevice());
    hdGetIntegerv(HD_CURRENT_BUTTONS, &d->buttons);
    hdGetBooleanv(HD_CURRENT_INKWELL_SWITCH, &d->inkwell);
    hdEndFrame(hdGetCurrentDevice());
    d->error = hdGetError();
    return HD_CALLBACK_DONE;
}

int main(int argc, char **argv)
{
    int seconds = argc > 1 ? atoi(argv[1]) : 20;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdStartScheduler();
    check("hdStartScheduler");
    DeviceData d = {0};
    long polls = 0;
    for (long waited = 0; waited < seconds * 1000L; waited += 5) {
        hdScheduleSynchronous(copy_state, &d, HD_DEFAULT_SCHEDULER_PRIORITY);
        polls++;
        if (HD_DEVICE_ERROR(d.error) && hduIsSchedulerError(&d.error)) {
            printf("scheduler-error 0x%x\n", d.error.errorCode);
            return 1;
        }
        if (d.buttons & HD_DEVICE_BUTTON_1) {
            printf("pressed buttons %d inkwell %d polls %ld\n", d.buttons, d.inkwell, polls);
            hdStopScheduler();
            hdDisableDevice(hdGetCurrentDevice());
            return 0;
        }
        sleep_ms(5);
    }
    printf("timeout buttons %d polls %ld\n", d.buttons, polls);
    return 1;
}
