"""Putting the accelerometer and the gyros in one frame.

The multi-position |a| = g fit cannot see the rotation Q between the accelerometer triad and
the board (M_true = L·Q, calib.accel.lower_triangular_form): its calibrated output is in the
sensor's own frame, x_a = Q·x_board. A turntable gyro calibration is in the board frame (the
table's axes). Integrated together (strapdown, the closure check) the two disagree by Q: a
few milliradians of gravity leak into the horizontal each time the board tilts.

Q is observable from the motions between the poses of the same session: the rotation method
(calib.gyro.rotation_method), fed gravity directions in the accelerometer's frame, returns the
gyro matrix in that frame, M_A = M_g·Qᵀ; the turntable returns M_B = M_g. So
M_B⁻¹·M_A = Qᵀ up to the two fits' noise, and the nearest rotation to it (polar decomposition)
is Qᵀ. The accelerometer's matrix in the board frame is then M = L·Q: its calibrated output
x = M⁻¹(u − b) = Qᵀ·x_a is in the board (gyro) frame. docs/calibration.md ("One frame").
"""
from __future__ import annotations

import numpy as np

from imubench.calib import CalibrationError, TriadFit

__all__ = ["align_accel_to_gyro", "nearest_rotation"]

# Larger than this between the two frames is not a mounting tolerance: something is wrong
# (an axis mislabelled, poses or turns about the wrong axes).
MAX_ALIGNMENT_RAD = np.radians(5.0)


def nearest_rotation(p: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to p in the Frobenius norm (polar decomposition)."""
    u, _, vt = np.linalg.svd(np.asarray(p, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix near the identity (exact for any angle < π)."""
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(c)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = np.sin(ang)
    return v * (0.5 if s < 1e-12 else ang / (2.0 * s))


def _aligned(l_mat: np.ndarray, m_a: np.ndarray, m_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    qt = nearest_rotation(np.linalg.solve(m_b, m_a))
    return l_mat @ qt.T, qt


def align_accel_to_gyro(accel: TriadFit, gyro_board: TriadFit, gyro_accel_frame: TriadFit) -> TriadFit:
    """The accelerometer fit re-expressed in the gyro (board) frame: M = L·Q with
    Qᵀ = nearest_rotation(M_B⁻¹·M_A) (module docstring). b is unchanged (it is in the sensor's
    own axes, u's). The covariance is propagated to first order from the three fits (taken as
    independent) by a numerical Jacobian; all nine entries of M are then estimated.
    extra gains "alignment_rad" (the rotation vector of Qᵀ: board axes seen from the
    accelerometer frame), "sigma_alignment_rad", "frame" = "board (gyro turntable axes)"."""
    if gyro_board.method != "turntable":
        raise CalibrationError(f"aligning to the gyro frame needs a turntable gyro fit (got {gyro_board.method})")
    l_mat = np.asarray(accel.m, dtype=np.float64)
    m_a = np.asarray(gyro_accel_frame.m, dtype=np.float64)
    m_b = np.asarray(gyro_board.m, dtype=np.float64)
    m_new, qt = _aligned(l_mat, m_a, m_b)
    phi = _rotvec(qt)
    if np.linalg.norm(phi) > MAX_ALIGNMENT_RAD:
        raise CalibrationError(
            f"the accelerometer and gyro frames differ by {np.degrees(np.linalg.norm(phi)):.1f}° "
            f"(rotation vector {np.round(np.degrees(phi), 2).tolist()} °): more than a mounting tolerance "
            f"({np.degrees(MAX_ALIGNMENT_RAD):.0f}°); check the axis labels and the turntable axes")

    # first-order covariance: z = (L (9), b (3), M_A (9), M_B (9)) -> (M (9), b (3), phi (3))
    def f(z: np.ndarray) -> np.ndarray:
        mm, q = _aligned(z[:9].reshape(3, 3), z[12:21].reshape(3, 3), z[21:30].reshape(3, 3))
        return np.concatenate([mm.ravel(), z[9:12], _rotvec(q)])

    z0 = np.concatenate([l_mat.ravel(), np.asarray(accel.b, dtype=np.float64), m_a.ravel(), m_b.ravel()])
    jac = np.empty((15, 30))
    h = 1e-7
    for k in range(30):
        dz = np.zeros(30)
        dz[k] = h
        jac[:, k] = (f(z0 + dz) - f(z0 - dz)) / (2 * h)
    sigma = np.zeros((30, 30))
    sigma[:12, :12] = np.nan_to_num(accel.cov)
    sigma[12:21, 12:21] = np.nan_to_num(gyro_accel_frame.cov[:9, :9])
    sigma[21:30, 21:30] = np.nan_to_num(gyro_board.cov[:9, :9])
    cov = jac @ sigma @ jac.T
    extra = dict(accel.extra)
    extra.update({"frame": "board (gyro turntable axes)", "alignment_rad": phi.tolist(),
                  "sigma_alignment_rad": np.sqrt(np.clip(np.diag(cov)[12:], 0, None)).tolist(),
                  "lower_triangular_m": l_mat.tolist()})
    return TriadFit(method=accel.method, m=m_new, b=np.asarray(accel.b, dtype=np.float64).copy(), cov=cov[:12, :12],
                    residual_rms=accel.residual_rms, residuals=accel.residuals, dof=accel.dof,
                    estimated=np.ones(12, dtype=bool), extra=extra)
