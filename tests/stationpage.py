"""How a test opens the station page as its operator does: the address the station printed
(with its one-time secret), the session the page then holds, a report through its ticket."""
from __future__ import annotations

import json
import urllib.request

SESSION_KEY = "imubench-station-session"
#: the first address `imubench station` / `calibrate --ui web` prints
FIRST_URL = r"station page: (http://127\.0\.0\.1:\d+/#token=[\w-]+)"
#: the next one, printed once a browser has traded the first
NEXT_URL = r"to open it in another: (http://127\.0\.0\.1:\d+/#token=[\w-]+)"


def base_of(url: str) -> str:
    return url.split("#", 1)[0]


def session_of(page) -> str:
    """The session the page traded its secret for (it lives in the tab's sessionStorage)."""
    page.wait_for_function(f"() => !!sessionStorage.getItem('{SESSION_KEY}')")
    return page.evaluate(f"sessionStorage.getItem('{SESSION_KEY}')")


def headers_of(page, origin: bool = True) -> dict:
    h = {"X-Imubench-Session": session_of(page)}
    if origin:
        h["Origin"] = page.evaluate("location.origin")
    return h


def report_url(page, link) -> str:
    """The address a report link opens (with its single-use ticket), as the page asks for it."""
    path = link.get_attribute("data-report")
    return page.evaluate(f"""(p) => fetch('/api/ticket', {{method: 'POST', headers: {{'Content-Type': 'application/json',
        'X-Imubench-Session': sessionStorage.getItem('{SESSION_KEY}')}}, body: JSON.stringify({{path: p}})}})
        .then((r) => r.json()).then((j) => location.origin + j.url)""", path)


def get_json(url: str, session: str, timeout: float = 10):
    req = urllib.request.Request(base_of(url), headers={"X-Imubench-Session": session})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())
