"""Static attitude (roll, pitch) from the accelerometer and gyros: three filters. Pure numpy
and scipy: arrays in, angles out (the device side is imubench.procedures.attitude).

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
"""
from __future__ import annotations

import math

import numpy as np

from imubench.units import G0_MPS2
from imubench.wire.board_parts import DEFAULT as DEFAULT_PARTS

DEG = math.pi / 180.0


# Noise of the parts, from the parts table (protocol/parts.toml, their data sheets): white noise as
# the Allan coefficient N (units/√Hz), bias random walk K (units·√Hz), as in docs/conventions.md.
# The defaults are the default board's (ADXL355: 25 µg/√Hz; ADXRS450: 0.015 °/s/√Hz); part_noise
# gives a board's own.


def part_noise(parts=DEFAULT_PARTS) -> dict:
    """KalmanTilt's white-noise figures for a board's parts (wire.board_parts.BoardParts):
    accel_noise_n (m/s²/√Hz, the accelerometer's) and gyro_noise_n (rad/s/√Hz, the noisiest gyro's)."""
    return {"accel_noise_n": parts.accel.noise_per_rthz * G0_MPS2,
            "gyro_noise_n": max(g.noise_per_rthz for g in parts.gyros) * DEG}


ACCEL_NOISE_N = part_noise()["accel_noise_n"]
GYRO_NOISE_N = part_noise()["gyro_noise_n"]


GYRO_BIAS_RW_K = 0.001 * DEG            # 0.001 °/s·√Hz -> rad/s·√Hz (bias random walk)


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
        from scipy.signal import lfilter  # lazily: scipy.signal takes 0.5 s to import
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
        from scipy.signal import lfilter  # lazily: scipy.signal takes 0.5 s to import
        y, _ = lfilter([1.0], [1.0, -al], u, axis=0, zi=(al * y0)[None, :])
        self._state = y[-1].copy()
        return y[:, 0], y[:, 1]


def make_filters(which: str = "all", num: float = 20, tau_s: float = 0.5, parts=DEFAULT_PARTS) -> list[_TiltFilter]:
    """Filters by name: rc, kalman, complementary or all; the Kalman filter's noise is the
    board's parts' (part_noise)."""
    table = {"rc": lambda: RCLowPass(num), "kalman": lambda: KalmanTilt(**part_noise(parts)),
             "complementary": lambda: Complementary(tau_s)}
    names = list(table) if which == "all" else [which]
    return [table[n]() for n in names]


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
