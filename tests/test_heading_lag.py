"""The heading fuser's causal magnetometer-lag estimate against a known lag (synthetic and real data)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magmesh import maths
from services.heading_fuser import profiles
from services.heading_fuser.core import HeadingFilter, MagLagEstimator

RATE_HZ = 285.714  # BROAD's rate
FIELD_ENU_NT = np.array([100.0, 15800.0, -40800.0])


def _attitude(t):
    """A board turned every way (yaw, pitch, roll smooth, up to ~2.5 rad/s): body → ENU."""
    a = np.column_stack([2.0 * np.sin(0.5 * t) + 0.5 * np.sin(2.1 * t), 0.6 * np.sin(0.8 * t + 1) + 0.3 * np.sin(2.7 * t),
                         0.7 * np.sin(0.6 * t + 2) + 0.3 * np.sin(3.3 * t)])
    return Rotation.from_euler("ZYX", a)


def synth(lag_s: float, duration_s: float = 40.0, seed: int = 1, hard_iron_nt=(3000.0, -2000.0, 1500.0)):
    """(t, gyro, accel, mag) with the magnetometer showing the field of t − lag_s, noise of BROAD's size
    (gyro 0.002 rad/s, field 700 nT per axis) and an uncalibrated body-fixed offset."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(duration_s * RATE_HZ)) / RATE_HZ
    h = 1e-5
    gyro = (_attitude(t - h).inv() * _attitude(t + h)).as_rotvec() / (2 * h)
    accel = _attitude(t).inv().apply([0.0, 0.0, maths.G0])
    mag = _attitude(t - lag_s).inv().apply(FIELD_ENU_NT) + np.asarray(hard_iron_nt)
    n = len(t)
    return (t, gyro + rng.normal(0, 0.002, (n, 3)), accel + rng.normal(0, 0.05, (n, 3)),
            mag + rng.normal(0, 700.0, (n, 3)))


@pytest.mark.parametrize("lag_ms", [0.0, 20.0])
def test_the_fuser_estimates_a_known_lag_online_within_3_ms(lag_ms):
    t, gyro, accel, mag = synth(lag_ms / 1000.0)
    f = HeadingFilter(profiles.settings(profiles.IMU_ONLY))
    assert f.settings.mag_delay_online
    estimates = []
    for i in range(len(t)):
        f.update_imu(gyro[i], accel[i], 0.0 if i == 0 else 1.0 / RATE_HZ)
        f.update_mag(mag[i])
        if i % 1000 == 0:
            estimates.append(f.mag_delay_s)
    assert f._lag.n >= f._lag.min_samples  # the estimate is from the pairs, not the 0 it starts with
    assert abs(f.mag_delay_s - lag_ms / 1000.0) < 0.003, (f.mag_delay_s, estimates)
    # causal and settled: the last quarter of the run's estimates all within the bound too
    late = np.array(estimates[-len(estimates) // 4:])
    assert np.all(np.abs(late - lag_ms / 1000.0) < 0.003), late


def test_the_body_fixed_offset_is_solved_for_jointly():
    """A large uncalibrated offset: the lag is still right, and the offset solved with it is the true one."""
    hi = np.array([8000.0, -6000.0, 4000.0])
    t, gyro, _, mag = synth(0.015, duration_s=30.0, seed=2, hard_iron_nt=hi)
    e = MagLagEstimator()
    for i in range(len(t)):
        e.add_gyro(t[i], gyro[i])
        e.add_mag(t[i], mag[i], 0.0)  # no strength check: the offset moves |m| by up to 25 %
    assert abs(e.delay_s - 0.015) < 0.003, e.delay_s
    assert np.linalg.norm(e.offset_nt - hi) < 300.0, e.offset_nt


def test_no_estimate_without_turning():
    e = MagLagEstimator()
    for i in range(3000):
        t = i / RATE_HZ
        e.add_gyro(t, (0.001, -0.002, 0.001))
        e.add_mag(t, FIELD_ENU_NT + np.sin(i) * 50.0, float(np.linalg.norm(FIELD_ENU_NT)))
    assert e.n == 0 and e.delay_s == 0.0


def test_a_real_trial_shifted_by_20_ms_is_estimated_20_ms_later():
    """BROAD trial 07 (fast rotations, CC-BY-4.0): its magnetometer's own lag, then the same trial with
    the magnetometer delayed by a further 20 ms (linear interpolation): the estimates differ by 20 ms."""
    from bench import heading_broad as hb

    trial = hb.load_trial(hb.BROAD_DIR / "07_undisturbed_fast_rotation_B.hdf5").sliced(int(70 * RATE_HZ))
    t = np.arange(len(trial.gyro_rad_s)) / trial.rate_hz
    ref = float(np.linalg.norm(trial.mag_nt[:300].mean(axis=0)))
    got = []
    for shift_s in (0.0, 0.020):
        mag = np.column_stack([np.interp(t - shift_s, t, trial.mag_nt[:, k]) for k in range(3)])
        e = MagLagEstimator()
        for i in range(len(t)):
            e.add_gyro(t[i], trial.gyro_rad_s[i])
            e.add_mag(t[i], mag[i], ref)
        assert e.n >= e.min_samples
        got.append(e.delay_s)
    assert 0.002 < got[0] < 0.03, got  # a lag of its own, well inside the grid (not clipped at 0 or the end)
    assert abs((got[1] - got[0]) - 0.020) < 0.003, got
