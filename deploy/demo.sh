#!/usr/bin/env bash
# The README's main command (for now: the per-shape half of the pipeline, since the
# matcher and the daemon are not built yet): installs dependencies, builds, makes two
# shapes of its own, Draco-encodes one, and computes and saves both spectral bases.
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/install-deps.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)"
out=out/demo
mkdir -p "$out"
sm=./build/clients/shapematch
$sm synth blob --subdiv 5 --seed 1 -o "$out/blob1.off"
$sm synth blob --subdiv 5 --seed 2 --stretch 1,1.4,0.8 -o "$out/blob2.off"
$sm encode "$out/blob2.off" -o "$out/blob2.drc"
$sm basis "$out/blob1.off" --kind lb -k 100 -o "$out/blob1.lb.smb"
$sm basis "$out/blob2.drc" --kind elastic -k 100 -o "$out/blob2.elastic.smb"
$sm info "$out/blob1.lb.smb"
$sm info "$out/blob2.elastic.smb"
