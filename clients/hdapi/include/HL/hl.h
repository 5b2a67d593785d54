/* omnid provides the OpenHaptics Device API (HD, with its utilities HDU) but not the Haptic
 * Library API (HL): see docs/HDAPI.md, What libHD is not. A program that only includes this
 * header and calls nothing of HL (the ROS Phantom Omni driver) builds with
 * -DOMNID_HL_INCLUDE_ONLY. */
#ifndef OMNID_HL_H
#define OMNID_HL_H
#ifndef OMNID_HL_INCLUDE_ONLY
#error "HL/hl.h: omnid provides HD and HDU (the OpenHaptics Device API, -lHD -lHDU) but not HL (the Haptic Library API); see docs/HDAPI.md in omnid"
#endif
#endif
