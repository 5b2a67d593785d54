#!/bin/sh
# Install omnid's libHD: the library as libHD.so.3.4.0 with the links programs look for
# (libHD.so.3.4, its SONAME; libHD.so.3.0, the 3.0 SDK's; libHD.so, what dlopen users ask
# for), the utility library libHDU.a (built here from hdu/ with ${CXX:-c++}) and the
# headers (HD/, HDU/, HL/). Programs link with -lHDU -lHD (the SDK examples' Makefiles:
# -lHDU -lHD -lrt -lncurses). docs/HDAPI.md, Build and install, and libHDU.
#
#   clients/hdapi/install.sh [--lib PATH/libomnid_hd.so] PREFIX
#
# Without --lib it builds the library (cargo build --locked --release -p omnid-hd, in
# target/hd-install) first.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
lib=
if [ "${1:-}" = "--lib" ]; then
  lib=$2
  shift 2
fi
if [ $# -ne 1 ]; then
  echo "usage: $0 [--lib PATH/libomnid_hd.so] PREFIX   (e.g. /usr/local or \$HOME/.local)" >&2
  exit 2
fi
prefix=$1
if [ -z "$lib" ]; then
  # A target directory of its own: a `cargo install` or `cargo test` running in the clone
  # holds the shared one's lock for minutes.
  target=${CARGO_TARGET_DIR:-$here/../../target/hd-install}
  (cd "$here/../.." && cargo build --locked --release -p omnid-hd --target-dir "$target")
  lib=$target/release/libomnid_hd.so
fi
[ -f "$lib" ] || { echo "$0: no library at $lib" >&2; exit 1; }
mkdir -p "$prefix/lib" "$prefix/include"
cp "$lib" "$prefix/lib/libHD.so.3.4.0.tmp"
mv -f "$prefix/lib/libHD.so.3.4.0.tmp" "$prefix/lib/libHD.so.3.4.0"
for name in libHD.so.3.4 libHD.so.3.0 libHD.so; do
  ln -sfn libHD.so.3.4.0 "$prefix/lib/$name"
done
sh "$here/hdu/build.sh" "$prefix/lib/libHDU.a"
# -lHDU finds libHDU.so before libHDU.a: a GNU ld script (as libc.so is one) that links the
# archive and, only where a program uses them, the libraries the SDK's examples rely on
# without naming them all (Vibration calls libm without -lm, CommandMotorDAC ncurses without
# -lncurses). ncurses is named only where it links, so a machine without it still links.
needed=-lm
if printf 'int main(void){return 0;}\n' | ${CC:-cc} -x c - -lncurses -o /dev/null 2>/dev/null; then
  needed="$needed -lncurses"
fi
printf '/* GNU ld script: omnid'"'"'s libHDU (install.sh) */\nINPUT ( %s AS_NEEDED ( %s ) )\n' \
  "$(cd "$prefix/lib" && pwd)/libHDU.a" "$needed" > "$prefix/lib/libHDU.so.tmp"
mv -f "$prefix/lib/libHDU.so.tmp" "$prefix/lib/libHDU.so"
cp -R "$here/include/HD" "$here/include/HDU" "$here/include/HL" "$prefix/include/"
echo "libHD and libHDU (omnid) installed in $prefix/lib, headers in $prefix/include"
