"""Geometry of attitudes: the turn between two directions of the board's up.

Pure numerics (no device): the virtual bench, the virtual fixture's plate and the simulated
person turn the board with it; conventions (board frame, right-handed turns) are
docs/conventions.md's.
"""
from __future__ import annotations

import numpy as np


def rotation_to(up_now, up_wanted) -> tuple[list[float], float] | None:
    """The turn (unit axis in the board frame, angle in degrees) that brings the board's up
    direction from up_now to up_wanted; None when it is there already."""
    cur = np.asarray(up_now, dtype=float)
    cur = cur / np.linalg.norm(cur)
    target = np.asarray(up_wanted, dtype=float)
    target = target / np.linalg.norm(target)
    axis = np.cross(target, cur)
    s, c = np.linalg.norm(axis), float(np.clip(cur @ target, -1.0, 1.0))
    if s < 1e-9:
        if c > 0:
            return None
        axis = np.cross(cur, [1.0, 0.0, 0.0] if abs(cur[0]) < 0.9 else [0.0, 1.0, 0.0])  # any perpendicular
    return list(axis / np.linalg.norm(axis)), float(np.degrees(np.arctan2(s, c)))
