"""Closure check: drive the board around a closed path, integrate its accelerations twice
(strapdown, attitude from the gyros) and see how far from the start the integration ends,
once with the raw sensor data (nominal datasheet scaling) and once with the calibration
applied. A calibrated IMU closes the loop to within its noise; an uncalibrated one ends
metres away. docs/closure.md describes the method and its numbers.

The integration itself (motion window, levelling, strapdown, noise floor) is
imubench.analysis.strapdown, pure numpy; this module applies the calibration to a recording
(closure_from_block, also pure), records paths on a device and runs the command line.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from imubench.wire import params as PR
from imubench import units as U
from imubench.results.atomic import write_json_atomic
from imubench.wire.decoder import SampleBlock, decode_bytes
from imubench.wire.protocol_gen import Params
from imubench.analysis.strapdown import (
    ClosureError,
    motion_window,
    noise_floor,
    strapdown,
)

__all__ = [
    "PATHS",
    "ClosureError",
    "closure_from_block",
    "main_closure",
    "plot_closure",
    "record_path",
    "summarize",
]

G0 = U.G0_MPS2

# Paths the virtual bench can drive (firmware/boards/sim/sim_physics.c: legs rest to rest on
# a minimum-jerk profile; move_m in the level frame, turns about a board axis). Both end
# where they started.
PATHS: dict[str, list[dict]] = {
    # a cart on a level floor: 0.5 m square, turning 90° left at each corner
    "square": [leg for k in range(4) for leg in (
        {"duration_s": 1.2, "move_m": [0.5 * math.cos(k * math.pi / 2), 0.5 * math.sin(k * math.pi / 2), 0.0]},
        {"duration_s": 0.8, "axis": "z", "turn_deg": 90.0})],
    # a 3-D loop that tilts the board while it moves, and undoes the turns in reverse order
    # so it ends where and as it started: every axis of both sensors is excited and gravity
    # moves across the accelerometer axes (scale and cross-axis errors show)
    "box": [
        {"duration_s": 1.2, "move_m": [0.5, 0.0, 0.0], "axis": "y", "turn_deg": 30.0},
        {"duration_s": 1.2, "move_m": [0.0, 0.5, 0.2], "axis": "x", "turn_deg": -30.0},
        {"duration_s": 1.2, "move_m": [-0.5, 0.0, 0.0], "axis": "z", "turn_deg": 90.0},
        {"duration_s": 1.2, "move_m": [0.0, -0.5, 0.0], "axis": "z", "turn_deg": -90.0},
        {"duration_s": 1.2, "move_m": [0.0, 0.0, -0.2], "axis": "x", "turn_deg": 30.0},
        {"duration_s": 1.2, "axis": "y", "turn_deg": -30.0},
    ],
}


# ------------------------------------------------------------------ one recording
def _temperatures(block: SampleBlock) -> tuple[np.ndarray, np.ndarray]:
    return (U.accel_temp_counts_to_c(block.accel_temp_counts), U.gyro_temp_counts_to_c(block.gyro_temp_counts))


def corrected(block: SampleBlock, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """(accel m/s², rate rad/s) of a RAW block with params applied on the host, exactly as
    the device applies them (imubench.wire.params.correct, per-sample sensor temperatures)."""
    acc, gyr = block.si()
    ta, tg = _temperatures(block)
    return PR.correct(PR.accel(params), acc, ta), PR.correct(PR.gyro(params), gyr, tg)


def closure_from_block(block: SampleBlock, params: Params, rest_s: float = 2.0, g_mps2: float = G0,
                       align_s: float | None = None, window: tuple[int, int] | None = None) -> dict:
    """The closure check of one raw recording: still for rest_s at the start, a closed path,
    still at the end. Integrates it over the same motion window (detected on the calibrated
    data unless given) as "before" (nominal scaling: no calibration), "after" (params applied)
    and "after_rest_bias" (params applied, and the gyro bias the calibrated gyros still show
    at the start rest removed, as navigation does at every power-up). Returns those three
    Integrations, "gyro_bias_at_rest_rad_s" (what the calibrated gyros read at rest: the bias
    change since the calibration), "window", "noise_floor", "improvement" (before / after)."""
    if block is None or block.calibrated:
        raise ClosureError("the closure check needs a RAW recording (it applies the calibration itself)")
    si = np.diff(block.sample_index)
    if len(si) and (si != 1).any():
        lost = int((si[si > 1] - 1).sum())
        raise ClosureError(f"{lost} samples were lost in the recording ({int((si != 1).sum())} gaps); "
                           "an integration across a gap is meaningless: record again (lower --rate?)")
    bad = int(np.count_nonzero(block.status))
    if bad:
        raise ClosureError(f"{bad} samples carry sensor fault bits; fix the sensors and record again")
    t = block.t_us.astype(np.float64) * 1e-6
    fs = (len(t) - 1) / (t[-1] - t[0])
    acc_b, gyr_b = block.si()
    acc_a, gyr_a = corrected(block, params)
    i0, i1 = window if window is not None else motion_window(t, acc_a, gyr_a, rest_s)
    align_n = int(round((align_s if align_s is not None else 0.8 * rest_s) * fs))
    before = strapdown(t, acc_b, gyr_b, i0, i1, align_n, g_mps2, "before calibration (nominal scaling)")
    after = strapdown(t, acc_a, gyr_a, i0, i1, align_n, g_mps2, "after calibration")
    # the gyro bias moves between power-ups and with time (bias repeatability, random walk):
    # navigation re-measures it at rest before moving; so does this third integration
    a0 = max(0, i0 - align_n + 1)
    rest_bias = gyr_a[a0:i0 + 1].mean(axis=0)
    after_zb = strapdown(t, acc_a, gyr_a - rest_bias, i0, i1, align_n, g_mps2,
                         "after, gyro bias zeroed at rest")
    rest_n = int(np.searchsorted(t, t[0] + rest_s))
    floor = noise_floor(acc_a[:rest_n], gyr_a[:rest_n], fs, t[i1] - t[i0], align_n, g_mps2)
    return {"before": before, "after": after, "after_rest_bias": after_zb,
            "gyro_bias_at_rest_rad_s": rest_bias.tolist(),
            "window": {"i0": int(i0), "i1": int(i1), "t0_s": float(t[i0]), "t1_s": float(t[i1]),
                       "duration_s": float(t[i1] - t[i0]), "fs_hz": float(fs), "samples": int(i1 - i0 + 1)},
            "noise_floor": floor,
            "improvement": before.distance_m / max(after.distance_m, 1e-12)}


def result_json(res: dict, extra: dict | None = None) -> dict:
    """The JSON-able summary (closure.json) of a closure_from_block result."""
    out = {"schema": 1, "before": res["before"].as_dict(), "after": res["after"].as_dict(),
           "after_rest_bias": res["after_rest_bias"].as_dict(),
           "gyro_bias_at_rest_rad_s": res["gyro_bias_at_rest_rad_s"],
           "window": res["window"], "noise_floor": res["noise_floor"], "improvement": res["improvement"],
           "g_mps2": res.get("g_mps2", G0)}
    out.update(extra or {})
    return out


def summarize(res: dict) -> str:
    """A text table: closure before and after calibration."""
    b, a, nf = res["before"], res["after"], res["noise_floor"]
    w = res["window"]
    lines = [f"closure check: {w['duration_s']:.2f} s of motion, {w['samples']} samples at {w['fs_hz']:.0f} Hz; "
             f"path length (calibrated) {a.path_length_m:.2f} m",
             f"{'':32} {'distance m':>11} {'horiz m':>9} {'vert m':>9} {'end speed m/s':>14} "
             f"{'closure x, y, z (m)':>30}"]
    for r in (b, a, res["after_rest_bias"]):
        cx, cy, cz = r.closure_m
        lines.append(f"{r.label:32} {r.distance_m:11.4f} {r.horizontal_m:9.4f} {r.vertical_m:9.4f} "
                     f"{r.end_speed_mps:14.4f} {cx:+10.4f} {cy:+9.4f} {cz:+9.4f}")
    lines.append(f"{'white-noise floor (1 sigma)':32} {nf['sigma_distance_m']:11.4f} "
                 f"{math.hypot(nf['sigma_x_m'], nf['sigma_y_m']):9.4f} {nf['sigma_z_m']:9.4f}")
    gb = np.degrees(res["gyro_bias_at_rest_rad_s"])
    lines.append(f"calibrated gyros at the start rest read {gb[0]:+.4f} {gb[1]:+.4f} {gb[2]:+.4f} °/s "
                 "(the bias change since the calibration)")
    lines.append(f"calibration shrinks the closure error {res['improvement']:.0f}x "
                 f"({100 * a.distance_m / max(a.path_length_m, 1e-9):.2f} % of the path length after)")
    return "\n".join(lines)


def plot_closure(res: dict, path, truth_path_m: np.ndarray | None = None) -> Path:
    """PNG: top views (navigation X/Y) after and before calibration, and each integration's
    distance from the start over time (log scale)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b, a = res["before"], res["after"]
    fig, axs = plt.subplots(1, 3, figsize=(16, 5))
    for ax, r, col in ((axs[0], a, "C0"), (axs[1], b, "C3")):
        ax.plot(r.pos_m[:, 0], r.pos_m[:, 1], color=col, lw=1.2, label=r.label)
        ax.plot(r.pos_m[0, 0], r.pos_m[0, 1], "ko", label="start")
        ax.plot(r.pos_m[-1, 0], r.pos_m[-1, 1], "x", color=col, ms=10, mew=2,
                label=f"end: {r.distance_m:.3g} m from the start")
        if r is a:
            z = res["after_rest_bias"]
            ax.plot(z.pos_m[:, 0], z.pos_m[:, 1], color="C2", lw=1.0, label=z.label)
            ax.plot(z.pos_m[-1, 0], z.pos_m[-1, 1], "x", color="C2", ms=10, mew=2,
                    label=f"end: {z.distance_m:.3g} m from the start")
            if truth_path_m is not None:
                ax.plot(truth_path_m[:, 0], truth_path_m[:, 1], "k--", lw=0.8, label="path driven (truth)")
        ax.set_xlabel("x, initial heading (m)")
        ax.set_ylabel("y, left (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        ax.set_title(("after" if r is a else "before") + " calibration: top view")
    ax = axs[2]
    for r, col in ((b, "C3"), (a, "C0"), (res["after_rest_bias"], "C2")):
        ax.semilogy(r.t_s, np.maximum(np.linalg.norm(r.pos_m - r.pos_m[0], axis=1), 1e-6), color=col,
                    label=r.label)
    ax.set_xlabel("time since the motion window start (s)")
    ax.set_ylabel("distance from the start (m)")
    ax.set_title("distance from the start (the end value is the closure error)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


# ------------------------------------------------------------------ recording on a device
def record_path(dev, start: Callable[[], None], finished: Callable[[list[SampleBlock]], bool],
                rest_s: float = 2.0, end_rest_s: float = 2.0, rate_hz: int = 1000, max_s: float = 120.0,
                say: Callable[[str], None] = print) -> SampleBlock:
    """Stream RAW at rate_hz: rest_s still, then start() (the motion begins), reading on
    until finished(blocks read since start) says the board is back at rest, then end_rest_s
    still. Consecutive reads are contiguous, so the result holds every sample in order."""
    chunk = max(10, rate_hz // 20)
    dev.start_stream(rate_hz=rate_hz, calibrated=False)
    try:
        dev.read(n_samples=chunk)                      # the stream is flowing
        dev.discard_buffered()
        say(f"hold the board still at the start mark ({rest_s:g} s)")
        blocks = [dev.read(n_samples=int(round(rest_s * rate_hz)))]
        start()
        moving: list[SampleBlock] = []
        t0 = time.monotonic()
        while not finished(moving):
            if time.monotonic() - t0 > max_s:
                raise ClosureError(f"the motion did not end within {max_s:g} s")
            moving.append(dev.read(n_samples=chunk))
        blocks += moving
        say(f"hold the board still at the start mark ({end_rest_s:g} s)")
        blocks.append(dev.read(n_samples=int(round(end_rest_s * rate_hz))))
    finally:
        dev.stop_stream()
    return SampleBlock.concat(blocks)


def human_finished(rest: SampleBlock | None = None, still_s: float = 1.0, k: float = 8.0):
    """finished() for a real bench: True once the board has moved (a 50 ms block whose mean
    gyro rate departs from the rest mean by k rest sigmas of such a block) and has been still
    again for still_s. The rest statistics come from the first blocks seen if not given."""
    state: dict = {"ref": rest, "moved": False, "still_t": 0.0, "seen": 0}

    def finished(blocks: list[SampleBlock]) -> bool:
        new = blocks[state["seen"]:]
        state["seen"] = len(blocks)
        for b in new:
            g = U.gyro_counts_to_rad_s(b.gyro_counts)
            if state["ref"] is None:
                state["ref"] = b
                continue
            ref = U.gyro_counts_to_rad_s(state["ref"].gyro_counts)
            sd = ref.std(axis=0, ddof=1) / math.sqrt(len(g)) + 1e-5
            dt = (int(b.t_us[-1]) - int(b.t_us[0])) * 1e-6 + 1e-3
            if (np.abs(g.mean(axis=0) - ref.mean(axis=0)) > k * sd).any():
                state["moved"], state["still_t"] = True, 0.0
            elif state["moved"]:
                state["still_t"] += dt
        return state["moved"] and state["still_t"] >= still_s
    return finished


# ------------------------------------------------------------------ command line
def _load_params(src: str | None, dev=None) -> Params:
    from imubench.wire.protocol_gen import ParamsWhich
    if src is None or src == "device":
        return dev.get_params(ParamsWhich.ACTIVE).params
    data = json.loads(Path(src).read_text())
    if "params" in data:
        data = data["params"]
    return PR.from_json(data)


def analyse(out_dir: Path, rest_s: float | None = None, g_mps2: float | None = None, quiet: bool = False) -> dict:
    """(Re)compute closure.json and closure.png from out_dir/capture.bin and the parameters
    recorded in out_dir/closure.json (written before the recording started)."""
    meta = json.loads((out_dir / "closure.json").read_text())
    _, raw, _, stats = decode_bytes((out_dir / "capture.bin").read_bytes())
    if raw is None:
        raise ClosureError(f"no raw samples in {out_dir / 'capture.bin'}")
    params = PR.from_json(meta["params"])
    rest = float(rest_s if rest_s is not None else meta.get("rest_s", 2.0))
    g = float(g_mps2 if g_mps2 is not None else meta.get("g_mps2", G0))
    res = closure_from_block(raw, params, rest, g)
    res["g_mps2"] = g
    truth = np.asarray(meta["truth_path_m"]) if meta.get("truth_path_m") else None
    png = plot_closure(res, out_dir / "closure.png", truth)
    keep = {k: meta[k] for k in ("params", "device", "path", "rest_s", "truth_path_m", "truth_closure_m",
                                 "started") if k in meta}
    keep["rest_s"] = rest
    keep["decoder"] = stats.as_dict()
    keep["plot"] = png.name
    write_json_atomic(out_dir / "closure.json", result_json(res, keep))
    if not quiet:
        print(summarize(res))
        print(f"results: {out_dir / 'closure.json'}, plot: {png}")
    return res


def run_closure(dev, out_dir: Path, params: Params, vb=None, path: str = "box", rest_s: float = 2.0,
                rate_hz: int = 1000, g_mps2: float = G0, max_s: float = 120.0,
                say: Callable[[str], None] = print) -> dict:
    """Record one closed path into out_dir (capture.bin as it arrives, closure.json with the
    parameters first) and analyse it. With a VirtualBench vb its bench drives PATHS[path] and
    the truth (path, and how far the bench's own path closes) is recorded too; without one the
    user carries the board (human_finished). Returns the closure_from_block result."""
    out_dir.mkdir(parents=True, exist_ok=True)
    info = dev.info()
    meta = {"schema": 1, "started": _dt.datetime.now().isoformat(timespec="seconds"),
            "path": path if vb is not None else "by hand", "rest_s": rest_s, "g_mps2": g_mps2,
            "params": PR.to_json(params), "device": {"mcu_uid": bytes(info.mcu_uid).hex(), "fw_build": info.fw_build}}
    if vb is not None:
        legs = PATHS[path]
        meta["truth_path_m"] = sim_truth_path(legs).tolist()
        pos0 = np.asarray(vb.status()["position_m"])

        def start() -> None:
            vb.path(legs, wait=False)

        def finished(blocks: list[SampleBlock]) -> bool:
            return bool(blocks) and not vb.status()["moving"]
    else:
        def start() -> None:
            say("now move the board along a closed path and put it back on the start mark")
        finished = human_finished()
    write_json_atomic(out_dir / "closure.json", meta)
    cap = open(out_dir / "capture.bin", "ab")  # noqa: SIM115 - closed below
    old = dev.link.capture
    dev.link.capture = cap
    try:
        record_path(dev, start, finished, rest_s, rest_s, rate_hz, max_s, say)
    finally:
        dev.link.capture = old
        cap.close()
    if vb is not None:
        meta["truth_closure_m"] = (np.asarray(vb.status()["position_m"]) - pos0).tolist()
        write_json_atomic(out_dir / "closure.json", meta)
    return analyse(out_dir, rest_s, g_mps2, quiet=True)


def sim_truth_path(legs: Sequence[dict], n_per_leg: int = 50) -> np.ndarray:
    """Positions (level frame, m) along the legs (minimum-jerk), for plots; rotated so that
    the board's X at the start is the navigation X (the virtual board starts at yaw 0)."""
    pos, out = np.zeros(3), [np.zeros(3)]
    s = np.linspace(0.0, 1.0, n_per_leg)[1:]
    h = s ** 3 * (10 - 15 * s + 6 * s ** 2)
    for leg in legs:
        d = np.asarray(leg.get("move_m", [0.0, 0.0, 0.0]), dtype=float)
        out.extend(pos + d * hh for hh in h)
        pos = pos + d
    return np.array(out)


def is_factory(p: Params) -> bool:
    """True for parameters that change nothing (identity matrices, zero biases and tempcos)."""
    ident = PR.identity()
    return all(np.allclose(getattr(p, f), getattr(ident, f)) for f in
               ("accel_m", "accel_b_mps2", "gyro_m", "gyro_b_rad_s", "accel_bias_tc_mps2_per_c",
                "accel_scale_tc_per_c", "gyro_bias_tc_rad_s_per_c", "gyro_scale_tc_per_c"))


def calibrate_virtual(vb, dev, directory: Path, seed: int = 1, say: Callable[[str], None] = print) -> Params:
    """Calibrate a virtual device as `make demo` does (multi-position + turntable), write the
    parameters back and return them."""
    from imubench.procedures.session import Session, SessionConfig, SimPresenter, plan_for
    cfg = SessionConfig(method="multi", gyro="turntable")
    sess = Session(dev, directory, cfg, SimPresenter(vb, seed=seed, quiet=True))
    say(f"calibrating the virtual device first (multi-position + turntable; session in {directory})")
    result = sess.run(plan_for(cfg.method))
    if not result["passed"]:
        raise ClosureError("the calibration of the virtual device did not pass; see " + str(directory))
    wb = sess.write_back(sess.accel_fit, sess.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
    return wb["params"]


def main_closure(argv: Sequence[str] | None = None) -> int:
    """`imubench closure`: integrate a closed path before and after calibration."""
    from imubench.device.link import DEFAULT_BAUD, Device, DeviceError, LinkError, LinkTimeout

    ap = argparse.ArgumentParser(
        prog="imubench closure",
        description="closure check: record a closed path (still at the start and at the end), integrate "
                    "the accelerations twice with nominal scaling and with the calibration applied, and "
                    "report how far from the start each integration ends (docs/closure.md)")
    ap.add_argument("--port", help="pyserial URL of the device (default: $IMUBENCH_PORT)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"baud rate for a real UART (default {DEFAULT_BAUD})")
    ap.add_argument("--params", default="device", metavar="device|FILE",
                    help="calibration to apply: the device's active parameters (default) or a JSON file "
                         "(a closure.json, or Params fields)")
    ap.add_argument("--rate", type=int, default=1000, help="raw sample rate in Hz (default 1000)")
    ap.add_argument("--rest", type=float, default=2.0, help="seconds still at the start and at the end (default 2)")
    ap.add_argument("--max-s", type=float, default=120.0, help="longest motion accepted, s (default 120)")
    ap.add_argument("--g", type=float, default=G0, help=f"local gravity, m/s² (default {G0})")
    ap.add_argument("--out", help="output directory (default ./imubench-closure-<time>)")
    ap.add_argument("--analyse", metavar="DIR", help="recompute the result of an earlier recording (capture.bin)")
    ap.add_argument("--sim", action="store_true", help="virtual device with random truth errors: calibrate it, "
                    "then drive the path on its bench")
    ap.add_argument("--path", choices=sorted(PATHS), default="box", help="path the virtual bench drives (default box)")
    ap.add_argument("--sim-seed", type=int, default=1)
    ap.add_argument("--sim-speed", type=float, default=20.0)
    a = ap.parse_args(argv)
    try:
        if a.analyse:
            analyse(Path(a.analyse), a.rest, a.g)
            return 0
        out = Path(a.out or f"imubench-closure-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
        if (out / "capture.bin").exists():
            print(f"imubench closure: {out / 'capture.bin'} exists; --analyse {out} recomputes it, "
                  "or choose another --out", file=sys.stderr)
            return 2
        vb = None
        try:
            if a.sim:
                from imubench.device.sim import VirtualBench
                vb = VirtualBench(speed=a.sim_speed, seed=a.sim_seed, truth="random")
                url = vb.port_url
            else:
                url = a.port
            with Device.open(url, baudrate=a.baud, timeout=5.0) as dev:
                if a.sim:
                    params = calibrate_virtual(vb, dev, out / "session", a.sim_seed)
                else:
                    params = _load_params(a.params, dev)
                if is_factory(params):
                    raise ClosureError("the calibration to apply is the factory default (it changes nothing): "
                                       "calibrate the device first (imubench calibrate) or give --params FILE")
                res = run_closure(dev, out, params, vb, a.path, a.rest, a.rate, a.g, a.max_s)
        finally:
            if vb is not None:
                vb.stop()
        print(summarize(res))
        print(f"results: {out / 'closure.json'}, plot: {out / 'closure.png'}, raw capture: {out / 'capture.bin'}")
        return 0
    except (ClosureError, LinkError, LinkTimeout, DeviceError, FileNotFoundError) as e:
        print(f"imubench closure: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main_closure())
