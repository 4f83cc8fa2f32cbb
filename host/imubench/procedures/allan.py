"""Noise characterisation of a resting IMU: overlapping Allan deviation and its read-offs.

    res = allan(gyro_rad_s, fs_hz=100)            # (n, 3) SI rates -> dict per axis "x"/"y"/"z"
    res["x"]["N"], res["x"]["B"], res["x"]["K"]   # white noise, bias instability, rate random walk
    plot_allan(res, "allan_gyro.png", "gyro", "rad/s")

    imubench allan --port URL --duration 2h [--rate 100] [--out DIR]   record (crash-safe) + analyse
    imubench allan --analyse DIR/capture.bin [--out DIR]               analyse an existing capture

Conventions (docs/conventions.md, docs/noise.md): white noise coefficient N with
ADEV(τ) = N/√τ (read at τ = 1 s on the −1/2 line); rate random walk K with ADEV(τ) = K·√(τ/3)
(read at τ = 3 s on the +1/2 line); bias instability B = min ADEV / 0.664.

How the lines are fitted (see docs/noise.md):
  * local log-log slopes between adjacent octave τ;
  * −1/2 region: the longest run of consecutive τ, starting at the first segment (at or
    before the curve's minimum) whose slope is within −1/2 ± 0.15, ending at the first
    segment outside that band. N = weighted mean of log(ADEV·√τ) over it (slope fixed at
    −1/2, weights = equivalent degrees of freedom, i.e. 1/var(log ADEV)).
  * +1/2 region: from the smallest τ after the minimum such that a free weighted log-log fit
    from there to τ_end has slope +1/2 ± 0.15 (at least 3 points), to τ_end = the longest
    τ <= T/8 (T the record length; longer τ have too few independent windows). K = weighted mean of log(√(ADEV² − N²/τ)·√(3/τ)) over it: the white part, known from the
    −1/2 fit, is removed so the points near the crossover do not bias K upwards.
"""
from __future__ import annotations

import argparse
import json
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np

from imubench.device.link import DEFAULT_BAUD

G0 = 9.80665
RAD2DEG = 180.0 / np.pi
SLOPE_TOL = 0.15
MAX_TAU_FRACTION = 8.0
AXES = ("x", "y", "z")


# ---------------------------------------------------------------- analysis
def _edf_and_ci(taus, devs, slopes_pt, n_freq, fs_hz):
    import allantools
    edfs, lo, hi = [], [], []
    for tau, dev, s in zip(taus, devs, slopes_pt):
        # noise type from the local slope: ADEV ∝ τ^s  <=>  S_y ∝ f^α with α = −2s − 1
        alpha = int(np.clip(np.round(-2.0 * s - 1.0), -2, 0))
        m = int(round(tau * fs_hz))
        try:
            edf = float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n_freq + 1,
                                                 overlapping=True, modified=False))
        except Exception:  # noqa: BLE001 - fall back to the simple estimate
            edf = float(allantools.edf_simple(n_freq + 1, m, alpha))
        edf = max(edf, 1.0)
        a, b = allantools.confidence_interval(dev=dev, edf=edf)
        edfs.append(edf)
        lo.append(float(a))
        hi.append(float(b))
    return np.array(edfs), np.array(lo), np.array(hi)


def _fixed_slope_fit(logtau, logy, w, slope):
    """Weighted mean of the intercept of a line of given slope in log10 space, and its 1σ."""
    c = logy - slope * logtau
    W = np.sum(w)
    c0 = float(np.sum(w * c) / W)
    return c0, float(np.sqrt(1.0 / W))


def _free_slope(logtau, logy, w):
    A = np.vstack([logtau, np.ones_like(logtau)]).T * np.sqrt(w)[:, None]
    coef, *_ = np.linalg.lstsq(A, logy * np.sqrt(w), rcond=None)
    return float(coef[0])


def allan_axis(x: np.ndarray, fs_hz: float) -> dict:
    """Allan analysis of one axis (1-D rate samples in SI at fs_hz)."""
    import allantools
    x = np.asarray(x, dtype=np.float64)
    taus, devs, _errs, ns = allantools.oadev(x, rate=fs_hz, data_type="freq", taus="octave")
    keep = (devs > 0) & (ns >= 1)
    taus, devs, ns = np.asarray(taus)[keep], np.asarray(devs)[keep], np.asarray(ns)[keep]
    if len(taus) < 3:
        raise ValueError(f"too few samples for an Allan analysis ({len(x)})")
    lt, ld = np.log10(taus), np.log10(devs)
    seg = np.diff(ld) / np.diff(lt)                          # slope of segment i -> i+1
    pt = np.empty_like(ld)                                   # slope at each point
    pt[0], pt[-1] = seg[0], seg[-1]
    pt[1:-1] = 0.5 * (seg[:-1] + seg[1:])
    edf, lo, hi = _edf_and_ci(taus, devs, pt, len(x), fs_hz)
    w = 2.0 * edf * np.log(10.0) ** 2                        # 1/var(log10 ADEV) ≈ 2·edf·ln(10)²
    i_min = int(np.argmin(devs))

    # ---- −1/2 line (white noise N)
    ok = np.abs(seg + 0.5) <= SLOPE_TOL
    cand = [i for i in range(min(i_min, len(seg))) if ok[i]] if i_min > 0 else []
    white = {"ok": bool(cand)}
    if cand:
        j0 = cand[0]
        j1 = j0
        while j1 < len(seg) and ok[j1]:
            j1 += 1
        idx = np.arange(j0, j1 + 1)                          # points joined by good segments
    else:                                                    # no −1/2 region: first two points
        idx = np.arange(0, 2)
    c, sc = _fixed_slope_fit(lt[idx], ld[idx], w[idx], -0.5)
    N = 10 ** c
    white.update(N=N, N_rel_1sigma=float(sc * np.log(10)), tau_range=[float(taus[idx[0]]), float(taus[idx[-1]])],
                 n_points=int(len(idx)), free_slope=_free_slope(lt[idx], ld[idx], w[idx]) if len(idx) > 1 else None)

    # ---- +1/2 line (rate random walk K)
    rw = {"ok": False, "K": None}
    # the longest τ are estimated from too few independent windows (their edf estimate is
    # unreliable too): the +1/2 fit uses τ <= T/MAX_TAU_FRACTION only
    last = int(np.searchsorted(taus, len(x) / fs_hz / MAX_TAU_FRACTION, side="right")) - 1
    for j in range(i_min + 1, last - 1):
        s = _free_slope(lt[j:last + 1], ld[j:last + 1], w[j:last + 1])
        if abs(s - 0.5) <= SLOPE_TOL:
            idx = np.arange(j, last + 1)
            var_k = devs[idx] ** 2 - N ** 2 / taus[idx]      # remove the white part (known from N)
            good = var_k > 0
            idx = idx[good]
            if len(idx) == 0:
                break
            yk = 0.5 * np.log10(devs[idx] ** 2 - N ** 2 / taus[idx])
            c, sc = _fixed_slope_fit(lt[idx], yk, w[idx], 0.5)
            K = 10 ** c * np.sqrt(3.0)                       # line K·√(τ/3): value at τ = 3 s is K
            rw = {"ok": True, "K": K, "K_rel_1sigma": float(sc * np.log(10)),
                  "tau_range": [float(taus[idx[0]]), float(taus[idx[-1]])], "n_points": int(len(idx)),
                  "free_slope": s}
            break

    B = devs[i_min] / 0.664
    return {
        "taus": taus.tolist(), "adev": devs.tolist(), "ci_lo": lo.tolist(), "ci_hi": hi.tolist(),
        "edf": edf.tolist(), "n_pairs": np.asarray(ns).tolist(),
        "N": N, "white": white,
        "B": float(B), "B_tau": float(taus[i_min]), "B_adev_ci": [float(lo[i_min]), float(hi[i_min])],
        "K": rw["K"], "rate_rw": rw,
    }


def allan(rates: np.ndarray, fs_hz: float) -> dict:
    """Overlapping Allan deviation (octave τ, 68 % edf confidence intervals) and read-offs
    of each axis of `rates` ((n, 3) in SI: m/s² or rad/s). Returns {"x": {...}, "y": ..., "z": ...,
    "fs_hz": .., "n": .., "duration_s": ..}; each axis: taus, adev, ci_lo, ci_hi, N, B, B_tau, K
    (K None when the recording shows no +1/2 region) and the fit details."""
    r = np.asarray(rates, dtype=np.float64)
    if r.ndim == 1:
        r = r[:, None]
    out = {AXES[k]: allan_axis(r[:, k], fs_hz) for k in range(r.shape[1])}
    out.update(fs_hz=float(fs_hz), n=int(r.shape[0]), duration_s=r.shape[0] / float(fs_hz))
    return out


def usual_units(res_axis: dict, kind: str) -> dict:
    """Read-offs of one axis in the usual units: kind 'accel' (SI m/s²) or 'gyro' (rad/s)."""
    N, B, K = res_axis["N"], res_axis["B"], res_axis["K"]
    if kind == "accel":
        ug = 1e6 / G0
        return {"N_ug_per_rtHz": N * ug, "VRW_m_s_per_rth": N * 60.0, "B_ug": B * ug,
                "K_ug_rtHz": None if K is None else K * ug}
    return {"N_deg_per_rth": N * RAD2DEG * 60.0, "N_deg_s_per_rtHz": N * RAD2DEG, "B_deg_h": B * RAD2DEG * 3600.0,
            "K_deg_h_per_rth": None if K is None else K * RAD2DEG * 3600.0 ** 1.5}


# -------------------------------------------------------------------- plot
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
        ks = f"{r['K']:.3g}" if r["K"] is not None else "n/a"
        lab = f"{a}: N={r['N']:.3g} {unit}/√Hz, B={r['B']:.3g} {unit} (τ={r['B_tau']:.3g} s), K={ks} {unit}·√Hz"
        if kind in ("accel", "gyro"):
            u = usual_units(r, kind)
            if kind == "accel":
                lab += (f"\n     = VRW {u['N_ug_per_rtHz']:.3g} µg/√Hz, B {u['B_ug']:.3g} µg, "
                        f"K {_fmt(u['K_ug_rtHz'], '{:.3g}')} µg·√Hz")
            else:
                lab += (f"\n     = ARW {u['N_deg_per_rth']:.3g} °/√h, B {u['B_deg_h']:.3g} °/h, "
                        f"RRW {_fmt(u['K_deg_h_per_rth'], '{:.3g}')} °/h/√h")
        ax.errorbar(t, d, yerr=err, fmt="o-", ms=3.5, lw=1.2, capsize=2.5, color=col, label=lab)
        ax.plot(tt, r["N"] / np.sqrt(tt), "--", color=col, lw=0.9, alpha=0.8)
        ax.plot([1.0], [r["N"]], "s", color=col, mfc="none", ms=8)
        if r["K"] is not None:
            ax.plot(tt, r["K"] * np.sqrt(tt / 3.0), ":", color=col, lw=1.3, alpha=0.9)
            ax.plot([3.0], [r["K"]], "^", color=col, mfc="none", ms=8)
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
    ax.set_title(f"{title}: overlapping Allan deviation, {dur / 3600:.2f} h at {result.get('fs_hz', 0):g} Hz "
                 "(error bars: 68 % CI)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=1, frameon=False)
    fig.tight_layout()
    fig.savefig(str(path))


# ---------------------------------------------------------------- command
def parse_duration(s: str) -> float:
    """'90s', '30m', '2h', '1h30m', '45' (seconds) -> seconds."""
    s = s.strip().lower()
    if re.fullmatch(r"\d+(\.\d+)?", s):
        return float(s)
    parts = re.findall(r"(\d+(?:\.\d+)?)\s*([hms])", s)
    if not parts or "".join(n + u for n, u in parts) != s.replace(" ", ""):
        raise argparse.ArgumentTypeError(f"bad duration {s!r} (use e.g. 90s, 30m, 2h, 1h30m)")
    return sum(float(n) * {"h": 3600, "m": 60, "s": 1}[u] for n, u in parts)


def _fmt(v, f="{:.4g}"):
    return "n/a" if v is None else f.format(v)


def analyse_capture(paths, out_dir: Path, rate_hz: float | None = None, log=print) -> dict:
    """Decode capture file(s), convert raw counts to SI, run allan() on accel and gyro,
    write allan.json and the two PNGs to out_dir; returns the summary dict."""
    from imubench.wire.decoder import decode_bytes
    data = b"".join(Path(p).read_bytes() for p in paths)
    _msgs, raw, _cal, stats = decode_bytes(data)
    if raw is None or len(raw) < 16:
        raise ValueError(f"{', '.join(map(str, paths))}: no raw samples to analyse "
                         f"({stats.samples} samples, {stats.frames_rejected} rejected frames)")
    if rate_hz is None:                          # from the device time stamps
        rate_hz = (len(raw) - 1) / ((raw.t_us[-1] - raw.t_us[0]) / 1e6)
        rate_hz = float(np.round(rate_hz, 1))
    acc, gyr = raw.si()
    out_dir.mkdir(parents=True, exist_ok=True)
    res = {"source": [str(p) for p in paths], "samples": len(raw), "rate_hz": rate_hz,
           "duration_s": len(raw) / rate_hz, "decoder": stats.as_dict(),
           "accel": allan(acc, rate_hz), "gyro": allan(gyr, rate_hz)}
    if stats.samples_missing:
        log(f"warning: {stats.samples_missing} samples were lost in {stats.sample_gaps} gaps; "
            "the analysis joins the pieces (fine for a few, biased for many)")
    res["accel_usual"] = {a: usual_units(res["accel"][a], "accel") for a in AXES}
    res["gyro_usual"] = {a: usual_units(res["gyro"][a], "gyro") for a in AXES}
    (out_dir / "allan.json").write_text(json.dumps(res, indent=1))
    plot_allan(res["accel"], out_dir / "allan_accel.png", "Accelerometer (ADXL355)", "m/s²", "accel")
    plot_allan(res["gyro"], out_dir / "allan_gyro.png", "Gyroscope (ADXRS450)", "rad/s", "gyro")
    log(f"analysed {len(raw)} samples = {res['duration_s'] / 3600:.3f} h at {rate_hz:g} Hz")
    log(f"{'':6} {'VRW N [µg/√Hz]':>15} {'[m/s/√h]':>10} {'bias inst. B [µg]':>18} {'at τ [s]':>9} "
        f"{'RRW K [µg·√Hz]':>15}")
    for a in AXES:
        r, u = res["accel"][a], res["accel_usual"][a]
        log(f"acc {a}: {_fmt(u['N_ug_per_rtHz']):>15} {_fmt(u['VRW_m_s_per_rth']):>10} {_fmt(u['B_ug']):>18} "
            f"{r['B_tau']:9.4g} {_fmt(u['K_ug_rtHz']):>15}")
    log(f"{'':6} {'ARW N [°/√h]':>15} {'[°/s/√Hz]':>10} {'bias inst. B [°/h]':>18} {'at τ [s]':>9} "
        f"{'RRW K [°/h/√h]':>15}")
    for a in AXES:
        r, u = res["gyro"][a], res["gyro_usual"][a]
        log(f"gyr {a}: {_fmt(u['N_deg_per_rth']):>15} {_fmt(u['N_deg_s_per_rtHz']):>10} {_fmt(u['B_deg_h']):>18} "
            f"{r['B_tau']:9.4g} {_fmt(u['K_deg_h_per_rth']):>15}")
    log("(SI: N in m/s²/√Hz or rad/s/√Hz, B in m/s² or rad/s, K in m/s²·√Hz or rad/s·√Hz: see allan.json)")
    log(f"wrote {out_dir / 'allan.json'}, {out_dir / 'allan_accel.png'}, {out_dir / 'allan_gyro.png'}")
    return res


def record(port, duration_s: float, rate_hz: int, capture_path: Path, baud: int = DEFAULT_BAUD,
           progress_s: float = 5.0, stop: dict | None = None, log=print) -> str:
    """Stream raw at rate_hz into capture_path (every byte appended as it arrives) until
    duration_s of *device* time has been received, stop["now"] is set, or the link is lost.
    Returns why it ended: 'done', 'interrupted' or 'link lost: ...'."""
    from imubench.device.link import Device, DeviceError, LinkError, LinkTimeout
    stop = stop if stop is not None else {"now": False}
    want = int(round(duration_s * rate_hz))
    why = "done"
    with open(capture_path, "ab", buffering=0) as cap:
        try:
            dev = Device.open(port, baudrate=baud, capture=cap, timeout=3.0)
        except LinkError as e:
            return f"link lost: {e}"
        with dev:
            try:
                dev.start_stream(rate_hz, calibrated=False)
            except (LinkError, LinkTimeout, DeviceError) as e:
                return f"link lost: {e}"
            t0 = time.monotonic()
            t_next = t0 + progress_s
            have, t_first, t_last = 0, None, None
            log(f"recording raw at {rate_hz} Hz for {duration_s:g} s of device time to {capture_path}; "
                "Ctrl-C stops and analyses what was recorded")
            try:
                for b in dev.stream(poll_s=0.1):
                    if len(b):
                        have += len(b)
                        t_first = b.t_us[0] if t_first is None else t_first
                        t_last = b.t_us[-1]
                    now = time.monotonic()
                    if now >= t_next or have >= want:
                        t_next = now + progress_s
                        st = dev.link.decoder.stats
                        dev_s = (t_last - t_first) / 1e6 if t_first is not None else 0.0
                        log(f"  {dev_s:9.1f} / {duration_s:g} s ({100 * min(have, want) / max(want, 1):5.1f} %), "
                            f"{have} samples, wall {now - t0:.1f} s | link: {st.bytes_in} B, "
                            f"{st.frames_ok} frames, {st.frames_rejected} rejected, {st.samples_missing} lost",
                            flush=True)
                    if have >= want:
                        break
                    if stop["now"]:
                        why = "interrupted"
                        break
            except (LinkError, LinkTimeout, DeviceError, OSError) as e:
                why = f"link lost: {e}"
            try:
                if not why.startswith("link lost"):
                    dev.stop_stream()
            except (LinkError, LinkTimeout, DeviceError) as e:
                log(f"warning: could not stop the stream: {e}")
    return why


def main_allan(argv=None) -> int:
    """`imubench allan --port URL --duration 2h [--rate 100] [--out DIR] [--analyse FILE...]`"""
    ap = argparse.ArgumentParser(prog="imubench allan",
                                 description="Record a resting IMU for a long time (crash-safe) and compute "
                                             "Allan deviations and the noise read-offs N, B, K per axis.")
    ap.add_argument("--port", help="pyserial URL of the device (default: $IMUBENCH_PORT)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"baud rate for a real UART (default {DEFAULT_BAUD})")
    ap.add_argument("--duration", type=parse_duration, default=None,
                    help="recording length in device time: 90s, 30m, 2h, 1h30m (required unless --analyse)")
    ap.add_argument("--rate", type=int, default=100, help="sample rate in Hz (default 100)")
    ap.add_argument("--out", default="allan-out", help="output directory (default ./allan-out)")
    ap.add_argument("--analyse", nargs="+", metavar="FILE",
                    help="analyse existing capture file(s) (e.g. of a crashed recording) without a device")
    ap.add_argument("--progress", type=float, default=5.0, help="seconds between progress lines (default 5)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.analyse:
        try:
            analyse_capture([Path(p) for p in a.analyse], out)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
        return 0
    if a.duration is None:
        ap.error("--duration is required to record (or give --analyse FILE)")
    out.mkdir(parents=True, exist_ok=True)
    cap = out / "capture.bin"
    if cap.exists() and cap.stat().st_size:
        print(f"error: {cap} exists; analyse it with --analyse {cap} or choose another --out", file=sys.stderr)
        return 1
    stop = {"now": False}
    old = None
    try:
        old = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("now", True))
    except ValueError:                        # not the main thread: no Ctrl-C handling
        pass
    try:
        why = record(a.port, a.duration, a.rate, cap, a.baud, a.progress, stop)
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)
    print(f"recording ended: {why}; analysing {cap}", flush=True)
    try:
        analyse_capture([cap], out, rate_hz=float(a.rate))
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0 if why in ("done", "interrupted") else 2


if __name__ == "__main__":
    sys.exit(main_allan())
