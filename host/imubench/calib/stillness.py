"""Live stillness: is the board moving, settling or still, sample by sample, for a guided
session (the same thresholds as calib.static's offline detection, from the measured noise).

    StillnessDetector(fs_hz, noise_sigma).update(samples) -> StillnessState

calib.static finds the still intervals of a whole recording; this module follows a live stream
block by block, so it keeps running sums rather than the recording.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imubench.calib.static import REL_SIGMA_FLOOR, k_min_for_window, moving_variance, window_length

__all__ = ["StillnessDetector", "StillnessState"]


@dataclass
class StillnessState:
    state: str                    # "moving", "settling" or "still"
    mean: np.ndarray              # (3,) mean since the stillness began (still), else of the last window
    std: np.ndarray               # (3,) std over the same samples
    n: int                        # samples in that mean
    still_s: float                # how long the board has been still (0 unless still/settling-still)
    ratio: float                  # current window std / rest noise, max over axes (k-equivalent)

    @property
    def sigma_mean(self) -> np.ndarray:
        return self.std / math.sqrt(max(self.n, 1))


class StillnessDetector:
    """Classifies a live stream as "moving" / "settling" / "still" for a guided session.

    The current window (trailing, window_s) is compared with the rest noise: its std above
    k_move × sigma is "moving" (k_move = 2·k, PX4 uses 4× on variance); at most k × sigma for
    the last settle_s (default one window) is "still"; in between "settling". k defaults to
    max(3, k_min_for_window(w)), so a still board is never called moving by chance (< 1e-6 per
    window and axis) and the thresholds come from the measured noise, not from fixed m/s².

    update(samples) takes any number of new samples (n, 3) and returns a StillnessState; every
    sample is examined, so a bump between two updates is not missed."""

    def __init__(self, fs_hz: float, noise_sigma, window_s: float = 0.5, k: float | None = None,
                 k_move: float | None = None, settle_s: float | None = None, scale: float | None = None):
        self.fs_hz = float(fs_hz)
        self.w = window_length(window_s, fs_hz)
        self.window_s = window_s
        self._sigma_in = np.broadcast_to(np.asarray(noise_sigma, dtype=np.float64), (3,)).copy()
        self.sigma = self._sigma_in.copy()
        self.scale = scale
        if scale:
            self.sigma = np.maximum(self._sigma_in, REL_SIGMA_FLOOR * scale)
        self.k = float(k) if k is not None else max(3.0, k_min_for_window(self.w))
        self.k_move = float(k_move) if k_move is not None else 2.0 * self.k
        self.settle_n = max(1, int(round((settle_s if settle_s is not None else window_s) * fs_hz)))
        self.reset()

    def reset(self) -> None:
        self._tail = np.zeros((0, 3))        # last w-1 samples
        self._quiet = 0                      # consecutive samples whose window was quiet
        self._hold_ref = None                # running sums over the current hold
        self._hold_s1 = np.zeros(3)
        self._hold_s2 = np.zeros(3)
        self._hold_n = 0
        self._last_ratio = float("inf")

    def _hold_add(self, x: np.ndarray) -> None:
        if len(x) == 0:
            return
        if self._hold_ref is None:
            self._hold_ref = x[0].copy()
        d = x - self._hold_ref
        self._hold_s1 += d.sum(axis=0)
        self._hold_s2 += (d * d).sum(axis=0)
        self._hold_n += len(x)

    def _hold_reset(self) -> None:
        self._hold_ref = None
        self._hold_s1 = np.zeros(3)
        self._hold_s2 = np.zeros(3)
        self._hold_n = 0

    def update(self, samples) -> StillnessState:
        x = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
        if not self.scale and len(x):
            # floor of the noise (noise-free data): REL_SIGMA_FLOOR of the data's magnitude
            sc = float(np.median(np.linalg.norm(x, axis=1)))
            if sc > 0:
                self.scale = sc
                self.sigma = np.maximum(self._sigma_in, REL_SIGMA_FLOOR * sc)
        if not np.all(self.sigma > 0):
            self.sigma = np.where(self.sigma > 0, self.sigma, 1e-150)   # all-zero data
        buf = np.vstack([self._tail, x])
        w = self.w
        if len(buf) >= w and len(x):
            var = moving_variance(buf, w, centred=False)        # one per complete trailing window
            r2 = np.max(var / self.sigma**2, axis=1)
            # sample index (in buf) that closes each window
            ends = np.arange(w - 1, len(buf))
            # only windows closed by the new samples are new
            new = ends >= len(self._tail)
            r2, ends = r2[new], ends[new]
            loud = r2 > self.k**2
            if loud.any():
                last_loud = int(np.nonzero(loud)[0][-1])
                self._quiet = len(r2) - 1 - last_loud
                self._hold_reset()
                # the hold now starts with the first quiet window after the last loud one
                qs = ends[last_loud + 1:] if last_loud + 1 < len(ends) else ends[:0]
                if len(qs):
                    self._hold_add(buf[qs[0] - w + 1 + w // 2: ends[-1] + 1])
            else:
                if self._quiet == 0 and self._hold_n == 0:
                    # a hold starts half a window into its first quiet window (as detect_static
                    # trims), so the end of the motion stays out of the mean
                    self._hold_add(buf[ends[0] - w + 1 + w // 2: ends[-1] + 1])
                else:
                    self._hold_add(x[-len(r2):] if len(r2) <= len(x) else x)
                self._quiet += len(r2)
            if len(r2):
                self._last_ratio = float(math.sqrt(r2[-1]))
        self._tail = buf[-(w - 1):] if w > 1 else buf[:0]

        ratio = self._last_ratio
        if len(buf) < w:
            state = "settling"
        elif ratio > self.k_move:
            state = "moving"
        elif ratio <= self.k and self._quiet >= self.settle_n:
            state = "still"
        else:
            state = "settling"

        if state == "still" and self._hold_n > 1:
            m = self._hold_s1 / self._hold_n
            var = (self._hold_s2 - self._hold_n * m * m) / (self._hold_n - 1)
            mean = self._hold_ref + m
            std = np.sqrt(np.clip(var, 0, None))
            n = self._hold_n
        else:
            win = buf[-w:] if len(buf) else np.zeros((1, 3))
            mean = win.mean(axis=0)
            std = win.std(axis=0, ddof=1) if len(win) > 1 else np.zeros(3)
            n = len(win)
        still_s = self._hold_n / self.fs_hz if self._quiet > 0 else 0.0
        return StillnessState(state=state, mean=mean, std=std, n=n, still_s=still_s, ratio=ratio)
