"""Static attitude (roll, pitch) from the calibrated accelerometer and gyros, three filters.

Convention (docs/attitude.md, the same as the simulator's set_orientation): board X forward,
Y left, Z up; R = Rz(yaw)·Ry(pitch)·Rx(roll), right-handed rotations about board axes, so a
still board measures the specific force

    f = g0 · (−sin θ, sin φ cos θ, cos φ cos θ)

and the tilt is recovered from the normalised specific force as

    φ (roll)  = atan2(f_y, f_z)                      right side (−Y) down is NEGATIVE roll
    θ (pitch) = atan2(−f_x, √(f_y² + f_z²))          nose (+X) DOWN is POSITIVE pitch

Filters (each: ``run(accel, gyro, fs_hz) -> (roll_deg, pitch_deg)`` for whole arrays, and
``update(accel_block, gyro_block, dt)`` for streaming, keeping state between blocks):

    RCLowPass(num)        y += (x − y)/num on the accelerometer angles (first-order RC)
    KalmanTilt(...)       one Kalman1D per axis: state (angle, gyro bias), the Euler rate
                          from the gyros as input, the accelerometer angle as measurement
    Complementary(tau_s)  integrates the Euler rates, pulls toward the accelerometer angle
                          with time constant tau

    settling_time(t, angle, target, band_deg, t_step)    time after a step to stay in band
    tilt_step_experiment(bench, dev, ...)                 the turntable step test
    plot_steps(results, path)                             PNG of angle vs time per filter
    main_attitude(argv)                                   `imubench attitude`
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from imubench.device.link import DEFAULT_BAUD
from imubench.units import G0_MPS2

DEG = math.pi / 180.0

# Noise of the parts (datasheet values; the simulator's default truth uses the same):
# white noise as the Allan coefficient N (units/√Hz), bias random walk K (units·√Hz),
# as in docs/conventions.md.
ACCEL_NOISE_N = 22.5e-6 * G0_MPS2       # ADXL355: 22.5 µg/√Hz  -> m/s²/√Hz
GYRO_NOISE_N = 0.015 * DEG              # ADXRS450: 0.015 °/s/√Hz -> rad/s/√Hz
GYRO_BIAS_RW_K = 0.001 * DEG            # 0.001 °/s·√Hz -> rad/s·√Hz (bias random walk)

__all__ = [
    "Complementary",
    "Kalman1D",
    "KalmanTilt",
    "RCLowPass",
    "StepResult",
    "accel_tilt",
    "euler_rates",
    "main_attitude",
    "make_filters",
    "plot_steps",
    "settling_time",
    "tilt_step_experiment",
]


# --------------------------------------------------------------------- geometry
def accel_tilt(accel) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch in degrees from specific force (n,3) (or one (3,) vector), any unit.
    roll = atan2(f_y, f_z), pitch = atan2(−f_x, √(f_y² + f_z²))."""
    f = np.asarray(accel, dtype=np.float64)
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    roll = np.degrees(np.arctan2(fy, fz))
    pitch = np.degrees(np.arctan2(-fx, np.hypot(fy, fz)))
    return roll, pitch


def euler_rates(gyro, roll_deg, pitch_deg) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch rates (rad/s) from body rates (n,3) rad/s for R = Rz·Ry·Rx:
    φ' = p + tan θ (q sin φ + r cos φ),  θ' = q cos φ − r sin φ."""
    w = np.asarray(gyro, dtype=np.float64)
    p, q, r = w[..., 0], w[..., 1], w[..., 2]
    phi = np.radians(roll_deg)
    th = np.radians(np.clip(pitch_deg, -89.0, 89.0))     # tan θ blows up at ±90°
    sphi, cphi = np.sin(phi), np.cos(phi)
    return p + np.tan(th) * (q * sphi + r * cphi), q * cphi - r * sphi


class _TiltFilter:
    """Shared streaming interface: run() = reset() + update() over whole arrays."""

    name = "filter"

    def reset(self) -> None:
        self._state = None

    def run(self, accel, gyro, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
        self.reset()
        return self.update(accel, gyro, 1.0 / float(fs_hz))

    def update(self, accel, gyro, dt: float) -> tuple[np.ndarray, np.ndarray]:
        a = np.atleast_2d(np.asarray(accel, dtype=np.float64))
        g = None if gyro is None else np.atleast_2d(np.asarray(gyro, dtype=np.float64))
        if len(a) == 0:
            return np.empty(0), np.empty(0)
        return self._update(a, g, float(dt))

    def _update(self, a, g, dt):  # pragma: no cover - abstract
        raise NotImplementedError


# ------------------------------------------------------------------------ filters
class RCLowPass(_TiltFilter):
    """The seed's first-order RC filter on the accelerometer angles: y += (x − y)/num.
    Time constant num/fs (num samples); the gyros are not used. Starts at the first angle."""

    def __init__(self, num: float = 20):
        if not num >= 1:
            raise ValueError("num must be >= 1")
        self.num = float(num)
        self.name = f"rc{num:g}"
        self.reset()

    def _update(self, a, g, dt):
        x = np.stack(accel_tilt(a), axis=1)                 # (n, 2) degrees
        k = 1.0 / self.num
        y0 = x[0] if self._state is None else self._state
        zi = ((1.0 - k) * y0)[None, :]                       # y[-1] = y0
        y, _ = lfilter([k], [1.0, -(1.0 - k)], x, axis=0, zi=zi)
        self._state = y[-1].copy()
        return y[:, 0], y[:, 1]


class Kalman1D:
    """One tilt axis: state (angle rad, gyro bias rad/s); input the Euler rate from the
    gyros, measurement the accelerometer angle. Model, with dt the sample period:

        angle_k+1 = angle_k + (rate_k − bias_k)·dt,   bias_k+1 = bias_k + w_b
        Q = diag(N_g²·dt, K_g²·dt)      N_g: gyro angle random walk (rad/s/√Hz)
                                         K_g: gyro bias random walk (rad/s·√Hz)
        R = (N_a·√fs / g0)²              accelerometer white noise per sample, as angle (rad²)

    A Python loop per sample: about 2 µs per sample and axis (4 µs per sample for roll and
    pitch; 200 Hz needs 0.1 % of a core)."""

    def __init__(self, gyro_noise_n: float = GYRO_NOISE_N, gyro_bias_rw_k: float = GYRO_BIAS_RW_K,
                 accel_noise_n: float = ACCEL_NOISE_N, angle0: float = 0.0, bias0: float = 0.0,
                 p0_angle: float = (1.0 * DEG) ** 2, p0_bias: float = (0.1 * DEG) ** 2):
        self.gyro_noise_n = gyro_noise_n
        self.gyro_bias_rw_k = gyro_bias_rw_k
        self.accel_noise_n = accel_noise_n
        self.angle = angle0
        self.bias = bias0
        self.p = [p0_angle, 0.0, p0_bias]           # P00, P01, P11

    def noise(self, dt: float) -> tuple[float, float, float]:
        """(q_angle, q_bias, r) for a sample period dt."""
        return (self.gyro_noise_n ** 2 * dt, self.gyro_bias_rw_k ** 2 * dt,
                (self.accel_noise_n / G0_MPS2) ** 2 / dt)

    def filter(self, rate, meas, dt: float) -> np.ndarray:
        """Run over arrays of Euler rate (rad/s) and measured angle (rad); returns angles (rad)."""
        qa, qb, r = self.noise(dt)
        ang, b = self.angle, self.bias
        p00, p01, p11 = self.p
        out = np.empty(len(meas))
        two_pi = 2.0 * math.pi
        for i, (w, z) in enumerate(zip(np.asarray(rate, float).tolist(), np.asarray(meas, float).tolist())):
            ang += (w - b) * dt                               # predict
            p00 += dt * (dt * p11 - 2.0 * p01) + qa
            p01 -= dt * p11
            p11 += qb
            s = p00 + r                                       # update
            k0, k1 = p00 / s, p01 / s
            y = (z - ang + math.pi) % two_pi - math.pi        # innovation, wrapped
            ang += k0 * y
            b += k1 * y
            p11 -= k1 * p01
            p01 -= k0 * p01
            p00 -= k0 * p00
            out[i] = ang
        self.angle, self.bias, self.p = ang, b, [p00, p01, p11]
        return out


class KalmanTilt(_TiltFilter):
    """Two independent Kalman1D (roll, pitch). The Euler rates are formed from the gyros
    with the accelerometer angles (exact for turns about one board axis; a second-order
    effect otherwise). Starts at the first accelerometer angle, bias 0."""

    def __init__(self, gyro_noise_n: float = GYRO_NOISE_N, gyro_bias_rw_k: float = GYRO_BIAS_RW_K,
                 accel_noise_n: float = ACCEL_NOISE_N):
        self.kw = {"gyro_noise_n": gyro_noise_n, "gyro_bias_rw_k": gyro_bias_rw_k,
                   "accel_noise_n": accel_noise_n}
        self.name = "kalman"
        self.reset()

    def reset(self) -> None:
        self.axes: list[Kalman1D] | None = None

    def _update(self, a, g, dt):
        if g is None:
            raise ValueError("the Kalman filter needs the gyro rates")
        roll_m, pitch_m = accel_tilt(a)
        rr, pr = euler_rates(g, roll_m, pitch_m)
        if self.axes is None:
            self.axes = [Kalman1D(angle0=roll_m[0] * DEG, **self.kw),
                         Kalman1D(angle0=pitch_m[0] * DEG, **self.kw)]
        roll = self.axes[0].filter(rr, roll_m * DEG, dt)
        pitch = self.axes[1].filter(pr, pitch_m * DEG, dt)
        return np.degrees(roll), np.degrees(pitch)


class Complementary(_TiltFilter):
    """y_k = α·(y_k−1 + rate_k·dt) + (1 − α)·x_k, α = tau/(tau + dt): gyro integration
    high-passed, accelerometer angle low-passed, both with time constant tau_s. Vectorised
    (scipy.signal.lfilter); Euler rates from the accelerometer angles as in KalmanTilt."""

    def __init__(self, tau_s: float = 0.5):
        if not tau_s > 0:
            raise ValueError("tau_s must be > 0")
        self.tau_s = float(tau_s)
        self.name = f"comp{tau_s:g}s"
        self.reset()

    def _update(self, a, g, dt):
        if g is None:
            raise ValueError("the complementary filter needs the gyro rates")
        x = np.stack(accel_tilt(a), axis=1)
        rates = np.degrees(np.stack(euler_rates(g, x[:, 0], x[:, 1]), axis=1))
        al = self.tau_s / (self.tau_s + dt)
        u = al * rates * dt + (1.0 - al) * x
        y0 = x[0] if self._state is None else self._state
        y, _ = lfilter([1.0], [1.0, -al], u, axis=0, zi=(al * y0)[None, :])
        self._state = y[-1].copy()
        return y[:, 0], y[:, 1]


def make_filters(which: str = "all", num: float = 20, tau_s: float = 0.5) -> list[_TiltFilter]:
    """Filters by name: rc, kalman, complementary or all."""
    table = {"rc": lambda: RCLowPass(num), "kalman": KalmanTilt,
             "complementary": lambda: Complementary(tau_s)}
    names = list(table) if which == "all" else [which]
    return [table[n]() for n in names]


# ----------------------------------------------------------------------- metrics
def settling_time(t, angle, target: float, band_deg: float, t_step: float | None = None) -> float:
    """Seconds from t_step (default t[0]) until the angle enters ±band_deg of target and stays
    there up to the end of the record; 0 if never outside, inf if outside at the end."""
    t = np.asarray(t, dtype=np.float64)
    a = np.asarray(angle, dtype=np.float64)
    t0 = t[0] if t_step is None else float(t_step)
    sel = t >= t0
    t, a = t[sel], a[sel]
    if len(t) == 0:
        return math.inf
    out = np.flatnonzero(np.abs(a - target) > band_deg)
    if len(out) == 0:
        return 0.0
    if out[-1] == len(t) - 1:
        return math.inf
    return float(t[out[-1] + 1] - t0)


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
    filters = list(filters) if filters is not None else [RCLowPass(10), RCLowPass(40), KalmanTilt(),
                                                          Complementary(0.1), Complementary(0.5)]
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
            from imubench.wire.decoder import SampleBlock
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


def summarize(results: dict) -> str:
    """Text table of settling times and static errors per step and filter, and RMS errors."""
    names = ["accel"] + results["filters"]
    lines = [f"{'axis':5} {'target':>7} | " + " ".join(f"{n:>17}" for n in names),
             f"{'':5} {'deg':>7} | " + " ".join(f"{'settle s / err °':>17}" for _ in names)]
    for s in results["steps"]:
        lines.append(f"{s.axis:5} {s.target_deg:7.2f} | " + " ".join(
            f"{s.settle_s[n]:7.3f} {s.error_deg[n]:+9.5f}" for n in names))
    rms = {n: math.sqrt(np.mean([s.error_deg[n] ** 2 for s in results["steps"]])) for n in names}
    lines.append(f"{'RMS static error (deg)':15} | " + " ".join(f"{rms[n]:17.5f}" for n in names))
    return "\n".join(lines)


def plot_steps(results: dict, path) -> None:
    """PNG: one panel per axis, angle (deg) vs device time (s) for each filter, with the
    step targets (simulator truth) as a dashed staircase."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = results["t"]
    t0 = t[0]
    axes_used = [a for a in ("roll", "pitch") if any(s.axis == a for s in results["steps"])]
    fig, axs = plt.subplots(len(axes_used), 2, figsize=(15, 4 * len(axes_used)), squeeze=False,
                            gridspec_kw={"width_ratios": [3, 2]})
    band = results.get("band_deg", 0.05)
    for row, axis in zip(axs, axes_used):
        ax, ex = row
        k = 0 if axis == "roll" else 1
        steps = [s for s in results["steps"] if s.axis == axis]
        lo, hi = steps[0].t_step - 1.0, steps[-1].t_end + 0.5
        sel = (t >= lo) & (t <= hi)
        target = np.full(len(t), np.nan)
        for s in steps:
            target[(t >= s.t_step) & (t <= s.t_end)] = s.target_deg
        ax.plot(t[sel] - t0, results["angles"]["accel"][k][sel], color="0.8", lw=0.5, label="accelerometer")
        ex.plot(t[sel] - t0, (results["angles"]["accel"][k] - target)[sel], color="0.85", lw=0.5,
                label="accelerometer")
        for name in results["filters"]:
            ax.plot(t[sel] - t0, results["angles"][name][k][sel], lw=1.0, label=name)
            ex.plot(t[sel] - t0, (results["angles"][name][k] - target)[sel], lw=0.8, label=name)
        for s in steps:
            ax.hlines(s.target_deg, s.t_step - t0, s.t_end - t0, colors="k", linestyles="--", lw=0.8)
        ex.axhspan(-band, band, color="g", alpha=0.08, label=f"settling band ±{band:g}°")
        ex.set_ylim(-4 * band, 4 * band)
        ax.set_xlabel("device time (s)")
        ax.set_ylabel(f"{axis} (deg)")
        ax.set_title(f"{axis} steps on the virtual turntable (dashed: truth)")
        ex.set_xlabel("device time (s)")
        ex.set_ylabel(f"{axis} − target (deg)")
        ex.set_title(f"{axis} error after each step starts (zoom)")
        for a_ in (ax, ex):
            a_.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        ex.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# -------------------------------------------------------------------- command line
def main_attitude(argv: Sequence[str] | None = None) -> int:
    """`imubench attitude`: live roll/pitch from the device's calibrated stream."""
    from imubench.device.link import Device, DeviceError, LinkError, LinkTimeout

    ap = argparse.ArgumentParser(prog="imubench attitude",
                                 description="live roll/pitch (deg) from the device's calibrated output; "
                                 "roll = atan2(fy, fz), pitch = atan2(-fx, hypot(fy, fz)), "
                                 "positive pitch = nose down (docs/attitude.md)")
    ap.add_argument("--port", help="pyserial URL of the device (default: $IMUBENCH_PORT)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"baud rate for a real UART (default {DEFAULT_BAUD})")
    ap.add_argument("--rate", type=int, default=200, help="sample rate in Hz (default 200)")
    ap.add_argument("--duration", type=float, default=None, help="seconds to run (default: until Ctrl-C)")
    ap.add_argument("--filter", choices=("rc", "kalman", "complementary", "all"), default="all")
    ap.add_argument("--num", type=float, default=20, help="RC filter num (default 20)")
    ap.add_argument("--tau", type=float, default=0.5, help="complementary time constant s (default 0.5)")
    ap.add_argument("--record", metavar="FILE", help="append the raw bytes to FILE and write the "
                    "angles to FILE.angles.csv (or --csv)")
    ap.add_argument("--csv", metavar="FILE", help="write the angles to this CSV")
    ap.add_argument("--print-hz", type=float, default=4.0, help="live lines per second (default 4)")
    a = ap.parse_args(argv)

    filters = make_filters(a.filter, a.num, a.tau)
    csv_path = a.csv or (a.record + ".angles.csv" if a.record else None)
    capture = open(a.record, "ab") if a.record else None  # noqa: SIM115 - closed in finally
    csv_file = open(csv_path, "w", newline="") if csv_path else None  # noqa: SIM115
    writer = None
    if csv_file:
        writer = csv.writer(csv_file)
        writer.writerow(["t_s", "accel_roll_deg", "accel_pitch_deg"]
                        + [f"{f.name}_{c}_deg" for f in filters for c in ("roll", "pitch")])
    dt = 1.0 / a.rate
    n_total = 0
    try:
        with Device.open(a.port, baudrate=a.baud, capture=capture) as dev:
            dev.start_stream(rate_hz=a.rate, calibrated=True)
            print("   t (s)  " + "  ".join(f"{f.name:>10} roll/pitch (deg)" for f in filters), flush=True)
            t_start = time.monotonic()
            next_print = t_start
            t0_us = None
            try:
                for block in dev.stream():
                    acc = block.accel_mps2.astype(np.float64)
                    gyr = block.rate_rad_s.astype(np.float64)
                    if t0_us is None:
                        t0_us = int(block.t_us[0])
                    res = [f.update(acc, gyr, dt) for f in filters]
                    n_total += len(block)
                    if writer is not None:
                        ar, ap_ = accel_tilt(acc)
                        cols = [(block.t_us - t0_us) * 1e-6, ar, ap_] + [c for r in res for c in r]
                        writer.writerows(np.column_stack(cols).round(6).tolist())
                    now = time.monotonic()
                    if now >= next_print:
                        next_print = now + 1.0 / a.print_hz
                        ts = (int(block.t_us[-1]) - t0_us) * 1e-6
                        print(f"{ts:8.2f}  " + "  ".join(f"{f.name:>10} {r[0][-1]:+8.3f} {r[1][-1]:+8.3f}"
                                                          for f, r in zip(filters, res)), flush=True)
                    if a.duration is not None and now - t_start >= a.duration:
                        break
            except KeyboardInterrupt:
                pass
            finally:
                try:
                    dev.stop_stream()
                except (LinkError, LinkTimeout, DeviceError):
                    pass
    except (LinkError, LinkTimeout, DeviceError) as e:
        print(f"imubench attitude: {e}", file=sys.stderr)
        return 1
    finally:
        if capture:
            capture.close()
        if csv_file:
            csv_file.close()
    print(f"{n_total} samples" + (f"; angles in {csv_path}" if csv_path else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main_attitude())
