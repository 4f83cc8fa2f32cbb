"""The history as text for a terminal: the devices, one device's runs and drift, first-pass
yield, failures and station sessions (`imubench history`); the data come from
results.history and analysis.drift."""
from __future__ import annotations

import math

from imubench.results.export import measurement_text
from imubench.results.numbers import pm
from imubench.results.record import _parse_time
from imubench.text import one_line
from imubench.wire.ids import parts_text, sn_text

_AXES = ("x", "y", "z")


def _pm(v, s, dec: int, width: int = 0) -> str:
    """value ± sigma to sigma's precision (results.numbers; `dec` decimals where no sigma)."""
    if v is None:
        return "-".rjust(width)
    if s is not None and math.isfinite(s) and s > 0:
        txt = pm(v, s)
    else:
        txt = f"{v:+.{dec}f} (not estimated)"
    return txt.ljust(width)


def _when(iso: str) -> str:
    t = _parse_time(iso)
    return t.strftime("%Y-%m-%d %H:%M UTC") if t else str(iso)


def _yes(b: bool) -> str:
    return "yes" if b else "NO"


def format_devices(devs: list[dict], path) -> str:
    if not devs:
        return f"no calibrations recorded yet in {path}"
    lines = [f"{'MCU UID':<24}  {'board':<6} {'runs':>4}  {'last calibration':<20}  {'method':<16}  {'result':<34}  "
             "parts (accel, gyro X Y Z)"]
    for d in devs:
        lr = d["last_run"] or {}
        method = lr.get("method", "-") + (f"/{lr['gyro_method']}" if lr.get("gyro_method") else "")
        res = ("passed" if lr.get("passed") else "FAILED") + (", written" if lr.get("written") else ", not written") \
            + (", verified" if lr.get("verified") else ", not verified") if lr else "-"
        parts = " ".join(d.get("parts") or ["-"])
        lines.append(f"{d['mcu_uid']:<24}  {d['board'] or '-':<6} {d['runs']:>4}  {_when(d['last_seen']):<20}  "
                     f"{method:<16}  {res:<34}  {parts}".rstrip())
    lines.append(f"({len(devs)} device{'s' if len(devs) != 1 else ''} in {path}; "
                 "`imubench history DEVICE` for one device's runs and drift)")
    return "\n".join(lines)


_LABEL_W = 24       # label column of the per-run lines
_CELL_W = 20        # one axis: "+1.0197 ± 0.0020"


def _triad_lines(t: dict, name: str, bias_unit: str, bias_label: str, bias_dec: int) -> list[str]:
    def row(label, values, sigmas, dec):
        return (f"  {label}".ljust(_LABEL_W)
                + "  ".join(f"{ax.upper()} " + _pm(v, s, dec, _CELL_W) for ax, v, s in zip(_AXES, values, sigmas))).rstrip()
    lines = [row(f"{name} bias [{bias_label}]", t[f"bias_{bias_unit}"], t[f"bias_sigma_{bias_unit}"], bias_dec),
             row(f"{name} scale [ppm]", t["scale_error_ppm"], t["scale_error_sigma_ppm"], 1)]
    c = t["cross_axis"]
    lines.append(f"  {name} cross-axis".ljust(_LABEL_W) + f"largest {c['term']} = {_pm(c['ppm'], c['sigma_ppm'], 1)} ppm")
    return lines


def format_device_report(rep: dict) -> str:
    dev = rep["device"]
    runs = rep["runs"]
    sn = dev.get("gyro_sn")
    out = [f"device {dev['mcu_uid']}  board {dev['board'] or '-'}"
           + (f"  parts {parts_text(dev['parts'])}" if dev.get("parts") else "")
           + (f"  gyro SN {' '.join(sn_text(x) for x in sn)}" if sn else "")
           + f"  {len(runs)} run{'s' if len(runs) != 1 else ''}"]
    for s in runs:
        out.append("")
        gm = f", gyro {s['gyro_method']}" if s["gyro_method"] else ", no gyro calibration"
        out.append(f"run {s['index']} (id {s['run_id']})  {_when(s['started'])}  method {s['method']}{gm}  "
                   f"fw {s['fw_version']} ({s['fw_build']})")
        out += _station_lines(s)
        if s["accel"] is None:
            out.append("  accel".ljust(_LABEL_W) + "no fit (the board failed before it)")
        else:
            out += _triad_lines(s["accel"], "accel", "mg", "mg", 4)
        if s["accel"] is not None and s["accel"]["residual_rms_mg"] is not None:
            out.append("  accel fit residual".ljust(_LABEL_W) + f"{s['accel']['residual_rms_mg']:.4f} mg RMS")
        if s["gyro"] is not None:
            out += _triad_lines(s["gyro"], "gyro", "dps", "°/s", 5)
        t = s["temperature_c"]
        temp = []
        if t["accel"] is not None:
            temp.append(f"accel {t['accel']:.1f} °C")
        if t["gyro"]:
            temp.append("gyro X/Y/Z " + "/".join("-" if v is None else f"{v:.1f}" for v in t["gyro"]) + " °C")
        out.append("  temperature".ljust(_LABEL_W) + (", ".join(temp) or "-"))
        out.append("  status".ljust(_LABEL_W) + f"passed {_yes(s['passed'])}, written {_yes(s['written'])}, "
                   f"verified {_yes(s['verified'])}")
        if s.get("failure"):
            out.append("  failed".ljust(_LABEL_W) + one_line(f"at {s['failed_stage']}: {s['failure']}"))
        for m in s.get("measurements") or []:
            out.append("  measured".ljust(_LABEL_W) + f"{m['name']} = {measurement_text(m)}")
        if s["note"]:
            out.append("  note".ljust(_LABEL_W) + one_line(s["note"]))
    out.append("")
    out += _format_drift(rep["drift"], len(runs))
    return "\n".join(out)


def _station_lines(s: dict) -> list[str]:
    """Where and by whom a run was made, and where its raw capture is (schema-2 runs)."""
    out = []
    if s.get("station_id") or s.get("operator") or s.get("fixture"):
        parts = [f"station {s.get('station_id') or '-'}" + (f" slot {s['slot']}" if s.get("slot") is not None else "")]
        if s.get("operator"):
            parts.append(f"operator {s['operator']}")
        if s.get("fixture"):
            parts.append(f"fixture {s['fixture']}")
        if s.get("host_version"):
            parts.append(f"host {s['host_version']}")
        if s.get("session_id"):
            parts.append(f"session {s['session_id']}")
        out.append("  where".ljust(_LABEL_W) + ", ".join(parts))
    if s.get("capture_sha256"):
        out.append("  raw capture".ljust(_LABEL_W) + f"capture sha256 {s['capture_sha256']}"
                   + (f" at {s['capture_uri']}" if s.get("capture_uri") else ""))
    return out


# ------------------------------------------------------------------ production queries, as text
def _pct(x) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def format_yield(rows: list[dict], by: str, path) -> str:
    """First-pass yield per station and/or day (a percentage of counted runs: one decimal,
    the resolution of 1 in 1000 runs)."""
    if not rows:
        return f"no runs in {path} match"
    keys = {"station": ["station"], "day": ["day"], "station_day": ["station", "day"]}[by]
    w = {"station": max(8, *(len(str(r["station"])) for r in rows)) if "station" in keys else 0, "day": 10}
    head = "".join(f"{k:<{w[k]}}  " for k in keys) + f"{'runs':>5} {'passed':>6} {'failed':>6} {'yield':>8}  boards"
    lines = [head]
    for r in rows:
        lines.append("".join(f"{str(r[k]):<{w[k]}}  " for k in keys)
                     + f"{r['runs']:>5} {r['passed']:>6} {r['failed']:>6} {_pct(r['yield']):>8}  {r['devices']}")
    n = sum(r["runs"] for r in rows)
    p = sum(r["passed"] for r in rows)
    lines.append("".join(f"{('total' if i == 0 else ''):<{w[k]}}  " for i, k in enumerate(keys))
                 + f"{n:>5} {p:>6} {n - p:>6} {_pct(p / n if n else None):>8}")
    lines.append(f"(first-pass yield = passed runs / runs, from {path}; `--failed` lists why the others failed)")
    return "\n".join(lines)


def format_failures(runs: list[dict], path) -> str:
    """The boards that failed and why: the stage and reason, or the measurements out of limits."""
    if not runs:
        return f"no failed runs in {path}"
    lines = []
    for r in runs:
        who = r["mcu_uid"] or f"unidentified board (port {r.get('port') or '-'})"
        where = f"station {r.get('station_id') or '-'}" + (f" slot {r['slot']}" if r.get("slot") is not None else "")
        lines.append(f"{_when(r['started'])}  {who}  {where}  run {r['run_id']}"
                     + (f"  session {r['session_id']}" if r.get("session_id") else ""))
        reasons = []
        if r.get("failure"):
            reasons.append(f"failed at {r.get('failed_stage') or '?'}: {r['failure']}")
        for m in r.get("measurements") or []:
            if not m.get("passed"):
                reasons.append(f"{m['name']} = {measurement_text(m)}")
        if not reasons:
            reasons.append("did not pass" + (f" ({r['note']})" if r.get("note") else ""))
        lines += [f"    {x}" for x in reasons]
    lines.append(f"({len(runs)} failed run{'s' if len(runs) != 1 else ''} in {path}, newest first)")
    return "\n".join(lines)


def format_sessions(rows: list[dict], path) -> str:
    if not rows:
        return f"no station sessions in {path}"
    lines = [f"{'session':<36}  {'station':<10} {'operator':<10} {'started':<20} boards passed"]
    for r in rows:
        lines.append(f"{r['session_id']:<36}  {r['station_id'] or '-':<10} {r['operator'] or '-':<10} "
                     f"{_when(r['started']):<20} {r['boards']:>6} {r['passed']:>6}")
    lines.append("(`imubench history --export SESSION --format junit|json` writes one as a test record)")
    return "\n".join(lines)


_DRIFT_LABELS = {"accel_bias_mg": ("accel bias [mg]", 4), "accel_scale_ppm": ("accel scale [ppm]", 1),
                 "gyro_bias_dps": ("gyro bias [°/s]", 5), "gyro_scale_ppm": ("gyro scale [ppm]", 1)}


_DRIFT_LABEL_W = 28
_DRIFT_CELL_W = 28


def _format_drift(dr: dict, n_runs: int) -> list[str]:
    thr = dr["threshold_sigmas"]
    if n_runs < 2:
        return ["drift: only one run, nothing to compare yet"]
    out = [f"drift across runs: change ± combined 1σ; DRIFT where |change| > {thr:g}σ (a real change, not fit noise)"]
    for key, q in dr["quantities"].items():
        label, dec = _DRIFT_LABELS[key]
        # rows: each step, then first -> last, over the runs that estimated the quantity
        rows: dict[tuple, dict] = {}
        for ax in _AXES:
            a = q["axes"][ax]
            for st in a["steps"]:
                rows.setdefault(("step", st["from"], st["to"]), {})[ax] = st
            if a["first_last"] is not None and len(a["runs"]) > 2:
                fl = a["first_last"]
                rows.setdefault(("first_last", fl["from"], fl["to"]), {})[ax] = fl
        if not rows:
            out.append(f"  {label}: fewer than two runs estimated it")
            continue
        out.append(f"  {label}".ljust(_DRIFT_LABEL_W) + "".join(f"{ax.upper():<{_DRIFT_CELL_W}}" for ax in _AXES).rstrip())
        for k in sorted(rows, key=lambda k: (k[0] == "first_last", k[1], k[2])):
            name = (f"first -> last ({k[1]} -> {k[2]})" if k[0] == "first_last" else f"run {k[1]} -> {k[2]}")
            cells = []
            for ax in _AXES:
                st = rows[k].get(ax)
                cell = "-" if st is None else _pm(st["change"], st["sigma"], dec) + (" DRIFT" if st["flagged"] else "")
                cells.append(cell.ljust(_DRIFT_CELL_W))
            out.append(f"    {name}".ljust(_DRIFT_LABEL_W) + "".join(cells).rstrip())
    flagged = dr["flagged"]
    if flagged:
        out.append(f"{len(flagged)} change{'s' if len(flagged) != 1 else ''} larger than {thr:g}σ: "
                   + "; ".join(f"{f['quantity'].rsplit('_', 1)[0].replace('_', ' ')} {f['axis'].upper()} "
                               f"run {f['from']} -> {f['to']} {f['change']:+.{_DRIFT_LABELS[f['quantity']][1]}f} "
                               f"{f['unit']} ({f['n_sigma']:.1f}σ)" for f in flagged))
    else:
        out.append(f"no change larger than {thr:g}σ: bias and scale are stable within the fits' uncertainty")
    return out


# ------------------------------------------------------------------ CLI
def strict_json(x):
    """NaN/inf → null, so --json output is standard JSON."""
    if isinstance(x, dict):
        return {k: strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
