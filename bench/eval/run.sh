#!/usr/bin/env bash
# The evaluation suite, one command per experiment:
#   bench/eval/run.sh ablation|curves|classify|visual|robust|report|all|ci|bounds [--quick]
# Installs the Debian packages (deploy/install-deps.sh), builds the optimized tree in
# build/, then runs bench/eval/suite.py (see its --help). Results: docs/eval/*.json and
# *.png, docs/RESULTS.md; bases cached in out/eval/. `ci` writes to out/eval-ci/ instead.
set -euo pipefail
cd "$(dirname "$0")/../.."
./deploy/install-deps.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build build -j"$(nproc)" --target shapematch shapematchd eval_pairs eval_tool >/dev/null
if [ "${1:-}" = ci ]; then
  exec /usr/bin/python3 bench/eval/suite.py ci --out out/eval-ci/docs/eval --work out/eval-ci "${@:2}"
fi
exec /usr/bin/python3 bench/eval/suite.py "$@"
