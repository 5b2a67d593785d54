"""pyOpenHaptics (from PyPI, unmodified) on omnid's libHD: read the stylus, then render a
spring that pulls the tip 20 mm along +x, until it gets there (tests/suite/hdapi.rs runs this with
the library on LD_LIBRARY_PATH against `omnid serve --device sim`)."""

import sys
import threading
import time

from pyOpenHaptics.hd_device import HapticDevice
import pyOpenHaptics.hd as hd
from pyOpenHaptics.hd_callback import hd_callback

STIFFNESS_N_PER_MM = 0.05
OFFSET_MM = 20.0

lock = threading.Lock()
seen = {"ticks": 0, "pos": None, "q": None, "g": None, "buttons": None, "anchor": None}


@hd_callback
def spring():
    t = hd.get_transform()
    pos = [t[3][0], t[3][1], t[3][2]]
    q = list(hd.get_joints())
    g = list(hd.get_gimbals())
    buttons = hd.get_buttons()
    with lock:
        if seen["anchor"] is None:
            seen["anchor"] = [pos[0] + OFFSET_MM, pos[1], pos[2]]
            seen["first"] = (pos, q, g, buttons)
        anchor = seen["anchor"]
        seen.update(ticks=seen["ticks"] + 1, pos=pos, q=q, g=g, buttons=buttons)
    hd.set_force([STIFFNESS_N_PER_MM * (anchor[i] - pos[i]) for i in range(3)])


def fmt(v):
    return " ".join("%.12f" % x for x in v)


def main():
    device = HapticDevice(callback=spring)
    try:
        deadline = time.monotonic() + 30.0
        reached = False
        while time.monotonic() < deadline:
            time.sleep(0.01)
            with lock:
                if seen["anchor"] is None:
                    continue
                dx = seen["anchor"][0] - seen["pos"][0]
                if abs(dx) < 2.0 and seen["ticks"] > 200:
                    reached = True
                    break
        with lock:
            pos, q, g, buttons = seen["first"]
            print("sample pos %s q %s tr %s g %s buttons %d" % (fmt(pos), fmt(q), fmt(pos), fmt(g), buttons))
            print("spring %s ticks %d dx %.3f" % ("reached" if reached else "missed", seen["ticks"],
                                                   seen["anchor"][0] - seen["pos"][0]))
    finally:
        device.close()
    print("done")
    sys.stdout.flush()
    return 0 if reached else 1


if __name__ == "__main__":
    sys.exit(main())
