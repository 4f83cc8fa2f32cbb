"""What a warm-up calibration keeps and shows: DIR/thermal.json (kind "imubench thermal warmup",
rewritten atomically as the run goes), the printed progress and fit tables, and the plot of the
binned biases against temperature with the fitted curves."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.analysis.thermal_poly import AxisFit, Binned, PolyFit
from imubench.results.atomic import save_figure, write_json_atomic
from imubench.results.numbers import pm
from imubench.results.record import now_utc
from imubench.results.thermal import _js
from imubench.files import make_dir
from imubench.wire.board_parts import DEFAULT as DEFAULT_PARTS
from imubench.wire.board_parts import BoardParts

WARMUP_SCHEMA = 1
KIND = "imubench thermal warmup"
UNITS = {"accel": "m/s^2", "gyro": "rad/s"}


def temperature_words(triad: str, parts: BoardParts = DEFAULT_PARTS) -> str:
    """The temperature a triad is fitted against, named with the board's parts."""
    if triad == "accel":
        return f"the {parts.accel.name} temperature (all three axes)"
    return f"each {parts.gyro_words}'s own temperature (gyro X, Y, Z)"


def axis_json(a: AxisFit) -> dict:
    f = a.bias
    return _js({"order": f.order, "coef": [None if not math.isfinite(v) else v for v in f.coef],
                "coef_sigma": f.sigma, "cov": f.cov, "heldout_rms": f.heldout_rms,
                "heldout_by_order": {str(k): v for k, v in f.heldout_by_order.items()},
                "span_c": list(f.span_c), "n_bins": f.n_bins, "n_distinct_temps": f.n_distinct,
                "max_supported_order": f.max_supported_order, "chi2_red": f.chi2_red,
                "sigma_over_span": f.sigma_over_span(), "n_cells": f.n_cells,
                "rw_var_per_s": f.rw_var_per_s, "rw_timelines": [_thin(T, t) for T, t in f.rw_timelines],
                "alt_coef": None if f.alt_coef is None else [None if not math.isfinite(v) else v for v in f.alt_coef],
                "scale_tc_per_c": a.scale_tc_per_c,
                "scale_tc_sigma_per_c": a.scale_tc_sigma_per_c, "notes": list(f.notes),
                "undetermined": list(a.undetermined)})


def _thin(T, t, n: int = 120) -> list:
    """A timeline (temperatures, times) cut to at most n points (for the JSON; interpolated between)."""
    T, t = np.asarray(T, float), np.asarray(t, float)
    if len(T) > n:
        i = np.unique(np.r_[np.linspace(0, len(T) - 1, n).round().astype(int)])
        T, t = T[i], t[i]
    return [T.tolist(), t.tolist()]


def polyfit_from_json(a: dict, t_ref_c: float) -> PolyFit:
    """An axis of thermal.json's fit back as a PolyFit (to evaluate the curve and its σ); an
    undetermined c0 (null) comes back as 0."""
    def arr(v):
        return None if v is None else np.array([np.nan if x is None else x for x in v], float)
    coef = np.nan_to_num(arr(a["coef"]))
    alt = arr(a.get("alt_coef"))
    if alt is not None:
        alt[0] = coef[0] if not np.isfinite(alt[0]) else alt[0]
    return PolyFit(order=int(a["order"]), coef=coef, cov=np.array(a["cov"], float), heldout_rms=a["heldout_rms"],
                   heldout_by_order={int(k): v for k, v in (a.get("heldout_by_order") or {}).items()},
                   span_c=tuple(a["span_c"]), n_bins=int(a["n_bins"]), t_ref_c=float(t_ref_c), alt_coef=alt,
                   rw_var_per_s=float(a.get("rw_var_per_s") or 0.0),
                   rw_timelines=[(np.asarray(T, float), np.asarray(t, float)) for T, t in a.get("rw_timelines") or []])


def fit_json(fits: dict, t_ref: dict, parts: BoardParts = DEFAULT_PARTS) -> dict:
    """{"accel": {...}, "gyro": {...}}: per triad the unit (coefficient i in unit/°C^i), the
    temperature each axis is fitted against (named with the board's parts), t_ref_c and the
    three axes (axis_json)."""
    out = {}
    for triad, axes in fits.items():
        unit, temp = UNITS[triad], temperature_words(triad, parts)
        out[triad] = {"unit": unit, "coef_unit": f"{unit} per degC^i (coef[i])", "temperature": temp,
                      "t_ref_c": t_ref[triad], "axes": [axis_json(a) for a in axes]}
    return out


def bins_json(b: Binned) -> dict:
    """The bins of a run (device time, temperatures: accelerometer, gyro X/Y/Z; accel and gyro means and σ)."""
    return _js({"t_s": b.t_s, "temp_c": b.temp_c, "accel_mps2": b.mean[:, :3], "gyro_rad_s": b.mean[:, 3:6],
                "accel_sigma_mps2": b.sigma[:, :3], "gyro_sigma_rad_s": b.sigma[:, 3:6], "n": b.n})


class WarmupRecord:
    """DIR/thermal.json of a warm-up, rewritten atomically by every update; a directory that
    already holds a thermal.json is refused."""

    NAME = "thermal.json"

    def __init__(self, directory, config: dict):
        self.dir = Path(directory)
        self.path = self.dir / self.NAME
        make_dir(self.dir)
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


def _rate(r) -> str:
    return "   —  " if not math.isfinite(r) else f"{r:+.2f}"


def format_progress(p: dict) -> str:
    """One line: device time, the four temperatures (accelerometer, gyro X/Y/Z), their rates, the span
    each covered, and the orders fitted so far (accel x/y/z, gyro x/y/z)."""
    span = " ".join(f"{lo:.1f}..{hi:.1f}" for lo, hi in p["span_c"])
    s = (f"{p['elapsed_s']:6.0f} s  T {_temps(p['temp_c'])} °C  dT/dt {'/'.join(_rate(r) for r in p['rate_c_per_min'])}"
         f" °C/min  covered {span} °C")
    fit = p.get("fit")
    if fit:
        s += ("  orders accel " + "/".join(str(o) for o in fit["accel"]["order"])
              + " gyro " + "/".join(str(o) for o in fit["gyro"]["order"]))
    return s


_SHOW = {"accel": (1e6 / U.G0_MPS2, "µg"), "gyro": (1e3 * 180.0 / math.pi, "m°/s")}


def format_fit(fj: dict) -> str:
    """The fitted polynomials per axis: order, c1..c3 ± σ (in µg or m°/s per °C^i), the held-out
    RMS, the span and the curve's σ over it; then what could not be determined."""
    L = []
    for triad, d in fj.items():
        k, u = _SHOW[triad]
        L.append(f"{triad} (t_ref {d['t_ref_c']:g} °C; against {d['temperature']}):")
        for ax, a in zip("xyz", d["axes"]):
            terms = [pm(c, s, f"{u}/°C{'' if i == 1 else '²' if i == 2 else '³'}", k)
                     for i, (c, s) in enumerate(zip(a["coef"], a["coef_sigma"])) if 1 <= i <= a["order"]]
            scale = ""
            if a.get("scale_tc_per_c") is not None:
                scale = "  scale " + pm(a["scale_tc_per_c"], a["scale_tc_sigma_per_c"], "ppm/°C", 1e6)
            rw = a.get("rw_var_per_s") or 0.0
            rw = f", bias random walk {math.sqrt(rw) * k:.2g} {u}/√s" if rw > 0 else ""
            L.append(f"  {ax}: order {a['order']}  {', '.join(terms) or 'no temperature dependence'}{scale}  "
                     f"held-out {a['heldout_rms'] * k:.3g} {u}, curve σ ≤ {a['sigma_over_span'] * k:.2g} {u} over "
                     f"{a['span_c'][0]:.1f}..{a['span_c'][1]:.1f} °C ({a['n_bins']} bins{rw})")
        for a in d["axes"]:
            L += [f"  note: {n}" for n in a["notes"] + a["undetermined"]]
        if any((a.get("rw_var_per_s") or 0) > 0 for a in d["axes"]):
            L.append("  note: a bias random walk (bins at one temperature, apart in time) is in the curve's σ: "
                     "one warm-up cannot tell it from a thermal slope")
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
    parts = BoardParts.of_device(data.get("device"))     # the parts the board reported, named on the axes
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
        ax.set_xlabel(f"{parts.accel.name} temperature (°C)" if triad == "accel" else
                      f"gyro temperature (°C, each its own: {parts.gyro_words})")
        ax.set_ylabel(f"bias − bias at t_ref ({u})")
        ax.set_title(f"{triad}: warm-up bins and fitted polynomial (t_ref {d['t_ref_c']:g} °C)", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)


def warmup_html(data: dict, esc, img, tmpdir: Path) -> str:
    """The report's temperature section for a warm-up's thermal.json: status, stop reason, the
    fitted terms per axis (order, c1..c3 ± σ, held-out RMS, span, curve σ), what could not be
    determined, the write-back, and the plot (img(png_path, alt) embeds it)."""
    out = ["<p>method: warm-up (the board warmed while it lay still; polynomial per axis against its "
           "sensor's own temperature, order by held-out error)</p>"]
    if data.get("status") != "done":
        out.append(f'<p class="note">incomplete run: status {esc(data.get("status"))}; '
                   f'{esc(data.get("stop_reason") or "")} {esc(data.get("error") or "")}; the fit of what came is shown.</p>')
    else:
        out.append(f"<p>stopped: {esc(data.get('stop_reason'))}</p>")
    fj = data.get("fit")
    if not fj:
        out.append('<p class="missing">no fit (too few bins).</p>')
        return "\n".join(out)
    rows = []
    for triad, d in fj.items():
        k, u = _SHOW[triad]
        for ax, a in zip("xyz", d["axes"]):
            terms = [pm(c, s, "", k) for i, (c, s) in enumerate(zip(a["coef"], a["coef_sigma"])) if 1 <= i <= 3]
            terms = [t if i < a["order"] else "—" for i, t in enumerate(terms)]
            rows.append(f"<tr><td style='white-space:nowrap'>{esc(triad)} {ax}</td><td>{a['order']}</td>"
                        + "".join(f"<td>{esc(t)}</td>" for t in terms)
                        + f"<td>{a['heldout_rms'] * k:.3g}</td><td style='white-space:nowrap'>{a['span_c'][0]:.1f}–{a['span_c'][1]:.1f}</td>"
                        f"<td>{a['sigma_over_span'] * k:.2g}</td></tr>")
    out.append("<table><tr><th>axis</th><th>order</th><th>c1 [µg or m°/s per °C]</th><th>c2 [per °C²]</th>"
               "<th>c3 [per °C³]</th><th>held-out RMS [µg or m°/s]</th><th>span [°C]</th>"
               "<th>curve σ over span [µg or m°/s]</th></tr>" + "".join(rows) + "</table>")
    for d in fj.values():
        for a in d["axes"]:
            for n in a["notes"] + a["undetermined"]:
                out.append(f'<p class="note">{esc(n)}</p>')
    w = data.get("write")
    if w:
        out.append(f"<p>written: {esc(', '.join(w.get('steps') or []))}; device check "
                   f"{'passed' if w.get('verified') else 'FAILED: ' + esc(w.get('error') or '')}</p>")
    png = plot_warmup(data, Path(tmpdir) / "warmup.png")
    if png is not None:
        out.append("<h3>Bias against temperature</h3>" + img(png, "warm-up bins and the fitted polynomials"))
    return "\n".join(out)
