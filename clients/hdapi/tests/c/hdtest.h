/* Helpers shared by the call-order replays (tests/suite/hdapi.rs runs them against omnid serve). */
#ifndef HDTEST_H
#define HDTEST_H

#include <HD/hd.h>
#include <HDU/hduError.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static inline void check(const char *what)
{
    HDErrorInfo e = hdGetError();
    if (HD_DEVICE_ERROR(e)) {
        hduPrintError(stderr, &e, what);
        printf("FAILED %s 0x%x\n", what, e.errorCode);
        exit(1);
    }
}

static inline void sleep_ms(long ms)
{
    struct timespec t = {ms / 1000, (ms % 1000) * 1000000L};
    nanosleep(&t, NULL);
}

/* One sample as the program read it, printed as one line for the test to check. */
typedef struct {
    HDdouble position[3], velocity[3], transform[16], joints[3], gimbal[3];
    HDint buttons;
    HDboolean inkwell;
} Sample;

static inline void read_sample(Sample *s)
{
    hdGetDoublev(HD_CURRENT_POSITION, s->position);
    hdGetDoublev(HD_CURRENT_VELOCITY, s->velocity);
    hdGetDoublev(HD_CURRENT_TRANSFORM, s->transform);
    hdGetDoublev(HD_CURRENT_JOINT_ANGLES, s->joints);
    hdGetDoublev(HD_CURRENT_GIMBAL_ANGLES, s->gimbal);
    hdGetIntegerv(HD_CURRENT_BUTTONS, &s->buttons);
    hdGetBooleanv(HD_CURRENT_INKWELL_SWITCH, &s->inkwell);
}

static inline void print_sample(const char *tag, const Sample *s)
{
    printf("%s pos %.9f %.9f %.9f q %.12f %.12f %.12f tr %.9f %.9f %.9f g %.9f %.9f %.9f "
           "buttons %d\n",
           tag, s->position[0], s->position[1], s->position[2], s->joints[0], s->joints[1],
           s->joints[2], s->transform[12], s->transform[13], s->transform[14], s->gimbal[0],
           s->gimbal[1], s->gimbal[2], s->buttons);
    fflush(stdout);
}

#endif
