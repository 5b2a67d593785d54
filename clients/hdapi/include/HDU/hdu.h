/* omnid libHDU: every HDU header at once (docs/HDAPI.md, libHDU). C and C++; in C only the
 * C parts (hduError, the hduVec* functions, hduMath) are there. Link -lHDU -lHD. */
#ifndef OMNID_HDU_H
#define OMNID_HDU_H

#include <HD/hd.h>
#include <HDU/hduError.h>
#include <HDU/hduMath.h>
#include <HDU/hduVector.h>
#include <HDU/hduMatrix.h>
#include <HDU/hduQuaternion.h>
#include <HDU/hduLineSegment.h>

#endif
