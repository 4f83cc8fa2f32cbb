"""Device identifiers in the one format imubench prints and accepts everywhere: upper-case hex,
no separators (docs/conventions.md, "Identifiers").

    MCU UID        96 bits   24 hex digits        e.g. 1F0027001047333035343733
    ADXRS450 SN    32 bits    8 hex digits        e.g. B559FCF4
    ADXRS450 PID   16 bits    4 hex digits        e.g. 5201
    ADXL355 IDs    4 bytes    2 hex digits each   e.g. AD 1D ED 01

Input is forgiving about case, a leading 0x and separators (spaces, ':' and '-'), never about
the base: an identifier is always hexadecimal.
"""
from __future__ import annotations

import re

from imubench.parts_gen import PART_BY_ID
from imubench.wire.protocol_gen import Board, SampleStatus

#: the four sensors in the protocol's order (Info.sensors_present bit i, fault events' sensor i)
SENSOR_NAMES = ("accelerometer", "gyro X", "gyro Y", "gyro Z")
#: each sensor's bad-sample bit in SampleStatus, in that order
SENSOR_BAD_BITS = (SampleStatus.ACCEL_BAD, SampleStatus.GYRO_X_BAD, SampleStatus.GYRO_Y_BAD, SampleStatus.GYRO_Z_BAD)


def board_name(code: int) -> str:
    """The name of a board code of an Info message; a code this imubench does not know (a newer
    firmware) is named by its number, never an error."""
    try:
        return Board(code).name
    except ValueError:
        return f"unknown board code {int(code)} (firmware newer than this imubench? update imubench)"


def uid_text(uid) -> str:
    """The MCU unique ID (bytes, or the 12 ints of an Info message) as 24 hex digits."""
    return bytes(uid).hex().upper()


def sn_text(sn: int) -> str:
    return f"{int(sn):08X}"


def pid_text(pid: int) -> str:
    return f"{int(pid):04X}"


def byte_ids_text(ids) -> str:
    return " ".join(f"{int(x):02X}" for x in ids)


def parse_id(text: str) -> str:
    """Normalise an identifier typed by a person: upper-case hex digits, nothing else.
    Raises ValueError (naming the format) for anything that is not hexadecimal."""
    s = str(text).strip()
    if s[:2].lower() == "0x":
        s = s[2:]
    s = re.sub(r"[\s:\-]", "", s).upper()
    if not s or not re.fullmatch(r"[0-9A-F]+", s):
        raise ValueError(f"{text!r} is not an identifier: give hex digits as `imubench info` prints them "
                         "(an MCU UID or a unique prefix of it, or a gyro serial number)")
    return s


SLOT_NAMES = ("accel", "gyro_x", "gyro_y", "gyro_z")


def part_name(part_id: int) -> str:
    """The name of a part id of info.parts (protocol/parts.toml); 0 = none in that slot; an id
    this imubench does not know (a newer firmware) is named by its number."""
    if int(part_id) == 0:
        return "none"
    p = PART_BY_ID.get(int(part_id))
    return p.name if p else f"part {int(part_id)}"


def part_names(info) -> list[str]:
    """The part in each slot (accelerometer, gyro X, Y, Z) as the device identified them."""
    return [part_name(x) for x in getattr(info, "parts", (0, 0, 0, 0))]


def parts_text(parts) -> str:
    """One line for people: 'accel ADXL359, gyro_x ADXRS450, gyro_y ADXRS450, gyro_z ADXRS453'."""
    return ", ".join(f"{s} {p}" for s, p in zip(SLOT_NAMES, parts))


def device_identity(info) -> dict:
    """The identity of a device from its Info message, in the one format: what every result
    file records so that a result can be matched to its device (results.report refuses a
    part from another device)."""
    return {"mcu_uid": uid_text(info.mcu_uid), "board": board_name(info.board),
            "fw_version": ".".join(map(str, info.fw_version)), "fw_build": info.fw_build,
            "parts": part_names(info),
            "accel_ids": list(info.accel_ids), "gyro_pid": list(info.gyro_pid), "gyro_sn": list(info.gyro_sn)}
