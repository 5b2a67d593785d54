// omnid libHDU: HDErrorInfo on a C++ stream (docs/HDAPI.md, libHDU).
#include <HDU/hduError.h>
#include <ios>
#include <ostream>
#include "hduErrorName.h"

std::ostream &operator<<(std::ostream &os, const HDErrorInfo &error)
{
    std::ios_base::fmtflags flags = os.flags();
    os << "HD Error: " << hduErrorName(error.errorCode) << " (0x" << std::hex << error.errorCode
       << std::dec << "): " << hdGetErrorString(error.errorCode) << "\nHHD: " << error.hHD
       << ", internal error code: " << error.internalErrorCode;
    os.flags(flags);
    return os;
}
