"""The least-squares pieces both accelerometer fits share (calib.accel's six-position and
multi-position): the input checks, the χ² scaling of a covariance, the leave-one-out χ² of each
pose, and M = L·Q (the part of M that |a| = g can see)."""
from __future__ import annotations

import math

import numpy as np

from imubench.calib import CalibrationError
from imubench.units import G0_MPS2

__all__ = ["lower_triangular_form", "deletion_chi2"]

# --------------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------------

def _check_g(u: np.ndarray, g: float) -> None:
    if not (g > 0 and math.isfinite(g)):
        raise ValueError(f"g must be positive, got {g}")
    ratio = float(np.median(np.linalg.norm(u, axis=1))) / g
    if not 0.5 <= ratio <= 1.5:
        raise CalibrationError(
            f"the pose means have a median magnitude of {ratio:.4g} × g (g = {g:g}): the means "
            f"and g must be in the same unit — m/s² with g = {G0_MPS2}, or raw counts with "
            f"g = LSB per g (256000 at ±2 g, 128000 at ±4 g, 64000 at ±8 g)")


def _sigmas(sigmas, m: int) -> np.ndarray | None:
    if sigmas is None:
        return None
    s = np.asarray(sigmas, dtype=np.float64)
    if s.ndim == 1 and s.shape[0] == m:
        s = np.repeat(s[:, None], 3, axis=1)
    s = np.broadcast_to(s, (m, 3)).astype(np.float64)
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError("sigmas must be finite and > 0 (pass None for unknown noise)")
    return s


def _chi2_factor(chi2: float, dof: int, weighted: bool, mode: str) -> float:
    """Factor applied to the covariance (JᵀWJ)⁻¹.

    weighted (measured sigmas): "inflate" (default) multiplies by max(1, χ²/dof): the sigmas of
    the means are measured, so the covariance is never shrunk below what they imply, and it is
    inflated when the residuals show unmodelled error (tilted faces, motion, drift). "always"
    multiplies by χ²/dof (scipy curve_fit's default), "never" by 1. Unweighted: always by
    χ²/dof (the residuals are the only estimate of the noise)."""
    if dof <= 0:
        return 1.0 if weighted else float("nan")
    red = chi2 / dof
    if not weighted:
        return red
    if mode == "inflate":
        return max(1.0, red)
    if mode == "always":
        return red
    if mode == "never":
        return 1.0
    raise ValueError(f"chi2_scaling must be 'inflate', 'always' or 'never', not {mode!r}")


def lower_triangular_form(m) -> tuple[np.ndarray, np.ndarray]:
    """M = L·Q with L lower triangular (positive diagonal) and Q orthogonal: L is M expressed
    in the frame whose x axis is the sensor's X sensitive axis and whose y axis lies in the
    plane of the sensor's X and Y axes — the frame of multi_position. |M⁻¹·(u − b)| does not
    depend on Q, so L is all of M that |a| = g can observe."""
    m = np.asarray(m, dtype=np.float64)
    q, r = np.linalg.qr(m.T)              # mᵀ = q·r  →  m = rᵀ·qᵀ
    d = np.sign(np.diag(r))
    d[d == 0] = 1.0
    L = r.T * d                            # rᵀ·D
    Q = (q * d).T                          # D·qᵀ
    return L, Q


def deletion_chi2(Aw: np.ndarray, rw: np.ndarray, k: int) -> np.ndarray:
    """Per pose (k consecutive whitened rows each): by how much χ² drops when that pose is left
    out of the (linearised) fit, q_i = e_iᵀ (I − H_ii)⁻¹ e_i, H the hat matrix of the whitened
    design Aw, e_i the pose's whitened residuals. q_i is the squared Mahalanobis distance of the
    pose from what the other poses predict for it: χ² with k dof when the model holds and the
    sigmas are right (Cook & Weisberg, Residuals and Influence in Regression, 1982). Infinite
    where the other poses cannot predict the pose (H_ii singular: it alone fixes a parameter)."""
    q, _ = np.linalg.qr(Aw)
    H = q @ q.T
    m = len(rw) // k
    out = np.empty(m)
    for i in range(m):
        sl = slice(k * i, k * i + k)
        A = np.eye(k) - H[sl, sl]
        e = rw[sl]
        if np.linalg.cond(A) > 1e10:
            out[i] = math.inf
        else:
            out[i] = float(e @ np.linalg.solve(A, e))
    return out


