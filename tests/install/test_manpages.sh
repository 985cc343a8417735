#!/usr/bin/env bash
# test_manpages: the man pages built from the --help texts (deploy/cmake, docs/man) agree
# with the programs: every option and command of --help is in the rendered page, the
# version is the program's, the exit codes the EXIT STATUS section lists are the ones
# the programs return, and man (or nroff when man is absent) renders without warnings.
# Usage: test_manpages.sh SHAPEMATCH SHAPEMATCHD MAN_DIR WORK_DIR
set -euo pipefail
cli=$1 daemon=$2 mandir=$3 work=$4
rm -rf "$work" && mkdir -p "$work"
export LC_ALL=C MANWIDTH=100 # ASCII output: \- is a plain hyphen, lines wide enough
failed=0
fail() { echo "FAIL: $*" >&2; failed=1; }

render() { # PAGE -> plain text on stdout, warnings in $work/warnings
  if command -v man > /dev/null; then
    man --warnings -P cat -l "$1" 2> "$work/warnings"
  elif command -v nroff > /dev/null; then
    nroff -man -ww -Tascii "$1" 2> "$work/warnings" | sed 's/.\x08//g'
  else
    echo "SKIP: neither man nor nroff" >&2
    exit 77
  fi
}

check_page() { # PROGRAM PAGE
  local prog=$1 page=$2 text help opt version
  text=$(render "$page")
  [ -s "$work/warnings" ] && fail "$page renders with warnings: $(cat "$work/warnings")"
  help=$("$prog" --help)
  for opt in $(grep -oE '(^|[[ (|,])--?[a-z][a-z0-9-]*' <<< "$help" | sed 's/^[[ (|,]//' | sort -u); do
    grep -qF -- "$opt" <<< "$text" || fail "$page lacks $opt of $(basename "$prog") --help"
  done
  # every line of the help, words joined by single spaces, is in the page's text
  local flat_help flat_text line
  flat_text=$(tr -s ' \n' '  ' <<< "$text")
  while IFS= read -r line; do
    line=$(tr -s ' ' <<< "$line" | sed 's/^ //;s/ $//')
    [ -z "$line" ] && continue
    grep -qF -- "$line" <<< "$flat_text" || fail "$page lacks the help line '$line'"
  done <<< "$help"
  version=$("$prog" --version | cut -d' ' -f1,2)
  grep -qF "$version" <<< "$text" || fail "$page does not show '$version'"
  for code in 0 1 2; do
    sed -n '/^EXIT STATUS/,/^[A-Z]/p' <<< "$text" | grep -qE "^ +$code\b" ||
      fail "$page: exit status $code not documented"
  done
}

check_page "$cli" "$mandir/shapematch.1"
check_page "$daemon" "$mandir/shapematchd.8"

# the documented exit codes are the real ones
status() { set +e; "$@" > /dev/null 2>&1; echo $?; set -e; }
[ "$(status "$cli" --version)" = 0 ] || fail "shapematch --version: not 0"
[ "$(status "$cli" info "$work/no-such-mesh.off")" = 1 ] || fail "shapematch info on a missing file: not 1"
[ "$(status "$cli" no-such-command)" = 2 ] || fail "shapematch no-such-command: not 2"
[ "$(status "$cli" match only-one.off)" = 2 ] || fail "shapematch match with one mesh: not 2"
[ "$(status "$daemon" --version)" = 0 ] || fail "shapematchd --version: not 0"
[ "$(status "$daemon" --no-such-flag 1)" = 2 ] || fail "shapematchd --no-such-flag: not 2"
touch "$work/file"
[ "$(status "$daemon" --port 0 --data-dir "$work/file/store")" = 1 ] ||
  fail "shapematchd with an unusable data directory: not 1"
[ $failed = 0 ] && rm -rf "$work" && echo "test_manpages: ok"
exit $failed
