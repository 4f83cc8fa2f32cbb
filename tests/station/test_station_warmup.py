"""The station page's temperature warm-up step (issue 23) in Debian's chromium (Playwright, as
tests/station/test_station_browser.py), on the virtual bench with its thermal model on and short
time constants (tens of seconds, so a run takes seconds of wall time):

* a warm-up to its end: started from the setup form, the board's column shows the four sensors'
  temperatures (those of the station's state) named with the parts the board reported (an
  ADXL359 and an ADXRS453 on Z here), their rate in °C/min, the span covered as a bar,
  the fit's order and held-out error per axis while it runs, then the verdict (written and
  verified), the fit with the 1σ of each curve, what could not be determined (one face: the
  accelerometer's scale terms) and where thermal.json is;
* a second warm-up from the column's own step, stopped on the page: the column says the fit of
  what came is kept, thermal.json holds it (status "interrupted"), nothing is written;
* the new request goes through the page's rules (security.py): refused without the page's
  Origin, a bad option named in one line, another page cannot stop it.

Screenshots: build/test-artifacts/station-warmup-running.png and station-warmup-done.png
(docs/station-warmup.png is a copy of the first)."""
from __future__ import annotations

import json
import re
from pathlib import Path


from imubench.station.runner import SIM_KEY, Station
from stationpage import headers_of, session_of
from imubench.station.server import Server

ARTIFACTS = Path(__file__).resolve().parents[2] / "build" / "test-artifacts"
SHORT = {"tau_s": [20.0, 30.0, 25.0, 28.0], "self_heat_c": [1.0, 3.0, 2.0, 3.0]}
QUICK = {"rate_hz": 100, "bin_s": 2.0, "stop_window_s": 30.0, "stop_rate_c_per_min": 0.3, "fit_every_s": 10.0}


TEMPS = """() => [...document.querySelectorAll('.board-col .warm-temps tr')].slice(1).map((r) =>
  [...r.querySelectorAll('td')].slice(0, 4).map((td) => td.textContent))"""


def test_warmup_step_on_the_station_page(tmp_path, browser):
    station = Station(workdir=tmp_path, db=tmp_path / "history.sqlite", sim_speed=25.0, sim_seed=5,
                      sim_thermal=SHORT, warmup=QUICK, sim_parts="accel=adxl359,gyro_z=adxrs453")
    server = Server(station).start()
    origin = server.url.rstrip("/")
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 1000})
        page.set_default_timeout(120_000)
        page.goto(server.launch_url)
        page.locator("#setup").wait_for()
        page.check("#use-sim")
        page.fill("#warm-lo", "5")
        page.fill("#warm-hi", "40")
        page.click("#start-warmup")
        col = page.locator(f'.board-col[data-key="{SIM_KEY}"]')
        col.locator(".warm-state", has_text="running").wait_for()
        assert col.locator(".warm-stop").is_visible() and not col.locator("button.stop").is_visible()
        assert not col.locator(".warm-form").is_visible()          # no second warm-up while one runs

        # while it runs: temperatures rising, their rate, the span covered, the fit's order per axis
        page.wait_for_function("() => document.querySelectorAll('.board-col .warm-fit tr').length === 7", polling=100)
        rows = page.evaluate(TEMPS)
        # named with the parts the board reported (a board with the siblings: issue 35)
        assert [r[0] for r in rows] == ["ADXL359", "gyro X ADXRS450", "gyro Y ADXRS450", "gyro Z ADXRS453"]
        shown = [float(re.match(r"(-?\d+\.\d\d) °C", r[1]).group(1)) for r in rows]
        rates = [float(re.match(r"([+-]\d+\.\d\d) °C/min", r[2]).group(1)) for r in rows]
        covered = [tuple(float(x) for x in re.match(r"(-?\d+\.\d)–(-?\d+\.\d) °C", r[3]).groups()) for r in rows]
        prog = station.state.boards[SIM_KEY].warmup["progress"]
        assert all(abs(a - b) < 3.0 for a, b in zip(shown, prog["temp_c"])), (shown, prog["temp_c"])
        assert all(r > 0.5 for r in rates), rates                    # warming, °C per minute
        assert all(lo < 8.0 and hi > lo + 5 for lo, hi in covered), covered   # from the cold soak upwards
        widths = page.evaluate("() => [...document.querySelectorAll('.board-col .span-covered')].map((e) => "
                               "parseFloat(e.style.width))")
        assert len(widths) == 4 and all(w > 10 for w in widths), widths
        fit_rows = col.locator(".warm-fit tr")
        first = fit_rows.nth(1).locator("td")
        assert first.nth(0).text_content() == "accel X" and re.fullmatch(r"[0-3]", first.nth(1).text_content())
        assert re.fullmatch(r"\d+\.\d{3} mg", first.nth(2).text_content())
        assert re.fullmatch(r"\d+\.\d{2} m°/s", fit_rows.nth(4).locator("td").nth(2).text_content())
        assert "scale temperature terms need more faces" in col.locator(".warm-notes").text_content()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "station-warmup-running.png"), full_page=True)

        # another page watches: it cannot stop the warm-up
        watcher = browser.new_page()
        watcher.goto(server.new_launch_url())
        watcher.locator(f'.board-col[data-key="{SIM_KEY}"] .owner', has_text="read-only").wait_for()
        assert not watcher.locator(".warm-stop").is_visible()
        refused = watcher.request.post(server.url + "api/stop", data={"key": SIM_KEY}, headers=headers_of(watcher))
        assert refused.status == 409 and "another page" in refused.json()["error"]
        watcher.close()
        page.bring_to_front()

        # to its end: span covered (or the temperatures flat), written and verified
        col.locator(".warm-state", has_text="done").wait_for()
        summary = col.locator(".warm-summary").text_content()
        assert "warm-up finished" in summary and "written to the device and verified" in summary, summary
        assert col.locator(".warm-fit th", has_text="1σ of the curve").count() == 1
        assert col.locator(".warm-fit tr").count() == 7
        notes = col.locator(".warm-notes").text_content()
        assert "accel" in notes and "scale" in notes, notes                # what one face cannot give
        files = col.locator(".warm-files").text_content()
        tj = Path(files.split("saved: ")[1].strip())
        data = json.loads(tj.read_text())
        assert data["kind"] == "imubench thermal warmup" and data["status"] == "done" and data["write"]["verified"]
        assert col.locator(".warm-form").is_visible() and not col.locator(".warm-stop").is_visible()
        page.screenshot(path=str(ARTIFACTS / "station-warmup-done.png"), full_page=True)

        # the new request keeps the page's rules
        mine = {"X-Imubench-Session": session_of(page)}
        r = page.request.post(server.url + "api/warmup", data={"port": SIM_KEY}, headers=mine)       # no Origin
        assert r.status == 403
        r = page.request.post(server.url + "api/warmup", data={"port": SIM_KEY}, headers={"Origin": origin})
        assert r.status == 403 and "no session" in r.json()["error"]                                  # no session
        r = page.request.post(server.url + "api/warmup", data={"port": SIM_KEY, "face": "up"}, headers={"Origin": origin, **mine})
        assert r.status == 400 and "face must be one of" in r.json()["error"]
        r = page.request.post(server.url + "api/warmup", data={"port": SIM_KEY, "span_lo_c": 30, "span_hi_c": 20},
                              headers={"Origin": origin, **mine})
        assert r.status == 400 and "too narrow" in r.json()["error"]
        r = page.request.post(server.url + "api/warmup", data={"port": SIM_KEY, "span_lo_c": "5"},
                              headers={"Origin": origin, **mine})
        assert r.status == 400 and "span_lo_c must be a number" in r.json()["error"]

        # a second warm-up from the column's own step, stopped on the page: the fit of what came is kept
        col.locator(".warm-lo").fill("5")
        col.locator(".warm-hi").fill("45")
        col.locator(".warm-start").click()
        col.locator(".warm-state", has_text="running").wait_for()
        page.wait_for_function("() => document.querySelectorAll('.board-col .warm-fit tr').length === 7", polling=100)
        col.locator(".warm-stop").click()
        col.locator(".warm-state", has_text="stopped, fit kept").wait_for()
        summary = col.locator(".warm-summary").text_content()
        assert "the fit of what came is kept" in summary and "not written" in summary, summary
        assert col.locator(".warm-fit tr").count() == 7
        tj2 = Path(col.locator(".warm-files").text_content().split("saved: ")[1].strip())
        assert tj2 != tj
        data = json.loads(tj2.read_text())
        assert data["status"] == "interrupted" and data["fit"] and not data["write"]
        assert page.evaluate("window.__streamErrors") == 0
    finally:
        server.stop()
        station.close()
