/* omnid libHD: the HL API is not provided. Programs that include this header without calling
 * HL (the ROS driver) build; calling HL is not supported (docs/HDAPI.md). */
#ifndef OMNID_HL_H
#define OMNID_HL_H
#endif
