"""smdaemon: the real shapematchd, started for a benchmark on a free loopback port.

One home for what bench/bench_capacity.py, bench/eval/suite.py and bench/eval/query_scale.py
each did alike: start the daemon with --port 0 (the kernel picks a free port), learn the
port from the daemon's log line `msg=listening port=N`, and stop it with SIGTERM.

    proc, port = smdaemon.start(daemon_bin, data_dir, extra_args, log_path, env=None)
    rc = smdaemon.stop(proc)

start raises RuntimeError naming the log when the daemon exits or does not listen within
wait_s seconds; stop returns the daemon's exit status (SIGKILL after wait_s seconds).
"""
import re
import signal
import subprocess
import time


def start(daemon_bin, data_dir, extra_args, log_path, env=None, wait_s=20.0):
    with open(log_path, "w") as log:
        proc = subprocess.Popen([daemon_bin, "--port", "0", "--data-dir", data_dir] +
                                list(extra_args), stderr=log, env=env)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        with open(log_path) as f:
            m = re.search(r"msg=listening port=(\d+)", f.read())
        if m:
            return proc, int(m.group(1))
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    raise RuntimeError("shapematchd did not start; see " + log_path)


def stop(proc, wait_s=120.0):
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()
