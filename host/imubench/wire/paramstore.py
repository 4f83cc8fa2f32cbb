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
    16       N     payload (the params block, protocol_gen.Params packed: 248 bytes in layout 3;
                   196 in layout 2, which is layout 3 without the bias polynomial's c2, c3 and
                   the spans; 160 in layout 1, layout 2 without gyro_g. The firmware reads a
                   layout-1 or -2 record with G = 0 (layout 1), c2 = c3 = 0 and the span
                   −40..85 °C (params.migrated_span); params_record(..., layout=1 or 2) writes one)
    16+N     P     zero padding up to crc_off = round_up(16 + N, a)
    crc_off  4     CRC-32C over bytes [0, crc_off)
    +4       a-4   zero padding (program_unit > 4 only)

tests/device/test_qemu.py checks these bytes against the C store (ib_ps_save / ib_ps_load).

    python -m imubench.wire.paramstore --layout qemu-f1 -o page.bin            # identity params
    python -m imubench.wire.paramstore --layout f4 --params cal.json -o page.bin
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, replace

import crcmod.predefined

from imubench.wire import params as PR
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
    # STM32F103CB image (pages 62-63 of its 128 KiB; the image also runs on a C8): 1 KiB pages
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


PARAMS_SIZE_V2 = 196                       # layout 2: layout 3 without c2, c3 (4 × 3 float32) and the spans (4 int8)
PARAMS_SIZE_V1 = PARAMS_SIZE_V2 - 36       # layout 1: layout 2 without gyro_g (9 float32 at its end)
assert Params.SIZE == PARAMS_SIZE_V2 + 52 and PARAM_BLOCK_VERSION == 3, "migration below knows layouts 1..3"


def _default_tail_ok(p: Params) -> bool:
    """True when p's layout-3 fields are those a migration gives a layout-2 block."""
    zero = not any(any(getattr(p, f)) for f in ("accel_bias_tc2_mps2_per_c2", "accel_bias_tc3_mps2_per_c3",
                                                  "gyro_bias_tc2_rad_s_per_c2", "gyro_bias_tc3_rad_s_per_c3"))
    return (zero and (p.accel_t_min_c, p.accel_t_max_c) == PR.migrated_span(p.accel_t_ref_c)
            and (p.gyro_t_min_c, p.gyro_t_max_c) == PR.migrated_span(p.gyro_t_ref_c))


def params_payload(p: Params, layout: int = PARAM_BLOCK_VERSION) -> bytes:
    """The parameter block (ib_params_pack): 248 bytes in layout 3; layout=2 or 1 gives the block
    a previous firmware stored (its first 196 or 160 bytes; what they lack must then be what
    the migration restores: c2 = c3 = 0, the default span, and for layout 1 G = 0)."""
    data = Params.STRUCT.pack(*p.values())
    if layout == PARAM_BLOCK_VERSION:
        return data
    if layout in (1, 2):
        if not _default_tail_ok(p):
            raise ValueError(f"a layout-{layout} block has no bias c2, c3 or span: they must be 0 and "
                             f"{PR.DEFAULT_SPAN_C[0]}..{PR.DEFAULT_SPAN_C[1]} °C")
        if layout == 1 and any(p.gyro_g_rad_s_per_mps2):
            raise ValueError("a layout-1 block has no gyro g-sensitivity: G must be zero")
        return data[:PARAMS_SIZE_V1 if layout == 1 else PARAMS_SIZE_V2]
    raise ValueError(f"parameter block layout {layout}: this host knows 1 to {PARAM_BLOCK_VERSION}")


def params_record(p: Params, *, generation: int = 1, program_unit: int = 4, layout: int = PARAM_BLOCK_VERSION) -> bytes:
    """A record holding p, in today's layout or (layout=1, 2) as a previous firmware stored it."""
    return build_record(params_payload(p, layout), generation=generation, payload_version=layout,
                        program_unit=program_unit)


def migrate(payload: bytes, layout: int) -> Params:
    """A stored block of layout 1, 2 or 3 as today's Params, migrated as the firmware does
    (core.c read_stored): G = 0 for layout 1, c2 = c3 = 0 and the span of params.migrated_span."""
    size = {1: PARAMS_SIZE_V1, 2: PARAMS_SIZE_V2, PARAM_BLOCK_VERSION: Params.SIZE}.get(layout)
    if size is None or len(payload) != size:
        raise ValueError(f"payload is {len(payload)} bytes of layout {layout}, a params block "
                         f"{Params.SIZE} (layout {PARAM_BLOCK_VERSION}), {PARAMS_SIZE_V2} (2) or {PARAMS_SIZE_V1} (1)")
    p = Params.from_values(Params.STRUCT.unpack(payload + bytes(Params.SIZE - size)))
    if layout < PARAM_BLOCK_VERSION:
        a, g = PR.migrated_span(p.accel_t_ref_c), PR.migrated_span(p.gyro_t_ref_c)
        p = replace(p, accel_t_min_c=a[0], accel_t_max_c=a[1], gyro_t_min_c=g[0], gyro_t_max_c=g[1])
    return p


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
        """The block, a layout-1 or -2 one migrated as the firmware does (migrate)."""
        return migrate(self.payload, self.payload_version if self.payload_version in (1, 2) else PARAM_BLOCK_VERSION)


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
