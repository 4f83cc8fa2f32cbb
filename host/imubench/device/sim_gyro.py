"""The virtual ADXRS450's noise, straight from the C model (libimumodels.so), without a
virtual session: a recording of one chip at rest, and the Allan deviation its truth should
give (docs/simulator.md, "Gyro noise").

    rates = record(seed=1, n=3_600_000, rate_hz=10.0)          # rad/s, one chip at rest
    model_adev(taus_s, noise_n=..., bias_instability_rad_s=..., bias_rw_k=...)   # rad/s

The model's bias is white noise N (ADEV N/√τ), a bias instability B made of first-order
Gauss-Markov processes one per decade of correlation time (adxrs450_model.h; their
constants are read from the library, not copied here), and a rate random walk K
(ADEV K·√(τ/3)); the three are independent, so their Allan variances add.
"""
from __future__ import annotations

import ctypes
from functools import lru_cache

import numpy as np

from imubench import units as U


@lru_cache(maxsize=1)
def _lib() -> ctypes.CDLL:
    from imubench.device.artifacts import models_library
    lib = ctypes.CDLL(str(models_library()))
    lib.sim_adxrs450_record.restype = ctypes.c_int
    lib.sim_adxrs450_record.argtypes = [ctypes.c_uint64, ctypes.c_int, ctypes.c_int, ctypes.c_double,
                                        ctypes.c_size_t, ctypes.POINTER(ctypes.c_int16)]
    lib.sim_adxrs450_flicker_taus.restype = ctypes.POINTER(ctypes.c_double)
    lib.sim_adxrs450_flicker_taus.argtypes = []
    lib.sim_adxrs450_flicker_weight.restype = ctypes.c_double
    lib.sim_adxrs450_flicker_weight.argtypes = []
    lib.sim_adxrs450_flicker_n.restype = ctypes.c_int
    lib.sim_adxrs450_flicker_n.argtypes = []
    return lib


def flicker_bank() -> tuple[np.ndarray, float]:
    """(correlation times in s, each process's σ / B) of the model's bias-instability bank."""
    lib = _lib()
    p = lib.sim_adxrs450_flicker_taus()
    return (np.array([p[i] for i in range(lib.sim_adxrs450_flicker_n())]),
            float(lib.sim_adxrs450_flicker_weight()))


def record(seed: int, n: int, rate_hz: float = 10.0, axis: int = 0, random_truth: bool = False) -> np.ndarray:
    """n rate samples (rad/s) of one chip at rest at 25 °C, read through its SPI protocol at
    rate_hz (the default truth, or the random truth of `seed`)."""
    buf = (ctypes.c_int16 * n)()
    if _lib().sim_adxrs450_record(seed, axis, 1 if random_truth else 0, rate_hz, n, buf) != 0:
        raise ValueError(f"bad rate {rate_hz} Hz")
    return U.gyro_counts_to_rad_s(np.frombuffer(buf, dtype=np.int16).astype(np.float64))


def gauss_markov_avar(taus_s, sigma: float, corr_s: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov process of standard deviation sigma and
    correlation time corr_s (IEEE Std 952-1997, annex C; El-Sheimy, Hou, Niu 2008)."""
    x = np.asarray(taus_s, float) / corr_s
    return 2.0 * sigma ** 2 / x * (1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))


def model_adev(taus_s, noise_n: float, bias_instability_rad_s: float, bias_rw_k: float) -> np.ndarray:
    """The Allan deviation (rad/s) the model's truth gives at taus_s (s)."""
    t = np.asarray(taus_s, float)
    corr, weight = flicker_bank()
    var = noise_n ** 2 / t + bias_rw_k ** 2 * t / 3.0
    for c in corr:
        var = var + gauss_markov_avar(t, weight * bias_instability_rad_s, c)
    return np.sqrt(var)


# A gyro truth update that holds the bias still (set_truth(gyro=[NO_DRIFT] * 3), or
# {**NO_DRIFT, ...}): no rate random walk, no bias instability. The white noise stays.
NO_DRIFT = {"bias_rw_k": 0.0, "bias_instability_rad_s": 0.0}
