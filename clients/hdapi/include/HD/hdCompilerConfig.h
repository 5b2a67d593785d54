/* omnid libHD: compiler settings the HD headers need (written for omnid, docs/HDAPI.md). */
#ifndef OMNID_HD_COMPILER_CONFIG_H
#define OMNID_HD_COMPILER_CONFIG_H

#if defined(__cplusplus)
#define HD_EXTERN_C extern "C"
#define HD_BEGIN_DECLS extern "C" {
#define HD_END_DECLS }
#else
#define HD_EXTERN_C
#define HD_BEGIN_DECLS
#define HD_END_DECLS
#endif

#endif
