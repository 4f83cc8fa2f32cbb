"""`imubench calibrate --from FILE`: the options that read a recording (shared with `allan
--from`), and the run that reads it, has it analysed (procedures.from_file) and prints the
result; nothing is written to a device."""
from __future__ import annotations

import argparse
import datetime as _dt
import shlex
import sys
from pathlib import Path

from imubench.cli.calibrate_result import _print_fit, _record_history
from imubench.cli.common import CommandError, UsageError, existing_file, positive_float
from imubench.results import exports as X
from imubench.text import one_line, printable

# imubench.recordings.FORMATS, named here so that building the parser does not load it
# (tests/procedures/test_from_file.py checks they agree); the export formats are the registry's
FORMATS = ("csv", "imutk", "imucal", "npz", "capture", "rosbag")


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


def px4_device_id(s: str) -> int:
    """A PX4 device id (decimal, or 0x hex): a positive INT32, as PX4's CAL_*_ID parameters hold it."""
    try:
        v = int(s, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer device id (decimal or 0x hex)") from None
    if not 0 < v < 2 ** 31:
        raise argparse.ArgumentTypeError(f"{v} is not a PX4 device id (1 .. 2147483647)")
    return v


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
    from imubench.procedures.from_file import FileConfig
    from imubench.procedures.from_file_write import calibrate_recording
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
