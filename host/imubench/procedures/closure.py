"""Closure check on a device: drive (or carry) the board around a closed path while its raw
stream goes to disk as it arrives, then integrate it before and after calibration
(imubench.analysis.closure) and keep closure.json and closure.png beside the capture.

A calibrated IMU closes the loop to within its noise; an uncalibrated one ends metres away.
docs/closure.md describes the method and its numbers.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.analysis.closure import closure_from_block
from imubench.analysis.strapdown import ClosureError, euler_matrix, yaw_between
from imubench.files import MAX_CAPTURE_BYTES, make_dir, read_bytes, read_text
from imubench.results.atomic import write_json_atomic
from imubench.results.closure import plot_closure, result_json
from imubench.wire import params as PR
from imubench.wire.decoder import SampleBlock, decode_bytes
from imubench.wire.ids import device_identity
from imubench.wire.protocol_gen import Params, ParamsWhich

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
        t0 = dev.clock.now()            # device time against a lockstep virtual device
        while not finished(moving):
            if dev.clock.now() - t0 > max_s:
                raise ClosureError(f"the motion did not end within {max_s:g} s")
            moving.append(dev.read(n_samples=chunk))
        blocks += moving
        say(f"back at the start mark: hold the board still again ({end_rest_s:g} s)")
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


def load_params(src: str | None, dev=None) -> Params:
    """The calibration to apply: "device" (its active parameters) or a JSON file (a
    closure.json or session result with a "params" member, or Params fields)."""
    if src is None or src == "device":
        return dev.get_params(ParamsWhich.ACTIVE).params
    try:
        data = json.loads(read_text(src, what="the parameters"))
    except ValueError as e:
        raise ClosureError(f"{src} is not JSON ({e}); give a closure.json or a JSON object of Params fields") from None
    if isinstance(data, dict) and "params" in data:
        data = data["params"]
    return PR.from_json(data)


def analyse(out_dir: Path, rest_s: float | None = None, g_mps2: float | None = None) -> dict:
    """(Re)compute closure.json and closure.png from out_dir/capture.bin and the parameters
    recorded in out_dir/closure.json (written before the recording started)."""
    for name in ("closure.json", "capture.bin"):
        if not (out_dir / name).is_file():
            raise ClosureError(f"{out_dir} holds no {name}: it is not a closure recording "
                               "(imubench closure --out DIR writes one)")
    try:
        meta = json.loads(read_text(out_dir / "closure.json"))
        params = PR.from_json(meta["params"])
    except (ValueError, KeyError, TypeError) as e:
        raise ClosureError(f"{out_dir / 'closure.json'} is damaged ({type(e).__name__}: {e})") from None
    _, raw, _, stats = decode_bytes(read_bytes(out_dir / "capture.bin", MAX_CAPTURE_BYTES, "the capture"))
    if raw is None:
        raise ClosureError(f"no raw samples in {out_dir / 'capture.bin'}")
    rest = float(rest_s if rest_s is not None else meta.get("rest_s", 2.0))
    g = float(g_mps2 if g_mps2 is not None else meta.get("g_mps2", G0))
    res = closure_from_block(raw, params, rest, g)
    res["g_mps2"] = g
    truth = truth_in_navigation_frame(meta, res)
    png = plot_closure(res, out_dir / "closure.png", truth)
    keep = {k: meta[k] for k in ("params", "device", "path", "rest_s", "truth_path_m", "truth_closure_m",
                                 "start_attitude_deg", "started") if k in meta}
    keep["rest_s"] = rest
    keep["decoder"] = stats.as_dict()
    keep["plot"] = png.name
    write_json_atomic(out_dir / "closure.json", result_json(res, keep))
    return res


def run_closure(dev, out_dir: Path, params: Params, vb=None, path: str = "box", rest_s: float = 2.0,
                rate_hz: int = 1000, g_mps2: float = G0, max_s: float = 120.0,
                say: Callable[[str], None] = print) -> dict:
    """Record one closed path into out_dir (capture.bin as it arrives, closure.json with the
    parameters first) and analyse it. With a VirtualBench vb its bench drives PATHS[path] and
    the truth (path, and how far the bench's own path closes) is recorded too; without one the
    user carries the board (human_finished). Returns the closure_from_block result."""
    make_dir(out_dir)
    info = dev.info()
    meta = {"schema": 1, "started": _dt.datetime.now().isoformat(timespec="seconds"),
            "path": path if vb is not None else "by hand", "rest_s": rest_s, "g_mps2": g_mps2,
            "params": PR.to_json(params), "device": device_identity(info)}
    if vb is not None:
        legs = PATHS[path]
        meta["truth_path_m"] = sim_truth_path(legs).tolist()
        st = vb.status()
        pos0 = np.asarray(st["position_m"])
        # the board need not start level at yaw 0 (after a session it is in its last
        # verification attitude): keep its attitude to put the truth in the navigation frame
        meta["start_attitude_deg"] = {k: float(st[f"{k}_deg"]) for k in ("roll", "pitch", "yaw")}

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
    return analyse(out_dir, rest_s, g_mps2)


def truth_in_navigation_frame(meta: dict, res: dict) -> np.ndarray | None:
    """The virtual bench's path (closure.json "truth_path_m", in the simulator's level world
    frame) in the navigation frame of the integration, whose heading is that of the board's
    attitude at the start (analysis.strapdown): turned about the vertical by the heading
    between the two, found from the board's start attitude seen both ways. None without a
    truth; the world frame as it is for recordings made before the attitude was kept."""
    if not meta.get("truth_path_m"):
        return None
    truth = np.asarray(meta["truth_path_m"], dtype=float)
    att, r0 = meta.get("start_attitude_deg"), res["after"].r0
    if not att or r0 is None:
        return truth
    psi = yaw_between(r0, euler_matrix(att["roll"], att["pitch"], att["yaw"]))
    c, s = math.cos(psi), math.sin(psi)
    return truth @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def sim_truth_path(legs: Sequence[dict], n_per_leg: int = 50) -> np.ndarray:
    """Positions (the simulator's level world frame, m) along the legs (minimum-jerk), for
    plots (truth_in_navigation_frame puts them where the integration is)."""
    pos, out = np.zeros(3), [np.zeros(3)]
    s = np.linspace(0.0, 1.0, n_per_leg)[1:]
    h = s ** 3 * (10 - 15 * s + 6 * s ** 2)
    for leg in legs:
        d = np.asarray(leg.get("move_m", [0.0, 0.0, 0.0]), dtype=float)
        out.extend(pos + d * hh for hh in h)
        pos = pos + d
    return np.array(out)


def calibrate_virtual(vb, dev, directory: Path, seed: int = 1, say: Callable[[str], None] = print) -> Params:
    """Calibrate a virtual device as `make demo` does (multi-position + turntable), write the
    parameters back and return them."""
    from imubench.procedures.session import (
        Session,
        SessionConfig,
        SimPresenter,
        plan_for,
    )
    cfg = SessionConfig(method="multi", gyro="turntable")
    sess = Session(dev, directory, cfg, SimPresenter(vb, seed=seed, quiet=False))
    say(f"calibrating the virtual device first (multi-position + turntable; session in {directory})")
    result = sess.run(plan_for(cfg.method))
    if not result["passed"]:
        raise ClosureError("the calibration of the virtual device did not pass; see " + str(directory))
    wb = sess.write_back(sess.accel_fit, sess.gyro_fit, cal_id=int(time.time()) & 0xFFFFFFFF)
    return wb["params"]
