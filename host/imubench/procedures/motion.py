"""The turns of a calibration session: turntable turns at known rates, and known-angle turns
by hand (--gyro turns), captured from the blocks `next_block()` returns (the session reads the
device; a test returns arrays) and fitted (calib.gyro, calib.turns)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from imubench.calib.turns import TURN_DEG
from imubench.procedures.config import SessionConfig
from imubench.procedures.errors import SessionAborted
from imubench.procedures.poses import DETECT_TOL_DEG
from imubench.procedures.presenter import TURN_POSE_SUFFIX, Presenter
from imubench.wire.decoder import SampleBlock


class MotionCapture:
    """The turns of one session (its config, its rest: noise and gyro bias, its presenter)."""

    def __init__(self, cfg: SessionConfig, rest: dict | None, ui: Presenter, next_block: Callable[[], SampleBlock]):
        self.cfg = cfg
        self.rest = rest
        self.ui = ui
        self.next_block = next_block

    # ------------------------------------------------------------- turntable
    def capture_turntable(self) -> list:
        """Turns at known rates about each board axis, both ways; returns the segments
        (measured rates, axis, table rate, None, mean raw acceleration m/s²): the session turns
        the last into the calibrated specific force for calib.gyro.turntable's g-sensitivity."""
        fs = self.cfg.rate_hz
        segments = []
        for axis_name, axis in (("X", (1.0, 0, 0)), ("Y", (0, 1.0, 0)), ("Z", (0, 0, 1.0))):
            for rate in self.cfg.turntable_rates_dps:
                for sign in (1.0, -1.0):
                    r_dps = sign * rate
                    self.ui.present_turn(np.array(axis), r_dps, self.cfg.turntable_s)
                    need = int(0.6 * self.cfg.turntable_s * fs)     # the steady middle of the turn
                    got = self._steady_turn_samples(np.array(axis), np.radians(r_dps), need,
                                                    int((self.cfg.turntable_s + 30) * fs))
                    seg_acc, seg = got if got is not None else (None, None)
                    if seg is None:
                        raise SessionAborted(f"no steady turn at {r_dps:+g} °/s about {axis_name} was seen")
                    if len(seg) < need // 2:
                        raise SessionAborted(f"the turn at {r_dps:+g} °/s about {axis_name} was too short or unsteady")
                    segments.append((seg, np.array(axis), np.radians(r_dps), None, seg_acc.mean(axis=0)))
                    # let the table stop before the next turn
                    self._wait_still(2.0)
        return segments

    def _steady_turn(self, axis: np.ndarray, rate_rad_s: float, need: int, limit: int) -> np.ndarray | None:
        """The gyro samples (rad/s) of one steady turn (see _steady_turn_samples)."""
        got = self._steady_turn_samples(axis, rate_rad_s, need, limit)
        return None if got is None else got[1]

    def _steady_turn_samples(self, axis: np.ndarray, rate_rad_s: float, need: int,
                             limit: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The accelerometer (m/s², raw) and gyro (rad/s) samples of one steady turn: the first
        run of consecutive samples within 10 % of the table's rate about axis, up to `need` of
        them (or shorter when the turn ended first); None when none began within `limit`
        samples. Judged sample by sample: a block read after a busy moment may hold the whole
        turn and its ends. The accelerometer's share gives the specific force during the turn,
        for the gyro's g-sensitivity."""
        acc, gyr = np.zeros((0, 3)), np.zeros((0, 3))
        waited = 0
        while True:
            b = self.next_block()
            waited += len(b)
            a_si, g_si = b.si()
            acc, gyr = np.concatenate([acc, a_si]), np.concatenate([gyr, g_si])
            on = np.abs(gyr @ axis - rate_rad_s) < 0.1 * abs(rate_rad_s)
            while on.any():
                start = int(np.argmax(on))
                off = np.flatnonzero(~on[start:])
                stop = start + int(off[0]) if len(off) else len(on)
                if stop - start >= need:
                    return acc[start:start + need], gyr[start:start + need]
                if not len(off):
                    break                                           # still turning: read on
                if stop - start >= need // 2:
                    return acc[start:stop], gyr[start:stop]         # the turn ended early
                acc, gyr, on = acc[stop:], gyr[stop:], on[stop:]    # a blip at the band's edge
            if not on.any():
                acc, gyr = acc[-1:], gyr[-1:]                       # nothing of a turn yet
            if waited > limit:
                return None

    def _wait_still(self, timeout_s: float) -> None:
        from imubench.calib.stillness import StillnessDetector
        det = StillnessDetector(self.cfg.rate_hz, np.asarray(self.rest["noise_mps2"]), window_s=self.cfg.settle_s)
        waited = 0
        while waited < timeout_s * self.cfg.rate_hz:
            b = self.next_block()
            waited += len(b)
            _, gyr = b.si()
            st = det.update(b.si()[0])
            if st.state == "still" and np.abs(gyr.mean(axis=0)).max() < np.radians(2.0):
                return

    # ------------------------------------------------------- known-angle turns
    TURN_MOVING_DPS = 5.0            # above the rest bias: the board is turning

    def capture_known_turns(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """--gyro turns: for X, Y and Z up in turn, the board lies still, is turned by hand one
        full turn on the table about the vertical, and lies still again. Returns per turn the
        samples (accel m/s², gyro rad/s) from the rest before to the rest after; the turns are
        found in them by calib.turns.detect_turns and fitted in calib.fit.known_turns_fit."""
        from imubench.calib.stillness import StillnessDetector
        fs = self.cfg.rate_hz
        noise = np.asarray(self.rest["noise_mps2"])
        bias = np.mean(np.asarray(self.rest["gyro"]), axis=0) if self.rest.get("gyro") is not None else np.zeros(3)
        hold_n = int(self.cfg.hold_s * fs)
        out = []
        for i, (name, axis) in enumerate((("X", (1.0, 0, 0)), ("Y", (0, 1.0, 0)), ("Z", (0, 0, 1.0)))):
            self.ui.present_pose(f"+{name} up{TURN_POSE_SUFFIX}", np.array(axis), i, 3)
            det = StillnessDetector(fs, noise, window_s=self.cfg.settle_s)
            recent: list[SampleBlock] = []
            got: list[SampleBlock] = []
            phase, moved, waited, after_n = "settle", False, 0, 0
            while True:
                b = self.next_block()
                waited += len(b)
                acc, gyr = b.si()
                st = det.update(acc)
                quiet = np.abs(gyr - bias).max() < np.radians(self.TURN_MOVING_DPS)
                still = st.state == "still" and quiet
                if phase == "settle":
                    recent.append(b)
                    d = acc.mean(axis=0) / np.linalg.norm(acc.mean(axis=0))
                    if still and st.n >= hold_n and d @ np.array(axis) > np.cos(np.radians(DETECT_TOL_DEG)):
                        run = SampleBlock.concat(recent)
                        got = [run[len(run) - min(st.n, len(run)):]]
                        phase = "turn"
                        self.ui.present_known_turn(np.array(axis), TURN_DEG)
                        det.reset()
                    elif len(recent) > 200:
                        recent.pop(0)
                else:
                    got.append(b)
                    after_n = 0 if not quiet else after_n + len(b)
                    moved = moved or not quiet
                    if moved and still and min(st.n, after_n) >= hold_n:
                        break
                if self.cfg.pose_timeout_s is not None and waited > self.cfg.pose_timeout_s * fs:
                    raise SessionAborted(f"known-angle turn about {name}: no "
                                         + ("still attitude with " + name + " up" if phase == "settle" else
                                            "turn followed by a rest") + f" within {self.cfg.pose_timeout_s:g} s")
            blk = SampleBlock.concat(got)
            out.append(blk.si())
            self.ui.say(f"  turn about {name} captured ({len(blk) / fs:.1f} s from rest to rest)")
        return out
