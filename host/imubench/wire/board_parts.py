"""The sensor parts one board carries, as its device reported them (info.parts) and the parts
table (protocol/parts.toml, generated into imubench.parts_gen) describes them: what every text
and file about that board names, and the part constants the host uses for it (the temperature
step of each part, the range all of them work in).

    parts = BoardParts.of_info(dev.info())       # a live device
    parts = BoardParts.of_device(rec["device"])  # a record (its device section's "parts")
    parts.accel.name, parts.gyro_words, parts.temperature_names, parts.operating_c
"""
from __future__ import annotations

from dataclasses import dataclass

from imubench.parts_gen import PART_BY_ID, PARTS, PartSpec

#: the parts of a board that reported none (firmware before the parts table, records made by it):
#: those boards carried an ADXL355 and three ADXRS450 (docs/sensors.md)
DEFAULT_NAMES = ("ADXL355", "ADXRS450", "ADXRS450", "ADXRS450")


def _spec(name_or_id, default: str) -> PartSpec:
    """The table's part for a name ("ADXL359") or an id (2); the default part for none or one
    this imubench does not know (a newer firmware's: its constants are not here)."""
    if isinstance(name_or_id, str):
        return PARTS.get(name_or_id.strip().lower()) or PARTS[default.lower()]
    return PART_BY_ID.get(int(name_or_id or 0)) or PARTS[default.lower()]


@dataclass(frozen=True)
class BoardParts:
    """The accelerometer part and the gyro part of each axis (X, Y, Z) of one board."""
    accel: PartSpec
    gyros: tuple[PartSpec, PartSpec, PartSpec]

    @classmethod
    def of(cls, parts) -> BoardParts:
        """From the four slots (accel, gyro X, Y, Z) as ids (info.parts) or names (a record's
        device["parts"]); None or a short list: the defaults (DEFAULT_NAMES) where missing."""
        p = list(parts or ())
        p += [None] * (4 - len(p))
        return cls(_spec(p[0], DEFAULT_NAMES[0]), tuple(_spec(x, DEFAULT_NAMES[1]) for x in p[1:4]))

    @classmethod
    def of_info(cls, info) -> BoardParts:
        """The parts a device reported in its Info message."""
        return cls.of(getattr(info, "parts", None))

    @classmethod
    def of_device(cls, device: dict | None) -> BoardParts:
        """The parts of a record's device section (wire.ids.device_identity: "parts" by name)."""
        return cls.of((device or {}).get("parts"))

    # ---------------------------------------------------------------- names
    @property
    def names(self) -> tuple[str, str, str, str]:
        return (self.accel.name, *(g.name for g in self.gyros))

    @property
    def gyro_words(self) -> str:
        """The gyros' part: "ADXRS450" when the three are one part, else per axis
        "ADXRS450/ADXRS450/ADXRS453" (X/Y/Z)."""
        names = [g.name for g in self.gyros]
        return names[0] if len(set(names)) == 1 else "/".join(names)

    @property
    def temperature_names(self) -> tuple[str, str, str, str]:
        """The four temperatures a board reports, named with their parts: the accelerometer's
        die ("ADXL355") and each gyro's own ("gyro X ADXRS450", ...)."""
        return (self.accel.name, *(f"gyro {a} {g.name}" for a, g in zip("XYZ", self.gyros)))

    @property
    def temperatures_text(self) -> str:
        """The four temperatures in a few words: "ADXL355/gyro X/Y/Z (ADXRS450)"."""
        return f"{self.accel.name}/gyro X/Y/Z ({self.gyro_words})"

    @property
    def text(self) -> str:
        """One line: "accelerometer ADXL355, gyros ADXRS450" (X/Y/Z when they differ)."""
        return f"accelerometer {self.accel.name}, gyros {self.gyro_words}"

    # ---------------------------------------------------------------- constants
    @property
    def accel_temp_step_c(self) -> float:
        """One LSB of the accelerometer's temperature, °C (ADXL355: 1/9.05)."""
        return 1.0 / abs(self.accel.temp_lsb_per_c)

    @property
    def gyro_temp_step_c(self) -> float:
        """One LSB of the coarsest gyro's temperature, °C (ADXRS450: 0.2)."""
        return max(1.0 / abs(g.temp_lsb_per_c) for g in self.gyros)

    @property
    def temp_step_c(self) -> float:
        """The coarsest temperature step of the board's parts, °C."""
        return max(self.accel_temp_step_c, self.gyro_temp_step_c)

    @property
    def operating_c(self) -> tuple[float, float]:
        """The temperatures every part of the board works in (their data sheets' operating
        ranges, intersected), °C."""
        specs = (self.accel, *self.gyros)
        return float(max(p.t_min_c for p in specs)), float(min(p.t_max_c for p in specs))

    def limiting_part(self, t_c: float) -> PartSpec | None:
        """The first part whose operating range does not hold t_c (None: all do)."""
        return next((p for p in (self.accel, *self.gyros) if not p.t_min_c <= t_c <= p.t_max_c), None)


DEFAULT = BoardParts.of(DEFAULT_NAMES)


def any_board_c() -> tuple[float, float]:
    """The temperatures a board of any parts in the table works in (every part's range,
    intersected), °C: what is checked before a device has said which parts it has."""
    return (float(max(p.t_min_c for p in PARTS.values())), float(min(p.t_max_c for p in PARTS.values())))


def coarsest_temp_step_c() -> float:
    """The coarsest temperature step of any part in the table, °C: what a check made before a
    device has said which parts it has must allow for."""
    return max(1.0 / abs(p.temp_lsb_per_c) for p in PARTS.values())
