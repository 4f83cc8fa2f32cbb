"""The `imubench` command line.

    imubench decode FILE [--npz OUT] [--csv OUT] [--json]   decode a recorded byte stream
    imubench monitor [--port URL] [--rate HZ] [--calibrated] [--duration S] [--record FILE]
    imubench info [--port URL]                               device information
    imubench sim [--speed X] [--seed N] [--truth default|random] [--pty]   the virtual device
    imubench qemu --board f103|f4 [--params FILE]            the ARM image under QEMU
    imubench flash --board f103|f4 [--probe openocd|stlink|serial] [--port DEV] [--dry-run]
    imubench calibrate / history / allan / attitude / thermal / report   see README.md
    imubench fake [--speed X]                                run the Python fake device on a pty

--port takes any pyserial URL (/dev/ttyUSB0, socket://HOST:PORT, rfc2217://..., spy://...)
and defaults to the environment variable IMUBENCH_PORT.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.wire.decoder import decode_bytes
from imubench.device.link import DEFAULT_BAUD, PORT_ENV, Device, DeviceError, LinkError, LinkTimeout
from imubench.wire.protocol_gen import Board, ClockSource, MsgType, ParamSource, StreamState


def _port_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", help=f"pyserial URL of the device (default: ${PORT_ENV})")
    p.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"baud rate for a real UART (default {DEFAULT_BAUD})")


def _axes(v: np.ndarray, fmt: str) -> str:
    return " ".join(fmt.format(x) for x in v)


# ------------------------------------------------------------------- decode
def cmd_decode(a) -> int:
    data = Path(a.file).read_bytes()
    msgs, raw, cal, stats = decode_bytes(data)
    kinds: dict[str, int] = {}
    for m in msgs:
        kinds[MsgType(m.type).name.lower()] = kinds.get(MsgType(m.type).name.lower(), 0) + 1
    summary = {"file": a.file, "bytes": len(data), "messages": kinds, "decoder": stats.as_dict()}
    for name, b in (("raw", raw), ("calibrated", cal)):
        if b is None:
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
        print(json.dumps(summary))
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
                "accel_temp_c": U.accel_temp_counts_to_c(block.accel_temp_counts),
                "gyro_temp_c": U.gyro_temp_counts_to_c(block.gyro_temp_counts)}
        if not block.calibrated:
            cols["accel_counts"] = block.accel_counts
            cols["gyro_counts"] = block.gyro_counts
        if a.npz:
            np.savez_compressed(a.npz, **cols)
            print(f"  wrote {a.npz}")
        if a.csv:
            header = ("t_us,sample_index,status,ax_mps2,ay_mps2,az_mps2,wx_rad_s,wy_rad_s,wz_rad_s,"
                      "accel_temp_c,gyro_x_temp_c,gyro_y_temp_c,gyro_z_temp_c")
            table = np.column_stack([block.t_us, block.sample_index, block.status, acc, gyr,
                                     cols["accel_temp_c"], cols["gyro_temp_c"]])
            np.savetxt(a.csv, table, delimiter=",", header=header, comments="",
                       fmt=["%d", "%d", "%d"] + ["%.9g"] * 10)
            print(f"  wrote {a.csv}")
    return 0 if stats.frames_ok or not data else 1


# ------------------------------------------------------------------ monitor
def _print_info(info) -> None:
    uid = bytes(info.mcu_uid).hex()
    sensors = []
    names = ["ADXL355", "gyro X", "gyro Y", "gyro Z"]
    for i, n in enumerate(names):
        sensors.append(f"{n} {'ok' if info.sensors_present >> i & 1 else 'MISSING'}")
    print(f"device: board {Board(info.board).name}, firmware {'.'.join(map(str, info.fw_version))} "
          f"({info.fw_build}), protocol {info.protocol_version}, MCU UID {uid}")
    print(f"  clock {ClockSource(info.clock_source).name}, uptime {info.uptime_ms / 1000:.1f} s, "
          f"baud {info.baud or '-'}; " + ", ".join(sensors))
    print(f"  ADXL355 IDs {' '.join(f'{x:02X}' for x in info.accel_ids)}, range ±{info.accel_range_g} g; "
          f"ADXRS450 PID {' '.join(f'{x:04X}' for x in info.gyro_pid)} "
          f"SN {' '.join(f'{x:08X}' for x in info.gyro_sn)}")
    print(f"  parameters: {ParamSource(info.param_source).name} (block v{info.param_block_version}, "
          f"generation {info.param_generation}); stream {StreamState(info.stream_state).name}")


def cmd_info(a) -> int:
    with Device.open(a.port, baudrate=a.baud) as dev:
        _print_info(dev.info())
    return 0


def cmd_monitor(a) -> int:
    capture = open(a.record, "ab") if a.record else None
    stop = {"now": False}
    signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("now", True))
    try:
        with Device.open(a.port, baudrate=a.baud, capture=capture) as dev:
            _print_info(dev.info())
            batch = dev.start_stream(a.rate, calibrated=a.calibrated, accel_range_g=a.range)
            print(f"streaming {'calibrated' if a.calibrated else 'raw'} at {a.rate} Hz, {batch} samples/frame"
                  + (f", recording to {a.record}" if a.record else "") + "; Ctrl-C to stop")
            print(f"{'time':>7} {'rate':>7} | {'accel mean [g]':^29} | {'noise [mg]':^20} | "
                  f"{'gyro mean [°/s]':^26} | {'T[°C]':>5} | link")
            t0 = time.monotonic()
            try:
                while not stop["now"] and (a.duration is None or time.monotonic() - t0 < a.duration):
                    b = dev.read(duration_s=a.interval)
                    acc, gyr = b.si()
                    span = (b.t_us[-1] - b.t_us[0]) / 1e6 if len(b) > 1 else 0
                    rate = (len(b) - 1) / span if span else 0
                    st = dev.link.decoder.stats
                    faults = f" faults {len(dev.link.fault_events)}" if dev.link.fault_events else ""
                    bad = int(np.count_nonzero(b.status))
                    print(f"{time.monotonic() - t0:7.1f} {rate:7.1f} | "
                          f"{_axes(U.mps2_to_mg(acc.mean(axis=0)) / 1000, '{:+9.5f}')} | "
                          f"{_axes(U.mps2_to_mg(acc.std(axis=0)), '{:6.3f}')} | "
                          f"{_axes(U.rad_s_to_dps(gyr.mean(axis=0)), '{:+8.3f}')} | "
                          f"{float(U.accel_temp_counts_to_c(b.accel_temp_counts[-1])):5.1f} | "
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
        if capture:
            capture.close()
    return 0


def cmd_fake(a) -> int:
    from imubench.device.fake import FakeDevice
    with FakeDevice(seed=a.seed, speed=a.speed) as f:
        print(f"fake device (Python emulation, synthetic still board) on {f.port_url}", flush=True)
        print(f"try: IMUBENCH_PORT={f.port_url} imubench monitor", flush=True)
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="imubench", description="IMU calibration bench")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("decode", help="decode a recorded byte stream")
    p.add_argument("file")
    p.add_argument("--npz", help="write the samples to a .npz file")
    p.add_argument("--csv", help="write the samples to a CSV file (SI units)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(fn=cmd_decode)
    p = sub.add_parser("monitor", help="stream and show live values")
    _port_arg(p)
    p.add_argument("--rate", type=int, default=1000, help="sample rate in Hz (divides 4000; default 1000)")
    p.add_argument("--range", type=int, default=0, choices=[0, 2, 4, 8], help="accelerometer range in g (0 = keep)")
    p.add_argument("--calibrated", action="store_true", help="stream the device's calibrated output")
    p.add_argument("--interval", type=float, default=1.0, help="seconds per printed line")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--record", help="append every received byte to this file")
    p.set_defaults(fn=cmd_monitor)
    p = sub.add_parser("info", help="show device information")
    _port_arg(p)
    p.set_defaults(fn=cmd_info)
    for name, (_, _, helptext) in DELEGATED.items():
        sub.add_parser(name, help=helptext, add_help=False)
    p = sub.add_parser("fake", help="run the Python fake device on a pseudo-terminal")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--speed", type=float, default=1.0)
    p.set_defaults(fn=cmd_fake)
    return ap


# Subcommands that own their whole argument list (their modules parse it).
DELEGATED = {
    "sim": ("imubench.device.sim", "main_cli", "run the virtual device (firmware core + sensor models)"),
    "qemu": ("imubench.device.qemu", "main_qemu", "run the real STM32 firmware image under qemu-system-arm"),
    "flash": ("imubench.device.flash", "main_flash", "write the firmware to a board (openocd, st-flash, stm32flash)"),
    "calibrate": ("imubench.procedures.session", "main_calibrate", "guided calibration session, write-back and verification"),
    "history": ("imubench.results.history", "main_history", "calibration history of a device"),
    "allan": ("imubench.procedures.allan", "main_allan", "record for hours and read the Allan deviation (noise terms)"),
    "attitude": ("imubench.procedures.attitude", "main_attitude", "live pitch/roll through RC, Kalman and complementary filters"),
    "thermal": ("imubench.procedures.thermal", "main_thermal", "fit temperature coefficients over a sweep and write them back"),
    "closure": ("imubench.procedures.closure", "main_closure", "integrate a closed path before and after calibration"),
    "report": ("imubench.results.report", "main_report", "one self-contained HTML report of a session"),
}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in DELEGATED:
        import importlib
        module, fn, _ = DELEGATED[argv[0]]
        return getattr(importlib.import_module(module), fn)(argv[1:])
    a = build_parser().parse_args(argv)
    try:
        return a.fn(a)
    except (LinkError, LinkTimeout, DeviceError, FileNotFoundError) as e:
        print(f"imubench {a.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
