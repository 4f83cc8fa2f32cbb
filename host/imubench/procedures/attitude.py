"""Attitude on a device: the turntable step test on the virtual bench, and the live view.

    tilt_step_experiment(bench, dev, ...)   steps the virtual turntable, streams the device's
                                            calibrated output, runs the filters over it
    live(dev, filters, ...)                 streams and yields the filters' angles per block

The filters and the tilt geometry are imubench.analysis.tilt; the table and plot
imubench.results.attitude. docs/attitude.md.
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from imubench.analysis.tilt import (
    Complementary,
    KalmanTilt,
    RCLowPass,
    _TiltFilter,
    accel_tilt,
    part_noise,
    settling_time,
)
from imubench.wire.board_parts import BoardParts
from imubench.wire.decoder import SampleBlock


@dataclass
class StepResult:
    """One tilt step on the turntable. Times in s of device time."""

    axis: str               # "roll" or "pitch"
    target_deg: float       # attitude after the step (simulator truth)
    t_step: float           # motion started
    t_end: float            # dwell ended
    settle_s: dict = field(default_factory=dict)      # filter -> settling time
    error_deg: dict = field(default_factory=dict)     # filter -> mean(angle) − target over the window


def _dev_time(bench) -> float:
    return float(bench.status()["time_us"]) * 1e-6


def tilt_step_experiment(bench, dev, angles: Sequence[float] = (-20, -10, 0, 10, 20),
                         axes: Sequence[str] = ("roll", "pitch"), rate_hz: int = 200,
                         rate_dps: float = 20.0, dwell_s: float = 6.0, avg_s: float = 3.0,
                         band_deg: float = 0.05, filters: Sequence[_TiltFilter] | None = None) -> dict:
    """Step the virtual turntable through `angles` about each axis (roll: board X, pitch:
    board Y, starting level), turning at rate_dps, dwelling dwell_s after each move; stream
    the device's calibrated output at rate_hz and run the filters over it.

    Returns {"t", "accel", "gyro", "angles": {name: (roll, pitch)}, "steps": [StepResult],
    "band_deg", "filters": [names]}. A step's static error is the mean over the last avg_s of
    its dwell minus the simulator's roll/pitch; its settling time counts from the motion start.
    """
    if filters is None:         # the Kalman filter tuned to the parts the device reported
        noise = part_noise(BoardParts.of_info(dev.info()))
        filters = [RCLowPass(10), RCLowPass(40), KalmanTilt(**noise), Complementary(0.1), Complementary(0.5)]
    filters = list(filters)
    steps: list[StepResult] = []
    bench.set_orientation(roll_deg=0, pitch_deg=0, yaw_deg=0)
    dev.start_stream(rate_hz=rate_hz, calibrated=True)
    try:
        bench.wait(2.0)
        for axis in axes:
            ax = {"roll": "x", "pitch": "y"}[axis]
            cur = 0.0
            for tgt in angles:
                delta = float(tgt) - cur
                t_step = _dev_time(bench)
                if delta:       # the simulator reports the device time the motion started
                    r = bench.rotate(ax if delta > 0 else "-" + ax, rate_dps, abs(delta) / rate_dps)
                    t_step = float(r.get("t_start_us", t_step * 1e6)) * 1e-6
                bench.wait(dwell_s)
                st = bench.status()
                t_end = float(st["time_us"]) * 1e-6
                steps.append(StepResult(axis, float(st[f"{axis}_deg"]), t_step, t_end))
                cur = float(tgt)
            bench.rotate(ax if cur < 0 else "-" + ax, rate_dps, abs(cur) / rate_dps)  # back to level
            bench.wait(1.0)
        bench.wait(0.5)
        block = dev.read(duration_s=0.3)
        more = dev.link.take_samples(True)
        if more is not None and len(more):
            block = SampleBlock.concat([block, more])
    finally:
        dev.stop_stream()
    t = block.t_us.astype(np.float64) * 1e-6
    acc = block.accel_mps2.astype(np.float64)
    gyr = block.rate_rad_s.astype(np.float64)
    out = {"t": t, "accel": acc, "gyro": gyr, "angles": {}, "steps": steps, "band_deg": band_deg,
           "filters": [f.name for f in filters], "rate_hz": rate_hz}
    out["angles"]["accel"] = accel_tilt(acc)
    for f in filters:
        out["angles"][f.name] = f.run(acc, gyr, rate_hz)
    for s in steps:
        win = (t >= s.t_step) & (t <= s.t_end)
        avg = (t > s.t_end - avg_s) & (t <= s.t_end)
        k = 0 if s.axis == "roll" else 1
        for name in ["accel"] + out["filters"]:
            ang = out["angles"][name][k]
            s.error_deg[name] = float(np.mean(ang[avg]) - s.target_deg) if avg.any() else math.nan
            s.settle_s[name] = settling_time(t[win], ang[win], s.target_deg, band_deg, s.t_step)
    return out


def live(dev, filters: Sequence[_TiltFilter], rate_hz: int, duration_s: float | None = None) -> Iterator[tuple]:
    """Stream the device's calibrated output at rate_hz and run the filters over it, block by
    block: yields (block, t_s since the first sample, [(roll_deg, pitch_deg) per filter])
    until duration_s of DEVICE time has been received (the last block cut there), or forever:
    a virtual device at any speed gives as many seconds of data as a real one. The stream is
    stopped at the end, also when the caller stops early or is interrupted."""
    dt = 1.0 / rate_hz
    dev.start_stream(rate_hz=rate_hz, calibrated=True)
    try:
        t0_us = None
        for block in dev.stream():
            if t0_us is None:
                t0_us = int(block.t_us[0])
            t_s = (block.t_us - t0_us) * 1e-6
            last = duration_s is not None and t_s[-1] >= duration_s
            if last:
                keep = int(np.searchsorted(t_s, duration_s, side="right"))
                block, t_s = block[:max(keep, 1)], t_s[:max(keep, 1)]
            acc = block.accel_mps2.astype(np.float64)
            gyr = block.rate_rad_s.astype(np.float64)
            yield block, t_s, [f.update(acc, gyr, dt) for f in filters]
            if last:
                break
    finally:
        try:
            dev.stop_stream()
        except Exception:  # noqa: BLE001 - the link may be gone; the caller reports its own error
            pass
