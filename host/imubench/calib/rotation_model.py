"""The rotation method's solver: the motions between rests, the gravity-direction model, its
Jacobians, the least-squares fit and its covariance (calib.gyro.rotation_method is the front end
that checks the inputs and decides observability; this module does the numbers).

Model (docs/conventions.md): the gyro reads u = M·x + b_j during motion j, x the body rate in
rad/s. With P = M⁻¹, x = P·(u − b_j) is integrated over motion j (calib.gyro.integrate_rotation)
to R_j, the attitude after the motion in the frame before it; the previous rest's gravity
direction seen after the motion is predicted as g_pred = R_jᵀ·g_prev and compared with the next
rest's measured g_next along two directions perpendicular to it (radians, divided by the
motion's expected noise σ_j).

b_j is the bias during motion j, (J, 3) rad/s: one rest bias for every motion, or a bias that
depends on the attitude (g-sensitivity, calib.gsens) interpolated between the rests around
each motion. Its uncertainty enters the covariance of M through ∂r/∂b.

numpy/scipy only; nothing here touches a port or a file.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

from imubench.calib.rotint import (
    _quat_chain,
    _quat_matrix,
    _quat_matrix_cf,
    _quat_prefix,
    _rotate,
    _rotvec_quat,
    _skew_rows,
    _step_vectors,
    _tangent_basis,
)


@dataclass
class Motions:
    """The J motions used: padded sample runs and what each is compared with."""

    h: float                    # sample period, s
    Uc: np.ndarray              # (3, J, L) readings, component-first, padded with the start sample
    lens: np.ndarray            # (J,) samples in each run (from the last rest sample to the next rest's first)
    step_mask: np.ndarray       # (J, L-1) True for the steps inside each run
    valid: np.ndarray           # (J, L) True for the samples inside each run
    dur: np.ndarray             # (J,) s
    g_prev: np.ndarray          # (J, 3) unit gravity direction at the rest before
    g_next: np.ndarray          # (J, 3) unit gravity direction at the rest after
    T: np.ndarray               # (J, 2, 3) basis perpendicular to g_next
    sigma: np.ndarray           # (J,) rad per residual component
    noise_density: np.ndarray   # (3,) rad/s/√Hz from the rests

    @property
    def J(self) -> int:
        return len(self.lens)


def motions(u: np.ndarray, fs_hz: float, iv: np.ndarray, g: np.ndarray, gsig: np.ndarray,
            keep: np.ndarray) -> Motions:
    """Cut the motions between consecutive rests (those with keep[j] True) out of u (n, 3)."""
    h = 1.0 / fs_hz
    k = len(iv)
    starts = iv[:-1, 1][keep] - 1
    ends = iv[1:, 0][keep]
    lens = ends - starts + 1
    L = int(lens.max())
    idx = starts[:, None] + np.arange(L)[None, :]
    valid = np.arange(L)[None, :] < lens[:, None]
    idx = np.where(valid, idx, starts[:, None])
    Uc = np.ascontiguousarray(np.moveaxis(u[idx], -1, 0))
    step_mask = np.arange(L - 1)[None, :] < (lens - 1)[:, None]
    dur = (lens - 1) * h
    # gyro white noise from the rests (weights only; the covariance is rescaled by χ²)
    dev = np.concatenate([u[a:z] - u[a:z].mean(axis=0) for a, z in iv])
    nst = int(sum(z - a for a, z in iv))
    var = np.sum(dev**2, axis=0) / (nst - k) if nst - k >= 3 else np.zeros(3)
    nd = np.sqrt(var * h)
    nd2 = max(float(np.mean(nd**2)), 1e-18)
    sig = np.sqrt(nd2 * dur + gsig[:-1][keep] ** 2 + gsig[1:][keep] ** 2)
    gp0, gn1 = g[:-1][keep], g[1:][keep]
    return Motions(h=h, Uc=Uc, lens=lens, step_mask=step_mask, valid=valid, dur=dur, g_prev=gp0, g_next=gn1,
                   T=_tangent_basis(gn1), sigma=np.maximum(sig, 1e-12), noise_density=nd)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (rad) between the rows of a and b."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


class GravityModel:
    """Residuals and Jacobians of the gravity directions after each motion, for M (row-major)
    and for the bias during each motion."""

    def __init__(self, mo: Motions, motion_bias: np.ndarray):
        self.mo = mo
        self.b = np.broadcast_to(np.asarray(motion_bias, float), (mo.J, 3)).copy()
        # quadrature-weighted (u − b) per step: the linear part of φ is P·v_lin
        self._vlin = _step_vectors(mo.Uc - self.b.T[:, :, None], mo.h, mo.lens, mo.step_mask, coning=False)
        self._gx = _skew_rows(mo.g_prev)

    def _phi(self, mflat: np.ndarray, bb: np.ndarray | None = None):
        mo = self.mo
        bb = self.b if bb is None else np.broadcast_to(bb, (mo.J, 3))
        P = np.linalg.inv(mflat.reshape(3, 3))
        X = np.tensordot(P, mo.Uc, axes=1) - (P @ bb.T)[:, :, None]
        return P, _step_vectors(X, mo.h, mo.lens, mo.step_mask)

    def rotations(self, mflat: np.ndarray, bb: np.ndarray | None = None) -> np.ndarray:
        """(J, 3, 3): each motion's rotation with M = mflat and bias bb (default: the model's)."""
        return _rotate(self._phi(mflat, bb)[1])

    def predicted(self, mflat: np.ndarray, bb: np.ndarray | None = None) -> np.ndarray:
        """(J, 3): the previous rest's gravity direction carried through each motion."""
        return np.einsum("jca,jc->ja", self.rotations(mflat, bb), self.mo.g_prev)

    def residual(self, mflat: np.ndarray, bb: np.ndarray | None = None) -> np.ndarray:
        mo = self.mo
        return (np.einsum("jkc,jc->jk", mo.T, self.predicted(mflat, bb)) / mo.sigma[:, None]).ravel()

    def angles(self, mflat: np.ndarray, bb: np.ndarray | None = None) -> np.ndarray:
        """(J,) rad: angle between predicted and measured gravity after each motion."""
        return angle_between(self.predicted(mflat, bb), self.mo.g_next)

    def jacobian(self, mflat: np.ndarray, with_bias: bool = False):
        """Analytic Jacobian of residual() w.r.t. M (2J, 9), and optionally w.r.t. a bias common
        to all motions (2J, 3).

        A perturbation of the step rotation vectors δφ_k changes the motion's rotation as
        δR = [δθ]×·R with δθ = Σ_k A_{k+1}·J_r(φ_k)·δφ_k in the start frame (A_{k+1} the
        attitude after step k, J_r ≈ I − ½[φ_k]×); δφ_k = δP·v_k (coning term's derivative
        neglected, relative size ~h·|ω|/6) and δP = −P·δM·P. Then δ(Rᵀg) = Rᵀ·(g × δθ).
        """
        mo, J = self.mo, self.mo.J
        P, phi = self._phi(mflat)
        q = _rotvec_quat(phi)
        A = _quat_matrix_cf(_quat_prefix(q))                        # (3, 3, J, L-1)
        R = _quat_matrix(_quat_chain(q))                            # (J, 3, 3)
        Q = A.copy()                                                # Q_k = A_{k+1}·(I − ½[φ_k]×)
        hp = 0.5 * phi
        Q[:, 0] -= A[:, 1] * hp[2] - A[:, 2] * hp[1]
        Q[:, 1] -= A[:, 2] * hp[0] - A[:, 0] * hp[2]
        Q[:, 2] -= A[:, 0] * hp[1] - A[:, 1] * hp[0]
        dth_dp = np.einsum("cajk,bjk->jcab", Q, self._vlin)         # ∂θ/∂P_ab (J, 3, 3, 3)
        dth_dm = -np.einsum("jcab,ae,fb->jcef", dth_dp, P, P).reshape(J, 3, 9)
        W = np.einsum("jkc,jdc,jde->jke", mo.T, R, self._gx) / mo.sigma[:, None, None]   # T·Rᵀ·[g]× /σ
        jm = np.einsum("jke,jep->jkp", W, dth_dm).reshape(2 * J, 9)
        if not with_bias:
            return jm
        dth_db = -mo.h * np.einsum("cajk,jk,ad->jcd", Q, mo.step_mask.astype(float), P)   # (J, 3, 3)
        jb = np.einsum("jke,jep->jkp", W, dth_db).reshape(2 * J, 3)
        return jm, jb

    def jacobian_fd(self, mflat: np.ndarray, step: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
        """Forward differences of residual() w.r.t. M and a common bias (a check on jacobian())."""
        r0 = self.residual(mflat)
        jm = np.empty((r0.size, 9))
        for i in range(9):
            xx = mflat.copy()
            xx[i] += step
            jm[:, i] = (self.residual(xx) - r0) / step
        jb = np.empty((r0.size, 3))
        for i in range(3):
            bb = self.b.copy()
            bb[:, i] += step
            jb[:, i] = (self.residual(mflat, bb) - r0) / step
        return jm, jb


class _Held:
    """A GravityModel seen through its free entries of M (the others fixed at mflat's)."""

    def __init__(self, model: GravityModel, mflat: np.ndarray, free: np.ndarray):
        self.model, self.x0, self.free = model, np.asarray(mflat, float).copy(), free

    def jacobian(self, x, with_bias: bool = False):
        t = self.x0.copy()
        t[self.free] = x
        out = self.model.jacobian(t, with_bias=with_bias)
        return (out[0][:, self.free], out[1]) if with_bias else out[:, self.free]


@dataclass
class Solution:
    m: np.ndarray               # (3, 3)
    m_cov: np.ndarray           # (9, 9) incl. the bias's uncertainty propagated
    mb_cov: np.ndarray | None   # (9, 3) cross-covariance with the bias, or None (bias exact)
    chi2: float
    dof: int
    reduced_chi2: float
    nfev: int
    converged: bool
    message: str
    residual: np.ndarray        # weighted residuals at the solution


def solve(model: GravityModel, m0: np.ndarray, cov_b: np.ndarray | None, free=None,
          held_sigma: float = 0.0) -> Solution:
    """Levenberg–Marquardt on M (scipy.optimize.least_squares); covariance = (JᵀJ)⁻¹ scaled by
    the reduced χ² (with the common bias error removed from χ²), plus ∂M/∂b·Σb·∂M/∂bᵀ.
    free: (9,) bool, the entries of M (row-major) fitted; the others are held at m0's and
    considered (Schmidt 1966): held_sigma, the size they may have, is carried into the fitted
    entries' covariance (K·σ²·Kᵀ, K = −(J_fᵀJ_f)⁻¹J_fᵀJ_h) and is their own σ."""
    free = np.ones(9, bool) if free is None else np.asarray(free, bool)
    x0 = m0.ravel().astype(float)

    def full(x):
        t = x0.copy()
        t[free] = x
        return t

    sol = optimize.least_squares(lambda x: model.residual(full(x)), x0[free],
                                 jac=lambda x: model.jacobian(full(x))[:, free], method="lm",
                                 xtol=1e-10, ftol=1e-10, gtol=1e-10)
    x = full(sol.x)
    rw = model.residual(x)
    if cov_b is not None:
        Jall, Jb = model.jacobian(x, with_bias=True)
    else:
        Jall, Jb = model.jacobian(x), None
    Jm, Jh = Jall[:, free], Jall[:, ~free]
    C = np.linalg.pinv(Jm.T @ Jm)
    chi2 = float(rw @ rw)
    if cov_b is not None:
        # the rest-bias error is common to all motions: residual covariance I + Jb·Σb·Jbᵀ
        Lb = np.linalg.cholesky(cov_b + 1e-30 * np.eye(3))
        Z = Jb @ Lb
        v = Z.T @ rw
        chi2 -= float(v @ np.linalg.solve(np.eye(3) + Z.T @ Z, v))
    dof = rw.size - int(free.sum())
    s2 = chi2 / dof if dof > 0 else float("nan")
    cf = C * s2 if dof > 0 else C
    mb_cov = None
    if cov_b is not None:
        dm_db = -C @ (Jm.T @ Jb)                                   # (free, 3)
        cf = cf + dm_db @ cov_b @ dm_db.T
        mb_cov = np.zeros((9, 3))
        mb_cov[free] = dm_db @ cov_b
    if Jh.shape[1] and held_sigma > 0:
        K = -C @ (Jm.T @ Jh)
        cf = cf + K @ K.T * held_sigma ** 2
    m_cov = np.zeros((9, 9))
    m_cov[np.ix_(free, free)] = cf
    m_cov[~free, ~free] = held_sigma ** 2
    return Solution(m=x.reshape(3, 3), m_cov=m_cov, mb_cov=mb_cov, chi2=chi2, dof=dof, reduced_chi2=s2,
                    nfev=int(sol.nfev), converged=bool(sol.status > 0), message=str(sol.message), residual=rw)


def parameter_sigmas(model: GravityModel, mflat: np.ndarray, noise_scale: float,
                     cov_b: np.ndarray | None, free=None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted 1σ of M's 9 entries at mflat before fitting (inf where the motions leave an
    entry undetermined), with the residuals' scale noise_scale and the bias's uncertainty; and
    the null direction (9,) of the Jacobian when it is singular (else zeros). free: the
    entries fitted (the others held: σ 0 here)."""
    free = np.ones(9, bool) if free is None else np.asarray(free, bool)
    if not free.all():
        sig, null = parameter_sigmas(_Held(model, mflat, free), mflat[free], noise_scale, cov_b)
        out, nul = np.zeros(9), np.zeros(9)
        out[free], nul[free] = sig, null
        return out, nul
    if cov_b is not None:
        Jm, Jb = model.jacobian(mflat, with_bias=True)
    else:
        Jm, Jb = model.jacobian(mflat), None
    cn = np.linalg.norm(Jm, axis=0)
    s, vt = np.linalg.svd(Jm / np.maximum(cn, 1e-300), full_matrices=False)[1:]
    null = np.zeros(Jm.shape[1])
    if np.any(cn < 1e-9 * max(cn.max(), 1e-300)) or s[-1] < 1e-7 * s[0]:
        null = vt[-1]
        sig = np.where(np.abs(null) > 0.3, np.inf, np.nan)
        return sig, null
    C = np.linalg.inv(Jm.T @ Jm)
    cov = C * noise_scale**2
    if Jb is not None:
        d = -C @ (Jm.T @ Jb)
        cov = cov + d @ cov_b @ d.T
    return np.sqrt(np.diag(cov)), null
