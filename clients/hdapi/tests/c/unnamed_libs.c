/* Links with "-lHDU -lHD" only, as two of the SDK's example Makefiles do: it calls libm (as
 * Vibration does, without -lm) and ncurses (as CommandMotorDAC does, without -lncurses);
 * install.sh's libHDU.so names both as needed. */
#include <curses.h>
#include <math.h>
#include <stdio.h>
#include <HD/hd.h>
#include <HDU/hduError.h>

int main(int argc, char **argv)
{
    (void)argv;
    volatile double x = 0.5 * argc;
    HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
    HDErrorInfo e = hdGetError();
    if (argc > 5) {
        initscr(); /* never reached: the program only needs to link it */
        endwin();
    }
    printf("sin %.6f handle %#x error %#x\n", sin(x), hhd, e.errorCode);
    return 0;
}
