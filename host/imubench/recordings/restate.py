"""A recording's reading said back to people: the lines about its time stamps (what
check_timing found and did) and the command-line options that read its file again the same
way (printed, kept in session.json and the README of a --from session)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from imubench.recordings import GAP_FACTOR

if TYPE_CHECKING:
    from imubench.recordings import Recording


def timing_lines(rec: Recording) -> list[str]:
    """What the timing check found and did, for a person."""
    tm = rec.timing or {}
    out = []
    if not tm:
        return [f"{len(rec)} samples at {rec.fs_hz:g} Hz (declared rate; no timestamps to check)"]
    mean = tm.get("mean_dt_s", tm["median_dt_s"])
    rate = f"{tm['n_read']} samples at {tm['fs_hz']:.4g} Hz measured from the time stamps (mean step {mean * 1e3:.4g} ms)"
    if tm["jitter_rel"] < 1e-4:
        out.append(f"{rate}, regular steps (jitter under 0.01 % of a step)")
    else:
        out.append(f"{rate}, step jitter {tm.get('jitter_s', tm['jitter_rel'] * mean) * 1e3:.2g} ms RMS "
                   f"({100 * tm['jitter_rel']:.2g} %; steps {tm.get('min_dt_s', mean) * 1e3:.3g}"
                   f"–{tm.get('max_dt_s', mean) * 1e3:.3g} ms outside gaps)")
    if tm.get("long_steps_jitter"):
        out.append(f"{tm['long_steps_jitter']} steps longer than {GAP_FACTOR:g}× the mean are the clock's jitter, "
                   "not gaps: the next time stamps make them up (no sample missing)")
    if tm.get("duplicates"):
        out.append(f"{tm['duplicates']} samples repeat the timestamp before them "
                   f"({tm.get('duplicates_identical', 0)} identical rows): dropped")
    for gp in tm.get("gaps", [])[:10]:
        out.append(f"gap of {gp['duration_s']:.3f} s at t = {gp['t_s']:.3f} s ({gp['missing']} samples missing): "
                   "a still interval may continue across it; a turn or motion across it is not used for the gyro")
    if len(tm.get("gaps", [])) > 10:
        out.append(f"… {len(tm['gaps']) - 10} more gaps")
    if tm.get("resampled"):
        out.append(f"irregular steps: each continuous piece was resampled to a uniform {tm['fs_hz']:.4g} Hz grid "
                   f"(linear interpolation between the time stamps), {tm['n_used']} samples")
    return out


#: read() options and the command-line options that give them (imubench calibrate/allan --from)
_FLAGS = (("format", "--format"), ("gyro_file", "--gyro-file"), ("skip_rows", "--skip-rows"),
          ("columns", "--columns"), ("time_column", "--time-column"), ("time_unit", "--time-unit"),
          ("rate_hz", "--rate"), ("accel_unit", "--accel-unit"), ("gyro_unit", "--gyro-unit"), ("sensor", "--sensor"),
          ("accel_counts_per_g", "--accel-scale"), ("gyro_counts_per_dps", "--gyro-scale"),
          ("accel_offset", "--accel-offset"), ("gyro_offset", "--gyro-offset"), ("gyro_range_dps", "--gyro-range"),
          ("topic", "--topic"), ("device", "--device"))


def command_options(rec: Recording) -> list[str]:
    """The command-line options that read rec's file again the same way (rec.options: declared
    and detected), for a person to type and for session.json."""
    out = []
    for key, flag in _FLAGS:
        v = rec.options.get(key)
        if v is None or v == {}:
            continue
        if isinstance(v, dict):
            v = ",".join(f"{k}={x}" for k, x in v.items())
        elif isinstance(v, float):
            v = f"{v:g}"
        out += [flag, str(v)]
    return out


def command_line(rec: Recording, command: str = "calibrate") -> str:
    """`imubench COMMAND --from FILE OPTIONS`: the command that reads rec's file again the same way."""
    import shlex
    return " ".join(["imubench", command, "--from"] + [shlex.quote(x) for x in
                                                       [rec.source.split(" + ")[0], *command_options(rec)]])
