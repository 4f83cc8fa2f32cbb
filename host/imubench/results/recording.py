"""What a calibration from a file shows about its recording: the segmentation plot (still
intervals, turns, breaks, an annotation if given) and text tables of the segmentation, the
turns and the comparison with an annotation. Drawn on a matplotlib Figure with the Agg canvas
(no pyplot), like results.calibration."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.results.atomic import save_figure

_FACE_COLOURS = {"+X": "#1f77b4", "-X": "#aec7e8", "+Y": "#2ca02c", "-Y": "#98df8a", "+Z": "#d62728",
                 "-Z": "#ff9896", "other": "#bbbbbb"}


def plot_segmentation(rec, result: dict, path, *, accel_factor: float, gyro_factor: float) -> Path:
    """PNG: |a| (g) and the gyro rates (°/s) over time, the detected still intervals shaded by
    face, the turns marked with their integrated angle, breaks as red lines, and the annotated
    sections (if any) as a strip under the data."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fs = rec.fs_hz
    t = np.arange(len(rec)) / fs
    acc_g = np.linalg.norm(rec.accel * accel_factor, axis=1) / U.G0_MPS2
    gyr = np.degrees(rec.gyro * gyro_factor)
    step = max(1, len(t) // 20000)
    fig = Figure(figsize=(13, 6.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t[::step], acc_g[::step], lw=0.6, color="k")
    for k, c in zip(range(3), ("#1f77b4", "#2ca02c", "#d62728")):
        ax2.plot(t[::step], gyr[::step, k], lw=0.6, color=c, label="xyz"[k])
    for seg in result.get("segmentation", []):
        for ax in (ax1, ax2):
            ax.axvspan(seg["start"] / fs, seg["stop"] / fs, color=_FACE_COLOURS.get(seg["face"], "#bbb"),
                       alpha=0.35, lw=0)
        ax1.text((seg["start"] + seg["stop"]) / 2 / fs, 0.97, seg["face"], ha="center", va="top", fontsize=8,
                 transform=ax1.get_xaxis_transform())
    for tr in result.get("turns", []):
        ax2.axvspan(tr["start"] / fs, tr["stop"] / fs, color="#ffdd55" if tr["usable"] else "#cccccc", alpha=0.4, lw=0)
        ax2.text((tr["start"] + tr["stop"]) / 2 / fs, 0.97, f"{tr['label']}\n{tr['before_deg']:.1f}°"
                 + (f" → {tr['after_deg']:.1f}°" if "after_deg" in tr else "")
                 + ("" if tr["usable"] else "\n(not used)"), ha="center", va="top", fontsize=7,
                 transform=ax2.get_xaxis_transform())
    for b, _ in rec.breaks:
        for ax in (ax1, ax2):
            ax.axvline(b / fs, color="r", lw=1.0, ls="--")
    parts = result.get("annotation") or []
    for p in parts:
        ax1.plot([p["start"] / fs, p["stop"] / fs], [0.02, 0.02], transform=ax1.get_xaxis_transform(),
                 color="#444", lw=4, solid_capstyle="butt")
        ax1.text(p["start"] / fs, 0.05, p["section"], transform=ax1.get_xaxis_transform(), fontsize=7, color="#444")
    ax1.set_ylabel("|a| [g] (nominal)")
    ax2.set_ylabel("rate [°/s] (nominal)")
    ax2.set_xlabel("time [s]")
    ax2.legend(loc="lower right", fontsize=8)
    ax1.set_title(f"{Path(rec.source.split(' + ')[0]).name}: still intervals (shaded by face), turns (yellow)"
                  + (", breaks (red dashed)" if rec.breaks else "")
                  + (", annotated sections (dark bars)" if parts else ""), fontsize=10)
    save_figure(fig, path)
    return path


def segmentation_table(result: dict) -> str:
    rows = ["still intervals found by the data:",
            f"  {'face':>5} {'start [s]':>9} {'end [s]':>8} {'length [s]':>10}  |a| before / after [g]"]
    poses = result.get("poses", [])
    for seg, p in zip(result.get("segmentation", []), poses):
        rows.append(f"  {seg['face']:>5} {seg['t_start_s']:9.2f} {seg['t_start_s'] + seg['duration_s']:8.2f} "
                    f"{seg['duration_s']:10.2f}  {p['before_g']:.5f} / {p['after_g']:.5f}")
    return "\n".join(rows)


def turns_table(result: dict) -> str:
    turns = result.get("turns") or []
    if not turns:
        return "turns: none found (a turn is a motion about the vertical between two rests of the same attitude)"
    rows = ["turns found by the data (integrated, bias-corrected rate along the vertical):",
            f"  {'turn':<14} {'start [s]':>9} {'length [s]':>10} {'known':>7} {'before':>9} {'after':>9} "
            f"{'σ':>6}  off-axis   (degrees; σ: the turn's error budget along the vertical)"]
    for tr in turns:
        after = f"{tr['after_deg']:9.2f}" if "after_deg" in tr else f"{'-':>9}"
        sig = f"{tr['sigma_deg']:6.2f}" if "sigma_deg" in tr else f"{'-':>6}"
        rows.append(f"  {tr['label']:<14} {tr['t_start_s']:9.2f} {tr['duration_s']:10.2f} {tr['known_deg']:7.0f} "
                    f"{tr['before_deg']:9.2f} {after} {sig}  {tr['off_axis_deg']:.2f}°"
                    + ("" if tr["usable"] else f"  NOT USED: {tr['reason']}"))
    return "\n".join(rows)


def annotation_table(result: dict) -> str:
    ann = result.get("annotation")
    if not ann:
        return ""
    rows = ["compared with the annotation (differences detected − annotated, s; + = later):",
            f"  {'section':<8} {'found':<6} {'start Δ':>8} {'end Δ':>8}  annotated section inside the detected one"]
    for a in ann:
        if not a["found"]:
            rows.append(f"  {a['section']:<8} NO     (nothing detected overlaps samples {a['start']}–{a['stop']})")
            continue
        rows.append(f"  {a['section']:<8} {a['kind']:<6} {a['start_diff_s']:+8.2f} {a['stop_diff_s']:+8.2f}  "
                    f"{'yes' if a['annotated_inside_detected'] else 'no'}")
    return "\n".join(rows)


def recording_html(result: dict, esc, img) -> str:
    """The report's section about the recording a calibration came from (report.py calls it)."""
    src = result.get("source") or {}
    rate = float(src.get("rate_hz", math.nan))
    dur = float(src.get("duration_s", math.nan))
    out = ['<h3>Recording</h3>',
           f"<p>file <code>{esc(src.get('file'))}</code>, format {esc(src.get('format'))}, {esc(src.get('units'))}; "
           f"{esc(src.get('samples'))} samples at {rate:.5g} Hz ({dur:.1f} s)</p>"]
    lines = list(src.get("timing") or []) + list(src.get("reader_notes") or []) + list(result.get("notes") or [])
    if lines:
        out.append("<ul>" + "".join(f"<li>{esc(x)}</li>" for x in lines) + "</ul>")
    out.append(img)
    for table in (segmentation_table(result), turns_table(result), annotation_table(result)):
        if table:
            out.append(f"<pre>{esc(table)}</pre>")
    return "\n".join(out)
