"""How long a person stands at the bench: today's fixed 26-attitude plan against the adaptive
session, side by side, on the virtual bench with a simulated person (procedures/virtual.py:
random order, 3–8 s hand moves, each attitude within ±5–10° of the plan, tremor while still).

    PYTHONPATH=host python bench/session_time.py [--seed N] [--speed X] [--no-publish]

Prints the markdown table README states and publishes it (bench/publish.py).

Bench time = device time (the virtual device on the lockstep clock: the same on any machine, idle
or busy) from the first prompt (hold still at the start) to the last
attitude captured, the person's moves included (the fit that follows takes well under a
second of host time and is not counted). Both sessions run on the same virtual device
(random truth, --seed) with the same person; the adaptive session holds each attitude until
its |a| is known to the pose target and stops when every parameter's sigma is at its
target (imubench.procedures.poses.Targets). Target: adaptive <= half the fixed plan's bench
time, and under 3 minutes.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "host"))

from imubench.device.sim import VirtualBench  # noqa: E402
from imubench.procedures.virtual import SimPerson  # noqa: E402
from imubench.procedures.poses import PARAM_NAMES, PARAM_UNITS, Targets, target_of  # noqa: E402
from imubench.procedures.session import Session, SessionConfig, plan_for  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

KINDS = {"b": "bias", "s": "scale", "a": "non-orthogonality"}


def _sig2(v: float) -> str:
    """Two significant figures, trailing zeros kept (0.010, 0.0098, 12)."""
    return f"{v:.{max(0, 1 - math.floor(math.log10(abs(v))))}f}" if v else "0"


def one(vb, adaptive: bool, seed: int, workdir: Path) -> dict:
    cfg = SessionConfig(method="multi", gyro=None, write=False, adaptive=adaptive, pose_timeout_s=None)
    person = SimPerson(vb, seed=seed)
    with vb.device() as dev:
        t0 = time.monotonic()
        s = Session(dev, workdir / ("adaptive" if adaptive else "fixed"), cfg, person)
        result = s.run(plan_for("multi"))
        wall = time.monotonic() - t0
    return {"result": result, "order": person.order, "moves_s": person.moves_s, "wall_s": wall}


def _mean_hold_s(result: dict) -> float:
    poses = result["poses"]
    return sum(p["n"] for p in poses) / SessionConfig().rate_hz / len(poses)


def table(fixed: dict, adapt: dict, t: Targets, rate_hz: float) -> str:
    """The markdown table README states: both sessions side by side."""
    fb, ab = fixed["result"]["bench_time_s"], adapt["result"]["bench_time_s"]
    hold = fixed["result"]["poses"][0]["n"] / rate_hz
    rows = [("bench time (device time)", f"{fb:.1f} s", f"{ab:.1f} s ({ab / fb:.2f} of the fixed plan; target ≤ 0.5 and < 180 s)"),
            ("of which the person's moves", f"{fixed['moves_s']:.1f} s", f"{adapt['moves_s']:.1f} s"),
            ("attitudes used", f"{len(fixed['result']['poses'])}", f"{len(adapt['result']['poses'])}"),
            ("mean hold per attitude", f"{_mean_hold_s(fixed['result']):.2f} s", f"{_mean_hold_s(adapt['result']):.2f} s"),
            ("RMS of \\|a\\| − g after calibration", f"{fixed['result']['accel_rms_after_mg']:.3f} mg",
             f"{adapt['result']['accel_rms_after_mg']:.3f} mg"),
            ("wall time the bench took (wall clock; the machine's load moves it, not the rows above)",
             f"{fixed['wall_s']:.0f} s", f"{adapt['wall_s']:.0f} s")]
    for k, kind in KINDS.items():
        names = [n for n in PARAM_NAMES if n[0] == k]
        unit = PARAM_UNITS[k]
        label = f"1σ {kind} {' / '.join(names)} (target ≤ {target_of(names[0], t):g} {unit})"
        rows.append((label, *(" / ".join(_sig2(r['result']['accel_sigmas'][n]) for n in names) + f" {unit}"
                              for r in (fixed, adapt))))
    return (f"| | fixed {len(fixed['result']['poses'])}-attitude plan ({hold:.0f} s holds) | adaptive |\n|---|---|---|\n"
            + "".join(f"| {a} | {b} | {c} |\n" for a, b, c in rows))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=7, help="virtual device and person seed")
    ap.add_argument("--speed", type=float, default=0.0,
                    help="ceiling on device time per wall time (0: none; the virtual device is on the lockstep "
                         "clock, so the device-time figures do not depend on it or on the machine's load)")
    add_arguments(ap)
    a = ap.parse_args()
    t = Targets()
    print(t.describe())
    with tempfile.TemporaryDirectory() as tmp, VirtualBench(speed=a.speed, seed=a.seed, truth="random") as vb:
        runs = {name: one(vb, adaptive, a.seed, Path(tmp)) for name, adaptive in (("fixed 26", False),
                                                                                  ("adaptive", True))}
    fixed, adapt = runs["fixed 26"], runs["adaptive"]
    w = 14
    print(f"\n{'':28s}{'fixed 26-attitude plan':>{w + 10}s}{'adaptive':>{w}s}")
    rows = [("bench time (device s)", lambda r: f"{r['result']['bench_time_s']:.1f}"),
            ("  of which hand moves (s)", lambda r: f"{r['moves_s']:.1f}"),
            ("attitudes used", lambda r: f"{len(r['result']['poses'])}"),
            ("mean hold per attitude (s)", lambda r: f"{_mean_hold_s(r['result']):.2f}"),
            ("RMS |a| - g after (mg)", lambda r: f"{r['result']['accel_rms_after_mg']:.3f}")]
    for label, f in rows:
        print(f"{label:28s}{f(fixed):>{w + 10}s}{f(adapt):>{w}s}")
    print("final 1-sigma of each parameter (target):")
    for n in PARAM_NAMES:
        unit = PARAM_UNITS[n[0]]
        print(f"  {n + ' (' + unit + ')':26s}{fixed['result']['accel_sigmas'][n]:>{w + 10}.3g}"
              f"{adapt['result']['accel_sigmas'][n]:>{w}.3g}   (≤ {target_of(n, t):g})")
    ratio = adapt["result"]["bench_time_s"] / fixed["result"]["bench_time_s"]
    ok = ratio <= 0.5 and adapt["result"]["bench_time_s"] < 180 and all(
        adapt["result"]["accel_sigmas"][n] <= target_of(n, t) for n in PARAM_NAMES)
    print(f"\nadaptive / fixed bench time = {ratio:.2f} (target ≤ 0.5), adaptive "
          f"{adapt['result']['bench_time_s']:.0f} s (target < 180 s): {'MET' if ok else 'NOT MET'}")
    print(f"(order the person chose, adaptive: {', '.join(adapt['order'])})")
    print(f"wall time {fixed['wall_s']:.0f} s + {adapt['wall_s']:.0f} s (wall clock; speed ceiling "
          f"{a.speed:g}, 0 = none)")
    md = table(fixed, adapt, t, SessionConfig().rate_hz)
    print("\n" + md, end="")
    publish("session_time", md, {"seed": a.seed, "method": "multi, gyro none", "rate": f"{SessionConfig().rate_hz:g} Hz"},
            enabled=not a.no_publish)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
