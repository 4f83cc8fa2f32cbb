"""Framing and message codec of the imubench wire protocol (protocol/SPEC.md).

A frame on the wire is COBS(header + payload + CRC-32C) followed by one 0x00 byte:

    header   version u8 | type u8 | seq u16 | timestamp_us u32     (little-endian)
    payload  the message's fields (layouts in protocol_gen, generated from the definition)
    crc      CRC-32C over header + payload, u32 little-endian

Functions here work on one frame at a time; imubench.wire.decoder does streams.
"""
from __future__ import annotations

import enum
import struct
from collections.abc import Callable
from dataclasses import dataclass

import crcmod.predefined
import numpy as np
from cobs import cobs

from imubench.wire import protocol_gen as gen
from imubench.wire.protocol_gen import (  # noqa: F401  (re-exported: the public names of the protocol)
    CRC_SIZE,
    HEADER_SIZE,
    MAX_ENCODED,
    MAX_FRAME,
    MAX_PAYLOAD,
    MESSAGES,
    MESSAGES_BY_NAME,
    PROTOCOL_VERSION,
    BatchFlags,
    Board,
    ClockSource,
    Error,
    FaultKind,
    MsgType,
    Params,
    ParamSource,
    ParamsWhich,
    SampleStatus,
    Sensor,
    StreamMode,
    StreamState,
)

crc32c = crcmod.predefined.mkCrcFun(gen.CRC_NAME)
HEADER = struct.Struct("<BBHI")
CRC = struct.Struct("<I")


class FrameError(enum.Enum):
    """Why a frame was rejected. Checked in this order (protocol/SPEC.md, "Receiving")."""

    OVERSIZE = "oversize"          # encoded frame longer than MAX_ENCODED, or decoded than MAX_FRAME
    COBS = "cobs"                  # not valid COBS
    TOO_SHORT = "too_short"        # shorter than header + CRC
    CRC = "crc"                    # CRC-32C mismatch
    BAD_VERSION = "bad_version"    # header version is not PROTOCOL_VERSION
    UNKNOWN_TYPE = "unknown_type"  # message type not in the definition
    BAD_LENGTH = "bad_length"      # payload length (or record count) wrong for the type
    # a well-formed frame whose fields hold what the definition does not allow (the rules of
    # protocol/imubench.toml, generated into protocol_gen.VALUE_RULES / RECORD_RULES)
    BAD_ENUM = "bad_enum"          # not one of its enum's values (or of the field's listed values)
    OUT_OF_RANGE = "out_of_range"  # below its min or above its max (a sample period of 0)
    NOT_FINITE = "not_finite"      # a float that must be finite is NaN or infinite
    BAD_FLAGS = "bad_flags"        # a bit outside the field's bit set


VALUE_ERRORS = {kind: FrameError(reason) for kind, reason in gen.VALUE_REASONS.items()}


def _rule_fails(kind: str, arg, v) -> bool:
    if kind == "enum":
        return v not in arg
    if kind == "min":
        return v < arg
    if kind == "max":
        return v > arg
    if kind == "finite":
        return v != v or v in (float("inf"), float("-inf"))
    return bool(v & ~arg)


def _compile_rules(rules) -> Callable[[tuple], bool]:
    """One function that says whether every rule of a message's fixed part holds for its
    unpacked values: the rules as a single expression (a call per value of _rule_fails costs
    more than the rest of decoding a one-sample batch). The same tests as _rule_fails,
    negated, NaN included (a NaN passes min and max there, and here)."""
    ns: dict = {"INF": float("inf")}
    terms = []
    for j, (slot, n, _path, kind, arg) in enumerate(rules):
        ns[f"a{j}"] = arg
        for k in range(slot, slot + n):
            v = f"v[{k}]"
            terms.append({"enum": f"{v} in a{j}", "min": f"not {v} < a{j}", "max": f"not {v} > a{j}",
                          "finite": f"-INF < {v} < INF"}.get(kind, f"not {v} & ~a{j}"))
    return eval(f"lambda v: {' and '.join(terms) or 'True'}", ns)      # noqa: S307 (our own rules)


#: msg_type -> compiled check of its VALUE_RULES (value_error's fast path)
VALUE_OK = {mtype: _compile_rules(rules) for mtype, rules in gen.VALUE_RULES.items()}


def value_error(msg_type: int, payload: bytes | memoryview, values: tuple | None = None) -> FrameError | None:
    """What the fields of a length-checked payload hold, against the definition's rules: None,
    or the reason of the first field that breaks its rule (fixed part in layout order, then
    each record in turn). `values`: the fixed part already unpacked with the message's STRUCT."""
    d = MESSAGES[msg_type]
    rules = gen.VALUE_RULES.get(msg_type)
    if rules:
        if values is None:
            values = d.cls.STRUCT.unpack_from(payload, 0)
        if VALUE_OK[msg_type](values):
            rules = ()                     # all hold: no need to look for the first that fails
        for slot, n, _path, kind, arg in rules:
            for v in values[slot:slot + n]:
                if _rule_fails(kind, arg, v):
                    return VALUE_ERRORS[kind]
    rec_rules = gen.RECORD_RULES.get(d.record) if d.record is not None else None
    if rec_rules and len(payload) > d.cls.SIZE:
        return record_value_error(d, payload[d.cls.SIZE:], rec_rules)
    return None


def value_problem(msg_type: int, payload: bytes | memoryview, values: tuple | None = None):
    """(field path, value, rule kind, rule argument) of the first field of the fixed part that
    breaks its rule, or None: what value_error found, named (a newer firmware's info: "unknown
    value N for FIELD")."""
    rules = gen.VALUE_RULES.get(msg_type)
    if not rules:
        return None
    if values is None:
        values = MESSAGES[msg_type].cls.STRUCT.unpack_from(payload, 0)
    for slot, n, path, kind, arg in rules:
        for i, v in enumerate(values[slot:slot + n]):
            if _rule_fails(kind, arg, v):
                return (f"{path}[{i}]" if n > 1 else path), v, kind, arg
    return None


def record_value_error(d, data: bytes | memoryview, rules=None) -> FrameError | None:
    """Vectorised rules of concatenated records: the reason of the first failing field of the
    first failing record, or None."""
    rules = gen.RECORD_RULES.get(d.record, ()) if rules is None else rules
    if not rules or not len(data):
        return None
    f = unpack_record_fields(d, data)
    bad = np.empty((len(data) // d.record_dtype.itemsize, len(rules)), dtype=bool)
    for k, (name, kind, arg) in enumerate(rules):
        v = f[name]
        if kind == "enum":
            b = ~np.isin(v, list(arg))
        elif kind == "min":
            b = v < arg
        elif kind == "max":
            b = v > arg
        elif kind == "finite":
            b = ~np.isfinite(v)
        else:
            b = (v.astype(np.int64) & ~arg) != 0
        bad[:, k] = b.reshape(len(bad), -1).any(axis=1)
    if not bad.any():
        return None
    return VALUE_ERRORS[rules[int(np.argmax(bad.ravel())) % len(rules)][1]]


class ProtocolError(ValueError):
    def __init__(self, reason: FrameError, detail: str = ""):
        super().__init__(f"{reason.value}: {detail}" if detail else reason.value)
        self.reason = reason


@dataclass
class Frame:
    """A checked frame: header fields and the raw payload bytes."""

    type: int
    seq: int
    timestamp_us: int
    payload: bytes
    version: int = PROTOCOL_VERSION


def build_frame(msg_type: int, payload: bytes, seq: int, timestamp_us: int = 0,
                version: int = PROTOCOL_VERSION) -> bytes:
    """Encode one frame, delimiter included."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds MAX_PAYLOAD={MAX_PAYLOAD}")
    raw = HEADER.pack(version, msg_type, seq & 0xFFFF, timestamp_us & 0xFFFFFFFF) + payload
    raw += CRC.pack(crc32c(raw))
    return cobs.encode(raw) + b"\0"


def payload_error(msg_type: int, payload: bytes | memoryview) -> FrameError | None:
    """Length check of a payload against the definition (None when valid)."""
    d = MESSAGES.get(msg_type)
    if d is None:
        return FrameError.UNKNOWN_TYPE
    fixed = d.cls.SIZE
    n = len(payload)
    if d.record is None:
        return None if n == fixed else FrameError.BAD_LENGTH
    rsize = d.record_dtype.itemsize
    if n < fixed or (n - fixed) % rsize:
        return FrameError.BAD_LENGTH
    count = (n - fixed) // rsize
    if count > d.max_records or payload[d.count_offset] != count:
        return FrameError.BAD_LENGTH
    return None


def parse_frame(encoded: bytes | memoryview) -> Frame:
    """Check and split one encoded frame (without its 0x00 delimiter).
    Raises ProtocolError with the first reason in FrameError order."""
    if len(encoded) > MAX_ENCODED:
        raise ProtocolError(FrameError.OVERSIZE, f"{len(encoded)} bytes")
    try:
        raw = cobs.decode(encoded)
    except cobs.DecodeError as e:
        raise ProtocolError(FrameError.COBS, str(e)) from None
    if len(raw) > MAX_FRAME:
        raise ProtocolError(FrameError.OVERSIZE, f"{len(raw)} bytes decoded")
    if len(raw) < HEADER_SIZE + CRC_SIZE:
        raise ProtocolError(FrameError.TOO_SHORT, f"{len(raw)} bytes")
    if crc32c(raw[:-CRC_SIZE]) != CRC.unpack_from(raw, len(raw) - CRC_SIZE)[0]:
        raise ProtocolError(FrameError.CRC)
    version, msg_type, seq, ts = HEADER.unpack_from(raw)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(FrameError.BAD_VERSION, f"version {version}")
    payload = raw[HEADER_SIZE:-CRC_SIZE]
    err = payload_error(msg_type, payload)
    if err is not None:
        raise ProtocolError(err, f"type 0x{msg_type:02X}, {len(payload)} bytes")
    err = value_error(msg_type, payload)
    if err is not None:
        raise ProtocolError(err, f"type 0x{msg_type:02X}")
    return Frame(msg_type, seq, ts, bytes(payload), version)


# ------------------------------------------------------------------ messages
def encode_message(msg, records=None) -> bytes:
    """Payload bytes of a message object (a protocol_gen dataclass). For batch messages,
    `records` (or msg.records) is a numpy structured array or a dict of per-field arrays
    with the record's leaf fields (e.g. accel_x_counts ... status, gyro_counts)."""
    d = MESSAGES_BY_NAME[message_name(msg)]
    out = msg.STRUCT.pack(*msg.values())
    if d.record is not None:
        recs = records if records is not None else msg.records
        rec_bytes = pack_records(d, recs if recs is not None else {})
        count = len(rec_bytes) // d.record_dtype.itemsize
        if out[d.count_offset] != count:
            raise ValueError(f"{d.count_path} is {out[d.count_offset]} but {count} records were given")
        out += rec_bytes
    return out


def decode_message(msg_type: int, payload: bytes):
    """Message object from a checked payload; batch records become a numpy structured
    array of leaf fields on `.records`."""
    d = MESSAGES[msg_type]
    msg = d.cls.from_values(d.cls.STRUCT.unpack_from(payload, 0))
    if d.record is not None:
        msg.records = unpack_records(d, payload[d.cls.SIZE:])
    return msg


def message_name(msg) -> str:
    for d in MESSAGES.values():
        if type(msg) is d.cls:
            return d.name
    raise TypeError(f"{type(msg).__name__} is not a protocol message")


def encode(msg, seq: int, timestamp_us: int = 0, records=None) -> bytes:
    """A whole frame for a message object."""
    d = MESSAGES_BY_NAME[message_name(msg)]
    return build_frame(d.id, encode_message(msg, records), seq, timestamp_us)


def record_leaf_dtype(d) -> np.dtype:
    """dtype of decoded records: bit-field words expanded into their fields."""
    fields = []
    bit_words = {w for w, *_ in d.record_bits}
    for name in d.record_dtype.names:
        if name in bit_words:
            for w, bname, lsb, width, signed in d.record_bits:
                if w == name:
                    fields.append((bname, np.int32 if signed else (np.uint8 if width <= 8 else np.uint32)))
        else:
            base, shape = d.record_dtype.fields[name][0].base, d.record_dtype.fields[name][0].shape
            fields.append((name, base, shape) if shape else (name, base))
    return np.dtype(fields)


def unpack_record_fields(d, data: bytes | memoryview) -> dict[str, np.ndarray]:
    """Vectorised decode of concatenated records (any count): one array per leaf field,
    bit fields extracted and sign-extended."""
    wire = np.frombuffer(data, dtype=d.record_dtype)
    out: dict[str, np.ndarray] = {}
    bit_words = {w for w, *_ in d.record_bits}
    for name in d.record_dtype.names:
        if name not in bit_words:
            out[name] = wire[name]
    words = {w: np.ascontiguousarray(wire[w]) for w in bit_words}
    for word, name, lsb, width, signed in d.record_bits:
        w = words[word]
        if signed:
            # move the field to the top of an int64, then arithmetic-shift it back down
            out[name] = ((w << np.uint64(64 - lsb - width)).view(np.int64) >> np.int64(64 - width)).astype(np.int32)
        else:
            out[name] = ((w >> np.uint64(lsb)) & np.uint64((1 << width) - 1)).astype(
                np.uint8 if width <= 8 else np.uint32)
    return out


def unpack_records(d, data: bytes | memoryview) -> np.ndarray:
    """Records as one numpy structured array of leaf fields (see record_leaf_dtype)."""
    fields = unpack_record_fields(d, data)
    n = len(data) // d.record_dtype.itemsize
    out = np.empty(n, dtype=record_leaf_dtype(d))
    for name in out.dtype.names:
        out[name] = fields[name]
    return out


def pack_records(d, recs) -> bytes:
    """Inverse of unpack_records; `recs` is a structured array or a dict of arrays."""
    if isinstance(recs, np.ndarray):
        n = len(recs)
        get = lambda k: recs[k]  # noqa: E731
    else:
        if not recs:
            return b""
        n = max(len(np.atleast_1d(v)) for v in recs.values())
        get = lambda k: np.asarray(recs[k])  # noqa: E731
    wire = np.zeros(n, dtype=d.record_dtype)
    bit_words = {w for w, *_ in d.record_bits}
    for name in d.record_dtype.names:
        if name not in bit_words:
            wire[name] = get(name)
    for word, name, lsb, width, signed in d.record_bits:
        v = np.asarray(get(name)).astype(np.int64) & ((1 << width) - 1)
        wire[word] |= v.astype(np.uint64) << np.uint64(lsb)
    return wire.tobytes()
