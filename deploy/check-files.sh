#!/usr/bin/env bash
# deploy/check-files.sh BUILD_DIR: the deployment files checked by the tools that read
# them (docs/DEPLOY.md), on this machine, without a service manager, container engine or
# cluster:
#   - deploy/systemd/shapematchd.service: `systemd-analyze verify` without a single
#     warning (unknown keys are only warnings there), and its exposure score offline;
#   - deploy/systemd/shapematchd.conf: the real daemon starts with it (--config);
#   - sd_notify: the daemon, run with $NOTIFY_SOCKET on a socket of this script, sends
#     READY=1 once it listens and STOPPING=1 on SIGTERM (when built with libsystemd);
#   - deploy/cluster/haproxy.cfg and deploy/k8s/haproxy.cfg: `haproxy -c`;
#   - deploy/k8s/*.yaml: parsed (python3-yaml), every object named, the kustomization's
#     files present, selectors matching their pod labels, referenced claims, config maps
#     and named ports defined;
#   - deploy/Containerfile: every runtime package it installs exists in apt.
# A step whose tool is missing is reported and skipped; exit 77 if every step was.
set -euo pipefail
build=$(cd "${1:-build}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d)
dpid=
cleanup() { [ -n "$dpid" ] && kill -9 "$dpid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
fail() { echo "deploy files: FAILED: $*" >&2; exit 1; }
ran=0
skip() { echo "deploy files: $1 not available, skipped"; }

# systemd unit
if command -v systemd-analyze >/dev/null; then
  sed "s|/usr/local/bin/shapematchd|$build/server/shapematchd|" \
    "$here/systemd/shapematchd.service" > "$work/shapematchd.service"
  out=$(systemd-analyze verify "$work/shapematchd.service" 2>&1) || fail "systemd-analyze verify: $out"
  [ -z "$out" ] || fail "systemd-analyze verify warns: $out"
  score=$(systemd-analyze security --offline=true "$work/shapematchd.service" 2>/dev/null |
          sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p')
  echo "deploy files: systemd unit verified, exposure level ${score:-?} (systemd-analyze security)"
  ran=1
else
  skip systemd-analyze
fi

# the shipped config file, and sd_notify
start_with_conf() { # $1: extra environment assignment or ""
  : > "$work/d.log"
  env $1 "$build/server/shapematchd" --config "$here/systemd/shapematchd.conf" \
    --data-dir "$work/data" --port 0 --metrics-port 0 2> "$work/d.log" &
  dpid=$!
  for _ in $(seq 200); do
    grep -q 'msg=listening' "$work/d.log" && return 0
    kill -0 "$dpid" 2>/dev/null || break
    sleep 0.05
  done
  cat "$work/d.log" >&2
  fail "shapematchd does not start with deploy/systemd/shapematchd.conf"
}
if ldd "$build/server/shapematchd" | grep -q libsystemd && command -v python3 >/dev/null; then
  python3 - "$work/notify.sock" > "$work/notify.txt" <<'PY' &
import socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sys.argv[1])
s.settimeout(60)
while True:
    msg = s.recv(4096).decode()
    print(msg, flush=True)
    if "STOPPING=1" in msg:
        break
PY
  npid=$!
  for _ in $(seq 100); do [ -S "$work/notify.sock" ] && break; sleep 0.05; done
  start_with_conf "NOTIFY_SOCKET=$work/notify.sock"
  for _ in $(seq 100); do grep -q READY=1 "$work/notify.txt" && break; sleep 0.05; done
  grep -q READY=1 "$work/notify.txt" || fail "no READY=1 on \$NOTIFY_SOCKET"
  kill -TERM "$dpid"
  wait "$dpid" || fail "shapematchd did not exit cleanly on SIGTERM"
  dpid=
  wait "$npid" || fail "no STOPPING=1 on \$NOTIFY_SOCKET after SIGTERM"
  echo "deploy files: shapematchd.conf accepted; sd_notify READY=1, then STOPPING=1 on SIGTERM"
else
  start_with_conf ""
  kill -TERM "$dpid"
  wait "$dpid" || fail "shapematchd did not exit cleanly on SIGTERM"
  dpid=
  echo "deploy files: shapematchd.conf accepted (built without libsystemd: no sd_notify check)"
fi
ran=1

# HAProxy configurations
if command -v haproxy >/dev/null; then
  SM_FRONT_BIND=127.0.0.1:7878 SM_DAEMON1=127.0.0.1:7001 SM_DAEMON2=127.0.0.1:7002 \
    SM_DAEMON3=127.0.0.1:7003 haproxy -c -q -f "$here/cluster/haproxy.cfg" ||
    fail "haproxy -c deploy/cluster/haproxy.cfg"
  haproxy -c -q -f "$here/k8s/haproxy.cfg" || fail "haproxy -c deploy/k8s/haproxy.cfg"
  echo "deploy files: both haproxy configurations valid (haproxy -c)"
  ran=1
else
  skip haproxy
fi

# Kubernetes manifests
if python3 -c 'import yaml' 2>/dev/null; then
  python3 - "$here/k8s" <<'PY' || fail "deploy/k8s manifests"
import os, sys, yaml
d = sys.argv[1]
kz = yaml.safe_load(open(os.path.join(d, "kustomization.yaml")))
objs, errors = [], []
for r in kz["resources"]:
    for doc in yaml.safe_load_all(open(os.path.join(d, r))):
        if doc:
            objs.append((r, doc))
for g in kz.get("configMapGenerator", []):
    for f in g["files"]:
        if not os.path.exists(os.path.join(d, f)):
            errors.append(f"configMapGenerator file {f} missing")
config_maps = {g["name"] for g in kz.get("configMapGenerator", [])}
claims = {o["metadata"]["name"] for _, o in objs if o["kind"] == "PersistentVolumeClaim"}
pod_labels = []
for r, o in objs:
    for k in ("apiVersion", "kind", "metadata"):
        if k not in o:
            errors.append(f"{r}: an object without {k}")
    if "name" not in o.get("metadata", {}):
        errors.append(f"{r}: a {o.get('kind')} without a name")
    if o.get("kind") in ("Deployment", "StatefulSet"):
        name = o["metadata"]["name"]
        sel = o["spec"]["selector"]["matchLabels"]
        labels = o["spec"]["template"]["metadata"]["labels"]
        pod_labels.append(labels)
        if any(labels.get(k) != v for k, v in sel.items()):
            errors.append(f"{name}: selector {sel} does not match the pod labels {labels}")
        pod = o["spec"]["template"]["spec"]
        vols = {v["name"]: v for v in pod.get("volumes", [])}
        for v in vols.values():
            if "persistentVolumeClaim" in v and v["persistentVolumeClaim"]["claimName"] not in claims:
                errors.append(f"{name}: claim {v['persistentVolumeClaim']['claimName']} undefined")
            if "configMap" in v and v["configMap"]["name"] not in config_maps:
                errors.append(f"{name}: config map {v['configMap']['name']} undefined")
        for c in pod["containers"]:
            ports = {p["name"] for p in c.get("ports", [])}
            for m in c.get("volumeMounts", []):
                if m["name"] not in vols:
                    errors.append(f"{name}/{c['name']}: mount of undefined volume {m['name']}")
            for probe in ("readinessProbe", "livenessProbe"):
                p = c.get(probe, {})
                port = p.get("tcpSocket", {}).get("port")
                if isinstance(port, str) and port not in ports:
                    errors.append(f"{name}/{c['name']}: {probe} on undefined port {port}")
for r, o in objs:
    if o.get("kind") == "Service":
        sel = o["spec"]["selector"]
        if not any(all(l.get(k) == v for k, v in sel.items()) for l in pod_labels):
            errors.append(f"Service {o['metadata']['name']}: selector {sel} matches no pods")
for e in errors:
    print("deploy/k8s:", e, file=sys.stderr)
print(f"deploy files: {len(objs)} Kubernetes objects parsed and cross-checked")
sys.exit(1 if errors else 0)
PY
  ran=1
else
  skip python3-yaml
fi

# Containerfile: the runtime packages exist in this Debian's apt.
if command -v apt-cache >/dev/null; then
  pkgs=$(sed -n '/^FROM debian:bookworm-slim$/,$p' "$here/Containerfile" |
         sed -n '/apt-get install/,/rm -rf/p' | tr -d '\\' | tr ' ' '\n' |
         grep -E '^lib|^zlib' || true)
  [ -n "$pkgs" ] || fail "no runtime packages found in deploy/Containerfile"
  for p in $pkgs; do
    apt-cache show "$p" >/dev/null 2>&1 || fail "deploy/Containerfile: no apt package $p"
  done
  echo "deploy files: the Containerfile's $(echo $pkgs | wc -w) runtime packages exist in apt"
  ran=1
else
  skip apt-cache
fi
[ "$ran" = 1 ] || exit 77
