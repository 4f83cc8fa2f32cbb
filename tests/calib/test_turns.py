"""Known-angle turns (imubench.calib.turns): the fit, its uncertainty against simulated hand
errors, observability, detection and combination with another fit."""
from __future__ import annotations

import math

import numpy as np
import pytest

from imubench.calib import NotObservable, TriadFit
from imubench.calib.turns import Turn, combine_fits, detect_turns, known_angle_turns, split_by_rotation


def _turn(m_true, up, angle_deg, rng, angle_sigma_deg=1.0, axis_sigma_deg=0.5, dur=4.0, bias_sigma=1e-4):
    """A turn's integral as a hand makes it: angle and axis off by the declared sigmas."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    tilt = rng.normal(0, math.radians(axis_sigma_deg), 3)
    tilt -= (tilt @ up) * up
    axis = up + tilt
    axis /= np.linalg.norm(axis)
    theta = math.radians(angle_deg) + rng.normal(0, math.radians(angle_sigma_deg))
    s = m_true @ (theta * axis) + rng.normal(0, bias_sigma * dur, 3)
    return Turn(start=0, stop=int(dur * 100), rest_before=0, rest_after=1, up=up, integral_rad=s,
                integration_err_rad=np.zeros(3), bias_rad_s=np.zeros(3), bias_sigma_rad_s=np.full(3, bias_sigma),
                duration_s=dur, angle_rad=math.copysign(math.radians(abs(angle_deg)), angle_deg), label="t")


M_TRUE = np.array([[1.02, 0.004, -0.006], [0.003, 0.985, 0.008], [-0.01, 0.005, 1.003]])


def test_three_turns_recover_m_within_their_sigmas_over_many_hand_errors():
    """The declared error budget is honest: with hand errors drawn from it, the normalised
    errors of M have unit spread (Monte Carlo over 300 sessions of three turns)."""
    rng = np.random.default_rng(3)
    z = []
    for _ in range(300):
        turns = [_turn(M_TRUE, e, 360.0, rng) for e in np.eye(3)]
        fit = known_angle_turns(turns)
        z.append(((fit.m - M_TRUE) / fit.sigma_m).ravel())
        assert fit.dof == 0 and "cannot check the fit" in fit.extra["warnings"][0]
    z = np.array(z)
    assert 0.8 < z.std() < 1.2, z.std(axis=0)
    assert abs(z.mean()) < 0.1


def test_more_turns_overdetermine_and_scale_by_chi2():
    rng = np.random.default_rng(4)
    turns = [_turn(M_TRUE, e, a, rng) for e in np.eye(3) for a in (360.0, -360.0)]
    fit = known_angle_turns(turns)
    assert fit.dof == 9
    assert np.all(np.abs(fit.m - M_TRUE) < 4 * fit.sigma_m)
    assert math.isfinite(fit.extra["chi2_red"])
    # the table reports each turn before and after
    row = fit.extra["turns"][0]
    assert row["known_deg"] == 360.0 and abs(row["after_deg"] - 360.0) < 3.0


def test_two_axes_only_is_refused_naming_the_missing_axis():
    rng = np.random.default_rng(5)
    turns = [_turn(M_TRUE, e, 360.0, rng) for e in np.eye(3)[:2]] * 2
    with pytest.raises(NotObservable, match="near board Z"):
        known_angle_turns(turns)


def test_unusable_turns_are_left_out_and_named():
    rng = np.random.default_rng(6)
    turns = [_turn(M_TRUE, e, 360.0, rng) for e in np.eye(3)]
    turns[2].usable = False
    turns[2].reason = "a gap inside it"
    with pytest.raises(NotObservable, match="a gap inside it"):
        known_angle_turns(turns)


def _synthetic_rest_turn_rest(fs=100.0, up=(0, 0, 1), deg=360.0, gap=None):
    n_rest, n_turn = 300, 400
    t = (np.arange(n_turn) + 0.5) / n_turn
    rate = math.radians(deg) / (n_turn / fs) * (1 - np.cos(2 * np.pi * t))
    up = np.asarray(up, float)
    gyr = np.concatenate([np.zeros((n_rest, 3)), rate[:, None] * up, np.zeros((n_rest, 3))])
    acc = np.repeat(up[None, :] * 9.80665, len(gyr), 0) + np.random.default_rng(0).normal(0, 1e-3, (len(gyr), 3))
    return acc, gyr


def test_detect_turns_finds_the_turn_and_refuses_it_over_a_gap():
    from imubench.calib.static import detect_static
    fs = 100.0
    acc, gyr = _synthetic_rest_turn_rest(fs)
    iv = split_by_rotation(acc, gyr, fs, detect_static(acc, fs))
    assert len(iv) == 2                       # the accelerometer alone sees one long rest
    up = np.array([i.mean for i in iv])
    turns = detect_turns(gyr, fs, iv, up)
    assert len(turns) == 1 and turns[0].usable
    assert abs(math.degrees(turns[0].measured_rad) - 360.0) < 0.5
    turns = detect_turns(gyr, fs, iv, up, breaks=[500])
    assert not turns[0].usable and "not continuous" in turns[0].reason
    turns = detect_turns(gyr, fs, iv, up, clip_rad_s=math.radians(100))
    assert not turns[0].usable and "clipped" in turns[0].reason
    # half a turn is not a known-angle turn
    acc, gyr = _synthetic_rest_turn_rest(fs, deg=170.0)
    iv = split_by_rotation(acc, gyr, fs, detect_static(acc, fs))
    assert detect_turns(gyr, fs, iv, np.array([i.mean for i in iv])) == []


def test_combine_fits_weights_by_covariance_and_flags_disagreement():
    cov_a = np.full((12, 12), np.nan)
    cov_a[:9, :9] = np.eye(9) * 1e-6
    cov_a[9:, 9:] = np.eye(3) * 1e-8
    cov_b = np.full((12, 12), np.nan)
    cov_b[:9, :9] = np.eye(9) * 4e-6
    a = TriadFit("turns", np.eye(3), np.zeros(3), cov_a)
    b = TriadFit("rotation", np.eye(3) + 0.001, np.zeros(3), cov_b)
    c = combine_fits(a, b)
    assert c.consistent
    assert np.allclose(c.fit.m, np.eye(3) + 0.001 * 0.2)          # weights 4:1
    assert np.allclose(c.fit.sigma_m, math.sqrt(0.8e-6))
    far = TriadFit("rotation", np.eye(3) + 0.05, np.zeros(3), cov_b)
    c = combine_fits(a, far)
    assert not c.consistent and "disagree" in c.notes[0]
    assert c.fit.method == "turns+rotation"
