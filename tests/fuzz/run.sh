#!/usr/bin/env bash
# tests/fuzz/run.sh SECONDS [HARNESS...]: builds the libFuzzer harnesses of tests/fuzz
# (clang, -fsanitize=fuzzer,address,undefined, in build-fuzz/ or $SM_FUZZ_BUILD) and runs
# each (default: all) for SECONDS, one at a time, single process.
#
# Corpus of a harness h: build-fuzz/corpus/h (kept between runs; new inputs go there), read
# together with the generated seeds (fuzz_seeds; for draco_mesh small meshes in every Draco
# coder) and tests/fuzz/regress/h (committed crashers). SM_FUZZ_SHARED_SEEDS=1 adds, for
# draco_mesh, the Draco files of ../shared/data under 64 KB (used in place, never copied
# into the repository): 5,000-vertex meshes that cost about 13 ms an iteration under ASan
# against about 50 us for the generated seeds, for the same decoders (Draco itself is not
# instrumented, and our passes have no size-dependent branch), so they are off by default.
# Dictionary: tests/fuzz/sm_fuzz.dict.
# A crash, leak, sanitizer report, timeout (> 10 s an input) or OOM (> 2 GB) leaves its
# input in build-fuzz/artifacts/h/ and makes the script exit 1 after the other harnesses
# ran; fix the bug and copy the input to tests/fuzz/regress/h/ (tests/fuzz/README.md).
# Prints "fuzz <h>: <execs> execs in <s> s (<n>/s), <cov> edges, <result>" per harness and
# writes the same lines to build-fuzz/summary.txt.
# Exit: 0 clean, 1 something found, 2 usage or build error, 77 no clang/libFuzzer here
# (deploy/install-deps.sh installs them).
set -uo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
all=(proto_frame proto_decode draco_mesh meshio basis_io srv_conn)
secs="${1:-}"
if ! [[ "$secs" =~ ^[0-9]+$ ]] || [ "$secs" -lt 1 ]; then
  echo "usage: $0 SECONDS [HARNESS...]   (harnesses: ${all[*]})" >&2
  exit 2
fi
shift
harnesses=("$@")
[ ${#harnesses[@]} -eq 0 ] && harnesses=("${all[@]}")
build="${SM_FUZZ_BUILD:-$root/build-fuzz}"
jobs="${SM_FUZZ_JOBS:-$(nproc)}"

# clang alone is not enough: libFuzzer's runtime is a separate Debian package.
cc="${SM_FUZZ_CC:-clang}"
cxx="${SM_FUZZ_CXX:-clang++}"
probe="$(mktemp -d)"
trap 'rm -rf "$probe"' EXIT
echo 'int LLVMFuzzerTestOneInput(const char *d, unsigned long n) { (void)d; return (int)n * 0; }' > "$probe/p.c"
if ! command -v "$cc" >/dev/null || ! "$cc" -fsanitize=fuzzer,address,undefined "$probe/p.c" -o "$probe/p" 2>"$probe/err"; then
  echo "fuzz: SKIPPED: '$cc' cannot build a libFuzzer binary on this machine:" >&2
  sed 's/^/  /' "$probe/err" >&2
  echo "fuzz: deploy/install-deps.sh installs clang and libclang-rt-dev" >&2
  exit 77
fi

shared_seeds="${SM_FUZZ_SHARED_SEEDS:-0}"
max_len() {
  case "$1" in
    draco_mesh) if [ "$shared_seeds" = 1 ]; then echo 65536; else echo 4096; fi ;;
    proto_frame|meshio|srv_conn) echo 16384 ;;
    *) echo 4096 ;;
  esac
}

echo "fuzz: building in $build" >&2
if ! CC="$cc" CXX="$cxx" cmake -S "$root" -B "$build" -DCMAKE_BUILD_TYPE=RelWithDebInfo \
     -DSM_ASAN=ON -DSM_FUZZ_ENGINE=libfuzzer >"$build.cmake.log" 2>&1; then
  cat "$build.cmake.log" >&2
  exit 2
fi
rm -f "$build.cmake.log"
cmake --build "$build" -j"$jobs" --target fuzz_all >/dev/null || exit 2
bin="$build/tests/fuzz"
rm -rf "$build/seeds"
"$bin/fuzz_seeds" "$build/seeds" || exit 2

# Small Draco files of the shared data set, linked (not copied) as extra seeds.
shared="$root/../shared/data"
mkdir -p "$build/shared-seeds/draco_mesh"
rm -f "$build/shared-seeds/draco_mesh/"*.drc
if [ "$shared_seeds" = 1 ] && [ -d "$shared" ]; then
  find "$shared" -name '*.drc' -size -64k -print0 2>/dev/null |
    while IFS= read -r -d '' f; do ln -sf "$f" "$build/shared-seeds/draco_mesh/$(basename "$f")"; done
fi

export ASAN_OPTIONS="${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=1:allocator_may_return_null=1}"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}"
status=0
: >"$build/summary.txt"
for h in "${harnesses[@]}"; do
  if [ ! -x "$bin/fuzz_$h" ]; then
    echo "fuzz: unknown harness $h (harnesses: ${all[*]})" >&2
    exit 2
  fi
  corpus="$build/corpus/$h"
  art="$build/artifacts/$h"
  mkdir -p "$corpus" "$art" "$build/shared-seeds/$h"
  log="$build/fuzz-$h.log"
  "$bin/fuzz_$h" "$corpus" "$build/seeds/$h" "$here/regress/$h" "$build/shared-seeds/$h" \
    -dict="$here/sm_fuzz.dict" -max_total_time="$secs" -max_len="$(max_len "$h")" \
    -timeout=10 -rss_limit_mb=2048 -artifact_prefix="$art/" -print_final_stats=1 \
    >"$log" 2>&1
  rc=$?
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
  secs_run=$(sed -n 's/^Done [0-9]* runs in \([0-9]*\) second.*/\1/p' "$log" | tail -1)
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
  if [ "$rc" -eq 0 ]; then result="clean"; else result="FAILED (exit $rc, see $log, inputs in $art)"; status=1; fi
  line="fuzz $h: ${execs:-?} execs in ${secs_run:-?} s (${rate:-?}/s), ${cov:-?} edges, $result"
  echo "$line" | tee -a "$build/summary.txt"
  if [ "$rc" -ne 0 ]; then grep -m1 -A12 -E '^==[0-9]+==ERROR|fuzz invariant failed|runtime error|SUMMARY' "$log" >&2; fi
done
exit $status
