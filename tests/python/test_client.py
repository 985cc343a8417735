"""test_python: the Python client (clients/python) against the real shapematchd and CLI.

Run by tests/python/run.sh (ctest test_python) with SM_SERVER_BIN, SM_CLI_BIN and
SM_TEST_TMP in the environment. One daemon on a loopback port serves every case; shapes
are made by `shapematch synth` (the demo's blob pair plus a third blob). What is checked:
- the codec against PROTOCOL.md section 9's vectors;
- ids, maps (xy, yx), functional maps, distances and query hits equal the CLI's output on
  the same shapes byte for byte (the CLI's own number formats applied to our values);
- a pipelined batch gives the same results as sequential calls, and really pipelines;
- statuses raise StatusError with the right code, name and detail, and the connection
  survives request-level ones; a wrong token is fatal (UNAUTHORIZED);
- maps come as numpy int32 arrays, as lists with use_numpy=False or $SHAPEMATCH_NO_NUMPY,
  and as lists where numpy cannot be imported at all;
- the example script writes the coloured PLYs it promises.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
CLIENT_DIR = os.path.join(HERE, "..", "..", "clients", "python")
sys.path.insert(0, CLIENT_DIR)

import shapematch  # noqa: E402
from shapematch import wire  # noqa: E402
from shapematch.meshes import read_off  # noqa: E402

SERVER = os.environ.get("SM_SERVER_BIN")
CLI = os.environ.get("SM_CLI_BIN")
TMP = os.path.join(os.environ.get("SM_TEST_TMP", "/tmp"), "test_python")
TOKEN = "s3cret-token"

daemons = []   # (process, address) started here, stopped in tearDownModule
ADDR = None
SHAPES = {}    # name -> path


def start_daemon(name, *extra):
    """Starts shapematchd on a free loopback port with its store in TMP/name."""
    log_path = os.path.join(TMP, name + ".log")
    log = open(log_path, "w")
    proc = subprocess.Popen([SERVER, "--bind", "127.0.0.1", "--port", "0", "--data-dir",
                             os.path.join(TMP, name), "--threads", "2", *extra],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log)
    log.close()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        with open(log_path) as f:
            for line in f:
                if "msg=listening port=" in line:
                    addr = "127.0.0.1:" + line.split("msg=listening port=")[1].split()[0]
                    daemons.append((proc, addr))
                    return addr
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError("shapematchd did not start; log: " + open(log_path).read())


def cli(*args, check=True):
    """Runs the CLI against the test daemon; returns (stdout, stderr) as text."""
    env = dict(os.environ, SHAPEMATCH_SERVER=ADDR)
    env.pop("SHAPEMATCH_TOKEN", None)
    run = subprocess.run([CLI, *args], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, timeout=300)
    if check and run.returncode != 0:
        raise AssertionError("shapematch %s failed (%d): %s"
                             % (" ".join(args), run.returncode, run.stderr.decode()))
    return run.stdout.decode(), run.stderr.decode()


def map_text(m):
    """A map as the CLI writes it (-o): one "%d\\n" line per entry."""
    return "".join("%d\n" % v for v in (m.tolist() if hasattr(m, "tolist") else m))


def fmap_text(C):
    """A functional map as the CLI writes it (--fmap): rows, "%.17g" numbers."""
    rows = C.tolist() if hasattr(C, "tolist") else C
    return "".join(" ".join("%.17g" % v for v in row) + "\n" for row in rows)


def setUpModule():
    global ADDR
    if not (SERVER and CLI):
        raise RuntimeError("SM_SERVER_BIN and SM_CLI_BIN must name shapematchd and shapematch")
    shutil.rmtree(TMP, ignore_errors=True)
    os.makedirs(TMP)
    # the demo's pair (deploy/demo.sh) at subdiv 3 (642 vertices), and a third blob
    for name, extra in (("blob1", ["--seed", "1", "--amp", "0.8"]),
                        ("blob2", ["--seed", "1", "--amp", "0.95", "--stretch", "1,1.2,1"]),
                        ("blob3", ["--seed", "2", "--amp", "0.6"])):
        SHAPES[name] = os.path.join(TMP, name + ".off")
        subprocess.run([CLI, "synth", "blob", "--subdiv", "3", *extra, "-o", SHAPES[name]],
                       check=True, stderr=subprocess.DEVNULL)
    SHAPES["blob2.drc"] = os.path.join(TMP, "blob2.drc")
    subprocess.run([CLI, "encode", SHAPES["blob2"], "-o", SHAPES["blob2.drc"]], check=True,
                   stderr=subprocess.DEVNULL)
    os.environ["SHAPEMATCH_CLI"] = CLI
    ADDR = start_daemon("store")


def tearDownModule():
    for proc, _ in daemons:
        proc.send_signal(signal.SIGTERM)
    for proc, addr in daemons:
        if proc.wait(60) != 0:
            raise AssertionError("shapematchd at %s exited with %d" % (addr, proc.returncode))


class Codec(unittest.TestCase):
    """PROTOCOL.md section 9."""

    def test_vectors(self):
        self.assertEqual(wire.crc32c(b"123456789"), 0xE3069283)
        self.assertEqual(wire.crc32c(bytes(32)), 0x8A9136AA)
        frame = wire.encode_frame(1, wire.PING, 9, (5).to_bytes(8, "little"))
        self.assertEqual(frame.hex(), "89534d5001020000090000000000000008000000791dd9ed"
                                      "0500000000000000")

    def test_bad_arguments_name_the_field(self):
        with self.assertRaisesRegex(ValueError, "basis"):
            shapematch.MatchRequest("0" * 64, "1" * 64, basis="bogus")
        with self.assertRaisesRegex(ValueError, "k0"):
            shapematch.MatchRequest("0" * 64, "1" * 64, k0=-1)
        with self.assertRaisesRegex(ValueError, "eta"):
            shapematch.MatchRequest("0" * 64, "1" * 64, eta=float("nan"))
        with self.assertRaisesRegex(ValueError, "landmarks must be pairs"):
            shapematch.MatchRequest("0" * 64, "1" * 64, landmarks=[1, 2, 3])
        with self.assertRaisesRegex(ValueError, "64-hex"):
            shapematch.HasRequest("not an id")
        with self.assertRaisesRegex(ValueError, "query k"):
            shapematch.QueryRequest("0" * 64, k=0)
        with self.assertRaisesRegex(shapematch.ConnectFailed, "port"):
            shapematch.parse_address("host:99999")
        with self.assertRaisesRegex(ValueError, "multires"):
            shapematch.MatchRequest("0" * 64, "1" * 64, multires="yes")
        with self.assertRaisesRegex(ValueError, "multires"):
            shapematch.DistanceRequest("0" * 64, "1" * 64, multires="on")

    def test_multires_flags(self):
        """Version 3's MATCH flags (section 5.7): bit 6 MULTIRES, bit 7 DIRECT, neither for
        auto; refused before sending to an older server."""
        def flags(req):
            return int.from_bytes(req.body[66:68], "little")
        for mode, bit in (("auto", 0), ("on", 64), ("off", 128)):
            req = shapematch.MatchRequest("0" * 64, "1" * 64, multires=mode, want_yx=True)
            self.assertEqual(flags(req), bit | wire.M_WANT_YX)

        class Ctx:
            version = 2
        on = shapematch.MatchRequest("0" * 64, "1" * 64, multires="on")
        with self.assertRaisesRegex(shapematch.OverLimit, "version 2.*version 3"):
            on.payload(Ctx())
        auto = shapematch.MatchRequest("0" * 64, "1" * 64)
        self.assertEqual(auto.payload(Ctx()), auto.body)


class AgainstCli(unittest.TestCase):
    """The Python client's answers equal the CLI's on the same shapes."""

    @classmethod
    def setUpClass(cls):
        cls.c = shapematch.Client(ADDR)
        cls.ids = {}
        for name in ("blob1", "blob2.drc", "blob3"):
            cls.ids[name] = cls.c.put(SHAPES[name]).id

    @classmethod
    def tearDownClass(cls):
        cls.c.close()

    def test_ids_equal_cli_put(self):
        out, _ = cli("put", SHAPES["blob1"], SHAPES["blob2.drc"], SHAPES["blob3"])
        cli_ids = [line.split()[0] for line in out.splitlines()]
        self.assertEqual(cli_ids, [self.ids["blob1"], self.ids["blob2.drc"], self.ids["blob3"]])
        # the same mesh as arrays (through a temporary OFF) is the same Draco bytes
        V, F = read_off(SHAPES["blob1"])
        self.assertEqual(self.c.put_mesh(V, F).id, self.ids["blob1"])
        # an OFF file and its .drc encoding are one shape
        self.assertEqual(self.c.put(SHAPES["blob2"]).id, self.ids["blob2.drc"])

    def test_match_equals_cli(self):
        a, b = self.ids["blob1"], self.ids["blob2.drc"]
        xy, yx, fm = (os.path.join(TMP, n) for n in ("cli_xy.txt", "cli_yx.txt", "cli_fmap.txt"))
        out, _ = cli("match", SHAPES["blob1"], SHAPES["blob2.drc"], "-o", xy, "--yx", yx,
                     "--fmap", fm, "--json")
        r = self.c.match(a, b, want_yx=True, want_fmap=True)
        with open(xy) as f:
            self.assertEqual(map_text(r.map), f.read())
        with open(yx) as f:
            self.assertEqual(map_text(r.map_yx), f.read())
        with open(fm) as f:
            self.assertEqual(fmap_text(r.fmap), f.read())
        j = json.loads(out)
        self.assertEqual("%.6f" % r.orientation, "%.6f" % j["orientation"])
        self.assertEqual("%.6f" % r.confidence, "%.6f" % j["confidence"])
        self.assertEqual(r.init_used, j["start_used"])
        self.assertEqual(len(r.map), 642)
        # the blobs share vertex order: the true map is the identity
        self.assertGreater(sum(int(v) == i for i, v in enumerate(r.map)), 600)
        self.assertTrue(0.0 <= r.confidence <= 1.0)
        self.assertGreater(r.t_total, 0.0)
        self.assertGreaterEqual(r.t_total, r.t_init + r.t_refine - 1e-6)

    def test_match_with_options_equals_cli(self):
        xy = os.path.join(TMP, "cli_lb.txt")
        lm = os.path.join(TMP, "landmarks.txt")
        with open(lm, "w") as f:
            f.write("0 0\n10 10\n")
        cli("match", self.ids["blob3"], self.ids["blob1"], "--basis", "lb", "-k", "60",
            "--init", "nn", "--landmarks", lm, "-o", xy)
        r = self.c.match(self.ids["blob3"], self.ids["blob1"], basis="lb", k1=60, init="nn",
                         landmarks=[(0, 0), (10, 10)])
        with open(xy) as f:
            self.assertEqual(map_text(r.map), f.read())

    def test_multires_equals_cli_local(self):
        """multires="on" through a daemon whose coarse level has 300 vertices: the map equals
        the CLI's local --multires on --coarse-nv 300 map of the same files, and differs
        from the direct path's (the flag reached the server)."""
        addr = start_daemon("store_mr", "--multires-coarse-nv", "300")
        xy = os.path.join(TMP, "cli_mr.txt")
        cli("match", SHAPES["blob1"], SHAPES["blob2.drc"], "--local", "--multires", "on",
            "--coarse-nv", "300", "-o", xy)
        with shapematch.Client(addr) as c:
            self.assertEqual(c.version, wire.VERSION_MULTIRES)
            a, b = c.put(SHAPES["blob1"]).id, c.put(SHAPES["blob2.drc"]).id
            on = c.match(a, b, multires="on")
            off = c.match(a, b, multires="off")
            auto = c.match(a, b)
        with open(xy) as f:
            self.assertEqual(map_text(on.map), f.read())
        self.assertEqual(map_text(off.map), map_text(auto.map))  # 642 vertices: direct
        self.assertNotEqual(map_text(on.map), map_text(off.map))
        self.assertEqual(len(on.map), 642)
        # the blobs share vertex order: most of the coarse path's map is still the identity
        self.assertGreater(sum(int(v) == i for i, v in enumerate(on.map)), 400)

    def test_distance_equals_cli(self):
        a, b = self.ids["blob1"], self.ids["blob3"]
        out, err = cli("distance", a, b, "--json")
        d = self.c.distance(a, b)
        self.assertEqual(out, "%.6f\n" % d.total)
        j = err.strip().splitlines()[-1]
        mine = ('{"distance":%.9f,"point_xy":%.9f,"point_yx":%.9f,"spectrum_lb":%.9f,'
                '"spectrum_elastic":%.9f,' % (d.total, d.point_xy, d.point_yx, d.spectrum_lb,
                                              d.spectrum_elastic))
        self.assertEqual(j[:len(mine)], mine)
        self.assertTrue(0.0 < d.total <= 2.0)
        self.assertEqual(float(d), d.total)

    def test_query_equals_cli(self):
        out, _ = cli("query", self.ids["blob1"], "-k", "2", "--mode", "full")
        q = self.c.query(self.ids["blob1"], k=2, mode="full")
        self.assertEqual(out, "".join("%.6f %s\n" % (h.distance, h.id) for h in q.hits))
        self.assertEqual(len(q.hits), 2)
        self.assertGreaterEqual(q.n_considered, 2)
        self.assertLessEqual(q.hits[0].distance, q.hits[1].distance)


class Batch(unittest.TestCase):
    def test_batch_equals_sequential(self):
        """Client.batch (pipelined requests) and Client.server_batch (one BATCH request)
        answer as the same calls made one after the other."""
        with shapematch.Client(ADDR) as c:
            a, b, d = (c.put(SHAPES[n]).id for n in ("blob1", "blob2", "blob3"))
            M, D, Q = shapematch.MatchRequest, shapematch.DistanceRequest, shapematch.QueryRequest
            reqs = [M(a, b), M(b, a, want_distance=True), D(a, d), M(d, a, basis="hybrid"),
                    Q(a, k=2, mode="spectral"), M(a, "f" * 64), shapematch.HasRequest(d)]
            seq = [c.match(a, b), c.match(b, a, want_distance=True), c.distance(a, d),
                   c.match(d, a, basis="hybrid"), c.query(a, k=2, mode="spectral")]
            # pipelined requests, then the same as one BATCH request (the server's fan-out)
            for run in (lambda cb: c.batch(reqs, inflight=4, callback=cb),
                        lambda cb: c.server_batch(reqs, callback=cb)):
                order = []
                results = run(lambda i, r: order.append(i))
                self.assertEqual(sorted(order), list(range(len(reqs))))
                self.check_same(results, seq)
            self.assertGreater(c.ping(), 0)  # the connection is in step afterwards

    def check_same(self, results, seq):
        self.assertIsInstance(results[5], shapematch.StatusError)
        self.assertEqual((results[5].name, results[5].detail), ("NOT_FOUND", 1))
        self.assertTrue(results[6].stored)
        for got, want in zip(results, seq):
            if isinstance(want, shapematch.MatchResult):
                self.assertEqual(map_text(got.map), map_text(want.map))
                self.assertEqual((got.orientation, got.confidence, got.distance),
                                 (want.orientation, want.confidence, want.distance))
            elif isinstance(want, shapematch.DistanceResult):
                self.assertEqual(got.total, want.total)
                self.assertEqual(got.point_xy, want.point_xy)
            else:
                self.assertEqual(got.hits, want.hits)
        self.assertGreater(len(seq), 4)

    def test_pipelined_for_real(self):
        """A PING sent after a MATCH in one batch is answered first (the server answers
        PINGs at once), which only happens when both were in flight together. The MATCH
        uses an eta no other case uses, so it computes new bases (a second or so), not a
        race against a cached answer."""
        with shapematch.Client(ADDR) as c:
            a, d = c.put(SHAPES["blob1"]).id, c.put(SHAPES["blob3"]).id
            order = []
            reqs = [shapematch.MatchRequest(a, d, eta=3e-4), shapematch.PingRequest()]
            c.batch(reqs, inflight=2, callback=lambda i, r: order.append(i))
            self.assertEqual(order, [1, 0])
            order.clear()
            c.batch(reqs, inflight=1, callback=lambda i, r: order.append(i))
            self.assertEqual(order, [0, 1])


class Errors(unittest.TestCase):
    def setUp(self):
        self.c = shapematch.Client(ADDR)
        self.a = self.c.put(SHAPES["blob1"]).id

    def tearDown(self):
        self.c.close()

    def assertStatus(self, name, status, fn, *args, **kw):
        with self.assertRaises(shapematch.StatusError) as cm:
            fn(*args, **kw)
        self.assertEqual((cm.exception.name, cm.exception.status), (name, status))
        self.assertFalse(cm.exception.fatal)
        self.assertIn(name, str(cm.exception))
        self.assertTrue(self.c.is_open)
        return cm.exception

    def test_request_level_statuses(self):
        e = self.assertStatus("NOT_FOUND", 3, self.c.match, "e" * 64, self.a)
        self.assertEqual(e.detail, 0)
        e = self.assertStatus("NOT_FOUND", 3, self.c.distance, self.a, "e" * 64)
        self.assertEqual(e.detail, 1)
        self.assertStatus("NOT_FOUND", 3, self.c.drop, "e" * 64)
        self.assertStatus("DECODE_FAILED", 4, self.c.put, b"this is not a Draco file")
        self.assertStatus("BAD_REQUEST", 1, self.c.match, self.a, self.a,
                          landmarks=[(100000, 0)])
        e = self.assertStatus("LIMIT_EXCEEDED", 6, self.c.query, self.a,
                              k=self.c.limits.max_query_k + 1)
        self.assertEqual(e.detail, self.c.limits.max_query_k)
        bad = shapematch.PutRequest(b"some draco bytes")
        bad.id = bytes(32)  # an id that is not their SHA-256
        (res,) = self.c.batch([bad])
        self.assertEqual((res.name, res.status), ("ID_MISMATCH", 7))
        self.assertGreater(self.c.ping(), 0)

    def test_has_drop(self):
        blob3 = self.c.put(SHAPES["blob3"])
        self.assertTrue(self.c.has(blob3).stored)
        self.c.drop(blob3)
        h = self.c.has(blob3)
        self.assertEqual((h.stored, h.prepared, h.n_vertices), (False, False, 0))
        self.assertFalse(self.c.put(SHAPES["blob3"]).existed)
        self.assertTrue(self.c.put(SHAPES["blob3"]).existed)

    def test_local_errors(self):
        with self.assertRaisesRegex(shapematch.MeshError, "no-such.off"):
            self.c.put(os.path.join(TMP, "no-such.off"))
        junk = os.path.join(TMP, "junk.off")
        with open(junk, "w") as f:
            f.write("OFF\n3 1 0\n0 0 0\n")
        with self.assertRaisesRegex(shapematch.MeshError, "junk.off"):
            self.c.put(junk)
        with self.assertRaisesRegex(shapematch.MeshError, "face 0"):
            self.c.put_mesh([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 7)])
        with self.assertRaisesRegex(shapematch.ConnectFailed, "127.0.0.1:1"):
            shapematch.Client("127.0.0.1:1", connect_timeout=2)
        self.c.close()
        with self.assertRaises(shapematch.ConnectionClosed):
            self.c.ping()

    def test_token(self):
        addr = start_daemon("token-store", "--token", TOKEN)
        with self.assertRaises(shapematch.StatusError) as cm:
            shapematch.Client(addr, token="wrong")
        e = cm.exception
        self.assertEqual((e.name, e.status, e.fatal), ("UNAUTHORIZED", 0x8008, True))
        with shapematch.Client(addr, token=TOKEN) as c:
            self.assertTrue(c.limits.auth_required)
            self.assertGreater(c.ping(), 0)

    def test_payload_crc(self):
        with shapematch.Client(ADDR, payload_crc=True) as c:
            self.assertTrue(c.has(self.a).stored)
            self.assertIn("shapes", c.stats())


class Numpy(unittest.TestCase):
    def test_numpy_and_lists_agree(self):
        if shapematch.NUMPY is None:
            self.fail("numpy is not importable: install python3-numpy (deploy/install-deps.sh)")
        np = shapematch.NUMPY
        with shapematch.Client(ADDR) as c, shapematch.Client(ADDR, use_numpy=False) as l:
            a, b = c.put(SHAPES["blob1"]).id, c.put(SHAPES["blob2"]).id
            rn = c.match(a, b, want_fmap=True, k1=30)
            rl = l.match(a, b, want_fmap=True, k1=30)
        self.assertIsInstance(rn.map, np.ndarray)
        self.assertEqual(rn.map.dtype, np.int32)
        self.assertIsInstance(rl.map, list)
        self.assertIsInstance(rl.map[0], int)
        self.assertEqual(rn.map.tolist(), rl.map)
        self.assertEqual(rn.fmap.shape, (30, 30))
        self.assertEqual(rn.fmap.tolist(), rl.fmap)

    def run_without(self, prelude, env_extra):
        """Matches blob1 -> blob2 in a fresh interpreter; returns (NUMPY, map type, map)."""
        code = (prelude + "import json, shapematch\n"
                "c = shapematch.Client(%r)\n"
                "r = c.match(c.put(%r), c.put(%r))\n"
                "print(json.dumps([shapematch.NUMPY is None, type(r.map).__name__, r.map]))\n"
                % (ADDR, SHAPES["blob1"], SHAPES["blob2"]))
        env = dict(os.environ, PYTHONPATH=CLIENT_DIR, **env_extra)
        out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                             stdout=subprocess.PIPE, timeout=300).stdout
        return json.loads(out)

    def test_without_numpy(self):
        with shapematch.Client(ADDR) as c:
            want = list(c.match(c.put(SHAPES["blob1"]), c.put(SHAPES["blob2"])).map)
        want = [int(v) for v in want]
        # numpy installed but switched off
        self.assertEqual(self.run_without("", {"SHAPEMATCH_NO_NUMPY": "1"}), [True, "list", want])
        # numpy not importable at all
        blocked = "import sys\nsys.modules['numpy'] = None\n"
        self.assertEqual(self.run_without(blocked, {}), [True, "list", want])


class Example(unittest.TestCase):
    def test_example_writes_colored_plys(self):
        prefix = os.path.join(TMP, "example")
        script = os.path.join(CLIENT_DIR, "examples", "match_two_shapes.py")
        run = subprocess.run([sys.executable, script, SHAPES["blob1"], SHAPES["blob2"], "-o",
                              prefix, "--server", ADDR, "--cli", CLI], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, timeout=300)
        self.assertEqual(run.returncode, 0, run.stderr.decode())
        src, tgt = (self.read_ply(prefix + s) for s in ("_source.ply", "_target.ply"))
        self.assertEqual((len(src), len(tgt)), (642, 642))
        with shapematch.Client(ADDR) as c:
            m = c.match(c.put(SHAPES["blob1"]), c.put(SHAPES["blob2"])).map
        pre = {}
        for i, j in enumerate(m):
            pre.setdefault(int(j), []).append(i)
        single = [(j, p[0]) for j, p in pre.items() if len(p) == 1]
        self.assertGreater(len(single), 300)
        for j, i in single:  # a target vertex with one preimage wears its colour
            self.assertEqual(tgt[j], src[i])
        self.assertGreater(len(set(src)), 100)  # a colour field, not one colour

    @staticmethod
    def read_ply(path):
        with open(path) as f:
            lines = f.read().splitlines()
        nv = int(next(l for l in lines if l.startswith("element vertex")).split()[2])
        start = lines.index("end_header") + 1
        return [tuple(int(w) for w in l.split()[3:6]) for l in lines[start:start + nv]]


if __name__ == "__main__":
    unittest.main(verbosity=2)
