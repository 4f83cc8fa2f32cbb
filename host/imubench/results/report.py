"""One self-contained HTML report per session: calibration, noise, attitude, temperature.

    build_report(session_dir, out_path=None, allan_dir=None, attitude_png=None, thermal_json=None) -> Path
    imubench report SESSION_DIR [--out FILE] [--allan DIR] [--attitude PNG] [--thermal JSON] [--closure DIR]

The report is ONE .html file that can be archived or sent on its own: the CSS is inline, every
plot is a PNG embedded as a data:image/png;base64 URI, there is no JavaScript and no reference
to anything outside the file. Every string taken from the data is HTML-escaped.

Inputs:
  * calibration: SESSION_DIR/session.json (imubench.procedures.session: "config", "poses", "result") and
    SESSION_DIR/residuals.png if present (else drawn with imubench.results.calibration.plot_pose_residuals);
  * noise: allan.json + allan_accel.png / allan_gyro.png (imubench.procedures.allan) in SESSION_DIR or --allan DIR;
  * closure check: closure.json + closure.png (imubench.procedures.closure) in SESSION_DIR/closure or --closure DIR;
  * attitude: a PNG (imubench.procedures.attitude's plot) given with --attitude;
  * temperature: DIR/thermal.json of `imubench thermal --out DIR`, given with --thermal
    (coefficients ± sigma, the per-temperature points, drift before/after, the write-back);
    any other JSON is shown as a key/value table.
A section without input is shown as "not measured in this session", never silently omitted.
"""
from __future__ import annotations

import datetime as _dt
import math
import tempfile
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.calib.fit import accel_method_words, fit_text   # the front door's one list of methods

from imubench.results.atomic import write_text_atomic
from imubench.results.numbers import pm as _pm_sigma
from imubench.results.report_html import (
    _badge,
    esc,
    _f,
    _foreign,
    _id_text,
    _img,
    _missing,
    _num,
    _png,
    png_data_uri,
    read_json_within,
    Refused,
    _table,
    _version,
)
from imubench.results.report_parts import (
    _attitude_numbers,
    _attitude_section,
    _closure_section,
    closure_verdict,
    _noise_section,
    _thermal_section,
)
from imubench.results.sessionfile import load_state
from imubench.files import make_dir

G0 = U.G0_MPS2
RAD2DEG = 180.0 / math.pi
AXES = ("x", "y", "z")

CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;margin:2em auto;max-width:1100px;
     color:#222;line-height:1.4;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:1.8em}
h3{margin-bottom:.3em}
table{border-collapse:collapse;margin:.6em 0 1em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#f0f0f0}td.l,th.l{text-align:left}
.badge{display:inline-block;padding:.15em .7em;border-radius:1em;font-weight:bold;margin-right:.4em;
       font-size:.9em;color:#fff}
.ok{background:#2e9e4f}.bad{background:#c0392b}.na{background:#888}
.note{background:#fff8dc;border-left:4px solid #e0b84c;padding:.4em .8em;margin:.6em 0}
.missing{background:#f4f4f4;border-left:4px solid #999;padding:.4em .8em;color:#555;font-style:italic}
img{max-width:100%;height:auto;border:1px solid #ddd;margin:.4em 0}
pre{background:#f7f7f7;padding:.6em;overflow-x:auto;font-size:.85em}
footer{margin-top:3em;border-top:1px solid #ccc;padding-top:.5em;color:#666;font-size:.85em}
.mono{font-family:monospace}
.verdict{border:3px solid #888;border-radius:.5em;padding:.6em 1em;margin:1em 0}
.verdict.pass{border-color:#2e9e4f;background:#f0faf3}.verdict.fail{border-color:#c0392b;background:#fdf1ef}
.verdict.incomplete{border-color:#e0b84c;background:#fffaf0}
.verdict h2{border:none;margin:.1em 0 .4em 0;font-size:1.35em}
.verdict table{margin:.3em 0}
.foreign{background:#fdecea;border-left:4px solid #c0392b;padding:.4em .8em;margin:.6em 0;color:#8b1a10}
nav.toc{font-size:.95em}nav.toc ol{margin:.2em 0 .2em 1.2em;padding:0}
"""


# ------------------------------------------------------------------ helpers
def _device_section(state: dict, result: dict | None) -> str:
    dev = (result or {}).get("device") or {}
    rows = []
    for label, key in (("MCU UID", "mcu_uid"), ("board", "board"), ("firmware", "fw_version"),
                       ("firmware build", "fw_build"), ("parts (accel, gyro X, Y, Z)", "parts"),
                       ("accelerometer IDs", "accel_ids"),
                       ("gyro part IDs", "gyro_pid"), ("gyro serial numbers", "gyro_sn")):
        if key in dev:
            v = _id_text(key, dev[key])
            rows.append([esc(label), f'<span class="mono">{esc(v)}</span>'])
    r = result or {}
    for label, v in (("session started", state.get("started")), ("run started", r.get("started")),
                     ("finished", r.get("finished"))):
        if v:
            rows.append([esc(label), esc(v)])
    if not rows:
        return _missing("device identity", "the session has no result record")
    return _table(["", "value"], rows, left=2)


def _fit_table(fit: dict, kind: str) -> str:
    """M (dimensionless; the scale error M_ii − 1 in ppm) and b in SI and usual units, every
    estimate ± 1σ to the precision its σ allows; entries the model does not estimate say so."""
    si = "b_mps2" if kind == "accel" else "b_rad_s"
    m, sm = fit.get("m") or [], fit.get("sigma_m") or []
    b, sb = fit.get(si) or [], fit.get("sigma_" + si) or []

    def at(x, i, j=None):
        try:
            return x[i] if j is None else x[i][j]
        except (IndexError, TypeError, KeyError):
            return None
    rows = []
    for i, ax in enumerate(AXES):
        cells = [esc(ax)]
        for j in range(3):
            v = at(m, i, j)
            cells.append(esc(_pm_sigma(v, at(sm, i, j), fixed_text=f"{_num(v, '{:+.0f}')} (not estimated)")))
        diag = at(m, i, i)
        cells.append(esc(_pm_sigma(_f(diag) - 1.0, at(sm, i, i), scale=1e6)))
        if kind == "accel":
            cells.append(esc(_pm_sigma(at(b, i), at(sb, i))))
            cells.append(esc(_pm_sigma(at(b, i), at(sb, i), scale=1e3 / G0)))
        else:
            cells.append(esc(_pm_sigma(at(b, i), at(sb, i))))
            cells.append(esc(_pm_sigma(at(b, i), at(sb, i), scale=RAD2DEG)))
        rows.append(cells)
    bu = ("b [m/s²]", "b [mg]") if kind == "accel" else ("b [rad/s]", "b [°/s]")
    head = ["axis", "M[·,x] ± 1σ", "M[·,y] ± 1σ", "M[·,z] ± 1σ", "scale error M<sub>ii</sub> − 1 [ppm]",
            esc(bu[0]) + " ± 1σ", esc(bu[1]) + " ± 1σ"]
    out = _table(head, rows)
    method = fit.get("method", "?")
    facts = [f"method: <b>{esc(fit_text(method))}</b>"]
    rr = _f(fit.get("residual_rms_mps2", fit.get("residual_rms")))
    extra = fit.get("extra") if isinstance(fit.get("extra"), dict) else {}
    if math.isfinite(rr):
        if kind == "accel":
            facts.append(f"residual RMS {esc(_num(rr * 1e3 / G0, '{:.2g}'))} mg")
        elif method == "turntable":
            facts.append(f"residual RMS over the turns {esc(_num(rr * RAD2DEG, '{:.2g}'))} °/s")
        elif method == "rotation":
            facts.append(f"residual RMS of the gravity directions {esc(_num(rr * RAD2DEG, '{:.2g}'))}°")
    chi = _f(extra.get("chi2_red", extra.get("reduced_chi2")))
    if math.isfinite(chi):
        facts.append(f"χ²/dof {esc(_num(chi, '{:.2g}'))} (1 when the residuals are as large as the noise says)")
    if extra.get("frame"):
        facts.append(f"frame: {esc(extra['frame'])}")
    al, sal = extra.get("alignment_rad"), extra.get("sigma_alignment_rad")
    if isinstance(al, list) and len(al) == 3:
        sal = sal if isinstance(sal, list) and len(sal) == 3 else [None] * 3
        facts.append("rotated into the gyro frame by " + ", ".join(
            f"{ax} {_pm_sigma(v, s, 'mrad', scale=1e3)}" for ax, v, s in zip(AXES, al, sal)))
    out += "<p>" + "; ".join(facts) + "</p>"
    return out


def _before_after_html(result: dict) -> str:
    """The before/after table of imubench.results.calibration.before_after_table, as HTML."""
    from imubench.results.calibration import (
        _poses,
        _rms,
        _tol,
        _verification,
        before_after_table,
    )
    names, before, after, sigma = _poses(result)
    temps = [p.get("temp_c") for p in result.get("poses") or []]
    ns = [p.get("n") for p in result.get("poses") or []]
    rows = []
    for k, (n, b, a, s) in enumerate(zip(names, before, after, sigma)):
        rows.append([esc(n), esc(_num(ns[k] if k < len(ns) else None, "{:.0f}")),
                     esc(f"{1 + b / 1000:.5f}") if math.isfinite(b) else "–",
                     esc(f"{1 + a / 1000:.5f}") if math.isfinite(a) else "–",
                     esc(_num(a - b, "{:+.3f}")), esc(_pm_sigma(a, s)),
                     esc(_num(temps[k] if k < len(temps) else None, "{:.2f}"))])
    out = _table(["pose", "samples", "|a| before [g]", "|a| after [g]", "Δ after − before [mg]",
                  "after: |a| − g ± 1σ [mg]", "temp [°C]"], rows)
    tol = _tol(result, "accel_rms_mg")
    rb, ra = _rms(before), _rms(after)
    verdict = "no tolerance given" if tol is None else \
        f"tolerance {tol:g} mg RMS: {'PASS' if ra <= tol else 'FAIL'}"
    out += f"<p>RMS of |a| − g over {len(names)} poses: before {rb:.3f} mg, after {ra:.4f} mg; {esc(verdict)}</p>"
    if result.get("tolerance_source"):          # a recording of another IMU: where its tolerance comes from
        out += f"<p>tolerance: {esc(result['tolerance_source'])}</p>"
    if result.get("verdict"):                   # calibrate --from: what was calibrated, what not and why
        out += f"<p><b>{esc(result['verdict'])}</b></p>"
    vnames, vafter, _vs = _verification(result)
    if len(vnames):
        vtol = _tol(result, "verify_mg")
        vrows = []
        for n, a, v in zip(vnames, vafter, result.get("verification") or []):
            ok = "" if vtol is None or not math.isfinite(a) else ("ok" if abs(a) <= vtol else "FAIL")
            vrows.append([esc(n), esc(f"{1 + a / 1000:.5f}") if math.isfinite(a) else "–",
                          esc(_num(a + 0.0 if round(a, 4) else 0.0, "{:+.4f}")), esc(_num(v.get("angle_from_plan_deg"), "{:.2f}")), esc(ok)])
        out += "<h4>Verification: the device's own calibrated output after write-back</h4>"
        out += _table(["pose", "|a| [g]", "|a| − g [mg]", "angle from plan [°]",
                       f"within ±{vtol:g} mg" if vtol else "verdict"], vrows)
    else:
        out += _missing("verification", "parameters not written back, so the device's output was not checked")
    out += ("<details><summary>as text (imubench.results.calibration.before_after_table)</summary><pre>"
            + esc(before_after_table(result)) + "</pre></details>")
    return out


def _calibration_section(session_dir: Path, state: dict) -> str:
    cfg = state.get("config") or {}
    result = state.get("result")
    out = ['<h2 id="calibration">Calibration</h2>']
    out.append("<h3>Device</h3>" + _device_section(state, result))
    method = (result or {}).get("method", cfg.get("method"))
    gyro_method = (result or {}).get("gyro_method", cfg.get("gyro"))
    out.append(f"<p>accelerometer method: <b>{esc(accel_method_words(method))}</b>; "
               f"gyro method: <b>{esc(gyro_method if gyro_method else 'none')}</b>; "
               f"rate {esc(_num(cfg.get('rate_hz'), '{:g}'))} Hz, hold {esc(_num(cfg.get('hold_s'), '{:g}'))} s per pose</p>")
    note = (result or {}).get("note", cfg.get("note"))
    if note:
        out.append(f'<p class="note"><b>note:</b> {esc(note)}</p>')
    if not result:
        n = len(state.get("poses") or [])
        out.append(_missing("calibration result", f"the session stopped before the fit: {n} pose(s) captured; "
                            "resume it with imubench calibrate --resume"))
        if state.get("poses"):
            out.append(_table(["pose", "samples", "temp [°C]"],
                              [[esc(p.get("name")), esc(p.get("n")), esc(_num(p.get("temp_c"), "{:.2f}"))]
                               for p in state["poses"]]))
        return "\n".join(out)
    rms = result.get("accel_rms_after_mg")
    out.append("<p>" + _badge("passed", result.get("passed")) + _badge("written", result.get("written"))
               + _badge("verified", result.get("verified") if result.get("written") or result.get("verification")
                        else None)
               + (f" accelerometer RMS of |a| − g after calibration: <b>{esc(_num(rms, '{:.2g}'))} mg</b>"
                  if rms is not None else "")
               + "</p>")
    tol = result.get("tolerances") or {}
    words = {"accel_rms_mg": "RMS of |a| − g over the poses after calibration ≤ {} mg",
             "verify_mg": "each verification attitude, | |a| − g | of the device's own output ≤ {} mg",
             "gyro_turntable_rms_dps": "turntable residual RMS ≤ {} °/s",
             "gyro_rotation_rms_deg": "rotation-method residual RMS ≤ {}°"}
    if tol:
        out.append("<p>tolerances: " + "; ".join(esc(words.get(k, k + " = {}").format(_num(v, "{:g}")))
                                                 for k, v in tol.items()) + "</p>")
    out.append("<h3>Accelerometer parameters</h3><p>model (docs/conventions.md): u = M·x + b, u the measured "
               "specific force at nominal scale, x the true one; the device applies x = M⁻¹·(u − b)</p>")
    out.append(_fit_table(result["accel"], "accel") if result.get("accel") else _missing("accelerometer fit", "no fit"))
    out.append("<h3>Gyroscope parameters</h3><p>the same model for the angular rate</p>")
    out.append(_fit_table(result["gyro"], "gyro") if result.get("gyro")
               else _missing("gyroscope calibration", "no gyro method was chosen"))
    out.append("<h3>|a| per pose, before and after calibration</h3>")
    try:
        out.append(_before_after_html(result))
    except ValueError as e:
        out.append(f'<p class="missing">{esc(e)}</p>')
    uri, refused = _png("residuals.png", within=session_dir)
    if uri is None and result.get("poses"):
        from imubench.results.calibration import plot_pose_residuals
        with tempfile.TemporaryDirectory() as td:
            uri = png_data_uri(plot_pose_residuals(result, Path(td) / "residuals.png"))
        if refused is not None:
            out.append(f'<p class="note">residuals.png of the session refused, not embedded ({esc(refused)}); '
                       "drawn again from the result</p>")
            refused = None
    out.append("<h3>Residual plot</h3>" + _img(uri, "|a| − g per pose, before and after calibration", refused))
    if isinstance(result.get("source"), dict):          # calibrated from a file (procedures.from_file)
        from imubench.results.recording import recording_html
        seg_uri, seg_refused = _png("segmentation.png", within=session_dir)
        out.append(recording_html(result, esc, _img(seg_uri, "the recording: still intervals and turns", seg_refused)))
    return "\n".join(out)


# ------------------------------------------------------------------ noise
def _calibration_part(state: dict, result: dict) -> tuple[str, str]:
    """(status, words) of the calibration: pass / fail / incomplete, the reason in words."""
    if not result:
        n = len(state.get("poses") or [])
        return "incomplete", (f"the session stopped before the fit ({n} attitude(s) captured): continue it with "
                              "imubench calibrate --resume DIR")
    rms, tol = _f(result.get("accel_rms_after_mg")), _f((result.get("tolerances") or {}).get("accel_rms_mg"))
    vtol = _f((result.get("tolerances") or {}).get("verify_mg"))
    fit = f"RMS of |a| − g after calibration {rms:.2g} mg" + (f" (tolerance {tol:g} mg)" if math.isfinite(tol) else "")
    if not result.get("passed"):
        why = f"the fit did not pass: {fit}"
        chi = _f(((result.get("accel") or {}).get("extra") or {}).get("chi2_red"))
        if result.get("method") == "six" and math.isfinite(chi) and chi > 100:
            off = _f(result.get("faces_off_square_deg"))
            how = f"{off:.1f}° off square" if math.isfinite(off) else "not square"
            why += (f"; the six faces are {how} (χ²/dof {chi:.2g}): use --method multi, which needs no "
                    "square fixture")
        return "fail", why + "; nothing was written to the device"
    ver = [_f(v.get("after_g")) for v in result.get("verification") or [] if isinstance(v, dict)]
    worst = max((abs(v - 1.0) * 1e3 for v in ver if math.isfinite(v)), default=math.nan)
    if result.get("written") and result.get("verified"):
        return "pass", (f"fitted ({fit}), written, read back, saved, rebooted and verified on the device's own "
                        f"output (worst attitude {worst:.2g} mg" + (f", tolerance {vtol:g} mg)" if math.isfinite(vtol)
                                                                    else ")"))
    if ver:
        return "fail", (f"the device's own output failed verification (worst attitude {worst:.2g} mg"
                        + (f" > {vtol:g} mg" if math.isfinite(vtol) else "") + "): the previous parameters were "
                        "written back")
    return "pass", f"fitted ({fit}); not written to the device (--no-write)"


def calibration_verdict(result: dict, state: dict | None = None) -> tuple[str, str]:
    """(status, words) of a calibration session's result, as the report says it (pass /
    fail / incomplete and why); a six-position fit on faces that are not square says by how
    many degrees (the worst face's angle from its plan) and to use --method multi."""
    return _calibration_part(state or {}, result or {})


def parameter_rows(result: dict) -> list[tuple[str, str]]:
    """(name, value ± sigma with unit) of the accelerometer's (and gyro's) parameters, each to
    the precision of its sigma (results.numbers): scale and cross terms of M in ppm, biases
    in mg (accelerometer) or °/s (gyro)."""
    from imubench.results.numbers import pm
    rows = []
    for kind, unit, bkey, bscale in (("accel", "mg", "b_mps2", 1e3 / 9.80665), ("gyro", "°/s", "b_rad_s", 180 / math.pi)):
        fit = (result or {}).get(kind)
        if not isinstance(fit, dict):
            continue
        m, sm = np.asarray(fit["m"], float), np.asarray(fit["sigma_m"], float)
        b, sb = np.asarray(fit[bkey], float), np.asarray(fit[f"sigma_{bkey}"], float)
        for i in range(3):
            for j in range(3):
                v = (m[i, j] - (1.0 if i == j else 0.0)) * 1e6
                rows.append((f"{kind} M{'xyz'[i]}{'xyz'[j]}" + (" − 1" if i == j else ""), pm(v, sm[i, j] * 1e6, "ppm")))
        for i in range(3):
            rows.append((f"{kind} b{'xyz'[i]}", pm(b[i] * bscale, sb[i] * bscale, unit)))
    return rows


def _parts(state, result, closure_dir, allan_dir, attitude_png, thermal_json, uid,
           closure_within=None, allan_within=None) -> list[tuple]:
    """(name, anchor, status, words) of every part of the report: status pass / fail /
    incomplete / info / foreign (another device: refused) / missing."""
    parts = [("calibration", "calibration", *_calibration_part(state, result))]
    if result.get("gyro_refused") and parts[0][2] == "pass":     # calibrate --from: the gyro part was refused
        parts[0] = ("calibration", "calibration", "incomplete",
                    f"{parts[0][3]}; gyro not calibrated: {result['gyro_refused']}")

    def load(path, within=None):
        try:
            return read_json_within(path, within)
        except (OSError, ValueError, TypeError, Refused):
            return None
    c = load(closure_dir / "closure.json", closure_within) if closure_dir is not None else None
    if c is None:
        parts.append(("closure check", "closure", "missing", "give --closure DIR (imubench closure --out DIR, or calibrate --closure)"))
    elif _foreign(c, uid, "")[1] == "foreign":
        parts.append(("closure check", "closure", "foreign", "from another device: refused"))
    elif not isinstance(c, dict) or closure_verdict(c) is None:
        parts.append(("closure check", "closure", "incomplete", "the recording has no result"))
    else:
        ok, words = closure_verdict(c)
        parts.append(("closure check", "closure", "pass" if ok else "fail", words))
    a = load(allan_dir / "allan.json", allan_within) if allan_dir is not None else None
    if a is None:
        parts.append(("noise", "noise", "missing", "give --allan DIR (imubench allan --out DIR)"))
    elif _foreign(a, uid, "")[1] == "foreign":
        parts.append(("noise", "noise", "foreign", "from another device: refused"))
    else:
        from imubench.analysis.allan import duration_text
        withheld = sorted({k for kind in ("accel", "gyro") for ax in AXES
                           for k in ("B", "K") if isinstance((a.get(kind) or {}).get(ax), dict)
                           and a[kind][ax].get(k) is None})
        parts.append(("noise", "noise", "info",
                      f"Allan deviation of {duration_text(_f(a.get('duration_s')))} at rest"
                      + (f"; withheld (record too short): {', '.join(withheld)}" if withheld else "")))
    if attitude_png is None:
        parts.append(("attitude", "attitude", "missing", "give --attitude FILE.png (imubench attitude --plot FILE.png)"))
    else:
        d = _attitude_numbers(Path(attitude_png))
        if _foreign(d, uid, "")[1] == "foreign":
            parts.append(("attitude", "attitude", "foreign", "from another device: refused"))
        elif d and (d.get("device") or {}).get("factory_parameters"):
            parts.append(("attitude", "attitude", "fail", "measured with factory parameters: uncalibrated output"))
        elif d and d.get("mode") == "steps":
            rms = d.get("rms_static_error_deg") or {}
            parts.append(("attitude", "attitude", "info", "step test: RMS static error "
                          + ", ".join(f"{k} {_num(v, '{:.2g}')}°" for k, v in rms.items() if k != "accel")))
        else:
            parts.append(("attitude", "attitude", "info", "roll and pitch of the calibrated output"))
    th = load(thermal_json) if thermal_json is not None else None
    if th is None:
        parts.append(("temperature", "temperature", "missing", "give --thermal DIR/thermal.json (imubench thermal --out DIR)"))
    elif _foreign(th, uid, "")[1] == "foreign":
        parts.append(("temperature", "temperature", "foreign", "from another device: refused"))
    elif not isinstance(th, dict) or th.get("status") not in (None, "done"):
        err = th.get("error") if isinstance(th, dict) else None
        parts.append(("temperature", "temperature", "fail", "the sweep did not finish" + (f": {err}" if err else "")))
    else:
        b, af = th.get("drift_before") or {}, th.get("drift_after") or {}

        def worst_ratio(key, n):
            rs = [_f(x) / _f(y) for x, y in zip((b.get(key) or [])[:n], (af.get(key) or [])[:n])
                  if _f(y) > 0]
            return min(rs) if rs else math.nan
        ra, rg = worst_ratio("accel_drift_mps2", 3), worst_ratio("gyro_drift_rad_s", 3)
        wb = th.get("write") if isinstance(th.get("write"), dict) else None
        if wb and not wb.get("verified"):
            parts.append(("temperature", "temperature", "fail", f"write-back failed: {wb.get('error')}"))
        elif math.isfinite(ra) and math.isfinite(rg):
            parts.append(("temperature", "temperature", "pass",
                          f"coefficients fitted and written; the drift of the calibrated output falls at least "
                          f"{ra:.0f}x (accelerometer) and {rg:.0f}x (gyro) over the sweep"))
        else:
            parts.append(("temperature", "temperature", "info", "coefficients fitted (not written: no drift measured)"))
    return parts


def _verdict_box(parts: list[tuple], device: dict, uid: str) -> tuple[str, str]:
    """(overall word, HTML) of the verdict that opens the report."""
    st = [p[2] for p in parts]
    overall = "FAILED" if any(s in ("fail", "foreign") for s in st) else \
        "INCOMPLETE" if "incomplete" in st else "PASSED"
    cls = {"PASSED": "pass", "FAILED": "fail", "INCOMPLETE": "incomplete"}[overall]
    badge = {"pass": '<span class="badge ok">pass</span>', "fail": '<span class="badge bad">FAIL</span>',
             "foreign": '<span class="badge bad">refused</span>', "incomplete": '<span class="badge na">incomplete</span>',
             "info": '<span class="badge na">measured</span>', "missing": '<span class="badge na">not measured</span>'}
    rows = [[f'<a href="#{esc(a)}">{esc(n)}</a>', badge[s], esc(w)] for n, a, s, w in parts]
    dev = ", ".join(x for x in (f"board {device.get('board')}" if device.get("board") else "",
                                f"firmware {device.get('fw_version')}" if device.get("fw_version") else "") if x)
    html_ = (f'<div class="verdict {cls}"><h2>Verdict: {overall}</h2>'
             f'<p>device <b class="mono">{esc(uid or "unknown")}</b>{(", " + esc(dev)) if dev else ""}</p>'
             + _table(["part", "", "in words"], rows, left=3) + "</div>")
    return overall, html_


# ------------------------------------------------------------------ the report
def build_report(session_dir, out_path=None, allan_dir=None, attitude_png=None, thermal_json=None,
                 closure_dir=None) -> Path:
    """Write the session's report as one self-contained HTML file and return its path
    (default SESSION_DIR/report.html). allan_dir defaults to session_dir (its allan.json is
    used if present), closure_dir to SESSION_DIR/closure (imubench calibrate --closure).
    Raises SessionFileError if session_dir has no readable session.json."""
    session_dir = Path(session_dir)
    state = load_state(session_dir)
    result = state.get("result") or {}
    out_path = Path(out_path) if out_path is not None else session_dir / "report.html"
    # JSON is embedded only from the directory it was asked from: the session directory for
    # the parts found there by default, the directory given for the others (read_json_within)
    allan_within = Path(allan_dir) if allan_dir is not None else session_dir
    closure_within = Path(closure_dir) if closure_dir is not None else session_dir
    allan_dir = Path(allan_dir) if allan_dir is not None else session_dir
    device = result.get("device") if isinstance(result.get("device"), dict) else {}
    uid = str(device.get("mcu_uid", "")).upper() or None
    when = str(result.get("started") or state.get("started") or "")
    closure_dir = Path(closure_dir) if closure_dir is not None else session_dir / "closure"
    attitude_png = Path(attitude_png) if attitude_png else None
    thermal_json = Path(thermal_json) if thermal_json else None

    sections = [_calibration_section(session_dir, state), _closure_section(closure_dir, uid, closure_within),
                _noise_section(allan_dir, uid, allan_within), _attitude_section(attitude_png, uid),
                _thermal_section(thermal_json, uid)]
    parts = _parts(state, result, closure_dir, allan_dir, attitude_png, thermal_json, uid, closure_within,
                   allan_within)
    overall, verdict = _verdict_box(parts, device, uid or "")
    toc = ('<nav class="toc"><b>Contents</b><ol>' + "".join(
        f'<li><a href="#{esc(a)}">{esc(n)}</a>{"" if s != "missing" else " (not measured)"}</li>'
        for n, a, s, _w in parts) + "</ol></nav>")
    generated = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    doc = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>imubench report: {esc(overall)}, {esc(uid or "unknown device")} {esc(when)}</title>
<style>{CSS}</style></head>
<body>
<h1>IMU calibration report: {esc(overall)}</h1>
{verdict}
<p>session started {esc(state.get('started', '?'))}; every estimate is given ± its 1σ uncertainty, rounded to
two significant digits of the uncertainty</p>
{toc}
{chr(10).join(sections)}
<footer>generated by imubench {esc(_version())} at {esc(generated)} from session directory
<span class="mono">{esc(session_dir.resolve())}</span></footer>
</body></html>
"""
    make_dir(out_path.parent)
    return write_text_atomic(out_path, doc)
