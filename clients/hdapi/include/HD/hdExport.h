/* omnid libHD: export macros. On x86-64 Linux every entry point is a plain SysV C function
 * (docs/HDAPI.md, Types and ABI), so the calling-convention macro is empty. */
#ifndef OMNID_HD_EXPORT_H
#define OMNID_HD_EXPORT_H

#define HDAPI
#define HDAPIENTRY
#define HDCALLBACK

#endif
