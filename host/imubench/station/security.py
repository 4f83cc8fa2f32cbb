"""Who may drive the station page, and what a page may ask for (docs/production.md, "Who can
drive the station page").

The page controls hardware and writes files, so only the operator's own browser on this
machine may drive it:

    PageAccess   the addresses the page is served as (127.0.0.1 / localhost / [::1] with the
                 served port, and any --allow-origin); the Host and Origin a request must carry
    PageGuard    ASGI middleware in front of every route: a Host the page is not served as is
                 refused with the address to open instead (DNS rebinding; Starlette's
                 TrustedHostMiddleware behind it checks the name again), a state-changing
                 request needs this page's Origin and a JSON body, a cross-site fetch of the API
                 is refused, and bodies are bounded
    PortPolicy   the device ports a page may open: serial devices, socket:// and rfc2217:// on
                 this machine; other hosts and other pyserial URL handlers only when the command
                 line allows them; spy:// never writes a file
    parse_body   a request's JSON object, bounded in size and depth, values scalars only

Each refusal is a StationError with a one-line reason and an HTTP status (4xx).
"""
from __future__ import annotations

import ipaddress
import json
import math
import os
import re
import stat
from urllib.parse import parse_qs, urlsplit

from imubench.errors import ImubenchError

BODY_DEADLINE_S = 5.0               # a request's whole body, from its head (the page's arrive at once)
MAX_BODY_BYTES = 16 * 1024          # the page's largest request (start: a port and a note) is < 1 KiB
MAX_JSON_DEPTH = 1                  # every request is one flat object of scalars
MAX_JSON_KEYS = 16
MAX_KEY_CHARS = 32                  # a JSON member name
MAX_PORT_CHARS = 256                # a device port URL (also the key of its column)
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
SESSION_HEADER = "x-imubench-session"   # the session the page holds (sessionStorage: this origin only)
LAUNCH_HEADER = "x-imubench-launch"     # the one-time launch secret the page trades for a session
MAX_SECRETS = 4                     # launch secrets not yet traded (the printed one and any asked for)
TICKET_S = 60.0                     # a report link's ticket: single use, this long
MAX_TICKETS = 64
# what a request may ask without a session: the page itself (static HTML, script, style), so
# that it can trade the secret in its address for one; everything else needs the session
PUBLIC_PATHS = ("/", "/favicon.ico")
PUBLIC_PREFIXES = ("/static/",)
REPORT_PATH = re.compile(r"/report/[^/]{1,300}/report\.html")
#: what a ticket may open (a tab or a download sends no header): a report or a board's export file
TICKET_PATH = re.compile(r"/report/[^/]{1,300}/report\.html|/export/[^/]{1,300}/[^/]{1,300}")
# pyserial's URL handlers besides socket:// and rfc2217:// (serial.urlhandler.protocol_*)
PORT_HANDLERS = ("alt", "cp2110", "hwgrep", "loop", "spy")
ALWAYS_HANDLERS = ("socket", "rfc2217")
SPY_OPTIONS = ("color", "raw", "all")           # spy://'s "file" option writes a file: never from a page


class StationError(ImubenchError, ValueError):
    """A request the station cannot do (bad option, device busy, not yours); says why.
    status: the HTTP status the page gets (400 unless said otherwise)."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


# ------------------------------------------------------------------ who: Host and Origin
class PageAccess:
    """The authorities (host:port) the page is served as: 127.0.0.1, localhost and [::1] with
    the served port (known once bound), plus the origins the command line adds
    (--allow-origin http://localhost:9000, for an SSH tunnel whose local port differs)."""

    def __init__(self, extra_origins=()):
        self.port: int | None = None
        self.extra = [origin_authority(o) for o in extra_origins]

    def bind(self, port: int) -> None:
        self.port = int(port)

    @property
    def authorities(self) -> set[str]:
        own = {f"{h}:{self.port}" for h in LOOPBACK_NAMES} if self.port else set()
        return own | set(self.extra)

    @property
    def hostnames(self) -> list[str]:
        return list(LOOPBACK_NAMES) + sorted({a.rsplit(":", 1)[0] for a in self.extra})

    @property
    def origins(self) -> set[str]:
        return {f"http://{a}" for a in self.authorities}



class Launch:
    """The launch secret, as Jupyter's token: the station prints (and opens) its address with
    a secret in the fragment (http://127.0.0.1:PORT/#token=SECRET: a fragment never goes to
    any server, nor into a Referer or a log); the page trades it once (POST /api/session with
    the secret in X-Imubench-Launch) for a session, which it keeps in sessionStorage (scoped
    to this scheme, host and port: no other local server's page can read it) and sends in
    X-Imubench-Session with every request. Nothing rides in a cookie, since a browser sends a
    127.0.0.1 cookie to every port of 127.0.0.1.

    A secret is spent when traded; the station then makes a fresh one (on_new) for the next
    browser, so the address left in a terminal, a browser's history or a process list opens
    nothing once it was used. Sessions are the state's client identities (state.new_client),
    made only here: they live as long as this launch and are known to this server only.

    Report links (opened in a new tab, which cannot carry a header) get a ticket: single use,
    TICKET_S long, for that one path."""

    def __init__(self, on_new=None):
        import threading
        self._lock = threading.Lock()
        self._secrets: list[str] = []
        self._tickets: dict[str, tuple[str, float]] = {}
        self.on_new = on_new            # called with each secret made after the first
        self.issue()

    def issue(self) -> str:
        import secrets
        secret = secrets.token_urlsafe(32)          # 256 bits
        with self._lock:
            self._secrets.append(secret)
            del self._secrets[:-MAX_SECRETS]
        return secret

    def valid(self, secret: str | None) -> bool:
        import hmac
        if not secret or len(secret) > 100:
            return False
        with self._lock:
            return any(hmac.compare_digest(secret.encode(), s.encode()) for s in self._secrets)

    def trade(self, secret: str | None) -> bool:
        """Spend secret (True if it was one not yet spent); a fresh one replaces it."""
        import hmac
        if not secret or len(secret) > 100:
            return False
        with self._lock:
            hit = next((s for s in self._secrets if hmac.compare_digest(secret.encode(), s.encode())), None)
            if hit is None:
                return False
            self._secrets.remove(hit)
        fresh = self.issue()
        if self.on_new is not None:
            self.on_new(fresh)
        return True

    def ticket(self, path: str) -> str:
        import secrets
        import time
        t = secrets.token_urlsafe(24)
        now = time.monotonic()
        with self._lock:
            self._tickets = {k: v for k, v in self._tickets.items() if v[1] > now}
            if len(self._tickets) >= MAX_TICKETS:
                del self._tickets[min(self._tickets, key=lambda k: self._tickets[k][1])]
            self._tickets[t] = (path, now + TICKET_S)
        return t

    def use_ticket(self, ticket: str | None, path: str) -> bool:
        import time
        if not ticket:
            return False
        with self._lock:
            got = self._tickets.pop(ticket, None)
        return got is not None and got[0] == path and got[1] > time.monotonic()


def origin_authority(origin: str) -> str:
    """'http://localhost:9000' -> 'localhost:9000' (the form --allow-origin takes)."""
    p = urlsplit(origin.strip())
    try:
        port = p.port
    except ValueError:
        port = None
    if p.scheme != "http" or not p.hostname or port is None or p.path not in ("", "/") or p.query:
        raise ValueError(f"{origin!r} is not an origin like http://localhost:9000 (http, a host and a port)")
    host = f"[{p.hostname}]" if ":" in p.hostname else p.hostname
    return f"{host.lower()}:{port}"


def _json_refusal(status: int, message: str, close: bool = False):
    """A refusal; close: and the connection closed after it (a body cut short). Otherwise a
    stranger's connection is closed by the server's idle deadline (server.Crowd): closing at
    once would only invite a crowd to reconnect at once, each time costing the server more."""
    from starlette.responses import JSONResponse
    headers = {"Cache-Control": "no-store"}
    if close:
        headers["Connection"] = "close"
    return JSONResponse({"error": message}, status_code=status, headers=headers)


SAFE_METHODS = ("GET", "HEAD")
# on every response: no framing (clickjacking of Start/Stop), no sniffing, no referrer; the page
# loads only its own script, style and pictures; a report (HTML built from a session) runs no
# script at all, so no text in it can act as the page
PAGE_CSP = ("default-src 'self'; img-src 'self' data:; object-src 'none'; base-uri 'none'; "
            "form-action 'self'; frame-ancestors 'none'")
REPORT_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; frame-ancestors 'none'"


class PageGuard:
    """ASGI middleware: refuses, with a 4xx and a one-line reason, every request that does not
    come from the page as served here:
    - a Host that is not one of the page's host:port (evil.example:PORT, the DNS-rebinding
      case; localhost:OTHER; none)                                               403
    - any /api/ request a browser marks cross-site or same-site (Sec-Fetch-Site)  403
    - a request carrying an Origin that is not the page's                         403
    - a state-changing request (not GET/HEAD) without the page's Origin           403
    - ... or whose body is not JSON (text/plain and forms: no simple requests)  415
    - a body larger than MAX_BODY_BYTES (read no further)                        413
    and adds to every response a Content-Security-Policy (the page: its own files only, never
    framed; a report: no script), X-Frame-Options, nosniff and no referrer.
    """

    def __init__(self, app, access: PageAccess, launch: Launch | None = None, is_session=None):
        self.app = app
        self.access = access
        self.launch = launch
        self.is_session = is_session

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        refusal = self.refusal(scope, headers)
        cut_short = False
        if refusal is None and scope["method"] not in SAFE_METHODS:
            body, refusal = await _bounded_body(receive, headers)
            cut_short = refusal is not None
            if refusal is None:
                receive = _replay(body, receive)
        csp = REPORT_CSP if scope["path"].startswith("/report/") else PAGE_CSP
        extra = [(b"content-security-policy", csp.encode()), (b"x-frame-options", b"DENY"),
                 (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"no-referrer")]

        async def send_with_headers(m):
            if m["type"] == "http.response.start":
                m = {**m, "headers": [*m.get("headers", []), *extra]}
            await send(m)
        if refusal is not None:
            return await _json_refusal(*refusal, close=cut_short)(scope, receive, send_with_headers)
        return await self.app(scope, receive, send_with_headers)

    def refusal(self, scope, headers) -> tuple[int, str] | None:
        a = self.access
        host = headers.get("host", "").lower()
        if host not in a.authorities:
            return 403, (f"this page is served as http://127.0.0.1:{a.port}/ only, not as {host or 'no Host'}: "
                         "open it there (a foreign Host is how a DNS-rebinding site reaches the station)")
        site = headers.get("sec-fetch-site")
        if scope["path"].startswith("/api/") and site in ("cross-site", "same-site"):
            return 403, f"a {site} request to the station's API is refused: only its own page drives it"
        origin = headers.get("origin")
        if origin is not None and origin not in a.origins:
            return 403, f"requests from {origin} are refused: only the station's own page drives it"
        who = self._who(scope, headers)
        if who is not None:
            return who
        if scope["method"] in SAFE_METHODS:
            return None
        if origin is None:
            return 403, (f"a request that changes the station needs the page's Origin "
                         f"(http://127.0.0.1:{a.port}): send it from the station page")
        ctype = headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return 415, f"send JSON (Content-Type: application/json), not {ctype or 'no Content-Type'}"
        return None


    def _who(self, scope, headers) -> tuple[int, str] | None:
        """None if the request may go on: the page's own files, the secret's trade (with a
        secret not yet spent), a report with its ticket, or anything with this launch's session."""
        if self.launch is None:
            return None
        path, method = scope["path"], scope["method"]
        if method in SAFE_METHODS and (path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)):
            return None
        if path == "/api/session" and method == "POST":
            if self.launch.valid(headers.get(LAUNCH_HEADER)):
                return None
            return 403, ("this address's secret is spent or wrong: open the newest address the station printed "
                         "in its terminal (each opens the page once)")
        if self.is_session(headers.get(SESSION_HEADER)):
            return None
        if method in SAFE_METHODS and TICKET_PATH.fullmatch(path):
            ticket = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("ticket", [None])[0]
            if self.launch.use_ticket(ticket, path):
                return None
        return 403, ("no session of this station: open the address it printed in its terminal "
                     "(http://127.0.0.1:PORT/#token=...: the secret in it opens the page once)").replace(
                         "PORT", str(self.access.port))


async def _bounded_body(receive, headers) -> tuple[bytes, tuple[int, str] | None]:
    """The body, read up to MAX_BODY_BYTES and within BODY_DEADLINE_S of its head: a body that
    dribbles in holds no connection past the deadline (408)."""
    import asyncio
    import time
    too_big = (413, f"the request body is larger than {MAX_BODY_BYTES // 1024} KiB")
    t_end = time.monotonic() + BODY_DEADLINE_S
    try:
        if int(headers.get("content-length", "0")) > MAX_BODY_BYTES:
            return b"", too_big
    except ValueError:
        return b"", (400, "Content-Length is not a number")
    parts, n = [], 0
    while True:
        try:
            m = await asyncio.wait_for(receive(), max(0.0, t_end - time.monotonic()))
        except asyncio.TimeoutError:
            return b"", (408, f"the request body did not arrive within {BODY_DEADLINE_S:g} s")
        if m["type"] != "http.request":
            return b"", (400, "the client went away before sending its request")
        chunk = m.get("body", b"")
        n += len(chunk)
        if n > MAX_BODY_BYTES:
            return b"", too_big
        parts.append(chunk)
        if not m.get("more_body"):
            return b"".join(parts), None


def _replay(body: bytes, receive):
    sent = False

    async def again():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()
    return again


def guard(app, access: PageAccess, launch: Launch | None = None, is_session=None):
    """The app behind PageGuard (Host with the port, Origin, JSON, body size; a refusal says
    which address to open) and, inside it, Starlette's TrustedHostMiddleware: a second,
    independent check of the host name by the library's own Host parser, so that a mistake
    in PageGuard alone does not let a rebinding site in. (TrustedHostMiddleware alone is not
    enough: it ignores the port and answers only "Invalid host header".)"""
    from starlette.middleware.trustedhost import TrustedHostMiddleware
    return PageGuard(TrustedHostMiddleware(app, allowed_hosts=access.hostnames, www_redirect=False), access,
                     launch, is_session)


# ------------------------------------------------------------------ what: the request body
def parse_body(raw: bytes) -> dict:
    """A request's JSON: one object of at most MAX_JSON_KEYS members whose values are strings,
    numbers, booleans or null (nothing nested), NaN and Infinity refused."""
    depth = _depth(raw)
    if depth > MAX_JSON_DEPTH:
        raise StationError(f"JSON nested {depth} deep: the station takes one flat object")

    def constant(name):
        raise StationError(f"{name} is not a JSON number")
    try:
        d = json.loads(raw.decode("utf-8"), parse_constant=constant)
    except UnicodeDecodeError:
        raise StationError("the request body is not UTF-8") from None
    except ValueError as e:
        if isinstance(e, StationError):
            raise
        raise StationError(f"the request body is not JSON: {e.args[0] if e.args else e}") from None
    if not isinstance(d, dict):
        raise StationError("the request must be a JSON object")
    if len(d) > MAX_JSON_KEYS:
        raise StationError(f"the request has {len(d)} members: at most {MAX_JSON_KEYS}")
    for k in d:
        if len(k) > MAX_KEY_CHARS:
            raise StationError(f"a member name of {len(k)} characters: at most {MAX_KEY_CHARS}")
    return d


def _depth(raw: bytes) -> int:
    """The nesting depth of a JSON text (strings skipped), without parsing it."""
    depth = deepest = 0
    in_str = esc = False
    for c in raw:
        if in_str:
            if esc:
                esc = False
            elif c == 0x5C:             # backslash
                esc = True
            elif c == 0x22:             # quote
                in_str = False
        elif c == 0x22:
            in_str = True
        elif c in (0x5B, 0x7B):         # [ {
            depth += 1
            deepest = max(deepest, depth)
        elif c in (0x5D, 0x7D):
            depth -= 1
    return deepest


def text_field(d: dict, name: str, max_chars: int, default: str = "") -> str:
    v = d.get(name)
    if v is None:
        return default
    if not isinstance(v, str):
        raise StationError(f"{name} must be a string, not {_kind(v)}")
    if len(v) > max_chars:
        raise StationError(f"{name} is {len(v)} characters long: at most {max_chars}")
    return v


def bool_field(d: dict, name: str, default: bool) -> bool:
    v = d.get(name)
    if v is None:
        return default
    if not isinstance(v, bool):
        raise StationError(f"{name} must be true or false (a JSON boolean), not {_kind(v)}")
    return v


def int_field(d: dict, name: str, default: int, allowed) -> int:
    v = d.get(name)
    if v is None:
        return default
    if isinstance(v, bool) or not isinstance(v, int) or v not in allowed:
        choices = ", ".join(str(x) for x in sorted(allowed))
        raise StationError(f"{name} must be one of {choices}, not {_kind(v)}")
    return v


def number_field(d: dict, name: str, default: float, lo: float, hi: float) -> float:
    """A JSON number (not a boolean, not a string) within [lo, hi]."""
    v = d.get(name)
    if v is None:
        return default
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
        raise StationError(f"{name} must be a number from {lo:g} to {hi:g}, not {_kind(v)}")
    return float(v)


def _kind(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return repr(v[:40] + ("…" if len(v) > 40 else ""))
    if isinstance(v, float) and not math.isfinite(v):
        return "a number out of range"
    return repr(v) if isinstance(v, (int, float)) else type(v).__name__


# ------------------------------------------------------------------ what: the device port
SERIAL_PATH = re.compile(r"/dev/(tty[A-Za-z0-9_.-]+|cu\.[A-Za-z0-9_.-]+|rfcomm[0-9]+"
                         r"|serial/by-(id|path)/[A-Za-z0-9_.:@+-]+)")
# what a character device is, from the kernel's table of tty drivers (/proc/tty/drivers: name,
# node, major, minors, type): "serial" (8250 UARTs, USB-serial, ACM, ...) and "pty:slave" (a
# pseudo-terminal: socat, a virtual device) are serial ports; "console" (the virtual consoles
# /dev/tty1..63), "system" (/dev/tty, /dev/console, /dev/ptmx, /dev/tty0) and every device that
# is no tty at all (/dev/zero, /dev/watchdog) are not
SERIAL_KINDS = ("serial", "pty:slave")
TTY_DRIVERS = "/proc/tty/drivers"
WINDOWS_PORT = re.compile(r"(\\\\\.\\)?COM[0-9]{1,3}", re.I)
URL = re.compile(r"([A-Za-z][A-Za-z0-9+.-]*)://(.*)", re.S)


class PortPolicy:
    """The ports a page may open (the command line opens any: it is the operator's).

    handlers  pyserial URL handlers allowed besides socket:// and rfc2217:// (--allow-port-handler)
    hosts     hosts other than this machine that socket:// and rfc2217:// may reach
              (--allow-port-host; "*" any): a page must not make the station connect anywhere
    """

    def __init__(self, handlers=(), hosts=()):
        for h in handlers:
            if h not in PORT_HANDLERS:
                raise ValueError(f"{h!r} is not a pyserial URL handler the station knows "
                                 f"({', '.join(PORT_HANDLERS)}; socket and rfc2217 are always allowed)")
        self.handlers = tuple(handlers)
        self.hosts = {h.strip("[]").lower() for h in hosts}

    def check(self, port: str) -> str:
        """The port, if a page may open it; else a StationError saying why and what allows it."""
        if not isinstance(port, str) or not port:
            raise StationError("give the device's port (e.g. /dev/ttyUSB0, socket://HOST:PORT)")
        if len(port) > MAX_PORT_CHARS:
            raise StationError(f"a port of {len(port)} characters: at most {MAX_PORT_CHARS}")
        if any(ord(c) < 0x21 or ord(c) == 0x7F for c in port):
            raise StationError("a port has no spaces or control characters")
        m = URL.fullmatch(port)
        if m is None:
            return self._serial(port)
        scheme = m.group(1).lower()
        if scheme in ALWAYS_HANDLERS:
            return self._network(port, scheme)
        if scheme not in self.handlers:
            allowed = "socket:// and rfc2217://" + "".join(f", {h}://" for h in self.handlers)
            raise StationError(f"{scheme}:// ports are not opened from the page (serial devices, {allowed} are); "
                               f"start the station with --allow-port-handler {scheme} to allow them")
        if scheme == "spy":
            parts = urlsplit(port)
            opts = parse_qs(parts.query, True)             # the way pyserial's spy handler reads them
            bad = [o for o in opts if o not in SPY_OPTIONS]
            if bad:
                raise StationError(f"spy:// option {bad[0]!r} is refused from the page (it takes "
                                   f"{', '.join(SPY_OPTIONS)}; its log goes to the station's terminal)")
            inner = parts.netloc + parts.path               # what spy:// opens: a serial device
            self._serial(inner)
        elif scheme == "alt":                               # alt://PATH?class=...: PATH as any port
            parts = urlsplit(port)
            self._serial(parts.netloc + parts.path)
        elif scheme == "hwgrep":
            self._hwgrep(m.group(2).split("&")[0])
        return port

    def _serial(self, path: str) -> str:
        """path, if it is a serial device: decided by what the device is (tty_kind), not by its
        name; a path that does not exist yet must at least be named as a serial device."""
        if WINDOWS_PORT.fullmatch(path):
            return path
        if not path.startswith("/") or "\0" in path:
            raise StationError(f"{path[:80]!r} is not a serial device (/dev/ttyUSB0, /dev/ttyACM0, "
                               "/dev/serial/by-id/..., COM3) nor socket://HOST:PORT or rfc2217://HOST:PORT")
        if not os.path.lexists(path):
            if not SERIAL_PATH.fullmatch(path) or "/../" in path or path.endswith("/.."):
                raise StationError(f"{path[:80]!r} is not a serial device (/dev/ttyUSB0, /dev/ttyACM0, "
                                   "/dev/serial/by-id/..., COM3) nor socket://HOST:PORT or rfc2217://HOST:PORT")
            return path                 # not plugged in: opening it will say so
        real = os.path.realpath(path)
        kind = tty_kind(real)
        if kind not in SERIAL_KINDS:
            shown = path if real == path else f"{path} ({real})"
            raise StationError(f"{shown[:160]} is not a serial device: it is {kind}; a page opens UARTs, "
                               "USB-serial adapters and pseudo-terminals only")
        return path

    def _hwgrep(self, regex: str) -> None:
        """hwgrep:// opens the first serial port whose description matches: each one it could
        open is checked as a path is."""
        from imubench.device.link import ports_matching
        try:
            found = ports_matching(regex)
        except re.error as e:
            raise StationError(f"hwgrep://{regex[:40]}: not a regular expression ({e})") from None
        if not found:
            raise StationError(f"hwgrep://{regex[:40]}: no serial port matches")
        for dev in found:
            self._serial(dev)

    def _network(self, port: str, scheme: str) -> str:
        p = urlsplit(port)
        try:
            num = p.port
        except ValueError:
            num = None
        if not p.hostname or num is None or not 0 < num < 65536:
            raise StationError(f"{scheme}:// needs a host and a port number: {scheme}://HOST:PORT")
        if _loopback(p.hostname) or "*" in self.hosts or p.hostname.lower() in self.hosts:
            return port
        raise StationError(f"{p.hostname} is not this machine: a page opens {scheme}:// ports on this machine only; "
                           f"start the station with --allow-port-host {p.hostname} to reach it")


def tty_kind(path: str) -> str:
    """What the file at path is, in words: 'serial' or 'pty:slave' for a serial port, else what
    it is instead ('a virtual console', 'a character device that is no tty (1:5)', 'a regular
    file', ...). On Linux by the device's major and minor number in /proc/tty/drivers; where
    there is no such table (macOS, BSD), by the name the device node has in /dev."""
    try:
        st = os.stat(path)
    except OSError as e:
        return f"not readable ({e.strerror})"
    if not stat.S_ISCHR(st.st_mode):
        from imubench.files import kind_of
        return kind_of(st.st_mode)
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    try:
        with open(TTY_DRIVERS, encoding="ascii", errors="replace") as fh:
            table = fh.read(1 << 16)
    except OSError:
        table = None
    if table is None:
        name = os.path.basename(path)
        if re.fullmatch(r"(tty|cu)\.[A-Za-z0-9_.-]+|tty(USB|ACM|S|AMA|SAC|p)[0-9]+|pts/[0-9]+", name) or \
                re.fullmatch(r"/dev/pts/[0-9]+", path):
            return "serial"
        return f"a character device not named as a serial port ({major}:{minor})"
    for line in table.splitlines():
        f = line.split()
        if len(f) < 5 or not f[2].isdigit() or int(f[2]) != major:
            continue
        lo, _, hi = f[3].partition("-")
        if lo.isdigit() and int(lo) <= minor <= int(hi or lo):
            kind = f[4]
            if kind in SERIAL_KINDS:
                return kind
            words = {"console": "a virtual console", "system:vtmaster": "the current virtual console",
                     "system:/dev/tty": "the controlling terminal", "system:console": "the system console",
                     "pty:master": "the master side of a pseudo-terminal",
                     "system": "a system tty (the pseudo-terminal multiplexer)"}
            return f"{words.get(kind, 'a tty of the kind ' + kind)} ({f[1]}, {major}:{minor})"
    return f"a character device that is no tty ({major}:{minor})"


def _loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False
