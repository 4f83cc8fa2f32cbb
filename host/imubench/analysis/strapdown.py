"""Strapdown integration for the closure check (imubench.procedures.closure): motion detection, levelling,
attitude from the gyros, double integration of the specific force, and the closure error that
white sensor noise alone would give. Pure numpy: samples in, positions out; nothing here
touches a device (imubench.procedures.closure records, this computes). docs/closure.md.

Frames (docs/conventions.md): board X forward, Y left, Z up. The navigation frame is the
level frame at the start: Z up, X the board's X axis projected on the horizontal at the
start (yaw 0 at the start), Y completing a right-handed frame. Specific force f = a − g_vec,
so a level board at rest reads f = (0, 0, +g) and a_nav = R·f − (0, 0, g).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imubench import units as U
from imubench.analysis.tilt import accel_tilt
from imubench.errors import ImubenchError

__all__ = ["ClosureError", "Integration", "align_level", "motion_flags", "motion_window", "noise_floor",
           "strapdown"]

G0 = U.G0_MPS2


class ClosureError(ImubenchError, RuntimeError):
    """The recording cannot give a closure figure (no motion, lost samples, ...); says why."""


# ------------------------------------------------------------------ motion detection
def _moving_mean(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving mean over w samples (edges: the partial window)."""
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    n = len(x)
    h = w // 2
    lo = np.clip(np.arange(n) - h, 0, n)
    hi = np.clip(np.arange(n) + h + 1, 0, n)
    return (c[hi] - c[lo]) / (hi - lo)[:, None]


def motion_flags(accel, gyro, rest_n: int, fs_hz: float, window_s: float = 0.05, k: float = 8.0) -> np.ndarray:
    """Per sample: is the board moving? Two statistics per axis, each against the largest
    value it takes during the first half of the first rest_n samples (known still), times k,
    so the thresholds
    follow the measured noise and its correlation, in any unit:
      gyro:  |moving mean over window_s − rest mean|   (any rotation)
      accel: |mean of the next window_s − mean of the previous window_s|   (any change of
             specific force: translation or rotation; a board still in another attitude
             than at the start is not moving)."""
    a = np.asarray(accel, dtype=np.float64)
    g = np.asarray(gyro, dtype=np.float64)
    n = len(a)
    if rest_n < 10 or rest_n > n:
        raise ClosureError(f"need at least 10 samples of rest at the start (have {min(rest_n, n)})")
    w = max(3, int(round(window_s * fs_hz)) | 1)
    if rest_n < 8 * w:
        raise ClosureError(f"the rest at the start ({rest_n} samples) must be at least 8 windows of {w}")
    gdev = np.abs(_moving_mean(g, w) - g[:rest_n].mean(axis=0))
    c = np.cumsum(np.vstack([np.zeros((1, 3)), a]), axis=0)
    idx = np.arange(n)
    lo, mid, hi = np.clip(idx - w, 0, n), idx, np.clip(idx + w, 0, n)
    before = (c[mid] - c[lo]) / np.maximum(mid - lo, 1)[:, None]
    after = (c[hi] - c[mid]) / np.maximum(hi - mid, 1)[:, None]
    adev = np.abs(after - before)
    adev[:w] = adev[-w:] = 0.0                           # partial windows at the edges
    x = np.hstack([gdev, adev])
    # the reference: statistics wholly inside the first half of the rest (the second half is
    # then checked like the rest of the recording: motion there is refused by motion_window)
    inner = slice(w, max(w + 1, rest_n // 2 - w))
    scale = x[inner].max(axis=0)
    ref = np.hstack([np.abs(g[:rest_n].mean(axis=0)), np.abs(a[:rest_n].mean(axis=0))])
    floor = 1e-9 * np.maximum(ref, 1.0)                  # noise-free data (simulation)
    thr = k * np.maximum(scale, floor)
    return (x > thr).any(axis=1)


def motion_window(t_s, accel, gyro, rest_s: float, pad_s: float = 0.25, min_still_end_s: float = 0.5,
                  window_s: float = 0.05, k: float = 8.0) -> tuple[int, int]:
    """Indices (i0, i1) bracketing the motion: i0 pad_s before the first moving sample, i1
    pad_s after the last one; the board is still at both. The first rest_s seconds must be
    still (they set the noise reference). Raises ClosureError when there is no motion, the
    motion starts inside the rest, or the recording ends less than min_still_end_s after it."""
    t = np.asarray(t_s, dtype=np.float64)
    if len(t) < 20:
        raise ClosureError(f"only {len(t)} samples recorded")
    fs = (len(t) - 1) / (t[-1] - t[0])
    rest_n = int(np.searchsorted(t, t[0] + rest_s))
    moving = motion_flags(accel, gyro, rest_n, fs, window_s, k)
    idx = np.flatnonzero(moving)
    if len(idx) == 0:
        raise ClosureError("no motion found in the recording: drive or carry the board around the path")
    first, last = int(idx[0]), int(idx[-1])
    pad = int(round(pad_s * fs))
    w = max(3, int(round(window_s * fs)) | 1)     # the statistics see a motion up to w samples early
    if first < rest_n - 2 * w or first - pad < 0:
        raise ClosureError(f"the board moved {t[first] - t[0]:.2f} s into the recording, before its rest of "
                           f"{rest_s:g} s was over; keep it still at the start")
    if t[-1] - t[last] < min_still_end_s:
        raise ClosureError(f"the board was still moving {t[-1] - t[last]:.2f} s before the recording ended; "
                           f"hold it still at the end for at least {min_still_end_s:g} s")
    return first - pad, min(len(t) - 1, last + pad)


# ------------------------------------------------------------------ strapdown
def yaw_between(r_nav: np.ndarray, r_world: np.ndarray) -> float:
    """The heading (rad) of the navigation frame in a level world frame, from the same board
    attitude seen both ways (board -> nav, board -> world): the rotation about the vertical
    that takes world coordinates into navigation coordinates. Well defined at any attitude,
    also nose up, where Euler yaw is not."""
    m = np.asarray(r_nav) @ np.asarray(r_world).T
    return math.atan2(m[1, 0], m[0, 0])


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """R = Rz(yaw)·Ry(pitch)·Rx(roll), board -> level (docs/attitude.md)."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def align_level(f_mean) -> np.ndarray:
    """Rotation matrix R (board -> level, yaw 0) from the mean specific force at rest, with
    the direction-cosine tilt of docs/attitude.md: R = Ry(pitch)·Rx(roll), so that R·f is
    vertical (up)."""
    roll_deg, pitch_deg = accel_tilt(np.asarray(f_mean, dtype=np.float64))
    r, p = math.radians(float(roll_deg)), math.radians(float(pitch_deg))
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return ry @ rx


def _attitudes(r0: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (n+1, 3, 3): R_0 = r0, R_{k+1} = R_k·exp([rotvec_k]×) (body-frame
    increments composed on the right), through calib.gyro's vectorised quaternion products."""
    from scipy.spatial.transform import Rotation

    from imubench.calib.gyro import _qmul, _quat_matrix, _quat_prefix, _rotvec_quat
    x, y, z, w = Rotation.from_matrix(r0).as_quat()
    q0 = np.array([w, x, y, z])
    q = np.empty((4, len(rotvec) + 1))
    q[:, 0] = q0
    if len(rotvec):
        q[:, 1:] = _qmul(q0[:, None], _quat_prefix(_rotvec_quat(rotvec.T)[:, None, :])[:, 0, :])
    return _quat_matrix(q)


@dataclass
class Integration:
    """One double integration over the motion window. pos_m/vel_mps (n, 3) in the navigation
    frame (module docstring), t_s (n,) from the window start."""
    label: str
    t_s: np.ndarray
    pos_m: np.ndarray
    vel_mps: np.ndarray
    heading_deg: np.ndarray
    r0: np.ndarray | None = None        # board -> navigation frame at the window start (levelling)

    @property
    def closure_m(self) -> np.ndarray:
        return self.pos_m[-1] - self.pos_m[0]

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.closure_m))

    @property
    def horizontal_m(self) -> float:
        return float(np.hypot(*self.closure_m[:2]))

    @property
    def vertical_m(self) -> float:
        return float(abs(self.closure_m[2]))

    @property
    def end_speed_mps(self) -> float:
        return float(np.linalg.norm(self.vel_mps[-1]))

    @property
    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.pos_m, axis=0), axis=1).sum())

    def as_dict(self) -> dict:
        return {"label": self.label, "closure_m": [float(v) for v in self.closure_m],
                "distance_m": self.distance_m, "horizontal_m": self.horizontal_m,
                "vertical_m": self.vertical_m, "end_speed_mps": self.end_speed_mps,
                "path_length_m": self.path_length_m,
                "heading_change_deg": float(self.heading_deg[-1] - self.heading_deg[0])}


def strapdown(t_s, accel_mps2, gyro_rad_s, i0: int, i1: int, align_n: int, g_mps2: float = G0,
              label: str = "") -> Integration:
    """Integrate samples i0..i1 (inclusive) starting at rest (velocity 0, position 0) with
    the attitude levelled from the mean specific force of the align_n samples ending at i0.
    Attitude: body-frame rotation increments (ω_k + ω_{k+1})/2·Δt composed as quaternions;
    a_nav = R·f − (0, 0, g); velocity and position by the trapezoid rule. Nothing else is
    estimated from the data (no gyro bias at rest, no zero-velocity updates): what the sensors
    get wrong stays in."""
    t = np.asarray(t_s, dtype=np.float64)
    f = np.asarray(accel_mps2, dtype=np.float64)
    w = np.asarray(gyro_rad_s, dtype=np.float64)
    if not (0 <= i0 < i1 < len(t)):
        raise ClosureError(f"bad window {i0}..{i1} of {len(t)} samples")
    a0 = max(0, i0 - align_n + 1)
    r0 = align_level(f[a0:i0 + 1].mean(axis=0))
    sl = slice(i0, i1 + 1)
    tt, ff, ww = t[sl], f[sl], w[sl]
    dt = np.diff(tt)
    rm = _attitudes(r0, 0.5 * (ww[:-1] + ww[1:]) * dt[:, None])
    a_nav = np.einsum("nij,nj->ni", rm, ff)
    a_nav[:, 2] -= g_mps2
    vel = np.zeros_like(a_nav)
    vel[1:] = np.cumsum(0.5 * (a_nav[:-1] + a_nav[1:]) * dt[:, None], axis=0)
    pos = np.zeros_like(a_nav)
    pos[1:] = np.cumsum(0.5 * (vel[:-1] + vel[1:]) * dt[:, None], axis=0)
    # heading of the board's X axis in the navigation frame
    heading = np.degrees(np.unwrap(np.arctan2(rm[:, 1, 0], rm[:, 0, 0])))
    return Integration(label, tt - tt[0], pos, vel, heading, r0)


def noise_floor(accel_rest_mps2, gyro_rest_rad_s, fs_hz: float, duration_s: float, align_n: int,
                g_mps2: float = G0) -> dict:
    """1-sigma closure error expected from white sensor noise alone, per axis, from the noise
    measured at rest (densities N = σ_sample / √fs, white noise assumed):
      accelerometer noise:   N_a·T^1.5/√3                       (each axis)
      levelling at the start: σ_a/√n_align·T²/2                  (horizontal: the tilt error)
      gyro angle random walk: g·N_g·T^2.5/√20                    (horizontal: tilt error growing;
                                                                   N_g the RMS over the axes, as the
                                                                   board turns every gyro tilts it)
    Bias instability and the calibration's own uncertainty are not included."""
    sa = np.std(np.asarray(accel_rest_mps2, dtype=np.float64), axis=0, ddof=1)
    sg = np.std(np.asarray(gyro_rest_rad_s, dtype=np.float64), axis=0, ddof=1)
    na, ng = sa / math.sqrt(fs_hz), sg / math.sqrt(fs_hz)
    T = float(duration_s)
    acc_term = na * T ** 1.5 / math.sqrt(3.0)
    lev_term = sa / math.sqrt(max(align_n, 1)) * T ** 2 / 2.0
    gyr = g_mps2 * float(np.sqrt(np.mean(ng ** 2))) * T ** 2.5 / math.sqrt(20.0)
    horiz = np.sqrt(acc_term[:2] ** 2 + lev_term[:2] ** 2 + gyr ** 2)
    vert = float(acc_term[2])
    return {"accel_noise_mps2_rthz": na.tolist(), "gyro_noise_rad_s_rthz": ng.tolist(),
            "duration_s": T, "sigma_x_m": float(horiz[0]), "sigma_y_m": float(horiz[1]), "sigma_z_m": vert,
            "sigma_distance_m": float(math.sqrt(horiz[0] ** 2 + horiz[1] ** 2 + vert ** 2))}
