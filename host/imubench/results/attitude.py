"""What the attitude step test shows: the table of settling times and static errors, and the plot."""
from __future__ import annotations

import math

import numpy as np

from imubench.results.atomic import save_figure


def summarize(results: dict) -> str:
    """Text table of settling times and static errors per step and filter, and RMS errors."""
    names = ["accel"] + results["filters"]
    lines = [f"{'axis':5} {'target':>7} | " + " ".join(f"{n:>17}" for n in names),
             f"{'':5} {'deg':>7} | " + " ".join(f"{'settle s / err °':>17}" for _ in names)]
    for s in results["steps"]:
        lines.append(f"{s.axis:5} {s.target_deg:7.2f} | " + " ".join(
            f"{s.settle_s[n]:7.3f} {s.error_deg[n]:+9.5f}" for n in names))
    rms = {n: math.sqrt(np.mean([s.error_deg[n] ** 2 for s in results["steps"]])) for n in names}
    lines.append(f"{'RMS static error (deg)':15} | " + " ".join(f"{rms[n]:17.5f}" for n in names))
    return "\n".join(lines)


def plot_steps(results: dict, path) -> None:
    """PNG: one panel per axis, angle (deg) vs device time (s) for each filter, with the
    step targets (simulator truth) as a dashed staircase."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = results["t"]
    t0 = t[0]
    axes_used = [a for a in ("roll", "pitch") if any(s.axis == a for s in results["steps"])]
    fig, axs = plt.subplots(len(axes_used), 2, figsize=(15, 4 * len(axes_used)), squeeze=False,
                            gridspec_kw={"width_ratios": [3, 2]})
    band = results.get("band_deg", 0.05)
    for row, axis in zip(axs, axes_used):
        ax, ex = row
        k = 0 if axis == "roll" else 1
        steps = [s for s in results["steps"] if s.axis == axis]
        lo, hi = steps[0].t_step - 1.0, steps[-1].t_end + 0.5
        sel = (t >= lo) & (t <= hi)
        target = np.full(len(t), np.nan)
        for s in steps:
            target[(t >= s.t_step) & (t <= s.t_end)] = s.target_deg
        ax.plot(t[sel] - t0, results["angles"]["accel"][k][sel], color="0.8", lw=0.5, label="accelerometer")
        ex.plot(t[sel] - t0, (results["angles"]["accel"][k] - target)[sel], color="0.85", lw=0.5,
                label="accelerometer")
        for name in results["filters"]:
            ax.plot(t[sel] - t0, results["angles"][name][k][sel], lw=1.0, label=name)
            ex.plot(t[sel] - t0, (results["angles"][name][k] - target)[sel], lw=0.8, label=name)
        for s in steps:
            ax.hlines(s.target_deg, s.t_step - t0, s.t_end - t0, colors="k", linestyles="--", lw=0.8)
        ex.axhspan(-band, band, color="g", alpha=0.08, label=f"settling band ±{band:g}°")
        ex.set_ylim(-4 * band, 4 * band)
        ax.set_xlabel("device time (s)")
        ax.set_ylabel(f"{axis} (deg)")
        ax.set_title(f"{axis} steps on the virtual turntable (dashed: truth)")
        ex.set_xlabel("device time (s)")
        ex.set_ylabel(f"{axis} − target (deg)")
        ex.set_title(f"{axis} error after each step starts (zoom)")
        for a_ in (ax, ex):
            a_.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        ex.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def steps_json(results: dict) -> dict:
    """The numbers of a step test, JSON-able: every step's target, settling time and static
    error per filter, and the RMS static error per filter (degrees, seconds)."""
    names = ["accel"] + results["filters"]
    steps = [{"axis": s.axis, "target_deg": s.target_deg, "settle_s": dict(s.settle_s),
              "error_deg": dict(s.error_deg)} for s in results["steps"]]
    rms = {n: math.sqrt(np.mean([s.error_deg[n] ** 2 for s in results["steps"]])) for n in names}
    return {"mode": "steps", "rate_hz": results.get("rate_hz"), "band_deg": results.get("band_deg"),
            "filters": names, "steps": steps, "rms_static_error_deg": rms}


def live_json(t_s: np.ndarray, angles: dict) -> dict:
    """The numbers of a live run: per filter the mean and standard deviation of roll and
    pitch over the run (degrees): a still board's attitude and its noise."""
    out = {"mode": "live", "duration_s": float(t_s[-1] - t_s[0]) if len(t_s) > 1 else 0.0, "samples": len(t_s),
           "filters": list(angles), "roll_deg": {}, "pitch_deg": {}}
    for name, (roll, pitch) in angles.items():
        out["roll_deg"][name] = {"mean": float(np.mean(roll)), "std": float(np.std(roll, ddof=1))}
        out["pitch_deg"][name] = {"mean": float(np.mean(pitch)), "std": float(np.std(pitch, ddof=1))}
    return out


def plot_live(t_s: np.ndarray, angles: dict, path, title: str = "") -> None:
    """PNG: roll and pitch (deg) over time for the accelerometer angle and each filter."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7), dpi=100)
    FigureCanvasAgg(fig)
    axs = fig.subplots(2, 1, sharex=True)
    for k, (ax, what) in enumerate(zip(axs, ("roll", "pitch"))):
        for name, ang in angles.items():
            ax.plot(t_s, ang[k], lw=0.6 if name == "accel" else 1.0,
                    color="0.75" if name == "accel" else None,
                    label=f"{name}: mean {np.mean(ang[k]):+.3f}°, std {np.std(ang[k], ddof=1):.3f}°")
        ax.set_ylabel(f"{what} (deg)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axs[0].set_title(title or "roll and pitch from the device's calibrated output", fontsize=10)
    axs[1].set_xlabel("time since the first sample (s)")
    fig.tight_layout()
    save_figure(fig, path)
