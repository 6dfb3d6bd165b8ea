"""Reading the robot link's line protocol from a raw socket in tests."""
import json


def read_reply(sock, buf: bytearray) -> dict:
    """The next reply line on ``sock`` (``buf`` keeps what arrived after it), parsed."""
    for _ in range(1000):               # bounded; each recv is bounded by the socket timeout
        nl = buf.find(b"\n")
        if nl >= 0:
            line = bytes(buf[:nl])
            del buf[:nl + 1]
            return json.loads(line)
        chunk = sock.recv(65536)
        assert chunk, "server closed the connection"
        buf.extend(chunk)
    raise AssertionError("no reply line")
