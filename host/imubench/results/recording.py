"""What a calibration from a file shows about its recording: the segmentation plot (still
intervals coloured by their use in the fit, turns, clipped motions, breaks, an annotation if
given), text tables of the segmentation, the rests, the turns and the comparison with an
annotation, and the evidence every run leaves in its folder, accepted or refused: rests.csv
and README.md (write_evidence). Drawn on a matplotlib Figure with the Agg canvas (no pyplot),
like results.calibration."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.results.atomic import atomic_output, save_figure, write_text_atomic
from imubench.results.numbers import decimals_for

# a rest's use in the fit (procedures.from_file: "used", "down-weighted" (its σ inflated), "left out")
USE_COLOURS = {"used": "#2ca02c", "down-weighted": "#ff9f1c", "left out": "#d62728"}
RESTS_CSV, README = "rests.csv", "README.md"
REST_COLUMNS = ("index", "t_start_s", "duration_s", "face", "mean_x_g", "mean_y_g", "mean_z_g", "sigma_x_mg",
                "sigma_y_mg", "sigma_z_mg", "use", "sigma_inflation", "use_reason")
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
    step = max(1, len(rec) // 20000)      # decimated before anything is computed: ~20,000 points a curve
    t = np.arange(0, len(rec), step) / fs
    acc_g = np.linalg.norm(rec.accel[::step] * accel_factor, axis=1) / U.G0_MPS2
    gyr = np.degrees(rec.gyro[::step] * gyro_factor)
    fig = Figure(figsize=(13, 6.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, acc_g, lw=0.6, color="k")
    for k, c in zip(range(3), ("#1f77b4", "#2ca02c", "#d62728")):
        ax2.plot(t, gyr[:, k], lw=0.6, color=c, label="xyz"[k])
    rests = result.get("rests")
    if rests is not None:                 # coloured by use, labelled by index and face
        for r in rests:
            for ax in (ax1, ax2):
                ax.axvspan(r["start"] / fs, r["stop"] / fs, color=USE_COLOURS.get(r["use"], "#bbb"),
                           alpha=0.35, lw=0, hatch=None if r["use"] == "used" else "//")
            ax1.text((r["start"] + r["stop"]) / 2 / fs, 0.97, f"{r['index']}\n{r['face']}", ha="center", va="top",
                     fontsize=7, transform=ax1.get_xaxis_transform())
        from matplotlib.patches import Patch
        ax1.legend(handles=[Patch(color=c, alpha=0.35, label=f"rest {u}") for u, c in USE_COLOURS.items()],
                   loc="lower right", fontsize=8)
    for seg in result.get("segmentation", []) if rests is None else ():
        for ax in (ax1, ax2):
            ax.axvspan(seg["start"] / fs, seg["stop"] / fs, color=_FACE_COLOURS.get(seg["face"], "#bbb"),
                       alpha=0.35, lw=0)
        ax1.text((seg["start"] + seg["stop"]) / 2 / fs, 0.97, seg["face"], ha="center", va="top", fontsize=8,
                 transform=ax1.get_xaxis_transform())
    for m in (result.get("clipping") or {}).get("gyro", []):
        ax2.axvspan(m["t_start_s"], m["t_stop_s"], color="#d62728", alpha=0.25, lw=0, hatch="xx")
        ax2.text((m["t_start_s"] + m["t_stop_s"]) / 2, 0.03, f"motion {m['motion']}\nclipped", ha="center",
                 va="bottom", fontsize=7, color="#a00", transform=ax2.get_xaxis_transform())
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
    lo, hi = ax1.get_ylim()
    ax1.set_ylim(lo, hi + 0.15 * (hi - lo))           # room for the rests' labels above the data
    ax1.set_ylabel("|a| [g] (nominal)")
    ax2.set_ylabel("rate [°/s] (nominal)")
    ax2.set_xlabel("time [s]")
    ax2.legend(loc="lower right", fontsize=8)
    what = "rests (shaded by use: used, down-weighted, left out)" if rests is not None else \
        "still intervals (shaded by face)"
    ax1.set_title(f"{Path(rec.source.split(' + ')[0]).name}: {what}, turns (yellow)"
                  + (", gyro clipped (red, crossed)" if (result.get("clipping") or {}).get("gyro") else "")
                  + (", breaks (red dashed)" if rec.breaks else "")
                  + (", annotated sections (dark bars)" if parts else "")
                  + ("\n" + textwrap.shorten("REFUSED: " + result["refused"], 170) if result.get("refused") else ""),
                  fontsize=10)
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


SIGMA_FLOOR_MG = 1e-3       # 1 µg: no accelerometer's mean is known better (a clipped axis has σ = 0)


def _rest_cells(r: dict) -> list[str]:
    """A rest's row as text, each mean to the precision its own σ allows (two digits of σ)."""
    sig = [max(float(x), SIGMA_FLOOR_MG) for x in r["sigma_mg"]]
    means = [f"{m:+.{max(0, decimals_for(s / 1e3))}f}" for m, s in zip(r["mean_g"], sig)]
    sigmas = [f"{x:.{max(0, decimals_for(s))}f}" for x, s in zip(r["sigma_mg"], sig)]
    return [str(r["index"]), f"{r['t_start_s']:.2f}", f"{r['duration_s']:.2f}", r["face"], *means, *sigmas,
            r["use"], f"{r['sigma_inflation']:.3g}", r["use_reason"]]


def rests_table(result: dict) -> str:
    """Every rest found, with its use in the fit and the reason: text for the console and README."""
    rests = result.get("rests") or []
    if not rests:
        return "rests: none found by the data"
    head = ["#", "start [s]", "length [s]", "face", "mean x [g]", "mean y [g]", "mean z [g]", "σ x [mg]", "σ y [mg]",
            "σ z [mg]", "use", "σ ×", "reason"]
    rows = [head] + [_rest_cells(r) for r in rests]
    w = [max(len(row[k]) for row in rows) for k in range(len(head) - 1)]
    lines = ["rests found by the data (σ: the 1σ of each mean; σ ×: its inflation in the fit):"]
    lines += ["  " + " ".join(c.rjust(w[k]) for k, c in enumerate(row[:-1])) + "  " + row[-1] for row in rows]
    return "\n".join(lines)


def write_rests_csv(result: dict, path) -> Path:
    """rests.csv: one row per rest (REST_COLUMNS), the numbers to the precision their σ allows."""
    import csv
    path = Path(path)
    with atomic_output(path) as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(REST_COLUMNS)
        for r in result.get("rests") or []:
            w.writerow(_rest_cells(r))
    return path


def write_evidence(directory, result: dict, *, command: str = "") -> list[Path]:
    """What every calibration from a file leaves in its folder, accepted or refused: rests.csv
    and README.md (the verdict or the reason of the refusal, the rests table, the gyro's clipped
    motions, the notes, the files). The segmentation plot is plot_segmentation's."""
    d = Path(directory)
    src = result.get("source") or {}
    refused = result.get("refused")
    lines = [f"# imubench calibrate --from {src.get('file', '?')}", ""]
    if command:
        lines += ["```", command, "```", ""]
    if src.get("detected"):          # what the reader settled, and the command that states it (issue 40, 6)
        lines += ["The reader detected (each settled without an option):", ""]
        lines += [f"- {d}" for d in src["detected"]] + ["", "The same reading with every option stated:", "",
                                                         "```", src.get("command", ""), "```", ""]
    lines += [f"**{'REFUSED' if refused else 'Verdict'}:** {refused or result.get('verdict', '')}", "",
              f"Recording: {src.get('format', '?')}, {src.get('samples', '?')} samples at "
              f"{float(src.get('rate_hz', math.nan)):.5g} Hz; {src.get('units', '')}.", "",
              "Files here: segmentation.png (the data, the rests coloured by use: used green, down-weighted orange, "
              "left out red and hatched; clipped gyro motions crossed), rests.csv (the table below)"
              + ("" if refused else ", session.json, residuals.png, report.html") + ".", "",
              "## Rests", "", "```", rests_table(result), "```", ""]
    clip = result.get("clipping") or {}
    if clip.get("gyro") or clip.get("accel"):
        lines += ["## Clipping", ""]
        for m in clip.get("gyro", []):
            lines.append(f"- motion {m['motion']} ({m['t_start_s']:.2f}–{m['t_stop_s']:.2f} s), left out of the gyro "
                         "fit: " + "; ".join(f"{a['axis']} at {a['level']} for {a['samples']} samples ({a['source']})"
                                             for a in m["axes"]))
        for a in clip.get("accel", []):
            lines.append(f"- rest at {a['rest_t_start_s']:.2f} s, left out: accelerometer {a['axis']} at "
                         f"{a['level_g']:+.4g} g for {a['samples']} samples")
        lines.append("")
    notes = list(src.get("timing") or []) + list(src.get("reader_notes") or []) + list(result.get("notes") or [])
    if notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    return [write_rests_csv(result, d / RESTS_CSV), write_text_atomic(d / README, "\n".join(lines))]


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
    for table in (segmentation_table(result), rests_table(result) if result.get("rests") else "",
                  turns_table(result), annotation_table(result)):
        if table:
            out.append(f"<pre>{esc(table)}</pre>")
    return "\n".join(out)
