"""A client of ``omnid serve``, the Phantom Omni daemon (Python standard library only).

``omnid serve`` holds one haptic device and serves programs on the same machine over a
Unix ``SOCK_SEQPACKET`` socket, one JSON object per message; ``docs/PROTOCOL.md`` in the
omnid repository is the contract this module implements (protocol version 1). This file is
self-contained: copy it next to your script, or put its directory on ``PYTHONPATH``.

Print the stylus tip position about ten times a second until Ctrl-C::

    from omnid_client import Client

    with Client(name="tip-printer") as omni:
        omni.stream(10)                      # 10 samples per second
        for s in omni.states():
            print("tip %7.1f %7.1f %7.1f mm" % tuple(s.tip_mm))

(``python3 omnid_client.py`` runs exactly that.)

Overview
--------
- :func:`find_socket` finds the daemon's socket as ``omnid watch`` does: ``$OMNID_SOCKET``,
  else the only ``*.sock`` in ``$RUNTIME_DIRECTORY``, ``$XDG_RUNTIME_DIR/omnid``,
  ``/run/omnid``.
- :class:`Client` connects and says hello (``client.hello`` is the daemon's answer);
  :meth:`Client.request` sends any request and waits for its reply; named methods wrap each
  request of the protocol (:meth:`~Client.status`, :meth:`~Client.stream`,
  :meth:`~Client.hold`, :meth:`~Client.servo_jp`, ...).
- Incoming messages are sorted as they are read into two bounded buffers: state samples
  (read with :meth:`~Client.next_state`, :meth:`~Client.states`,
  :meth:`~Client.latest_state`) and everything else that is not a reply (events, ``lost``
  notices, refusals of stream commands; read with :meth:`~Client.next_event`,
  :meth:`~Client.events`, :meth:`~Client.wait_event`, or handed to an ``on_event`` callback
  as soon as it is read). :meth:`~Client.next_message` reads both in arrival order. Nothing
  that arrives while a request waits for its reply is lost, up to the buffers' bounds (the
  oldest state samples go first; they are counted in ``client.dropped_total``).
- Errors are :class:`OmnidError` subclasses: :class:`RefusedError` (the daemon said no; its
  message is the daemon's), :class:`ConnectionClosedError` (``bye`` or a closed socket),
  :class:`OmnidTimeout`, :class:`SocketNotFoundError`, :class:`ProtocolError`.

A client is a plain blocking object: use it from one thread at a time.
"""

import glob
import json
import math
import os
import select
import socket
import time
from collections import deque
from typing import (
    Any,
    Callable,
    Deque,
    Dict,
    Iterator,
    List,
    NamedTuple,
    Optional,
    Sequence,
    Tuple,
    Union,
)

__all__ = [
    "PROTOCOL_VERSION",
    "MAX_MESSAGE",
    "OmnidError",
    "SocketNotFoundError",
    "find_arm_socket",
    "ConnectError",
    "RefusedError",
    "ConnectionClosedError",
    "OmnidTimeout",
    "ProtocolError",
    "State",
    "Client",
    "default_socket_dirs",
    "find_socket",
]

#: The protocol version this module speaks.
PROTOCOL_VERSION = 1
# Where `omnid serve --zenoh` listens by default (loopback; docs/ZENOH.md): the next port after
# the ROS 2 router's 7447.
DEFAULT_ZENOH_PORT = 7448

#: Largest message either side may send, bytes.
MAX_MESSAGE = 64 * 1024

# Room to notice a message longer than the protocol allows (a SOCK_SEQPACKET recv with a
# smaller buffer would cut it silently).
_RECV_SIZE = 2 * MAX_MESSAGE

# Stream commands: the daemon answers them only when it refuses one.
_STREAM_OPS = ("servo_jp", "servo_jf", "servo_cf")


# --------------------------------------------------------------------------------------
# Errors


class OmnidError(Exception):
    """Base class of every error this module raises."""


class SocketNotFoundError(OmnidError, FileNotFoundError):
    """No socket path was given and none could be found (the message says where we looked)."""


class ConnectError(OmnidError, ConnectionError):
    """The socket exists (or was named) but connecting to it failed."""


class RefusedError(OmnidError):
    """The daemon refused a request (or the connection); ``message`` is its reason.

    Attributes: ``message`` (the daemon's text), ``op`` (the request it refused, or
    ``"connect"``), ``reply`` (the whole ``error`` message as a dict).
    """

    def __init__(self, message: str, op: Optional[str] = None, reply: Optional[dict] = None):
        super().__init__(message)
        self.message = message
        self.op = op
        self.reply = reply or {}

    def __str__(self) -> str:
        if self.op:
            return "%s refused: %s" % (self.op, self.message)
        return self.message


class ConnectionClosedError(OmnidError, ConnectionError):
    """The daemon said ``bye`` (it is stopping) or the connection closed.

    ``message`` is the daemon's goodbye when it sent one.
    """

    def __init__(self, message: str = "the daemon closed the connection"):
        super().__init__(message)
        self.message = message


class OmnidTimeout(OmnidError, TimeoutError):
    """Nothing (or not what was waited for) arrived in time."""


class ProtocolError(OmnidError):
    """The daemon sent something this client cannot read (not JSON, too long, ...)."""


# --------------------------------------------------------------------------------------
# State samples


_NAN3 = (math.nan, math.nan, math.nan)


class State(NamedTuple):
    """One state sample (``{"type":"state",...}``); see PROTOCOL.md, *The state stream*.

    Vectors are tuples of 3 floats (joints 1..3, or x, y, z). Keys the daemon adds in later
    versions are ignored; keys it leaves out take neutral defaults (NaN, ``False``, ``""``).
    """

    seq: int
    """Tick number since the daemon started."""
    t: float
    """Device time since the daemon started, s."""
    q: Tuple[float, float, float]
    """Joint angles, rad (OpenHaptics: j1 base yaw, j2 upper arm, j3 lower arm)."""
    qd: Tuple[float, float, float]
    """Estimated joint velocity, rad/s."""
    tip_mm: Tuple[float, float, float]
    """Stylus tip, mm (+x right, +y up, +z toward the user)."""
    buttons: Tuple[bool, bool]
    inkwell: bool
    tau: Tuple[float, float, float]
    """Torque sent to the motors, N·m."""
    tau_hat: Tuple[float, float, float]
    """The identifier's prediction of the torque that acted, N·m."""
    controller: str
    mode: str
    """idle, hold, blend, track, free, servo_jp, servo_jf, servo_cf, teleop, or stop (the last
    tick)."""
    amps: bool
    flags: int
    cmd_seq: int
    """``seq`` of the last servo_jp/servo_jf/servo_cf command applied."""
    fext: Tuple[float, float, float] = _NAN3
    """The outside's force on the tip estimated from the motors and the arm's model, N."""
    teleop: Optional[str] = None
    """This arm's side of a teleoperation pair: waiting, engaged, clutched, link_lost, down
    (None: not in a pair)."""

    @classmethod
    def from_message(cls, m: Dict[str, Any]) -> "State":
        """Build a sample from a decoded ``state`` message (unknown keys ignored)."""
        g = m.get
        return cls(
            seq=int(g("seq", 0)),
            t=float(g("t", math.nan)),
            q=tuple(g("q", _NAN3)),
            qd=tuple(g("qd", _NAN3)),
            tip_mm=tuple(g("tip_mm", _NAN3)),
            buttons=tuple(g("buttons", (False, False))),
            inkwell=bool(g("inkwell", False)),
            tau=tuple(g("tau", _NAN3)),
            tau_hat=tuple(g("tau_hat", _NAN3)),
            controller=str(g("controller", "")),
            mode=str(g("mode", "")),
            amps=bool(g("amps", False)),
            flags=int(g("flags", 0)),
            cmd_seq=int(g("cmd_seq", 0)),
            fext=tuple(g("fext", _NAN3)),
            teleop=g("teleop"),
        )


# --------------------------------------------------------------------------------------
# Finding the socket


def default_socket_dirs() -> List[str]:
    """The directories a daemon puts its socket in, in order of preference.

    ``$RUNTIME_DIRECTORY`` (systemd's ``RuntimeDirectory=``), ``$XDG_RUNTIME_DIR/omnid``,
    ``/run/omnid`` (empty variables are skipped).
    """
    dirs = []
    runtime = os.environ.get("RUNTIME_DIRECTORY")
    if runtime:
        dirs.append(runtime)
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        dirs.append(os.path.join(xdg, "omnid"))
    dirs.append("/run/omnid")
    return dirs


def find_socket() -> str:
    """The socket to connect to when none is given.

    ``$OMNID_SOCKET`` when set; else the only ``*.sock`` in the first of
    :func:`default_socket_dirs` that holds any. Raises :class:`SocketNotFoundError` naming
    the sockets when a directory holds several, or the directories searched when there is
    none.
    """
    env = os.environ.get("OMNID_SOCKET")
    if env:
        return env
    dirs = default_socket_dirs()
    for d in dirs:
        found = sorted(glob.glob(os.path.join(glob.escape(d), "*.sock")))
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            arms = [os.path.basename(f)[: -len(".sock")] for f in found]
            raise SocketNotFoundError(
                "several arms are served in %s: %s; name one with Client(arm=...) (or pass "
                "the socket's path)" % (d, ", ".join(arms))
            )
    raise SocketNotFoundError(
        "no omnid socket found in %s: is `omnid serve` running? (or pass the path, "
        "Client(path), or set OMNID_SOCKET)" % ", ".join(dirs)
    )


def find_arm_socket(arm: str) -> str:
    """The socket of the arm named ``arm`` (its name or an alias, e.g. ``"PHANToM 1"``).

    ``<dir>/<arm>.sock`` in the first of :func:`default_socket_dirs` that has it; else the
    daemon socket whose hello names the arm (``arm`` or ``aliases``). Raises
    :class:`SocketNotFoundError` naming the arms that are served.
    """
    dirs = default_socket_dirs()
    if arm and "/" not in arm and "\0" not in arm:
        for d in dirs:
            p = os.path.join(d, arm + ".sock")
            if os.path.exists(p):
                return p
    served = []
    for d in dirs:
        for p in sorted(glob.glob(os.path.join(glob.escape(d), "*.sock"))):
            try:
                with Client(p, name="python (looking for an arm)", timeout=2.0) as c:
                    hello = c.hello
            except OmnidError:
                continue
            if hello.get("arm") == arm or arm in hello.get("aliases", []):
                return p
            served.append(hello.get("arm", "?"))
    raise SocketNotFoundError(
        "no arm named %r is served in %s (arms served: %s); is `omnid serve` running with it?"
        % (arm, ", ".join(dirs), ", ".join(served) or "none")
    )


# --------------------------------------------------------------------------------------
# The client


Message = Union[State, Dict[str, Any]]


# A remote client is bound to its owner (docs/ZENOH.md, "A client is bound to its key"): at
# hello it agrees a secret with the daemon by ephemeral X25519 Diffie-Hellman through
# HKDF-SHA256, and every later request carries a counter and an HMAC-SHA256 with that secret in
# the zenoh sample's attachment, so no other peer's request is taken as this client's.

_KDF_LABEL = b"omnid remote client v1"
_MAC_LABEL = b"omnid request v1\0"
_P25519 = 2**255 - 19


def _x25519(scalar: bytes, u: bytes) -> bytes:
    """RFC 7748's X25519 function (the Montgomery ladder of its section 5), used when the
    ``cryptography`` package is not installed."""
    k = bytearray(scalar)
    k[0] &= 248
    k[31] &= 127
    k[31] |= 64
    n = int.from_bytes(bytes(k), "little")
    x1 = int.from_bytes(u, "little") & ((1 << 255) - 1)
    p = _P25519
    x2, z2, x3, z3, swap = 1, 0, x1, 1, 0
    for t in range(254, -1, -1):
        bit = (n >> t) & 1
        swap ^= bit
        if swap:
            x2, x3, z2, z3 = x3, x2, z3, z2
        swap = bit
        a, b = (x2 + z2) % p, (x2 - z2) % p
        aa, bb = a * a % p, b * b % p
        e = (aa - bb) % p
        c, d = (x3 + z3) % p, (x3 - z3) % p
        da, cb = d * a % p, c * b % p
        x3 = (da + cb) ** 2 % p
        z3 = x1 * ((da - cb) ** 2) % p
        x2 = aa * bb % p
        z2 = e * (aa + 121665 * e) % p
    if swap:
        x2, x3, z2, z3 = x3, x2, z3, z2
    return (x2 * pow(z2, p - 2, p) % p).to_bytes(32, "little")


class _KeyPair:
    """An ephemeral X25519 key pair (``cryptography``'s when installed, else :func:`_x25519`)."""

    def __init__(self) -> None:
        try:
            from cryptography.hazmat.primitives.asymmetric import x25519  # type: ignore
            from cryptography.hazmat.primitives import serialization  # type: ignore

            self._private: Any = x25519.X25519PrivateKey.generate()
            raw = serialization.Encoding.Raw, serialization.PublicFormat.Raw
            self.public = self._private.public_key().public_bytes(*raw)
        except ImportError:
            self._private = os.urandom(32)
            self.public = _x25519(self._private, (9).to_bytes(32, "little"))

    def shared(self, peer: bytes) -> bytes:
        if isinstance(self._private, bytes):
            out = _x25519(self._private, peer)
        else:
            from cryptography.hazmat.primitives.asymmetric import x25519  # type: ignore

            out = self._private.exchange(x25519.X25519PublicKey.from_public_bytes(peer))
        if out == bytes(32):
            raise ValueError("the daemon's key is a degenerate X25519 point")
        return out


def _fingerprint(public: bytes) -> str:
    """The end of a remote client's id: the first 16 bytes of its key's SHA-256, hex."""
    import hashlib

    return hashlib.sha256(public).digest()[:16].hex()


def _derive(shared: bytes, cid: str, client: bytes, daemon: bytes) -> bytes:
    """HKDF-SHA256 (RFC 5869) of the X25519 output: the client's 32-byte secret."""
    import hashlib
    import hmac

    prk = hmac.new(_KDF_LABEL, shared, hashlib.sha256).digest()
    info = _KDF_LABEL + cid.encode() + b"\0" + client + daemon
    return hmac.new(prk, info + b"\x01", hashlib.sha256).digest()


def _seal(secret: bytes, counter: int, data: bytes) -> bytes:
    """A request's attachment: its counter (u64, little-endian), then the HMAC-SHA256."""
    import hashlib
    import hmac
    import struct

    c = struct.pack("<Q", counter)
    return c + hmac.new(secret, _MAC_LABEL + c + data, hashlib.sha256).digest()


class _ZenohLink:
    """omnid's protocol over zenoh (needs ``pip install eclipse-zenoh``): this client's
    liveliness token ``omnid/<arm>/client/<id>``, its requests put on ``omnid/<arm>/in/<id>``
    and the daemon's messages for it, from ``omnid/<arm>/out/<id>``, written into a socket
    pair the client reads. Its id ends with its key's fingerprint; after the hello every
    request carries the code of the secret agreed there."""

    def __init__(
        self,
        remote: str,
        arm: str,
        name: str,
        user: Optional[str] = None,
        password: Optional[str] = None,
    ):
        try:
            import zenoh  # type: ignore
        except ImportError as e:
            raise ConnectError(
                "a remote client needs the zenoh package: pip install eclipse-zenoh"
            ) from e
        import base64
        import threading

        self._keys = _KeyPair()
        self.key = base64.b64encode(self._keys.public).decode()
        self.cid = "py-" + _fingerprint(self._keys.public)
        self._secret: Optional[bytes] = None
        self._counter = 0
        self._put_lock = threading.Lock()
        self.dropped = 0
        self.reader, self._writer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._writer.setblocking(False)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([remote]))
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        if user is not None:
            # zenoh's user/password authentication, for a daemon that checks who connects
            # (its [zenoh] users_file).
            conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
            conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password or ""))
        try:
            self._session = zenoh.open(conf)
        except Exception as e:  # zenoh raises its own ZError
            raise ConnectError("cannot open a zenoh session to %s: %s" % (remote, e)) from e
        prefix = "omnid/%s" % arm
        self._sub = self._session.declare_subscriber(
            "%s/out/%s" % (prefix, self.cid), self._arrived
        )
        self._token = self._session.liveliness().declare_token(
            "%s/client/%s" % (prefix, self.cid)
        )
        self._in = self._session.declare_publisher("%s/in/%s" % (prefix, self.cid))
        self._closed = False
        # A zenoh session left open keeps the interpreter from exiting (it waits for threads
        # before atexit runs): close it first, so a script that never closes its client ends.
        import threading

        getattr(threading, "_register_atexit", lambda f: None)(self.close)

    def _arrived(self, sample: Any) -> None:
        data = bytes(sample.payload.to_bytes())
        if self._secret is None and b'"hello"' in data:
            # The daemon's hello: its key completes the agreement, before the client reads it.
            try:
                import base64

                m = json.loads(data)
                if m.get("type") != "hello":
                    raise ValueError("not the hello")
                daemon = base64.b64decode(m["key"])
                shared = self._keys.shared(daemon)
                self._secret = _derive(shared, self.cid, self._keys.public, daemon)
            except (ValueError, KeyError, TypeError):
                pass
        try:
            self._writer.send(data)
        except (BlockingIOError, OSError):
            # The reader is not keeping up (or is closed): the message is dropped.
            self.dropped += 1

    def put(self, data: bytes) -> None:
        # One lock: the counters leave in order (the daemon takes each only once, ascending).
        with self._put_lock:
            if self._secret is None:
                self._in.put(data)
                return
            self._counter += 1
            self._in.put(data, attachment=_seal(self._secret, self._counter, data))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for thing in (self._token, self._sub, self._in):
            try:
                thing.undeclare()
            except Exception:
                pass
        try:
            self._session.close()
        except Exception:
            pass
        self._writer.close()


class Client:
    """A connection to ``omnid serve``.

    ``Client(path=None, name="python", timeout=10.0, on_event=None, state_buffer=10000,
    event_buffer=10000, arm=None)`` connects to ``path`` (else the socket of ``arm``, by
    name or alias, :func:`find_arm_socket`; else :func:`find_socket`), sends
    ``{"op":"hello","protocol":1,"name":name}`` and waits for the daemon's hello, kept in
    :attr:`hello` (a dict: ``device``, ``arm``, ``aliases``, ``rate_hz``, ``access`` (``read`` or ``control``),
    ``client`` (this connection's number), ``stream_ttl_ms``, ``controllers``, ``modes``,
    ``server``, ``protocol``). A refused connection raises :class:`RefusedError` with the
    daemon's reason.

    ``remote="tcp/host:7448"`` (with ``arm``) reaches a daemon on another PC through zenoh
    (``omnid serve --zenoh``; needs ``pip install eclipse-zenoh``), with the same methods and
    messages; the daemon refuses commands over the network unless its ``[zenoh]
    allow_commands`` is on. ``user`` and ``password`` are this client's zenoh credentials, for
    a daemon that checks who connects (``[zenoh] users_file``; docs/ZENOH.md).

    ``timeout`` (s) is the default wait for a reply. ``on_event(message)``, when given, is
    called with every message that is neither a state sample nor a reply (``event``,
    ``lost``, the ``error`` of a refused stream command) at the moment it is read, by
    whichever method read it; those messages are also kept for :meth:`next_event`.
    ``state_buffer`` and ``event_buffer`` bound the two buffers of unread messages (the
    oldest go first; dropped states are counted in :attr:`dropped_total`).

    Use it as a context manager, or call :meth:`close`.

    Attributes:
        hello: the daemon's hello (dict).
        stream_rate_hz: the state stream's rate as the daemon granted it (0: not streaming).
        lost_total: state samples the daemon dropped because this client read too slowly
            (the largest ``total`` of its ``lost`` messages).
        dropped_total: state samples this client dropped from its own full buffer.
        bye: the daemon's goodbye message once it said ``bye`` (else None).
        seq: the ``seq`` of the last servo_jp/servo_jf/servo_cf sent.
    """

    def __init__(
        self,
        path: Optional[str] = None,
        name: str = "python",
        timeout: float = 10.0,
        on_event: Optional[Callable[[Dict[str, Any]], None]] = None,
        state_buffer: int = 10000,
        event_buffer: int = 10000,
        arm: Optional[str] = None,
        remote: Optional[str] = None,
        user: Optional[str] = None,
        password: Optional[str] = None,
    ):
        self._zenoh: Optional["_ZenohLink"] = None
        if remote is not None:
            if not arm:
                raise ValueError("a remote client names its arm: Client(remote=..., arm='left')")
            self.path = "zenoh:%s/%s" % (remote, arm)
        elif path is not None:
            self.path = os.fspath(path)
        elif arm is not None:
            self.path = find_arm_socket(arm)
        else:
            self.path = find_socket()
        self.name = name
        self.timeout = timeout
        self.on_event = on_event
        self.hello: Dict[str, Any] = {}
        self.stream_rate_hz = 0.0
        self.lost_total = 0
        self.dropped_total = 0
        self.bye: Optional[str] = None
        self.seq = 0
        self._state_cap = max(1, int(state_buffer))
        self._states: Deque[Tuple[int, State]] = deque()
        self._events: Deque[Tuple[int, Dict[str, Any]]] = deque(maxlen=max(1, event_buffer))
        self._arrivals = 0
        self._next_id = 1
        self._stream_error: Optional[Dict[str, Any]] = None
        self._closed_reason: Optional[str] = None
        self._sock: Optional[socket.socket] = None
        self._poll = select.poll()

        if remote is not None:
            # The daemon's messages arrive on zenoh's threads and are written into one end of
            # a socket pair; this client reads the other end exactly as it reads a daemon's
            # socket.
            self._zenoh = _ZenohLink(remote, str(arm), name, user, password)
            sock = self._zenoh.reader
            sock.setblocking(False)
            self._sock = sock
            self._poll.register(sock.fileno(), select.POLLIN)
            try:
                self._greet(timeout)
            except OmnidTimeout:
                self.close()
                raise OmnidTimeout(
                    "no hello from arm %r at %s within %.1f s: check that `omnid serve --zenoh` "
                    "runs there and serves that arm (its start-up line says where zenoh listens, "
                    "by default tcp/127.0.0.1:%d), and that this PC can reach that address"
                    % (str(arm), remote, timeout, DEFAULT_ZENOH_PORT)
                ) from None
            except BaseException:
                self.close()
                raise
            return

        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.connect(self.path)
        except FileNotFoundError:
            sock.close()
            raise ConnectError(
                "cannot connect to %s: no such socket (is `omnid serve` running?)" % self.path
            ) from None
        except OSError as e:
            sock.close()
            raise ConnectError("cannot connect to %s: %s" % (self.path, e.strerror or e)) from e
        sock.setblocking(False)
        self._sock = sock
        self._poll.register(sock.fileno(), select.POLLIN)
        try:
            self._greet(timeout)
        except BaseException:
            self.close()
            raise

    # ---------------------------------------------------------------- session

    def _greet(self, timeout: float) -> None:
        hello: Dict[str, Any] = {"op": "hello", "protocol": PROTOCOL_VERSION, "name": self.name}
        if self._zenoh is not None:
            hello["key"] = self._zenoh.key
        try:
            self.send(hello)
        except ConnectionClosedError:
            # A daemon that refuses the connection (access, too many clients) says why and
            # closes at once: its reason is still there to read.
            self._closed_reason = None
        deadline = time.monotonic() + timeout
        while True:
            m = self._read(deadline, "hello from the daemon")
            kind = m.get("type")
            if kind == "hello":
                self.hello = m
                return
            if kind == "error":
                raise RefusedError(
                    str(m.get("message", "refused")), m.get("op") or "connect", m
                )
            # Anything else before the hello is kept like any other message.
            self._file(m)

    @property
    def client_id(self) -> int:
        """This connection's number (named in lease events and refusals)."""
        return int(self.hello.get("client", 0))

    @property
    def rate_hz(self) -> float:
        """The device's tick rate, Hz."""
        return float(self.hello.get("rate_hz", 0.0))

    @property
    def access(self) -> str:
        """``read`` or ``control``."""
        return str(self.hello.get("access", ""))

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called or the daemon ended the connection."""
        return self._sock is None or self._closed_reason is not None

    def close(self) -> None:
        """Close the connection (idempotent). The daemon frees this client's lease."""
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                self._poll.unregister(sock.fileno())
            except (KeyError, ValueError, OSError):
                pass
            sock.close()
        link, self._zenoh = self._zenoh, None
        if link is not None:
            link.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return "<omnid Client %s #%s %s%s>" % (
            self.path,
            self.hello.get("client", "?"),
            self.hello.get("access", "?"),
            " closed" if self.closed else "",
        )

    # ---------------------------------------------------------------- wire

    def send(self, message: Dict[str, Any], timeout: Optional[float] = None) -> None:
        """Send one message as it is (no reply awaited).

        Raises ``ValueError`` for values JSON cannot carry (NaN, infinity),
        :class:`ConnectionClosedError` when the connection is gone.
        """
        sock = self._live_socket()
        data = json.dumps(message, separators=(",", ":"), allow_nan=False).encode("utf-8")
        if len(data) > MAX_MESSAGE:
            raise ValueError("message of %d bytes exceeds %d" % (len(data), MAX_MESSAGE))
        if self._zenoh is not None:
            self._zenoh.put(data)
            return
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            try:
                sock.send(data)
                return
            except (BlockingIOError, InterruptedError):
                pass
            except (BrokenPipeError, ConnectionResetError) as e:
                self._closed_reason = "the daemon closed the connection"
                raise ConnectionClosedError(self._closed_reason) from e
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise OmnidTimeout("the daemon did not take a message within the time-out")
            p = select.poll()
            p.register(sock.fileno(), select.POLLOUT)
            p.poll(_ms(remaining))

    def _live_socket(self) -> socket.socket:
        if self._closed_reason is not None:
            raise ConnectionClosedError(self._closed_reason)
        if self._sock is None:
            raise ConnectionClosedError("the client is closed")
        return self._sock

    def _recv_now(self) -> Optional[Dict[str, Any]]:
        """One message if one is waiting in the socket, else None (never blocks)."""
        sock = self._live_socket()
        try:
            data = sock.recv(_RECV_SIZE)
        except BlockingIOError:
            return None
        except ConnectionResetError:
            # Linux reports a reset (the daemon closed without reading all this client sent,
            # e.g. when it refuses a connection) before the messages the daemon sent last:
            # those are still there to read.
            try:
                data = sock.recv(_RECV_SIZE)
            except OSError:
                data = b""
        if not data:
            self._closed_reason = self.bye or "the daemon closed the connection"
            raise ConnectionClosedError(self._closed_reason)
        if len(data) > MAX_MESSAGE:
            raise ProtocolError("message of %d bytes from the daemon is too long" % len(data))
        try:
            m = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as e:
            raise ProtocolError("unreadable message from the daemon: %s" % e) from e
        if not isinstance(m, dict):
            raise ProtocolError("message from the daemon is not a JSON object: %r" % (m,))
        if m.get("type") == "bye":
            self.bye = str(m.get("message", "the daemon is stopping"))
            self._closed_reason = "the daemon is stopping: %s" % self.bye
            raise ConnectionClosedError(self._closed_reason)
        return m

    def _read(self, deadline: Optional[float], what: str) -> Dict[str, Any]:
        """The next message from the socket, waiting until ``deadline`` (None: forever)."""
        while True:
            m = self._recv_now()
            if m is not None:
                return m
            if deadline is None:
                self._poll.poll()
                continue
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise OmnidTimeout("no %s within the time-out" % what)
            self._poll.poll(_ms(remaining))

    def _file(self, m: Dict[str, Any]) -> Optional[State]:
        """Sort a message that is not an awaited reply into the buffers; a state is returned."""
        self._arrivals += 1
        kind = m.get("type")
        if kind == "state":
            s = State.from_message(m)
            if len(self._states) >= self._state_cap:
                self._states.popleft()
                self.dropped_total += 1
            self._states.append((self._arrivals, s))
            return s
        if kind in ("reply", "hello"):
            # The answer to a request that gave up waiting: nobody wants it any more.
            return None
        if kind == "lost":
            # `total` is cumulative; take the largest seen, whatever order they come in.
            total = int(m.get("total", self.lost_total + int(m.get("count", 0))))
            self.lost_total = max(self.lost_total, total)
        elif kind == "error" and m.get("op") in _STREAM_OPS:
            self._stream_error = m
        self._events.append((self._arrivals, m))
        if self.on_event is not None:
            self.on_event(m)
        return None

    def _pump(self) -> int:
        """Sort every message already waiting in the socket into the buffers; how many."""
        n = 0
        while True:
            m = self._recv_now()
            if m is None:
                return n
            self._file(m)
            n += 1

    # ---------------------------------------------------------------- requests

    def request(self, op: str, timeout: Optional[float] = None, **fields: Any) -> Dict[str, Any]:
        """Send request ``op`` with ``fields`` (those that are None are left out) and an
        ``id``; return the daemon's reply (a dict with ``type``, ``op``, ``id`` and the
        request's own keys).

        Raises :class:`RefusedError` with the daemon's message when it refuses,
        :class:`ConnectionClosedError` on ``bye`` or a closed connection, and
        :class:`OmnidTimeout` after ``timeout`` s (default: the client's). Messages that
        arrive meanwhile are kept for later reads. Stream commands (servo_jp, servo_jf,
        servo_cf) have no reply: use :meth:`servo_jp`, :meth:`servo_jf`, :meth:`servo_cf` or
        :meth:`send`.
        """
        if op in _STREAM_OPS:
            raise ValueError("%s has no reply; use servo_jp/servo_jf/servo_cf or send()" % op)
        rid = self._next_id
        self._next_id += 1
        msg: Dict[str, Any] = {"op": op}
        msg.update((k, v) for k, v in fields.items() if v is not None)
        msg["id"] = rid
        wait = self.timeout if timeout is None else timeout
        self.send(msg, wait)
        deadline = time.monotonic() + wait
        while True:
            m = self._read(deadline, "reply to %s" % op)
            kind = m.get("type")
            if kind in ("reply", "error") and m.get("id") == rid:
                if kind == "error":
                    raise RefusedError(str(m.get("message", "refused")), op, m)
                return m
            if kind == "error" and "id" not in m and m.get("op") == op:
                # A request the daemon could not parse: it cannot know the id.
                raise RefusedError(str(m.get("message", "refused")), op, m)
            self._file(m)

    def status(self) -> Dict[str, Any]:
        """The daemon's status: the run summary so far plus ``mode``, ``lease`` (who holds
        the command lease, or None), ``clients``, ``recording``, ``socket``, ``heat``,
        ``protocol``."""
        return self.request("status")["status"]

    def stream(self, rate_hz: float) -> float:
        """Ask for state samples at ``rate_hz`` (0 stops); return the rate granted (the
        device rate divided by a whole number). Samples are read with :meth:`next_state`,
        :meth:`states` or :meth:`latest_state`."""
        reply = self.request("stream", rate_hz=float(rate_hz))
        self.stream_rate_hz = float(reply.get("rate_hz", 0.0))
        return self.stream_rate_hz

    def take_lease(self) -> int:
        """Take the command lease; return the holder (this client's number). Any command
        takes it implicitly while it is free."""
        return int(self.request("lease")["holder"])

    def release(self) -> None:
        """Give the command lease back (a servo_jp/servo_jf/servo_cf stream then falls back)."""
        self.request("release")

    def mode(self, name: str, trajectory: Optional[str] = None) -> str:
        """Change mode: ``idle``, ``hold``, ``track`` (with ``trajectory``: ``sine``,
        ``multisine``, ``hold``) or ``free``; return the mode the daemon took."""
        return str(self.request("mode", mode=name, trajectory=trajectory)["mode"])

    def hold(self) -> str:
        """Hold the current pose (CRTK ``hold``)."""
        return str(self.request("hold")["mode"])

    def free(self) -> str:
        """Compensation only: the arm moves freely (CRTK ``free``)."""
        return str(self.request("free")["mode"])

    def idle(self) -> str:
        """No torque, amplifiers off (the state still streams)."""
        return self.mode("idle")

    def track(self, trajectory: str = "sine") -> str:
        """Follow a built-in trajectory (``sine``, ``multisine``, ``hold``), blended in from
        the current pose (the stream's mode reads ``blend``, then ``track``)."""
        return self.mode("track", trajectory)

    def controller(self, name: str) -> str:
        """Switch the control law (``pd``, ``ct``, ``nnidc``, ``off``) without a bump."""
        return str(self.request("controller", controller=name)["controller"])

    def adapt(self, on: bool = True) -> bool:
        """Resume (``on=True``) or freeze (``on=False``) the identifier's adaptation."""
        return bool(self.request("adapt", on=bool(on))["adapt"])

    def freeze(self) -> bool:
        """Freeze the identifier's online adaptation (``adapt(False)``)."""
        return self.adapt(False)

    def save_weights(self, path: str) -> str:
        """Have the daemon write the identifier's current weights to ``path`` (made
        absolute here; the daemon writes it, so it must be writable by the daemon)."""
        return str(self.request("weights_save", path=os.path.abspath(path))["path"])

    def load_weights(self, path: str) -> str:
        """Load identifier weights from ``path``; returns once the servo swapped them in."""
        return str(self.request("weights_load", path=os.path.abspath(path))["path"])

    def record_start(self, path: Optional[str] = None) -> str:
        """Start recording every tick to a CSV file (default: in the daemon's state
        directory); return its path."""
        if path is not None:
            path = os.path.abspath(path)
        return str(self.request("record_start", path=path)["path"])

    def record_stop(self) -> Dict[str, Any]:
        """Stop recording; return ``{"path": ..., "rows": ..., "error": None or why}``."""
        reply = self.request("record_stop")
        return {"path": reply.get("path"), "rows": reply.get("rows"), "error": reply.get("error")}

    def shutdown(self, wait: bool = True, timeout: Optional[float] = None) -> Optional[str]:
        """Stop the daemon (zero torque, amplifiers off, socket removed).

        With ``wait`` (the default), also wait for its ``bye`` (or the connection's end) and
        return the goodbye message; the client is closed afterwards.
        """
        self.request("shutdown", timeout=timeout)
        if not wait:
            return None
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        try:
            while True:
                self._file(self._read(deadline, "goodbye"))
        except ConnectionClosedError:
            pass
        self.close()
        return self.bye

    # ---------------------------------------------------------------- streams

    def _stream_command(
        self,
        op: str,
        key: str,
        values: Sequence[float],
        seq: Optional[int],
        ttl_ms: Optional[float],
    ) -> int:
        v = [float(x) for x in values]
        if len(v) != 3:
            raise ValueError("%s: %s needs 3 values, got %d" % (op, key, len(v)))
        if not all(math.isfinite(x) for x in v):
            raise ValueError("%s: %s must be finite numbers, got %r" % (op, key, v))
        # See whether the daemon refused an earlier command of the stream.
        self._pump()
        err, self._stream_error = self._stream_error, None
        if err is not None:
            raise RefusedError(str(err.get("message", "refused")), err.get("op"), err)
        self.seq = self.seq + 1 if seq is None else int(seq)
        msg: Dict[str, Any] = {"op": op, "seq": self.seq, key: v}
        if ttl_ms is not None:
            msg["ttl_ms"] = float(ttl_ms)
        self.send(msg)
        return self.seq

    def servo_jp(
        self, q: Sequence[float], seq: Optional[int] = None, ttl_ms: Optional[float] = None
    ) -> int:
        """Joint position setpoint ``q`` (3 angles, rad); the first one enters ``servo_jp``.

        No reply: a setpoint lasts ``ttl_ms`` (default the daemon's ``stream_ttl_ms``), so
        send them continuously (e.g. one per state sample, ``seq=state.seq``). ``seq``
        defaults to the previous one plus 1; the sequence number sent is returned and
        echoed as ``cmd_seq`` in the stream. A refusal by the daemon arrives later: it is
        raised as :class:`RefusedError` by the next servo_jp/servo_jf/servo_cf call (and is among
        the events).
        """
        return self._stream_command("servo_jp", "q", q, seq, ttl_ms)

    def servo_jf(
        self, tau: Sequence[float], seq: Optional[int] = None, ttl_ms: Optional[float] = None
    ) -> int:
        """Joint torque ``tau`` (3 values, N·m) on top of the compensation; as
        :meth:`servo_jp`."""
        return self._stream_command("servo_jf", "tau", tau, seq, ttl_ms)

    def servo_cf(
        self, force: Sequence[float], seq: Optional[int] = None, ttl_ms: Optional[float] = None
    ) -> int:
        """Tip force ``force`` (3 values, N, OpenHaptics frame: +x right, +y up, +z toward
        the user) on top of the compensation, applied as joint torque Jᵀ F; its norm is
        clamped to the daemon's ``[haptics] max_force_n`` (3.3 N by default). As
        :meth:`servo_jp`."""
        return self._stream_command("servo_cf", "force", force, seq, ttl_ms)

    # ---------------------------------------------------------------- haptic effects

    def effect(self, slot: int, effect: Optional[Dict[str, Any]]) -> Dict[str, Any]:
        """Put a haptic effect in ``slot`` (0..7) of the scene, or remove it (``None``).

        ``effect`` is a dict with ``type`` (``spring``, ``damper``, ``plane``, ``box``,
        ``constant``) and its parameters (docs/HAPTICS.md), e.g.
        ``{"type": "plane", "point_mm": [0, -40, 0], "normal": [0, 1, 0],
        "stiffness_n_per_mm": 1.0}``. Effects are rendered in ``free`` and ``servo_cf``; a
        change fades in without a jump. Returns the daemon's reply.
        """
        return self.request("effect", slot=int(slot), effect=effect)

    def passivity(self, on: bool = True) -> bool:
        """Turn the passivity controller on the effects on or off."""
        return bool(self.request("passivity", on=bool(on))["passivity"])

    # ---------------------------------------------------------------- teleoperation

    def teleop(self, role: str, peer: str, **settings: Any) -> Dict[str, Any]:
        """Couple this arm as ``role`` (``"leader"`` or ``"follower"``) of a pair with
        ``peer``, another arm of the same daemon; the other side is started the same way on
        ``peer``'s own connection, with the same ``settings`` (changes to ``[teleop]``:
        ``architecture``, ``motion_scale``, ``force_scale``, ``operator``, ``passivity``).
        Returns the side as started (docs/TELEOP.md §8)."""
        return self.request("teleop", role=role, peer=peer, **settings)["teleop"]

    def teleop_stop(self) -> None:
        """Uncouple this arm; it holds where it is."""
        self.request("teleop_stop")

    def teleop_scale(self, motion_scale: float) -> float:
        """The leader's motion scale, changed live without a jump."""
        return float(self.request("teleop_scale", motion_scale=float(motion_scale))["motion_scale"])

    # ---------------------------------------------------------------- reading

    def next_state(self, timeout: Optional[float] = None) -> State:
        """The next state sample (oldest unread first), waiting at most ``timeout`` s
        (None: the client's time-out). Other messages read meanwhile are kept."""
        if self._states:
            return self._states.popleft()[1]
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            m = self._read(deadline, "state sample")
            if m.get("type") == "state":
                self._arrivals += 1
                return State.from_message(m)
            self._file(m)

    def states(self, timeout: Optional[float] = None) -> Iterator[State]:
        """Iterate over state samples as they arrive (after :meth:`stream`).

        Each wait lasts at most ``timeout`` s (None: the client's time-out) before
        :class:`OmnidTimeout`; the iteration ends with :class:`ConnectionClosedError` when the
        daemon stops. Events go to ``on_event`` and :meth:`next_event` meanwhile.
        """
        while True:
            yield self.next_state(timeout)

    def latest_state(self, timeout: float = 1.0) -> State:
        """The most recent state sample: everything queued is read and the newest sample
        returned (older unread samples are discarded). Starts streaming at the device's
        full rate when not streaming yet. Waits at most ``timeout`` s for a first sample,
        and up to about two sample periods more to be sure no newer sample is on its way
        (the daemon refills the socket from its own queue as this client reads).
        """
        if self.stream_rate_hz <= 0:
            self.stream(self.rate_hz or 1000.0)
        period = 1.0 / (self.stream_rate_hz or 1000.0)
        deadline = time.monotonic() + timeout
        newest: Optional[State] = None
        waited = False
        self._pump()
        while True:
            n = len(self._states)
            if n:
                newest = self._states[-1][1]
                self._states.clear()
            # The daemon refills the socket from its own queue as it empties, so a backlog
            # shows up as several samples at once; at the live edge at most one arrives
            # per period.
            if newest is not None and waited and n <= 1:
                return newest
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if newest is not None:
                    return newest
                raise OmnidTimeout("no state sample within %.3g s" % timeout)
            wait = min(remaining, 2.0 * period) if newest is not None else remaining
            ready = self._poll.poll(_ms(wait))
            waited = True
            if not ready and newest is not None:
                return newest
            self._pump()

    def next_event(self, timeout: Optional[float] = 0.0) -> Optional[Dict[str, Any]]:
        """The next message that is neither a state sample nor a reply (``event``,
        ``lost``, the ``error`` of a refused stream command), as a dict; None when none
        arrives within ``timeout`` s (0: only what is already here; None: the client's
        time-out). State samples read meanwhile are kept."""
        if self._events:
            return self._events.popleft()[1]
        wait = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + wait
        while True:
            try:
                m = self._read(deadline, "event")
            except OmnidTimeout:
                return None
            self._file(m)
            if self._events:
                return self._events.popleft()[1]

    def events(self, timeout: Optional[float] = 0.0) -> Iterator[Dict[str, Any]]:
        """Iterate over events (as :meth:`next_event`) until none arrives within
        ``timeout`` s; with the default 0, just the ones already received."""
        while True:
            e = self.next_event(timeout)
            if e is None:
                return
            yield e

    def wait_event(self, event: str, timeout: Optional[float] = None) -> Dict[str, Any]:
        """Wait for the event named ``event`` (e.g. ``"stream-stale"``, ``"mode"``) and
        return it; it is taken out of the event buffer, other events stay. Raises
        :class:`OmnidTimeout` after ``timeout`` s (None: the client's time-out)."""
        for k, (_, m) in enumerate(self._events):
            if m.get("type") == "event" and m.get("event") == event:
                del self._events[k]
                return m
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            m = self._read(deadline, "`%s` event" % event)
            self._file(m)
            if m.get("type") == "event" and m.get("event") == event:
                # It is the newest in the buffer (unless the callback consumed it).
                if self._events and self._events[-1][1] is m:
                    self._events.pop()
                return m

    def next_message(self, timeout: Optional[float] = None) -> Message:
        """The next unread message of any kind, in arrival order: a :class:`State` for a
        state sample, else the message as a dict (events, ``lost``, stray errors). Raises
        :class:`OmnidTimeout` after ``timeout`` s (None: the client's time-out)."""
        if self._states or self._events:
            if not self._events or (self._states and self._states[0][0] < self._events[0][0]):
                return self._states.popleft()[1]
            return self._events.popleft()[1]
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            m = self._read(deadline, "message")
            s = self._file(m)
            if s is not None:
                return self._states.pop()[1]
            if self._events:
                return self._events.pop()[1]

    def discard_states(self) -> int:
        """Drop every state sample received and not read yet (reading what is already
        waiting in the socket first); return how many. Events stay."""
        self._pump()
        n = len(self._states)
        self._states.clear()
        return n

    def pending(self) -> Tuple[int, int]:
        """(state samples, other messages) read and not yet consumed (reads what is
        already waiting in the socket first)."""
        self._pump()
        return len(self._states), len(self._events)


def _ms(seconds: float) -> int:
    """Seconds to a poll() time-out in whole milliseconds, rounded up (never negative)."""
    return max(0, int(math.ceil(seconds * 1000.0)))


def _main() -> int:
    import sys

    path = sys.argv[1] if len(sys.argv) > 1 else None
    try:
        with Client(path, name="tip-printer") as omni:
            omni.stream(10)
            for s in omni.states():
                print("tip %7.1f %7.1f %7.1f mm" % tuple(s.tip_mm), flush=True)
    except KeyboardInterrupt:
        return 0
    except OmnidError as e:
        print("omnid_client: %s" % e, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
