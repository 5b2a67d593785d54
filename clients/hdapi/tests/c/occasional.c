/* A program whose frames are occasional and push nothing, as the SDK's Calibration example
 * commits one frame a second: the arm must be left alone between them (argument: ms between
 * frames). */
#include "hdtest.h"
#include <stdlib.h>

int main(int argc, char **argv)
{
    int every_ms = argc > 1 ? atoi(argv[1]) : 300;
    hdInitDevice(HD_DEFAULT_DEVICE);
    check("hdInitDevice");
    hdEnable(HD_FORCE_OUTPUT);
    hdStartScheduler();
    check("hdStartScheduler");
    int frames = 0;
    for (int elapsed = 0; elapsed < 2000; elapsed += every_ms) {
        hdBeginFrame(hdGetCurrentDevice());
        HDdouble p[3];
        hdGetDoublev(HD_CURRENT_POSITION, p);
        hdEndFrame(hdGetCurrentDevice());
        check("frame");
        frames++;
        sleep_ms(every_ms);
    }
    hdStopScheduler();
    printf("frames %d\n", frames);
    return 0;
}
