#!/usr/bin/env bash
# test_install: `cmake --install` into a temporary prefix, then the sample program
# (tests/install/sample) built against that tree twice, with find_package(shapematch) and
# with `pkg-config --cflags --libs shapematch`, and run against the installed daemon.
# Usage: test_install.sh CMAKE BUILD_DIR SAMPLE_DIR CC WORK_DIR
set -euo pipefail
cmake=$1 build=$2 sample=$3 cc=$4 work=$5
rm -rf "$work" && mkdir -p "$work"
prefix=$work/prefix daemon_pid=""
trap '[ -n "$daemon_pid" ] && kill "$daemon_pid" 2>/dev/null; true' EXIT
fail() { echo "test_install: $*" >&2; exit 1; }

"$cmake" --install "$build" --prefix "$prefix" > "$work/install.log"
libdir=$(sed -n 's/^libdir=\${prefix}\///p' "$prefix"/lib*/pkgconfig/shapematch.pc)
for f in bin/shapematch bin/shapematchd include/shapematch/sm_client.h \
         include/shapematch/sm_mesh.h include/shapematch/sm_proto.h \
         include/shapematch/sm_version.h "$libdir/libsmcore.a" "$libdir/libsmclient.a" \
         "$libdir/libsmproto.a" "$libdir/cmake/shapematch/shapematchConfig.cmake" \
         "$libdir/pkgconfig/shapematch.pc" share/man/man1/shapematch.1 \
         share/man/man8/shapematchd.8 share/bash-completion/completions/shapematch; do
  [ -f "$prefix/$f" ] || fail "not installed: $f"
done
[ -x "$prefix/bin/shapematch" ] && [ -x "$prefix/bin/shapematchd" ] || fail "programs not executable"
"$prefix/bin/shapematch" --version | grep -q '^shapematch [0-9]' || fail "installed shapematch --version"

# 1. a C-only CMake project: find_package(shapematch) with the prefix on CMAKE_PREFIX_PATH
"$cmake" -S "$sample" -B "$work/cmake-build" -DCMAKE_PREFIX_PATH="$prefix" \
  -DCMAKE_C_COMPILER="$cc" > "$work/cmake-configure.log" || { cat "$work/cmake-configure.log"; fail "find_package configure"; }
"$cmake" --build "$work/cmake-build" > "$work/cmake-build.log" 2>&1 || { cat "$work/cmake-build.log"; fail "find_package build"; }

# 2. plain cc with pkg-config (the .pc finds its prefix from its own place)
export PKG_CONFIG_PATH=$prefix/$libdir/pkgconfig
flags=$(pkg-config --cflags --libs shapematch) || fail "pkg-config shapematch"
# shellcheck disable=SC2086 # the flags are words
"$cc" -std=c11 -o "$work/sample-pc" "$sample/sample.c" $flags || fail "pkg-config build"
[ "$(pkg-config --modversion shapematch)" = "$("$prefix/bin/shapematch" --version | cut -d' ' -f2)" ] \
  || fail "shapematch.pc version differs from shapematch --version"

# 3. both samples against the installed daemon (the port it announces, --port 0). The log
# exists before the daemon starts: the background job opens it in its own process, and the
# first sed below could otherwise run first and fail (set -e), as it did in a loaded CI run.
: > "$work/daemon.log"
"$prefix/bin/shapematchd" --port 0 --data-dir "$work/data" --threads 1 2> "$work/daemon.log" &
daemon_pid=$!
port=""
for _ in $(seq 100); do
  port=$(sed -n 's/.*msg=listening port=\([0-9]*\).*/\1/p' "$work/daemon.log")
  [ -n "$port" ] && break
  kill -0 "$daemon_pid" 2>/dev/null || { cat "$work/daemon.log"; fail "daemon exited"; }
  sleep 0.1
done
[ -n "$port" ] || fail "daemon did not announce its port"
"$work/cmake-build/sample" "127.0.0.1:$port" || fail "sample (find_package) failed"
"$work/sample-pc" "127.0.0.1:$port" || fail "sample (pkg-config) failed"
kill "$daemon_pid" && wait "$daemon_pid" || fail "daemon did not exit 0 on SIGTERM"
daemon_pid=""
rm -rf "$work"
echo "test_install: ok"
