"""The station page attacked as a hostile party would (issue 25, "The page"), only ever against
127.0.0.1 and in bounded loops: a foreign Host (DNS rebinding, also in a real Chromium with a
host-resolver rule), cross-site and simple requests, tokens from a body or a URL, ports that
are not a device (spy:// writing a file, socket:// anywhere), unbounded bodies, keys, boards,
clients and event streams, bad types. Every attack is refused with a 4xx and a one-line
reason, and the page keeps serving its operator, who keeps the device."""
from __future__ import annotations

import http.client
import http.server
import http.cookiejar
import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from imubench.station import state as S
from imubench.station.runner import Station, StationError
from imubench.station.security import MAX_BODY_BYTES, PortPolicy
from imubench.station.server import Server

DEVICE = "socket://127.0.0.1:1"          # nothing listens there: a started session fails at once


class Client:
    """A browser as the station's page uses it: the page's Origin, JSON, the session it got for
    a launch secret (sent in X-Imubench-Session), a cookie jar (which must stay empty)."""

    def __init__(self, server: Server, origin: str | None = None):
        self.server = server
        self.base = server.url
        self.origin = server.url.rstrip("/") if origin is None else origin
        self.session: str | None = None
        self.jar = http.cookiejar.CookieJar()
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(self.jar))

    def call(self, path: str, data=None, headers=None, raw: bytes | None = None):
        body = raw if raw is not None else None if data is None else json.dumps(data).encode()
        h = {"Content-Type": "application/json", **({"Origin": self.origin} if self.origin else {}),
             **({"X-Imubench-Session": self.session} if self.session else {}), **(headers or {})}
        req = urllib.request.Request(self.base + path, data=body, headers=h)
        try:
            with self.opener.open(req, timeout=20) as r:
                text = r.read().decode()
                return r.status, (json.loads(text) if r.headers.get_content_type() == "application/json" else text)
        except urllib.error.HTTPError as e:
            text = e.read().decode()
            return e.code, (json.loads(text) if e.headers.get_content_type() == "application/json" else text)

    def trade(self, secret: str):
        return self.call("api/session", {}, {"X-Imubench-Launch": secret})

    def open_session(self) -> "Client":
        """As the page does with the address the station printed: trade its secret."""
        code, body = self.trade(self.server.new_launch_url().split("#token=")[1])
        assert code == 200 and set(body) == {"session"}, body
        self.session = body["session"]
        return self


def raw_request(port: int, head: str, body: bytes = b"") -> tuple[int, str]:
    """One request written byte for byte (any Host, any header); the status and body."""
    with socket.create_connection(("127.0.0.1", port), timeout=20) as s:
        s.sendall(head.replace("\n", "\r\n").encode() + b"\r\n" + body)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head_out, _, rest = data.partition(b"\r\n\r\n")
    return int(head_out.split()[1]), rest.decode(errors="replace")


def error_of(code_body) -> str:
    code, body = code_body
    assert 400 <= code < 500, (code, body)
    text = body["error"] if isinstance(body, dict) else body
    assert text and "\n" not in text.strip() and "Traceback" not in text, text
    return text


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    station = Station(workdir=tmp_path_factory.mktemp("station"), allow_sim=False, history=False)
    server = Server(station).start()
    try:
        yield server
    finally:
        server.stop()
        station.close()


@pytest.fixture(scope="module")
def operator(served):
    """The operator's page: it drives DEVICE for the whole module."""
    op = Client(served).open_session()
    code, body = op.call("api/claim", {"key": DEVICE})
    assert code == 200 and body["yours"] is True, body
    return op


def still_serves(served, operator) -> None:
    """The page is up, the operator still drives DEVICE and can start a session on it."""
    code, snap = operator.call("api/state")
    assert code == 200 and {b["key"]: b["yours"] for b in snap["boards"]}.get(DEVICE) is True, snap
    code, body = operator.call("api/start", {"port": DEVICE, "write": False})
    assert code == 200 and body == {"key": DEVICE}, body
    served.station.wait(DEVICE, timeout=30)


# ------------------------------------------------------------------------- Host
def test_a_foreign_host_is_refused(served, operator, monkeypatch):
    port = served.port
    for host in (f"evil.example:{port}", f"127.0.0.1.evil.example:{port}", "evil.example", f"127.0.0.1:{port}@evil"):
        text = error_of(raw_request(port, f"GET /api/state HTTP/1.1\nHost: {host}\nConnection: close\n"))
        assert f"served as http://127.0.0.1:{port}/ only, not as {host.lower()}" in text, (host, text)
    # the right name on another port (a proxy, another service): refused with the reason
    text = error_of(raw_request(port, f"GET /api/state HTTP/1.1\nHost: localhost:{port + 1}\nConnection: close\n"))
    assert f"served as http://127.0.0.1:{port}/ only" in text and "DNS-rebinding" in text
    # no Host at all (HTTP/1.0)
    assert "not as no Host" in error_of(raw_request(port, "GET /api/state HTTP/1.0\n"))
    # a POST from a rebinding page: refused before its body is read
    code, _ = raw_request(port, f"POST /api/claim HTTP/1.1\nHost: evil.example:{port}\nOrigin: http://evil.example:{port}\n"
                                f"Content-Type: application/json\nContent-Length: 16\nConnection: close\n", b'{"key": "sim"}  ')
    assert code == 403
    # behind PageGuard, Starlette's TrustedHostMiddleware checks the name on its own: were
    # PageGuard to let evil.example through, the library still refuses it
    from imubench.station.security import PageAccess
    monkeypatch.setattr(PageAccess, "authorities", property(lambda a: {f"evil.example:{port}", f"127.0.0.1:{port}"}))
    code, text = raw_request(port, f"GET / HTTP/1.1\nHost: evil.example:{port}\nConnection: close\n")
    assert code == 400 and text == "Invalid host header"
    monkeypatch.undo()
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}"):   # the page's own names
        assert raw_request(port, f"GET / HTTP/1.1\nHost: {host}\nConnection: close\n")[0] == 200
    still_serves(served, operator)


def test_an_ssh_tunnel_on_another_port_is_served_only_when_allowed(tmp_path):
    """ssh -L 9000:127.0.0.1:PORT: the browser says Host localhost:9000 and that Origin; the
    station serves it only with --allow-origin http://localhost:9000 (Server(allow_origins))."""
    station = Station(workdir=tmp_path, allow_sim=False, history=False)
    server = Server(station, allow_origins=["http://localhost:9000"]).start()
    try:
        head = ("POST /api/session HTTP/1.1\nHost: {h}\nOrigin: http://{h}\nContent-Type: application/json\n"
                "X-Imubench-Launch: {s}\nContent-Length: 2\nConnection: close\n")
        secret = lambda: server.new_launch_url().split("#token=")[1]        # noqa: E731
        assert raw_request(server.port, head.format(h="localhost:9000", s=secret()), b"{}")[0] == 200
        assert raw_request(server.port, head.format(h=f"127.0.0.1:{server.port}", s=secret()), b"{}")[0] == 200
        code, text = raw_request(server.port, head.format(h="localhost:9001", s=secret()), b"{}")
        assert code == 403 and "served as" in text
    finally:
        server.stop()
        station.close()


def test_the_page_cannot_be_framed_and_a_report_runs_no_script(served, operator):
    with urllib.request.urlopen(served.url, timeout=10) as r:
        csp = r.headers["Content-Security-Policy"]
        assert "frame-ancestors 'none'" in csp and "default-src 'self'" in csp and r.headers["X-Frame-Options"] == "DENY"
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(urllib.request.Request(served.url + "report/x/report.html",
                                                      headers={"X-Imubench-Session": operator.session}), timeout=10)
    assert e.value.code == 404 and e.value.headers["Content-Security-Policy"].startswith("default-src 'none'")


# ------------------------------------------------------------------------- Origin and JSON
def test_state_changes_need_the_pages_origin_and_a_json_body(served, operator):
    port = served.port
    evil = Client(served, origin=f"http://evil.example:{port}")
    assert "requests from http://evil.example" in error_of(evil.call("api/claim", {"key": DEVICE}))
    none = Client(served, origin="")
    none.session = operator.session
    assert "needs the page's Origin" in error_of(none.call("api/claim", {"key": DEVICE}))
    other_port = Client(served, origin=f"http://127.0.0.1:{port + 1}")       # another local service's page
    assert error_of(other_port.call("api/claim", {"key": DEVICE}))
    # the simple requests any site may send without asking: text/plain and forms
    for ctype, body in (("text/plain", b'{"key": "socket://127.0.0.1:1"}'),
                        ("application/x-www-form-urlencoded", b"key=socket%3A%2F%2F127.0.0.1%3A1"),
                        ("multipart/form-data; boundary=x", b"--x\r\nContent-Disposition: form-data; name=key\r\n\r\nk\r\n--x--")):
        code, out = operator.call("api/claim", raw=body, headers={"Content-Type": ctype})
        assert code == 415 and "send JSON" in out["error"], (ctype, code, out)
    # a browser's own word that the request is cross-site
    assert "cross-site request" in error_of(operator.call("api/state", headers={"Sec-Fetch-Site": "cross-site"}))
    # a cross-origin read of the state or the events
    assert error_of(evil.call("api/state"))
    assert error_of(evil.call("api/events"))
    still_serves(served, operator)


# ------------------------------------------------------------------------- tokens
def test_a_session_comes_only_from_the_launch_secret_and_never_from_a_cookie(served, operator):
    """issue 36 items 2, 3: the identity cookie reached every server on 127.0.0.1 and any local
    process was an operator. Now the station prints an address with a one-time secret; the
    page trades it for a session it sends in a header; nothing is a cookie."""
    # the secret: in the address's fragment (never sent to a server), 256 bits, spent once
    url = served.new_launch_url()
    assert re.fullmatch(rf"http://127\.0\.0\.1:{served.port}/#token=[A-Za-z0-9_-]{{43}}", url)
    secret = url.split("#token=")[1]
    page = Client(served)
    code, body = page.trade(secret)
    assert code == 200 and set(body) == {"session"} and len(body["session"]) >= 32
    page.session = body["session"]
    assert "secret is spent or wrong" in error_of(Client(served).trade(secret))      # replayed
    assert "secret is spent or wrong" in error_of(Client(served).trade("x" * 43))    # guessed
    assert "secret is spent or wrong" in error_of(Client(served).call("api/session", {}))
    # a secret the command printed is another one, still unspent: the next browser's
    assert served.launch_url.split("#token=")[1] not in (secret, "")
    # no response sets a cookie; a session is nobody's but this server's
    for c in (page, operator):
        assert len(c.jar) == 0
    r = urllib.request.urlopen(urllib.request.Request(served.url + "api/session", data=b"{}", headers={
        "Content-Type": "application/json", "Origin": served.url.rstrip("/"),
        "X-Imubench-Launch": served.new_launch_url().split("#token=")[1]}), timeout=10)
    assert r.headers.get("Set-Cookie") is None and r.headers["Cache-Control"] == "no-store"
    # without a session, nothing but the page's own files: refused before any work
    stranger = Client(served)
    for path, data, headers in (("api/state", None, {}), ("api/events", None, {}),
                                ("pose.svg?up=0,0,1", None, {}), ("turn.svg?axis=0,0,1", None, {}),
                                ("report/x/report.html", None, {}),
                                ("api/claim", {"key": DEVICE, "token": "mine"}, {}),
                                ("api/claim?token=mine", {"key": DEVICE}, {}),
                                ("api/stop", {"key": DEVICE}, {"X-Station-Token": "mine"}),
                                ("api/stop", {"key": DEVICE}, {"X-Imubench-Session": "forged"}),
                                ("api/stop", {"key": DEVICE}, {"X-Imubench-Launch": secret}),
                                ("api/stop", {"key": DEVICE}, {"Cookie": f"imubench-station-{served.port}=x"})):
        assert "no session of this station" in error_of(stranger.call(path, data, headers)), path
    assert "no session of this station" in error_of(stranger.call("api/start", raw=b"{" * 100000))   # not read
    for path in ("", "static/station.js", "static/station.css"):
        assert stranger.call(path)[0] == 200
    # the owner's session never reaches another page: the state does not carry it
    code, snap = page.call("api/state")
    assert operator.session not in json.dumps(snap) and all(b["yours"] is False for b in snap["boards"])
    # another browser with its own session only watches the operator's device
    other = Client(served).open_session()
    code, body = other.call("api/claim", {"key": DEVICE})
    assert code == 200 and body["yours"] is False
    assert "driven from another page" in error_of(other.call("api/stop", {"key": DEVICE}))
    assert "shows no device 'socket://127.0.0.1:9'" in error_of(other.call("api/resume", {"key": "socket://127.0.0.1:9"}))
    # a report link: a ticket for that path, once
    code, body = operator.call("api/ticket", {"path": "/report/x/report.html"})
    assert code == 200 and body["url"].startswith("/report/x/report.html?ticket=")
    assert stranger.call(body["url"].lstrip("/"))[0] == 404             # let through: no such report
    assert "no session" in error_of(stranger.call(body["url"].lstrip("/")))   # spent
    assert "a ticket is for a report" in error_of(operator.call("api/ticket", {"path": "/api/stop"}))
    still_serves(served, operator)


def test_the_ports_a_page_may_open(tmp_path):
    target = tmp_path / "victim.txt"
    target.write_text("keep me\n")
    p = PortPolicy()
    for ok in ("/dev/ttyUSB0", "/dev/ttyACM3", "/dev/serial/by-id/usb-STM_VCP_123-if00", "COM7",
               "socket://127.0.0.1:4000", "socket://localhost:4000", "rfc2217://[::1]:2217"):
        assert p.check(ok) == ok
    refused = {f"spy://loop://?file={target}": "spy:// ports are not opened",
               "loop://": "--allow-port-handler loop", "hwgrep://USB": "--allow-port-handler hwgrep",
               "alt:///dev/ttyUSB0?class=PosixPollSerial": "--allow-port-handler alt",
               "socket://10.1.2.3:4000": "--allow-port-host 10.1.2.3",
               "rfc2217://evil.example:2217": "--allow-port-host evil.example",
               "socket://127.0.0.1": "needs a host and a port", "socket://127.0.0.1:http": "needs a host and a port",
               "/etc/passwd": "not a serial device", "/dev/../etc/passwd": "not a serial device",
               "/dev/tty": "not a serial device", "/dev/zero": "not a serial device",
               str(target): "not a serial device", "/dev/ttyUSB0 ; rm": "no spaces",
               "x" * 300: "at most 256"}
    for port, why in refused.items():
        with pytest.raises(StationError, match=why.replace("+", r"\+").replace("?", r"\?")):
            p.check(port)
    # allowed on the command line: spy:// and loop://, but spy:// never writes a file
    p = PortPolicy(handlers=("spy", "loop"), hosts=("10.1.2.3",))
    assert p.check("loop://") == "loop://" and p.check("spy:///dev/ttyUSB0?color") == "spy:///dev/ttyUSB0?color"
    assert p.check("socket://10.1.2.3:4000") == "socket://10.1.2.3:4000"
    for port in (f"spy://loop://?file={target}", f"spy:///dev/ttyUSB0?fil%65={target}", f"spy:///dev/ttyUSB0?raw&file={target}"):
        with pytest.raises(StationError, match="spy:// option 'file' is refused"):
            p.check(port)
    with pytest.raises(StationError, match="not a serial device"):
        p.check("spy://socket://10.9.9.9:1")                 # what spy:// wraps is checked too
    with pytest.raises(ValueError, match="not a pyserial URL handler"):
        PortPolicy(handlers=("ftp",))
    assert target.read_text() == "keep me\n"


def test_the_allow_list_decides_by_what_a_device_is(tmp_path):
    """issue 36 item 6: the path inside alt:// was not checked (a regular file, a FIFO,
    /dev/zero, /dev/watchdog were opened read-write), and /dev/tty0 and /dev/tty1 (virtual
    consoles) passed as serial devices by their names. Now the kernel's tty driver table
    decides: UARTs, USB-serial and pty slaves pass, for every handler that takes a path."""
    master, slave = os.openpty()
    try:
        pty = os.ttyname(slave)
        link = tmp_path / "imu0"
        link.symlink_to(pty)                     # a udev-style alias of a serial device
        fifo = tmp_path / "fifo"
        os.mkfifo(fifo)
        zero_link = tmp_path / "ttyUSB9"
        zero_link.symlink_to("/dev/zero")
        p = PortPolicy(handlers=("alt", "spy"))
        for ok in (pty, str(link), f"alt://{pty}?class=PosixPollSerial", f"spy://{pty}?color"):
            assert p.check(ok) == ok
        refused = {"/dev/tty0": "current virtual console", "/dev/tty1": "a virtual console",
                   "/dev/tty": "controlling terminal", "/dev/console": "system console",
                   "/dev/ptmx": "pseudo-terminal multiplexer", "/dev/zero": "no tty (1:5)",
                   str(zero_link): "no tty (1:5)", str(fifo): "a FIFO", str(tmp_path): "a directory",
                   "/etc/passwd": "a regular file", "/dev/../etc/passwd": "a regular file", "/dev/ttyUSB0/../../etc/passwd": "(/dev/ttyUSB0",
                   "alt:///dev/zero?class=PosixPollSerial": "no tty (1:5)",
                   "alt:///dev/tty1?class=PosixPollSerial": "a virtual console",
                   f"alt://{fifo}?class=PosixPollSerial": "a FIFO",
                   "alt:///etc/passwd?class=PosixPollSerial": "a regular file",
                   "alt://relative/path": "not a serial device", "spy:///dev/tty0": "current virtual console"}
        for port, why in refused.items():
            with pytest.raises(StationError, match=re.escape(why)) as e:
                p.check(port)
            assert "\n" not in str(e.value) and "not a serial device" in str(e.value)
        # hwgrep:// picks from the serial ports it finds: what it could pick is checked too
        h = PortPolicy(handlers=("hwgrep",))
        with pytest.raises(StationError, match="no serial port matches"):
            h.check("hwgrep://no-such-port-anywhere-zz9")
        with pytest.raises(StationError, match="not a regular expression"):
            h.check("hwgrep://(")
    finally:
        os.close(master)
        os.close(slave)


def test_a_page_cannot_open_other_ports_through_the_server(served, operator, tmp_path):
    target = tmp_path / "victim.txt"
    target.write_text("keep me\n")
    for port in (f"spy://loop://?file={target}", "socket://10.1.2.3:4000", "/etc/passwd"):
        assert error_of(operator.call("api/claim", {"key": port}))
        assert error_of(operator.call("api/start", {"port": port, "write": False}))
    assert target.read_text() == "keep me\n"
    assert not any(k.startswith(("spy", "socket://10")) for k in served.station.state.boards)
    still_serves(served, operator)


def test_port_options_on_the_command_line_fail_in_one_line():
    r = subprocess.run([sys.executable, "-m", "imubench", "station", "--allow-port-handler", "ftp"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "'ftp' is not a pyserial URL handler to allow" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "imubench", "station", "--allow-origin", "evil.example"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "is not an origin like http://localhost:9000" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "imubench", "station", "--allow-port-host", "socket://10.0.0.5:4000"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "is not a host (an IP address or a name" in r.stderr, r.stderr


# ------------------------------------------------------------------------- bad values
def test_bad_values_are_refused_with_the_reason(served, operator):
    cases = [({"port": DEVICE, "write": "false"}, "write must be true or false (a JSON boolean), not 'false'"),
             ({"port": DEVICE, "rate_hz": "abc"}, "rate_hz must be one of"),
             ({"port": DEVICE, "rate_hz": 123}, "not 123"),
             ({"port": DEVICE, "rate_hz": True}, "not true"),
             ({"port": DEVICE, "note": "n" * 501}, "note is 501 characters long: at most 500"),
             ({"port": DEVICE, "note": 5}, "note must be a string"),
             ({"port": DEVICE, "method": ["multi"]}, "nested 2 deep"),
             ({"port": DEVICE, "retries": 3}, "unknown option 'retries'"),
             ({"port": 5}, "port must be a string")]
    for data, why in cases:
        assert why in error_of(operator.call("api/start", data)), data
    for raw, why in ((b'{"port": "%s", "rate_hz": 1e999}' % DEVICE.encode(), "not a number out of range"),
                     (b'{"port": "%s", "rate_hz": NaN}' % DEVICE.encode(), "NaN is not a JSON number"),
                     (b"[" * 5000 + b"]" * 5000, "nested 5000 deep"),
                     (b'{"key": ' * 1500, "nested 1500 deep"),
                     (b"[1, 2]", "must be a JSON object"), (b"{", "not JSON"), (b"\xff\xfe", "not UTF-8"),
                     (b'{"%s": 1}' % (b"k" * 100), "a member name of 100 characters")):
        assert why in error_of(operator.call("api/start", raw=raw)), raw[:40]
    for q in ("pose.svg?up=1e999,0,0", "pose.svg?up=nan,0,1", "turn.svg?axis=0,0,1&rate=1e999",
              "turn.svg?axis=0,0,1&angle=nan", "turn.svg?axis=0,0,1&rate=abc"):
        assert error_of(operator.call(q)), q
    for q in ("pose.svg?up=1e300,1e300,0", "pose.svg?up=0,1e-320,0", "turn.svg?axis=1e300,0,0&rate=5"):
        code, svg = operator.call(q)                          # extreme but valid: drawn, not NaN
        assert code == 200 and svg.startswith("<svg") and "nan" not in svg.lower(), q
    still_serves(served, operator)


# ------------------------------------------------------------------------- bounds
def test_bodies_keys_boards_and_clients_are_bounded(served, operator):
    port = served.port
    # a 50 MB body: refused from its Content-Length, nothing read
    code, text = raw_request(port, f"POST /api/claim HTTP/1.1\nHost: 127.0.0.1:{port}\nOrigin: http://127.0.0.1:{port}\n"
                                   f"X-Imubench-Session: {operator.session}\n"
                                   f"Content-Type: application/json\nContent-Length: {50 << 20}\nConnection: close\n")
    assert code == 413 and f"larger than {MAX_BODY_BYTES // 1024} KiB" in text
    # ... and chunked, without a length: read up to the bound only
    chunk = b"%x\r\n%s\r\n" % (8192, b" " * 8192)
    code, text = raw_request(port, f"POST /api/claim HTTP/1.1\nHost: 127.0.0.1:{port}\nOrigin: http://127.0.0.1:{port}\n"
                                   f"X-Imubench-Session: {operator.session}\n"
                                   f"Content-Type: application/json\nTransfer-Encoding: chunked\nConnection: close\n",
                             chunk * 4 + b"0\r\n\r\n")
    assert code == 413
    assert "at most 256" in error_of(operator.call("api/claim", {"key": "socket://127.0.0.1:" + "1" * 300}))
    # 200 claims of distinct devices from other browsers: the list stops at its bound, the
    # operator's device stays
    clients = [Client(served).open_session() for _ in range(4)]
    refused = 0
    for k in range(200):
        code, body = clients[k % 4].call("api/claim", {"key": f"socket://127.0.0.1:{20000 + k}"})
        if code == 429:
            refused += 1
            assert "devices already" in body["error"]
        else:
            assert code == 200
    st = served.station.state
    assert sum(b.by_page for b in st.boards.values()) <= S.MAX_PAGE_BOARDS and refused >= 200 - S.MAX_PAGE_BOARDS
    assert DEVICE in st.boards
    # 100 browsers: the oldest that own nothing and have no page open make way; at most MAX_CLIENTS
    for _ in range(100):
        Client(served).open_session()
    assert len(st.clients) <= S.MAX_CLIENTS
    still_serves(served, operator)


def _open_stream(port: int, session: str | None = None) -> tuple[socket.socket, int]:
    s = socket.create_connection(("127.0.0.1", port), timeout=20)
    s.sendall((f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAccept: text/event-stream\r\n"
               + (f"X-Imubench-Session: {session}\r\n" if session else "") + "\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(4096)
        if not chunk:
            break
        head += chunk
    return s, int(head.split()[1])


def test_event_streams_are_bounded_and_never_hold_up_the_commands(served, operator, monkeypatch):
    """200 pages open the event stream: without a session each is refused (403); with one (25
    browsers, 8 tabs each) the first MAX_STREAMS are served, the rest get a 429 (too many);
    /api/start answers at once all the while, and the operator keeps the device although it
    has not spoken for longer than the grace time (its page is open)."""
    port = served.port
    own, code = _open_stream(port, operator.session)          # the operator's page
    assert code == 200
    socks, codes = [], []
    try:
        for _ in range(50):
            s, code = _open_stream(port)
            s.close()
            assert code == 403
        watchers = [Client(served).open_session() for _ in range(25)]
        for k in range(200):
            s, code = _open_stream(port, watchers[k // S.MAX_STREAMS_PER_CLIENT].session)
            codes.append(code)
            (socks.append(s) if code == 200 else s.close())
        assert codes.count(200) == S.MAX_STREAMS and codes.count(429) == 200 - S.MAX_STREAMS, codes
        t0 = time.monotonic()
        still_serves(served, operator)                         # start while the streams are open
        start_s = time.monotonic() - t0
        assert start_s < 15, start_s                           # was 30 s with 20 streams, never with 200
        # another browser tries to take the device over: the owner's page is open, it stays
        monkeypatch.setattr(S, "OWNER_GRACE_S", 0.0)
        thief = Client(served).open_session()
        code, body = thief.call("api/claim", {"key": DEVICE})
        assert code == 200 and body["yours"] is False
        # the streams the page opened are still live: a change reaches them
        own.settimeout(20)
        assert b"data: " in own.recv(65536) or b"data: " in own.recv(65536)
    finally:
        for s in socks:
            s.close()
        own.close()
    t_end = time.monotonic() + 20                              # the slots come back
    while served.station.state.streams and time.monotonic() < t_end:
        time.sleep(0.1)
    assert sum(served.station.state.streams.values()) == 0


# ------------------------------------------------------------------------- a real browser
CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--no-first-run",
         "--host-resolver-rules=MAP evil.example 127.0.0.1",
         # let the hostile page's requests reach the station: it is the station that must refuse them
         "--disable-features=PrivateNetworkAccessSendPreflights,PrivateNetworkAccessRespectPreflightResults,"
         "BlockInsecurePrivateNetworkRequests,LocalNetworkAccessChecks"]

HOSTILE = """<!DOCTYPE html><title>cats</title><script>
window.done = (async () => {
  const out = {};
  const post = (path, body, type) => fetch(path, {method: "POST", headers: {"Content-Type": type || "application/json"},
                                                  body: JSON.stringify(body)})
    .then(async (r) => [r.status, await r.text()]).catch((e) => ["failed", String(e)]);
  out.session = await fetch("/api/session", {method: "POST", headers: {"Content-Type": "application/json",
    "X-Imubench-Launch": "guess"}, body: "{}"}).then(async (r) => [r.status, await r.text()]);
  out.claim = await post("/api/claim", {key: "DEVICE", token: "mine"});
  out.plain = await post("/api/claim", {key: "DEVICE"}, "text/plain");
  out.start = await post("/api/start", {port: "DEVICE", write: true});
  out.state = await fetch("/api/state").then(async (r) => [r.status, await r.text()]).catch((e) => ["failed", String(e)]);
  out.events = await new Promise((res) => { const es = new EventSource("/api/events");
    es.onmessage = (m) => { es.close(); res(["read", m.data]); };
    es.onerror = () => { es.close(); res(["refused", ""]); }; });
  return out;
})();
</script>"""

CROSS_SITE = """<!DOCTYPE html><title>cats</title><script>
window.done = (async () => {
  const T = "STATION";
  const tries = [
    fetch(T + "api/claim", {method: "POST", mode: "no-cors", credentials: "include", headers: {"Content-Type": "text/plain"},
                             body: JSON.stringify({key: "DEVICE"})}),
    fetch(T + "api/start", {method: "POST", mode: "no-cors", credentials: "include", headers: {"Content-Type": "text/plain"},
                             body: JSON.stringify({port: "DEVICE", write: true})}),
    fetch(T + "api/stop", {method: "POST", credentials: "include", headers: {"Content-Type": "application/json"},
                            body: JSON.stringify({key: "DEVICE"})}),
    fetch(T + "api/state", {credentials: "include"}).then((r) => r.text()),
  ];
  const out = [];
  for (const t of tries) out.push(await t.then((r) => (r && r.type) || "read", (e) => "blocked"));
  const f = document.createElement("form");
  f.method = "POST"; f.action = T + "api/claim"; f.enctype = "text/plain"; f.target = "sink";
  const i = document.createElement("input"); i.name = '{"key": "DEVICE", "x": "'; i.value = '"}'; f.appendChild(i);
  const sink = document.createElement("iframe"); sink.name = "sink"; document.body.appendChild(sink);
  document.body.appendChild(f); f.submit();
  await new Promise((r) => setTimeout(r, 1500));
  return out;
})();
</script>"""


ANOTHER_LOCAL_PAGE = """<!DOCTYPE html><title>another local tool</title><script>
window.done = (async () => {
  const out = {cookie: document.cookie, session: sessionStorage.length, local: localStorage.length};
  await fetch("/collect", {method: "POST", body: JSON.stringify(out)});    // what a page could send home
  return out;
})();
</script>"""


class _Recorder(http.server.BaseHTTPRequestHandler):
    """Another local web server (another port of 127.0.0.1): records every request it gets."""
    seen: list = []

    def _record(self):
        n = int(self.headers.get("Content-Length") or 0)
        self.seen.append((self.command, self.path, dict(self.headers), self.rfile.read(n).decode()))
        body = ANOTHER_LOCAL_PAGE.encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_POST = _record

    def log_message(self, *a):
        pass


def test_a_hostile_page_in_chromium_cannot_drive_the_station(served, operator, monkeypatch):
    """DNS rebinding in a real Chromium: evil.example resolves to 127.0.0.1 (a host-resolver
    rule), its page (served by the attacker before the rebinding; here by Playwright's route)
    then calls the station same-origin. Every call is refused by the station, the operator's
    page (a real one, in another browser context) keeps driving. Then an ordinary cross-site
    page (no rebinding) tries simple requests and a form: the state does not change."""
    if not CHROMIUM.is_file():
        pytest.fail("chromium is missing: `make system-deps` installs Debian's chromium (SYSTEM_PKGS)")
    from playwright.sync_api import sync_playwright
    from imubench.station import security
    port = served.port
    st = served.station.state
    served.station.wait(DEVICE, timeout=30)
    refused = []                                   # what reached the station and was refused there
    refusal = security.PageGuard.refusal

    def record(self, scope, headers):
        r = refusal(self, scope, headers)
        if r is not None:
            refused.append((scope["method"], scope["path"], r[0]))
        return r
    monkeypatch.setattr(security.PageGuard, "refusal", record)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=FLAGS)
        try:
            ctx = browser.new_context()
            page = ctx.new_page()                          # the operator's real page
            page.goto(served.new_launch_url())
            page.wait_for_function("() => document.querySelector('#conn').textContent === 'live'")
            assert "#token" not in page.url                 # the secret left the address bar
            claimed = page.evaluate("""fetch('/api/claim', {method: 'POST', headers: {'Content-Type': 'application/json',
                                       'X-Imubench-Session': sessionStorage.getItem('imubench-station-session')},
                                       body: JSON.stringify({key: 'sim-free-device'})}).then((r) => r.status)""")
            assert claimed == 400                          # not a port: the real page's requests are checked too
            boards_before = {k: (b.status, b.owner, b.session_dir) for k, b in st.boards.items()}
            version_before = st.version

            # 1. DNS rebinding: the hostile page at http://evil.example:PORT, same-origin with the station
            evil = browser.new_context()
            hostile = evil.new_page()
            hostile.route(f"http://evil.example:{port}/", lambda r: r.fulfill(
                status=200, content_type="text/html", body=HOSTILE.replace("DEVICE", DEVICE)))
            hostile.goto(f"http://evil.example:{port}/")
            out = hostile.evaluate("window.done")
            for name in ("session", "claim", "plain", "start", "state"):
                status, text = out[name]
                assert status == 403 and "DNS-rebinding" in text, (name, out[name])   # the station refused it
            assert out["events"][0] == "refused", out["events"]
            # the hostile page loaded from the station itself (after the rebinding) is refused too
            resp = hostile.goto(f"http://evil.example:{port}/api/state")
            assert resp.status == 403

            assert {("POST", "/api/session", 403), ("POST", "/api/start", 403), ("GET", "/api/events", 403)} <= set(refused)
            refused.clear()

            # 2. an ordinary cross-site page in the operator's own browser (its session is there)
            cross = ctx.new_page()
            cross.route(f"http://evil.example:{port + 1}/", lambda r: r.fulfill(
                status=200, content_type="text/html",
                body=CROSS_SITE.replace("DEVICE", DEVICE).replace("STATION", served.url)))
            cross.goto(f"http://evil.example:{port + 1}/")
            cross.evaluate("window.done")
            # the station saw them and refused them (not merely the browser)
            for call in (("POST", "/api/claim"), ("POST", "/api/start"), ("GET", "/api/state")):
                assert (*call, 403) in refused, (call, refused)
            assert refused.count(("POST", "/api/claim", 403)) == 2, refused      # the fetch and the form
            # nothing changed: no board added or taken, no session started
            assert {k: (b.status, b.owner, b.session_dir) for k, b in st.boards.items()} == boards_before
            assert st.version == version_before, "a hostile page changed the station's state"
            # the operator's page is still live and still drives
            assert page.locator("#conn").text_content() == "live"

            # 3. another local server (issue 36): its page, open in the operator's own browser,
            # and the server itself receive nothing that drives the station: no cookie, no session
            import threading
            other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Recorder)
            threading.Thread(target=other.serve_forever, daemon=True).start()
            try:
                session = page.evaluate("sessionStorage.getItem('imubench-station-session')")
                assert session and st.client(session) is not None
                visit = ctx.new_page()
                visit.goto(f"http://127.0.0.1:{other.server_address[1]}/")
                seen_by_page = visit.evaluate("window.done")
                visit.goto(f"http://localhost:{other.server_address[1]}/")     # the other name, too
                visit.evaluate("window.done")
            finally:
                other.shutdown()
            assert seen_by_page == {"cookie": "", "session": 0, "local": 0}
            assert [r[1] for r in _Recorder.seen].count("/collect") == 2 and all("Cookie" not in h and "cookie" not in h for _, _, h, _ in _Recorder.seen)
            everything = json.dumps(_Recorder.seen)
            assert session not in everything and "token" not in everything
            assert ctx.cookies() == []                      # the station never set one, for any port
            still_serves(served, operator)
        finally:
            browser.close()


# ------------------------------------------------------------------------- deadlines
def _closed_within(s: socket.socket, seconds: float) -> tuple[bool, bytes]:
    """Whether the server closed s within seconds (and what it sent before)."""
    s.settimeout(seconds)
    got = b""
    try:
        while chunk := s.recv(65536):
            got += chunk
        return True, got
    except ConnectionResetError:
        return True, got
    except socket.timeout:
        return False, got


def test_deadlines_close_silent_slow_and_idle_connections(served, operator, monkeypatch):
    """issue 36 item 1: no deadline before the first request, none for a body. Here (with the
    deadlines shortened) a silent connection, a head sent by halves, a stranger's idle
    keep-alive and a body that never ends are each closed at their deadline; the operator's
    kept-alive connection outlives a stranger's."""
    from imubench.station import security, server
    monkeypatch.setattr(server, "HEAD_DEADLINE_S", 0.5)
    monkeypatch.setattr(server, "STRANGER_IDLE_S", 0.3)
    monkeypatch.setattr(security, "BODY_DEADLINE_S", 0.5)
    port = served.port
    host = f"Host: 127.0.0.1:{port}\r\n"
    silent = socket.create_connection(("127.0.0.1", port))
    half = socket.create_connection(("127.0.0.1", port))
    half.sendall(b"GET / HTTP/1.1\r\n" + host.encode())             # the head's end never comes
    idle = socket.create_connection(("127.0.0.1", port))
    idle.sendall(f"GET / HTTP/1.1\r\n{host}\r\n".encode())            # answered, then kept alive
    mine = socket.create_connection(("127.0.0.1", port))
    mine.sendall(f"GET /api/state HTTP/1.1\r\n{host}X-Imubench-Session: {operator.session}\r\n\r\n".encode())
    slow = socket.create_connection(("127.0.0.1", port))
    slow.sendall((f"POST /api/claim HTTP/1.1\r\n{host}Origin: http://127.0.0.1:{port}\r\n"
                  f"X-Imubench-Session: {operator.session}\r\nContent-Type: application/json\r\n"
                  "Content-Length: 100\r\n\r\n{\"key\": ").encode())          # the operator's own, too slow
    t0 = time.monotonic()
    try:
        for s in (silent, half, idle):
            closed, got = _closed_within(s, 3.0)
            assert closed, got
        closed, got = _closed_within(slow, 3.0)
        assert closed and got.startswith(b"HTTP/1.1 408") and b"did not arrive within 0.5 s" in got, got
        assert time.monotonic() - t0 < 3.0
        closed, got = _closed_within(mine, 0.5)              # a session's keep-alive: 20 s
        assert not closed and got.startswith(b"HTTP/1.1 200"), got[:100]
    finally:
        for s in (silent, half, idle, mine, slow):
            s.close()
    assert served.crowd.timed_out >= 3
    still_serves(served, operator)


def test_warnings_are_rate_limited():
    import logging

    from imubench.station.server import _FewWarnings
    f = _FewWarnings()
    recs = [logging.LogRecord("uvicorn.error", logging.WARNING, "", 0, "Invalid HTTP request received.", (), None)
            for _ in range(5000)]
    assert sum(f.filter(r) for r in recs) == 1
    f.last = {k: v - 11 for k, v in f.last.items()}          # ten seconds later: one line, with the count
    r = logging.LogRecord("uvicorn.error", logging.WARNING, "", 0, "Invalid HTTP request received.", (), None)
    assert f.filter(r) and "4999 more like it in the last 10 s not shown" in r.getMessage()
