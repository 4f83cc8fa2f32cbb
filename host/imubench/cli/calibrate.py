"""`imubench calibrate`: the guided calibration session, write-back, verification, history."""
from __future__ import annotations

import argparse
import datetime as _dt
import shlex
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
    resolve_sim_speed,
    speed_text,
    stream_rate,
)
from imubench.cli.calibrate_station import (
    PLATE_TIMEOUT_HAND_S,
    PLATE_TIMEOUT_VIRTUAL_S,
    SIM_SPEED,
    _inject_sim_fault,
    _run_station,
    _sim_fault,
    _station_session,
    write_exports,
)
from imubench.calib.fit import accel_method_names, gyro_method_names
# --from FILE (its options are also allan --from's: add_reader_options, read_recording_args) and what follows a fit
from imubench.cli.calibrate_file import (  # noqa: F401 - FORMATS, memory_budget, px4_device_id: named here too
    _FILE_ONLY,
    FORMATS,
    _add_from_file,
    _run_from_file,
    add_reader_options,
    memory_budget,
    px4_device_id,
    read_recording_args,
)
from imubench.cli.calibrate_result import (
    _add_station_fields,
    _check_history,
    _closure_after_session,
    _params_or_none,
    _print_fit,
    _record_history,
)
from imubench.cli.station import add_web
from imubench.results import exports as X
from imubench.results.record import verdict

METHODS = accel_method_names(live=True)     # calib.fit.ACCEL_METHOD_LIST: the accelerometer methods of a session
CAPTURES = ("adaptive", "plan")
SIX_WARNING = ("warning: --method six needs a square fixture (a machined cube against a square): held by hand the "
               "faces are degrees off square and the fit fails; --method multi needs none")
GYRO_METHODS = gyro_method_names()          # calib.fit.GYRO_METHODS: the one list of gyro methods
WRITERS = X.names("calibration")


def rate_hz(s: str) -> float:
    """calibrate's --rate: a positive number here; a protocol stream rate (common.stream_rate)
    when a device is calibrated, any rate when it is a file's (--from) — checked in run()."""
    return positive_float(s)


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="guided calibration session, write-back and verification",
                       description="Guided calibration session: capture the attitudes (and turns), fit, write "
                                   "the parameters to the device, read them back, save, reboot, verify the "
                                   "device's own output and record the run in the history (docs/calibration.md). "
                                   "Everything captured is on disk as it arrives: --resume DIR continues.")
    add_port(p, many=True)
    p.add_argument("--method", choices=METHODS, default=None,
                   help="accelerometer model: the multi-position |a| = g fit (any attitudes, by hand; the default) or "
                        "six faces (linear least squares, full M; needs a square fixture); with --from the default "
                        "is multi when the recording's attitudes constrain it, else six")
    p.add_argument("--capture", choices=CAPTURES, default="adaptive",
                   help="adaptive: hold each attitude until its |a| is known, stop when every parameter's sigma is "
                        "at its target (docs/calibration.md); plan: every planned attitude, --hold seconds each")
    p.add_argument("--pose-timeout", type=positive_float, default=None, metavar="S",
                   help="give up when no planned attitude is held still within S seconds (default: wait)")
    p.add_argument("--ui", choices=("terminal", "web"), default="terminal",
                   help="terminal prompts, or the station page in the browser (imubench station)")
    add_web(p)
    p.add_argument("--gyro", choices=GYRO_METHODS, default=None,
                   help="gyro method: scale and misalignment from a turntable, from the rotations between "
                        "attitudes, or from known-angle turns by hand (one full turn on a table about X, Y and Z "
                        "pointing up); only the bias at rest, or none. Default: bias for a device; with --from, "
                        "auto (known-angle turns and/or the rotation method, whatever the recording supports; "
                        "the bias at rest when neither can be used, and the output says why)")
    p.add_argument("--dir", type=out_dir, metavar="DIR",
                   help="session directory (default: ./imubench-session-<time>)")
    p.add_argument("--resume", type=existing_dir, metavar="DIR", help="continue the session in DIR")
    p.add_argument("--redo", action="append", default=[], metavar="POSE",
                   help="with --resume: capture this pose again (repeatable; names as printed)")
    p.add_argument("--rate", type=rate_hz, metavar="HZ", default=None,
                   help="sample rate in Hz: the device's stream rate (default 500), or with --from the file's "
                        "rate when it has no time column")
    p.add_argument("--hold", type=positive_float, default=2.0, metavar="S", help="seconds captured per attitude")
    p.add_argument("--no-write", action="store_true", help="fit only; do not write the parameters to the device")
    p.add_argument("--db", metavar="PATH|URL", help="history database: an SQLite file or a postgresql:// URL shared by "
                                                     "several stations (default: $IMUBENCH_DB, else a file in the user "
                                                     "data directory)")
    p.add_argument("--note", default="", help="a note kept with the run in the history")
    add_sim(p, "run on a virtual device (random truth errors) whose bench presents the attitudes")
    p.add_argument("--sim-tilt", type=float, default=0.0, metavar="DEG",
                   help="with --sim: misalign each virtual attitude by this many degrees")
    p.add_argument("--closure", action="store_true",
                   help="after a verified write-back, run the closure check (imubench closure) into DIR/closure: "
                        "the virtual bench drives a closed path, or you carry the board around one")
    p.add_argument("--sim-boards", type=_board_count, default=1, metavar="N",
                   help="with --sim: N virtual devices on one virtual fixture (each its own random truth and serial "
                        "numbers, seeds --sim-seed, --sim-seed + 1, ...): one station session")
    p.add_argument("--sim-fault", type=_sim_fault, action="append", default=[], metavar="K:SENSOR",
                   help="with --sim: virtual board K's SENSOR (accel, gyro_x, gyro_y, gyro_z) is faulted from the start "
                        "(a gyro reports its fault bits; the accelerometer goes missing: its data stop updating, which the "
                        "device reports as 'accel stale'), to see a failing board")
    p.add_argument("--station-file", type=_station_file, metavar="FILE",
                   help="a TOML file describing this station: station, operator, fixture, db and ports = [URL, ...] "
                        "(the boards on its fixture); options given on the command line win (docs/production.md)")
    p.add_argument("--station", metavar="ID", help="station id kept with every record (default: the host name)")
    p.add_argument("--operator", metavar="NAME", default="", help="who runs the station, kept with every record")
    p.add_argument("--fixture", metavar="NAME", default="", help="the fixture (plate, turntable) in use, kept with "
                                                                 "every record")
    p.add_argument("--link-timeout", type=positive_float, default=10.0, metavar="S",
                   help="with several boards: a board that sends nothing for S seconds has lost its link and "
                        "is marked failed (the others go on)")
    p.add_argument("--plate-timeout", type=positive_float, default=None, metavar="S",
                   help="with several boards: a board waits at most S seconds of device time for the plate to "
                        "present what it needs (the other boards' attitudes come first), else it fails and the "
                        f"others go on (default {PLATE_TIMEOUT_VIRTUAL_S:g} on the virtual bench, "
                        f"{PLATE_TIMEOUT_HAND_S:g} when a person moves the plate)")
    _add_from_file(p)
    p.set_defaults(run=run)


def _board_count(s: str) -> int:
    try:
        n = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number of boards") from None
    if not 1 <= n <= 64:
        raise argparse.ArgumentTypeError(f"{n} boards: give 1 to 64")
    return n


STATION_KEYS = {"station", "operator", "fixture", "db", "ports", "baud"}


def _station_file(s: str) -> dict:
    """A station file (TOML), checked for what it holds before anything is opened."""

    from imubench.errors import ImubenchError
    from imubench.files import read_text
    try:
        import tomllib
    except ImportError:                     # Python 3.10
        import tomli as tomllib
    path = Path(s)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{s} is not a file")
    try:
        d = tomllib.loads(read_text(path, what="the station file"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, ImubenchError) as e:
        raise argparse.ArgumentTypeError(f"{s} is not a TOML station file: {e}") from None
    unknown = set(d) - STATION_KEYS
    if unknown:
        raise argparse.ArgumentTypeError(f"{s}: unknown key{'s' if len(unknown) > 1 else ''} "
                                         f"{', '.join(sorted(unknown))} (known: {', '.join(sorted(STATION_KEYS))})")
    ports = d.get("ports", [])
    if not (isinstance(ports, list) and all(isinstance(x, str) and x for x in ports)):
        raise argparse.ArgumentTypeError(f"{s}: ports must be a list of port URLs, e.g. ports = [\"/dev/ttyUSB0\"]")
    if len(set(ports)) != len(ports):
        raise argparse.ArgumentTypeError(f"{s}: a port is listed twice: one board per port")
    for k in ("station", "operator", "fixture", "db"):
        if k in d and not isinstance(d[k], str):
            raise argparse.ArgumentTypeError(f"{s}: {k} must be text")
    return d


def run(a) -> int:
    resolve_sim_speed(a)              # `imubench demo` parses with calibrate's own parser
    if a.sim and getattr(a, "ui", None) == "web" and not a.sim_speed_given and not a.sim_speed:
        a.sim_speed = SIM_SPEED       # the station page: a ceiling a person can follow
    if a.db and Path(a.db).is_dir():
        raise UsageError(f"--db {a.db} is a directory", f"give the database file, e.g. {Path(a.db) / 'history.sqlite'}")
    _check_history(a.db or (a.station_file or {}).get("db"))
    if a.from_file is not None:
        return _run_from_file(a)
    stray = [k for k in _FILE_ONLY if getattr(a, k, None) is not None]
    if stray:
        raise UsageError(f"--{stray[0].replace('_', '-')} goes with --from FILE",
                         "drop it to calibrate a device, or give the recording with --from")
    if a.gyro is None:
        a.gyro = "bias"
    if a.gyro == "auto":
        raise UsageError("--gyro auto is for recordings (--from FILE)",
                         "a session needs its gyro method chosen: rotation, turns, turntable or bias")
    from imubench.procedures.poses import plan_problem
    problem = plan_problem(a.method or "multi", a.gyro)
    if problem and not a.resume:
        raise UsageError(problem[0], problem[1] + "; nothing was captured")
    if a.rate is None:
        a.rate = 500
    try:
        a.rate = stream_rate(f"{a.rate:g}")
    except Exception as e:  # argparse.ArgumentTypeError: the one-line usage error
        raise UsageError(f"--rate {a.rate:g}: {e}", "the device streams at the protocol's rates") from None
    from imubench.device.link import Device
    from imubench.procedures.session import SessionConfig, SimPresenter, run_session

    if a.sim_fault and not a.sim:
        raise UsageError("--sim-fault goes with --sim", "it faults a sensor of a virtual board")
    if a.redo and not a.resume:
        raise UsageError("--redo goes with --resume DIR", "give the session directory to continue")
    if a.resume and a.dir:
        raise UsageError("--dir and --resume exclude each other", "--resume DIR continues the session in DIR")
    if a.plate_timeout is not None and not _station_session(a):
        raise UsageError("--plate-timeout goes with several boards on one fixture",
                         "give --port once per board (or --sim --sim-boards N), or drop it")
    if a.resume and not _station_session(a):
        from imubench.results.sessionfile import load_state
        load_state(a.resume)            # a damaged or foreign session.json is named before a device is opened
    cfg = SessionConfig(method=a.method or "multi", gyro=None if a.gyro == "none" else a.gyro, rate_hz=a.rate,
                        hold_s=a.hold, write=not a.no_write, note=a.note, adaptive=a.capture == "adaptive",
                        pose_timeout_s=a.pose_timeout)
    if a.method == "six" and not a.resume:
        print(SIX_WARNING)
    if _station_session(a):
        return _run_station(a, cfg)
    directory = Path(a.resume or a.dir or f"imubench-session-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    a.on_interrupt = lambda: (f"everything captured is kept in {directory}; continue with: "
                              f"imubench calibrate --resume {shlex.quote(str(directory))}" + (" --sim" if a.sim else "")
                              if (directory / "session.json").exists() else "nothing was captured")
    if a.ui == "web":
        if a.export:
            print("note: --ui web: the page offers every export format of a calibration that passed as a download "
                  f"(the files go to {directory}/exports); --export writes them from the terminal session")
        if a.redo or a.closure:
            raise UsageError(f"{'--redo' if a.redo else '--closure'} is a terminal option",
                             "run it without --ui web (the page resumes a session with its Resume button)")
        return _run_web(a, cfg, directory)
    if a.sim:
        from imubench.device.sim import VirtualBench
        bench = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, truth="random", target=a.target, clock=a.sim_clock, parts=a.sim_parts)
    with bench if a.sim else nullcontext() as vb:
        if vb is not None:
            for slot, sensor in a.sim_fault:
                if slot != 1:
                    raise UsageError(f"--sim-fault {slot}:{sensor}: there is one virtual board",
                                     "give 1:SENSOR, or --sim-boards N for several")
                _inject_sim_fault(vb, sensor)
            url = vb.port_url
            ui = SimPresenter(vb, tilt_deg=a.sim_tilt, seed=a.sim_seed)
            print(f"virtual device with random truth (seed {a.sim_seed}) on {url}, {speed_text(a.sim_speed, a.sim_clock)}")
        else:
            from imubench.cli.terminal import HumanPresenter
            url, ui = a.port, HumanPresenter()
        with Device.open(url, baudrate=a.baud, timeout=5.0) as dev:
            params_before = _params_or_none(dev)        # for the record: the block before anything is written
            result, sess = run_session(dev, directory, cfg, ui, resume=bool(a.resume), redo=a.redo,
                                       on_start=lambda s: print(f"session directory: {s.dir} (raw captures and "
                                                                f"state; --resume {shlex.quote(str(s.dir))} continues it)"),
                                       report=_print_fit(vb))
            if a.closure and result["written"] and "closure" not in result:
                result["closure"] = _closure_after_session(dev, vb, sess.dir / "closure")
                sess.finish(result)
            if "station" not in result:     # a run finished before (resumed) keeps what it recorded
                _add_station_fields(result, a, sess.dir, params_before, _params_or_none(dev), url)
                sess.finish(result)
    _record_history(result, a.db or (getattr(a, "station_file", None) or {}).get("db"), sess.state_path)
    ok, _ = verdict(result, cfg.write)
    write_exports(a, result, sess.dir, (result.get("device") or {}).get("mcu_uid") or "device", ok)
    print("\ncalibration " + ("PASSED" if ok else "FAILED"))
    if not ok and result.get("gyro_refused"):
        raise CommandError(f"accelerometer calibrated; gyro not: {result['gyro_refused']}; nothing was written "
                           "to the device", f"the accelerometer's result is in {directory / 'session.json'} and the "
                           "history; record what the reason asks for, or run with --gyro bias to write it")
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
    from imubench.cli.station import port_policy, serve_page
    from imubench.station.runner import SIM_KEY, Station
    station = Station(workdir=directory.parent, db=a.db, sim_speed=a.sim_speed, sim_seed=a.sim_seed, sim_parts=a.sim_parts,
                      allow_sim=a.sim, person={"offset_deg": (a.sim_tilt, a.sim_tilt)} if a.sim_tilt else None,
                      ports=port_policy(a))
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
        serve_page(station, a, until=ended,
                   start=lambda: station.start(options, None, directory=directory, resume=bool(a.resume)))
    finally:
        station.close()
    b = station.state.boards.get(key)
    if b is None or not b.result or b.result["status"] != "pass":
        raise CommandError("the calibration did not pass" if b is not None and b.result else
                           "the session did not finish", f"everything captured is kept in {directory}; "
                           f"continue with: imubench calibrate --resume {shlex.quote(str(directory))} --ui web")
    return 0
