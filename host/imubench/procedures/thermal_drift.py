"""Residual temperature drift of a device's CALIBRATED stream over a span, on the virtual bench:
what is left after a temperature calibration (step sweep or warm-up), warming and cooling.

The bench soaks the board at the span's low end (ambient and every die there at once), then
ramps the ambient slowly past the high end (warming) and back below the low end (cooling)
while the device streams calibrated, level and still. One-second chunk means are binned by
each sensor's own die temperature (the ADXL355's for the accelerometer axes, each gyro's for
its axis); per axis the drift is max − min of the bin means over the span: both branches
together (the hysteresis between warming and cooling shows there) and warming alone.

Used by bench/thermal_time.py and tests/procedures/test_warmup_compare.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imubench import units as U


@dataclass
class DriftSweep:
    ramp_c_per_min: float = 0.5        # the ambient's ramp while measuring
    rate_hz: int = 100                 # calibrated stream rate
    bin_c: float = 2.0                 # die-temperature bins over the span
    min_chunks: int = 20               # 1 s chunks a bin needs to count
    beyond_c: float = 2.0              # how far past each end the ambient goes (the dies lag)
    max_s: float = 6 * 3600.0          # per branch, device time


def residual_drift(vb, dev, span_c, self_heat_c=(0.0,), sweep: DriftSweep | None = None) -> dict:
    """Sweep the calibrated stream over span_c (lo, hi) on VirtualBench vb with dev open on it;
    self_heat_c: the dies' self-heating above the ambient (the cooling branch sends the ambient
    that much further down, so that the dies reach the low end). Returns per axis (x, y, z)
    `accel_mg`, `gyro_dps` (both branches), `accel_mg_warming`, `gyro_dps_warming`, the bin
    means per branch (`bins`: {branch: {"accel_mps2" (nbins, 3), "gyro_rad_s" (nbins, 3)}},
    NaN where a bin has too few chunks), `edges_c`, `filled` ({branch: bins with data}) and
    `device_s` (the sweep's device time)."""
    sw = sweep or DriftSweep()
    lo, hi = float(span_c[0]), float(span_c[1])
    if not hi > lo:
        raise ValueError(f"span {lo:g}..{hi:g} °C: the high end must be above the low end")
    branches: dict[str, np.ndarray] = {}
    vb.set_temperature(lo, soak=True)
    dev.start_stream(rate_hz=sw.rate_hz, calibrated=True)
    t_first = t_last = None
    try:
        for name, target, done in (
                ("warming", hi + sw.beyond_c, lambda t: np.all(t >= hi + 0.5)),
                ("cooling", lo - max(self_heat_c) - sw.beyond_c, lambda t: np.all(t <= lo - 0.5))):
            vb.set_temperature(target, ramp_c_per_s=sw.ramp_c_per_min / 60.0)
            dev.discard_buffered()
            rows, t_start = [], None
            n = sw.rate_hz                                            # 1 s chunks, read 10 at a time
            while True:
                b = dev.read(n_samples=10 * n)
                m = len(b.t_us) // n * n
                temps = np.column_stack([U.accel_temp_counts_to_c(b.accel_temp_counts[:m], range_g=b.accel_range_g[:m]),
                                         U.gyro_temp_counts_to_c(b.gyro_temp_counts[:m])])
                block = np.column_stack([temps, b.accel_mps2[:m].astype(np.float64), b.rate_rad_s[:m].astype(np.float64)])
                chunks = block.reshape(-1, n, block.shape[1]).mean(axis=1)
                rows.append(chunks)
                t_now = b.t_us[-1] * 1e-6
                t_start = t_now if t_start is None else t_start
                t_first = t_start if t_first is None else t_first
                t_last = t_now
                if done(chunks[-1, :4]):
                    break
                if t_now - t_start > sw.max_s:
                    raise RuntimeError(f"drift sweep, {name}: the dies did not reach the span's end in "
                                       f"{sw.max_s:g} s (at {np.round(chunks[-1, :4], 1).tolist()} °C)")
            branches[name] = np.vstack(rows)
    finally:
        dev.stop_stream()
    return drift_from_chunks(branches, (lo, hi), sw) | {"device_s": float(t_last - t_first)}


def drift_from_chunks(branches: dict, span_c, sw: DriftSweep | None = None) -> dict:
    """The binning of residual_drift, on chunk rows (temps (4), accel (3) m/s², gyro (3) rad/s)."""
    sw = sw or DriftSweep()
    lo, hi = span_c
    edges = np.arange(lo, hi + 1e-9, sw.bin_c)
    bins = {}
    for name, r in branches.items():
        accel = np.column_stack([_bin_means(r[:, 0], r[:, 4 + k], edges, sw.min_chunks) for k in range(3)])
        gyro = np.column_stack([_bin_means(r[:, 1 + k], r[:, 7 + k], edges, sw.min_chunks) for k in range(3)])
        bins[name] = {"accel_mps2": accel, "gyro_rad_s": gyro}
    both_a = np.vstack([b["accel_mps2"] for b in bins.values()])
    both_g = np.vstack([b["gyro_rad_s"] for b in bins.values()])
    w = bins.get("warming", next(iter(bins.values())))
    return {"edges_c": edges, "bins": bins,
            "filled": {n: int(np.sum(np.all(np.isfinite(b["gyro_rad_s"]), axis=1))) for n, b in bins.items()},
            "accel_mg": U.mps2_to_mg(_ptp(both_a)), "gyro_dps": U.rad_s_to_dps(_ptp(both_g)),
            "accel_mg_warming": U.mps2_to_mg(_ptp(w["accel_mps2"])),
            "gyro_dps_warming": U.rad_s_to_dps(_ptp(w["gyro_rad_s"]))}


def _bin_means(temp, y, edges, min_n: int) -> np.ndarray:
    idx = np.digitize(temp, edges) - 1
    m = np.full(len(edges) - 1, np.nan)
    for i in range(len(edges) - 1):
        sel = idx == i
        if sel.sum() >= min_n:
            m[i] = y[sel].mean()
    return m


def _ptp(x: np.ndarray) -> np.ndarray:
    """max − min per column, NaN bins left out (a column with no bin at all: NaN)."""
    out = np.full(x.shape[1], np.nan)
    for k in range(x.shape[1]):
        v = x[np.isfinite(x[:, k]), k]
        if len(v):
            out[k] = v.max() - v.min()
    return out
