"""What a calibration session shows about its accelerometer fit: a per-pose plot (PNG) and a
before/after table, both from the session's result record (see imubench.results.history for its keys).

The per-pose quantity is |a| − g: the magnitude of the measured specific force, lying still,
minus one standard gravity (docs/conventions.md: g0 = 9.80665 m/s²). The record carries |a| in
units of g0 per pose, before calibration (nominal datasheet scaling) and after (the fitted
M, b applied), with sigma_g the 1-sigma of that pose's mean; this module shows them in mg.

The plot is drawn on a matplotlib Figure with the Agg canvas directly (no pyplot): it never
needs a display and never changes the process's matplotlib backend.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.calib.fit import accel_method_words
from imubench.results.atomic import save_figure
from imubench.results.numbers import pm
from imubench.files import make_dir

ACCEL_TOL_KEY = "accel_rms_mg"      # RMS of |a| − g over the poses after calibration
VERIFY_TOL_KEY = "verify_mg"        # each verification pose: | |a| − g | of the device's output


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _poses(result: dict):
    poses = result.get("poses") or []
    if not poses:
        raise ValueError("the result record has no poses")
    names = [str(p.get("name", f"pose {i + 1}")) for i, p in enumerate(poses)]
    before = np.array([(_f(p.get("before_g")) - 1.0) * 1000.0 for p in poses])
    after = np.array([(_f(p.get("after_g")) - 1.0) * 1000.0 for p in poses])
    sigma = np.array([_f(p.get("sigma_g")) * 1000.0 for p in poses])
    return names, before, after, sigma


def _verification(result: dict):
    ver = result.get("verification") or []
    names = [str(v.get("name", f"check {i + 1}")) for i, v in enumerate(ver)]
    after = np.array([(_f(v.get("after_g")) - 1.0) * 1000.0 for v in ver])
    sigma = np.array([_f(v.get("sigma_g")) * 1000.0 for v in ver])
    return names, after, sigma


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else math.nan


def _tol(result: dict, key: str) -> float | None:
    v = (result.get("tolerances") or {}).get(key)
    v = _f(v)
    return v if math.isfinite(v) and v > 0 else None


def _uid(result: dict) -> str:
    return str((result.get("device") or {}).get("mcu_uid", "unknown device")).upper()


def _method(result: dict) -> str:
    return accel_method_words(result.get("method", "?"))


# ------------------------------------------------------------------ plot
def plot_pose_residuals(result: dict, path) -> Path:
    """Write a PNG of |a| − g per pose, in mg, and return its path.

    Top panel: before (nominal scaling) and after calibration as grouped bars with 1-sigma
    error bars; the after values are usually 100-1000x smaller, so the bottom panel shows the
    after values (and the verification poses read back from the device, if any) on their
    own scale, with the tolerance band(s) as dashed lines. Pose names on the shared x axis.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    path = Path(path)
    names, before, after, sigma = _poses(result)
    vnames, vafter, vsigma = _verification(result)
    tol = _tol(result, ACCEL_TOL_KEY)
    vtol = _tol(result, VERIFY_TOL_KEY)

    # x positions: one slot per calibration pose; a verification pose of the same name shares
    # its slot, others get slots of their own after the calibration poses.
    labels = list(names)
    vx = []
    for n in vnames:
        if n in names:
            vx.append(names.index(n))
        else:
            labels.append(f"{n} (check)")
            vx.append(len(labels) - 1)
    x = np.arange(len(names))
    vx = np.array(vx, dtype=float)
    err = np.where(np.isfinite(sigma), sigma, 0.0)
    verr = np.where(np.isfinite(vsigma), vsigma, 0.0)

    width_in = max(8.0, 0.42 * len(labels) + 3.0) + 3.2     # + the legends, right of the plots
    fig = Figure(figsize=(width_in, 7.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1.15]})

    c_before, c_after, c_ver, c_tol, c_vtol = "#d98b2b", "#2a6fbb", "#2e9e4f", "#c0392b", "#7d3c98"
    w = 0.38
    ax1.bar(x - w / 2, before, w, yerr=err, capsize=2, color=c_before, label="before calibration (nominal scaling)")
    ax1.bar(x + w / 2, after, w, yerr=err, capsize=2, color=c_after, label="after calibration (fitted M, b)")
    ax1.axhline(0.0, color="black", lw=0.8)
    if tol:
        for s in (+1, -1):
            ax1.axhline(s * tol, color=c_tol, ls="--", lw=1.0)
    ax1.set_ylabel("|a| − g  [mg]")
    rb, ra = _rms(before), _rms(after)
    ax1.set_title(f"before vs after calibration — RMS {rb:.3f} mg → {ra:.4f} mg", fontsize=10)
    h1, l1 = ax1.get_legend_handles_labels()
    if tol:
        h1.append(Line2D([], [], color=c_tol, ls="--"))
        l1.append(f"tolerance ±{tol:g} mg")
    ax1.legend(h1, l1, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax1.grid(axis="y", alpha=0.3)

    ax2.errorbar(x, after, yerr=err, fmt="o", color=c_after, ms=5, capsize=3,
                 label="after calibration (fit, ±1σ)")
    if len(vnames):
        off = np.where(vx < len(names), 0.18, 0.0)    # beside a calibration pose of the same name
        ax2.errorbar(vx + off, vafter, yerr=verr, fmt="D", color=c_ver, ms=5, capsize=3,
                     label="verification (device output after write-back)")
    ax2.axhline(0.0, color="black", lw=0.8)
    # the scale follows the data; a tolerance far outside it is named instead of squashing the data flat
    spread = np.concatenate([np.abs(after) + err, np.abs(vafter) + verr])
    spread = spread[np.isfinite(spread)]
    data_max = float(spread.max()) if spread.size and spread.max() > 0 else (tol or vtol or 1.0)
    ymax = 1.3 * data_max
    for t, key, style, color, what in ((tol, "tol", "--", c_tol, "RMS over poses"),
                                       (vtol if len(vnames) else None, "vtol", ":", c_vtol, "each pose")):
        if not t:
            continue
        label = f"{'tolerance' if key == 'tol' else 'verification tolerance'} ±{t:g} mg ({what})"
        if t <= 4.0 * data_max:
            ymax = max(ymax, 1.15 * t)
            ax2.axhline(+t, color=color, ls=style, lw=1.2, label=label)
            ax2.axhline(-t, color=color, ls=style, lw=1.2)
        else:
            ax2.plot([], [], color=color, ls=style, lw=1.2, label=label + ": off this scale")
    ax2.set_ylim(-ymax, ymax)
    verdict = "" if tol is None else (" — PASS" if ra <= tol else " — FAIL")
    tol_txt = "" if tol is None else f" (tolerance {tol:g} mg RMS){verdict}"
    ax2.set_title(f"after calibration, zoomed: RMS {ra:.4f} mg{tol_txt}", fontsize=10)
    ax2.set_ylabel("|a| − g after calibration  [mg]")
    ax2.set_xlabel("pose (gravity direction in the board frame)")
    ax2.set_xticks(np.arange(len(labels)))
    ax2.set_xticklabels(labels, rotation=45 if len(labels) <= 12 else 60, ha="right", fontsize=8)
    ax2.set_xlim(-0.7, len(labels) - 0.3)
    ax2.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax2.grid(axis="y", alpha=0.3)

    when = str(result.get("started", ""))[:16].replace("T", " ")
    status = ", ".join(f"{k} {'yes' if result.get(k) else 'NO'}" for k in ("passed", "written", "verified")
                       if k in result)
    title = (f"Accelerometer |a| − g per pose: {_method(result)} fit\n"
             f"device {_uid(result)}" + (f", {when} UTC" if when else "") + (f"; {status}" if status else ""))
    fig.suptitle(title, fontsize=11)
    make_dir(path.parent)
    # the title also as PNG text, so that what the picture says can be checked without eyes
    save_figure(fig, path, format="png", metadata={"Title": title.replace("\n", " ")})
    return path


# ------------------------------------------------------------------ table
def before_after_table(result: dict) -> str:
    """Plain text: per pose |a| before -> after in g, Δ = after − before in mg and the
    remaining |a| − g after calibration in mg (±1σ); the verification poses if any; then the
    RMS of |a| − g before and after in mg and pass/fail against the tolerance."""
    names, before, after, sigma = _poses(result)
    vnames, vafter, vsigma = _verification(result)
    tol = _tol(result, ACCEL_TOL_KEY)
    vtol = _tol(result, VERIFY_TOL_KEY)
    nw = max([4, *map(len, names), *map(len, vnames)])

    def g(mg: float) -> str:
        return f"{1.0 + mg / 1000.0:.5f} g" if math.isfinite(mg) else "   -    "

    def mg(v: float, s: float = math.nan, dec: int = 3) -> str:
        if not math.isfinite(v):
            return "-"
        return f"{v:+.{dec}f}" + (f" ± {s:.{dec}f}" if math.isfinite(s) else "") + " mg"

    lines = [f"Accelerometer |a| per pose, {_method(result)} fit, device {_uid(result)} (g = 9.80665 m/s²)",
             f"{'pose':<{nw}} | {'before':>9}    {'after':>9} | {'Δ (after − before)':>18} | after: |a| − g"]
    lines.append("-" * len(lines[-1]))
    for n, b, a, s in zip(names, before, after, sigma):
        lines.append(f"{n:<{nw}} | {g(b)} -> {g(a)} | {mg(a - b):>18} | {mg(a, s)}")
    rb, ra = _rms(before), _rms(after)
    if tol is None:
        verdict = "no tolerance given"
    else:
        verdict = f"tolerance {tol:g} mg RMS: {'PASS' if ra <= tol else 'FAIL'}"
    summary = (f"RMS of |a| − g over {len(names)} poses: before {rb:.3f} mg, after {ra:.3f} mg; {verdict}")
    if len(vnames):
        lines.append("")
        lines.append("verification (the device's own calibrated output after write-back):")
        for n, a, s in zip(vnames, vafter, vsigma):
            ok = "" if vtol is None else ("  ok" if abs(a) <= vtol else "  FAIL")
            lines.append(f"{n:<{nw}} | {'':13}{g(a)} | {'':>18} | {mg(a, s)}{ok}")
        vr = _rms(vafter)
        worst = float(np.nanmax(np.abs(vafter))) if np.isfinite(vafter).any() else math.nan
        vverdict = "" if vtol is None else \
            f"; tolerance ±{vtol:g} mg each: {'PASS' if worst <= vtol else 'FAIL'}"
        lines.append("")
        lines.append(summary)
        lines.append(f"verification over {len(vnames)} poses: RMS {vr:.3f} mg, worst {worst:.3f} mg{vverdict}")
    else:
        lines.append("")
        lines.append(summary)
    return "\n".join(lines)


def truth_in_fit_frame(result: dict, truth: dict) -> dict:
    """The virtual device's truth expressed as the session's fit can observe it.

    The multi-position |a| = g model cannot see the accelerometer triad's rotation Q relative
    to the board (M = L·Q, calib.accel.lower_triangular_form): it returns L, and its calibrated
    output is in the Q-rotated frame. A rotation-method gyro fit, which matches gravity
    directions in that frame, then returns M_gyro·Qᵀ. Six-position and the turntable are
    tied to the board axes and see the truth as it is."""
    from imubench.calib.accel import lower_triangular_form
    m_a = np.array(truth["accel"]["m"], dtype=float)
    m_g = np.array([g["sens"] for g in truth["gyro"]], dtype=float)
    q = np.eye(3)
    if result["method"] == "multi" and not str(result.get("accel_frame", "")).startswith("board"):
        m_a, q = lower_triangular_form(m_a)
    if result.get("gyro_method") == "rotation":
        m_g = m_g @ q.T
    return {"accel_m": m_a, "accel_b_mps2": np.array(truth["accel"]["true_bias_mps2"], dtype=float),
            "gyro_m": m_g, "gyro_b_rad_s": np.array([g["true_bias_rad_s"] for g in truth["gyro"]], dtype=float)}


def truth_table(result: dict, truth: dict) -> str:
    """Recovered parameters beside the virtual device's truth, with 1-sigma and |error|/sigma."""
    t = truth_in_fit_frame(result, truth)
    lines = [f"{'parameter':<14}{'truth':>14}{'recovered':>14}{'1-sigma':>12}{'|err|/σ':>9}"]
    acc = result["accel"]
    for i in range(3):
        for j in range(3):
            if acc["sigma_m"][i][j] > 0:          # entries the model fixes are not listed
                lines.append(_row(f"accel M{i}{j}", t["accel_m"][i, j], acc["m"][i][j], acc["sigma_m"][i][j]))
    for i, ax in enumerate("xyz"):
        lines.append(_row(f"accel b{ax} mg", t["accel_b_mps2"][i] / U.G0_MPS2 * 1e3, acc["b_mps2"][i] / U.G0_MPS2 * 1e3,
                          acc["sigma_b_mps2"][i] / U.G0_MPS2 * 1e3))
    g = result.get("gyro")
    if g:
        for i, ax in enumerate("xyz"):
            lines.append(_row(f"gyro b{ax} °/s", np.degrees(t["gyro_b_rad_s"][i]), np.degrees(g["b_rad_s"][i]),
                              np.degrees(g["sigma_b_rad_s"][i])))
        if g["method"] != "bias":
            for i in range(3):
                for j in range(3):
                    lines.append(_row(f"gyro M{i}{j}", t["gyro_m"][i, j], g["m"][i][j], g["sigma_m"][i][j]))
    if result["method"] == "multi" and not str(result.get("accel_frame", "")).startswith("board"):
        lines.append("(multi-position: M in the frame of the sensor's X axis and X-Y plane; "
                     "see docs/calibration.md)")
    elif result["method"] == "multi":
        lines.append("(multi-position: M rotated into the gyro turntable's board frame by the rotations "
                     "between poses; see docs/calibration.md, \"One frame\")")
    lines.append("(biases: the models' bias random walk moves them during the session; the truth shown is "
                 "the value at the end, the estimate the mean over the session's rest or poses)")
    return "\n".join(lines)


def _matrix_lines(m, sigma_m) -> list[str]:
    """M row by row, each entry ± 1σ to its precision; an entry the model holds fixed is
    shown as its value with "(fixed)"."""
    cells = [[pm(m[i][j], sigma_m[i][j], fixed_text=f"{m[i][j]:+.0f} (fixed)") for j in range(3)] for i in range(3)]
    w = max(len(c) for row in cells for c in row)
    return ["  ".join(c.rjust(w) for c in row) for row in cells]


def params_table(result: dict) -> str:
    """The fitted parameters with their 1-sigma uncertainties, each to the precision its
    uncertainty allows (results.numbers), in the model of docs/conventions.md:
    u = M·x + b, the device applies x = M⁻¹·(u − b)."""
    a = result["accel"]
    rows = _matrix_lines(a["m"], a["sigma_m"])
    L = [f"accelerometer ({a['method']}): u = M·x + b, the device applies x = M⁻¹·(u − b)",
         "  M = " + "\n      ".join(rows),
         "  b = " + "   ".join(f"{ax} {pm(v, s, 'mg', scale=1e3 / U.G0_MPS2)}"
                              for ax, v, s in zip("xyz", a["b_mps2"], a["sigma_b_mps2"]))]
    held = (a.get("extra") or {}).get("held") or []
    if held:
        L.append(f"  held at nominal (not resolved by the rests): {', '.join(held)}; the size they may have "
                 "is carried into the σ above")
    g = result.get("gyro")
    if g:
        L.append(f"gyro ({g['method']}):")
        if g["method"] != "bias":
            L.append("  M = " + "\n      ".join(_matrix_lines(g["m"], g["sigma_m"])))
        else:
            L.append("  M = identity (not estimated: --gyro bias measures the bias only)")
        L.append("  b = " + "   ".join(f"{ax} {pm(v, s, '°/s', scale=180.0 / np.pi)}"
                                      for ax, v, s in zip("xyz", g["b_rad_s"], g["sigma_b_rad_s"])))
    return "\n".join(L)


def _row(name, truth, got, sigma):
    z = abs(got - truth) / sigma if sigma > 0 else float("nan")
    return f"{name:<14}{truth:>14.6f}{got:>14.6f}{sigma:>12.6f}{z:>9.2f}"
