"""The six-position accelerometer fit: linear least squares on the six faces, each square to
gravity (12 parameters: the full M and b). calib.accel names it with the multi-position fit."""
from __future__ import annotations

import math

import numpy as np

from imubench.calib import CalibrationError, NotObservable, TriadFit
from imubench.units import G0_MPS2
from imubench.calib.accel_lsq import _check_g, _chi2_factor, _sigmas, deletion_chi2
from imubench.calib.poseplan import AXES, _units

__all__ = ["FACES", "FACE_TOL_DEG", "identify_faces", "six_position"]

FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
FACE_TOL_DEG = 30.0          # a pose counts as a face when its mean is this close to an axis

# --------------------------------------------------------------------------------------------
# six-position
# --------------------------------------------------------------------------------------------

def identify_faces(means, max_angle_deg: float = FACE_TOL_DEG) -> tuple[list[str | None], np.ndarray]:
    """Face of each pose: which board axis is vertical and its sign ("+Z" = Z up, reading +g),
    and the angle (deg) between the mean and that axis. None where the angle exceeds
    max_angle_deg (not a face pose)."""
    d = _units(means)
    j = np.argmax(np.abs(d), axis=1)
    comp = d[np.arange(len(d)), j]
    ang = np.degrees(np.arccos(np.clip(np.abs(comp), -1, 1)))
    faces = [(("+" if c > 0 else "-") + AXES[a]) if t <= max_angle_deg else None
             for a, c, t in zip(j, comp, ang)]
    return faces, ang


def _face_report(faces: list[str | None]) -> tuple[list[str], list[str]]:
    missing = [f for f in FACES if f not in faces]
    repeated = []
    for f in FACES:
        idx = [i + 1 for i, x in enumerate(faces) if x == f]
        if len(idx) > 1:
            repeated.append(f"{f} (poses {', '.join(map(str, idx[:-1]))} and {idx[-1]})")
    return missing, repeated


def _check_faces(faces, angles, skip_non_faces: bool) -> None:
    bad = [i for i, f in enumerate(faces) if f is None]
    if bad and not skip_non_faces:
        lst = ", ".join(f"pose {i + 1} ({angles[i]:.0f}°)" for i in bad)
        raise CalibrationError(
            f"six-position needs every pose on a face (one axis vertical, within "
            f"{FACE_TOL_DEG:.0f}°); these are not: {lst}. Use multi_position for tilted poses, or "
            f"pass skip_non_faces=True to ignore them.")
    missing, repeated = _face_report(faces)
    if missing:
        msg = f"missing faces: {', '.join(missing)}"
        if repeated:
            msg += f"; repeated: {'; '.join(repeated)}"
        msg += (". Six-position needs each of the six faces up at least once (+X = X axis up, "
                "reading +g); poses are numbered from 1.")
        raise NotObservable(msg)


def six_position(means, sigmas=None, g: float = G0_MPS2, *, skip_non_faces: bool = False,
                 chi2_scaling: str = "inflate", covs=None) -> TriadFit:
    """Six-position calibration: every pose lies on a face, so its true specific force is ±g on
    one board axis; weighted linear least squares on the stacked z = A·β, β = (M row-major, b).

    means (m, 3), m ≥ 6, each face at least once (repeats add redundancy); sigmas (m, 3) the
    1-sigma uncertainty of each mean (weights 1/σ²), or None (unit weights, noise from the
    residuals). Raises NotObservable naming missing (and repeated) faces. The covariance is
    (AᵀWA)⁻¹ × max(1, χ²/dof) (see _chi2_factor): the spread of (M, b) from the noise of the
    means, inflated when the residuals exceed that noise — it does not cover a tilt of the
    faces that the residuals cannot see (docs/calibration.md). covs (m, 3, 3): a further
    covariance of each mean (a rest's own motion, calib.rests) added to diag(sigmas²); each
    pose's three rows are then whitened by the Cholesky factor of the sum (needs sigmas)."""
    u = np.asarray(means, dtype=np.float64)
    faces, angles = identify_faces(u)
    _check_faces(faces, angles, skip_non_faces)
    use = np.array([f is not None for f in faces])
    u_all = u
    u = u[use]
    _check_g(u, g)
    m = len(u)
    sig = _sigmas(sigmas, len(u_all))
    sig = sig[use] if sig is not None else None
    if covs is not None and sig is None:
        raise ValueError("covs needs sigmas (the noise of the means they add to)")
    cv = None if covs is None else np.asarray(covs, dtype=np.float64).reshape(len(u_all), 3, 3)[use]

    f_true = np.zeros((m, 3))
    for i, f in enumerate([f for f in faces if f is not None]):
        f_true[i, AXES.index(f[1])] = g if f[0] == "+" else -g

    # z = A·β: rows (pose i, axis a): u_ia = Σ_c M_ac f_ic + b_a
    A = np.zeros((3 * m, 12))
    for i in range(m):
        for a in range(3):
            A[3 * i + a, 3 * a:3 * a + 3] = f_true[i]
            A[3 * i + a, 9 + a] = 1.0
    z = u.ravel()
    if cv is None:
        w = 1.0 / (sig.ravel() if sig is not None else np.ones(3 * m))
        Wh = np.diag(w)
    else:                         # block whitening: L_i⁻¹ with L_i·L_iᵀ = diag(σ_i²) + C_i
        Wh = np.zeros((3 * m, 3 * m))
        for i in range(m):
            L = np.linalg.cholesky(np.diag(sig[i] ** 2) + cv[i])
            Wh[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(L)
    Aw = Wh @ A
    zw = Wh @ z
    beta, *_ = np.linalg.lstsq(Aw, zw, rcond=None)
    res = z - A @ beta
    chi2 = float(np.sum((Wh @ res) ** 2))
    dof = 3 * m - 12
    N = Aw.T @ Aw
    cov = np.linalg.inv(N) * _chi2_factor(chi2, dof, sig is not None, chi2_scaling)

    M = beta[:9].reshape(3, 3)
    b = beta[9:]
    resid = res.reshape(m, 3)
    extra = {
        "faces": [f for f in faces if f is not None],
        "used_poses": [int(i) for i in np.nonzero(use)[0]],
        "skipped_poses": [int(i) for i in np.nonzero(~use)[0]],
        "face_angle_deg": angles[use],
        "chi2": chi2,
        "chi2_red": chi2 / dof if dof > 0 else float("nan"),
        "chi2_scaling": chi2_scaling if sig is not None else "always (unweighted)",
        "deletion_chi2": deletion_chi2(Aw, Wh @ res, 3),
        # misfit as an angle: the rms residual over g; a large value means the faces were not
        # square to gravity (or the board moved)
        "residual_angle_deg": math.degrees(float(np.sqrt(np.mean(res ** 2))) / g),
        "g": g,
    }
    return TriadFit(method="six_position", m=M, b=b, cov=cov,
                    residual_rms=float(np.sqrt(np.mean(res ** 2))), residuals=resid, dof=dof,
                    estimated=np.ones(12, dtype=bool), extra=extra)


