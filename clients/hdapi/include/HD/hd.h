/* omnid libHD: the HD API over `omnid serve` (docs/HDAPI.md). */
#ifndef OMNID_HD_H
#define OMNID_HD_H

#include <stddef.h>

#include "hdCompilerConfig.h"
#include "hdExport.h"
#include "hdDefines.h"
#include "hdDevice.h"
#include "hdScheduler.h"

#endif
