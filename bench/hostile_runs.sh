#!/usr/bin/env bash
# bench/hostile_runs.sh [-n RUNS] [-b BUILD] [DAEMON...] [-- bench_hostile args]: runs
# bench_hostile RUNS times (default 5) per daemon binary (default: BUILD's shapematchd),
# daemons alternating run by run so that the machine's other load falls on each alike,
# and prints, per daemon, every run's good-client figures (unloaded -> loaded) and their
# medians: PING p50/p99, DISTANCE p50/p99 and the loaded/unloaded DISTANCE ratios, peak RSS,
# and the CPU seconds of the daemon's loop thread during the loaded phase.
# Each run is one bench_hostile process: its own daemon, unloaded phase, then loaded phase.
# Raw outputs: $TMPDIR/hostile_runs.*/ (printed at the end).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
runs=5
build="$here/../build"
while getopts "n:b:" o; do
  case "$o" in
    n) runs="$OPTARG" ;;
    b) build="$OPTARG" ;;
    *) echo "usage: $0 [-n RUNS] [-b BUILD] [DAEMON...] [-- bench_hostile args]" >&2; exit 2 ;;
  esac
done
shift $((OPTIND - 1))
daemons=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do daemons+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#daemons[@]} -eq 0 ] && daemons=("$build/server/shapematchd")
bench="$build/bench/bench_hostile"
[ -x "$bench" ] || { echo "no $bench (build the bench target)" >&2; exit 2; }
out="$(mktemp -d "${TMPDIR:-/tmp}/hostile_runs.XXXXXX")"

for r in $(seq "$runs"); do
  for i in "${!daemons[@]}"; do
    f="$out/d$i.r$r.txt"
    "$bench" --daemon "${daemons[$i]}" "$@" >"$f" 2>&1 || { echo "run failed: $f" >&2; cat "$f" >&2; exit 1; }
    echo "daemon $i run $r: $(grep -m1 '^Targets' "$f")" >&2
  done
done

# Table rows: | phase | PINGs | PING p50 | PING p99 | DISTs | DIST p50 | DIST p99 | errors | admitted | RSS |
for i in "${!daemons[@]}"; do
  echo "## ${daemons[$i]} ($runs runs)"
  echo
  echo "| run | PING p50 ms | PING p99 ms | DIST p50 ms | DIST p99 ms | p50 ratio | p99 ratio | errors | loaded RSS MiB | loop CPU s (loaded) |"
  echo "|---|---|---|---|---|---:|---:|---|---:|---:|"
  for r in $(seq "$runs"); do
    awk -F'|' -v run="$r" '
      function t(x) { gsub(/ /, "", x); return x }
      $2 ~ /unloaded/ { up50 = t($4); up99 = t($5); ud50 = t($7); ud99 = t($8); ue = t($9) }
      $2 ~ / loaded/  { lp50 = t($4); lp99 = t($5); ld50 = t($7); ld99 = t($8); le = t($9); rss = t($11) }
      /^Daemon CPU:/ { s = $0; sub(/.*loaded phase [0-9.]+ s \(loop thread /, "", s); loop = s + 0 }
      END { printf "| %d | %s -> %s | %s -> %s | %s -> %s | %s -> %s | %.2f | %.2f | %s/%s | %s | %.2f |\n",
                   run, up50, lp50, up99, lp99, ud50, ld50, ud99, ld99, ld50 / ud50, ld99 / ud99,
                   ue, le, rss, loop }' "$out/d$i.r$r.txt"
  done | tee "$out/d$i.rows"
  # medians of the loaded figures and of the ratios
  awk -F'|' '
    function med(a, n,   i, j, x) { for (i = 2; i <= n; i++) { x = a[i]; for (j = i - 1; j >= 1 && a[j] > x; j--) a[j + 1] = a[j]; a[j + 1] = x }
                                    return n % 2 ? a[(n + 1) / 2] : (a[n / 2] + a[n / 2 + 1]) / 2 }
    function lo(s,   p) { split(s, p, "->"); return p[2] + 0 }
    function un(s,   p) { split(s, p, "->"); return p[1] + 0 }
    { n++; a1[n] = un($3); b1[n] = lo($3); a2[n] = un($4); b2[n] = lo($4); a3[n] = un($5); b3[n] = lo($5)
      a4[n] = un($6); b4[n] = lo($6); r1[n] = $7 + 0; r2[n] = $8 + 0; m[n] = $10 + 0; l[n] = $11 + 0 }
    END { printf "| median | %.3f -> %.3f | %.3f -> %.3f | %.2f -> %.2f | %.2f -> %.2f | %.2f | %.2f | | %.0f | %.2f |\n",
                 med(a1, n), med(b1, n), med(a2, n), med(b2, n), med(a3, n), med(b3, n), med(a4, n), med(b4, n),
                 med(r1, n), med(r2, n), med(m, n), med(l, n) }' "$out/d$i.rows"
  echo
done
echo "raw outputs: $out"
