"""Pins of the online GNSS-aided hard-iron EKF (services/calibration/online_ekf.py, docs/methods.md).

Every expected value is computed here from the method's definition: the levelled heading
ψ_m = atan2(l_y, l_x) + D with l = Ry(−θ) Rx(φ) M (m − b), one scalar Kalman step
(S = HPHᵀ + R, K = PHᵀ/S, P⁺ = (I − KH)P for the optimal gain), R = σ_ψ² + (σ_v / v)², the innovation
gate z² ≤ g² S, the random-walk prediction P += q² dt I, the starting conditions (fix type, satellites,
PDOP, speed, yaw rate), and which components are observable and applied. Hand-made epochs, no drive
simulation, so the file runs in seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.calibration import online_ekf as oe

ST = oe.EkfSettings()


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _psi(M, m, b, roll, pitch, dec):
    lev = _ry(-pitch) @ _rx(roll) @ (M @ (np.asarray(m) - b))
    return math.atan2(lev[1], lev[0]) + dec, lev


MIX = np.array([[1.04, 0.03, -0.02], [0.03, 0.96, 0.01], [-0.02, 0.01, 1.01]])


# ---- settings and starting conditions ----------------------------------------------------------


def test_settings_are_the_documented_gates_and_are_checked():
    assert (ST.min_speed_m_s, ST.max_yaw_rate_rad_s, ST.min_sats, ST.max_pdop) == (3.0, 0.35, 6, 3.0)
    assert ST.gate_sigma == 3.0 and ST.min_tilt_for_vertical_rad == 0.15 and not ST.estimate_mount_yaw
    for bad in (dict(prior_std_nt=0.0), dict(heading_noise_rad=0.0), dict(gate_sigma=0.0),
                dict(observable_ratio=0.0), dict(observable_ratio=1.0)):
        with pytest.raises(ValueError):
            oe.EkfSettings(**bad)
    oe.EkfSettings(prior_std_nt=1e-3, heading_noise_rad=1e-6, gate_sigma=1e-3, observable_ratio=0.999)


def test_gnss_starting_conditions_at_their_bounds():
    for fix in ("3d", "dgps", "rtk_float", "rtk_fixed"):
        assert oe.gnss_usable(fix, 6, 3.0, 3.0, ST) == (True, "")
    for fix in ("2d", "none", "3D", ""):
        ok, why = oe.gnss_usable(fix, 12, 1.0, 10.0, ST)
        assert not ok and fix in why
    ok, why = oe.gnss_usable("3d", 5, 1.0, 10.0, ST)
    assert not ok and "5 satellites" in why
    ok, why = oe.gnss_usable("3d", 12, 3.01, 10.0, ST)
    assert not ok and "PDOP" in why
    ok, why = oe.gnss_usable("3d", 12, 1.0, 2.99, ST)
    assert not ok and "speed" in why
    strict = oe.EkfSettings(min_sats=9, max_pdop=1.5, min_speed_m_s=8.0)
    assert not oe.gnss_usable("3d", 8, 1.0, 10.0, strict)[0]
    assert not oe.gnss_usable("3d", 9, 1.6, 10.0, strict)[0]
    assert not oe.gnss_usable("3d", 9, 1.5, 7.9, strict)[0]
    assert oe.gnss_usable("3d", 9, 1.5, 8.0, strict)[0]


def test_speed_rate_is_the_least_squares_slope_over_the_window():
    rate = oe.SpeedRate(window_s=1.0)
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 3.0, 0.25)  # exact in binary: the window edge is exact
    v = 5.0 + 0.7 * t + rng.normal(0, 0.05, len(t))
    assert rate.update(t[0], v[0]) == 0.0  # one epoch: no slope
    out = [rate.update(ti, vi) for ti, vi in zip(t[1:], v[1:], strict=True)]
    for k in range(1, len(t)):
        sel = t[: k + 1] >= t[k] - 1.0
        want = np.polyfit(t[: k + 1][sel], v[: k + 1][sel], 1)[0] if sel.sum() >= 2 else 0.0
        assert out[k - 1] == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert len(rate.t) == 5  # t − 1 s ≤ τ ≤ t at 4 Hz: the window edge is kept
    wide = oe.SpeedRate(window_s=2.0)
    for ti, vi in zip(t, v, strict=True):
        wide.update(ti, vi)
    assert len(wide.t) == 9
    same = oe.SpeedRate()
    assert same.update(1.0, 4.0) == 0.0 and same.update(1.0, 6.0) == 0.0  # no time spread: no slope
    assert same.t == [1.0, 1.0]  # an equal time stamp is not the clock going back
    back = oe.SpeedRate()
    back.update(5.0, 1.0)
    back.update(5.2, 2.0)
    assert back.update(1.0, 9.0) == 0.0 and back.t == [1.0] and back.v == [9.0]  # clock went back
    assert oe.SpeedRate().window_s == 1.0


def test_car_roll_pitch_removes_forward_and_centripetal_acceleration():
    roll, pitch = math.radians(4.0), math.radians(-3.0)
    g = 9.81 * np.array([math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)])
    a_fwd, v, r = 1.3, 12.0, 0.2
    got = oe.car_roll_pitch(g + np.array([a_fwd, v * r, 0.0]), a_fwd, v, r)
    assert got[0] == pytest.approx(roll, abs=1e-9) and got[1] == pytest.approx(pitch, abs=1e-9)
    acc = [0.1, 0.2, 9.8]
    keep = np.array(acc)
    assert oe.car_roll_pitch(acc) == pytest.approx((math.atan2(0.2, 9.8), math.atan2(0.1, math.hypot(0.2, 9.8))))
    np.testing.assert_array_equal(acc, keep)
    assert all(isinstance(x, float) for x in got)
    # centripetal = speed × yaw rate: either one alone removes nothing sideways
    flat = np.array([0.0, 1.0, 9.8])
    assert oe.car_roll_pitch(flat, 0.0, 10.0) == pytest.approx(oe.car_roll_pitch(flat))
    assert oe.car_roll_pitch(flat, 0.0, yaw_rate_rad_s=0.3) == pytest.approx(oe.car_roll_pitch(flat))
    # integer readings are accepted (the correction is applied in floating point)
    assert oe.car_roll_pitch([1, 0, 10], 0.5) == pytest.approx(oe.car_roll_pitch([1.0, 0.0, 10.0], 0.5))


# ---- the model ----------------------------------------------------------------------------------


def test_heading_is_the_levelled_compensated_field_plus_declination():
    ekf = oe.HardIronEkf(matrix=MIX)
    m = np.array([-12000.0, 21000.0, -38000.0])
    b = np.array([900.0, -400.0, 1200.0])
    for roll, pitch, dec in ((0.0, 0.0, 0.0), (0.08, -0.05, 0.2), (-0.1, 0.12, -0.3)):
        psi, lev, R = ekf.heading(m, b, roll, pitch, dec)
        want, lev_ref = _psi(MIX, m, b, roll, pitch, dec)
        assert psi == pytest.approx(want % (2 * math.pi), abs=1e-12) and 0.0 <= psi < 2 * math.pi
        np.testing.assert_allclose(lev, lev_ref, rtol=1e-12)
        np.testing.assert_allclose(R, _ry(-pitch) @ _rx(roll), atol=1e-15)
    assert oe.HardIronEkf().M.tolist() == np.eye(3).tolist()
    np.testing.assert_array_equal(oe.HardIronEkf(matrix=MIX.ravel().tolist()).M, MIX)


def test_jacobian_is_the_three_partials_and_ignores_vertical_level():
    ekf = oe.HardIronEkf(matrix=MIX)
    lev = np.array([3000.0, -4000.0, 50000.0])
    R = _ry(0.1) @ _rx(0.05)
    H = ekf.jacobian(lev, R)
    want = -(np.array([4000.0, 3000.0, 0.0]) / 25e6) @ R @ MIX
    np.testing.assert_allclose(H, want, rtol=1e-12)
    # a vanishing horizontal field does not divide by zero
    assert np.all(np.isfinite(ekf.jacobian(np.array([0.0, 0.0, 1.0]), R)))


# ---- one epoch ----------------------------------------------------------------------------------

M_NT = np.array([20000.0, 6000.0, -40000.0])


def _epoch(ekf, t, course, m=M_NT, **kw):
    kw.setdefault("speed_m_s", 10.0)
    return ekf.update(t, m, course, **kw)


def test_one_update_is_the_scalar_kalman_step():
    st = oe.EkfSettings()
    x0 = np.array([500.0, -300.0, 200.0])
    ekf = oe.HardIronEkf(st, offset0_nt=x0, matrix=MIX)
    roll, pitch, dec, v = 0.03, -0.02, 0.1, 7.0
    psi, lev = _psi(MIX, M_NT, x0, roll, pitch, dec)
    course = psi + math.radians(2.0)
    assert ekf.update(0.0, M_NT, course, roll, pitch, dec, speed_m_s=v)
    H = -(np.array([-lev[1], lev[0], 0.0]) / (lev[0] ** 2 + lev[1] ** 2)) @ _ry(-pitch) @ _rx(roll) @ MIX
    H[2] = 0.0  # b_z is not estimated before the tilt excites it
    P = np.eye(3) * st.prior_std_nt**2
    r = st.heading_noise_rad**2 + (st.gnss_vel_std_m_s / v) ** 2
    S = H @ P @ H + r
    K = P @ H / S
    z = math.radians(2.0)
    np.testing.assert_allclose(ekf.x, x0 + K * z, rtol=1e-9)
    np.testing.assert_allclose(ekf.P, (np.eye(3) - np.outer(K, H)) @ P, rtol=1e-9, atol=1e-6)
    assert ekf.x[2] == x0[2] and ekf.P[2, 2] == P[2, 2]  # the unexcited vertical keeps its prior
    assert ekf.innovation_rad == pytest.approx(z, abs=1e-12) and ekf.innovation_var_rad2 == pytest.approx(S)
    assert ekf.test_ratio == pytest.approx(z * z / (9.0 * S))
    assert ekf.n_fused == 1 and ekf.fused and ekf.n_rejected == 0 and ekf.n_skipped == 0
    assert ekf.tilt_sq_sum == pytest.approx(roll**2 + pitch**2)
    # the innovation wraps: a course 2π away is the same measurement
    other = oe.HardIronEkf(st, offset0_nt=x0, matrix=MIX)
    other.update(0.0, M_NT, course + 2 * math.pi, roll, pitch, dec, speed_m_s=v)
    np.testing.assert_allclose(other.x, ekf.x, rtol=1e-9)
    # a slow vehicle's course is noisier: R grows as (σ_v / v)², the step shrinks
    slow = oe.HardIronEkf(oe.EkfSettings(min_speed_m_s=0.05, gnss_vel_std_m_s=0.5), offset0_nt=x0, matrix=MIX)
    slow.update(0.0, M_NT, course, roll, pitch, dec, speed_m_s=0.05)
    r_slow = st.heading_noise_rad**2 + (0.5 / 0.1) ** 2  # speed floored at 0.1 m/s
    assert slow.innovation_var_rad2 == pytest.approx(H @ P @ H + r_slow)


def test_the_gate_rejects_beyond_gate_sigma_standard_deviations():
    psi, _ = _psi(np.eye(3), M_NT, np.zeros(3), 0.0, 0.0, 0.0)
    probe = oe.HardIronEkf()
    _epoch(probe, 0.0, psi)
    sd = math.sqrt(probe.innovation_var_rad2)
    inside, outside = oe.HardIronEkf(), oe.HardIronEkf()
    assert _epoch(inside, 0.0, psi + 2.9 * sd)
    assert not _epoch(outside, 0.0, psi + 3.1 * sd)
    assert outside.n_rejected == 1 and outside.n_fused == 0 and not outside.fused
    assert outside.test_ratio == pytest.approx(3.1**2 / 9.0, rel=1e-6)
    np.testing.assert_array_equal(outside.x, np.zeros(3))
    wide = oe.HardIronEkf(oe.EkfSettings(gate_sigma=4.0))
    assert _epoch(wide, 0.0, psi + 3.1 * sd)


def test_epochs_without_a_usable_course_are_skipped_and_counted():
    ekf = oe.HardIronEkf()
    assert not _epoch(ekf, 0.0, None)
    assert ekf.skip_reason == "no usable GNSS course"
    assert not _epoch(ekf, 0.1, 1.0, gnss_ok=False)
    assert not _epoch(ekf, 0.2, 1.0, speed_m_s=2.99)
    assert "speed" in ekf.skip_reason
    assert _epoch(ekf, 0.3, ekf.heading(M_NT, ekf.x, 0.0, 0.0, 0.0)[0], speed_m_s=3.0)
    assert not _epoch(ekf, 0.4, 1.0, yaw_rate_rad_s=-0.36)
    assert "turning" in ekf.skip_reason
    assert _epoch(ekf, 0.5, ekf.heading(M_NT, ekf.x, 0.0, 0.0, 0.0)[0], yaw_rate_rad_s=0.35)
    assert (ekf.n_skipped, ekf.n_fused, ekf.n_rejected) == (4, 2, 0)
    assert ekf.fused  # the last epoch (0.35 rad/s, at the bound) was fused


def test_prediction_adds_the_random_walk_and_ignores_a_clock_going_back():
    st = oe.EkfSettings(random_walk_nt_sqrt_s=40.0)
    ekf = oe.HardIronEkf(st)
    P0 = ekf.P.copy()
    ekf.predict(10.0)
    np.testing.assert_array_equal(ekf.P, P0)  # first epoch: nothing to integrate
    ekf.predict(12.5)
    np.testing.assert_allclose(ekf.P, P0 + np.eye(3) * 40.0**2 * 2.5)
    ekf.predict(11.0)  # back in time: no growth, the clock restarts from here
    np.testing.assert_allclose(ekf.P, P0 + np.eye(3) * 40.0**2 * 2.5)
    ekf.predict(12.0)
    np.testing.assert_allclose(ekf.P, P0 + np.eye(3) * 40.0**2 * 3.5)
    assert ekf.t_last == 12.0
    four = oe.HardIronEkf(oe.EkfSettings(estimate_mount_yaw=True))
    q0 = four.P[3, 3]
    four.predict(0.0)
    four.predict(5.0)
    assert four.P[3, 3] == q0  # the mounting yaw is a constant


# ---- the vertical component, observability, outputs ---------------------------------------------


TRUE_OFFSET = np.array([800.0, -600.0, 400.0])


def _drive(ekf, n, roll=0.0, pitch=0.0, truth=TRUE_OFFSET, t0=0.0):
    """Epochs whose course is the heading the true offset gives, over a full turn of the field."""
    fused = 0
    for k in range(n):
        yaw = 2 * math.pi * k / n
        h = _rz(-yaw) @ np.array([22000.0, 0.0, -40000.0])
        m = np.linalg.solve(_ry(-pitch) @ _rx(roll), h) + truth
        course = ekf.heading(m, truth, roll, pitch, 0.0)[0]
        fused += ekf.update(t0 + k, m, course, roll, pitch, 0.0, speed_m_s=10.0)
    return fused


def test_b_z_waits_for_ten_fused_epochs_of_enough_tilt():
    flat = oe.HardIronEkf()
    _drive(flat, 40, roll=0.05, pitch=0.05)
    assert flat.n_fused == 40 and not flat.vertical_excited
    assert flat.tilt_rms_rad == pytest.approx(math.hypot(0.05, 0.05))
    # b_z keeps its prior: no update, only the random walk of 39 one-second predictions
    assert flat.x[2] == 0.0 and flat.P[2, 2] == pytest.approx(ST.prior_std_nt**2 + ST.random_walk_nt_sqrt_s**2 * 39)
    assert flat.observable == (True, True, False)
    np.testing.assert_array_equal(flat.applied_offset()[2], 0.0)
    tilted = oe.HardIronEkf()
    _drive(tilted, 9, roll=0.12, pitch=0.1)
    assert tilted.tilt_rms_rad >= ST.min_tilt_for_vertical_rad and not tilted.vertical_excited  # 9 < 10
    _drive(tilted, 1, roll=0.12, pitch=0.1, t0=9.0)
    assert tilted.n_fused == 10 and tilted.vertical_excited
    _drive(tilted, 200, roll=0.12, pitch=0.1, t0=10.0)
    assert tilted.P[2, 2] < ST.prior_std_nt**2 and tilted.x[2] != 0.0
    low = oe.HardIronEkf(oe.EkfSettings(min_tilt_for_vertical_rad=0.05))
    _drive(low, 10, roll=0.04, pitch=0.031)
    assert low.tilt_rms_rad == pytest.approx(math.hypot(0.04, 0.031)) and low.vertical_excited
    assert oe.HardIronEkf().tilt_rms_rad == 0.0


def test_observable_converged_and_applied_offset():
    ekf = oe.HardIronEkf(offset0_nt=(100.0, 200.0, 300.0))
    assert ekf.observable == (False, False, False) and not ekf.converged
    np.testing.assert_array_equal(ekf.applied_offset(), [100.0, 200.0, 300.0])
    _drive(ekf, 120)
    std = ekf.std_nt
    np.testing.assert_allclose(std, np.sqrt(np.diag(ekf.P)))
    assert ekf.observable == tuple(bool(s < 0.3 * ST.prior_std_nt) for s in std[:2]) + (False,)
    assert ekf.observable == (True, True, False)
    assert ekf.converged == bool(np.all(std[:2] < ST.converged_std_nt))
    app = ekf.applied_offset()
    np.testing.assert_array_equal(app, [ekf.x[0], ekf.x[1], 300.0])
    assert np.linalg.norm(app[:2] - [800.0, -600.0]) < 50.0  # the true horizontal offset is found
    tight = oe.HardIronEkf(oe.EkfSettings(converged_std_nt=1.0), offset0_nt=(100.0, 200.0, 300.0))
    _drive(tight, 120)
    assert tight.observable == (True, True, False) and not tight.converged
    strict = oe.HardIronEkf(oe.EkfSettings(observable_ratio=1e-4))
    _drive(strict, 120)
    assert strict.observable == (False, False, False) and not strict.converged


def test_internal_states_and_flags_report_the_filter():
    ekf = oe.HardIronEkf()
    _drive(ekf, 30)
    _epoch(ekf, 31.0, None)
    s, f = ekf.internal_states, ekf.flags
    assert s["offset_nt"] == [float(v) for v in ekf.x] and s["offset_std_nt"] == [float(v) for v in ekf.std_nt]
    assert (s["n_fused"], s["n_rejected"], s["n_skipped"]) == (30, 0, 1)
    assert s["innovation_rad"] == ekf.innovation_rad and s["innovation_var_rad2"] == ekf.innovation_var_rad2
    assert s["test_ratio"] == ekf.test_ratio and s["tilt_rms_rad"] == 0.0
    assert s["mount_yaw_rad"] == 0.0 and s["mount_yaw_std_rad"] == 0.0
    assert f == {"converged": ekf.converged, "observable": [True, True, False], "fused": False}
    ekf.reset()
    assert ekf.n_fused == 0 and ekf.t_last is None and ekf.innovation_rad is None and ekf.test_ratio is None
    assert ekf.tilt_sq_sum == 0.0 and ekf.skip_reason == "" and ekf.P[0, 0] == ST.prior_std_nt**2
    np.testing.assert_array_equal(ekf.x, np.zeros(3))
    ekf.reset((1.0, 2.0, 3.0))
    np.testing.assert_array_equal(ekf.x, [1.0, 2.0, 3.0])
    ekf.reset()
    np.testing.assert_array_equal(ekf.prior, [1.0, 2.0, 3.0])  # reset() keeps the last prior


def test_mount_yaw_state_is_a_heading_bias_with_unit_jacobian():
    st = oe.EkfSettings(estimate_mount_yaw=True)
    ekf = oe.HardIronEkf(st)
    assert ekf.n == 4 and ekf.P.shape == (4, 4) and ekf.P[3, 3] == pytest.approx(math.radians(3.0) ** 2)
    psi = ekf.heading(M_NT, ekf.x, 0.0, 0.0, 0.0)[0]
    bias = math.radians(1.0)
    _epoch(ekf, 0.0, psi + bias)
    # hand-made step: H = [H_b, 0 (b_z), 1], z = course − ψ − δψ̂
    _, lev = _psi(np.eye(3), M_NT, np.zeros(3), 0.0, 0.0, 0.0)
    Hb = -(np.array([-lev[1], lev[0], 0.0]) / (lev[0] ** 2 + lev[1] ** 2))
    H = np.r_[Hb[:2], 0.0, 1.0]
    P = np.diag([st.prior_std_nt**2] * 3 + [st.mount_yaw_prior_std_rad**2])
    r = st.heading_noise_rad**2 + (st.gnss_vel_std_m_s / 10.0) ** 2
    K = P @ H / (H @ P @ H + r)
    np.testing.assert_allclose(ekf.xs, K * bias, rtol=1e-9, atol=1e-12)
    assert ekf.mount_yaw_rad == pytest.approx(K[3] * bias) and ekf.mount_yaw_std_rad == pytest.approx(
        math.sqrt(ekf.P[3, 3]))
    # the estimated bias enters the next innovation
    z_next = (psi + bias) - ekf.heading(M_NT, ekf.x, 0.0, 0.0, 0.0)[0] - ekf.mount_yaw_rad
    _epoch(ekf, 1.0, psi + bias)
    assert ekf.innovation_rad == pytest.approx(z_next, abs=1e-9)
    # δψ applied only once known to better than 0.3°
    assert not ekf.mount_yaw_observable
    np.testing.assert_array_equal(ekf.applied_matrix(), np.eye(3))
    ekf.P[3, 3] = math.radians(0.29) ** 2
    assert ekf.mount_yaw_observable
    np.testing.assert_allclose(ekf.applied_matrix(), _rz(ekf.mount_yaw_rad), atol=1e-15)
    three = oe.HardIronEkf(matrix=MIX)
    assert not three.mount_yaw_observable and three.mount_yaw_rad == 0.0 and three.mount_yaw_std_rad == 0.0
    np.testing.assert_array_equal(three.applied_matrix(), MIX)
    am = three.applied_matrix()
    am[0, 0] = 9.0
    assert three.M[0, 0] == MIX[0, 0]  # a copy, not the filter's own matrix
