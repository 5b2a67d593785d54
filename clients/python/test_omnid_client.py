"""Tests of omnid_client.py against a real ``omnid serve --device sim`` (standard library only).

Run from the repository root:

    OMNID_BIN=target/debug/omnid python3 -m unittest -v clients/python/test_omnid_client.py

(``cargo test --test python_client`` does exactly that with the freshly built binary.) The
classes that need a daemon are skipped when ``OMNID_BIN`` is unset; each starts its own
daemon on a socket in a temporary directory, with ``OMNID_STATE_DIR`` there too.
"""

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import unittest
from unittest import mock

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import omnid_client  # noqa: E402
from omnid_client import (  # noqa: E402
    Client,
    ConnectionClosedError,
    OmnidTimeout,
    RefusedError,
    SocketNotFoundError,
    State,
    find_arm_socket,
    find_socket,
)

OMNID_BIN = os.environ.get("OMNID_BIN")
NEEDS_DAEMON = "OMNID_BIN is not set: point it at the omnid binary (cargo test --test python_client does)"

# The default geometry of crates/omnid-core/src/omni/kinematics.rs (Geometry::default), mm.
L1 = 133.35
L2 = 133.35
Y_OFFSET = 23.35
Z_OFFSET = 168.35


def tip_mm(q):
    """Forward kinematics of the Omni (OpenHaptics frame), written here from the formula of
    `tip_position_mm` so the daemon's tip_mm is checked independently."""
    s1, c1 = math.sin(q[0]), math.cos(q[0])
    s2, c2 = math.sin(q[1]), math.cos(q[1])
    s3, c3 = math.sin(q[2]), math.cos(q[2])
    r = L1 * c2 + L2 * s3
    return (-s1 * r, L1 * s2 - L2 * c3 + Y_OFFSET, c1 * r - Z_OFFSET)


class RemoteBindingTests(unittest.TestCase):
    """The remote client's key agreement and request codes (docs/ZENOH.md), without a daemon:
    RFC 7748's X25519 vectors, and the secret and tag the daemon's src/transport/zenoh/bind.rs
    derives from the same inputs (its test the_secret_is_rfc_7748s_x25519_through_hkdf)."""

    def test_x25519_is_rfc_7748s(self):
        alice = bytes.fromhex("77076d0a7318a57d3c16c17251b26645df4c2f87ebc0992ab177fba51db92c2a")
        bob = bytes.fromhex("5dab087e624a8a4b79e17f8b83800ee66f3bb1292618b6fd1c2f8b27ff88e0eb")
        nine = (9).to_bytes(32, "little")
        a_pub = omnid_client._x25519(alice, nine)
        b_pub = omnid_client._x25519(bob, nine)
        self.assertEqual(
            a_pub.hex(), "8520f0098930a754748b7ddcb43ef75a0dbf3a0d26381af4eba4a98eaa9b4e6a"
        )
        self.assertEqual(
            b_pub.hex(), "de9edb7d7b7dc1b4d35b61c2ece435373f8343c85b78674dadfc7e146f882b4f"
        )
        shared = "4a5d9d5ba4ce2de1728e3bf480350f25e07e21c947d19e3376f09b3c1e161742"
        self.assertEqual(omnid_client._x25519(alice, b_pub).hex(), shared)
        self.assertEqual(omnid_client._x25519(bob, a_pub).hex(), shared)

    def test_secret_and_tag_are_the_daemons(self):
        a_pub = bytes.fromhex("8520f0098930a754748b7ddcb43ef75a0dbf3a0d26381af4eba4a98eaa9b4e6a")
        b_pub = bytes.fromhex("de9edb7d7b7dc1b4d35b61c2ece435373f8343c85b78674dadfc7e146f882b4f")
        shared = bytes.fromhex("4a5d9d5ba4ce2de1728e3bf480350f25e07e21c947d19e3376f09b3c1e161742")
        secret = omnid_client._derive(shared, "py-abc", a_pub, b_pub)
        self.assertEqual(
            secret.hex(), "9327c8ff1944d0c35ca05439b0417d16dd4874e8c208005ca138f79e92d76dcd"
        )
        self.assertEqual(
            omnid_client._seal(secret, 1, b'{"op":"status"}').hex(),
            "010000000000000067ce1dc74910e163124a05a2651ff3df0d90d5e84041215698ca04fc73db8c7e",
        )

    def test_two_key_pairs_agree_and_the_id_ends_with_the_fingerprint(self):
        a, b = omnid_client._KeyPair(), omnid_client._KeyPair()
        self.assertEqual(a.shared(b.public), b.shared(a.public))
        self.assertEqual(len(omnid_client._fingerprint(a.public)), 32)
        with self.assertRaises(ValueError):
            a.shared(bytes(32))


class Daemon:
    """One `omnid serve --device sim` in a temporary directory."""

    def __init__(self, config=None):
        self.dir = tempfile.mkdtemp(prefix="omnid-py-")
        self.socket = os.path.join(self.dir, "sim.sock")
        self.state_dir = os.path.join(self.dir, "state")
        self.log_path = os.path.join(self.dir, "daemon.log")
        env = dict(os.environ)
        env["OMNID_STATE_DIR"] = self.state_dir
        env.pop("OMNID_SOCKET", None)
        args = [OMNID_BIN, "serve", "--device", "sim", "--socket", self.socket]
        if config is not None:
            path = os.path.join(self.dir, "omnid.toml")
            with open(path, "w") as f:
                f.write(config)
            args += ["--config", path]
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        try:
            self._wait_ready(30.0)
        except BaseException:
            self.stop()
            raise

    def log(self):
        try:
            with open(self.log_path, "r", errors="replace") as f:
                return f.read()
        except OSError:
            return ""

    def _wait_ready(self, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    "omnid serve exited with %s before listening:\n%s"
                    % (self.proc.returncode, self.log())
                )
            if os.path.exists(self.socket):
                # Ready once the servo ticks: a state sample arrives.
                try:
                    with Client(self.socket, name="ready-probe", timeout=5.0) as probe:
                        probe.stream(1000)
                        probe.next_state(timeout=max(0.1, deadline - time.monotonic()))
                    return
                except (omnid_client.OmnidError, OSError):
                    pass
            time.sleep(0.02)
        raise RuntimeError(
            "omnid serve did not listen on %s within %.0f s:\n%s"
            % (self.socket, timeout, self.log())
        )

    def stop(self):
        """Shut the daemon down through the protocol; terminate it if that fails."""
        if self.proc.poll() is None:
            try:
                with Client(self.socket, name="teardown", timeout=5.0) as c:
                    c.shutdown(timeout=5.0)
                self.proc.wait(timeout=10.0)
            except (omnid_client.OmnidError, OSError, subprocess.TimeoutExpired):
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10.0)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        self._log.close()
        shutil.rmtree(self.dir, ignore_errors=True)


class DaemonTestCase(unittest.TestCase):
    """A test class with its own daemon (started once for the class)."""

    daemon = None
    config = None

    @classmethod
    def setUpClass(cls):
        if not OMNID_BIN:
            raise unittest.SkipTest(NEEDS_DAEMON)
        cls.daemon = Daemon(cls.config)

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            cls.daemon.stop()
            cls.daemon = None

    def connect(self, name="test", **kw):
        c = Client(self.daemon.socket, name=name, **kw)
        self.addCleanup(c.close)
        return c

    def wait_for(self, c, pred, what, timeout=3.0):
        """Read state samples until one satisfies `pred`; fail after `timeout` s."""
        deadline = time.monotonic() + timeout
        last = None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                s = c.next_state(timeout=remaining)
            except OmnidTimeout:
                break
            last = s
            if pred(s):
                return s
        self.fail("no state with %s within %.1f s; last: %r" % (what, timeout, last))


class ReadingTests(DaemonTestCase):
    """What any client can do: hello, status, the state stream."""

    def test_hello(self):
        c = self.connect("hello-test")
        h = c.hello
        self.assertEqual(h["type"], "hello")
        self.assertEqual(h["protocol"], 1)
        self.assertEqual(h["device"], "sim")
        self.assertEqual(h["rate_hz"], 1000.0)
        self.assertEqual(h["access"], "control")
        self.assertTrue(h["server"].startswith("omnid "), h["server"])
        self.assertIsInstance(h["client"], int)
        self.assertGreaterEqual(h["client"], 1)
        self.assertEqual(c.client_id, h["client"])
        self.assertEqual(c.rate_hz, 1000.0)
        self.assertEqual(c.access, "control")
        self.assertEqual(h["stream_ttl_ms"], 20.0)
        self.assertEqual(set(h["controllers"]), {"pd", "nnidc", "ct", "off"})
        self.assertEqual(
            h["modes"],
            ["idle", "hold", "track", "free", "servo_jp", "servo_jf", "servo_cf"],
        )
        other = self.connect("hello-test-2")
        self.assertNotEqual(other.client_id, c.client_id)

    def test_status(self):
        c = self.connect("status-test")
        st = c.status()
        self.assertEqual(st["end"], "running")
        self.assertEqual(st["device"], "sim")
        self.assertEqual(st["mode"], "idle")
        self.assertIsNone(st["lease"])
        self.assertIsNone(st["recording"])
        self.assertGreaterEqual(st["clients"], 1)
        self.assertEqual(st["socket"], self.daemon.socket)
        self.assertEqual(st["protocol"], 1)
        self.assertGreater(st["ticks"], 0)
        self.assertEqual(len(st["heat"]), 3)

    def test_stream_full_rate_has_consecutive_seq(self):
        c = self.connect("seq-test")
        self.assertEqual(c.stream(1000), 1000.0)
        lost_before = c.lost_total
        samples = [c.next_state(timeout=2.0) for _ in range(200)]
        for s in samples:
            self.assertIsInstance(s, State)
            self.assertEqual(len(s.q), 3)
            self.assertEqual(s.mode, "idle")
            self.assertFalse(s.amps)
        gaps = sum(b.seq - a.seq - 1 for a, b in zip(samples, samples[1:]))
        for a, b in zip(samples, samples[1:]):
            self.assertGreater(b.seq, a.seq)
            if b.seq == a.seq + 1:
                self.assertAlmostEqual(b.t - a.t, 1e-3, places=9)
        # A client that keeps up loses nothing; a gap must be explained by `lost`.
        self.assertEqual(gaps, c.lost_total - lost_before)
        self.assertEqual(c.dropped_total, 0)

    def test_stream_rate_is_a_divisor_of_the_device_rate(self):
        c = self.connect("divisor-test")
        granted = c.stream(300)
        self.assertAlmostEqual(granted, 1000.0 / 3.0)
        samples = [c.next_state(timeout=2.0) for _ in range(20)]
        for a, b in zip(samples, samples[1:]):
            self.assertEqual(b.seq - a.seq, 3)
        self.assertTrue(all(s.seq % 3 == 0 for s in samples))
        self.assertEqual(c.stream(0), 0.0)

    def test_latest_state_starts_the_stream_and_is_the_newest(self):
        c = self.connect("latest-test")
        other = self.connect("latest-test-clock")
        self.assertEqual(c.stream_rate_hz, 0.0)
        first = c.latest_state(timeout=2.0)
        self.assertEqual(c.stream_rate_hz, 1000.0)
        self.assertIsInstance(first, State)
        for _ in range(3):
            # Build a backlog on purpose (more than the socket holds), then ask again: the
            # answer must be at least as new as the servo's tick count taken just before.
            time.sleep(0.3)
            ticks = other.status()["ticks"]
            s = c.latest_state(timeout=2.0)
            self.assertGreaterEqual(s.seq, ticks - 5, "latest_state returned an old sample")
        self.assertGreater(s.seq, first.seq)

    def test_a_slow_reader_is_told_what_it_lost(self):
        c = self.connect("slow-reader")
        c.stream(1000)
        # Read nothing for longer than the daemon's queue (1024 samples) and the socket
        # buffer hold: the daemon must drop the oldest samples and say how many.
        time.sleep(2.0)
        c.stream(0)  # its reply comes after every sample queued before it
        samples = []
        while c.pending()[0]:
            samples.append(c.next_state(timeout=0))
        self.assertGreater(c.lost_total, 0)
        self.assertGreater(len(samples), 100)
        gaps = sum(b.seq - a.seq - 1 for a, b in zip(samples, samples[1:]))
        self.assertEqual(gaps, c.lost_total, "seq gaps must equal the `lost` total")
        self.assertEqual(c.dropped_total, 0)

    def test_refusals_name_what_is_wrong_and_keep_the_connection(self):
        c = self.connect("refusal-test")
        with self.assertRaises(RefusedError) as cm:
            c.request("fly")
        self.assertIn("fly", cm.exception.message)
        with self.assertRaises(RefusedError) as cm:
            c.request("status", colour=1)
        self.assertIn("colour", cm.exception.message)
        with self.assertRaises(ValueError):
            c.servo_jp([0.0, float("nan"), 0.0])
        with self.assertRaises(ValueError):
            c.servo_jp([0.0, 0.0])
        self.assertEqual(c.status()["end"], "running")

    def test_hello_with_another_protocol_is_refused(self):
        with mock.patch.object(omnid_client, "PROTOCOL_VERSION", 99):
            with self.assertRaises(RefusedError) as cm:
                Client(self.daemon.socket, name="future")
        self.assertIn("protocol 99", cm.exception.message)

    def test_socket_from_the_environment(self):
        with mock.patch.dict(os.environ, {"OMNID_SOCKET": self.daemon.socket}):
            with Client(name="env-test") as c:
                self.assertEqual(c.path, self.daemon.socket)
                self.assertEqual(c.hello["device"], "sim")
        env = {"OMNID_SOCKET": "", "RUNTIME_DIRECTORY": self.daemon.dir}
        with mock.patch.dict(os.environ, env):
            self.assertEqual(find_socket(), self.daemon.socket)
            with Client(name="runtime-dir-test") as c:
                self.assertEqual(c.hello["device"], "sim")


class CommandTests(DaemonTestCase):
    """Commands: modes, controllers, streams, the lease, weights, recordings."""

    @classmethod
    def setUpClass(cls):
        super().setUpClass()
        try:
            cls.c = Client(cls.daemon.socket, name="commander")
        except BaseException:
            super().tearDownClass()
            raise

    @classmethod
    def tearDownClass(cls):
        cls.c.close()
        super().tearDownClass()

    def setUp(self):
        c = self.c
        c.stream(1000)
        c.discard_states()
        list(c.events())  # start each test with an empty event buffer

    def tearDown(self):
        self.c.stream(0)
        self.c.discard_states()

    def wait_lease(self, c, holder, timeout=3.0):
        """Read `lease` events until one names `holder` (None: the lease is free)."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                ev = c.wait_event("lease", timeout=max(0.0, remaining))
            except OmnidTimeout:
                self.fail("no lease event with holder %r within %.1f s" % (holder, timeout))
            if ev["holder"] == holder:
                return ev

    def settle(self, c):
        """A known start whatever earlier tests did to the arm: blend onto the reference
        centre (track `hold`) with PD, which is stable from any pose (the pre-tuned nnidc is
        not, from poses far outside those it was tuned on: it can trip the speed limit there),
        wait until the arm is still, then hand over to nnidc."""
        c.controller("pd")
        c.track("hold")
        try:
            self.wait_for(c, lambda s: s.mode == "track", "mode track (blended)", timeout=5.0)
        except AssertionError:
            trips = [e.get("message") for e in c.events() if e.get("event") == "safety-trip"]
            raise AssertionError("settling failed; safety trips: %r" % trips)
        c.controller("nnidc")
        return self.wait_for(
            c,
            lambda s: s.mode == "track"
            and s.controller == "nnidc"
            and max(map(abs, s.qd)) < 0.05
            and not s.flags & 16,
            "the arm still at the centre pose under nnidc",
            timeout=5.0,
        )

    def test_modes_show_in_the_stream(self):
        c = self.c
        c.idle()
        self.wait_for(c, lambda s: s.mode == "idle", "mode idle")
        list(c.events())
        self.assertEqual(c.hold(), "hold")
        s = self.wait_for(c, lambda s: s.mode == "hold" and s.amps, "mode hold, amps on")
        self.assertEqual(c.wait_event("mode", timeout=2.0)["mode"], "hold")
        self.assertEqual(c.track("sine"), "track")
        self.wait_for(c, lambda s: s.mode == "blend", "mode blend")
        self.wait_for(c, lambda s: s.mode == "track", "mode track", timeout=5.0)
        self.assertEqual(c.free(), "free")
        self.wait_for(c, lambda s: s.mode == "free", "mode free")
        self.assertEqual(c.idle(), "idle")
        s = self.wait_for(c, lambda s: s.mode == "idle", "mode idle")
        self.wait_for(c, lambda s: not s.amps, "amplifiers off")
        modes = [e["mode"] for e in c.events() if e.get("event") == "mode"]
        self.assertEqual(modes, ["blend", "free", "idle"])
        with self.assertRaises(RefusedError) as cm:
            c.mode("fly")
        self.assertIn("unknown mode", cm.exception.message)
        with self.assertRaises(RefusedError) as cm:
            c.track("zigzag")
        self.assertIn("zigzag", cm.exception.message)
        with self.assertRaises(RefusedError):
            c.mode("servo_jp")

    def test_tip_position_matches_the_forward_kinematics(self):
        c = self.c
        c.track("multisine")
        q1 = []
        deadline = time.monotonic() + 0.6
        n = 0
        while time.monotonic() < deadline:
            s = c.next_state(timeout=2.0)
            n += 1
            q1.append(s.q[0])
            expected = tip_mm(s.q)
            for axis in range(3):
                self.assertAlmostEqual(s.tip_mm[axis], expected[axis], delta=1e-6, msg=str(s))
        self.assertGreater(n, 300)
        self.assertGreater(max(q1) - min(q1), 0.005, "the arm should move while tracking")
        c.hold()

    def test_controller_switch_shows_in_the_stream(self):
        c = self.c
        c.hold()
        self.assertEqual(c.controller("pd"), "pd")
        self.wait_for(c, lambda s: s.controller == "pd", "controller pd")
        self.assertEqual(c.wait_event("controller", timeout=2.0)["controller"], "pd")
        self.assertEqual(c.controller("nnidc"), "nnidc")
        self.wait_for(c, lambda s: s.controller == "nnidc", "controller nnidc")
        with self.assertRaises(RefusedError) as cm:
            c.controller("magic")
        self.assertIn("magic", cm.exception.message)
        self.assertEqual(c.freeze(), False)
        self.assertFalse(c.status()["identifier"]["adapt"])
        self.assertEqual(c.adapt(), True)
        self.assertTrue(c.status()["identifier"]["adapt"])

    def test_servo_jp_moves_the_arm_and_a_stale_stream_falls_back_to_hold(self):
        c = self.c
        start = self.settle(c)
        target = [start.q[0] + 0.1, start.q[1], start.q[2]]
        # One setpoint per sample (1 kHz) for a second, each answering the sample it saw.
        end = time.monotonic() + 1.0
        s = start
        sent = set()
        in_time = 0
        while time.monotonic() < end:
            prev, s = s, c.next_state(timeout=1.0)
            if s.mode == "servo_jp":
                self.assertIn(s.cmd_seq, sent, "cmd_seq must be a seq this client sent")
                # Answered state k with seq = k in time: state k + 1 shows cmd_seq = k.
                if s.seq == prev.seq + 1 and s.cmd_seq == prev.seq:
                    in_time += 1
            sent.add(c.servo_jp(target, seq=s.seq))
        self.assertEqual(s.mode, "servo_jp")
        self.assertGreater(in_time, 0, "no setpoint was applied at the next tick")
        err0 = abs(start.q[0] - target[0])
        err1 = abs(s.q[0] - target[0])
        self.assertLess(err1, 0.3 * err0, "q1 %.4f should approach %.4f from %.4f" % (s.q[0], target[0], start.q[0]))
        # Stop sending: within the time to live (20 ms) the arm falls back to hold.
        stale = c.wait_event("stream-stale", timeout=2.0)
        self.assertEqual(stale["mode"], "hold")
        self.assertIn("message", stale)
        self.wait_for(c, lambda s: s.mode == "hold", "mode hold after the stream")

    def test_servo_jf_stream_and_auto_seq(self):
        c = self.c
        self.settle(c)
        first = c.servo_jf([0.0, 0.0, 0.0], ttl_ms=200)
        s = self.wait_for(c, lambda s: s.mode == "servo_jf", "mode servo_jf")
        second = c.servo_jf([0.0, 0.0, 0.0], ttl_ms=200)
        self.assertEqual(second, first + 1)
        self.wait_for(c, lambda s: s.cmd_seq == second, "cmd_seq %d" % second)
        self.assertEqual(c.wait_event("stream-stale", timeout=3.0)["mode"], "hold")
        c.hold()

    def test_servo_cf_stream_and_bad_values(self):
        c = self.c
        self.settle(c)
        # A non-finite force never leaves the client.
        with self.assertRaises(ValueError):
            c.servo_cf([float("nan"), 0.0, 0.0])
        with self.assertRaises(ValueError):
            c.servo_cf([0.0, 0.0])
        first = c.servo_cf([0.0, 0.0, 0.0], ttl_ms=200)
        self.wait_for(c, lambda s: s.mode == "servo_cf", "mode servo_cf")
        second = c.servo_cf([0.0, 0.0, 0.0], ttl_ms=200)
        self.assertEqual(second, first + 1)
        self.wait_for(c, lambda s: s.cmd_seq == second, "cmd_seq %d" % second)
        self.assertEqual(c.wait_event("stream-stale", timeout=3.0)["mode"], "hold")
        c.hold()

    def test_effects(self):
        c = self.c
        r = c.effect(0, {"type": "damper", "damping_n_s_per_m": 1.0})
        self.assertEqual(r["slot"], 0)
        self.assertEqual(c.effect(0, None)["slot"], 0)
        with self.assertRaises(RefusedError) as cm:
            c.effect(0, {"type": "damper", "damping_n_s_per_m": -1.0})
        self.assertIn("damping_n_s_per_m", cm.exception.message)
        self.assertFalse(c.passivity(False))
        self.assertTrue(c.passivity(True))

    def test_teleop_refusals_name_the_problem(self):
        # One arm here: a pair needs a peer this daemon serves, and a scale needs a pair.
        c = self.c
        arm = c.hello["arm"]
        with self.assertRaises(RefusedError) as cm:
            c.teleop("leader", "nobody")
        self.assertIn("no arm `nobody`", cm.exception.message)
        self.assertIn(arm, cm.exception.message)
        with self.assertRaises(RefusedError) as cm:
            c.teleop("leader", arm)
        self.assertIn("its own follower", cm.exception.message)
        with self.assertRaises(RefusedError) as cm:
            c.teleop("boss", "nobody")
        self.assertIn("leader or follower", cm.exception.message)
        with self.assertRaises(RefusedError) as cm:
            c.teleop_scale(0.5)
        self.assertIn("not in a pair", cm.exception.message)
        self.assertIsNone(c.teleop_stop())
        # Every state carries the force estimate; `teleop` only while in a pair.
        s = c.latest_state()
        self.assertEqual(len(s.fext), 3)
        self.assertTrue(all(math.isfinite(v) for v in s.fext), s.fext)
        self.assertIsNone(s.teleop)

    def test_lease(self):
        c = self.c
        holder = c.take_lease()
        self.assertEqual(holder, c.client_id)
        with Client(self.daemon.socket, name="second") as c2:
            with self.assertRaises(RefusedError) as cm:
                c2.hold()
            self.assertIn("lease", cm.exception.message)
            self.assertIn("client %d" % c.client_id, cm.exception.message)
            self.assertIn("commander", cm.exception.message)
            with self.assertRaises(RefusedError):
                c2.take_lease()
            # Reading is never refused.
            lease = c2.status()["lease"]
            self.assertEqual(lease["client"], c.client_id)
            self.assertEqual(lease["pid"], os.getpid())
            # A refused stream command is raised by the next one.
            deadline = time.monotonic() + 2.0
            with self.assertRaises(RefusedError) as cm:
                while time.monotonic() < deadline:
                    c2.servo_jp([0.0, 0.5, 0.3])
                    c2.next_event(timeout=0.01)
            self.assertIn("lease", cm.exception.message)
            # Free the lease: the second client may now command, and the first may not.
            c.release()
            self.wait_lease(c2, None)
            self.assertEqual(c2.hold(), "hold")
            self.assertEqual(c2.status()["lease"]["client"], c2.client_id)
            with self.assertRaises(RefusedError) as cm:
                c.hold()
            self.assertIn("client %d" % c2.client_id, cm.exception.message)
            c2.release()
        self.assertEqual(c.take_lease(), c.client_id)

    def test_lease_is_freed_when_its_holder_disconnects(self):
        c = self.c
        c.take_lease()
        c.release()
        c2 = Client(self.daemon.socket, name="leaver")
        c2.hold()
        self.wait_lease(c, c2.client_id)
        with self.assertRaises(RefusedError):
            c.hold()
        c2.close()
        self.wait_lease(c, None)
        self.assertEqual(c.hold(), "hold")

    def test_weights_round_trip(self):
        c = self.c
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "weights.json")
            self.assertEqual(c.save_weights(path), path)
            with open(path) as f:
                saved = json.load(f)
            self.assertTrue(saved)
            self.assertEqual(c.load_weights(path), path)
            ev = c.wait_event("weights", timeout=2.0)
            self.assertIn(path, ev["message"])
            with self.assertRaises(RefusedError):
                c.load_weights(os.path.join(d, "missing.json"))
            garbage = os.path.join(d, "garbage.json")
            with open(garbage, "w") as f:
                f.write("{\"not\": \"weights\"}")
            with self.assertRaises(RefusedError):
                c.load_weights(garbage)

    def test_recording_writes_a_csv(self):
        c = self.c
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "rec.csv")
            self.assertEqual(c.record_start(path), path)
            self.assertEqual(c.status()["recording"]["path"], path)
            with self.assertRaises(RefusedError) as cm:
                c.record_start(os.path.join(d, "other.csv"))
            self.assertIn("already recording", cm.exception.message)
            first = c.next_state(timeout=2.0)
            self.wait_for(c, lambda s: s.seq >= first.seq + 100, "100 more ticks")
            result = c.record_stop()
            self.assertEqual(result["path"], path)
            self.assertIsNone(result["error"])
            self.assertGreaterEqual(result["rows"], 100)
            with open(path) as f:
                lines = f.read().splitlines()
            self.assertTrue(lines[0].startswith("t,q1,q2,q3,tau1,tau2,tau3"), lines[0])
            self.assertEqual(len(lines) - 1, result["rows"])
            with self.assertRaises(RefusedError) as cm:
                c.record_stop()
            self.assertIn("not recording", cm.exception.message)
        # Without a path, the recording goes to the state directory.
        default = c.record_start()
        self.assertTrue(
            default.startswith(os.path.join(self.daemon.state_dir, "recordings")), default
        )
        self.assertEqual(c.record_stop()["path"], default)
        self.assertTrue(os.path.exists(default))


class RefusedConnectionTests(DaemonTestCase):
    config = "[serve]\nmax_clients = 1\n"

    def test_a_refused_connection_raises_with_the_daemons_reason(self):
        # The readiness probe's slot frees as soon as the daemon sees it close.
        deadline = time.monotonic() + 5.0
        while True:
            try:
                first = self.connect("the-only-one")
                break
            except RefusedError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.02)
        # Root and the daemon's own user (these tests) have 8 slots more: the one who can
        # stop the arm always gets in.
        kept = [self.connect("kept %d" % k) for k in range(8)]
        with self.assertRaises(RefusedError) as cm:
            Client(self.daemon.socket, name="one-too-many")
        self.assertIn("too many clients", cm.exception.message)
        self.assertEqual(cm.exception.op, "connect")
        self.assertEqual(first.status()["clients"], 1 + len(kept))


class ShutdownTests(DaemonTestCase):
    def test_shutdown_ends_the_daemon_and_removes_the_socket(self):
        d = self.daemon
        watcher = self.connect("watcher")
        watcher.stream(100)
        watcher.next_state(timeout=2.0)
        c = self.connect("stopper")
        bye = c.shutdown(timeout=10.0)
        self.assertTrue(bye, "the daemon should say bye")
        self.assertTrue(c.closed)
        with self.assertRaises(ConnectionClosedError):
            c.status()
        # Every other client is told too: its reads end with ConnectionClosedError.
        with self.assertRaises(ConnectionClosedError) as cm:
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                watcher.next_message(timeout=10.0)
        self.assertIn("stopping", str(cm.exception))
        self.assertEqual(watcher.bye, bye)
        try:
            code = d.proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self.fail("omnid serve still runs after shutdown:\n" + d.log())
        self.assertEqual(code, 0, d.log())
        self.assertFalse(os.path.exists(d.socket), "the socket should be removed")
        self.assertIn("shut down by a client", d.log())


class ArmTests(unittest.TestCase):
    """Two arms in one daemon, each picked by name or by alias (Client(arm=...))."""

    def test_each_arm_by_name_and_by_alias(self):
        if not OMNID_BIN:
            self.skipTest(NEEDS_DAEMON)
        d = tempfile.mkdtemp(prefix="omnid-arms-")
        self.addCleanup(shutil.rmtree, d, True)
        left, right = "left-%d" % os.getpid(), "right-%d" % os.getpid()
        config = os.path.join(d, "omnid.toml")
        with open(config, "w") as f:
            f.write('[[arm]]\nname = "%s"\naliases = ["PHANToM 1"]\n'
                    '[[arm]]\nname = "%s"\naliases = ["PHANToM 2"]\n' % (left, right))
        env = dict(os.environ, XDG_RUNTIME_DIR=d, OMNID_STATE_DIR=os.path.join(d, "state"))
        env.pop("OMNID_SOCKET", None)
        env.pop("RUNTIME_DIRECTORY", None)
        proc = subprocess.Popen([OMNID_BIN, "serve", "--config", config], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        self.addCleanup(proc.wait)
        self.addCleanup(proc.terminate)
        with mock.patch.dict(os.environ, env, clear=True):
            deadline = time.monotonic() + 30
            while not all(os.path.exists(os.path.join(d, "omnid", n + ".sock"))
                          for n in (left, right)):
                self.assertLess(time.monotonic(), deadline, "the arms' sockets never appeared")
                time.sleep(0.05)
            for asked, arm in ((left, left), (right, right), ("PHANToM 1", left),
                               ("PHANToM 2", right)):
                with Client(arm=asked, name="arm test") as c:
                    self.assertEqual(c.hello["arm"], arm)
                    c.stream(100)
                    self.assertGreaterEqual(c.next_state(timeout=5.0).seq, 0)
            with self.assertRaises(SocketNotFoundError) as cm:
                find_arm_socket("nobody")
            self.assertIn(left, str(cm.exception))


class FindSocketTests(unittest.TestCase):
    """Socket discovery (no daemon needed)."""

    def setUp(self):
        self.dir = tempfile.mkdtemp(prefix="omnid-find-")
        self.addCleanup(shutil.rmtree, self.dir, True)

    def touch(self, *parts):
        path = os.path.join(self.dir, *parts)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        open(path, "w").close()
        return path

    def test_environment_variable_wins(self):
        with mock.patch.dict(os.environ, {"OMNID_SOCKET": "/somewhere/x.sock"}):
            self.assertEqual(find_socket(), "/somewhere/x.sock")

    def test_the_only_socket_in_the_first_directory_that_has_one(self):
        runtime = os.path.join(self.dir, "runtime")
        os.makedirs(runtime)
        xdg_sock = self.touch("xdg", "omnid", "usb.sock")
        self.touch("xdg", "omnid", "usb.sock.lock")
        env = {"OMNID_SOCKET": "", "RUNTIME_DIRECTORY": runtime,
               "XDG_RUNTIME_DIR": os.path.join(self.dir, "xdg")}
        with mock.patch.dict(os.environ, env):
            self.assertEqual(find_socket(), xdg_sock)
            runtime_sock = self.touch("runtime", "sim.sock")
            self.assertEqual(find_socket(), runtime_sock)

    def test_several_sockets_are_listed(self):
        a = self.touch("rt", "a.sock")
        b = self.touch("rt", "b.sock")
        env = {"OMNID_SOCKET": "", "RUNTIME_DIRECTORY": os.path.join(self.dir, "rt")}
        with mock.patch.dict(os.environ, env):
            with self.assertRaises(SocketNotFoundError) as cm:
                find_socket()
        # The arms are named (by their sockets' names), with the directory and how to choose.
        message = str(cm.exception)
        self.assertIn(os.path.dirname(a), message)
        self.assertIn("a, b", message)
        self.assertIn("Client(arm=", message)
        self.assertNotIn(os.path.basename(b) + ",", message)

    def test_no_socket_lists_the_directories_searched(self):
        if os.path.isdir("/run/omnid"):
            self.skipTest("/run/omnid exists on this machine")
        env = {"OMNID_SOCKET": "", "RUNTIME_DIRECTORY": os.path.join(self.dir, "none"),
               "XDG_RUNTIME_DIR": self.dir}
        with mock.patch.dict(os.environ, env):
            with self.assertRaises(SocketNotFoundError) as cm:
                find_socket()
            with self.assertRaises(SocketNotFoundError):
                Client()
        msg = str(cm.exception)
        for d in (os.path.join(self.dir, "none"), os.path.join(self.dir, "omnid"), "/run/omnid"):
            self.assertIn(d, msg)
        self.assertIsInstance(cm.exception, FileNotFoundError)

    def test_a_missing_socket_is_a_clear_connect_error(self):
        with self.assertRaises(omnid_client.ConnectError) as cm:
            Client(os.path.join(self.dir, "absent.sock"))
        self.assertIn("absent.sock", str(cm.exception))

    def test_state_ignores_unknown_keys(self):
        s = State.from_message({
            "type": "state", "seq": 5, "t": 0.005, "q": [0.1, 0.2, 0.3], "qd": [0, 0, 0],
            "tip_mm": [1, 2, 3], "buttons": [True, False], "inkwell": True,
            "tau": [0, 0, 0], "tau_hat": [0, 0, 0], "controller": "pd", "mode": "hold",
            "amps": True, "flags": 32, "cmd_seq": 4, "future_key": {"x": 1},
        })
        self.assertEqual(s.seq, 5)
        self.assertEqual(s.q, (0.1, 0.2, 0.3))
        self.assertEqual(s.buttons, (True, False))
        self.assertEqual(s.cmd_seq, 4)


if __name__ == "__main__":
    unittest.main()
