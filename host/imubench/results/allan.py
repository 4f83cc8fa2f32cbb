"""What an Allan analysis shows: the log-log plot with its read-off lines and the printed table."""
from __future__ import annotations

import numpy as np

from imubench.analysis.allan import AXES, duration_text, usual_units
from imubench.results.atomic import save_figure


def _fmt(v, f="{:.4g}"):
    return "withheld" if v is None else f.format(v)


def plot_allan(result: dict, path, title: str, unit: str, kind: str | None = None) -> None:
    """Log-log ADEV per axis with 68 % error bars, the −1/2 and +1/2 lines through the
    read-offs, and the bias-instability markers. `unit` is the SI unit of the rates; kind
    "accel"/"gyro" (or unit m/s² / rad/s) adds the read-offs in the usual units to the legend."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    kind = kind or {"m/s²": "accel", "rad/s": "gyro"}.get(unit)
    fig = Figure(figsize=(9, 8), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    colors = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
    tmin = min(min(result[a]["taus"]) for a in AXES if a in result)
    tmax = max(max(result[a]["taus"]) for a in AXES if a in result)
    tt = np.logspace(np.log10(tmin), np.log10(tmax), 50)
    for a in AXES:
        if a not in result:
            continue
        r, col = result[a], colors[a]
        t, d = np.array(r["taus"]), np.array(r["adev"])
        err = np.vstack([d - np.array(r["ci_lo"]), np.array(r["ci_hi"]) - d])
        ks = f"{r['K']:.3g} {unit}·√Hz" if r["K"] is not None else "withheld"
        bs = f"{r['B']:.3g} {unit} (τ={r['B_tau']:.3g} s)" if r.get("B") is not None else "withheld"
        lab = f"{a}: N={r['N']:.3g} {unit}/√Hz, B={bs}, K={ks}"
        if kind in ("accel", "gyro"):
            u = usual_units(r, kind)
            if kind == "accel":
                lab += (f"\n     = VRW {u['N_ug_per_rtHz']:.3g} µg/√Hz, B {_fmt(u['B_ug'], '{:.3g} µg')}, "
                        f"K {_fmt(u['K_ug_rtHz'], '{:.3g} µg·√Hz')}")
            else:
                lab += (f"\n     = ARW {u['N_deg_per_rth']:.3g} °/√h, B {_fmt(u['B_deg_h'], '{:.3g} °/h')}, "
                        f"RRW {_fmt(u['K_deg_h_per_rth'], '{:.3g} °/h/√h')}")
        ax.errorbar(t, d, yerr=err, fmt="o-", ms=3.5, lw=1.2, capsize=2.5, color=col, label=lab)
        ax.plot(tt, r["N"] / np.sqrt(tt), "--", color=col, lw=0.9, alpha=0.8)
        ax.plot([1.0], [r["N"]], "s", color=col, mfc="none", ms=8)
        if r["K"] is not None:
            ax.plot(tt, r["K"] * np.sqrt(tt / 3.0), ":", color=col, lw=1.3, alpha=0.9)
            ax.plot([3.0], [r["K"]], "^", color=col, mfc="none", ms=8)
        if r.get("B") is not None:
            ax.plot([r["B_tau"]], [r["B"] * 0.664], "*", color=col, ms=13, mec="k", mew=0.6)
            ax.axhline(r["B"] * 0.664, color=col, lw=0.6, alpha=0.4)
    # legend entries explaining the markers
    ax.plot([], [], "k--", lw=0.9, label="−1/2 line N/√τ (□ at τ = 1 s: N)")
    ax.plot([], [], "k:", lw=1.3, label="+1/2 line K·√(τ/3) (△ at τ = 3 s: K)")
    ax.plot([], [], "k*", ms=10, ls="none", label="minimum = 0.664·B (bias instability)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    lows = [min(result[a]["ci_lo"]) for a in AXES if a in result]
    lows += [result[a]["K"] for a in AXES if a in result and result[a]["K"] is not None]
    ax.set_ylim(min(lows) / 2,
                max(max(result[a]["ci_hi"]) for a in AXES if a in result) * 2)
    ax.set_xlabel("averaging time τ [s]")
    ax.set_ylabel(f"Allan deviation σ(τ) [{unit}]")
    dur = result.get("duration_s", 0)
    withheld = sorted({w for a in AXES if a in result for w in ("B", "K") if result[a].get(w) is None})
    if withheld:
        ax.text(0.02, 0.02, "withheld (the record cannot support them): " + ", ".join(withheld)
                + "; reasons in allan.json", transform=ax.transAxes, fontsize=8, color="darkred")
    ax.set_title(f"{title}: overlapping Allan deviation, {duration_text(dur)} at {result.get('fs_hz', 0):g} Hz "
                 "(error bars: 68 % CI)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=1, frameon=False)
    fig.tight_layout()
    save_figure(fig, path)


def format_readoffs(res: dict) -> list[str]:
    """The read-offs of an analyse_capture result as a text table, in the usual units, and
    for every read-off the record cannot support, why it is withheld."""
    lines = [f"analysed {res['samples']} samples = {duration_text(res['duration_s'])} at {res['rate_hz']:g} Hz"]
    lines.append(f"{'':6} {'VRW N [µg/√Hz]':>15} {'[m/s/√h]':>10} {'bias inst. B [µg]':>18} {'at τ [s]':>9} "
                 f"{'RRW K [µg·√Hz]':>15}")
    for a in AXES:
        r, u = res["accel"][a], res["accel_usual"][a]
        lines.append(f"acc {a}: {_fmt(u['N_ug_per_rtHz']):>15} {_fmt(u['VRW_m_s_per_rth']):>10} "
                     f"{_fmt(u['B_ug']):>18} {_tau(r):>9} {_fmt(u['K_ug_rtHz']):>15}")
    lines.append(f"{'':6} {'ARW N [°/√h]':>15} {'[°/s/√Hz]':>10} {'bias inst. B [°/h]':>18} {'at τ [s]':>9} "
                 f"{'RRW K [°/h/√h]':>15}")
    for a in AXES:
        r, u = res["gyro"][a], res["gyro_usual"][a]
        lines.append(f"gyr {a}: {_fmt(u['N_deg_per_rth']):>15} {_fmt(u['N_deg_s_per_rtHz']):>10} "
                     f"{_fmt(u['B_deg_h']):>18} {_tau(r):>9} {_fmt(u['K_deg_h_per_rth']):>15}")
    reasons = []
    for kind in ("accel", "gyro"):
        for key, what in (("B_reason", "B"), ("K_reason", "K")):
            texts = {res[kind][a].get(key) for a in AXES} - {None}
            reasons += [f"{kind} {what} withheld: {r}" for r in sorted(texts)]
        wr = {res[kind][a]["white"].get("reason") for a in AXES} - {None}
        reasons += [f"{kind} N: {r}" for r in sorted(wr)]
    lines += reasons
    lines.append("(SI: N in m/s²/√Hz or rad/s/√Hz, B in m/s² or rad/s, K in m/s²·√Hz or rad/s·√Hz: see allan.json)")
    return lines


def _tau(r: dict) -> str:
    return f"{r['B_tau']:.4g}" if r.get("B") is not None else "–"
