/* The inkwell switch as a program reads it: prints `inkwell 0|1` at the start and on every
 * change of HD_CURRENT_INKWELL_SWITCH (read in a synchronous call, as the SDK's examples do),
 * and `buttons N` on every change of HD_CURRENT_BUTTONS, until it has seen the number of
 * inkwell changes asked for (argument 1) or the time runs out (argument 2, s). */
#include "hdtest.h"
#include <stdlib.h>

typedef struct {
    HDint buttons;
    HDboolean inkwell;
} State;

static HDCallbackCode HDCALLBACK copy_state(void *data)
{
    State *s = (State *)data;
    hdBeginFrame(hdGetCurrentDevice());
    hdGetIntegerv(HD_CURRENT_BUTTONS, &s->buttons);
    hdGetBooleanv(HD_CURRENT_INKWELL_SWITCH, &s->inkwell);
    hdEndFrame(hdGetCurrentDevice());
    return HD_CALLBACK_DONE;
}

int main(int argc, char **argv)
{
    int want = argc > 1 ? atoi(argv[1]) : 2;
    int seconds = argc > 2 ? atoi(argv[2]) : 20;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdStartScheduler();
    check("hdStartScheduler");
    State s = {0}, seen;
    hdScheduleSynchronous(copy_state, &s, HD_DEFAULT_SCHEDULER_PRIORITY);
    seen = s;
    printf("inkwell %d\nbuttons %d\n", s.inkwell, s.buttons);
    fflush(stdout);
    int changes = 0;
    for (long waited = 0; changes < want && waited < seconds * 1000L; waited += 2) {
        hdScheduleSynchronous(copy_state, &s, HD_DEFAULT_SCHEDULER_PRIORITY);
        if (s.inkwell != seen.inkwell) {
            printf("inkwell %d\n", s.inkwell);
            changes++;
        }
        if (s.buttons != seen.buttons)
            printf("buttons %d\n", s.buttons);
        fflush(stdout);
        seen = s;
        sleep_ms(2);
    }
    check("reads");
    hdStopScheduler();
    printf("done %d\n", changes);
    return 0;
}
