#!/usr/bin/env python3
"""The station page under a flood (issue 25): how much memory the server holds after the
bounded attacks, and how long /api/start takes while pages hold event streams open.

Starts `imubench station` in its own process on 127.0.0.1 (any free port), lets an operator's
client claim a device, then
  1. floods it: 200 claims of devices with 256-character keys, 100 new browsers, 20 bodies
     of 50 MB (announced) and 20 sent chunked, 100 JSON texts nested 5000 deep, 200 event
     streams opened at once (kept open), and reports the server's resident memory (VmRSS)
     before and after, with how many requests were refused;
  2. measures /api/start (median and worst of 5) with 0, 20, 60 and 200 event streams open,
     and whether another browser could take the operator's device while they were.

Target: memory after the flood within 50 MB of before; /api/start under 0.5 s with 200
streams open (it was delayed 30 s by 20 streams, and stopped by 200, before issue 25).

    python bench/station_flood.py [--no-publish]

Prints a table and a final JSON line; the markdown table docs/production.md states is printed
and published (bench/publish.py; --no-publish to leave the docs alone).
"""
from __future__ import annotations

import argparse
import http.cookiejar
import json
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

DEVICE = "socket://127.0.0.1:1"          # nothing listens: a started session fails at once


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        kb = int(re.search(r"VmRSS:\s+(\d+)", f.read()).group(1))
    return kb / 1024


class Addresses:
    """The station's addresses with a one-time secret, as it prints them: the first at start,
    the next each time a browser has traded one (issue 36)."""

    def __init__(self, proc):
        self.proc = proc

    def next(self) -> str:
        while True:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError("the station ended before printing its address")
            m = re.search(r"(http://127\.0\.0\.1:\d+/)#token=([\w-]+)", line)
            if m:
                return m.group(0)


class Client:
    """A page: it trades a secret the station printed for a session (open()), sent in a header."""

    def __init__(self, url: str):
        self.url = url.split("#", 1)[0]
        self.session = ""
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(http.cookiejar.CookieJar()))

    def open(self, addresses: "Addresses") -> int:
        code, body = self.call("api/session", {}, headers={"X-Imubench-Launch": addresses.next().split("#token=")[1]})
        if code == 200:
            self.session = body["session"]
        return code

    def call(self, path, data=None, raw=None, headers=None):
        body = raw if raw is not None else None if data is None else json.dumps(data).encode()
        req = urllib.request.Request(self.url + path, data=body, headers={
            "Content-Type": "application/json", "Origin": self.url.rstrip("/"),
            **({"X-Imubench-Session": self.session} if self.session else {}), **(headers or {})})
        try:
            with self.opener.open(req, timeout=60) as r:
                return r.status, json.loads(r.read() or b"null")
        except urllib.error.HTTPError as e:
            return e.code, json.loads(e.read() or b"null")



def send_raw(port: int, head: str, body_chunks=()) -> int:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    try:
        s.sendall(head.replace("\n", "\r\n").encode() + b"\r\n")
        for c in body_chunks:
            try:
                s.sendall(c)
            except OSError:
                break
        data = s.recv(4096)
        return int(data.split()[1]) if data else 0
    except OSError:
        return 0
    finally:
        s.close()


def open_stream(port: int, session: str = "") -> tuple[socket.socket, int]:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    s.sendall((f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
               + (f"X-Imubench-Session: {session}\r\n" if session else "") + "\r\n").encode())
    head = s.recv(65536)
    return s, int(head.split()[1])


def start_once(op: Client, server_state) -> float:
    t0 = time.perf_counter()
    code, body = op.call("api/start", {"port": DEVICE, "write": False})
    dt = time.perf_counter() - t0
    assert code == 200, body
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end:                  # the session fails at once (nothing listens)
        st = server_state()
        if next(b for b in st["boards"] if b["key"] == DEVICE)["status"] != "running":
            break
        time.sleep(0.05)
    return dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="station-flood-") as tmp:
        return run(tmp, not a.no_publish)


def _ms(s: float) -> str:
    return f"{s * 1e3:.1f}" if s < 0.01 else f"{s * 1e3:.0f}"


def table(out: dict) -> str:
    """The markdown table docs/production.md states."""
    rows = out["start"]
    ns = " / ".join(str(r["streams"]) for r in rows)
    return ("| figure | value |\n|---|---|\n"
            f"| server memory (VmRSS) before → after the flood | {out['rss_before_mb']:.0f} MB → "
            f"{out['rss_after_flood_mb']:.0f} MB (target: within 50 MB) |\n"
            f"| `/api/start` with {ns} event streams asked for, median of 5 | "
            + " / ".join(_ms(r["median_s"]) for r in rows) + " ms (target < 500 ms) |\n"
            "| the same, worst of 5 | " + " / ".join(_ms(r["worst_s"]) for r in rows) + " ms |\n"
            f"| event streams served of {ns} asked for | " + " / ".join(str(r["served"]) for r in rows) + " |\n"
            "| another browser took the operator's device | "
            + ("never" if all(r["kept"] for r in rows) else "YES") + " |\n")


def run(tmp: str, publishing: bool = False) -> int:
    proc = subprocess.Popen([sys.executable, "-m", "imubench", "station", "--http-port", "0", "--dir", tmp,
                             "--db", os.path.join(tmp, "h.sqlite")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out = {}
    try:
        addresses = Addresses(proc)
        first = addresses.next()
        url = first.split("#", 1)[0]
        port = int(url.rsplit(":", 1)[1].strip("/"))
        op = Client(url)
        code, body = op.call("api/session", {}, headers={"X-Imubench-Launch": first.split("#token=")[1]})
        assert code == 200, body
        op.session = body["session"]
        assert op.call("api/claim", {"key": DEVICE})[1]["yours"]
        state = lambda: op.call("api/state")[1]       # noqa: E731
        start_once(op, state)                         # warm: imports of the session code
        out["rss_before_mb"] = rss_mb(proc.pid)

        refused = {}
        others = [Client(url) for _ in range(4)]
        for c in others:
            c.open(addresses)
        for k in range(200):
            key = f"socket://127.0.0.1:{1024 + k}?" + "x" * 200
            code, _ = others[k % 4].call("api/claim", {"key": key[:256]})
            refused[code] = refused.get(code, 0) + 1
        for _ in range(100):
            code = Client(url).open(addresses)
            refused[code] = refused.get(code, 0) + 1
        post = (f"POST /api/claim HTTP/1.1\nHost: 127.0.0.1:{port}\nOrigin: http://127.0.0.1:{port}\n"
                f"X-Imubench-Session: {op.session}\nContent-Type: application/json\n")
        for _ in range(20):
            code = send_raw(port, post + f"Content-Length: {50 << 20}\n")
            refused[code] = refused.get(code, 0) + 1
        chunk = b"%x\r\n%s\r\n" % (1 << 20, b" " * (1 << 20))
        for _ in range(20):
            code = send_raw(port, post + "Transfer-Encoding: chunked\n", [chunk] * 50)
            refused[code] = refused.get(code, 0) + 1
        for _ in range(100):
            code, _ = op.call("api/start", raw=b"[" * 5000 + b"]" * 5000)
            refused[code] = refused.get(code, 0) + 1
        socks = []
        for _ in range(200):
            s, code = open_stream(port)
            refused[code] = refused.get(code, 0) + 1
            (socks.append(s) if code == 200 else s.close())
        time.sleep(1.0)
        out["rss_after_flood_mb"] = rss_mb(proc.pid)
        out["answers"] = {str(k): v for k, v in sorted(refused.items())}
        for s in socks:
            s.close()
        time.sleep(1.0)

        print(f"server memory (VmRSS): {out['rss_before_mb']:.0f} MB before, {out['rss_after_flood_mb']:.0f} MB "
              f"after the flood (answers by HTTP status: {out['answers']})")
        print(f"{'streams opened':>15} {'served':>7} {'start median s':>15} {'start worst s':>14}  device kept")
        out["start"] = []
        own, _ = open_stream(port, op.session)         # the operator's page is open
        for n in (0, 20, 60, 200):
            socks = []
            watchers = [Client(url) for _ in range(-(-n // 8))]     # 8 tabs a browser
            for w in watchers:
                w.open(addresses)
            for k in range(n):
                s, code = open_stream(port, watchers[k // 8].session)
                (socks.append(s) if code == 200 else s.close())
            times = [start_once(op, state) for _ in range(5)]
            thief = Client(url)
            thief.open(addresses)
            kept = thief.call("api/claim", {"key": DEVICE})[1]["yours"] is False
            row = {"streams": n, "served": len(socks), "median_s": statistics.median(times), "worst_s": max(times),
                   "kept": kept}
            out["start"].append(row)
            print(f"{n:>15} {len(socks):>7} {row['median_s']:>15.3f} {row['worst_s']:>14.3f}  {'yes' if kept else 'NO'}")
            for s in socks:
                s.close()
            time.sleep(0.5)
        own.close()
        out["rss_end_mb"] = rss_mb(proc.pid)
    finally:
        proc.terminate()
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    md = table(out)
    print("\n" + md, end="")
    publish("station_flood", md, {"answers by HTTP status": out["answers"]}, enabled=publishing)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
