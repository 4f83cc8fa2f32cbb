"""Which attitude the board is in, in words a person understands, and when a session has
captured enough: the pose logic of the guided session (imubench.procedures.session).

    pose_words(direction)                "Z up, board level", "X up, connector to the floor"
    detect_attitude(mean, plan)          the planned attitude nearest the measured gravity, or None
    Targets                              the sigma targets of an adaptive session
    hold_sigma_g(acc_mps2)               sigma of the mean of |a| over a hold, in g
    accel_sigmas(fit)                    the accelerometer parameters' sigmas in target units
    enough_attitudes(means, ...)         has an adaptive multi-position session reached its targets?
    suggest_next(done, todo)             the missing attitude that helps the fit most
    plan_problem(method, gyro)           a method/gyro pair that cannot work, known before capture

The board's connector is on its rear (−X) edge (docs/conventions.md, "Pictures of the board"):
with X up the connector points to the floor.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from imubench import units as U
from imubench.calib.poseplan import PLAN_TOL_DEG

#: a measured attitude within this angle of a planned one is that attitude (the plan's
#: neighbours are 35-45° apart: a hand within ±10° is always nearest the one it meant)
DETECT_TOL_DEG = PLAN_TOL_DEG

_AXES = "XYZ"
_FACE_WORDS = {
    (0, 0, 1): "Z up, board level",
    (0, 0, -1): "Z down, board upside down",
    (1, 0, 0): "X up, connector to the floor",
    (-1, 0, 0): "X down, connector up",
    (0, 1, 0): "Y up, board on its right edge",
    (0, -1, 0): "Y down, board on its left edge",
}


def pose_words(direction) -> str:
    """The attitude with gravity direction `direction` (the board axes that point up, board
    frame) in words: which axes point up and down, and what that means for the board."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    signs = tuple(int(np.sign(c)) if abs(c) > 0.3 else 0 for c in d)
    if sum(1 for s in signs if s) == 1:
        return _FACE_WORDS[signs]
    up = [_AXES[i] for i, s in enumerate(signs) if s > 0]
    down = [_AXES[i] for i, s in enumerate(signs) if s < 0]
    level = [_AXES[i] for i, s in enumerate(signs) if s == 0]
    parts = []
    if up:
        parts.append(f"{_join(up)} up")
    if down:
        parts.append(f"{_join(down)} down")
    if level:     # an edge: tilted 45° between two faces, the third axis horizontal
        return ", ".join(parts) + f" (45° on an edge, {level[0]} level)"
    return ", ".join(parts) + " (on a corner, 35° from each face)"


def _join(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def angle_deg(a, b) -> float:
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def detect_attitude(mean, plan, tol_deg: float = DETECT_TOL_DEG) -> tuple[int | None, float]:
    """(index into `plan` of the planned attitude nearest the measured mean specific force,
    angle to it in degrees); index None when even the nearest is more than tol_deg away."""
    angles = plan_angles_deg(mean, plan)
    k = int(np.argmin(angles))
    return (k if angles[k] <= tol_deg else None), float(angles[k])


def plan_angles_deg(mean, plan) -> np.ndarray:
    """Angle in degrees between a measured direction and each planned attitude (vectorised:
    the session asks 20 times a second of device time)."""
    d = np.asarray(mean, float)
    d = d / np.linalg.norm(d)
    v = np.array([np.asarray(p, float) for _, p in plan])
    v /= np.linalg.norm(v, axis=1)[:, None]
    return np.degrees(np.arccos(np.clip(v @ d, -1.0, 1.0)))


# ------------------------------------------------------------------------- targets
@dataclass
class Targets:
    """What an adaptive session aims for. A pose is held until the mean of |a| over it is
    known to pose_sigma_mg (1 sigma), at least hold_min_s and at most hold_max_s; attitudes are
    added until every accelerometer parameter's 1-sigma is at its target (and at least
    min_attitudes, so that the fit has degrees of freedom left to show a bad pose)."""
    accel_bias_mg: float = 0.1           # each bias b_x, b_y, b_z
    accel_scale_ppm: float = 100.0       # each scale factor s_x, s_y, s_z
    accel_nonorth_mrad: float = 0.1      # each non-orthogonality angle a_yx, a_zx, a_zy
    pose_sigma_mg: float = 0.03          # sigma of the mean |a| of one pose
    hold_min_s: float = 0.5
    hold_max_s: float = 4.0
    min_attitudes: int = 12              # calib.accel's GOOD_ATTITUDES

    def as_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        return (f"targets: accel bias ≤ {self.accel_bias_mg:g} mg, scale ≤ {self.accel_scale_ppm:g} ppm, "
                f"non-orthogonality ≤ {self.accel_nonorth_mrad:g} mrad (1 σ); each attitude held until "
                f"its |a| is known to {self.pose_sigma_mg * 1e3:g} µg ({self.hold_min_s:g}–{self.hold_max_s:g} s)")


def hold_sigma_g(acc_mps2) -> float:
    """1-sigma of the mean of |a| over the samples of a hold, in g, correlated noise
    included (calib.static.sigma_of_mean). |a| is what the multi-position fit uses, and it
    does not see a hand's tremor (a tilt of a few hundredths of a degree changes the axes,
    not |a|)."""
    from imubench.calib.static import sigma_of_mean
    nrm = np.linalg.norm(np.asarray(acc_mps2, dtype=float), axis=1)
    return float(sigma_of_mean(nrm)) / U.G0_MPS2


#: the accelerometer's parameters as they are reported against the targets
PARAM_NAMES = ("b_x", "b_y", "b_z", "s_x", "s_y", "s_z", "a_yx", "a_zx", "a_zy")
PARAM_UNITS = {"b": "mg", "s": "ppm", "a": "mrad"}


def accel_sigmas(fit) -> dict:
    """{name: 1-sigma in the target's unit (mg, ppm, mrad)} of a multi-position fit."""
    sp = fit.extra["sigma_params"]
    out = {}
    for n in PARAM_NAMES:
        v = float(sp[n])
        out[n] = v / U.G0_MPS2 * 1e3 if n[0] == "b" else v * 1e6 if n[0] == "s" else v * 1e3
    return out


def target_of(name: str, t: Targets) -> float:
    return {"b": t.accel_bias_mg, "s": t.accel_scale_ppm, "a": t.accel_nonorth_mrad}[name[0]]


def enough_attitudes(means, sigmas, t: Targets) -> tuple[bool, dict | None, str]:
    """Whether the poses so far reach every target of an adaptive multi-position session:
    (reached, {name: sigma} or None when no fit is possible yet, a line for the person)."""
    from imubench.calib import CalibrationError
    from imubench.calib import accel as CA
    means = np.asarray(means, float)
    if len(means) < t.min_attitudes:
        return False, None, f"{len(means)} of at least {t.min_attitudes} attitudes"
    try:
        fit = CA.multi_position(means, sigmas)
    except CalibrationError as e:
        return False, None, f"not yet: {e}"
    sig = accel_sigmas(fit)
    over = [n for n in PARAM_NAMES if sig[n] > target_of(n, t)]
    if over:
        worst = max(over, key=lambda n: sig[n] / target_of(n, t))
        return False, sig, (f"{len(over)} parameters above target, worst {worst} = {sig[worst]:.3g} "
                            f"{PARAM_UNITS[worst[0]]} (target {target_of(worst, t):g})")
    return True, sig, "every parameter at its target"


def suggest_next(done_dirs, todo) -> str | None:
    """The name of the attitude in `todo` [(name, direction)] that helps the |a| = g fit most
    after the attitudes in `done_dirs`: the one that lowers the worst parameter's sigma most
    (calib.accel.dilution); while the attitudes so far cannot constrain every parameter, the
    one farthest from all of them. A suggestion: the person may present any."""
    from imubench.calib.accel import dilution
    if not todo:
        return None
    done = [np.asarray(d, float) / np.linalg.norm(d) for d in done_dirs]
    cands = [(n, np.asarray(v, float) / np.linalg.norm(v)) for n, v in todo]
    best, best_score = None, None
    for n, v in cands:
        sig = dilution(np.array(done + [v])) if len(done) >= 8 else None
        if sig is not None:
            score = (0, float(np.max(sig)))
        else:      # spread first: the farthest from what is there (the largest smallest angle)
            score = (1, -min((angle_deg(v, d) for d in done), default=180.0))
        if best_score is None or score < best_score:
            best, best_score = n, score
    return best


def plan_problem(method: str, gyro: str | None) -> tuple[str, str] | None:
    """(problem, what to do) when a session's accelerometer plan cannot give its gyro method what
    it needs, known before anything is captured; None when it can. The rotation method needs at
    least calib.gyro.MIN_MOTIONS motions between the planned attitudes."""
    if gyro == "rotation":
        from imubench.calib.accel import POSE_PLAN
        from imubench.calib.gyro import MIN_MOTIONS
        poses = sum(1 for p in POSE_PLAN if method != "six" or np.count_nonzero(p.vector) == 1)
        if poses - 1 < MIN_MOTIONS:
            return (f"--method {method} --gyro rotation: {poses} attitudes give {poses - 1} motion(s) between them; "
                    f"the rotation method needs at least {MIN_MOTIONS} (12-24 recommended)",
                    "use --method multi (its attitudes give the motions), or --gyro turns / turntable / bias")
    return None
