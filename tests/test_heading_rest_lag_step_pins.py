"""Pins of the heading fuser's rest, gravity low-pass and lag steps (services/heading_fuser/core.py), each against
a reference computed here on a hand-set state:

- rest detection: the low-passed rate less the bias and the accelerometer's deviation from its low-pass, both
  under their limits for rest_min_s; the noise variances learned at rest (a ~10 s average of the per-sample
  squared deviations); the zero-rate update z = ω, H = [0, I];
- what update_imu fuses at rest (the accelerometer with the learned noise, then the zero rate) and with the
  gravity low-pass (its output with gravity_lpf_noise_m_s2, no rate term);
- the gravity low-pass: first order, and second order as scipy's Butterworth (same coefficients, the same
  output sequence from a steady start), in the gyro's frame or the estimate's, restarted at rest;
- the causal lag estimator: the gyro's trapezoid integration and ring buffer, the interpolated attitudes, which
  field pairs count, the normal equations of one pair, the solve and its parabola, and a known lag recovered;
  the batch lag estimate.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal
from heading_refmaths import cross_mat, qof, rexp, rmat
from scipy.spatial.transform import Rotation

from magmesh import maths
from services.heading_fuser import core

G = maths.G0
LEVEL = np.array([0.0, 0.0, G])
FIELD = np.array([0.0, 20000.0, -40000.0])
DT = 1.0 / 64.0


def _aligned(**kw) -> core.HeadingFilter:
    f = core.HeadingFilter(core.Settings(init_duration_s=0.0, **kw))
    f.align(LEVEL, FIELD)
    return f


def ref_accel(Rq, P, accel, sig_base, rate, s: core.Settings, floor: float = 0.0):
    a = np.asarray(accel, float)
    na = float(np.linalg.norm(a))
    g = Rq.T @ np.array([0.0, 0.0, 1.0])
    H = np.hstack([cross_mat(g), np.zeros((3, 3))])
    sig = max((sig_base + 2.0 * abs(na - G) + s.accel_noise_per_rate_m_s2_per_rad_s * rate) / G, floor)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + sig**2 * np.eye(3))
    K[:3] = (np.eye(3) - np.outer(g, g)) @ K[:3]
    dx = K @ (a / na - g)
    A = np.eye(6) - K @ H
    return dx, A @ P @ A.T + sig**2 * K @ K.T


def ref_zero_rate(P, bias, gyro, r):
    K = P[:, 3:] @ np.linalg.inv(P[3:, 3:] + r * np.eye(3))
    return K @ (np.asarray(gyro, float) - bias), P - K @ P[3:, :]


# ---- rest detection ---------------------------------------------------------------------------------------------------
def test_rest_detection_step_by_step():
    s = dict(rest_detection=True, rest_gyro_rad_s=0.03, rest_accel_m_s2=0.4, rest_min_s=0.25, rest_filter_tau_s=0.25,
             rest_gyro_noise_rad_s=0.02, rest_accel_noise_m_s2=0.3)
    f = _aligned(**s)
    f.bias = np.array([0.004, -0.002, 0.003])
    rng = np.random.default_rng(1)
    gl, al, since = np.zeros(3), None, None
    gvar, avar = 0.02**2, 0.3**2
    k = DT / 0.25
    seen = []
    for i in range(100):
        t = (i + 1) * DT
        gyro = f.bias + rng.normal(0, 0.003, 3) + (np.array([0.0, 0.0, 0.6]) if 20 <= i < 22 else 0.0)
        accel = LEVEL + rng.normal(0, 0.02, 3) + (np.array([0.6, 0.0, 0.0]) if i == 80 else 0.0)
        f.t_s = t
        f._detect_rest(gyro, accel, DT)
        al = accel.copy() if al is None else al
        gl = gl + k * (gyro - gl)
        al = al + k * (accel - al)
        da, dg = accel - al, gl - f.bias
        quiet = dg @ dg < 0.03**2 and da @ da < 0.4**2
        if not quiet:
            since, rest = None, False
        else:
            since = t if since is None else since
            rest = t - since >= 0.25
            if rest:
                kn = DT / 10.0
                e = gyro - gl
                gvar += kn * (e @ e / 3.0 - gvar)
                avar += kn * (da @ da / 3.0 - avar)
        assert np.allclose(f._rest_gyro_lp, gl, atol=1e-15) and np.allclose(f._rest_acc_lp, al, atol=1e-13)
        assert f.at_rest is rest and f._rest_since_t == since, i
        assert f._noise_gyro_var == pytest.approx(gvar, rel=1e-12) and f._noise_acc_var == pytest.approx(avar, rel=1e-12)
        seen.append(rest)
    # quiet from the start (bias removed): at rest from 0.25 s; the turn and the tap each end it
    assert seen[:16] == [False] * 16 and seen[16] is True
    assert not any(seen[20:30]) and seen[79] is True and seen[80] is False
    assert f._noise_gyro_var < 0.02**2 and f._noise_acc_var < 0.3**2  # learned towards the real, smaller noise


def test_rest_low_pass_gain_is_capped_at_one_and_the_noise_average_at_ten_seconds():
    f = _aligned(rest_detection=True, rest_min_s=0.0, rest_filter_tau_s=0.5)
    f._detect_rest((0.001, 0.0, 0.0), (0.0, 0.0, G), 2.0)  # dt > tau: the low-pass takes the sample itself
    assert f._rest_gyro_lp == [0.001, 0.0, 0.0] and f.at_rest
    assert f._noise_gyro_var == pytest.approx(0.005**2 + 0.2 * (0.0 - 0.005**2), rel=1e-12)  # kn = 2/10
    g = _aligned(rest_detection=True, rest_min_s=0.0)
    g._detect_rest((0.0, 0.0, 0.0), (0.0, 0.0, G), 12.0)  # kn capped at 1: the last sample's deviations
    assert g._noise_gyro_var == 0.0 and g._noise_acc_var == 0.0


def test_rest_needs_both_quiet_tests():
    for gyro, accel, rest in (((0.0, 0.0, 0.0), LEVEL, True), ((0.0, 0.0, 2.0), LEVEL, False),
                              ((0.0, 2.0, 0.0), LEVEL, False), ((2.0, 0.0, 0.0), LEVEL, False),
                              ((0.0, 0.0, 0.0), LEVEL + np.array([0.0, 2.0, 0.0]), False),
                              ((0.0, 0.0, 0.0), LEVEL + np.array([2.0, 0.0, 0.0]), False),
                              ((0.0, 0.0, 0.0), LEVEL + np.array([0.0, 0.0, 2.0]), False)):
        f = _aligned(rest_detection=True, rest_min_s=0.0, rest_filter_tau_s=0.5)
        f._detect_rest((0.0, 0.0, 0.0), LEVEL, DT)
        f._detect_rest(gyro, accel, DT)
        assert f.at_rest is rest, (gyro, accel)
    # each limit is strict: a low-passed rate (dt > tau: the sample itself) of exactly the limit is not quiet ...
    f = _aligned(rest_detection=True, rest_min_s=0.0, rest_gyro_rad_s=0.03)
    f._detect_rest((0.0, 0.03, 0.0), LEVEL, 1.0)
    assert not f.at_rest
    f._detect_rest((0.0, np.nextafter(0.03, 0.0), 0.0), LEVEL, 1.0)
    assert f.at_rest
    # ... nor an accelerometer deviation of exactly the limit (half-way low-pass: 0.8 − 0.4)
    for limit, rest in ((0.4, False), (np.nextafter(0.4, 1.0), True)):
        f = _aligned(rest_detection=True, rest_min_s=0.0, rest_filter_tau_s=0.5, rest_accel_m_s2=limit)
        f._detect_rest((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.25)
        f._detect_rest((0.0, 0.0, 0.0), (0.0, 0.0, 0.8), 0.25)
        assert f.at_rest is rest


def test_zero_rate_update_against_the_reference():
    f = _aligned()
    rng = np.random.default_rng(2)
    A = rng.normal(0, 1, (6, 6)) * np.array([0.05, 0.05, 0.1, 0.01, 0.01, 0.01])[:, None]
    f.P = A @ A.T + 1e-6 * np.eye(6)
    f.q = qof(Rotation.from_euler("ZYX", [0.3, -0.2, 0.1]).as_matrix())
    f.bias = np.array([0.002, -0.001, 0.004])
    f._noise_gyro_var = 0.003**2
    R0, P0, b0 = rmat(f.q), f.P.copy(), f.bias.copy()
    gyro = (0.01, -0.006, 0.002)
    dx, P = ref_zero_rate(P0, b0, gyro, 0.003**2)
    f._zero_rate(gyro)
    assert np.allclose(rmat(f.q), R0 @ rexp(dx[:3]), atol=1e-14)
    assert np.allclose(f.bias, b0 + dx[3:], atol=1e-15)
    assert np.allclose(f.P, P, atol=1e-15) and np.array_equal(f.P, f.P.T)
    assert np.linalg.norm(dx[:3]) > 1e-5  # the attitude moved too (P couples it to the bias)


def test_update_imu_at_rest_fuses_gravity_with_the_learned_noise_and_the_zero_rate():
    s = dict(rest_detection=True, rest_min_s=0.0, accel_noise_per_rate_m_s2_per_rad_s=3.0,
             gravity_lpf_tau_s=2.0, gravity_lpf_noise_m_s2=0.05)
    f = _aligned(**s)
    rng = np.random.default_rng(3)
    A = rng.normal(0, 1, (6, 6)) * np.array([0.05, 0.05, 0.1, 0.01, 0.01, 0.01])[:, None]
    f.P = A @ A.T + 1e-6 * np.eye(6)
    f.q = qof(Rotation.from_euler("ZYX", [0.3, -0.05, 0.04]).as_matrix())
    gyro, accel = np.array([0.001, 0.002, -0.001]), LEVEL + np.array([0.05, -0.03, 0.01])
    g = _aligned(**s)
    g.q, g.P = f.q, f.P.copy()
    g.t_s = f.t_s + DT
    g._predict(gyro, DT)
    g._detect_rest(gyro, accel, DT)
    assert g.at_rest
    R1, P1, b1 = rmat(g.q), g.P.copy(), g.bias.copy()
    dx, P2 = ref_accel(R1, P1, accel, math.sqrt(g._noise_acc_var), 0.0, g.settings)
    R2, b2 = R1 @ rexp(dx[:3]), b1 + dx[3:]
    dz, P3 = ref_zero_rate(P2, b2, gyro, g._noise_gyro_var)
    f.update_imu(gyro, accel, DT)
    assert f.at_rest and f._acc_lp_i is not None
    assert np.allclose(rmat(f.q), R2 @ rexp(dz[:3]), atol=1e-13)
    assert np.allclose(f.bias, b2 + dz[3:], atol=1e-15)
    assert np.allclose(f.P, P3, atol=1e-14)


def test_update_imu_with_the_gravity_low_pass_fuses_its_output():
    s = dict(gravity_lpf_tau_s=0.5, gravity_lpf_noise_m_s2=0.07, accel_noise_per_rate_m_s2_per_rad_s=3.0)
    f = _aligned(**s)
    f.P = np.diag([0.01, 0.02, 0.03, 1e-4, 1e-4, 1e-4])
    gyro = (0.2, -0.1, 0.3)
    for i, a in enumerate((LEVEL + [0.5, 0.0, 0.0], LEVEL + [0.0, -0.4, 0.2], LEVEL + [0.3, 0.3, -0.3])):
        g = _aligned(**s)
        g.q, g.P, g._qg, g.bias = f.q, f.P.copy(), f._qg, f.bias.copy()
        g._acc_lp_i = None if f._acc_lp_i is None else f._acc_lp_i.copy()
        g._predict(gyro, DT)
        Rg = rmat(g._qg)
        lp = Rg @ a if g._acc_lp_i is None else g._acc_lp_i + (DT / 0.5) * (Rg @ a - g._acc_lp_i)
        R1, P1 = rmat(g.q), g.P.copy()
        dx, P = ref_accel(R1, P1, Rg.T @ lp, 0.07, 0.0, g.settings)
        f.update_imu(gyro, a, DT)
        assert np.allclose(f._acc_lp_i, lp, atol=1e-12), i
        assert np.allclose(rmat(f.q), R1 @ rexp(dx[:3]), atol=1e-13), i
        assert np.allclose(f.P, P, atol=1e-14), i


@pytest.mark.parametrize("in_estimate,loop_gain", [(True, 1.7), (False, 1.7), (True, 0.0)])
def test_the_tilt_loop_limit_floors_the_low_passed_gravitys_noise(in_estimate, loop_gain):
    """gravity_lpf_loop_gain: with the low-pass in the estimate's frame, the low-passed gravity's σ is at least
    √(λ (1 − k) / k), λ the largest eigenvalue of the nav-frame (east, north) tilt covariance after the prediction and
    k = 1 − exp(−T · gain / τ), T the time since the last accelerometer update; in the gyro's frame (no loop) or with
    the gain 0 it is not floored."""
    tau, period = 0.5, 0.02
    s = dict(gravity_lpf_tau_s=tau, gravity_lpf_noise_m_s2=0.01, gravity_lpf_in_estimate=in_estimate,
             gravity_lpf_loop_gain=loop_gain, accel_update_period_s=period)
    f = _aligned(**s)
    f.P = np.diag([0.01, 0.02, 0.03, 1e-4, 1e-4, 1e-4])
    f.P[0, 1] = f.P[1, 0] = 0.005
    f.q = qof(Rotation.from_euler("ZYX", [0.3, -0.05, 0.04]).as_matrix())
    f._last_accel_t = f.t_s + DT - period
    gyro, a = (0.2, -0.1, 0.3), LEVEL + np.array([0.5, -0.4, 0.2])
    g = _aligned(**s)
    g.q, g.P, g._qg, g.bias = f.q, f.P.copy(), f._qg, f.bias.copy()
    g._predict(gyro, DT)
    R1, P1 = rmat(g.q), g.P.copy()
    lam = float(np.linalg.eigvalsh(R1[:2] @ P1[:3, :3] @ R1[:2].T)[-1])
    k = 1.0 - math.exp(-period * loop_gain / tau)
    floor = math.sqrt(lam * (1.0 - k) / k) if in_estimate and loop_gain > 0 else 0.0
    if floor:
        assert floor > (0.01 + 2.0 * abs(np.linalg.norm(a) - G)) / G  # the floor is what counts here
    dx, P = ref_accel(R1, P1, a, 0.01, 0.0, g.settings, floor=floor)  # the low-pass's first output: a itself
    f.update_imu(gyro, a, DT)
    assert np.allclose(rmat(f.q), R1 @ rexp(dx[:3]), atol=1e-13)
    assert np.allclose(f.P, P, atol=1e-14)


# ---- the gravity low-pass ---------------------------------------------------------------------------------------------
def test_butterworth_coefficients_are_scipys():
    for tau, dt in ((3.0, 0.01), (0.5, 1.0 / 285.714), (0.2, 0.05)):
        fc = math.sqrt(2.0) / (2.0 * math.pi) / tau
        b, a = scipy.signal.butter(2, fc, fs=1.0 / dt)
        assert np.allclose(core.butterworth2(tau, dt), [b[0], b[1], b[2], a[1], a[2]], rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("in_estimate", [False, True])
def test_first_order_low_pass_in_the_inertial_frame(in_estimate):
    """The accelerometer turned into the (gyro's or estimate's) frame, averaged there, turned back into the body."""
    f = _aligned(gravity_lpf_tau_s=0.25, gravity_lpf_in_estimate=in_estimate)
    rng = np.random.default_rng(4)
    lp = None
    for i in range(6):
        f.q = qof(Rotation.from_euler("ZYX", rng.uniform(-0.5, 0.5, 3)).as_matrix())
        f._qg = qof(Rotation.from_euler("ZYX", rng.uniform(-0.5, 0.5, 3)).as_matrix())
        a = LEVEL + rng.normal(0, 1.0, 3)
        dt = 0.125 if i < 5 else 0.5  # the last step longer than tau: the gain is capped at 1
        Rg = rmat(f.q if in_estimate else f._qg)
        lp = Rg @ a if lp is None else lp + min(1.0, dt / 0.25) * (Rg @ a - lp)
        out = f._gravity_lpf(a, dt)
        assert np.allclose(out, Rg.T @ lp, atol=1e-12), i
        assert np.allclose(f._acc_lp_i, lp, atol=1e-12)
    f.at_rest = True  # at rest the average restarts at the sample
    a = LEVEL + np.array([1.0, 2.0, -0.5])
    assert np.allclose(f._gravity_lpf(a, 0.125), a, atol=1e-12)


@pytest.mark.parametrize("in_estimate", [False, True])
def test_second_order_low_pass_is_the_butterworth_from_a_steady_start(in_estimate):
    tau, dt = 0.5, 0.02
    f = _aligned(gravity_lpf_tau_s=tau, gravity_lpf_order=2, gravity_lpf_in_estimate=in_estimate)
    rng = np.random.default_rng(5)
    acc = LEVEL + rng.normal(0, 2.0, (40, 3))
    frames = [Rotation.from_euler("ZYX", rng.uniform(-0.5, 0.5, 3)).as_matrix() for _ in range(40)]
    inertial = np.array([frames[i] @ acc[i] for i in range(40)])
    b, a = scipy.signal.butter(2, math.sqrt(2.0) / (2.0 * math.pi) / tau, fs=1.0 / dt)
    zi = scipy.signal.lfilter_zi(b, a)
    want = np.column_stack([scipy.signal.lfilter(b, a, inertial[:, k], zi=zi * inertial[0, k])[0] for k in range(3)])
    for i in range(40):
        if in_estimate:
            f.q = qof(frames[i])
        else:
            f._qg = qof(frames[i])
        out = f._gravity_lpf(acc[i], dt)
        assert np.allclose(frames[i] @ out, want[i], atol=1e-9), i
    f.at_rest = True
    s0, s1 = f._acc_lp_s
    out = f._gravity_lpf(acc[0], dt)
    assert np.allclose(out, acc[0], atol=1e-12)
    b0, _, b2, _, a2 = core.butterworth2(tau, dt)
    ai = (frames[-1]) @ acc[0]
    assert np.allclose(f._acc_lp_s[0], ai * (1.0 - b0), atol=1e-9) and np.allclose(f._acc_lp_s[1], ai * (b2 - a2),
                                                                                   atol=1e-9)


# ---- the causal lag estimator -------------------------------------------------------------------------------------------
def test_lag_estimator_integrates_the_gyro_by_trapezoids_into_a_ring_buffer():
    e = core.MagLagEstimator(n_buf=4)
    rates = [(0.1, 0.2, -0.3), (0.5, -0.1, 0.2), (0.0, 0.3, 0.1), (-0.2, 0.0, 0.4), (0.3, 0.3, 0.3), (0.1, -0.4, 0.2)]
    R = np.eye(3)
    for i, w in enumerate(rates):
        t = 1.0 + i * 0.125
        e.add_gyro(t, w)
        if i:
            R = R @ rexp(0.0625 * (np.asarray(rates[i - 1]) + np.asarray(w)))
        assert np.allclose(rmat(e._q), R, atol=1e-14) and abs(np.linalg.norm(e._q) - 1.0) < 1e-15
        assert e._i == i + 1
    assert list(e._gt) == [1.5, 1.625, 1.25, 1.375]  # the last four, in ring order
    assert np.allclose(rmat(e._gq[1]), R, atol=1e-14)
    e.add_gyro(1.625, (9.0, 9.0, 9.0))  # no time passed: nothing integrated
    assert np.allclose(rmat(e._q), R, atol=1e-14)


def test_lag_estimator_interpolates_attitudes():
    e = core.MagLagEstimator()
    gt = np.array([0.0, 0.5, 1.0])
    q0, q1 = np.array([1.0, 0.0, 0.0, 0.0]), np.array(qof(rexp((0.0, 0.0, 0.4))))
    q2 = np.array(qof(rexp((0.3, 0.0, 0.4))))
    gq = np.array([q0, q1, q2])
    got = e._attitudes_at(np.array([0.25, -1.0, 0.5, 2.0, 0.75]), gt, gq)
    mid, mid2 = (q0 + q1) / np.linalg.norm(q0 + q1), (q1 + q2) / np.linalg.norm(q1 + q2)
    assert np.allclose(got, [mid, q0, q1, q2, mid2], atol=1e-15)  # clipped at both ends, not extrapolated
    got = e._attitudes_at(np.array([0.5]), np.array([0.0, 0.5, 0.5 + 1e-12]), gq)  # a near-zero interval
    assert np.all(np.isfinite(got))


def _lag_data(lag_s: float, n: int, rate_hz: float = 200.0, hi=(3000.0, -2000.0, 1500.0)):
    """Gyro samples of a tumbling body (exact rates, the attitude a smooth function of time) and the field it sees
    lag_s late, plus a body-fixed offset."""
    def att(t):
        return Rotation.from_euler("ZYX", [1.5 * math.sin(1.1 * t), 0.7 * math.sin(1.7 * t + 1.0),
                                           0.8 * math.sin(1.3 * t + 2.0)])

    t = np.arange(n) / rate_hz
    h = 1e-5
    gyro = np.array([(att(x - h).inv() * att(x + h)).as_rotvec() / (2 * h) for x in t])
    b = np.array([0.0, 20000.0, -40000.0])
    mag = np.array([att(x - lag_s).inv().apply(b) for x in t]) + np.asarray(hi)
    return t, gyro, mag


def test_lag_estimator_recovers_a_lag_between_grid_points_and_the_offset():
    t, gyro, mag = _lag_data(0.0125, 700)
    e = core.MagLagEstimator(max_delay_s=0.025, step_s=0.005, min_samples=20, period_s=0.05)
    delays = []
    for i in range(len(t)):
        e.add_gyro(t[i], gyro[i])
        e.add_mag(t[i], mag[i], 0.0)
        delays.append((e.n, e.delay_s))
    assert e.n >= 40
    assert all(d == 0.0 for n, d in delays if n < 20)  # nothing reported before min_samples pairs
    assert abs(e.delay_s - 0.0125) < 0.001, e.delay_s  # between the 0.010 and 0.015 candidates: the parabola
    assert np.allclose(e.offset_nt, (3000.0, -2000.0, 1500.0), atol=150.0), e.offset_nt  # (at the best candidate)
    j = int(np.argmin(e.cost))
    assert e.grid[j] in (0.01, 0.015) and e.cost[j] < 0.05 * e.cost[0]
    # one pair per period_s at most: 700 samples at 200 Hz (3.5 s) give at most 70 pairs
    assert e.n <= 70


def test_lag_estimator_one_pair_normal_equations():
    t, gyro, mag = _lag_data(0.0, 256, rate_hz=256.0)  # times, lags and the baseline on a binary grid
    e = core.MagLagEstimator(max_delay_s=2 / 256, step_s=1 / 256, min_samples=1000, period_s=0.05, baseline_s=0.25)
    ref_q = [np.eye(3)]
    for i in range(1, len(t)):
        ref_q.append(ref_q[-1] @ rexp(0.5 * (gyro[i - 1] + gyro[i]) * (t[i] - t[i - 1])))
    n0 = 0
    for i in range(len(t)):
        e.add_gyro(t[i], gyro[i])
        A0, b0, c0 = e.A.copy(), e.b.copy(), e.c.copy()
        e.add_mag(t[i], mag[i], 0.0)
        if e.n > n0:
            n0 = e.n
            i0 = max(j for j in range(i) if t[j] <= t[i] - 0.25)  # the newest sample at least a baseline older
            for g, d in enumerate(e.grid):
                k = int(round(d * 256.0))  # the candidate lag in samples (on the gyro's grid here)
                if i0 - k < 0:
                    continue
                Md = ref_q[i - k].T @ ref_q[i0 - k]
                M = np.eye(3) - Md
                r0 = mag[i] - Md @ mag[i0]
                assert np.allclose(e.A[g] - A0[g], M.T @ M, atol=1e-9)
                assert np.allclose(e.b[g] - b0[g], M.T @ r0, atol=1e-5)
                assert e.c[g] - c0[g] == pytest.approx(r0 @ r0, rel=1e-9)
            if n0 >= 3:
                break
    assert n0 == 3


def test_lag_estimator_defaults_and_initial_state():
    """The filter builds it as MagLagEstimator(mag_delay_max_s): a 1 ms grid to 50 ms, pairs 0.2 s apart that
    turned half of 0.5 rad/s over it, one per 50 ms, 200 before a first estimate, 512 gyro samples kept."""
    e = core.MagLagEstimator()
    assert len(e.grid) == 51 and e.grid[-1] == pytest.approx(0.05) and e.step_s == 0.001
    assert e.min_turn_rad == pytest.approx(0.05) and e.baseline_s == 0.2 and e.period_s == 0.05
    assert e.min_samples == 200 and e._gt.shape == (512,) and e._gq.shape == (512, 4)
    assert e.delay_s == 0.0 and e.n == 0 and np.array_equal(e.offset_nt, np.zeros(3))
    assert np.array_equal(e.cost, np.zeros(51)) and e.A.shape == (51, 3, 3) and not e.A.any()
    assert np.all(np.isneginf(e._gt)) and e._q == (1.0, 0.0, 0.0, 0.0)
    assert len(core.MagLagEstimator(max_delay_s=0.02).grid) == 21


def test_lag_estimator_renormalises_its_attitude():
    e = core.MagLagEstimator()
    e._q = (2.0, 0.0, 0.0, 0.0)  # (a drifted norm)
    e.add_gyro(0.0, (0.1, 0.2, 0.3))
    e.add_gyro(0.125, (0.1, 0.2, 0.3))
    assert math.sqrt(sum(c * c for c in e._q)) == pytest.approx(1.0, abs=1e-15)
    assert np.allclose(rmat(e._q), rexp(0.125 * np.array([0.1, 0.2, 0.3])), atol=1e-15)


def _ref_pairs(gyro_t, gyro, mags, *, n_buf, grid, baseline, period, min_turn, ref_nt):
    """The pairs the estimator should take and their sums, from its definition: the gyro attitude by trapezoids;
    a field sample is dropped 10 % off the reference; it pairs with the newest kept sample at least a baseline older,
    if 0.8 to 2 baselines older, at most one pair per period, with both times (less every candidate lag) inside the
    gyro samples kept, and the pair counts if the body turned at least min_turn (candidate 0)."""
    R = [np.eye(3)]
    for i in range(1, len(gyro_t)):
        R.append(R[-1] @ rexp(0.5 * (gyro[i - 1] + gyro[i]) * (gyro_t[i] - gyro_t[i - 1])))
    index = {round(t * 256): i for i, t in enumerate(gyro_t)}
    kept, last, pairs = [], -math.inf, []
    A, b, c = np.zeros((len(grid), 3, 3)), np.zeros((len(grid), 3)), np.zeros(len(grid))
    for t, m, n_gyro in mags:
        if ref_nt and abs(np.linalg.norm(m) / ref_nt - 1.0) > 0.1:
            continue
        kept.append((t, m))
        while len(kept) > 1 and kept[1][0] <= t - baseline:
            kept.pop(0)
        if t - last < period or n_gyro < 2:
            continue
        t0, m0 = kept[0]
        if not 0.8 * baseline <= t - t0 <= 2.0 * baseline:
            continue
        first = gyro_t[max(0, n_gyro - n_buf)]
        if t0 - grid[-1] < first or t > gyro_t[n_gyro - 1] + 1e-6:
            continue
        last = t
        Ms = [R[index[round((t - d) * 256)]].T @ R[index[round((t0 - d) * 256)]] for d in grid]
        if Rotation.from_matrix(Ms[0]).magnitude() < min_turn:
            continue
        pairs.append((t, t0))
        for g, Md in enumerate(Ms):
            M = np.eye(3) - Md
            r0 = m - Md @ m0
            A[g] += M.T @ M
            b[g] += M.T @ r0
            c[g] += r0 @ r0
    return pairs, A, b, c


# field samples (gyro sample indices): every one at first, then every other one, with a gap in between
SCHEDULE_A = dict(n=700, n_buf=160, dense=(2, 100), sparse=[(100, 330), (488, 700)])  # gap: pair 158/256 s apart
SCHEDULE_B = dict(n=700, n_buf=512, dense=(2, 100), sparse=[(100, 300), (480, 700)])  # gap: 180/256 s


@pytest.mark.parametrize("sched", [SCHEDULE_A, SCHEDULE_B], ids=["buffer-short", "gap-long"])
def test_lag_estimator_takes_the_pairs_of_its_definition(sched):
    """256 Hz gyro from t = 3 s, field samples on a schedule, two of them 20 % off the reference; the body turns
    fast, slowly for a while (pairs below the minimum turn), then fast again. Every pair, and the normal equations,
    as the definition says: the first pair 0.8 baselines apart with its earlier time less the largest lag exactly
    the first gyro time; after the gap, a pair whose earlier time is no longer in a short buffer (A), or one more
    than two baselines apart (B)."""
    n = sched["n"]
    gyro_t = 3.0 + np.arange(n) / 256.0
    x = gyro_t - 3.0
    s = np.where((0.8 <= x) & (x < 1.2), 0.1, 1.0)
    gyro = np.column_stack([0.4 * s * np.sin(2.0 * gyro_t), 0.5 * s * np.cos(1.3 * gyro_t), 0.6 * s])
    b_enu = np.array([0.0, 20000.0, -40000.0])
    R = [np.eye(3)]
    for i in range(1, n):
        R.append(R[-1] @ rexp(0.5 * (gyro[i - 1] + gyro[i]) / 256.0))
    ref_nt = float(np.linalg.norm(b_enu))
    e = core.MagLagEstimator(max_delay_s=2 / 256, step_s=1 / 256, min_rate_rad_s=0.4, min_samples=10**6,
                             period_s=0.0625, baseline_s=0.3125, n_buf=sched["n_buf"])
    field_at = set(range(*sched["dense"])) | {i for a, b in sched["sparse"] for i in range(a, b, 2)}
    mags, taken = [], []
    for i in range(n):
        e.add_gyro(gyro_t[i], gyro[i])
        if i not in field_at:
            continue
        m = R[i].T @ b_enu * (1.2 if i in (300, 520) else 1.0)
        mags.append((gyro_t[i], m, i + 1))
        n0 = e.n
        e.add_mag(gyro_t[i], m, ref_nt)
        if e.n > n0:
            taken.append(gyro_t[i])
    pairs, A, b, c = _ref_pairs(gyro_t, gyro, mags, n_buf=sched["n_buf"], grid=e.grid, baseline=0.3125,
                                period=0.0625, min_turn=0.4 * 0.3125 * 0.5, ref_nt=ref_nt)
    assert [p[0] for p in pairs] == taken and len(pairs) >= 20
    assert pairs[0] == (3.0 + 66 / 256, 3.0 + 2 / 256)  # 0.8 baselines; 2/256 s (the largest lag) after the first gyro
    assert np.allclose(e.A, A, atol=1e-9) and np.allclose(e.b, b, atol=1e-5) and np.allclose(e.c, c, rtol=1e-9)


@pytest.mark.parametrize("after_s, pairs", [(1e-6, 1), (2e-6, 0)])
def test_lag_estimator_takes_a_sample_up_to_a_microsecond_after_the_gyro(after_s, pairs):
    late = core.MagLagEstimator(max_delay_s=0.0, min_samples=10**6, baseline_s=0.3)
    late.add_gyro(0.0, (0.0, 0.0, 1.0))
    late.add_gyro(1.0, (0.0, 0.0, 1.0))
    late.add_mag(0.5, FIELD, 0.0)
    late.add_mag(1.0 + after_s, FIELD, 0.0)
    assert late.n == pairs


def test_lag_estimator_a_pair_that_did_not_turn():
    """The body turned, then held still: the pair's attitudes are equal, their product's w rounds a little above 1
    (a turn of 0, not a domain error), and the pair does not count."""
    e = core.MagLagEstimator(max_delay_s=0.0, min_samples=10**6, baseline_s=0.25)
    for t, w in ((0.0, (0.0, 0.0, 0.0)), (0.1, (-1.9338894578858836, 1.2530809568010897, 1.6510223091108869)),
                 (0.2, (0.0, 0.0, 0.0)), (1.0, (0.0, 0.0, 0.0))):
        e.add_gyro(t, w)
    q0, q1 = e._attitudes_at(np.array([0.5, 0.75]), e._gt[:4], e._gq[:4])
    assert q1[0] * q0[0] + q1[1] * q0[1] + q1[2] * q0[2] + q1[3] * q0[3] > 1.0
    e.add_mag(0.5, FIELD, 0.0)
    e.add_mag(0.75, FIELD, 0.0)
    assert e.n == 0 and e._last_t == 0.75  # looked at (the period starts), not counted


def test_lag_estimator_solves_every_tenth_pair_from_min_samples():
    t, gyro, mag = _lag_data(0.01, 900, rate_hz=256.0)
    e = core.MagLagEstimator(max_delay_s=0.02, step_s=0.005, min_samples=25, period_s=0.02)
    solved = []
    for i in range(len(t)):
        e.add_gyro(t[i], gyro[i])
        cost = e.cost.copy()
        n0 = e.n
        e.add_mag(t[i], mag[i], 0.0)
        if e.n > n0 and not np.array_equal(cost, e.cost):
            solved.append(e.n)
    assert e.n >= 50 and solved == list(range(30, e.n + 1, 10))
    assert e.delay_s == pytest.approx(0.01, abs=0.002)


def test_lag_estimator_regularises_an_axis_never_turned_about():
    """Turns about z only: the information about the offset's z part is nil; the solve adds 1e-9 of the trace
    (plus 1e-12) to the diagonal, so a little noise along z gives a bounded offset there."""
    e = core.MagLagEstimator(max_delay_s=0.002, step_s=0.001)
    A1 = np.diag([2.0, 3.0, 0.0])
    e.A = np.array([A1, A1 * 1.5, A1 * 2.0])
    e.b = np.array([[2.0, 3.0, 1e-6], [3.0, 4.5, 2e-6], [4.0, 6.0, 1e-6]])
    e.c = np.array([10.0, 7.0, 11.0])  # the best: the middle one
    e._solve()
    h = np.array([np.linalg.solve(A + (1e-9 * np.trace(A) + 1e-12) * np.eye(3), bb) for A, bb in zip(e.A, e.b, strict=True)])
    assert e.offset_nt == pytest.approx(h[1], rel=1e-9)
    assert np.allclose(e.cost, e.c - np.einsum("gi,gi->g", e.b, h), rtol=1e-12)


def test_lag_estimator_refines_even_a_shallow_minimum():
    e = core.MagLagEstimator(max_delay_s=0.004, step_s=0.001)
    e.A = np.tile(np.eye(3), (5, 1, 1))
    e.b = np.zeros((5, 3))
    e.c = np.array([0.9, 0.5, 0.1, 0.2, 0.4])  # curvature 0.5: still refined
    e._solve()
    assert e.delay_s == pytest.approx(0.002 + 0.001 * 0.5 * (0.5 - 0.2) / (0.5 - 2 * 0.1 + 0.2), abs=1e-12)
    e.c = np.array([3.0, 2.0, 1.0, 0.0, 2.0])  # the best last but one
    e._solve()
    assert e.delay_s == pytest.approx(0.003 - 0.001 / 6.0, abs=1e-12)


def test_lag_estimator_skips_what_does_not_count():
    t, gyro, mag = _lag_data(0.0, 120)
    ref = float(np.linalg.norm(mag[0]))
    e = core.MagLagEstimator(min_samples=1000)
    e.add_mag(0.0, mag[0], ref)  # no gyro yet
    assert e.n == 0 and len(e._mags) == 1
    e.add_mag(0.001, mag[0] * 1.2, ref)  # 20 % off the reference strength: not even kept
    assert len(e._mags) == 1
    e.add_mag(0.002, mag[0] * 1.09, ref)  # 9 %: kept
    assert len(e._mags) == 2
    # two gyro samples are enough to pair (a constant rate between them)
    e = core.MagLagEstimator(max_delay_s=0.0, min_samples=1000, baseline_s=0.25)
    e.add_gyro(0.0, (0.0, 0.0, 1.0))
    e.add_gyro(1.0, (0.0, 0.0, 1.0))
    e.add_mag(0.5, FIELD, 0.0)
    e.add_mag(0.75, rexp((0.0, 0.0, 0.25)).T @ FIELD, 0.0)
    assert e.n == 1
    # a body at rest: no pair turns enough
    s = core.MagLagEstimator(min_samples=1000)
    for i in range(200):
        s.add_gyro(i / 200.0, (0.0, 0.0, 0.001))
        s.add_mag(i / 200.0, FIELD, 0.0)
    assert s.n == 0 and not s.A.any()


def test_lag_estimator_solve():
    e = core.MagLagEstimator(max_delay_s=0.004, step_s=0.001)
    assert len(e.grid) == 5
    rng = np.random.default_rng(6)
    B = rng.normal(0, 1, (5, 3, 3))
    e.A = np.einsum("gij,gkj->gik", B, B) + np.eye(3)
    h_true = rng.normal(0, 1, (5, 3))
    e.b = np.einsum("gij,gj->gi", e.A, h_true)
    resid = np.array([5.0, 2.0, 1.0, 3.0, 7.0])
    e.c = resid + np.einsum("gi,gi->g", e.b, h_true)
    e._solve()
    assert np.allclose(e.cost, resid, rtol=1e-6, atol=1e-6)
    assert np.allclose(e.offset_nt, h_true[2], rtol=1e-6)
    frac = 0.5 * (2.0 - 3.0) / (2.0 - 2.0 + 3.0)
    assert e.delay_s == pytest.approx(0.002 + frac * 0.001, rel=1e-6)
    for resid, want in (([1.0, 2.0, 3.0, 4.0, 5.0], 0.0), ([5.0, 4.0, 3.0, 2.0, 1.0], 0.004),
                        ([3.0, 2.0, 1.0, 0.0, 1.0], 0.003)):
        e.c = np.array(resid) + np.einsum("gi,gi->g", e.b, h_true)
        e._solve()
        assert e.delay_s == pytest.approx(want, abs=1e-9), resid
    e.c = np.array([4.0, 2.0, 3.0, 5.0, 6.0]) + np.einsum("gi,gi->g", e.b, h_true)
    e._solve()
    assert e.delay_s == pytest.approx(0.001 + 0.001 / 6.0, abs=1e-9)


def _batch_reference(w, m, rate, max_delay_s):
    """ṁ(t) = −ω(t − d) × m(t): the mean squared residual for each whole-sample shift, the parabola through the
    best and its neighbours (an interior best only)."""
    dm = np.gradient(m, axis=0) * rate
    kmax = max(1, int(round(max_delay_s * rate)))
    cost = np.array([np.mean(np.sum((dm[k:] + np.cross(w[: len(w) - k], m[k:])) ** 2, axis=1))
                     for k in range(kmax + 1)])
    j = int(np.argmin(cost))
    frac = 0.0
    if 0 < j < kmax:
        c0, c1, c2 = cost[j - 1: j + 2]
        frac = 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2)
    return (j + frac) / rate, j


@pytest.mark.parametrize("lag,max_delay,j,scale", [(0.0, 0.05, 0, 1.0), (0.013, 0.05, 1, 1.0), (0.0235, 0.03, 2, 1.0),
                                                   (0.031, 0.04, 3, 1.0), (0.07, 0.05, 5, 1.0), (0.0, 0.001, 0, 1.0),
                                                   (0.013, 0.001, 1, 1.0), (0.0235, 0.03, 2, 1e-6)])
def test_batch_lag_estimate(lag, max_delay, j, scale):
    t, gyro, mag = _lag_data(lag, 300, rate_hz=100.0, hi=(0.0, 0.0, 0.0))
    mag = mag * scale  # (1e-6: the costs' curvature far below 1)
    want, jj = _batch_reference(gyro, mag, 100.0, max_delay)
    assert jj == j  # the best shift: first, interior, last but one, last (the shifts: at least one)
    args = () if max_delay == 0.05 else (max_delay,)
    got = core.estimate_mag_delay_s(gyro, mag, 100.0, *args)
    assert got == pytest.approx(want, rel=1e-12, abs=0.0)
    if 0 < j < max(1, round(max_delay * 100.0)):
        assert abs(got * 100.0 - j) > 1e-3  # refined off the whole sample
