#!/usr/bin/env bash
# The README's main command (for now local, since the daemon is not built yet): installs
# dependencies, builds, makes two shapes of its own (a bumpy blob, and the same blob with
# bumps 20% higher, stretched 1.2x along y: a non-isometric deformation with the same
# vertex order, so the true map is the identity), Draco-encodes one,
# matches them with the default pipeline, prints their distance and the map's accuracy.
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/install-deps.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)"
out=out/demo
mkdir -p "$out"
sm=./build/clients/shapematch
$sm synth blob --subdiv 4 --seed 1 --amp 0.8 -o "$out/blob1.off"
$sm synth blob --subdiv 4 --seed 1 --amp 0.95 --stretch 1,1.2,1 -o "$out/blob2.off"
$sm encode "$out/blob2.off" -o "$out/blob2.drc"
$sm basis "$out/blob2.drc" --kind elastic -k 100 -o "$out/blob2.elastic.smb"
$sm match "$out/blob1.off" "$out/blob2.drc" -o "$out/map_1_to_2.txt"
echo "distance: $($sm distance "$out/blob1.off" "$out/blob2.drc")"
$sm eval "$out/blob1.off" "$out/blob2.drc" --map "$out/map_1_to_2.txt" --gt-kind identity
echo "map (line i = vertex of blob2 for vertex i of blob1): $out/map_1_to_2.txt"
