"""The station's web server: Starlette (routing, static files, streaming responses) on
uvicorn, bound to 127.0.0.1 only. Live updates are server-sent events: one snapshot of the
station's state (station.state) each time it changes, at most ten a second.

Only the operator's own browser drives it (station.security; docs/station.md): the station
prints its address with a one-time launch secret (security.Launch, as Jupyter's token); the
page trades it for a session it sends in a header with every request. Every request passes
PageGuard (Host with the served port, the page's Origin and a JSON body for every POST, the
session, bounded bodies with a deadline) and TrustedHostMiddleware (the host name, again).
Nothing is kept in a cookie: a browser sends 127.0.0.1's cookies to every port.

    GET  /                     the page (static/station.html; no session needed, nor given)
    GET  /static/...           its CSS and JS (package data; nothing from the network)
    POST /api/session          {} with X-Imubench-Launch: SECRET: a session -> {session}
    POST /api/ticket           {path}: a single-use link to a report (a new tab sends no header)
    GET  /api/state            a snapshot (JSON)
    GET  /api/events           server-sent events: snapshots as they change (the session says whose)
    POST /api/claim            {key}: drive the device if it is free -> {key, yours}
    POST /api/start            {port, method, gyro, capture, write, note, rate_hz} (claims the device)
    POST /api/warmup           {port, span_lo_c, span_hi_c, face, write, rate_hz}: a temperature
                               warm-up on that device (claims it; procedures.warmup.run_warmup)
    POST /api/stop, /api/resume  {key} (the owner only; a warm-up stops keeping the fit of what came)
    GET  /pose.svg?up=x,y,z    the board in that attitude (results.boardpic)
    GET  /turn.svg?axis=x,y,z&rate=R  (or &angle=A: a turn by hand)
    GET  /report/KEY/report.html  the session's HTML report
"""
from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from functools import lru_cache

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from imubench.station.runner import Station, StationError
from imubench.station.security import SESSION_HEADER, TICKET_PATH, Launch, PageAccess, guard, parse_body
from imubench.station.state import Refused

EVENT_MIN_INTERVAL_S = 0.1
KEEPALIVE_S = 10.0
# a crowd of local connections (issue 36): uvicorn's own limit (limit_concurrency) counted every
# connection, idle or half-sent, and answered 503 to the operator's Stop once strangers held
# 256. Here a connection is a stranger's until a request on it carries this launch's session:
HEAD_DEADLINE_S = 5.0           # from the connection (or the last response) to a request's whole head
STRANGER_IDLE_S = 2.0           # a stranger's connection after its answer (keep-alive): then closed
KEEPALIVE_IDLE_S = 20.0         # a session's idle keep-alive connection: then closed
MAX_STRANGERS = 1024            # strangers' silent connections at once: past it the oldest is closed
MAX_SESSION_CONNECTIONS = 24    # one session's connections counted as its own (tabs, streams)
WARNING_EVERY_S = 10.0          # one log line per kind of warning per this long, with a count


class _Changes:
    """Wakes the event streams on the server's event loop when the state changes (from any
    thread): streams wait here, not in a thread of the pool the commands use."""

    def __init__(self, state):
        self.state = state
        self.loop: asyncio.AbstractEventLoop | None = None
        self.event: asyncio.Event | None = None
        state.on_change(self._changed)

    def _changed(self) -> None:
        loop = self.loop
        if loop is not None:
            try:
                loop.call_soon_threadsafe(self._fire)
            except RuntimeError:            # the loop is closed: the server has stopped
                pass

    def _fire(self) -> None:
        ev, self.event = self.event, asyncio.Event()
        ev.set()

    async def wait(self, version: int, timeout: float) -> None:
        if self.loop is None:
            self.loop, self.event = asyncio.get_running_loop(), asyncio.Event()
        ev = self.event
        if self.state.version != version or self.state.closed:
            return
        try:
            await asyncio.wait_for(ev.wait(), timeout)
        except asyncio.TimeoutError:
            pass


class _Stream(StreamingResponse):
    """A streaming response that gives its slot back however it ends (even unstarted)."""

    def __init__(self, content, release, **kw):
        super().__init__(content, **kw)
        self._release = release

    async def __call__(self, scope, receive, send):
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._release()


# ------------------------------------------------------------------ handlers that need no station
async def page(request: Request):
    return Response(_page_html(), media_type="text/html; charset=utf-8", headers={"Cache-Control": "no-store"})


@lru_cache(maxsize=1)
def _page_html() -> str:
    from importlib.resources import files
    return (files("imubench.station") / "static" / "station.html").read_text(encoding="utf-8")


async def pose_svg(request: Request):
    up = _vector(request.query_params.get("up"))
    return Response(_pose_svg(up), media_type="image/svg+xml", headers={"Cache-Control": "max-age=3600"})


async def turn_svg(request: Request):
    from imubench.results.boardpic import turn_svg as draw
    axis = _vector(request.query_params.get("axis"))
    try:
        rate = request.query_params.get("rate")
        angle = request.query_params.get("angle")
        rate = None if rate is None else float(rate)
        angle = None if angle is None else float(angle)
    except ValueError:
        raise StationError("rate (°/s) and angle (°) must be numbers") from None
    if any(x is not None and not (math.isfinite(x) and abs(x) <= 1e4) for x in (rate, angle)):
        raise StationError("rate (°/s) and angle (°) must be numbers within ±10000")
    if rate is None and angle is None:
        rate = 0.0
    return Response(draw(axis, rate_dps=rate, angle_deg=angle), media_type="image/svg+xml")


async def bad_request(request: Request, exc: StationError):
    return JSONResponse({"error": str(exc)}, status_code=getattr(exc, "status", 400),
                        headers={"Cache-Control": "no-store"})


def create_app(station: Station, access: PageAccess | None = None, launch: Launch | None = None):
    """The station's ASGI app, guarded (security.guard): access says which Host and Origin
    are the page's (its port is set once the server is bound); launch holds the secret a
    page trades for its session (a new one if not given)."""
    state = station.state
    access = access or PageAccess()
    launch = launch or Launch()
    changes = _Changes(state)

    def identity(request: Request) -> str | None:
        return state.client(request.headers.get(SESSION_HEADER))

    def need_identity(request: Request) -> str:
        tok = identity(request)
        if tok is None:
            raise StationError("this page has no session on the station: open the address the station printed",
                               status=403)
        return tok

    async def session(request: Request):
        from imubench.station.security import LAUNCH_HEADER
        await body(request)
        if not launch.trade(request.headers.get(LAUNCH_HEADER)):     # spent since PageGuard looked
            raise StationError("this address's secret is spent: open the newest address the station printed",
                               status=403)
        try:
            tok = state.new_client()
        except Refused as e:
            raise StationError(str(e), status=429) from None
        return JSONResponse({"session": tok}, headers={"Cache-Control": "no-store"})

    async def ticket(request: Request):
        d = await body(request)
        path = d.get("path")
        if not isinstance(path, str) or not TICKET_PATH.fullmatch(path):
            raise StationError("a ticket is for a report or an export: give path /report/KEY/report.html "
                               "or /export/KEY/FILE")
        return JSONResponse({"url": f"{path}?ticket={launch.ticket(path)}"}, headers={"Cache-Control": "no-store"})

    async def snapshot(request: Request):
        return JSONResponse(_finite(state.snapshot(identity(request))), headers={"Cache-Control": "no-store"})

    async def events(request: Request):
        token = identity(request)
        try:
            state.stream_opened(token)
        except Refused as e:
            raise StationError(str(e), status=429) from None

        async def stream():
            version = -1
            last_send = 0.0
            while True:
                if state.closed or await request.is_disconnected():
                    return
                state.seen(token)
                await changes.wait(version, KEEPALIVE_S)
                if state.closed:
                    return
                if state.version == version:
                    yield ": keep-alive\n\n"
                    continue
                wait = EVENT_MIN_INTERVAL_S - (time.monotonic() - last_send)
                if wait > 0:
                    await asyncio.sleep(wait)
                snap = state.snapshot(token)
                version = snap["version"]
                last_send = time.monotonic()
                yield f"data: {json.dumps(_finite(snap), allow_nan=False, default=_num)}\n\n"

        return _Stream(stream(), lambda: state.stream_closed(token), media_type="text/event-stream",
                       headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    async def body(request: Request) -> dict:
        return parse_body(await request.body())     # PageGuard has bounded it already

    def key_of(d: dict) -> str:
        key = d.get("key")
        if not isinstance(key, str) or not key:
            raise StationError("which device? give key (a string)")
        if len(key) > 256:
            raise StationError(f"a key of {len(key)} characters: at most 256")
        return key

    async def claim(request: Request):
        d = await body(request)
        key = key_of(d)
        tok = need_identity(request)
        return JSONResponse({"key": key, "yours": station.claim(key, tok)})

    async def start(request: Request):
        d = await body(request)
        tok = need_identity(request)
        key = await asyncio.to_thread(station.start, d, tok)
        return JSONResponse({"key": key})

    async def warmup(request: Request):
        d = await body(request)
        tok = need_identity(request)
        key = await asyncio.to_thread(station.start_warmup, d, tok)
        return JSONResponse({"key": key})

    async def stop(request: Request):
        d = await body(request)
        station.stop(key_of(d), need_identity(request))
        return JSONResponse({"ok": True})

    async def resume(request: Request):
        d = await body(request)
        station.resume(key_of(d), need_identity(request))
        return JSONResponse({"ok": True})

    async def report(request: Request):
        p = station.report_path(request.path_params["key"])
        if p is None or not p.is_file():
            return JSONResponse({"error": "no report for this device yet"}, status_code=404)
        return FileResponse(p, media_type="text/html")

    async def export(request: Request):
        p = station.export_path(request.path_params["key"], request.path_params["name"])
        if p is None or not p.is_file():
            return JSONResponse({"error": "no such export for this device"}, status_code=404)
        return FileResponse(p, media_type="text/plain; charset=utf-8", filename=p.name)

    from importlib.resources import files
    static_dir = str(files("imubench.station") / "static")
    routes = [Route("/", page), Route("/api/session", session, methods=["POST"]),
              Route("/api/ticket", ticket, methods=["POST"]),
              Route("/api/state", snapshot), Route("/api/events", events),
              Route("/api/claim", claim, methods=["POST"]), Route("/api/start", start, methods=["POST"]),
              Route("/api/warmup", warmup, methods=["POST"]),
              Route("/api/stop", stop, methods=["POST"]), Route("/api/resume", resume, methods=["POST"]),
              Route("/pose.svg", pose_svg), Route("/turn.svg", turn_svg),
              Route("/report/{key}/report.html", report), Route("/export/{key}/{name}", export), Mount("/static", StaticFiles(directory=static_dir))]
    app = Starlette(routes=routes, exception_handlers={StationError: bad_request})
    return guard(app, access, launch, lambda tok: state.client(tok) is not None)


@lru_cache(maxsize=64)
def _pose_svg(up: tuple) -> str:
    from imubench.results.boardpic import board_svg
    return board_svg(up, size_px=150)


def _vector(text) -> tuple:
    try:
        v = tuple(float(x) for x in str(text)[:100].split(","))
    except ValueError:
        v = ()
    if len(v) != 3 or not any(v) or not all(math.isfinite(x) for x in v):
        raise StationError("give a direction as x,y,z (board frame), finite numbers, not all zero")
    big = max(abs(x) for x in v)            # scaled to at most 1: 1e300 or 1e-320 draw as 1
    return tuple(x / big for x in v)


def _finite(x):
    """JSON has no NaN or infinity: a number not known (NaN) or unbounded is sent as null."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _num(x):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    return v if math.isfinite(v) else None


class Crowd:
    """Who holds the server's connections. A new connection is a stranger's, in a pool of at
    most MAX_STRANGERS: when one more arrives the oldest stranger is closed, so that a crowd of
    silent, half-sent or idle connections can never keep out a new one whose request comes at
    once (a browser's). A connection whose request carries this launch's session becomes its
    session's (up to MAX_SESSION_CONNECTIONS each): never closed for a stranger, not counted
    with them. Deadlines (the protocol below): a request's head HEAD_DEADLINE_S after the
    connection or the last answer; a stranger's keep-alive STRANGER_IDLE_S, a session's
    KEEPALIVE_IDLE_S; the body BODY_DEADLINE_S (security._bounded_body)."""

    def __init__(self, is_session):
        from collections import OrderedDict
        self.is_session = is_session
        self.strangers: OrderedDict = OrderedDict()
        self.sessions: dict[str, set] = {}
        self.closed_strangers = 0           # how many were closed to make room (tests, the bench)
        self.timed_out = 0                  # ... closed at a deadline

    def arrived(self, conn) -> None:
        self.strangers[conn] = None
        while len(self.strangers) > MAX_STRANGERS:
            old = self._quietest()
            if old is None:
                if len(self.strangers) <= 2 * MAX_STRANGERS:
                    return                  # all are talking: they are read next, then judged
                old = next(iter(self.strangers))
            del self.strangers[old]
            self.closed_strangers += 1
            old.transport.abort()           # connection_lost follows: left() forgets it

    def _quietest(self):
        """The stranger to close: the oldest with nothing waiting to be read. A connection
        accepted in the same burst as a crowd's, whose request is already in its socket (a
        browser sends it at once), has not been read yet but is not silent: it stays."""
        for conn in self.strangers:
            if _pending_bytes(conn.transport) == 0:
                return conn
        return None


    def promote(self, conn, session: str) -> bool:
        """conn carried session: its own from now on (False: not a session, or it has enough)."""
        if conn.session == session:
            return True
        if not session or not self.is_session(session):
            return False
        mine = self.sessions.setdefault(session, set())
        if len(mine) >= MAX_SESSION_CONNECTIONS:
            return False
        self.strangers.pop(conn, None)
        mine.add(conn)
        conn.session = session
        return True

    def left(self, conn) -> None:
        self.strangers.pop(conn, None)
        if conn.session is not None:
            mine = self.sessions.get(conn.session)
            if mine is not None:
                mine.discard(conn)
                if not mine:
                    del self.sessions[conn.session]


def _pending_bytes(transport) -> int:
    """Bytes received on transport's socket and not read yet (FIONREAD), 0 if unknown."""
    import array
    try:
        import fcntl
        import termios
    except ImportError:                 # Windows: every stranger counts as silent
        return 0
    sock = transport.get_extra_info("socket")
    if sock is None:
        return 0
    buf = array.array("i", [0])
    try:
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, buf, True)
    except OSError:
        return 0
    return buf[0]


def _protocol(crowd: Crowd):
    """uvicorn's h11 protocol with the crowd's rules (Crowd): deadlines for a request's head and
    for idle keep-alive connections, a bounded pool of strangers, sessions apart."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class GuardedH11(H11Protocol):
        def connection_made(self, transport):
            super().connection_made(transport)
            self.session = None
            self._timer = None
            crowd.arrived(self)
            self._arm(HEAD_DEADLINE_S)

        def _arm(self, seconds: float) -> None:
            if self._timer is not None:
                self._timer.cancel()
            self._timer = self.loop.call_later(seconds, self._late)

        def _late(self) -> None:
            self._timer = None
            busy = self.cycle is not None and not self.cycle.response_complete
            if not busy and not self.transport.is_closing():
                crowd.timed_out += 1
                self.transport.abort()

        def data_received(self, data: bytes) -> None:
            cycle = self.cycle
            super().data_received(data)
            if self.cycle is not cycle and self.cycle is not None:      # a request's head is complete
                if self._timer is not None:
                    self._timer.cancel()
                    self._timer = None
                token = dict(self.headers).get(SESSION_HEADER.encode())
                if token is not None:
                    crowd.promote(self, token.decode("latin-1"))

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._unset_keepalive_if_required()          # ours instead: by whose connection it is
                self._arm(KEEPALIVE_IDLE_S if self.session else STRANGER_IDLE_S)

        def connection_lost(self, exc) -> None:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            crowd.left(self)
            super().connection_lost(exc)

    return GuardedH11


def _room_for_connections(n: int) -> None:
    """Raise this process's open-file limit (the soft one, up to the hard one) to n if it is
    lower: a crowd's connections are closed by the station's rules (Crowd), not by running
    out of descriptors (accept() failing stops the server accepting the operator too)."""
    try:
        import resource
    except ImportError:                 # Windows
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < n:
        want = n if hard == resource.RLIM_INFINITY else min(n, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
        except (ValueError, OSError):
            pass


class _FewWarnings:
    """A logging filter: the first warning of each kind, then at most one per WARNING_EVERY_S
    saying how many like it were not shown (a crowd wrote 4,784 lines before)."""

    def __init__(self):
        self.last: dict[str, float] = {}
        self.hidden: dict[str, int] = {}

    def filter(self, record) -> bool:
        key = str(record.msg)[:80]
        now = time.monotonic()
        if now - self.last.get(key, -1e9) < WARNING_EVERY_S:
            self.hidden[key] = self.hidden.get(key, 0) + 1
            return False
        self.last[key] = now
        n = self.hidden.pop(key, 0)
        if n:
            record.msg = f"{record.getMessage()} ({n} more like it in the last {WARNING_EVERY_S:.0f} s not shown)"
            record.args = ()
        return True


_FEW_WARNINGS = _FewWarnings()


class Server:
    """uvicorn serving the station on 127.0.0.1:port (0: a free port; .port is the real one).
    allow_origins: origins besides http://127.0.0.1:PORT (and localhost, [::1]) the page may be
    opened as (--allow-origin, e.g. the local end of an SSH tunnel on another port)."""

    def __init__(self, station: Station, port: int = 0, host: str = "127.0.0.1", allow_origins=()):
        import uvicorn
        self.station = station
        self.access = PageAccess(allow_origins)
        self.launch = Launch(on_new=self._new_secret)
        self.secret = self.launch._secrets[-1]      # the one the command prints
        self.on_new_url = None                      # told each fresh address (serve_forever prints it)
        self.crowd = Crowd(lambda tok: station.state.client(tok) is not None)
        self.config = uvicorn.Config(create_app(station, self.access, self.launch), host=host, port=port,
                                     log_level="warning", lifespan="off", access_log=False,
                                     timeout_graceful_shutdown=1, http=_protocol(self.crowd),
                                     timeout_keep_alive=int(KEEPALIVE_IDLE_S))
        import logging
        for name in ("uvicorn.error", "uvicorn"):
            lg = logging.getLogger(name)
            if _FEW_WARNINGS not in lg.filters:
                lg.addFilter(_FEW_WARNINGS)
        self.server = uvicorn.Server(self.config)
        self.thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        for s in self.server.servers:
            for sock in s.sockets:
                return int(sock.getsockname()[1])
        return int(self.config.port)

    @property
    def url(self) -> str:
        """The page's address without a secret: it shows the page, which opens nothing."""
        return f"http://127.0.0.1:{self.port}/"

    def secret_url(self, secret: str) -> str:
        return f"{self.url}#token={secret}"

    @property
    def launch_url(self) -> str:
        """The address the command prints: the page with the launch secret not yet spent."""
        return self.secret_url(self.secret)

    def new_launch_url(self) -> str:
        """One more address with a fresh one-time secret (a second browser, a test's page)."""
        return self.secret_url(self.launch.issue())

    def _new_secret(self, secret: str) -> None:
        self.secret = secret
        if self.on_new_url is not None:
            self.on_new_url(self.secret_url(secret))

    def start(self, timeout: float = 15.0) -> "Server":
        """Bind 127.0.0.1:port here (a port in use is a StationError, before anything else has
        started), then serve in a background thread; return once it listens."""
        import socket
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.config.host, self.config.port))
        except OSError as e:
            sock.close()
            raise StationError(f"the station cannot listen on {self.config.host}:{self.config.port}: "
                               f"{e.strerror or e}") from None
        self.access.bind(sock.getsockname()[1])
        _room_for_connections(2 * MAX_STRANGERS + 512)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [sock]}, name="station server",
                                       daemon=True)
        self.thread.start()
        t_end = time.monotonic() + timeout
        while not self.server.started:
            if not self.thread.is_alive():
                raise StationError(f"the station's web server stopped before it listened on "
                                   f"127.0.0.1:{self.port}")
            if time.monotonic() > t_end:
                raise StationError("the station's web server did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.station.state.close()      # open pages' event streams end first
        self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(10)
