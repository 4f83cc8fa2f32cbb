"""Writing a parameter block back to a device and proving it took.

One sequence for every writer (the one-board session, the fixture's boards, the thermal
calibration): set, read back bit-exactly, save, reboot, read back again; on any failure the
previous parameters are put back. Also the flash-wear policy (warn before a save that takes a
parameter slot near its rated erase cycles) and the parameter block built from fits.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from imubench import units as U
from imubench.calib import TriadFit
from imubench.device.link import Device
from imubench.procedures.errors import SessionAborted
from imubench.procedures.presenter import Presenter
from imubench.wire.protocol_gen import Params, ParamsWhich


# Rated erase cycles of a flash page/sector per board (the parameter slots): STM32F103 datasheet
# (DS5319, "Flash memory endurance: 10 kcycles"); STM32F405/407 datasheet (DS8626: 10 kcycles,
# not checked against the datasheet here); the virtual device models the F103's.
ERASE_ENDURANCE = {"STM32F103": 10_000, "STM32F4": 10_000, "SIM": 10_000}
WEAR_WARN_FRACTION = 0.8        # warn before a save that takes a slot past 80 % of its rating


def wear_warning(dev: Device, fraction: float = WEAR_WARN_FRACTION, endurance: int | None = None) -> str | None:
    """The warning to give before a save, or None: a save erases the slot not holding the
    current block; if that takes it past `fraction` of the rated erase cycles, say so with the
    slot, its erase count (the device's lower bound, stats.param_slot_erases) and the rating."""
    from imubench.wire.ids import board_name
    stats = dev.stats()
    info = dev.info()
    rated = endurance or ERASE_ENDURANCE.get(board_name(info.board), 10_000)
    erases = [int(e) for e in stats.param_slot_erases]
    after = min(erases) + 1            # the next save erases the slot not holding the current block
    if after <= fraction * rated:
        return None
    return (f"flash wear: saving a changed block erases a parameter slot for at least the {after}th time (slots erased "
            f"{erases[0]} and {erases[1]} times so far), {100 * after / rated:.0f} % of the {rated} erase cycles "
            f"the flash is rated for (warning from {100 * fraction:.0f} %); save only when the parameters changed")


def write_verified(dev: Device, new: Params, previous: Params | None = None,
                   say=lambda s: None, reboot_wait_s: float = 10.0) -> dict:
    """Write a parameter block and prove it took: set_params, read back bit-exactly, save,
    reboot, read the active parameters back (bit-exactly, and the generation just saved).
    On any failure the previous parameters (`previous`, default: the active ones read
    first) are put back, and saved again if the new ones had been saved; the error is
    re-raised (SessionAborted if the restore failed too). Returns {"generation", "steps",
    "params"}. The caller validates `new` first (params.validate)."""
    if previous is None:
        previous = dev.get_params(ParamsWhich.ACTIVE).params
    steps = []
    saved = False                       # the new block reached the flash: a restore saves too
    try:
        dev.set_params(new)
        steps.append("set")
        if _pack(dev.get_params(ParamsWhich.ACTIVE).params) != _pack(new):
            raise SessionAborted("read-back after set_params differs from what was written")
        steps.append("read back")
        warning = wear_warning(dev)
        if warning:
            say(f"warning: {warning}")
        gen = dev.save_params()
        saved = True
        steps.append(f"already stored, flash untouched (generation {gen})" if dev.last_save_unchanged
                     else f"saved (generation {gen})")
        info = dev.reboot(wait_s=reboot_wait_s)
        dev.discard_buffered()
        steps.append("rebooted")
        stored = dev.get_params(ParamsWhich.ACTIVE)
        if _pack(stored.params) != _pack(new) or stored.generation != gen:
            raise SessionAborted("after reboot the active parameters are not the ones saved")
        steps.append(f"read back after reboot ({info.param_source and 'flash'})")
    except Exception as e:
        say(f"write-back failed after: {', '.join(steps) or 'nothing'} — {e}; restoring the previous parameters")
        try:
            dev.set_params(previous)
            if saved:
                dev.save_params()
        except Exception as e2:  # noqa: BLE001 - report both failures
            raise SessionAborted(f"write-back failed ({e}) and restoring the previous parameters failed too ({e2})") from e
        raise
    return {"generation": gen, "steps": steps, "params": new}


def restore(dev: Device, previous: Params) -> None:
    """Put a previous parameter block back, in RAM and in flash."""
    dev.set_params(previous)
    dev.save_params()


class VerifyFailed(SessionAborted):
    """The written parameters could not be verified; the message says whether the previous
    ones were put back."""


@dataclass
class WriteOutcome:
    written: bool                    # the new parameters are the device's now (False: the previous were put back)
    verified: bool                   # the device's own output within verify_mg in every verification attitude
    steps: list[str]                 # what write_verified did (set, read back, saved, rebooted, ...)
    verification: list[dict] = field(default_factory=list)    # [{name, after_g, angle_from_plan_deg}]
    worst_mg: float | None = None    # the worst | |a| - g | of the verification, mg


def write_and_verify(dev: Device, new: Params, previous: Params, verify: Callable[[], list[dict]],
                     verify_mg: float, ui: Presenter) -> WriteOutcome:
    """The one write-back of a calibration (the one-board session and every board of a
    fixture): write_verified (set, read back, save, reboot, read back; the previous block
    put back on any failure, which is re-raised), then verify() the device's own calibrated
    output; if the worst | |a| - g | is above verify_mg, or verify() fails (VerifyFailed, after
    restoring), the previous parameters are put back and saved. The steps are told to
    ui.step (write, verify) as they happen."""
    ui.step("write", "writing the parameters: set, read back, save, reboot, read back", "running")
    try:
        wb = write_verified(dev, new, previous=previous, say=ui.say)
    except Exception as e:
        ui.step("write", f"write-back failed: {e}; the previous parameters were put back", "failed")
        raise
    ui.say(f"written: {', '.join(wb['steps'])}")
    ui.step("write", f"written: {', '.join(wb['steps'])}", "done")
    ui.step("verify", "verifying the device's own output in the verification attitudes", "running")
    try:
        verification = verify()
    except Exception as e:
        reason = str(e)
        try:
            restore(dev, previous)
            reason += "; the previous parameters were restored"
        except Exception as e2:  # noqa: BLE001 - report both failures
            reason += f"; restoring the previous parameters failed too ({e2})"
        ui.step("verify", f"verification failed: {reason}", "failed")
        raise VerifyFailed(reason) from e
    worst = max(abs(v["after_g"] - 1.0) * 1e3 for v in verification)
    verified = worst <= verify_mg
    text = f"worst | |a| − g | = {worst:.3f} mg ({'within' if verified else 'OUTSIDE'} {verify_mg} mg)"
    ui.say(f"verification of the device's calibrated output: {text.replace('−', '-')}")
    ui.step("verify", text, "done" if verified else "failed")
    if not verified:
        restore(dev, previous)
        ui.say("verification failed: the previous parameters were written back and saved")
    return WriteOutcome(written=verified, verified=verified, steps=wb["steps"], verification=verification,
                        worst_mg=worst)


# ------------------------------------------------------------------- helpers
def params_from_fits(accel: TriadFit | None, gyro: TriadFit | None, base: Params, cal_id: int,
                     gsens=None) -> Params:
    """The device parameter block from fits (fields a fit does not cover keep `base`). A gyro
    fit sets the g-sensitivity too: gsens's G (calib.gsens, rad/s per g; stored per m/s²), or
    zero without one (the bias then holds it at the attitudes of the fit)."""
    p = Params.from_values(base.values())
    if accel is not None:
        p.accel_m = tuple(float(v) for v in np.asarray(accel.m).ravel())
        p.accel_b_mps2 = tuple(float(v) for v in accel.b)
    if gyro is not None:
        p.gyro_m = tuple(float(v) for v in np.asarray(gyro.m).ravel())
        p.gyro_b_rad_s = tuple(float(v) for v in gyro.b)
        g = np.zeros(9) if gsens is None else np.asarray(gsens.g, float).ravel() / U.G0_MPS2
        p.gyro_g_rad_s_per_mps2 = tuple(float(v) for v in g)
    p.cal_time_unix_s = int(time.time())
    p.cal_id = cal_id & 0xFFFFFFFF
    return p


def _pack(p: Params) -> bytes:
    return p.STRUCT.pack(*p.values())
