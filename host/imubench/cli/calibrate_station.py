"""`imubench calibrate` with several boards: one station session (procedures.fixture), a
verdict per board, on the terminal or the station page; and the virtual boards' faults."""
from __future__ import annotations

import datetime as _dt
from pathlib import Path

from imubench.cli.common import CommandError, UsageError, speed_text
from imubench.text import one_line, shell_word

SIM_SPEED = 20.0
#: a station session's plate deadline (fixture.Plate) when --plate-timeout is not given: the
#: virtual plate moves in a few seconds; a person may take a minute per attitude
PLATE_TIMEOUT_VIRTUAL_S = 300.0
PLATE_TIMEOUT_HAND_S = 1200.0
#: samples per second of host time the virtual fixture's boards may send together when
#: --sim-speed is not given: the host decodes every board's stream in Python, on the same
#: cores as the virtual devices; past this the links fall behind on this project's loaded
#: 2-core machine (16 boards at speed 20 and 500 Hz, 160000 samples/s, left stop_stream
#: unanswered behind the backlog; 8 boards at speed 20, 80000 samples/s, lost samples on one
#: board in one run of three). A real line runs at speed 1: bench/multi_dut.py measures that.
SIM_SAMPLES_PER_S = 40_000
#: with the station page (--ui web) the host also serves the page's events (8 boards at speed
#: 20 on the page lost samples on two boards)
SIM_SAMPLES_PER_S_PAGE = 30_000


def _station_sim_speed(boards: int, rate_hz: float, page: bool = False) -> float:
    """The virtual fixture's speed when none is given: SIM_SPEED, or less for many boards."""
    budget = SIM_SAMPLES_PER_S_PAGE if page else SIM_SAMPLES_PER_S
    return min(SIM_SPEED, max(1.0, budget / (boards * rate_hz)))


SIM_FAULT_SENSORS = ("accel", "gyro_x", "gyro_y", "gyro_z")


def _sim_fault(text: str) -> tuple[int, str]:
    """--sim-fault K:SENSOR: board K (1-based) with that sensor faulted."""
    import argparse
    slot, _, sensor = text.partition(":")
    if not slot.strip().isdigit() or int(slot) < 1 or sensor not in SIM_FAULT_SENSORS:
        raise argparse.ArgumentTypeError(f"{text!r} is not K:SENSOR (K a board from 1, SENSOR one of "
                                         f"{', '.join(SIM_FAULT_SENSORS)}), e.g. 2:gyro_y")
    return int(slot), sensor


def _inject_sim_fault(vb, sensor: str) -> None:
    if sensor == "accel":
        vb.inject("missing", sensor="accel")
    else:
        vb.inject("gyro_fault_bits", sensor=sensor, bits=0x10, persistent=True)


def _station_session(a) -> bool:
    """Several boards on one fixture (procedures.fixture) rather than the one-board session."""
    sf = getattr(a, "station_file", None) or {}
    return len(getattr(a, "ports", None) or []) > 1 or getattr(a, "sim_boards", 1) > 1 or bool(sf.get("ports"))


def _run_station(a, cfg) -> int:
    """`imubench calibrate` with several boards: one station session, a verdict per board."""
    from contextlib import ExitStack

    from imubench.procedures.fixture import Station, run_fixture
    from imubench.procedures.virtual import PlatePresenter
    sf = a.station_file or {}
    ports = list(a.ports or sf.get("ports") or [])
    if a.resume:
        raise UsageError("--resume continues a one-board session; a station session with several boards is "
                         "started afresh", "run it again with --dir NEW_DIR (each board's captures stay in DIR/slot-K)")
    if a.closure:
        raise UsageError("--closure goes with a one-board session", "run `imubench closure --port URL` per board")
    if a.sim and ports:
        raise UsageError("--sim and --port (or a station file's ports) exclude each other",
                         "--sim --sim-boards N starts N virtual devices on one virtual fixture")
    if a.sim_boards > 1 and not a.sim:
        raise UsageError("--sim-boards goes with --sim", "give --sim --sim-boards N, or --port URL once per board")
    station = Station(station_id=a.station or sf.get("station", ""), operator=a.operator or sf.get("operator", ""),
                      fixture=a.fixture or sf.get("fixture", ""))
    db = a.db or sf.get("db") or None
    if db is None:
        from imubench.results.history import default_target
        db = default_target()
    directory = Path(a.dir or f"imubench-station-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    if (directory / "station.json").exists():
        raise UsageError(f"{directory} already holds a station session", "give another --dir")
    a.on_interrupt = lambda: (f"what was captured is kept in {directory}/slot-K; boards already finished are "
                              "recorded; run the station session again for the others")
    with ExitStack() as stack:
        if a.sim:
            from imubench.device.sim import VirtualBench
            capped = _station_sim_speed(a.sim_boards, cfg.rate_hz, page=a.ui == "web")
            if not a.sim_speed_given and capped < a.sim_speed:
                a.sim_speed = capped
                print(f"virtual devices at speed {a.sim_speed:g} (not {SIM_SPEED:g}): {a.sim_boards} boards at "
                      f"{cfg.rate_hz:g} Hz send {a.sim_boards * cfg.rate_hz * a.sim_speed:.0f} samples/s, what the "
                      "host decodes alongside them" + (" and the page" if a.ui == "web" else "")
                      + "; --sim-speed X to choose")
            benches = [stack.enter_context(VirtualBench(speed=a.sim_speed, seed=a.sim_seed + k, truth="random",
                                                        target=a.target, clock=a.sim_clock))
                       for k in range(a.sim_boards)]
            ports = [vb.port_url for vb in benches]
            for slot, sensor in a.sim_fault:
                if slot > len(benches):
                    raise UsageError(f"--sim-fault {slot}:{sensor}: there are {len(benches)} virtual boards",
                                     f"give a board from 1 to {len(benches)}")
                _inject_sim_fault(benches[slot - 1], sensor)
            mover = PlatePresenter(benches, tilt_deg=a.sim_tilt, seed=a.sim_seed)
            print(f"{len(benches)} virtual devices with random truth (seeds {a.sim_seed}..{a.sim_seed + len(benches) - 1}) "
                  f"on one virtual fixture, {speed_text(a.sim_speed, a.sim_clock)}")
        else:
            from imubench.cli.terminal import HumanPresenter
            mover = HumanPresenter()
            mover.say(f"{len(ports)} boards on the fixture: every instruction is for the whole plate")
        # the station name, the folder and the database come from the user or a file: one line each
        print(f"station {one_line(station.station_id)}, session directory {one_line(directory)} (DIR/slot-K per "
              f"board); records go to {one_line(_shown(db))}")
        plate_timeout = a.plate_timeout = (a.plate_timeout if a.plate_timeout is not None else
                                           PLATE_TIMEOUT_VIRTUAL_S if a.sim else PLATE_TIMEOUT_HAND_S)
        last: dict[int, tuple] = {}
        waits: dict[int, str | None] = {}
        import threading
        lock = threading.Lock()

        def on_event(st: dict) -> None:         # one line per board and stage (called from the boards' threads)
            key = (st["stage"], st["state"])
            with lock:
                who = one_line(st["uid"] or st["port"])
                if last.get(st["slot"]) != key:
                    last[st["slot"]] = key
                    print(f"  slot {st['slot']} {who}: {st['state'] if st['state'] != 'running' else st['stage']}"
                          + (f" ({one_line(st['reason'])})" if st["reason"] else ""), flush=True)
                if st.get("waiting") and waits.get(st["slot"]) is None:      # starts waiting for the others
                    print(f"  slot {st['slot']} {who}: {one_line(st['waiting'])}", flush=True)
                waits[st["slot"]] = st.get("waiting")
        if a.ui == "web":
            res = _station_on_page(a, cfg, ports, directory, mover, station, db, on_event)
        else:
            res = run_fixture(ports, directory, cfg, mover, station=station, db=db, on_event=on_event,
                              link_timeout_s=a.link_timeout, baudrate=a.baud, plate_timeout_s=plate_timeout)
    if getattr(a, "export", ()):
        print()
        for b in res.boards:
            rec = res.results.get(b.slot) or {}
            print(f"slot {b.slot} {b.uid or b.port}:")
            write_exports(a, rec, directory / f"slot-{b.slot}", b.uid or f"slot-{b.slot}", b.state == "passed",
                          say=lambda line: print(f"  {line}"))
    print()
    print(_station_table(res))
    print(f"station session {one_line(res.session_id)}: {len(res.passed)} of {len(res.boards)} boards passed "
          f"({res.wall_s:.0f} s); `imubench history --export {shell_word(res.session_id)} --format junit` exports it")
    if res.failed:
        raise CommandError(f"{len(res.failed)} of {len(res.boards)} boards failed: "
                           + "; ".join(f"slot {b.slot} at {one_line(b.stage)}" for b in res.boards if b.state != "passed"),
                           "see the table above; the boards that passed are written and recorded")
    return 0


def _station_on_page(a, cfg, ports, directory: Path, mover, station, db, on_event):
    """The station session with the station page: one column per board (live view, the pose
    cards, the stages, the verdict, parameters and report). The page stays up after the
    session until Ctrl-C; Ctrl-C during the session stops every board where it is."""
    import threading

    from imubench.cli.station import port_policy, serve_page
    from imubench.procedures.fixture import run_fixture
    from imubench.station.runner import Station as Page
    page = Page(workdir=directory, db=db, allow_sim=False, history=False, ports=port_policy(a))
    page.state.mode = "session"
    options = {"port": ", ".join(ports), "method": cfg.method, "gyro": a.gyro, "capture": a.capture,
               "write": cfg.write, "note": cfg.note, "rate_hz": cfg.rate_hz, "fixture": True}
    box: dict = {}

    def both(st: dict) -> None:
        on_event(st)
        page.board_event(st["port"], st)

    uis = {port: page.adopt(port, options, k + 1) for k, port in enumerate(ports)}   # the columns in slot order
    def run() -> None:
        try:
            box["res"] = run_fixture(ports, directory, cfg, mover, station=station, db=db, on_event=both,
                                     link_timeout_s=a.link_timeout, baudrate=a.baud,
                                     pages=lambda slot, port: uis[port], on_plate=page.plate_event,
                                     plate_timeout_s=a.plate_timeout)
            for b in box["res"].boards:   # verdicts, parameters and reports on the columns
                page.board_result(b.port, box["res"].results.get(b.slot) or {}, directory / f"slot-{b.slot}",
                                  b.run_id)
        except BaseException as e:  # noqa: BLE001 - re-raised in the command's thread
            box["error"] = e
        finally:
            box["done"] = True

    worker = threading.Thread(target=run, name="station session", daemon=True)
    told = []

    def ended() -> bool:
        if box.get("done") and not told:
            told.append(True)
            if "res" in box:
                print(f"station session over: {len(box['res'].passed)} of {len(box['res'].boards)} boards passed; "
                      "the page stays up until Ctrl-C", flush=True)
        return False

    try:
        serve_page(page, a, until=ended, start=worker.start)
    finally:
        page.close()                    # a session still running stops where it is
        if worker.ident is not None:     # started (the page could be served)
            worker.join()
    if "error" in box:
        raise box["error"]
    return box["res"]


def write_exports(a, result: dict, directory: Path, name: str, ok: bool, say=print) -> dict:
    """The --export files of a session's (or one station board's) result into directory, as
    calibration-NAME.* (procedures.export_files.write_calibration); none for a result that did not pass
    (a file a tool would load must hold a calibration that passed). Says each file, and when the
    PX4 file lacks its ids."""
    kinds = tuple(getattr(a, "export", ()) or ())
    if not kinds:
        return {}
    if not ok or not (result.get("accel") or {}).get("m"):
        say(f"exports ({', '.join(kinds)}) not written: the calibration did not pass")
        return {}
    comment = f"imubench calibration of {name}, {result.get('finished') or ''}".strip(", ")
    from imubench.procedures.export_files import write_calibration
    files = write_calibration(kinds, directory, result, name=name, comment=comment, px4_acc_id=a.px4_acc_id,
                                px4_gyro_id=a.px4_gyro_id)
    for kind, paths in files.items():
        say(f"{kind}: {one_line(', '.join(paths))}")
    from imubench.results.paramfiles import PX4_ID_HOW, px4_missing_ids
    missing = px4_missing_ids(a.px4_acc_id, a.px4_gyro_id, result.get("gyro") is not None)
    if files.get("px4") and missing:
        say(f"px4: NOT USABLE AS IS, no {' / '.join(missing)} (PX4 ignores the slot): {PX4_ID_HOW}")
    return files


def _shown(db) -> str:
    from imubench.results.db import describe
    return describe(db)


def _station_table(res) -> str:
    from imubench.results.export import measurement_text
    lines = [f"{'slot':>4}  {'MCU UID':<24}  {'verdict':<7}  {'run':>5}  details"]
    for b in res.boards:
        rec = res.results.get(b.slot) or {}
        meas = {m["name"]: m for m in rec.get("measurements") or []}
        if b.state == "passed":
            parts = []
            if "accel_norm_rms_mg" in meas:
                parts.append("|a| − g RMS " + measurement_text(meas["accel_norm_rms_mg"]).split(" (")[0])
            ver = [m for k, m in meas.items() if k.startswith("verify_")]
            if ver:
                worst = max(ver, key=lambda m: m["value"] or 0)
                parts.append("worst verification " + measurement_text(worst).split(" (")[0])
            detail = ", ".join(parts) + ", written and verified" if rec.get("written") else ", ".join(parts)
        else:
            detail = f"at {b.stage}: {one_line(b.reason)}"
        lines.append(f"{b.slot:>4}  {one_line(b.uid or '(no answer)'):<24}  {'PASSED' if b.state == 'passed' else 'FAILED':<7}  "
                     f"{b.run_id if b.run_id is not None else '-':>5}  {detail}")
    return "\n".join(lines)
