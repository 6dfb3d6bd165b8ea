"""Robot link (JSON lines over TCP, loopback only): protocol round trip, refusal of bad
input without losing the connection, model-side safety limits, timeouts, reconnects.

Every server runs in a background thread with its own event loop, binds 127.0.0.1 on an
ephemeral port and is stopped at test end; every socket read has a timeout."""

import logging
import socket
import time

import numpy as np
import pytest

from jaxrkpm.rig.link import MAX_LINE_BYTES, LinkClosed, LinkTimeout, RemoteError, RobotClient, SafetyError, SafetyLimits, SimulatedRobotServer, encode_message

from .lines import read_reply

STIFFNESS_N_PER_M = 250.0   # simulated object: a linear spring on the paddle


def spring_force(position_m):
    return -STIFFNESS_N_PER_M * position_m


@pytest.fixture
def server(caplog):
    srv = SimulatedRobotServer(force_fn=spring_force).start()
    try:
        yield srv
    finally:
        srv.stop()
    # the server thread must neither crash nor leave asyncio errors behind at shutdown
    errors = [r.getMessage() for r in caplog.records
              if r.name == "asyncio" and r.levelno >= logging.ERROR]
    assert errors == []


@pytest.fixture
def raw(server):
    """A plain socket to the server and a helper sending one line and reading one reply."""
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=2.0)
    buf = bytearray()

    def ask(line: bytes) -> dict:
        sock.sendall(line)
        return read_reply(sock, buf)

    try:
        yield ask
    finally:
        sock.close()


def test_round_trip(server):
    with RobotClient(port=server.port, timeout_s=1.0) as c:
        assert c.server_info["version"] == 1 and c.server_info["ok"] is True
        assert np.array_equal(c.last_commanded_m, np.zeros(3))   # read at connect
        pos = c.move_paddle([0.01, -0.005, 0.0])
        assert np.allclose(pos, [0.01, -0.005, 0.0], atol=0, rtol=0)
        pose = c.read_pose()
        assert np.array_equal(pose.position_m, [0.01, -0.005, 0.0])
        assert np.array_equal(pose.rotation, np.eye(3))
        f = c.read_force()
        assert np.allclose(f, [-2.5, 1.25, 0.0], atol=1e-12)
        assert c.hello()["server"] == server.name
    ops = [m["op"] for m in server.messages()]
    assert ops == ["hello", "read_pose", "move_paddle", "read_pose", "read_force", "hello"]
    assert all(m["v"] == 1 and type(m["id"]) is int for m in server.messages())
    assert len({m["id"] for m in server.messages()}) == 6            # ids are unique


def test_malformed_json_refused_connection_survives(raw):
    r = raw(b'{"v": 1, "id": 3, "op": "read_pose"\n')                # truncated
    assert r["ok"] is False and r["code"] == "bad_json" and r["id"] is None
    r = raw(b"[1, 2, 3]\n")                                          # not an object
    assert r["ok"] is False and r["code"] == "bad_json"
    r = raw(b'{"v": 1, "id": 4, "op": "move_paddle", "target_m": [NaN, 0, 0]}\n')
    assert r["ok"] is False and r["code"] == "bad_json"
    r = raw(b"\xff\xfe garbage\n")
    assert r["ok"] is False and r["code"] == "bad_json"
    r = raw(b'{"v": 1, "id": 5, "op": "read_pose"}\n')
    assert r["ok"] is True and r["id"] == 5 and r["position_m"] == [0.0, 0.0, 0.0]


def test_unknown_op_and_bad_fields_refused(raw):
    r = raw(b'{"v": 1, "id": 7, "op": "self_destruct"}\n')
    assert (r["ok"], r["code"], r["id"]) == (False, "unknown_op", 7)
    assert "self_destruct" in r["error"]
    r = raw(b'{"v": 1, "id": "x", "op": "read_pose"}\n')
    assert (r["ok"], r["code"]) == (False, "bad_request")
    r = raw(b'{"v": 1, "id": 8, "op": "move_paddle", "target_m": [1, 2]}\n')
    assert (r["ok"], r["code"], r["id"]) == (False, "bad_request", 8)
    r = raw(b'{"v": 1, "id": 9, "op": "move_paddle", "target_m": [0.001, 0, true]}\n')
    assert (r["ok"], r["code"]) == (False, "bad_request")
    r = raw(b'{"v": 1, "id": 10, "op": "read_force"}\n')
    assert r["ok"] is True and r["force_n"] == [0.0, 0.0, 0.0]


def test_wrong_version_refused(raw):
    r = raw(b'{"v": 2, "id": 11, "op": "read_pose"}\n')
    assert (r["ok"], r["code"], r["id"]) == (False, "bad_version", 11)
    r = raw(b'{"id": 12, "op": "read_pose"}\n')                      # no version at all
    assert (r["ok"], r["code"]) == (False, "bad_version")
    r = raw(b'{"v": true, "id": 13, "op": "read_pose"}\n')          # true == 1 in Python
    assert (r["ok"], r["code"]) == (False, "bad_version")
    r = raw(b'{"v": 1, "id": 14, "op": "hello", "versions": [2, 3]}\n')
    assert (r["ok"], r["code"]) == (False, "bad_version")
    r = raw(b'{"v": 1, "id": 15, "op": "hello", "versions": [1]}\n')
    assert r["ok"] is True and r["version"] == 1


def test_oversized_line_refused(raw):
    big = b'{"v": 1, "id": 16, "op": "read_pose", "pad": "' + b"x" * (MAX_LINE_BYTES + 10) + b'"}\n'
    r = raw(big)
    assert (r["ok"], r["code"]) == (False, "too_long")
    # an over-long line arriving in pieces, the newline much later, also gives ONE refusal
    r = raw(b"y" * (3 * MAX_LINE_BYTES) + b"\n" + b'{"v": 1, "id": 17, "op": "read_pose"}\n')
    assert (r["ok"], r["code"]) == (False, "too_long")
    r = raw(b"")                                                     # the queued reply
    assert r["ok"] is True and r["id"] == 17
    # a line just under the limit is fine
    pad = MAX_LINE_BYTES - 100
    r = raw(b'{"v": 1, "id": 18, "op": "read_pose", "pad": "' + b"z" * pad + b'"}\n')
    assert r["ok"] is True and r["id"] == 18


def test_remote_error_through_client_keeps_connection(server):
    with RobotClient(port=server.port, timeout_s=1.0) as c:
        with pytest.raises(RemoteError) as ei:
            c.request("dance")
        assert ei.value.code == "unknown_op"
        assert c.connected and c.n_reconnects == 0
        assert np.array_equal(c.read_pose().position_m, np.zeros(3))


def test_broken_force_callback_is_an_error_reply_not_a_crash():
    def bad_force(_):
        raise RuntimeError("sensor unplugged")

    with SimulatedRobotServer(force_fn=bad_force) as srv, RobotClient(port=srv.port) as c:
        with pytest.raises(RemoteError, match="sensor unplugged") as ei:
            c.read_force()
        assert ei.value.code == "internal"
        assert np.array_equal(c.read_pose().position_m, np.zeros(3))


# ----------------------------------------------------------------------------- safety


def test_safety_limits_refuse_before_sending(server):
    limits = SafetyLimits(workspace_min_m=[-0.05, -0.05, -0.01],
                          workspace_max_m=[0.05, 0.05, 0.01], max_step_m=0.01)
    with RobotClient(port=server.port, timeout_s=1.0, safety=limits) as c:
        c.move_paddle([0.005, 0.0, 0.0])
        c.move_paddle([0.012, 0.005, 0.0])                  # step 0.0086 m: allowed
        n_before = len(server.messages())
        with pytest.raises(SafetyError, match="outside the workspace"):
            c.move_paddle([0.06, 0.005, 0.0])               # outside the box
        with pytest.raises(SafetyError, match="exceeds max_step_m"):
            c.move_paddle([0.012, 0.02, 0.0])               # 0.015 m step, inside the box
        with pytest.raises(SafetyError, match="finite"):
            c.move_paddle([np.nan, 0.0, 0.0])
        with pytest.raises(SafetyError, match="shape"):
            c.move_paddle([0.0, 0.0])
        assert len(server.messages()) == n_before           # the server saw nothing
        assert np.array_equal(server.position_m, [0.012, 0.005, 0.0])
        assert np.array_equal(c.last_commanded_m, [0.012, 0.005, 0.0])


def test_safety_limits_validation():
    with pytest.raises(ValueError):
        SafetyLimits([0, 0, 0], [0, 1, 1], 0.01)            # empty box
    with pytest.raises(ValueError):
        SafetyLimits([0, 0, 0], [1, 1, 1], 0.0)
    with pytest.raises(ValueError):
        SafetyLimits([0, 0], [1, 1], 0.1)


# ----------------------------------------------------------------------------- failures


def test_silent_server_gives_link_timeout_not_a_hang(server):
    timeout_s = 0.3
    c = RobotClient(port=server.port, timeout_s=timeout_s)
    c.connect()
    server.silent = True
    try:
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout):
            c.read_pose()
        elapsed = time.monotonic() - t0
        assert 0.9 * timeout_s <= elapsed < 2 * timeout_s
        assert not c.connected                               # desynchronised socket dropped
        # connecting to a server that accepts but never answers the hello also times out
        c2 = RobotClient(port=server.port, timeout_s=timeout_s)
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout):
            c2.connect()
        assert time.monotonic() - t0 < 2 * timeout_s
        server.silent = False                                # it answers again: recover
        assert np.array_equal(c.read_pose().position_m, np.zeros(3))
    finally:
        c.close()


def test_reconnect_after_server_drops_connection(server):
    with RobotClient(port=server.port, timeout_s=1.0, max_reconnects=3) as c:
        c.move_paddle([0.002, 0.0, 0.0])
        assert server.drop_connections() == 1
        time.sleep(0.05)                                      # let the FIN arrive
        pose = c.read_pose()                                  # reconnects transparently
        assert np.array_equal(pose.position_m, [0.002, 0.0, 0.0])
        assert c.n_reconnects >= 1
        assert [m["op"] for m in server.messages()][-2:] == ["hello", "read_pose"]


def test_reconnect_is_bounded_when_server_is_gone(caplog):
    srv = SimulatedRobotServer().start()
    c = RobotClient(port=srv.port, timeout_s=0.5, max_reconnects=2, reconnect_delay_s=0.01)
    c.connect()
    t0 = time.monotonic()
    srv.stop()                                   # with the client still connected
    assert time.monotonic() - t0 < 1.0
    assert [r.getMessage() for r in caplog.records if r.name == "asyncio"] == []
    t0 = time.monotonic()
    with pytest.raises(LinkClosed, match="2 reconnect attempts"):
        c.read_pose()
    assert time.monotonic() - t0 < 1.0
    c.close()


def test_server_binds_loopback_only_and_encoder_refuses_nan():
    with pytest.raises(ValueError, match="loopback"):
        SimulatedRobotServer(host="0.0.0.0")
    with pytest.raises(ValueError):
        encode_message({"v": 1, "id": 1, "op": "move_paddle", "target_m": [float("nan"), 0, 0]})
    srv = SimulatedRobotServer().start()
    try:
        assert srv.port > 0
        assert srv._server.sockets[0].getsockname()[0] == "127.0.0.1"
    finally:
        srv.stop()
