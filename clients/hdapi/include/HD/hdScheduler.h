/* omnid libHD: the scheduler (docs/HDAPI.md, Scheduler). */
#ifndef OMNID_HD_SCHEDULER_H
#define OMNID_HD_SCHEDULER_H

#include "hdDefines.h"

HD_BEGIN_DECLS

typedef HDCallbackCode(HDCALLBACK *HDSchedulerCallback)(void *pUserData);

HDAPI void HDAPIENTRY hdStartScheduler(void);
HDAPI void HDAPIENTRY hdStopScheduler(void);
HDAPI void HDAPIENTRY hdSetSchedulerRate(HDulong nRate);
HDAPI HDSchedulerHandle HDAPIENTRY hdScheduleAsynchronous(HDSchedulerCallback pCallback,
                                                          void *pUserData, HDushort nPriority);
HDAPI void HDAPIENTRY hdScheduleSynchronous(HDSchedulerCallback pCallback, void *pUserData,
                                            HDushort nPriority);
HDAPI void HDAPIENTRY hdUnschedule(HDSchedulerHandle hHandle);
HDAPI HDboolean HDAPIENTRY hdWaitForCompletion(HDSchedulerHandle hHandle, HDWaitCode param);
HDAPI HDdouble HDAPIENTRY hdGetSchedulerTimeStamp(void);

HD_END_DECLS

#endif
