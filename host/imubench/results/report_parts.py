"""The report's sections beyond the calibration: noise (Allan), attitude (the step test),
temperature (the thermal fit) and the closure check, each from its own result file."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

from imubench import units as U
from imubench.wire.board_parts import BoardParts

from imubench.results.numbers import pm as _pm_sigma
from imubench.results.report_html import (
    esc,
    _f,
    _foreign,
    _img,
    _load_part,
    _missing,
    _num,
    _png,
    png_data_uri,
    read_json_within,
    _table,
    _unnamed_note,
)

G0 = U.G0_MPS2
RAD2DEG = 180.0 / math.pi
AXES = ("x", "y", "z")


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


def seq(x, n=3) -> list:
    """x as a list of n entries (None where x has none, or is not a list)."""
    x = x if isinstance(x, (list, tuple)) else []
    return [x[k] if k < len(x) else None for k in range(n)]


def _thermal_drift_and_write(data: dict) -> list[str]:
    """The thermal section's drift table (before and after writing the coefficients) and the
    write-back's outcome."""
    out = []
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
    return out


def _thermal_section(path: Path | None, session_uid: str | None = None) -> str:
    out = ['<h2 id="temperature">Temperature</h2>']
    data = _load_part(path, "temperature", "no thermal data given; run imubench thermal --out DIR and pass "
                      "--thermal DIR/thermal.json", out, session_uid, "temperature sweep")
    if data is None:
        return "\n".join(out)
    out.append(f"<p>from {esc(Path(path).name)}</p>")
    if isinstance(data, dict) and data.get("kind") == "imubench thermal warmup":
        from imubench.results.thermal_warmup import warmup_html
        with tempfile.TemporaryDirectory() as td:
            out.append(warmup_html(data, esc, lambda png, alt: _img(png_data_uri(png), alt), Path(td)))
        return "\n".join(out)

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
        parts = BoardParts.of_device(data.get("device"))     # the board's parts, as it reported them
        out.append(_table(["set [°C]", f"{parts.accel.name} [°C]", f"gyro X / Y / Z ({parts.gyro_words}) [°C]",
                           "settled after [s]",
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

    out += _thermal_drift_and_write(data)

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
