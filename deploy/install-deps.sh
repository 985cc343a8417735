#!/usr/bin/env bash
# Installs the Debian packages shapematch builds and tests with. Idempotent; needs root
# (or sudo). Skips apt entirely when every package is already installed.
set -euo pipefail

PKGS=(
  build-essential cmake pkg-config
  libopenmesh-dev          # mesh files, cleanup, decimation
  libflann-dev liblz4-dev  # nearest neighbours (flann's headers include lz4)
  libdraco-dev             # Draco decode/encode
  zlib1g-dev               # reading .gz mesh files
  libxxhash-dev            # XXH3 checksums of stored files
  libsuitesparse-dev       # CHOLMOD sparse Cholesky
  liblapacke-dev libopenblas-dev  # dense algebra
  python3 python3-numpy python3-scipy  # reference evaluator in ../shared/tools
  python3-matplotlib       # the evaluation suite's plots (bench/eval)
  clang libclang-rt-dev    # fuzz harnesses: libFuzzer + ASan/UBSan (tests/fuzz/run.sh)
  afl++                    # the same harnesses under AFL++ (tests/fuzz/README.md)
  haproxy stunnel4 openssl # the TLS front of deploy/tls, checked by deploy/tls/check.sh
  libsystemd-dev           # sd_notify (Type=notify, deploy/systemd); optional at build time
  python3-yaml             # deploy/check-files.sh reads the Kubernetes manifests
  man-db                   # test_manpages renders the man pages with man --warnings
)

missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0

SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
