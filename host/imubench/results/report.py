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

import base64
import datetime as _dt
import html
import json
import math
import os
import stat
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from imubench.files import MAX_JSON_BYTES
from imubench.results.atomic import write_text_atomic
from imubench.results.numbers import pm as _pm_sigma
from imubench.results.sessionfile import load_state
from imubench.wire.ids import byte_ids_text, pid_text, sn_text

G0 = 9.80665
RAD2DEG = 180.0 / math.pi
AXES = ("x", "y", "z")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MAX_PLOT_BYTES = 16 * 1024 * 1024     # an embedded plot: ours are ~100 kB

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
def esc(x) -> str:
    return html.escape("" if x is None else str(x), quote=True)


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _num(x, fmt="{:.6g}") -> str:
    v = _f(x)
    return "–" if not math.isfinite(v) else fmt.format(v)


class Refused(ValueError):
    """A file the report will not embed; the message says why."""


def read_png(path, within=None, max_bytes: int = MAX_PLOT_BYTES) -> bytes | None:
    """The bytes of the PNG at path; None when there is no such file. Raises Refused for
    anything else than a regular PNG file of at most max_bytes, or (with `within`) one whose
    real path (symlinks resolved) is outside the directory `within`: a report is sent on its
    own, so it carries no file from elsewhere on the disk, and never blocks (a FIFO) or reads
    without end (a device)."""
    data = read_within(path, within, max_bytes)
    if data is not None and not data.startswith(PNG_MAGIC):
        raise Refused(f"{path} is not a PNG")
    return data


def read_json_within(path, within=None, max_bytes: int = MAX_JSON_BYTES):
    """The JSON at path, read as read_within reads (a symlink out of `within`, by default the
    directory the file is named in, is refused: the report embeds no file from elsewhere);
    None when there is no such file. Raises Refused, or ValueError when it does not parse."""
    path = Path(path).absolute()
    data = read_within(path, path.parent if within is None else within, max_bytes)
    return None if data is None else json.loads(data)


def read_within(path, within=None, max_bytes: int = MAX_PLOT_BYTES) -> bytes | None:
    """The bytes of the regular file at path (at most max_bytes; never a FIFO or a device),
    None when there is none; with `within`, refused unless its real path is inside it."""
    path = Path(path)
    if within is not None:
        base = Path(within).resolve()
        real = (base / path).resolve() if not path.is_absolute() else path.resolve()
        if not real.is_relative_to(base):
            raise Refused(f"{path} is outside {base}")
        path = real
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        return None
    except OSError as e:
        raise Refused(f"{path}: {e.strerror or e}") from None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise Refused(f"{path} is not a regular file")
        if st.st_size > max_bytes:
            raise Refused(f"{path} is {st.st_size} bytes, more than the limit of {max_bytes}")
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise Refused(f"{path} is more than the limit of {max_bytes} bytes")
    return data


def png_data_uri(path, within=None) -> str | None:
    """The PNG at path as a data URI, or None if it is missing or refused (read_png)."""
    try:
        data = read_png(path, within)
    except Refused:
        return None
    return None if data is None else "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _png(path, within=None) -> tuple[str | None, str | None]:
    """(data URI, None), (None, None) when there is no file, or (None, why it was refused)."""
    try:
        data = read_png(path, within)
    except Refused as e:
        return None, str(e)
    return (None if data is None else "data:image/png;base64," + base64.b64encode(data).decode("ascii")), None


def _img(uri: str | None, alt: str, refused: str | None = None) -> str:
    if refused is not None:
        return f'<p class="missing">{esc(alt)}: plot refused, not embedded ({esc(refused)})</p>'
    if uri is None:
        return f'<p class="missing">{esc(alt)}: plot not available</p>'
    return f'<p><img src="{uri}" alt="{esc(alt)}"></p>'


def _badge(label: str, value) -> str:
    cls = "na" if value is None else ("ok" if value else "bad")
    word = "n/a" if value is None else ("yes" if value else "NO")
    return f'<span class="badge {cls}">{esc(label)}: {word}</span>'


def _table(header: Sequence[str], rows: Sequence[Sequence], left: int = 1) -> str:
    """rows of already-escaped HTML cells; the first `left` columns are left-aligned."""
    h = "".join(f'<th class="{"l" if i < left else ""}">{c}</th>' for i, c in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
                   + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def _missing(what: str, how: str) -> str:
    return f'<p class="missing">{esc(what)}: not measured in this session ({esc(how)}).</p>'


def _load_json(path: Path | None, what: str, how: str, out: list[str], within=None):
    """The JSON at path, or None after appending to out why there is none: "not measured"
    (with how to get it) when the file is absent, "refused" when it is a link out of `within`
    (default: its own directory) or not a regular file, "unreadable" when it does not parse."""
    try:
        data = None if path is None else read_json_within(path, within)
    except Refused as e:
        out.append(f'<p class="foreign"><b>refused</b>: {esc(what)} data not embedded ({esc(e)}).</p>')
        return None
    except (OSError, ValueError) as e:
        out.append(f'<p class="missing">{esc(what)} data {esc(path)}: unreadable ({esc(e)}); '
                   "not measured in this session.</p>")
        return None
    if data is None:
        out.append(_missing(what, how))
    return data


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("imubench")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "unknown"


def _foreign(data, session_uid: str | None, what: str) -> tuple[str | None, str]:
    """(refusal HTML or None, state) for a result file checked against the session's device:
    "same", "foreign" (another MCU UID: refused, its numbers are not shown), "unnamed" (the
    file names no device: shown with a warning) or "unknown" (the session names none)."""
    dev = data.get("device") if isinstance(data, dict) else None
    uid = str(dev.get("mcu_uid", "")).upper() if isinstance(dev, dict) else ""
    if not session_uid:
        return None, "unknown"
    if not uid:
        return None, "unnamed"
    if uid != session_uid:
        return (f'<p class="foreign"><b>refused: from another device.</b> This {esc(what)} was measured on '
                f'<span class="mono">{esc(uid)}</span>, not on this session\'s device '
                f'<span class="mono">{esc(session_uid)}</span>; its numbers are not part of this report.</p>'), "foreign"
    return None, "same"


def _load_part(path: Path | None, what: str, how: str, out: list[str], session_uid: str | None, label: str,
               within=None):
    """_load_json, then the device check: None (after appending why to out) when the file is
    missing, unreadable or from another device; a note is appended when it names no device."""
    data = _load_json(path, what, how, out, within)
    if data is None:
        return None
    refusal, state = _foreign(data, session_uid, label)
    if refusal:
        out.append(refusal)
        return None
    if state == "unnamed":
        out.append(_unnamed_note(label))
    return data


def _unnamed_note(what: str) -> str:
    return (f'<p class="note">this {esc(what)} does not name its device (recorded by an older imubench): '
            "it cannot be checked against the session's device.</p>")


# ------------------------------------------------------------------ calibration
def _id_text(key: str, v) -> str:
    """Identifiers in the one format `imubench info` prints (imubench.wire.ids)."""
    fmt = {"accel_ids": byte_ids_text, "gyro_pid": lambda xs: " ".join(pid_text(x) for x in xs),
           "gyro_sn": lambda xs: " ".join(sn_text(x) for x in xs)}.get(key)
    if fmt is not None and isinstance(v, list) and all(isinstance(x, int) for x in v):
        return fmt(v)
    if key == "mcu_uid" and isinstance(v, str):
        return v.upper()
    return ", ".join(map(str, v)) if isinstance(v, list) else str(v)


def _device_section(state: dict, result: dict | None) -> str:
    dev = (result or {}).get("device") or {}
    rows = []
    for label, key in (("MCU UID", "mcu_uid"), ("board", "board"), ("firmware", "fw_version"),
                       ("firmware build", "fw_build"), ("accelerometer IDs", "accel_ids"),
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


FIT_METHODS = {"six_position": "six-position least squares (full M and b)",
               "multi_position": "multi-position |a| = g (3 biases, 3 scales, 3 non-orthogonality angles)",
               "bias": "bias at rest (scale and misalignment not estimated)",
               "turntable": "turntable (known rates about each axis, both ways)",
               "rotation": "rotation method (gyro integrated between attitudes)",
               "turns": "known-angle turns (Ferraris: hand turns of a known angle about the vertical)",
               "turns+rotation": "known-angle turns and the rotation method, combined (inverse-covariance)"}


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
    facts = [f"method: <b>{esc(FIT_METHODS.get(method, method))}</b>"]
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
    out.append(f"<p>accelerometer method: <b>{esc({'six': 'six-position', 'multi': 'multi-position'}.get(method, method))}</b>; "
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
def _noise_section(allan_dir: Path | None, session_uid: str | None = None, within=None) -> str:
    out = ['<h2 id="noise">Noise (Allan deviation)</h2>']
    res = _load_part(allan_dir / "allan.json" if allan_dir is not None else None, "noise",
                     "no allan.json; record one with imubench allan and give --allan DIR", out, session_uid,
                     "noise recording", within)
    if res is None:
        return "\n".join(out)
    from imubench.analysis.allan import duration_text, usual_units
    dur = _f(res.get("duration_s"))
    out.append(f"<p>{esc(_num(res.get('samples'), '{:.0f}'))} samples at {esc(_num(res.get('rate_hz'), '{:g}'))} Hz "
               f"= {esc(duration_text(dur) if math.isfinite(dur) else '?')} at rest</p>")
    dec = res.get("decoder") or {}
    if dec.get("samples_missing"):
        out.append(f'<p class="note">{esc(dec["samples_missing"])} samples were lost in the recording; the '
                   "analysis joins the pieces.</p>")
    reasons = set()
    for kind, title, si in (("accel", "Accelerometer", "m/s²"), ("gyro", "Gyroscope", "rad/s")):
        r = res.get(kind) or {}
        usual = res.get(kind + "_usual") or {}
        rows = []
        for a in AXES:
            if a not in r or not isinstance(r[a], dict):
                continue
            ra = r[a]
            u = usual.get(a) or usual_units(ra, kind)
            n_rel = _f((ra.get("white") or {}).get("N_rel_1sigma"))
            k_rel = _f((ra.get("rate_rw") or {}).get("K_rel_1sigma"))
            nk = ("N_ug_per_rtHz", "B_ug", "K_ug_rtHz") if kind == "accel" else \
                ("N_deg_per_rth", "B_deg_h", "K_deg_h_per_rth")
            n_u, b_u, k_u = (u.get(k) for k in nk)
            cells = [esc(a), esc(_pm_sigma(n_u, _f(n_u) * n_rel) if math.isfinite(n_rel) else _num(n_u, "{:.2g}"))]
            cells.append(esc(_num(b_u, "{:.2g}")) if b_u is not None else "withheld")
            cells.append(esc(_num(ra.get("B_tau"), "{:.3g}")) if b_u is not None else "–")
            cells.append(esc(_pm_sigma(k_u, _f(k_u) * k_rel) if math.isfinite(k_rel) else _num(k_u, "{:.2g}"))
                         if k_u is not None else "withheld")
            rows.append(cells)
            for key in ("B_reason", "K_reason"):
                if ra.get(key):
                    reasons.add(f"{kind} {key[0]}: {ra[key]}")
        head = (["axis", "VRW N [µg/√Hz]", "bias instability B [µg]", "B at τ [s]", "RRW K [µg·√Hz]"]
                if kind == "accel" else
                ["axis", "ARW N [°/√h]", "bias instability B [°/h]", "B at τ [s]", "RRW K [°/h/√h]"])
        out.append(f"<h3>{title}</h3>")
        out.append(_table([esc(h) for h in head], rows) if rows else _missing(title, "no axes in allan.json"))
        uri, refused = _png(f"allan_{kind}.png", within=allan_dir)
        out.append(_img(uri, f"{title} Allan deviation ({si})", refused))
    for rsn in sorted(reasons):
        out.append(f'<p class="note">withheld, {esc(rsn)}</p>')
    out.append("<p>N: white noise, ADEV(τ) = N/√τ read at τ = 1 s; B: bias instability = min ADEV / 0.664; "
               "K: rate random walk, ADEV(τ) = K·√(τ/3) read at τ = 3 s (docs/noise.md). A read-off the record "
               "cannot support is withheld with the reason.</p>")
    return "\n".join(out)


# ------------------------------------------------------------------ attitude, thermal
def _attitude_numbers(png: Path | None) -> dict | None:
    """The numbers `imubench attitude --plot FILE.png` writes beside its plot (FILE.json)."""
    if png is None:
        return None
    try:
        data = read_json_within(Path(png).with_suffix(".json"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("kind") == "imubench attitude" else None


def _attitude_section(png: Path | None, session_uid: str | None = None) -> str:
    out = ['<h2 id="attitude">Attitude</h2>']
    if png is None:
        out.append(_missing("attitude", "no plot given; run imubench attitude --plot FILE.png (or with --sim "
                            "--steps) and give --attitude FILE.png"))
        return "\n".join(out)
    data = _attitude_numbers(png)
    refusal, state = _foreign(data, session_uid, "attitude result")
    if refusal:
        return "\n".join(out + [refusal])
    if data is None:
        out.append(f'<p class="note">no numbers beside {esc(png.name)} ({esc(png.with_suffix(".json").name)} '
                   "from imubench attitude --plot): the plot alone, from an unnamed device.</p>")
    else:
        if state == "unnamed":
            out.append(_unnamed_note("attitude result"))
        if (data.get("device") or {}).get("factory_parameters"):
            out.append('<p class="foreign">measured with the device\'s FACTORY parameters: its "calibrated" '
                       "output was uncalibrated.</p>")
        if data.get("mode") == "steps":
            rms = data.get("rms_static_error_deg") or {}
            rows = [[esc(n), esc(_num(v, "{:.2g}"))] for n, v in rms.items()]
            out.append("<p>the step test on the virtual turntable (−20° to +20° about X and Y, 10° steps): static "
                       "error after settling, RMS over the steps</p>")
            out.append(_table(["filter", "RMS static error [°]"], rows, left=1))
        elif data.get("mode") == "live":
            rows = []
            for n in data.get("filters") or []:
                r, pt = (data.get("roll_deg") or {}).get(n) or {}, (data.get("pitch_deg") or {}).get(n) or {}
                rows.append([esc(n), esc(_num(r.get("mean"), "{:+.3f}")), esc(_num(r.get("std"), "{:.2g}")),
                             esc(_num(pt.get("mean"), "{:+.3f}")), esc(_num(pt.get("std"), "{:.2g}"))])
            out.append(f"<p>{esc(_num(data.get('duration_s'), '{:.3g}'))} s of the device's calibrated output at "
                       f"{esc(_num(data.get('rate_hz'), '{:g}'))} Hz; roll and pitch through each filter</p>")
            out.append(_table(["filter", "roll mean [°]", "roll std [°]", "pitch mean [°]", "pitch std [°]"], rows))
    uri, refused = _png(png)        # the file the user named: anywhere, but a regular PNG of limited size
    if uri is None:
        out.append(f'<p class="missing">attitude plot {esc(png)} is missing or refused'
                   f'{" (" + esc(refused) + ")" if refused else ""}.</p>')
    else:
        out.append(f"<p>from {esc(png.name)}</p>" + _img(uri, "roll/pitch from the attitude filters"))
    return "\n".join(out)


# (key, unit suffix of its SI value in thermal.json, label, display unit, SI -> display factor).
# imubench thermal writes f"{key}_{suffix}" and f"{key}_sigma_{suffix}"; the bare key and
# f"{key}_sigma" (ThermalFit's field names) are read too.
THERMAL_FIELDS = (("accel_bias_tc", "mps2_per_c", "accel bias", "µg/°C", 1e6 / G0),
                  ("accel_scale_tc", "per_c", "accel scale", "ppm/°C", 1e6),
                  ("gyro_bias_tc", "rad_s_per_c", "gyro bias", "m°/s/°C", RAD2DEG * 1e3),
                  ("gyro_scale_tc", "per_c", "gyro scale", "ppm/°C", 1e6))


def _thermal_section(path: Path | None, session_uid: str | None = None) -> str:
    out = ['<h2 id="temperature">Temperature</h2>']
    data = _load_part(path, "temperature", "no thermal data given; run imubench thermal --out DIR and pass "
                      "--thermal DIR/thermal.json", out, session_uid, "temperature sweep")
    if data is None:
        return "\n".join(out)
    out.append(f"<p>from {esc(Path(path).name)}</p>")

    def seq(x, n=3) -> list:
        x = x if isinstance(x, (list, tuple)) else []
        return [x[k] if k < len(x) else None for k in range(n)]

    def pm(v, s, fmt, scale):                  # value ± sigma in display units, to sigma's precision
        return esc(_pm_sigma(v, s, scale=scale, fixed_text="not measured"))

    fit_keys = {}
    if isinstance(data, dict):
        for key, suffix, *_ in THERMAL_FIELDS:
            for vk, sk in ((f"{key}_{suffix}", f"{key}_sigma_{suffix}"), (key, key + "_sigma")):
                if vk in data:
                    fit_keys[key] = (vk, sk)
                    break
    if not (isinstance(data, dict) and (fit_keys or "points" in data)):
        out.append(f'<p class="missing">{esc(Path(path).name)} is not a thermal.json of imubench thermal '
                   "(no coefficients, no temperature points): not shown.</p>")
        return "\n".join(out)

    status = data.get("status")
    if status not in (None, "done"):
        msg = f"incomplete run: status {status}, stage {data.get('stage')}"
        if data.get("error"):
            msg += f"; error: {data['error']}"
        out.append(f'<p class="note">{esc(msg)}; what was measured is shown.</p>')
    if data.get("t_ref_c") is not None:
        out.append(f"<p>reference temperature {esc(_num(data['t_ref_c'], '{:g}'))} °C</p>")
    rows = []
    for key, _suffix, label, unit, scale in THERMAL_FIELDS:
        if key not in fit_keys:
            continue
        vk, sk = fit_keys[key]
        v, s = seq(data.get(vk)), seq(data.get(sk))
        if all(x is None for x in v):
            continue
        rows.append([esc(f"{label} [{unit}]")] + [pm(v[k], s[k], ".3f", scale) for k in range(3)])
    if rows:
        out.append(_table(["coefficient ± 1σ", "x", "y", "z"], rows))
    elif "points" in data:
        out.append('<p class="missing">coefficients: not fitted (the sweep did not finish).</p>')
    for n in data.get("notes") or []:
        out.append(f'<p class="note">{esc(n)}</p>')

    points = [p for p in data.get("points") or [] if isinstance(p, dict)]
    if points:
        out.append("<h3>Temperature points</h3>")
        rows = []
        for p in points:
            st = p.get("settle") if isinstance(p.get("settle"), dict) else {}
            rates = [abs(_f(r)) for r in st.get("rate_c_per_min") or []]
            t0, t1 = _f(p.get("t_first_us")) * 1e-6, _f(p.get("t_last_us")) * 1e-6
            gs = p.get("gyro_rest_sigma_rad_s")
            rows.append([esc(_num(p.get("set_c"), "{:g}")), esc(_num(p.get("accel_temp_c"), "{:.2f}")),
                         esc(" / ".join(_num(t, "{:.2f}") for t in seq(p.get("gyro_temp_c")))),
                         esc(_num(st.get("waited_s"), "{:.0f}")),
                         esc(_num(max(rates) if rates else None, "{:.3f}")),
                         esc(f"{_num(t0, '{:.1f}')} – {_num(t1, '{:.1f}')}")]
                        + [pm(g, s, ".4f", RAD2DEG) for g, s in zip(seq(p.get("gyro_rest_rad_s")), seq(gs))])
        out.append(_table(["set [°C]", "ADXL355 [°C]", "gyro X / Y / Z [°C]", "settled after [s]",
                           "max |dT/dt| [°C/min]", "measured, device time [s]", "gyro at rest x [°/s]",
                           "y [°/s]", "z [°/s]"], rows, left=0))
        out.append("<p>Temperatures are the sensors' own readings (the fit uses them, not the set point); "
                   "settled: every sensor's |dT/dt| over the settling window below the limit.</p>")
        rows = []
        for p in points:
            acc, sig = p.get("accel_mps2") or {}, p.get("accel_sigma_mps2") or {}
            for pose in acc if isinstance(acc, dict) else []:
                rows.append([esc(_num(p.get("set_c"), "{:g}")), esc(pose)]
                            + [pm(v, s, ".3f", 1e3 / G0) for v, s in zip(seq(acc.get(pose)), seq(sig.get(pose)))])
        if rows:
            out.append("<h3>Accelerometer means per pose (nominal scaling)</h3>")
            out.append(_table(["set [°C]", "pose", "x [mg]", "y [mg]", "z [mg]"], rows, left=2))
        rows = [[esc(_num(p.get("set_c"), "{:g}"))]
                + [pm(v, s, ".4f", RAD2DEG) for v, s in zip(seq(p.get("gyro_turn_rad_s")), seq(p.get("gyro_turn_sigma_rad_s")))]
                for p in points if p.get("gyro_turn_rad_s")]
        if rows:
            out.append("<h3>Gyro turntable, (ω₊ − ω₋)/2</h3>")
            out.append(_table(["set [°C]", "x [°/s]", "y [°/s]", "z [°/s]"], rows))

    before, after = data.get("drift_before"), data.get("drift_after")
    if isinstance(before, dict):
        after = after if isinstance(after, dict) else {}
        out.append("<h3>Drift of the device's calibrated output over the sweep (max − min)</h3>")
        rows = []
        for i, (label, key, unit, scale, fmt) in enumerate(
                [(f"accel {a}", "accel_drift_mps2", "mg", 1e3 / G0, "{:.4f}") for a in AXES]
                + [("|accel|", "accel_drift_mps2", "mg", 1e3 / G0, "{:.4f}")]
                + [(f"gyro {a}", "gyro_drift_rad_s", "°/s", RAD2DEG, "{:.5f}") for a in AXES]):
            k = i if i < 4 else i - 4
            b, a = _f(seq(before.get(key), 4)[k]) * scale, _f(seq(after.get(key), 4)[k]) * scale
            ratio = b / a if math.isfinite(a) and a > 0 and math.isfinite(b) else math.nan
            rows.append([esc(f"{label} [{unit}]"), esc(_num(b, fmt)), esc(_num(a, fmt)), esc(_num(ratio, "{:.0f}x"))])
        out.append(_table(["quantity", "before writing", "after writing", "before / after"], rows))
        out.append(f"<p>level, +Z up, at {esc(', '.join(_num(c, '{:g}') for c in before.get('set_c') or []))} °C "
                   "(set points); before: the parameters the device had, after: with the temperature coefficients "
                   "written.</p>")
    wb = data.get("write")
    if isinstance(wb, dict):
        if wb.get("verified"):
            out.append(f"<p>written to the device: generation {esc(wb.get('generation'))}, read back bit-exactly, "
                       f"saved, rebooted and read back again ({esc(', '.join(map(str, wb.get('steps') or [])))}).</p>")
        else:
            restored = {True: "the previous parameters are active again", False: "the previous parameters are NOT "
                        "active", None: "whether the previous parameters are active is unknown"}.get(wb.get("previous_restored"))
            out.append(f'<p class="note">write-back failed: {esc(wb.get("error"))}; {esc(restored)}.</p>')

    from imubench.results.thermal import plot_thermal
    with tempfile.TemporaryDirectory() as td:
        png = plot_thermal(data, Path(td) / "thermal.png") if isinstance(data, dict) else None
        if png is not None:
            out.append("<h3>Bias against temperature</h3>"
                       + _img(png_data_uri(png), "gyro and accelerometer against temperature, with the fits"))
    return "\n".join(out)


# ------------------------------------------------------------------ closure
def closure_verdict(data: dict) -> tuple[bool, str] | None:
    """(passed, words) of a closure.json, as the console says it (results.closure.verdict_of)."""
    from imubench.results.closure import verdict_of
    z, floor = _f((data.get("after_rest_bias") or {}).get("distance_m")), _f((data.get("noise_floor") or {}).get(
        "sigma_distance_m"))
    if not (math.isfinite(z) and math.isfinite(floor) and floor > 0):
        return None
    return verdict_of(z, floor)


def _closure_section(directory: Path | None, session_uid: str | None = None, within=None) -> str:
    out = ['<h2 id="closure">Closure check</h2>']
    path = directory / "closure.json" if directory is not None else None
    data = _load_part(path, "closure check", "run imubench calibrate --closure, or imubench closure --out DIR "
                      "and give --closure DIR", out, session_uid, "closure check", within)
    if data is None:
        return "\n".join(out)
    if not isinstance(data, dict) or "after" not in data:
        out.append(f'<p class="missing">{esc(path)} holds no result (the recording did not finish: '
                   f'imubench closure --analyse {esc(directory)} recomputes it from capture.bin).</p>')
        return "\n".join(out)
    w = data.get("window") or {}
    out.append(f"<p>path {esc(data.get('path', '?'))}: {esc(_num(w.get('duration_s'), '{:.2f}'))} s of motion, "
               f"{esc(w.get('samples', '?'))} raw samples at {esc(_num(w.get('fs_hz'), '{:.0f}'))} Hz, integrated "
               "(strapdown, attitude from the gyros) from rest to rest; the closure is how far from the start the "
               "integration ends (docs/closure.md).</p>")
    rows = []
    for key in ("before", "after", "after_rest_bias"):
        r = data.get(key) or {}
        c = r.get("closure_m") or [None] * 3
        rows.append([esc(r.get("label", key))] + [esc(_num(v, "{:.4f}")) for v in (
            r.get("distance_m"), r.get("horizontal_m"), r.get("vertical_m"), r.get("end_speed_mps"), *c)])
    nf = data.get("noise_floor") or {}
    rows.append([esc("white-noise floor (1 sigma)"), esc(_num(nf.get("sigma_distance_m"), "{:.4f}")),
                 "", esc(_num(nf.get("sigma_z_m"), "{:.4f}")), "", "", "", ""])
    out.append(_table(["integration", "distance m", "horizontal m", "vertical m", "end speed m/s",
                       "x m", "y m", "z m"], rows))
    gb = data.get("gyro_bias_at_rest_rad_s")
    if gb:
        out.append(f"<p>the calibrated gyros read {esc(', '.join(_num(v * RAD2DEG, '{:+.4f}') for v in gb))} °/s "
                   "at the start rest (their bias change since the calibration).</p>")
    if data.get("improvement"):
        out.append(f"<p>calibration shrinks the closure error <b>{esc(_num(data['improvement'], '{:.0f}'))}x</b>.</p>")
    v = closure_verdict(data)
    if v is not None:
        out.append(f'<p class="{"note" if v[0] else "foreign"}">{esc(v[1])}</p>')
    if data.get("truth_closure_m") is not None:
        out.append(f"<p>the virtual bench's own path closes to {esc(_num(max(abs(v) for v in data['truth_closure_m']), '{:.1e}'))} m.</p>")
    plot = data.get("plot", "closure.png")
    uri, refused = _png(str(plot), within=directory) if isinstance(plot, str) and plot else \
        (None, f"the plot field {plot!r} is not a file name")
    if uri is not None or refused is not None:
        out.append(_img(uri, "top views before and after calibration and the distance from the start over time",
                        refused and f"closure.json names {plot!r}: {refused}"))
    return "\n".join(out)


# ------------------------------------------------------------------ the verdict
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
            why += (f"; the six faces are not square (χ²/dof {chi:.2g}): use --method multi, which needs no "
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
    status, words = _calibration_part(state or {}, result or {})
    off = _f((result or {}).get("faces_off_square_deg"))
    chi = _f((((result or {}).get("accel") or {}).get("extra") or {}).get("chi2_red"))
    if status == "fail" and math.isfinite(off) and "not square" in words:
        words = words.replace(f"the six faces are not square (χ²/dof {chi:.2g})",
                              f"the six faces are {off:.1f}° off square (χ²/dof {chi:.2g})")
    return status, words


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
    out_path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(out_path, doc)
