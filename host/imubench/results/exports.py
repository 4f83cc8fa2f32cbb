"""The export registry: every file imubench writes for another tool, in one place.

For each format: its family (what it is made from), its consumer, the consumer's source file
its layout follows, its file name, what it holds exactly, what it cannot hold and what the user
must still do with it (ids, a reboot). Every command that writes these files takes its names,
file names and option syntax from here:

    family        made from                          written by
    calibration   a calibration result (M, b, G)     calibrate --from, calibrate --sim/--port (one board
                                                     or a station, one set per board), the station page
                                                     (a download per board)
    noise         an Allan analysis                  allan --from, allan --port, allan --analyse
    thermal       a warm-up's temperature fit        thermal --export
    session       a station session's records        history --export SESSION --format

One option syntax everywhere: ``--export a,b`` and ``--export a --export b`` both work, in any
mix; an unknown name is refused with the family's names (add_option). Each file carries in
its consumer's own comment syntax what it holds, what it leaves out and what the user must still
do (stamp); a format whose consumer reads no comments (imu_tk's 21 numbers, our parameter
JSON) has it in the index file written beside the exports (index_text).

Nothing here touches a port; writing is results.paramfiles', results.noise_export's and
results.thermal_export's, with the file names given here; a session's result record becomes
files in procedures.export_files.write_calibration.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from imubench.text import comment as comment_line
from imubench.text import one_line

__all__ = ["Format", "FORMATS", "FAMILIES", "names", "get", "file_names", "parse", "add_option", "stamp",
           "index_text", "write_index"]


@dataclass(frozen=True)
class Format:
    family: str          # calibration | noise | thermal | session
    name: str            # the option's value
    consumer: str        # who reads the file
    source: str          # the consumer's source file the layout follows
    files: tuple         # file names, "{prefix}" replaced (calibration: calibration-NAME; others fixed)
    holds: str           # what it holds exactly
    cannot_hold: str     # what it cannot hold (left out)
    todo: str            # what the user must still do with it ("" when nothing)
    comments: str        # the consumer's comment syntax: "#", "json" (a comment field) or "" (none)


FAMILIES = {"calibration": "a calibration result", "noise": "an Allan analysis",
            "thermal": "a warm-up's temperature fit", "session": "a station session"}

PX4_TODO = ("CAL_ACC0_ID / CAL_GYRO0_ID must be the sensors' PX4 device ids (--px4-acc-id / --px4-gyro-id; PX4 "
            "shell `listener sensor_accel` / `sensor_gyro`): a file without them says so below and is not used; load "
            "with QGroundControl (Parameters > Tools > Load from file), reboot")

FORMATS: tuple[Format, ...] = (
    # ---------------------------------------------------------------- a calibration result
    Format("calibration", "params", "imubench (this device's parameter block)", "protocol/params (wire.params.to_json)",
           ("{prefix}.params.json",), "M, b of both triads and the gyro g-sensitivity, in SI", "nothing",
           ("a session writes it to the device itself; for a factory image: `imubench param-page --params FILE "
            "--layout BOARD -o PAGE`"), ""),
    Format("calibration", "imutk", "imu_tk (Tedaldi et al. 2014)", "imu_tk include/imu_tk/calibration.h CalibratedTriad_::load",
           ("{prefix}_acc.calib", "{prefix}_gyro.calib"), "M, b of both triads exactly (T unit-diagonal, K, B)",
           "the gyro g-sensitivity", "", ""),
    Format("calibration", "imucal", "imucal (mad-lab-fau, PyPI)", "imucal/ferraris_calibration_info.py "
           "FerrarisCalibrationInfo (format 2.0.0)", ("{prefix}.imucal.json",),
           "M, b of both triads exactly; G as K_ga when fitted", "nothing of our model", "", "json"),
    Format("calibration", "ardupilot", "ArduPilot (MAVProxy `param load`, Mission Planner)",
           "libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp _rotate_and_correct_accel/_gyro",
           ("{prefix}.ardupilot.param",), "accelerometer offsets and diagonal scales, gyro offsets",
           "accelerometer cross-axis terms, the gyro's scale and cross-axis terms, G (the loss is stated in the file)",
           "INS_ACC_ID / INS_GYR_ID on the vehicle must already name this sensor; record in the autopilot "
           "board's axes", "#"),
    Format("calibration", "kalibr", "Kalibr (and OpenVINS' kalibr model)",
           "kalibr aslam_offline_calibration/kalibr/python/kalibr_imu_camera_calibration/IccSensors.py "
           "ScaledMisalignedImu", ("{prefix}.kalibr-imu.yaml",),
           "M of both triads and G exactly (M = L·Q, the rotation Q_a in a comment)", "biases (estimated online)",
           "take the IMU frame's rotation Q_a into the camera-IMU extrinsics", "#"),
    Format("calibration", "px4", "PX4 (QGroundControl parameter file)",
           "PX4-Autopilot src/lib/sensor_calibration/Utilities.cpp FindCurrentCalibrationIndex, Accelerometer.hpp",
           ("{prefix}.px4.params",), "accelerometer offsets and diagonal scales, gyro offsets, CAL_*0_ID and PRIO "
           "when given", "cross-axis terms, a gyro scale, G (stated in the file)", PX4_TODO, "#"),
    Format("calibration", "imu-calib", "ROS imu_calib (dpkoch)", "imu_calib src/accel_calib/accel_calib.cpp AccelCalib::loadCalib",
           ("{prefix}.imu_calib.yaml",), "the accelerometer's M, b exactly", "the gyro (imu_calib has none)", "", "#"),
    # ---------------------------------------------------------------- an Allan analysis
    Format("noise", "kalibr", "Kalibr imu.yaml", "kalibr kalibr_common/ConfigReader.py ImuParameters",
           ("kalibr-imu.yaml",), "N, K continuous-time (the worst axis)", "B; the other axes (comments)",
           "inflate for what a still record does not see, as your estimator needs", "#"),
    Format("noise", "openvins", "OpenVINS kalibr_imu_chain.yaml", "open_vins ov_msckf/src/core/VioManagerOptions.h "
           "print_and_load_noise, print_and_load_state", ("openvins-kalibr_imu_chain.yaml",),
           "N, K continuous-time; identity intrinsics (imubench's calibrated stream)", "B; the other axes",
           "use it on the calibrated stream (or replace the intrinsics with the kalibr calibration export)", "#"),
    Format("noise", "vins-fusion", "VINS-Fusion config (IMU keys)", "VINS-Fusion vins_estimator/src/estimator/"
           "parameters.cpp readParameters, factor/integration_base.h", ("vins-fusion-imu.yaml",),
           "N·√f, K·√f (per-sample sigmas at the recording's rate)", "B; the other axes",
           "copy the keys into your VINS-Fusion config; at another IMU rate rescale by √rate", "#"),
    Format("noise", "imu-utils", "imu_utils output", "imu_utils src/imu_an.cpp writeYAML, src/gyr_lib/fitallan_gyr.cpp",
           ("imu_utils.yaml",), "what imu_utils writes: N·√f and the Allan minimum", "K (comment only)", "", "#"),
    # ---------------------------------------------------------------- a warm-up's temperature fit
    Format("thermal", "px4", "PX4 temperature compensation", "PX4-Autopilot src/modules/temperature_compensation/"
           "TemperatureCompensation.cpp calc_thermal_offsets_3D", ("{prefix}.px4-thermal.params",),
           "bias polynomials of order <= 3 per axis", "scale temperature terms, a temperature per gyro axis",
           "replace TC_A0_ID / TC_G0_ID (0) with the sensors' PX4 device ids; reboot", "#"),
    Format("thermal", "ardupilot", "ArduPilot INS_TCAL", "libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp "
           "TCal::correct_sensor", ("{prefix}.ardupilot-thermal.param",),
           "bias polynomials of order <= 3 per axis about 35 degC",
           "scale temperature terms, a temperature per gyro axis, a constant term",
           "load, reboot (INS_TCAL1_ENABLE = 1 makes the INS_TCAL1_* exist), load again", "#"),
    # ---------------------------------------------------------------- a station session
    Format("session", "json", "any tool (imubench's session record)", "results/export.py session_dict",
           ("session-{prefix}.json",), "every board's measurements, limits, verdict, parameters, capture hash",
           "the raw captures (their SHA-256 and place only)", "", ""),
    Format("session", "junit", "CI and test-station dashboards (JUnit XML)", "Ant's JUnit task XML (testsuite, "
           "testcase, failure, error, properties)", ("session-{prefix}.junit.xml",),
           "one testsuite per board, one testcase per measurement with its limits",
           "the parameters themselves (the json format has them)", "", ""),
)


def names(family: str) -> tuple[str, ...]:
    return tuple(f.name for f in FORMATS if f.family == family)


def get(family: str, name: str) -> Format:
    for f in FORMATS:
        if f.family == family and f.name == name:
            return f
    raise ValueError(f"unknown {family} export {name!r}; one of {', '.join(names(family))}")


def file_names(family: str, name: str, prefix: str = "") -> list[str]:
    return [p.replace("{prefix}", prefix) for p in get(family, name).files]


def parse(values, family: str) -> tuple[str, ...]:
    """The formats of repeated and comma-separated values (['px4,kalibr', 'params']), in the
    order given, each once; ValueError names the first unknown one with the family's names."""
    out = []
    for v in values or ():
        for item in str(v).split(","):
            item = item.strip().lower()
            if not item:
                continue
            if item not in names(family):
                raise ValueError(f"unknown format {one_line(item)!r}; one of {', '.join(names(family))} "
                                 f"(a comma list or the option repeated)")
            if item not in out:
                out.append(item)
    return tuple(out)


class _ExportAction(argparse.Action):
    """--export a,b --export c: appends the parsed names; a bad name is argparse's one-line error."""

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            got = parse([values], self.const)
        except ValueError as e:
            raise argparse.ArgumentError(self, str(e)) from None
        old = list(getattr(namespace, self.dest) or ())
        setattr(namespace, self.dest, tuple(dict.fromkeys(old + list(got))))


def add_option(group, family: str, flag: str = "--export", dest: str | None = None, what: str = "also write"):
    """Add the family's export option: comma list and repeats both work; default ()."""
    fmts = [f for f in FORMATS if f.family == family]
    listed = "; ".join(f"{f.name}: {f.consumer}" for f in fmts)
    return group.add_argument(flag, dest=dest, action=_ExportAction, const=family, default=(),
                              metavar=",".join(names(family)),
                              help=f"{what} {FAMILIES[family]} in other tools' files ({listed}); a comma list or "
                                   "the option repeated (docs/calibration.md, docs/noise.md)")


# ------------------------------------------------------------------ what each file says of itself
def stamp_lines(fmt: Format) -> list[str]:
    return [f"Holds: {fmt.holds}.", f"Cannot hold (left out): {fmt.cannot_hold}.",
            f"You must still: {fmt.todo}." if fmt.todo else "You must still: nothing; load it as it is.",
            f"Layout followed: {fmt.source} ({fmt.consumer})."]


def stamp(text: str, fmt: Format) -> str:
    """text with the format's what-it-holds lines in its consumer's comment syntax, after a
    first line the consumer needs first (OpenCV's %YAML:1.0) or the first comment line; a JSON
    file gets them in its comment field (imucal); a format without comments is returned as is."""
    if fmt.comments == "#":
        lines = [comment_line(s) for s in stamp_lines(fmt)]
        head, rest = ("", text)
        if text.startswith("%YAML"):
            head, rest = text.split("\n", 1)
            head += "\n"
        first, _, tail = rest.partition("\n")
        if first.startswith("#"):
            return head + first + "\n" + "\n".join(lines) + "\n" + tail
        return head + "\n".join(lines) + "\n" + rest
    if fmt.comments == "json":
        import json
        d = json.loads(text)
        d["comment"] = " ".join([one_line(d.get("comment", "")), *stamp_lines(fmt)]).strip()
        return json.dumps(d, indent=4) + "\n"
    return text


def index_text(family: str, written: dict, title: str = "") -> str:
    """A plain index of the files written: per format its files, consumer, source followed,
    what it holds, cannot hold and what is left to do (also for formats that take no comments)."""
    lines = [f"# {one_line(title or 'imubench exports')}: what each file is for (imubench.results.exports)", ""]
    for name, paths in written.items():
        f = get(family, name)
        lines += [f"{name}: {', '.join(Path(p).name for p in paths) if paths else 'not written'}",
                  f"  consumer: {f.consumer}", f"  layout followed: {f.source}", f"  holds: {f.holds}",
                  f"  cannot hold: {f.cannot_hold}", f"  still to do: {f.todo or 'nothing'}", ""]
    return "\n".join(lines)


def write_index(directory, family: str, written: dict, title: str = "") -> Path:
    from imubench.results.atomic import write_text_atomic
    return write_text_atomic(Path(directory) / f"exports-{family}.txt", index_text(family, written, title))
