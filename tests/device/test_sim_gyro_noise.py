"""The virtual ADXRS450's Allan curve against its data sheet (docs/simulator.md, "Gyro noise"):
one chip of the C model recorded at rest through its SPI protocol (libimumodels.so, 111 h of
device time in about 2 s, no virtual session), analysed with imubench's own Allan read-offs.

Data sheet (Analog Devices, ADXRS450 data sheet, Rev. C): rate noise density 0.015 °/s/√Hz,
in-run bias stability 25 °/h, read as IEEE Std 952-1997's bias instability B (Allan floor
0.664·B = 16.6 °/h; docs/noise.md's read-off B = min ADEV / 0.664).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from imubench import units as U
from imubench.analysis.allan import allan_axis
from imubench.device import sim_gyro as G

DPH = U.DEG / 3600.0                       # 1 °/h in rad/s
DS_NOISE_N = 0.015 * U.DEG                 # rad/s/√Hz, data sheet rate noise density
DS_BIAS_INSTABILITY = 25.0 * DPH           # rad/s, data sheet in-run bias stability
MODEL_K = 8e-5 * U.DEG                     # rad/s·√Hz, the model's rate random walk (no data sheet figure)
RATE_HZ = 10.0
HOURS = 111.0                              # T/8 = 14 h: the +1/2 tail after 10^4 s is inside
P_OUT = 1e-3                               # two-sided: a point outside this interval is a real misfit


@pytest.fixture(scope="module")
def rec():
    x = G.record(seed=1, n=int(HOURS * 3600 * RATE_HZ), rate_hz=RATE_HZ)
    return x, allan_axis(x, RATE_HZ)


def _interval(adev, edf, p=P_OUT):
    """The interval ADEV's true value lies in with probability 1 − p (χ² with edf degrees)."""
    lo = adev * np.sqrt(edf / stats.chi2.ppf(1 - p / 2, edf))
    hi = adev * np.sqrt(edf / stats.chi2.ppf(p / 2, edf))
    return lo, hi


def model_curve(taus, quantised: bool = False):
    """The model's truth; quantised: plus the rounding of each sample to 1/80 °/s (white,
    σ = LSB/√12 per sample: ADEV² = LSB²/(12·fs·τ), 0.3 % of the white part)."""
    adev = G.model_adev(taus, DS_NOISE_N, DS_BIAS_INSTABILITY, MODEL_K)
    if quantised:
        lsb = U.DEG / 80.0
        adev = np.sqrt(adev ** 2 + lsb ** 2 / 12.0 / (RATE_HZ * np.asarray(taus, float)))
    return adev


def test_bank_floor_is_0664_B():
    """The bank alone (no white noise, no random walk) gives 0.664·B over τ = 20 .. 5000 s
    within the ±2 % the model's header documents, and falls off outside its decades."""
    taus = np.logspace(np.log10(20), np.log10(5000), 60)
    floor = G.model_adev(taus, 0.0, DS_BIAS_INSTABILITY, 0.0) / (0.664 * DS_BIAS_INSTABILITY)
    assert floor.min() > 0.98 and floor.max() < 1.02, (floor.min(), floor.max())
    corr, _w = G.flicker_bank()
    assert list(corr) == [2.0, 20.0, 200.0, 2000.0, 20000.0]
    assert G.model_adev([1e6], 0.0, DS_BIAS_INSTABILITY, 0.0)[0] < 0.3 * 0.664 * DS_BIAS_INSTABILITY


def test_default_truth_is_the_data_sheet():
    """The model's curve (its truth: N, B, K) sits at the data sheet's floor between 100 and
    1000 s: above 0.664·25 °/h by what white noise and the random walk add (at most 6 %)."""
    taus = np.array([100.0, 200.0, 500.0, 1000.0])
    ratio = model_curve(taus) / (0.664 * DS_BIAS_INSTABILITY)
    assert np.all(ratio >= 1.0) and np.all(ratio < 1.06), ratio


def test_recorded_curve_matches_the_model(rec):
    """Every octave τ from 0.1 s to T/8 (14 h): the model's curve lies inside the recorded
    ADEV's 99.9 % interval (equivalent degrees of freedom from imubench.analysis.allan)."""
    _x, r = rec
    taus, adev, edf = (np.array(r[k]) for k in ("taus", "adev", "edf"))
    keep = taus <= HOURS * 3600 / 8
    lo, hi = _interval(adev[keep], edf[keep])
    want = model_curve(taus[keep], quantised=True)
    bad = [(float(t), float(w / DPH), float(a / DPH)) for t, w, a, l_, h in
           zip(taus[keep], want, adev[keep], lo, hi) if not l_ <= w <= h]
    assert not bad, f"(τ s, model °/h, recorded °/h) outside the 99.9 % interval: {bad}"
    print("τ s / recorded °/h / model °/h:",
          [(round(t, 1), round(a / DPH, 2), round(w / DPH, 2)) for t, a, w in zip(taus[keep], adev[keep], want)])


def test_readoffs_match_the_data_sheet(rec):
    """What a user reads off the recording: N at the data sheet's density and B at its in-run
    stability, each within its own 99.9 % uncertainty plus the known offset of the model's
    minimum (white noise and random walk lift it 3.4 % above 0.664·B), and the curve rising
    after its minimum (the rate random walk; how much is test_recorded_curve_matches_the_model's)."""
    _x, r = rec
    z = stats.norm.ppf(1 - P_OUT / 2)
    assert abs(r["N"] / DS_NOISE_N - 1) < z * r["white"]["N_rel_1sigma"] + 0.01, r["N"] / U.DEG
    i_min = int(np.argmin(r["adev"]))
    lo, hi = _interval(r["adev"][i_min], r["edf"][i_min])
    offset = float(model_curve(np.logspace(1, 4, 400)).min() / (0.664 * DS_BIAS_INSTABILITY))
    assert 1.0 < offset < 1.04
    B = r["B"]
    assert 100.0 <= r["B_tau"] <= 2000.0, r["B_tau"]
    assert lo / 0.664 <= DS_BIAS_INSTABILITY * offset <= hi / 0.664, (B / DPH, lo / 0.664 / DPH, hi / 0.664 / DPH)
    taus = np.array(r["taus"])
    last = int(np.searchsorted(taus, HOURS * 3600 / 8, side="right")) - 1
    assert r["adev"][last] > r["adev"][i_min] and last > i_min + 3, "no rise at long τ"
    print(f"N {r['N'] / U.DEG:.4f} °/s/√Hz, B {B / DPH:.1f} °/h at τ {r['B_tau']:.0f} s")


def test_deterministic_per_seed():
    a, b, c = (G.record(seed=s, n=20000) for s in (3, 3, 4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
