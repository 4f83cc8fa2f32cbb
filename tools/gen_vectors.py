#!/usr/bin/env python3
"""Write protocol/vectors/vectors.json: encoded frames with their decoded content.

The vectors are golden data: once committed, both codecs (C and Python) are tested
against them, so a change to either that alters the wire format fails the tests. Run this
only when the protocol definition itself changes (and bump the protocol version if the
change is not backwards compatible, see protocol/SPEC.md).

Field values are chosen to be exact in float32 and to exercise sign bits, array order,
bit-field packing and COBS code bytes (payloads with zeros and with runs of > 254
non-zero bytes).
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "host"))

from imubench.wire import frame as P  # noqa: E402

OUT = ROOT / "protocol" / "vectors" / "vectors.json"


def f32(x: float) -> float:
    return float(np.float32(x))


def leaves(obj, prefix=""):
    """Flatten a message object into {path: value} like the C descriptor tables."""
    out = {}
    for name, val in vars(obj).items():
        if name == "records":
            continue
        path = prefix + name
        if hasattr(val, "values") and hasattr(val, "FORMAT"):
            out.update(leaves(val, path + "."))
        elif isinstance(val, str):
            out[path] = val
        elif isinstance(val, tuple):
            out[path] = [f32(v) if isinstance(v, float) else int(v) for v in val]
        else:
            out[path] = f32(val) if isinstance(val, float) else int(val)
    return out


def records_list(recs) -> list[dict]:
    out = []
    for r in recs:
        d = {}
        for name in recs.dtype.names:
            v = r[name]
            if np.ndim(v):
                d[name] = [f32(x) if recs.dtype[name].base.kind == "f" else int(x) for x in v]
            else:
                d[name] = f32(v) if recs.dtype[name].kind == "f" else int(v)
        out.append(d)
    return out


def good(name, msg, seq, ts, records=None):
    frame = P.encode(msg, seq, ts, records=records)
    parsed = P.parse_frame(frame[:-1])
    dec = P.decode_message(parsed.type, parsed.payload)
    v = {"name": name, "frame_hex": frame.hex(), "expect": "ok",
         "message": {"type": P.message_name(msg), "seq": seq, "timestamp_us": ts, "fields": leaves(dec)}}
    recs = getattr(dec, "records", None)
    if recs is not None:
        v["message"]["records"] = records_list(recs)
    return v


def bad(name, frame: bytes, reason: str, note: str):
    return {"name": name, "frame_hex": frame.hex(), "expect": reason, "note": note}


def params_example():
    G = gen = __import__("imubench.wire.protocol_gen", fromlist=["Params"])
    return G.Params(
        accel_m=tuple(f32(x) for x in (1.0125, -0.0043, 0.002, 0.0031, 0.9875, -0.0011, -0.0025, 0.0017, 1.003)),
        accel_b_mps2=(f32(0.196133), f32(-0.0980665), f32(0.0490333)),
        gyro_m=tuple(f32(x) for x in (0.98, 0.01, -0.005, -0.012, 1.02, 0.003, 0.0, 0.0, 1.0)),
        gyro_b_rad_s=(f32(0.0087), f32(-0.0052), f32(0.0)),
        accel_bias_tc_mps2_per_c=(f32(1e-4), f32(-2e-4), f32(0.0)),
        accel_scale_tc_per_c=(f32(5e-5), 0.0, f32(-5e-5)),
        gyro_bias_tc_rad_s_per_c=(f32(-1e-5), 0.0, f32(2e-5)),
        gyro_scale_tc_per_c=(0.0, f32(1e-4), 0.0),
        accel_t_ref_c=f32(25.0), gyro_t_ref_c=f32(31.5),
        cal_time_unix_s=1795000000, cal_id=0xDEADBEEF,
        accel_bias_tc2_mps2_per_c2=(f32(2e-6), 0.0, f32(-1e-6)), accel_bias_tc3_mps2_per_c3=(0.0, f32(3e-8), 0.0),
        gyro_bias_tc2_rad_s_per_c2=(0.0, f32(-4e-7), 0.0), gyro_bias_tc3_rad_s_per_c3=(f32(1e-9), 0.0, 0.0),
        accel_t_min_c=-5, accel_t_max_c=60, gyro_t_min_c=0, gyro_t_max_c=55,
    ), gen


def main() -> int:
    params, G = params_example()
    V = []
    V.append(good("ping", G.Ping(nonce=0x12345678), 7, 99))
    V.append(good("get_info", G.GetInfo(), 1, 0))
    V.append(good("start_stream_4k_raw", G.StartStream(rate_hz=4000, mode=0, batch=16, accel_range_g=2), 0xFFFF, 0xFFFFFFFF))
    V.append(good("start_stream_1k_cal", G.StartStream(rate_hz=1000, mode=1, batch=0, accel_range_g=0), 300, 5))
    V.append(good("stop_stream", G.StopStream(), 2, 0))
    V.append(good("set_params", G.SetParams(params=params), 41, 0))
    V.append(good("get_params_stored", G.GetParams(which=1), 42, 0))
    V.append(good("save_params", G.SaveParams(), 43, 0))
    V.append(good("clear_params", G.ClearParams(), 44, 0))
    V.append(good("reboot", G.Reboot(), 45, 0))
    V.append(good("self_test", G.SelfTest(), 46, 0))
    V.append(good("get_stats_reset", G.GetStats(reset=1), 47, 0))
    V.append(good("ack_ok", G.Ack(request_id=41, command=0x05, error=0, value=0), 100, 123456))
    V.append(good("ack_nack_ill_conditioned", G.Ack(request_id=42, command=0x05, error=7, value=3), 101, 123500))
    V.append(good("info", G.Info(
        request_id=0, protocol_version=P.PROTOCOL_VERSION, board=2, fw_version=(0, 3, 12), clock_source=2,
        fw_build="v0.3.12-4-gabcdef0", mcu_uid=tuple(range(0x30, 0x3C)), sensors_present=0b1101,
        accel_range_g=4, parts=(1, 3, 4, 0), accel_ids=(0xAD, 0x1D, 0xED, 0x01), gyro_pid=(0x5201, 0x5202, 0),
        gyro_sn=(0x12345678, 0x9ABCDEF0, 0), stream_state=1, param_source=1, stream_rate_hz=4000,
        max_rate_hz=4000, param_block_version=1, param_generation=17, baud=2000000, uptime_ms=3600000),
        102, 4000000000))
    V.append(good("params_readback", G.ParamsReadback(request_id=42, which=1, source=1, generation=17, params=params), 103, 7))
    V.append(good("stats", G.Stats(request_id=0, frames_sent=1000000, frames_dropped=3, samples_produced=16000000,
                                   samples_dropped=48, spi_errors=2, sensor_faults=5, bad_commands=1,
                                   rx_frame_errors=4, uptime_ms=4000000), 104, 8))
    V.append(good("fault_event_gyro_q", G.FaultEvent(sensor=2, kind=2, active=1, detail=0x40), 105, 9))
    V.append(good("self_test_result", G.SelfTestResult(request_id=46, passed=0b0111, tested=0b1111,
                                                       accel_delta_counts=(76800, 77000, -384000),
                                                       gyro_chk_faults=(0xFE, 0xFE, 0x00)), 106, 10))
    n = 16
    raw_recs = {
        "accel_x_counts": np.array([0, 1, -1, 256000, -256000, 524287, -524288, 128000] * 2),
        "accel_y_counts": np.arange(n) * 32768 - 262144,
        "accel_z_counts": np.array([256000 + k for k in range(n)]),
        "status": np.arange(n) % 16,
        "gyro_counts": np.stack([np.arange(n) * 80 - 640, -np.arange(n) * 8, np.full(n, 32767) - np.arange(n) * 4096], axis=1),
    }
    hdr = G.BatchHeader(sample_index=123456, period_us=250, count=n, sensor_flags=0b0100000,
                        accel_temp_counts=1885, accel_status=0x01, accel_range_g=2,
                        gyro_temp_counts=(-45, 0, 511), gyro_faults=(0, 0x41, 0))
    V.append(good("raw_batch_16", G.RawBatch(header=hdr), 200, 30864000, records=raw_recs))
    hdr1 = G.BatchHeader(sample_index=0, period_us=1000, count=1, accel_range_g=8)
    V.append(good("raw_batch_1", G.RawBatch(header=hdr1), 201, 0, records={k: v[:1] for k, v in raw_recs.items()}))
    cal_recs = {
        "accel_mps2": np.array([[f32(0.01 * k), f32(-9.80665), f32(9.80665 + k)] for k in range(8)], dtype=np.float32),
        "rate_rad_s": np.array([[f32(0.5 * k), f32(-1e-3), f32(3.14159)] for k in range(8)], dtype=np.float32),
        "status": np.array([0, 1, 2, 4, 8, 15, 0, 0]),
    }
    hdr8 = G.BatchHeader(sample_index=800, period_us=1000, count=8, accel_temp_counts=1850, accel_range_g=2,
                         gyro_temp_counts=(10, 12, 14))
    V.append(good("cal_batch_8", G.CalBatch(header=hdr8), 203, 800000, records=cal_recs))

    # ---------------------------------------------------------------- bad frames
    ping = P.encode(G.Ping(nonce=0x12345678), 7, 99)
    raw = bytearray(P.HEADER.pack(P.PROTOCOL_VERSION, 0x01, 7, 99) + (0x12345678).to_bytes(4, "little"))
    crc_ok = P.crc32c(bytes(raw))

    def frame_of(raw_bytes: bytes, crc: int | None = None) -> bytes:
        c = P.crc32c(raw_bytes) if crc is None else crc
        from cobs import cobs
        return cobs.encode(raw_bytes + c.to_bytes(4, "little")) + b"\0"

    V.append(bad("crc_wrong", frame_of(bytes(raw), crc_ok ^ 0x00010000), "crc", "ping with one CRC bit flipped"))
    flipped = bytearray(raw)
    flipped[9] ^= 0x80
    V.append(bad("payload_bit_flipped", frame_of(bytes(flipped), crc_ok), "crc", "payload bit flipped, old CRC"))
    V.append(bad("truncated", ping[:-4] + b"\0", "cobs", "last 3 encoded bytes lost: the last COBS code overruns"))
    batch = P.encode(G.RawBatch(header=hdr), 9, 0, records=raw_recs)
    for cut in range(100, len(batch) - 1):   # first lost byte that leaves valid COBS
        try:
            P.parse_frame(batch[:cut] + batch[cut + 1:-1])
        except P.ProtocolError as e:
            if e.reason is P.FrameError.CRC:
                break
    V.append(bad("byte_dropped_mid_batch", batch[:cut] + batch[cut + 1:], "crc",
                 f"byte {cut} lost: still valid COBS, the CRC catches it"))
    V.append(bad("too_short", frame_of(b"\x01\x01\x07"), "too_short", "3 bytes + CRC: shorter than header + CRC"))
    V.append(bad("empty_after_cobs", b"\x01\0", "too_short", "a lone COBS code byte decodes to nothing"))
    V.append(bad("cobs_code_overruns", b"\x09\x01\x02\0", "cobs", "COBS code byte points past the end"))
    V.append(bad("unknown_type", frame_of(P.HEADER.pack(P.PROTOCOL_VERSION, 0x7E, 1, 0) + b"\x00\x00\x00\x00"), "unknown_type", "type 0x7E is not defined"))
    V.append(bad("wrong_version", frame_of(P.HEADER.pack(P.PROTOCOL_VERSION + 1, 0x01, 1, 0) + b"\x00\x00\x00\x00"),
                 "bad_version", f"version {P.PROTOCOL_VERSION + 1}"))
    V.append(bad("bad_length_ping", frame_of(P.HEADER.pack(P.PROTOCOL_VERSION, 0x01, 1, 0) + b"\x01\x02\x03"), "bad_length", "ping with a 3-byte payload"))
    b16 = bytearray(P.parse_frame(P.encode(G.RawBatch(header=hdr), 1, 0, records=raw_recs)[:-1]).payload)
    b16[6] = 15
    V.append(bad("batch_count_mismatch", frame_of(P.HEADER.pack(P.PROTOCOL_VERSION, 0x90, 1, 0) + bytes(b16)), "bad_length", "count says 15, 16 records follow"))
    over = P.HEADER.pack(P.PROTOCOL_VERSION, 0x90, 1, 0) + bytes([0x55]) * (P.MAX_PAYLOAD + 1)
    V.append(bad("payload_over_max", frame_of(over), "oversize", "payload of MAX_PAYLOAD+1 bytes: encoded length above MAX_ENCODED"))
    zeros = P.HEADER.pack(P.PROTOCOL_VERSION, 0x90, 1, 0) + bytes(P.MAX_PAYLOAD + 1)
    V.append(bad("decoded_over_max", frame_of(zeros), "oversize", "encoded length within MAX_ENCODED, decoded frame one byte over MAX_FRAME"))
    V.append(bad("oversize_garbage", bytes([0x11]) * (P.MAX_ENCODED + 1) + b"\0", "oversize", "no delimiter for MAX_ENCODED+1 bytes"))

    # ------------------------------------------- well-formed frames whose fields break their rules
    def payload_frame(msg, seq, records=None) -> bytes:
        d = P.MESSAGES_BY_NAME[P.message_name(msg)]
        return frame_of(P.HEADER.pack(P.PROTOCOL_VERSION, d.id, seq, 0) + P.encode_message(msg, records))

    one_raw = {k: v[:1] for k, v in raw_recs.items()}
    V.append(bad("batch_range_undefined", payload_frame(G.RawBatch(header=replace(hdr1, accel_range_g=7)), 210, one_raw),
                 "bad_enum", "accel_range_g 7: only a full scale of a part of protocol/parts.toml (never scaled with a guessed range)"))
    V.append(bad("batch_period_zero", payload_frame(G.RawBatch(header=replace(hdr1, period_us=0)), 211, one_raw),
                 "out_of_range", "period_us 0: the sample period must be at least 1 us"))
    V.append(bad("batch_flags_undefined_bit", payload_frame(G.RawBatch(header=replace(hdr1, sensor_flags=0x80)), 212, one_raw),
                 "bad_flags", "sensor_flags bit 7 is not a batch_flags bit"))
    V.append(bad("batch_period_zero_and_range_undefined",
                 payload_frame(G.RawBatch(header=replace(hdr1, period_us=0, accel_range_g=7)), 213, one_raw),
                 "out_of_range", "two broken fields: the first in layout order (period_us) is reported"))
    nan_recs = {k: np.array(v[:2]) for k, v in cal_recs.items()}
    nan_recs["rate_rad_s"][1, 2] = np.float32("nan")
    hdr2 = replace(hdr8, count=2)
    V.append(bad("cal_sample_nan", payload_frame(G.CalBatch(header=hdr2), 214, nan_recs),
                 "not_finite", "second sample's rate z is NaN"))
    inf_recs = {k: np.array(v[:2]) for k, v in cal_recs.items()}
    inf_recs["accel_mps2"][0, 0] = np.float32("inf")
    V.append(bad("cal_sample_inf", payload_frame(G.CalBatch(header=hdr2), 215, inf_recs),
                 "not_finite", "first sample's accel x is +Inf"))
    st_recs = {k: np.array(v[:2]) for k, v in cal_recs.items()}
    st_recs["status"][1] = 0x10
    V.append(bad("cal_status_undefined_bit", payload_frame(G.CalBatch(header=hdr2), 216, st_recs),
                 "bad_flags", "second sample's status has bit 4, not a sample_status bit"))
    V.append(bad("start_stream_mode_undefined", payload_frame(G.StartStream(rate_hz=1000, mode=2, batch=0), 217),
                 "bad_enum", "stream mode 2 is not defined (the device nacks it BAD_ARGUMENT)"))
    V.append(bad("fault_event_kind_undefined", payload_frame(G.FaultEvent(sensor=1, kind=0, active=1), 218),
                 "bad_enum", "fault kind 0 is not defined"))

    # values no definition allows (issue 25): refused, never delivered
    V.append(bad("raw_batch_empty", payload_frame(G.RawBatch(header=G.BatchHeader(sample_index=5, period_us=1000, count=0,
                                                                                  accel_range_g=2)), 202, {}),
                 "out_of_range", "count 0: an empty batch carries nothing and is never sent"))
    V.append(bad("ack_error_undefined", payload_frame(G.Ack(request_id=41, command=0x05, error=200, value=0), 219),
                 "bad_enum", "error 200 is not an error code (codes come only with a protocol version)"))
    V.append(bad("self_test_bit_for_no_sensor", payload_frame(G.SelfTestResult(request_id=46, passed=0b10001, tested=0b1111), 220),
                 "bad_flags", "passed bit 4: there is no sensor 4"))
    V.append(bad("info_sensor_bit_for_no_sensor", payload_frame(G.Info(
        request_id=0, protocol_version=P.PROTOCOL_VERSION, board=2, clock_source=2, sensors_present=0x80,
        accel_range_g=4, stream_state=0, param_source=0), 221),
                 "bad_flags", "sensors_present bit 7: there is no sensor 7"))
    V.append(bad("info_clock_source_undefined", payload_frame(G.Info(
        request_id=0, protocol_version=P.PROTOCOL_VERSION, board=2, clock_source=9, sensors_present=0b1111,
        accel_range_g=4, stream_state=0, param_source=0), 222),
                 "bad_enum", "clock_source 9: not defined here (a newer firmware's; the host says so)"))
    V.append(bad("batch_reserved_nonzero", payload_frame(G.RawBatch(header=replace(hdr1, reserved2=1)), 223, one_raw),
                 "out_of_range", "reserved2 1: reserved fields are 0"))
    V.append(bad("start_stream_reserved_nonzero",
                 payload_frame(G.StartStream(rate_hz=1000, mode=0, batch=0, reserved=(0, 0, 4)), 224),
                 "out_of_range", "reserved byte 2 is 4 (the device nacks it BAD_ARGUMENT)"))
    V.append(bad("stats_reserved_nonzero", payload_frame(G.Stats(request_id=0, reserved=1), 225),
                 "out_of_range", "stats reserved 1"))
    V.append(bad("fault_event_reserved_nonzero", payload_frame(G.FaultEvent(sensor=1, kind=2, active=1, reserved=0x80), 226),
                 "out_of_range", "fault_event reserved 0x80"))

    OUT.parent.mkdir(parents=True, exist_ok=True)
    # the signed step between two u32 device times (SPEC.md, Header fields): both sides agree
    H = 1 << 31
    steps = [(0, 0), (1, 0), (0, 1), (H - 1, 0), (H, 0), (H + 1, 0), (0, H), (0xFFFFFFFF, 0), (0, 0xFFFFFFFF),
             (0x7FFF0000, 0xFFFF0000), (0xFFFF0000, 0x7FFF0000), (0x7FFF0001, 0xFFFF0000), (5, 0xFFFFFFF0)]
    time_steps = [{"now": now, "prev": prev, "step_us": ((now - prev + H) & 0xFFFFFFFF) - H} for now, prev in steps]
    doc = {
        "protocol_version": P.PROTOCOL_VERSION,
        "about": "Shared test vectors. frame_hex includes the 0x00 delimiter. expect is 'ok' or the "
                 "rejection reason (protocol/SPEC.md, Receiving). Fields are flattened by path.",
        "vectors": V,
        "time_steps": time_steps,
    }
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {OUT.relative_to(ROOT)}: {len(V)} vectors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
