"""A lab's authenticated zenoh, from the other side (docs/ZENOH.md, "A lab network"):
PyPI's eclipse-zenoh through omnid's Python client against `omnid serve` with
`[zenoh] users_file` and `commanders`.

    python check_auth.py ENDPOINT ARM CLIENT_DIR

Prints one JSON line: what each principal could do.
"""

import json
import sys
import time

endpoint, arm, client_dir = sys.argv[1:4]
sys.path.insert(0, client_dir)
import zenoh  # noqa: E402
import omnid_client  # noqa: E402

out = {}


def attempt(label, **kw):
    """A remote client as `kw` says: what it got (its access, or why it got nothing)."""
    try:
        c = omnid_client.Client(remote=endpoint, arm=arm, name=label, timeout=4.0, **kw)
    except omnid_client.OmnidTimeout:
        return {"hello": False, "why": "no hello"}
    except omnid_client.ConnectError as e:
        return {"hello": False, "why": "cannot connect: %s" % e}
    r = {"hello": True, "access": c.access}
    try:
        r["mode"] = c.mode("hold")
    except omnid_client.OmnidError as e:
        r["mode_error"] = str(e)
    c.close()
    return r


out["commander"] = attempt("lab", user="lab", password="lab-secret")
out["anonymous"] = attempt("anon")
out["wrong_password"] = attempt("lab-guess", user="lab", password="guess")
out["viewer"] = attempt("viewer", user="viewer", password="viewer-secret")


def reads(user, password):
    """Whether a session with these credentials receives the arm's ROS 2 state."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    s = zenoh.open(conf)
    got = []
    sub = s.declare_subscriber("**/%s/measured_js/**" % arm, lambda sample: got.append(1))
    time.sleep(2.0)
    sub.undeclare()
    s.close()
    return len(got)


out["viewer_reads"] = reads("viewer", "viewer-secret")
out["anonymous_reads"] = reads(None, None)
print(json.dumps(out))
