"""The attitudes of a calibration: the 26-attitude plan of Syed et al. (2007) (6 faces, 12
edges, 8 corners), which of them a set of pose means covers, and the per-pose |a| table of a
fit. calib.accel fits them; procedures.poses names them for a person."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imubench.calib import CalibrationError, TriadFit
from imubench.units import G0_MPS2

AXES = "XYZ"
PLAN_TOL_DEG = 20.0          # a pose is a planned attitude within this angle (neighbours are ≥ 35° apart)


# --------------------------------------------------------------------------------------------
# the pose plan
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PlannedPose:
    name: str
    direction: tuple[float, float, float]   # unit specific force in the board frame (the "up" axis)

    @property
    def vector(self) -> np.ndarray:
        return np.array(self.direction)


_FACE_NAMES = {
    (0, 0, 1): "+Z up (level)", (0, 0, -1): "-Z up (upside down)",
    (1, 0, 0): "+X up (nose up)", (-1, 0, 0): "-X up (nose down)",
    (0, 1, 0): "+Y up (on its right side)", (0, -1, 0): "-Y up (on its left side)",
}


def _plan() -> tuple[PlannedPose, ...]:
    def label(v):
        return "".join(("+" if c > 0 else "-") + AXES[i] for i, c in enumerate(v) if c != 0)

    faces, edges, corners = [], [], []
    for v in [(0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]:
        faces.append(PlannedPose(_FACE_NAMES[v], tuple(float(c) for c in v)))
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for si in (1, -1):
            for sj in (1, -1):
                v = [0, 0, 0]
                v[i], v[j] = si, sj
                u = np.array(v, float) / math.sqrt(2.0)
                edges.append(PlannedPose(f"{label(v)} edge", tuple(u.tolist())))
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                v = (sx, sy, sz)
                u = np.array(v, float) / math.sqrt(3.0)
                corners.append(PlannedPose(f"{label(v)} corner", tuple(u.tolist())))
    return tuple(faces + edges + corners)


#: The 26 attitudes of Syed et al. (2007): 6 faces, 12 edges, 8 corners, neighbours 35–45°
#: apart. direction = the unit specific force the accelerometer should read (the axes that
#: point up), in the board frame (X forward, Y left, Z up).
POSE_PLAN: tuple[PlannedPose, ...] = _plan()
_PLAN_DIRS = np.array([p.direction for p in POSE_PLAN])


def _units(means) -> np.ndarray:
    u = np.asarray(means, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3:
        raise ValueError(f"expected pose means of shape (m, 3), got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError("pose means contain NaN or inf")
    n = np.linalg.norm(u, axis=1)
    if np.any(n == 0):
        raise CalibrationError("a pose mean is exactly zero: not an accelerometer at rest")
    return u / n[:, None]


def match_plan(means, tol_deg: float = PLAN_TOL_DEG) -> tuple[list[str], list[str], list[int]]:
    """Which planned attitudes the poses cover. Each mean is matched to the nearest plan
    direction by angle; within tol_deg it covers it. Returns (covered names in plan order,
    missing names in plan order, indices (0-based) of the means that match none)."""
    d = _units(means)
    cosang = np.clip(d @ _PLAN_DIRS.T, -1, 1)
    best = np.argmax(cosang, axis=1)
    ok = np.degrees(np.arccos(cosang[np.arange(len(d)), best])) <= tol_deg
    hit = set(best[ok].tolist())
    covered = [p.name for i, p in enumerate(POSE_PLAN) if i in hit]
    missing = [p.name for i, p in enumerate(POSE_PLAN) if i not in hit]
    unmatched = [int(i) for i in np.nonzero(~ok)[0]]
    return covered, missing, unmatched


def _pose_names(means, tol_deg: float = PLAN_TOL_DEG) -> list[str]:
    d = _units(means)
    cosang = np.clip(d @ _PLAN_DIRS.T, -1, 1)
    best = np.argmax(cosang, axis=1)
    names = []
    for i, b in enumerate(best):
        ang = math.degrees(math.acos(cosang[i, b]))
        names.append(POSE_PLAN[b].name if ang <= tol_deg else f"pose {i + 1}")
    return names


# --------------------------------------------------------------------------------------------
# session table
# --------------------------------------------------------------------------------------------

def pose_table(means, fit: TriadFit, g: float | None = None) -> list[dict]:
    """Per pose: {"index" (0-based), "pose" (plan name, or "pose N" counting from 1),
    "before_g": |u|/g, "after_g": |M⁻¹(u − b)|/g, "before_err_mg", "after_err_mg"} — |a| should be
    1 g in every pose after calibration. g defaults to the fit's (extra["g"]) or G0."""
    u = np.asarray(means, dtype=np.float64)
    if g is None:
        g = float(fit.extra.get("g", G0_MPS2))
    before = np.linalg.norm(u, axis=1) / g
    after = np.linalg.norm(fit.correct(u), axis=1) / g
    names = _pose_names(u)
    return [{"index": i, "pose": names[i], "before_g": float(before[i]), "after_g": float(after[i]),
             "before_err_mg": float((before[i] - 1) * 1e3), "after_err_mg": float((after[i] - 1) * 1e3)}
            for i in range(len(u))]
