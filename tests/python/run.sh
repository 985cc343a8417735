#!/bin/sh
# ctest test_python: the Python client's unittest suite (test_client.py) against the real
# daemon and CLI. Usage: run.sh SHAPEMATCHD SHAPEMATCH TMPDIR. Uses Debian's /usr/bin/python3
# (or $SM_PYTHON, or python3 on PATH); exit 77 (skipped) only when there is no python3.
py=${SM_PYTHON:-/usr/bin/python3}
[ -x "$py" ] || py=$(command -v python3) || { echo "test_python: no python3: skipped"; exit 77; }
SM_SERVER_BIN=$1 SM_CLI_BIN=$2 SM_TEST_TMP=$3 exec "$py" "$(dirname "$0")/test_client.py" -v
