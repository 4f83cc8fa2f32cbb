"""Temperature calibration: sweep the board over temperature, fit the bias and scale
temperature coefficients, write them to the device (which applies them itself).

Model (docs/conventions.md), per axis k, ΔT_k = T_k − t_ref:
    v_k = (u_k − b_k − bias_tc_k·ΔT_k) / (1 + scale_tc_k·ΔT_k)        x = M⁻¹·v
T_k: the ADXL355 temperature for every accelerometer axis, each ADXRS450's own temperature
for its gyro axis.

What a sweep measures at each temperature (RAW stream, nominal scaling, board still):
- gyro mean per axis at rest                → gyro bias(T) against that gyro's temperature
- accelerometer in poses; with both +k and −k up for an axis k:
      (u_k(+k) + u_k(−k))/2 = bias_k(T),   (u_k(+k) − u_k(−k))/2 = (1 + scale_tc_k·ΔT)·M_kk·g
  level only (+Z up): X/Y mean is their bias (they read ~0 g); Z gives b_z + M_zz·g, whose
  slope is bias_tc_z + scale_tc_z·g: put into bias_tc_z (right at level), scale_tc_z = 0.
- turntable (if available): ±rate about each axis, (ω(+) − ω(−))/2 = (1 + scale_tc·ΔT)·S·rate.
  Without a turntable the gyro scale_tc stays 0.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from . import params as PR
from . import units as U
from .protocol_gen import Params, ParamsWhich

__all__ = [
    "Hooks",
    "TempPoint",
    "ThermalFit",
    "apply_tempcos",
    "fit_sweep",
    "fit_tempco",
    "main_thermal",
    "measure_drift",
    "sim_hooks",
    "sweep",
]

AXES = "xyz"
POSES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
         "+z": (0, 0, 1), "-z": (0, 0, -1)}


# ------------------------------------------------------------------ the fit
def fit_tempco(temps_c, values, sigmas=None, t_ref_c: float = 25.0):
    """Weighted straight line per axis: values[:, k] = intercept_k + coef_k·(T − t_ref).

    temps_c (k,) or (k, 3) (one temperature per axis), values (k, 3), sigmas (k, 3) 1-sigma
    of each value or None (unweighted; the scatter about the line sets the sigmas).
    Returns coef (3,), intercept (3,) (the value at t_ref) and cov (3, 2, 2) of
    (coef, intercept) per axis; 1-sigma of coef_k is sqrt(cov[k, 0, 0]).
    With sigmas the covariance is the absolute one, inflated by the reduced chi² when that
    exceeds 1 (points scattering more than their sigmas say)."""
    y = np.asarray(values, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 3:
        raise ValueError("values must be (k, 3)")
    t = np.asarray(temps_c, dtype=np.float64)
    if t.ndim == 1:
        t = np.repeat(t[:, None], 3, axis=1)
    if t.shape != y.shape:
        raise ValueError("temps_c must be (k,) or (k, 3) matching values")
    k = len(y)
    if k < 2:
        raise ValueError("need at least two temperatures")
    coef, icpt, cov = np.zeros(3), np.zeros(3), np.zeros((3, 2, 2))
    for a in range(3):
        x = t[:, a] - t_ref_c
        if np.ptp(x) == 0:
            raise ValueError(f"axis {AXES[a]}: all points at the same temperature")
        A = np.column_stack([x, np.ones(k)])
        w = np.ones(k) if sigmas is None else 1.0 / np.asarray(sigmas, dtype=np.float64)[:, a] ** 2
        N = A.T @ (A * w[:, None])
        C = np.linalg.inv(N)
        p = C @ (A.T @ (w * y[:, a]))
        r = y[:, a] - A @ p
        dof = k - 2
        chi2 = float(np.sum(w * r * r)) / dof if dof > 0 else 0.0
        if sigmas is None or chi2 > 1.0:
            C = C * chi2
        coef[a], icpt[a], cov[a] = p[0], p[1], C
    return coef, icpt, cov


# ------------------------------------------------------------------ measurements
@dataclass
class TempPoint:
    """What one temperature step measured (nominally scaled SI, means and their 1-sigma)."""
    target_c: float | None
    accel_temp_c: float
    gyro_temp_c: np.ndarray                       # (3,)
    gyro_rest: np.ndarray                         # (3,) rad/s
    gyro_rest_sigma: np.ndarray                   # (3,)
    accel: dict = field(default_factory=dict)     # pose name -> (mean (3,), sigma (3,)) m/s²
    turns: dict = field(default_factory=dict)     # axis index -> (scale (rad/s, at +rate), sigma)


@dataclass
class Hooks:
    """What the bench can do. set_temperature(c): bring the board to c °C (None: the user
    waits for the ambient; `ready(c)` is called instead). orient(direction (3,)): put the
    board with the specific force along direction (None: it stays level, +Z up). turn(axis
    index, rate_dps, duration_s): spin about a board axis, returning when done (None: no
    turntable)."""
    set_temperature: Callable[[float], None] | None = None
    orient: Callable[[np.ndarray], None] | None = None
    turn: Callable[[int, float, float], None] | None = None
    ready: Callable[[float | None], None] | None = None
    say: Callable[[str], None] = lambda s: None


def sim_hooks(vb, say: Callable[[str], None] = lambda s: None) -> Hooks:
    """Hooks driving a VirtualBench: climate chamber (at once, no ramp), orientation, turntable."""
    def set_t(c):
        vb.set_temperature(c)
        vb.wait(0.05)

    def orient(d):
        vb.set_orientation(gravity=[float(v) for v in d])

    def turn(axis, rate_dps, duration_s):
        vb.rotate(AXES[axis] if rate_dps >= 0 else "-" + AXES[axis], abs(rate_dps), duration_s, wait=True)
        vb.wait(0.1)

    return Hooks(set_temperature=set_t, orient=orient, turn=turn, say=say)


def _settled(dev, n: int):
    dev.discard_buffered()
    dev.read(n_samples=max(20, n // 20))          # samples in flight from before the change
    return dev.read(n_samples=n)


def _mean_sigma(x: np.ndarray):
    return x.mean(axis=0), x.std(axis=0, ddof=1) / np.sqrt(len(x))


def _temps(b):
    return (float(U.accel_temp_counts_to_c(b.accel_temp_counts).mean()),
            U.gyro_temp_counts_to_c(b.gyro_temp_counts).mean(axis=0))


def measure_point(dev, hooks: Hooks, target_c: float | None, n: int = 2000,
                  poses: Sequence[str] = ("+z",), turn_rate_dps: float = 90.0) -> TempPoint:
    """One temperature step on a RAW stream that is running."""
    gyro_all, accel, atemps, gtemps = [], {}, [], []
    for name in poses:
        if hooks.orient is not None:
            hooks.orient(np.array(POSES[name], dtype=float))
        elif name != "+z":
            continue
        b = _settled(dev, n)
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
    return TempPoint(target_c, float(np.mean(atemps)), np.mean(gtemps, axis=0), gm, gs, accel, turns)


def sweep(dev, temps: Sequence[float | None], hooks: Hooks, n: int = 2000,
          poses: Sequence[str] = ("+z", "-z"), rate_hz: int = 200, turntable: bool = True,
          check_tol_c: float | None = 2.0) -> list[TempPoint]:
    """At each temperature (set by hooks.set_temperature, or waited for by the user), measure
    a TempPoint on a RAW stream at rate_hz. With check_tol_c and a set_temperature hook, the
    sensors' own temperature outputs must follow the set point within that tolerance."""
    h = hooks if turntable else Hooks(hooks.set_temperature, hooks.orient, None, hooks.ready, hooks.say)
    out = []
    dev.start_stream(rate_hz=rate_hz, calibrated=False)
    try:
        for c in temps:
            if h.set_temperature is not None and c is not None:
                h.set_temperature(c)
            elif h.ready is not None:
                h.ready(c)
            p = measure_point(dev, h, c, n=n, poses=poses)
            if check_tol_c is not None and h.set_temperature is not None and c is not None:
                dev_t = np.r_[p.accel_temp_c, p.gyro_temp_c]
                if np.any(np.abs(dev_t - c) > check_tol_c):
                    raise RuntimeError(f"set {c} °C but the sensors report {np.round(dev_t, 2).tolist()} °C")
            h.say(f"  {p.accel_temp_c:6.2f} °C (gyros {np.round(p.gyro_temp_c, 2).tolist()}): "
                  f"gyro {np.round(U.rad_s_to_dps(p.gyro_rest), 4).tolist()} °/s, "
                  f"accel +Z {np.round(U.mps2_to_mg(p.accel['+z'][0]), 3).tolist()} mg")
            out.append(p)
    finally:
        dev.stop_stream()
    return out


# ------------------------------------------------------------------ fitting a sweep
@dataclass
class ThermalFit:
    t_ref_c: float
    accel_bias_tc: np.ndarray          # m/s²/°C
    accel_bias_tc_sigma: np.ndarray
    accel_scale_tc: np.ndarray         # 1/°C
    accel_scale_tc_sigma: np.ndarray
    gyro_bias_tc: np.ndarray           # rad/s/°C
    gyro_bias_tc_sigma: np.ndarray
    gyro_scale_tc: np.ndarray
    gyro_scale_tc_sigma: np.ndarray
    notes: list = field(default_factory=list)


def fit_sweep(points: Sequence[TempPoint], t_ref_c: float = 25.0) -> ThermalFit:
    notes = []
    ta = np.array([p.accel_temp_c for p in points])
    tg = np.array([p.gyro_temp_c for p in points])
    gb, _, gcov = fit_tempco(tg, np.array([p.gyro_rest for p in points]),
                             np.array([p.gyro_rest_sigma for p in points]), t_ref_c)
    a_btc, a_btc_s = np.zeros(3), np.zeros(3)
    a_stc, a_stc_s = np.zeros(3), np.zeros(3)
    have = set(points[0].accel)
    for k in range(3):
        plus, minus = f"+{AXES[k]}", f"-{AXES[k]}"
        if plus in have and minus in have:
            up = np.array([p.accel[plus][0][k] for p in points])
            dn = np.array([p.accel[minus][0][k] for p in points])
            su = np.array([p.accel[plus][1][k] for p in points])
            sd = np.array([p.accel[minus][1][k] for p in points])
            s = np.hypot(su, sd) / 2
            c, _, cov = fit_tempco(ta, np.tile(((up + dn) / 2)[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_btc[k], a_btc_s[k] = c[0], np.sqrt(cov[0, 0, 0])
            c, i, cov = fit_tempco(ta, np.tile(((up - dn) / 2)[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_stc[k] = c[0] / i[0]
            a_stc_s[k] = np.sqrt(cov[0, 0, 0]) / abs(i[0])
        else:
            m = np.array([p.accel["+z"][0][k] for p in points])
            s = np.array([p.accel["+z"][1][k] for p in points])
            c, _, cov = fit_tempco(ta, np.tile(m[:, None], 3), np.tile(s[:, None], 3), t_ref_c)
            a_btc[k], a_btc_s[k] = c[0], np.sqrt(cov[0, 0, 0])
            if k == 2:
                notes.append("accel Z: level only, bias and scale tempco not separated "
                             "(slope = bias_tc + scale_tc·g put into bias_tc; right at level only)")
            else:
                notes.append(f"accel {AXES[k].upper()}: scale tempco not measured (needs ±{AXES[k].upper()} poses)")
    g_stc, g_stc_s = np.zeros(3), np.zeros(3)
    if all(len(p.turns) == 3 for p in points):
        sc = np.array([[p.turns[a][0] for a in range(3)] for p in points])
        ss = np.array([[p.turns[a][1] for a in range(3)] for p in points])
        c, i, cov = fit_tempco(tg, sc, ss, t_ref_c)
        g_stc, g_stc_s = c / i, np.sqrt(cov[:, 0, 0]) / np.abs(i)
    else:
        notes.append("gyro scale tempco not measured (no turntable): left at 0")
    return ThermalFit(t_ref_c, a_btc, a_btc_s, a_stc, a_stc_s, gb, np.sqrt(gcov[:, 0, 0]),
                      g_stc, g_stc_s, notes)


def apply_tempcos(params: Params, fits: ThermalFit, t_ref_c: float | None = None) -> Params:
    """A copy of params with the temperature coefficients and reference temperatures of fits
    (t_ref_c overrides fits.t_ref_c), checked with params.validate (raises InvalidParams)."""
    t_ref = float(fits.t_ref_c if t_ref_c is None else t_ref_c)
    p = Params.from_values(params.values())
    p.accel_bias_tc_mps2_per_c = tuple(float(v) for v in fits.accel_bias_tc)
    p.accel_scale_tc_per_c = tuple(float(v) for v in fits.accel_scale_tc)
    p.gyro_bias_tc_rad_s_per_c = tuple(float(v) for v in fits.gyro_bias_tc)
    p.gyro_scale_tc_per_c = tuple(float(v) for v in fits.gyro_scale_tc)
    p.accel_t_ref_c = t_ref
    p.gyro_t_ref_c = t_ref
    PR.validate(p)
    return p


# ------------------------------------------------------------------ drift of the calibrated output
def measure_drift(dev, temps: Sequence[float | None], hooks: Hooks, n: int = 2000, rate_hz: int = 200) -> dict:
    """Stream CALIBRATED, level and still, at each temperature; the device's corrected means
    and their drift (max − min over the sweep) per axis: accel x/y/z and |a| (m/s²), gyro
    x/y/z (rad/s)."""
    acc, gyr, tc = [], [], []
    if hooks.orient is not None:
        hooks.orient(np.array(POSES["+z"], dtype=float))
    dev.start_stream(rate_hz=rate_hz, calibrated=True)
    try:
        for c in temps:
            if hooks.set_temperature is not None and c is not None:
                hooks.set_temperature(c)
            elif hooks.ready is not None:
                hooks.ready(c)
            b = _settled(dev, n)
            a = b.accel_mps2.astype(np.float64)
            acc.append(np.r_[a.mean(axis=0), np.linalg.norm(a, axis=1).mean()])
            gyr.append(b.rate_rad_s.astype(np.float64).mean(axis=0))
            tc.append(float(U.accel_temp_counts_to_c(b.accel_temp_counts).mean()))
    finally:
        dev.stop_stream()
    acc, gyr = np.array(acc), np.array(gyr)
    return {"temps_c": tc, "accel_mean_mps2": acc, "gyro_mean_rad_s": gyr,
            "accel_drift_mps2": np.ptp(acc, axis=0),      # x, y, z, |a|
            "gyro_drift_rad_s": np.ptp(gyr, axis=0)}


# ------------------------------------------------------------------ command line
def format_fit(f: ThermalFit) -> str:
    L = [f"temperature coefficients (t_ref {f.t_ref_c:g} °C), ± 1 sigma:"]
    for k in range(3):
        L.append(f"  accel {AXES[k]}: bias {f.accel_bias_tc[k] / U.G0_MPS2 * 1e6:+9.2f} ± "
                 f"{f.accel_bias_tc_sigma[k] / U.G0_MPS2 * 1e6:.2f} µg/°C   scale "
                 f"{f.accel_scale_tc[k] * 1e6:+9.2f} ± {f.accel_scale_tc_sigma[k] * 1e6:.2f} ppm/°C")
    for k in range(3):
        L.append(f"  gyro  {AXES[k]}: bias {U.rad_s_to_dps(f.gyro_bias_tc[k]) * 1e3:+9.3f} ± "
                 f"{U.rad_s_to_dps(f.gyro_bias_tc_sigma[k]) * 1e3:.3f} m°/s/°C   scale "
                 f"{f.gyro_scale_tc[k] * 1e6:+9.2f} ± {f.gyro_scale_tc_sigma[k] * 1e6:.2f} ppm/°C")
    L += [f"  note: {n}" for n in f.notes]
    return "\n".join(L)


def format_drift(before: dict, after: dict | None) -> str:
    L = ["drift of the calibrated output over the sweep (max − min):"]
    names = ["accel x", "accel y", "accel z", "|accel|"]
    for i, nm in enumerate(names):
        b = before["accel_drift_mps2"][i] / U.G0_MPS2 * 1e3
        s = f"  {nm:8s} before {b:9.4f} mg"
        if after is not None:
            a = after["accel_drift_mps2"][i] / U.G0_MPS2 * 1e3
            s += f"   after {a:9.4f} mg   ({b / max(a, 1e-12):.0f}x)"
        L.append(s)
    for k in range(3):
        b = U.rad_s_to_dps(before["gyro_drift_rad_s"][k])
        s = f"  gyro {AXES[k]}   before {b:9.4f} °/s"
        if after is not None:
            a = U.rad_s_to_dps(after["gyro_drift_rad_s"][k])
            s += f"  after {a:9.4f} °/s  ({b / max(a, 1e-12):.0f}x)"
        L.append(s)
    return "\n".join(L)


def write_params(dev, new: Params) -> int:
    """set_params, read back bit-exactly, save; returns the flash generation."""
    dev.set_params(new)
    back = dev.get_params(ParamsWhich.ACTIVE).params
    if Params.STRUCT.pack(*back.values()) != Params.STRUCT.pack(*new.values()):
        raise RuntimeError("read-back after set_params differs from what was written")
    return dev.save_params()


# truth of the virtual device with --sim (within the device's limits)
SIM_ACCEL_TRUTH = {"bias_tc": [2e-3, -1.5e-3, 1e-3], "scale_tc": [0.0, 0.0, 2e-4], "rw_k": [0.0] * 3}
SIM_GYRO_TRUTH = [{"bias_tempco_rad_s_per_c": v * U.DEG, "scale_tempco_per_c": s, "bias_rw_k": 0.0}
                  for v, s in ((0.01, 1e-4), (-0.008, -5e-5), (0.006, 0.0))]


def main_thermal(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="imubench thermal", description="temperature calibration: "
                                 "sweep, fit bias and scale temperature coefficients, write them")
    ap.add_argument("--port", help="device URL (default $IMUBENCH_PORT)")
    ap.add_argument("--temps", default="10,25,40", help="temperatures in °C, comma separated (default 10,25,40)")
    ap.add_argument("--sim", action="store_true", help="run on a virtual device with temperature "
                    "coefficients in its truth; it drives temperature, orientation and turntable")
    ap.add_argument("--write", action="store_true", help="write the coefficients to the device "
                    "(set, read back, save) and measure the drift after")
    ap.add_argument("--t-ref", type=float, default=None, help="reference temperature (default: the device's)")
    ap.add_argument("--samples", type=int, default=2000, help="samples per measurement (default 2000 at 200 Hz)")
    ap.add_argument("--speed", type=float, default=20, help="--sim: device time per wall time (default 20)")
    a = ap.parse_args(argv)
    try:
        temps = [float(x) for x in a.temps.split(",") if x.strip()]
    except ValueError:
        ap.error("--temps: comma separated numbers")
    if len(temps) < 2:
        ap.error("--temps: at least two temperatures")
    say = lambda s: print(s, flush=True)
    from .link import Device
    vb = None
    try:
        if a.sim:
            from .sim import VirtualBench
            vb = VirtualBench(speed=a.speed)
            vb.set_truth(accel=SIM_ACCEL_TRUTH, gyro=SIM_GYRO_TRUTH)
            url, hooks, poses = vb.port_url, sim_hooks(vb, say), tuple(POSES)
        else:
            url, poses = a.port, ("+z",)
            def ready(c):
                input(f"bring the board (still, level, +Z up) to {c:g} °C and press Enter ")
            hooks = Hooks(ready=ready, say=say)
        with Device.open(url) as dev:
            old = dev.get_params(ParamsWhich.ACTIVE).params
            t_ref = float(old.accel_t_ref_c) if a.t_ref is None else a.t_ref
            say(f"sweep over {temps} °C ({'virtual bench' if a.sim else 'ambient: you set it'})")
            t0 = time.monotonic()
            points = sweep(dev, temps, hooks, n=a.samples, poses=poses, turntable=a.sim)
            fit = fit_sweep(points, t_ref)
            say(format_fit(fit))
            if not a.write:
                say(f"(not written: give --write) [{time.monotonic() - t0:.1f} s]")
                return 0
            new = apply_tempcos(old, fit, t_ref)
            before = measure_drift(dev, temps, hooks, n=a.samples)
            gen = write_params(dev, new)
            say(f"written, read back, saved (generation {gen})")
            after = measure_drift(dev, temps, hooks, n=a.samples)
            say(format_drift(before, after))
            return 0
    except (PR.InvalidParams, RuntimeError, OSError, ValueError) as e:
        print(f"imubench thermal: {e}", file=sys.stderr)
        return 1
    finally:
        if vb is not None:
            vb.close()


if __name__ == "__main__":
    sys.exit(main_thermal())
