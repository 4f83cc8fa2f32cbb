"""What calibrating a recording writes (`imubench calibrate --from`): the session directory of
the analysis (procedures.from_file.FileAnalysis) as a session's, with the recording's own
section and the result in other tools' layouts; a refused analysis still leaves its evidence.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.files import make_dir
from imubench.procedures.from_file import FileAnalysis, FileConfig
from imubench.recordings import Recording, RecordingError, timing_lines
from imubench.results.atomic import write_json_atomic
from imubench.results.record import jsonable
from imubench.results.sessionfile import SESSION_SCHEMA


def calibrate_recording(rec: Recording, directory, cfg: FileConfig, say=print) -> tuple[dict, FileAnalysis]:
    """Analyse a recording and write what a session writes into directory: session.json (with
    the result), residuals.png, segmentation.png, report.html and the layouts of cfg.writers.
    Returns (result, analysis). Recording in the history is the caller's (it owns the
    database's path)."""
    from imubench.results import paramfiles
    from imubench.results.calibration import plot_pose_residuals
    from imubench.results.recording import plot_segmentation
    from imubench.results.report import build_report
    from imubench.results.recording import README, RESTS_CSV, rests_table, write_evidence
    d = Path(directory)
    held = [f for f in ("session.json", RESTS_CSV, README, "segmentation.png") if (d / f).exists()]
    if held:
        raise RecordingError(f"{d} already holds a session ({', '.join(held)}); choose another --dir (nothing was "
                             "overwritten)")
    for line in timing_lines(rec) + rec.notes:
        say(f"  {line}")
    fa = FileAnalysis(rec, cfg, say)
    try:
        result = fa.run()
    except Exception as e:      # noqa: BLE001 - refused or not, the folder shows what was found; then the error
        _leave_evidence(d, fa, e, say)
        raise
    make_dir(d)
    result["capture_dir"] = str(d.resolve())
    files = {}
    for kind in cfg.writers:
        try:
            files[kind] = [str(p) for p in _write_one(kind, d / f"calibration-{_safe(result['device_name'])}",
                                                      fa, result, paramfiles)]
        except RecordingError as e:
            files[kind] = []
            result["notes"].append(f"{kind} not written: {e}")
            say(f"  note: {kind} not written: {e}")
    result["exports"] = files
    if any(files.values()):             # what each file is for, also those that take no comments (imu_tk, JSON)
        from imubench.results.exports import write_index
        write_index(d, "calibration", {k: v for k, v in files.items() if v}, f"calibration of {result['device_name']}")
    if files.get("px4"):
        result["px4_missing_ids"] = paramfiles.px4_missing_ids(cfg.px4_acc_id, cfg.px4_gyro_id, fa.gyro is not None)
    state = {"schema": SESSION_SCHEMA, "started": result["started"],
             "config": {"method": fa.method, "gyro": cfg.gyro, "rate_hz": rec.fs_hz, "hold_s": cfg.min_still_s,
                        "rest_s": 0.0, "settle_s": cfg.window_s, "note": cfg.note, "write": False,
                        "tolerances": result["tolerances"], "from_file": rec.source},
             "rest": None,
             "poses": [{"name": p["name"], "direction": [0.0, 0.0, 0.0], "mean_mps2": iv.mean.tolist(),
                        "sigma_mean_mps2": iv.sigma_mean.tolist(), "n": int(iv.n), "start_index": int(iv.start),
                        "stop_index": int(iv.stop), "gyro_mean_rad_s": (rec.gyro[iv.start:iv.stop].mean(axis=0)
                                                                         * fa.fg).tolist(), "stream": 0}
                       for p, iv in zip(result["poses"], fa.intervals)],
             "result": result, "complete": True}
    write_json_atomic(d / "session.json", jsonable(state))
    plot_pose_residuals(result, d / "residuals.png")
    plot_segmentation(rec, result, d / "segmentation.png", accel_factor=fa.fa, gyro_factor=fa.fg)
    write_evidence(d, result, command=cfg.command)
    result["report"] = str(build_report(d))
    uses = [r["use"] for r in result["rests"]]
    if any(u != "used" for u in uses):
        say(rests_table(result))
    say(f"rests: {uses.count('used')} used, {uses.count('down-weighted')} down-weighted, {uses.count('left out')} "
        f"left out (the table: {d / RESTS_CSV}, {d / README})")
    return result, fa


def _leave_evidence(d: Path, fa: FileAnalysis, error: Exception, say) -> None:
    """A refused (or failed) analysis still writes its folder: the segmentation plot with the
    rests coloured by use, rests.csv and README.md with the reason; and says where. A failure
    to write it is said, never raised over the refusal."""
    from imubench.errors import ImubenchError
    from imubench.results.recording import plot_segmentation, rests_table, write_evidence
    reason = str(error) if isinstance(error, ImubenchError) else f"internal error ({type(error).__name__}: {error})"
    rec = fa.rec
    if not fa.clipping["gyro"] and len(fa.intervals) >= 2:   # refused before the gyro: its clipping is evidence too
        quiet, fa.say = fa.say, (lambda _line: None)
        try:
            fa._clipped_motions(fa.intervals)
        except Exception:  # noqa: BLE001 - the refusal's evidence, not a second failure
            pass
        finally:
            fa.say = quiet
    result = {"source": fa.source(), "rests": fa.rest_rows(), "clipping": fa.clipping, "notes": list(fa.notes),
              "refused": reason, "turns": [], "segmentation": []}
    try:
        make_dir(d)
        fa_si = fa.fa or U.G0_MPS2 / max(float(np.median(np.linalg.norm(rec.accel, axis=1))), 1e-300)
        plot_segmentation(rec, result, d / "segmentation.png", accel_factor=fa_si, gyro_factor=fa.fg or 1.0)
        write_evidence(d, result, command=fa.cfg.command)
    except (OSError, ValueError, ImubenchError) as e:
        say(f"note: the evidence of the refusal could not be written to {d}: {e}")
        return
    say(rests_table(result))
    say(f"refused; what was found is in {d}: segmentation.png (rests coloured by use), rests.csv, README.md "
        "(the reason)")


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "imu"


def _write_one(kind: str, prefix: Path, fa: FileAnalysis, result: dict, paramfiles) -> list[Path]:
    rec = fa.rec
    comment = f"imubench from {Path(rec.source.split(' + ')[0]).name}, {result['finished']}"
    if kind in paramfiles.SI_WRITERS and not (rec.accel_scaled and (rec.gyro_scaled or fa.gyro is None)):
        raise RecordingError("needs SI parameters, i.e. a declared nominal scale of the raw counts "
                             "(--accel-scale / --gyro-scale); imutk and imucal take counts as they are")
    params = None
    gs = fa.gsens or {}
    gsens = np.radians(np.array(gs["g_dps_per_g"])) if gs.get("applied") else None     # rad/s per g
    if kind == "params":
        from imubench.calib.gsens import GSensFit
        from imubench.procedures.writeback import params_from_fits
        from imubench.wire import params as PR
        g_fit = None if gsens is None else GSensFit(b=np.zeros(3), g=gsens, cov=np.zeros((12, 12)), chi2=0.0, dof=0,
                                                    residuals=np.zeros((0, 3)))
        params = params_from_fits(fa.accel, fa.gyro, PR.identity(), 0, g_fit)
    return paramfiles.write(kind, prefix, accel=fa.accel, gyro=fa.gyro, accel_factor=fa.fa, gyro_factor=fa.fg,
                        accel_unit=rec.accel_unit, gyro_unit=rec.gyro_unit, scaled=rec.accel_scaled,
                        params=params, comment=comment, gsens=gsens, px4_acc_id=fa.cfg.px4_acc_id,
                        px4_gyro_id=fa.cfg.px4_gyro_id)
