"""Station: runs guided sessions (procedures.session.run_session) for the station page, one
per device, each in its own thread; stops them on request and resumes them in their
directory. The page's options become a SessionConfig here. A temperature warm-up
(procedures.warmup.run_warmup) runs the same way, one per device, its progress on the
device's column; Stop ends it keeping the fit of what came."""
from __future__ import annotations

import datetime as _dt
import threading
import time
from pathlib import Path

from imubench.calib.fit import accel_method_names, data_needed, gyro_method_names
from imubench.wire.board_parts import any_board_c
from imubench.errors import ImubenchError
from imubench.station.presenter import SessionStopped, WebPresenter
from imubench.station.security import PortPolicy, StationError, bool_field, int_field, number_field, text_field
from imubench.station.state import Refused, StationState

SIM_KEY = "sim"
METHODS = accel_method_names(live=True)     # calib.fit.ACCEL_METHOD_LIST: the accelerometer methods of a session
GYRO_METHODS = gyro_method_names(live=True)   # calib.fit.GYRO_METHODS: those a session on a device can use
CAPTURES = ("adaptive", "plan")
OPTIONS = ("port", "method", "gyro", "capture", "write", "note", "rate_hz")
NOTE_CHARS = 500
WARMUP_OPTIONS = ("port", "span_lo_c", "span_hi_c", "face", "write", "rate_hz")
FACES = ("+z", "-z", "+x", "-x", "+y", "-y")
WARMUP_SPAN_C = (5.0, 45.0)          # the span a warm-up asks for unless the page says otherwise
# a warm-up's span before its board said which parts it has: what every part of the table works in
WARMUP_LIMITS_C = any_board_c()     # (then run_warmup checks it against the parts the device reported)
PROGRESS_MIN_INTERVAL_S = 0.2        # a warm-up's progress reaches the pages at most five times a second
__all__ = ["Station", "StationError", "SIM_KEY"]


class Station:
    """The sessions of one station.

    workdir     where session directories are made (session-<device>-<time>)
    db          history database (None: the user's default, as `imubench calibrate`)
    sim_speed, sim_seed, person   the virtual bench ("sim" device): its speed, seed, and the
                SimPerson's keyword arguments (procedures.virtual) who presents the attitudes
    sim_thermal the virtual part's thermal model for a warm-up on the "sim" device: keyword
                arguments of VirtualBench.set_thermal (tau_s, self_heat_c; None: the part's own,
                drawn with its random truth)
    warmup      WarmupConfig fields for every warm-up besides the page's options (bin_s,
                stop_window_s, ...; default: WarmupConfig's)
    ports       the PortPolicy of the ports a page may open (default: serial devices, socket://
                and rfc2217:// on this machine)
    """

    def __init__(self, state: StationState | None = None, workdir: str | Path = ".", db=None,
                 sim_speed: float = 20.0, sim_seed: int = 1, sim_parts: str = "", person: dict | None = None, history: bool = True,
                 allow_sim: bool = True, ports: PortPolicy | None = None, sim_thermal: dict | None = None,
                 warmup: dict | None = None):
        self.ports = ports or PortPolicy()
        self.state = state or StationState()
        self.state.sim_available = allow_sim
        self.workdir = Path(workdir)
        self.db = db
        self.history = history
        self.sim_speed = sim_speed
        self.sim_seed = sim_seed
        self.sim_parts = sim_parts       # the virtual board's parts (imubench.device.sim.sim_parts_spec)
        self.person_kw = dict(person or {})
        self.sim_thermal = dict(sim_thermal or {})
        self.warmup_settings = dict(warmup or {})      # WarmupConfig fields besides the page's (tests: short runs)
        self._warm_stop: dict[str, threading.Event] = {}   # a running warm-up's stop, per device
        self._closing = False
        self._threads: dict[str, threading.Thread] = {}
        self._ui: dict[str, WebPresenter] = {}
        self._bench = None
        self._lock = threading.Lock()
        self._adopted: set[str] = set()               # boards of a station session run by the command
        self.persons: dict[str, object] = {}          # the SimPerson of the last sim run (tests read its order)

    # ----------------------------------------------------------------- requests
    def options(self, raw: dict, page: bool = False) -> dict:
        """The options, checked: a StationError names the first bad one. page: they come from
        the page (every type strict, unknown names refused, the port checked against
        self.ports); else from the command line (already checked there)."""
        from imubench.wire.protocol_gen import STREAM_RATES_HZ
        if page:
            unknown = [k for k in raw if k not in OPTIONS]
            if unknown:
                raise StationError(f"unknown option {unknown[0][:32]!r} (the options are {', '.join(OPTIONS)})")
        note = raw.get("note") or ""
        if not page and isinstance(note, str):
            note = note[:NOTE_CHARS]
        o = {"port": text_field(raw, "port", 256).strip(),
             "method": text_field(raw, "method", 32) or "multi",
             "gyro": text_field(raw, "gyro", 32) or "bias",
             "capture": text_field(raw, "capture", 32) or "adaptive",
             "write": bool_field(raw, "write", True),
             "note": text_field({"note": note}, "note", NOTE_CHARS),
             "rate_hz": int_field(raw, "rate_hz", 500, STREAM_RATES_HZ)}
        if o["port"] == SIM_KEY and not self.state.sim_available:
            raise StationError("the virtual bench is not offered: start the station with --sim")
        if not o["port"]:
            raise StationError("give the device's port (e.g. /dev/ttyUSB0, socket://HOST:PORT) or choose the virtual bench")
        for k, allowed in (("method", METHODS), ("gyro", GYRO_METHODS), ("capture", CAPTURES)):
            if o[k] not in allowed:
                raise StationError(f"{k} must be one of {', '.join(allowed)}, not {o[k]!r}")
        from imubench.procedures.poses import plan_problem
        problem = plan_problem(o["method"], o["gyro"])
        if problem:                                   # refused before anything is captured
            raise StationError(f"{problem[0].replace('--', '')}: {problem[1].replace('--', '')}")
        if page:
            self.check_port(o["port"])
        return o

    def check_port(self, key: str) -> str:
        """A device a page may name: the virtual bench (if offered), a device the station
        shows already, or a port self.ports allows."""
        if key == SIM_KEY:
            if not self.state.sim_available:
                raise StationError("the virtual bench is not offered: start the station with --sim")
            return key
        if isinstance(key, str) and key in self.state.boards:
            return key
        return self.ports.check(key)

    def claim(self, key: str, token: str) -> bool:
        """A page asks to drive the device (token: its identity, issued by the server)."""
        self.check_port(key)
        try:
            return self.state.claim(key, token) == token
        except Refused as e:
            raise StationError(str(e), status=429) from None

    def start(self, raw: dict, token: str | None, directory: str | Path | None = None, resume: bool = False) -> str:
        """Start a session with the page's options on their device; returns the device key.
        token None: started by the command (`imubench calibrate --ui web`); the first page to
        open then owns the device."""
        o = self.options(raw, page=token is not None)
        key = o["port"]
        if token is not None and not self.claim(key, token):
            raise StationError(f"{key} is driven from another page: this page only watches it", status=409)
        with self._lock:
            if self.running(key):
                raise StationError(f"a session is already running on {key}")
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            d = Path(directory) if directory else self.workdir / f"imubench-session-{_safe(key)}-{stamp}"

            def f(b):
                b.status, b.config, b.session_dir, b.error, b.result = "running", o, str(d), None, None
                b.plan, b.steps, b.turns, b.log, b.live, b.targets, b.done_seq = [], [], [], [], {}, {}, 0
                b.resumable = False
                b.phase = "start"
                b.warmup = {}
            self.state.update(key, f)
            self._launch(key, o, d, resume=resume)
        return key

    def resume(self, key: str, token: str | None) -> None:
        self._known(key)
        if not self.state.owns(key, token):
            raise StationError(f"{key[:80]} is driven from another page: this page only watches it", status=409)
        with self._lock:
            if self.running(key):
                raise StationError(f"a session is already running on {key}")
            b = self.state.board(key)
            if not b.session_dir or not (Path(b.session_dir) / "session.json").is_file():
                raise StationError(f"nothing to resume on {key}: start a new session")

            def f(b):
                b.status, b.error, b.resumable, b.result = "running", None, False, None
                b.steps = []
                b.turns = []
            self.state.update(key, f)
            self._launch(key, dict(b.config), Path(b.session_dir), resume=True)

    def stop(self, key: str, token: str | None) -> None:
        self._known(key)
        if not self.state.owns(key, token):
            raise StationError(f"{key[:80]} is driven from another page: this page only watches it", status=409)
        ui = self._ui.get(key)
        if ui is None or not self.running(key):
            raise StationError(f"no session is running on {key[:80]}")
        ev = self._warm_stop.get(key)
        if ev is not None:                  # a warm-up: it ends and keeps the fit of what came
            ui.say("stop asked on the page: the warm-up ends with the fit of what came")
            ev.set()
            return
        ui.stop()

    def _known(self, key: str) -> None:
        if key not in self.state.boards:
            raise StationError(f"this station shows no device {key[:80]!r}", status=404)

    def running(self, key: str) -> bool:
        t = self._threads.get(key)
        if key in self._adopted:
            b = self.state.boards.get(key)
            return b is not None and b.status == "running"
        return t is not None and t.is_alive()

    def wait(self, key: str, timeout: float | None = None) -> None:
        t = self._threads.get(key)
        if t is not None:
            t.join(timeout)

    def close(self) -> None:
        self._closing = True
        for ev in list(self._warm_stop.values()):
            ev.set()
        for key, ui in list(self._ui.items()):
            ui.stop("stopped: the station was closed (Ctrl-C); everything captured is kept")
        for t in list(self._threads.values()):
            t.join(30)
        if self._bench is not None:
            self._bench.close()
            self._bench = None

    # ------------------------------------------------------------------ running
    def _launch(self, key: str, o: dict, directory: Path, resume: bool) -> None:
        ui = WebPresenter(self.state, key)
        self._ui[key] = ui
        self._warm_stop.pop(key, None)
        t = threading.Thread(target=self._run, args=(key, o, directory, resume, ui), name=f"session {key}", daemon=True)
        self._threads[key] = t
        t.start()

    # ------------------------------------------------------------------ a temperature warm-up
    def warmup_options(self, raw: dict, page: bool = False) -> dict:
        """A warm-up's options, checked (as options()): the port, the span asked for
        (span_lo_c, span_hi_c, °C), the face up while it lies still, write, rate_hz."""
        from imubench.wire.protocol_gen import STREAM_RATES_HZ
        if page:
            unknown = [k for k in raw if k not in WARMUP_OPTIONS]
            if unknown:
                raise StationError(f"unknown option {unknown[0][:32]!r} (the options are {', '.join(WARMUP_OPTIONS)})")
        lo, hi = WARMUP_LIMITS_C
        o = {"port": text_field(raw, "port", 256).strip(),
             "span_lo_c": number_field(raw, "span_lo_c", WARMUP_SPAN_C[0], lo, hi),
             "span_hi_c": number_field(raw, "span_hi_c", WARMUP_SPAN_C[1], lo, hi),
             "face": text_field(raw, "face", 4) or "+z",
             "write": bool_field(raw, "write", True),
             "rate_hz": int_field(raw, "rate_hz", 200, STREAM_RATES_HZ)}
        if not o["port"]:
            raise StationError("give the device's port (e.g. /dev/ttyUSB0, socket://HOST:PORT) or choose the virtual bench")
        if o["port"] == SIM_KEY and not self.state.sim_available:
            raise StationError("the virtual bench is not offered: start the station with --sim")
        if o["face"] not in FACES:
            raise StationError(f"face must be one of {', '.join(FACES)} (the board axis that points up), not {o['face']!r}")
        if o["span_hi_c"] - o["span_lo_c"] < 5.0:
            raise StationError(f"the span {o['span_lo_c']:g}..{o['span_hi_c']:g} °C is too narrow: give at least 5 °C, "
                               "low end first (a fridge to a room gives about 5..25 °C)")
        if page:
            self.check_port(o["port"])
        return o

    def start_warmup(self, raw: dict, token: str | None, directory: str | Path | None = None) -> str:
        """Start a temperature warm-up on the page's device; returns the device key."""
        o = self.warmup_options(raw, page=token is not None)
        key = o["port"]
        if token is not None and not self.claim(key, token):
            raise StationError(f"{key} is driven from another page: this page only watches it", status=409)
        with self._lock:
            if self.running(key):
                raise StationError(f"a session is already running on {key}")
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            d = Path(directory) if directory else self.workdir / f"imubench-warmup-{_safe(key)}-{stamp}"

            def f(b):
                b.status, b.error, b.phase, b.resumable = "running", None, "warmup", False
                b.warmup = {"config": dict(o), "dir": str(d), "progress": {}, "result": None}
                b.plan, b.steps, b.turns, b.log, b.live, b.targets, b.done_seq = [], [], [], [], {}, {}, 0
                b.result, b.session_dir, b.config = None, None, {}
            self.state.update(key, f)
            ui = WebPresenter(self.state, key)
            ev = threading.Event()
            self._ui[key] = ui
            self._warm_stop[key] = ev
            t = threading.Thread(target=self._run_warmup, args=(key, o, d, ui, ev), name=f"warm-up {key}", daemon=True)
            self._threads[key] = t
            t.start()
        return key

    def _run_warmup(self, key: str, o: dict, d: Path, ui: WebPresenter, stop: threading.Event) -> None:
        from imubench.device.link import Device
        from imubench.procedures import warmup as W
        latest: dict = {}
        last = [0.0]

        def on_progress(p: dict) -> None:
            latest.clear()
            latest.update(_plain(p))
            now = time.monotonic()
            if now - last[0] >= PROGRESS_MIN_INTERVAL_S:
                last[0] = now
                snap = dict(latest)
                self.state.update(key, lambda b: b.warmup.__setitem__("progress", snap))

        try:
            lo, hi = o["span_lo_c"], o["span_hi_c"]
            if key == SIM_KEY:
                from imubench.device.sim import VirtualBench
                if self._bench is None or not self._bench.running:
                    self._bench = VirtualBench(speed=self.sim_speed, seed=self.sim_seed, truth="random", parts=self.sim_parts)
                hooks = W.sim_warmup_hooks(self._bench, cold_c=lo, warm_c=hi, say=ui.say,
                                           tau_s=self.sim_thermal.get("tau_s"),
                                           self_heat_c=self.sim_thermal.get("self_heat_c"))
                th = self._bench.status().get("thermal") or {}
                ui.say(f"virtual bench: thermal lag on (time constants {_fmt_list(th.get('tau_s'), '{:.0f}')} s, "
                       f"self-heating {_fmt_list(th.get('self_heat_c'), '{:.1f}')} °C); it soaks the board at "
                       f"{lo:g} °C (a night in a fridge), then the room goes to {hi:g} °C")
                url = self._bench.port_url
            else:
                hooks = W.WarmupHooks(say=ui.say)
                url = key
                ui.say(f"the board lies still, {o['face']} up, while it warms from cold (e.g. out of a fridge) "
                       f"towards {hi:g} °C: keep it away from drafts and do not touch it")
            cfg = W.WarmupConfig(**{"span_c": (lo, hi), "rate_hz": o["rate_hz"], "face": o["face"], "write": o["write"],
                                    **self.warmup_settings})
            self.state.update(key, lambda b: b.warmup["config"].update(                 # the page's rate colours
                stop_rate_c_per_min=cfg.stop_rate_c_per_min, stop_window_s=cfg.stop_window_s))
            with Device.open(url, timeout=5.0) as dev:
                from imubench.wire.ids import board_name, part_names, uid_text
                info = dev.info()
                self.state.update(key, lambda b: setattr(b, "device", {"board": board_name(info.board),
                                                                       "uid": uid_text(info.mcu_uid), "url": url,
                                                                       "parts": part_names(info)}))
                result = W.run_warmup(dev, d, cfg, hooks, on_progress=on_progress, stop=stop)
            summary = _warmup_summary(result, d, stopped=stop.is_set(), closing=self._closing)
            failed = result.get("status") == "failed"

            def f(b):
                b.warmup["progress"] = dict(latest) or b.warmup.get("progress") or {}
                b.warmup["result"] = summary
                b.status, b.phase = ("failed" if failed else "done"), "end"
                b.error = summary["verdict"] if failed else None
                b.log.append(summary["verdict"])
            self.state.update(key, f)
        except Exception as e:  # noqa: BLE001 - the page shows why; thermal.json keeps what came
            why = _one_line(e)

            def g(b):
                if latest:
                    b.warmup["progress"] = dict(latest)
                b.status, b.error, b.phase = "failed", why, "end"
                b.log.append(f"failed: {why}; what came is in {d}")
            self.state.update(key, g)
        finally:
            with self._lock:
                if self._warm_stop.get(key) is stop:
                    del self._warm_stop[key]

    def _device_url(self, key: str, ui: WebPresenter):
        if key != SIM_KEY:
            return key, ui
        from imubench.device.sim import VirtualBench
        from imubench.procedures.virtual import SimPerson
        if self._bench is None or not self._bench.running:
            self._bench = VirtualBench(speed=self.sim_speed, seed=self.sim_seed, truth="random", parts=self.sim_parts)
        person = SimPerson(self._bench, forward=ui, **{"seed": self.sim_seed, **self.person_kw})
        self.persons[key] = person
        return self._bench.port_url, person

    def _run(self, key: str, o: dict, directory: Path, resume: bool, ui: WebPresenter) -> None:
        from imubench.device.link import Device
        from imubench.procedures.session import SessionConfig, run_session
        sess_dir = directory
        try:
            url, presenter = self._device_url(key, ui)
            cfg = SessionConfig(method=o["method"], gyro=None if o["gyro"] == "none" else o["gyro"],
                                rate_hz=o["rate_hz"], write=o["write"], note=o["note"],
                                adaptive=o["capture"] == "adaptive", pose_timeout_s=None)
            ui.turns_total = 6 * len(cfg.turntable_rates_dps) if "turntable" in data_needed(cfg.method, cfg.gyro) else 0
            if o["method"] == "six":
                ui.say("warning: six-position needs a square fixture (a machined cube against a square); held by "
                       "hand its faces are degrees off square and the fit fails: use multi")
            with Device.open(url, timeout=5.0) as dev:
                from imubench.wire.ids import board_name, part_names, uid_text
                info = dev.info()
                self.state.update(key, lambda b: setattr(b, "device", {"board": board_name(info.board),
                                                                       "uid": uid_text(info.mcu_uid), "url": url,
                                                                       "parts": part_names(info)}))
                result, sess = run_session(dev, sess_dir, cfg, presenter, resume=resume)
            self._finish(key, result, sess_dir)
        except SessionStopped as e:
            self._failed(key, sess_dir, "interrupted", str(e))
        except Exception as e:  # noqa: BLE001 - the page shows why, the session stays resumable
            self._failed(key, sess_dir, "failed", _one_line(e))

    def _failed(self, key: str, d: Path, status: str, why: str) -> None:
        resumable = (d / "session.json").is_file()

        def f(b):
            b.status, b.error, b.resumable, b.phase = status, why, resumable, "end"
            b.log.append(f"{status}: {why}" + ("; resume it from this page" if resumable else ""))
        self.state.update(key, f)

    def _finish(self, key: str, result: dict, d: Path) -> None:
        recorded = None
        if self.history:
            try:
                from imubench.results.history import History
                with History(self.db) as h:
                    run_id, new = h.record_once(result)
                recorded = f"recorded in the history as run {run_id}" + ("" if new else " (already recorded)")
            except Exception as e:  # noqa: BLE001 - the result is safe in session.json
                recorded = f"not recorded in the history ({_one_line(e)}); the result is in {d / 'session.json'}"
        summary = _summary(key, result, d, recorded)

        def f(b):
            b.status, b.result, b.phase, b.resumable = "done", summary, "end", False
        self.state.update(key, f)

    # ------------------------------------------------------- a station session's boards
    # `imubench calibrate --port A --port B ... --ui web`: the command runs the station session
    # (procedures.fixture) and the page shows one column per board; Stop on a column stops
    # that board only (it leaves the plate, the others go on).
    def adopt(self, key: str, options: dict, slot: int) -> WebPresenter:
        """The column of one board of a station session; returns the presenter its session
        reports to."""
        ui = WebPresenter(self.state, key)
        with self._lock:
            self._ui[key] = ui
            self._adopted.add(key)

        def f(b):
            b.status, b.config, b.phase, b.error, b.result = "running", dict(options), "connect", None, None
            b.device = {"slot": slot}
        self.state.update(key, f)
        return ui

    def board_event(self, key: str, st: dict) -> None:
        """A station session's board status (procedures.fixture.BoardStatus) on its column."""
        def f(b):
            b.device = {**b.device, "slot": st["slot"], "uid": st.get("uid") or b.device.get("uid"), "url": st["port"]}
            b.fixture = {k: st.get(k) for k in ("slot", "stage", "state", "message", "progress", "reason", "waiting")}
            if st["state"] == "running":
                b.phase = {"turntable": "turns", "health": "start", "connect": "start"}.get(st["stage"], st["stage"])
                if st["stage"] in ("write", "verify"):  # the fixture writes and verifies each board itself
                    _close_steps(b, "done")
                    text = {"write": "writing the parameters, reading them back, saving, rebooting",
                            "verify": "verifying the device's calibrated output"}[st["stage"]]
                    if not any(x["kind"] == st["stage"] for x in b.steps):
                        b.steps.append({"kind": st["stage"], "text": text, "state": "running"})
            else:
                b.status, b.phase = {"passed": "done", "stopped": "stopped"}.get(st["state"], "failed"), "end"
                b.error = None if st["state"] == "passed" else f"{st['state']} at {st['stage']}: {st['reason']}"
                _close_steps(b, "done" if st["state"] == "passed" else "failed")
                for c in b.plan:                 # nothing is being captured any more
                    if c["state"] == "capturing":
                        c["state"], c["progress"] = "todo", 0.0
        self.state.update(key, f)

    def plate_event(self, ev: dict) -> None:
        """The plate of a station session, shown once for the whole fixture: its move
        (procedures.fixture.Plate: kind, key, serves, waiting, move) or {"deadlines": text}."""
        if "deadlines" in ev:
            self.state.set_plate(deadlines=ev["deadlines"])
        else:
            self.state.set_plate(move=dict(ev))

    def board_result(self, key: str, record: dict, d: Path, run_id=None) -> None:
        """A station session's board is over: its verdict, parameters and report on its column
        (the report is built here, after every board has finished: it takes the CPU the
        streams need)."""
        recorded = None if run_id is None else f"recorded in the history as run {run_id}"
        summary = _summary(key, record, d, recorded)
        if not record.get("passed"):
            fail = record.get("failure") or {}
            if fail:
                summary["status"] = "stopped" if fail.get("stopped") else "fail"
                summary["verdict"] = f"at {fail.get('stage')}: {fail.get('reason')}"
            elif summary["status"] == "pass":
                summary["status"] = "fail"
                summary["verdict"] = self.state.boards[key].error or "did not pass its limits"

        def f(b):
            b.result = summary
            b.status = {"pass": "done", "stopped": "stopped"}.get(summary["status"], "failed")
            b.phase = "end"
        self.state.update(key, f)

    def export_path(self, safe_key: str, name: str) -> Path | None:
        """One of a board's export files by its name (only the names its summary lists)."""
        for b in self.state.boards.values():
            if _safe(b.key) == safe_key and b.result:
                for e in b.result.get("exports") or []:
                    if e.get("name") == name and e.get("path"):
                        return Path(e["path"])
        return None

    def report_path(self, safe_key: str) -> Path | None:
        for b in self.state.boards.values():
            if _safe(b.key) == safe_key and b.result and b.result.get("report_path"):
                return Path(b.result["report_path"])
        return None


def _close_steps(b, state: str) -> None:
    for x in b.steps:
        if x["state"] == "running":
            x["state"] = state


def _summary(key: str, result: dict, d: Path, recorded: str | None) -> dict:
    """What a finished session's column shows: verdict first, parameters ± σ, the report."""
    from imubench.results.report import build_report, calibration_verdict, parameter_rows
    status, words = calibration_verdict(result)
    report = build_report(d) if (Path(d) / "session.json").is_file() else None
    params = [r for r in parameter_rows(result) if r[1] != "not estimated"]
    exports = _board_exports(key, result, d) if status == "pass" else []
    return {"exports": exports, "status": status, "verdict": words, "parameters": params,
            "accel_rms_after_mg": result.get("accel_rms_after_mg"), "bench_time_s": result.get("bench_time_s"),
            "attitudes": len(result.get("poses") or []), "passed": bool(result.get("passed")),
            "written": bool(result.get("written")), "verified": bool(result.get("verified")),
            "report": f"/report/{_safe(key)}/report.html" if report else None,
            "report_path": str(report) if report else None, "history": recorded, "session_dir": str(d)}


def _plain(x):
    """What on_progress or thermal.json hold, as JSON the page can take: numpy arrays and
    scalars become lists and floats, tuples lists, keys strings."""
    import numpy as np
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def _fmt_list(v, f: str) -> str:
    return "?" if not v else "/".join(f.format(x) for x in v)


def _warmup_summary(result: dict, d: Path, stopped: bool, closing: bool = False) -> dict:
    """What a finished warm-up's column shows: the verdict, the fit per triad and axis (order,
    held-out error, 1σ of the curve over its span, the span), what could not be determined,
    the write-back, where the files are."""
    r = _plain(result or {})
    status, why, wr = r.get("status"), r.get("stop_reason"), r.get("write") or {}
    verified = bool(wr.get("verified"))
    if status == "failed":
        verdict = f"warm-up failed ({r.get('error') or why or 'no reason given'})"
    elif stopped:
        verdict = ("stopped: the station was closed" if closing else "stopped on the page") + \
            ": the fit of what came is kept"
    else:
        verdict = f"warm-up finished: {why}" if why else "warm-up finished"
    if r.get("fit") is None:
        verdict += "; nothing fitted (too little data)"
    elif verified:
        verdict += "; written to the device and verified"
    elif wr.get("error"):
        verdict += f"; NOT written ({wr['error']}); the previous parameters are kept"
    else:
        verdict += "; not written"
    fit, notes = {}, []
    for triad, f in (r.get("fit") or {}).items():
        axes = f.get("axes") or []
        fit[triad] = [{"order": a.get("order"), "heldout_rms": a.get("heldout_rms"),
                       "sigma_over_span": a.get("sigma_over_span"), "span_c": a.get("span_c")} for a in axes]
        for k, a in enumerate(axes):
            for n in (a.get("undetermined") or []) + (a.get("notes") or []):
                notes.append(f"{triad} {'xyz'[k]}: {n}")
    notes += [str(n) for n in wr.get("notes") or []]
    return {"verdict": verdict, "stopped": stopped, "status": status, "written": verified, "fit": fit,
            "notes": notes, "stop_reason": why, "dir": str(d), "thermal_json": str(Path(d) / "thermal.json"),
            "exports": r.get("exports") or {}}


def _board_exports(key: str, result: dict, d: Path) -> list[dict]:
    """Every calibration format of the export registry for one board that passed, in
    d/exports (a download each on its column: /export/KEY/FILE); [] when they cannot be made."""
    from imubench.procedures.export_files import write_calibration
    from imubench.results import exports as X
    uid = (result.get("device") or {}).get("mcu_uid") or _safe(key)
    try:
        files = write_calibration(X.names("calibration"), Path(d) / "exports", result, name=uid,
                                    comment=f"imubench calibration of {uid}, {result.get('finished') or ''}")
    except (ValueError, OSError, KeyError) as e:
        return [{"kind": "error", "name": _one_line(e), "url": None}]
    # the page has no PX4 device ids: its px4 file says it is not usable as is, and so does its link
    label = {"px4": "px4 (not usable without CAL_*_ID: see the file)"}
    out = [{"kind": kind, "label": label.get(kind, kind) if len(paths) == 1 else f"{kind} {'accel' if k == 0 else 'gyro'}",
            "consumer": X.get("calibration", kind).consumer, "name": Path(p).name, "path": str(p),
            "url": f"/export/{_safe(key)}/{Path(p).name}"}
           for kind, paths in files.items() for k, p in enumerate(paths)]
    idx = Path(d) / "exports" / "exports-calibration.txt"
    out.append({"kind": "index", "label": "what each file is for", "consumer": "", "name": idx.name,
                "path": str(idx), "url": f"/export/{_safe(key)}/{idx.name}"})
    return out


def _safe(key: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in key).strip("-") or "device"


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return text if isinstance(e, ImubenchError) and text else f"{type(e).__name__}: {text}" if text else type(e).__name__
