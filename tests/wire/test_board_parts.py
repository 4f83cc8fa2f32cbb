"""A board's parts as its device reports them (wire.board_parts, issue 35): the names, the
temperature steps and the operating range every text and check about the board takes, from the
generated parts table, never from a copy."""
from __future__ import annotations

import math

import pytest

from imubench.parts_gen import PARTS
from imubench.wire.board_parts import DEFAULT, BoardParts, any_board_c, coarsest_temp_step_c


def test_the_parts_come_from_the_ids_or_the_names_a_device_reported():
    ids = (PARTS["adxl359"].id, PARTS["adxrs450"].id, PARTS["adxrs450"].id, PARTS["adxrs453"].id)
    by_id = BoardParts.of(ids)
    by_name = BoardParts.of_device({"parts": ["ADXL359", "ADXRS450", "ADXRS450", "ADXRS453"]})
    assert by_id == by_name
    assert by_id.names == ("ADXL359", "ADXRS450", "ADXRS450", "ADXRS453")
    assert by_id.gyro_words == "ADXRS450/ADXRS450/ADXRS453"
    assert by_id.temperatures_text == "ADXL359/gyro X/Y/Z (ADXRS450/ADXRS450/ADXRS453)"
    assert by_id.temperature_names[3] == "gyro Z ADXRS453"
    assert by_id.text == "accelerometer ADXL359, gyros ADXRS450/ADXRS450/ADXRS453"
    # a record from before the parts table (no "parts") and an empty slot: the parts those boards had
    assert BoardParts.of_device({}) == DEFAULT == BoardParts.of((0, 0, 0, 0))
    assert DEFAULT.gyro_words == "ADXRS450" and DEFAULT.accel.name == "ADXL355"


def test_the_constants_are_the_tables():
    d = DEFAULT
    assert d.accel_temp_step_c == pytest.approx(1 / 9.05)            # ADXL355: -9.05 LSB/°C
    assert d.gyro_temp_step_c == pytest.approx(0.2)                  # ADXRS450: 5 LSB/°C
    assert d.temp_step_c == pytest.approx(0.2)
    assert d.operating_c == (-40.0, 105.0)                           # the ADXRS450's end is the lower
    mixed = BoardParts.of(["ADXL359", "ADXRS453", "ADXRS450", "ADXRS450"])
    assert mixed.operating_c == (max(p.t_min_c for p in PARTS.values()), 105.0)
    assert mixed.limiting_part(110.0).name == "ADXRS453" and mixed.limiting_part(25.0) is None
    assert mixed.limiting_part(-41.0).name == "ADXL359"
    assert any_board_c() == (-40.0, 105.0)
    assert coarsest_temp_step_c() == max(1 / abs(p.temp_lsb_per_c) for p in PARTS.values())


def test_the_attitude_filter_is_tuned_to_the_boards_parts():
    """The Kalman tilt filter's noise figures are the parts' (analysis.tilt.part_noise): an ADXL359
    board's accelerometer noise is its 80 µg/√Hz, the default board's the ADXL355's from the table."""
    from imubench.analysis import tilt as T
    g0 = 9.80665
    (k,) = T.make_filters("kalman", parts=BoardParts.of(["ADXL359", "ADXRS450", "ADXRS450", "ADXRS453"]))
    assert k.kw["accel_noise_n"] == pytest.approx(PARTS["adxl359"].noise_per_rthz * g0)
    assert k.kw["gyro_noise_n"] == pytest.approx(PARTS["adxrs453"].noise_per_rthz * math.pi / 180)
    assert T.KalmanTilt().kw["accel_noise_n"] == pytest.approx(PARTS["adxl355"].noise_per_rthz * g0)
