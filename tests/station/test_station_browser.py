"""The station page in a real browser: Debian's chromium (/usr/bin/chromium, SYSTEM_PKGS in the
Makefile) driven by Playwright (test extra; its own browsers are never downloaded). A simulated
person (procedures/virtual.py) presents the attitudes on the virtual bench in a random order;
the page must show what happens: pose cards turning done in the order presented, the live |a|,
a stop and a resume from the page, the verdict, the report link; a second page only watches.
The finished page is kept as build/test-artifacts/station-finished.png."""
from __future__ import annotations

import re
from pathlib import Path


from procio import finish, wait_for_line
from stationpage import FIRST_URL, NEXT_URL, base_of, get_json, headers_of, report_url, session_of
from imubench.station.runner import SIM_KEY, Station
from imubench.station.server import Server

ARTIFACTS = Path(__file__).resolve().parents[2] / "build" / "test-artifacts"


def test_a_whole_session_on_the_station_page(tmp_path, browser):
    # the simulated person's hand moves take 1.5-4 s of device time rather than 3-8 s: the page's
    # cards, live |a|, stop and resume do not depend on how long a move takes, and the moves
    # were most of the session's device time
    station = Station(workdir=tmp_path, db=tmp_path / "history.sqlite", sim_speed=12.0, sim_seed=5,
                      person={"move_s": (1.5, 4.0)})
    server = Server(station).start()
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 1400})
        page.set_default_timeout(90_000)
        page.goto(server.launch_url)
        page.locator("#setup").wait_for()          # shown once the state has arrived (after the load event)
        # a six-position choice warns that it needs a square fixture
        page.select_option("#method", "six")
        assert page.locator("#six-warning").is_visible()
        page.select_option("#method", "multi")
        page.check("#use-sim")
        page.click("#start")

        col = page.locator(f'.board-col[data-key="{SIM_KEY}"]')
        col.locator(".status", has_text="running").wait_for()
        # the live |a| while the person holds the board
        page.wait_for_function(
            "() => /^[01]\\.\\d{4}$/.test((document.querySelector('.board-col .a-g') || {}).textContent || '')",
            polling=20)
        a_g = float(col.locator(".a-g").text_content())
        assert 0.9 < a_g < 1.1
        # one missing attitude is suggested (the one that helps the fit most)
        page.wait_for_function("() => !!document.querySelector('.card.suggested[data-state=todo]')", polling=20)

        # a second page sees the same device, read-only: no stop, no resume, refused if it tries
        watcher = browser.new_page()
        watcher.goto(server.new_launch_url())
        wcol = watcher.locator(f'.board-col[data-key="{SIM_KEY}"]')
        wcol.locator(".owner", has_text="read-only").wait_for()
        assert not wcol.locator("button.stop").is_visible()
        refused = watcher.request.post(server.url + "api/stop", data={"key": SIM_KEY},
                                       headers=headers_of(watcher))                  # its own session
        assert session_of(watcher) != session_of(page)
        assert refused.status == 409 and "another page" in refused.json()["error"]
        assert col.locator(".owner", has_text="you drive").is_visible()
        page.bring_to_front()              # a page in the background gets no animation frames

        # stop after three attitudes, then resume from the page
        # (polled on a timer: the page is in the background now, where animation frames stop)
        try:
            page.wait_for_function("() => document.querySelectorAll('.card[data-state=done]').length >= 3",
                                   polling=50)
        except Exception:
            b = station.state.boards[SIM_KEY]
            raise AssertionError(f"no three attitudes on the page: {b.status} {b.phase} {b.error} done {b.done_seq}; "
                                 f"page shows {page.locator('.card[data-state=done]').count()}; log {b.log[-5:]}") from None
        col.locator("button.stop").click()
        col.locator(".status", has_text="interrupted").wait_for()
        first_person = station.persons[SIM_KEY]
        kept = page.locator(".card[data-state=done]").count()
        assert kept >= 3
        col.locator("button.resume").click()
        col.locator(".verdict", has_text="PASSED").wait_for()
        second_person = station.persons[SIM_KEY]
        assert second_person is not first_person

        # the cards turned done in the order the person presented them (before and after the stop)
        cards = page.locator(".card[data-state=done]")
        seq = sorted((int(cards.nth(i).get_attribute("data-seq")), cards.nth(i).get_attribute("data-name"))
                     for i in range(cards.count()))
        done_order = [n for _, n in seq]
        presented = first_person.order[:kept] + second_person.order
        assert done_order == presented[:len(done_order)], (done_order, presented)
        assert [s for s, _ in seq] == list(range(1, len(seq) + 1))
        assert 12 <= len(done_order) < 26            # adaptive: stopped at the targets
        # the page saw cards being captured and turning done, never done before capturing
        trans = page.evaluate("window.__transitions")
        states = [s for _, _, s in trans]
        assert "capturing" in states and "done" in states
        # every done card shows |a| before -> after
        assert re.search(r"\|a\| \d\.\d{4} g → \d\.\d{5} g", cards.first.locator(".detail").text_content())

        # verdict first, parameters, write-back and verification steps, the report
        verdict = col.locator(".verdict").text_content()
        assert "written" in verdict and "verified" in verdict
        assert col.locator(".params tr").count() >= 12
        assert col.locator(".step[data-kind=write].done").count() == 1
        assert col.locator(".step[data-kind=verify].done").count() == 1
        with page.context.expect_page() as opened:          # the link opens the report in a new tab
            col.locator("a.report-link").click()
        tab = opened.value
        tab.wait_for_url("**/report/**")                    # about:blank first, then the ticket's address
        tab.wait_for_load_state()
        assert "/report/" in tab.url and "?ticket=" in tab.url and "IMU calibration report" in tab.content()
        assert page.request.get(tab.url).status == 403                     # a ticket opens once
        # an export downloads through a ticket of its own (a download sends no session header)
        links = col.locator("a.export-link")
        assert links.count() >= 5, col.inner_html()
        with page.expect_download() as got:
            links.first.click()
        name = links.first.get_attribute("download")
        assert got.value.suggested_filename == name and Path(got.value.path()).stat().st_size > 100
        # the watcher saw the end too, and neither page's event stream ever broke
        watcher.bring_to_front()
        wcol.locator(".verdict", has_text="PASSED").wait_for()
        assert page.evaluate("window.__streamErrors") == 0 and watcher.evaluate("window.__streamErrors") == 0
        assert page.locator("#conn").text_content() == "live"

        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        shot = ARTIFACTS / "station-finished.png"
        page.screenshot(path=str(shot), full_page=True)
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        server.stop()
        station.close()


def test_several_boards_one_column_each_on_the_page(tmp_path, browser):
    """`imubench calibrate --sim --sim-boards 3 --ui web`: the station session (procedures.fixture)
    on the page, one column per board. Slot 2's gyro Y is faulted: its column says it failed
    at the health check while the others are calibrated; the page that opens first drives every
    board (one token), a second page only watches; every finished column has its verdict,
    parameters and a report that opens; the command prints the per-board table after Ctrl-C."""
    import signal
    import subprocess
    import sys
    import urllib.request
    # the page's own speed ceiling (20, --sim-speed not given); 100 Hz: what the page shows does
    # not depend on the stream's rate, and it is a fifth of the samples to make and decode
    cmd = [sys.executable, "-m", "imubench", "calibrate", "--sim", "--sim-boards", "3", "--rate", "100",
           "--ui", "web", "--http-port", "0", "--dir", str(tmp_path / "st"), "--db", str(tmp_path / "h.sqlite"),
           "--hold", "0.5", "--sim-fault", "2:gyro_y"]
    # SIGINT to its default in the child: a run started in the background by a non-interactive
    # shell ignores it, and the child would too (the Ctrl-C below would then never stop it)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    try:
        url = wait_for_line(proc, FIRST_URL, lines).group(1)
        page = browser.new_page(viewport={"width": 1500, "height": 1300})
        page.set_default_timeout(120_000)
        page.goto(url)
        page.wait_for_function("() => document.querySelectorAll('.board-col').length === 3", polling=50)
        assert page.locator("main#boards.multi").count() == 1
        # the first page drives all three boards
        page.wait_for_function("() => /you drive slots 1–3/.test(document.querySelector('#role').textContent)", polling=50)
        # while the plate moves: cards turn done on the healthy boards, in the plan's order
        page.wait_for_function("() => document.querySelectorAll('.board-col .card.done').length >= 6", polling=50)
        # the whole session: every column ends with a verdict
        page.wait_for_function("() => document.querySelectorAll('.board-col .verdict:not([hidden])').length === 3",
                               polling=100)
        cols = page.locator(".board-col")
        verdicts = [cols.nth(k).locator(".verdict").text_content() for k in range(3)]
        names = [cols.nth(k).locator(".devname").text_content() for k in range(3)]
        assert [n.split(":")[0] for n in names] == ["slot 1", "slot 2", "slot 3"], names
        assert verdicts[0].startswith("PASSED") and verdicts[2].startswith("PASSED"), verdicts
        assert verdicts[1].startswith("FAILED") and "health" in verdicts[1] and "gyro" in verdicts[1].lower(), verdicts
        order = []
        for k in (0, 2):
            col = cols.nth(k)
            done = col.locator(".card.done")
            n = done.count()
            assert n >= 12
            seqs = {done.nth(i).get_attribute("data-name"): int(done.nth(i).get_attribute("data-seq")) for i in range(n)}
            assert sorted(seqs.values()) == list(range(1, n + 1))
            order.append(seqs)
        common = order[0].keys() & order[1].keys()  # the plate presents the same attitudes to both, in step
        assert len(common) >= 12 and all(order[0][c] == order[1][c] for c in common), order
        for k in (0, 2):
            col = cols.nth(k)
            assert col.locator(".steps .step.running").count() == 0
            assert col.locator(".steps .step[data-kind=verify]").count() == 1
            assert col.locator(".params tr").count() >= 12          # accelerometer M and b at least
            with urllib.request.urlopen(report_url(page, col.locator("a.report-link")), timeout=30) as r:
                assert r.status == 200 and b"imubench" in r.read()
        assert cols.nth(1).locator(".card.done").count() == 0
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "station-three-boards.png"), full_page=True)
        # a second page watches every board read-only
        other = browser.new_page(viewport={"width": 1200, "height": 900})
        other.goto(wait_for_line(proc, NEXT_URL, lines).group(1))
        other.wait_for_function("() => document.querySelectorAll('.board-col.readonly').length === 3", polling=50)
        assert "read-only" in other.locator("#role").text_content()
        st = get_json(base_of(url) + "api/state", session_of(other))
        assert [b["status"] for b in st["boards"]] == ["done", "failed", "done"]
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = finish(proc, timeout=60)
    out = "".join(lines) + out
    assert "Traceback" not in out + err, out + err
    assert proc.returncode == 1, out + err                 # one board failed: the command says so
    assert "1 of 3 boards failed: slot 2 at health" in err, err
    table = out[out.index("slot  MCU UID"):]
    assert re.search(r"^\s+1\s+\w{24}\s+PASSED", table, re.M) and re.search(r"^\s+2\s+\w{24}\s+FAILED", table, re.M)
