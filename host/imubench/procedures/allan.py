"""Allan recording: stream a resting IMU for hours into a capture file (every byte on disk as
it arrives, so Ctrl-C or a lost link keeps what was recorded), then analyse a capture:
decode it, compute the Allan deviations (imubench.analysis.allan), write allan.json and the
plots (imubench.results.allan). docs/noise.md.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from imubench.analysis.allan import AXES, allan, usual_units
from imubench.device.link import (
    DEFAULT_BAUD,
    Device,
    DeviceError,
    LinkError,
    LinkTimeout,
)
from imubench.errors import NotACapture
from imubench.files import MAX_CAPTURE_BYTES, make_dir, open_growing, read_bytes
from imubench.results.allan import format_readoffs, plot_allan
from imubench.wire.board_parts import BoardParts
from imubench.results.atomic import write_json_atomic
from imubench.wire.decoder import decode_bytes
from imubench.wire.ids import device_identity, uid_text
from imubench.wire.protocol_gen import MsgType


def analyse_capture(paths, out_dir: Path, rate_hz: float | None = None, log=print, exports=(),
                    topic: str = "/imu0", duration_s: float | None = None) -> dict:
    """Decode capture file(s), convert raw counts to SI, run allan() on accel and gyro,
    write allan.json, the two PNGs and each consumer's noise file of `exports`
    (results.noise_export) to out_dir; returns the summary dict. duration_s: the length asked
    for (device s): only that much is analysed (the stream runs on a little while it is being
    stopped; what came after stays in the capture)."""
    data = b"".join(read_bytes(p, MAX_CAPTURE_BYTES, "the capture") for p in paths)
    msgs, raw, _cal, stats = decode_bytes(data)
    infos = [m.msg for m in msgs if m.type == MsgType.INFO]     # record() asks for one into the capture
    if raw is None or len(raw) < 16:
        raise NotACapture(f"{', '.join(map(str, paths))}: no raw samples to analyse "
                          f"({stats.samples} samples, {stats.frames_ok} good and {stats.frames_rejected} "
                          "rejected frames); give an imubench capture (allan --out DIR writes DIR/capture.bin)")
    if rate_hz is None:                          # from the device time stamps
        rate_hz = (len(raw) - 1) / ((raw.t_us[-1] - raw.t_us[0]) / 1e6)
        rate_hz = float(np.round(rate_hz, 1))
    if duration_s is not None and len(raw) > int(round(duration_s * rate_hz)) >= 16:
        keep = int(round(duration_s * rate_hz))
        log(f"analysing the first {duration_s:g} s asked for ({keep} samples); the {len(raw) - keep} samples "
            f"({(len(raw) - keep) / rate_hz:.1f} s) that came while the stream was stopped stay in the capture")
        raw = raw[:keep]
    acc, gyr = raw.si()
    make_dir(out_dir)
    devices = {device_identity(i)["mcu_uid"]: device_identity(i) for i in infos}
    if len(devices) > 1:
        raise NotACapture(f"{', '.join(map(str, paths))} hold recordings of {len(devices)} devices "
                          f"({', '.join(devices)}); analyse each device's captures on their own")
    res = {"source": [str(p) for p in paths], "device": next(iter(devices.values()), None),
           "samples": len(raw), "rate_hz": rate_hz,
           "duration_s": len(raw) / rate_hz, "decoder": stats.as_dict(),
           "accel": allan(acc, rate_hz), "gyro": allan(gyr, rate_hz)}
    if stats.samples_missing:
        log(f"warning: {stats.samples_missing} samples were lost in {stats.sample_gaps} gaps; "
            "the analysis joins the pieces (fine for a few, biased for many)")
    res["accel_usual"] = {a: usual_units(res["accel"][a], "accel") for a in AXES}
    res["gyro_usual"] = {a: usual_units(res["gyro"][a], "gyro") for a in AXES}
    if exports:
        from imubench.results.noise_export import write_noise_files
        name = (res["device"] or {}).get("mcu_uid") or "imubench"
        res["exports"] = write_noise_files(exports, out_dir, res, topic=topic, name=name)
    write_json_atomic(out_dir / "allan.json", res)
    parts = BoardParts.of_device(res["device"])       # the parts the capture's device reported
    plot_allan(res["accel"], out_dir / "allan_accel.png", f"Accelerometer ({parts.accel.name})", "m/s²", "accel")
    plot_allan(res["gyro"], out_dir / "allan_gyro.png", f"Gyroscope ({parts.gyro_words})", "rad/s", "gyro")
    for line in format_readoffs(res):
        log(line)
    for kind, f in (res.get("exports") or {}).items():
        log(f"{kind}: {f}")
    log(f"wrote {out_dir / 'allan.json'}, {out_dir / 'allan_accel.png'}, {out_dir / 'allan_gyro.png'}")
    return res


MIN_STILL_S = 60.0          # the shortest still stretch a noise figure is read from (τ up to 6 s)
STILL_WINDOW_S = 0.5        # the segmentation of `calibrate --from` (procedures.from_file.FileConfig)
STILL_MIN_S = 1.0


def still_stretch(acc_mps2, gyro_rad_s, fs_hz: float) -> dict:
    """The longest still stretch of a recording, found as `calibrate --from` finds its rests:
    calib.static.detect_static on the accelerometer (same window, same automatic threshold),
    then calib.turns.split_by_rotation where only the gyro turned. Returns {'start', 'stop'
    (sample indices, stop exclusive), 't_start_s', 'duration_s', 'fraction' (of the recording),
    'stretches' (how many were found), 'whole' (True when it is the whole recording), 'note'}.
    Raises RecordingError when no stretch of MIN_STILL_S is still, with the stretches found:
    an Allan figure of a moving IMU is its motion, not its noise. In memory: float64 copies of both
    sensors and temporaries of the recording's size (~150 B a sample, measured on 1.44 M samples);
    still_stretch_blocks finds the same stretch a block at a time (what `allan --from` runs)."""
    from imubench.calib.static import detect_static
    from imubench.calib.turns import split_by_rotation
    a = np.asarray(acc_mps2, float)
    ivs = detect_static(a, fs_hz, window_s=STILL_WINDOW_S, min_duration_s=STILL_MIN_S)
    pieces = split_by_rotation(a, gyro_rad_s, fs_hz, list(ivs), min_duration_s=STILL_MIN_S)
    return _longest([(p.start, p.stop) for p in pieces], len(a), fs_hz)


def still_stretch_blocks(acc, gyro, fs_hz: float, acc_factor: float = 1.0, gyro_factor: float = 1.0) -> dict:
    """still_stretch(acc × acc_factor, gyro × gyro_factor, fs_hz) found a block at a time from the
    stored arrays (float32 or float64, never copied whole: calib.still_blocks): the same stretch,
    holding one working column of 8 B a sample at a time beside the recording."""
    from imubench.calib.still_blocks import Scaled, still_pieces
    pieces = still_pieces(Scaled(acc, acc_factor), Scaled(gyro, gyro_factor), fs_hz, STILL_WINDOW_S, STILL_MIN_S)
    return _longest(pieces, len(acc), fs_hz)


class _Piece:
    def __init__(self, start: int, stop: int, fs_hz: float):
        self.start, self.stop, self.n, self.t_start_s = int(start), int(stop), int(stop - start), start / fs_hz


def _longest(spans, n: int, fs_hz: float) -> dict:
    """still_stretch's answer from the still pieces (start, stop) of a recording of n samples."""
    from imubench.recordings import RecordingError
    pieces = [_Piece(s, e, fs_hz) for s, e in spans]
    total_s = n / fs_hz
    if not pieces:
        raise RecordingError(f"the recording ({total_s:.1f} s) is never still: the Allan figures of a moving IMU "
                             "measure its motion, not its noise. Record the IMU at rest on a firm surface (hours "
                             "for the bias terms) and give that file")
    best = max(pieces, key=lambda i: i.n)
    dur = best.n / fs_hz
    durs = sorted((p.n / fs_hz for p in pieces), reverse=True)
    listed = ", ".join(f"{d:.1f}" for d in durs[:8]) + (f", … ({len(durs) - 8} more)" if len(durs) > 8 else "")
    if dur < MIN_STILL_S:
        raise RecordingError(f"the recording ({total_s:.1f} s) is not still long enough for noise figures: its "
                             f"longest still stretch is {dur:.1f} s of {len(pieces)} found ({listed} s; the "
                             f"segmentation of calibrate --from), at least {MIN_STILL_S:.0f} s needed. The Allan "
                             "figures of a moving IMU measure its motion, not its noise: record the IMU at rest on "
                             "a firm surface (hours for the bias terms) and give that file")
    whole = best.start == 0 and best.stop == n
    note = "" if whole else (
        f"the recording is not still throughout: {len(pieces)} still stretch{'es' if len(pieces) != 1 else ''} "
        f"({listed} s) between motion; the longest, {best.t_start_s:.1f}–{best.t_start_s + dur:.1f} s "
        f"({100 * best.n / n:.0f} % of {total_s:.1f} s), is analysed")
    return {"start": int(best.start), "stop": int(best.stop), "t_start_s": float(best.t_start_s),
            "duration_s": float(dur), "fraction": best.n / n, "stretches": len(pieces), "whole": whole,
            "note": note}


def analyse_recording(rec, out_dir: Path, exports=(), topic: str = "/imu0", log=print,
                      memory_budget: int | None = None) -> dict:
    """The Allan analysis of a recording of any IMU read by imubench.recordings (the formats
    `calibrate --from` reads, with the same unit and timing checks), written like
    analyse_capture's, plus each consumer's noise file of `exports` (results.noise_export).
    The deviation is computed an axis at a time from the recording's own arrays, in memory or
    in chunks as the memory budget (imubench.memory) allows."""
    from imubench.procedures.recording_checks import check_accel_unit, check_gyro_unit
    from imubench.recordings import RecordingError
    from imubench.results.noise_export import write_noise_files
    fa, fg = rec.accel_factor(), rec.gyro_factor()
    if fa is None or fg is None:
        raise RecordingError("the Allan figures are in SI: give the raw counts' nominal scale (--accel-scale "
                             "COUNTS_PER_G, --gyro-scale COUNTS_PER_DPS, or --sensor NAME) or declare an SI unit")
    n = len(rec)
    if n < 64:
        raise RecordingError(f"{n} samples: far too few for an Allan analysis (record a still IMU for hours)")
    held = rec.accel.nbytes + rec.gyro.nbytes + (0 if rec.t_s is None else rec.t_s.nbytes)
    # still_stretch's stretch, found a block at a time from rec's own arrays: no SI copy of the recording
    # (still_stretch in memory takes ~150 B a sample, and 4x the time for statistics it does not use)
    still = still_stretch_blocks(rec.accel, rec.gyro, float(rec.fs_hz), fa, fg)
    s0, s1 = still["start"], still["stop"]
    chunk = max(1, int(10 * rec.fs_hz))
    norms = np.array([np.linalg.norm(rec.accel[i:i + chunk].mean(axis=0, dtype=np.float64))
                      for i in range(s0, s1 - chunk + 1, chunk)]
                     or [np.linalg.norm(rec.accel[s0:s1].mean(axis=0, dtype=np.float64))])
    check_accel_unit(rec, norms)                       # refuses only |a| far from 1 g
    warn = check_gyro_unit(rec, np.array([np.median(rec.gyro[s0:s1, j]) for j in range(3)], dtype=np.float64), fg)
    if warn:
        log(f"warning: {warn}")
    if still["note"]:
        log(f"note: {still['note']}")
    for b, why in rec.breaks:
        if s0 < b < s1:
            log(f"warning: break at sample {b}: {why}; the analysis joins the pieces")
    make_dir(out_dir)
    name = rec.device or Path(rec.source.split(" + ")[0]).stem
    res = {"source": [rec.source], "device": {"name": name}, "samples": s1 - s0, "rate_hz": float(rec.fs_hz),
           "duration_s": (s1 - s0) / rec.fs_hz, "format": rec.fmt, "units": rec.unit_text(),
           "timing": list(getattr(rec, "notes", [])), "still": still,
           "accel": _allan_of(rec.accel[s0:s1], "accelerometer", rec.fs_hz, fa, memory_budget, held),
           "gyro": _allan_of(rec.gyro[s0:s1], "gyro", rec.fs_hz, fg, memory_budget, held)}
    res["method"] = res["gyro"]["method"]
    res["storage"] = f"{rec.accel.dtype.name} values ({(rec.accel.nbytes + rec.gyro.nbytes) / n:.0f} B a sample)"
    res["accel_usual"] = {a: usual_units(res["accel"][a], "accel") for a in AXES}
    res["gyro_usual"] = {a: usual_units(res["gyro"][a], "gyro") for a in AXES}
    files = write_noise_files(exports, out_dir, res, topic=topic, name=name)
    res["exports"] = files
    write_json_atomic(out_dir / "allan.json", res)
    plot_allan(res["accel"], out_dir / "allan_accel.png", f"Accelerometer ({name})", "m/s²", "accel")
    plot_allan(res["gyro"], out_dir / "allan_gyro.png", f"Gyroscope ({name})", "rad/s", "gyro")
    for line in format_readoffs(res):
        log(line)
    for kind, f in files.items():
        log(f"{kind}: {f}")
    log(f"memory: {res['storage']}; Allan deviation by {res['method']}")
    log(f"wrote {out_dir / 'allan.json'}, {out_dir / 'allan_accel.png'}, {out_dir / 'allan_gyro.png'}")
    return res


def _allan_of(values, what: str, fs_hz: float, factor: float, memory_budget, held: int) -> dict:
    """allan() of a recording's sensor; what the analysis cannot do with the data (a constant axis)
    is the recording's fault, said in one line."""
    from imubench.recordings import RecordingError
    for k, axis in enumerate(AXES[:values.shape[1]]):
        col = values[:, k]
        if col.min() == col.max():
            raise RecordingError(f"the {what}'s axis {axis}: its samples do not vary (every one {float(col[0]):g} in "
                                 "the file's unit): there is no noise to analyse; is the column a constant, or the "
                                 "sensor's output stuck?")
    try:
        return allan(values, fs_hz, factor, memory_budget, held)
    except ValueError as e:
        raise RecordingError(f"the {what}'s {e}") from None


#: device time granted per step when recording from a lockstep virtual device, s
LOCKSTEP_STEP_S = 10.0


def record(port, duration_s: float, rate_hz: int, capture_path: Path, baud: int = DEFAULT_BAUD,
           progress_s: float = 5.0, stop: dict | None = None, log=print) -> str:
    """Stream raw at rate_hz into capture_path (every byte appended as it arrives) until
    duration_s of *device* time has been received, stop["now"] is set, or the link is lost.
    Returns why it ended: 'done', 'interrupted' or 'link lost: ...'."""
    stop = stop if stop is not None else {"now": False}
    want = int(round(duration_s * rate_hz))
    why = "done"
    with open_growing(capture_path, buffering=0) as cap:
        dev = Device.open(port, baudrate=baud, capture=cap, timeout=3.0)   # no port: nothing to record
        with dev:
            info = dev.info()            # its reply goes into the capture: the file names its device
            log(f"device {uid_text(info.mcu_uid)}")
            try:
                dev.start_stream(rate_hz, calibrated=False)
            except (LinkError, LinkTimeout, DeviceError) as e:
                return f"link lost: {e}"
            t0 = time.monotonic()
            t_next = t0 + progress_s
            have, t_first, t_last = 0, None, None
            log(f"recording raw at {rate_hz} Hz for {duration_s:g} s of device time to {capture_path}; "
                "Ctrl-C stops and analyses what was recorded")
            try:
                # a lockstep virtual device: ten seconds of device time per step (one control
                # round trip each: an hour is 360 of them); what runs past the duration is cut
                # off by the analysis (analyse_capture's duration_s)
                for b in dev.stream(poll_s=LOCKSTEP_STEP_S if dev.clock.lockstep else 0.1):
                    if len(b):
                        have += len(b)
                        t_first = b.t_us[0] if t_first is None else t_first
                        t_last = b.t_us[-1]
                    now = time.monotonic()
                    if now >= t_next or have >= want:
                        t_next = now + progress_s
                        st = dev.link.decoder.stats
                        dev_s = (t_last - t_first) / 1e6 if t_first is not None else 0.0
                        log(f"  {dev_s:9.1f} / {duration_s:g} s ({100 * min(have, want) / max(want, 1):5.1f} %), "
                            f"{have} samples, wall {now - t0:.1f} s | link: {st.bytes_in} B, "
                            f"{st.frames_ok} frames, {st.frames_rejected} rejected, {st.samples_missing} lost",
                            flush=True)
                    if have >= want:
                        break
                    if stop["now"]:
                        why = "interrupted"
                        break
            except (LinkError, LinkTimeout, DeviceError, OSError) as e:
                why = f"link lost: {e}"
            try:
                if not why.startswith("link lost"):
                    dev.stop_stream()
            except (LinkError, LinkTimeout, DeviceError) as e:
                log(f"warning: could not stop the stream: {e}")
    return why
