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

from imubench.results.atomic import write_text_atomic
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


def _pm(v, s, fmt="{:+.6g}", sfmt="{:.2g}", scale=1.0) -> str:
    v, s = _f(v) * scale, _f(s) * scale
    if not math.isfinite(v):
        return "–"
    out = fmt.format(v)
    if math.isfinite(s):
        out += " ± " + sfmt.format(abs(s))
    return out


class Refused(ValueError):
    """A file the report will not embed; the message says why."""


def read_png(path, within=None, max_bytes: int = MAX_PLOT_BYTES) -> bytes | None:
    """The bytes of the PNG at path; None when there is no such file. Raises Refused for
    anything else than a regular PNG file of at most max_bytes, or (with `within`) one whose
    real path (symlinks resolved) is outside the directory `within`: a report is sent on its
    own, so it carries no file from elsewhere on the disk, and never blocks (a FIFO) or reads
    without end (a device)."""
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
    if not data.startswith(PNG_MAGIC):
        raise Refused(f"{path} is not a PNG")
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


def _load_json(path: Path | None, what: str, how: str, out: list[str]):
    """The JSON at path, or None after appending to out why there is none: "not measured"
    (with how to get it) when the file is absent, "unreadable" when it does not parse."""
    if path is None or not Path(path).is_file():
        out.append(_missing(what, how))
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        out.append(f'<p class="missing">{esc(what)} data {esc(path)}: unreadable ({esc(e)}); '
                   "not measured in this session.</p>")
        return None


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("imubench")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "unknown"


def _kv(d: dict) -> str:
    rows = [[esc(k), f'<span class="mono">{esc(json.dumps(v) if not isinstance(v, str) else v)}</span>']
            for k, v in d.items()]
    return _table(["key", "value"], rows, left=2)


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


def _fit_table(fit: dict, kind: str) -> str:
    """M (dimensionless, with the scale error in ppm on the diagonal) and b in SI and usual units."""
    si = "b_mps2" if kind == "accel" else "b_rad_s"
    m, sm = fit.get("m") or [], fit.get("sigma_m") or []
    b, sb = fit.get(si) or [], fit.get("sigma_" + si) or []
    rows = []
    for i, ax in enumerate(AXES):
        mrow = m[i] if i < len(m) else []
        srow = sm[i] if i < len(sm) else []
        cells = [esc(ax)]
        for j in range(3):
            v = mrow[j] if j < len(mrow) else None
            s = srow[j] if j < len(srow) else None
            cells.append(esc(_pm(v, s, "{:.7f}", "{:.1g}")))
        diag = mrow[i] if i < len(mrow) else None
        sdiag = srow[i] if i < len(srow) else None
        cells.append(esc(_pm(_f(diag) - 1.0, sdiag, "{:+.1f}", "{:.1f}", scale=1e6)))
        bv = b[i] if i < len(b) else None
        bs = sb[i] if i < len(sb) else None
        if kind == "accel":
            cells.append(esc(_pm(bv, bs, "{:+.6f}", "{:.2g}")))
            cells.append(esc(_pm(bv, bs, "{:+.4f}", "{:.2g}", scale=1e3 / G0)))
        else:
            cells.append(esc(_pm(bv, bs, "{:+.3e}", "{:.2g}")))
            cells.append(esc(_pm(bv, bs, "{:+.5f}", "{:.2g}", scale=RAD2DEG)))
        rows.append(cells)
    bu = ("b [m/s²]", "b [mg]") if kind == "accel" else ("b [rad/s]", "b [°/s]")
    head = ["axis", "M[·,x] ± 1σ", "M[·,y] ± 1σ", "M[·,z] ± 1σ", "scale error M<sub>ii</sub>−1 [ppm]",
            esc(bu[0]) + " ± 1σ", esc(bu[1]) + " ± 1σ"]
    out = _table(head, rows)
    facts = [f"fit method: <b>{esc(fit.get('method', '?'))}</b>"]
    if kind == "accel":
        rr = fit.get("residual_rms_mps2", fit.get("residual_rms"))
        if math.isfinite(_f(rr)):
            facts.append(f"residual RMS {esc(_num(rr))} m/s² = {esc(_num(_f(rr) * 1e3 / G0, '{:.4f}'))} mg")
    else:
        rr = fit.get("residual_rms")
        if math.isfinite(_f(rr)):
            facts.append(f"residual RMS {esc(_num(rr))} (fit units)")
    out += "<p>" + "; ".join(facts) + "</p>"
    extra = fit.get("extra")
    if extra:
        out += "<details><summary>fit details (extra)</summary><pre>" + esc(json.dumps(extra, indent=1)) + "</pre></details>"
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
                     esc(_num(a - b, "{:+.3f}")), esc(_pm(a, s, "{:+.4f}", "{:.4f}")),
                     esc(_num(temps[k] if k < len(temps) else None, "{:.2f}"))])
    out = _table(["pose", "samples", "|a| before [g]", "|a| after [g]", "Δ after − before [mg]",
                  "after: |a| − g ± 1σ [mg]", "temp [°C]"], rows)
    tol = _tol(result, "accel_rms_mg")
    rb, ra = _rms(before), _rms(after)
    verdict = "no tolerance given" if tol is None else \
        f"tolerance {tol:g} mg RMS: {'PASS' if ra <= tol else 'FAIL'}"
    out += f"<p>RMS of |a| − g over {len(names)} poses: before {rb:.3f} mg, after {ra:.4f} mg; {esc(verdict)}</p>"
    vnames, vafter, _vs = _verification(result)
    if len(vnames):
        vtol = _tol(result, "verify_mg")
        vrows = []
        for n, a, v in zip(vnames, vafter, result.get("verification") or []):
            ok = "" if vtol is None or not math.isfinite(a) else ("ok" if abs(a) <= vtol else "FAIL")
            vrows.append([esc(n), esc(f"{1 + a / 1000:.5f}") if math.isfinite(a) else "–",
                          esc(_num(a, "{:+.4f}")), esc(_num(v.get("angle_from_plan_deg"), "{:.2f}")), esc(ok)])
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
    out = ["<h2>Calibration</h2>"]
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
               + (f" accelerometer RMS after calibration: <b>{esc(_num(rms, '{:.4f}'))} mg</b>" if rms is not None else "")
               + "</p>")
    tol = result.get("tolerances") or {}
    if tol:
        out.append("<p>tolerances: " + ", ".join(f"{esc(k)} = {esc(v)}" for k, v in tol.items()) + "</p>")
    out.append("<h3>Accelerometer parameters (corrected = M·(raw − b))</h3>")
    out.append(_fit_table(result["accel"], "accel") if result.get("accel") else _missing("accelerometer fit", "no fit"))
    out.append("<h3>Gyroscope parameters</h3>")
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
    return "\n".join(out)


# ------------------------------------------------------------------ noise
def _noise_section(allan_dir: Path | None) -> str:
    out = ["<h2>Noise (Allan deviation)</h2>"]
    res = _load_json(allan_dir / "allan.json" if allan_dir is not None else None, "noise",
                     "no allan.json; record one with imubench allan and give --allan DIR", out)
    if res is None:
        return "\n".join(out)
    from imubench.analysis.allan import usual_units
    dur = _f(res.get("duration_s"))
    out.append(f"<p>{esc(_num(res.get('samples'), '{:.0f}'))} samples at {esc(_num(res.get('rate_hz'), '{:g}'))} Hz = "
               f"{esc(_num(dur / 3600, '{:.3f}'))} h; source {esc(', '.join(map(str, res.get('source') or [])))}</p>")
    dec = res.get("decoder") or {}
    if dec.get("samples_missing"):
        out.append(f'<p class="note">{esc(dec["samples_missing"])} samples were lost in the recording; the '
                   "analysis joins the pieces.</p>")
    for kind, title, si in (("accel", "Accelerometer", "m/s²"), ("gyro", "Gyroscope", "rad/s")):
        r = res.get(kind) or {}
        usual = res.get(kind + "_usual") or {}
        rows = []
        for a in AXES:
            if a not in r:
                continue
            ra = r[a]
            u = usual.get(a) or usual_units(ra, kind)
            if kind == "accel":
                rows.append([esc(a), esc(_num(ra.get("N"), "{:.4g}")), esc(_num(u.get("N_ug_per_rtHz"), "{:.4g}")),
                             esc(_num(u.get("VRW_m_s_per_rth"), "{:.4g}")), esc(_num(ra.get("B"), "{:.4g}")),
                             esc(_num(u.get("B_ug"), "{:.4g}")), esc(_num(ra.get("B_tau"), "{:.4g}")),
                             esc(_num(ra.get("K"), "{:.4g}")), esc(_num(u.get("K_ug_rtHz"), "{:.4g}"))])
            else:
                rows.append([esc(a), esc(_num(ra.get("N"), "{:.4g}")), esc(_num(u.get("N_deg_per_rth"), "{:.4g}")),
                             esc(_num(u.get("N_deg_s_per_rtHz"), "{:.4g}")), esc(_num(ra.get("B"), "{:.4g}")),
                             esc(_num(u.get("B_deg_h"), "{:.4g}")), esc(_num(ra.get("B_tau"), "{:.4g}")),
                             esc(_num(ra.get("K"), "{:.4g}")), esc(_num(u.get("K_deg_h_per_rth"), "{:.4g}"))])
        if kind == "accel":
            head = ["axis", "N [m/s²/√Hz]", "VRW [µg/√Hz]", "VRW [m/s/√h]", "B [m/s²]", "B [µg]",
                    "B at τ [s]", "K [m/s²·√Hz]", "K [µg·√Hz]"]
        else:
            head = ["axis", "N [rad/s/√Hz]", "ARW [°/√h]", "ARW [°/s/√Hz]", "B [rad/s]", "B [°/h]",
                    "B at τ [s]", "K [rad/s·√Hz]", "RRW [°/h/√h]"]
        out.append(f"<h3>{title}</h3>")
        out.append(_table([esc(h) for h in head], rows) if rows else _missing(title, "no axes in allan.json"))
        uri, refused = _png(f"allan_{kind}.png", within=allan_dir)
        out.append(_img(uri, f"{title} Allan deviation ({si})", refused))
    out.append("<p>N: white noise, ADEV(τ) = N/√τ read at τ = 1 s; B: bias instability = min ADEV / 0.664; "
               "K: rate random walk, ADEV(τ) = K·√(τ/3) read at τ = 3 s; – where not resolved.</p>")
    return "\n".join(out)


# ------------------------------------------------------------------ attitude, thermal
def _attitude_section(png: Path | None) -> str:
    out = ["<h2>Attitude</h2>"]
    if png is None:
        out.append(_missing("attitude", "no plot given; give --attitude FILE.png from imubench attitude"))
    else:
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


def _thermal_section(path: Path | None) -> str:
    out = ["<h2>Temperature</h2>"]
    data = _load_json(path, "temperature", "no thermal data given; run imubench thermal --out DIR and pass "
                      "--thermal DIR/thermal.json", out)
    if data is None:
        return "\n".join(out)
    out.append(f"<p>from {esc(Path(path).name)}</p>")

    def seq(x, n=3) -> list:
        x = x if isinstance(x, (list, tuple)) else []
        return [x[k] if k < len(x) else None for k in range(n)]

    def pm(v, s, fmt, scale):                  # value ± sigma in display units
        return esc(_pm(v, s, "{:+" + fmt + "}", "{:" + fmt + "}", scale))

    fit_keys = {}
    if isinstance(data, dict):
        for key, suffix, *_ in THERMAL_FIELDS:
            for vk, sk in ((f"{key}_{suffix}", f"{key}_sigma_{suffix}"), (key, key + "_sigma")):
                if vk in data:
                    fit_keys[key] = (vk, sk)
                    break
    if not (isinstance(data, dict) and (fit_keys or "points" in data)):
        out.append(_kv(data) if isinstance(data, dict) else "<pre>" + esc(json.dumps(data, indent=1)) + "</pre>")
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

    known = {k for pair in fit_keys.values() for k in pair} | {
        "t_ref_c", "notes", "points", "drift_before", "drift_after", "write", "status", "stage", "error", "schema", "kind"}
    rest = {k: v for k, v in data.items() if k not in known}
    if rest:
        out.append(_kv(rest))
    return "\n".join(out)


# ------------------------------------------------------------------ closure
def _closure_section(directory: Path | None) -> str:
    out = ["<h2>Closure check</h2>"]
    path = directory / "closure.json" if directory is not None else None
    data = _load_json(path, "closure check", "run imubench calibrate --closure, or imubench closure --out DIR "
                      "and give --closure DIR", out)
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
    if data.get("truth_closure_m") is not None:
        out.append(f"<p>the virtual bench's own path closes to {esc(_num(max(abs(v) for v in data['truth_closure_m']), '{:.1e}'))} m.</p>")
    plot = data.get("plot", "closure.png")
    uri, refused = _png(str(plot), within=directory) if isinstance(plot, str) and plot else \
        (None, f"the plot field {plot!r} is not a file name")
    if uri is not None or refused is not None:
        out.append(_img(uri, "top views before and after calibration and the distance from the start over time",
                        refused and f"closure.json names {plot!r}: {refused}"))
    return "\n".join(out)


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
    allan_dir = Path(allan_dir) if allan_dir is not None else session_dir
    uid = str((result.get("device") or {}).get("mcu_uid", "unknown device")).upper()
    when = str(result.get("started") or state.get("started") or "")

    sections = [_calibration_section(session_dir, state), _noise_section(allan_dir),
                _attitude_section(Path(attitude_png) if attitude_png else None),
                _thermal_section(Path(thermal_json) if thermal_json else None)]
    closure_dir = Path(closure_dir) if closure_dir is not None else session_dir / "closure"
    sections.insert(1, _closure_section(closure_dir))
    present = {"calibration": bool(result), "closure check": (closure_dir / "closure.json").is_file(),
               "noise": (allan_dir / "allan.json").is_file(),
               "attitude": attitude_png is not None, "temperature": thermal_json is not None}
    summary = ", ".join(f"{esc(k)}: {'yes' if v else 'not measured'}" for k, v in present.items())
    generated = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    doc = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>imubench report: {esc(uid)} {esc(when)}</title>
<style>{CSS}</style></head>
<body>
<h1>IMU calibration report</h1>
<p>device <b class="mono">{esc(uid)}</b>, session started {esc(state.get('started', '?'))}</p>
<p>contents — {summary}</p>
{chr(10).join(sections)}
<footer>generated by imubench {esc(_version())} at {esc(generated)} from session directory
<span class="mono">{esc(session_dir.resolve())}</span></footer>
</body></html>
"""
    out_path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(out_path, doc)
