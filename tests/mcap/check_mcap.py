"""Check an omnid MCAP log with readers that are not omnid's (PyPI `mcap`, `mcap-ros2-support`).

    python check_mcap.py LOG.mcap LOG.csv
    python check_mcap.py --stream LOG.mcap

The second form streams a file that may be cut short and prints, as JSON, how many
`/joint_states` messages its complete chunks hold and whether the stream ended in an error.

LOG.csv is the CSV log of the same run (a simulator run is deterministic). Checks: every record
streams with CRCs validated; the summary has statistics, the `ros2` profile and a `ros2msg`
schema on every CDR channel; every message decodes, and re-encoding it with mcap_ros2's own
serializer gives the same bytes; `/joint_states` has one message per CSV row with no log-time
gap over 2 ms; every CSV value equals the MCAP's, bit for bit. Prints one JSON line of counts;
exits 1 with a reason on the first failure.
"""
import csv
import json
import math
import struct
import sys

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message, Schema
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic


def fail(msg):
    print(f"FAIL: {msg}")
    sys.exit(1)


def same(a, b):
    """Equal bit for bit (NaN equals NaN; -0.0 differs from 0.0)."""
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return struct.pack("<d", float(a)) == struct.pack("<d", float(b))


# The CSV columns each channel carries (docs/MCAP.md).
ARRAYS = {
    "/omnid/estimate/position": "qf",
    "/omnid/estimate/acceleration": "qdd",
    "/omnid/reference/position": "ref",
    "/omnid/torque/controller": "tau_cmd",
    "/omnid/torque/predicted": "tau_hat",
    "/omnid/torque/model": "tau_model",
    "/omnid/torque/external": "tau_ext",
    "/omnid/tip/position_mm": "tip",
}
WRENCHES = {
    "/omnid/tip/force": "fcmd",
    "/omnid/hand/force": "fhand",
    "/omnid/external/force": "fext",
}


def main(mcap_path, csv_path):
    with open(mcap_path, "rb") as f:
        records = list(StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True).records)
    schemas = {r.id: r for r in records if isinstance(r, Schema)}
    channels = {r.id: r for r in records if isinstance(r, Channel)}
    messages = [r for r in records if isinstance(r, Message)]

    with open(mcap_path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
    if header.profile != "ros2":
        fail(f"profile {header.profile!r}")
    if summary is None or summary.statistics is None:
        fail("no statistics in the summary")
    if summary.statistics.message_count != len(messages):
        fail(f"statistics count {summary.statistics.message_count} != {len(messages)} streamed")
    decoders, encoders = {}, {}
    for cid, ch in channels.items():
        s = schemas.get(ch.schema_id)
        if ch.message_encoding != "cdr" or s is None or s.encoding != "ros2msg":
            fail(f"channel {ch.topic}: {ch.message_encoding} / {s and s.encoding}")
        text = s.data.decode()
        dec, enc = generate_dynamic(s.name, text), serialize_dynamic(s.name, text)
        key = s.name if s.name in dec else s.name.replace("/msg/", "/")
        decoders[cid], encoders[cid] = dec[key], enc[key]

    rows = []
    row = {}
    carried = {}
    last_js_time = None
    max_gap = 0
    for m in messages:
        msg = decoders[m.channel_id](m.data)
        again = encoders[m.channel_id](msg)
        if bytes(again) != bytes(m.data):
            fail(f"{channels[m.channel_id].topic}: re-encoded bytes differ")
        topic = channels[m.channel_id].topic
        if topic == "/omnid/time":
            row = {"t": msg.data}
        elif topic in ARRAYS:
            for j, v in enumerate(msg.data):
                row[f"{ARRAYS[topic]}{j + 1}"] = v
        elif topic in WRENCHES:
            f = msg.wrench.force
            for j, v in enumerate((f.x, f.y, f.z)):
                row[f"{WRENCHES[topic]}{j + 1}"] = v
        elif topic == "/omnid/encoders":
            for j, v in enumerate(msg.data):
                row[f"enc{j + 1}"] = v
        elif topic == "/omnid/mode":
            carried["mode"] = msg.data
        elif topic == "/omnid/amplifiers":
            carried["amps"] = 1 if msg.data else 0
        elif topic == "/omnid/safety/flags":
            carried["flags"] = msg.data
        elif topic == "/omnid/buttons":
            for name, v in zip(("button1", "button2", "inkwell"), msg.buttons):
                carried[name] = v
        elif topic == "/joint_states":
            if list(msg.name) != ["joint1", "joint2", "joint3"]:
                fail(f"joint names {msg.name}")
            for j in range(3):
                row[f"q{j + 1}"] = msg.position[j]
                row[f"qd{j + 1}"] = msg.velocity[j]
                row[f"tau{j + 1}"] = msg.effort[j]
            row.update(carried)
            rows.append(row)
            if last_js_time is not None:
                max_gap = max(max_gap, m.log_time - last_js_time)
            last_js_time = m.log_time

    with open(csv_path, newline="") as f:
        table = list(csv.DictReader(f))
    if len(table) != len(rows):
        fail(f"{len(rows)} /joint_states messages, {len(table)} CSV rows")
    if max_gap > 2_000_000:
        fail(f"largest /joint_states gap {max_gap} ns")
    values = 0
    for i, (want, got) in enumerate(zip(table, rows)):
        for col, text in want.items():
            if col not in got:
                fail(f"row {i + 1}: no {col} in the MCAP")
            v = got[col]
            if col == "mode":
                ok = v == text
            elif col in ("amps", "flags", "button1", "button2", "inkwell") or col.startswith("enc"):
                ok = int(text) == int(v)
            else:
                ok = same(float(text), v)
            if not ok:
                fail(f"row {i + 1} column {col}: CSV {text}, MCAP {v!r}")
            values += 1
    topics = sorted({c.topic for c in channels.values()})
    print(json.dumps({"messages": len(messages), "rows": len(rows), "values": values,
                      "max_gap_ns": max_gap, "topics": topics}))


def stream(mcap_path):
    topics, n, error = {}, 0, None
    with open(mcap_path, "rb") as f:
        try:
            for r in StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True).records:
                if isinstance(r, Channel):
                    topics[r.id] = r.topic
                elif isinstance(r, Message) and topics.get(r.channel_id) == "/joint_states":
                    n += 1
        except Exception as e:  # the cut: whatever the reader raises there
            error = type(e).__name__
    print(json.dumps({"joint_states": n, "error": error}))


if __name__ == "__main__":
    if sys.argv[1] == "--stream":
        stream(sys.argv[2])
    else:
        main(sys.argv[1], sys.argv[2])
