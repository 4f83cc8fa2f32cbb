"""One screen for the operator (issue 24): a station session's overview on the station page,
in Debian's chromium (Playwright, as tests/station/test_station_browser.py), at 16 and at 8 boards.

* 16 boards: the page's state is fed what a station session publishes (fixture.BoardStatus per
  board: running, waiting for the others, passed, failed with long reasons; the plate's move and
  the deadlines), so every kind of tile is on screen at once; the overview must fit 1366 x 768
  without scrolling, every tile legible (slot, device ID, stage, progress, verdict with the
  reason), the plate shown once, a board's column on a click. The screenshot is
  build/test-artifacts/station-overview-16.png (docs/ has a copy).
* 8 boards end to end: `imubench calibrate --sim --sim-boards 8 --sim-fault 3:gyro_y --rate 100 --ui web`
  (100 Hz: what the page shows does not depend on the stream's rate, and at 500 Hz the default
  page ceiling drops to speed 7.5 for 8 boards; at 100 Hz the page's default ceiling, 20, holds),
  the whole session on the page: seven tiles PASSED, slot 3 FAILED at health with its reason,
  the plate's attitude on top, a click opens a column whose report link serves the report.
  The screenshots are build/test-artifacts/station-overview-8.png and station-board-column.png
  (slot 2's column, opened by a click); docs/ has copies.
"""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path


from procio import finish, wait_for_line
from stationpage import FIRST_URL, report_url
from imubench.station.runner import Station
from imubench.station.server import Server

SHOTS = Path(__file__).resolve().parents[2] / "build" / "test-artifacts"
SCREEN = {"width": 1366, "height": 768}

FITS = """() => {
  const ov = document.querySelector('#overview').getBoundingClientRect();
  const tiles = [...document.querySelectorAll('.tile')];
  const clipped = tiles.filter((t) => [...t.querySelectorAll('.top, .stage')].some((e) => e.scrollWidth > e.clientWidth + 1));
  return {bottom: ov.bottom, right: ov.right, scrollW: document.documentElement.scrollWidth,
          last: Math.max(...tiles.map((t) => t.getBoundingClientRect().bottom)), clipped: clipped.length,
          minFont: Math.min(...tiles.map((t) => parseFloat(getComputedStyle(t).fontSize)))};
}"""


def _uid(k: int) -> str:
    return f"{0x5184A0157883C687497907B0 + 977 * k:024X}"


def _feed(station: Station, n: int) -> None:
    """What a station session of n boards publishes, at one moment: every kind of tile."""
    opts = {"port": "", "method": "multi", "gyro": "bias", "capture": "adaptive", "write": True, "note": "",
            "rate_hz": 500, "fixture": True}
    long_reason = ("refusing to calibrate on faulted data: 500 of 500 samples flagged bad (gyro Y): sensor faults, "
                   "parity or SPI errors; 1 fault events from the device (gyro Y: gyro fault bits)")
    for k in range(1, n + 1):
        port = f"/dev/ttyUSB{k - 1}"
        ui = station.adopt(port, dict(opts, port=port), k)
        ui.present_plan([(f"att{j}", (0.0, 0.0, 1.0)) for j in range(26)], "multi")
        st = {"slot": k, "port": port, "uid": _uid(k), "stage": "poses", "state": "running", "message": "",
              "progress": 0.3, "reason": None, "waiting": None}
        if k % 5 == 0:          # passed
            st.update(stage="done", state="passed", message="PASSED", progress=1.0)
            for j in range(12):
                ui.pose_event(f"att{j}", "done", {"before_g": 1.001})
        elif k in (3, 11):      # failed, with a long reason
            st.update(stage="health" if k == 3 else "verify", state="failed",
                      reason=long_reason if k == 3 else "verification failed: verification: no still attitude for "
                      "-Z up (upside down); the previous parameters were restored")
        elif k % 4 == 0:        # done with its attitudes, waiting for the others
            st.update(stage="verify", message="[1/3] +Z up (level)",
                      waiting="waits for slots 1, 2, 6, 7 to come to verification (the plate serves what they "
                              "need first); deadline 300 s device time")
        else:
            st.update(message=f"[{k}/26] +Y-Z edge")
            for j in range(min(k, 11)):
                ui.pose_event(f"att{j}", "done", {"before_g": 1.001})
        station.board_event(port, st)
    station.plate_event({"deadlines": "deadlines (device time): a board waits at most 300 s for the plate (the "
                                      "attitudes other boards still need first, verification last) and 120 s for a "
                                      "presented attitude to be held still; past one it fails with the stage and the "
                                      "reason, and the others go on"})
    station.plate_event({"kind": "pose", "key": "+Y-Z edge", "serves": [1, 2, 6, 7], "waiting": [4, 8, 12, 16],
                         "move": 14, "up": [0.0, 0.7071, -0.7071], "words": "Y up, Z down (45° on an edge, X level)"})


def test_sixteen_boards_fit_one_1366x768_screen(tmp_path, browser):
    station = Station(workdir=tmp_path, db=tmp_path / "h.sqlite", allow_sim=False, history=False)
    station.state.mode = "session"
    _feed(station, 16)
    server = Server(station).start()
    try:
        page = browser.new_page(viewport=SCREEN)
        page.goto(server.launch_url)
        page.wait_for_function("() => document.querySelectorAll('.tile').length === 16", polling=50)
        m = page.evaluate(FITS)
        assert m["last"] <= SCREEN["height"] and m["bottom"] <= SCREEN["height"] + 30, m   # no scrolling for a tile
        assert m["scrollW"] <= SCREEN["width"] and m["clipped"] == 0 and m["minFont"] >= 12, m
        tiles = page.locator(".tile")
        assert [tiles.nth(i).locator(".slot").text_content() for i in range(16)] == [str(k) for k in range(1, 17)]
        assert all(tiles.nth(i).locator(".uid").text_content() == _uid(i + 1) for i in range(16))
        states = [tiles.nth(i).get_attribute("data-state") for i in range(16)]
        assert [k + 1 for k, s in enumerate(states) if s == "passed"] == [5, 10, 15]
        assert [k + 1 for k, s in enumerate(states) if s == "failed"] == [3, 11]
        t3 = tiles.nth(2)
        assert t3.locator(".verdict-text").text_content().startswith("FAILED at health: refusing to calibrate on faulted")
        assert "gyro fault bits" in t3.get_attribute("title")                     # the whole reason on hover
        assert "stopped at health check" in t3.locator(".stage").text_content()
        t4 = tiles.nth(3)
        assert "waiting" in t4.get_attribute("class") and t4.locator(".state").text_content() == "waits"
        assert "waits for slots 1, 2, 6, 7" in t4.locator(".verdict-text").text_content()
        assert "attitudes · 2 captured" in tiles.nth(1).locator(".stage").text_content()
        plate = page.locator("#plate")
        assert plate.count() == 1 and "+Y-Z edge" in plate.text_content() and "move 14" in plate.text_content()
        assert "for slots 1, 2, 6, 7; slots 4, 8, 12, 16 wait" in plate.text_content()
        assert "300 s for the plate" in plate.text_content()
        assert page.locator(".board-col:not(.closed)").count() == 0                  # columns on demand only
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / "station-overview-16.png"))
        # a click opens that board's column (its cards), a second click closes it
        tiles.nth(6).click()
        col = page.locator('.board-col[data-key="/dev/ttyUSB6"]')
        col.wait_for(state="visible")
        assert page.locator(".board-col:not(.closed)").count() == 1
        assert col.locator(".card").count() == 26 and col.locator(".card.done").count() == 7
        assert "selected" in tiles.nth(6).get_attribute("class")
        tiles.nth(6).click()
        col.wait_for(state="hidden")
    finally:
        server.stop()
        station.close()


def test_eight_boards_on_the_page_end_to_end(tmp_path, browser):
    cmd = [sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-boards", "8", "--sim-fault", "3:gyro_y",
           "--rate", "100", "--ui", "web", "--http-port", "0", "--dir", str(tmp_path / "st"), "--db", str(tmp_path / "h.sqlite")]
    # SIGINT to its default in the child: a run started in the background by a non-interactive
    # shell ignores it, and the child would too (the Ctrl-C below would then never stop it)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    try:
        url = wait_for_line(proc, FIRST_URL, lines).group(1)
        page = browser.new_page(viewport=SCREEN)
        page.set_default_timeout(240_000)
        page.goto(url)
        page.wait_for_function("() => document.querySelectorAll('.tile').length === 8", polling=50)
        # every slot this page drives is named at once, not as the claims come back (issue 38)
        page.wait_for_function("() => document.querySelector('#role').textContent === 'you drive slots 1–8'", polling=50,
                               timeout=3000)
        page.wait_for_function("() => /move \\d+/.test(document.querySelector('#plate').textContent)", polling=100)
        page.wait_for_function("() => [...document.querySelectorAll('.tile')].every((t) => t.dataset.state !== 'running')",
                               polling=200)
        page.wait_for_function("() => [...document.querySelectorAll('.tile .verdict-text')].every((v) => "
                               "/^(PASSED: |FAILED )/.test(v.textContent))", polling=200)
        m = page.evaluate(FITS)
        assert m["last"] <= SCREEN["height"] and m["scrollW"] <= SCREEN["width"] and m["clipped"] == 0, m
        tiles = page.locator(".tile")
        verdicts = [tiles.nth(i).locator(".verdict-text").text_content() for i in range(8)]
        assert [v.split(":")[0].split()[0] for v in verdicts] == ["PASSED"] * 2 + ["FAILED"] + ["PASSED"] * 5, verdicts
        assert "at health" in verdicts[2] and "gyro" in verdicts[2], verdicts
        assert all(re.fullmatch(r"[0-9A-F]{24}", tiles.nth(i).locator(".uid").text_content()) for i in range(8))
        # the end told (issue 38): the pass count on top, the plate closed
        assert "session over" in page.locator("#plate").text_content()
        assert page.locator("#over").text_content().startswith("7 of 8 passed"), page.locator("#over").text_content()
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / "station-overview-8.png"))
        tiles.nth(1).click()
        col = page.locator(".board-col:not(.closed)")
        col.wait_for(state="visible")
        with urllib.request.urlopen(report_url(page, col.locator("a.report-link")), timeout=30) as r:
            assert r.status == 200 and b"imubench" in r.read()
        assert col.locator(".verdict").text_content().startswith("PASSED")
        col.screenshot(path=str(SHOTS / "station-board-column.png"))
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = finish(proc, timeout=90)
    out = "".join(lines) + out
    assert "Traceback" not in out + err, out + err
    assert proc.returncode == 1 and "1 of 8 boards failed: slot 3 at health" in err, out + err
    assert "deadlines (device time): a board waits at most 300 s for the plate" in out, out
    assert "7 of 8 boards passed" in out, out
