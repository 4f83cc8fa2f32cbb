"""Estimates are printed to the precision their uncertainty allows (results.numbers: two
significant digits of sigma, the value to the same place), and a parameter the model holds
fixed says so instead of showing a meaningless 1.0000000."""
from __future__ import annotations

import pytest

from imubench.results.calibration import params_table
from imubench.results.numbers import pm, round_pair, value


@pytest.mark.parametrize("v,s,unit,text", [
    (3320.3, 25862.3, "ppm", "+3000 ± 26000 ppm"),          # seen on main: "+3320.3 ± 25862.3 ppm"
    (-8.218282, 0.00625, "mg", "-8.2183 ± 0.0063 mg"),
    (1.007256, 0.0000104, "", "+1.007256 ± 0.000010"),
    (0.0123, 0.0995, "", "+0.01 ± 0.10"),                   # sigma rounds up to the next decade
    (-0.00001, 0.003, "mg", "+0.0000 ± 0.0030 mg"),          # no "-0.0000"
    (123.456, 7.0, "s", "+123.5 ± 7.0 s"),
])
def test_pm_rounds_to_two_digits_of_sigma(v, s, unit, text):
    assert pm(v, s, unit) == text


def test_not_estimated_and_missing():
    assert pm(1.0, 0.0) == "not estimated"
    assert pm(1.0, None) == "not estimated"
    assert pm(None, 0.1) == "–" and pm(float("nan"), 0.1) == "–"
    assert round_pair(-2.5, 0.05) == ("-2.500", "0.050")
    assert value(0.1234567, 0.0021) == "+0.1235"


def test_params_table_precision_and_fixed_entries():
    result = {
        "accel": {"method": "multi_position", "m": [[1.0072633, 0.0, 0.0], [-0.00212, 1.0034612, 0.0],
                                                     [0.00252, 0.00549, 0.9935573]],
                  "sigma_m": [[8.3e-6, 0.0, 0.0], [3.5e-4, 8.5e-6, 0.0], [1.9e-4, 1.6e-4, 8.2e-6]],
                  "b_mps2": [-0.0806, -0.2227, -0.1638], "sigma_b_mps2": [5.3e-5, 5.5e-5, 5.3e-5]},
        "gyro": {"method": "bias", "m": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "sigma_m": [[0] * 3] * 3,
                 "b_rad_s": [0.00044, -0.0083, 0.0036], "sigma_b_rad_s": [9.9e-5, 1.4e-4, 1.3e-4]}}
    text = params_table(result)
    assert "+1.0072633 ± 0.0000083" in text and "-0.00212 ± 0.00035" in text
    assert "+0 (fixed)" in text                      # the multi-position model's upper triangle
    assert "identity (not estimated" in text         # a bias-only gyro fit estimates no M
    assert "x -8.2189 ± 0.0054 mg" in text
    assert "1.0000000" not in text and "±0." not in text
