#!/usr/bin/env bash
# test_completion: clients/shapematch.bash-completion sourced in a plain bash (no
# bash-completion package needed): subcommands, options, option values and file names
# complete as they should, and the options it offers are exactly those of
# `shapematch --help` (so neither can grow an option the other lacks).
# Usage: test_completion.sh COMPLETION_SCRIPT SHAPEMATCH SHAPEMATCHD WORK_DIR
set -euo pipefail
script=$1 cli=$2 daemon=$3 work=$4
rm -rf "$work" && mkdir -p "$work/sub" && cd "$work"
touch a.off b.PLY c.drc notes.txt basis.smb
PATH=$(dirname "$daemon"):$PATH
# shellcheck source=/dev/null
source "$script"
failed=0

# The words bash would offer for the command line $1 (a trailing space: a new word).
complete_line() {
  local line=$1
  read -r -a COMP_WORDS <<< "$line"
  [[ $line == *" " ]] && COMP_WORDS+=("")
  COMP_CWORD=$((${#COMP_WORDS[@]} - 1))
  COMPREPLY=()
  if [[ ${COMP_WORDS[0]} == shapematchd ]]; then _shapematchd; else _shapematch; fi
  printf '%s\n' "${COMPREPLY[@]}" | sort | tr '\n' ' ' | sed 's/ $//'
  echo
}

expect() { # LINE EXPECTED-WORDS (sorted, space-separated)
  local got
  got=$(complete_line "$1")
  if [[ $got != "$2" ]]; then
    echo "FAIL: '$1' -> '$got', expected '$2'" >&2
    failed=1
  fi
}

expect "shapematch ma" "match"
expect "shapematch re" "render"
expect "shapematch --v" "--version"
expect "shapematch match a.off b.off --ba" "--basis"
expect "shapematch match --basis " "elastic hybrid lb"
expect "shapematch distance a.off b.off --init " "nn sinkhorn"
expect "shapematch query a.off --mode " "default full spectral"
expect "shapematch eval a.off b.off --gt-kind i" "identity inverse"
expect "shapematch match " "a.off b.PLY c.drc sub"
expect "shapematch info " "a.off b.PLY basis.smb c.drc sub"
expect "shapematch render a.off b.off --map n" "notes.txt"
expect "shapematch synth " "blob sphere torus"
expect "shapematch match a.off b.off --png" "--png-out"
expect "shapematch match a.off b.off -k " ""
expect "shapematch put --pr" "--prepare"
expect "shapematchd --data" "--data-dir"
expect "shapematchd --data-dir " "sub"

# Every command of --help is offered first, every option of --help by some command,
# and nothing else.
help=$("$cli" --help)
commands=$(complete_line "shapematch " | tr ' ' '\n' | grep -v '^-' | grep -v '^help$' | sort -u)
# a command item: a line at indent 2 whose next line is its description at indent 8
# ("stats | ping": both words)
help_commands=$(awk 'prev ~ /^  [a-z]/ && /^        / { split(prev, w, " "); print w[1]
                      if (w[2] == "|" && w[3] !~ /^-/) print w[3] } { prev = $0 }' <<< "$help" |
                sort -u)
commands=$(echo $commands) help_commands=$(echo $help_commands) # one line each
if [[ $commands != "$help_commands" ]]; then
  echo "FAIL: commands differ: completion:" $commands "/ --help:" $help_commands >&2
  failed=1
fi
offered=$(for c in $commands; do complete_line "shapematch $c -" | tr ' ' '\n'; done
          complete_line "shapematch -" | tr ' ' '\n')
offered=$(grep -v "^$" <<< "$offered" | sort -u)
documented=$(grep -oE '(^|[[ (|,])--?[a-z][a-z0-9-]*' <<< "$help" | sed 's/^[[ (|,]//' | sort -u)
documented=$(printf '%s\n--help\n' "$documented" | sort -u) # --help: the help itself
if [[ $offered != "$documented" ]]; then
  echo "FAIL: options differ (< completion only, > --help only):" >&2
  diff <(echo "$offered") <(echo "$documented") >&2 || true
  failed=1
fi
[ $failed = 0 ] && rm -rf "$work" && echo "test_completion: ok"
exit $failed
