"""`imubench calibrate`: the guided calibration session, write-back, verification, history."""
from __future__ import annotations

import argparse
import datetime as _dt
import shlex
import sys
from contextlib import nullcontext
from pathlib import Path

from imubench.cli.common import (
    CommandError,
    UsageError,
    add_port,
    add_sim,
    existing_dir,
    existing_file,
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
from imubench.cli.station import add_web
from imubench.results import exports as X
from imubench.results.record import verdict
from imubench.text import one_line, printable

METHODS = accel_method_names(live=True)     # calib.fit.ACCEL_METHOD_LIST: the accelerometer methods of a session
CAPTURES = ("adaptive", "plan")
SIX_WARNING = ("warning: --method six needs a square fixture (a machined cube against a square): held by hand the "
               "faces are degrees off square and the fit fails; --method multi needs none")
GYRO_METHODS = gyro_method_names()          # calib.fit.GYRO_METHODS: the one list of gyro methods
# imubench.recordings.FORMATS, named here so that building the parser does not load it
# (tests/procedures/test_from_file.py checks they agree); the export formats are the registry's
FORMATS = ("csv", "imutk", "imucal", "npz", "capture", "rosbag")
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
    import argparse
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
    import argparse

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


def _add_from_file(p) -> None:
    """--from FILE and what reading a recording needs (imubench.procedures.from_file)."""
    e = p.add_argument_group("the result in other tools' files (a session, every board of a station, or --from)")
    X.add_option(e, "calibration")
    e.add_argument("--px4-acc-id", type=px4_device_id, metavar="ID",
                   help="--export px4: the PX4 device id of the accelerometer (`listener sensor_accel`, or CAL_ACC0_ID "
                        "of the vehicle's current parameters); PX4 ignores a calibration slot without it")
    e.add_argument("--px4-gyro-id", type=px4_device_id, metavar="ID",
                   help="--export px4: the PX4 device id of the gyro (`listener sensor_gyro`, or CAL_GYRO0_ID)")
    g = p.add_argument_group("calibrate from a recording (any 6-axis IMU; docs/calibration.md, From files)")
    g.add_argument("--from", dest="from_file", metavar="FILE",
                   help="calibrate from a recording instead of a device: the same analysis, report and history")
    g.add_argument("--format", choices=FORMATS, help="the recording's format (default: from its name and header)")
    g.add_argument("--gyro-file", type=existing_file, metavar="FILE",
                   help="with --format imutk: the gyro file (--from is the accelerometer's)")
    g.add_argument("--accel-unit", metavar="UNIT", help="accelerometer unit in the file: mps2, g, mg or counts")
    g.add_argument("--gyro-unit", metavar="UNIT", help="gyro unit in the file: rad_s, dps or counts")
    g.add_argument("--accel-scale", type=positive_float, metavar="COUNTS_PER_G",
                   help="nominal scale of raw accelerometer counts (datasheet); without it the fit reports counts per g")
    g.add_argument("--gyro-scale", type=positive_float, metavar="COUNTS_PER_DPS",
                   help="nominal scale of raw gyro counts (datasheet); without it the fit reports counts per °/s")
    add_reader_options(g)
    g.add_argument("--columns", metavar="KEY=NAME,...",
                   help="CSV columns: ax=...,ay=...,az=...,gx=...,gy=...,gz=...[,t=...] (default: common names)")
    g.add_argument("--time-column", metavar="NAME", help="CSV: the time column")
    g.add_argument("--time-unit", choices=("s", "ms", "us", "ns"), help="CSV: the time column's unit")
    g.add_argument("--profile", type=existing_file, metavar="TOML",
                   help="a file with the columns, units and rate of a CSV layout")
    g.add_argument("--topic", metavar="TOPIC", help="ROS bag: the sensor_msgs/Imu topic (needed when there are several)")
    g.add_argument("--device", metavar="NAME", help="a name for the IMU: the history groups its runs by it "
                                                    "(default: the file's name)")
    g.add_argument("--turn-angle", type=positive_float, default=360.0, metavar="DEG",
                   help="--gyro turns: the known angle of one turn")
    g.add_argument("--turn-sigma", type=positive_float, default=1.0, metavar="DEG",
                   help="--gyro turns: 1σ of where the hand puts the board back after a turn (a stop or a "
                        "marked edge does better than a free hand)")
    g.add_argument("--turn-axis-sigma", type=positive_float, default=0.5, metavar="DEG",
                   help="--gyro turns: 1σ of the turn axis off the measured vertical (table not level, board lifted)")
    g.add_argument("--gyro-range", type=positive_float, metavar="DPS",
                   help="the gyro's range: a motion reaching it is clipped and left out of the gyro fit (without "
                        "it, clipping is found in the data: samples held at the extreme of the values)")
    g.add_argument("--annotation", type=existing_file, metavar="JSON",
                   help="imucal's section list, to compare the segmentation with")
    g.add_argument("--tolerance-mg", type=positive_float, metavar="MG",
                   help="pass when the RMS of |a| − g over the still intervals after calibration is at most this "
                        "(default: the device's, 1 mg)")


def add_reader_options(g) -> None:
    """The reading options calibrate --from and allan --from share beyond units and columns
    (imubench.recordings: what detection cannot settle)."""
    g.add_argument("--skip-rows", type=_count, metavar="N",
                   help="text files: skip N lines before the header row (or the data); default: found by the reader")
    g.add_argument("--accel-offset", type=float, metavar="COUNTS",
                   help="counts subtracted from the accelerometer (default: 2^(n-1) for unsigned n-bit counts, said "
                        "when found; 0 keeps the values)")
    g.add_argument("--gyro-offset", type=float, metavar="COUNTS", help="counts subtracted from the gyro (as --accel-offset)")
    g.add_argument("--sensor", metavar="NAME[,NAME]",
                   help="the IMU chip, for the nominal scale of its raw counts from its data sheet (MPU-6050, MPU-9150, "
                        "MPU-9250, ICM-20602, ICM-20948, BMI160, LSM6DSO, LSM6DS3, LSM6DSL, ADXL355, ADXRS450); the "
                        "gyro's full-scale setting with --gyro-range")
    g.add_argument("--memory-budget", type=memory_budget, metavar="SIZE", default=None,
                   help="the memory the reading and the analysis keep within: 1G (the default), 800M, 4GB...; a "
                        "recording larger than the budget holds in float64 is held as float32 and analysed in "
                        "chunks, one past its sample limit refused before anything is read into memory")


def memory_budget(s: str) -> int:
    """--memory-budget: a size (1G, 800M, 512MiB)."""
    import argparse
    from imubench.memory import parse_budget
    try:
        return parse_budget(s)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _count(s: str) -> int:
    import argparse
    try:
        n = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number of lines") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n}: give 0 or more lines")
    return n


def _check_history(db) -> None:
    """Open the history database before anything is captured: a database that is down or a
    path that cannot be written is named now, not after a session whose record it would lose."""
    from imubench.results.db import describe
    from imubench.results.history import History, default_target
    import os
    target = db or default_target()
    path = None if "://" in str(target) else Path(target)
    if path is not None and not path.exists():
        # a new SQLite file: made by the first record, not now (a command refused later, e.g. a
        # usage error, leaves no empty database behind); here only whether it can be made
        parent = path.parent if str(path.parent) else Path(".")
        probe = next((q for q in [parent, *parent.parents] if q.exists()), None)
        if probe is None or not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
            raise CommandError(f"history database: {describe(target)}: cannot create it ({probe or parent} "
                               "is not a writable directory)",
                               "fix --db (or IMUBENCH_DB); nothing was captured")
        return
    try:
        with History(target, timeout_s=5.0):
            pass
    except Exception as e:  # noqa: BLE001 - any failure to open is the same answer to the user
        text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if describe(target) not in text:
            text = f"{describe(target)}: {text}"
        raise CommandError(f"history database: {text}",
                           "start the database or fix --db (or IMUBENCH_DB); nothing was captured") from None


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



def _params_or_none(dev):
    from imubench.wire.protocol_gen import ParamsWhich
    try:
        return dev.get_params(ParamsWhich.ACTIVE).params
    except Exception:  # noqa: BLE001 - the record says "unknown" rather than failing the session
        return None


def _add_station_fields(result: dict, a, directory: Path, before, after, url) -> None:
    """What a one-board session's record carries for the production database (schema 2):
    station, operator, fixture, host version, parameters before and after, raw capture hash."""
    from imubench.procedures.fixture import Station, capture_ref
    from imubench.wire import params as PR
    sf = getattr(a, "station_file", None) or {}
    st = Station(station_id=getattr(a, "station", None) or sf.get("station", ""),
                 operator=getattr(a, "operator", "") or sf.get("operator", ""),
                 fixture=getattr(a, "fixture", "") or sf.get("fixture", ""))
    result["station"] = {"id": st.station_id, "operator": st.operator, "fixture": st.fixture, "slot": 1,
                         "port": url, "host_version": st.host_version}
    result["params_before"] = PR.to_json(before) if before is not None else None
    result["params_after"] = PR.to_json(after) if after is not None and result.get("written") else None
    result["capture"] = capture_ref(directory)


def px4_device_id(s: str) -> int:
    """A PX4 device id (decimal, or 0x hex): a positive INT32, as PX4's CAL_*_ID parameters hold it."""
    try:
        v = int(s, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer device id (decimal or 0x hex)") from None
    if not 0 < v < 2 ** 31:
        raise argparse.ArgumentTypeError(f"{v} is not a PX4 device id (1 .. 2147483647)")
    return v


# ------------------------------------------------------------------ from a file
_FILE_ONLY = ("format", "gyro_file", "accel_unit", "gyro_unit", "accel_scale", "gyro_scale", "columns", "time_column",
              "time_unit", "profile", "topic", "device", "gyro_range", "annotation", "tolerance_mg", "skip_rows",
              "accel_offset", "gyro_offset", "sensor")


def _columns(text: str) -> dict:
    out = {}
    for item in text.split(","):
        if "=" not in item:
            raise UsageError(f"--columns {text!r}: each item is KEY=NAME", "e.g. --columns ax=AccX,ay=AccY,az=AccZ,"
                             "gx=GyrX,gy=GyrY,gz=GyrZ,t=Time")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def read_recording_args(a):
    """The recording --from names, read with the options of calibrate --from and allan --from
    (format, profile, units, scales, rate, columns, time, topic), and its one-line summary
    printed."""
    from imubench.recordings.readers import load_profile, read
    path = Path(a.from_file)
    if not path.exists():
        raise UsageError(f"--from {path}: no such file or directory", "check the path")
    opts = load_profile(a.profile) if a.profile else {}
    fmt = a.format or opts.pop("format", None)
    opts.pop("format", None)
    given = {"accel_unit": a.accel_unit, "gyro_unit": a.gyro_unit, "accel_counts_per_g": a.accel_scale,
             "gyro_counts_per_dps": a.gyro_scale, "rate_hz": a.rate, "time_column": a.time_column,
             "time_unit": a.time_unit, "topic": a.topic, "gyro_file": a.gyro_file, "device": a.device,
             "columns": _columns(a.columns) if a.columns else None, "skip_rows": a.skip_rows,
             "accel_offset": a.accel_offset, "gyro_offset": a.gyro_offset, "sensor": a.sensor,
             "gyro_range_dps": getattr(a, "gyro_range", None), "memory_budget": getattr(a, "memory_budget", None)}
    opts.update({k: v for k, v in given.items() if v is not None})
    if getattr(a, "cmd", "") == "calibrate":        # its analysis takes more a sample than the read: a lower limit
        from imubench import memory
        opts["memory_budget"] = memory.Budget(opts.get("memory_budget") or memory.DEFAULT_BUDGET_BYTES,
                                              memory.CALIBRATE_BYTES_PER_SAMPLE)
    if opts.get("topic") and (fmt or "") not in ("", "rosbag"):
        raise UsageError("--topic is for ROS bags", "drop it, or give --format rosbag")
    rec = read(path, fmt, **opts)
    print(f"recording: {one_line(rec.source)} ({rec.fmt}), {len(rec)} samples at {rec.fs_hz:.5g} Hz "
          f"({rec.duration_s:.1f} s); {rec.unit_text()}")
    for line in rec.detected:                   # what the reader settled without being told, one line each
        print(f"  detected: {printable(line)}")
    if rec.detected:
        from imubench.recordings import command_line
        print(f"  the same reading, every option stated: {printable(command_line(rec, a.cmd))}")
    return rec


def _run_from_file(a) -> int:
    """imubench calibrate --from FILE: read, analyse, write the session directory, record."""
    from imubench.procedures.from_file import FileConfig, calibrate_recording
    from imubench.procedures.session import Tolerances
    from imubench.recordings import RecordingError
    from imubench.recordings.readers import read_annotation
    from imubench.results.recording import annotation_table, segmentation_table, turns_table

    for flag, bad in (("--port", a.port), ("--sim", a.sim), ("--resume", a.resume), ("--redo", a.redo),
                      ("--closure", a.closure)):
        if bad:
            raise UsageError(f"--from and {flag} exclude each other", "a recording is calibrated without a device")
    if a.gyro == "turntable":
        raise UsageError("--gyro turntable needs a turntable's known rates",
                         "from a recording use --gyro turns (known-angle turns) or --gyro rotation")
    rec = read_recording_args(a)
    tol = Tolerances() if a.tolerance_mg is None else Tolerances(accel_rms_mg=a.tolerance_mg)
    if a.gyro is None:
        a.gyro = "auto"
    try:
        annotation = read_annotation(a.annotation) if a.annotation else None
    except RecordingError as e:
        raise UsageError(str(e), "give imucal's section list (JSON)") from None
    cfg = FileConfig(method=a.method or "auto", gyro=None if a.gyro == "none" else a.gyro, turn_deg=a.turn_angle,
                     angle_sigma_deg=a.turn_sigma, axis_sigma_deg=a.turn_axis_sigma,
                     gyro_range_dps=a.gyro_range, note=a.note, device=a.device or rec.device,
                     writers=tuple(a.export), px4_acc_id=a.px4_acc_id, px4_gyro_id=a.px4_gyro_id,
                     annotation=annotation, tolerances=tol,
                     tolerance_from_imu=a.tolerance_mg is None, command="imubench " + shlex.join(sys.argv[1:]))
    directory = Path(a.dir or f"imubench-file-{Path(a.from_file).stem}-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    a.on_interrupt = lambda: "nothing is kept from an interrupted analysis; run the command again"
    # what the analysis says quotes the file (its column names, its parts): printed safe
    result, fa = calibrate_recording(rec, directory, cfg, say=lambda line: print(printable(line)))
    print()
    print(segmentation_table(result))
    print()
    print(turns_table(result))
    ann = annotation_table(result)
    if ann:
        print()
        print(printable(ann))           # the part names come from the file
    _print_fit(None)(result)
    for key, unit in (("accel_counts_per_g", "counts per g"), ("gyro_counts_per_dps", "counts per °/s")):
        if key in result:
            import numpy as np
            print(f"\n{key.split('_')[0]} M in {unit} (no nominal scale was declared):")
            print("\n".join("  " + "  ".join(f"{v:12.6g}" for v in row) for row in np.asarray(result[key])))
    gyro = result.get("gyro") or {}
    for w in (gyro.get("extra") or {}).get("warnings", []):
        print(f"  gyro note: {w}")
    for kind, files in result.get("exports", {}).items():
        if files:
            print(f"{kind}: {one_line(', '.join(files))}")
    if result.get("exports", {}).get("px4") and result.get("px4_missing_ids"):
        from imubench.results.paramfiles import PX4_ID_HOW
        print(f"px4: NOT USABLE AS IS, no {' / '.join(result['px4_missing_ids'])} (PX4 ignores the slot): {PX4_ID_HOW}")
    print(f"session directory: {one_line(directory)} (session.json, residuals.png, segmentation.png, "
          "rests.csv, README.md)")
    print(f"report: {one_line(result['report'])}")
    _record_history(result, a.db, directory / "session.json")
    print(f"tolerance: {result['tolerance_source']}")
    refused_asked = bool(result.get("gyro_refused")) and a.gyro in ("turns", "rotation", "bias")
    print(f"\nverdict: {result['verdict']}")
    print("calibration " + ("PASSED" if result["passed"] and not result.get("gyro_refused") else
                            "PARTIAL" if result["passed"] else "FAILED")
          + " (fitted from a file; nothing is written to a device)")
    if not result["passed"]:
        raise CommandError(f"the RMS of |a| − g after calibration, {result['accel_rms_after_mg']:.3g} mg, is above "
                           f"the tolerance {result['tolerances']['accel_rms_mg']:.3g} mg",
                           f"see {directory / 'residuals.png'}; --tolerance-mg sets another tolerance")
    if refused_asked:
        raise CommandError(f"--gyro {a.gyro} was refused: {result['gyro_refused']}",
                           f"the accelerometer result is kept in {directory / 'session.json'} and the history; "
                           "--gyro auto takes what the recording supports")
    return 0
