"""`imubench allan --from` reads noise only from still data (issue 34, item 6): the recording is cut
into still stretches as `calibrate --from` cuts its rests (calib.static + calib.turns); the longest
is analysed, or the command refuses with the stretches it found. A figure the record cannot read
off (an upper bound) says so inside every file it reaches."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from imubench.cli import main as imubench
from imubench.procedures.allan import MIN_STILL_S, still_stretch

FS = 100.0
G0 = 9.80665
NA, NG = 2.0e-3, 2.0e-4              # m/s²/√Hz, rad/s/√Hz


def _still(rng, seconds, up):
    n = int(seconds * FS)
    return (np.asarray(up, float) * G0 + rng.normal(0, NA * np.sqrt(FS), (n, 3)),
            rng.normal(0, NG * np.sqrt(FS), (n, 3)))


def _tilt(rng, seconds, frm, to):
    """A turn of the board from one face up to another: gravity swings, the gyro sees ~60 °/s."""
    n = int(seconds * FS)
    t = np.linspace(0, 1, n)[:, None]
    up = (1 - t) * np.asarray(frm, float) + t * np.asarray(to, float)
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    rate = np.radians(90.0 / seconds) * np.cross(frm, to)[None, :] * np.ones((n, 1))
    return up * G0 + rng.normal(0, NA * np.sqrt(FS), (n, 3)), rate + rng.normal(0, NG * np.sqrt(FS), (n, 3))


def _record(tmp_path, parts, name="rec.txt"):
    rng = np.random.default_rng(3)
    acc, gyr = zip(*[f(rng, *a) for f, *a in parts])
    p = tmp_path / name
    np.savetxt(p, np.column_stack([np.vstack(acc), np.vstack(gyr)]), fmt="%.7g")
    return p


Z, X = (0, 0, 1), (1, 0, 0)


def _allan(path, out, *export):
    return imubench(["allan", "--from", str(path), "--rate", "100", "--accel-unit", "mps2", "--gyro-unit", "rad_s",
                     "--out", str(out), *export])


def test_a_handheld_recording_is_refused_with_the_stretches_it_has(tmp_path, capsys):
    # 21 hand turns with 4 s rests: never still for a minute
    parts = []
    for k in range(21):
        parts += [(_still, 4.0, Z if k % 2 == 0 else X), (_tilt, 1.5, Z if k % 2 == 0 else X, X if k % 2 == 0 else Z)]
    p = _record(tmp_path, parts)
    assert _allan(p, tmp_path / "out", "--export", "kalibr") == 1
    err = capsys.readouterr().err
    assert "not still long enough" in err and "longest still stretch is" in err
    assert f"at least {MIN_STILL_S:.0f} s" in err and "segmentation of calibrate --from" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "kalibr-imu.yaml").exists()


def test_the_longest_still_stretch_is_analysed_and_every_file_says_so(tmp_path, capsys):
    p = _record(tmp_path, [(_still, 65.0, Z), (_tilt, 2.0, Z, X), (_still, 110.0, X), (_tilt, 2.0, X, Z),
                           (_still, 30.0, Z)])
    out = tmp_path / "out"
    assert _allan(p, out, "--export", "kalibr", "--export", "openvins", "--export", "vins-fusion", "--export", "imu-utils") == 0
    stdout = capsys.readouterr().out
    assert "not still throughout" in stdout and "is analysed" in stdout
    import json
    res = json.loads((out / "allan.json").read_text())
    st = res["still"]
    assert not st["whole"] and st["stretches"] == 3
    assert 67.0 <= st["t_start_s"] <= 68.5 and 107.0 <= st["duration_s"] <= 110.0       # the 110 s rest, edges trimmed
    assert res["samples"] == st["stop"] - st["start"]
    # the white noise of the stretch is the noise, not the motion
    assert max(res["gyro"][a]["N"] for a in "xyz") == pytest.approx(NG, rel=0.15)
    files = {"kalibr-imu.yaml": None, "openvins-kalibr_imu_chain.yaml": "imu0", "vins-fusion-imu.yaml": None,
             "imu_utils.yaml": None}
    for f in files:
        text = (out / f).read_text()
        assert "Only a part of the recording is still" in text, f
        # 110 s shows no +1/2 slope: K is an upper bound, said in the header and on the field itself
        assert "UPPER BOUNDS, not read-offs" in text, f
        body = text.split("\n", 1)[1] if text.startswith("%YAML") else text
        body = body.split("---\n", 1)[-1]
        assert yaml.safe_load(body)                                   # still parses
    kal = (out / "kalibr-imu.yaml").read_text()
    line = next(x for x in kal.splitlines() if x.startswith("gyroscope_random_walk:"))
    assert "UPPER BOUND" in line
    vf = (out / "vins-fusion-imu.yaml").read_text()
    assert "UPPER BOUND" in next(x for x in vf.splitlines() if x.startswith("gyr_w:"))


def test_a_still_recording_is_analysed_whole():
    rng = np.random.default_rng(5)
    acc, gyr = _still(rng, 90.0, Z)
    st = still_stretch(acc, gyr, FS)
    assert st["whole"] and st["start"] == 0 and st["stop"] == len(acc) and st["note"] == ""


def test_a_turn_only_the_gyro_sees_splits_the_stretch():
    """A smooth turn about the vertical leaves the accelerometer still: the gyro cuts it (calib.turns)."""
    rng = np.random.default_rng(6)
    a1, g1 = _still(rng, 80.0, Z)
    a2, g2 = _still(rng, 4.0, Z)
    g2[:, 2] += np.radians(90.0)                                    # a 360° yaw in 4 s, gravity unmoved
    a3, g3 = _still(rng, 100.0, Z)
    st = still_stretch(np.vstack([a1, a2, a3]), np.vstack([g1, g2, g3]), FS)
    assert st["stretches"] == 2 and st["start"] >= len(a1) + len(a2)
