/* hdInitDevice with no daemon: HD_INVALID_HANDLE and a communication error, no crash. */
#include "hdtest.h"

int main(void)
{
    HHD hhd = hdInitDevice(HD_DEFAULT_DEVICE);
    HDErrorInfo e = hdGetError();
    printf("handle %#x error %#x then %#x\n", hhd, e.errorCode, hdGetError().errorCode);
    hdDisableDevice(hhd);
    hdStartScheduler();
    hdStopScheduler();
    return 0;
}
