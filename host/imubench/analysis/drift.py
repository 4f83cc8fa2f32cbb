"""How a device's calibration moved from run to run: bias and scale per run in user units
(mg, °/s, ppm), the change between runs with its combined sigma, and which changes are real
drifts (larger than DRIFT_SIGMAS combined sigmas) rather than the noise of two fits.

Pure numerics on the history's run dicts (results.history reads them; cli.history_text
prints them).
"""
from __future__ import annotations

import math

import numpy as np

from imubench import units as U

DRIFT_SIGMAS = 3.0          # a change is flagged when |change| > DRIFT_SIGMAS * combined sigma
_AXES = ("x", "y", "z")


def _fin(x) -> float | None:
    """A float for JSON: None for NaN/inf/None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _sigma_ok(s) -> bool:
    return s is not None and math.isfinite(s) and s > 0


def _triad_summary(t: dict | None, b_key: str, to_user, bias_unit: str) -> dict | None:
    """Bias in user units, scale error diag(M) − 1 in ppm, the largest off-diagonal of M in
    ppm; sigmas None where the fit did not estimate the parameter."""
    if t is None:
        return None
    m = np.array(t["m"], dtype=np.float64)
    sm = np.array(t["sigma_m"], dtype=np.float64)
    b = np.array(t[b_key], dtype=np.float64)
    sb = np.array(t[f"sigma_{b_key}"], dtype=np.float64)
    off = np.abs(m)
    np.fill_diagonal(off, -1.0)             # only the off-diagonal (cross-axis) terms compete
    i, j = np.unravel_index(int(np.argmax(off)), (3, 3))
    return {
        f"bias_{bias_unit}": [_fin(v) for v in to_user(b)],
        f"bias_sigma_{bias_unit}": [_fin(v) for v in to_user(sb)],
        "scale_error_ppm": [_fin(v) for v in (np.diag(m) - 1.0) * 1e6],
        "scale_error_sigma_ppm": [_fin(v) for v in np.diag(sm) * 1e6],
        "cross_axis": {"term": f"M[{_AXES[i]},{_AXES[j]}]", "row": int(i), "col": int(j),
                       "ppm": _fin(m[i, j] * 1e6), "sigma_ppm": _fin(sm[i, j] * 1e6)},
    }


def run_summary(run: dict, index: int) -> dict:
    """One run in user units (mg, °/s, ppm), as `imubench history DEVICE` shows it."""
    acc = _triad_summary(run["accel"], "b_mps2", U.mps2_to_mg, "mg")
    if acc is not None:
        rr = run["accel"].get("residual_rms_mps2")
        acc["residual_rms_mg"] = _fin(U.mps2_to_mg(rr)) if rr is not None else None
    gyr = _triad_summary(run["gyro"], "b_rad_s", U.rad_s_to_dps, "dps")
    if gyr is not None:
        gyr["residual_rms"] = _fin(run["gyro"].get("residual_rms"))
    return {
        "index": index, "run_id": run["run_id"], "started": run["started"], "finished": run["finished"],
        "method": run["method"], "gyro_method": run["gyro_method"],
        "fw_version": run["fw_version"], "fw_build": run["fw_build"],
        "accel": acc, "gyro": gyr,
        "temperature_c": {"accel": _fin(run["temperature_c"]["accel"]),
                          "gyro": None if run["temperature_c"]["gyro"] is None
                          else [_fin(v) for v in run["temperature_c"]["gyro"]]},
        "passed": run["passed"], "written": run["written"], "verified": run["verified"],
        "note": run["note"] or "", "capture_dir": run["capture_dir"],
        **{k: run.get(k) for k in ("station_id", "operator", "fixture", "slot", "port", "host_version",
                                   "session_id", "capture_sha256", "capture_uri", "failed_stage", "failure")},
        "measurements": run.get("measurements") or [],
    }


# (key, sensor, value key, sigma key, unit)
DRIFT_QUANTITIES = (
    ("accel_bias_mg", "accel", "bias_mg", "bias_sigma_mg", "mg"),
    ("accel_scale_ppm", "accel", "scale_error_ppm", "scale_error_sigma_ppm", "ppm"),
    ("gyro_bias_dps", "gyro", "bias_dps", "bias_sigma_dps", "°/s"),
    ("gyro_scale_ppm", "gyro", "scale_error_ppm", "scale_error_sigma_ppm", "ppm"),
)


def _change(a: dict, b: dict) -> dict:
    d = b["value"] - a["value"]
    s = math.hypot(a["sigma"], b["sigma"])
    return {"from": a["index"], "to": b["index"], "from_run_id": a["run_id"], "to_run_id": b["run_id"],
            "change": d, "sigma": s, "n_sigma": abs(d) / s, "flagged": abs(d) > DRIFT_SIGMAS * s}


def drift(summaries: list[dict]) -> dict:
    """How each bias and scale error moved across runs: per axis, the change between
    consecutive runs that estimated it, and first → last; each with the combined 1-sigma
    sqrt(σ1² + σ2²) and flagged when |change| > DRIFT_SIGMAS × that. A run where a quantity
    was not estimated (no sigma, e.g. the gyro scale of a bias-only run) is left out of it."""
    out = {"threshold_sigmas": DRIFT_SIGMAS, "quantities": {}, "flagged": []}
    for key, sensor, vkey, skey, unit in DRIFT_QUANTITIES:
        axes = {}
        for k, ax in enumerate(_AXES):
            series = []
            for s in summaries:
                t = s[sensor]
                if t is None:
                    continue
                v, sg = t[vkey][k], t[skey][k]
                if v is None or not _sigma_ok(sg):
                    continue
                series.append({"index": s["index"], "run_id": s["run_id"], "value": v, "sigma": sg})
            steps = [_change(a, b) for a, b in zip(series, series[1:])]
            first_last = _change(series[0], series[-1]) if len(series) >= 2 else None
            axes[ax] = {"runs": [x["index"] for x in series], "steps": steps, "first_last": first_last}
            for st in steps + ([first_last] if first_last and len(series) > 2 else []):
                if st["flagged"]:
                    out["flagged"].append({"quantity": key, "axis": ax, "unit": unit, **st})
        out["quantities"][key] = {"unit": unit, "axes": axes}
    return out
