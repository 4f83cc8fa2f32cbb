"""Noise figures (an Allan analysis, imubench.analysis.allan) in the files the estimators read.

    write_noise(kind, path, res, topic=...)      kind in NOISE_WRITERS; res: allan.json's dict

Every consumer here wants **continuous-time** densities and random walks (docs/noise.md):
white noise as its Allan coefficient N (the density: m/s²/√Hz, rad/s/√Hz; σ of one sample at
rate f is N·√f) and the bias random walk K (m/s³/√Hz, rad/s²/√Hz: ADEV(τ) = K·√(τ/3)). One field
takes one number: the worst axis goes in it, the three axes are in comments (kalibr#143). When
the record shows no +1/2 slope, K is not read off; the file then holds the upper bound the
longest τ allows, K ≤ ADEV(τ_max)·√(3/τ_max), and says so.

imu_utils is the exception: its own output's `gyr_w`/`acc_w` are the Allan minimum (bias
instability B), not a random walk (its src/gyr_lib/fitallan_gyr.cpp); the imu-utils file keeps
that meaning, as a file imu_utils wrote, and gives K beside it in a comment.

The usual advice to inflate these for an estimator (several times, for unmodelled effects:
vibration, temperature, the bias's own model) is written as a comment with its sources (kalibr
issue #663, allan_variance_ros issue #44) and never applied to the numbers.
"""
from __future__ import annotations

import math
from pathlib import Path

from imubench.results.atomic import write_text_atomic

NOISE_WRITERS = ("kalibr", "openvins", "vins-fusion", "imu-utils")
G0 = 9.80665
AXES = ("x", "y", "z")
INFLATE = ("# Estimators are usually given these inflated several times (commonly x2 to x10) for what the\n"
           "# Allan record does not see (vibration, temperature, the bias's own model): kalibr issue #663,\n"
           "# allan_variance_ros issue #44. Not applied here: the numbers are what the record shows.\n")


def _num(v: float) -> str:
    return f"{v:.6g}"


def _k_of(ax: dict) -> tuple[float, str]:
    """(K, how it was obtained) of one axis: read off, or the upper bound of the longest τ."""
    if ax.get("K") is not None:
        return float(ax["K"]), "read off the +1/2 slope"
    tau, dev = float(ax["taus"][-1]), float(ax["adev"][-1])
    return dev * math.sqrt(3.0 / tau), f"upper bound from ADEV({tau:.3g} s) (no +1/2 slope in the record)"


def noise_terms(res: dict) -> dict:
    """{'accel'|'gyro': {'n': [3], 'k': [3], 'b': [3 or None], 'k_how': [3], 'n_worst', 'k_worst'}} in SI."""
    out = {}
    for kind in ("accel", "gyro"):
        axes = [res[kind][a] for a in AXES]
        n = [float(a["N"]) for a in axes]
        ks = [_k_of(a) for a in axes]
        out[kind] = {"n": n, "k": [k for k, _ in ks], "k_how": [h for _, h in ks],
                     "b": [None if a.get("B") is None else float(a["B"]) for a in axes],
                     "n_worst": max(n), "k_worst": max(k for k, _ in ks)}
    return out


def _axes_comment(label: str, vals, unit: str) -> str:
    return f"#   {label}: " + ", ".join(f"{a} {v:.4g}" if v is not None else f"{a} -" for a, v in zip(AXES, vals)) \
        + f" {unit}\n"


def _header(res: dict, consumer: str) -> str:
    src = ", ".join(map(str, res.get("source", []))) or "?"
    return (f"# {consumer} noise parameters from imubench's Allan analysis of {src}\n"
            f"# ({res.get('samples', 0)} samples at {res['rate_hz']:.6g} Hz, {res['duration_s'] / 3600:.3g} h; "
            "docs/noise.md). Continuous-time: density N (sample sigma = N*sqrt(rate)), random walk K.\n")


def _per_axis(t: dict) -> str:
    a, g = t["accel"], t["gyro"]
    return ("# Per axis (the field holds the worst axis, kalibr#143):\n"
            + _axes_comment("accelerometer N", a["n"], "m/s^2/sqrt(Hz)")
            + _axes_comment("accelerometer K", a["k"], "m/s^3/sqrt(Hz)")
            + _axes_comment("gyroscope N", g["n"], "rad/s/sqrt(Hz)")
            + _axes_comment("gyroscope K", g["k"], "rad/s^2/sqrt(Hz)")
            + "".join(f"#   {kind} K, axis {ax}: {how}\n" for kind in ("accel", "gyro")
                      for ax, how in zip(AXES, t[kind]["k_how"]) if not how.startswith("read")))


def kalibr_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    return (_header(res, "Kalibr imu.yaml") + _per_axis(t) + INFLATE
            + f"rostopic: {topic}\n"
            + f"update_rate: {res['rate_hz']:.6g}  # Hz\n"
            + f"accelerometer_noise_density: {t['accel']['n_worst']:.6g}  # m/s^2/sqrt(Hz)\n"
            + f"accelerometer_random_walk: {t['accel']['k_worst']:.6g}  # m/s^3/sqrt(Hz)\n"
            + f"gyroscope_noise_density: {t['gyro']['n_worst']:.6g}  # rad/s/sqrt(Hz)\n"
            + f"gyroscope_random_walk: {t['gyro']['k_worst']:.6g}  # rad/s^2/sqrt(Hz)\n")


def openvins_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    eye = "\n".join(f"    - [{', '.join('1.0' if i == j else '0.0' for j in range(4))}]" for i in range(4))
    return ("%YAML:1.0\n" + _header(res, "OpenVINS kalibr_imu_chain.yaml") + _per_axis(t) + INFLATE
            + "# model 'calibrated': the intrinsics are already applied (imubench's calibrated stream)\n"
            + "imu0:\n"
            + "  T_i_b:\n" + eye + "\n"
            + f"  accelerometer_noise_density: {t['accel']['n_worst']:.6g}  # m/s^2/sqrt(Hz)\n"
            + f"  accelerometer_random_walk: {t['accel']['k_worst']:.6g}  # m/s^3/sqrt(Hz)\n"
            + f"  gyroscope_noise_density: {t['gyro']['n_worst']:.6g}  # rad/s/sqrt(Hz)\n"
            + f"  gyroscope_random_walk: {t['gyro']['k_worst']:.6g}  # rad/s^2/sqrt(Hz)\n"
            + f"  rostopic: {topic}\n"
            + "  time_offset: 0.0\n"
            + f"  update_rate: {res['rate_hz']:.6g}  # Hz\n"
            + "  model: calibrated\n")


def vins_fusion_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    return ("%YAML:1.0\n" + _header(res, "VINS-Fusion (the IMU keys of its config file)") + _per_axis(t) + INFLATE
            + f"# the IMU streams at {res['rate_hz']:.6g} Hz\n"
            + f"imu_topic: \"{topic}\"\n"
            + f"acc_n: {t['accel']['n_worst']:.6g}  # accelerometer noise density, m/s^2/sqrt(Hz)\n"
            + f"gyr_n: {t['gyro']['n_worst']:.6g}  # gyroscope noise density, rad/s/sqrt(Hz)\n"
            + f"acc_w: {t['accel']['k_worst']:.6g}  # accelerometer bias random walk, m/s^3/sqrt(Hz)\n"
            + f"gyr_w: {t['gyro']['k_worst']:.6g}  # gyroscope bias random walk, rad/s^2/sqrt(Hz)\n"
            + f"g_norm: {G0}  # m/s^2, standard gravity (use your site's value if you know it)\n")


def imu_utils_text(res: dict, name: str) -> str:
    t = noise_terms(res)

    def block(kind: str, unit: str, n_key: str, w_key: str) -> str:
        d = t[kind]
        b = d["b"]
        bw = max((v for v in b if v is not None), default=None)
        lines = [f"{'Gyr' if kind == 'gyro' else 'Acc'}:", f"   unit: \" {unit}\"",
                 "   avg-axis:", f"      {n_key}: {sum(d['n']) / 3:.6g}",
                 f"      {w_key}: " + (_num(sum(v for v in b if v is not None) / sum(v is not None for v in b))
                                       if bw is not None else ".nan  # B withheld: the record is too short")]
        for ax, n, bv in zip(AXES, d["n"], b):
            lines += [f"   {ax}-axis:", f"      {n_key}: {n:.6g}",
                      f"      {w_key}: " + (".nan  # B withheld: the record is too short" if bv is None else _num(bv))]
        return "\n".join(lines) + "\n"
    return ("%YAML:1.0\n" + _header(res, "imu_utils output") + _per_axis(t) + INFLATE
            + "# As imu_utils writes it: *_n the white noise density, *_w the Allan MINIMUM (bias instability B),\n"
            + "# NOT a random walk (imu_utils src/gyr_lib/fitallan_gyr.cpp). For a random walk use K above.\n"
            + "# Its avg-axis is the mean of the axes (imu_utils' own choice).\n"
            + "---\n"
            + "type: IMU\n"
            + f"name: {name}\n"
            + block("gyro", "gyr_n: rad / s, gyr_w: rad / s", "gyr_n", "gyr_w")
            + block("accel", "acc_n: m / s^2, acc_w: m / s^2", "acc_n", "acc_w"))


def write_noise(kind: str, path, res: dict, *, topic: str = "/imu0", name: str = "imu") -> Path:
    """Write one consumer's file; returns its path."""
    if kind not in NOISE_WRITERS:
        raise ValueError(f"unknown noise export {kind!r}; one of {', '.join(NOISE_WRITERS)}")
    text = {"kalibr": lambda: kalibr_text(res, topic), "openvins": lambda: openvins_text(res, topic),
            "vins-fusion": lambda: vins_fusion_text(res, topic), "imu-utils": lambda: imu_utils_text(res, name)}[kind]()
    return write_text_atomic(Path(path), text)
