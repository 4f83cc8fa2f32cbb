"""A session as a test record other tools read: the measurements of a run with their limits,
and the export of a station session (one run per board) as JSON or JUnit XML.

    imubench history --export SESSION --format junit --out session.xml

JUnit XML (the format of Ant's JUnit task that CI systems and test-station dashboards
ingest: Jenkins, GitLab, GitHub actions reporters): one <testsuite> per board, named by its
fixture slot and MCU UID, with the station, operator, fixture, firmware and host versions
and the capture's SHA-256 as <properties>; one <testcase> per measurement, its value, unit
and limits as the test case's <properties> and in words in <system-out>; a measurement
outside its limits is a <failure>, a board that stopped before it was measured an <error>
naming the stage and the reason.

Measurements (all with units in the name, docs/conventions.md):
    accel_norm_rms_mg              RMS of |a| − g over the poses after the fit   ≤ tolerance
    gyro_turntable_rms_dps         turntable fit residual RMS                    ≤ tolerance
    gyro_rotation_rms_deg          rotation-method residual RMS                  ≤ tolerance
    verify_<pose>_mg               | |a| − g | of the device's own output        ≤ tolerance
                                   (pose as plus_z_up, minus_x_up, ...)
    params_written                 1 when written, read back, saved, rebooted    ≥ 1
    samples_lost                   samples missing from the raw capture          ≤ 0
"""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

from imubench.results.numbers import significant
from imubench.text import xml_text

RAD_TO_DEG = 180.0 / math.pi


def _meas(name: str, value, unit: str, low=None, high=None) -> dict:
    v = None if value is None else float(value)
    ok = v is not None and math.isfinite(v) and (low is None or v >= low) and (high is None or v <= high)
    return {"name": name, "value": v, "unit": unit, "low": low, "high": high, "passed": bool(ok)}


def _slug(pose: str) -> str:
    """'+Z up (level)' -> 'plus_z_up': the pose's name without its gloss, signs as words."""
    base = pose.split("(")[0].replace("+", " plus ").replace("-", " minus ")
    return "_".join("".join(c if c.isalnum() else " " for c in base).lower().split())


def measurements_of(result: dict) -> list[dict]:
    """The measurements of a result record with their limits (the record's tolerances)."""
    tol = result.get("tolerances") or {}
    out = []
    rms = result.get("accel_rms_after_mg")
    if rms is None and result.get("poses") and result.get("accel"):
        after = [p.get("after_g") for p in result["poses"] if p.get("after_g") is not None]
        rms = math.sqrt(sum((a - 1.0) ** 2 for a in after) / len(after)) * 1e3 if after else None
    if rms is not None:
        out.append(_meas("accel_norm_rms_mg", rms, "mg", high=tol.get("accel_rms_mg")))
    g = result.get("gyro") or {}
    gm = g.get("method") or result.get("gyro_method")
    if g.get("residual_rms") is not None and gm == "turntable":
        out.append(_meas("gyro_turntable_rms_dps", g["residual_rms"] * RAD_TO_DEG, "°/s",
                         high=tol.get("gyro_turntable_rms_dps")))
    elif g.get("residual_rms") is not None and gm == "rotation":
        out.append(_meas("gyro_rotation_rms_deg", g["residual_rms"] * RAD_TO_DEG, "°",
                         high=tol.get("gyro_rotation_rms_deg")))
    for v in result.get("verification") or []:
        if v.get("after_g") is not None:
            out.append(_meas(f"verify_{_slug(v['name'])}_mg", abs(v["after_g"] - 1.0) * 1e3, "mg",
                             high=tol.get("verify_mg")))
    if result.get("accel") is not None and result.get("failure") is None:
        wanted = result.get("write_requested", True)
        if wanted:
            out.append(_meas("params_written", 1.0 if result.get("written") else 0.0, "bool", low=1.0))
    link = result.get("link") or {}
    if link.get("samples_missing") is not None:
        out.append(_meas("samples_lost", link["samples_missing"], "samples", high=0.0))
    return out


def _limits_text(m: dict) -> str:
    lo, hi, unit = m.get("low"), m.get("high"), m.get("unit") or ""
    u = f" {unit}" if unit and unit != "bool" else ""
    if lo is not None and hi is not None:
        return f"{lo:g} .. {hi:g}{u}"
    if hi is not None:
        return f"≤ {hi:g}{u}"
    if lo is not None:
        return f"≥ {lo:g}{u}"
    return "no limit"


def measurement_text(m: dict) -> str:
    """'0.0123 mg (limit ≤ 1 mg): pass' — three significant digits (a measured figure with
    no uncertainty of its own: results.numbers.value)."""
    v = m.get("value")
    unit = m.get("unit") or ""
    if v is None:
        vt = "not measured"
    elif unit == "bool":
        vt = "yes" if v >= 1 else "no"
    elif unit == "samples":                  # a count
        vt = f"{int(round(v))} samples"
    else:
        vt = significant(v, 3, unit)
    return f"{vt} (limit {_limits_text(m)}): {'pass' if m.get('passed') else 'FAIL'}"


def board_label(run: dict) -> str:
    slot = run.get("slot")
    who = run.get("mcu_uid") or (f"port {run['port']}" if run.get("port") else "unidentified board")
    return (f"slot {slot} " if slot is not None else "") + who


def _board_verdict(run: dict) -> str:
    if run.get("failure"):
        return "failed"
    return "passed" if run.get("passed") else "failed"


def session_dict(runs: list[dict]) -> dict:
    """One station session (or any list of runs) as a JSON-able test record."""
    first = runs[0] if runs else {}
    boards = []
    for r in runs:
        boards.append({
            "run_id": r["run_id"], "slot": r.get("slot"), "port": r.get("port"), "mcu_uid": r.get("mcu_uid"),
            "board": r.get("board"), "gyro_sn": r.get("gyro_sn"),
            "verdict": _board_verdict(r), "passed": bool(r.get("passed")), "written": bool(r.get("written")),
            "verified": bool(r.get("verified")),
            "failure": ({"stage": r.get("failed_stage"), "reason": r.get("failure")} if r.get("failure") else None),
            "started": r.get("started"), "finished": r.get("finished"),
            "method": r.get("method"), "gyro_method": r.get("gyro_method"),
            "fw_version": r.get("fw_version"), "fw_build": r.get("fw_build"),
            "measurements": r.get("measurements") or [],
            "params_before": r.get("params_before"), "params_after": r.get("params_after"),
            "capture": {"sha256": r.get("capture_sha256"), "uri": r.get("capture_uri")},
        })
    return {
        "format": "imubench-session", "version": 1,
        "session_id": first.get("session_id"), "station_id": first.get("station_id"),
        "operator": first.get("operator"), "fixture": first.get("fixture"), "host_version": first.get("host_version"),
        "started": min((r["started_utc"] for r in runs), default=None),
        "finished": max((r["finished_utc"] or "" for r in runs), default=None) or None,
        "boards": boards,
        "summary": {"boards": len(boards), "passed": sum(b["verdict"] == "passed" for b in boards),
                    "failed": sum(b["verdict"] != "passed" for b in boards)},
    }


def _strict(x):
    """NaN/inf -> null: standard JSON for other tools."""
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def session_json(runs: list[dict]) -> str:
    return json.dumps(_strict(session_dict(runs)), indent=1, allow_nan=False)


def _seconds(a: str | None, b: str | None) -> float:
    import datetime as dt
    try:
        return max(0.0, (dt.datetime.fromisoformat(b) - dt.datetime.fromisoformat(a)).total_seconds())
    except (TypeError, ValueError):
        return 0.0


def junit_xml(runs: list[dict]) -> str:
    """JUnit XML of a station session: one testsuite per board, one testcase per measurement."""
    d = session_dict(runs)
    root = ET.Element("testsuites", name=f"imubench session {d['session_id'] or ''}".strip())
    tot = {"tests": 0, "failures": 0, "errors": 0}
    for b, r in zip(d["boards"], runs):
        suite_name = f"{d['station_id'] or 'station'}/{board_label(r)}"
        suite = ET.SubElement(root, "testsuite", name=suite_name, timestamp=r.get("started_utc") or "",
                              hostname=str(d["station_id"] or ""),
                              time=f"{_seconds(r.get('started_utc'), r.get('finished_utc')):.1f}")
        props = ET.SubElement(suite, "properties")
        for k, v in (("mcu_uid", b["mcu_uid"]), ("slot", b["slot"]), ("port", b["port"]),
                     ("station_id", d["station_id"]), ("operator", d["operator"]), ("fixture", d["fixture"]),
                     ("session_id", d["session_id"]), ("run_id", b["run_id"]), ("fw_version", b["fw_version"]),
                     ("fw_build", b["fw_build"]), ("host_version", d["host_version"]),
                     ("capture_sha256", b["capture"]["sha256"]), ("capture_uri", b["capture"]["uri"]),
                     ("verdict", b["verdict"])):
            if v is not None:
                ET.SubElement(props, "property", name=k, value=str(v))
        classname = "imubench." + (b["mcu_uid"] or f"slot{b['slot']}")
        n = fails = errs = 0
        for m in b["measurements"]:
            n += 1
            tc = ET.SubElement(suite, "testcase", classname=classname, name=m["name"], time="0")
            tp = ET.SubElement(tc, "properties")
            for k in ("value", "unit", "low", "high"):
                if m.get(k) is not None:
                    ET.SubElement(tp, "property", name=k, value=repr(m[k]) if isinstance(m[k], float) else str(m[k]))
            text = measurement_text(m)
            if not m.get("passed"):
                fails += 1
                f = ET.SubElement(tc, "failure", type="limit", message=f"{m['name']} = {text}")
                f.text = text
            ET.SubElement(tc, "system-out").text = f"{m['name']} = {text}"
        if b["failure"]:
            n += 1
            errs += 1
            tc = ET.SubElement(suite, "testcase", classname=classname, name="session", time="0")
            e = ET.SubElement(tc, "error", type=b["failure"]["stage"] or "failed",
                              message=f"{b['failure']['stage']}: {b['failure']['reason']}")
            e.text = b["failure"]["reason"]
        elif not b["measurements"]:
            n += 1
            tc = ET.SubElement(suite, "testcase", classname=classname, name="session", time="0")
            if not b["passed"]:
                fails += 1
                ET.SubElement(tc, "failure", type="verdict", message="the run did not pass")
        suite.set("tests", str(n))
        suite.set("failures", str(fails))
        suite.set("errors", str(errs))
        suite.set("skipped", "0")
        tot["tests"] += n
        tot["failures"] += fails
        tot["errors"] += errs
    for k, v in tot.items():
        root.set(k, str(v))
    for el in root.iter():           # free text (a station name, a failure reason) stays well-formed XML
        for k, v in el.attrib.items():
            el.set(k, xml_text(v))
        if el.text is not None:
            el.text = xml_text(el.text)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
