"""`imubench thermal`: sweep over temperature, fit the temperature coefficients, write them back."""
from __future__ import annotations

import argparse
import datetime as _dt
import time
from contextlib import nullcontext
from pathlib import Path

from imubench.cli.common import (
    CommandError,
    UsageError,
    add_port,
    add_sim,
    non_negative_float,
    out_dir,
    positive_float,
)


def _temps(s: str) -> list[float]:
    try:
        temps = [float(x) for x in s.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r}: give temperatures in °C separated by commas, e.g. 10,25,40") from None
    if len(temps) < 2:
        raise argparse.ArgumentTypeError(f"{s!r}: at least two temperatures are needed to fit a slope")
    if len(set(temps)) < 2:
        raise argparse.ArgumentTypeError(f"{s!r}: the temperatures must differ")
    return temps


def register(sub) -> None:
    p = sub.add_parser("thermal", help="fit temperature coefficients over a sweep and write them back",
                       description="Temperature calibration: at each temperature (once the sensors' own "
                                   "temperatures have settled) measure the biases (and with poses and a turntable "
                                   "the scales), fit their temperature coefficients, optionally write them to the "
                                   "device and measure the drift before and after (docs/thermal.md).")
    add_port(p)
    p.add_argument("--temps", type=_temps, default=[10.0, 25.0, 40.0], metavar="C,C,...",
                   help="temperatures in °C, comma separated")
    p.add_argument("--write", action="store_true", help="write the coefficients to the device (set, read back, "
                   "save, reboot, read back) and measure the drift before and after")
    p.add_argument("--out", type=out_dir, metavar="DIR", help="directory for thermal.json, written after every "
                   "temperature point (default: ./imubench-thermal-<time>)")
    p.add_argument("--t-ref", type=float, default=None, help="reference temperature, °C (default: the device's)")
    p.add_argument("--samples", type=int, default=2000, help="samples per measurement (at 200 Hz)")
    p.add_argument("--settle-rate", type=positive_float, default=0.1, metavar="C_PER_MIN",
                   help="settled when every sensor's |dT/dt| is below this, in °C/min")
    p.add_argument("--settle-s", type=non_negative_float, default=None, metavar="S",
                   help="... over a sliding window of this many seconds of device time "
                        "(default: 300; with --sim 10); 0: do not wait")
    p.add_argument("--settle-timeout", type=positive_float, default=7200.0, metavar="S",
                   help="give up waiting for a temperature after this many seconds")
    add_sim(p, "run on a virtual device with temperature coefficients in its truth; its bench drives "
               "temperature, orientation and turntable")
    p.add_argument("--ramp", type=non_negative_float, default=None, metavar="C_PER_S",
                   help="with --sim: the virtual chamber's ramp in °C/s (default 0.5; 0 = at once)")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.analysis.thermal import POSES
    from imubench.device.link import Device
    from imubench.procedures.thermal import (
        SIM_ACCEL_TRUTH,
        SIM_GYRO_TRUTH,
        TEMP_RESOLUTION_C,
        Hooks,
        Settling,
        run_thermal,
        sim_hooks,
    )
    from imubench.results.thermal import ThermalRecord

    if a.ramp is not None and not a.sim:
        raise UsageError("--ramp goes with --sim", "a real chamber ramps by itself")
    ramp = 0.5 if a.ramp is None else a.ramp
    settle_s = (10.0 if a.sim else 300.0) if a.settle_s is None else a.settle_s
    settle = None
    if settle_s > 0:
        try:
            settle = Settling(a.settle_rate, settle_s, a.settle_timeout)
        except ValueError as e:
            raise UsageError(str(e), "--settle-timeout must be at least --settle-s") from None
    if settle is not None and not a.sim and settle.rate_c_per_min / 60.0 * settle.window_s < 2 * TEMP_RESOLUTION_C:
        print(f"note: over {settle.window_s:g} s a drift of {settle.rate_c_per_min:g} °C/min stays within "
              f"{2 * TEMP_RESOLUTION_C:g} °C, about the sensors' temperature resolution: it may pass as settled "
              "(a longer --settle-s sees it)", flush=True)
    out = Path(a.out or f"imubench-thermal-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    if (out / ThermalRecord.NAME).exists():
        raise CommandError(f"{out / ThermalRecord.NAME} exists", "choose another --out directory")
    a.on_interrupt = lambda: (f"what was measured is kept in {out / ThermalRecord.NAME}"
                              if (out / ThermalRecord.NAME).exists() else "nothing was measured")

    def say(s):
        print(s, flush=True)

    if a.sim:
        from imubench.device.sim import VirtualBench
        bench = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, target=a.target)
    with bench if a.sim else nullcontext() as vb:
        if vb is not None:
            vb.set_truth(accel=SIM_ACCEL_TRUTH, gyro=SIM_GYRO_TRUTH)
            url, hooks, poses = vb.port_url, sim_hooks(vb, say, ramp_c_per_s=ramp), tuple(POSES)
        else:
            url, poses = a.port, ("+z",)

            def ready(c):
                input(f"bring the board (still, level, +Z up) to {c:g} °C and press Enter ")
            hooks = Hooks(ready=ready, say=say)
        with Device.open(url, baudrate=a.baud) as dev:
            say(f"sweep over {a.temps} °C ({'virtual bench' if a.sim else 'ambient: you set it'})")
            t0 = time.monotonic()
            try:
                run_thermal(dev, out, a.temps, hooks, n=a.samples, poses=poses, turntable=a.sim,
                            t_ref_c=a.t_ref, write=a.write, settle=settle,
                            config={"sim": a.sim, "ramp_c_per_s": ramp if a.sim else None})
            except EOFError:
                raise CommandError("no answer on standard input (it is closed)",
                                   f"run thermal at a terminal; what was measured is in {out}") from None
            say(f"[{time.monotonic() - t0:.1f} s]")
    return 0
