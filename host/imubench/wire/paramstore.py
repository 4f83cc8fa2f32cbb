"""Parameter-store records built on the host, byte for byte as the firmware writes them.

The firmware keeps its calibration block in two flash slots (firmware/core/param_store.h).
This module builds and checks such records in Python, e.g. to preload a parameter page into
QEMU (`-device loader,file=page.bin,addr=0x0801F800,force-raw=on`, see imubench.device.qemu) or to
prepare a factory image. Record layout, store format 1 (all little-endian; a = max(4,
program_unit)):

    offset   size  field
    0        4     magic 0x53504249 ('I' 'B' 'P' 'S')
    4        2     format 1
    6        2     payload_version (the parameter block version, PARAM_BLOCK_VERSION)
    8        4     generation (newer wins, serial-number arithmetic; 0 is never written)
    12       2     payload_len N
    14       1     flags (bit 0 CLEARED: a factory reset, N == 0)
    15       1     crc_salt: smallest of 0, 1, 2 giving a CRC that is neither 0 nor 0xFFFFFFFF
    16       N     payload (the params block, protocol_gen.Params packed: 196 bytes in layout 2,
                   160 in layout 1, which is layout 2 without gyro_g; the firmware reads a
                   layout-1 record with G = 0, params_record(..., layout=1) writes one)
    16+N     P     zero padding up to crc_off = round_up(16 + N, a)
    crc_off  4     CRC-32C over bytes [0, crc_off)
    +4       a-4   zero padding (program_unit > 4 only)

tests/device/test_qemu.py checks these bytes against the C store (ib_ps_save / ib_ps_load).

    python -m imubench.wire.paramstore --layout qemu-f1 -o page.bin            # identity params
    python -m imubench.wire.paramstore --layout f4 --params cal.json -o page.bin
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import crcmod.predefined

from imubench.wire.protocol_gen import PARAM_BLOCK_VERSION, Params

MAGIC = 0x53504249
FORMAT = 1
HEADER_SIZE = 16
FLAG_CLEARED = 0x01
MAX_PROGRAM_UNIT = 32
HEADER = struct.Struct("<IHHIHBB")

_crc32c = crcmod.predefined.mkCrcFun("crc-32c")


def crc32c(data: bytes) -> int:
    """CRC-32C as ib_crc32c(0, data, len) computes it (check value 0xE3069283)."""
    return _crc32c(bytes(data))


@dataclass(frozen=True)
class Layout:
    """Where a board keeps its two slots (firmware/boards/*/*.ld, flash_if.h)."""
    slots: tuple[int, int]
    slot_size: int
    program_unit: int


LAYOUTS: dict[str, Layout] = {
    # STM32F103C8 image (64 KiB map, also fine on an RB): the last two 1 KiB pages
    "f103": Layout((0x0800F800, 0x0800FC00), 1024, 2),
    # QEMU stm32vldiscovery (128 KiB) and a 128 KiB F103RB layout
    "qemu-f1": Layout((0x0801F800, 0x0801FC00), 1024, 2),
    # STM32F405/407: sectors 10 and 11, 4 KiB used, x32 programming
    "f4": Layout((0x080C0000, 0x080E0000), 4096, 4),
    "qemu-f4": Layout((0x080C0000, 0x080E0000), 4096, 4),
}


def _check_pu(program_unit: int) -> int:
    if program_unit < 1 or program_unit > MAX_PROGRAM_UNIT or program_unit & (program_unit - 1):
        raise ValueError(f"program_unit must be a power of two in 1..{MAX_PROGRAM_UNIT}, not {program_unit}")
    return max(4, program_unit)


def _round_up(x: int, a: int) -> int:
    return (x + a - 1) // a * a


def record_size(payload_len: int, program_unit: int) -> int:
    """Bytes a record with a payload_len-byte payload occupies (ib_ps_record_size)."""
    a = _check_pu(program_unit)
    return _round_up(HEADER_SIZE + payload_len, a) + a


def max_payload(slot_size: int, program_unit: int) -> int:
    """Largest payload a slot holds (ib_ps_max_payload)."""
    a = _check_pu(program_unit)
    return min(0xFFFF, ((slot_size - a) // a) * a - HEADER_SIZE)


def build_record(payload: bytes, *, generation: int = 1, payload_version: int = PARAM_BLOCK_VERSION,
                 program_unit: int = 4, flags: int = 0) -> bytes:
    """One record exactly as ib_ps_save (flags 0) / ib_ps_clear (flags CLEARED) writes it."""
    payload = bytes(payload)
    a = _check_pu(program_unit)
    n = len(payload)
    if n > 0xFFFF:
        raise ValueError("payload longer than 65535 bytes")
    if flags & ~FLAG_CLEARED:
        raise ValueError(f"unknown flag bits 0x{flags:02X}")
    if flags & FLAG_CLEARED and n:
        raise ValueError("a cleared record carries no payload")
    if not 0 < generation <= 0xFFFFFFFF:
        raise ValueError("generation must be 1..2^32-1 (0 means 'none' and is never written)")
    if not 0 <= payload_version <= 0xFFFF:
        raise ValueError("payload_version must fit 16 bits")
    crc_off = _round_up(HEADER_SIZE + n, a)
    pad = bytes(crc_off - HEADER_SIZE - n)
    for salt in (0, 1, 2):
        body = HEADER.pack(MAGIC, FORMAT, payload_version, generation, n, flags, salt) + payload + pad
        crc = crc32c(body)
        if crc not in (0, 0xFFFFFFFF):
            break
    return body + struct.pack("<I", crc) + bytes(a - 4)


PARAMS_SIZE_V1 = Params.SIZE - 36          # layout 1: today's block without gyro_g (9 float32 at its end)


def params_payload(p: Params, layout: int = PARAM_BLOCK_VERSION) -> bytes:
    """The parameter block (ib_params_pack): 196 bytes in layout 2; layout=1 gives the block the
    previous firmware stored (its first 160 bytes; G must then be zero)."""
    data = Params.STRUCT.pack(*p.values())
    if layout == PARAM_BLOCK_VERSION:
        return data
    if layout == 1:
        if any(p.gyro_g_rad_s_per_mps2):
            raise ValueError("a layout-1 block has no gyro g-sensitivity: G must be zero")
        return data[:PARAMS_SIZE_V1]
    raise ValueError(f"parameter block layout {layout}: this host knows 1 and {PARAM_BLOCK_VERSION}")


def params_record(p: Params, *, generation: int = 1, program_unit: int = 4, layout: int = PARAM_BLOCK_VERSION) -> bytes:
    """A record holding p, in today's layout or (layout=1) as the previous firmware stored it."""
    return build_record(params_payload(p, layout), generation=generation, payload_version=layout,
                        program_unit=program_unit)


def cleared_record(*, generation: int = 1, program_unit: int = 4) -> bytes:
    """A factory-reset record (ib_ps_clear)."""
    return build_record(b"", generation=generation, payload_version=0, program_unit=program_unit,
                        flags=FLAG_CLEARED)


def slot_image(record: bytes, slot_size: int, fill: int = 0xFF) -> bytes:
    """A whole slot: the record, then `fill` (0xFF = erased NOR flash) up to slot_size."""
    if len(record) > slot_size:
        raise ValueError(f"record of {len(record)} bytes does not fit a {slot_size}-byte slot")
    return bytes(record) + bytes([fill]) * (slot_size - len(record))


@dataclass
class Record:
    generation: int
    payload_version: int
    flags: int
    salt: int
    payload: bytes

    @property
    def cleared(self) -> bool:
        return bool(self.flags & FLAG_CLEARED)

    def params(self) -> Params:
        """The block, a layout-1 one migrated as the firmware does (G = 0)."""
        payload = self.payload
        if self.payload_version == 1 and len(payload) == PARAMS_SIZE_V1:
            payload = payload + bytes(Params.SIZE - PARAMS_SIZE_V1)
        if len(payload) != Params.SIZE:
            raise ValueError(f"payload is {len(self.payload)} bytes, a params block {Params.SIZE}")
        return Params.from_values(Params.STRUCT.unpack(payload))


class InvalidRecord(ValueError):
    def __init__(self, state: str, detail: str = ""):
        super().__init__(f"{state}: {detail}" if detail else state)
        self.state = state  # the C store's slot state name (ib_ps_slot_state_name)


def parse_record(slot: bytes, *, program_unit: int = 4, slot_size: int | None = None) -> Record:
    """Validate a slot's contents as ps_check_slot() does; raises InvalidRecord with the
    C store's reason ('blank', 'bad magic', 'bad crc', ...)."""
    slot = bytes(slot)
    a = _check_pu(program_unit)
    slot_size = len(slot) if slot_size is None else slot_size
    if len(slot) < HEADER_SIZE:
        raise InvalidRecord("read error", "shorter than a header")
    hdr = slot[:HEADER_SIZE]
    if hdr in (bytes(HEADER_SIZE), b"\xff" * HEADER_SIZE):
        raise InvalidRecord("blank")
    magic, fmt, pv, gen, n, flags, salt = HEADER.unpack(hdr)
    if magic != MAGIC:
        raise InvalidRecord("bad magic", f"0x{magic:08X}")
    if fmt != FORMAT:
        raise InvalidRecord("unsupported format", str(fmt))
    if flags & ~FLAG_CLEARED or (flags & FLAG_CLEARED and n):
        raise InvalidRecord("bad header", f"flags 0x{flags:02X}, payload_len {n}")
    if n > max_payload(slot_size, program_unit):
        raise InvalidRecord("bad length", str(n))
    crc_off = _round_up(HEADER_SIZE + n, a)
    if len(slot) < crc_off + a:
        raise InvalidRecord("read error", "slot shorter than the record")
    stored = struct.unpack_from("<I", slot, crc_off)[0]
    if stored in (0, 0xFFFFFFFF):
        raise InvalidRecord("incomplete")
    if any(slot[crc_off + 4:crc_off + a]) or stored != crc32c(slot[:crc_off]):
        raise InvalidRecord("bad crc")
    return Record(gen, pv, flags, salt, slot[HEADER_SIZE:HEADER_SIZE + n])
