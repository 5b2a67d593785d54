/* CHAI3D's call order (docs/HDAPI.md, Behaviours): the device is opened from an ELF
 * constructor, a servo callback at the highest priority runs every tick, and setting a force
 * blocks until that callback has taken it. Prints a sample, then holds a force until killed. */
#include "hdtest.h"
#include <pthread.h>
#include <string.h>

static HHD device = HD_INVALID_HANDLE;
static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t taken = PTHREAD_COND_INITIALIZER;
static double wanted[3];
static int pending;
static Sample latest;

static HDCallbackCode HDCALLBACK servo(void *data)
{
    (void)data;
    hdBeginFrame(device);
    Sample s;
    read_sample(&s);
    pthread_mutex_lock(&lock);
    latest = s;
    hdSetDoublev(HD_CURRENT_FORCE, wanted);
    if (pending) {
        pending = 0;
        pthread_cond_broadcast(&taken);
    }
    pthread_mutex_unlock(&lock);
    hdEndFrame(device);
    return HD_CALLBACK_CONTINUE;
}

__attribute__((constructor)) static void open_device(void)
{
    device = hdInitDevice(HD_DEFAULT_DEVICE);
    if (device == HD_INVALID_HANDLE)
        return;
    hdEnable(HD_FORCE_OUTPUT);
    hdScheduleAsynchronous(servo, NULL, HD_MAX_SCHEDULER_PRIORITY);
    hdStartScheduler();
}

/* CHAI's set-force: hand the force to the servo callback and wait until it took it. */
static void set_force(double fx, double fy, double fz)
{
    pthread_mutex_lock(&lock);
    wanted[0] = fx, wanted[1] = fy, wanted[2] = fz;
    pending = 1;
    while (pending)
        pthread_cond_wait(&taken, &lock);
    pthread_mutex_unlock(&lock);
}

int main(int argc, char **argv)
{
    if (device == HD_INVALID_HANDLE) {
        check("hdInitDevice from the constructor");
        return 1;
    }
    check("constructor");
    set_force(0, 0, 0);
    pthread_mutex_lock(&lock);
    Sample s = latest;
    pthread_mutex_unlock(&lock);
    print_sample("sample", &s);
    double f = argc > 1 ? atof(argv[1]) : 0.5;
    set_force(f, 0, 0);
    printf("force-set %.6f 0 0\n", f);
    fflush(stdout);
    for (;;)
        sleep_ms(1000); /* killed by the test */
}
