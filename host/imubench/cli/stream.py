"""`imubench decode`, `monitor` and `info`: a recorded stream, a live stream, a device's identity."""
from __future__ import annotations

import json
import math
import signal
import sys

import numpy as np

from imubench import units as U
from imubench.cli.common import (
    CommandError,
    add_port,
    existing_file,
    new_file,
    stream_rate,
)
from imubench.device.link import Device, DeviceError, LinkError, LinkTimeout
from imubench.files import MAX_CAPTURE_BYTES, atomic_output, read_bytes
from imubench.text import one_line
from imubench.wire.decoder import decode_bytes
from imubench.wire.ids import SENSOR_NAMES, board_name, byte_ids_text, part_names, parts_text, pid_text, sn_text, uid_text
from imubench.wire.protocol_gen import (
    Board,
    ClockSource,
    MsgType,
    ParamSource,
    StreamState,
)


def register(sub) -> None:
    p = sub.add_parser("decode", help="summary / export of a recorded byte stream",
                       description="Decode a recorded imubench byte stream (monitor --record, a session's "
                                   "capture-N.bin, allan's capture.bin): frame and sample counts, gaps, means; "
                                   "optionally export the samples in SI units.")
    p.add_argument("file", type=existing_file, metavar="FILE", help="the recorded stream")
    p.add_argument("--npz", type=new_file, metavar="OUT", help="write the samples to a .npz file")
    p.add_argument("--csv", type=new_file, metavar="OUT", help="write the samples to a CSV file (SI units)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as strict JSON (a number that is not finite is written as null)")
    p.set_defaults(run=run_decode)
    p = sub.add_parser("monitor", help="stream and show live values",
                       description="Stream from a device and print one line of means, noise and link counters "
                                   "per interval; --record appends every received byte to a file.")
    add_port(p)
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=1000, help="sample rate in Hz")
    p.add_argument("--range", type=int, default=0, choices=[0, 2, 4, 8], help="accelerometer range in g (0 = keep)")
    p.add_argument("--calibrated", action="store_true", help="stream the device's calibrated output")
    p.add_argument("--interval", type=float, default=1.0, help="seconds per printed line")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--record", type=new_file, metavar="FILE", help="append every received byte to this file")
    p.set_defaults(run=run_monitor)
    p = sub.add_parser("info", help="show device information",
                       description="Identity and state of a device: board, firmware, MCU UID, sensors and "
                                   "their IDs (hex, the format every imubench command accepts), parameters.")
    add_port(p)
    p.set_defaults(run=run_info)


def _axes(v: np.ndarray, fmt: str) -> str:
    return " ".join(fmt.format(x) for x in v)


def _enum_name(enum, value) -> str:
    try:
        return enum(value).name
    except ValueError:
        return f"unknown ({value})"


def _finite_or_null(x):
    if isinstance(x, dict):
        return {k: _finite_or_null(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_null(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def run_decode(a) -> int:
    data = read_bytes(a.file, MAX_CAPTURE_BYTES, "the capture")
    msgs, raw, cal, stats = decode_bytes(data)
    if data and not stats.frames_ok:
        raise CommandError(
            f"{a.file} is not an imubench capture: no valid frame in {len(data)} bytes "
            f"({stats.frames_rejected} pieces rejected)",
            "give a file written by `imubench monitor --record`, `calibrate` (DIR/capture-N.bin) or `allan`")
    kinds: dict[str, int] = {}
    for m in msgs:
        kinds[MsgType(m.type).name.lower()] = kinds.get(MsgType(m.type).name.lower(), 0) + 1
    summary = {"file": str(a.file), "bytes": len(data), "messages": kinds, "decoder": stats.as_dict()}
    for name, b in (("raw", raw), ("calibrated", cal)):
        if b is None or not len(b):
            continue
        acc, gyr = b.si()
        dur = (b.t_us[-1] - b.t_us[0]) / 1e6 if len(b) > 1 else 0.0
        summary[name] = {
            "samples": len(b), "duration_s": dur,
            "rate_hz": (len(b) - 1) / dur if dur > 0 else None,
            "accel_mean_mps2": acc.mean(axis=0).round(6).tolist(),
            "accel_std_mg": U.mps2_to_mg(acc.std(axis=0)).round(4).tolist(),
            "rate_mean_dps": U.rad_s_to_dps(gyr.mean(axis=0)).round(5).tolist(),
            "rate_std_dps": U.rad_s_to_dps(gyr.std(axis=0)).round(5).tolist(),
            "samples_flagged_bad": int(np.count_nonzero(b.status)),
        }
    if a.json:
        # strict JSON: a number that is not finite (an overflow of values the decoder let through)
        # is written as null, documented in --help, never a bare NaN that JSON readers refuse
        print(json.dumps(_finite_or_null(summary), allow_nan=False))
    else:
        print(f"{a.file}: {len(data)} bytes")
        st = stats
        print(f"  frames ok {st.frames_ok}, rejected {st.frames_rejected} "
              f"(crc {st.crc}, cobs {st.cobs}, oversize {st.oversize}, too short {st.too_short}, "
              f"bad version {st.bad_version}, unknown type {st.unknown_type}, bad length {st.bad_length})")
        print(f"  gaps: {st.seq_gaps} in frame sequence ({st.frames_missing} frames), "
              f"{st.sample_gaps} in samples ({st.samples_missing} samples)")
        if kinds:
            print("  messages: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
        for name in ("raw", "calibrated"):
            s = summary.get(name)
            if not s:
                continue
            rate = f"{s['rate_hz']:.1f} Hz" if s["rate_hz"] else "-"
            print(f"  {name} samples: {s['samples']} over {s['duration_s']:.3f} s ({rate}); "
                  f"flagged bad: {s['samples_flagged_bad']}")
            print(f"    accel mean [m/s²]  {_axes(s['accel_mean_mps2'], '{:+10.5f}')}   std [mg] {_axes(s['accel_std_mg'], '{:.4f}')}")
            print(f"    rate  mean [°/s]   {_axes(s['rate_mean_dps'], '{:+10.5f}')}   std [°/s] {_axes(s['rate_std_dps'], '{:.4f}')}")
    block = raw if raw is not None else cal
    if block is not None and (a.npz or a.csv):
        acc, gyr = block.si()
        cols = {"t_us": block.t_us, "sample_index": block.sample_index, "status": block.status,
                "accel_mps2": acc, "rate_rad_s": gyr,
                "accel_temp_c": U.accel_temp_counts_to_c(block.accel_temp_counts, range_g=block.accel_range_g),
                "gyro_temp_c": U.gyro_temp_counts_to_c(block.gyro_temp_counts)}
        if not block.calibrated:
            cols["accel_counts"] = block.accel_counts
            cols["gyro_counts"] = block.gyro_counts
        if a.npz:
            with atomic_output(a.npz, binary=True) as fh:
                np.savez_compressed(fh, **cols)
            print(f"  wrote {a.npz}")
        if a.csv:
            header = ("t_us,sample_index,status,ax_mps2,ay_mps2,az_mps2,wx_rad_s,wy_rad_s,wz_rad_s,"
                      "accel_temp_c,gyro_x_temp_c,gyro_y_temp_c,gyro_z_temp_c")
            table = np.column_stack([block.t_us, block.sample_index, block.status, acc, gyr,
                                     cols["accel_temp_c"], cols["gyro_temp_c"]])
            with atomic_output(a.csv, newline="") as fh:
                np.savetxt(fh, table, delimiter=",", header=header, comments="",
                           fmt=["%d", "%d", "%d"] + ["%.9g"] * 10)
            print(f"  wrote {a.csv}")
    return 0


def _print_info(info) -> None:
    uid = uid_text(info.mcu_uid)
    sensors = []
    for i, n in enumerate(SENSOR_NAMES):
        sensors.append(f"{n} {'ok' if info.sensors_present >> i & 1 else 'MISSING'}")
    print(f"device: board {board_name(info.board)}, firmware {'.'.join(map(str, info.fw_version))} "
          f"({one_line(info.fw_build)}), protocol {info.protocol_version}, MCU UID {uid}")
    print(f"  clock {_enum_name(ClockSource, info.clock_source)}, uptime {info.uptime_ms / 1000:.1f} s, "
          f"baud {info.baud or '-'}; " + ", ".join(sensors))
    print(f"  parts: {parts_text(part_names(info))}")
    print(f"  accelerometer IDs {byte_ids_text(info.accel_ids)}, range ±{info.accel_range_g} g; "
          f"gyro PID {' '.join(pid_text(x) for x in info.gyro_pid)} "
          f"SN {' '.join(sn_text(x) for x in info.gyro_sn)}")
    print(f"  parameters: {_enum_name(ParamSource, info.param_source)} (block v{info.param_block_version}, "
          f"generation {info.param_generation}); stream {_enum_name(StreamState, info.stream_state)}")


# the boards `imubench flash` writes -> their image in this imubench (imubench.device.artifacts)
_FLASHABLE = {Board.STM32F103: "f103", Board.STM32F4: "f4"}


def _firmware_note(info) -> str | None:
    """How the device's firmware compares with the image this imubench would flash onto it."""
    image = _FLASHABLE.get(info.board)
    if image is None:
        return None
    from imubench.device.artifacts import build_info
    try:
        ours = build_info()["images"].get(image)
    except Exception:  # noqa: BLE001 - a note, never a reason for info to fail
        return None
    if not ours:
        return None
    fw = ".".join(map(str, info.fw_version))
    if fw == ours["fw_version"] and info.fw_build == ours["fw_build"][:15]:
        return f"  firmware: the same as this imubench's {image} image"
    return (f"  firmware: this imubench's {image} image is {ours['fw_version']} ({ours['fw_build']}); "
            f"imubench flash --board {image} writes it")


def run_info(a) -> int:
    with Device.open(a.port, baudrate=a.baud) as dev:
        info = dev.info()
    _print_info(info)
    note = _firmware_note(info)
    if note:
        print(note)
    return 0


def run_monitor(a) -> int:
    capture = open(a.record, "ab", buffering=0) if a.record else None  # noqa: SIM115 - closed below
    stop = {"now": False}
    # Ctrl-C ends the view; the caller's handler is put back after (main() in-process, as tests
    # and embedding programs call it, kept a dead handler that swallowed every later Ctrl-C)
    old_sigint = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("now", True))
    try:
        with Device.open(a.port, baudrate=a.baud, capture=capture) as dev:
            _print_info(dev.info())
            batch = dev.start_stream(a.rate, calibrated=a.calibrated, accel_range_g=a.range)
            print(f"streaming {'calibrated' if a.calibrated else 'raw'} at {a.rate} Hz, {batch} samples/frame"
                  + (f", recording to {a.record}" if a.record else "") + "; Ctrl-C to stop")
            print(f"{'time':>7} {'rate':>7} | {'accel mean [g]':^29} | {'noise [mg]':^20} | "
                  f"{'gyro mean [°/s]':^26} | {'T[°C]':>5} | link")
            # device time: the link's clock (the wall clock for a real board, device time for a
            # lockstep virtual device), so --duration gives as many seconds of data on any machine
            clock = dev.link.clock
            t0 = clock.now()
            try:
                while not stop["now"] and (a.duration is None or clock.now() - t0 < a.duration - 1e-9):
                    b = dev.read(duration_s=a.interval if a.duration is None
                                 else min(a.interval, a.duration - (clock.now() - t0)))
                    acc, gyr = b.si()
                    span = (b.t_us[-1] - b.t_us[0]) / 1e6 if len(b) > 1 else 0
                    rate = (len(b) - 1) / span if span else 0
                    st = dev.link.decoder.stats
                    faults = f" faults {len(dev.link.fault_events)}" if dev.link.fault_events else ""
                    bad = int(np.count_nonzero(b.status))
                    print(f"{clock.now() - t0:7.1f} {rate:7.1f} | "
                          f"{_axes(U.mps2_to_mg(acc.mean(axis=0)) / 1000, '{:+9.5f}')} | "
                          f"{_axes(U.mps2_to_mg(acc.std(axis=0)), '{:6.3f}')} | "
                          f"{_axes(U.rad_s_to_dps(gyr.mean(axis=0)), '{:+8.3f}')} | "
                          f"{float(U.accel_temp_counts_to_c(b.accel_temp_counts[-1], range_g=b.accel_range_g[-1])):5.1f} | "
                          f"rej {st.frames_rejected} lost {st.samples_missing}"
                          + (f" bad-samples {bad}" if bad else "") + faults, flush=True)
            finally:
                try:
                    dev.stop_stream()
                except (LinkError, LinkTimeout, DeviceError) as e:
                    print(f"warning: could not stop the stream: {e}", file=sys.stderr)
            st = dev.link.decoder.stats
            print(f"done: {st.samples} samples, {st.frames_ok} frames, {st.frames_rejected} rejected, "
                  f"{st.samples_missing} samples lost")
    finally:
        if old_sigint is not None:          # None: a handler not set from Python, nothing to put back
            signal.signal(signal.SIGINT, old_sigint)
        if capture:
            capture.close()
    return 0
