"""The shapes of other people's recordings (issues 32 and 40, the readers' part): preambles,
trailing whitespace, commented headers over wide logger rows, unsigned counts, imu_tk's pair
without --format, jittery logging clocks, raw counts without a scale and the sensor profiles.
Each shape is made here (tests/imu_synth.py), read by imubench.recordings, then run through the
command line as a new user types it; what the reader detected is said one line each and the
options that read the file again are written into session.json and the folder's README."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from inproc import run_main
from imu_synth import (
    G0,
    ferraris_session,
    logger_times,
    unsigned_counts,
    write_imutk_pair,
    write_table,
)
from imubench.recordings import RecordingError, check_timing, command_options, read, unsigned_offset
from imubench.recordings.readers import load_profile

FS = 100.0
EPOCH = 1535632344.47
PREAMBLE = ("Fs,100", "Logging Type,0", "Device,IMU-7", "Date,2024-05-01")


@pytest.fixture(scope="module")
def rec6():
    """A hand-turned session with rests both ways about each axis and three known-angle turns:
    accelerometer in g, gyro in °/s, and the truth."""
    ua, ug, truth, events = ferraris_session(fs=FS, seed=2, both_ways=True)
    return ua / G0, np.degrees(ug), truth, events


# ------------------------------------------------------------------ the reader
def test_preamble_before_the_header_is_metadata_and_its_rate_is_used(rec6, tmp_path):
    ag, gd, _, _ = rec6
    p = write_table(tmp_path / "log.csv", np.column_stack([ag, gd]), delim=",",
                    header=("ax", "ay", "az", "gx", "gy", "gz"), preamble=PREAMBLE)
    rec = read(p, accel_unit="g", gyro_unit="dps")
    assert len(rec) == len(ag) and np.allclose(rec.accel, ag, atol=1e-8) and rec.fs_hz == 100.0
    assert any("header row at line 5 after 4 line(s) of preamble" in d for d in rec.detected)
    assert any("sample rate 100 Hz from the preamble line 'Fs,100'" in d for d in rec.detected)
    assert rec.options["skip_rows"] == 4 and rec.options["rate_hz"] == 100.0
    # a declared rate wins, and the preamble's is named
    rec2 = read(p, accel_unit="g", gyro_unit="dps", rate_hz=50.0)
    assert rec2.fs_hz == 50.0 and any("the preamble states 'Fs,100'; --rate 50 is used" in n for n in rec2.notes)
    # "Sample rate: 200 Hz" is a rate too; no stated rate and no time column: asked for
    write_table(tmp_path / "b.csv", np.column_stack([ag, gd]), delim=",", header=("ax", "ay", "az", "gx", "gy", "gz"),
                preamble=("Logger v2", "Sample rate: 200 Hz"))
    assert read(tmp_path / "b.csv", accel_unit="g", gyro_unit="dps").fs_hz == 200.0
    write_table(tmp_path / "c.csv", np.column_stack([ag, gd]), delim=",", header=("ax", "ay", "az", "gx", "gy", "gz"),
                preamble=("Logger v2", "Operator,someone"))
    with pytest.raises(RecordingError, match="no time column; give --rate HZ"):
        read(tmp_path / "c.csv", accel_unit="g", gyro_unit="dps")


def test_skip_rows_where_detection_cannot_settle(rec6, tmp_path):
    """Lines of numbers of the table's width before the header look like data: the error says
    --skip-rows, which (or the profile's skip_rows) reads the file."""
    ag, gd, _, _ = rec6
    pre = ("Calibration matrix",) + tuple(",".join("1" if i == j else "0" for j in range(6)) for i in range(6))
    p = write_table(tmp_path / "m.csv", np.column_stack([ag, gd]), delim=",",
                    header=("ax", "ay", "az", "gx", "gy", "gz"), preamble=pre + ("Fs,100",))
    with pytest.raises(RecordingError, match="not numbers where numbers are expected.*--skip-rows N"):
        read(p, accel_unit="g", gyro_unit="dps", rate_hz=FS)
    rec = read(p, accel_unit="g", gyro_unit="dps", rate_hz=FS, skip_rows=8)
    assert np.allclose(rec.accel, ag, atol=1e-8)
    prof = tmp_path / "m.toml"
    prof.write_text('skip_rows = 8\nrate_hz = 100.0\n[units]\naccel = "g"\ngyro = "dps"\n')
    assert np.array_equal(read(p, **load_profile(prof)).accel, rec.accel)


@pytest.mark.parametrize("delim,end", [(" ", " \n"), ("\t", "\t\n"), ("   ", "  \n"), (" \t ", "\n"), (",", ", \n")])
def test_whitespace_at_line_ends_and_between_fields_is_format(rec6, tmp_path, delim, end):
    ag, gd, _, _ = rec6
    t = EPOCH + np.arange(len(ag)) / FS
    p = write_table(tmp_path / "log.txt", np.column_stack([t, ag, gd]), delim=delim, fmt="%.6f", line_end=end)
    rec = read(p, accel_unit="g", gyro_unit="dps")
    assert len(rec) == len(ag), "the first data row was read as a header"
    assert np.allclose(rec.accel, ag, atol=1e-6) and abs(rec.fs_hz - FS) < 1e-3
    assert any("time unit s" in d and "Unix time stamps" in d for d in rec.detected)


def test_commented_header_names_the_columns_of_wide_logger_rows(rec6, tmp_path):
    ag, gd, _, _ = rec6
    n = len(ag)
    t = EPOCH + np.arange(n) / FS
    rng = np.random.default_rng(0)
    wide = np.column_stack([t, ag * G0, np.radians(gd), rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 4))])
    p = write_table(tmp_path / "imu.txt", wide, fmt="%.6f",
                    comment_header="time tx ty tz wx wy wz mx my mz qx qy qz qw".split())
    rec = read(p, accel_unit="mps2", gyro_unit="rad_s")
    assert np.allclose(rec.accel, ag * G0, atol=1e-5) and np.allclose(rec.gyro, np.radians(gd), atol=1e-6)
    used = next(d for d in rec.detected if d.startswith("columns found by name"))
    assert "accel tx, ty, tz; gyro wx, wy, wz; time time; not used: mx, my, mz, qx, qy, qz, qw" in used
    assert rec.options["columns"] == {"ax": "tx", "ay": "ty", "az": "tz", "gx": "wx", "gy": "wy", "gz": "wz"}


@pytest.mark.parametrize("step, unit", [(0.01, "s"), (10.0, "ms"), (2500.0, "us"), (1e6, "ns"), (0.0005, "s")])
def test_relative_time_unit_from_the_only_unit_that_gives_an_imu_rate(rec6, tmp_path, step, unit):
    """Steps of 10 ms read as 0.01, 10, 10000 or 1e7: the units differ by 1000 and an IMU's
    rates (10 Hz to 5 kHz) by 500, so one unit at most fits; it is used and said."""
    ag, gd, _, _ = rec6
    p = write_table(tmp_path / "r.csv", np.column_stack([np.arange(len(ag)) * step, ag, gd]), delim=",",
                    header=("time", "ax", "ay", "az", "gx", "gy", "gz"))
    rec = read(p, accel_unit="g", gyro_unit="dps")
    f = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}[unit]
    assert rec.fs_hz == pytest.approx(1.0 / (step * f), rel=1e-9) and rec.options["time_unit"] == unit
    assert sum(f"time unit {unit}: the time column 'time' steps by" in d for d in rec.detected) == 1


@pytest.mark.parametrize("step", [0.15, 150.0])
def test_relative_time_between_the_units_still_asks_for_its_unit(rec6, tmp_path, step):
    """A step of 0.15 is 6.7 Hz in s or 6.7 kHz in ms: neither an IMU rate of 10 Hz to 5 kHz, so
    the unit is asked for rather than guessed."""
    ag, gd, _, _ = rec6
    p = write_table(tmp_path / "r.csv", np.column_stack([np.arange(len(ag)) * step, ag, gd]), delim=",",
                    header=("time", "ax", "ay", "az", "gx", "gy", "gz"))
    with pytest.raises(RecordingError, match="does not say its unit: give --time-unit"):
        read(p, accel_unit="g", gyro_unit="dps")


def test_unsigned_counts_are_found_by_their_values():
    rng = np.random.default_rng(4)
    faces = np.repeat(np.vstack([np.eye(3), -np.eye(3)]), 200, axis=0) + rng.normal(0, 0.002, (1200, 3))
    assert unsigned_offset(unsigned_counts(faces, 16384)) == (32768, 16)           # ±2 g
    assert unsigned_offset(unsigned_counts(faces, 2048)) == (32768, 16)            # ±16 g
    assert unsigned_offset(unsigned_counts(faces, 256, bits=12)) == (2048, 12)
    assert unsigned_offset(unsigned_counts(rng.normal(0, 0.3, (1000, 3)), 131)) == (32768, 16)   # a gyro at rest
    # signed counts are not: negative values, or one attitude of a signed sensor (a corner, all axes positive)
    assert unsigned_offset(np.round(faces * 16384)) is None
    corner = np.round(np.full((500, 3), 16384 / np.sqrt(3)) + rng.normal(0, 20, (500, 3)))
    assert unsigned_offset(corner) is None
    assert unsigned_offset(np.abs(faces) * 9.81) is None                           # not integers


def test_unsigned_counts_subtracted_said_declared_or_refused(rec6, tmp_path):
    ag, gd, _, _ = rec6
    n = len(ag)
    p = write_table(tmp_path / "u.csv", np.column_stack([np.arange(n) * 10.0, unsigned_counts(ag, 16384),
                                                         unsigned_counts(gd, 131)]),
                    delim=",", fmt="%.0f", header=("t_ms", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"))
    rec = read(p, accel_unit="counts", gyro_unit="counts")
    assert np.allclose(rec.accel / 16384, ag, atol=1 / 16384) and np.allclose(rec.gyro / 131, gd, atol=1 / 131)
    lines = [d for d in rec.detected if "unsigned 16-bit counts centred on 32768" in d]
    assert len(lines) == 2 and "--accel-offset 32768" in lines[0] and "--gyro-offset 32768" in lines[1]
    assert np.array_equal(read(p, accel_unit="counts", gyro_unit="counts", accel_offset=0).accel,
                          rec.accel + 32768)
    with pytest.raises(RecordingError, match="unsigned 16-bit counts centred on 32768.*not g: declare "
                                             "--accel-unit counts") as e:
        read(p, accel_unit="g", gyro_unit="dps")
    assert "--accel-scale 5" not in str(e.value)                  # never a scale for an offset


def test_a_jittery_clock_is_not_a_gap_and_its_rate_is_the_measured_mean():
    n, fs = 12000, 97.6
    t = logger_times(n, fs)
    x = np.zeros((n, 3))
    steps_ms = np.round(np.diff(t) * 1e3)
    assert set(steps_ms) == {5, 6, 10, 11, 15, 16}        # the shape: 10 ms, and late stamps 15 then 5
    _, _, _, fs_m, breaks, tm = check_timing(t, x, x)
    assert breaks == [] and tm["gaps"] == [] and tm["long_steps_jitter"] > 100
    assert abs(fs_m - fs) < 0.01 * fs and tm["jitter_s"] > 0.001 and tm["resampled"]
    # samples really missing in the same clock are a gap, counted
    keep = np.ones(n, bool)
    keep[5000:5020] = False
    _, _, _, _, breaks, tm = check_timing(t[keep], x[keep], x[keep])
    assert len(tm["gaps"]) == 1 and tm["gaps"][0]["missing"] in (19, 20, 21) and len(breaks) == 1
    # one sample missing on a steady clock is still found
    keep = np.ones(n, bool)
    keep[3000] = False
    tu = np.arange(n) / fs
    _, _, _, _, _, tm = check_timing(tu[keep], x[keep], x[keep])
    assert [g["missing"] for g in tm["gaps"]] == [1]


def test_sensor_profiles_give_the_counts_scale_or_ask_for_the_setting(rec6, tmp_path):
    ag, gd, _, _ = rec6
    n = len(ag)
    p = write_table(tmp_path / "mpu.csv", np.column_stack([np.arange(n) * 10.0, np.round(ag * 8192),
                                                           np.round(gd * 65.5)]),
                    delim=",", fmt="%.0f", header=("t_ms", "ax", "ay", "az", "gx", "gy", "gz"))
    with pytest.raises(RecordingError, match=r"--sensor MPU-6050: .*--gyro-range 250\|500\|1000\|2000 "
                                             r"\(131\|65.5\|32.8\|16.4 counts per °/s\) \[PS-MPU-6000A-00 Rev. 3.4\]"):
        read(p, sensor="MPU-6050")
    rec = read(p, sensor="mpu6050", gyro_range_dps=500)
    assert rec.accel_unit == rec.gyro_unit == "counts"
    assert rec.accel_counts_per_g == 8192 and rec.gyro_counts_per_dps == 65.5
    assert any("accelerometer full scale ±4 g of the MPU-6050" in d for d in rec.detected)
    with pytest.raises(RecordingError, match="--gyro-range 300 is none of them"):
        read(p, sensor="MPU-6050", gyro_range_dps=300)
    with pytest.raises(RecordingError, match="1 g at none of its settings"):
        read(p, sensor="ADXL355,ADXRS450")
    # a declared scale wins over the profile
    assert read(p, sensor="BMI160", gyro_counts_per_dps=70.0).gyro_counts_per_dps == 70.0
    with pytest.raises(RecordingError, match="not known; known: MPU-6050"):
        read(p, sensor="MPU-1234")
    q = write_table(tmp_path / "si.csv", np.column_stack([np.arange(n) * 10.0, ag, gd]), delim=",",
                    header=("t_ms", "ax", "ay", "az", "gx", "gy", "gz"))
    si = read(q, sensor="MPU-6050", accel_unit="g", gyro_unit="dps")
    assert "--sensor MPU-6050: not used for the accelerometer and gyro (declared in a unit, not counts)" in si.notes


def test_decimal_commas_are_named(rec6, tmp_path):
    ag, gd, _, _ = rec6
    p = tmp_path / "euro.csv"
    p.write_text("ax;ay;az;gx;gy;gz\n" + "".join(";".join(f"{v:.5f}".replace(".", ",") for v in row) + "\n"
                                                  for row in np.column_stack([ag, gd])[:50]))
    with pytest.raises(RecordingError, match="decimal commas"):
        read(p, accel_unit="g", gyro_unit="dps", rate_hz=FS)


def test_formats_by_content_and_the_options_read_the_file_again(rec6, tmp_path):
    ag, gd, _, _ = rec6
    t = np.arange(len(ag)) / FS
    a, g = write_imutk_pair(tmp_path, "xsens", t, ag * G0, np.radians(gd))
    rec = read(a, accel_unit="mps2", gyro_unit="rad_s")
    assert rec.fmt == "imutk" and rec.options["format"] == "imutk" and rec.options["gyro_file"] == str(g)
    assert np.allclose(rec.gyro, np.radians(gd), atol=1e-8)
    again = command_options(rec)
    assert again[:4] == ["--format", "imutk", "--gyro-file", str(g)]
    # a table of numbers under any name is read by content; the options read it the same way
    p = write_table(tmp_path / "run.dat", np.column_stack([EPOCH + t, ag, gd]), fmt="%.6f", line_end=" \n")
    rec = read(p, accel_unit="g", gyro_unit="dps")
    assert rec.fmt == "csv" and rec.options["time_unit"] == "s"
    opts = {k: v for k, v in rec.options.items() if k != "format"}
    assert np.array_equal(read(p, rec.options["format"], **opts).accel, rec.accel)


# ------------------------------------------------------------------ the command line, as a new user types it
def _cli(args, cwd: Path, command="calibrate"):
    env = dict(os.environ, IMUBENCH_DB=str(cwd / "history.sqlite"))
    return subprocess.run([sys.executable, "-m", "imubench", command, *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300, stdin=subprocess.DEVNULL, env=env)


def _main(args, cwd: Path, monkeypatch, capsys, command="calibrate"):
    """_cli's command through the same entry point (imubench.cli.main) in this process, with its
    working directory and history: for runs whose behaviour a subprocess run here also shows."""
    return run_main([command, *args], monkeypatch, capsys, cwd=cwd, env={"IMUBENCH_DB": cwd / "history.sqlite"})


def _shape(name, rec6, d: Path):
    """The file of a shape in d, and the units a user declares for it."""
    ag, gd, _, _ = rec6
    n = len(ag)
    t = EPOCH + np.arange(n) / FS
    if name == "preamble":
        return write_table(d / "log.csv", np.column_stack([ag, gd]), delim=",",
                           header=("ax", "ay", "az", "gx", "gy", "gz"), preamble=PREAMBLE), ["--accel-unit", "g",
                                                                                            "--gyro-unit", "dps"]
    if name == "unsigned":
        return write_table(d / "raw.csv", np.column_stack([np.arange(n) * 10.0, unsigned_counts(ag, 16384),
                                                           unsigned_counts(gd, 131)]), delim=",", fmt="%.0f",
                           header=("t_ms", "ax", "ay", "az", "gx", "gy", "gz")), ["--accel-unit", "counts",
                                                                                "--gyro-unit", "counts"]
    if name == "imutk":
        return write_imutk_pair(d, "xsens", t - EPOCH, ag * G0, np.radians(gd))[0], ["--accel-unit", "mps2",
                                                                                   "--gyro-unit", "rad_s"]
    if name == "trailing":
        return write_table(d / "imu.log", np.column_stack([t, ag * G0, np.radians(gd)]), fmt="%.6f",
                           line_end=" \n"), ["--accel-unit", "mps2", "--gyro-unit", "rad_s"]
    if name == "wide":
        rng = np.random.default_rng(0)
        wide = np.column_stack([t, ag * G0, np.radians(gd), rng.normal(0, 1, (n, 7))])
        return write_table(d / "imu.txt", wide, fmt="%.6f",
                           comment_header="time tx ty tz wx wy wz mx my mz qx qy qz qw".split()), \
            ["--accel-unit", "mps2", "--gyro-unit", "rad_s"]
    if name == "mpu":
        return write_table(d / "mpu.csv", np.column_stack([np.arange(n) * 10.0, np.round(ag * 8192),
                                                           np.round(gd * 65.5)]), delim=",", fmt="%.0f",
                           header=("t_ms", "ax", "ay", "az", "gx", "gy", "gz")), ["--sensor", "MPU-6050",
                                                                                "--gyro-range", "500"]
    raise AssertionError(name)


SHAPES = {  # shape: what the run must say it detected
    "preamble": ["header row at line 5 after 4 line(s) of preamble", "sample rate 100 Hz from the preamble"],
    "unsigned": ["accelerometer: unsigned 16-bit counts centred on 32768", "gyro: unsigned 16-bit counts"],
    "imutk": ["format imutk from the file's content", "the gyro file xsens_gyro.mat beside it"],
    "trailing": ["format csv from the file's content", "time unit s: imu.log: the time column (position 1)"],
    "wide": ["columns named by the comment line at line 1", "not used: mx, my, mz, qx, qy, qz, qw"],
    "mpu": ["accelerometer full scale ±4 g of the MPU-6050", "gyro full scale ±500 °/s of the MPU-6050"],
}


# the shape whose two runs are subprocesses, as a user types them; the others' runs take the same
# entry point in-process (the reader's detection and the options are the same code either way)
AS_TYPED = "preamble"


@pytest.mark.parametrize("name", list(SHAPES))
def test_each_shape_through_the_command_line(rec6, tmp_path, name, monkeypatch, capsys):
    _, _, truth, _ = rec6
    path, units = _shape(name, rec6, tmp_path)

    def cli(args):
        return _cli(args, tmp_path) if name == AS_TYPED else _main(args, tmp_path, monkeypatch, capsys)
    r = cli(["--from", path.name, *units, "--dir", "out"])
    out = r.stdout
    assert r.returncode == 0 and r.stderr == "" and "Traceback" not in out, out + r.stderr
    detected = [ln.strip()[len("detected: "):] for ln in out.splitlines() if ln.strip().startswith("detected: ")]
    for needle in SHAPES[name]:
        assert sum(needle in d for d in detected) == 1, (needle, detected)
    assert "calibration PASSED" in out and "gyro calibrated (turns+rotation)" in out
    res = json.loads((tmp_path / "out" / "session.json").read_text())["result"]
    # the truth within 3σ (the gyro; the accelerometer's six-position fit, 5σ as in test_from_file)
    m, s = np.array(res["gyro"]["m"]), np.array(res["gyro"]["sigma_m"])
    if res["gyro"].get("unit", "rad_s") != "counts" and "gyro_counts_per_dps" not in res:
        assert np.abs((m - truth["gyro_m"]) / s).max() < 3
    # the options that read it again: printed, in session.json and the README, and they do
    cmd = res["source"]["command"]
    assert cmd.startswith(f"imubench calibrate --from {path.name} --format ")
    assert f"\n```\n{cmd}\n```\n" in (tmp_path / "out" / "README.md").read_text()
    assert f"the same reading, every option stated: {cmd}" in out
    r2 = cli([*cmd.split()[2:], "--dir", "again"])
    assert r2.returncode == 0 and "detected:" not in r2.stdout, r2.stdout + r2.stderr
    res2 = json.loads((tmp_path / "again" / "session.json").read_text())["result"]
    assert res2["accel"]["m"] == res["accel"]["m"] and res2["source"]["rate_hz"] == res["source"]["rate_hz"]


def test_a_jittery_logging_clock_keeps_every_motion(tmp_path, monkeypatch, capsys):
    """Time stamps of a logging PC, 97.6 Hz with steps alternating long and short: no gap, no
    motion left out of the gyro fit; the rate is the measured mean with the jitter stated; the
    result is that of the same recording on a steady clock."""
    ua, ug, truth, _ = ferraris_session(fs=97.6, seed=2, both_ways=True)
    n = len(ua)
    hdr = ("time", "ax", "ay", "az", "gx", "gy", "gz")
    write_table(tmp_path / "jitter.csv", np.column_stack([logger_times(n, 97.6), ua, ug]), delim=",", fmt="%.6f",
                header=hdr)
    write_table(tmp_path / "steady.csv", np.column_stack([EPOCH + np.arange(n) / 97.6, ua, ug]), delim=",",
                fmt="%.6f", header=hdr)
    runs = {}
    for name in ("jitter", "steady"):
        r = _main(["--from", f"{name}.csv", "--accel-unit", "mps2", "--gyro-unit", "rad_s", "--dir", name], tmp_path,
                  monkeypatch, capsys)
        assert r.returncode == 0 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
        assert "gap of" not in r.stdout and "not continuous" not in r.stdout and "samples missing" not in r.stdout
        runs[name] = (r.stdout, json.loads((tmp_path / name / "session.json").read_text())["result"])
    out, res = runs["jitter"]
    assert "samples at 97.6 Hz measured from the time stamps (mean step 10.25 ms), step jitter" in out
    assert "steps longer than 1.5× the mean are the clock's jitter, not gaps" in out
    # every motion is used, as on the steady clock; the stamps' jitter (late by 5 ms, one sample in 8) moves
    # the gyro's M by a few 1e-4 (resampled on the stamps: the σ of M does not count the clock's jitter)
    steady = runs["steady"][1]
    rot = [r["gyro_parts"]["fits"]["rotation"]["extra"] for r in (res, steady)]
    assert rot[0]["n_motions"] == rot[1]["n_motions"] == 25 and rot[0]["excluded_motions"] == []
    m, s = np.array(res["gyro"]["m"]), np.array(res["gyro"]["sigma_m"])
    assert np.abs((np.array(steady["gyro"]["m"]) - truth["gyro_m"]) / s).max() < 3
    assert np.abs(m - truth["gyro_m"]).max() < 5e-4


def test_counts_without_a_gyro_scale_ask_for_it_in_one_line(rec6, tmp_path, monkeypatch, capsys):
    """Raw gyro counts that no known-angle turn scales: one line asking for the scale (once an
    internal TypeError); a named sensor without its gyro setting: one line asking for it."""
    ag, gd, _, events = rec6
    cut = [e for e in events if e[0] == "rot"][-3][1]          # the recording before its three turns
    write_table(tmp_path / "raw.csv", np.column_stack([np.arange(cut) * 10.0, np.round(ag[:cut] * 8192),
                                                       np.round(gd[:cut] * 65.5)]), delim=",", fmt="%.0f",
                header=("t_ms", "ax", "ay", "az", "gx", "gy", "gz"))
    for args, needle in (
            (["--accel-unit", "counts", "--gyro-unit", "counts", "--gyro", "none"],
             "the gyro is in counts without a nominal scale and no known-angle turn in the recording scales it: "
             "give --gyro-scale COUNTS_PER_DPS"),
            (["--sensor", "MPU-6050"], "--sensor MPU-6050: its gyro has several full-scale settings")):
        argv = ["--from", "raw.csv", *args, "--dir", "o"]        # the first as typed, the second in-process
        r = _cli(argv, tmp_path) if "--gyro" in args else _main(argv, tmp_path, monkeypatch, capsys)
        err = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 1 and len(err) == 1 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
        assert err[0].startswith("imubench calibrate: error: ") and needle in err[0], err[0]
    r = _main(["--from", "raw.csv", "--sensor", "MPU-6050", "--gyro-range", "500", "--dir", "o2"], tmp_path,
              monkeypatch, capsys)
    assert r.returncode == 0 and "gyro calibrated (rotation)" in r.stdout, r.stdout + r.stderr


def test_allan_from_uses_the_same_reader(tmp_path):
    """allan --from: a still recording with a preamble, in unsigned counts of a named sensor."""
    rng = np.random.default_rng(5)
    n = 6000
    acc = np.array([0.01, -0.02, 1.0]) + rng.normal(0, 0.002, (n, 3))
    gyr = np.array([0.3, -0.2, 0.1]) + rng.normal(0, 0.05, (n, 3))
    write_table(tmp_path / "still.csv", np.column_stack([unsigned_counts(acc, 16384), unsigned_counts(gyr, 131)]),
                delim=",", fmt="%.0f", header=("ax", "ay", "az", "gx", "gy", "gz"), preamble=PREAMBLE)
    r = _cli(["--from", "still.csv", "--sensor", "MPU-6050", "--gyro-range", "250", "--out", "a"], tmp_path,
             command="allan")
    assert r.returncode == 0 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    for needle in ("sample rate 100 Hz from the preamble", "accelerometer: unsigned 16-bit counts",
                   "accelerometer full scale ±2 g of the MPU-6050", "gyro full scale ±250 °/s"):
        assert needle in r.stdout, needle
    assert "imubench allan --from still.csv" in r.stdout
