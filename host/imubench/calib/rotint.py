"""Rotation kernels shared by the gyro fits (calib.gyro) and the rotation method's solver
(calib.rotation_model): quaternions of step rotation vectors, their ordered products and prefix
products, rotation matrices, the step integration with the coning term, and small geometry
helpers. Conventions: calib.gyro's module docstring. numpy only.
"""
from __future__ import annotations

import math

import numpy as np


def _rotvec_quat(phi: np.ndarray) -> np.ndarray:
    """Unit quaternions (4, ...) = (w, x, y, z) of rotation vectors given component-first,
    phi (3, ...)."""
    half = 0.5 * np.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    s = 0.5 * np.sinc(half * (1.0 / math.pi))          # sin(θ/2)/θ, smooth at 0
    q = np.empty((4,) + phi.shape[1:])
    q[0] = np.cos(half)
    np.multiply(phi, s, out=q[1:])
    return q


def _quat_chain(q: np.ndarray) -> np.ndarray:
    """Ordered Hamilton product q₀⊗q₁⊗…⊗q_{L-1} along the last axis of q (4, ..., L)."""
    while q.shape[-1] > 1:
        if q.shape[-1] % 2:
            pad = np.zeros(q.shape[:-1] + (1,))
            pad[0] = 1.0
            q = np.concatenate([q, pad], axis=-1)
        a0, a1, a2, a3 = q[..., 0::2]
        b0, b1, b2, b3 = q[..., 1::2]
        out = np.empty(q.shape[:-1] + (q.shape[-1] // 2,))
        out[0] = a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3
        out[1] = a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2
        out[2] = a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1
        out[3] = a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0
        q = out
    return q[..., 0]


def _qmul(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Hamilton product of quaternion arrays (4, ...), broadcasting; into out if given."""
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    if out is None:
        out = np.empty((4,) + np.broadcast_shapes(a0.shape, b0.shape))
    r0 = a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3
    r1 = a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2
    r2 = a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1
    out[3] = a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0
    out[0], out[1], out[2] = r0, r1, r2
    return out


def _quat_prefix(q: np.ndarray) -> np.ndarray:
    """Inclusive prefix products q₀⊗…⊗q_k along the last axis of q (4, J, n), by blocks of
    about √n (two short sequential passes of vectorised products)."""
    n = q.shape[-1]
    bl = max(1, int(math.ceil(math.sqrt(n))))
    nb = -(-n // bl)
    pad = nb * bl - n
    if pad:
        ident = np.zeros(q.shape[:-1] + (pad,))
        ident[0] = 1.0
        q = np.concatenate([q, ident], axis=-1)
    qb = np.ascontiguousarray(np.moveaxis(q.reshape(q.shape[:-1] + (nb, bl)), -1, 1))  # (4, bl, ..., nb)
    for i in range(1, bl):                       # within each block
        _qmul(qb[:, i - 1], qb[:, i], out=qb[:, i])
    carry = np.empty(qb[:, 0].shape)             # (4, ..., nb): product of all earlier blocks
    carry[..., 0] = 0.0
    carry[0, ..., 0] = 1.0
    for j in range(1, nb):
        _qmul(carry[..., j - 1], qb[:, -1, ..., j - 1], out=carry[..., j])
    out = _qmul(carry[:, None], qb)              # (4, bl, ..., nb)
    return np.moveaxis(out, 1, -1).reshape(q.shape)[..., :n]


def _quat_matrix_cf(q: np.ndarray) -> np.ndarray:
    """Rotation matrices component-first (3, 3, ...) of unit quaternions (4, ...)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (4, ...) (normalised here)."""
    q = q / np.sqrt(np.sum(q * q, axis=0))
    w, x, y, z = q
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _step_vectors(x: np.ndarray, h: float, lens: np.ndarray | None = None,
                  step_mask: np.ndarray | None = None, coning: bool = True) -> np.ndarray:
    """Rotation vector of each step between consecutive samples; component-first: x (3, ..., L)
    → (3, ..., L-1).

    The rate is taken as a smooth signal sampled at the sample instants: the integral over a
    step uses cubic interpolation through the four nearest samples, h·(−x₋₁ + 13x₀ + 13x₁ −
    x₂)/24 (one-sided quadratic, h·(5x₀ + 8x₁ − x₂)/12, at the first and last step), plus the
    second Magnus (coning) term h²/12·x₀ × x₁; the local error is O(h⁵). Constant rates are
    integrated exactly. lens: for x (3, J, L) holding J padded runs, the number of valid
    samples of each run; step_mask (J, L-1) zeroes the steps beyond a run's end.
    """
    L = x.shape[-1]
    x0, x1 = x[..., :-1], x[..., 1:]
    phi = x0 + x1
    phi *= 0.5 * h
    if L >= 4:
        phi[..., 1:-1] += (h / 24.0) * ((x[..., 1:-2] + x[..., 2:-1]) - (x[..., :-3] + x[..., 3:]))
    if L >= 3:
        first = (h / 12.0) * (5.0 * x[..., 0] + 8.0 * x[..., 1] - x[..., 2])
        if lens is None:
            phi[..., 0] = first
            phi[..., -1] = (h / 12.0) * (5.0 * x[..., -1] + 8.0 * x[..., -2] - x[..., -3])
        else:
            lens = np.asarray(lens)
            rows = np.flatnonzero(lens >= 3)
            last = lens[rows] - 1
            phi[:, rows, 0] = first[:, rows]
            phi[:, rows, last - 1] = (h / 12.0) * (5.0 * x[:, rows, last] + 8.0 * x[:, rows, last - 1]
                                                   - x[:, rows, last - 2])
    c = (h * h / 12.0) if coning else 0.0
    phi[0] += c * (x0[1] * x1[2] - x0[2] * x1[1])
    phi[1] += c * (x0[2] * x1[0] - x0[0] * x1[2])
    phi[2] += c * (x0[0] * x1[1] - x0[1] * x1[0])
    if step_mask is not None:
        phi *= step_mask
    return phi


def _rotate(phi: np.ndarray) -> np.ndarray:
    """Product of the step rotations exp([φ_k]×), phi component-first (3, ..., L) → (..., 3, 3)."""
    return _quat_matrix(_quat_chain(_rotvec_quat(phi)))


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """(k, 3, 3) cross-product matrices [v]× of the rows of v (k, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _tangent_basis(g: np.ndarray) -> np.ndarray:
    """(k, 2, 3): two orthonormal vectors perpendicular to each unit vector g (k, 3)."""
    a = np.where((np.abs(g[:, 0]) < 0.9)[:, None], np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    e1 = a - np.sum(a * g, axis=1)[:, None] * g
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(g, e1)
    return np.stack([e1, e2], axis=1)
