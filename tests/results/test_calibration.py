"""Per-pose residual plot and before/after table of a calibration result record."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from imubench.results.calibration import before_after_table, plot_pose_residuals

SIX = ["+X up", "-X up", "+Y up", "-Y up", "+Z up (level)", "-Z up"]


def make_result(n_poses=6, verification=True, tol=1.0):
    names = SIX + [f"tilt {i:02d} (az {15 * i}°, el {(-1) ** i * 30:+d}°)" for i in range(1, n_poses - 5)]
    before = [1.0250, 0.9800, 1.0100, 0.9950, 1.0040, 0.9900] + [1.0 + 0.002 * ((i % 7) - 3) for i in range(n_poses - 6)]
    after = [1.00001, 0.99998, 1.00002, 0.99999, 1.00000, 1.00003] + [1.0 + 1e-5 * ((i % 5) - 2) for i in range(n_poses - 6)]
    return {
        "schema": 1,
        "device": {"mcu_uid": "0123456789abcdef01234567", "board": "SIM"},
        "started": "2026-11-22T06:40:00+00:00", "method": "six" if n_poses == 6 else "multi",
        "poses": [{"name": n, "n": 2000, "before_g": b, "after_g": a, "sigma_g": 2e-5, "temp_c": 25.1}
                  for n, b, a in zip(names, before, after)],
        "tolerances": {"accel_rms_mg": tol, "verify_mg": 2.0},
        "passed": True, "written": True, "verified": verification,
        "verification": [{"name": "+Z up (level)", "after_g": 1.00001},
                         {"name": "-X up", "after_g": 0.99997},
                         {"name": "45° tilt about X", "after_g": 1.00004}] if verification else [],
    }


def png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG signature"
    length, kind = struct.unpack(">I4s", data[8:16])
    assert kind == b"IHDR" and length == 13
    return struct.unpack(">II", data[16:24])


@pytest.mark.parametrize("n_poses", [6, 26])
@pytest.mark.parametrize("verification", [False, True])
def test_png_is_written(tmp_path, n_poses, verification):
    out = plot_pose_residuals(make_result(n_poses, verification), tmp_path / "sub" / "poses.png")
    assert out == tmp_path / "sub" / "poses.png" and out.is_file()
    w, h = png_size(out)
    assert 600 <= h <= 1200 and 700 <= w <= 3000
    if n_poses == 26:
        assert w > 1400                                   # the figure widens with the number of poses
    assert out.stat().st_size > 20_000
    import matplotlib.image
    img = matplotlib.image.imread(out)
    assert img.shape[:2] == (h, w)
    assert img[..., :3].std() > 0.05                       # not a blank canvas


def test_plot_needs_no_display_and_no_pyplot(tmp_path):
    """Even with an interactive backend configured and no display, the plot is drawn (Agg
    canvas, no pyplot: the process's backend is not touched)."""
    import os
    import subprocess
    import sys
    code = ("import sys; from imubench.results.calibration import plot_pose_residuals; "
            "r = {'method': 'six', 'device': {'mcu_uid': 'ab' * 12}, "
            "'poses': [{'name': f'p{i}', 'before_g': 1.01, 'after_g': 1.0, 'sigma_g': 1e-5} for i in range(6)]}; "
            f"plot_pose_residuals(r, {str(tmp_path / 'p.png')!r}); "
            "assert 'matplotlib.pyplot' not in sys.modules")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MPLBACKEND"] = "TkAgg"
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    png_size(tmp_path / "p.png")


def test_plot_handles_missing_sigma_and_tolerances(tmp_path):
    r = make_result()
    for p in r["poses"]:
        del p["sigma_g"]
    del r["tolerances"]
    png_size(plot_pose_residuals(r, tmp_path / "p.png"))


def test_table_numbers():
    text = before_after_table(make_result())
    lines = text.splitlines()
    assert "device 0123456789ABCDEF01234567" in lines[0] and "six-position" in lines[0]
    x = next(ln for ln in lines if ln.startswith("+X up "))
    assert "1.02500 g -> 1.00001 g" in x and "-24.990 mg" in x and "+0.010 ± 0.020 mg" in x
    mx = next(ln for ln in lines if ln.startswith("-X up ") and "->" in ln)
    assert "0.98000 g -> 0.99998 g" in mx and "+19.980 mg" in mx and "-0.020 ± 0.020 mg" in mx
    rms_before = math.sqrt(np.mean(np.square([25.0, -20.0, 10.0, -5.0, 4.0, -10.0])))
    rms_after = math.sqrt(np.mean(np.square([0.01, -0.02, 0.02, -0.01, 0.0, 0.03])))
    summary = next(ln for ln in lines if ln.startswith("RMS"))
    assert summary == (f"RMS of |a| − g over 6 poses: before {rms_before:.3f} mg, after {rms_after:.3f} mg; "
                       "tolerance 1 mg RMS: PASS")
    # verification: after write-back, read from the device
    i = lines.index("verification (the device's own calibrated output after write-back):")
    ver = lines[i + 1:i + 4]
    assert ver[0].startswith("+Z up (level)") and "1.00001 g" in ver[0] and "+0.010 mg" in ver[0] and ver[0].endswith("ok")
    assert ver[1].startswith("-X up") and "-0.030 mg" in ver[1]
    assert ver[2].startswith("45° tilt about X") and "+0.040 mg" in ver[2]
    assert lines[-1].startswith("verification over 3 poses: RMS 0.029 mg, worst 0.040 mg; tolerance ±2 mg each: PASS")


def test_table_fail_and_no_verification():
    text = before_after_table(make_result(verification=False, tol=0.01))
    assert "verification" not in text
    assert text.splitlines()[-1].endswith("tolerance 0.01 mg RMS: FAIL")
    r = make_result(verification=False)
    del r["tolerances"]
    assert before_after_table(r).splitlines()[-1].endswith("no tolerance given")


def test_table_for_26_poses():
    text = before_after_table(make_result(26))
    assert "multi-position" in text.splitlines()[0]
    assert sum("->" in ln for ln in text.splitlines()) == 26
    assert "over 26 poses" in text


def test_no_poses_is_an_error(tmp_path):
    r = make_result()
    r["poses"] = []
    with pytest.raises(ValueError, match="no poses"):
        before_after_table(r)
    with pytest.raises(ValueError, match="no poses"):
        plot_pose_residuals(r, tmp_path / "p.png")
