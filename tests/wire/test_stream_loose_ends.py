"""Issue 25, the stream's last loose ends: a time step of exactly 2^31 us, decode --json of a
hostile stream, a socket:// URL without a port, a newer firmware's info, and the temporary
folder of a virtual device whose host was killed. (The values no definition allows are the
shared vectors' cases, checked against both codecs in tests/wire/test_protocol_vectors.py.) Each
test here failed on main 0ea9400."""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from imubench.cli.main import main as imubench
from imubench.wire import frame as P
from imubench.wire import protocol_gen as G
from imubench.wire.decoder import decode_bytes
from test_decoder_stream_rules import PERIOD_US, raw_batch

H = 1 << 31


def test_a_step_of_exactly_2_31_us_is_the_same_step_back_whichever_way_it_wraps():
    """SPEC.md: the step is taken modulo 2^32 in [-2^31, 2^31); on main a step of 2^31 without a
    wrap of the 32-bit value was forward (delivered) and the same step across the wrap backward."""
    results = []
    for t0 in (0x100, H + 0x100):                  # the second one wraps the u32 value
        data = raw_batch(1, 0, ts=t0) + raw_batch(2, 16, ts=(t0 + H) & 0xFFFFFFFF)
        _, raw, _, s = decode_bytes(data)
        results.append((len(raw), s.batches_time_backwards, s.samples_rejected))
    assert results[0] == results[1] == (16, 1, 16)
    # a step one microsecond short of it is forward, and delivered, both ways
    for t0 in (0x100, H + 0x100):
        _, raw, _, s = decode_bytes(raw_batch(1, 0, ts=t0) + raw_batch(2, 16, ts=(t0 + H - 1) & 0xFFFFFFFF))
        assert len(raw) == 32 and s.batches_time_backwards == 0 and s.samples_missing == 0


def test_decode_json_of_a_hostile_stream_is_valid_json(tmp_path, capsys):
    """On main an empty batch was delivered and its mean (NaN) ended `decode --json` in an
    internal error ("Out of range float values are not JSON compliant")."""
    cap = tmp_path / "c.bin"
    cap.write_bytes(raw_batch(1, 0, ts=1000) + raw_batch(2, 16, n=0, ts=1000 + 16 * PERIOD_US))
    assert imubench(["decode", str(cap), "--json"]) == 0
    out = capsys.readouterr()
    d = json.loads(out.out)
    assert d["raw"]["samples"] == 16 and d["decoder"]["out_of_range"] == 1 and out.err == ""
    from imubench.cli.stream import _finite_or_null
    assert _finite_or_null({"a": [1.0, float("inf")], "b": float("nan"), "c": 2}) == {"a": [1.0, None], "b": None,
                                                                                       "c": 2}


def test_a_socket_url_without_a_port_is_one_line(capsys):
    for url, needle in (("socket://localhost", "socket://localhost names no TCP port; give socket://HOST:PORT"),
                        ("rfc2217://localhost:abc", "the port is not a number from 1 to 65535")):
        assert imubench(["info", "--port", url]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err and "not supported between" not in err, err


def _newer_firmware(info_fields: dict):
    """A device on 127.0.0.1 (an ephemeral port) that answers get_info with an intact info
    holding info_fields (values this host's definition does not have), then its ack."""
    srv = socket.create_server(("127.0.0.1", 0))

    def serve():
        conn, _ = srv.accept()
        with conn:
            buf, seq = b"", 0
            while True:
                chunk = conn.recv(4096)
                if not chunk:
                    return
                buf += chunk
                *frames, buf = buf.split(b"\0")
                for fr in filter(None, frames):
                    f = P.parse_frame(fr)
                    if f.type != G.MsgType.GET_INFO:
                        continue
                    info = G.Info(request_id=f.seq, protocol_version=P.PROTOCOL_VERSION, board=1, clock_source=1,
                                  sensors_present=0b1111, accel_range_g=2, stream_state=0, param_source=0)
                    conn.sendall(P.encode(dataclasses.replace(info, **info_fields), seq, 0)
                                 + P.encode(G.Ack(request_id=f.seq, command=G.MsgType.GET_INFO, error=0), seq + 1, 0))
                    seq += 2
    threading.Thread(target=serve, daemon=True).start()
    return srv


def test_a_newer_firmwares_info_is_named_not_called_a_damaged_link(capsys):
    for fields, needle in (({"clock_source": 9}, "newer firmware: unknown value 9 for clock_source"),
                           ({"sensors_present": 0x3F}, "newer firmware: unknown bits 0x30 in sensors_present")):
        srv = _newer_firmware(fields)
        with srv:
            t0 = time.monotonic()
            code = imubench(["info", "--port", f"socket://127.0.0.1:{srv.getsockname()[1]}"])
        err = capsys.readouterr().err
        assert code == 1 and err.count("\n") == 1, err
        assert needle in err and "damaged" not in err, err
        assert time.monotonic() - t0 < 5           # said at the first answer, not after the retries


def test_a_killed_hosts_virtual_device_folder_does_not_stay(tmp_path):
    """A host killed with SIGKILL cannot remove its virtual device's folder; on main it stayed
    for ever. Now the sim, which watches its parent, removes it when the parent is gone."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    host = subprocess.Popen([sys.executable, "-c",
                             "import time\nfrom imubench.device.sim import VirtualBench\n"
                             "vb = VirtualBench(speed=1)\nprint(vb._tmpdir, vb.proc.pid, flush=True)\ntime.sleep(120)"],
                            env=env, stdout=subprocess.PIPE, text=True)
    try:
        folder, sim_pid = host.stdout.readline().split()
        assert os.path.isdir(folder) and os.path.dirname(folder) == str(tmp_path)
        assert sorted(os.listdir(folder)) == ["flash.bin", "owner.json", "sim.log"]
    finally:
        host.send_signal(signal.SIGKILL)
        host.wait(timeout=10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and (os.path.exists(folder) or os.path.exists(f"/proc/{sim_pid}")):
        time.sleep(0.05)
    assert not os.path.exists(folder) and not os.path.exists(f"/proc/{sim_pid}")
    assert list(tmp_path.iterdir()) == []


def test_folders_of_dead_owners_are_swept_by_the_next_virtual_device(tmp_path):
    """Where the sim could not clean up (the ARM targets, a sim killed too), the next virtual
    device removes the folders whose owner is dead, and only those."""
    from imubench.device.sim import TMP_PREFIX
    from imubench.device.tmpdirs import OWNER_FILE, _start_time
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    gone = {"pid": int(dead.stdout), "started": "1"}
    folders = {}
    for name, owner in (("dead", gone), ("alive", {"pid": os.getpid(), "started": _start_time(os.getpid())}),
                        ("reused", {"pid": os.getpid(), "started": "1"}), ("no-owner", None)):
        d = tmp_path / f"{TMP_PREFIX}{name}"
        d.mkdir()
        (d / "sim.log").write_text("x")
        if owner is not None:
            (d / OWNER_FILE).write_text(json.dumps(owner))
        folders[name] = d
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    subprocess.run([sys.executable, "-c", "from imubench.device.sim import VirtualBench\n"
                    "VirtualBench(start=False).close()"], env=env, check=True, timeout=60)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{TMP_PREFIX}alive", f"{TMP_PREFIX}no-owner"]
