"""The warm-up temperature calibration: a board lies still (on a face the person chooses) while
it warms from cold; the session streams raw all the while, keeps every byte on disk as it
arrives, cuts the stream into time bins, fits each axis's bias against its sensor's own
temperature as it goes (imubench.analysis.thermal_poly: order by held-out error, never more
than the span carries) and stops when the span asked for is covered by every sensor, the
temperatures stop rising, or the time is up. Ctrl-C (KeyboardInterrupt), a `stop` event or a
lost link keep the fit of what came (thermal.json status "interrupted" / "failed").

With `write` the terms go to the device (layout-3 parameter block: c1..c3 per axis, the linear
scale term where the faces separate it, the span rounded inwards to whole °C) through the
write-back every writer uses (procedures.writeback.write_verified: set, read back, save, reboot,
read back; the previous block restored on any failure), then a check that the device applies
them: its calibrated output at the current temperature must match what the host computes from
the raw stream just before.

    imubench thermal --warmup [--sim] [--span LO,HI] [--face +z] [--write] [--export px4,ardupilot]
"""
from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imubench import units as U
from imubench.analysis.thermal import POSES
from imubench.analysis.thermal_poly import AxisFit, Binned, FaceSegment, bin_stream, fit_triad_faces, neighbour_sigma
from imubench.device.link import DeviceError
from imubench.errors import ImubenchError
from imubench.files import open_growing
from imubench.results import thermal_export as TX
from imubench.results.thermal_warmup import (
    WarmupRecord,
    bins_json,
    fit_json,
    format_fit,
    format_progress,
    plot_warmup,
)
from imubench.wire import params as PR
from imubench.wire.board_parts import DEFAULT as DEFAULT_PARTS
from imubench.wire.board_parts import BoardParts
from imubench.wire.ids import SENSOR_BAD_BITS, device_identity, part_names, parts_text
from imubench.wire.protocol_gen import Params, ParamsWhich

CAPTURE_NAME = "capture.bin"
PLOT_NAME = "warmup.png"
BAD_MASK = int(sum(int(b) for b in SENSOR_BAD_BITS))
MIN_BINS_TO_FIT = 6
NOW_WINDOW_S = 0.5             # "now": the temperatures' mean over the latest half second


class WarmupError(ImubenchError):
    """A warm-up that cannot start or cannot be fitted (the message says why, in one line)."""


@dataclass
class WarmupConfig:
    """span_c: (lo, hi) °C every sensor must cover (None: until the temperatures stop rising);
    stop when every sensor's |dT/dt| over the last stop_window_s (device time) is below
    stop_rate_c_per_min, or after max_s; bins of bin_s; a fit every fit_every_s of device time;
    t_ref_c None: the device's own reference temperatures; write: to the device; exports:
    "px4", "ardupilot"."""
    span_c: tuple | None = None
    rate_hz: int = 200
    face: str = "+z"
    stop_rate_c_per_min: float = 0.05
    stop_window_s: float = 300.0
    max_s: float = 4 * 3600.0
    bin_s: float = 10.0
    t_ref_c: float | None = None
    write: bool = False
    exports: tuple = ()
    fit_every_s: float = 60.0
    max_order: int = 3
    span_tol_c: float = 0.5
    stall_s: float = 10.0          # no sample for this long (wall time): the link is lost

    def __post_init__(self):
        if self.face not in POSES:
            raise ValueError(f"face {self.face!r}: one of {', '.join(POSES)}")
        if self.span_c is not None:
            lo, hi = (float(v) for v in self.span_c)
            if not hi > lo:
                raise ValueError(f"span {lo:g},{hi:g}: the upper end must be above the lower")
            self.span_c = (lo, hi)
        for name in ("stop_rate_c_per_min", "stop_window_s", "max_s", "bin_s", "fit_every_s", "stall_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 (got {getattr(self, name)})")
        if self.stop_window_s < 3 * self.bin_s:
            raise ValueError(f"stop_window_s ({self.stop_window_s:g} s) must hold at least three bins of {self.bin_s:g} s")
        bad = [e for e in self.exports if e not in TX.KINDS]
        if bad:
            raise ValueError(f"export {bad[0]!r}: one of {', '.join(TX.KINDS)}")
        if not 0 <= self.max_order <= 3:
            raise ValueError("max_order: 0..3")

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["span_c"] = None if self.span_c is None else list(self.span_c)
        d["exports"] = list(self.exports)
        return d


@dataclass
class WarmupHooks:
    """What the bench can do. orient(direction (3,)): put the board on the face (None: the person
    did); cool(): bring it cold (a virtual fridge; None: it is cold already); warm(): let it warm
    (None: it warms by itself, e.g. from its own power); ready(text): a person confirms (Enter);
    reachable_c: (lo, hi) the temperatures the bench can bring the dies to (None: unknown)."""
    orient: Callable[[np.ndarray], None] | None = None
    cool: Callable[[], None] | None = None
    warm: Callable[[], None] | None = None
    ready: Callable[[str], None] | None = None
    say: Callable[[str], None] = lambda s: None
    reachable_c: tuple | None = None


def sim_warmup_hooks(vb, cold_c: float = 5.0, warm_c: float = 45.0, tau_s=None, self_heat_c=None,
                     say: Callable[[str], None] = lambda s: None) -> WarmupHooks:
    """Hooks for a VirtualBench with the thermal model: cool = the thermal model on (tau_s,
    self_heat_c: None keeps or draws them) and a soak at cold_c (ambient and every die at once,
    as after hours in a fridge); warm = the ambient to warm_c (the dies follow with their lag,
    plus self-heating)."""
    info = vb.set_thermal(enabled=True, tau_s=tau_s, self_heat_c=self_heat_c)
    heat = [float(v) for v in (info.get("self_heat_c") or info.get("thermal", {}).get("self_heat_c") or [0.0] * 4)]

    def orient(d):
        vb.set_orientation(gravity=[float(v) for v in d])

    def cool():
        vb.set_temperature(cold_c, soak=True)

    def warm():
        vb.set_temperature(warm_c)

    return WarmupHooks(orient=orient, cool=cool, warm=warm, say=say,
                       reachable_c=(float(cold_c), float(warm_c) + min(heat)))


# ------------------------------------------------------------------ the running state
@dataclass
class _State:
    cfg: WarmupConfig
    t0: float | None = None
    pending: list = field(default_factory=list)     # (t_s, temps (n,4), values (n,6)) not yet binned
    bins: list = field(default_factory=list)        # Binned pieces
    n_samples: int = 0
    n_bad: int = 0
    last_fit_s: float = -math.inf
    fits: dict | None = None
    t_last: float = 0.0
    seen_lo: np.ndarray = field(default_factory=lambda: np.full(4, np.inf))    # per sensor, of the samples
    seen_hi: np.ndarray = field(default_factory=lambda: np.full(4, -np.inf))
    temp_now: np.ndarray | None = None      # mean of the last NOW_WINDOW_S of samples (a bin's mean lags)

    def feed(self, b) -> int:
        """Add a raw block; bin what completes a bin. Returns the number of new bins."""
        ok = (b.status.astype(np.int64) & BAD_MASK) == 0
        self.n_bad += int((~ok).sum())
        self.n_samples += int(ok.sum())
        if not ok.any():
            return 0
        t = b.t_us[ok].astype(np.float64) * 1e-6
        a, g = b.si()
        temps = np.column_stack([U.accel_temp_counts_to_c(b.accel_temp_counts[ok], range_g=b.accel_range_g[ok]),
                                 U.gyro_temp_counts_to_c(b.gyro_temp_counts[ok])])
        if self.t0 is None:
            self.t0 = float(t[0])
        self.t_last = float(t[-1])
        self.seen_lo = np.minimum(self.seen_lo, temps.min(axis=0))
        self.seen_hi = np.maximum(self.seen_hi, temps.max(axis=0))
        self.temp_now = temps[t >= t[-1] - NOW_WINDOW_S].mean(axis=0)
        self.pending.append((t, temps, np.column_stack([a[ok], g[ok]])))
        edge = self.t0 + math.floor((self.t_last - self.t0) / self.cfg.bin_s) * self.cfg.bin_s
        t_all = np.concatenate([p[0] for p in self.pending])
        if t_all[0] >= edge:
            return 0
        temps_all = np.concatenate([p[1] for p in self.pending])
        v_all = np.concatenate([p[2] for p in self.pending])
        cut = int(np.searchsorted(t_all, edge))
        new = bin_stream(t_all[:cut], temps_all[:cut], v_all[:cut], self.cfg.bin_s, t0_s=self.t0)
        self.pending = [(t_all[cut:], temps_all[cut:], v_all[cut:])]
        if len(new):
            self.bins.append(new)
        return len(new)

    def binned(self) -> Binned:
        return Binned.concat(self.bins)

    @property
    def elapsed_s(self) -> float:
        return 0.0 if self.t0 is None else self.t_last - self.t0


def _rates(b: Binned, window_s: float) -> tuple[np.ndarray, bool]:
    """Each sensor's dT/dt (°C/min) from a straight line through the bins of the last window_s;
    and whether the bins cover the whole window."""
    if len(b) < 2:
        return np.full(4, np.nan), False
    sel = b.t_s >= b.t_s[-1] - window_s
    if sel.sum() < 2:
        sel[-2:] = True
    t = b.t_s[sel]
    slope = np.polyfit(t - t[0], b.temp_c[sel], 1)[0] * 60.0
    return slope, bool(b.t_s[-1] - b.t_s[0] >= window_s * 0.999)


def _honest(b: Binned) -> Binned:
    """The bins with each σ floored by the scatter between neighbouring bins."""
    floor = neighbour_sigma(b.mean)
    return Binned(b.t_s, b.temp_c, b.mean, np.maximum(b.sigma, floor[None, :]), b.n)


def fit_bins(segments: Sequence[tuple[np.ndarray, Binned]], t_ref: dict, max_order: int = 3,
             parts: BoardParts = DEFAULT_PARTS) -> dict:
    """Fit one or more warm-ups (face direction, its bins): {"accel": [AxisFit]*3, "gyro": [AxisFit]*3}.
    parts: the board's (wire.board_parts): each triad's span is rounded to its parts' temperature step."""
    segs = [(np.asarray(d, float), _honest(b)) for d, b in segments if len(b) >= 2]
    if not segs:
        raise WarmupError("no bins to fit")
    acc = [FaceSegment(d, b.temp_c[:, 0], b.mean[:, :3], b.sigma[:, :3], b.t_s) for d, b in segs]
    gyr = [FaceSegment(d, b.temp_c[:, 1:4], b.mean[:, 3:6], b.sigma[:, 3:6], b.t_s) for d, b in segs]
    try:
        return {"accel": fit_triad_faces(acc, t_ref["accel"], U.G0_MPS2, max_order, resolution_c=parts.accel_temp_step_c),
                "gyro": fit_triad_faces(gyr, t_ref["gyro"], None, max_order, resolution_c=parts.gyro_temp_step_c)}
    except ValueError as e:
        raise WarmupError(f"cannot fit: {e}") from None


def export_fits(segments, t_ref: dict, fits: dict, max_order: int = 3, parts: BoardParts = DEFAULT_PARTS) -> dict:
    """Per export kind (fits, words): an autopilot has one temperature per gyro sensor (PX4) or
    per IMU (ArduPilot), ours are one per axis: the gyro terms are fitted again against the
    temperature that firmware would be given (PX4: the mean of the three gyro temperatures;
    ArduPilot: the accelerometer's, the IMU's temperature for both). parts: the board's, named in
    the words and giving the gyros' temperature step."""
    segs = [(np.asarray(d, float), _honest(b)) for d, b in segments if len(b) >= 2]
    out = {}
    for kind, col, words in (("px4", None, f"the mean of the three {parts.gyro_words} temperatures"),
                             ("ardupilot", 0, f"the {parts.accel.name} temperature (for accelerometer and gyro)")):
        g = [FaceSegment(d, b.temp_c[:, 1:4].mean(axis=1) if col is None else b.temp_c[:, col], b.mean[:, 3:6],
                         b.sigma[:, 3:6], b.t_s) for d, b in segs]
        try:
            gf = fit_triad_faces(g, t_ref["gyro"], None, max_order, resolution_c=parts.gyro_temp_step_c)
        except ValueError as e:
            raise WarmupError(f"cannot fit the gyro for {kind}: {e}") from None
        out[kind] = ({"accel": fits["accel"], "gyro": gf}, words)
    return out


def _progress(st: _State, b: Binned) -> dict:
    rates, _ = _rates(b, st.cfg.stop_window_s)
    # the span covered: of the samples (a bin's mean lags the ends by half a bin of a fast rise)
    span = [[float(st.seen_lo[i]), float(st.seen_hi[i])] for i in range(4)] if st.t0 is not None else [[math.nan] * 2] * 4
    now = st.temp_now if st.temp_now is not None else (b.temp_c[-1] if len(b) else [math.nan] * 4)
    p = {"elapsed_s": st.elapsed_s, "temp_c": [float(v) for v in now],
         "rate_c_per_min": [float(v) for v in rates], "span_c": span, "n_bins": len(b), "samples": st.n_samples,
         "fit": None}
    if st.fits is not None:
        p["fit"] = {tr: {"order": [a.bias.order for a in axes], "heldout_rms": [a.bias.heldout_rms for a in axes]}
                    for tr, axes in st.fits.items()}
    return p


def _covered(st: _State, span, tol: float) -> bool:
    """Every sensor's samples have reached both ends of span (within tol)."""
    if span is None or st.t0 is None:
        return False
    lo, hi = span
    return bool(np.all(st.seen_lo <= lo + tol) and np.all(st.seen_hi >= hi - tol))


# ------------------------------------------------------------------ the run
def run_warmup(dev, out_dir, cfg: WarmupConfig, hooks: WarmupHooks, on_progress: Callable[[dict], None] | None = None,
               stop: threading.Event | None = None, *, config_extra: dict | None = None) -> dict:
    """The whole warm-up on an open device, recorded in out_dir (thermal.json, capture.bin).
    Returns the final thermal.json content; its status is "done", "interrupted" (Ctrl-C, stop)
    or "failed" (a lost link: `error` says why), each with the fit of what came when there was
    enough to fit. Raises WarmupError before streaming when the span cannot be covered, and the
    link's error when the device does not answer at all (nothing is recorded then). config_extra:
    more to keep in thermal.json's config (the CLI: the virtual bench's settings)."""
    say = hooks.say
    out_dir = Path(out_dir)
    if cfg.span_c is not None and hooks.reachable_c is not None:
        lo, hi = hooks.reachable_c
        if cfg.span_c[0] < lo - cfg.span_tol_c or cfg.span_c[1] > hi + cfg.span_tol_c:
            raise WarmupError(f"span {cfg.span_c[0]:g}..{cfg.span_c[1]:g} °C: this bench brings the sensors from "
                              f"{lo:g} to about {hi:.1f} °C only")
    info = dev.info()            # a port with no device on it fails here, before anything is recorded
    parts = BoardParts.of_info(info)     # the parts it reported: their names, steps and ranges
    if cfg.span_c is not None:
        for t_c in cfg.span_c:
            bad = parts.limiting_part(t_c)
            if bad is not None:
                raise WarmupError(f"span {cfg.span_c[0]:g}..{cfg.span_c[1]:g} °C: this board's {bad.name} works from "
                                  f"{bad.t_min_c:g} to {bad.t_max_c:g} °C only (its data sheet); give a span inside "
                                  f"{parts.operating_c[0]:g}..{parts.operating_c[1]:g} °C")
    rec = WarmupRecord(out_dir, {**cfg.to_json(), **(config_extra or {})})
    say(f"recording in {rec.path} (raw stream: {out_dir / CAPTURE_NAME})")
    say(f"parts: {parts_text(part_names(info))}")
    st = _State(cfg)
    status, error, reason = "done", None, None
    direction = np.array(POSES[cfg.face], dtype=float)
    capture = None
    old = None
    t_ref = None
    try:
        old = dev.get_params(ParamsWhich.ACTIVE).params
        t_ref = {"accel": float(old.accel_t_ref_c if cfg.t_ref_c is None else cfg.t_ref_c),
                 "gyro": float(old.gyro_t_ref_c if cfg.t_ref_c is None else cfg.t_ref_c)}
        rec.update(device=device_identity(info), t_ref_c=t_ref, stage="prepare")
        if hooks.orient is not None:
            hooks.orient(direction)
        if hooks.cool is not None:
            say("cooling the board (virtual fridge: a soak)")
            hooks.cool()
        if hooks.ready is not None:
            hooks.ready(f"lay the board still with {cfg.face.upper()} up, cold; it may warm from now on")
        capture = open_growing(out_dir / CAPTURE_NAME, buffering=0)
        dev.link.capture = capture
        rec.update(capture=CAPTURE_NAME, stage="warm-up")
        dev.start_stream(rate_hz=cfg.rate_hz, calibrated=False)
        if cfg.span_c is not None and hooks.cool is None:
            first = dev.read(n_samples=max(10, cfg.rate_hz // 2))
            now_c = np.r_[U.accel_temp_counts_to_c(first.accel_temp_counts, range_g=first.accel_range_g).mean(),
                          U.gyro_temp_counts_to_c(first.gyro_temp_counts).mean(axis=0)]
            if np.max(now_c) > cfg.span_c[0] + 2.0:
                raise WarmupError(f"the sensors are at {_fmt(now_c)} °C already, above the span's lower end "
                                  f"{cfg.span_c[0]:g} °C: cool the board first (a fridge), or start the span at "
                                  f"{math.ceil(np.max(now_c)):g} °C")
        if hooks.warm is not None:
            hooks.warm()
        say(f"streaming raw at {cfg.rate_hz} Hz while the board warms ({cfg.face.upper()} up, still); every "
            f"{cfg.fit_every_s:g} s: time, temperatures {parts.temperatures_text}, their rates, the span covered, the "
            "fitted orders. Ctrl-C ends it with the fit of what came")
        reason = _stream(dev, st, rec, say, on_progress, stop, t_ref, parts)
        if reason.startswith("stopped"):
            status = "interrupted"
    except KeyboardInterrupt:
        status, reason = "interrupted", "interrupted (Ctrl-C)"
    except (OSError, DeviceError, ImubenchError) as e:
        if isinstance(e, WarmupError) and st.t0 is None:
            rec.update(status="failed", error=str(e), stage="done")
            raise
        status, reason, error = "failed", "link lost", f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
    except BaseException as e:             # anything else (EOF at the prompt, a bug): say so on disk, raise
        rec.update(status="failed", error=f"{type(e).__name__}: {e}", stage="done")
        raise
    finally:
        if status == "done" or (status == "interrupted" and not dev.link.error):
            try:
                dev.stop_stream()
            except (OSError, DeviceError, KeyboardInterrupt):
                pass
        if capture is not None:
            dev.link.capture = None
            capture.close()
    b = st.binned()
    rec.update(stop_reason=reason, error=error, stage="fit",
               progress=_progress(st, b) if len(b) else None, bins=bins_json(b) if len(b) else None)
    say(f"stopped: {reason}")
    if len(b) < MIN_BINS_TO_FIT or t_ref is None:
        msg = f"{len(b)} bins of {cfg.bin_s:g} s: too few to fit (need {MIN_BINS_TO_FIT})"
        say(msg)
        rec.update(status=status if status != "done" else "failed", error=error or msg, stage="done")
        return rec.data
    try:
        fits = fit_bins([(direction, b)], t_ref, cfg.max_order, parts)
    except WarmupError as e:
        rec.update(status="failed", error=error or str(e), stage="done")
        return rec.data
    fj = fit_json(fits, t_ref, parts)
    rec.update(fit=fj)
    say(format_fit(fj))
    png = plot_warmup(rec.data, out_dir / PLOT_NAME)
    if png is not None:
        rec.update(plot=PLOT_NAME)
        say(f"plot: {png}")
    if cfg.exports:
        _exports(rec, out_dir, [(direction, b)], t_ref, fits, cfg, say, parts)
    if cfg.write:
        if status != "done":
            say("not written: the run did not finish (the fit of what came is in thermal.json)")
        else:
            rec.update(stage="write")
            try:
                rec.update(write=write_warmup(dev, old, fits, t_ref, b, cfg, say))
            except (OSError, DeviceError, ImubenchError) as e:
                rec.update(write={"verified": False, "error": str(e)})
                status, error = "failed", f"write: {e}"
    elif status == "done":
        say("(not written: give --write)")
    rec.update(status=status, error=error, stage="done")
    say(f"saved {rec.path}")
    return rec.data


def _exports(rec: WarmupRecord, out_dir: Path, segments, t_ref: dict, fits: dict, cfg: WarmupConfig, say,
             parts: BoardParts) -> None:
    """The PX4 / ArduPilot parameter files beside thermal.json; the fit is kept when they fail."""
    try:
        files = TX.write_exports(out_dir, export_fits(segments, t_ref, fits, cfg.max_order, parts), t_ref,
                                 cfg.exports, comment=f"imubench warm-up {rec.data['started']}", parts=parts)
    except (WarmupError, OSError) as e:           # the exports say why they are missing
        rec.update(exports={"error": str(e)})
        say(f"exports not written: {e}")
    else:
        rec.update(exports={k: [str(p) for p in v] for k, v in files.items()})
        for k, v in files.items():
            say(f"{k}: {', '.join(str(p) for p in v)}")


def _fmt(v) -> str:
    return "/".join(f"{x:.1f}" for x in v)


def _stream(dev, st: _State, rec: WarmupRecord, say, on_progress, stop, t_ref, parts: BoardParts) -> str:
    cfg = st.cfg
    next_say = 0.0          # the progress line is due at every multiple of fit_every_s of device time
    prog = None
    while True:
        # a stream that goes silent for cfg.stall_s raises LinkTimeout (the run ends "failed", fit
        # kept); the stop event is seen within a read (0.2 s)
        new = st.feed(dev.read(duration_s=0.2, timeout=cfg.stall_s))
        if stop is not None and stop.is_set():
            return "stopped (asked to)"
        if not new:
            # the line comes on time (within a read) even between bins: it was said only when a
            # bin completed, 26 to 51 s apart for "every 20 s" (issue 38)
            if prog is not None and st.elapsed_s >= next_say:
                next_say = (math.floor(st.elapsed_s / cfg.fit_every_s) + 1) * cfg.fit_every_s
                prog = _progress(st, st.binned())
                say(format_progress(prog))
                rec.update(progress=prog)
            continue
        b = st.binned()
        if st.elapsed_s - st.last_fit_s >= cfg.fit_every_s and len(b) >= MIN_BINS_TO_FIT:
            st.last_fit_s = st.elapsed_s
            try:
                st.fits = fit_bins([(np.array(POSES[cfg.face], float), b)], t_ref, cfg.max_order, parts)
            except WarmupError:
                st.fits = None
        prog = _progress(st, b)
        if on_progress is not None:
            on_progress(prog)
        if st.elapsed_s >= next_say:
            next_say = (math.floor(st.elapsed_s / cfg.fit_every_s) + 1) * cfg.fit_every_s
            say(format_progress(prog))
            rec.update(progress=prog)
        rates, full = _rates(b, cfg.stop_window_s)
        if _covered(st, cfg.span_c, cfg.span_tol_c) and len(b) >= 2 * MIN_BINS_TO_FIT:   # enough bins to fit
            return f"span {cfg.span_c[0]:g}..{cfg.span_c[1]:g} °C covered by every sensor"
        if full and np.all(np.abs(rates) < cfg.stop_rate_c_per_min):
            note = "" if cfg.span_c is None else " (span asked for NOT covered)"
            return (f"temperatures stopped rising: |dT/dt| < {cfg.stop_rate_c_per_min:g} °C/min over "
                    f"{cfg.stop_window_s:g} s{note}")
        if st.elapsed_s >= cfg.max_s:
            return f"time is up ({cfg.max_s:g} s)" + ("" if cfg.span_c is None else " (span asked for NOT covered)")


# ------------------------------------------------------------------ the device's parameters
def _set(p: Params, name: str, value) -> None:
    if name not in {f.name for f in dataclasses.fields(p)}:
        raise WarmupError(f"the device's parameter block has no {name}: it needs layout 3 (firmware with "
                          "polynomial temperature terms)")
    setattr(p, name, value)


def params_from_warmup(old: Params, fits: dict, t_ref: dict) -> tuple[Params, list[str]]:
    """The parameter block with the warm-up's terms: c1..c3 per axis, the accelerometer's linear
    scale term where the faces separated it (an axis along gravity on one face: 0, its slope is in
    c1), the other scale terms kept; the span rounded inwards to whole °C (accel: the accelerometer's;
    gyro: where all three gyros were). t_ref: the device's unless asked otherwise (then b moves
    along the fitted curve). Returns (params, notes); validated (params.validate)."""
    p = Params.from_values(old.values())
    notes = []
    for triad, pre in (("accel", "accel"), ("gyro", "gyro")):
        axes: list[AxisFit] = fits[triad]
        c = np.array([[a.bias.coef[i] if i <= a.bias.order else 0.0 for i in range(4)] for a in axes])
        unit = ("mps2", "m/s^2") if triad == "accel" else ("rad_s", "rad/s")
        _set(p, f"{pre}_bias_tc_{unit[0]}_per_c", tuple(float(v) for v in c[:, 1]))
        _set(p, f"{pre}_bias_tc2_{unit[0]}_per_c2", tuple(float(v) for v in c[:, 2]))
        _set(p, f"{pre}_bias_tc3_{unit[0]}_per_c3", tuple(float(v) for v in c[:, 3]))
        old_ref = float(getattr(old, f"{pre}_t_ref_c"))
        if abs(t_ref[triad] - old_ref) > 1e-9:
            c0 = c.copy()
            c0[:, 0] = 0.0
            from imubench.analysis.thermal_poly import poly_eval
            shift = np.array([poly_eval(c0[k], old_ref, t_ref[triad]) for k in range(3)])
            b = np.asarray(getattr(old, f"{pre}_b_{unit[0]}"), float) - shift
            _set(p, f"{pre}_b_{unit[0]}", tuple(float(v) for v in b))
            notes.append(f"{triad}: t_ref moved {old_ref:g} → {t_ref[triad]:g} °C, b moved along the fitted curve")
        _set(p, f"{pre}_t_ref_c", float(t_ref[triad]))
        spans = np.array([a.bias.span_c for a in axes])
        lo, hi = math.ceil(float(spans[:, 0].max()) - 1e-9), math.floor(float(spans[:, 1].min()) + 1e-9)
        if hi <= lo:
            raise WarmupError(f"{triad}: the warm-up spans {spans[:, 0].max():.1f}..{spans[:, 1].min():.1f} °C, not "
                              "a whole degree the device can hold: warm up over a wider span")
        if not lo <= t_ref[triad] <= hi:
            raise WarmupError(f"{triad}: the warm-up covered {lo}..{hi} °C (whole degrees inside its span), not the "
                              f"reference temperature {t_ref[triad]:g} °C of the device's calibration: start colder or "
                              "warm further (or give --t-ref inside the span)")
        _set(p, f"{pre}_t_min_c", int(lo))
        _set(p, f"{pre}_t_max_c", int(hi))
        if triad == "accel":
            s = list(old.accel_scale_tc_per_c)
            for k, a in enumerate(axes):
                if a.scale_tc_per_c is not None:
                    s[k] = float(a.scale_tc_per_c)
                elif any("not separated" in u for u in a.undetermined):
                    s[k] = 0.0
                    notes.append(f"accel {'xyz'[k]}: scale temperature term set to 0 (its slope is in c1: one attitude)")
            _set(p, "accel_scale_tc_per_c", tuple(s))
    try:
        PR.validate(p)
    except PR.InvalidParams as e:
        raise WarmupError(f"the fitted terms are outside what the device accepts: {e}") from None
    return p, notes


def expected_calibrated(p: Params, raw_accel, raw_gyro, temps) -> tuple[np.ndarray, np.ndarray]:
    """The device's model (docs/conventions.md; imubench.wire.params.correct, with the clamp) on
    the host: calibrated accel and gyro from nominal-scaled raw means (3,), at the temperatures
    (4,) (the accelerometer's, gyro X, Y, Z)."""
    a = PR.correct(PR.accel(p), np.asarray(raw_accel, float)[None, :], np.array([temps[0]]))
    g = PR.correct(PR.gyro(p), np.asarray(raw_gyro, float)[None, :], np.asarray(temps[1:4], float)[None, :],
                   accel_mps2=a)
    return a[0], g[0]


def _read_now(dev, rate_hz: int, calibrated: bool, n: int, timeout_s: float):
    dev.start_stream(rate_hz=rate_hz, calibrated=calibrated)
    try:
        dev.read(n_samples=max(20, n // 20), timeout=timeout_s)      # what was in flight before
        return dev.read(n_samples=n, timeout=timeout_s)
    finally:
        dev.stop_stream()


def write_warmup(dev, old: Params, fits: dict, t_ref: dict, b: Binned, cfg: WarmupConfig, say,
                 n_check: int = 1000) -> dict:
    """Write the warm-up's terms (write_verified), then check that the device applies them: the
    raw mean of n_check samples now and the calibrated mean right after must agree with the
    host's model within 5σ of the means plus what the temperature moved in between. On a
    failed check the previous parameters are restored (saved)."""
    from imubench.procedures.writeback import restore, write_verified
    new, notes = params_from_warmup(old, fits, t_ref)
    for n in notes:
        say(f"note: {n}")
    wait_s = 10.0 + 2.0 * n_check / cfg.rate_hz      # an emulated board may run at half real time
    raw = _read_now(dev, cfg.rate_hz, False, n_check, wait_s)
    wb = write_verified(dev, new, previous=old, say=say)
    say(f"written: {', '.join(wb['steps'])}")
    try:
        cal = _read_now(dev, cfg.rate_hz, True, n_check, wait_s)
    except (OSError, DeviceError) as e:
        restore(dev, old)
        raise WarmupError(f"could not check the written terms ({e}): the previous parameters were restored") from e
    ra, rg = raw.si()
    t_raw = np.r_[U.accel_temp_counts_to_c(raw.accel_temp_counts, range_g=raw.accel_range_g).mean(), U.gyro_temp_counts_to_c(raw.gyro_temp_counts).mean(axis=0)]
    t_cal = np.r_[U.accel_temp_counts_to_c(cal.accel_temp_counts, range_g=cal.accel_range_g).mean(), U.gyro_temp_counts_to_c(cal.gyro_temp_counts).mean(axis=0)]
    ea, eg = expected_calibrated(new, ra.mean(axis=0), rg.mean(axis=0), t_raw)
    ca, cg = cal.si()
    da, dg = ca.mean(axis=0) - ea, cg.mean(axis=0) - eg
    sa = np.hypot(ra.std(axis=0, ddof=1), ca.std(axis=0, ddof=1)) / math.sqrt(n_check)
    sg = np.hypot(rg.std(axis=0, ddof=1), cg.std(axis=0, ddof=1)) / math.sqrt(n_check)
    # what the temperature moved between the two reads, times the slopes of the raw stream's bins
    moved = np.abs(t_cal - t_raw)
    slope_a = np.array([abs(np.polyfit(b.temp_c[:, 0], b.mean[:, k], 1)[0]) for k in range(3)]) if len(b) > 2 else np.zeros(3)
    slope_g = np.array([abs(np.polyfit(b.temp_c[:, 1 + k], b.mean[:, 3 + k], 1)[0]) for k in range(3)]) if len(b) > 2 else np.zeros(3)
    tol_a = 5 * sa + slope_a * moved[0] + 1e-5
    tol_g = 5 * sg + slope_g * moved[1:] + 1e-7
    ok = bool(np.all(np.abs(da) <= tol_a) and np.all(np.abs(dg) <= tol_g))
    check = {"accel_diff_mps2": da.tolist(), "accel_tol_mps2": tol_a.tolist(), "gyro_diff_rad_s": dg.tolist(),
             "gyro_tol_rad_s": tol_g.tolist(), "temp_c": t_cal.tolist(), "ok": ok}
    out = {"generation": int(wb["generation"]), "steps": list(wb["steps"]), "notes": notes, "check": check,
           "params": PR.to_json(new), "verified": ok}
    if ok:
        say(f"the device applies the terms: its calibrated output matches the host's model at {t_cal[0]:.1f} °C "
            f"(accel within {np.max(np.abs(da)) * 1e6 / U.G0_MPS2:.1f} µg, gyro {np.max(np.abs(dg)) * 180e3 / math.pi:.2f} m°/s)")
    else:
        restore(dev, old)
        out["previous_restored"] = True
        say("the device's calibrated output does not match the host's model: the previous parameters were restored")
        raise WarmupError(f"device check failed (accel diff {np.round(da * 1e6 / U.G0_MPS2, 1).tolist()} µg, gyro diff "
                          f"{np.round(dg * 180e3 / math.pi, 2).tolist()} m°/s): previous parameters restored")
    return out
