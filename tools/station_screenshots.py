"""Retake the station page's screenshots in docs/ (issue 38): the end of a 16-board station
session on the virtual fixture with one board frozen (its simulator SIGSTOPped while the plate
works: its link open, nothing answering), in headless Chromium at 1366 x 768.

    .venv/bin/python tools/station_screenshots.py [--frozen K] [--out docs]

Writes OUT/station-overview-16.png (the overview at the end: the pass count, the closed plate,
15 tiles PASSED and the frozen one FAILED at its own stage with its reason) and
OUT/station-board-column.png (a passed board's column, opened by a click). Prints the
session's summary line and the frozen board's verdict.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCREEN = {"width": 1366, "height": 768}


def children(pid: int) -> list[int]:
    """The processes `pid` started (from /proc), oldest first."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if ppid == pid:
                out.append(int(d.name))
    return sorted(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frozen", type=int, default=7, help="the slot frozen (1..16)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright
    work = Path(tempfile.mkdtemp(prefix="imubench-shots-"))
    cmd = [sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-boards", "16", "--ui", "web",
           "--http-port", "0", "--dir", str(work / "st"), "--db", str(work / "h.sqlite")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=work)
    frozen_pid = None
    tail: list[str] = []                    # its output after the page's address, read as it comes
    try:
        url = None
        for line in proc.stdout:
            print(line, end="")
            m = re.search(r"station page: (http://127\.0\.0\.1:\d+/)", line)
            if m:
                url = m.group(1)
                break
        # the rest of its output is read as it comes (a full pipe would stall the session)
        reader = threading.Thread(target=lambda: tail.extend(proc.stdout), daemon=True)
        reader.start()
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", headless=True,
                                  args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
            page = b.new_page(viewport=SCREEN)
            page.set_default_timeout(900_000)
            page.goto(url)
            page.wait_for_function("() => document.querySelectorAll('.tile').length === 16", polling=50)
            # freeze the chosen board once it has two attitudes and waits at the plate
            page.wait_for_function("(k) => { const t = document.querySelectorAll('.tile')[k]; return !!t && "
                                   "/· ([2-9]|\\d\\d+) captured/.test(t.querySelector('.stage').textContent); }",
                                   arg=a.frozen - 1, polling=200)
            sims = [c for c in children(proc.pid) if "sim" in Path(f"/proc/{c}/cmdline").read_text(errors="replace")]
            frozen_pid = sims[a.frozen - 1]
            os.kill(frozen_pid, signal.SIGSTOP)
            print(f"froze slot {a.frozen} (simulator pid {frozen_pid})", flush=True)
            page.wait_for_function("() => document.querySelector('#over') && !document.querySelector('#over').hidden",
                                   polling=500)
            page.wait_for_function("() => [...document.querySelectorAll('.tile .verdict-text')].every((v) => "
                                   "/^(PASSED: |FAILED |STOPPED )/.test(v.textContent))", polling=200)
            time.sleep(0.5)
            a.out.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(a.out / "station-overview-16.png"))
            print("over:", page.locator("#over").text_content())
            print("plate:", page.locator("#plate").text_content().strip())
            tiles = page.locator(".tile")
            print(f"slot {a.frozen}:", tiles.nth(a.frozen - 1).locator(".verdict-text").text_content())
            first_ok = next(i for i in range(16) if i != a.frozen - 1)
            tiles.nth(first_ok).click()
            col = page.locator(".board-col:not(.closed)")
            col.wait_for(state="visible")
            col.screenshot(path=str(a.out / "station-board-column.png"))
            b.close()
    finally:
        if frozen_pid is not None:
            try:
                os.kill(frozen_pid, signal.SIGCONT)
            except OSError:
                pass
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
        err = proc.stderr.read()
        time.sleep(0.5)
        out = "".join(tail)
        print(out[-3000:])
        print(err[-2000:], file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
