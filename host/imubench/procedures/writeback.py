"""Writing a parameter block back to a device and proving it took.

One sequence for every writer (the one-board session, the fixture's boards, the thermal
calibration): set, read back bit-exactly, save, reboot, read back again; on any failure the
previous parameters are put back. Also the flash-wear policy (warn before a save that takes a
parameter slot near its rated erase cycles) and the parameter block built from fits.
"""
from __future__ import annotations

import time

import numpy as np

from imubench.calib import TriadFit
from imubench.device.link import Device
from imubench.procedures.errors import SessionAborted
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
            if "saved" in " ".join(steps):
                dev.save_params()
        except Exception as e2:  # noqa: BLE001 - report both failures
            raise SessionAborted(f"write-back failed ({e}) and restoring the previous parameters failed too ({e2})") from e
        raise
    return {"generation": gen, "steps": steps, "params": new}


# ------------------------------------------------------------------- helpers
def params_from_fits(accel: TriadFit | None, gyro: TriadFit | None, base: Params, cal_id: int) -> Params:
    """The device parameter block from fits (fields a fit does not cover keep `base`)."""
    p = Params.from_values(base.values())
    if accel is not None:
        p.accel_m = tuple(float(v) for v in np.asarray(accel.m).ravel())
        p.accel_b_mps2 = tuple(float(v) for v in accel.b)
    if gyro is not None:
        p.gyro_m = tuple(float(v) for v in np.asarray(gyro.m).ravel())
        p.gyro_b_rad_s = tuple(float(v) for v in gyro.b)
    p.cal_time_unix_s = int(time.time())
    p.cal_id = cal_id & 0xFFFFFFFF
    return p


def _pack(p: Params) -> bytes:
    return p.STRUCT.pack(*p.values())
