"""Pose capture without a device (procedures/capture.py): sample blocks made from arrays are
fed to PoseCapture, as the session feeds what it reads."""
from __future__ import annotations

import numpy as np
import pytest
from imubench import units as U
from imubench.procedures.capture import PoseCapture
from imubench.procedures.config import SessionConfig
from imubench.procedures.errors import SessionAborted
from imubench.procedures.presenter import Presenter
from imubench.procedures.session import plan_for
from imubench.wire.decoder import SampleBlock

FS = 100
NOISE_MPS2 = 0.003


class Said(Presenter):
    def __init__(self):
        self.lines: list[str] = []
        self.events: list[tuple[str, str]] = []

    def say(self, text):
        self.lines.append(text)

    def pose_event(self, name, state, detail):
        self.events.append((name, state))


class Board:
    """Calibrated sample blocks of 1/20 s from a board held in a direction (with noise)."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.index = 0

    def hold(self, up, seconds: float, wobble_mps2: float = 0.0):
        up = np.asarray(up, float) / np.linalg.norm(up)
        for _ in range(int(round(seconds * 20))):
            n = FS // 20
            acc = up * U.G0_MPS2 + self.rng.normal(0, NOISE_MPS2, (n, 3))
            if wobble_mps2:
                acc += wobble_mps2 * np.sin(np.arange(n) + self.index)[:, None]
            yield _block(acc, self.index)
            self.index += n


def _block(acc: np.ndarray, start: int) -> SampleBlock:
    n = len(acc)
    z = np.zeros(n, np.uint8)
    return SampleBlock(calibrated=True, t_us=np.arange(start, start + n, dtype=np.int64) * (1_000_000 // FS),
                       sample_index=np.arange(start, start + n, dtype=np.int64), status=z, sensor_flags=z,
                       accel_temp_counts=np.full(n, 1885, np.uint16), gyro_temp_counts=np.zeros((n, 3), np.int16),
                       gyro_faults=np.zeros((n, 3), np.uint8), accel_status=z, accel_range_g=np.full(n, 2, np.uint8),
                       accel_mps2=acc.astype(np.float32), rate_rad_s=np.zeros((n, 3), np.float32))


def _capture(cfg, plan, ui=None, captured=()):
    return PoseCapture(cfg, [NOISE_MPS2] * 3, plan, plan_for("six"), set(captured), stream_no=3, ui=ui)


def _feed(cap, blocks):
    for b in blocks:
        rec = cap.feed(b)
        if rec is not None:
            return rec
    return None


def test_a_still_planned_attitude_is_captured_with_exactly_the_hold():
    cfg = SessionConfig(rate_hz=FS, settle_s=0.5, hold_s=1.0)
    board, ui = Board(), Said()
    cap = _capture(cfg, plan_for("six"), ui)
    tilt = np.array([0.02, -0.01, 1.0])                 # ~1.3° off +Z: still within the attitude
    rec = _feed(cap, board.hold(tilt, 5.0))
    assert rec is not None and rec.name == "+Z up (level)"
    assert rec.n == FS * 1                             # hold_s of samples, no more
    assert rec.stream == 3 and rec.stop_index - rec.start_index == rec.n
    d = np.asarray(rec.mean_mps2) / np.linalg.norm(rec.mean_mps2)
    assert np.degrees(np.arccos(d @ (tilt / np.linalg.norm(tilt)))) < 0.1
    assert abs(rec.angle_from_plan_deg - np.degrees(np.arccos(1 / np.linalg.norm(tilt)))) < 0.1
    assert abs(np.linalg.norm(rec.mean_mps2) / U.G0_MPS2 - 1.0) < 1e-3
    assert ("+Z up (level)", "capturing") in ui.events
    assert cap.feed(next(board.hold(tilt, 0.05))) is rec        # once captured, always the same


def test_an_attitude_between_the_planned_ones_is_named_and_waited_past():
    cfg = SessionConfig(rate_hz=FS, settle_s=0.5, hold_s=1.0)
    board, ui = Board(1), Said()
    cap = _capture(cfg, plan_for("six"), ui)
    assert _feed(cap, board.hold([1.0, 0.0, 1.0], 4.0)) is None     # 45° between +X and +Z
    assert any("no planned attitude" in s for s in ui.lines), ui.lines
    rec = _feed(cap, board.hold([1.0, 0.0, 0.0], 4.0))
    assert rec is not None and rec.name == "+X up (nose up)"


def test_an_attitude_already_captured_is_not_captured_again():
    cfg = SessionConfig(rate_hz=FS, settle_s=0.5, hold_s=1.0)
    board, ui = Board(2), Said()
    missing = [p for p in plan_for("six") if p[0] != "+Z up (level)"]
    cap = _capture(cfg, missing, ui, captured={"+Z up (level)"})
    assert _feed(cap, board.hold([0, 0, 1.0], 4.0)) is None
    assert any("already captured" in s for s in ui.lines), ui.lines


def test_no_still_attitude_within_the_timeout_stops_the_capture():
    cfg = SessionConfig(rate_hz=FS, settle_s=0.5, hold_s=1.0, pose_timeout_s=3.0)
    cap = _capture(cfg, plan_for("six"))
    with pytest.raises(SessionAborted, match="no still attitude from the plan within 3 s"):
        _feed(cap, Board(3).hold([0, 0, 1.0], 10.0, wobble_mps2=0.5))     # shaken: never still


def test_an_adaptive_hold_stops_once_the_mean_is_known_to_its_target():
    cfg = SessionConfig(rate_hz=FS, settle_s=0.5, adaptive=True)
    cfg.targets.hold_min_s, cfg.targets.hold_max_s = 1.0, 10.0
    rec = _feed(_capture(cfg, plan_for("six")), Board(4).hold([0, -1.0, 0], 12.0))
    assert rec is not None and rec.name == "-Y up (on its left side)"
    assert FS * 1.0 <= rec.n < FS * 10.0                # quiet data: well before the longest hold
    assert rec.sigma_norm_g is not None and rec.sigma_norm_g * 1e3 <= cfg.targets.pose_sigma_mg
