"""`imubench calibrate`: the guided calibration session, write-back, verification, history."""
from __future__ import annotations

import datetime as _dt
import sys
from contextlib import nullcontext
from pathlib import Path

from imubench.cli.common import (
    CommandError,
    UsageError,
    add_port,
    add_sim,
    existing_dir,
    out_dir,
    positive_float,
    stream_rate,
)
from imubench.cli.station import add_web

METHODS = ("multi", "six")
CAPTURES = ("adaptive", "plan")
SIX_WARNING = ("warning: --method six needs a square fixture (a machined cube against a square): held by hand the "
               "faces are degrees off square and the fit fails; --method multi needs none")
GYRO_METHODS = ("turntable", "rotation", "bias", "none")


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="guided calibration session, write-back and verification",
                       description="Guided calibration session: capture the attitudes (and turns), fit, write "
                                   "the parameters to the device, read them back, save, reboot, verify the "
                                   "device's own output and record the run in the history (docs/calibration.md). "
                                   "Everything captured is on disk as it arrives: --resume DIR continues.")
    add_port(p)
    p.add_argument("--method", choices=METHODS, default="multi",
                   help="accelerometer model: the multi-position |a| = g fit (any attitudes, by hand) or six faces "
                        "(linear least squares, full M; needs a square fixture)")
    p.add_argument("--capture", choices=CAPTURES, default="adaptive",
                   help="adaptive: hold each attitude until its |a| is known, stop when every parameter's sigma is "
                        "at its target (docs/calibration.md); plan: every planned attitude, --hold seconds each")
    p.add_argument("--pose-timeout", type=positive_float, default=None, metavar="S",
                   help="give up when no planned attitude is held still within S seconds (default: wait)")
    p.add_argument("--ui", choices=("terminal", "web"), default="terminal",
                   help="terminal prompts, or the station page in the browser (imubench station)")
    add_web(p)
    p.add_argument("--gyro", choices=GYRO_METHODS, default="bias",
                   help="gyro method: scale and misalignment from a turntable or from the rotations between "
                        "attitudes, only the bias at rest, or none")
    p.add_argument("--dir", type=out_dir, metavar="DIR",
                   help="session directory (default: ./imubench-session-<time>)")
    p.add_argument("--resume", type=existing_dir, metavar="DIR", help="continue the session in DIR")
    p.add_argument("--redo", action="append", default=[], metavar="POSE",
                   help="with --resume: capture this pose again (repeatable; names as printed)")
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=500, help="sample rate in Hz")
    p.add_argument("--hold", type=positive_float, default=2.0, metavar="S", help="seconds captured per attitude")
    p.add_argument("--no-write", action="store_true", help="fit only; do not write the parameters to the device")
    p.add_argument("--db", metavar="PATH", help="history database (default: in the user data directory)")
    p.add_argument("--note", default="", help="a note kept with the run in the history")
    add_sim(p, "run on a virtual device (random truth errors) whose bench presents the attitudes")
    p.add_argument("--sim-tilt", type=float, default=0.0, metavar="DEG",
                   help="with --sim: misalign each virtual attitude by this many degrees")
    p.add_argument("--closure", action="store_true",
                   help="after a verified write-back, run the closure check (imubench closure) into DIR/closure: "
                        "the virtual bench drives a closed path, or you carry the board around one")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.device.link import Device
    from imubench.procedures.session import SessionConfig, SimPresenter, run_session

    if a.redo and not a.resume:
        raise UsageError("--redo goes with --resume DIR", "give the session directory to continue")
    if a.resume and a.dir:
        raise UsageError("--dir and --resume exclude each other", "--resume DIR continues the session in DIR")
    if a.db and Path(a.db).is_dir():
        raise UsageError(f"--db {a.db} is a directory", f"give the database file, e.g. {Path(a.db) / 'history.sqlite'}")
    if a.resume:
        from imubench.results.sessionfile import load_state
        load_state(a.resume)            # a damaged or foreign session.json is named before a device is opened
    cfg = SessionConfig(method=a.method, gyro=None if a.gyro == "none" else a.gyro, rate_hz=a.rate,
                        hold_s=a.hold, write=not a.no_write, note=a.note, adaptive=a.capture == "adaptive",
                        pose_timeout_s=a.pose_timeout)
    if a.method == "six" and not a.resume:
        print(SIX_WARNING)
    directory = Path(a.resume or a.dir or f"imubench-session-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    a.on_interrupt = lambda: (f"everything captured is kept in {directory}; continue with: "
                              f"imubench calibrate --resume {directory}" + (" --sim" if a.sim else "")
                              if (directory / "session.json").exists() else "nothing was captured")
    if a.ui == "web":
        if a.redo or a.closure:
            raise UsageError(f"{'--redo' if a.redo else '--closure'} is a terminal option",
                             "run it without --ui web (the page resumes a session with its Resume button)")
        return _run_web(a, cfg, directory)
    if a.sim:
        from imubench.device.sim import VirtualBench
        bench = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, truth="random")
    with bench if a.sim else nullcontext() as vb:
        if vb is not None:
            url = vb.port_url
            ui = SimPresenter(vb, tilt_deg=a.sim_tilt, seed=a.sim_seed)
            print(f"virtual device with random truth (seed {a.sim_seed}) on {url}")
        else:
            from imubench.cli.terminal import HumanPresenter
            url, ui = a.port, HumanPresenter()
        with Device.open(url, baudrate=a.baud, timeout=5.0) as dev:
            result, sess = run_session(dev, directory, cfg, ui, resume=bool(a.resume), redo=a.redo,
                                       on_start=lambda s: print(f"session directory: {s.dir} (raw captures and "
                                                                f"state; --resume {s.dir} continues it)"),
                                       report=_print_fit(vb))
            if a.closure and result["written"] and "closure" not in result:
                result["closure"] = _closure_after_session(dev, vb, sess.dir / "closure")
                sess.finish(result)
    _record_history(result, a.db, sess.state_path)
    ok = result["passed"] and (result["verified"] or not cfg.write)
    print("\ncalibration " + ("PASSED" if ok else "FAILED"))
    if not ok:
        raise CommandError("the calibration did not pass" + ("" if result["passed"] else " its tolerance")
                           + ("" if result["passed"] or not cfg.write else "; nothing was written to the device")
                           + (" (verification failed; the previous parameters were restored)"
                              if result["passed"] and cfg.write and not result["verified"] else ""),
                           f"see the tables above and {directory / 'residuals.png'}")
    return 0


def _run_web(a, cfg, directory: Path) -> int:
    """The session on the station page: served until Ctrl-C, so that a failed or stopped
    session can be resumed there; the exit code is the last session's verdict."""
    from imubench.cli.station import serve_forever
    from imubench.station.runner import SIM_KEY, Station
    from imubench.station.server import Server
    station = Station(workdir=directory.parent, db=a.db, sim_speed=a.sim_speed, sim_seed=a.sim_seed,
                      allow_sim=a.sim, person={"offset_deg": (a.sim_tilt, a.sim_tilt)} if a.sim_tilt else None)
    station.state.mode = "session"
    key = SIM_KEY if a.sim else a.port
    if not key:
        raise UsageError("no device: give --port URL (or set IMUBENCH_PORT), or --sim")
    options = {"port": key, "method": cfg.method, "gyro": a.gyro, "capture": a.capture, "write": cfg.write,
               "note": cfg.note, "rate_hz": cfg.rate_hz}
    reported = []

    def ended() -> bool:
        b = station.state.boards.get(key)
        if b is not None and b.status in ("done", "failed", "interrupted") and not station.running(key) \
                and reported[-1:] != [id(b.result) if b.result else b.error]:
            reported.append(id(b.result) if b.result else b.error)
            if b.result:
                print(f"calibration {'PASSED' if b.result['status'] == 'pass' else 'FAILED'}: {b.result['verdict']}\n"
                      f"report: {b.result['report_path']}  (the page stays up until Ctrl-C)", flush=True)
            else:
                print(f"session {b.status}: {b.error} (resume it on the page, or Ctrl-C)", flush=True)
        return False

    try:
        server = Server(station, port=a.http_port)
        station.start(options, None, directory=directory, resume=bool(a.resume))
        serve_forever(server, a.open, until=ended)
    except KeyboardInterrupt:
        pass
    except OSError as e:
        raise CommandError(f"cannot serve on 127.0.0.1:{a.http_port}: {e.strerror or e}",
                           "give another --http-port, or 0 for any free port") from None
    finally:
        station.close()
    b = station.state.boards.get(key)
    if b is None or not b.result or b.result["status"] != "pass":
        raise CommandError("the calibration did not pass" if b is not None and b.result else
                           "the session did not finish", f"everything captured is kept in {directory}; "
                           f"continue with: imubench calibrate --resume {directory} --ui web")
    return 0


def _print_fit(vb):
    """What the session prints once the fit is known (and, on a virtual device, the truth)."""
    def report(result: dict) -> None:
        from imubench.results.calibration import (
            before_after_table,
            params_table,
            truth_table,
        )
        print()
        print(params_table(result))
        print()
        print(before_after_table(result))
        if vb is not None:
            print("\nrecovered beside the virtual device's truth:")
            print(truth_table(result, vb.get_truth()))
    return report


def _closure_after_session(dev, vb, out: Path) -> dict:
    """The closure check with the parameters just written (imubench.procedures.closure): a
    summary for the session's result; the details are in out."""
    from imubench.analysis.strapdown import ClosureError
    from imubench.procedures.closure import run_closure
    from imubench.results.closure import summarize
    from imubench.wire.protocol_gen import ParamsWhich
    print("\nclosure check: integrating a closed path before and after calibration")
    try:
        res = run_closure(dev, out, dev.get_params(ParamsWhich.ACTIVE).params, vb, "box")
    except ClosureError as e:           # the calibration stands; say why there is no figure
        print(f"closure check not possible: {e}", file=sys.stderr)
        return {"error": str(e)}
    print(summarize(res))
    print(f"closure details: {out / 'closure.json'}, plot {out / 'closure.png'}")
    return {"dir": str(out), "before_m": res["before"].distance_m, "after_m": res["after"].distance_m,
            "after_rest_bias_m": res["after_rest_bias"].distance_m,
            "noise_floor_m": res["noise_floor"]["sigma_distance_m"]}


def _record_history(result: dict, db, state_path: Path) -> None:
    from imubench.results.history import History
    try:
        with History(db) as h:
            run_id, new = h.record_once(result)
        print(f"recorded in the history as run {run_id}" if new else
              f"already recorded in the history as run {run_id} (the same run: not recorded twice)")
    except Exception as e:  # noqa: BLE001 - the result is safe in session.json; say why it is not in the history
        print(f"warning: not recorded in the history ({e}); the result is in {state_path}", file=sys.stderr)

