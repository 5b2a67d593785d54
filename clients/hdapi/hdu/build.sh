#!/bin/sh
# Build libHDU.a (docs/HDAPI.md, libHDU) from the .cpp files beside this script:
#
#   clients/hdapi/hdu/build.sh OUT/libHDU.a
#
# C++ compiled (${CXX:-c++}), position-independent (so it links into shared libraries too),
# without exceptions and without errno from math functions: the C functions (hduVector.cpp,
# hduError.cpp) then need nothing of the C++ runtime nor libm (sqrt is an instruction), so C
# programs link them with a C compiler and the SDK's "-lHDU -lHD -lrt -lncurses".
set -eu
here=$(cd "$(dirname "$0")" && pwd)
[ $# -eq 1 ] || { echo "usage: $0 OUT/libHDU.a" >&2; exit 2; }
out=$1
objs=$(mktemp -d)
trap 'rm -rf "$objs"' EXIT
for src in "$here"/*.cpp; do
  ${CXX:-c++} -std=c++11 -O2 -fPIC -fno-exceptions -fno-math-errno -Wall -Wextra -Werror \
    -I "$here/../include" -I "$here" -c "$src" -o "$objs/$(basename "$src" .cpp).o"
done
mkdir -p "$(dirname "$out")"
rm -f "$out.tmp"
ar rcs "$out.tmp" "$objs"/*.o
mv -f "$out.tmp" "$out"
