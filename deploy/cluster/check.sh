#!/usr/bin/env bash
# deploy/cluster/check.sh BUILD_DIR: several daemons on one shared data directory behind
# Debian's haproxy with the shipped deploy/cluster/haproxy.cfg, end to end with the real
# daemon and CLI on loopback (docs/DEPLOY.md). Three shapematchd share one data directory:
#   1. shapes PUT through the front are visible from every daemon (QUERY on each), and
#      three daemons preparing the same shapes at once compute each basis once in all
#      (the sum of their bases_computed);
#   2. a batch of a few hundred distances through the front equals the same batch asked of
#      one daemon directly, result by result;
#   3. concurrent PUTs of the same shapes and of different shapes, one client per daemon;
#   4. the daemon serving a `shapematch batch` of a few hundred distances through the front
#      SIGKILLed in the middle, while another client PUTs shapes: the batch completes (the
#      CLI connects again and resends what the kill cut) with every result equal to one
#      daemon's, and every PUT is acknowledged;
#   5. that daemon restarted on the same directory: every acknowledged shape is there on
#      every daemon, every shape file's SHA-256 is its name, no temp file is left, no
#      daemon counted a corrupt shape or basis.
# Exit 77 when haproxy is missing (deploy/install-deps.sh installs it).
set -euo pipefail
build=$(cd "${1:-build}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
command -v haproxy >/dev/null || { echo "cluster check: haproxy not installed, skipped"; exit 77; }
cli="$build/clients/shapematch"
daemon="$build/server/shapematchd"
work=$(mktemp -d)
declare -a dpid dport
hpid=
cleanup() {
  for p in "${dpid[@]}" $hpid; do kill -9 "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT
fail() { echo "cluster check: FAILED: $*" >&2; exit 1; }
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
t_start=$(date +%s)

# start_daemon I [PORT]: shapematchd number I on the shared directory ($work/data).
start_daemon() {
  local i=$1 port=${2:-0}
  : > "$work/d$i.log"
  "$daemon" --port "$port" --data-dir "$work/data" --threads 1 --default-k 30 \
    2>> "$work/d$i.log" &
  dpid[$i]=$!
  for _ in $(seq 200); do
    dport[$i]=$(sed -n 's/.*msg=listening port=\([0-9]*\).*/\1/p' "$work/d$i.log" | head -1)
    [ -n "${dport[$i]}" ] && return 0
    kill -0 "${dpid[$i]}" 2>/dev/null || break
    sleep 0.05
  done
  cat "$work/d$i.log" >&2
  fail "daemon $i did not start"
}
d() { echo "127.0.0.1:${dport[$1]}"; }
stat_of() { "$cli" stats --server "$(d "$1")" --timeout 30 | awk -v k="$2" '$1 == k {print $2}'; }
# shape files whose SHA-256 is not their name, and temp files left over
check_files() {
  local bad=0 f
  for f in "$work"/data/shapes/*.drc; do
    [ "$(sha256sum "$f" | cut -c1-64)" = "$(basename "$f" .drc)" ] || { echo "bad: $f"; bad=1; }
  done
  [ "$bad" = 0 ] || fail "a shape file does not hold the bytes of its name"
  if ls "$work"/data/shapes "$work"/data/bases | grep -q '\.tmp\.'; then
    ls -l "$work"/data/shapes "$work"/data/bases | grep '\.tmp\.' >&2
    fail "temp files left in the data directory"
  fi
}

for i in $(seq 1 25); do
  "$cli" synth blob --subdiv 3 --seed "$i" -o "$work/m$i.off" 2>/dev/null
done
for i in 1 2 3; do start_daemon "$i"; done

export SM_FRONT_BIND="127.0.0.1:$(free_port)" SM_DAEMON1=$(d 1) SM_DAEMON2=$(d 2) SM_DAEMON3=$(d 3)
front=$SM_FRONT_BIND
haproxy -c -f "$here/haproxy.cfg" >/dev/null
haproxy -db -f "$here/haproxy.cfg" > "$work/haproxy.log" 2>&1 &
hpid=$!
for _ in $(seq 100); do
  "$cli" ping --server "$front" --timeout 2 >/dev/null 2>&1 && break
  sleep 0.1
done
"$cli" ping --server "$front" --timeout 5 >/dev/null || fail "no answer through haproxy"

# 1. PUT through the front; all three daemons rank all six at once.
"$cli" put "$work"/m{1..6}.off --server "$front" --timeout 60 > "$work/put1.txt"
mapfile -t ids < <(cut -d' ' -f1 "$work/put1.txt")
[ "${#ids[@]}" = 6 ] || fail "PUT through the front: ${#ids[@]} ids"
qp=()
for i in 1 2 3; do
  "$cli" query "${ids[0]}" -k 50 --server "$(d "$i")" --timeout 120 > "$work/q$i.txt" 2>/dev/null &
  qp+=($!)
done
for p in "${qp[@]}"; do wait "$p" || fail "QUERY on a daemon failed"; done
for i in 1 2 3; do
  n=$(wc -l < "$work/q$i.txt")
  [ "$n" = 5 ] || fail "daemon $i's QUERY ranks $n shapes, expected the 5 others"
done
computed=0
for i in 1 2 3; do computed=$((computed + $(stat_of "$i" bases_computed))); done
# 6 shapes x (Laplace-Beltrami + elastic), each computed by one daemon, loaded by the others
[ "$computed" = 12 ] || fail "bases computed $computed times for 12 bases (once per daemon?)"
echo "cluster check: 6 shapes PUT through the front visible on 3 daemons; 12 bases computed once in all"

# 2. A few hundred distances through the front = the same from daemon 1 alone.
: > "$work/pairs.txt"
for r in $(seq 7); do
  for a in "${ids[@]}"; do for b in "${ids[@]}"; do
    [ "$a" != "$b" ] && echo "$a $b" >> "$work/pairs.txt"
  done; done
done
npairs=$(wc -l < "$work/pairs.txt")
dist_of() { python3 -c 'import json,sys
for l in sys.stdin:
    j = json.loads(l)
    print(j["index"], j.get("ok"), "%.9f" % j["distance"] if j.get("ok") else "-")' | sort -n; }
"$cli" batch "$work/pairs.txt" --server "$(d 1)" --timeout 120 | dist_of > "$work/ref_batch.txt"
"$cli" batch "$work/pairs.txt" --server "$front" --timeout 120 | dist_of > "$work/front_batch.txt"
[ "$(grep -c ' True ' "$work/ref_batch.txt")" = "$npairs" ] || fail "batch on daemon 1 failed items"
cmp -s "$work/ref_batch.txt" "$work/front_batch.txt" || fail "batch through the front differs from daemon 1's"
echo "cluster check: batch of $npairs distances through the front equals daemon 1's"

# 3. Concurrent PUTs: every daemon stores shapes 7-12 at once, plus one of its own.
pp=()
for i in 1 2 3; do
  "$cli" put "$work"/m{7..12}.off "$work/m$((12 + i)).off" --server "$(d "$i")" --timeout 60 \
    > "$work/put3_$i.txt" &
  pp+=($!)
done
for p in "${pp[@]}"; do wait "$p" || fail "a concurrent PUT failed"; done
for i in 2 3; do
  diff <(head -6 "$work/put3_1.txt") <(head -6 "$work/put3_$i.txt") >/dev/null ||
    fail "concurrent PUTs of the same shapes gave different ids"
done
check_files
nshapes=$(ls "$work"/data/shapes/*.drc | wc -l)
[ "$nshapes" = 15 ] || fail "$nshapes shape files after the concurrent PUTs, expected 15"
echo "cluster check: concurrent PUTs of the same and different shapes from 3 daemons: 15 files, all intact"

# 4. The batch of step 2 again through the front, and one client PUTting 10 new shapes one
# by one; once the batch is under way, the daemon serving it is SIGKILLed. The CLI connects
# again by itself (HAProxy sends the new connection to a live daemon) and resends only the
# requests the kill cut: the batch completes with every result equal to daemon 1's (step
# 2's reference), and every PUT is acknowledged, each by one CLI run.
requests_of() { stat_of "$1" requests 2>/dev/null || echo 0; }
"$cli" batch "$work/pairs.txt" --server "$front" --timeout 120 --inflight 8 \
  > "$work/kill_batch.json" 2> "$work/kill_batch.err" &
bpid=$!
putter() { # PUT shapes 16-25 one by one through the front
  local i
  for i in $(seq 16 25); do
    "$cli" put "$work/m$i.off" --server "$front" --timeout 60 >> "$work/put4.txt" 2>>"$work/put4.err" ||
      echo "m$i.off" >> "$work/put4.failed"
  done
}
putter &
ppid=$!
for _ in $(seq 300); do # until a fifth of the batch is answered
  [ "$(wc -l < "$work/kill_batch.json")" -ge $((npairs / 5)) ] && break
  kill -0 "$bpid" 2>/dev/null || break
  sleep 0.05
done
kill -0 "$bpid" 2>/dev/null || fail "the batch ended before the kill: $(cat "$work/kill_batch.err")"
# the daemon serving the batch: the one holding the most requests in flight (the batch
# pipelines 8 on its one connection; a PUT has 1), summed over 5 looks; ties (all idle for a
# moment) go to the one whose request count grew most. The request count alone picked the
# PUTs' daemon once under AddressSanitizer, where the batch's distances are slow.
declare -a r0 infl
for i in 1 2 3; do r0[$i]=$(requests_of "$i"); infl[$i]=0; done
for _ in 1 2 3 4 5; do
  for i in 1 2 3; do infl[$i]=$(( infl[i] + $(stat_of "$i" inflight 2>/dev/null || echo 0) )); done
  sleep 0.1
done
victim=1 best=-1
for i in 1 2 3; do
  score=$(( 1000 * infl[i] + $(requests_of "$i") - r0[i] ))
  [ "$score" -gt "$best" ] && { best=$score; victim=$i; }
done
done_at_kill=$(wc -l < "$work/kill_batch.json")
kill -9 "${dpid[$victim]}"
wait "${dpid[$victim]}" 2>/dev/null || true
bst=0
wait "$bpid" || bst=$?
wait "$ppid"
[ "$bst" = 0 ] || { cat "$work/kill_batch.err" >&2; fail "the batch did not complete after daemon $victim was killed (exit $bst)"; }
grep -q "connection was lost and made again" "$work/kill_batch.err" ||
  fail "daemon $victim served the batch but the batch never connected again: was the right daemon killed?"
dist_of < "$work/kill_batch.json" > "$work/kill_batch.txt"
cmp -s "$work/ref_batch.txt" "$work/kill_batch.txt" ||
  fail "batch through the front with daemon $victim killed differs from daemon 1's"
[ -s "$work/put4.failed" ] && { cat "$work/put4.err" >&2; fail "PUTs not acknowledged: $(tr '\n' ' ' < "$work/put4.failed")"; }
[ "$(wc -l < "$work/put4.txt")" = 10 ] || fail "PUTs during the kill: $(wc -l < "$work/put4.txt") of 10 acknowledged"
echo "cluster check: daemon $victim killed after $done_at_kill of $npairs answers: the batch completed over a new connection ($(grep -o 'made again [0-9]* time' "$work/kill_batch.err")), all $npairs results equal daemon 1's; 10 PUTs acknowledged"

# 5. The killed daemon back on its port: nothing stored is lost or corrupt.
start_daemon "$victim" "${dport[$victim]}"
cat "$work/put1.txt" "$work"/put3_*.txt "$work/put4.txt" | cut -d' ' -f1 | sort -u > "$work/acked.txt"
nacked=$(wc -l < "$work/acked.txt")
[ "$nacked" = 25 ] || fail "$nacked distinct shapes acknowledged, expected 25"
check_files
for i in 1 2 3; do
  "$cli" query "${ids[0]}" -k 100 --server "$(d "$i")" --timeout 300 2>/dev/null | awk '{print $2}' |
    cat - <(echo "${ids[0]}") | sort > "$work/seen$i.txt"
  cmp -s "$work/acked.txt" "$work/seen$i.txt" ||
    fail "daemon $i does not rank exactly the $nacked acknowledged shapes"
  for k in shapes_corrupt bases_corrupt; do
    [ "$(stat_of "$i" "$k")" = 0 ] || fail "daemon $i counted $k $(stat_of "$i" "$k")"
  done
done
check_files
echo "cluster check: daemon $victim restarted: all $nacked acknowledged shapes on all 3 daemons, files intact, no temp file, nothing counted corrupt ($(( $(date +%s) - t_start )) s)"
