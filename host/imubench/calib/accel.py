"""Accelerometer calibration from static poses: the six-position linear least squares and the
multi-position |a| = g fit (Shin & El-Sheimy 2001, as modified by Syed et al. 2007).

Input: one mean per pose (the specific force the board measured while still, u in the model
u = M·x + b of docs/conventions.md) and, best, its 1-sigma uncertainty (StaticInterval.sigma_mean).
Units are free — m/s² or raw counts — as long as g is given in the same unit (g = 256000 for
±2 g counts); M is dimensionless either way and b comes back in the unit of the input.

    six_position(means, sigmas)              12 parameters, the faces must be square to gravity
                                             (calib.six_position; its shared least squares in
                                             calib.accel_lsq)
    multi_position(means, sigmas, init)      9 parameters, any attitudes, |a| = g
    POSE_PLAN, match_plan(means)             the 26 attitudes and which of them were covered
    check_observability(means, method)       raises NotObservable with the reason
    pose_table(means, fit)                   |a| before / after per pose
    lower_triangular_form(m)                 M = L·Q, the part of M that |a| = g can see

docs/calibration.md states the models, the parametrisation and what the covariance means.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from imubench.calib import CalibrationError, NotObservable, TriadFit
from imubench.calib.poseplan import (  # noqa: F401 - POSE_PLAN, PlannedPose, match_plan, pose_table: where callers found them
    _PLAN_DIRS,
    AXES,
    _FACE_NAMES,
    POSE_PLAN,
    PlannedPose,
    _units,
    match_plan,
    pose_table,
)
from imubench.calib.accel_lsq import (  # noqa: F401 - lower_triangular_form, deletion_chi2: where callers found them
    _check_g,
    _chi2_factor,
    _sigmas,
    deletion_chi2,
    lower_triangular_form,
)
from imubench.calib.six_position import (  # noqa: F401 - where callers found them
    FACE_TOL_DEG,
    FACES,
    _check_faces,
    _face_report,
    identify_faces,
    six_position,
)
from imubench.units import G0_MPS2

__all__ = [
    "FACES", "POSE_PLAN", "PlannedPose", "MULTI_PARAM_NAMES", "six_position", "multi_position",
    "identify_faces", "match_plan", "check_observability", "pose_table", "lower_triangular_form",
    "multi_params_to_mb",
]

DISTINCT_DEG = 10.0          # two poses closer than this are the same attitude
UPDOWN_COS = 0.5          # an axis "pointed up": within 60° of vertical (corners count)
MIN_ATTITUDES = 9
GOOD_ATTITUDES = 12
DOP_WARN = 4.0
DOP_MAX = 25.0
MULTI_PARAM_NAMES = ("b_x", "b_y", "b_z", "s_x", "s_y", "s_z", "a_yx", "a_zx", "a_zy")
# (row, column) of M that each angle sits in: M = diag(s)·(I + A), A strictly lower triangular
_ANGLE_POS = ((1, 0), (2, 0), (2, 1))


# --------------------------------------------------------------------------------------------
# multi-position
# --------------------------------------------------------------------------------------------

def multi_params_to_mb(theta) -> tuple[np.ndarray, np.ndarray]:
    """θ = (b_x, b_y, b_z, s_x, s_y, s_z, a_yx, a_zx, a_zy) → (M, b), M = diag(s)·(I + A) with
    A strictly lower triangular: A[1,0] = a_yx, A[2,0] = a_zx, A[2,1] = a_zy."""
    t = np.asarray(theta, dtype=np.float64)
    b = t[0:3].copy()
    s = t[3:6]
    T = np.eye(3)
    for (r, c), a in zip(_ANGLE_POS, t[6:9]):
        T[r, c] = a
    return s[:, None] * T, b


def _mb_to_params(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    L, _ = lower_triangular_form(M)
    s = np.diag(L).copy()
    ang = [L[r, c] / s[r] for r, c in _ANGLE_POS]
    return np.concatenate([np.asarray(b, float), s, ang])


def _param_jacobian_mb(theta) -> np.ndarray:
    """d(M row-major, b)/dθ, (12, 9)."""
    t = np.asarray(theta, dtype=np.float64)
    s = t[3:6]
    T = np.eye(3)
    for (r, c), a in zip(_ANGLE_POS, t[6:9]):
        T[r, c] = a
    G = np.zeros((12, 9))
    G[9:, 0:3] = np.eye(3)
    for j in range(3):                        # ∂M[j, k]/∂s_j = T[j, k]
        for k in range(3):
            G[3 * j + k, 3 + j] = T[j, k]
    for p, (r, c) in enumerate(_ANGLE_POS):   # ∂M[r, c]/∂a = s_r
        G[3 * r + c, 6 + p] = s[r]
    return G


def _residuals_and_jac(theta, u, g):
    """r_i = |x_i| − g, x_i = M⁻¹(u_i − b), and dr/dθ (m, 9)."""
    M, b = multi_params_to_mb(theta)
    Minv = np.linalg.inv(M)
    x = (u - b) @ Minv.T
    nx = np.linalg.norm(x, axis=1)
    r = nx - g
    xh = x / nx[:, None]
    v = xh @ Minv                               # rows: M⁻ᵀ x̂  (dr/du)
    s = theta[3:6]
    T = M / s[:, None]
    J = np.empty((len(u), 9))
    J[:, 0:3] = -v                              # dr/db
    Tx = x @ T.T                                # (T x)_j
    J[:, 3:6] = -v * Tx                         # dr/ds_j = −v_j (T x)_j
    for p, (rr, cc) in enumerate(_ANGLE_POS):   # dr/da = −v_r s_r x_c
        J[:, 6 + p] = -v[:, rr] * s[rr] * x[:, cc]
    return r, J, v


def _ellipsoid_init(u: np.ndarray, g: float) -> np.ndarray | None:
    """Algebraic quadric fit to the means (normalised by g), → θ, or None if it is not an
    ellipsoid (too few or badly spread poses)."""
    v = u / g
    if len(v) < 9:
        return None
    x, y, z = v.T
    D = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z,
                         np.ones_like(x)])
    try:
        _, _, vt = np.linalg.svd(D, full_matrices=False)
    except np.linalg.LinAlgError:
        return None
    p = vt[-1]
    Aq = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    bq = p[6:9]
    try:
        c0 = -np.linalg.solve(Aq, bq)
    except np.linalg.LinAlgError:
        return None
    k = c0 @ Aq @ c0 - p[9]
    if k == 0:
        return None
    P = Aq / k                                   # (v − c0)ᵀ P (v − c0) = 1
    try:
        Mm = np.linalg.cholesky(np.linalg.inv(P))  # M Mᵀ = P⁻¹, M lower triangular
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(Mm)) or np.any(np.diag(Mm) < 0.2) or np.any(np.diag(Mm) > 5):
        return None
    if np.any(np.abs(c0) > 1.0):
        return None
    return _mb_to_params(Mm, c0 * g)


def _minmax_init(u: np.ndarray, g: float) -> np.ndarray:
    b = np.zeros(3)
    s = np.ones(3)
    for a in range(3):
        hi, lo = u[:, a].max(), u[:, a].min()
        if hi > 0.5 * g and lo < -0.5 * g:
            b[a] = 0.5 * (hi + lo)
            s[a] = 0.5 * (hi - lo) / g
    return np.concatenate([b, s, np.zeros(3)])


def _obs_jacobian(d: np.ndarray) -> np.ndarray:
    """The |a| = g Jacobian at M = I, b = 0 for unit directions d (m, 3); bias columns per g."""
    J = np.empty((len(d), 9))
    J[:, 0:3] = -d
    J[:, 3:6] = -d * d
    for p, (r, c) in enumerate(_ANGLE_POS):
        J[:, 6 + p] = -d[:, r] * d[:, c]
    return J


def _free_mask(hold) -> np.ndarray:
    """Boolean mask over MULTI_PARAM_NAMES: False for the parameters held at nominal."""
    hold = tuple(hold or ())
    bad = [h for h in hold if h not in MULTI_PARAM_NAMES]
    if bad:
        raise ValueError(f"unknown parameters to hold: {bad}; the parameters are {MULTI_PARAM_NAMES}")
    return np.array([n not in hold for n in MULTI_PARAM_NAMES])


NOMINAL_THETA = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def dilution(directions) -> np.ndarray | None:
    """Per parameter of the |a| = g model (MULTI_PARAM_NAMES), its 1-sigma from poses in these
    directions (m, 3) with unit noise on |a|, at the nominal point (M = I, b = 0; biases per
    g); None when the directions leave a parameter unconstrained. What an attitude adds to a
    session can be judged from it before the attitude is presented."""
    return _param_sigmas_unit(_obs_jacobian(_units(directions)))


def _param_sigmas_unit(J: np.ndarray) -> np.ndarray | None:
    N = J.T @ J
    try:
        w = np.linalg.eigvalsh(N)
        if w[0] <= 1e-12 * w[-1]:
            return None
        return np.sqrt(np.diag(np.linalg.inv(N)))
    except np.linalg.LinAlgError:
        return None


_REF_SIGMA_SQRTM = _param_sigmas_unit(_obs_jacobian(_PLAN_DIRS)) * math.sqrt(len(_PLAN_DIRS))


def _ref_sigma_sqrtm(free: np.ndarray) -> np.ndarray:
    """The 26-attitude plan's per-pose sigma of the free parameters (DOP 1)."""
    if free.all():
        return _REF_SIGMA_SQRTM
    return _param_sigmas_unit(_obs_jacobian(_PLAN_DIRS)[:, free]) * math.sqrt(len(_PLAN_DIRS))


def _distinct(d: np.ndarray, tol_deg: float = DISTINCT_DEG) -> int:
    """Number of distinct attitudes: greedy, a pose within tol_deg of a kept one is a repeat."""
    c = math.cos(math.radians(tol_deg))
    close = (d @ d.T) >= c
    keep = np.zeros(len(d), dtype=bool)
    for i in range(len(d)):
        if not np.any(close[i] & keep):
            keep[i] = True
    return int(keep.sum())


def check_observability(means, method: str = "multi_position", hold=()) -> dict:
    """Raise NotObservable with the reason when the poses cannot constrain the model; return a
    report otherwise: {"method", "n_poses", "n_distinct", "dop" (multi: per parameter, 1 = as
    well constrained per pose as the 26-pose plan), "worst", "warnings"}.

    six_position: the six faces must all be present. multi_position: ≥ 9 distinct attitudes
    (warn under 12); every axis pointed up and down (within 60° of ±g: a corner counts); the |a| = g Jacobian at
    the nominal point of full rank, and no parameter's dilution of precision above DOP_MAX.
    hold: names of MULTI_PARAM_NAMES held at nominal (a nested model): the attitudes then need
    to constrain only the others (as many distinct attitudes as free parameters)."""
    u = np.asarray(means, dtype=np.float64)
    d = _units(u)
    rep: dict = {"method": method, "n_poses": len(u), "n_distinct": _distinct(d), "warnings": []}
    if method == "six_position":
        faces, angles = identify_faces(u)
        _check_faces(faces, angles, skip_non_faces=True)
        return rep
    if method != "multi_position":
        raise ValueError(f"method must be 'six_position' or 'multi_position', not {method!r}")

    free = _free_mask(hold)
    nfree = int(free.sum())
    nd = rep["n_distinct"]
    if nd < min(MIN_ATTITUDES, nfree):
        raise NotObservable(
            f"too few poses: {len(u)} given, {nd} distinct attitudes (poses within "
            f"{DISTINCT_DEG:.0f}° count once); the {nfree}-parameter |a| = g model needs at least "
            f"{min(MIN_ATTITUDES, nfree)}, in practice 12–26 well spread (faces, edges and corners: POSE_PLAN)")
    for a in range(3):
        up, down = d[:, a].max(), d[:, a].min()
        lacks = [w for w, ok in (("up", up >= UPDOWN_COS), ("down", down <= -UPDOWN_COS)) if not ok]
        if lacks:
            want = " or ".join(("+" if w == "up" else "-") + f"{AXES[a]} up" for w in lacks)
            raise NotObservable(
                f"the {AXES[a]} axis was never pointed {' or '.join(lacks)}: its reading ranged "
                f"{down:+.2f} … {up:+.2f} of |a| over the poses, and within 60° of "
                f"{' and '.join(('+g' if w == 'up' else '−g') for w in lacks)} is needed, or its bias "
                f"and scale factor cannot be told apart. Add poses with {want} "
                f"(e.g. {', '.join(repr(_face_pose(a, w == 'up')) for w in lacks)}).")
    names_free = [n for n, f in zip(MULTI_PARAM_NAMES, free) if f]
    J = _obs_jacobian(d)[:, free]
    sig = _param_sigmas_unit(J)
    if sig is None:
        # name the parameters of the unconstrained combination (the null vector of the
        # column-normalised normal matrix)
        Jn = J / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
        _, vec = np.linalg.eigh(Jn.T @ Jn)
        v = vec[:, 0]
        names = [names_free[i] for i in np.argsort(-np.abs(v)) if abs(v[i]) > 0.25]
        raise NotObservable(
            f"the poses leave a combination of {', '.join(names)} unconstrained (the |a| = g "
            f"Jacobian is rank-deficient): spread the attitudes over faces, edges and corners "
            f"(POSE_PLAN); {_missing_str(u)}")
    dop = sig * math.sqrt(len(d)) / _ref_sigma_sqrtm(free)
    rep["dop"] = dict(zip(names_free, dop.tolist()))
    worst = int(np.argmax(dop))
    rep["worst"] = names_free[worst]
    if dop[worst] > DOP_MAX:
        raise NotObservable(
            f"the poses constrain {names_free[worst]} poorly: {dop[worst]:.0f}× worse per "
            f"pose than the 26-attitude plan (limit {DOP_MAX:.0f}). Spread the attitudes: "
            f"faces, edges and corners (POSE_PLAN); {_missing_str(u)}")
    if nd < GOOD_ATTITUDES and free.all():
        rep["warnings"].append(f"only {nd} distinct attitudes: ≥ {GOOD_ATTITUDES} give a reliable "
                               f"fit (the 26 of POSE_PLAN best)")
    if dop[worst] > DOP_WARN:
        rep["warnings"].append(f"{names_free[worst]} is weakly constrained "
                               f"({dop[worst]:.1f}× the plan's dilution of precision)")
    return rep


def _missing_str(u) -> str:
    missing = match_plan(u)[1]
    if not missing:
        return "every planned attitude is covered"
    more = f", … ({len(missing) - 8} more)" if len(missing) > 8 else ""
    return f"not yet covered: {', '.join(missing[:8])}{more}"


def _face_pose(axis: int, up: bool) -> str:
    v = [0, 0, 0]
    v[axis] = 1 if up else -1
    return _FACE_NAMES[tuple(v)]


def _best_start(starts, solve, u: np.ndarray, g: float) -> tuple[tuple, int]:
    """Solve from each start in turn; the first that converges to a plausible solution (scales
    within 50 % of 1, |a| residuals below 1 % of g) is kept, else the lowest cost of all.
    Returns ((theta, cost, sol, start, theta0), function evaluations)."""
    best = None
    errors = []
    nfev = 0
    for theta0, start in starts:
        try:
            theta, cost, nf, sol = solve(theta0)
        except (CalibrationError, np.linalg.LinAlgError, ValueError) as e:
            errors.append(f"{start}: {e}")
            continue
        nfev += nf
        ok = np.all(np.abs(theta[3:6] - 1) < 0.5) and float(
            np.sqrt(np.mean(_residuals_and_jac(theta, u, g)[0] ** 2))) < 0.01 * g
        if best is None or cost < best[1] * (1 - 1e-9):
            best = (theta, cost, sol, start, theta0)
        if ok:
            break
    if best is None:
        raise CalibrationError("multi-position fit did not converge from any start ("
                               + "; ".join(errors) + "): give a six-position pre-calibration as init")
    return best, nfev


def multi_position(means, sigmas=None, init: TriadFit | None = None, g: float = G0_MPS2, *,
                   chi2_scaling: str = "inflate", check: bool = True, covs=None, hold=(),
                   held_sigma=None) -> TriadFit:
    """Multi-position calibration: 9 parameters from |M⁻¹(u_i − b)| = g at m ≥ 9 attitudes.

    θ = (b_x, b_y, b_z, s_x, s_y, s_z, a_yx, a_zx, a_zy), M = diag(s)·(I + A), A strictly lower
    triangular (A[1,0] = a_yx, A[2,0] = a_zx, A[2,1] = a_zy): the frame x = the sensor's X
    axis, y in the plane of its X and Y axes (docs/calibration.md). Nonlinear least squares
    (scipy least_squares, Levenberg–Marquardt, analytic Jacobian) on r_i = |x_i| − g weighted by
    the sigma of |x_i| propagated from sigmas; initial values from `init` (e.g. a six-position
    pre-calibration, Syed et al.), else an algebraic ellipsoid fit of the means, else min/max
    per axis (the first start that converges to a plausible solution is kept, else the lowest
    χ² of all). Covariance of θ: (JᵀJ)⁻¹ at the solution × max(1, χ²/dof) (see _chi2_factor),
    propagated to (M, b) through ∂(M, b)/∂θ; the three entries of M above the diagonal are 0
    by the frame convention (estimated = False, variance 0).

    covs (m, 3, 3): a further covariance of each mean (a rest's own motion, calib.rests), added
    to diag(sigmas²) when |x_i|'s sigma is propagated (needs sigmas). hold: names of
    MULTI_PARAM_NAMES held at their nominal values (b = 0, s = 1, angles 0): a nested model,
    fitted on the others; its entries of M / b count as not estimated. held_sigma: {name: σ}
    the size a held parameter may have in truth (its unit: g's unit for biases, 1 for scales, rad
    for angles). It is not assumed exact: a held parameter is a "consider" parameter (Schmidt,
    Application of state-space methods to navigation problems, 1966): its σ adds to each
    pose's |a| sigma what it could change there (J_h σ_h), and to the fitted parameters'
    covariance what it would move them by (K Σ_h Kᵀ, K = −(J_fᵀWJ_f)⁻¹J_fᵀWJ_h); its own
    sigma is reported as given."""
    u = np.asarray(means, dtype=np.float64)
    _units(u)
    _check_g(u, g)
    m = len(u)
    free = _free_mask(hold)
    rep = check_observability(u, "multi_position", hold=hold) if check else {"warnings": []}
    sig = _sigmas(sigmas, m)
    cv = None
    if covs is not None:
        if sig is None:
            raise ValueError("covs needs sigmas (the noise of the means they add to)")
        cv = np.asarray(covs, dtype=np.float64).reshape(m, 3, 3)

    xs = np.array([g * 1e-2] * 3 + [1e-2] * 6)[free]
    theta_nom = NOMINAL_THETA * np.array([g] * 3 + [1.0] * 6)

    def full(tf):
        t = theta_nom.copy()
        t[free] = tf
        return t

    def sig_r(theta):
        if sig is None:
            return np.ones(m)
        _, _, v = _residuals_and_jac(theta, u, g)
        var = np.sum((v * sig) ** 2, axis=1)
        if cv is not None:
            var = var + np.einsum("ij,ijk,ik->i", v, cv, v)
        return np.sqrt(var)

    def solve(theta0):
        """LM from theta0, re-weighting until the weights settle; (theta, cost, nfev, sol)."""
        theta = theta0.copy()
        theta[~free] = theta_nom[~free]
        nfev = 0
        sr = sig_r(theta)
        sol = None
        for _ in range(3):
            def fun(t, sr=sr):
                return _residuals_and_jac(full(t), u, g)[0] / sr

            def jac(t, sr=sr):
                return _residuals_and_jac(full(t), u, g)[1][:, free] / sr[:, None]

            sol = optimize.least_squares(fun, theta[free], jac=jac, method="lm", x_scale=xs,
                                         xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
            nfev += sol.nfev
            theta = full(sol.x)
            if not (np.all(np.isfinite(theta)) and np.all(theta[3:6] > 0)):
                raise CalibrationError("non-finite or negative scale")
            sr_new = sig_r(theta)
            if np.max(np.abs(sr_new / sr - 1.0)) < 1e-3:
                break
            sr = sr_new
        r = _residuals_and_jac(theta, u, g)[0]
        return theta, float(np.sum((r / sig_r(theta)) ** 2)), nfev, sol

    # starts: the given init, then the automatic ones; the given init alone when it fits well,
    # otherwise the best of all (a poor init can lead LM to a degenerate corner)
    starts = []
    if init is not None:
        starts.append((_mb_to_params(np.asarray(init.m, float), np.asarray(init.b, float)), "init"))
    t_ell = _ellipsoid_init(u, g)
    if t_ell is not None:
        starts.append((t_ell, "ellipsoid"))
    starts.append((_minmax_init(u, g), "minmax"))
    best, nfev = _best_start(starts, solve, u, g)
    theta, _, sol, start, theta0 = best

    sr = sig_r(theta)
    r, J, _ = _residuals_and_jac(theta, u, g)
    sh = np.array([(held_sigma or {}).get(n, 0.0) for n in MULTI_PARAM_NAMES])[~free]
    Jh = J[:, ~free] * sh[None, :]                 # |a| change per rest from each held parameter's σ
    sr = np.sqrt(sr ** 2 + np.sum(Jh ** 2, axis=1))
    Jw = J[:, free] / sr[:, None]
    rw = r / sr
    chi2 = float(rw @ rw)
    dof = m - int(free.sum())
    N = Jw.T @ Jw
    cn = np.sqrt(np.diag(N))
    ev = np.linalg.eigvalsh(N / np.outer(cn, cn)) if np.all(cn > 0) else np.zeros(1)
    if not ev[0] > 1e-12 * ev[-1]:
        raise NotObservable("the multi-position fit is singular at its solution: spread the poses "
                            "over faces, edges and corners (POSE_PLAN)")
    cov_t = np.zeros((9, 9))
    Ninv = np.linalg.inv(N)
    cov_t[np.ix_(free, free)] = Ninv * _chi2_factor(chi2, dof, sig is not None, chi2_scaling)
    if np.any(sh > 0):                             # consider parameters: their effect on the fitted ones
        K = -Ninv @ Jw.T @ (Jh / sr[:, None])
        cov_t[np.ix_(free, free)] += K @ K.T
        cov_t[~free, ~free] = sh ** 2
    G = _param_jacobian_mb(theta)
    cov = G @ cov_t @ G.T
    M, b = multi_params_to_mb(theta)
    est = np.ones(12, dtype=bool)
    for rr, cc in ((0, 1), (0, 2), (1, 2)):
        est[3 * rr + cc] = False
    for p, (rr, cc) in enumerate(_ANGLE_POS):      # a held angle: that entry of M is nominal
        est[3 * rr + cc] &= bool(free[6 + p])
    for a in range(3):                             # a held bias
        est[9 + a] &= bool(free[a])
    st = np.sqrt(np.clip(np.diag(cov_t), 0, None))
    # converged |a| residuals must be small compared with g; otherwise a local minimum
    rms = float(np.sqrt(np.mean(r ** 2)))
    if rms > 0.05 * g:
        raise CalibrationError(f"multi-position fit ended with |a| residuals of {rms / g:.3f} g rms: "
                               f"the poses were not still, or the start was too poor (give init)")
    extra = {
        "params": dict(zip(MULTI_PARAM_NAMES, theta.tolist())),
        "sigma_params": dict(zip(MULTI_PARAM_NAMES, st.tolist())),
        "cov_params": cov_t,
        "scales": theta[3:6].copy(),
        "sigma_scales": st[3:6].copy(),
        "angles_rad": {"a_yx": theta[6], "a_zx": theta[7], "a_zy": theta[8]},
        "sigma_angles_rad": {"a_yx": st[6], "a_zx": st[7], "a_zy": st[8]},
        "chi2": chi2,
        "chi2_red": chi2 / dof if dof > 0 else float("nan"),
        "chi2_scaling": chi2_scaling if sig is not None else "always (unweighted)",
        "start": start,
        "theta0": theta0,
        "nfev": nfev,
        "status": sol.status,
        "message": sol.message,
        "observability": rep,
        "held": [n for n, f in zip(MULTI_PARAM_NAMES, free) if not f],
        "sigma_r": sr,
        "deletion_chi2": deletion_chi2(Jw, rw, 1),
        "frame": "x = sensor X axis, y in the sensor X-Y plane (M lower triangular)",
        "g": g,
    }
    return TriadFit(method="multi_position", m=M, b=b, cov=cov, residual_rms=rms, residuals=r,
                    dof=dof, estimated=est, extra=extra)
