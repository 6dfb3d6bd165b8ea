"""Hostile input to the rig (issue 18): the link server survives any single line, the client
validates every reply field and raises LinkError subclasses only, and stereo detection names
bad images (dtype, NaN pixels, empty) instead of crashing in OpenCV or blaming occlusion.

Servers bind 127.0.0.1 on an ephemeral port, run in a background thread and are stopped at
test end; every socket read has a timeout."""
import json
import socket

import numpy as np
import pytest

from jaxrkpm.rig.link import LinkClosed, LinkError, ProtocolError, RobotClient, SimulatedRobotServer
from jaxrkpm.rig.stereo import StereoTracker, ParallelStereo, detect_blobs, draw_blobs, render_markers

from .lines import read_reply


def test_deeply_nested_line_is_refused_and_the_connection_stays():
    with SimulatedRobotServer() as srv:
        sock = socket.create_connection(("127.0.0.1", srv.port), timeout=3.0)
        buf = bytearray()
        try:
            sock.sendall(b"[" * 60000 + b"\n")
            r = read_reply(sock, buf)
            assert (r["ok"], r["code"]) == (False, "bad_json") and "nested" in r["error"]
            sock.sendall(b'{"v": 1, "id": 2, "op": "read_pose"}\n')
            r = read_reply(sock, buf)
            assert r["ok"] is True and r["id"] == 2
            # an error text quoting a huge field is cut to a line, not a dropped connection
            sock.sendall(json.dumps({"v": 1, "id": 3, "op": "x" * 60000}).encode() + b"\n")
            r = read_reply(sock, buf)
            assert (r["ok"], r["id"], r["code"]) == (False, 3, "unknown_op")
        finally:
            sock.close()


def test_huge_integer_target_is_a_bad_request():
    srv = SimulatedRobotServer()
    r = srv.handle({"v": 1, "id": 1, "op": "move_paddle", "target_m": [10**400, 0, 0]})
    assert (r["ok"], r["code"]) == (False, "bad_request") and "too large" in r["error"]
    assert np.array_equal(srv.position_m, np.zeros(3))


class _Lying(SimulatedRobotServer):
    """Once ``lying`` is set, answers ok with one reply field replaced (None: removed)."""

    def __init__(self, field, value):
        super().__init__()
        self.field, self.value, self.lying = field, value, False

    def handle(self, msg):
        r = super().handle(msg)
        if self.lying and r.get("ok") and self.field in r:
            if self.value is None:
                del r[self.field]
            else:
                r[self.field] = self.value
        return r


@pytest.mark.parametrize("field, value, call", [
    ("position_m", None, "read_pose"),
    ("rotation", [[1, 0, 0], [0, 1]], "read_pose"),
    ("force_n", ["a", 0, 0], "read_force"),
    ("position_m", [0, 0], "move_paddle"),
    ("ok", "yes", "read_force"),
    ("server", None, "hello"),
])
def test_client_validates_every_reply_field(field, value, call):
    with _Lying(field, value) as srv:
        with RobotClient(port=srv.port, timeout_s=2.0) as c:
            srv.lying = True       # after the handshake and the pose read of connect()
            fn = {"read_pose": c.read_pose, "read_force": c.read_force, "hello": c.hello,
                  "move_paddle": lambda: c.move_paddle([0.0, 0.0, 0.001])}[call]
            with pytest.raises(ProtocolError, match=repr(field)) as err:
                fn()
            assert isinstance(err.value, LinkError)


def test_connect_to_a_closed_port_names_host_and_port():
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()                        # nothing listens there now
    with pytest.raises(LinkClosed, match=f"127.0.0.1:{port}"):
        RobotClient(port=port, timeout_s=1.0).connect()


def test_float64_colour_image_is_detected_like_its_grey_version():
    uv = np.array([[20.3, 15.7], [41.0, 30.2]])
    grey = draw_blobs((64, 48), uv)
    colour = np.repeat(grey[:, :, None], 3, axis=2).astype(np.float64)
    np.testing.assert_allclose(detect_blobs(colour), detect_blobs(grey), atol=1e-9)
    np.testing.assert_allclose(detect_blobs(colour), uv, atol=0.05)


def test_nan_pixel_and_empty_image_are_named():
    img = draw_blobs((64, 48), [[20, 20], [40, 30]]).astype(float)
    img[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        detect_blobs(img)
    cam = ParallelStereo.bumblebee_like()
    left, right = render_markers(np.array([[0.0, 0.0, 1.0]]), cam, rng=np.random.default_rng(0))
    left = left.astype(float)
    left[5, 5] = np.nan
    with pytest.raises(ValueError, match="NaN") as err:
        StereoTracker(cam, 1).track(left, right)
    assert "occlu" not in str(err.value)
    with pytest.raises(ValueError, match="empty"):
        detect_blobs(np.zeros((0, 0), np.uint8))
