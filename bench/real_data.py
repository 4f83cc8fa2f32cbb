#!/usr/bin/env python3
"""imubench on real data no one here recorded: imucal's public example Ferraris session.

    python bench/real_data.py [--no-publish]   (figures for README.md and docs/calibration.md)

Data: tests/data/imucal/ (MIT, mad-lab-fau/imucal example_data; README there). Two files:
the session in m/s² and °/s at 102.4 Hz (six faces, then three 360° hand turns), and a file in
raw counts at 204.8 Hz cut into the named parts of a session, with imucal's own calibration of
it (imucal's tests). There is no ground truth: what is printed is what the data can say —
the automatic segmentation against one person's annotation, the fits with their sigmas, |a| − g
per rest before and after (and on rests the fit did not use), each turn's integrated angle
before and after, the multi-position refusal, imubench's counts fit beside imucal's, and the
SI file beside the counts file. Prints and publishes (bench/publish.py) the two markdown
tables README.md and docs/calibration.md state. The last line is JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "host"))

import numpy as np  # noqa: E402
from imubench.calib import CalibrationError  # noqa: E402
from imubench.calib import accel as CA  # noqa: E402
from imubench.procedures.from_file import FileAnalysis, FileConfig  # noqa: E402
from imubench.recordings import read  # noqa: E402
from imubench.recordings.readers import read_annotation  # noqa: E402
from imubench.units import G0_MPS2  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

DATA = ROOT / "tests" / "data" / "imucal"
SI_FILE = DATA / "example_ferraris_session.csv.gz"
COUNTS_FILE = DATA / "annotated_session.csv.gz"
ANNOTATION = DATA / "example_ferraris_session_list.json"
IMUCAL_CAL = DATA / "imucal_example_cal.json"


def _quiet(_s):
    pass


def si_figures() -> dict:
    """The SI session: segmentation, six-position and known-angle fits, multi refused, held-out rests."""
    rec = read(SI_FILE, rate_hz=102.4, accel_unit="mps2", gyro_unit="dps")
    ann = read_annotation(ANNOTATION)
    fa = FileAnalysis(rec, FileConfig(method="six", gyro="turns", annotation=ann), say=_quiet)
    res = fa.run()
    means = np.array([i.mean for i in fa.intervals])
    sig = np.array([i.sigma_mean for i in fa.intervals])
    # the multi-position method on these poses: refused, and why
    try:
        CA.check_observability(means, "multi_position")
        multi = "accepted"
    except CalibrationError as e:
        multi = str(e)
    # held out: fit on one rest per face (the longest), |a| - g on the rests not used
    best = {}
    for k, f in enumerate(fa.faces):
        if f not in best or fa.intervals[k].n > fa.intervals[best[f]].n:
            best[f] = k
    used = sorted(best.values())
    held = [k for k in range(len(means)) if k not in used]
    fit6 = CA.six_position(means[used], sig[used])
    held_after = (np.linalg.norm(fit6.correct(means[held]), axis=1) - G0_MPS2) / G0_MPS2 * 1e3
    held_before = (np.linalg.norm(means[held], axis=1) - G0_MPS2) / G0_MPS2 * 1e3
    return {"result": res, "analysis": fa, "multi_refusal": multi,
            "held_out": {"faces_used": [fa.faces[k] for k in used], "rests": [fa.faces[k] for k in held],
                         "before_mg": held_before.tolist(), "after_mg": held_after.tolist(),
                         "rms_after_mg": float(np.sqrt(np.mean(held_after ** 2)))}}


def counts_figures() -> dict:
    """The counts file: the same analysis, scales in counts per unit, beside imucal's own fit."""
    rec = read(COUNTS_FILE, rate_hz=204.8, accel_unit="counts", gyro_unit="counts")
    fa = FileAnalysis(rec, FileConfig(method="six", gyro="turns"), say=_quiet)
    res = fa.run()
    ref = json.loads(IMUCAL_CAL.read_text())
    ka, ra, kg, rg = (np.array(ref[k]) for k in ("K_a", "R_a", "K_g", "R_g"))
    imucal_acc = ka @ ra * G0_MPS2                # counts per g (imucal: K in counts per m/s²)
    imucal_gyr = kg @ rg                          # counts per °/s
    ours_acc = np.asarray(res["accel_counts_per_g"])
    ours_gyr = np.asarray(res["gyro_counts_per_dps"])
    sig_acc = fa.accel.sigma_m / fa.fa * G0_MPS2
    sig_gyr = fa.gyro.sigma_m / fa.fg * math.pi / 180
    return {"result": res, "analysis": fa, "imucal_acc": imucal_acc, "imucal_gyr": imucal_gyr,
            "ours_acc": ours_acc, "ours_gyr": ours_gyr, "z_acc": (ours_acc - imucal_acc) / sig_acc,
            "z_gyr": (ours_gyr - imucal_gyr) / sig_gyr, "sig_acc": sig_acc, "sig_gyr": sig_gyr}


def scale_free(fit, factor_si_per_unit: float, g_unit_per_g: float):
    """Quantities that do not depend on the files' nominal scales: M with its rows divided by
    the diagonal (cross-axis terms), the scale ratios M_yy/M_xx and M_zz/M_xx, and each bias in
    units of its own axis's scale (in g for the accelerometer)."""
    m = fit.m
    d = np.diag(m)
    return {"cross": (m / d[:, None]), "ratios": np.array([d[1] / d[0], d[2] / d[0]]),
            "bias_own_scale": fit.b / d / g_unit_per_g}


def si_vs_counts(si: dict, counts: dict) -> dict:
    a, b = si["analysis"], counts["analysis"]
    out = {}
    for kind, fs_, fc_ in (("accel", a.accel, b.accel), ("gyro", a.gyro, b.gyro)):
        unit = G0_MPS2 if kind == "accel" else math.pi / 180
        s, c = scale_free(fs_, 1.0, unit), scale_free(fc_, 1.0, unit)
        ss = fs_.sigma_m / np.diag(fs_.m)[:, None]
        sc = fc_.sigma_m / np.diag(fc_.m)[:, None]
        zc = (s["cross"] - c["cross"]) / np.sqrt(ss ** 2 + sc ** 2)
        np.fill_diagonal(zc, 0.0)
        sb = np.sqrt((fs_.sigma_b / np.diag(fs_.m)) ** 2 + (fc_.sigma_b / np.diag(fc_.m)) ** 2) / unit
        zb = (s["bias_own_scale"] - c["bias_own_scale"]) / sb
        out[kind] = {"cross_si": s["cross"], "cross_counts": c["cross"], "z_cross": zc,
                     "bias_si": s["bias_own_scale"], "bias_counts": c["bias_own_scale"], "z_bias": zb}
    return out


# ------------------------------------------------------------------ every real recording: the gyro's residual
SHARED = Path(__import__("os").environ.get("IMUBENCH_REAL_DATA", str(ROOT.parent.parent / "shared" / "data")))
# (name, path, read options): the recordings of other IMUs that can be read without asking (units,
# rate as their READMEs state them); shared ones are used when ../shared/data is there
MIKOFF = ROOT / "tests" / "data" / "mikoff"        # gzip copies of ../shared/data/mikoff (MIT)


def _mikoff(name: str) -> Path:
    shared = SHARED / "mikoff" / name
    return shared if shared.exists() else MIKOFF / f"{name}.gz"


RECORDINGS = [
    ("mikoff imu0 (MPU-9150)", _mikoff("imu0.log"), {"rate_hz": 100.0, "accel_unit": "mps2", "gyro_unit": "rad_s"}),
    ("mikoff imu1 (MPU-9150)", _mikoff("imu1.log"), {"rate_hz": 100.0, "accel_unit": "mps2", "gyro_unit": "rad_s"}),
    ("imucal Ferraris (SI)", SI_FILE, {"rate_hz": 102.4, "accel_unit": "mps2", "gyro_unit": "dps"}),
    ("imucal annotated (counts)", COUNTS_FILE, {"rate_hz": 204.8, "accel_unit": "counts", "gyro_unit": "counts"}),
]
VARIANTS = ("one start bias", "all rests' mean bias", "between-rests bias", "G", "G + between-rests bias")


def _folds(n: int) -> list[list[int]]:
    return [list(range(0, n, 2)), list(range(1, n, 2))]


def gyro_residuals(path, opts) -> dict:
    """The rotation method's residual (angle between predicted and measured gravity after each
    motion, °) on one recording, in sample and on held-out motions (two folds: fit on the even
    motions, evaluate on the odd ones and back), for four models of the bias during a motion:
    the first rest's (one start bias), the mean of the two rests around the motion, b + G·f(t)
    with G fitted on all the rests, and b + G·f(t) with the remaining rest-to-rest change
    interpolated. G's fit (with σ) or why it was refused."""
    from imubench.calib import gyro as CG
    from imubench.calib.gsens import fit_gsens
    rec = read(path, **opts)
    fa = FileAnalysis(rec, FileConfig(gyro="auto"), say=_quiet)
    fa.run()
    fs = rec.fs_hz
    if fa.fg is None:
        return {"refused": "the gyro has no scale (counts without turns to scale them)"}
    gyr = rec.gyro * fa.fg
    acc_g = fa.accel.correct(rec.accel * fa.fa) / G0_MPS2            # calibrated specific force, g
    iv = [(i.start, i.stop) for i in fa.intervals]
    k = len(iv)
    up = np.array([acc_g[a:z].mean(axis=0) for a, z in iv])
    f_rest = up.copy()
    up = up / np.linalg.norm(up, axis=1)[:, None]
    brk = [b for b, _ in rec.breaks]
    broken = [j for j in range(k - 1) if any(iv[j][1] - 1 < b <= iv[j + 1][0] for b in brk)]
    out = {"rests": k, "motions": k - 1 - len(broken), "excluded": broken}
    if k - 1 - len(broken) < 2 * CG.MIN_MOTIONS:
        out["refused"] = (f"{k - 1 - len(broken)} continuous motions between rests: too few for the rotation method "
                          f"in two folds ({2 * CG.MIN_MOTIONS} needed)")
        return out
    means = np.array([gyr[a:z].mean(axis=0) for a, z in iv])
    sig = np.array([CG._mean_uncertainty(gyr[a:z], min_cluster=max(1, int(0.02 * fs)))["sigma"] for a, z in iv])
    rest0 = CG.gyro_bias(gyr[iv[0][0]:iv[0][1]], fs)
    try:
        gs = fit_gsens(means, sig, f_rest)
        out["G_dps_per_g"] = (gs.g * 180 / math.pi).tolist()
        out["G_sigma_dps_per_g"] = (gs.sigma_g * 180 / math.pi).tolist()
        out["G_resolved"] = gs.resolved.tolist()
        out["G_summary"] = gs.summary()
        out["rest_scatter_dps"] = {"one bias": float(np.sqrt(np.mean((means - means.mean(0)) ** 2)) * 180 / math.pi),
                                   "b + G·f": gs.extra["rest_scatter_dps"]}
    except CalibrationError as e:
        gs = None
        out["G_refused"] = str(e)
    series = {}
    between = 0.5 * (means[:-1] + means[1:])
    series["one start bias"] = (gyr, np.broadcast_to(rest0.b, (k - 1, 3)))
    series["all rests' mean bias"] = (gyr, np.broadcast_to(np.average(means, axis=0, weights=1 / sig**2),
                                                           (k - 1, 3)))   # control: what averaging alone gives
    series["between-rests bias"] = (gyr, between)
    if gs is not None:
        ug = gyr - acc_g @ gs.g.T
        mg = np.array([ug[a:z].mean(axis=0) for a, z in iv])
        series["G"] = (ug, np.broadcast_to(gs.b, (k - 1, 3)))
        series["G + between-rests bias"] = (ug, 0.5 * (mg[:-1] + mg[1:]))
    res = {}
    for name, (u, mb) in series.items():
        row = {}
        try:
            f = CG.rotation_method(u, fs, iv, up, rest0, motion_bias=mb, exclude_motions=broken, max_sigma=1.0,
                                   max_residual_deg=90.0, max_rate_rad_s=None)
            row["in_sample_rms_deg"] = float(np.sqrt(np.mean(f.extra["angle_residuals_deg"] ** 2)))
            row["m_diag"] = np.diag(f.m).tolist()
        except CalibrationError as e:
            row["in_sample_refused"] = str(e)
        held = []
        usable = [j for j in range(k - 1) if j not in broken]
        for fold in _folds(len(usable)):
            test = [usable[i] for i in fold]
            try:
                f = CG.rotation_method(u, fs, iv, up, rest0, motion_bias=mb, exclude_motions=broken + test,
                                       max_sigma=1.0, max_residual_deg=90.0, max_rate_rad_s=None)
            except CalibrationError as e:
                row["held_out_refused"] = str(e)
                break
            ang = CG.rotation_residuals(u, fs, iv, up, f.m, mb)
            held.extend(ang[test].tolist())
        if "held_out_refused" not in row:
            row["held_out_rms_deg"] = float(np.sqrt(np.mean(np.square(held))))
        res[name] = row
    out["variants"] = res
    return out


def all_recordings() -> list[tuple[str, dict]]:
    out = []
    for name, path, opts in RECORDINGS:
        if not Path(path).exists():
            out.append((name, {"refused": f"{path} not here"}))
            continue
        out.append((name, gyro_residuals(path, opts)))
    return out


def print_gyro_residuals(rows) -> None:
    print("\n== the gyro on every real recording: rotation-method residual (angle between predicted and measured "
          "gravity after each motion, RMS °) ==")
    print(f"{'recording':<28} {'motions':>7}  " + "  ".join(f"{v:>22}" for v in VARIANTS))
    print(f"{'':<28} {'':>7}  " + "  ".join(f"{'in sample / held out':>22}" for _ in VARIANTS))
    for name, r in rows:
        if "variants" not in r:
            print(f"{name:<28} {r.get('motions', '-'):>7}  {r['refused']}")
            continue
        cells = []
        for v in VARIANTS:
            c = r["variants"].get(v)
            if c is None:
                cells.append(f"{'(no G)':>22}")
                continue
            a = f"{c['in_sample_rms_deg']:.3f}" if "in_sample_rms_deg" in c else "refused"
            b = f"{c['held_out_rms_deg']:.3f}" if "held_out_rms_deg" in c else "refused"
            cells.append(f"{a + ' / ' + b:>22}")
        print(f"{name:<28} {r['motions']:>7}  " + "  ".join(cells))
    for name, r in rows:
        for v, c in r.get("variants", {}).items():
            for key in ("in_sample_refused", "held_out_refused"):
                if key in c:
                    print(f"{name}, {v}: {key.split('_refused')[0].replace('_', ' ')} refused: {c[key]}")
    for name, r in rows:
        if "G_summary" in r:
            sc = r["rest_scatter_dps"]
            print(f"{name}: {r['G_summary']}\n  rest-to-rest gyro scatter: {sc['one bias']:.4f} °/s about one "
                  f"bias, {sc['b + G·f']:.4f} °/s about b + G·f")
        elif "G_refused" in r:
            print(f"{name}: G not fitted: {r['G_refused']}")


def _deg(v: float) -> str:
    return f"{v:.2f}°".replace("-", "−")


def _range(vals, fmt: str) -> str:
    lo, hi = min(vals), max(vals)
    return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else fmt.format(lo) + "–" + fmt.format(hi)


def imucal_table(si: dict, c: dict, x: dict) -> str:
    """The figures README states for imucal's example session, as a markdown table."""
    r, h, fa = si["result"], si["held_out"], si["analysis"]
    turns = [t for t in r["turns"] if t["usable"]]
    found = [a for a in r["annotation"] if a["found"]]
    ends = [abs(v) for a in found for v in (a["start_diff_s"], a["stop_diff_s"])]
    before = np.sqrt(np.mean([(p["before_g"] - 1) ** 2 for p in r["poses"]])) * 1e3
    am, asig = np.diag(fa.accel.m), np.diag(fa.accel.sigma_m)
    gm, gsig = np.diag(fa.gyro.m), np.diag(fa.gyro.sigma_m)
    m = re.search(r"(\d+) distinct attitudes.*?needs at least (\d+)", si["multi_refusal"])
    multi = (f"refused: {m.group(1)} distinct attitudes, {m.group(2)} needed" if m
             else si["multi_refusal"].replace("|", "\\|"))
    zb = np.abs(np.concatenate([x["accel"]["z_bias"], x["gyro"]["z_bias"]]))
    rows = [
        ("segmentation without the annotation",
         f"{len(r['segmentation'])} rests ({len(set(s_['face'] for s_ in r['segmentation']))} faces) and "
         f"{len(turns)} turns; {len(found)} of {len(r['annotation'])} annotated sections found, ends "
         f"{_range(ends, '{:.1f}')} s apart"),
        (f"six-position, \\|a\\| − g RMS over the {len(r['poses'])} rests",
         f"{before:.1f} mg before, {r['accel_rms_after_mg']:.1f} mg after; {h['rms_after_mg']:.1f} mg on "
         f"{len(h['rests'])} rests held out of the fit"),
        ("accelerometer M diagonal ± σ",
         ", ".join(f"{v:.5f}" if s_ < 0.001 else f"{v:.4f}" for v, s_ in zip(am, asig))
         + f" ± {_range(asig, '{:.4f}')}"),
        (f"turns, integrated before → after ({fa.gyro.method.replace('+', ' + ')} fit)",
         " / ".join(_deg(t["before_deg"]) for t in turns) + " → "
         + " / ".join(_deg(t["after_deg"]) for t in turns if "after_deg" in t)
         + f" (σ {_range([t['sigma_deg'] for t in turns if 'sigma_deg' in t], '{:.2f}')}°)"),
        (f"gyro scale ± σ ({fa.gyro.method.replace('+', ' + ')})", ", ".join(f"{v:.4f}" for v in gm) + f" ± {_range(gsig, '{:.4f}')}"),
        ("multi-position on six faces", multi),
        ("counts file vs imucal's own fit",
         f"accelerometer 9 entries within {np.abs(c['z_acc']).max():.2f} σ; gyro scales within "
         f"{np.abs(np.diag(c['z_gyr'])).max():.1f} σ, cross terms within {np.abs(c['z_gyr']).max():.1f} σ"),
        ("SI file vs counts file",
         f"not the same recording: biases differ by {zb.min():.0f}–{zb.max():.0f} σ in scale-free units"),
    ]
    return "| what | figure |\n|---|---|\n" + "".join(f"| {a} | {b} |\n" for a, b in rows)


def gyro_table(rows) -> str:
    """The rotation method's residual on every real recording, as a markdown table."""
    out = "| recording | motions | " + " | ".join(VARIANTS) + " |\n|---|---|" + "---|" * len(VARIANTS) + "\n"
    for name, r in rows:
        if "variants" not in r:
            out += f"| {name} | {r.get('motions', '–')} | {r['refused']} |" + " |" * (len(VARIANTS) - 1) + "\n"
            continue
        cells = []
        for v in VARIANTS:
            c = r["variants"].get(v)
            if c is None:
                cells.append("G not fitted")
                continue
            a = f"{c['in_sample_rms_deg']:.3f}°" if "in_sample_rms_deg" in c else "not resolved"
            b = f"{c['held_out_rms_deg']:.3f}°" if "held_out_rms_deg" in c else "not resolved"
            cells.append(f"{a} / {b}")
        out += f"| {name} | {r['motions']} | " + " | ".join(cells) + " |\n"
    return out


def _m(m, fmt="{:+9.5f}") -> str:
    return "\n".join("    " + " ".join(fmt.format(v) for v in row) for row in np.asarray(m))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    a = ap.parse_args()
    from imubench.results.calibration import params_table
    from imubench.results.recording import annotation_table, segmentation_table, turns_table
    si = si_figures()
    r = si["result"]
    print(f"== imucal's example session, m/s² and °/s at 102.4 Hz ({SI_FILE.name}) ==\n")
    print(segmentation_table(r))
    print()
    print(turns_table(r))
    print()
    print(annotation_table(r))
    print()
    print(params_table(r))
    print(f"\n|a| − g over the {len(r['poses'])} rests: RMS before "
          f"{np.sqrt(np.mean([(p['before_g'] - 1) ** 2 for p in r['poses']])) * 1e3:.2f} mg, after "
          f"{r['accel_rms_after_mg']:.2f} mg")
    h = si["held_out"]
    print(f"held out: fitted on one rest per face ({', '.join(h['faces_used'])}), |a| − g on the "
          f"{len(h['rests'])} other rests ({', '.join(h['rests'])}): before "
          + ", ".join(f"{v:+.1f}" for v in h["before_mg"]) + " mg; after "
          + ", ".join(f"{v:+.2f}" for v in h["after_mg"]) + f" mg (RMS {h['rms_after_mg']:.2f} mg)")
    print(f"multi-position on these rests: refused: {si['multi_refusal']}")
    for w in (r["gyro"]["extra"] or {}).get("warnings", []):
        print(f"gyro: {w}")
    for n in r["notes"]:
        print(f"note: {n}")

    c = counts_figures()
    rc = c["result"]
    print(f"\n== the counts file, raw counts at 204.8 Hz, cut into parts ({COUNTS_FILE.name}) ==\n")
    print(segmentation_table(rc))
    print()
    print(turns_table(rc))
    print(f"\naccelerometer M, counts per g: imubench\n{_m(c['ours_acc'], '{:10.2f}')}\n  imucal's own fit (K·R)\n"
          f"{_m(c['imucal_acc'], '{:10.2f}')}\n  difference / imubench's σ\n{_m(c['z_acc'], '{:+10.2f}')}")
    print(f"gyro M, counts per °/s: imubench\n{_m(c['ours_gyr'], '{:10.4f}')}\n  imucal's own fit (K·R)\n"
          f"{_m(c['imucal_gyr'], '{:10.4f}')}\n  difference / imubench's σ\n{_m(c['z_gyr'], '{:+10.2f}')}")

    x = si_vs_counts(si, c)
    print("\n== the SI file beside the counts file (quantities free of the nominal scales) ==")
    for kind, unit in (("accel", "mg"), ("gyro", "°/s")):
        k = x[kind]
        sc = 1e3 if kind == "accel" else 1.0
        print(f"{kind}: cross-axis terms M_ij/M_ii, SI file\n{_m(k['cross_si'])}\n  counts file\n"
              f"{_m(k['cross_counts'])}\n  difference / σ\n{_m(k['z_cross'], '{:+9.1f}')}")
        print(f"{kind}: bias in its axis's own scale [{unit}]: SI " + ", ".join(f"{v * sc:+.2f}" for v in k["bias_si"])
              + "; counts " + ", ".join(f"{v * sc:+.2f}" for v in k["bias_counts"])
              + "; difference / σ " + ", ".join(f"{v:+.0f}" for v in k["z_bias"]))
    rows = all_recordings()
    print_gyro_residuals(rows)
    md, gmd = imucal_table(si, c, x), gyro_table(rows)
    print("\n" + md + "\n" + gmd, end="")
    publish("real_data", md, {"data": "tests/data/imucal"}, enabled=not a.no_publish)
    publish("real_data-gyro", gmd, {"data": "../shared/data when there, else tests/data"}, enabled=not a.no_publish)
    summary = {
        "si_rests": len(r["segmentation"]), "si_faces": sorted(set(s["face"] for s in r["segmentation"])),
        "si_turns": [t["label"] for t in r["turns"] if t["usable"]],
        "annotation_found": sum(a["found"] for a in r["annotation"]), "annotation_sections": len(r["annotation"]),
        "annotation_max_end_diff_s": max(max(abs(a["start_diff_s"]), abs(a["stop_diff_s"])) for a in r["annotation"]
                                         if a["found"]),
        "accel_rms_before_mg": float(np.sqrt(np.mean([(p["before_g"] - 1) ** 2 for p in r["poses"]])) * 1e3),
        "accel_rms_after_mg": r["accel_rms_after_mg"], "held_out_rms_after_mg": h["rms_after_mg"],
        "turns_before_deg": [round(t["before_deg"], 2) for t in r["turns"]],
        "gyro_scale_sigma_ppm": float(np.mean(np.diag(si["analysis"].gyro.sigma_m)) * 1e6),
        "counts_vs_imucal_max_z_accel": float(np.abs(c["z_acc"]).max()),
        "counts_vs_imucal_max_z_gyro_diag": float(np.abs(np.diag(c["z_gyr"])).max()),
        "counts_vs_imucal_max_z_gyro": float(np.abs(c["z_gyr"]).max()),
        "si_vs_counts_max_z_accel_bias": float(np.abs(x["accel"]["z_bias"]).max()),
        "gyro_residual_deg": {name: {v: {k2: round(c[k2], 4) for k2 in ("in_sample_rms_deg", "held_out_rms_deg")
                                         if k2 in c} for v, c in r.get("variants", {}).items()} for name, r in rows},
        "g_resolved": {name: int(np.sum(r["G_resolved"])) for name, r in rows if "G_resolved" in r},
    }
    print("\n" + json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
