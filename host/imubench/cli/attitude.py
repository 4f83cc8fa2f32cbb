"""`imubench attitude`: roll and pitch from the device's calibrated output through three filters,
live (until Ctrl-C or --duration), or as the turntable step test on the virtual bench (--steps)."""
from __future__ import annotations

import csv
import sys
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from imubench.cli.common import (
    UsageError,
    add_port,
    add_sim,
    new_file,
    positive_float,
    stream_rate,
)


def register(sub) -> None:
    p = sub.add_parser("attitude", help="live pitch/roll through RC, Kalman and complementary filters",
                       description="Roll/pitch (deg) from the device's calibrated output; "
                                   "roll = atan2(fy, fz), pitch = atan2(-fx, hypot(fy, fz)), positive pitch = "
                                   "nose down (docs/attitude.md). Live until Ctrl-C or --duration; with --sim "
                                   "--steps, the step test on the virtual turntable.")
    add_port(p)
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=200, help="sample rate in Hz")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds of data to take, in device time (default: until Ctrl-C)")
    p.add_argument("--filter", choices=("rc", "kalman", "complementary", "all"), default="all",
                   help="which tilt filter(s) to run")
    p.add_argument("--num", type=positive_float, default=20, help="RC low-pass constant num in y += (x - y)/num")
    p.add_argument("--tau", type=positive_float, default=0.5, help="complementary filter time constant, s")
    p.add_argument("--record", type=new_file, metavar="FILE",
                   help="append the received bytes to FILE and write the angles to FILE.angles.csv (or --csv)")
    p.add_argument("--csv", type=new_file, metavar="FILE", help="write the angles to this CSV")
    p.add_argument("--plot", type=new_file, metavar="PNG",
                   help="draw the angles to this PNG and write their numbers beside it (PNG with .json): "
                        "what imubench report --attitude embeds")
    p.add_argument("--print-hz", type=positive_float, default=4.0, help="live lines per second")
    add_sim(p, "run on a virtual device with ideal parts (its calibrated output is exact)", lockstep_speed=20.0)
    p.add_argument("--steps", action="store_true",
                   help="with --sim: step the virtual turntable -20..+20 deg about X and Y and measure each "
                        "filter's settling time and static error")
    p.set_defaults(run=run)


def _json_path(png: Path) -> Path:
    return png.with_suffix(".json")


def run(a) -> int:
    from imubench.device.link import Device
    if a.steps and not a.sim:
        raise UsageError("--steps needs --sim", "a real board has no turntable imubench can drive")
    if a.sim:
        from imubench.device.sim import VirtualBench
        bench = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, target=a.target, clock=a.sim_clock, parts=a.sim_parts)
    with bench if a.sim else nullcontext() as vb:
        url = vb.port_url if vb is not None else a.port
        with Device.open(url, baudrate=a.baud, capture=None) as dev:
            device = _device(dev)
            if a.steps:
                return _steps(a, vb, dev, device)
            return _live(a, dev, device)


def _device(dev) -> dict:
    from imubench.wire.ids import uid_text
    from imubench.wire.params import is_factory
    from imubench.wire.protocol_gen import ParamsWhich
    info = dev.info()
    factory = is_factory(dev.get_params(ParamsWhich.ACTIVE).params)
    return {"mcu_uid": uid_text(info.mcu_uid), "fw_build": info.fw_build, "factory_parameters": factory}


def _steps(a, vb, dev, device: dict) -> int:
    from imubench.procedures.attitude import tilt_step_experiment
    from imubench.results.atomic import write_json_atomic
    from imubench.results.attitude import plot_steps, steps_json, summarize
    print("step test on the virtual turntable: -20, -10, 0, +10, +20 deg about X (roll) and Y (pitch)", flush=True)
    res = tilt_step_experiment(vb, dev, rate_hz=a.rate)
    print(summarize(res))
    if a.plot:
        plot_steps(res, a.plot)
        write_json_atomic(_json_path(a.plot), {"schema": 1, "kind": "imubench attitude", "device": device,
                                               **steps_json(res)})
        print(f"plot: {a.plot}, numbers: {_json_path(a.plot)}")
    return 0


def _live(a, dev, device: dict) -> int:
    from imubench.analysis.tilt import accel_tilt, make_filters
    from imubench.files import open_growing
    from imubench.procedures.attitude import live
    from imubench.wire.board_parts import BoardParts
    filters = make_filters(a.filter, a.num, a.tau, BoardParts.of_info(dev.info()))   # tuned to its parts
    csv_path = a.csv or (f"{a.record}.angles.csv" if a.record else None)
    if device["factory_parameters"]:
        print("warning: this device has factory parameters: its \"calibrated\" output is the raw data at "
              "nominal scale (calibrate it first: imubench calibrate)", file=sys.stderr, flush=True)
    keep = a.plot is not None
    t_all, ang_all = [], {name: ([], []) for name in ["accel"] + [f.name for f in filters]}
    n_total, t_s = 0, 0.0
    with open_growing(a.record, buffering=0) if a.record else nullcontext() as capture, \
            open_growing(csv_path, append=False, binary=False, newline="") if csv_path else nullcontext() as csv_file:
        writer = None
        if csv_path:
            writer = csv.writer(csv_file)
            writer.writerow(["t_s", "accel_roll_deg", "accel_pitch_deg"]
                            + [f"{f.name}_{c}_deg" for f in filters for c in ("roll", "pitch")])
        if capture is not None:
            dev.link.capture = capture
        print("   t (s)  " + "  ".join(f"{f.name:>10} roll/pitch (deg)" for f in filters), flush=True)
        next_print = 0.0                  # device seconds: the same lines on any machine
        try:
            for block, t, res in live(dev, filters, a.rate, a.duration):
                n_total += len(block)
                t_s = float(t[-1])
                ar, ap_ = accel_tilt(block.accel_mps2.astype(np.float64))
                if writer is not None:
                    writer.writerows(np.column_stack([t, ar, ap_] + [c for r in res for c in r]).round(6).tolist())
                if keep:
                    t_all.append(t)
                    for name, (r_, p_) in zip(ang_all, [(ar, ap_)] + list(res)):
                        ang_all[name][0].append(np.asarray(r_))
                        ang_all[name][1].append(np.asarray(p_))
                if t_s >= next_print:
                    next_print = t_s + 1.0 / a.print_hz
                    print(f"{t_s:8.2f}  " + "  ".join(f"{f.name:>10} {r[0][-1]:+8.3f} {r[1][-1]:+8.3f}"
                                                     for f, r in zip(filters, res)), flush=True)
        except KeyboardInterrupt:
            pass                          # Ctrl-C is how a live view ends
        finally:
            dev.link.capture = None
    print(f"{n_total} samples over {t_s:.1f} s" + (f"; angles in {csv_path}" if csv_path else ""), file=sys.stderr)
    if keep and t_all:
        from imubench.results.atomic import write_json_atomic
        from imubench.results.attitude import live_json, plot_live
        t = np.concatenate(t_all)
        angles = {k: (np.concatenate(v[0]), np.concatenate(v[1])) for k, v in ang_all.items()}
        plot_live(t, angles, a.plot, "roll and pitch from the device's calibrated output"
                  + (" (FACTORY parameters: uncalibrated)" if device["factory_parameters"] else ""))
        write_json_atomic(_json_path(a.plot), {"schema": 1, "kind": "imubench attitude", "device": device,
                                               "rate_hz": a.rate, **live_json(t, angles)})
        print(f"plot: {a.plot}, numbers: {_json_path(a.plot)}", file=sys.stderr)
    return 0
