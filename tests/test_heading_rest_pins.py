"""Pins of the heading fuser's rest and gravity steps (services/heading_fuser/core.py), the settings a handheld
board's profile turns on:

- Rest: the low-passed rate (less the bias estimate) and the accelerometer's deviation from its low-pass both
  below their limits for ``rest_min_s``; any rotation or a tap ends it at once, and it needs ``rest_min_s``
  again. While at rest the per-sample gyro and accelerometer noise variances are learned.
- The zero-rate update at rest observes the gyro bias on every axis: the vertical axis too, which gravity
  cannot observe; without rest detection that bias stays unknown.
- The gravity low-pass: a horizontal shake of the accelerometer averages out, so the tilt stays near level
  where the raw accelerometer would tilt the filter.
- A calibration change re-bases the field reference from the next steady window.
"""

from __future__ import annotations

import math

import numpy as np

from magmesh import maths
from services.heading_fuser import core

DT = 0.01
LEVEL = np.array([0.0, 0.0, maths.G0])
FIELD = np.array([0.0, 20000.0, -40000.0])  # level sensor facing north, dip about 63°


def _filter(**kw) -> core.HeadingFilter:
    f = core.HeadingFilter(core.Settings(init_duration_s=0.0, **kw))
    f.align(LEVEL, FIELD)
    assert f.aligned
    return f


def _rest(f: core.HeadingFilter, seconds: float, rng, gyro_bias=(0.0, 0.0, 0.0), gyro_sd=0.002, acc_sd=0.02) -> list:
    states = []
    for _ in range(int(round(seconds / DT))):
        f.update_imu(np.asarray(gyro_bias) + rng.normal(0, gyro_sd, 3), LEVEL + rng.normal(0, acc_sd, 3), DT)
        states.append(f.at_rest)
    return states


def test_rest_needs_its_minimum_time_and_ends_with_a_rotation_or_a_tap():
    rng = np.random.default_rng(1)
    f = _filter(rest_detection=True, rest_min_s=1.5)
    states = _rest(f, 3.0, rng)
    assert not any(states[:140]) and all(states[160:]), (states.index(True) if True in states else None)
    for _ in range(50):  # 0.5 s turning at 0.3 rad/s about up
        f.update_imu((0.0, 0.0, 0.3), LEVEL, DT)
    assert not f.at_rest
    states = _rest(f, 3.0, rng)
    first = states.index(True)
    assert 1.5 <= first * DT <= 2.5, first  # the low-pass settles, then rest_min_s again
    f.update_imu((0.0, 0.0, 0.0), LEVEL + np.array([3.0, 0.0, 0.0]), DT)  # a tap: 3 m/s² for one sample
    assert not f.at_rest
    g = _filter(rest_detection=True, rest_min_s=1.5, rest_accel_m_s2=0.5)
    _rest(g, 3.0, rng)
    g.update_imu((0.0, 0.0, 0.0), LEVEL + np.array([0.3, 0.0, 0.0]), DT)  # below the accelerometer limit
    assert g.at_rest


def test_rest_learns_the_sensor_noise():
    rng = np.random.default_rng(2)
    f = _filter(rest_detection=True, rest_gyro_noise_rad_s=0.01, rest_accel_noise_m_s2=0.2)  # priors far off
    _rest(f, 60.0, rng, gyro_sd=0.002, acc_sd=0.03)  # averaged over ~10 s: the priors' share is e^-5.85
    assert 0.9 < math.sqrt(f._noise_gyro_var) / 0.002 < 1.1, math.sqrt(f._noise_gyro_var)
    assert 0.9 < math.sqrt(f._noise_acc_var) / 0.03 < 1.1, math.sqrt(f._noise_acc_var)
    g = _filter(rest_detection=False, rest_gyro_noise_rad_s=0.01)
    _rest(g, 5.0, rng)
    assert math.isclose(math.sqrt(g._noise_gyro_var), 0.01)  # learned only at rest


def test_zero_rate_at_rest_learns_the_vertical_gyro_bias():
    bias = (0.004, -0.003, 0.006)  # rad/s
    rng = np.random.default_rng(3)
    f = _filter(rest_detection=True)
    h0 = f.heading_rad()
    _rest(f, 30.0, rng, gyro_bias=bias)
    assert np.allclose(f.bias, bias, atol=5e-4), f.bias
    g = _filter(rest_detection=False)  # gravity alone: the horizontal bias, never the vertical one
    _rest(g, 30.0, np.random.default_rng(3), gyro_bias=bias)
    assert abs(g.bias[2] - bias[2]) > 3e-3, g.bias
    # at rest the heading holds: the vertical bias is not integrated into it
    assert abs(math.remainder(f.heading_rad() - g.heading_rad(), 2 * math.pi)) > math.radians(3.0)
    assert abs(math.remainder(f.heading_rad() - h0, 2 * math.pi)) < math.radians(3.0), math.degrees(f.heading_rad())


def _shake(f: core.HeadingFilter, seconds: float) -> float:
    """A horizontal shake (±4 m/s² at 1 Hz along x, no rotation); returns the largest tilt seen, rad."""
    worst = 0.0
    for i in range(int(round(seconds / DT))):
        a = LEVEL + np.array([4.0 * math.sin(2 * math.pi * 1.0 * i * DT), 0.0, 0.0])
        f.update_imu((0.0, 0.0, 0.0), a, DT)
        _, pitch, roll = f.euler()
        worst = max(worst, abs(pitch), abs(roll))
    return worst


def test_gravity_low_pass_keeps_the_tilt_under_a_shake():
    raw = _shake(_filter(accel_noise_m_s2=0.3, accel_rejection_m_s2=5.0), 10.0)
    # what is left of the shake after the low-pass: about 4 / (2π · 1 Hz · τ) m/s², 0.13 m/s² (0.75°) for τ = 5 s
    lpf = _shake(_filter(accel_noise_m_s2=0.3, accel_rejection_m_s2=5.0, gravity_lpf_tau_s=5.0), 10.0)
    assert raw > math.radians(3.0), math.degrees(raw)  # the raw accelerometer is taken for tilt
    assert lpf < math.radians(1.5) and lpf < raw / 4, (math.degrees(lpf), math.degrees(raw))


def test_a_calibration_change_rebases_the_field_reference():
    f = _filter()
    ref = f.ref_field_nt
    assert math.isclose(ref, float(np.linalg.norm(FIELD)), rel_tol=1e-6)
    new = FIELD * 1.3  # the same direction, 30 % stronger after a new calibration
    f.rebase_field_reference()
    n0 = f.n_rebases
    for _ in range(600):
        f.update_imu((0.0, 0.0, 0.0), LEVEL, DT)
        f.update_mag(new)
    assert f.n_rebases == n0 + 1 and math.isclose(f.ref_field_nt, float(np.linalg.norm(new)), rel_tol=0.01)
    assert f.mode == "magnetic"
    g = _filter()  # without the re-base the stronger field is off the reference: the magnetometer is not trusted
    for _ in range(600):
        g.update_imu((0.0, 0.0, 0.0), LEVEL, DT)
        g.update_mag(new)
    assert g.mode != "magnetic" and math.isclose(g.ref_field_nt, ref)
