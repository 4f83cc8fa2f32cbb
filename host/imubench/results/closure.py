"""What a closure check shows: closure.json's summary, the printed table and the plot."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.results.atomic import save_figure

G0 = U.G0_MPS2


def result_json(res: dict, extra: dict | None = None) -> dict:
    """The JSON-able summary (closure.json) of a closure_from_block result."""
    out = {"schema": 1, "before": res["before"].as_dict(), "after": res["after"].as_dict(),
           "after_rest_bias": res["after_rest_bias"].as_dict(),
           "gyro_bias_at_rest_rad_s": res["gyro_bias_at_rest_rad_s"],
           "window": res["window"], "noise_floor": res["noise_floor"], "improvement": res["improvement"],
           "g_mps2": res.get("g_mps2", G0)}
    out.update(extra or {})
    return out


VERDICT_FLOORS = 3.0      # closes within this many white-noise floors (1 sigma): consistent with noise


def verdict_of(distance_m: float, floor_m: float) -> tuple[bool, str]:
    """(passed, words): whether a calibrated integration (gyro bias zeroed at rest) that ends
    distance_m from the start closes within VERDICT_FLOORS white-noise floors (floor_m, 1 sigma),
    and what that means. The console and the HTML report both say it this way."""
    k = distance_m / floor_m if floor_m > 0 else math.inf
    words = f"calibrated, the path closes to {distance_m:.2g} m = {k:.1f}x the white-noise floor ({floor_m:.2g} m)"
    if k <= VERDICT_FLOORS:
        return True, f"PASS: {words}: no calibration error shows at this path length"
    return False, f"ABOVE THE NOISE: {words}: a calibration error or a moving gyro bias remains (docs/closure.md)"


def verdict(res: dict) -> tuple[bool, str]:
    """verdict_of a closure_from_block result."""
    return verdict_of(res["after_rest_bias"].distance_m, res["noise_floor"]["sigma_distance_m"])


def summarize(res: dict) -> str:
    """A text table: closure before and after calibration, the noise floor, and the verdict."""
    b, a, nf = res["before"], res["after"], res["noise_floor"]
    w = res["window"]
    rows = [(r.label, r) for r in (b, a, res["after_rest_bias"])]
    lw = max(len(r.label) for _, r in rows) + 2
    lines = [f"closure check: {w['duration_s']:.2f} s of motion, {w['samples']} samples at {w['fs_hz']:.0f} Hz; "
             f"path length (calibrated) {a.path_length_m:.2f} m",
             f"{'':{lw}}{'distance m':>11} {'horiz m':>9} {'vert m':>9} {'end speed m/s':>14}   "
             f"{'closure x, y, z (m)':>28}"]
    for label, r in rows:
        cx, cy, cz = r.closure_m
        lines.append(f"{label:{lw}}{r.distance_m:11.4f} {r.horizontal_m:9.4f} {r.vertical_m:9.4f} "
                     f"{r.end_speed_mps:14.4f}   {cx:+9.4f} {cy:+9.4f} {cz:+9.4f}")
    lines.append(f"{'white-noise floor (1 sigma)':{lw}}{nf['sigma_distance_m']:11.4f} "
                 f"{math.hypot(nf['sigma_x_m'], nf['sigma_y_m']):9.4f} {nf['sigma_z_m']:9.4f}")
    gb = np.degrees(res["gyro_bias_at_rest_rad_s"])
    lines.append(f"calibrated gyros at the start rest read {gb[0]:+.4f} {gb[1]:+.4f} {gb[2]:+.4f} °/s "
                 "(the bias change since the calibration)")
    lines.append(f"calibration shrinks the closure error {res['improvement']:.0f}x "
                 f"({100 * a.distance_m / max(a.path_length_m, 1e-9):.2f} % of the path length after)")
    lines.append(verdict(res)[1])
    return "\n".join(lines)


def plot_closure(res: dict, path, truth_path_m: np.ndarray | None = None) -> Path:
    """PNG: top views (navigation X/Y) after calibration (with the driven path, when known, in
    the same frame) and before, and the distance from the start over time on a linear scale
    with the white-noise floor, under the verdict."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b, a = res["before"], res["after"]
    fig, axs = plt.subplots(1, 3, figsize=(16, 5))
    for ax, r, col in ((axs[0], a, "C0"), (axs[1], b, "C3")):
        ax.plot(r.pos_m[:, 0], r.pos_m[:, 1], color=col, lw=1.2, label=r.label)
        ax.plot(r.pos_m[0, 0], r.pos_m[0, 1], "ko", label="start")
        ax.plot(r.pos_m[-1, 0], r.pos_m[-1, 1], "x", color=col, ms=10, mew=2,
                label=f"end: {r.distance_m:.3g} m from the start")
        if r is a:
            z = res["after_rest_bias"]
            ax.plot(z.pos_m[:, 0], z.pos_m[:, 1], color="C2", lw=1.0, label=z.label)
            ax.plot(z.pos_m[-1, 0], z.pos_m[-1, 1], "x", color="C2", ms=10, mew=2,
                    label=f"end: {z.distance_m:.3g} m from the start")
            if truth_path_m is not None:
                ax.plot(truth_path_m[:, 0], truth_path_m[:, 1], "k--", lw=0.8,
                        label="path driven (the virtual bench's truth)")
        ax.set_xlabel("x, initial heading (m)")
        ax.set_ylabel("y, left (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        ax.set_title(("after" if r is a else "before") + " calibration: top view")
    ax = axs[2]
    floor = res["noise_floor"]["sigma_distance_m"]
    top = 0.0
    for r, col in ((a, "C0"), (res["after_rest_bias"], "C2")):
        d = np.linalg.norm(r.pos_m - r.pos_m[0], axis=1)
        top = max(top, float(d.max()))
        ax.plot(r.t_s, d, color=col, label=f"{r.label}: {r.distance_m:.2g} m at the end")
    db = np.linalg.norm(b.pos_m - b.pos_m[0], axis=1)
    ax.plot(b.t_s, db, color="C3", lw=0.8, label=f"{b.label}: {b.distance_m:.2g} m at the end (off this scale)")
    t_end = float(a.t_s[-1])
    for k, ls in ((1, "--"), (VERDICT_FLOORS, ":")):      # the floor is that of the end point
        ax.hlines(k * floor, 0.75 * t_end, 1.02 * t_end, colors="k", linestyles=ls, lw=1.0,
                  label=f"white-noise floor at the end: {k:g} sigma = {k * floor:.2g} m")
    ax.set_xlim(0, t_end * 1.02)
    ax.set_ylim(0, 1.7 * max(top, VERDICT_FLOORS * floor))
    ax.set_xlabel("time since the motion window start (s)")
    ax.set_ylabel("distance from the start (m)")
    ax.set_title("distance from the start: its end value is the closure error", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(verdict(res)[1], fontsize=10, color="darkgreen" if verdict(res)[0] else "darkred")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)
