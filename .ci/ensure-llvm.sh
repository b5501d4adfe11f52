#!/bin/sh
# Mitsuba's llvm_* variants need a shared LLVM library >= 16 (docs/rendering.md: Debian 12's
# LLVM 15 aborts). Install libllvm19 when root; otherwise say what to install.
set -e
have_llvm() {
    for v in 25 24 23 22 21 20 19 18 17 16; do
        for f in /usr/lib/*/libLLVM-$v.so* /usr/lib/*/libLLVM.so.$v* /usr/lib/llvm-$v/lib/libLLVM*.so*; do
            [ -e "$f" ] && return 0
        done
    done
    [ -n "$DRJIT_LIBLLVM_PATH" ] && [ -e "$DRJIT_LIBLLVM_PATH" ] && return 0
    return 1
}
if have_llvm; then exit 0; fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing libllvm19 (needed by Mitsuba's llvm variants)"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19
    have_llvm && exit 0
fi
echo "scopetwin needs a shared LLVM library >= 16 for Mitsuba: run 'sudo apt-get install -y libllvm19'" \
     "(or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version 16 or newer)" >&2
exit 1
