"""Temperature calibration: sweep the board over temperature, fit the bias and scale
temperature coefficients (imubench.analysis.thermal), write them to the device (which applies
them itself).

Model (docs/conventions.md), per axis k, ΔT_k = T_k − t_ref:
    v_k = (u_k − b_k − bias_tc_k·ΔT_k) / (1 + scale_tc_k·ΔT_k)        x = M⁻¹·v
T_k: the accelerometer's temperature for every accelerometer axis, each gyro's own temperature
for its gyro axis.

What a sweep measures at each temperature (RAW stream, nominal scaling, board still):
- gyro mean per axis at rest                → gyro bias(T) against that gyro's temperature
- accelerometer in poses; with both +k and −k up for an axis k:
      (u_k(+k) + u_k(−k))/2 = bias_k(T),   (u_k(+k) − u_k(−k))/2 = (1 + scale_tc_k·ΔT)·M_kk·g
  level only (+Z up): X/Y mean is their bias (they read ~0 g); Z gives b_z + M_zz·g, whose
  slope is bias_tc_z + scale_tc_z·g: put into bias_tc_z (right at level), scale_tc_z = 0.
- turntable (if available): ±rate about each axis, (ω(+) − ω(−))/2 = (1 + scale_tc·ΔT)·S·rate.
  Without a turntable the gyro scale_tc stays 0.

Before each temperature is measured the sensors' own temperatures must have settled
(wait_settled: |dT/dt| from a straight line over a sliding window below a limit). Everything
measured is kept in DIR/thermal.json (ThermalRecord), rewritten atomically after every
temperature point and every later step, so an interrupted sweep keeps what it measured.
"""
from __future__ import annotations

import collections
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench import units as U
from imubench.analysis.thermal import AXES, POSES, TempPoint, apply_tempcos, fit_sweep
from imubench.errors import ImubenchError
from imubench.results.thermal import (
    ThermalRecord,
    drift_json,
    fit_json,
    format_drift,
    format_fit,
)
from imubench.wire.board_parts import BoardParts, coarsest_temp_step_c
from imubench.wire.ids import device_identity, parts_text
from imubench.wire.protocol_gen import Params, ParamsWhich

# ------------------------------------------------------------------ the fit


# ------------------------------------------------------------------ measurements


@dataclass
class Hooks:
    """What the bench can do. set_temperature(c): bring the board to c °C (None: the user
    waits for the ambient; `ready(c)` is called instead); it may return before the sensors
    got there (a chamber ramping): the sweep waits for their temperatures to settle. orient(
    direction (3,)): put the board with the specific force along direction (None: it stays
    level, +Z up). turn(axis index, rate_dps, duration_s): spin about a board axis, returning
    when done (None: no turntable)."""
    set_temperature: Callable[[float], None] | None = None
    orient: Callable[[np.ndarray], None] | None = None
    turn: Callable[[int, float, float], None] | None = None
    ready: Callable[[float | None], None] | None = None
    say: Callable[[str], None] = lambda s: None


def sim_hooks(vb, say: Callable[[str], None] = lambda s: None, ramp_c_per_s: float = 0.0) -> Hooks:
    """Hooks driving a VirtualBench: climate chamber, orientation, turntable. With
    ramp_c_per_s > 0 the chamber ramps linearly towards the set point and set_temperature
    returns at once (the sweep's settling wait sees the ramp); 0: the temperature jumps."""
    def set_t(c):
        if ramp_c_per_s > 0:
            vb.set_temperature(c, ramp_c_per_s=ramp_c_per_s)
        else:
            vb.set_temperature(c)
            vb.wait(0.05)

    def orient(d):
        vb.set_orientation(gravity=[float(v) for v in d])

    def turn(axis, rate_dps, duration_s):
        vb.rotate(AXES[axis] if rate_dps >= 0 else "-" + AXES[axis], abs(rate_dps), duration_s, wait=True)
        vb.wait(0.1)

    return Hooks(set_temperature=set_t, orient=orient, turn=turn, say=say)


# ------------------------------------------------------------------ thermal settling
@dataclass(frozen=True)
class Settling:
    """Measure only when every sensor's temperature (accelerometer, gyro X/Y/Z) changes slower than
    rate_c_per_min, the rate being the slope of a straight line through the last window_s
    seconds (device time) of its readings; give up after timeout_s (device time)."""
    rate_c_per_min: float = 0.1
    window_s: float = 300.0
    timeout_s: float = 7200.0

    def __post_init__(self):
        if not (self.rate_c_per_min > 0 and self.window_s > 0 and self.timeout_s >= self.window_s):
            raise ValueError(f"settling: need rate > 0, window > 0 and timeout ≥ window (got {self.rate_c_per_min} "
                             f"°C/min, {self.window_s} s, timeout {self.timeout_s} s)")


DEFAULT_SETTLING = Settling()


class SettleTimeout(ImubenchError):
    """The sensors' temperatures did not settle in time; the message says where they were
    and how fast they moved (also as temp_c and rate_c_per_min: accelerometer, gyro X, Y, Z)."""

    def __init__(self, msg: str, target_c: float | None, temp_c, rate_c_per_min):
        super().__init__(msg)
        self.target_c = target_c
        self.temp_c = [float(v) for v in temp_c]
        self.rate_c_per_min = [float(v) for v in rate_c_per_min]


SELF_HEAT_ALLOWANCE_C = 5.0    # how far a powered die may sit above the chamber's air (the virtual
                               # part draws 2-5 °C for the gyros, 0.5-2.5 °C for the accelerometer)
# one LSB of the coarsest part's temperature (protocol/parts.toml; ADXRS450: 0.2 °C, ADXL355: 1/9.05 °C),
# for what is said before a device has told which parts it has
TEMP_RESOLUTION_C = coarsest_temp_step_c()


def wait_settled(dev, settle: Settling, rate_hz: int = 200, target_c: float | None = None,
                 say: Callable[[str], None] = lambda s: None, report_every_s: float = 30.0,
                 parts: BoardParts | None = None) -> dict:
    """On a running stream, read the sensors' temperatures until all four change slower than
    settle.rate_c_per_min over a full window of settle.window_s (device time). Returns
    {"waited_s", "window_s", "limit_c_per_min", "rate_c_per_min" (4: accelerometer, gyro X, Y, Z),
    "temp_c" (4, the latest readings)}. Raises SettleTimeout after settle.timeout_s of device
    time, naming the temperatures reached and their rates. While it waits it says where the
    temperatures are every report_every_s of WALL time (a person watching; a fast virtual
    chamber settles before the first report), and once when they have settled. parts: the
    board's (wire.board_parts; None: asked of the device), named with their temperatures."""
    if parts is None:
        parts = BoardParts.of_info(dev.info())
    chunk_s = min(1.0, settle.window_s / 10.0)
    chunk_n = max(1, round(rate_hz * chunk_s))
    dev.discard_buffered()
    win = collections.deque()                     # (t0 s, t_mean s, temps (4,)) per chunk
    t_begin = None
    said_wall = time.monotonic()
    rates = np.full(4, np.nan)
    while True:
        b = dev.read(n_samples=chunk_n)
        t = b.t_us.astype(np.float64) * 1e-6
        at, gt = _temps(b)
        win.append((t[0], t.mean(), np.r_[at, gt]))
        t_now = t[-1]
        if t_begin is None:
            t_begin = t[0]
        while len(win) >= 2 and win[1][0] <= t_now - settle.window_s:
            win.popleft()
        covered = t_now - win[0][0] >= settle.window_s * (1 - 1e-6)
        temps = np.array([w[2] for w in win])
        if len(win) >= 2:
            tm = np.array([w[1] for w in win])
            rates = np.polyfit(tm - tm[0], temps, 1)[0] * 60.0
        now_c = win[-1][2]                         # the latest chunk's mean
        if covered and np.all(np.abs(rates) < settle.rate_c_per_min):
            info = {"waited_s": float(t_now - t_begin), "window_s": settle.window_s,
                    "limit_c_per_min": settle.rate_c_per_min, "rate_c_per_min": [float(r) for r in rates],
                    "temp_c": [float(v) for v in now_c]}
            say(f"  settled after {t_now - t_begin:.0f} s: {_fmt_temps(now_c, parts)} "
                f"(|dT/dt| ≤ {np.max(np.abs(rates)):.3f} °C/min over {settle.window_s:g} s)")
            return info
        if t_now - t_begin > settle.timeout_s:
            at_c = f" at the set point {target_c:g} °C" if target_c is not None else ""
            raise SettleTimeout(
                f"temperature not settled{at_c} within {settle.timeout_s:g} s: the sensors reached "
                f"{_fmt_temps(now_c, parts)}, changing at {_fmt_rates(rates, parts)} (limit {settle.rate_c_per_min:g} °C/min "
                f"over {settle.window_s:g} s)", target_c, now_c, rates)
        if time.monotonic() - said_wall >= report_every_s:
            said_wall = time.monotonic()
            say(f"  settling: {_fmt_temps(now_c, parts)}, {_fmt_rates(rates, parts)} after {t_now - t_begin:.0f} s")


def _fmt_temps(c, parts: BoardParts) -> str:
    return f"{parts.accel.name} {c[0]:.2f} °C, gyros ({parts.gyro_words}) {c[1]:.2f}/{c[2]:.2f}/{c[3]:.2f} °C"


def _fmt_rates(r, parts: BoardParts) -> str:
    return "[" + ", ".join(f"{v:+.3f}" for v in r) + f"] °C/min ({parts.accel.name}, gyro X/Y/Z)"


def _settled(dev, n: int):
    dev.discard_buffered()
    dev.read(n_samples=max(20, n // 20))          # samples in flight from before the change
    return dev.read(n_samples=n)


def _mean_sigma(x: np.ndarray):
    return x.mean(axis=0), x.std(axis=0, ddof=1) / np.sqrt(len(x))


def _temps(b):
    return (float(U.accel_temp_counts_to_c(b.accel_temp_counts, range_g=b.accel_range_g).mean()),
            U.gyro_temp_counts_to_c(b.gyro_temp_counts).mean(axis=0))


def measure_point(dev, hooks: Hooks, target_c: float | None, n: int = 2000,
                  poses: Sequence[str] = ("+z",), turn_rate_dps: float = 90.0) -> TempPoint:
    """One temperature step on a RAW stream that is running."""
    gyro_all, accel, atemps, gtemps, times = [], {}, [], [], []
    for name in poses:
        if hooks.orient is not None:
            hooks.orient(np.array(POSES[name], dtype=float))
        elif name != "+z":
            continue
        b = _settled(dev, n)
        times += [int(b.t_us[0]), int(b.t_us[-1])]
        a, g = b.si()
        accel[name] = _mean_sigma(a)
        gyro_all.append(g)
        at, gt = _temps(b)
        atemps.append(at)
        gtemps.append(gt)
    if hooks.orient is not None and list(poses) != ["+z"]:
        hooks.orient(np.array(POSES["+z"], dtype=float))
    turns = {}
    if hooks.turn is not None:
        dur = 360.0 / turn_rate_dps                      # a full turn: back where it started
        for ax in range(3):
            half = []
            for sgn in (1.0, -1.0):
                dev.discard_buffered()
                hooks.turn(ax, sgn * turn_rate_dps, dur)
                b = dev.read(duration_s=0.05)
                times += [int(b.t_us[0]), int(b.t_us[-1])]
                w = b.si()[1][:, ax]
                target = sgn * turn_rate_dps * U.DEG
                sel = np.flatnonzero(np.abs(w - target) < 0.1 * abs(target))
                if len(sel) < 20:
                    raise RuntimeError(f"turntable: only {len(sel)} samples at speed about {AXES[ax]}")
                sel = sel[5:-5]                           # away from the start and end of the move
                half.append(_mean_sigma(w[sel]))
            s = (half[0][0] - half[1][0]) / 2.0
            ss = np.hypot(half[0][1], half[1][1]) / 2.0
            turns[ax] = (float(s), float(ss))
    g = np.concatenate(gyro_all)
    gm, gs = _mean_sigma(g)
    return TempPoint(target_c, float(np.mean(atemps)), np.mean(gtemps, axis=0), gm, gs, accel, turns,
                     t_first_us=min(times), t_last_us=max(times))


def _go_to(dev, hooks: Hooks, c: float | None, settle: Settling | None, rate_hz: int,
           parts: BoardParts | None = None) -> dict | None:
    """Bring the board to c (set point, or the user) and, with settle, wait for the sensors."""
    if hooks.set_temperature is not None and c is not None:
        hooks.set_temperature(c)
    elif hooks.ready is not None:
        hooks.ready(c)
    if settle is None:
        return None
    return wait_settled(dev, settle, rate_hz=rate_hz, target_c=c, say=hooks.say, parts=parts)


def sweep(dev, temps: Sequence[float | None], hooks: Hooks, n: int = 2000,
          poses: Sequence[str] = ("+z", "-z"), rate_hz: int = 200, turntable: bool = True,
          check_tol_c: float | None = 2.0, settle: Settling | None = DEFAULT_SETTLING,
          on_point: Callable[[TempPoint], None] | None = None) -> list[TempPoint]:
    """At each temperature (set by hooks.set_temperature, or waited for by the user), wait
    until the sensors' temperatures have settled (settle; None: measure at once), then
    measure a TempPoint on a RAW stream at rate_hz; on_point(point) is called with each
    point as soon as it is measured (to save it). With check_tol_c and a set_temperature
    hook, the sensors' own temperature outputs must follow the set point within that
    tolerance (above it: that plus SELF_HEAT_ALLOWANCE_C, a powered die's self-heating)."""
    h = hooks if turntable else Hooks(hooks.set_temperature, hooks.orient, None, hooks.ready, hooks.say)
    out = []
    parts = BoardParts.of_info(dev.info())      # the parts it reported: named in what is said
    dev.start_stream(rate_hz=rate_hz, calibrated=False)
    try:
        for c in temps:
            st = _go_to(dev, h, c, settle, rate_hz, parts)
            p = measure_point(dev, h, c, n=n, poses=poses)
            p.settle = st
            if check_tol_c is not None and h.set_temperature is not None and c is not None:
                dev_t = np.r_[p.accel_temp_c, p.gyro_temp_c]
                off = dev_t - c               # a powered die sits above the air: self-heating
                if np.any(off < -check_tol_c) or np.any(off > check_tol_c + SELF_HEAT_ALLOWANCE_C):
                    raise RuntimeError(f"set {c} °C but the sensors report {np.round(dev_t, 2).tolist()} °C "
                                       f"(expected {c - check_tol_c:g} to {c + check_tol_c + SELF_HEAT_ALLOWANCE_C:g} °C: "
                                       f"within {check_tol_c:g} °C, or up to {SELF_HEAT_ALLOWANCE_C:g} °C more "
                                       f"above it from self-heating)")
            h.say(f"  {p.accel_temp_c:6.2f} °C (gyros {np.round(p.gyro_temp_c, 2).tolist()}): "
                  f"gyro {np.round(U.rad_s_to_dps(p.gyro_rest), 4).tolist()} °/s, "
                  f"accel +Z {np.round(U.mps2_to_mg(p.accel['+z'][0]), 3).tolist()} mg")
            out.append(p)
            if on_point is not None:
                on_point(p)
    finally:
        dev.stop_stream()
    return out


# ------------------------------------------------------------------ fitting a sweep


# ------------------------------------------------------------------ drift of the calibrated output
def measure_drift(dev, temps: Sequence[float | None], hooks: Hooks, n: int = 2000, rate_hz: int = 200,
                  settle: Settling | None = DEFAULT_SETTLING) -> dict:
    """Stream CALIBRATED, level and still, at each temperature (after the sensors settled,
    as in sweep); the device's corrected means and their drift (max − min over the sweep)
    per axis: accel x/y/z and |a| (m/s²), gyro x/y/z (rad/s)."""
    acc, gyr, tc = [], [], []
    if hooks.orient is not None:
        hooks.orient(np.array(POSES["+z"], dtype=float))
    parts = BoardParts.of_info(dev.info())
    dev.start_stream(rate_hz=rate_hz, calibrated=True)
    try:
        for c in temps:
            _go_to(dev, hooks, c, settle, rate_hz, parts)
            b = _settled(dev, n)
            a = b.accel_mps2.astype(np.float64)
            acc.append(np.r_[a.mean(axis=0), np.linalg.norm(a, axis=1).mean()])
            gyr.append(b.rate_rad_s.astype(np.float64).mean(axis=0))
            tc.append(float(U.accel_temp_counts_to_c(b.accel_temp_counts, range_g=b.accel_range_g).mean()))
    finally:
        dev.stop_stream()
    acc, gyr = np.array(acc), np.array(gyr)
    return {"set_c": [None if c is None else float(c) for c in temps], "accel_temp_c": tc,
            "accel_mean_mps2": acc, "gyro_mean_rad_s": gyr,
            "accel_drift_mps2": np.ptp(acc, axis=0),      # x, y, z, |a|
            "gyro_drift_rad_s": np.ptp(gyr, axis=0)}


# ------------------------------------------------------------------ thermal.json


def _device_json(dev) -> dict:
    return device_identity(dev.info())


# ------------------------------------------------------------------ command line


def write_params(dev, new: Params, say: Callable[[str], None] = lambda s: None) -> dict:
    """set_params, bit-exact read-back, save, reboot, bit-exact read-back of the active
    parameters after the reboot (imubench.procedures.session.write_verified, as `imubench calibrate`
    does); on any failure the previous parameters are put back (and saved again if they had
    been saved) and the error raised. Returns {"generation", "steps", "verified": True}."""
    from imubench.procedures.writeback import write_verified
    r = write_verified(dev, new, say=say)
    return {"generation": int(r["generation"]), "steps": list(r["steps"]), "verified": True}


def _is_active(dev, p: Params) -> bool | None:
    """Whether the device's active parameters are p, bit-exactly (None: cannot tell)."""
    try:
        return Params.STRUCT.pack(*dev.get_params(ParamsWhich.ACTIVE).params.values()) == Params.STRUCT.pack(*p.values())
    except Exception:  # noqa: BLE001 - the device may be gone; say so rather than guess
        return None


def run_thermal(dev, out_dir, temps: Sequence[float | None], hooks: Hooks, *, n: int = 2000,
                poses: Sequence[str] = ("+z",), turntable: bool = False, t_ref_c: float | None = None,
                write: bool = False, settle: Settling | None = DEFAULT_SETTLING, rate_hz: int = 200,
                config: dict | None = None) -> dict:
    """The whole run of `imubench thermal` on an open device, recorded in out_dir/thermal.json
    (ThermalRecord): sweep (each point saved as soon as it is measured), fit, and with write
    the drift before, the verified write-back (write_params) and the drift after. On any
    error (or Ctrl-C) the file keeps what was done, with status "failed" and the error, and
    the error is raised. Returns the final content of thermal.json."""
    say = hooks.say
    cfg = {"temps_c": list(temps), "samples_per_measurement": n, "rate_hz": rate_hz, "poses": list(poses),
           "turntable": turntable, "turn_rate_dps": 90.0 if turntable else None, "write": write,
           "settle_rate_c_per_min": None if settle is None else settle.rate_c_per_min,
           "settle_s": None if settle is None else settle.window_s,
           "settle_timeout_s": None if settle is None else settle.timeout_s, **(config or {})}
    rec = ThermalRecord(out_dir, cfg)
    say(f"recording in {rec.path}")
    try:
        old = dev.get_params(ParamsWhich.ACTIVE).params
        t_ref = float(old.accel_t_ref_c) if t_ref_c is None else float(t_ref_c)
        rec.update(device=_device_json(dev), t_ref_c=t_ref, stage="sweep")
        say(f"parts: {parts_text(rec.data['device']['parts'])}")
        points = sweep(dev, temps, hooks, n=n, poses=poses, rate_hz=rate_hz, turntable=turntable,
                       settle=settle, on_point=rec.add_point)
        fit = fit_sweep(points, t_ref)
        rec.update(stage="fitted", **fit_json(fit))
        say(format_fit(fit))
        if write:
            new = apply_tempcos(old, fit, t_ref)
            rec.update(stage="drift before")
            say("drift of the device's calibrated output before writing (the same temperatures):")
            before = measure_drift(dev, temps, hooks, n=n, rate_hz=rate_hz, settle=settle)
            rec.update(stage="write", drift_before=drift_json(before))
            try:
                wb = write_params(dev, new, say=say)
            except Exception as e:
                rec.update(write={"generation": None, "steps": [], "verified": False, "error": str(e),
                                  "previous_restored": _is_active(dev, old)})
                raise
            rec.update(stage="drift after", write=wb)
            say(f"written, read back, saved, rebooted, read back again (generation {wb['generation']})")
            say("drift of the device's calibrated output after writing:")
            after = measure_drift(dev, temps, hooks, n=n, rate_hz=rate_hz, settle=settle)
            rec.update(drift_after=drift_json(after))
            say(format_drift(before, after))
        else:
            say("(not written: give --write)")
        rec.update(status="done", stage="done")
    except BaseException as e:
        rec.update(status="failed", error=f"{type(e).__name__}: {e}" if str(e) else type(e).__name__)
        raise
    say(f"saved {rec.path}")
    return rec.data


# truth of the virtual device with --sim (within the device's limits)
SIM_ACCEL_TRUTH = {"bias_tc": [2e-3, -1.5e-3, 1e-3], "scale_tc": [0.0, 0.0, 2e-4], "rw_k": [0.0] * 3}
SIM_GYRO_TRUTH = [{"bias_tempco_rad_s_per_c": v * U.DEG, "scale_tempco_per_c": s, **GYRO_NO_DRIFT}
                  for v, s in ((0.01, 1e-4), (-0.008, -5e-5), (0.006, 0.0))]
