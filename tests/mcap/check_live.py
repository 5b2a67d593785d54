"""A headless Foxglove WebSocket viewer for omnid's live view (`omnid serve --foxglove`).

    python check_live.py URL SECONDS            # subscribe to everything, decode, count
    python check_live.py --stuck URL SECONDS    # subscribe, then never read
    python check_live.py --old URL              # offer only the old subprotocol

The first form prints one JSON line: per topic, messages received over SECONDS of the
stream's own log time, and their rate (from their log times), and the number that failed to decode against their advertised schema (every
payload is decoded with PyPI's mcap-ros2-support). The second holds a subscription without
reading for SECONDS (its queue fills on the server). The third prints the HTTP status the
server answers a client offering only `foxglove.websocket.v1`.
"""
import asyncio
import json
import struct
import sys
import time

import websockets
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

SUBPROTOCOL = "foxglove.sdk.v1"


def decoder_for(ch):
    schema = Schema(id=ch["id"], name=ch["schemaName"],
                    encoding=ch.get("schemaEncoding", "ros2msg"), data=ch["schema"].encode())
    return DecoderFactory().decoder_for(ch["encoding"], schema)


async def subscribe_all(ws):
    """Read until the advertisement; subscribe to every channel. {subscription: channel}."""
    while True:
        m = await asyncio.wait_for(ws.recv(), 10)
        if isinstance(m, str):
            j = json.loads(m)
            if j.get("op") == "advertise":
                subs = {i + 1: ch for i, ch in enumerate(j["channels"])}
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": sid, "channelId": ch["id"]} for sid, ch in subs.items()]}))
                return subs


async def watch(url, secs):
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
        subs = await subscribe_all(ws)
        decoders = {sid: decoder_for(ch) for sid, ch in subs.items()}
        count, bad, first, last = {}, {}, {}, {}
        # `secs` of the daemon's time (the messages' log times), not of this script's: on a
        # loaded machine this decoder falls behind the stream, and a wall-clock window would
        # then see less than `secs` of it. The wall clock only bounds a stream that stalls.
        start = None
        give_up = time.monotonic() + 6 * secs
        while time.monotonic() < give_up:
            try:
                m = await asyncio.wait_for(ws.recv(), max(0.01, give_up - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if isinstance(m, str) or m[0] != 0x01:  # 0x01: message data
                continue
            sid, log_time = struct.unpack_from("<IQ", m, 1)
            start = log_time if start is None else start
            if (log_time - start) / 1e9 >= secs:
                break
            topic = subs[sid]["topic"]
            count[topic] = count.get(topic, 0) + 1
            first.setdefault(topic, log_time)
            last[topic] = log_time
            try:
                decoders[sid](bytes(m[13:]))
            except Exception:
                bad[topic] = bad.get(topic, 0) + 1
        out = {}
        for sid, ch in subs.items():
            t = ch["topic"]
            n = count.get(t, 0)
            span = (last.get(t, 0) - first.get(t, 0)) / 1e9
            out[t] = {"messages": n, "hz": (n - 1) / span if span > 0 else 0.0,
                      "undecodable": bad.get(t, 0), "type": ch["schemaName"],
                      "encoding": ch["encoding"]}
        print(json.dumps(out))


def stuck(url, secs):
    """A viewer that subscribes to everything and then never reads its socket again: a plain
    socket, so nothing (no library's background reader) drains it."""
    import os
    import socket
    host, port = url.removeprefix("ws://").rstrip("/").rsplit(":", 1)
    s = socket.create_connection((host, int(port)))
    s.sendall((f"GET / HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: b21uaWQtc3R1Y2stdmlldw==\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n").encode())
    f = s.makefile("rb")
    while f.readline() not in (b"\r\n", b""):
        pass

    def frame():
        b0, b1 = f.read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", f.read(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", f.read(8))[0]
        return b0 & 0x0F, f.read(n)

    while True:
        op, payload = frame()
        if op == 1 and json.loads(payload).get("op") == "advertise":
            channels = json.loads(payload)["channels"]
            break
    text = json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i + 1, "channelId": ch["id"]} for i, ch in enumerate(channels)]}).encode()
    mask = os.urandom(4)
    head = bytes([0x81]) + (bytes([0x80 | 126]) + struct.pack(">H", len(text)) if len(text) > 125
                            else bytes([0x80 | len(text)]))
    s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(text)))
    print("subscribed", flush=True)
    time.sleep(secs)


async def old(url):
    try:
        async with websockets.connect(url, subprotocols=["foxglove.websocket.v1"]):
            print(json.dumps({"status": 101}))
    except websockets.exceptions.InvalidStatus as e:
        print(json.dumps({"status": e.response.status_code}))


if __name__ == "__main__":
    if sys.argv[1] == "--stuck":
        stuck(sys.argv[2], float(sys.argv[3]))
    elif sys.argv[1] == "--old":
        asyncio.run(old(sys.argv[2]))
    else:
        asyncio.run(watch(sys.argv[1], float(sys.argv[2])))
