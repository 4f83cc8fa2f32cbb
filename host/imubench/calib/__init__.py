"""Calibration algorithms. Pure numpy/scipy: nothing here touches a serial port.

Model (docs/conventions.md), per sensor triad, with u the nominally scaled measurement and
x the true quantity, both in SI:

    u = M · x + b          x = M⁻¹ · (u − b)

Every fit returns a TriadFit: M, b and their 1-sigma uncertainties, with the covariance of
the 12 parameters in the order (M row-major, then b) — the order of the device's parameter
block (protocol `params`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imubench.errors import ImubenchError


class CalibrationError(ImubenchError, ValueError):
    """The data cannot give a calibration; the message says why and what to do."""


class NotObservable(CalibrationError):
    """The poses or motions do not constrain every parameter (e.g. an axis never pointed
    both up and down)."""


@dataclass
class TriadFit:
    """Result of a triad calibration. Units: M dimensionless, b in SI (m/s² or rad/s)."""

    method: str                       # "six_position", "multi_position", "turntable", "rotation", "bias"
    m: np.ndarray                     # (3, 3)
    b: np.ndarray                     # (3,)
    cov: np.ndarray                   # (12, 12): covariance of (M row-major, b); NaN where not estimated,
                                      # 0 where the model fixes an entry (multi-position's upper triangle)
    residual_rms: float = float("nan")     # RMS of the fit's residuals, in the residual's unit
    residuals: np.ndarray | None = None    # per observation (pose or segment)
    dof: int = 0                           # observations minus estimated parameters
    estimated: np.ndarray = field(default_factory=lambda: np.ones(12, dtype=bool))  # which of the 12 were fitted
    extra: dict = field(default_factory=dict)  # method-specific (angles, scales, their sigmas, ...)

    @property
    def sigma_m(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov)[:9], 0, None)).reshape(3, 3)

    @property
    def sigma_b(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov)[9:], 0, None))

    def correct(self, u: np.ndarray) -> np.ndarray:
        """x = M⁻¹ (u − b) for measurements u (n, 3)."""
        return (np.asarray(u, dtype=np.float64) - self.b) @ np.linalg.inv(self.m).T


def face_of(d: np.ndarray) -> str:
    """The board face a specific force points (the up axis, "+X" ... "-Z"), or "other" when
    it is more than 30° off every axis."""
    import math
    k = int(np.argmax(np.abs(d)))
    ang = math.degrees(math.acos(min(1.0, abs(d[k]) / np.linalg.norm(d))))
    return (("+" if d[k] > 0 else "-") + "XYZ"[k]) if ang <= 30.0 else "other"
