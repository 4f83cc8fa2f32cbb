"""A device that answers in another protocol version: the host says so in one line, first,
instead of timing out on frames it silently rejects."""
import socket
import subprocess
import sys
import threading

import pytest

from imubench.device.link import Device, ProtocolVersionError
from imubench.wire import frame as P
from imubench.wire.protocol_gen import PROTOCOL_VERSION, MsgType


class OtherVersionDevice:
    """A TCP 'device' that answers every byte it receives with an intact frame of `version`."""

    def __init__(self, version: int):
        self.version = version
        self.srv = socket.socket()
        self.srv.bind(("127.0.0.1", 0))
        self.srv.listen(1)
        self.url = f"socket://127.0.0.1:{self.srv.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        try:
            c, _ = self.srv.accept()
        except OSError:
            return
        with c:
            c.settimeout(10)
            try:
                while c.recv(4096):
                    c.sendall(P.build_frame(MsgType.ACK, bytes(8), 1, 0, version=self.version))
            except OSError:
                pass

    def close(self):
        self.srv.close()


@pytest.mark.parametrize("version", [PROTOCOL_VERSION + 1, PROTOCOL_VERSION - 1])
def test_device_of_another_protocol_version_is_named_at_once(version):
    dev_srv = OtherVersionDevice(version)
    try:
        with pytest.raises(ProtocolVersionError) as e, Device.open(dev_srv.url, timeout=5.0) as dev:
            dev.info()
        assert e.value.device_version == version
        assert f"protocol version {version}" in str(e.value) and f"version {PROTOCOL_VERSION}" in str(e.value)
    finally:
        dev_srv.close()


def test_info_says_it_in_one_line_before_anything_else():
    dev_srv = OtherVersionDevice(PROTOCOL_VERSION + 1)
    try:
        r = subprocess.run([sys.executable, "-m", "imubench", "info", "--port", dev_srv.url],
                           capture_output=True, text=True, timeout=60)
    finally:
        dev_srv.close()
    assert r.returncode == 1
    assert r.stdout == ""
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("imubench info: error: the device on socket://127.0.0.1:")
    assert f"speaks protocol version {PROTOCOL_VERSION + 1}" in lines[0]
    assert "install a newer imubench" in lines[0]
