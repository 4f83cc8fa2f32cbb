"""Many boards on one fixture: one station session calibrates every board on the plate.

    imubench calibrate --port URL1 --port URL2 ... [--station-file FILE] [--station ID] [--operator NAME]
    imubench calibrate --sim --sim-boards 4

The boards are mounted on one plate, so they see the same attitudes and the same turntable
motion. Each board runs the ordinary guided session (imubench.procedures.session: health
check, rest, poses, turns, fit, write-back, verification) in its own thread on its own link,
in its own session directory (DIR/slot-K). The plate is shared: a board's session that asks
for its next move (any attitude it still misses, a turn, a verification attitude) waits at
the Plate until every board still running has asked; then the plate makes the move that
serves the most boards (procedures.schedule: the attitudes boards still need first, the most
shared first; turns; verification last), by the operator or on the virtual bench by a
PlatePresenter that moves every virtual device, and the boards it serves go on. Every wait
has a deadline in device time (PLATE_TIMEOUT_S at the plate, POSE_TIMEOUT_S for a presented
attitude): past it that board fails with the stage and the reason. A board that fails
(its link lost, a sensor faulted, its fit refused or out of tolerance, its write-back or
verification failed) leaves the plate with its stage and reason, and the others carry on:
the verdict is per board.

Every board gets a record (schema 2, results.history) with the station, operator, fixture,
slot and port, firmware and host versions, the parameter block before and after, the
measurements with their limits, and the SHA-256 of its raw capture with where it is stored;
a board that failed before it was fitted gets a record with the stage and reason. They are
recorded as each board finishes (the database may be shared with other stations).

Per-board state is published as it changes: `on_event(status)` is called with a dict
(slot, port, uid, stage, state running/passed/failed, message, progress, reason) for a
station page or a log; `FixtureRun.snapshot()` gives all of them at once.

Here the station session (FixtureRun); one board's status, presenter and session are in
fixture_board.py, the boards' records in fixture_record.py.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from imubench.calib import CalibrationError
from imubench.device.clock import ClockError
from imubench.device.link import Device, LinkError, LinkTimeout
from imubench.errors import ImubenchError
from imubench.files import make_dir, write_text
from imubench.procedures.errors import SessionAborted
from imubench.procedures.plate import POSE_TIMEOUT_S, PLATE_TIMEOUT_S, BoardFailed, BoardStopped, Plate  # noqa: F401 - where callers found them
from imubench.procedures.session import SessionConfig, plan_for
from imubench.procedures.writeback import VerifyFailed
from imubench.results.atomic import write_json_atomic
from imubench.results.record import device_ident, jsonable, now_utc
from imubench.wire import params as PR
from imubench.wire.protocol_gen import ParamsWhich
# one board (fixture_board) and the records (fixture_record), named here as before
from imubench.procedures.fixture_board import BoardPresenter, BoardSession, BoardStatus, Station, _line
from imubench.procedures.fixture_record import FixtureRecords, capture_ref  # noqa: F401 - capture_ref: named here too


# ---------------------------------------------------------------- the station session
@dataclass
class FixtureResult:
    session_id: str
    directory: Path
    boards: list[BoardStatus]
    results: dict[int, dict] = field(default_factory=dict)      # slot -> the board's record
    wall_s: float = 0.0

    @property
    def passed(self) -> list[int]:
        return [b.slot for b in self.boards if b.state == "passed"]

    @property
    def failed(self) -> list[int]:
        return [b.slot for b in self.boards if b.state != "passed"]

    @property
    def stopped(self) -> list[int]:
        return [b.slot for b in self.boards if b.state == "stopped"]

    interrupted: str | None = None      # why the whole session was stopped (Ctrl-C, SIGTERM, the page), if it was


class FixtureRun(FixtureRecords):
    """One station session over several boards (see the module's doc)."""

    def __init__(self, ports: list[str], directory, cfg: SessionConfig, mover, station: Station | None = None,
                 db=None, on_event: Callable[[dict], None] | None = None, link_timeout_s: float = 10.0,
                 baudrate: int | None = None, say=print, plots: bool = True,
                 pages: Callable[[int, str], object] | None = None, plate_timeout_s: float = PLATE_TIMEOUT_S,
                 on_plate: Callable[[dict], None] | None = None, resume: bool = False, extra: dict | None = None):
        if not ports:
            raise ValueError("no boards: give at least one port")
        self.ports = list(ports)
        self.dir = Path(directory)
        # a station session has no wait without an end: a presented attitude is held still
        # within pose_timeout_s of device time, or that board fails (the others go on)
        self.cfg = cfg if cfg.pose_timeout_s is not None else dataclasses.replace(cfg, pose_timeout_s=POSE_TIMEOUT_S)
        self.on_plate = on_plate        # on_plate(move): the plate's current attitude or turn, for a page
        self.station = station or Station()
        self.db = db
        self.on_event = on_event
        self.link_timeout_s = link_timeout_s
        self.baudrate = baudrate
        self.say = say
        self.plots = plots
        self.pages = pages              # pages(slot, port): a station page's presenter for that board, or None
        self.session_id = (f"{self.station.station_id}-{_dt.datetime.now(_dt.timezone.utc):%Y%m%dT%H%M%SZ}-"
                           f"{uuid.uuid4().hex[:6]}")
        self.boards = {k + 1: BoardStatus(slot=k + 1, port=p, directory=str(self.dir / f"slot-{k + 1}"))
                       for k, p in enumerate(self.ports)}
        self.extra = dict(extra or {})  # kept in station.json (e.g. the virtual fixture's seed)
        self.resume = resume
        self.kept: set[int] = set()     # a resumed session: the boards that had finished (not run again)
        self.results: dict[int, dict] = {}
        if resume:
            self._load_station()
        self.plate = Plate(mover, [s for s in self.boards if s not in self.kept], say=say, deadline_s=plate_timeout_s,
                           on_wait=self._on_wait, on_move=self._on_move)
        self._lock = threading.Lock()
        self.stop_reason: str | None = None     # the whole session was stopped: why (stop())

    # ------------------------------------------------------------ stopping
    def stop(self, reason: str = "stopped") -> None:
        """Stop every board where it is (Ctrl-C, SIGTERM, the page closed): each stops at its
        next block of samples or check at the plate, is recorded as stopped with its stage,
        and the boards already finished keep their records. Any thread may call it."""
        if self.stop_reason is None:
            self.stop_reason = reason
        with self.plate._cv:
            self.plate._cv.notify_all()

    def check_stop(self, slot: int) -> None:
        if self.stop_reason is not None:
            raise BoardStopped(self.boards[slot].stage, f"stopped: {self.stop_reason}")

    # ------------------------------------------------------------ state
    def _update(self, slot: int, publish: bool = True, **kw) -> None:
        with self._lock:
            st = self.boards[slot]
            for k, v in kw.items():
                setattr(st, k, v)
            snap = st.as_dict()
        if publish and self.on_event is not None:
            try:
                self.on_event(snap)
            except Exception:  # noqa: BLE001 - a broken listener must not fail a board
                pass

    def _on_wait(self, slot: int, text: str | None) -> None:
        self._update(slot, waiting=text)

    def _on_move(self, move: dict) -> None:
        if self.on_plate is not None:
            try:
                self.on_plate(move)
            except Exception:  # noqa: BLE001 - a broken listener must not stop the plate
                pass

    def deadlines_text(self) -> str:
        return (f"deadlines (device time): a board waits at most {self.plate.deadline_s:g} s for the plate "
                f"(the attitudes other boards still need first, verification last) and "
                f"{self.cfg.pose_timeout_s:g} s for a presented attitude to be held still; past one it fails "
                "with the stage and the reason, and the others go on")

    def snapshot(self) -> list[dict]:
        with self._lock:
            return [b.as_dict() for b in self.boards.values()]

    def _save_station(self, finished: bool = False) -> None:
        write_json_atomic(self.dir / "station.json", {
            "schema": 1, "session_id": self.session_id, "station": dataclasses.asdict(self.station),
            "config": jsonable(dataclasses.asdict(self.cfg)), "ports": self.ports, "finished": finished,
            "stopped": self.stop_reason, "resumed": self.resume, **self.extra, "boards": self.snapshot()})

    def _load_station(self) -> None:
        """A whole station session resumed: the same session id; each board that finished
        (passed or failed, its record written) stays finished; the others continue their own
        capture in DIR/slot-K (a board that had none starts it), each on the device it was
        captured on (Session refuses another)."""
        import json
        path = self.dir / "station.json"
        try:
            saved = json.loads(path.read_text())
            boards = {int(b["slot"]): b for b in saved["boards"]}
            self.session_id = str(saved["session_id"])
        except FileNotFoundError:
            raise SessionAborted(f"cannot resume: {self.dir} holds no station.json (not a station session)") from None
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SessionAborted(f"cannot resume: {path} is damaged ({type(e).__name__}: {e})") from None
        if len(boards) != len(self.boards):
            raise SessionAborted(f"cannot resume: {self.dir} is a station session of {len(boards)} boards; "
                                 f"{len(self.boards)} were given")
        for slot, b in boards.items():
            rec_path = self.dir / f"slot-{slot}" / "record.json"
            if b.get("state") in ("passed", "failed") and rec_path.is_file() and slot in self.boards:
                st = self.boards[slot]
                for k in ("uid", "stage", "state", "message", "progress", "reason", "run_id", "device"):
                    if k in b:
                        setattr(st, k, b[k])
                try:
                    self.results[slot] = json.loads(rec_path.read_text())
                except (OSError, ValueError):
                    continue
                self.kept.add(slot)

    # ------------------------------------------------------------ run
    def run(self) -> FixtureResult:
        t0 = time.monotonic()
        make_dir(self.dir)
        if (self.dir / "station.json").exists() and not self.resume:
            raise SessionAborted(f"{self.dir} already holds a station session: continue it with --resume "
                                 f"{self.dir}, or give another --dir")
        self._save_station()
        for slot in sorted(self.kept):
            self.say(f"slot {slot}: {self.boards[slot].state} before; kept (its record stays)")
        self.say(self.deadlines_text())
        self._on_move({"deadlines": self.deadlines_text()})
        # Each board's thread sets its event as its very last step, and this thread waits on the
        # events, never on Thread.join: in CPython 3.11 a signal (Ctrl-C, SIGTERM made one) that
        # interrupts join(timeout) marks a running thread as finished (gh-90882), and the session
        # then ended while a board was still writing its history row.
        done = {slot: threading.Event() for slot in self.boards if slot not in self.kept}
        for slot, ev in done.items():
            threading.Thread(target=self._board_then, args=(slot, ev), name=f"board-{slot}", daemon=True).start()
        try:
            for ev in done.values():
                while not ev.wait(0.25):    # a wait with a timeout: Ctrl-C reaches this thread
                    pass
        except KeyboardInterrupt as e:      # Ctrl-C (or SIGTERM made one): every board stops and is recorded
            self.stop(_stop_words(e))
            for ev in done.values():
                ev.wait()
        if self.plots:                  # after the boards: the plots take CPU the live streams need
            from imubench.results.calibration import plot_pose_residuals
            for slot, rec in sorted(self.results.items()):
                if rec.get("accel") is not None and rec.get("poses"):
                    try:
                        plot_pose_residuals(rec, self.dir / f"slot-{slot}" / "residuals.png")
                    except Exception as e:  # noqa: BLE001 - a plot is not worth a board's verdict
                        self.say(f"warning: slot {slot}: no residual plot ({e})")
        self._save_station(finished=True)
        res = FixtureResult(self.session_id, self.dir, [self.boards[s] for s in sorted(self.boards)],
                            dict(self.results), time.monotonic() - t0)
        res.interrupted = self.stop_reason
        return res

    def _board_then(self, slot: int, done: threading.Event) -> None:
        try:
            self._board(slot)
        finally:
            done.set()

    def _board(self, slot: int) -> None:
        st = self.boards[slot]
        started = now_utc()
        dev = None
        result: dict | None = None
        info_dev: dict = {"mcu_uid": None}
        params_before = None
        try:
            self._update(slot, stage="connect", message=f"opening {st.port}")
            try:
                self._guard_clock(st.port)
                kw = {"timeout": 5.0} | ({"baudrate": self.baudrate} if self.baudrate else {})
                dev = Device.open(st.port, **kw)
                info = dev.info()
            except (OSError, LinkError, TimeoutError, ImubenchError) as e:
                raise BoardFailed("connect", f"no answer from the device on {st.port}: {_line(e)}") from None
            info_dev = device_ident(info)
            self._update(slot, uid=info_dev["mcu_uid"], device=info_dev,
                         message=f"{info_dev['board']} {info_dev['mcu_uid']}")
            params_before = dev.get_params(ParamsWhich.ACTIVE).params
            stats, rate = dev.link.decoder.stats, float(self.cfg.rate_hz)
            again = self.resume and (self.dir / f"slot-{slot}" / "session.json").is_file()
            try:
                sess = BoardSession(dev, self.dir / f"slot-{slot}", dataclasses.replace(self.cfg),
                                    BoardPresenter(self, slot, discard=dev.discard_buffered,
                                                   page=self.pages(slot, st.port) if self.pages else None,
                                                   clock=lambda: stats.samples / rate),
                                    board_run=self, slot=slot, link_timeout_s=self.link_timeout_s, resume=again)
            except SessionAborted as e:     # e.g. another device than its capture's: refused, this board only
                raise BoardFailed("connect", str(e)) from None
            except (LinkError, ImubenchError, TimeoutError, OSError) as e:     # it stopped answering already
                raise BoardFailed("connect", f"no answer from the device on {st.port}: {_line(e)}") from None
            try:
                result = sess.run(plan_for(self.cfg.method))
            except CalibrationError as e:
                raise BoardFailed("fit", f"fit refused: {e}") from None
            except (LinkTimeout, LinkError, ClockError, TimeoutError, ConnectionError) as e:
                raise BoardFailed("link", f"link lost: {_line(e)}") from None
            except (SessionAborted, ImubenchError) as e:   # e.g. stopped on the station page
                why = _line(e)
                if self.stop_reason is not None or type(e).__name__ == "SessionStopped":
                    raise BoardStopped(self.boards[slot].stage, f"stopped: {self.stop_reason or why}") from None
                if "a frozen device" in why:        # a lockstep device's grant passed its wall-clock guard
                    raise BoardFailed("link", f"link lost: {why}") from None
                raise BoardFailed(self.boards[slot].stage, why) from None
            self._update(slot, stage="fit", message=f"fit: |a| − g RMS {result['accel_rms_after_mg']:.3f} mg")
            result["write_requested"] = bool(self.cfg.write)
            if result["passed"] and self.cfg.write:
                self._write_and_verify(slot, sess, result)
            elif not result["passed"]:
                self.plate.leave(slot)
            result["params_after"] = PR.to_json(dev.get_params(ParamsWhich.ACTIVE).params)
            sess.finish(result)
        except BoardStopped as e:
            self._fail(slot, e.stage, e.reason, state="stopped")
        except BoardFailed as e:
            if self.stop_reason is not None and e.stage == "link":     # the stop cut its link, not a fault
                self._fail(slot, self.boards[slot].stage, f"stopped: {self.stop_reason}", state="stopped")
            else:
                self._fail(slot, e.stage, e.reason)
        except Exception as e:  # noqa: BLE001 - a bug on one board must not stop the others; it is named
            self._fail(slot, self.boards[slot].stage, f"{type(e).__name__}: {e}")
            make_dir((self.dir / f"slot-{slot}"))
            write_text(self.dir / f"slot-{slot}" / "error.txt", traceback.format_exc())
        finally:
            self.plate.leave(slot)
            try:
                link_stats = dev.link.decoder.stats if dev is not None else None
                if dev is not None:
                    dev.close()
            except Exception:  # noqa: BLE001
                link_stats = None
        try:
            rec = self._record_for(slot, started, result, info_dev, params_before, link_stats)
        except Exception as e:  # noqa: BLE001 - every board gets a record, even when building it failed
            st = self.boards[slot]
            if st.state == "running":
                self._update(slot, state="failed", reason=f"{type(e).__name__}: {e}")
            rec = {"device": info_dev, "started": started, "passed": False, "session_id": self.session_id,
                   "station": {"id": self.station.station_id, "slot": slot, "port": st.port},
                   "failure": {"stage": st.stage, "reason": st.reason or f"{type(e).__name__}: {e}",
                               "stopped": st.state == "stopped"}, "measurements": []}
            (self.dir / f"slot-{slot}").mkdir(parents=True, exist_ok=True)
            write_text(self.dir / f"slot-{slot}" / "error.txt", traceback.format_exc())
        self.results[slot] = rec
        self._record(slot, rec)

    def _guard_clock(self, port: str) -> None:
        """A lockstep virtual device's grants get this board's link timeout as their wall-clock
        guard: a frozen simulator (its process stopped, its link open) never lets its device
        time pass, so no device-time deadline of its own could ever end the wait; with the
        guard the board fails at link within link_timeout_s of wall time, alone (each
        board's clock is its own), and the others' grants go on."""
        from imubench.device.clock import for_url
        clk = for_url(port)
        if getattr(clk, "lockstep", False):
            clk.guard_wall_s = min(clk.guard_wall_s, max(float(self.link_timeout_s), 1.0))

    def _write_and_verify(self, slot: int, sess: BoardSession, result: dict) -> None:
        """The session's write-back (procedures.writeback.write_and_verify: the previous
        parameters put back when it fails); a failure is the board's, at its stage."""
        try:
            out = sess.write_and_verify()
        except BoardStopped:
            self.plate.leave(slot)
            raise
        except VerifyFailed as e:
            self.plate.leave(slot)
            if self.stop_reason is not None:
                raise BoardStopped("verify", f"stopped: {self.stop_reason}; the previous parameters were put back") from None
            result["written"] = False
            raise BoardFailed("verify", f"verification failed: {_line(e)}") from None
        except (PR.InvalidParams, SessionAborted, LinkError, TimeoutError, ImubenchError, OSError) as e:
            self.plate.leave(slot)
            raise BoardFailed("write", f"write-back failed: {_line(e)}") from None
        result.update(written=out.written, verified=out.verified, verification=out.verification,
                      write_steps=out.steps)

    def _fail(self, slot: int, stage: str, reason: str, state: str = "failed") -> None:
        self.plate.leave(slot)
        self._update(slot, state=state, stage=stage or "connect", reason=reason, message=f"{state.upper()}: {reason}")
        if self.on_event is None:       # a listener shows the failure with the board's other events
            self.say(f"slot {slot} ({self.boards[slot].port}) {state.upper()} at {stage}: {reason}")


def run_fixture(ports: list[str], directory, cfg: SessionConfig, mover, **kw) -> FixtureResult:
    """One station session over the boards on `ports` (see FixtureRun)."""
    return FixtureRun(ports, directory, cfg, mover, **kw).run()


# ------------------------------------------------------------------- helpers
def _stop_words(e: BaseException) -> str:
    """Why a KeyboardInterrupt stopped the session: Ctrl-C, or a signal the command made one."""
    import signal
    if type(e).__name__ != "_Terminated":
        return "interrupted (Ctrl-C)"
    if e.args and e.args[0] == getattr(signal, "SIGHUP", None):
        return "the terminal hung up (SIGHUP: the link to the host was lost)"
    return "terminated (SIGTERM)"


