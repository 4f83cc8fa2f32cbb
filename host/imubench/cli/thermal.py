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
    existing_dir,
    non_negative_float,
    out_dir,
    positive_float,
)
from imubench.results import exports as X
from imubench.results import thermal_export as TX
from imubench.files import make_dir



def _speed(a, realtime_default: float) -> float:
    """--sim-speed, or on the real-time clock this command's pace when none was given."""
    return realtime_default if a.sim_speed is None else a.sim_speed

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
    p.add_argument("--temps", type=_temps, default=None, metavar="C,C,...",
                   help="step method: temperatures in °C, comma separated (default 10,25,40)")
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
               "temperature, orientation and turntable (on the real-time clock --sim-speed 20, 100 with --warmup)", speed=None)
    p.add_argument("--ramp", type=non_negative_float, default=None, metavar="C_PER_S",
                   help="with --sim: the virtual chamber's ramp in °C/s (default 0.5; 0 = at once)")
    w = p.add_argument_group("warm-up method (no chamber: the board warms from cold while it lies still; "
                             "docs/thermal.md)")
    w.add_argument("--warmup", action="store_true", help="calibrate from one warm-up instead of set points")
    w.add_argument("--fit-warmups", nargs="+", type=existing_dir, metavar="DIR",
                   help="fit several warm-ups (DIRs of `thermal --warmup`, e.g. on faces of a cube) together")
    w.add_argument("--span", type=_span, default=None, metavar="LO,HI",
                   help="stop when every sensor has covered LO..HI °C (default: when the temperatures stop rising)")
    w.add_argument("--face", type=_face, default="+z", metavar="±X|±Y|±Z",
                   help="the board face that points up during the warm-up")
    X.add_option(w, "thermal", what="also write (beside thermal.json)")
    w.add_argument("--stop-rate", type=positive_float, default=None, metavar="C_PER_MIN",
                   help="the temperatures have stopped rising when every |dT/dt| is below this (default 0.05; --sim 0.3)")
    w.add_argument("--stop-window", type=positive_float, default=None, metavar="S",
                   help="... over this many seconds of device time (default 300; --sim 30)")
    w.add_argument("--max-time", type=positive_float, default=None, metavar="S",
                   help="give up after this many seconds of device time (default 14400; --sim 3600)")
    w.add_argument("--bin", type=positive_float, default=None, metavar="S", help="bin length, s (default 10; --sim 2)")
    w.add_argument("--cold", type=float, default=5.0, metavar="C", help="with --sim: the virtual fridge, °C")
    w.add_argument("--warm", type=float, default=45.0, metavar="C", help="with --sim: the room it warms in, °C")
    w.add_argument("--tau", type=positive_float, default=None, metavar="S",
                   help="with --sim: the dies' thermal time constant, s (default: the part's own)")
    p.set_defaults(run=run)


def _span(s: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r}: give LO,HI in °C, e.g. 5,45") from None
    if not hi > lo:
        raise argparse.ArgumentTypeError(f"{s!r}: HI must be above LO")
    return lo, hi


def _face(s: str) -> str:
    from imubench.analysis.thermal import POSES
    f = s.strip().lower()
    if f in ("x", "y", "z"):
        f = "+" + f
    if f not in POSES:
        raise argparse.ArgumentTypeError(f"{s!r}: one of +x, -x, +y, -y, +z, -z (the face pointing up)")
    return f


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

    if a.warmup or a.fit_warmups:
        return run_warmup_cmd(a)
    warm_only = [o for o, v in (("--span", a.span), ("--export", a.export), ("--stop-rate", a.stop_rate),
                                ("--stop-window", a.stop_window), ("--max-time", a.max_time), ("--bin", a.bin),
                                ("--tau", a.tau)) if v]
    if warm_only or a.face != "+z":
        raise UsageError(f"{(warm_only or ['--face'])[0]} goes with --warmup", "the step method (--temps) has no such option")
    if a.temps is None:
        a.temps = [10.0, 25.0, 40.0]
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
        bench = VirtualBench(speed=_speed(a, 20.0), seed=a.sim_seed, target=a.target, clock=a.sim_clock,
                             parts=a.sim_parts)
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


def run_warmup_cmd(a) -> int:
    """`imubench thermal --warmup` and `--fit-warmups DIR...` (imubench.procedures.warmup)."""
    from imubench.device.link import Device
    from imubench.procedures import warmup as W
    from imubench.results.thermal_warmup import WarmupRecord

    step = [o for o, v in (("--temps", a.temps), ("--ramp", a.ramp), ("--settle-s", a.settle_s)) if v is not None]
    if a.warmup and a.fit_warmups:
        raise UsageError("--warmup and --fit-warmups are two commands", "record one warm-up, or fit recorded ones")
    if step:
        raise UsageError(f"{step[0]} is an option of the step method, not of the warm-up",
                         "a warm-up has no set points: drop it, or drop --warmup")
    sim_only = [o for o, v in (("--tau", a.tau),) if v is not None]
    if sim_only and not a.sim:
        raise UsageError(f"{sim_only[0]} goes with --sim", "a real board has its own thermal time constants")
    if not a.sim and (a.cold != 5.0 or a.warm != 45.0):
        raise UsageError("--cold/--warm go with --sim", "a real board: cool it (a fridge), then run")
    out = Path(a.out or f"imubench-thermal-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    if (out / WarmupRecord.NAME).exists():
        raise CommandError(f"{out / WarmupRecord.NAME} exists", "choose another --out directory")

    def say(s):
        print(s, flush=True)

    if a.fit_warmups:
        return _fit_warmups(a, out, say)
    sim = a.sim
    try:
        cfg = W.WarmupConfig(span_c=a.span, face=a.face, write=a.write, exports=a.export or (),
                             stop_rate_c_per_min=a.stop_rate or (0.3 if sim else 0.05),
                             stop_window_s=a.stop_window or (30.0 if sim else 300.0),
                             max_s=a.max_time or (3600.0 if sim else 4 * 3600.0), bin_s=a.bin or (2.0 if sim else 10.0),
                             fit_every_s=20.0 if sim else 60.0, rate_hz=100 if sim else 200, t_ref_c=a.t_ref)
    except ValueError as e:
        raise UsageError(str(e), "see imubench thermal --help") from None
    a.on_interrupt = lambda: (f"the fit of what came is in {out / WarmupRecord.NAME}"
                              if (out / WarmupRecord.NAME).exists() else "nothing was recorded")
    if sim:
        from imubench.device.sim import VirtualBench
        # a warm-up lasts tens of minutes of device time: the virtual part runs it faster
        bench = VirtualBench(speed=_speed(a, 100.0), seed=a.sim_seed, target=a.target, clock=a.sim_clock, truth="random",
                             parts=a.sim_parts)
    with bench if sim else nullcontext() as vb:
        if vb is not None:
            tau = None if a.tau is None else [a.tau] * 4
            hooks = W.sim_warmup_hooks(vb, a.cold, a.warm, tau_s=tau, say=say)
            url = vb.port_url
        else:
            url = a.port

            def ready(text):
                input(f"{text}; press Enter to start ")
            hooks = W.WarmupHooks(ready=ready, say=say)
        with Device.open(url, baudrate=a.baud) as dev:
            t0 = time.monotonic()
            try:
                extra = {"sim": sim, "target": a.target if sim else None, "sim_seed": a.sim_seed if sim else None,
                         "sim_tau_s": a.tau if sim else None, "sim_cold_c": a.cold if sim else None,
                         "sim_warm_c": a.warm if sim else None}
                d = W.run_warmup(dev, out, cfg, hooks, config_extra=extra)
            except W.WarmupError as e:
                raise CommandError(str(e), "give a --span the board can cover, or none (until it stops warming)") from None
            except EOFError:
                raise CommandError("no answer on standard input (it is closed)",
                                   "run the warm-up at a terminal") from None
            say(f"[{time.monotonic() - t0:.1f} s]")
    if d["status"] == "interrupted":
        say(f"interrupted: the fit of what came is in {out / WarmupRecord.NAME}")
        return 130
    if d["status"] != "done":
        raise CommandError(f"warm-up {d['status']}: {d.get('error')}", f"what came is in {out}")
    return 0


def _fit_warmups(a, out: Path, say) -> int:
    from imubench.procedures import warmup as W
    from imubench.procedures import warmup_files as WF
    from imubench.results.atomic import write_json_atomic
    from imubench.results.record import now_utc
    from imubench.results.thermal_warmup import fit_json, format_fit
    from imubench.wire.board_parts import BoardParts
    if a.sim:
        raise UsageError("--fit-warmups fits recorded warm-ups", "drop --sim (give --port URL --write to write the fit)")
    if a.write and not a.port:
        raise UsageError("--write needs the device: give --port URL", "the fit is written to the board it came from")
    try:
        fits, t_ref, runs = WF.fit_warmups(a.fit_warmups, t_ref_c=a.t_ref)
    except W.WarmupError as e:
        raise CommandError(str(e), "give directories written by imubench thermal --warmup") from None
    parts = BoardParts.of_device(runs[0].get("device"))      # the board's parts, as it reported them
    fj = fit_json(fits, t_ref, parts)
    say(f"{len(runs)} warm-ups on faces {', '.join((r.get('config') or {}).get('face', '?') for r in runs)}")
    say(format_fit(fj))
    make_dir(out)
    data = {"schema": 1, "kind": "imubench thermal warmups", "created": now_utc(),
            "sources": [str(x) for x in a.fit_warmups], "faces": [(r.get("config") or {}).get("face") for r in runs],
            "device": runs[0].get("device"), "t_ref_c": t_ref, "fit": fj, "exports": {}}
    if a.export:
        segs = [WF.load_warmup(x)[:2] for x in a.fit_warmups]
        files = TX.write_exports(out, W.export_fits(segs, t_ref, fits, parts=parts), t_ref, a.export,
                                 comment=f"imubench warm-ups {', '.join(data['faces'])}", parts=parts)
        data["exports"] = {k: [str(p) for p in v] for k, v in files.items()}
        for k, v in files.items():
            say(f"{k}: {', '.join(str(p) for p in v)}")
    write_json_atomic(out / "thermal.json", data)
    if a.write:
        from imubench.device.link import Device
        from imubench.procedures.writeback import write_verified
        from imubench.wire import params as PR
        from imubench.wire.ids import device_identity
        from imubench.wire.protocol_gen import ParamsWhich
        with Device.open(a.port, baudrate=a.baud) as dev:
            uid = device_identity(dev.info())["mcu_uid"]
            if data["device"] and data["device"].get("mcu_uid") != uid:
                raise CommandError(f"the device on {a.port} ({uid}) is not the one warmed up "
                                   f"({data['device'].get('mcu_uid')})", "connect the board the warm-ups came from")
            old = dev.get_params(ParamsWhich.ACTIVE).params
            try:
                new, notes = W.params_from_warmup(old, fits, t_ref)
            except W.WarmupError as e:
                raise CommandError(str(e), "nothing was written") from None
            for n in notes:
                say(f"note: {n}")
            wb = write_verified(dev, new, previous=old, say=say)
            data["write"] = {"generation": int(wb["generation"]), "steps": list(wb["steps"]), "notes": notes,
                             "params": PR.to_json(new), "verified": True}
            say(f"written: {', '.join(wb['steps'])}")
        write_json_atomic(out / "thermal.json", data)
    say(f"saved {out / 'thermal.json'}")
    return 0
