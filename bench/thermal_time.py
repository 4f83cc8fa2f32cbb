"""Temperature calibration, step method against warm-up: the device time each needs and the
calibrated stream's residual drift over the span after it, on the virtual device with thermal
lag and curved truth (issue 23).

    PYTHONPATH=host python bench/thermal_time.py [--seed N] [--speed X] [--span 5,45]
                                                 [--random-walk on|off|both] [--no-publish]

Each method runs on its own fresh virtual device, the same part (random truth from --seed,
its thermal time constants and self-heating drawn with it: VirtualBench.set_thermal with no
constants given), starting at 25 °C ambient just after power-up, level (+Z up):

* step, waiting for the lag: `imubench thermal`'s sweep (procedures.thermal: sweep, fit_sweep,
  apply_tempcos, write_params) at 5, 25, 45 °C (the documented command), the chamber ramping
  at 0.5 °C/s, each point measured once every sensor's |dT/dt| < 0.1 °C/min over 300 s
  (the command's defaults); a straight line per axis.
* step, not waiting: the same, each point measured as soon as the chamber's air is at the
  set point (the dies still lag behind it).
* warm-up: procedures.warmup.run_warmup with sim_warmup_hooks: the board soaked at the span's
  low end (a night in a fridge: not counted, it needs nobody), then the room at the high end;
  polynomial of the order the data choose, span clamped on the device.

Time = device time from the method's first command to its parameters written and verified
(the virtual device in lockstep: device time does not depend on the machine's load); the
wall time each method took is printed and tabled apart, labelled with its clock. A link or
simulator error in a method, or in its drift measurement, is caught per method and named
(which method, which stage, which error) in the output and the table.
Residual drift = on the device's CALIBRATED stream (100 Hz, level, still), the ambient soaked
at the low end then ramped at 0.5 °C/min past the high end (warming) and back below the low
end (cooling); chunk means (1 s) binned by each sensor's own die temperature in 2 °C bins over
the span; per axis, max − min of the bin means over both branches (the hysteresis between
warming and cooling shows there) and over the warming branch alone. Gyro in °/s,
accelerometer in mg (x, y, z of the output; Z carries 1 g, so its scale tempco shows too).

Each method runs twice (--random-walk both, the default): on the part as drawn, and with its
gyro bias drift (bias instability and rate random walk, docs/simulator.md) and accelerometer
random walk off. Over the hours a sweep takes the drift moves the bias (it is not a
temperature effect: no method removes it), so the second run shows the temperature error alone.

Ends with one JSON line: step_time_s, warmup_time_s, step_nowait_time_s and
{step,step_nowait,warmup}_drift_{gyro_dps,accel_mg} (per-axis lists x, y, z, both branches;
the part as drawn), the same with _warming (warming branch only) and with _no_rw (bias drift
off), aim_met / aim_met_no_rw, and the part's thermal constants.
Aim (issue 23): warm-up drift no worse than the step method's, in at most a third of its time.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "host"))

from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT  # noqa: E402
from imubench import units as U  # noqa: E402
from imubench.device.sim import VirtualBench  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

STEP_TEMPS_C = (5.0, 25.0, 45.0)   # docs/thermal.md's command: imubench thermal --sim --temps 5,25,45
CHAMBER_RAMP_C_PER_S = 0.5         # `imubench thermal --ramp` default
DRIFT_RAMP_C_PER_MIN = 0.5
DRIFT_RATE_HZ = 50
BIN_C = 2.0
MIN_CHUNKS_PER_BIN = 20
SENSORS = ("ADXL355", "gyro X", "gyro Y", "gyro Z")


# ------------------------------------------------------------------ the methods
def fresh_bench(speed: float, seed: int, random_walk: bool = True) -> VirtualBench:
    vb = VirtualBench(speed=speed, seed=seed, truth="random")
    vb.set_thermal(enabled=True)            # the part's own constants, drawn with its truth
    if not random_walk:                     # the temperature error alone: no bias drift
        vb.set_truth(accel={"rw_k": [0.0] * 3}, gyro=[GYRO_NO_DRIFT] * 3)
    return vb


def device_s(vb) -> float:
    return float(vb.status()["time_s"])


def step_method(vb, out: Path, span, wait: bool) -> dict:
    """The sweep of `imubench thermal` (waiting for the lag or not), fit, write, verify."""
    from imubench.procedures.thermal import Hooks, Settling, sweep, write_params
    from imubench.analysis.thermal import apply_tempcos, fit_sweep
    from imubench.wire.protocol_gen import ParamsWhich

    temps = [t for t in STEP_TEMPS_C if span[0] <= t <= span[1]]
    if wait:
        def set_t(c):
            vb.set_temperature(c, ramp_c_per_s=CHAMBER_RAMP_C_PER_S)
        settle = Settling(rate_c_per_min=0.1, window_s=300.0, timeout_s=6 * 3600.0)
    else:
        def set_t(c):                       # the air at the set point; the dies lag behind
            vb.set_temperature(c, ramp_c_per_s=CHAMBER_RAMP_C_PER_S, wait=True)
        settle = None
    hooks = Hooks(set_temperature=set_t)
    with vb.device() as dev:
        t0 = device_s(vb)
        old = dev.get_params(ParamsWhich.ACTIVE).params
        t_ref = float(old.accel_t_ref_c)
        points = sweep(dev, temps, hooks, n=2000, poses=("+z",), turntable=False, settle=settle,
                       check_tol_c=2.0 if wait else None)   # not waiting: the dies lag, by design
        fit = fit_sweep(points, t_ref)
        write_params(dev, apply_tempcos(old, fit, t_ref))
        t1 = device_s(vb)
    die = [[p.accel_temp_c, *[float(g) for g in p.gyro_temp_c]] for p in points]
    return {"time_s": t1 - t0, "points_die_c": die, "order": "1 (straight line)"}


def warmup_method(vb, out: Path, span) -> dict:
    """procedures.warmup.run_warmup on the virtual bench: soak cold, then warm; write, verify."""
    from imubench.procedures.warmup import WarmupConfig, run_warmup, sim_warmup_hooks
    cfg = WarmupConfig(span_c=tuple(span), write=True)
    hooks = sim_warmup_hooks(vb, cold_c=span[0], warm_c=span[1])
    with vb.device() as dev:
        t0 = device_s(vb)
        result = run_warmup(dev, out, cfg, hooks)
        t1 = device_s(vb)
    if result.get("status") != "done" or not (result.get("write") or {}).get("verified"):
        raise RuntimeError(f"warm-up {result.get('status')}: {result.get('error') or result.get('stop_reason')}")
    print(f"  warm-up stopped: {result.get('stop_reason')}", flush=True)
    return {"time_s": t1 - t0, "result": result, "order": _orders(result)}


def _orders(result: dict) -> str:
    """The orders the warm-up chose per axis (x/y/z), as a short text."""
    fit = (result or {}).get("fit") or {}
    parts = [f"{tr} {'/'.join(str(a.get('order')) for a in (fit.get(tr) or {}).get('axes') or [])}"
             for tr in ("accel", "gyro") if fit.get(tr)]
    if not parts:
        return f"nothing fitted ({(result or {}).get('error') or (result or {}).get('stop_reason')})"
    return "polynomial, order " + ", ".join(parts)


# ------------------------------------------------------------------ residual drift
def drift(vb, span, self_heat_c) -> dict:
    """The calibrated stream over the span, warming then cooling (procedures.thermal_drift)."""
    from imubench.procedures.thermal_drift import DriftSweep, residual_drift
    sw = DriftSweep(ramp_c_per_min=DRIFT_RAMP_C_PER_MIN, rate_hz=DRIFT_RATE_HZ, bin_c=BIN_C,
                    min_chunks=MIN_CHUNKS_PER_BIN)
    with vb.device() as dev:
        d = residual_drift(vb, dev, span, self_heat_c, sw)
    d["bins_filled"] = list(d["filled"].values())
    d["nbins"] = len(d["edges_c"]) - 1
    return d


def truth_drift(truth: dict, span) -> dict:
    """The bias change the truth puts over the span, uncorrected (warming and cooling)."""
    from imubench.device.sim_thermal import truth_bias
    temps = np.repeat(np.linspace(span[0], span[1], 81)[:, None], 4, axis=1)
    a = np.vstack([truth_bias(truth, temps, warming=w)[0] for w in (True, False)])
    g = np.vstack([truth_bias(truth, temps, warming=w)[1] for w in (True, False)])
    return {"accel_mg": U.mps2_to_mg(np.ptp(a, axis=0)), "gyro_dps": U.rad_s_to_dps(np.ptp(g, axis=0))}


# ------------------------------------------------------------------ output
def _sig(v: float, n: int = 2) -> str:
    if not math.isfinite(v):
        return "–"
    if v == 0:
        return "0"
    return f"{v:.{max(0, n - 1 - math.floor(math.log10(abs(v))))}f}"


def _minutes(s: float) -> str:
    return "–" if not math.isfinite(s) else f"{s / 60:.0f} min"


def _axes(v) -> str:
    return " / ".join(_sig(float(x)) for x in v)


METHODS = (("step, waiting for the lag", "step"), ("step, not waiting", "step_nowait"), ("warm-up", "warmup"))
VARIANTS = (("", "the part as drawn (bias drift on)"), ("_no_rw", "bias drift off: the temperature error alone"))


def table(runs: dict, truth_d: dict, thermal: dict, span, suffixes) -> str:
    """The markdown table: device time and model of the first variant run, then each variant's drift."""
    cols = list(METHODS)
    first = suffixes[0]
    rows = []
    for suffix, words in VARIANTS:
        if suffix in suffixes:
            rows.append((f"calibration time, device clock; {words}",
                         [_minutes(runs[k + suffix]["time_s"]) for _, k in cols]))
            rows.append((f"this run's wall time (calibration and drift), wall clock; {words}",
                         [_minutes(runs[k + suffix].get("wall_s", math.nan)) for _, k in cols]))
    rows.append(("temperature model fitted", [runs[k + first]["order"] for _, k in cols]))
    if "warmup" + first in runs and runs["warmup" + first].get("result"):
        rows.append(("warm-up stopped because", ["", "", str(runs["warmup" + first]["result"].get("stop_reason"))]))
    for suffix, words in VARIANTS:
        if suffix not in suffixes:
            continue
        for q, unit, name in (("gyro_dps", "°/s", "gyro"), ("accel_mg", "mg", "accel")):
            rows.append((f"{name} drift x / y / z ({unit}), warming and cooling; {words}",
                         [_axes(runs[k + suffix]["drift"][q]) for _, k in cols]))
            rows.append((f"{name} drift, warming only ({unit}); {words}",
                         [_axes(runs[k + suffix]["drift"][q + "_warming"]) for _, k in cols]))
    head = "| | " + " | ".join(c for c, _ in cols) + " |\n|---|" + "---|" * len(cols) + "\n"
    body = "".join(f"| {label} | " + " | ".join(v) + " |\n" for label, v in rows)
    tau = "/".join(f"{t:.0f}" for t in thermal["tau_s"])
    sh = "/".join(f"{t:.1f}" for t in thermal["self_heat_c"])
    pad = " |" * len(cols)
    foot = (f"| uncorrected bias change over {span[0]:g}–{span[1]:g} °C (truth) | gyro {_axes(truth_d['gyro_dps'])} °/s, "
            f"accel {_axes(truth_d['accel_mg'])} mg{pad}\n"
            f"| the part's thermal time constants (ADXL355, gyro X/Y/Z), self-heating | {tau} s, {sh} °C{pad}\n")
    errors = "".join(f"| {k}: failed | {r['error'][:200]}{pad}\n" for k, r in runs.items() if r.get("error"))
    return head + body + foot + errors


def _failed(key: str, stage: str, e: BaseException) -> dict:
    """A method's result when its `stage` raised e (a link error, a timeout, the simulator)."""
    what = f"{stage}: {type(e).__name__}: {e}"
    print(f"{key}: FAILED in the {what}", flush=True)
    return {"time_s": math.nan, "order": f"failed ({stage})", "error": what,
            "drift": {k: np.full(3, np.nan) for k in ("gyro_dps", "accel_mg", "gyro_dps_warming", "accel_mg_warming")}
            | {"bins_filled": [0, 0], "nbins": 0}}


def _verdict(runs: dict, suffix: str) -> tuple[bool, str]:
    st, wu = runs["step" + suffix], runs["warmup" + suffix]
    ratio = wu["time_s"] / st["time_s"]
    mg, sg = np.nanmax(wu["drift"]["gyro_dps"]), np.nanmax(st["drift"]["gyro_dps"])
    ma, sa = np.nanmax(wu["drift"]["accel_mg"]), np.nanmax(st["drift"]["accel_mg"])
    better = mg <= sg and ma <= sa
    ok = bool(better and ratio <= 1 / 3)
    return ok, (f"warm-up / step time = {ratio:.2f} (aim ≤ 0.33); worst axis, warm-up against step: gyro "
                f"{_sig(mg)} against {_sig(sg)} °/s, accel {_sig(ma)} against {_sig(sa)} mg: "
                f"{'MET' if ok else 'NOT MET'}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=7, help="the virtual part (random truth and thermal constants)")
    ap.add_argument("--speed", type=float, default=0.0,
                    help="ceiling of device time per wall time (0: none; the virtual device runs in lockstep)")
    ap.add_argument("--span", default="5,45", help="LO,HI in °C (default 5,45)")
    ap.add_argument("--random-walk", choices=("on", "off", "both"), default="both",
                    help="the part's bias drift (gyro bias instability and random walks): as drawn (on), off "
                         "(the temperature error alone), or both runs")
    add_arguments(ap)
    a = ap.parse_args()
    try:
        span = tuple(float(x) for x in a.span.split(","))
        if len(span) != 2 or not span[0] + 10 <= span[1]:
            raise ValueError
    except ValueError:
        ap.error(f"--span {a.span!r}: give LO,HI in °C, at least 10 °C apart (e.g. 5,45)")
    variants = {"on": [("", True)], "off": [("_no_rw", False)], "both": [("", True), ("_no_rw", False)]}[a.random_walk]
    wall0 = time.monotonic()
    runs: dict[str, dict] = {}
    thermal = truth = None
    with tempfile.TemporaryDirectory() as tmp:
        for suffix, rw in variants:
            for _, method in METHODS:
                key = method + suffix
                w0 = time.monotonic()
                with fresh_bench(a.speed, a.seed, random_walk=rw) as vb:
                    st = vb.status()["thermal"]
                    thermal = thermal or {"tau_s": list(st["tau_s"]), "self_heat_c": list(st["self_heat_c"])}
                    truth = truth or vb.get_truth()
                    out = Path(tmp) / key
                    try:
                        r = (warmup_method(vb, out, span) if method == "warmup"
                             else step_method(vb, out, span, wait=method == "step"))
                    except Exception as e:  # noqa: BLE001 - a method that fails is a result too
                        r = _failed(key, "calibration", e)
                    else:
                        print(f"{key}: calibrated in {r['time_s']:.0f} s of device time; measuring the drift …", flush=True)
                        try:
                            r["drift"] = drift(vb, span, thermal["self_heat_c"])
                        except Exception as e:  # noqa: BLE001 - LinkTimeout, LinkError, SimError: named
                            r = {**_failed(key, "drift measurement", e), "time_s": r["time_s"], "order": r["order"]}
                r["wall_s"] = time.monotonic() - w0
                runs[key] = r
                d = r["drift"]
                print(f"  gyro drift {_axes(d['gyro_dps'])} °/s, accel drift {_axes(d['accel_mg'])} mg "
                      f"(bins filled {d['bins_filled']} of {d['nbins']}; wall {r['wall_s']:.0f} s)", flush=True)
    truth_d = truth_drift(truth, span)
    first = variants[0][0]
    md = table(runs, truth_d, thermal, span, [s for s, _ in variants])
    print("\n" + md, end="")
    verdicts = {s: _verdict(runs, s) for s, _ in variants}
    for s, words in VARIANTS:
        if s in verdicts:
            print(f"{words}: {verdicts[s][1]}")
    wall = time.monotonic() - wall0
    print(f"wall time {wall:.0f} s at sim speed {a.speed:g}")
    publish("thermal_time", md, {"seed": a.seed, "span": f"{span[0]:g}–{span[1]:g} °C", "sim speed": f"{a.speed:g}",
                                 "wall time": f"{wall:.0f} s"}, enabled=not a.no_publish)
    line = {"wall_s": {k: round(r.get("wall_s", math.nan), 1) for k, r in runs.items()},
            "errors": {k: r["error"] for k, r in runs.items() if r.get("error")},
            "drift": "per-axis lists x, y, z: max − min of 2 °C bin means of the calibrated stream over the span, "
                     "warming and cooling together (_warming: warming only); _no_rw: the part's bias drift off",
            "seed": a.seed, "tau_s": [round(t, 1) for t in thermal["tau_s"]],
            "self_heat_c": [round(t, 2) for t in thermal["self_heat_c"]]}
    for _, k in METHODS:
        t = runs[k + first]["time_s"]
        line[f"{k}_time_s"] = None if not math.isfinite(t) else round(t, 1)
    for suffix, _rw in variants:
        for _, k in METHODS:
            for q, unit in (("gyro", "dps"), ("accel", "mg")):
                for w in ("", "_warming"):
                    line[f"{k}_drift_{q}_{unit}{w}{suffix}"] = [None if not math.isfinite(v) else float(f"{v:.3g}")
                                                                for v in runs[k + suffix]["drift"][f"{q}_{unit}{w}"]]
        line[f"aim_met{suffix}"] = verdicts[suffix][0]
    st = runs["step" + first]["time_s"]
    line["warmup_over_step_time"] = round(runs["warmup" + first]["time_s"] / st, 3) if math.isfinite(st) else None
    print(json.dumps(line, ensure_ascii=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
