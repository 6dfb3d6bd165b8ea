"""Robot link over TCP: a small versioned JSON-lines protocol, a simulated robot server
and a blocking, safety-checked client (thesis section 4.2: model, camera and robot talk
over TCP/IP so the model may run on another machine).

Protocol (version 1). Every message is ONE JSON object on ONE line (UTF-8, ``\\n``
terminated, at most :data:`MAX_LINE_BYTES` bytes):

  request  ``{"v": 1, "id": <int>, "op": <str>, ...}``
  reply    ``{"v": 1, "id": <same int>, "ok": true, ...}``
           ``{"v": 1, "id": <int or null>, "ok": false, "error": <text>, "code": <str>}``

  op            request fields              reply fields (ok)
  ``hello``     ``versions``: [int]          ``server``: str, ``version``: 1
  ``move_paddle`` ``target_m``: [x, y, z]    ``position_m``: [x, y, z]
  ``read_pose``   --                         ``position_m``, ``rotation`` (3x3 rows)
  ``read_force``  --                         ``force_n``: [fx, fy, fz] (newtons)

``target_m`` is the paddle's displacement from its reference pose in metres: absolute,
not incremental, so re-sending it after a reconnect is harmless (idempotent).

Error codes: ``too_long``, ``bad_json``, ``bad_version``, ``bad_request``,
``unknown_op``, ``internal``. A refused line never closes the connection.

Nothing here imports the jaxrkpm solver core.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import json
import math
import socket
import threading
import time
from typing import Callable

import numpy as np

__all__ = [
    "PROTOCOL_VERSION",
    "MAX_LINE_BYTES",
    "LinkError",
    "LinkTimeout",
    "LinkClosed",
    "RemoteError",
    "ProtocolError",
    "SafetyError",
    "SafetyLimits",
    "Pose",
    "encode_message",
    "decode_message",
    "SimulatedRobotServer",
    "RobotClient",
]

PROTOCOL_VERSION = 1
"""The protocol version this side speaks (``hello`` negotiates it)."""
MAX_LINE_BYTES = 64 * 1024
"""The longest message line, in bytes, that the server and the client accept by default (the
server answers a longer one with ``too_long``)."""
OPS = ("hello", "move_paddle", "read_pose", "read_force")
_LOOPBACK = ("127.0.0.1", "localhost", "::1")


# ----------------------------------------------------------------------------- errors


class LinkError(RuntimeError):
    """Base class of robot-link failures."""


class LinkTimeout(LinkError, TimeoutError):
    """The server did not answer within the client's timeout."""


class LinkClosed(LinkError, ConnectionError):
    """The connection dropped and the bounded reconnect attempts failed."""


class RemoteError(LinkError):
    """The server refused a request (``ok: false``); ``code`` and ``reply`` say why."""

    def __init__(self, message: str, code: str | None, reply: dict):
        super().__init__(message)
        self.code = code
        self.reply = reply


class ProtocolError(LinkError):
    """The server's reply breaks the protocol (a missing, mistyped or non-finite field)."""


class SafetyError(ValueError):
    """A motion command was refused on the model side, before anything was sent."""


# ----------------------------------------------------------------------------- encoding


def _reject_constant(name):
    raise ValueError(f"non-finite number {name} is not valid JSON")


def encode_message(msg: dict, max_line_bytes: int = MAX_LINE_BYTES) -> bytes:
    """dict -> one ``\\n``-terminated UTF-8 JSON line. NaN/inf are refused (ValueError)."""
    line = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8") + b"\n"
    if len(line) > max_line_bytes:
        raise ValueError(f"message is {len(line)} bytes, over the {max_line_bytes}-byte line limit")
    return line


def decode_message(line: bytes) -> dict:
    """One line (without or with its ``\\n``) -> dict. ValueError if not a JSON object
    (also for nesting too deep for the parser: ``"[" * 60000`` fits in one line)."""
    try:
        obj = json.loads(line.decode("utf-8"), parse_constant=_reject_constant)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    if not isinstance(obj, dict):
        raise ValueError(f"a message must be a JSON object, got {type(obj).__name__}")
    return obj


def _vec3(value, name: str) -> np.ndarray:
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)):
        raise ValueError(f"{name} must be a list of 3 numbers")
    try:
        v = np.array([float(c) for c in value])
    except OverflowError:   # a JSON integer of hundreds of digits is no float
        raise ValueError(f"{name} must be finite numbers (an integer is too large)") from None
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite")
    return v


def _matrix3(value, name: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError(f"{name} must be 3 rows of 3 numbers")
    return np.stack([_vec3(row, f"{name} row {i}") for i, row in enumerate(value)])


# ----------------------------------------------------------------------------- safety


@dataclasses.dataclass(frozen=True)
class SafetyLimits:
    """Model-side motion limits, checked by :class:`RobotClient` before sending.

    workspace_min_m, workspace_max_m: (3,) corners of the allowed box for the paddle
    target (metres, same frame as ``target_m``). max_step_m: largest allowed Euclidean
    distance between consecutive commanded targets (metres) -- the tracking law clamps
    its increments, so a big jump means a bug or a diverged model, not a plan.
    """

    workspace_min_m: np.ndarray
    workspace_max_m: np.ndarray
    max_step_m: float

    def __post_init__(self):
        lo = np.asarray(self.workspace_min_m, dtype=np.float64).reshape(-1)
        hi = np.asarray(self.workspace_max_m, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError("workspace_min_m and workspace_max_m must have 3 entries")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise ValueError(f"need finite workspace_min_m < workspace_max_m; got {lo}, {hi}")
        if not (math.isfinite(self.max_step_m) and self.max_step_m > 0):
            raise ValueError(f"max_step_m must be finite and > 0; got {self.max_step_m}")
        object.__setattr__(self, "workspace_min_m", lo)
        object.__setattr__(self, "workspace_max_m", hi)

    def check(self, target_m: np.ndarray, last_m: np.ndarray | None) -> None:
        """Raise :class:`SafetyError` unless ``target_m`` is inside the box and within
        ``max_step_m`` of ``last_m`` (the last commanded target; None skips the step check)."""
        t = np.asarray(target_m, dtype=np.float64)
        if np.any(t < self.workspace_min_m) or np.any(t > self.workspace_max_m):
            raise SafetyError(f"target {t.tolist()} m is outside the workspace box "
                              f"[{self.workspace_min_m.tolist()}, {self.workspace_max_m.tolist()}] m")
        if last_m is not None:
            step = float(np.linalg.norm(t - np.asarray(last_m, dtype=np.float64)))
            if step > self.max_step_m:
                raise SafetyError(f"step of {step:.6g} m from the last commanded position "
                                  f"exceeds max_step_m = {self.max_step_m:.6g} m")


@dataclasses.dataclass(frozen=True)
class Pose:
    """Paddle pose: position_m (3,) metres, rotation (3, 3)."""

    position_m: np.ndarray
    rotation: np.ndarray


# ----------------------------------------------------------------------------- server


ForceFn = Callable[[np.ndarray], "np.ndarray | list[float]"]


class SimulatedRobotServer:
    """A simulated robot: keeps a paddle pose and answers the v1 protocol over TCP.

    Binds only to loopback, on an ephemeral port by default (``port=0``; read
    ``.port`` after start). The force reading comes from ``force_fn(position_m (3,)) ->
    (3,) newtons`` so a simulated physical object can answer later (default: zero).

    Run it in a background thread with its own event loop (:meth:`start` / :meth:`stop`,
    or as a context manager), or inside a running loop (:meth:`start_async` /
    :meth:`stop_async`).

    Test hooks: ``silent = True`` makes it read but never answer; :meth:`drop_connections`
    closes every client connection; :meth:`messages` / ``n_lines`` show what arrived.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0,
                 force_fn: ForceFn | None = None, initial_position_m=(0.0, 0.0, 0.0),
                 max_line_bytes: int = MAX_LINE_BYTES, log_size: int = 1000,
                 name: str = "jaxrkpm-simulated-robot"):
        if host not in _LOOPBACK:
            raise ValueError(f"the simulated robot binds only to loopback, not {host!r}")
        self.host, self.port = host, int(port)
        self.name = name
        self.force_fn = force_fn
        self.max_line_bytes = int(max_line_bytes)
        self.position_m = _vec3(list(map(float, initial_position_m)), "initial_position_m")
        self.rotation = np.eye(3)
        self.silent = False
        self.n_lines = 0
        self._log: collections.deque = collections.deque(maxlen=log_size)
        self._log_lock = threading.Lock()
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None

    # -- what arrived (thread-safe copies)
    def messages(self) -> list[dict]:
        """Decoded request objects received so far (malformed lines are not included)."""
        with self._log_lock:
            return list(self._log)

    # -- protocol (pure; no I/O)
    def handle(self, msg: dict) -> dict:
        """One decoded request -> its reply dict (never raises)."""
        mid = msg.get("id")
        rid = mid if type(mid) is int else None

        def err(code, text):
            return {"v": PROTOCOL_VERSION, "id": rid, "ok": False, "error": text, "code": code}

        v = msg.get("v")
        if not (type(v) is int and v == PROTOCOL_VERSION):
            return err("bad_version", f"unsupported protocol version {v!r}; this server "
                                      f"speaks v{PROTOCOL_VERSION}")
        if type(mid) is not int:
            return err("bad_request", "'id' must be an integer")
        op = msg.get("op")
        if op not in OPS:
            return err("unknown_op", f"unknown op {op!r}; known: {', '.join(OPS)}")
        ok = {"v": PROTOCOL_VERSION, "id": mid, "ok": True}
        try:
            if op == "hello":
                versions = msg.get("versions", [PROTOCOL_VERSION])
                if not isinstance(versions, list) or PROTOCOL_VERSION not in versions:
                    return err("bad_version", f"client versions {versions!r} do not include "
                                              f"v{PROTOCOL_VERSION}")
                return {**ok, "server": self.name, "version": PROTOCOL_VERSION}
            if op == "move_paddle":
                try:
                    target = _vec3(msg.get("target_m"), "target_m")
                except ValueError as e:
                    return err("bad_request", str(e))
                self.position_m = target
                return {**ok, "position_m": self.position_m.tolist()}
            if op == "read_pose":
                return {**ok, "position_m": self.position_m.tolist(),
                        "rotation": self.rotation.tolist()}
            # read_force
            f = (np.zeros(3) if self.force_fn is None
                 else np.asarray(self.force_fn(self.position_m.copy()), dtype=np.float64))
            if f.shape != (3,) or not np.all(np.isfinite(f)):
                return err("internal", f"force_fn returned {f!r}, expected 3 finite numbers")
            return {**ok, "force_n": f.tolist()}
        except Exception as e:  # a broken callback must not take the server down
            return err("internal", f"{type(e).__name__}: {e}")

    def _reply_for_line(self, line: bytes) -> dict:
        try:
            msg = decode_message(line)
        except Exception as e:  # any line a client can send is refused, never fatal
            return {"v": PROTOCOL_VERSION, "id": None, "ok": False, "code": "bad_json",
                    "error": f"malformed JSON line: {e}"}
        with self._log_lock:
            self._log.append(msg)
        return self.handle(msg)

    # -- connection loop
    async def _serve_conn(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self._writers.add(writer)
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        buf = bytearray()
        discarding = False  # inside an over-long line: drop bytes up to its newline

        async def send(reply: dict):
            if not self.silent:
                try:
                    line = encode_message(reply, self.max_line_bytes)
                except ValueError as e:  # e.g. an error text quoting a huge field
                    line = encode_message({"v": PROTOCOL_VERSION, "id": reply.get("id"), "ok": False,
                                           "code": reply.get("code", "internal"),
                                           "error": f"reply not sendable: {e}"[:1000]})
                writer.write(line)
                await writer.drain()

        too_long = {"v": PROTOCOL_VERSION, "id": None, "ok": False, "code": "too_long",
                    "error": f"line exceeds {self.max_line_bytes} bytes"}
        try:
            while True:  # ends on EOF, connection error, or cancellation at stop()
                chunk = await reader.read(65536)
                if not chunk:
                    break
                buf += chunk
                while True:
                    nl = buf.find(b"\n")
                    if nl < 0:
                        if len(buf) > self.max_line_bytes:
                            discarding = True
                            buf.clear()  # never buffer more than one line's worth
                        break
                    line = bytes(buf[:nl]).rstrip(b"\r")
                    del buf[:nl + 1]
                    self.n_lines += 1
                    if discarding or len(line) > self.max_line_bytes:
                        discarding = False
                        await send(too_long)
                        continue
                    if not line.strip():
                        continue  # blank keep-alive line
                    await send(self._reply_for_line(line))
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # only stop_async cancels us; end normally, because asyncio (3.11) calls
            # task.exception() on a finished connection task, which re-raises a
            # cancellation as a logged "Exception in callback"
            pass
        finally:
            self._writers.discard(writer)
            if task is not None:
                self._tasks.discard(task)
            writer.close()

    # -- lifecycle in a running loop
    async def start_async(self) -> "SimulatedRobotServer":
        """Bind and start serving in the current event loop; sets ``.port``."""
        self._server = await asyncio.start_server(self._serve_conn, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def drop_connections_async(self) -> int:
        n = len(self._writers)
        for w in list(self._writers):
            w.close()
        return n

    async def stop_async(self) -> None:
        if self._server is not None:
            self._server.close()
        # closing the transports makes every reader see EOF, so connection tasks end
        # on their own; cancel only those still running after a short grace period
        await self.drop_connections_async()
        tasks = list(self._tasks)
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=0.5)
            for t in pending:
                t.cancel()
            if pending:
                await asyncio.wait(pending, timeout=1.5)
        if self._server is not None:
            await asyncio.wait_for(self._server.wait_closed(), timeout=2.0)

    # -- lifecycle in a background thread
    def start(self, timeout_s: float = 5.0) -> "SimulatedRobotServer":
        """Serve from a daemon thread with its own event loop; returns once bound."""
        if self._thread is not None:
            raise RuntimeError("server already started")
        self._ready.clear()
        self._thread = threading.Thread(target=self._run_thread, daemon=True,
                                        name=f"{self.name}:loop")
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"simulated robot server did not start within {timeout_s} s")
        if self._start_error is not None:
            raise RuntimeError("simulated robot server failed to start") from self._start_error
        return self

    def _run_thread(self):
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._thread_main())
        finally:
            loop.close()

    async def _thread_main(self):
        self._stop_event = asyncio.Event()
        try:
            await self.start_async()
        except BaseException as e:
            self._start_error = e
            self._ready.set()
            return
        self._ready.set()
        await self._stop_event.wait()
        await self.stop_async()

    def drop_connections(self, timeout_s: float = 2.0) -> int:
        """Close every client connection now (thread mode); returns how many."""
        if self._loop is None:
            raise RuntimeError("server not running in a thread")
        fut = asyncio.run_coroutine_threadsafe(self.drop_connections_async(), self._loop)
        return fut.result(timeout_s)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread-mode server and join its thread (bounded by ``timeout_s``)."""
        if self._thread is None:
            return
        if self._loop is not None and self._stop_event is not None and not self._loop.is_closed():
            try:
                self._loop.call_soon_threadsafe(self._stop_event.set)
            except RuntimeError:
                pass  # loop already closed
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise RuntimeError(f"simulated robot server did not stop within {timeout_s} s")
        self._thread = None

    def __enter__(self) -> "SimulatedRobotServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


# ----------------------------------------------------------------------------- client


class RobotClient:
    """Blocking robot client, usable from a notebook (no event loop needed).

    Every call is bounded in time: a server that does not answer within ``timeout_s``
    raises :class:`LinkTimeout` (the socket is then dropped, since a late reply would
    desynchronise the stream; the next call reconnects). A dropped connection is
    re-opened -- with the hello handshake -- up to ``max_reconnects`` times per call, then
    :class:`LinkClosed`. Requests are resent after a reconnect, which is safe because all
    ops are idempotent (``move_paddle`` targets are absolute).

    With ``safety`` set, :meth:`move_paddle` checks the target against the workspace box
    and the step from the last commanded target BEFORE sending; a violation raises
    :class:`SafetyError` and nothing goes on the wire.

    Requests are serialised by an internal lock, but ``last_commanded_m`` is per client:
    give each thread that moves the paddle its own view of it, or share one client.
    """

    def __init__(self, host: str = "127.0.0.1", port: int | None = None, *, timeout_s: float = 2.0,
                 connect_timeout_s: float | None = None, max_reconnects: int = 3,
                 reconnect_delay_s: float = 0.05, safety: SafetyLimits | None = None,
                 client_name: str = "jaxrkpm", max_line_bytes: int = MAX_LINE_BYTES):
        if port is None or not (0 < int(port) < 65536):
            raise ValueError(f"port must be a TCP port number (1-65535); got {port!r}")
        if not (timeout_s > 0):
            raise ValueError("timeout_s must be > 0")
        if max_reconnects < 0:
            raise ValueError("max_reconnects must be >= 0")
        self.host, self.port = host, int(port)
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(connect_timeout_s or timeout_s)
        self.max_reconnects = int(max_reconnects)
        self.reconnect_delay_s = float(reconnect_delay_s)
        self.safety = safety
        self.client_name = client_name
        self.max_line_bytes = int(max_line_bytes)
        self.server_info: dict | None = None
        self.last_commanded_m: np.ndarray | None = None
        self.n_reconnects = 0
        self._sock: socket.socket | None = None
        self._buf = bytearray()
        self._next_id = 0
        self._lock = threading.Lock()

    # -- connection management
    @property
    def connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> dict:
        """Open the connection, do the hello handshake and read the current pose (so the
        first step is checked against where the paddle really is). Returns hello's reply."""
        with self._lock:
            try:
                self._ensure_connected()
            except LinkError:
                raise
            except socket.timeout as e:
                raise LinkTimeout(f"connecting to {self.host}:{self.port} timed out after "
                                  f"{self.connect_timeout_s} s") from e
            except OSError as e:  # refused, unreachable, reset during the handshake
                raise LinkClosed(f"cannot connect to {self.host}:{self.port}: {e}") from e
        if self.last_commanded_m is None:
            self.last_commanded_m = self.read_pose().position_m
        assert self.server_info is not None
        return self.server_info

    def close(self) -> None:
        self._drop()

    def __enter__(self) -> "RobotClient":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _drop(self):
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock = None
        self._buf.clear()

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id

    def _open_and_handshake(self):
        sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # small request/reply
        self._sock, self._buf = sock, bytearray()
        mid = self._new_id()
        self._send({"v": PROTOCOL_VERSION, "id": mid, "op": "hello",
                    "versions": [PROTOCOL_VERSION], "client": self.client_name})
        self.server_info = self._checked_hello(self._await_reply(mid, time.monotonic() + self.timeout_s))

    def _checked_hello(self, reply: dict) -> dict:
        if not isinstance(reply.get("server"), str) or reply.get("version") != PROTOCOL_VERSION \
                or type(reply.get("version")) is not int:
            raise ProtocolError(f"hello reply from {self.host}:{self.port} needs 'server' (str) and "
                                f"'version' {PROTOCOL_VERSION}: {str(reply)[:200]}")
        return reply

    def _ensure_connected(self):
        if self._sock is None:
            try:
                self._open_and_handshake()
            except BaseException:
                self._drop()
                raise

    # -- wire
    def _send(self, msg: dict):
        data = encode_message(msg, self.max_line_bytes)
        assert self._sock is not None
        self._sock.settimeout(self.timeout_s)
        try:
            self._sock.sendall(data)
        except socket.timeout as e:
            raise LinkTimeout(f"sending to {self.host}:{self.port} timed out after "
                              f"{self.timeout_s} s") from e

    def _recv_line(self, deadline: float) -> bytes:
        assert self._sock is not None
        while True:  # each pass returns, raises, or grows the buffer; deadline bounds it
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line = bytes(self._buf[:nl])
                del self._buf[:nl + 1]
                return line
            if len(self._buf) > self.max_line_bytes:
                raise LinkError(f"reply line over {self.max_line_bytes} bytes")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LinkTimeout(f"no reply from {self.host}:{self.port} within "
                                  f"{self.timeout_s} s")
            self._sock.settimeout(remaining)
            try:
                chunk = self._sock.recv(65536)
            except socket.timeout as e:
                raise LinkTimeout(f"no reply from {self.host}:{self.port} within "
                                  f"{self.timeout_s} s") from e
            if not chunk:
                raise ConnectionResetError("server closed the connection")
            self._buf += chunk

    def _await_reply(self, mid: int, deadline: float) -> dict:
        while True:  # bounded by the deadline inside _recv_line
            line = self._recv_line(deadline)
            if not line.strip():
                continue
            try:
                reply = decode_message(line)
            except ValueError as e:
                raise LinkError(f"malformed reply from server: {e}") from e
            rid = reply.get("id")
            if rid is not None and rid != mid:
                continue  # stale reply to an earlier, timed-out request
            if reply.get("v") != PROTOCOL_VERSION:
                raise LinkError(f"server replied with protocol version {reply.get('v')!r}")
            if not isinstance(reply.get("ok"), bool):
                raise ProtocolError(f"reply has no boolean 'ok' field: {str(reply)[:200]}")
            if not reply["ok"]:
                raise RemoteError(f"server refused the request: {reply.get('error')}",
                                  reply.get("code"), reply)
            return reply

    def request(self, op: str, **fields) -> dict:
        """Send one request and return the ok reply (raises RemoteError / LinkTimeout /
        LinkClosed). Reconnects (bounded) if the connection drops."""
        with self._lock:
            mid = self._new_id()
            msg = {"v": PROTOCOL_VERSION, "id": mid, "op": op, **fields}
            encode_message(msg, self.max_line_bytes)  # refuse unsendable input up front
            failures = 0
            while True:  # at most max_reconnects + 1 passes
                try:
                    self._ensure_connected()
                    self._send(msg)
                    return self._await_reply(mid, time.monotonic() + self.timeout_s)
                except LinkTimeout:
                    self._drop()
                    raise
                except RemoteError:
                    raise  # the server refused this request; the connection is fine
                except LinkError:
                    self._drop()  # garbled stream: resynchronise on a fresh connection
                    raise
                except (ConnectionError, OSError) as e:
                    self._drop()
                    failures += 1
                    if failures > self.max_reconnects:
                        raise LinkClosed(f"connection to {self.host}:{self.port} lost and "
                                         f"{self.max_reconnects} reconnect attempts failed: "
                                         f"{e}") from e
                    self.n_reconnects += 1
                    time.sleep(self.reconnect_delay_s * failures)

    # -- ops
    def hello(self) -> dict:
        return self._checked_hello(self.request("hello", versions=[PROTOCOL_VERSION], client=self.client_name))

    def _field(self, reply: dict, name: str, parse=_vec3) -> np.ndarray:
        """A validated reply field; ProtocolError if it is missing or malformed."""
        try:
            return parse(reply[name], name)
        except (KeyError, ValueError) as e:
            what = "missing" if isinstance(e, KeyError) else str(e)
            raise ProtocolError(f"reply to {reply.get('id')!r} from {self.host}:{self.port}: "
                                f"field {name!r} {what}") from None

    def read_pose(self) -> Pose:
        r = self.request("read_pose")
        return Pose(self._field(r, "position_m"), self._field(r, "rotation", _matrix3))

    def read_force(self) -> np.ndarray:
        """(3,) contact force in newtons."""
        return self._field(self.request("read_force"), "force_n")

    def move_paddle(self, target_m) -> np.ndarray:
        """Command the paddle to displacement ``target_m`` (3,) metres from its reference.

        Checked against ``safety`` before sending (:class:`SafetyError`, nothing sent).
        Returns the position the server reports, (3,) metres.
        """
        t = np.asarray(target_m, dtype=np.float64)
        if t.shape != (3,):
            raise SafetyError(f"target_m must have shape (3,); got {t.shape}")
        if not np.all(np.isfinite(t)):
            raise SafetyError(f"target_m must be finite; got {t.tolist()}")
        if self.safety is not None:
            if self.last_commanded_m is None:
                # the step check needs a reference: where the paddle is now
                self.last_commanded_m = self.read_pose().position_m
            self.safety.check(t, self.last_commanded_m)
        r = self.request("move_paddle", target_m=t.tolist())
        self.last_commanded_m = t.copy()
        return self._field(r, "position_m")
