"""Noise figures (an Allan analysis, imubench.analysis.allan) in the files the estimators read.

    write_noise(kind, path, res, topic=...)      kind in NOISE_WRITERS; res: allan.json's dict

Each file holds what its consumer's own code takes (docs/noise.md; the consumers' sources named
there). Kalibr and OpenVINS want **continuous-time** figures: white noise as its Allan coefficient
N (the density: m/s²/√Hz, rad/s/√Hz; σ of one sample at rate f is N·√f) and the bias random walk
K (m/s³/√Hz, rad/s²/√Hz: ADEV(τ) = K·√(τ/3)). VINS-Fusion's integration_base.h uses its acc_n,
gyr_n as the σ of one sample and acc_w, gyr_w as the σ of one step's bias increment over dt:
the file holds N·√f and K·√f. imu_utils' own output (src/gyr_lib/fitallan_gyr.cpp) holds
`*_n` = N·√f and `*_w` = the Allan deviation's minimum (0.664·B, not a random walk): the
imu-utils file writes exactly that and names it. One field takes one number: the worst axis
goes in it, the three axes are in comments (kalibr#143). When the record shows no +1/2 slope,
K is not read off; the file then holds the upper bound the longest τ allows,
K ≤ ADEV(τ_max)·√(3/τ_max), and says so.

OpenVINS' VioManagerOptions.h requires Tw, Ta, R_IMUtoACC, R_IMUtoGYRO and Tg for every IMU model
(it stops with "unable to parse all parameters" otherwise): the file is for imubench's
calibrated stream, so they are identities and Tg zero.

Quoted names (the recording's, the topic) are made safe (imubench.text: comment, token).

The usual advice to inflate these for an estimator (several times, for unmodelled effects:
vibration, temperature, the bias's own model) is written as a comment with its sources (kalibr
issue #663, allan_variance_ros issue #44) and never applied to the numbers.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from imubench.results.atomic import write_text_atomic
from imubench.results.exports import names
from imubench.text import comment, token

NOISE_WRITERS = names("noise")              # the export registry's (results.exports)
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


def _n_how(ax: dict) -> str:
    """How N of one axis was obtained: read off the −1/2 line, or an upper bound (analysis.allan)."""
    w = ax.get("white") or {}
    return "read off the -1/2 slope" if w.get("ok", True) else f"UPPER BOUND: {w.get('reason') or 'no -1/2 slope'}"


def noise_terms(res: dict) -> dict:
    """{'accel'|'gyro': {'n': [3], 'k': [3], 'b': [3 or None], 'n_how', 'k_how': [3], 'n_worst', 'k_worst',
    'n_bound', 'k_bound'}} in SI; *_bound: the worst axis's figure (the one a file holds) is an upper
    bound, not a read-off."""
    out = {}
    for kind in ("accel", "gyro"):
        axes = [res[kind][a] for a in AXES]
        n = [float(a["N"]) for a in axes]
        ks = [_k_of(a) for a in axes]
        n_how = [_n_how(a) for a in axes]
        k_how = [h for _, h in ks]
        i_n = int(np.argmax(n))
        i_k = int(np.argmax([k for k, _ in ks]))
        out[kind] = {"n": n, "k": [k for k, _ in ks], "n_how": n_how, "k_how": k_how,
                     "b": [None if a.get("B") is None else float(a["B"]) for a in axes],
                     "n_worst": max(n), "k_worst": max(k for k, _ in ks),
                     "n_bound": not n_how[i_n].startswith("read"), "k_bound": not k_how[i_k].startswith("read")}
    return out


def _mark(bound: bool) -> str:
    """The words after a field's unit when the figure it holds is an upper bound."""
    return "; UPPER BOUND, not a read-off (see above)" if bound else ""


def _axes_comment(label: str, vals, unit: str) -> str:
    return f"#   {label}: " + ", ".join(f"{a} {v:.4g}" if v is not None else f"{a} -" for a, v in zip(AXES, vals)) \
        + f" {unit}\n"


def _header(res: dict, consumer: str) -> str:
    src = ", ".join(map(str, res.get("source", []))) or "?"
    still = res.get("still") or {}
    part = "" if not still or still.get("whole") else comment(
        f"Only a part of the recording is still: the longest still stretch, {still['t_start_s']:.1f} s to "
        f"{still['t_start_s'] + still['duration_s']:.1f} s ({100 * still['fraction']:.0f} % of it; "
        f"{still['stretches']} still stretches found, as calibrate --from finds rests), is analysed.") + "\n"
    t = noise_terms(res)
    bounds = [f"{kind} {w}" for kind in ("accel", "gyro") for w in ("N", "K") if t[kind][f"{w.lower()}_bound"]]
    bound = "" if not bounds else comment(
        f"UPPER BOUNDS, not read-offs: {', '.join(bounds)} (the record shows no slope to read them from; "
        "the true figure is at most this). Record longer, still, to read them.") + "\n"
    return (comment(f"{consumer} noise parameters from imubench's Allan analysis of {src}") + "\n"
            + f"# ({res.get('samples', 0)} samples at {res['rate_hz']:.6g} Hz, {res['duration_s'] / 3600:.3g} h; "
            "docs/noise.md). Allan figures: density N (sample sigma = N*sqrt(rate)), random walk K.\n"
            + part + bound)


def _matrix(m) -> str:
    return "".join(f"    - [{', '.join(f'{v:.12g}' for v in row)}]\n" for row in np.asarray(m, float))


def _per_axis(t: dict) -> str:
    a, g = t["accel"], t["gyro"]
    return ("# Per axis (the field holds the worst axis, kalibr#143):\n"
            + _axes_comment("accelerometer N", a["n"], "m/s^2/sqrt(Hz)")
            + _axes_comment("accelerometer K", a["k"], "m/s^3/sqrt(Hz)")
            + _axes_comment("gyroscope N", g["n"], "rad/s/sqrt(Hz)")
            + _axes_comment("gyroscope K", g["k"], "rad/s^2/sqrt(Hz)")
            + "".join(comment(f"  {kind} {what}, axis {ax}: {how}") + "\n" for kind in ("accel", "gyro")
                      for what in ("N", "K") for ax, how in zip(AXES, t[kind][f"{what.lower()}_how"])
                      if not how.startswith("read")))


def kalibr_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    return (_header(res, "Kalibr imu.yaml") + _per_axis(t) + INFLATE
            + f"rostopic: \"{token(topic)}\"\n"
            + f"update_rate: {res['rate_hz']:.6g}  # Hz\n"
            + f"accelerometer_noise_density: {t['accel']['n_worst']:.6g}  # m/s^2/sqrt(Hz)"
            + _mark(t['accel']['n_bound']) + "\n"
            + f"accelerometer_random_walk: {t['accel']['k_worst']:.6g}  # m/s^3/sqrt(Hz)"
            + _mark(t['accel']['k_bound']) + "\n"
            + f"gyroscope_noise_density: {t['gyro']['n_worst']:.6g}  # rad/s/sqrt(Hz)"
            + _mark(t['gyro']['n_bound']) + "\n"
            + f"gyroscope_random_walk: {t['gyro']['k_worst']:.6g}  # rad/s^2/sqrt(Hz)"
            + _mark(t['gyro']['k_bound']) + "\n")


def openvins_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    eye = "\n".join(f"    - [{', '.join('1.0' if i == j else '0.0' for j in range(4))}]" for i in range(4))
    return ("%YAML:1.0\n" + _header(res, "OpenVINS kalibr_imu_chain.yaml") + _per_axis(t) + INFLATE
            + "# model 'calibrated': the intrinsics are already applied (imubench's calibrated stream), so\n"
            + "# Tw = Ta = R_IMUtoACC = R_IMUtoGYRO = I and Tg = 0 (ov_msckf VioManagerOptions.h requires all five)\n"
            + "imu0:\n"
            + "  T_i_b:\n" + eye + "\n"
            + "".join(f"  {key}:\n" + _matrix(np.eye(3) if key != "Tg" else np.zeros((3, 3)))
                      for key in ("Tw", "R_IMUtoGYRO", "Ta", "R_IMUtoACC", "Tg"))
            + f"  accelerometer_noise_density: {t['accel']['n_worst']:.6g}  # m/s^2/sqrt(Hz)"
            + _mark(t['accel']['n_bound']) + "\n"
            + f"  accelerometer_random_walk: {t['accel']['k_worst']:.6g}  # m/s^3/sqrt(Hz)"
            + _mark(t['accel']['k_bound']) + "\n"
            + f"  gyroscope_noise_density: {t['gyro']['n_worst']:.6g}  # rad/s/sqrt(Hz)"
            + _mark(t['gyro']['n_bound']) + "\n"
            + f"  gyroscope_random_walk: {t['gyro']['k_worst']:.6g}  # rad/s^2/sqrt(Hz)"
            + _mark(t['gyro']['k_bound']) + "\n"
            + f"  rostopic: \"{token(topic)}\"\n"
            + "  time_offset: 0.0\n"
            + f"  update_rate: {res['rate_hz']:.6g}  # Hz\n"
            + "  model: calibrated\n")


def vins_fusion_text(res: dict, topic: str) -> str:
    t = noise_terms(res)
    root_f = math.sqrt(float(res["rate_hz"]))
    return ("%YAML:1.0\n" + _header(res, "VINS-Fusion (the IMU keys of its config file)") + _per_axis(t) + INFLATE
            + "# VINS-Fusion (integration_base.h) uses acc_n, gyr_n as the sigma of ONE sample and acc_w, gyr_w\n"
            + "# as the sigma of one step's bias increment over dt: they hold N*sqrt(f) and K*sqrt(f), f = the IMU\n"
            + f"# rate, {res['rate_hz']:.6g} Hz here (at another rate multiply N, K above by sqrt(rate)).\n"
            + f"imu_topic: \"{token(topic)}\"\n"
            + f"acc_n: {t['accel']['n_worst'] * root_f:.6g}  # accelerometer sample sigma N*sqrt(f), m/s^2"
            + _mark(t['accel']['n_bound']) + "\n"
            + f"gyr_n: {t['gyro']['n_worst'] * root_f:.6g}  # gyroscope sample sigma N*sqrt(f), rad/s"
            + _mark(t['gyro']['n_bound']) + "\n"
            + f"acc_w: {t['accel']['k_worst'] * root_f:.6g}  # accelerometer bias random walk K*sqrt(f), m/s^3"
            + _mark(t['accel']['k_bound']) + "\n"
            + f"gyr_w: {t['gyro']['k_worst'] * root_f:.6g}  # gyroscope bias random walk K*sqrt(f), rad/s^2"
            + _mark(t['gyro']['k_bound']) + "\n"
            + f"g_norm: {G0}  # m/s^2, standard gravity (use your site's value if you know it)\n")


ADEV_MIN_PER_B = 0.664                # B = min ADEV / 0.664 (imubench.analysis.allan); imu_utils keeps the minimum


def imu_utils_text(res: dict, name: str) -> str:
    t = noise_terms(res)
    root_f = math.sqrt(float(res["rate_hz"]))

    def block(kind: str, unit: str, n_key: str, w_key: str) -> str:
        d = t[kind]
        n = [v * root_f for v in d["n"]]
        w = [None if v is None else v * ADEV_MIN_PER_B for v in d["b"]]
        known = [v for v in w if v is not None]
        nan = ".nan  # withheld: the record is too short to show the minimum"
        bound = [not h.startswith("read") for h in d["n_how"]]
        lines = [f"{'Gyr' if kind == 'gyro' else 'Acc'}:", f"   unit: \" {unit}\"",
                 "   avg-axis:", f"      {n_key}: {sum(n) / 3:.6g}" + ("  # UPPER BOUND" if any(bound) else ""),
                 f"      {w_key}: " + (_num(sum(known) / len(known)) if known else nan)]
        for ax, nv, wv, nb in zip(AXES, n, w, bound):
            lines += [f"   {ax}-axis:", f"      {n_key}: {nv:.6g}" + ("  # UPPER BOUND" if nb else ""),
                      f"      {w_key}: " + (nan if wv is None else _num(wv))]
        return "\n".join(lines) + "\n"
    return ("%YAML:1.0\n" + _header(res, "imu_utils output") + _per_axis(t) + INFLATE
            + "# What imu_utils writes (src/gyr_lib/fitallan_gyr.cpp, src/acc_lib/fitallan_acc.cpp):\n"
            + f"# *_n = N*sqrt(f), the sigma of one sample at f = {res['rate_hz']:.6g} Hz (getWhiteNoise);\n"
            + "# *_w = the MINIMUM of the Allan deviation (getBiasInstability; = 0.664*B), NOT a random walk:\n"
            + "# for a random walk use K above. avg-axis is the mean of the axes (imu_utils' own choice).\n"
            + "---\n"
            + "type: IMU\n"
            + f"name: \"{token(name)}\"\n"
            + block("gyro", "gyr_n: rad / s, gyr_w: rad / s", "gyr_n", "gyr_w")
            + block("accel", "acc_n: m / s^2, acc_w: m / s^2", "acc_n", "acc_w"))


def write_noise(kind: str, path, res: dict, *, topic: str = "/imu0", name: str = "imu") -> Path:
    """Write one consumer's file; returns its path."""
    if kind not in NOISE_WRITERS:
        raise ValueError(f"unknown noise export {kind!r}; one of {', '.join(NOISE_WRITERS)}")
    from imubench.results import exports as X
    text = {"kalibr": lambda: kalibr_text(res, topic), "openvins": lambda: openvins_text(res, topic),
            "vins-fusion": lambda: vins_fusion_text(res, topic), "imu-utils": lambda: imu_utils_text(res, name)}[kind]()
    return write_text_atomic(Path(path), X.stamp(text, X.get("noise", kind)))


def write_noise_files(kinds, out_dir, res: dict, *, topic: str = "/imu0", name: str = "imu") -> dict:
    """Each consumer's file of `kinds` into out_dir under the registry's file name (results.exports),
    and the index beside them; returns {kind: path as str}."""
    from imubench.results import exports as X
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    files = {k: str(write_noise(k, Path(out_dir) / X.file_names("noise", k)[0], res, topic=topic, name=name))
             for k in dict.fromkeys(kinds)}
    if files:
        X.write_index(out_dir, "noise", {k: [v] for k, v in files.items()}, f"noise figures of {name}")
    return files
