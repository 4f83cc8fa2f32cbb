"""What a thermal run keeps and shows: DIR/thermal.json (rewritten atomically after every point
and step) and the printed coefficient and drift tables."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.analysis.thermal import AXES, TempPoint, ThermalFit
from imubench.results.atomic import save_figure, write_json_atomic
from imubench.results.numbers import pm
from imubench.results.record import now_utc
from imubench.files import make_dir
from imubench.wire.board_parts import BoardParts

THERMAL_SCHEMA = 1


FIT_KEYS = (("accel_bias_tc", "mps2_per_c"), ("accel_scale_tc", "per_c"),
            ("gyro_bias_tc", "rad_s_per_c"), ("gyro_scale_tc", "per_c"))


def _js(x):
    """JSON-able copy (numpy arrays and scalars to lists and floats)."""
    if isinstance(x, dict):
        return {str(k): _js(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_js(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


def point_json(p: TempPoint) -> dict:
    """One temperature point as stored in thermal.json (SI; the unit ends each key)."""
    d = {"set_c": p.target_c, "accel_temp_c": p.accel_temp_c, "gyro_temp_c": p.gyro_temp_c,
         "t_first_us": p.t_first_us, "t_last_us": p.t_last_us, "settle": p.settle,
         "gyro_rest_rad_s": p.gyro_rest, "gyro_rest_sigma_rad_s": p.gyro_rest_sigma,
         "accel_mps2": {k: v[0] for k, v in p.accel.items()},
         "accel_sigma_mps2": {k: v[1] for k, v in p.accel.items()},
         "gyro_turn_rad_s": None, "gyro_turn_sigma_rad_s": None}
    if len(p.turns) == 3:
        d["gyro_turn_rad_s"] = [p.turns[a][0] for a in range(3)]
        d["gyro_turn_sigma_rad_s"] = [p.turns[a][1] for a in range(3)]
    return _js(d)


def fit_json(f: ThermalFit) -> dict:
    """The fit's coefficients and 1-sigma, keyed with their units (the params field names)."""
    d = {"t_ref_c": f.t_ref_c}
    for key, unit in FIT_KEYS:
        d[f"{key}_{unit}"] = getattr(f, key)
        d[f"{key}_sigma_{unit}"] = getattr(f, key + "_sigma")
    d["notes"] = list(f.notes)
    return _js(d)


def drift_json(d: dict) -> dict:
    return _js({"set_c": d["set_c"], "accel_temp_c": d["accel_temp_c"],
                "accel_mean_mps2": d["accel_mean_mps2"], "gyro_mean_rad_s": d["gyro_mean_rad_s"],
                "accel_drift_mps2": d["accel_drift_mps2"], "gyro_drift_rad_s": d["gyro_drift_rad_s"]})


class ThermalRecord:
    """DIR/thermal.json of one run, rewritten atomically (temp file + os.replace) by every
    update, so a crash leaves the previous or the new version, never a torn one. A directory
    that already holds a thermal.json is refused (no --resume: choose another directory)."""

    NAME = "thermal.json"

    def __init__(self, directory, config: dict):
        self.dir = Path(directory)
        self.path = self.dir / self.NAME
        make_dir(self.dir)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists: choose another --out directory")
        self.data = {"schema": THERMAL_SCHEMA, "kind": "imubench thermal", "status": "running",
                     "stage": "start", "error": None, "started": now_utc(), "updated": None,
                     "config": _js(config), "device": None, "t_ref_c": None, "points": []}
        self.save()

    def update(self, **kw) -> None:
        self.data.update(_js(kw))
        self.save()

    def add_point(self, p: TempPoint) -> None:
        self.data["points"].append(point_json(p))
        self.save()

    def save(self) -> None:
        self.data["updated"] = now_utc()
        write_json_atomic(self.path, self.data)


def format_fit(f: ThermalFit) -> str:
    """The coefficients ± 1 sigma, each to the precision its sigma allows (results.numbers)."""
    rows = []
    for k in range(3):
        rows.append((f"accel {AXES[k]}", pm(f.accel_bias_tc[k], f.accel_bias_tc_sigma[k], "µg/°C", 1e6 / U.G0_MPS2),
                     pm(f.accel_scale_tc[k], f.accel_scale_tc_sigma[k], "ppm/°C", 1e6)))
    for k in range(3):
        rows.append((f"gyro {AXES[k]}", pm(f.gyro_bias_tc[k], f.gyro_bias_tc_sigma[k], "m°/s/°C",
                                           1e3 * 180.0 / math.pi),
                     pm(f.gyro_scale_tc[k], f.gyro_scale_tc_sigma[k], "ppm/°C", 1e6)))
    w = max(len(r[1]) for r in rows)
    L = [f"temperature coefficients (t_ref {f.t_ref_c:g} °C), ± 1 sigma:"]
    L += [f"  {name:8} bias {b:>{w}}   scale {s}" for name, b, s in rows]
    L += [f"  note: {n}" for n in f.notes]
    return "\n".join(L)


def format_drift(before: dict, after: dict | None) -> str:
    L = ["drift of the calibrated output over the sweep (max − min):"]
    names = ["accel x", "accel y", "accel z", "|accel|"]
    for i, nm in enumerate(names):
        b = before["accel_drift_mps2"][i] / U.G0_MPS2 * 1e3
        s = f"  {nm:8s} before {b:9.4f} mg"
        if after is not None:
            a = after["accel_drift_mps2"][i] / U.G0_MPS2 * 1e3
            s += f"   after {a:9.4f} mg   ({b / max(a, 1e-12):.0f}x)"
        L.append(s)
    for k in range(3):
        b = U.rad_s_to_dps(before["gyro_drift_rad_s"][k])
        s = f"  gyro {AXES[k]}   before {b:9.4f} °/s"
        if after is not None:
            a = U.rad_s_to_dps(after["gyro_drift_rad_s"][k])
            s += f"  after {a:9.4f} °/s  ({b / max(a, 1e-12):.0f}x)"
        L.append(s)
    return "\n".join(L)


def plot_thermal(data: dict, path) -> Path | None:
    """PNG of a thermal.json: each gyro's rest rate against its own temperature, and the
    accelerometer's level (+Z up) means against its own temperature, with the fitted
    temperature coefficients as lines through the points' mean. None when there are fewer
    than two points."""
    pts = [p for p in data.get("points") or [] if isinstance(p, dict)]
    if len(pts) < 2:
        return None
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax_g, ax_a = fig.subplots(1, 2)
    colors = ("tab:red", "tab:green", "tab:blue")
    deg = 180.0 / math.pi
    for k, ax_name in enumerate(AXES):
        tg = np.array([p["gyro_temp_c"][k] for p in pts], dtype=float)
        g = np.array([p["gyro_rest_rad_s"][k] for p in pts], dtype=float) * deg
        gs = np.array([(p.get("gyro_rest_sigma_rad_s") or [0, 0, 0])[k] for p in pts], dtype=float) * deg
        ax_g.errorbar(tg, g, yerr=gs, fmt="o", color=colors[k], label=f"gyro {ax_name}")
        coef = (data.get("gyro_bias_tc_rad_s_per_c") or [None] * 3)[k]
        if coef is not None:
            tt = np.array([tg.min(), tg.max()])
            ax_g.plot(tt, g.mean() + coef * deg * (tt - tg.mean()), "--", color=colors[k], lw=1,
                      label=f"fit: {coef * deg * 1e3:+.3g} m°/s/°C")
    ax_g.set_xlabel(f"gyro temperature (°C, each gyro's own: {BoardParts.of_device(data.get('device')).gyro_words})")
    ax_g.set_ylabel("rate at rest (°/s, nominal scaling)")
    ax_g.set_title("gyro bias against temperature", fontsize=10)
    ta = np.array([p["accel_temp_c"] for p in pts], dtype=float)
    lvl = [p.get("accel_mps2", {}).get("+z") for p in pts]
    if all(v is not None for v in lvl):
        a = np.array(lvl, dtype=float) * 1e3 / U.G0_MPS2
        for k, ax_name in enumerate(AXES):
            y = a[:, k] - a[:, k].mean()
            ax_a.plot(ta, y, "o", color=colors[k], label=f"accel {ax_name} (+Z up) − its mean")
            coef = (data.get("accel_bias_tc_mps2_per_c") or [None] * 3)[k]
            if coef is not None:
                # level, Z reads b_z + (1 + scale_tc_z·ΔT)·g: its slope is bias_tc + scale_tc·g
                stc = (data.get("accel_scale_tc_per_c") or [0.0] * 3)[k] if k == 2 else 0.0
                slope = coef + (stc or 0.0) * U.G0_MPS2
                tt = np.array([ta.min(), ta.max()])
                ax_a.plot(tt, slope * 1e3 / U.G0_MPS2 * (tt - ta.mean()), "--", color=colors[k], lw=1,
                          label=(f"fit: bias {coef * 1e6 / U.G0_MPS2:+.3g} µg/°C"
                                 + (f" + scale {stc * 1e6:+.3g} ppm/°C × 1 g" if k == 2 else "")))
    ax_a.set_xlabel(f"{BoardParts.of_device(data.get('device')).accel.name} temperature (°C)")
    ax_a.set_ylabel("change of the level mean (mg)")
    ax_a.set_title("accelerometer, level, against temperature", fontsize=10)
    for ax in (ax_g, ax_a):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)
