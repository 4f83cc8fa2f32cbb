#!/usr/bin/env python3
"""imubench on real data no one here recorded: imucal's public example Ferraris session.

    python bench/real_data.py            (figures for README.md and docs/calibration.md)

Data: tests/data/imucal/ (MIT, mad-lab-fau/imucal example_data; README there). Two files:
the session in m/s² and °/s at 102.4 Hz (six faces, then three 360° hand turns), and a file in
raw counts at 204.8 Hz cut into the named parts of a session, with imucal's own calibration of
it (imucal's tests). There is no ground truth: what is printed is what the data can say —
the automatic segmentation against one person's annotation, the fits with their sigmas, |a| − g
per rest before and after (and on rests the fit did not use), each turn's integrated angle
before and after, the multi-position refusal, imubench's counts fit beside imucal's, and the
SI file beside the counts file. The last line is JSON.
"""
from __future__ import annotations

import json
import math
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


def _m(m, fmt="{:+9.5f}") -> str:
    return "\n".join("    " + " ".join(fmt.format(v) for v in row) for row in np.asarray(m))


def main() -> int:
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
    }
    print("\n" + json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
