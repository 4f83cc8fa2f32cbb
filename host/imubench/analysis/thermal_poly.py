"""Bias against temperature from a warm-up: binning a still stream, polynomial fits whose order
the data choose, and the separation of accelerometer bias and scale terms over several faces.
Pure numpy: arrays in, coefficients with their covariance out (the warm-up on a device is
imubench.procedures.warmup).

Model (docs/conventions.md, issue 23), per axis k, ΔT = clamp(T, t_min, t_max) − t_ref:

    bias_k(ΔT) = c0 + c1·ΔT + c2·ΔT² + c3·ΔT³          (c0: the bias at t_ref; the device keeps it in b)

Order. A polynomial of order p is *allowed* only if the span and the number of distinct
temperatures carry it (`supported_order`: at least MIN_SPAN_C + SPAN_PER_ORDER_C·(p − 1) °C of
span and 3·(p + 1) distinct temperatures at the sensor's resolution); among the allowed orders
the one chosen is the lowest whose held-out error is within one standard error of the best
(the "one-standard-error rule", Hastie, Tibshirani and Friedman, *The Elements of Statistical
Learning*, 2nd ed. 2009, §7.10). Held-out error: the temperature span is cut into N_BLOCKS
equal intervals; each interior interval in turn is left out, the rest fitted, the left-out bins
predicted (the first and the last interval are always fitted, so a prediction is an
interpolation, never an extrapolation: a warm-up's bins are strongly ordered in temperature and
leaving out the hottest would judge the orders on extrapolation). The error of an order is the
root of the mean over the left-out intervals of each interval's mean squared residual (each
temperature interval counts once, however long the board stayed in it).

Uncertainty. Samples within a bin are correlated (slow drift: bias instability, a temperature
still moving): σ/√n of white noise would claim too much. A bin's σ is the larger of the white
σ/√n and the batch-means estimate (the bin cut into N_BATCHES batches, the spread of their
means / √N_BATCHES; Law and Kelton, *Simulation Modeling and Analysis*, 3rd ed. 2000, §9.5.3);
`neighbour_sigma` gives the scatter between neighbouring bins (second differences, robust),
used as a floor; and the fit's covariance is inflated by the reduced χ² when the bins scatter
more than their σ say.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import polynomial as P

N_BLOCKS = 10            # temperature intervals of the cross-validation
N_BATCHES = 8            # batches of a bin for its batch-means σ
MIN_SPAN_C = 1.0         # span an order-1 fit needs, °C (5 LSB of the ADXRS450's 0.2 °C)
SPAN_PER_ORDER_C = 6.0   # each further order needs this much more span, °C
MIN_BINS_PER_PARAM = 3   # distinct temperatures per fitted coefficient
DEFAULT_RESOLUTION_C = 0.2   # the coarser of the two sensors' temperature steps (ADXRS450)


# ------------------------------------------------------------------ binning
@dataclass
class Binned:
    """A stream cut into time bins: per bin its device time (s, the mean), the mean of each
    temperature column (°C), the mean of each value column, its honest 1-σ and the samples."""
    t_s: np.ndarray          # (k,)
    temp_c: np.ndarray       # (k, nt)
    mean: np.ndarray         # (k, m)
    sigma: np.ndarray        # (k, m)
    n: np.ndarray            # (k,)

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def concat(cls, parts: Sequence["Binned"]) -> "Binned":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls(np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros(0, int))
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t_s", "temp_c", "mean", "sigma", "n")))


def bin_stream(t_s, temp_c, values, bin_s: float, min_fill: float = 0.5, t0_s: float | None = None) -> Binned:
    """Cut a stream into consecutive bins of bin_s seconds (of t_s, device time) from its first
    sample (or from t0_s); a bin with fewer than min_fill of the samples a full one holds is dropped (a gap, a
    partial bin at the end: the caller keeps the rest for the next call). temp_c (n, nt),
    values (n, m). Each bin's σ: max(white σ/√n, batch means over N_BATCHES batches)."""
    t = np.asarray(t_s, dtype=np.float64)
    tc = np.asarray(temp_c, dtype=np.float64).reshape(len(t), -1)
    v = np.asarray(values, dtype=np.float64).reshape(len(t), -1)
    if len(t) < 2 or bin_s <= 0:
        return Binned(np.zeros(0), np.zeros((0, tc.shape[1])), np.zeros((0, v.shape[1])),
                      np.zeros((0, v.shape[1])), np.zeros(0, int))
    dt = float(np.median(np.diff(t)))
    full = max(1, int(round(bin_s / dt))) if dt > 0 else len(t)
    idx = np.floor((t - (t[0] if t0_s is None else t0_s)) / bin_s).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    stops = np.r_[starts[1:], len(t)]
    rows = []
    for a, b in zip(starts, stops):
        n = b - a
        if n < max(2 * N_BATCHES, min_fill * full):
            continue
        x = v[a:b]
        white = x.std(axis=0, ddof=1) / np.sqrt(n)
        nb = n // N_BATCHES
        bm = x[: nb * N_BATCHES].reshape(N_BATCHES, nb, -1).mean(axis=1)
        batch = bm.std(axis=0, ddof=1) / np.sqrt(N_BATCHES)
        rows.append((t[a:b].mean(), tc[a:b].mean(axis=0), x.mean(axis=0), np.maximum(white, batch), n))
    if not rows:
        return Binned(np.zeros(0), np.zeros((0, tc.shape[1])), np.zeros((0, v.shape[1])),
                      np.zeros((0, v.shape[1])), np.zeros(0, int))
    return Binned(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                  np.array([r[3] for r in rows]), np.array([r[4] for r in rows]))


def neighbour_sigma(y) -> np.ndarray:
    """The scatter of consecutive bin means about their local straight line, per column: from
    the second differences d_i = y_i − (y_{i−1} + y_{i+1})/2 (var = 1.5 σ² for independent
    bins), robustly (1.4826·MAD). Zero with fewer than 5 bins."""
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    if len(y) < 5:
        return np.zeros(y.shape[1])
    d = y[1:-1] - 0.5 * (y[:-2] + y[2:])
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(1.5)


def steady_sigma(sigma) -> np.ndarray:
    """Each bin's σ floored at the median of all: a still sensor's noise does not change from bin
    to bin, but a σ estimated from N_BATCHES batches scatters by about ±25 %, and a fit weighted
    by those scattered σ trusts the lucky bins more than it should (its covariance then claims
    too much)."""
    s = np.asarray(sigma, float)
    pos = s[s > 0]
    return np.maximum(s, np.median(pos)) if len(pos) else s


def merge_cells(temp_c, y, sigma, cell_c: float):
    """Time bins merged into temperature cells of cell_c °C (a board that stays at one temperature
    for long gives many bins there: one cell, not many independent points). Per cell: the mean
    temperature, the mean value and its σ = max(σ of the bins' mean as if independent, batch
    means: the cell's bins in time order cut into up to 4 batches, the spread of the batch means
    / √batches), which keeps a slow wander (bias instability) within the cell in its σ.
    Returns (temp (c,), y (c,), sigma (c,), bins per cell (c,))."""
    t = np.asarray(temp_c, float)
    y = np.asarray(y, float)
    s = steady_sigma(sigma)
    if cell_c is None or cell_c <= 0 or len(t) == 0:
        return t, y, s, np.ones(len(t), int)
    cell = np.floor(t / cell_c).astype(np.int64)
    out = []
    for c in np.unique(cell):
        i = np.flatnonzero(cell == c)              # in time order (the bins come in time order)
        m = len(i)
        white = np.sqrt(np.sum(s[i] ** 2)) / m
        sg = white
        if m >= 4:
            nb = min(4, m // 2)
            per = m // nb
            bm = np.array([y[i[j * per:(j + 1) * per]].mean() for j in range(nb)])
            sg = max(white, float(bm.std(ddof=1) / np.sqrt(nb)))
        out.append((t[i].mean(), y[i].mean(), sg, m))
    a = np.array(out)
    return a[:, 0], a[:, 1], a[:, 2], a[:, 3].astype(int)


# ------------------------------------------------------------------ the fit
@dataclass
class PolyFit:
    """A bias polynomial about t_ref: coef c0..c3 (unused orders 0), cov (4, 4) of them
    (inflated by the reduced χ² when > 1), the held-out RMS of the chosen order and of every
    order tried, the temperature span of the data (°C), the number of bins."""
    order: int
    coef: np.ndarray
    cov: np.ndarray
    heldout_rms: float
    heldout_by_order: dict
    span_c: tuple
    n_bins: int
    t_ref_c: float = 25.0
    chi2_red: float = float("nan")
    n_distinct: int = 0
    max_supported_order: int = 0
    n_cells: int = 0                 # temperature cells fitted (merge_cells; = n_bins without merging)
    alt_coef: np.ndarray | None = None   # the fit at the highest supported order (when higher than order)
    rw_var_per_s: float = 0.0            # bias random walk K² (unit²/s) estimated from the bins (0: none seen)
    rw_timelines: list = field(default_factory=list)   # per warm-up: (temps (m,), times (m,)) the temperature rose along
    notes: list = field(default_factory=list)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))

    def __call__(self, temp_c, clamp: bool = True) -> np.ndarray:
        """The fitted bias at temp_c (clamped to the span, as the device does)."""
        return poly_eval(self.coef, temp_c, self.t_ref_c, *(self.span_c if clamp else (-np.inf, np.inf)))

    def curve_sigma(self, temp_c, relative: bool = False) -> np.ndarray:
        """1-σ of the fitted curve at temp_c (clamped to the span): the coefficients' covariance
        and, when a higher order was supported but not chosen, the difference to that fit (the
        order choice's own uncertainty: a curvature within the noise of the held-out test is
        not claimed to be absent). relative: of bias(T) − bias(t_ref) (c0 left out)."""
        x = np.clip(np.asarray(temp_c, dtype=np.float64), *self.span_c) - self.t_ref_c
        V = np.vander(np.atleast_1d(x), 4, increasing=True)
        if relative:
            V[:, 0] = 0.0
        var = np.einsum("ij,jk,ik->i", V, self.cov, V)
        if self.alt_coef is not None:
            d = np.nan_to_num(self.alt_coef - self.coef)
            d[0] = 0.0 if relative else d[0]
            var = var + (V @ d) ** 2
        var = var + self.rw_variance(x + self.t_ref_c)
        return np.sqrt(np.clip(var, 0, None)).reshape(np.shape(x))

    def rw_variance(self, temp_c) -> np.ndarray:
        """What the bias random walk adds to the curve's variance at temp_c: K²·|t(T) − t(t_ref)|
        per warm-up, t(T) the time its temperature passed T (a walk and a thermal slope look alike
        in one warm-up: the fit takes the walk for temperature dependence); averaged over the
        warm-ups fitted together (independent walks)."""
        T = np.atleast_1d(np.asarray(temp_c, float))
        if not self.rw_var_per_s or not self.rw_timelines:
            return np.zeros(T.shape)
        n = len(self.rw_timelines)
        out = np.zeros(T.shape)
        for temps, times in self.rw_timelines:
            tt, ti = np.asarray(temps, float), np.asarray(times, float)
            out += self.rw_var_per_s * np.abs(np.interp(T, tt, ti) - np.interp(self.t_ref_c, tt, ti)) / n ** 2
        return out

    def sigma_over_span(self, n: int = 41) -> float:
        """The largest 1-σ of the fitted curve over the span."""
        return float(np.max(self.curve_sigma(np.linspace(*self.span_c, n))))


def poly_eval(coef, temp_c, t_ref_c: float, t_min_c: float = -np.inf, t_max_c: float = np.inf) -> np.ndarray:
    """Σ c_i·ΔT^i, ΔT = clamp(T, t_min, t_max) − t_ref (Horner), as the device and PX4 evaluate it."""
    x = np.clip(np.asarray(temp_c, dtype=np.float64), t_min_c, t_max_c) - t_ref_c
    c = np.asarray(coef, dtype=np.float64)
    out = np.zeros_like(x) + c[-1]
    for ci in c[-2::-1]:
        out = out * x + ci
    return out


def shift_poly(coef, from_ref_c: float, to_ref_c: float) -> np.ndarray:
    """The same polynomial expressed about another reference temperature:
    Σ c_i (T − from)^i = Σ d_i (T − to)^i (exact re-expansion)."""
    c = np.asarray(coef, dtype=np.float64)
    d = to_ref_c - from_ref_c                  # T − from = (T − to) + d
    out = np.zeros(len(c))
    for i, ci in enumerate(c):
        term = P.polypow([d, 1.0], i) if i else np.array([1.0])
        out[: len(term)] += ci * term
    return out


def supported_order(span_c: float, n_distinct: int, max_order: int = 3) -> int:
    """The highest order the span and the distinct temperatures carry (see the module doc)."""
    best = 0
    for p in range(1, max_order + 1):
        if span_c >= MIN_SPAN_C + SPAN_PER_ORDER_C * (p - 1) and n_distinct >= MIN_BINS_PER_PARAM * (p + 1):
            best = p
    return best


def _distinct(temp_c, resolution_c: float) -> int:
    return int(len(np.unique(np.round(np.asarray(temp_c) / resolution_c))))


def _wls(A, y, w):
    """Weighted least squares; (params, cov (unscaled), chi2, dof). Column-scaled for conditioning."""
    s = np.sqrt(w)
    As = A * s[:, None]
    norm = np.linalg.norm(As, axis=0)
    norm[norm == 0] = 1.0
    sol, *_ = np.linalg.lstsq(As / norm, y * s, rcond=None)
    p = sol / norm
    N = (As / norm).T @ (As / norm)
    C = np.linalg.pinv(N) / np.outer(norm, norm)
    r = y - A @ p
    dof = len(y) - A.shape[1]
    return p, C, float(np.sum(w * r * r)), dof


def _blocks(x, n_blocks: int = N_BLOCKS) -> np.ndarray:
    lo, hi = float(np.min(x)), float(np.max(x))
    if hi <= lo:
        return np.zeros(len(x), int)
    return np.minimum((n_blocks * (x - lo) / (hi - lo)).astype(int), n_blocks - 1)


def _cv(x, y, w, design, n_blocks: int = N_BLOCKS):
    """Held-out error of a design (a function x-index-mask -> A): per interior block, the mean
    squared residual of its bins predicted from the others; (rms, se of the mean square, per-block ms)."""
    blk = _blocks(x, n_blocks)
    A = design()
    ms = []
    for b in range(1, n_blocks - 1):
        test = blk == b
        train = ~test
        if not test.any():
            continue
        At = A[train]
        keep = np.linalg.norm(At, axis=0) > 0       # a group (face) with no bin left in training
        if np.any(np.linalg.norm(A[test][:, ~keep], axis=0) > 0):
            continue
        if train.sum() <= keep.sum():
            continue
        p, *_ = _wls(At[:, keep], y[train], w[train])
        r = y[test] - A[test][:, keep] @ p
        ms.append(float(np.mean(r * r)))
    if not ms:
        return float("nan"), float("nan"), []
    ms = np.array(ms)
    return float(np.sqrt(ms.mean())), float(ms.std(ddof=1) / np.sqrt(len(ms))) if len(ms) > 1 else float("inf"), ms


def _choose(cv: dict) -> int:
    """Lowest order whose held-out mean square is within one standard error of the best."""
    ok = {p: v for p, v in cv.items() if np.isfinite(v[0])}
    if not ok:
        return min(cv)
    best = min(ok, key=lambda p: ok[p][0])
    limit = ok[best][0] ** 2 + (ok[best][1] if np.isfinite(ok[best][1]) else 0.0)
    return min(p for p, v in ok.items() if v[0] ** 2 <= limit)


def fit_bias_poly(temp_c, y, sigma, t_ref_c: float, max_order: int = 3, *,
                  resolution_c: float = DEFAULT_RESOLUTION_C, order: int | None = None,
                  cell_c: float | None = None) -> PolyFit:
    """A bias polynomial of y against temp_c (k bins, 1-σ sigma) about t_ref_c: the order (0..
    max_order) chosen by held-out error among those the data support (module doc), or `order`
    if given (still capped by the support); with cell_c the bins are merged into temperature
    cells first (merge_cells). Raises ValueError without two bins."""
    t, yy, ss, m = merge_cells(temp_c, y, sigma, cell_c)
    f = _fit_groups(t, yy, ss, np.zeros(len(t), int), None, t_ref_c, max_order, resolution_c, order)[0]
    f.n_cells, f.n_bins = f.n_bins, int(m.sum())
    return f


def _fit_groups(x_c, y, sigma, group, mvals, t_ref_c, max_order, resolution_c, order):
    """The shared fit: y = I_group + Σ_{i≥1} c_i ΔT^i [+ s·m_group·ΔT]; returns (PolyFit, params,
    cov of params, scale (s, σ) or None). With one group I_0 is c0."""
    k = len(y)
    if k < 2 or np.ptp(x_c) == 0:
        raise ValueError("need bins at two or more temperatures")
    sig = np.where(sigma > 0, sigma, np.max(sigma[sigma > 0]) if np.any(sigma > 0) else 1.0)
    w = 1.0 / sig ** 2
    x = x_c - t_ref_c
    groups = np.unique(group)
    G = (group[:, None] == groups[None, :]).astype(float)
    with_scale = mvals is not None and len(np.unique(np.round(mvals[groups], 6))) > 1
    span = (float(np.min(x_c)), float(np.max(x_c)))
    nd = _distinct(x_c, resolution_c)
    sup = supported_order(span[1] - span[0], nd, max_order)

    def design(p):
        cols = [G] + [x[:, None] ** i for i in range(1, p + 1)]
        if with_scale:
            cols.append((mvals[group] * x)[:, None])
        return lambda: np.hstack(cols)

    cv = {p: _cv(x_c, y, w, design(p)) for p in range(0, sup + 1)}
    chosen = min(order, sup) if order is not None else _choose(cv)
    A = design(chosen)()
    prm, C, chi2, dof = _wls(A, y, w)
    chi2_red = chi2 / dof if dof > 0 else float("nan")
    if dof > 0 and chi2_red > 1.0:
        C = C * chi2_red
    ng = len(groups)
    coef, cov = np.zeros(4), np.zeros((4, 4))
    idx = list(range(ng, ng + chosen))           # c1..cp
    if ng == 1:
        idx = [0] + idx
        coef[: chosen + 1] = prm[idx]
        cov[: chosen + 1, : chosen + 1] = C[np.ix_(idx, idx)]
    else:
        coef[1: chosen + 1] = prm[idx]
        cov[1: chosen + 1, 1: chosen + 1] = C[np.ix_(idx, idx)]
    alt = None
    if sup > chosen:
        p2, *_ = _wls(design(sup)(), y, w)
        alt = np.zeros(4)
        if ng == 1:
            alt[: sup + 1] = p2[: sup + 1]
        else:
            alt[1: sup + 1] = p2[ng: ng + sup]
    notes = []
    if sup < max_order:
        notes.append(f"order limited to {sup} by the data: span {span[1] - span[0]:.1f} °C, {nd} distinct temperatures "
                     f"(order p needs {MIN_SPAN_C:g} + {SPAN_PER_ORDER_C:g}·(p − 1) °C and {MIN_BINS_PER_PARAM}·(p + 1) of them)")
    if order is not None and order > sup:
        notes.append(f"order {order} asked for; the data carry only {sup}")
    if not (span[0] <= t_ref_c <= span[1]):
        notes.append(f"t_ref {t_ref_c:g} °C lies outside the span {span[0]:.1f}..{span[1]:.1f} °C: c0 is extrapolated")
    fit = PolyFit(order=chosen, coef=coef, cov=cov, heldout_rms=cv[chosen][0],
                  heldout_by_order={p: v[0] for p, v in cv.items()}, span_c=span, n_bins=k, t_ref_c=float(t_ref_c),
                  chi2_red=chi2_red, n_distinct=nd, max_supported_order=sup, notes=notes, alt_coef=alt)
    scale = (float(prm[-1]), float(np.sqrt(C[-1, -1]))) if with_scale else None
    return fit, prm, C, scale, groups


def timeline(temp_c, t_s) -> tuple[np.ndarray, np.ndarray]:
    """(temperatures, times) along which a warm-up's temperature rose: the running maximum of the
    bins' temperature against their time, strictly increasing (for interpolation)."""
    order = np.argsort(t_s)
    t, T = np.asarray(t_s, float)[order], np.maximum.accumulate(np.asarray(temp_c, float)[order])
    keep = np.r_[True, np.diff(T) > 0]
    return T[keep], t[keep]


def rw_variance_rate(temp_c, resid, t_s, cell_c: float = 0.5, max_pairs: int = 4000) -> float:
    """The bias random walk K² (unit²/s) from the residuals of the bins about the fitted curve:
    pairs of bins in the same temperature cell (the same thermal bias) but at different times
    differ by white noise and the walk: E[(r_i − r_j)²] = 2σ² + K²·|t_i − t_j|; a straight line
    through (|Δt|, (Δr)²) gives K² (0 when it does not rise, or with too few pairs)."""
    T, r, t = (np.asarray(v, float) for v in (temp_c, resid, t_s))
    cell = np.floor(T / cell_c).astype(np.int64)
    dts, d2s = [], []
    for c in np.unique(cell):
        i = np.flatnonzero(cell == c)
        if len(i) < 3:
            continue
        a, b = np.triu_indices(len(i), 1)
        dts.append(np.abs(t[i[a]] - t[i[b]]))
        d2s.append((r[i[a]] - r[i[b]]) ** 2)
    if not dts:
        return 0.0
    dt, d2 = np.concatenate(dts), np.concatenate(d2s)
    if len(dt) > max_pairs:
        sel = np.random.default_rng(0).choice(len(dt), max_pairs, replace=False)
        dt, d2 = dt[sel], d2[sel]
    if len(dt) < 10 or np.ptp(dt) <= 0:
        return 0.0
    slope = np.polyfit(dt, d2, 1)[0]
    return float(max(slope, 0.0))


# ------------------------------------------------------------------ several warm-ups (faces)
@dataclass
class FaceSegment:
    """One warm-up's bins on one face: the unit direction of the specific force in the board
    frame (level: (0, 0, 1)), the temperature of each bin (°C) and the values (k, 3) with σ."""
    gravity_dir: np.ndarray
    temp_c: np.ndarray
    y: np.ndarray
    sigma: np.ndarray
    t_s: np.ndarray | None = None      # device time of each bin (s): the bias random walk is estimated with it


@dataclass
class AxisFit:
    """One axis of a triad over one or more warm-ups: the bias polynomial (c0 only with the
    faces that fix it), the linear scale term where the faces separate it, what could not be
    determined, and the per-face intercepts (value at t_ref on each face)."""
    bias: PolyFit
    scale_tc_per_c: float | None = None
    scale_tc_sigma_per_c: float | None = None
    intercepts: dict = field(default_factory=dict)
    undetermined: list = field(default_factory=list)


def _random_walk(fit: PolyFit, segs, k: int, prm, groups, scale, mvals, cell_c) -> None:
    """Estimate the bias random walk of axis k from the residuals of each warm-up's bins about
    the fit (needs the bins' times), and keep each warm-up's timeline for the curve's σ."""
    ks, lines = [], []
    c = np.nan_to_num(fit.coef.copy())
    c[0] = 0.0
    for j, (g, s) in enumerate(zip(groups, segs)):
        if s.t_s is None:
            return
        T = np.asarray(s.temp_c, float)
        T = T[:, k] if T.ndim == 2 else T
        ts = np.asarray(s.t_s, float)
        model = prm[j] + poly_eval(c, T, fit.t_ref_c)
        if scale is not None:
            model = model + scale[0] * mvals[g] * (T - fit.t_ref_c)
        ks.append(rw_variance_rate(T, np.asarray(s.y, float)[:, k] - model, ts, cell_c or 0.5))
        lines.append(timeline(T, ts))
    fit.rw_var_per_s = float(np.mean(ks)) if ks else 0.0
    fit.rw_timelines = lines


def fit_triad_faces(segments: Sequence[FaceSegment], t_ref_c: float, g_mps2: float | None, max_order: int = 3,
                    resolution_c: float = DEFAULT_RESOLUTION_C, cell_c: float | None = 0.5) -> list[AxisFit]:
    """Fit each axis of a triad over one or more still warm-ups. g_mps2: the specific force's
    magnitude for an accelerometer (its axis k reads b_k + bias_k(ΔT) + (1 + s_k·ΔT)·m_k, m_k =
    g·(face direction)_k nominally: the scale term multiplies what the axis sees), None for a
    gyro (each face adds a constant: Earth rate, g-sensitivity; no scale term from a still board).

    Per axis: one intercept per face (the value at t_ref), shared c1..c3, and with an
    accelerometer where the faces give the axis two different m (e.g. +k and −k, or +k and a
    side face) the linear scale term s_k. What the faces do not determine is said:
    - one face with the axis along gravity: bias and scale slope not separated (the fitted
      c1 = bias_tc + scale_tc·m, right on that face only);
    - an axis that never saw gravity: scale term not determined (bias right on any face);
    - c0 (bias at t_ref) only from two opposite faces (their mean), or a single face where the
      axis sees no gravity (cross-axis terms aside)."""
    segs = list(segments)
    if not segs:
        raise ValueError("no warm-up to fit")
    out = []
    for k in range(3):
        xs, ys, ss, gr, mv = [], [], [], [], []
        nbins = 0
        for i, s in enumerate(segs):
            t = np.asarray(s.temp_c, float)
            if t.ndim == 2:
                t = t[:, k]
            t, yy, sg, cnt = merge_cells(t, np.asarray(s.y, float)[:, k], np.asarray(s.sigma, float)[:, k], cell_c)
            nbins += int(cnt.sum())
            xs.append(t)
            ys.append(yy)
            ss.append(sg)
            gr.append(np.full(len(t), i))
            d = np.asarray(s.gravity_dir, float)
            mv.append(0.0 if g_mps2 is None else g_mps2 * d[k] / max(np.linalg.norm(d), 1e-12))
        x, y, sg, grp, m = (np.concatenate(xs), np.concatenate(ys), np.concatenate(ss), np.concatenate(gr),
                            np.array(mv))
        fit, prm, C, scale, groups = _fit_groups(x, y, sg, grp, None if g_mps2 is None else m, t_ref_c, max_order,
                                                 resolution_c, None)
        fit.n_cells, fit.n_bins = fit.n_bins, nbins
        ng = len(groups)
        inter = {int(g): (float(prm[j]), float(np.sqrt(C[j, j]))) for j, g in enumerate(groups)}
        und = []
        if g_mps2 is not None:
            ms = np.round(m[groups] / g_mps2, 3)
            if scale is None:
                if np.any(np.abs(ms) > 0.5):
                    und.append(f"bias and scale temperature terms of accelerometer {'xyz'[k]} not separated (one attitude of "
                               "this axis): c1 = bias_tc + scale_tc·m, right in this attitude only")
                else:
                    und.append(f"scale temperature term of accelerometer {'xyz'[k]} not determined (the axis never saw gravity)")
            # c0 from two opposite faces, or from a face where the axis sees no gravity
            opp = [(a, b) for a in range(ng) for b in range(ng) if a < b and abs(ms[a] + ms[b]) < 0.05 and abs(ms[a]) > 0.5]
            zero = [a for a in range(ng) if abs(ms[a]) < 0.05]
            if opp:
                a, b = opp[0]
                fit.coef[0] = 0.5 * (prm[a] + prm[b])
                fit.cov[0, 0] = 0.25 * (C[a, a] + C[b, b] + 2 * C[a, b])
            elif zero:
                fit.coef[0] = prm[zero[0]]
                fit.cov[0, 0] = C[zero[0], zero[0]]
                if ng == 1:
                    pass
            else:
                fit.coef[0] = np.nan
                und.append(f"bias of accelerometer {'xyz'[k]} at t_ref not determined (it always saw gravity along one "
                           "direction: bias and g·scale together)")
        elif ng > 1:
            fit.coef[0] = float(np.mean(prm[:ng]))   # a gyro: faces differ by Earth rate and g-sensitivity
            fit.cov[0, 0] = float(np.mean(np.diag(C)[:ng])) / ng
            und.append(f"gyro {'xyz'[k]}: the bias at t_ref is the mean over the faces (each adds Earth rate "
                       "and g-sensitivity)")
        if fit.alt_coef is not None and ng > 1:
            fit.alt_coef[0] = fit.coef[0]
        _random_walk(fit, segs, k, prm, groups, scale, None if g_mps2 is None else m, cell_c)
        out.append(AxisFit(bias=fit, scale_tc_per_c=None if scale is None else scale[0],
                           scale_tc_sigma_per_c=None if scale is None else scale[1], intercepts=inter,
                           undetermined=und))
    return out
