"""One board of a station session (procedures.fixture): who and where (Station), its published
status (BoardStatus), its presenter (instructions to its status, moves to the shared plate) and
its session (the ordinary one with the stages published, a lost link and a faulted sensor
failing this board alone).
"""
from __future__ import annotations

import dataclasses
import socket
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from imubench.device.link import Device, LinkError, LinkTimeout
from imubench.errors import ImubenchError
from imubench.procedures.errors import SessionAborted
from imubench.procedures.plate import BoardFailed, BoardStopped
from imubench.procedures.presenter import Presenter
from imubench.procedures.schedule import Need
from imubench.procedures.session import Session, SessionConfig
from imubench.wire.ids import SENSOR_BAD_BITS, SENSOR_NAMES


@dataclass
class Station:
    """Who and where: goes into every board's record."""
    station_id: str = ""
    operator: str = ""
    fixture: str = ""
    host_version: str = ""

    def __post_init__(self):
        if not self.station_id:
            self.station_id = socket.gethostname()
        if not self.host_version:
            from imubench import __version__
            self.host_version = __version__


@dataclass
class BoardStatus:
    slot: int
    port: str
    uid: str | None = None
    stage: str = "waiting"          # connect, health, rest, poses, turntable, fit, write, verify, record, done
    state: str = "running"          # running | passed | failed | stopped (Ctrl-C, SIGTERM, Stop on the page)
    message: str = ""
    progress: float = 0.0
    reason: str | None = None
    run_id: int | None = None
    directory: str = ""
    waiting: str | None = None      # done with a phase, waiting for the other boards: for whom, till when
    device: dict | None = None      # its identity (results.record.device_ident: UID, serials, firmware build)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class BoardPresenter(Presenter):
    """One board's Presenter: instructions go to its status, moves to the shared plate. With
    `page` (a station page's presenter for this board's column, imubench.station.presenter)
    the session's live view, pose cards, fit and steps go there too; the plate stays the one
    that moves: a board asks it for any of the attitudes it still misses (present_todo), and
    the plate presents what most boards need (procedures.schedule). `clock()` is the board's
    device time in seconds (its samples so far): the plate's deadlines are counted on it. `run`:
    the station session (procedures.fixture.FixtureRun) the board belongs to."""

    def __init__(self, run, slot: int, discard=lambda: None, page=None,
                 clock: Callable[[], float] | None = None):
        self.run, self.slot = run, slot
        self.discard = discard          # drop what the board sent while it waited for the plate
        self.page = page
        self.clock = clock
        self.suggested = None
        self.shown = page if page is not None else Presenter()     # where the session's views go

    # what the session shows goes to the page (nothing without one); suggest is this board's vote
    def present_plan(self, plan, method):
        self.shown.present_plan(plan, method)

    def present_rest(self, duration_s):
        self.shown.present_rest(duration_s)

    def pose_event(self, name, state, detail):
        self.shown.pose_event(name, state, detail)

    def live(self, state):
        self.shown.live(state)

    def targets(self, sigmas, targets, reached):
        self.shown.targets(sigmas, targets, reached)

    def step(self, kind, text, state):
        if kind in ("write", "verify") and state == "running":
            self.run._update(self.slot, stage=kind, message=text)
        self.shown.step(kind, text, state)

    def say(self, text: str) -> None:
        self.run._update(self.slot, message=text)
        if self.page is not None:
            self.page.say(text)

    def _check_page(self) -> None:
        self.run.check_stop(self.slot)  # the whole station session stopped (Ctrl-C, SIGTERM, the page closed)
        if self.page is not None:
            try:
                self.page.check_stop()  # stopped on the page: this board stops here
            except ImubenchError as e:
                raise BoardStopped(self.run.boards[self.slot].stage, f"stopped: {_line(e)}") from None

    def suggest(self, name) -> None:
        """The missing attitude that helps this board's fit most: its vote at the plate."""
        self.suggested = name
        if self.page is not None:
            self.page.suggest(name)

    def present_todo(self, todo, done, total):
        """The attitudes this board still misses, in any order: the plate presents one of
        them (the one most boards miss) when every board has asked."""
        self._check_page()
        self.run._update(self.slot, stage="poses", message=f"{len(done)} of {total} captured; waiting for the plate",
                         progress=len(done) / max(total, 1))
        need = Need("pose", tuple(n for n, _ in todo), prefer=self.suggested)
        args = {n: (n, np.asarray(d, float)) for n, d in todo}
        key = self.run.plate.request(self.slot, need, args, clock=self.clock, stage="poses", check=self._check_page)
        if key is not None:
            self.run._update(self.slot, message=f"[{len(done) + 1}/{total}] {key}")
            if self.page is not None:
                self.page.pose_event(key, "capturing", {"progress": 0.0})
        # while this board waited for the others, its samples of the old attitude piled up: they
        # are in the raw capture, but the session's wait for the new attitude starts now
        self.discard()

    def present_pose(self, name, direction, index, total):
        """A directed attitude: one of verification (after the write-back), or of a known-angle
        turn; every board asks for it in the same order."""
        self._check_page()
        st = self.run.boards[self.slot]
        verify = st.stage in ("write", "verify")
        stage = "verify" if verify else "poses"
        self.run._update(self.slot, stage=stage, message=f"[{index + 1}/{total}] {name}", progress=index / max(total, 1))
        if self.page is not None:
            if verify:
                self.page.present_pose(name, direction, index, total)
            else:
                self.page.pose_event(name, "capturing", {"progress": 0.0})
        need = Need("verify" if verify else "turn", (name,))
        self.run.plate.request(self.slot, need, {name: (name, np.asarray(direction, float), index, total)},
                               clock=self.clock, stage=stage, check=self._check_page)
        self.discard()

    def present_turn(self, axis, rate_dps, duration_s):
        self._check_page()
        self.run._update(self.slot, stage="turntable", message=f"turn {rate_dps:+.0f} °/s about {np.round(axis, 2).tolist()}")
        if self.page is not None:
            self.page.present_turn(axis, rate_dps, duration_s)
        key = (tuple(float(x) for x in np.round(np.asarray(axis, float), 6)), float(rate_dps))
        self.run.plate.request(self.slot, Need("turn", (key,)), {key: (np.asarray(axis, float), rate_dps, duration_s)},
                               clock=self.clock, stage="turntable", check=self._check_page)
        self.discard()

    def progress(self, label, fraction):
        self._check_page()
        self.run._update(self.slot, progress=float(fraction), publish=False)
        if self.page is not None:
            self.page.progress(label, fraction)


class BoardSession(Session):
    """The ordinary session with the stages published and two production rules: no data for
    link_timeout_s is a lost link, and a sample flagged bad (a sensor fault, parity or SPI
    error) during capture stops the board, naming the sensor. board_run: the station session
    (procedures.fixture.FixtureRun) its stages are published to, or None."""

    def __init__(self, device: Device, directory, config: SessionConfig, presenter: Presenter, *,
                 board_run=None, slot: int = 0, link_timeout_s: float = 10.0,
                 resume: bool = False):
        super().__init__(device, directory, config, presenter, resume=resume)
        self.board_run = board_run
        self.slot = slot
        self.link_timeout_s = link_timeout_s
        self.link_lost: str | None = None   # why the link was lost, once it was

    def _stage(self, stage: str) -> None:
        if self.board_run is not None:
            self.board_run._update(self.slot, stage=stage)

    def check_health(self) -> dict:
        self._stage("health")
        try:
            return super().check_health()
        except SessionAborted as e:
            raise BoardFailed("health", str(e)) from None

    def capture_rest(self) -> dict:
        self._stage("rest")
        return super().capture_rest()

    def _stop_stream(self) -> None:
        """As the session's, but after a lost link only the capture file is closed: asking a
        silent device to stop would just wait out the retries and hide why the board failed."""
        if self.link_lost is None:
            try:
                return super()._stop_stream()
            except (LinkError, TimeoutError, ImubenchError, OSError) as e:    # any error of this board's link
                self.link_lost = _line(e)
        cap, self.dev.link.capture = self.dev.link.capture, None
        if cap is not None:
            cap.close()

    def _leave_plate(self) -> None:
        """Stop holding the plate at once (the session's clean-up may still take a while)."""
        if self.board_run is not None:
            self.board_run.plate.leave(self.slot)

    def _next_block(self, timeout: float = 10.0):
        if self.board_run is not None:
            self.board_run.check_stop(self.slot)
        try:
            b = self.dev.read(duration_s=0.05, timeout=min(timeout, self.link_timeout_s))
        except LinkTimeout:
            self._leave_plate()
            self.link_lost = f"link lost: no data from the device for {self.link_timeout_s:g} s"
            raise BoardFailed("link", self.link_lost) from None
        except (LinkError, ImubenchError, TimeoutError, OSError) as e:
            # any error of this board's link (a lost port, a simulator that stopped answering:
            # its grant passed the clock's wall-clock guard) is this board's alone
            self._leave_plate()
            self.link_lost = f"link lost: {_line(e)}"
            raise BoardFailed("link", self.link_lost) from None
        bad = int(np.bitwise_or.reduce(b.status)) if len(b) else 0
        if bad:
            names = [n for bit, n in zip(SENSOR_BAD_BITS, SENSOR_NAMES) if bad & bit]
            self._leave_plate()
            raise BoardFailed("sensor", f"{', '.join(names)} flagged bad during capture "
                                        f"({int(np.count_nonzero(b.status))} of {len(b)} samples): a faulted sensor; "
                                        "nothing is calibrated on faulted data")
        self._count_block(b)
        return b


def _line(e: BaseException | str) -> str:
    """An error as one line (a simulator's error may carry its log's tail); a lockstep
    device's grant past its wall-clock guard is said as what it is."""
    import re
    text = str(e).strip()
    text = text.splitlines()[0] if text else type(e).__name__
    return re.sub(r"no reply to (run|status) within ([0-9.]+) s",
                  lambda m: f"the device stopped answering (no device time passed in {float(m.group(2)):.3g} s of "
                            "wall time: a frozen device)", text)
