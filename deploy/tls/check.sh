#!/usr/bin/env bash
# deploy/tls/check.sh BUILD_DIR: the TLS front of deploy/tls/haproxy.cfg, end to end with
# real components: a throwaway self-signed certificate (openssl), shapematchd on a loopback
# port, Debian's haproxy terminating TLS with the shipped configuration, and the CLI, which
# speaks clear text, reaching it through stunnel4 in client mode (TLS verified against the
# throwaway certificate). Passes if `shapematch ping` and `stats` answer through TLS and a
# plain-text connection to the TLS port gets no answer. Exit 77 when haproxy, stunnel4 or
# openssl is missing.
set -euo pipefail
build=$(cd "${1:-build}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
for t in haproxy stunnel4 openssl; do
  command -v "$t" >/dev/null || { echo "tls check: $t not installed, skipped"; exit 77; }
done
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj "/CN=localhost" \
  -addext "subjectAltName=DNS:localhost,IP:127.0.0.1" \
  -keyout "$work/key.pem" -out "$work/cert.pem" 2>/dev/null
cat "$work/cert.pem" "$work/key.pem" > "$work/tls.pem"

: > "$work/daemon.log" # before the daemon opens it: the sed below may run first
"$build/server/shapematchd" --port 0 --data-dir "$work/data" 2> "$work/daemon.log" &
pids+=($!)
for _ in $(seq 100); do
  dport=$(sed -n 's/.*msg=listening port=\([0-9]*\).*/\1/p' "$work/daemon.log" | head -1)
  [ -n "$dport" ] && break
  sleep 0.1
done
[ -n "${dport:-}" ] || { echo "tls check: daemon did not start"; cat "$work/daemon.log"; exit 1; }

export SM_TLS_PORT=$(free_port) SM_TLS_PEM="$work/tls.pem" SM_DAEMON_PORT=$dport
haproxy -c -f "$here/haproxy.cfg" >/dev/null
haproxy -db -f "$here/haproxy.cfg" > "$work/haproxy.log" 2>&1 &
pids+=($!)

cport=$(free_port)
cat > "$work/stunnel-client.conf" <<CONF
foreground = yes
pid =
[client]
client = yes
accept = 127.0.0.1:$cport
connect = 127.0.0.1:$SM_TLS_PORT
CAfile = $work/cert.pem
verifyChain = yes
checkHost = localhost
CONF
stunnel4 "$work/stunnel-client.conf" > "$work/stunnel.log" 2>&1 &
pids+=($!)

ok=0
for _ in $(seq 50); do
  if "$build/clients/shapematch" ping --server "127.0.0.1:$cport" --timeout 5 > "$work/ping.txt" 2>&1; then
    ok=1
    break
  fi
  sleep 0.2
done
[ "$ok" = 1 ] || { echo "tls check: ping through TLS failed"; cat "$work/ping.txt" "$work/haproxy.log" "$work/stunnel.log"; exit 1; }
"$build/clients/shapematch" stats --server "127.0.0.1:$cport" --timeout 5 | grep -q '^shapes' ||
  { echo "tls check: stats through TLS failed"; exit 1; }
# The TLS port does not speak clear text: the CLI's plain HELLO gets no protocol answer.
if "$build/clients/shapematch" ping --server "127.0.0.1:$SM_TLS_PORT" --timeout 3 --io-timeout 3 >/dev/null 2>&1; then
  echo "tls check: the TLS port answered a clear-text client"; exit 1
fi
echo "tls check: ping and stats answered through haproxy TLS termination ($(cat "$work/ping.txt"))"
