"""What a warm-up calibration keeps and shows: DIR/thermal.json (kind "imubench thermal warmup",
rewritten atomically as the run goes), the printed progress and fit tables, and the plot of the
binned biases against temperature with the fitted curves."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.analysis.thermal_poly import AxisFit, Binned
from imubench.results.atomic import save_figure, write_json_atomic
from imubench.results.numbers import pm
from imubench.results.record import now_utc
from imubench.results.thermal import _js

WARMUP_SCHEMA = 1
KIND = "imubench thermal warmup"
SENSORS = ("ADXL355", "gyro X", "gyro Y", "gyro Z")
TRIADS = {"accel": ("m/s^2", "ADXL355 temperature (all three axes)"),
          "gyro": ("rad/s", "each ADXRS450's own temperature (gyro X, Y, Z)")}


def axis_json(a: AxisFit) -> dict:
    f = a.bias
    return _js({"order": f.order, "coef": [None if not math.isfinite(v) else v for v in f.coef],
                "coef_sigma": f.sigma, "cov": f.cov, "heldout_rms": f.heldout_rms,
                "heldout_by_order": {str(k): v for k, v in f.heldout_by_order.items()},
                "span_c": list(f.span_c), "n_bins": f.n_bins, "n_distinct_temps": f.n_distinct,
                "max_supported_order": f.max_supported_order, "chi2_red": f.chi2_red,
                "sigma_over_span": f.sigma_over_span(), "scale_tc_per_c": a.scale_tc_per_c,
                "scale_tc_sigma_per_c": a.scale_tc_sigma_per_c, "notes": list(f.notes),
                "undetermined": list(a.undetermined)})


def fit_json(fits: dict, t_ref: dict) -> dict:
    """{"accel": {...}, "gyro": {...}}: per triad the unit (coefficient i in unit/°C^i), the
    temperature each axis is fitted against, t_ref_c and the three axes (axis_json)."""
    out = {}
    for triad, axes in fits.items():
        unit, temp = TRIADS[triad]
        out[triad] = {"unit": unit, "coef_unit": f"{unit} per degC^i (coef[i])", "temperature": temp,
                      "t_ref_c": t_ref[triad], "axes": [axis_json(a) for a in axes]}
    return out


def bins_json(b: Binned) -> dict:
    """The bins of a run (device time, temperatures ADXL355/gyro X/Y/Z, accel and gyro means and σ)."""
    return _js({"t_s": b.t_s, "temp_c": b.temp_c, "accel_mps2": b.mean[:, :3], "gyro_rad_s": b.mean[:, 3:6],
                "accel_sigma_mps2": b.sigma[:, :3], "gyro_sigma_rad_s": b.sigma[:, 3:6], "n": b.n})


class WarmupRecord:
    """DIR/thermal.json of a warm-up, rewritten atomically by every update; a directory that
    already holds a thermal.json is refused."""

    NAME = "thermal.json"

    def __init__(self, directory, config: dict):
        self.dir = Path(directory)
        self.path = self.dir / self.NAME
        self.dir.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists: choose another --out directory")
        self.data = {"schema": WARMUP_SCHEMA, "kind": KIND, "status": "running", "stage": "start", "error": None,
                     "started": now_utc(), "updated": None, "config": _js(config), "device": None,
                     "t_ref_c": None, "capture": None, "progress": None, "stop_reason": None, "fit": None,
                     "bins": None, "write": None, "exports": {}}
        self.save()

    def update(self, **kw) -> None:
        self.data.update(_js(kw))
        self.save()

    def save(self) -> None:
        self.data["updated"] = now_utc()
        write_json_atomic(self.path, self.data)


def _temps(v) -> str:
    return "/".join(f"{x:.1f}" for x in v)


def format_progress(p: dict) -> str:
    """One line: device time, the four temperatures, their rates and spans, the fitted orders."""
    span = " ".join(f"{lo:.1f}..{hi:.1f}" for lo, hi in p["span_c"])
    s = (f"{p['elapsed_s']:7.0f} s  T {_temps(p['temp_c'])} °C  rate "
         f"{'/'.join(f'{r:+.2f}' for r in p['rate_c_per_min'])} °C/min  span {span} °C")
    fit = p.get("fit")
    if fit:
        s += "  order a " + "".join(str(o) for o in fit["accel"]["order"]) + " g " + "".join(
            str(o) for o in fit["gyro"]["order"])
    return s


_SHOW = {"accel": (1e6 / U.G0_MPS2, "µg"), "gyro": (1e3 * 180.0 / math.pi, "m°/s")}


def format_fit(fj: dict) -> str:
    """The fitted polynomials per axis: order, c1..c3 ± σ (in µg or m°/s per °C^i), the held-out
    RMS, the span and the curve's σ over it; then what could not be determined."""
    L = []
    for triad, d in fj.items():
        k, u = _SHOW[triad]
        L.append(f"{triad} (t_ref {d['t_ref_c']:g} °C; against the {d['temperature']}):")
        for ax, a in zip("xyz", d["axes"]):
            terms = [pm(c, s, f"{u}/°C{'' if i == 1 else '²' if i == 2 else '³'}", k)
                     for i, (c, s) in enumerate(zip(a["coef"], a["coef_sigma"])) if 1 <= i <= a["order"]]
            scale = ""
            if a.get("scale_tc_per_c") is not None:
                scale = "  scale " + pm(a["scale_tc_per_c"], a["scale_tc_sigma_per_c"], "ppm/°C", 1e6)
            L.append(f"  {ax}: order {a['order']}  {', '.join(terms) or 'no temperature dependence'}{scale}  "
                     f"held-out {a['heldout_rms'] * k:.3g} {u}, curve σ ≤ {a['sigma_over_span'] * k:.2g} {u} over "
                     f"{a['span_c'][0]:.1f}..{a['span_c'][1]:.1f} °C ({a['n_bins']} bins)")
        for a in d["axes"]:
            L += [f"  note: {n}" for n in a["notes"] + a["undetermined"]]
    return "\n".join(L)


def plot_warmup(data: dict, path) -> Path | None:
    """PNG: per triad, each axis's binned bias (minus its value at t_ref) against its temperature
    with the fitted curve and its 1-σ band; None without bins or a fit."""
    bins, fit = data.get("bins"), data.get("fit")
    if not bins or not fit or len(bins.get("t_s") or []) < 2:
        return None
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from imubench.analysis.thermal_poly import poly_eval
    fig = Figure(figsize=(12, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    temp = np.asarray(bins["temp_c"], float)
    colors = ("tab:red", "tab:green", "tab:blue")
    for ax, triad, key in ((axes[0], "accel", "accel_mps2"), (axes[1], "gyro", "gyro_rad_s")):
        k, u = _SHOW[triad]
        y = np.asarray(bins[key], float)
        d = fit[triad]
        for i, a in enumerate(d["axes"]):
            t = temp[:, 0] if triad == "accel" else temp[:, 1 + i]
            c = np.array([0.0 if v is None else v for v in a["coef"]])
            c[0] = 0.0                                   # each face has its own intercept: shown as 0
            lo, hi = a["span_c"]
            tt = np.linspace(lo, hi, 100)
            icpt = float(np.median(y[:, i] - poly_eval(c, t, d["t_ref_c"], lo, hi)))   # the face's intercept
            ax.plot(t, (y[:, i] - icpt) * k, ".", ms=3, color=colors[i], alpha=0.5, label=f"{'xyz'[i]} bins")
            cov = np.asarray(a["cov"], float)
            V = np.vander(tt - d["t_ref_c"], 4, increasing=True)
            sg = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", V, cov, V), 0, None))
            f = poly_eval(c, tt, d["t_ref_c"])
            ax.plot(tt, f * k, "-", color=colors[i], lw=1.2, label=f"{'xyz'[i]} fit, order {a['order']}")
            ax.fill_between(tt, (f - sg) * k, (f + sg) * k, color=colors[i], alpha=0.2, lw=0)
        ax.set_xlabel("ADXL355 temperature (°C)" if triad == "accel" else "gyro temperature (°C, each its own)")
        ax.set_ylabel(f"bias − bias at t_ref ({u})")
        ax.set_title(f"{triad}: warm-up bins and fitted polynomial (t_ref {d['t_ref_c']:g} °C)", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)
