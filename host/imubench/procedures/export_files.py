"""A session's result record in the calibration formats of the export registry
(results.exports): what a live session, a station board and the station page write."""
from __future__ import annotations

from pathlib import Path

from imubench.results.exports import write_index


def _safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or "imu"


def write_calibration(kinds, directory, result: dict, *, name: str, comment: str = "",
                      px4_acc_id: int | None = None, px4_gyro_id: int | None = None) -> dict:
    """The calibration formats `kinds` of a session's result record (accel/gyro M and b in SI,
    the g-sensitivity when applied, the parameter block written) into directory as
    calibration-NAME.*; returns {kind: [paths]} (a format that cannot be made from this result
    maps to [] and the reason is in result['notes'])."""
    import numpy as np

    from imubench.calib import TriadFit
    from imubench.results import paramfiles
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)

    def fit(sec, bkey):
        if not sec or sec.get("m") is None:
            return None
        return TriadFit(method=sec.get("method", ""), m=np.asarray(sec["m"], float), b=np.asarray(sec[bkey], float),
                        cov=np.zeros((12, 12)))
    accel, gyro = fit(result.get("accel"), "b_mps2"), fit(result.get("gyro"), "b_rad_s")
    if accel is None:
        raise ValueError("the result has no accelerometer calibration to export")
    gs = result.get("gsens") or {}
    gsens = np.radians(np.asarray(gs["g_dps_per_g"], float)) if gs.get("applied") else None
    params = None
    if "params" in kinds:
        from imubench.wire import params as PR
        if result.get("params_after"):
            params = PR.from_json(result["params_after"])
        else:
            from imubench.calib.gsens import GSensFit
            from imubench.procedures.writeback import params_from_fits
            g_fit = None if gsens is None else GSensFit(b=np.zeros(3), g=gsens, cov=np.zeros((12, 12)), chi2=0.0,
                                                        dof=0, residuals=np.zeros((0, 3)))
            params = params_from_fits(accel, gyro, PR.identity(), 0, g_fit)
    out = {}
    for kind in kinds:
        out[kind] = [str(p) for p in paramfiles.write(
            kind, d / f"calibration-{_safe_name(name)}", accel=accel, gyro=gyro, accel_factor=1.0,
            gyro_factor=1.0, accel_unit="mps2", gyro_unit="rad_s", scaled=True, params=params, comment=comment,
            gsens=gsens, px4_acc_id=px4_acc_id, px4_gyro_id=px4_gyro_id)]
    write_index(d, "calibration", out, comment)
    return out
