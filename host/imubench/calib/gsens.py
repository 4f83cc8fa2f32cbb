"""Gyro g-sensitivity: a bias that depends on the specific force the gyro feels.

Model (docs/conventions.md, "Gyro g-sensitivity"):

    u = M·x + b + G·f          f: the calibrated specific force in g (+1 g "up" at rest)

G (3×3) in rad/s per g here (°/s per g where printed); the ADXRS450 data sheet gives 0.03 °/s/g
typical ("linear acceleration effect"). At rest x ≈ 0 (the Earth's rate, ≤ 0.0042 °/s, is left
in b), so each rest's gyro mean is ū_j = b + G·f_j: with rests in attitudes whose f_j span three
dimensions (and an offset), b and G follow by linear least squares, row by row.

    fit_gsens(rest_means, rest_sigmas, f_g)   GSensFit: b, G, covariance, which entries are resolved
    GSensFit.bias(f_g)                        the bias predicted for specific forces f (n, 3) in g

The fit is refused (NotObservable) when the attitudes cannot separate G from b (fewer than
four rests, or their f_j lying in a plane through no offset: the design is singular), naming
the entries; an entry whose σ exceeds max_sigma is refused likewise. G is "resolved" when it
differs from zero jointly at p < 0.01 (χ², 9 dof); entries beyond 2σ are listed. The rest-to-rest scatter beyond the
rests' own noise (bias drift, a bump) scales the covariance by the reduced χ² when it is > 1.

numpy only; nothing here touches a port or a file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from imubench.calib import CalibrationError, NotObservable, TriadFit

DPS = 180.0 / math.pi
MAX_SIGMA_DPS_PER_G = 0.2       # refuse an entry known no better than this (°/s per g)


@dataclass
class GSensFit:
    b: np.ndarray               # (3,) rad/s: the bias at zero specific force
    g: np.ndarray               # (3, 3) rad/s per g
    cov: np.ndarray             # (12, 12): covariance of (G row-major, b)
    chi2: float
    dof: int
    residuals: np.ndarray       # (k, 3) rad/s: rest means minus the model
    extra: dict = field(default_factory=dict)

    @property
    def sigma_g(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov)[:9], 0, None)).reshape(3, 3)

    @property
    def sigma_b(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov)[9:], 0, None))

    @property
    def resolved(self) -> np.ndarray:
        """(3, 3) True where |G| > 2σ (per entry; with 9 entries one may pass by chance)."""
        return np.abs(self.g) > 2.0 * self.sigma_g

    @property
    def p_zero(self) -> float:
        """p-value of G = 0 (all nine entries jointly, χ² with 9 dof from G's covariance)."""
        from scipy import special
        c = self.cov[:9, :9]
        v = self.g.ravel()
        return float(special.chdtrc(9, float(v @ np.linalg.solve(c, v))))

    @property
    def significant(self) -> bool:
        """G differs from zero at p < 0.01 (jointly): then it is worth applying."""
        return self.p_zero < 0.01

    def bias(self, f_g) -> np.ndarray:
        """The bias b + G·f (rad/s) for specific forces f (n, 3) or (3,) in g."""
        f = np.asarray(f_g, float)
        return self.b + f @ self.g.T

    def summary(self) -> str:
        g, s = self.g * DPS, self.sigma_g * DPS
        rows = ["  " + "  ".join(f"{g[i, j]:+.4f} ± {s[i, j]:.4f}" for j in range(3)) for i in range(3)]
        res = self.resolved
        word = (f"{'resolved' if self.significant else 'not resolved'} (p = {self.p_zero:.2g} that G = 0, all entries jointly); "
                + ("no entry beyond 2σ" if not res.any() else
                   "beyond 2σ: " + ", ".join(f"G{i}{j}" for i, j in zip(*np.nonzero(res)))))
        return "gyro g-sensitivity G (°/s per g), " + word + ":\n" + "\n".join(rows)


def fit_gsens(rest_means, rest_sigmas, f_g, *, max_sigma_dps_per_g: float = MAX_SIGMA_DPS_PER_G,
              sigma_from_scatter: bool = False) -> GSensFit:
    """b and G from the rests' gyro means (k, 3) rad/s, their 1σ (k, 3) rad/s, and the rests'
    specific force f (k, 3) in g (the calibrated accelerometer's mean, ≈ unit "up").
    sigma_from_scatter: the given sigmas are relative weights only (e.g. all ones); the
    covariance is scaled by the reduced χ² whatever its value."""
    u = np.asarray(rest_means, float)
    s = np.asarray(rest_sigmas, float)
    f = np.asarray(f_g, float)
    k = len(u)
    if u.shape != (k, 3) or s.shape != (k, 3) or f.shape != (k, 3):
        raise CalibrationError("fit_gsens: rest means, sigmas and specific forces must each be (k, 3)")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(f)) and np.all(s > 0)):
        raise CalibrationError("fit_gsens: non-finite means or specific forces, or sigmas not > 0")
    if k < 5:
        raise NotObservable(f"g-sensitivity: {k} rests; b and G (12 parameters, 4 per axis) need at least 5 "
                            "rests in attitudes spanning three directions (the six faces do)")
    A = np.column_stack([f, np.ones(k)])                      # (k, 4): G row, b
    cn = np.linalg.norm(A, axis=0)
    an = A / np.maximum(cn, 1e-300)
    _, sv, vt = np.linalg.svd(an, full_matrices=True)
    if np.any(cn < 1e-9) or sv[-1] < 1e-6 * sv[0]:
        v = vt[-1] if np.all(cn >= 1e-9) else (cn < 1e-9).astype(float)
        names = [(f"G's column {'xyz'[i]} (the response to f_{'xyz'[i]})") if i < 3 else "the bias b"
                 for i in range(4) if abs(v[i]) > 0.2]
        raise NotObservable("g-sensitivity: the rests' attitudes cannot separate " + ", ".join(names)
                            + " (σ unbounded): rest with the board in attitudes that span three directions, "
                            "e.g. each face up once")
    G = np.empty((3, 3))
    b = np.empty(3)
    cov = np.zeros((12, 12))
    resid = np.empty((k, 3))
    chi2 = 0.0
    for i in range(3):
        w = 1.0 / s[:, i]
        Aw = A * w[:, None]
        sol, *_ = np.linalg.lstsq(Aw, u[:, i] * w, rcond=None)
        C = np.linalg.inv(Aw.T @ Aw)
        G[i], b[i] = sol[:3], sol[3]
        resid[:, i] = u[:, i] - A @ sol
        chi2 += float(np.sum((resid[:, i] * w) ** 2))
        idx = [3 * i, 3 * i + 1, 3 * i + 2, 9 + i]
        cov[np.ix_(idx, idx)] = C
    dof = 3 * k - 12
    red = chi2 / dof if dof > 0 else float("nan")
    if dof > 0 and (red > 1.0 or sigma_from_scatter):
        cov *= red
    elif sigma_from_scatter:
        raise NotObservable(f"g-sensitivity: {k} rests leave no degree of freedom to estimate the noise from")
    fit = GSensFit(b=b, g=G, cov=cov, chi2=chi2, dof=dof, residuals=resid,
                   extra={"reduced_chi2": red, "n_rests": k,
                          "rest_scatter_dps": float(np.sqrt(np.mean(resid**2))) * DPS})
    sig = fit.sigma_g.ravel() * DPS
    over = np.flatnonzero(~(sig <= max_sigma_dps_per_g))
    if over.size:
        raise NotObservable("g-sensitivity: " + ", ".join(f"G{i // 3}{i % 3} σ {sig[i]:.3g} °/s/g" for i in over)
                            + f" above the limit {max_sigma_dps_per_g:g} °/s/g: the rests' attitudes or their "
                            "length leave it undetermined (longer rests, more attitudes)")
    return fit


def zero_force_bias(gsens, bias: TriadFit) -> TriadFit:
    """The g-sensitivity fit's bias at zero specific force, with its covariance, as the fixed
    bias of a gyro fit whose readings are taken less G·f (rotation method, turntable)."""
    from imubench.calib.gyro import _cov12
    return TriadFit(method="bias", m=np.eye(3), b=gsens.b.copy(), cov=_cov12(b_cov=gsens.cov[9:, 9:]),
                    estimated=np.array([False] * 9 + [True] * 3), extra=dict(bias.extra))


def with_zero_force_bias(fit: TriadFit, gsens) -> TriadFit:
    """fit with b (and its covariance) replaced by the g-sensitivity fit's bias at zero
    specific force (M and its covariance kept)."""
    cov = np.array(fit.cov, dtype=float)
    cov[9:, :] = np.nan
    cov[:, 9:] = np.nan
    cov[9:, 9:] = gsens.cov[9:, 9:]
    extra = dict(fit.extra, bias_source="g-sensitivity fit (b at zero specific force)")
    return TriadFit(method=fit.method, m=fit.m, b=gsens.b.copy(), cov=cov, residual_rms=fit.residual_rms,
                    residuals=fit.residuals, dof=fit.dof, estimated=np.array(list(fit.estimated[:9]) + [True] * 3),
                    extra=extra)
