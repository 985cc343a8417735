#!/usr/bin/env bash
# The README's main command: installs dependencies, builds, makes two shapes of its own (a
# bumpy blob, and the same blob with bumps 20% higher, stretched 1.2x along y: a
# non-isometric deformation with the same vertex order, so the true map is the identity),
# Draco-encodes one, starts the daemon with its on-disk store on a free loopback port,
# matches the pair through the CLI, prints the distance and the map's accuracy, compares
# with a local computation, and stops the daemon with SIGTERM.
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/install-deps.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)" --target shapematch shapematchd
out=out/demo
mkdir -p "$out"
sm=./build/clients/shapematch
$sm synth blob --subdiv 4 --seed 1 --amp 0.8 -o "$out/blob1.off"
$sm synth blob --subdiv 4 --seed 1 --amp 0.95 --stretch 1,1.2,1 -o "$out/blob2.off"
$sm encode "$out/blob2.off" -o "$out/blob2.drc"

./build/server/shapematchd --port 0 --data-dir "$out/store" 2>"$out/shapematchd.log" &
daemon=$!
trap 'kill -TERM $daemon 2>/dev/null || true' EXIT
for _ in $(seq 50); do
  port=$(grep -o 'msg=listening port=[0-9]*' "$out/shapematchd.log" | grep -o '[0-9]*$' || true)
  [ -n "$port" ] && break
  sleep 0.1
done
[ -n "$port" ] || { echo "shapematchd did not start:"; cat "$out/shapematchd.log"; exit 1; }
export SHAPEMATCH_SERVER=127.0.0.1:$port
echo "shapematchd listening on $SHAPEMATCH_SERVER, store in $out/store"

$sm put "$out/blob1.off" "$out/blob2.drc"
$sm match "$out/blob1.off" "$out/blob2.drc" -o "$out/map_1_to_2.txt"
echo "distance: $($sm distance "$out/blob1.off" "$out/blob2.drc")"
$sm eval "$out/blob1.off" "$out/blob2.drc" --map "$out/map_1_to_2.txt" --gt-kind identity
$sm match "$out/blob1.off" "$out/blob2.drc" --local -o "$out/map_local.txt" 2>/dev/null
cmp -s "$out/map_1_to_2.txt" "$out/map_local.txt" && echo "daemon map == local map"
echo "map (line i = vertex of blob2 for vertex i of blob1): $out/map_1_to_2.txt"
kill -TERM $daemon
wait $daemon && echo "shapematchd stopped cleanly (exit 0)"
trap - EXIT
