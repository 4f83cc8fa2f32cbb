"""`imubench closure`: integrate a closed path before and after calibration (docs/closure.md)."""
from __future__ import annotations

import datetime as _dt
import shlex
from contextlib import nullcontext
from pathlib import Path

from imubench import units as U
from imubench.cli.common import (
    CommandError,
    add_port,
    add_sim,
    existing_dir,
    out_dir,
    positive_float,
    stream_rate,
)


def register(sub) -> None:
    from imubench.procedures.closure import PATHS
    p = sub.add_parser("closure", help="integrate a closed path before and after calibration",
                       description="Closure check: record a closed path (still at the start and at the end), "
                                   "integrate the accelerations twice with nominal scaling and with the "
                                   "calibration applied, and report how far from the start each integration ends "
                                   "(docs/closure.md).")
    add_port(p)
    p.add_argument("--params", default="device", metavar="device|FILE",
                   help="calibration to apply: the device's active parameters, or a JSON file "
                        "(a closure.json, or Params fields)")
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=1000, help="raw sample rate in Hz")
    p.add_argument("--rest", type=positive_float, default=2.0, help="seconds still at the start and at the end")
    p.add_argument("--max-s", type=positive_float, default=120.0, help="longest motion accepted, s")
    p.add_argument("--g", type=positive_float, default=U.G0_MPS2, help="local gravity, m/s²")
    p.add_argument("--out", type=out_dir, help="output directory (default: ./imubench-closure-<time>)")
    p.add_argument("--analyse", type=existing_dir, metavar="DIR",
                   help="recompute the result of an earlier recording in DIR (closure.json + capture.bin)")
    add_sim(p, "virtual device with random truth errors: calibrate it, then drive the path on its bench")
    p.add_argument("--path", choices=sorted(PATHS), default="box", help="path the virtual bench drives")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.analysis.strapdown import ClosureError
    from imubench.device.link import Device
    from imubench.procedures.closure import (
        analyse,
        calibrate_virtual,
        load_params,
        run_closure,
    )
    from imubench.results.closure import summarize
    from imubench.wire.params import is_factory

    if a.analyse:
        res = analyse(a.analyse, a.rest, a.g)
        print(summarize(res))
        print(f"results: {a.analyse / 'closure.json'}, plot: {a.analyse / 'closure.png'}")
        return 0
    out = Path(a.out or f"imubench-closure-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    if (out / "capture.bin").exists():
        raise CommandError(f"{out / 'capture.bin'} exists",
                           f"imubench closure --analyse {shlex.quote(str(out))} recomputes it, or choose another --out")
    recording_hint = (lambda: f"the recording in {out} is incomplete; drive the path again with another --out"
                      if (out / "capture.bin").exists() else "nothing was recorded")
    a.on_interrupt = recording_hint
    if a.sim:
        from imubench.device.sim import VirtualBench
        bench = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, truth="random", target=a.target, clock=a.sim_clock, parts=a.sim_parts)
    with bench if a.sim else nullcontext() as vb:
        url = vb.port_url if vb is not None else a.port
        with Device.open(url, baudrate=a.baud, timeout=5.0) as dev:
            if vb is not None:
                a.on_interrupt = (f"the virtual device's calibration in {out / 'session'} was interrupted; "
                                  "run imubench closure --sim again with another --out")
                params = calibrate_virtual(vb, dev, out / "session", a.sim_seed)
            else:
                params = load_params(a.params, dev)
            if is_factory(params):
                raise ClosureError("the calibration to apply is the factory default (it changes nothing); "
                                   "calibrate the device first (imubench calibrate) or give --params FILE")
            a.on_interrupt = recording_hint
            res = run_closure(dev, out, params, vb, a.path, a.rest, a.rate, a.g, a.max_s)
    print(summarize(res))
    print(f"results: {out / 'closure.json'}, plot: {out / 'closure.png'}, raw capture: {out / 'capture.bin'}")
    return 0
