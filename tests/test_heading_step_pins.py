"""Pins of each IMU-side step of the heading fuser's reference filter (services/heading_fuser/core.py) against
references computed here independently (scipy's rotations, explicit matrices), one step at a time on a hand-set
state, so that a one-line change to a step changes a number checked here:

- the quaternion helpers (exponential, product, rotation matrix, skew) against scipy's rotations;
- prediction: q ⊗ exp((ω − b) T) for the estimate and the gyro-only attitude, the integrated nav-frame yaw, and
  P ← F P Fᵀ + Q with F = [[I − [(ω − b) T]×, −T I], [0, I]] and Q from the gyro noise, its rate-proportional part
  and the bias walk;
- the error injection q ⊗ exp(δθ), b + δb;
- the accelerometer update: z = a/|a| against Rᵀ e_up, H = [[g]×, 0], σ = (σ_a + 2 ||a| − g| + k |ω|) / g, the
  heading row of the gain removed, Joseph-form covariance; the rejection limits, the update period;
- update_imu's orchestration (clock, history, the rate it hands on, the heading σ and the uncertainty flag);
- alignment from averaged accelerometer and field (with a body turning during the averaging, and declination);
- the outputs (heading, Euler angles, attitude σ) and the settings' checks.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from heading_refmaths import cross_mat, qof, rexp, rmat
from scipy.spatial.transform import Rotation

from magmesh import maths
from services.heading_fuser import core

G = maths.G0
LEVEL = (0.0, 0.0, G)
FIELD = np.array([0.0, 20000.0, -40000.0])  # level sensor facing north, dip ≈ 63°


def random_state(f: core.HeadingFilter, seed: int) -> None:
    """A tilted, turned attitude, a different gyro-only attitude, a bias and a full covariance."""
    rng = np.random.default_rng(seed)
    f.q = qof(Rotation.from_euler("ZYX", rng.uniform(-0.6, 0.6, 3)).as_matrix())
    f._qg = qof(Rotation.from_euler("ZYX", rng.uniform(-0.6, 0.6, 3)).as_matrix())
    f.bias = rng.normal(0.0, 0.01, 3)
    A = rng.normal(0.0, 1.0, (6, 6)) * np.array([0.05, 0.05, 0.1, 0.01, 0.01, 0.01])[:, None]
    f.P = A @ A.T + np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])


def ref_predict(q, qg, bias, P, yaw, gyro, dt, s: core.Settings):
    w = np.asarray(gyro, float) - bias
    E = rexp(w * dt)
    Rq, Rg = rmat(q) @ E, rmat(qg) @ E
    yaw = yaw + float(Rq[2] @ w) * dt
    F = np.eye(6)
    F[:3, :3] = np.eye(3) - cross_mat(w * dt)
    F[:3, 3:] = -dt * np.eye(3)
    qgyro = (s.gyro_noise_rad_s_rt_hz**2 + s.gyro_rate_noise_frac_rt_hz**2 * float(w @ w)) * dt
    qbias = s.gyro_bias_walk_rad_s2_rt_hz**2 * dt
    P = F @ P @ F.T + np.diag([qgyro] * 3 + [qbias] * 3)
    return Rq, Rg, yaw, P


def ref_accel(Rq, bias, P, accel, rate, s: core.Settings, noise=None):
    """(R, bias, P) after the accelerometer update, computed from the definitions."""
    a = np.asarray(accel, float)
    na = float(np.linalg.norm(a))
    err = na - G
    g = Rq.T @ np.array([0.0, 0.0, 1.0])
    H = np.hstack([cross_mat(g), np.zeros((3, 3))])
    sig = ((s.accel_noise_m_s2 if noise is None else noise) + 2.0 * abs(err)
           + s.accel_noise_per_rate_m_s2_per_rad_s * rate) / G
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + sig**2 * np.eye(3))
    up = Rq.T @ np.array([0.0, 0.0, 1.0])
    K[:3] = (np.eye(3) - np.outer(up, up)) @ K[:3]
    dx = K @ (a / na - g)
    A = np.eye(6) - K @ H
    P = A @ P @ A.T + sig**2 * K @ K.T
    return Rq @ rexp(dx[:3]), bias + dx[3:], P, dx


def _aligned(**kw) -> core.HeadingFilter:
    f = core.HeadingFilter(core.Settings(init_duration_s=0.0, **kw))
    f.align(LEVEL, FIELD)
    assert f.mode == "magnetic"
    return f


def _close(a, b, tol=1e-12):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.max(np.abs(a - b)) <= tol * max(1.0, float(np.max(np.abs(b)))), (a, b)


# ---- quaternion helpers -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("v", [(0.3, -0.5, 0.9), (2.5, 0.1, -1.0), (0.0, 0.0, 1.2e-3)])
def test_quaternion_exponential_product_and_matrix_match_rotations(v):
    q = core._quat_exp(*v)
    assert len(q) == 4 and abs(math.sqrt(sum(c * c for c in q)) - 1.0) < 1e-15
    _close(rmat(q), rexp(v), 1e-14)
    _close(core._qmat(q), rexp(v), 1e-14)
    p = core._quat_exp(-0.2, 0.7, 0.4)
    _close(core._qmat(core._qmul(p, q)), rexp((-0.2, 0.7, 0.4)) @ rexp(v), 1e-14)
    _close(core._qmat(core._qmul(q, p)), rexp(v) @ rexp((-0.2, 0.7, 0.4)), 1e-14)
    u = np.array([0.3, -1.7, 2.2])
    _close(core._skew(v) @ u, np.cross(v, u), 1e-15)


def test_quaternion_exponential_of_a_tiny_rotation_is_first_order():
    assert core._quat_exp(0.0, 0.0, 0.0) == (1.0, 0.0, 0.0, 0.0)
    q = core._quat_exp(2e-10, -4e-10, 6e-10)  # below 1e-9 rad: 1, v/2
    assert q == (1.0, 1e-10, -2e-10, 3e-10)
    q = core._quat_exp(8e-10, 0.0, 0.0)  # still below
    assert q[1] == 4e-10


# ---- prediction ---------------------------------------------------------------------------------------------------
PRED = dict(gyro_noise_rad_s_rt_hz=0.003, gyro_rate_noise_frac_rt_hz=0.02, gyro_bias_walk_rad_s2_rt_hz=7e-4)


@pytest.mark.parametrize("gyro,dt", [((0.4, -0.7, 1.1), 0.25), ((0.02, 0.01, -0.03), 0.01)])
def test_predict_propagates_attitude_yaw_and_covariance(gyro, dt):
    f = _aligned(**PRED)
    random_state(f, 1)
    f._gyro_yaw = 0.3
    q0, qg0, b0, P0 = f.q, f._qg, f.bias.copy(), f.P.copy()
    Rq, Rg, yaw, P = ref_predict(q0, qg0, b0, P0, 0.3, gyro, dt, f.settings)
    f._predict(gyro, dt)
    _close(core._qmat(f.q), Rq)
    _close(rmat(f.q), Rq)
    _close(rmat(f._qg), Rg)
    assert abs(math.sqrt(sum(c * c for c in f.q)) - 1.0) < 1e-15
    assert abs(math.sqrt(sum(c * c for c in f._qg)) - 1.0) < 1e-15
    assert f._gyro_yaw == pytest.approx(yaw, abs=1e-14)
    _close(f.P, P, 1e-13)
    assert np.array_equal(f.bias, b0)  # the bias is only changed by updates


def test_predict_renormalises_both_attitudes():
    f = _aligned(**PRED)
    random_state(f, 9)
    R0, Rg0 = rmat(f.q), rmat(f._qg)
    f.q = tuple(1.5 * c for c in f.q)  # norms drifted away from 1
    f._qg = tuple(0.7 * c for c in f._qg)
    w = np.array([0.3, -0.2, 0.5]) - f.bias
    f._predict(tuple(np.array([0.3, -0.2, 0.5])), 0.1)
    assert math.sqrt(sum(c * c for c in f.q)) == pytest.approx(1.0, abs=1e-15)
    assert math.sqrt(sum(c * c for c in f._qg)) == pytest.approx(1.0, abs=1e-15)
    _close(rmat(f.q), R0 @ rexp(w * 0.1), 1e-14)
    _close(rmat(f._qg), Rg0 @ rexp(w * 0.1), 1e-14)


def test_predict_of_a_rate_equal_to_the_bias_keeps_the_attitude():
    f = _aligned(**PRED)
    random_state(f, 2)
    q0 = f.q
    f._predict(tuple(f.bias), 0.5)
    _close(rmat(f.q), rmat(q0), 1e-15)


def test_inject_applies_a_body_frame_rotation_and_a_bias_step():
    f = _aligned()
    random_state(f, 3)
    q0, b0 = f.q, f.bias.copy()
    dx = np.array([0.05, -0.3, 0.2, 1e-3, -2e-3, 3e-3])
    f._inject(dx)
    _close(rmat(f.q), rmat(q0) @ rexp(dx[:3]), 1e-14)
    assert isinstance(f.q, tuple) and abs(math.sqrt(sum(c * c for c in f.q)) - 1.0) < 1e-15
    _close(f.bias, b0 + dx[3:], 1e-15)
    f.q = tuple(2.0 * c for c in q0)  # a drifted norm is restored
    f._inject(dx)
    assert abs(math.sqrt(sum(c * c for c in f.q)) - 1.0) < 1e-15
    _close(rmat(f.q), rmat(q0) @ rexp(dx[:3]), 1e-14)


# ---- accelerometer update ----------------------------------------------------------------------------------------
ACC = dict(accel_noise_m_s2=0.7, accel_noise_per_rate_m_s2_per_rad_s=3.0, accel_rejection_m_s2=2.5)


@pytest.mark.parametrize("noise", [None, 0.2])
def test_accelerometer_update_against_the_reference(noise):
    f = _aligned(**ACC)
    random_state(f, 4)
    Rq0, b0, P0 = rmat(f.q), f.bias.copy(), f.P.copy()
    accel = np.array([1.1, -0.6, 9.9])  # |a| − g ≈ 0.23, well off the predicted gravity
    R, b, P, dx = ref_accel(Rq0, b0, P0, accel, 0.4, f.settings, noise)
    f._fuse_accel(accel, 0.4, noise)
    assert not f.flags.accel_ignored
    assert f.states.accel_error_m_s2 == pytest.approx(np.linalg.norm(accel) - G, abs=1e-14)
    _close(rmat(f.q), R)
    _close(f.bias, b, 1e-13)
    _close(f.P, P, 1e-12)
    # the update never turns the heading: the correction has no part about the nav vertical
    assert abs(float(Rq0[2] @ dx[:3])) < 1e-15
    assert float(np.linalg.norm(dx[:3])) > 1e-3  # not vacuous: the attitude moved


def test_accelerometer_rejection_limits():
    err_limit = (G + 2.5) - G  # the deviation of |a| = g + 2.5 exactly as the filter computes it
    for mag, ignored in ((G + 2.5 + 1e-6, True), (G - 2.5 - 1e-6, True), (G + 2.5 - 1e-6, False)):
        f = _aligned(**ACC)
        random_state(f, 5)
        q0, P0 = f.q, f.P.copy()
        f._fuse_accel((0.0, 0.6, math.sqrt(mag * mag - 0.36)), 0.0)
        assert f.flags.accel_ignored is ignored, mag
        assert f.states.accel_error_m_s2 == pytest.approx(mag - G, abs=1e-12)
        assert (f.q == q0 and np.array_equal(f.P, P0)) is ignored
    # a reading of exactly 1e-6 m/s² (a huge limit): still fused; the rate term defaults to none
    f = _aligned(**dict(ACC, accel_rejection_m_s2=50.0))
    f._fuse_accel((1e-6, 0.0, 0.0))
    assert f.flags.accel_ignored is False
    f = _aligned(**ACC)
    random_state(f, 5)
    R, b, P, _ = ref_accel(rmat(f.q), f.bias.copy(), f.P.copy(), (0.3, 0.2, 9.9), 0.0, f.settings)
    f._fuse_accel((0.3, 0.2, 9.9))
    _close(rmat(f.q), R)
    # exactly at the limit: still fused
    f = _aligned(**dict(ACC, accel_rejection_m_s2=err_limit))
    f._fuse_accel((0.0, 0.0, G + 2.5), 0.0)
    assert f.flags.accel_ignored is False
    # a zero reading is never fused, whatever the limit; a weak one within the limit is
    f = _aligned(**dict(ACC, accel_rejection_m_s2=50.0))
    q0 = f.q
    f._fuse_accel((0.0, 0.0, 0.0), 0.0)
    assert f.flags.accel_ignored and f.q == q0
    f._fuse_accel((0.0, 0.3, 0.5), 0.0)
    assert not f.flags.accel_ignored and f.q != q0


# ---- update_imu ------------------------------------------------------------------------------------------------
def test_update_imu_is_prediction_then_the_accelerometer_with_the_raw_rate():
    f = _aligned(**PRED, **ACC)
    random_state(f, 6)
    f._last_fused_t = -0.75
    gyro, accel, dt = (0.3, -0.2, 0.5), (0.4, 0.3, 9.7), 0.02
    Rq, Rg, yaw, P = ref_predict(f.q, f._qg, f.bias, f.P, f._gyro_yaw, gyro, dt, f.settings)
    R, b, P, _ = ref_accel(Rq, f.bias, P, accel, math.sqrt(0.09 + 0.04 + 0.25), f.settings)
    n_hist = len(f._history)
    t0 = f.t_s
    f.update_imu(gyro, accel, dt)
    assert f.t_s == t0 + dt
    _close(rmat(f.q), R)
    _close(rmat(f._qg), Rg)
    _close(f.bias, b, 1e-13)
    _close(f.P, P, 1e-12)
    assert len(f._history) == n_hist + 1
    th, qh, yh = f._history[-1]
    assert th == f.t_s and qh == f._qg and yh == f._gyro_yaw == pytest.approx(yaw, abs=1e-14)
    st = f.internal_states
    assert st is f.states
    assert st.time_since_mag_fused_s == pytest.approx(f.t_s + 0.75, abs=1e-15)
    assert st.gyro_only_duration_s == 0.0
    up = R[2]
    assert st.heading_std_rad == pytest.approx(math.sqrt(up @ P[:3, :3] @ up), rel=1e-12)
    assert not f.flags.heading_uncertain  # magnetic: never, whatever the σ
    f.update_imu(gyro, accel, 0.01, t_s=7.25)  # the sample's own time sets the clock
    assert f.t_s == 7.25 and f._history[-1][0] == 7.25


def test_update_steps_10_ms_by_default():
    f = _aligned()
    f.update((0.0, 0.0, 0.0), LEVEL)
    assert f.t_s == 0.01


def test_update_returns_the_mode_and_passes_the_verdict():
    f = _aligned(clear_hold_s=0.5)
    assert f.update((0.0, 0.0, 0.0), LEVEL, FIELD, dt_s=0.01, dmc_valid=False) == "gyro_only"
    assert f.flags.dmc_valid is False and f.t_s == pytest.approx(0.01)
    assert f.update((0.0, 0.0, 0.0), LEVEL, None, dt_s=0.01) == "gyro_only"  # no sample: no verdict read
    assert f.flags.dmc_valid is False


def test_heading_uncertain_only_off_magnetic_and_above_the_limit():
    def run(limit):
        f = _aligned(heading_alarm_std_rad=limit)
        f.t_s = 0.5
        f._set_mode("gyro_only", "test")
        f.P[:3, :3] = np.diag([1e-4, 1e-4, 0.01])
        f.update_imu((0.0, 0.0, 0.0), LEVEL, 0.01)
        return f

    f = run(0.05)
    h = f.internal_states.heading_std_rad
    assert h == pytest.approx(math.sqrt(0.01 + 0.0005**2 * 0.01), rel=1e-3)
    assert f.flags.heading_uncertain
    assert f.internal_states.gyro_only_duration_s == pytest.approx(0.01)  # since the mode change at 0.5 s
    assert run(h).flags.heading_uncertain is False  # exactly at the limit: not above it
    assert run(h * (1 - 1e-12)).flags.heading_uncertain is True
    assert run(0.2).flags.heading_uncertain is False


def test_accelerometer_update_period():
    f = _aligned(accel_update_period_s=0.05)
    used = []
    for k, t in enumerate([1.0, 1.01, 1.02, 1.05 - 5e-10, 1.06, 1.0999, 1.1 + 1e-12]):
        a = (0.0, 0.0, G + 0.01 * (k + 1))
        f.update_imu((0.0, 0.0, 0.0), a, 0.01, t_s=t)
        used.append(f.states.accel_error_m_s2 == pytest.approx(0.01 * (k + 1), abs=1e-12))
    assert used == [True, False, False, True, False, False, True]
    g = _aligned(accel_update_period_s=0.05)
    g.update_imu((0.0, 0.0, 0.0), LEVEL, 0.01, t_s=0.0)
    g.update_imu((0.0, 0.0, 0.0), (0.0, 0.0, G + 0.5), 0.01, t_s=0.05 - 1e-9)  # exactly the period less the slack
    assert g.states.accel_error_m_s2 == pytest.approx(0.5, abs=1e-12)


# ---- initial alignment --------------------------------------------------------------------------------------------
def test_align_sets_the_attitude_and_learns_the_field_reference():
    R_true = Rotation.from_euler("ZYX", [1.1, -0.25, 0.4]).as_matrix()
    decl = -0.09
    b = np.array([20000.0 * math.sin(decl), 20000.0 * math.cos(decl), -41000.0])  # 20,000 nT horizontal at azimuth decl
    # the attitude of the sensor is given in true ENU
    f = core.HeadingFilter(core.Settings(init_duration_s=0.0, declination_rad=decl))
    f.t_s = 3.5
    f.align(R_true.T @ np.array([0.0, 0.0, 7.0]), R_true.T @ b)
    _close(rmat(f.q), R_true, 1e-12)
    assert f.ref_field_nt == pytest.approx(np.linalg.norm(b), rel=1e-14)
    assert f.ref_dip_rad == pytest.approx(math.atan2(41000.0, 20000.0), abs=1e-12)
    assert f.mode == "magnetic" and f.transitions == [(3.5, "initialising", "magnetic", "aligned")]
    assert f._last_fused_t == 3.5 and f.aligned
    # given references are kept
    g = core.HeadingFilter(core.Settings(init_duration_s=0.0, ref_field_nt=45000.0, ref_dip_rad=1.0))
    g.align(LEVEL, FIELD)
    assert (g.ref_field_nt, g.ref_dip_rad) == (45000.0, 1.0)


def test_initialisation_averages_in_the_frame_of_the_first_sample_and_aligns_at_the_end():
    """A body turning at a constant body rate (about all three axes) while the filter averages for 0.5 s: aligned at
    the end of it, exactly; the field samples scatter about the Earth field (their mean is it), so the average
    counts, not the last sample."""
    R0 = Rotation.from_euler("ZYX", [0.4, 0.2, -0.3]).as_matrix()
    b = np.array([0.0, 20000.0, -40000.0])
    w, dt = np.array([0.3, -0.5, 0.8]), 1.0 / 64.0
    scatter = np.array([3000.0, -2000.0, 1000.0])  # +1 on the 17 even samples, −17/16 on the 16 odd ones
    f0 = core.HeadingFilter(core.Settings(init_duration_s=0.0))
    assert f0.update_mag(FIELD) is False and f0.mode == "initialising"  # no IMU sample yet: no alignment
    f0.update_imu((0.0, 0.0, 0.0), LEVEL, 0.01)
    assert f0.update_mag(FIELD) is False and f0.mode == "magnetic"
    f = core.HeadingFilter(core.Settings(init_duration_s=0.5))
    n = 0
    while f.mode == "initialising":
        Rk = R0 @ rexp(w * n * dt)
        tilt = np.array([0.5, -0.3, 0.0]) * (1.0 if n % 2 == 0 else -17.0 / 16.0)  # scattered about gravity too
        f.update_imu(tuple(w), Rk.T @ (np.array([0.0, 0.0, G]) + tilt), dt, t_s=n * dt)
        assert f.update_mag(Rk.T @ (b + scatter * (1.0 if n % 2 == 0 else -17.0 / 16.0))) is False
        assert f.flags.initialising is (f.mode == "initialising")
        n += 1
        assert n < 100
    assert (n - 1) * dt == 0.5  # aligned at the sample 0.5 s after the first
    _close(rmat(f.q), R0 @ rexp(w * 0.5), 1e-12)
    assert f._last_mag_t == 0.5 and f._init_n == [n, n]
    assert f.ref_field_nt == pytest.approx(np.linalg.norm(b), rel=1e-12)  # learned from the average
    # a magnetometer sample first, then the IMU: the IMU sample already turns the averaging frame
    g = core.HeadingFilter(core.Settings(init_duration_s=0.25))
    g.update_mag(R0.T @ b, t_s=0.0)
    for k in range(1, 17):
        Rk = R0 @ rexp(w * k * dt)
        g.update_imu(tuple(w), Rk.T @ np.array([0.0, 0.0, G]), dt, t_s=k * dt)
        g.update_mag(Rk.T @ b)
    assert g.aligned
    _close(rmat(g.q), R0 @ rexp(w * 0.25), 1e-12)
    # two IMU samples before the first field sample: the second already turns the averaging frame
    h = core.HeadingFilter(core.Settings(init_duration_s=0.25))
    for k in range(0, 18):
        Rk = R0 @ rexp(w * k * dt)
        h.update_imu(tuple(w), Rk.T @ np.array([0.0, 0.0, G]), dt, t_s=k * dt)
        if k >= 1:
            h.update_mag(Rk.T @ b)
    assert h.aligned
    _close(rmat(h.q), R0 @ rexp(w * (17 * dt)), 1e-12)


def test_alignment_needs_its_duration_to_within_a_nanosecond():
    f = core.HeadingFilter(core.Settings(init_duration_s=0.5))
    f.update_imu((0.0, 0.0, 0.0), LEVEL, 0.0, t_s=0.0)
    f.update_mag(FIELD, t_s=0.0)
    f.update_imu((0.0, 0.0, 0.0), LEVEL, 0.0, t_s=0.5 - 1e-9)
    f.update_mag(FIELD, t_s=0.5 - 1e-9)  # exactly the duration less the slack
    assert f.aligned
    for gap, aligned in ((0.5 - 5e-10, True), (0.5 - 5e-9, False)):
        f = core.HeadingFilter(core.Settings(init_duration_s=0.5))
        f.update_imu((0.0, 0.0, 0.0), LEVEL, 0.0, t_s=10.0)
        f.update_mag(FIELD, t_s=10.0)
        f.update_imu((0.0, 0.0, 0.0), LEVEL, 0.0, t_s=10.0 + gap)
        f.update_mag(FIELD, t_s=10.0 + gap)
        assert f.aligned is aligned, gap


# ---- outputs ----------------------------------------------------------------------------------------------------
def test_heading_euler_quaternion_and_attitude_std():
    f = _aligned()
    R = Rotation.from_euler("ZYX", [0.9, 0.3, -0.2]).as_matrix()  # yaw 0.9 (CCW); about y by +0.3: nose down
    f.q = qof(R)
    heading = (math.pi / 2 - 0.9) % (2 * math.pi)
    assert f.heading_rad() == pytest.approx(heading, abs=1e-12)
    h, p, r = f.euler()
    assert (h, p, r) == pytest.approx((heading, -0.3, -0.2), abs=1e-12)
    _close(rmat(f.quaternion()), R, 1e-14)
    rng = np.random.default_rng(7)
    A = rng.normal(0, 0.05, (3, 3))
    f.P[:3, :3] = A @ A.T
    Pn = R @ f.P[:3, :3] @ R.T
    fwd = np.array([R[0, 0], R[1, 0], 0.0]) / math.hypot(R[0, 0], R[1, 0])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    sh, sp, sr = f.attitude_std()
    assert sh == pytest.approx(math.sqrt(Pn[2, 2]), rel=1e-12)
    assert sp == pytest.approx(math.sqrt(right @ Pn @ right), rel=1e-12)
    assert sr == pytest.approx(math.sqrt(fwd @ Pn @ fwd), rel=1e-12)
    assert len({round(sh, 9), round(sp, 9), round(sr, 9)}) == 3  # three different σ: each is its own axis
    # nose straight up: forward has no horizontal part; east is taken as forward (whatever the yaw)
    f.q = qof(Rotation.from_euler("ZYX", [0.7, -math.pi / 2, 0.0]).as_matrix())
    f.P[:3, :3] = np.diag([0.01, 0.04, 0.09])
    Rv = rmat(f.q)
    Pn = Rv @ f.P[:3, :3] @ Rv.T
    _, sp, sr = f.attitude_std()
    assert sr == pytest.approx(math.sqrt(Pn[0, 0]), rel=1e-9) and sp == pytest.approx(math.sqrt(Pn[1, 1]), rel=1e-9)


def test_magnetic_heading_is_the_tilt_compensated_field_azimuth():
    R = Rotation.from_euler("ZYX", [0.5, 0.2, -0.1]).as_matrix()
    b = np.array([20000.0 * math.sin(0.1), 20000.0 * math.cos(0.1), -40000.0])  # declination 0.1
    h = core.magnetic_heading(R.T @ b, R.T @ np.array([0.0, 0.0, G]), 0.1)
    assert float(h) == pytest.approx(math.pi / 2 - 0.5, abs=1e-9)
    h = core.magnetic_heading(R.T @ b, R.T @ np.array([0.0, 0.0, G]))  # no declination: the magnetic heading
    assert float(h) == pytest.approx(math.pi / 2 - 0.5 - 0.1, abs=1e-9)


# ---- settings ------------------------------------------------------------------------------------------------------
def test_settings_checks():
    core.Settings(declination_rad=-0.2, mag_noise_nt=0.0, gravity_lpf_order=2, mag_gate_sigma=1e-9)
    core.Settings(ref_dip_rad=-0.5, use_dmc=False)  # the dip is a signed angle; flags are not numbers
    assert math.isnan(core.Settings().ref_dip_rad)
    for bad in (dict(mag_noise_nt=-1e-9), dict(recovery_hold_s=float("nan")), dict(clear_hold_s=None),
                dict(mag_gate_sigma=0.0), dict(quasi_static_window_s=0.0), dict(gravity_lpf_order=3),
                dict(gravity_lpf_order=0), dict(min_hold_s=-0.1)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            core.Settings(**bad)


def test_the_late_sample_history_spans_1024_imu_steps():
    assert _aligned()._history.maxlen == 1024


def test_reset_restores_the_initial_state():
    f = _aligned(init_tilt_std_rad=0.03, init_heading_std_rad=0.4, gyro_bias_init_std_rad_s=0.02)
    random_state(f, 8)
    f.update_imu((0.1, 0.0, 0.0), LEVEL, 0.01)
    f.update_mag(FIELD, dmc_valid=False)
    f.reset()
    assert f.mode == "initialising" and not f.aligned and f.flags.initialising
    assert f.q == (1.0, 0.0, 0.0, 0.0) and f.t_s == 0.0 and f.transitions == []
    _close(f.P, np.diag([0.03**2, 0.03**2, 0.4**2, 0.02**2, 0.02**2, 0.02**2]), 1e-15)
    assert np.array_equal(f.bias, np.zeros(3)) and len(f._history) == 0
    g = copy.deepcopy(f)
    assert g.update_mag(FIELD) is False and g.mode == "initialising"
