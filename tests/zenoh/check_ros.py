"""An independent ROS 2-over-zenoh peer for tests/suite/zenoh_peers.rs: PyPI's eclipse-zenoh, rosbags and
xxhash, nothing of omnid's but its stdlib socket client (to compare with the socket's stream).

    check_ros.py MODE ENDPOINT ARM SOCKET CLIENT_DIR

MODE is `ros` (graph, data, attachments, a servo_cf push), `remote` (omnid's protocol over
zenoh with the Python client) or `hostile` (bad samples and a flood). Prints one JSON object.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import xxhash
import zenoh
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

MODE, ENDPOINT, ARM, SOCKET, CLIENT_DIR = sys.argv[1:6]
sys.path.insert(0, CLIENT_DIR)
import omnid_client  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)
TS.register(
    get_types_from_msg(
        "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
        "crtk_msgs/msg/OperatingState",
    )
)
TS.register(
    get_types_from_msg("std_msgs/Header header\nstring string\n", "crtk_msgs/msg/StringStamped")
)


def session():
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([ENDPOINT]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def tokens(s):
    out = []
    for r in s.liveliness().get("@ros2_lv/**", timeout=3.0):
        if r.ok is not None:
            out.append(str(r.ok.key_expr))
    return out


def parse(token):
    """As rmw_zenoh's graph cache reads a token: '%' back to '/'."""
    p = token.split("/")
    d = {
        "domain": int(p[1]),
        "zid": p[2],
        "nid": int(p[3]),
        "eid": int(p[4]),
        "kind": p[5],
        "enclave": p[6].replace("%", "/"),
        "namespace": p[7].replace("%", "/"),
        "node": p[8].replace("%", "/"),
    }
    if len(p) >= 13:
        d.update(
            topic=p[9].replace("%", "/"),
            dds_type=p[10].replace("%", "/"),
            hash=p[11].replace("%", "/"),
            qos=p[12],
        )
    return d


def ros_name(dds):
    pkg, _msg, _dds, ty = dds.split("::")
    return "%s/msg/%s" % (pkg, ty[:-1])


def gid(token):
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def key_of(t):
    return "%d/%s/%s/%s" % (t["domain"], t["topic"].strip("/"), t["dds_type"], t["hash"])


def find(toks, kind, leaf):
    for tok in toks:
        t = parse(tok)
        if t["kind"] == kind and t.get("topic") == "/%s/%s" % (ARM, leaf):
            return tok, t
    raise SystemExit("no %s token for /%s/%s among %d tokens" % (kind, ARM, leaf, len(toks)))


def socket_states(seconds, out, started):
    with omnid_client.Client(SOCKET, name="compare") as c:
        c.stream(1000)
        started.set()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            st = c.next_state(timeout=1.0)
            out.append(st)


def ros():
    s = session()
    time.sleep(0.5)
    toks = tokens(s)
    res = {"tokens": len(toks)}
    nodes = [parse(t) for t in toks if parse(t)["kind"] == "NN"]
    res["node"] = [n["node"] for n in nodes]
    js_tok, js = find(toks, "MP", "measured_js")
    res["js_hash_ok"] = js["hash"] == TS.hash_rihs01(ros_name(js["dds_type"]))
    hashes = {}
    for kind, leaf in [
        ("MP", "measured_cp"),
        ("MP", "measured_cv"),
        ("MP", "operating_state"),
        ("MP", "button1"),
        ("MP", "button2"),
        ("MS", "servo_cf"),
        ("MS", "servo_jp"),
        ("MS", "state_command"),
    ]:
        _, t = find(toks, kind, leaf)
        hashes[leaf] = t["hash"] == TS.hash_rihs01(ros_name(t["dds_type"]))
    res["hashes_ok"] = hashes
    res["js_qos"] = js["qos"]

    # measured_js for 5 s, beside the socket's stream.
    samples = []
    sub = s.declare_subscriber(
        key_of(js),
        lambda smp: samples.append(
            (
                bytes(smp.payload.to_bytes()),
                bytes(smp.attachment.to_bytes()) if smp.attachment is not None else b"",
                time.time_ns(),
            )
        ),
    )
    time.sleep(0.3)
    samples.clear()
    states = []
    started = threading.Event()
    th = threading.Thread(target=socket_states, args=(5.5, states, started))
    th.start()
    started.wait(5)
    samples.clear()
    t0 = time.monotonic()
    time.sleep(5.0)
    got = list(samples)
    dt = time.monotonic() - t0
    th.join()
    sub.undeclare()
    res["rate_hz"] = len(got) / dt
    want_gid = gid(js_tok)
    seqs, bad_att, bad_ts, positions = [], 0, 0, set()
    efforts = []
    for payload, att, recv_ns in got:
        if len(att) != 33 or att[16] != 16 or att[17:] != want_gid:
            bad_att += 1
            continue
        seqs.append(int.from_bytes(att[:8], "little", signed=True))
        ts = int.from_bytes(att[8:16], "little", signed=True)
        if abs(ts - recv_ns) > 2_000_000_000:
            bad_ts += 1
        m = TS.deserialize_cdr(payload, "sensor_msgs/msg/JointState")
        positions.add(tuple(float(x) for x in m.position))
        efforts.append(list(m.effort))
    res["bad_attachments"] = bad_att
    res["bad_timestamps"] = bad_ts
    res["seq_gaps"] = sum(1 for a, b in zip(seqs, seqs[1:]) if b != a + 1)
    res["seq_first"] = seqs[0] if seqs else None
    # Every socket state inside the window has its exact joint angles among the ROS samples.
    inside = [st for st in states]
    matched = sum(1 for st in inside if tuple(st.q) in positions)
    res["socket_states"] = len(inside)
    res["socket_matched"] = matched

    # The other topics arrive and decode.
    decoded = {}
    for leaf, ty in [
        ("measured_cp", "geometry_msgs/msg/PoseStamped"),
        ("measured_cv", "geometry_msgs/msg/TwistStamped"),
        ("operating_state", "crtk_msgs/msg/OperatingState"),
    ]:
        _, t = find(toks, "MP", leaf)
        box = []
        sb = s.declare_subscriber(key_of(t), lambda smp, box=box: box.append(bytes(smp.payload.to_bytes())))
        deadline = time.monotonic() + 3
        while not box and time.monotonic() < deadline:
            time.sleep(0.05)
        sb.undeclare()
        if box:
            m = TS.deserialize_cdr(box[0], ty)
            decoded[leaf] = getattr(m, "state", None) or True
        else:
            decoded[leaf] = False
    res["decoded"] = decoded

    # servo_cf in ROS form pushes the arm up (+y); the socket sees the mode.
    _, cf = find(toks, "MS", "servo_cf")
    Wrench = TS.types["geometry_msgs/msg/WrenchStamped"]
    Header = TS.types["std_msgs/msg/Header"]
    Time = TS.types["builtin_interfaces/msg/Time"]
    Vector3 = TS.types["geometry_msgs/msg/Vector3"]
    W = TS.types["geometry_msgs/msg/Wrench"]
    pub = s.declare_publisher(key_of(cf))
    with omnid_client.Client(SOCKET, name="watch") as c:
        c.stream(1000)
        before = c.latest_state()
        modes = set()
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            now = time.time_ns()
            msg = Wrench(
                header=Header(stamp=Time(sec=now // 10**9, nanosec=now % 10**9), frame_id=""),
                wrench=W(force=Vector3(x=0.0, y=0.6, z=0.0), torque=Vector3(x=0.0, y=0.0, z=0.0)),
            )
            pub.put(bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/WrenchStamped")))
            time.sleep(0.002)
            during = c.latest_state()
            modes.add(during.mode)
        res["push_modes"] = sorted(modes)
        # The motors push: the commanded torque moved by Jᵀ F (the docked stylus may not move).
        res["push_dtau_nm"] = max(abs(a - b) for a, b in zip(during.tau, before.tau))
        time.sleep(1.6)
        st = c.latest_state()
        res["mode_after"] = st.mode
        res["lease_after"] = c.status().get("lease")
    pub.undeclare()
    s.close()
    return res


def remote():
    res = {}
    with omnid_client.Client(remote=ENDPOINT, arm=ARM, name="far") as c:
        res["access"] = c.access
        res["rate"] = c.stream(100)
        n = 0
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            c.next_state(timeout=1.0)
            n += 1
        res["states_1s"] = n
        res["holder"] = c.take_lease() == c.client_id
        modes = set()
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            c.servo_cf([0.0, 0.3, 0.0], ttl_ms=100)
            modes.add(c.next_state(timeout=1.0).mode)
        res["modes"] = sorted(modes)
        res["status_zenoh"] = c.status().get("zenoh")
    # A remote commander killed mid-stream: the socket sees its command end within its time to
    # live, and its lease freed once zenoh notices the session is gone.
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys,time; sys.path.insert(0, %r); import omnid_client as o\n"
            "c = o.Client(remote=%r, arm=%r, name='doomed')\n"
            "c.take_lease(); print('ready', flush=True)\n"
            "while True:\n    c.servo_cf([0.0, 0.3, 0.0], ttl_ms=50); time.sleep(0.005)\n"
            % (CLIENT_DIR, ENDPOINT, ARM),
        ],
        stdout=subprocess.PIPE,
    )
    assert child.stdout.readline().strip() == b"ready"
    with omnid_client.Client(SOCKET, name="watch") as w:
        w.stream(1000)
        deadline = time.monotonic() + 3
        while w.latest_state().mode != "servo_cf" and time.monotonic() < deadline:
            pass
        res["doomed_mode"] = w.latest_state().mode
        os.kill(child.pid, signal.SIGKILL)
        killed = time.monotonic()
        child.wait()
        while w.next_state(timeout=1.0).mode == "servo_cf":
            pass
        res["command_gone_ms"] = (time.monotonic() - killed) * 1e3
        lease_gone = None
        while time.monotonic() - killed < 30:
            if w.status().get("lease") is None:
                lease_gone = time.monotonic() - killed
                break
            time.sleep(0.1)
        res["lease_gone_s"] = lease_gone
    return res


def hostile():
    s = session()
    time.sleep(0.5)
    toks = tokens(s)
    _, cf = find(toks, "MS", "servo_cf")
    pub = s.declare_publisher(key_of(cf))
    good = TS.types["geometry_msgs/msg/WrenchStamped"]
    Header = TS.types["std_msgs/msg/Header"]
    Time = TS.types["builtin_interfaces/msg/Time"]
    V = TS.types["geometry_msgs/msg/Vector3"]
    W = TS.types["geometry_msgs/msg/Wrench"]
    nan = bytes(
        TS.serialize_cdr(
            good(
                header=Header(stamp=Time(sec=1, nanosec=0), frame_id=""),
                wrench=W(force=V(x=float("nan"), y=0.0, z=0.0), torque=V(x=0.0, y=0.0, z=0.0)),
            ),
            "geometry_msgs/msg/WrenchStamped",
        )
    )
    bad = [nan[:20], b"\x00\x01\x00\x00" + b"\xff" * 9, nan, b"", b"\x07" * (10 * 1024 * 1024)]
    for b in bad:
        pub.put(b)
    flood = s.declare_publisher("omnid/%s/in/flood" % ARM)
    for i in range(20000):
        flood.put(b'{"op":"status","id":%d}' % i)
    time.sleep(1.0)
    res = {"sent_bad": len(bad), "flood": 20000}
    with omnid_client.Client(SOCKET, name="after") as c:
        c.stream(1000)
        n = 0
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            c.next_state(timeout=1.0)
            n += 1
        res["states_after"] = n
        st = c.status()
        res["zenoh"] = st.get("zenoh")
        res["mode"] = st.get("mode")
    s.close()
    return res


print(json.dumps({"ros": ros, "remote": remote, "hostile": hostile}[MODE]()))
