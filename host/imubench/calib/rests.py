"""How far each rest can be trusted: the uncertainty its own motion implies.

A still interval found by the data (calib.static.detect_static) is a pose held by a hand or a
fixture. A hand drifts: the mean of the rest then stands for an attitude (and a |a|) somewhere in
the range the rest passed through. Such a rest is not thrown away; its mean is given the extra
covariance of that range, so a fit weighs it by what it can still say (docs/calibration.md,
"How rests are weighed").

    rest_motion(samples)              RestMotion: the drift, its significance, its covariance
    motion_covariances(acc, rests)    (m, 3, 3) the extra covariance of every rest's mean

Units are those of the samples (m/s², counts, g); angles in degrees.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special   # χ² survival function (chdtrc): lighter to import than scipy.stats

from imubench.calib.static import interval_stats

__all__ = ["ALPHA_DRIFT", "RestMotion", "RestRecord", "rest_motion", "motion_covariances"]

# A rest "moved" when the difference between the means of its first and last thirds is this
# unlikely under its own noise (χ² with 3 degrees of freedom, noise correlation included).
ALPHA_DRIFT = 1e-3
# A linear drift from the first third's centre to the last third's spans 2/3 of the rest:
# the whole rest moved 1.5 × the difference of the thirds.
_SPAN = 1.5


@dataclass
class RestRecord:
    """One rest of a recording as the accelerometer fit used it (what a segmentation plot and
    the rests table show). use: "used", "down-weighted" (its own motion inflated its sigma by
    sigma_inflation) or "left out" (use_reason says why, with the numbers)."""
    start: int                    # sample index of its first sample
    stop: int                     # exclusive
    t_start_s: float
    duration_s: float
    face: str
    use: str = "used"
    use_reason: str = ""
    sigma_inflation: float = 1.0  # sigma the fit weighed it by / its noise sigma (≥ 1)
    motion: dict | None = None    # direction_deg, magnitude_change_mg, drift_chi2, drift_p


@dataclass
class RestMotion:
    """What a rest's own samples say about its motion (units of the samples)."""
    drift: np.ndarray             # (3,) mean(last third) − mean(first third)
    chi2: float                   # drift against its noise, 3 dof
    p: float                      # probability of a drift at least this large from noise alone
    significant: bool             # p < ALPHA_DRIFT
    cov: np.ndarray               # (3, 3) covariance added to the rest's mean (0 unless significant)
    direction_deg: float          # angle between the first and last thirds' means
    magnitude_change: float       # |mean(last third)| − |mean(first third)|

    def describe(self, g: float) -> str:
        """'moved 0.12° in direction and +0.05 mg in |a| (drift χ² = 40 for 3 dof)', g in the
        samples' unit (for mg)."""
        return (f"moved {_fmt(self.direction_deg)}° in direction and {self.magnitude_change / g * 1e3:+.2g} mg in "
                f"|a| within it (drift χ² = {self.chi2:.3g} for 3 dof, p = {self.p:.1g})")


def _fmt(x: float) -> str:
    return f"{x:.2g}" if x < 10 else f"{x:.0f}"


def rest_motion(samples) -> RestMotion:
    """The motion of one rest (n, 3) from its own samples. The drift d = mean(last third) −
    mean(first third) is tested against its noise (each third's mean σ from interval_stats, so
    correlated noise counts): χ² = Σ d²/σ_d² with 3 dof. Where it is significant (p <
    ALPHA_DRIFT) the rest moved by D = 1.5·d over its length, and its mean stands for any
    point of that range: the covariance of a uniform spread along D, D·Dᵀ/12, is added to the
    mean's. Otherwise nothing is added."""
    x = np.asarray(samples, dtype=np.float64)
    n = len(x)
    t = n // 3
    zero = np.zeros((3, 3))
    if t < 2:
        return RestMotion(np.zeros(3), 0.0, 1.0, False, zero, 0.0, 0.0)
    m1, _, s1 = interval_stats(x[:t])
    m3, _, s3 = interval_stats(x[-t:])
    d = m3 - m1
    var = np.maximum(s1 ** 2 + s3 ** 2, 1e-300)
    chi2 = float(np.sum(d * d / var))
    p = float(special.chdtrc(3, chi2))
    c = float(np.dot(m1, m3) / max(np.linalg.norm(m1) * np.linalg.norm(m3), 1e-300))
    ang = math.degrees(math.acos(min(1.0, max(-1.0, c))))
    sig = p < ALPHA_DRIFT
    big = _SPAN * d
    cov = np.outer(big, big) / 12.0 if sig else zero
    return RestMotion(d, chi2, p, sig, cov, ang, float(np.linalg.norm(m3) - np.linalg.norm(m1)))


def motion_covariances(acc, rests) -> tuple[np.ndarray, list[RestMotion]]:
    """(m, 3, 3) covariance each rest's motion adds to its mean, and the RestMotion of each;
    rests: objects with start and stop (sample indices into acc)."""
    a = np.asarray(acc, dtype=np.float64)
    mot = [rest_motion(a[r.start:r.stop]) for r in rests]
    return np.array([m.cov for m in mot]).reshape(len(mot), 3, 3), mot
