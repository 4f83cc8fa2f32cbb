"""The station's web server: Starlette (routing, static files, streaming responses) on
uvicorn, bound to 127.0.0.1 only. Live updates are server-sent events: one snapshot of the
station's state (station.state) each time it changes, at most ten a second.

    GET  /                     the page (static/station.html)
    GET  /static/...           its CSS and JS (package data; nothing from the network)
    GET  /api/state            a snapshot (JSON)
    GET  /api/events?token=T   server-sent events: snapshots as they change
    POST /api/claim            {key}: own the device if it is free -> {token | null}
    POST /api/start            {port, method, gyro, capture, write, note} (X-Station-Token)
    POST /api/stop, /api/resume  {key} (the owner only)
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

EVENT_MIN_INTERVAL_S = 0.1
KEEPALIVE_S = 10.0


def create_app(station: Station) -> Starlette:
    state = station.state

    async def page(request: Request):
        from importlib.resources import files
        return Response((files("imubench.station") / "static" / "station.html").read_text(encoding="utf-8"),
                        media_type="text/html; charset=utf-8", headers={"Cache-Control": "no-store"})

    async def snapshot(request: Request):
        return JSONResponse(_finite(state.snapshot(request.query_params.get("token"))))

    async def events(request: Request):
        token = request.query_params.get("token")

        async def stream():
            version = -1
            last_send = 0.0
            while True:
                if state.closed or await request.is_disconnected():
                    return
                state.seen(token)
                new = await asyncio.to_thread(state.wait, version, KEEPALIVE_S)
                if state.closed:
                    return
                if new == version:
                    yield ": keep-alive\n\n"
                    continue
                wait = EVENT_MIN_INTERVAL_S - (time.monotonic() - last_send)
                if wait > 0:
                    await asyncio.sleep(wait)
                snap = state.snapshot(token)
                version = snap["version"]
                last_send = time.monotonic()
                yield f"data: {json.dumps(_finite(snap), allow_nan=False, default=_num)}\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    async def body(request: Request) -> dict:
        try:
            d = await request.json()
        except ValueError:
            d = None
        if not isinstance(d, dict):
            raise StationError("the request must be a JSON object")
        return d

    def token_of(request: Request) -> str | None:
        return request.headers.get("x-station-token") or None

    async def claim(request: Request):
        d = await body(request)
        key = str(d.get("key") or "")
        if not key:
            raise StationError("which device? give key")
        return JSONResponse({"key": key, "token": state.claim(key, d.get("token") or token_of(request))})

    async def start(request: Request):
        d = await body(request)
        tok = token_of(request)
        if not tok:
            raise StationError("this page owns no device: reload it")
        key = await asyncio.to_thread(station.start, d, tok)
        return JSONResponse({"key": key})

    async def stop(request: Request):
        d = await body(request)
        station.stop(str(d.get("key") or ""), token_of(request))
        return JSONResponse({"ok": True})

    async def resume(request: Request):
        d = await body(request)
        station.resume(str(d.get("key") or ""), token_of(request))
        return JSONResponse({"ok": True})

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
        if rate is None and angle is None:
            rate = 0.0
        return Response(draw(axis, rate_dps=rate, angle_deg=angle), media_type="image/svg+xml")

    async def report(request: Request):
        p = station.report_path(request.path_params["key"])
        if p is None or not p.is_file():
            return JSONResponse({"error": "no report for this device yet"}, status_code=404)
        return FileResponse(p, media_type="text/html")

    async def bad_request(request: Request, exc: StationError):
        return JSONResponse({"error": str(exc)}, status_code=409 if "another page" in str(exc) else 400)

    from importlib.resources import files
    static_dir = str(files("imubench.station") / "static")
    routes = [Route("/", page), Route("/api/state", snapshot), Route("/api/events", events),
              Route("/api/claim", claim, methods=["POST"]), Route("/api/start", start, methods=["POST"]),
              Route("/api/stop", stop, methods=["POST"]), Route("/api/resume", resume, methods=["POST"]),
              Route("/pose.svg", pose_svg), Route("/turn.svg", turn_svg),
              Route("/report/{key}/report.html", report), Mount("/static", StaticFiles(directory=static_dir))]
    return Starlette(routes=routes, exception_handlers={StationError: bad_request})


@lru_cache(maxsize=64)
def _pose_svg(up: tuple) -> str:
    from imubench.results.boardpic import board_svg
    return board_svg(up, size_px=150)


def _vector(text) -> tuple:
    try:
        v = tuple(float(x) for x in str(text).split(","))
    except ValueError:
        v = ()
    if len(v) != 3 or not any(v):
        raise StationError("give a direction as x,y,z (board frame), not all zero")
    return v


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


class Server:
    """uvicorn serving the station on 127.0.0.1:port (0: a free port; .port is the real one)."""

    def __init__(self, station: Station, port: int = 0, host: str = "127.0.0.1"):
        import uvicorn
        self.station = station
        self.config = uvicorn.Config(create_app(station), host=host, port=port, log_level="warning",
                                     lifespan="off", access_log=False, timeout_graceful_shutdown=1)
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
        return f"http://127.0.0.1:{self.port}/"

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
