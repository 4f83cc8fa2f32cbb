"""Allan-deviation noise characterisation (imubench.procedures.allan): synthetic data with known noise,
the virtual device's known noise parameters, and the crash-safe `imubench allan` command."""
from __future__ import annotations

import json

import numpy as np
import pytest
from imubench.analysis.allan import allan
from imubench.cli import main as imubench
from imubench.cli.allan import parse_duration
from imubench.results.allan import plot_allan

FS = 100.0
GYRO_N, GYRO_K = 2.6e-4, 1.0e-4        # rad/s/√Hz, rad/s·√Hz
ACC_N, ACC_K = 2.2e-4, 5.0e-5          # m/s²/√Hz, m/s²·√Hz
HOURS = 4.0                            # 4 h: K within 10 % (1 h gives only ~25 %: docs/noise.md)


def _synthetic(n_s: float, N, K, seed: int) -> np.ndarray:
    """White noise N (σ = N·√fs per sample) plus bias random walk K (K·√dt per step), as the
    simulator's convention in docs/conventions.md."""
    rng = np.random.default_rng(seed)
    n = int(n_s * FS)
    N, K = np.asarray(N, float), np.asarray(K, float)
    return (rng.standard_normal((n, 3)) * N * np.sqrt(FS)
            + np.cumsum(rng.standard_normal((n, 3)), axis=0) * K / np.sqrt(FS))


def test_parse_duration():
    assert parse_duration("90s") == 90 and parse_duration("30m") == 1800
    assert parse_duration("2h") == 7200 and parse_duration("1h30m") == 5400 and parse_duration("45") == 45
    with pytest.raises(Exception):
        parse_duration("2 days")


def test_synthetic_readoffs_within_10_percent(tmp_path):
    N, K = [GYRO_N, ACC_N, 1e-3], [GYRO_K, ACC_K, 2e-4]
    res = allan(_synthetic(HOURS * 3600, N, K, seed=7), FS)
    for i, a in enumerate("xyz"):
        r = res[a]
        assert r["N"] == pytest.approx(N[i], rel=0.10), a
        assert r["K"] == pytest.approx(K[i], rel=0.10), a
        assert r["white"]["ok"] and r["rate_rw"]["ok"]
        # the fitted ranges really have the slopes they claim
        assert abs(r["white"]["free_slope"] + 0.5) < 0.15 and abs(r["rate_rw"]["free_slope"] - 0.5) < 0.15
        assert r["white"]["tau_range"][0] <= 1.0 <= r["white"]["tau_range"][1] * 2
        # bias instability: the minimum of the curve, at the crossover of the two lines
        i_min = int(np.argmin(r["adev"]))
        assert r["B"] == pytest.approx(r["adev"][i_min] / 0.664) and r["B_tau"] == r["taus"][i_min]
        assert all(lo <= d <= hi for lo, d, hi in zip(r["ci_lo"], r["adev"], r["ci_hi"]))
    plot_allan(res, tmp_path / "a.png", "synthetic", "rad/s")
    assert (tmp_path / "a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_white_noise_only_has_no_random_walk():
    res = allan(_synthetic(1800, [GYRO_N] * 3, [0.0] * 3, seed=3), FS)
    for a in "xyz":
        assert res[a]["N"] == pytest.approx(GYRO_N, rel=0.05)
        assert res[a]["K"] is None or res[a]["K"] < 0.2 * GYRO_K


@pytest.fixture(scope="module")
def vb():
    from imubench.device.sim import VirtualBench
    with VirtualBench(speed=0, seed=5) as b:
        # white noise and a random walk only, as _synthetic: the default gyro's bias instability
        # (25 °/h, docs/simulator.md) would lift the K read-off by 6-9 % (the +1/2 fit removes
        # the white part, not a floor); its read-off is tests/device/test_sim_gyro_noise.py's
        b.set_truth(accel={"noise_n": [ACC_N] * 3, "rw_k": [ACC_K] * 3},
                    gyro=[{"noise_n": GYRO_N, "bias_rw_k": GYRO_K, "bias_instability_rad_s": 0.0}] * 3)
        yield b


def test_virtual_device_readoffs_within_10_percent_of_truth(vb, tmp_path):
    """The issue's requirement: read-offs within 10 % of the virtual device's known noise
    parameters. 4 h of device time at 100 Hz (a few seconds of wall time at speed 0)."""
    truth = vb.get_truth()
    out = tmp_path / "rec"
    assert imubench(["allan", "--port", vb.port_url, "--duration", f"{HOURS:g}h", "--rate", "100",
                       "--out", str(out), "--progress", "2"]) == 0
    res = json.loads((out / "allan.json").read_text())
    # speed 0 streams as fast as the host reads, and the virtual device drops (as a UART does)
    # when the host stalls for over 50 ms: on a loaded machine (the suite runs on both cores)
    # some stretches can be lost. Each is counted and the analysis joins the pieces; the
    # read-offs below must still hold, with at most a quarter of the recording missing.
    missing = res["decoder"]["samples_missing"]
    assert missing <= 0.25 * HOURS * 3600 * FS, missing
    assert res["samples"] + missing >= HOURS * 3600 * FS
    report = {}
    for kind, n_key, k_key in (("accel", "noise_n", "rw_k"), ("gyro", "noise_n", "bias_rw_k")):
        for i, a in enumerate("xyz"):
            t = truth["accel"] if kind == "accel" else truth["gyro"][i]
            n_true = t[n_key][i] if kind == "accel" else t[n_key]
            k_true = t[k_key][i] if kind == "accel" else t[k_key]
            r = res[kind][a]
            report[f"{kind} {a}"] = (r["N"] / n_true - 1, r["K"] / k_true - 1)
    print("relative errors (N, K):", {k: f"{n:+.3f} {kk:+.3f}" for k, (n, kk) in report.items()})
    for k, (en, ek) in report.items():
        assert abs(en) < 0.10, (k, en)
        assert abs(ek) < 0.10, (k, ek)


def test_main_allan_short_and_truncated_capture(vb, tmp_path, capsys):
    out = tmp_path / "short"
    assert imubench(["allan", "--port", vb.port_url, "--duration", "10m", "--out", str(out), "--progress", "1",
                     "--export", "kalibr,vins-fusion"]) == 0
    for f in ("capture.bin", "allan.json", "allan_accel.png", "allan_gyro.png", "kalibr-imu.yaml",
              "vins-fusion-imu.yaml", "exports-noise.txt"):
        assert (out / f).stat().st_size > 0, f
    text = capsys.readouterr().out
    assert "samples" in text and "ARW N [°/√h]" in text and "µg/√Hz" in text
    # a second recording into the same directory refuses to overwrite the capture
    assert imubench(["allan", "--port", vb.port_url, "--duration", "10s", "--out", str(out)]) == 1
    # simulated crash: the capture ends in the middle of a frame
    data = (out / "capture.bin").read_bytes()
    cut = data[: len(data) // 2]
    last0 = cut.rfind(b"\0")
    cut = cut[: last0 + 20]                         # 19 bytes into the next frame
    crashed = tmp_path / "crashed.bin"
    crashed.write_bytes(cut)
    out2 = tmp_path / "after-crash"
    assert imubench(["allan", "--analyse", str(crashed), "--out", str(out2), "--export", "openvins"]) == 0
    res = json.loads((out2 / "allan.json").read_text())
    assert set(res["exports"]) == {"openvins"} and (out2 / "openvins-kalibr_imu_chain.yaml").is_file()
    full = json.loads((out / "allan.json").read_text())
    # the capture names its device (the recording asks for its info into the file), so does
    # the analysis of a crashed capture
    from imubench.device.link import Device
    from imubench.wire.ids import uid_text
    with Device.open(vb.port_url) as dev:
        uid = uid_text(dev.info().mcu_uid)
    assert full["device"]["mcu_uid"] == uid and res["device"]["mcu_uid"] == uid
    assert 0.4 * full["samples"] < res["samples"] < 0.6 * full["samples"]
    assert res["rate_hz"] == pytest.approx(100.0)
    assert res["gyro"]["x"]["N"] == pytest.approx(GYRO_N, rel=0.10)
    assert (out2 / "allan_gyro.png").exists()


def test_analyse_missing_or_empty_file(tmp_path, capsys):
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert imubench(["allan", "--analyse", str(empty), "--out", str(tmp_path / "o")]) == 1
    assert imubench(["allan", "--analyse", str(tmp_path / "nope.bin"), "--out", str(tmp_path / "o")]) == 2   # a missing file is a wrong argument
    assert "error" in capsys.readouterr().err


def test_a_short_record_withholds_what_it_cannot_support(tmp_path):
    """17 s of data: the Allan deviation is still falling at the longest τ the record supports,
    so there is no minimum to read a bias instability from, and no +1/2 region: both are
    withheld with the reason (on main: B at the last τ, no warning, a plot titled "0.00 h")."""
    from imubench.results.allan import format_readoffs
    x = _synthetic(17, [GYRO_N] * 3, [GYRO_K] * 3, seed=9)
    res = allan(x, FS)
    for a in "xyz":
        assert res[a]["B"] is None and res[a]["B_reason"].startswith("record too short for bias instability")
        assert res[a]["K"] is None and "no rate random walk read-off" in res[a]["K_reason"]
        assert res[a]["N"] == pytest.approx(GYRO_N, rel=0.3)          # N is still there
    from imubench.analysis.allan import usual_units
    summary = {"samples": len(x), "duration_s": 17.0, "rate_hz": FS, "accel": res, "gyro": res,
               "accel_usual": {a: usual_units(res[a], "accel") for a in "xyz"},
               "gyro_usual": {a: usual_units(res[a], "gyro") for a in "xyz"}}
    text = "\n".join(format_readoffs(summary))
    assert "17 s at 100 Hz" in text and "0.00" not in text.splitlines()[0]
    assert "withheld" in text and "gyro B withheld: record too short for bias instability" in text
    plot_allan(res, tmp_path / "a.png", "Gyroscope", "rad/s", "gyro")      # draws without B and K


def test_a_long_record_reads_everything_off():
    res = allan(_synthetic(3 * 3600, [GYRO_N] * 3, [GYRO_K] * 3, seed=4), FS)
    for a in "xyz":
        assert res[a]["B"] is not None and res[a]["B_reason"] is None
        assert res[a]["K"] is not None and res[a]["K_reason"] is None


def test_duration_text():
    from imubench.analysis.allan import duration_text
    assert duration_text(17) == "17 s" and duration_text(600) == "10 min" and duration_text(7200) == "2 h"
