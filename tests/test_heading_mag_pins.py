"""Pins of each magnetometer-side step of the heading fuser's reference filter (services/heading_fuser/core.py)
against references computed here, on hand-set states and short sample sequences (times on a 1/64 s grid, so
every hold is an exact number of samples):

- the field checks (strength and dip of one sample and of the window mean, each against its own tolerance);
- the sliding window's sums, its span and the quasi-static tests, and the adaptive noise gain they choose;
- the heading measurement: ν = azimuth − D, S = Hr P Hrᵀ + max(σ_m²/|h|², floor²) · gain + leak, where the leak
  is the tilt covariance seen through the azimuth's sensitivity to a tilt of the levelled field (here by finite
  differences); the gate ν² / (gate² S) ≤ 1; the Kalman update of the heading; the field-direction update;
- the modes: magnetic → gyro_only (DMC or field), the clear hold, recovering (the consistency hold, the
  re-acquisition's slew limit inside the gate and its rate-limited slew outside it, the exit hold), persistent
  gate rejections, the holds scaled with a DMC-only outage, and every transition's reason;
- the weak fusion of a disturbed field, the hard-iron tracking (slow mean and from the sensor's rotation), the
  field re-base, late and lagging samples levelled with the attitude of their time, the update period.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from heading_refmaths import qof, rexp, rmat
from scipy.spatial.transform import Rotation

from magmesh import maths
from services.heading_fuser import core

G = maths.G0
LEVEL = (0.0, 0.0, G)
ZERO = (0.0, 0.0, 0.0)
FIELD = np.array([0.0, 20000.0, -40000.0])  # level sensor facing north: |b| = 44,721 nT, dip 63.4°
DT = 1.0 / 64.0
ISOLATED = dict(init_duration_s=0.0, adaptive_noise=False, mag_vector_fusion=False, use_field_check=False)


def rz(a: float) -> np.ndarray:
    return rexp((0.0, 0.0, a))


def _aligned(**kw) -> core.HeadingFilter:
    kw.setdefault("init_duration_s", 0.0)
    f = core.HeadingFilter(core.Settings(**kw))
    f.align(LEVEL, FIELD)
    assert f.mode == "magnetic"
    assert f.q == (1.0, 0.0, 0.0, 0.0) or f.settings.declination_rad  # level, facing magnetic north
    return f


def _tilted(f: core.HeadingFilter, seed: int) -> None:
    """A tilted, turned attitude and an anisotropic covariance."""
    rng = np.random.default_rng(seed)
    f.q = qof(Rotation.from_euler("ZYX", [0.7, 0.25, -0.35]).as_matrix())
    A = rng.normal(0.0, 1.0, (6, 6)) * np.array([0.06, 0.02, 0.1, 0.01, 0.01, 0.01])[:, None]
    f.P = A @ A.T + np.diag([1e-4, 4e-4, 3e-4, 1e-5, 2e-5, 3e-5])


def ref_innovation(R, P, m, s: core.Settings, gain: float = 1.0, recovering: bool = False):
    """(ν, S, r) of a field sample m levelled with R, from the definitions; the tilt leak from the azimuth's
    numerical sensitivity to a rotation of the levelled field about east and about north."""
    mn = R @ np.asarray(m, float)
    h2 = mn[0] ** 2 + mn[1] ** 2
    nu = math.remainder(math.atan2(mn[0], mn[1]) - s.declination_rad, 2 * math.pi)

    def az(phi):
        v = rexp(phi) @ mn
        return math.atan2(v[0], v[1])

    eps = 1e-7
    J = np.array([(az(e * eps) - az(-e * eps)) / (2 * eps) for e in np.eye(3)[:2]])
    Pn = R @ P[:3, :3] @ R.T
    leak = float(J @ Pn[:2, :2] @ J) if h2 > 1.0 else 0.0
    r = max(s.mag_noise_nt**2 / max(h2, 1.0), s.mag_heading_noise_floor_rad**2) * gain + leak
    if recovering:
        r *= s.recovery_noise_gain
    return nu, float(R[2] @ P[:3, :3] @ R[2]) + r, r


def ref_heading_update(R, P, nu, S):
    Hr = R[2]
    PHt = P[:, :3] @ Hr
    K = PHt / S
    return K * nu, P - np.outer(K, PHt)


def _step(f, t, m=FIELD, dmc=None, gyro=ZERO):
    f.update_imu(gyro, LEVEL, DT, t_s=t)
    return f.update_mag(m, dmc, t_s=t)


# ---- the heading measurement and its gate -------------------------------------------------------------------------
@pytest.mark.parametrize("noise_nt,floor", [(900.0, 0.01), (1.0, 0.02)])
def test_heading_innovation_variance_with_the_tilt_leak_and_the_update(noise_nt, floor):
    """A tilted attitude with an anisotropic covariance: the leak is that of the axis the field's azimuth is
    sensitive to; the update is the scalar Kalman update of the heading row."""
    f = _aligned(**ISOLATED, mag_noise_nt=noise_nt, mag_heading_noise_floor_rad=floor, declination_rad=0.05)
    _tilted(f, 1)
    R, P0, b0 = rmat(f.q), f.P.copy(), f.bias.copy()
    b = 21000.0 * np.array([math.sin(0.09), math.cos(0.09), -2.2])  # azimuth 0.09, dip 65.6°
    m = R.T @ b
    nu, S, _ = ref_innovation(R, P0, m, f.settings)
    assert nu == pytest.approx(0.04, abs=1e-12)
    fused = f.update_mag(m)
    st = f.internal_states
    assert fused and f.flags.mag_fused and not f.flags.mag_rejected_gate
    assert st.mag_innovation_rad == pytest.approx(nu, abs=1e-12)
    assert st.mag_innovation_var_rad2 == pytest.approx(S, rel=1e-7)
    assert st.mag_test_ratio == pytest.approx(nu * nu / (25.0 * S), rel=1e-7)
    assert st.mag_noise_gain == 1.0
    dx, P = ref_heading_update(R, P0, nu, S)
    assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-9)
    assert np.allclose(f.bias, b0 + dx[3:], atol=1e-12)
    assert np.allclose(f.P, P, atol=1e-10) and np.array_equal(f.P, f.P.T)
    assert f._last_fused_t == f.t_s and f.internal_states.time_since_mag_fused_s == 0.0


def test_leak_comes_from_the_tilt_about_the_horizontal_field():
    """A level sensor, the field due north, a large tilt σ about north (the axis along the horizontal field): a tilt
    about it swings the field's vertical part sideways, so it leaks tan²(dip) σ²; the same σ about east does not."""
    out = {}
    for axis in (0, 1):
        f = _aligned(**ISOLATED)
        f.P[:3, :3] = np.diag([1e-6, 1e-6, 1e-4])
        f.P[axis, axis] = 0.0025
        f.update_mag(FIELD)
        out[axis] = f.internal_states.mag_innovation_var_rad2
    floor = max(150.0**2 / 20000.0**2, 0.01**2)
    assert out[1] == pytest.approx(1e-4 + floor + 4.0 * 0.0025, rel=1e-9)  # tan²(dip) = 4
    assert out[0] == pytest.approx(1e-4 + floor + 4.0 * 1e-6, rel=1e-9)


def test_a_vertical_field_has_the_noise_of_a_unit_horizontal_part():
    f = _aligned(**ISOLATED)
    p22 = f.P[2, 2]
    f.update_mag((0.0, 0.0, -45000.0))
    assert f.internal_states.mag_innovation_var_rad2 == pytest.approx(p22 + 150.0**2, rel=1e-12)
    # a horizontal part of 1 nT: no leak term (h² must exceed 1 nT²); of 1.2 nT: the leak, (z/h)² σ² along it
    for h, leak in ((1.0, 0.0), (1.2, (45000.0 / 1.2) ** 2 * 1e-6)):
        g = _aligned(**ISOLATED)
        g.P[:3, :3] = np.diag([1e-6, 1e-6, 1e-4])
        g.update_mag((0.0, h, -45000.0))
        want = 1e-4 + 150.0**2 / max(h * h, 1.0) + leak
        assert g.internal_states.mag_innovation_var_rad2 == pytest.approx(want, rel=1e-9), h


@pytest.mark.parametrize("gate", [5.0, 2.0])
def test_gate_boundary(gate):
    """A test ratio just above 1 is rejected and leaves the state alone; just below, fused."""
    f0 = _aligned(**ISOLATED, mag_gate_sigma=gate)
    _, S, _ = ref_innovation(np.eye(3), f0.P, FIELD, f0.settings)
    for k, rejected in ((1.0 + 1e-6, True), (1.0 - 1e-6, False), (-1.0 - 1e-6, True)):
        f = _aligned(**ISOLATED, mag_gate_sigma=gate)
        nu = k * gate * math.sqrt(S)
        m = rz(-nu) @ FIELD  # turned clockwise by nu: azimuth nu
        q0, P0 = f.q, f.P.copy()
        fused = f.update_mag(m)
        assert f.internal_states.mag_innovation_rad == pytest.approx(nu, rel=1e-9)
        assert f.flags.mag_rejected_gate is rejected and fused is not rejected and f.flags.mag_fused is not rejected
        assert (f.q == q0 and np.array_equal(f.P, P0)) is rejected
        assert f.mode == "magnetic"


@pytest.mark.parametrize("noise_nt", [400.0, 50.0])  # the sensor noise above the floor; the floor above it
def test_field_direction_update_when_consistent_and_quasi_static(noise_nt):
    s = dict(init_duration_s=0.0, declination_rad=-0.07, mag_noise_nt=noise_nt)
    f = _aligned(**s)
    _tilted(f, 2)
    R, P0, b0 = rmat(f.q), f.P.copy(), f.bias.copy()
    dip = f.ref_dip_rad
    u = np.array([math.cos(dip) * math.sin(-0.07), math.cos(dip) * math.cos(-0.07), -math.sin(dip)])
    b_true = rz(-0.02) @ rexp((0.01, -0.015, 0.0)) @ (u * 44721.0)  # a little off in azimuth and tilt
    m = R.T @ b_true
    assert f.update_mag(m) and f.flags.quasi_static and not f.flags.field_inconsistent
    h = R.T @ u
    H = np.hstack([np.column_stack([np.cross(h, e) for e in np.eye(3)]), np.zeros((3, 3))])
    mn = R @ m
    var = max(noise_nt**2 / (mn[0] ** 2 + mn[1] ** 2), 0.01**2) * (mn[0] ** 2 + mn[1] ** 2) / float(mn @ mn)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + var * np.eye(3))
    dx = K @ (m / np.linalg.norm(m) - h)
    A = np.eye(6) - K @ H
    P = A @ P0 @ A.T + var * K @ K.T
    assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-12)
    assert np.allclose(f.bias, b0 + dx[3:], atol=1e-13)
    assert np.allclose(f.P, P, atol=1e-12)
    assert abs(dx[0]) + abs(dx[1]) > 1e-4  # it also moved the tilt (a heading update would not)


# ---- field checks ----------------------------------------------------------------------------------------------------
def test_one_sample_checks_strength_and_dip_each_at_its_tolerance():
    """R = I exactly: the levelled field is the sample itself, so the errors are exact."""
    base = dict(init_duration_s=0.0, ref_field_nt=40000.0, ref_dip_rad=math.atan2(4.0, 3.0), mag_vector_fusion=False)
    m = np.array([0.0, 30000.0, -40000.0])  # |m| = 50,000: strength error exactly 0.25, dip error 0
    for tol, bad in ((0.25, False), (0.25 * (1 - 1e-12), True)):
        f = _aligned(**base, sample_strength_tol_frac=tol)
        f.update_mag(m)
        st = f.internal_states
        assert st.field_strength_error_frac == 0.25 and st.field_dip_error_rad == 0.0
        assert f.flags.field_inconsistent is bad and f.flags.mag_fused is not bad
    m = np.array([0.0, 40000.0, -30000.0])  # |m| = 50,000, dip atan2(3, 4)
    derr = math.atan2(30000.0, 40000.0) - math.atan2(4.0, 3.0)
    for tol, bad in ((abs(derr), False), (abs(derr) * (1 - 1e-12), True)):
        f = _aligned(**base, sample_strength_tol_frac=0.3, sample_dip_tol_rad=tol)
        f.update_mag(m)
        assert f.internal_states.field_dip_error_rad == derr
        assert f.flags.field_inconsistent is bad
    f = _aligned(**base, sample_strength_tol_frac=0.1, sample_dip_tol_rad=0.1, use_field_check=False)
    f.update_mag(m)
    assert not f.flags.field_inconsistent and f.flags.mag_fused


@pytest.mark.parametrize("what", ["strength", "dip"])
def test_window_mean_off_the_reference_is_disturbed_each_test_alone(what):
    """1 s of a field 5 % stronger (or its dip 0.1 rad steeper), the other quantity unchanged: once the window
    spans 0.8 s the filter goes gyro_only for the field, not the DMC."""
    f = _aligned(mag_vector_fusion=False)  # (a field-direction update would take the dip for a tilt)
    b = FIELD * 1.05 if what == "strength" else np.linalg.norm(FIELD) * np.array(
        [0.0, math.cos(f.ref_dip_rad + 0.1), -math.sin(f.ref_dip_rad + 0.1)])
    modes = []
    for k in range(1, 70):
        _step(f, k * DT, b, True)
        modes.append(f.mode)
    first = modes.index("gyro_only") + 1
    assert first == 53  # the first window spanning 0.8 s: 52 · 1/64 s ≥ 0.8 s
    assert f.transitions[-1] == (53 * DT, "magnetic", "gyro_only", "field strength/dip off reference")
    assert f.flags.field_inconsistent and f.flags.dmc_valid
    g = _aligned(mag_vector_fusion=False,
                 **({"field_strength_tol_frac": 0.06} if what == "strength" else {"field_dip_tol_rad": 0.11}))
    for k in range(1, 70):
        _step(g, k * DT, b, True)
    assert g.mode == "magnetic" and not g.flags.field_inconsistent


# ---- the window and the adaptive noise ----------------------------------------------------------------------------------
def test_window_sums_span_and_statistics():
    w = core._Window(0.5)
    rng = np.random.default_rng(3)
    items = []
    for k in range(40):
        t = k * 0.03125
        it = (t, 40000.0 + rng.normal(0, 300), 1.1 + rng.normal(0, 0.02), 0.5 + 0.01 * k)
        w.add(*it)
        items.append(it)
        kept = [x for x in items if t - x[0] <= 0.5]
        assert [x[0] for x in w.items] == [x[0] for x in kept]
        assert w.full(t) is (len(kept) >= 3 and t - kept[0][0] >= 0.4)
        b = np.array([x[1] for x in kept])
        d = np.array([x[2] for x in kept])
        mb, vb, md, vd, dpsi = w.stats()
        assert mb == pytest.approx(b.mean(), rel=1e-12) and md == pytest.approx(d.mean(), rel=1e-12)
        assert vb == pytest.approx(b.var(), rel=1e-6, abs=1e-6) and vd == pytest.approx(d.var(), rel=1e-6, abs=1e-12)
        assert dpsi == pytest.approx(abs(kept[-1][3] - kept[0][3]), abs=1e-12)
    assert len(w.items) == 17  # 0.5 s at 1/32 s, both ends kept
    w.add(20.0, 1.0, 1.0, 3.0)
    assert len(w.items) == 1 and w.stats()[:4] == pytest.approx((1.0, 0.0, 1.0, 0.0), abs=1e-4)  # running sums
    w.clear()
    assert len(w.items) == 0 and not w.s.any()
    w = core._Window(0.625)  # full from a span of 0.5 s
    w.add(20.0, 1.0, 1.0, 3.0)
    w.add(20.5, 1.0, 1.0, 3.0)
    assert not w.full(20.5)  # two samples are not enough
    w = core._Window(0.625)
    w.add(20.0, 1.0, 1.0, 3.0)
    w.add(20.25, 1.0, 1.0, 3.0 - 2 * math.pi + 0.1)  # the heading change is taken the short way round
    assert w.stats()[4] == pytest.approx(0.1, abs=1e-12)
    w.add(20.4375, 1.0, 1.0, 3.0)
    assert not w.full(20.4375)
    w.add(20.5, 1.0, 1.0, 3.0)
    assert w.full(20.5) and not w.full(20.4375)
    w.add(20.625, 1.0, 1.0, 3.0)
    assert [x[0] for x in w.items] == [20.0, 20.25, 20.4375, 20.5, 20.625]  # a span of exactly the length is kept


def _noisy_field(k: int, strength_sd: float = 0.0, dip_sd: float = 0.0, turn: float = 0.0) -> np.ndarray:
    """FIELD with its strength and dip alternating ± the given σ (exact sample variance σ² over an even count),
    its azimuth turned by ``turn`` rad per second."""
    sgn = 1.0 if k % 2 else -1.0
    B = float(np.linalg.norm(FIELD)) + sgn * strength_sd
    dip = math.atan2(40000.0, 20000.0) + sgn * dip_sd
    return rz(-turn * k * DT) @ (B * np.array([0.0, math.cos(dip), -math.sin(dip)]))


@pytest.mark.parametrize("case,gain,qs", [
    ("steady", 1.0, True), ("strength", 200.0, False), ("dip", 200.0, False), ("turn", 150.0, False),
    ("strength+turn", 200.0, False)])
def test_quasi_static_tests_choose_the_noise_gain(case, gain, qs):
    """The strength variance (1,000² nT² > 0.8·10⁶), the dip variance (0.02² rad² > 3·10⁻⁴) and the heading change
    the gyro does not see (0.1 rad/s for 0.8 s > 0.035 rad) each fail the test alone; k1 = 200, k2 = 150, both: the
    larger."""
    f = _aligned(**ISOLATED | dict(adaptive_noise=True, mag_gate_sigma=1e6))
    kw = {"steady": {}, "strength": dict(strength_sd=1000.0), "dip": dict(dip_sd=0.02), "turn": dict(turn=0.1),
          "strength+turn": dict(strength_sd=1000.0, turn=0.1)}[case]
    for k in range(1, 60):
        f.update_mag(_noisy_field(k, **kw), t_s=k * DT)
        if k < 52:
            assert f.flags.quasi_static and f.internal_states.mag_noise_gain == 1.0  # window not yet full
    assert f.flags.quasi_static is qs
    assert f.internal_states.mag_noise_gain == gain
    R, P = rmat(f.q), f.P
    g = _aligned(**ISOLATED | dict(adaptive_noise=True, mag_gate_sigma=1e6))
    g.q, g.P, g._window, g._gyro_yaw = f.q, P.copy(), f._window, f._gyro_yaw
    g._last_mag_t = 59 * DT
    m = _noisy_field(60, **kw)
    g.update_mag(m, t_s=60 * DT)
    assert g.internal_states.mag_innovation_var_rad2 == pytest.approx(ref_innovation(R, P, m, g.settings, gain)[1],
                                                                      rel=1e-7)
    h = _aligned(**ISOLATED | dict(mag_gate_sigma=1e6, adaptive_gain_variance=120.0, adaptive_gain_heading=170.0))
    for k in range(1, 60):
        h.update_mag(_noisy_field(k, **kw), t_s=k * DT)
    assert h.internal_states.mag_noise_gain == 1.0 and h.flags.quasi_static is qs  # adaptive_noise off: tested only


def test_larger_of_the_two_gains_decides():
    f = _aligned(**ISOLATED | dict(adaptive_noise=True, mag_gate_sigma=1e6, adaptive_gain_variance=120.0,
                                   adaptive_gain_heading=170.0))
    for k in range(1, 60):
        f.update_mag(_noisy_field(k, strength_sd=1000.0, turn=0.1), t_s=k * DT)
    assert f.internal_states.mag_noise_gain == 170.0


# ---- modes and holds ----------------------------------------------------------------------------------------------------
def _run(f, t0, t1, field=lambda t: FIELD, dmc=lambda t: True):
    """Samples on the 1/64 s grid from t0 to t1 (exclusive); returns [(t, mode, fused)]."""
    out = []
    k = round(t0 / DT)
    while k * DT < t1:
        t = k * DT
        fused = _step(f, t, field(t), dmc(t))
        out.append((t, f.mode, fused))
        k += 1
    return out


# the holds one after the other; the agreement hold counted from the clear hold's start (agreement_from_clear, the
# default) is pinned on its own below
HOLDS = dict(init_duration_s=0.0, clear_hold_s=1.0, recovery_hold_s=2.0, min_hold_s=0.25, agreement_from_clear=False)


def test_dmc_only_outage_scales_both_holds():
    f = _aligned(**HOLDS)
    out = _run(f, DT, 5.0, dmc=lambda t: not 2.0 <= t < 2.5)
    assert [t for t, mode, fused in out if not fused] == [k * DT for k in range(128, 193)]  # 2.0 … 3.0 s
    assert [tr[:3] for tr in f.transitions] == [(0.0, "initialising", "magnetic"), (2.0, "magnetic", "gyro_only"),
                                                (3.0, "gyro_only", "recovering"),
                                                (3.0 + DT + 0.5, "recovering", "magnetic")]
    assert [tr[3] for tr in f.transitions[1:]] == ["DMC says invalid", "disturbance cleared",
                                                   "magnetometer consistent and its heading agrees"]
    assert f.flags.dmc_valid and not f.flags.field_inconsistent


def test_a_very_short_outage_holds_at_least_min_hold():
    f = _aligned(**HOLDS)
    _run(f, DT, 3.0, dmc=lambda t: not 2.0 <= t < 2.0 + 2 * DT)
    assert [tr[0] for tr in f.transitions[1:]] == [2.0, 2.0 + 2 * DT + 0.25, 2.0 + 3 * DT + 0.25 + 0.25]


def test_full_holds_without_scaling():
    f = _aligned(**HOLDS, holds_scale_with_outage=False)
    _run(f, DT, 6.5, dmc=lambda t: not 2.0 <= t < 2.5)
    assert [tr[0] for tr in f.transitions[1:]] == [2.0, 3.5, 3.5 + DT + 2.0]


def test_full_holds_when_the_field_checks_failed_in_the_outage():
    """A field 40 % off for 0.25 s with the DMC saying nothing: the window (0.25 s) judges it; the holds after
    it are the full ones (scaled they would be about half as long)."""
    f = _aligned(**HOLDS, quasi_static_window_s=0.25)
    clear = []

    def field(t):
        return FIELD * 1.4 if 2.0 <= t < 2.25 else FIELD

    for k in range(1, 384):
        _step(f, k * DT, field(k * DT), True)
        if f.mode == "gyro_only" and not f.flags.field_inconsistent and not clear:
            clear.append(k * DT)  # the window is back on the reference: the clear hold starts
    assert f.transitions[1][1:] == ("magnetic", "gyro_only", "field strength/dip off reference")
    rec = [tr[0] for tr in f.transitions if tr[2] == "recovering"]
    mag = [tr[0] for tr in f.transitions[2:] if tr[2] == "magnetic"]
    assert clear and clear[0] - f.transitions[1][0] < 0.6  # scaled, the hold would have been < 0.6 s
    assert rec == [clear[0] + 1.0] and mag == [rec[0] + DT + 2.0]
    g = _aligned(**HOLDS, quasi_static_window_s=0.25, holds_scale_with_outage=False)  # the same either way
    _run(g, DT, 6.0, field=field)
    assert [tr[0] for tr in g.transitions] == [tr[0] for tr in f.transitions]


def test_disturbed_again_while_recovering():
    f = _aligned(**HOLDS, holds_scale_with_outage=False)
    _run(f, DT, 7.0, dmc=lambda t: not (2.0 <= t < 2.5 or t == 3.75))
    assert [tr[1:] for tr in f.transitions[1:]] == [("magnetic", "gyro_only", "DMC says invalid"),
                                                    ("gyro_only", "recovering", "disturbance cleared"),
                                                    ("recovering", "gyro_only", "disturbed again while recovering"),
                                                    ("gyro_only", "recovering", "disturbance cleared"),
                                                    ("recovering", "magnetic",
                                                     "magnetometer consistent and its heading agrees")]
    # one disturbed sample at 3.75 s: the clear hold again from the next one, then the agreement hold
    assert [tr[0] for tr in f.transitions[3:]] == [3.75, 3.75 + DT + 1.0, 3.75 + 2 * DT + 1.0 + 2.0]


def test_persistent_gate_rejections_go_to_recovering_after_the_timeout():
    f = _aligned(**ISOLATED, rejection_timeout_s=1.5)
    off = rz(-1.2) @ FIELD

    def field(t):
        return FIELD if abs(t - 1.25) < 1e-9 else off

    _run(f, DT, 3.0, field=field)
    # rejected from 1/64 s, reset by the good sample at 1.25 s, rejected again from 1.25 + 1/64: strictly more
    # than 1.5 s later, recovering
    t_rec = 1.25 + DT + 1.5 + DT
    assert f.transitions[1] == (t_rec, "magnetic", "recovering", "innovation outside the gate for too long")
    # the field back on the heading: the agreement hold (the full one: no outage to scale it) and magnetic
    _run(f, 3.0, 6.0)
    assert f.transitions[2][:3] == (3.0 + 2.0, "recovering", "magnetic")


def test_recovery_inside_the_gate_is_slew_limited():
    """After a 0.5 s DMC outage the heading is 0.3 rad off; the magnetometer is inside the (recovery-widened) gate:
    each update moves the heading by at most recovery_slew_rad_s · Δt, the bias correction scaled with it."""
    f = _aligned(**HOLDS, holds_scale_with_outage=False, init_heading_std_rad=0.5, mag_vector_fusion=False)
    _run(f, DT, 2.5, dmc=lambda t: t < 2.0)
    assert f.mode == "gyro_only"
    f.q = qof(rz(0.3))
    _run(f, 2.5, 3.5 + DT)
    assert f.mode == "recovering" and f.transitions[-1][0] == 3.5
    for k in range(3):
        t = 3.5 + (k + 1) * DT
        R, P0, b0 = rmat(f.q), f.P.copy(), f.bias.copy()
        f.update_imu(ZERO, LEVEL, DT, t_s=t)
        R, P0, b0 = rmat(f.q), f.P.copy(), f.bias.copy()
        nu, S, _ = ref_innovation(R, P0, FIELD, f.settings, recovering=True)
        assert f.update_mag(FIELD, True, t_s=t)
        dx, P = ref_heading_update(R, P0, nu, S)
        limit = f.settings.recovery_slew_rad_s * DT
        assert abs(R[2] @ dx[:3]) > limit
        dx *= limit / abs(R[2] @ dx[:3])
        assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-13)
        assert np.allclose(f.bias, b0 + dx[3:], atol=1e-15)
        assert np.allclose(f.P, P, atol=1e-13)


def test_recovery_outside_the_gate_slews_once_consistent():
    """The heading 0.5 rad off and a tight covariance: outside the gate. Once the field has been consistent for
    recovery_hold_s the heading turns towards it at exactly recovery_slew_rad_s, never before; a single sample off
    in strength is not slewed to."""
    s = dict(HOLDS, holds_scale_with_outage=False, init_heading_std_rad=0.005, recovery_hold_s=0.5,
             quasi_static_var_nt2=1e12, quasi_static_dip_var_rad2=10.0)  # (one sample off: still quasi-static)
    f = _aligned(**s)
    _run(f, DT, 2.5, dmc=lambda t: t < 2.0)
    f.q = qof(rz(0.5))
    _run(f, 2.5, 3.5 + DT)
    assert f.mode == "recovering" and f.transitions[-1][0] == 3.5
    heads = []
    for k in range(1, 45):
        t = 3.5 + k * DT
        m = FIELD * 1.2 if k == 40 else FIELD
        h0 = f.heading_rad()
        fused = _step(f, t, m, True)
        assert not fused and f.flags.mag_rejected_gate
        heads.append((t, math.remainder(f.heading_rad() - h0, 2 * math.pi)))
    step = f.settings.recovery_slew_rad_s * DT
    for t, dh in heads:
        if t < 3.5 + DT + 0.5 or abs(t - (3.5 + 40 * DT)) < 1e-9:
            assert abs(dh) < 1e-9, (t, dh)
        else:
            assert dh == pytest.approx(step, rel=1e-6), (t, dh)  # towards north: the heading grows back
    assert f.mode == "recovering"


def test_slew_is_a_rotation_about_the_vertical_clamped_to_the_rate():
    f = _aligned()
    f.q = qof(Rotation.from_euler("ZYX", [0.3, 0.2, -0.1]).as_matrix())
    R = rmat(f.q)
    f._slew(0.5, R[2], 0.1)
    assert np.allclose(rmat(f.q), R @ rexp(R[2] * 0.007), atol=1e-14)
    f.q = qof(R)
    f._slew(-0.5, R[2], 0.1)
    assert np.allclose(rmat(f.q), R @ rexp(R[2] * -0.007), atol=1e-14)
    f.q = qof(R)
    f._slew(0.002, R[2], 0.1)
    assert np.allclose(rmat(f.q), R @ rexp(R[2] * 0.002), atol=1e-14)
    f.q = qof(R)
    f._slew(-0.002, R[2], 0.1)
    assert np.allclose(rmat(f.q), R @ rexp(R[2] * -0.002), atol=1e-14)


def test_recovering_exit_needs_the_innovation_inside_recovery_exit_for_the_hold():
    """recovering, the field consistent: the exit hold runs only while |ν| ≤ recovery_exit_rad."""
    f = _aligned(**dict(HOLDS, holds_scale_with_outage=False, recovery_exit_rad=0.01, mag_vector_fusion=False,
                        recovery_hold_s=0.25))
    _run(f, DT, 2.5, dmc=lambda t: t < 2.0)
    _run(f, 2.5, 3.5 + DT)
    assert f.mode == "recovering"
    # 0.02 rad off for 10 samples (outside the exit band, inside the gate), then on the field with one outlier
    # far outside the gate: each restarts the exit hold
    off, outlier = rz(-0.02) @ FIELD, rz(-3.0) @ FIELD

    def field(t):
        return off if t < 3.5 + 11 * DT else outlier if abs(t - (3.5 + 20 * DT)) < 1e-9 else FIELD

    out = _run(f, 3.5 + DT, 4.5, field=field)
    assert [fused for t, _, fused in out if abs(t - (3.5 + 20 * DT)) < 1e-9] == [False]  # the outlier: rejected
    back = [t for t, mode, _ in out if mode == "magnetic"]
    assert back and back[0] == 3.5 + 21 * DT + 0.25
    assert f.transitions[-1][1:] == ("recovering", "magnetic", "magnetometer consistent and its heading agrees")


# ---- weak fusion of a disturbed field, hard iron ---------------------------------------------------------------------
def _disturbed(**kw):
    """gyro_only because the field is 8 % stronger than the reference (window judged), the DMC saying valid."""
    f = _aligned(**kw)
    _run(f, DT, 1.0, field=lambda t: FIELD * 1.08)
    assert f.mode == "gyro_only" and f.flags.dmc_valid
    return f


@pytest.mark.parametrize("nu,dmc,gain,weak", [(0.1, True, 50.0, True), (-0.34, True, 50.0, True),
                                              (0.36, True, 50.0, False), (0.1, False, 50.0, False),
                                              (0.1, True, 0.0, False), (0.1, True, 0.5, True)])
def test_weak_fusion_of_a_disturbed_field(nu, dmc, gain, weak):
    f = _disturbed(disturbed_noise_gain=gain, mag_vector_fusion=False)
    t = 1.0
    f.update_imu(ZERO, LEVEL, DT, t_s=t)
    R, P0, b0, q0 = rmat(f.q), f.P.copy(), f.bias.copy(), f.q
    m = rz(-nu) @ FIELD * 1.08
    g = f.internal_states.mag_noise_gain
    assert f.update_mag(m, dmc, t_s=t) is False  # a weak update is not "fused"
    assert f.mode == "gyro_only" and f.internal_states.mag_innovation_rad == pytest.approx(nu, abs=1e-12)
    if not weak:
        assert f.q == q0 and np.array_equal(f.P, P0)
        return
    g = f.internal_states.mag_noise_gain
    nu_r, S, r = ref_innovation(R, P0, m, f.settings, gain=g)
    dx, P = ref_heading_update(R, P0, nu_r, S - r + r * gain)
    assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-13)
    assert np.allclose(f.bias, b0 + dx[3:], atol=1e-15)
    assert np.allclose(f.P, P, atol=1e-13)


def test_hard_iron_slow_mean_and_its_innovation():
    """The tracked magnet is the slow mean (time constant hard_iron_tau_s) of measured − expected field; its
    innovation is that of the field less the magnet, once tau has passed and the rest is consistent."""
    f = _aligned(hard_iron_tracking=True, hard_iron_tau_s=0.5, declination_rad=0.04)
    R = rmat(qof(Rotation.from_euler("ZYX", [0.3, 0.1, 0.05]).as_matrix()))
    dip, B = f.ref_dip_rad, f.ref_field_nt
    b_ref = B * np.array([math.cos(dip) * math.sin(0.04), math.cos(dip) * math.cos(0.04), -math.sin(dip)])
    magnet = np.array([5000.0, -3000.0, 2000.0])
    m = R.T @ (rz(-0.03) @ b_ref) + magnet  # the Earth field 0.03 rad further clockwise, plus the magnet
    hi = np.zeros(3)
    for k, dt in enumerate((0.125, 0.125, 0.125, 0.125, 0.7)):
        a = min(1.0, dt / 0.5)
        hi = (1 - a) * hi + a * (m - R.T @ b_ref)
        out = f._hard_iron_innovation(m, R, dt)
        assert np.allclose(f._hard_iron, hi, atol=1e-9) and f._hard_iron_t == pytest.approx(0.125 * (k + 1) + (
            0.575 if k == 4 else 0.0))
        if k < 3:
            assert out is None  # tau not yet passed
        else:
            assert out is not None  # from exactly tau on
    # after 0.7 s (a = 1): the mean is measured − expected exactly: the compensated field is the reference one
    assert out == pytest.approx(0.0, abs=1e-9)
    f._hard_iron = magnet.copy()
    assert f._hard_iron_innovation(m, R, 0.0) == pytest.approx(0.03, abs=1e-9)
    f._hard_iron = magnet + np.array([0.0, 0.0, 9000.0])  # compensated field 20 % off: not consistent
    assert f._hard_iron_innovation(m, R, 0.0) is None
    f._hard_iron = magnet + 6000.0 * np.array([0.0, math.sin(dip), math.cos(dip)])  # dip off by ~0.13 rad, |b| kept
    f.settings = core.Settings(hard_iron_tracking=True, hard_iron_tau_s=0.5, declination_rad=0.04,
                               sample_dip_tol_rad=0.05, sample_strength_tol_frac=0.5)
    assert f._hard_iron_innovation(m, R, 0.0) is None


def test_hard_iron_tracking_steers_the_heading_in_gyro_only():
    f = _aligned(hard_iron_tracking=True, hard_iron_tau_s=0.25, hard_iron_noise_gain=3.0, mag_vector_fusion=False)
    magnet = np.array([6000.0, 2000.0, -1000.0])
    _run(f, DT, 1.5, field=lambda t: FIELD + magnet)
    assert f.mode == "gyro_only" and f._hard_iron_t > 0.25
    t = 1.5
    f.update_imu(ZERO, LEVEL, DT, t_s=t)
    R, P0 = rmat(f.q), f.P.copy()
    m = rz(-0.02) @ FIELD + magnet
    hi = f._hard_iron + (DT / 0.25) * ((m - R.T @ FIELD) - f._hard_iron)
    f.update_mag(m, True, t_s=t)
    assert np.allclose(f._hard_iron, hi, atol=1e-6)
    nu_c = ref_innovation(R, P0, m - hi, f.settings)[0]
    # ν of the compensated field; the raw field's own (adaptive) noise and leak, times hard_iron_noise_gain
    _, _, r_raw = ref_innovation(R, P0, m, f.settings, gain=f.internal_states.mag_noise_gain)
    dx, P = ref_heading_update(R, P0, nu_c, float(R[2] @ P0[:3, :3] @ R[2]) + 3.0 * r_raw)
    assert abs(nu_c) > 1e-3 and f.internal_states.mag_innovation_rad != pytest.approx(nu_c, abs=1e-6)
    assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-12)
    assert np.allclose(f.P, P, atol=1e-12)
    f._set_mode("magnetic", "test")
    assert not f._hard_iron.any() and f._hard_iron_t == 0.0  # the magnet is forgotten in magnetic mode


def _hir_run(h, R0, path, n, dt=0.01, hi=(3000.0, -2000.0, 1500.0)):
    """Samples of a body turned by path(t) (the gyro-integrated attitude) from R0, with a body-fixed field hi."""
    b = np.array([0.0, 20000.0, -40000.0])
    hi = np.asarray(hi)
    for k in range(n):
        Q = path(k * dt)
        h.add(k * dt, (R0 @ Q).T @ b + hi, qof(Q))


def _tumble(t):
    return Rotation.from_euler("ZYX", [1.0 * t, 0.5 * math.sin(2.0 * t), 0.6 * math.sin(1.5 * t)]).as_matrix()


def test_hard_iron_from_rotation_solves_the_pairs_normal_equations():
    h = core.HardIronFromRotation(tau_s=2.0, min_info=0.25)
    hi = np.array([3000.0, -2000.0, 1500.0])
    R0 = Rotation.from_euler("ZYX", [0.3, 0.1, 0.2]).as_matrix()
    assert h.estimate() is None
    _hir_run(h, R0, _tumble, 200, hi=hi)
    assert h.estimate() is not None and np.allclose(h.estimate(), hi, atol=1e-6)
    assert 0.25 < np.linalg.eigvalsh(h.A)[0] < 0.6
    h.min_info = 0.6  # the information's smallest eigenvalue decides
    assert h.estimate() is None
    # one pair by hand: a fresh estimator, samples 0.05 s apart; the first pair at 0.2 s (0.8 × 0.2 s)
    g = core.HardIronFromRotation(tau_s=2.0, min_info=0.0, baseline_s=0.25, spacing_s=0.0625)
    w = np.array([0.6, -0.8, 1.0])
    b = np.array([0.0, 20000.0, -40000.0])
    for k in range(6):
        t = k * 0.0625
        g.add(t, (R0 @ rexp(w * t)).T @ b + hi, qof(rexp(w * t)))
        g.add(t + 0.01, np.zeros(3), (1.0, 0.0, 0.0, 0.0))  # inside the spacing: ignored
        if k < 4:
            assert not g.A.any()
    A, bb = np.zeros((3, 3)), np.zeros(3)
    for k in (4, 5):  # pairs 0.25 s apart: (0.25, 0), (0.3125, 0.0625)
        t1, t0 = k * 0.0625, (k - 4) * 0.0625
        Md = rexp(w * t1).T @ rexp(w * t0)
        M = np.eye(3) - Md
        m1, m0 = (R0 @ rexp(w * t1)).T @ b + hi, (R0 @ rexp(w * t0)).T @ b + hi
        a = 0.0625 / 2.0
        A, bb = (1 - a) * A + M.T @ M, (1 - a) * bb + M.T @ (m1 - Md @ m0)
    assert np.allclose(g.A, A, atol=1e-12) and np.allclose(g.b, bb, atol=1e-6)
    assert [x[0] for x in g.items] == [0.0625, 0.125, 0.1875, 0.25, 0.3125]


def test_hard_iron_from_rotation_needs_turning_about_every_axis():
    h = core.HardIronFromRotation(tau_s=2.0, min_info=0.5)
    _hir_run(h, np.eye(3), lambda t: rz(t), 150)  # about one axis: the offset along it is not observable
    lam = core.min_eig_sym3(*(h.A[i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))))
    assert lam < 1e-9 and h.estimate() is None
    g = core.HardIronFromRotation(tau_s=2.0, min_info=0.5)
    _hir_run(g, np.eye(3), lambda t: _tumble(0.1 * t), 150)  # < 0.05 rad per pair: below min_turn_rad, nothing added
    assert not g.A.any() and g.estimate() is None


def test_hard_iron_from_rotation_spacing_and_forgetting():
    w = np.array([0.6, -0.8, 1.0])
    b = np.array([0.0, 20000.0, -40000.0])

    def sample(t):
        return (rexp(w * t)).T @ b, qof(rexp(w * t))

    g = core.HardIronFromRotation(tau_s=0.5, min_info=0.0, baseline_s=0.25, spacing_s=0.0625)
    g.add(0.0, *sample(0.0))
    g.add(0.0625 - 1e-9, *sample(0.0625 - 1e-9))  # the spacing less the nanosecond slack: kept
    assert len(g.items) == 2
    g = core.HardIronFromRotation(tau_s=0.5, min_info=0.0, baseline_s=0.25, spacing_s=0.0625)
    pairs = []
    for t in (0.0, 0.25, 1.25):  # the last 1 s after the one before: more than tau, everything before forgotten
        g.add(t, *sample(t))
        pairs.append(g.A.copy())
    Md = rexp(w * 1.25).T @ rexp(w * 0.25)
    assert np.allclose(g.A, (np.eye(3) - Md).T @ (np.eye(3) - Md), atol=1e-12) and pairs[1].any()
    # a pair from 0.8 baseline_s apart exactly (0.25 s of 0.3125 s), at any time
    g = core.HardIronFromRotation(tau_s=0.5, min_info=0.0, baseline_s=0.3125, spacing_s=0.0625)
    for t in (5.0, 5.0625, 5.125, 5.1875):
        g.add(t, *sample(t))
    assert not g.A.any()
    g.add(5.25, *sample(5.25))
    Md = rexp(w * 5.25).T @ rexp(w * 5.0)
    assert np.allclose(g.A, (np.eye(3) - Md).T @ (np.eye(3) - Md), atol=1e-12)
    # the turn between the pair's attitudes: exactly min_turn_rad counts; none at all (|w| of q*q rounding above 1)
    q1 = qof(rexp((0.02, -0.01, 0.03)))
    turn = 2.0 * math.acos(min(1.0, abs(core._qmul((q1[0], -q1[1], -q1[2], -q1[3]), (1.0, 0.0, 0.0, 0.0))[0])))
    g = core.HardIronFromRotation(tau_s=0.5, min_info=0.0, min_turn_rad=turn)
    g.add(1.0, b, (1.0, 0.0, 0.0, 0.0))
    g.add(1.25, rexp((0.02, -0.01, 0.03)).T @ b, q1)
    assert g.A.any()
    q = (0.8620622389278576, 0.13060439483655198, -0.21952757388009944, -0.4377200390322391)
    assert core._qmul((q[0], -q[1], -q[2], -q[3]), q)[0] > 1.0
    g = core.HardIronFromRotation(tau_s=0.5, min_info=0.0)
    g.add(1.0, b, q)
    g.add(1.25, b, q)
    assert not g.A.any()


def test_hard_iron_estimate_needs_the_smallest_eigenvalue():
    h = core.HardIronFromRotation(tau_s=2.0, min_info=1.5)
    h.A = np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 3.0]])  # eigenvalues 1, 3, 3
    h.b = h.A @ np.array([100.0, -200.0, 300.0])
    assert h.estimate() is None
    h.min_info = core.min_eig_sym3(2.0, 1.0, 0.0, 2.0, 0.0, 3.0)
    assert h.min_info == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(h.estimate(), (100.0, -200.0, 300.0), atol=1e-9)  # at the limit: observable
    h.A = np.array([[3.0, 0.0, 1.0], [0.0, 3.0, 1.0], [1.0, 1.0, 3.0]])  # 3 − √2 ≈ 1.586
    h.min_info = 1.5
    assert h.estimate() is not None
    h.min_info = 1.6
    assert h.estimate() is None


def test_hard_iron_innovation_limits_and_wrap():
    """From the rotation estimate: a magnet exactly at the strength tolerance is used; the compensated field's
    strength and dip each exactly at their tolerance still count; the innovation is wrapped to ±π."""
    f = _aligned(hard_iron_tracking=True, hard_iron_from_rotation=True, hard_iron_min_info=0.5)
    f._hi_rot.A = np.eye(3)
    lim = f.settings.field_strength_tol_frac * f.ref_field_nt
    f._hi_rot.b = np.array([lim, 0.0, 0.0])
    assert f._hard_iron_innovation(FIELD + f._hi_rot.b, np.eye(3), 0.01) == pytest.approx(0.0, abs=1e-12)
    f._hi_rot.b = np.array([np.nextafter(lim, 0.0), 0.0, 0.0])
    assert f._hard_iron_innovation(FIELD + f._hi_rot.b, np.eye(3), 0.01) is None
    f._hi_rot.b = np.array([2000.0, 0.0, 0.0])
    f.ref_field_nt, f.ref_dip_rad = 40000.0, math.atan2(40000.0, 30000.0) - 0.1
    tol_dip = abs(math.atan2(40000.0, 30000.0) - f.ref_dip_rad)
    m = np.array([2000.0, 30000.0, -40000.0])  # less the magnet: 50,000 nT, 0.25 above 40,000; dip 0.1 steeper
    for strength_tol, dip_tol, used in ((0.25, tol_dip, True), (np.nextafter(0.25, 0.0), tol_dip, False),
                                        (0.25, np.nextafter(tol_dip, 0.0), False)):
        f.settings = core.Settings(hard_iron_tracking=True, hard_iron_from_rotation=True,
                                   sample_strength_tol_frac=strength_tol, sample_dip_tol_rad=dip_tol)
        assert (f._hard_iron_innovation(m, np.eye(3), 0.01) is not None) is used, (strength_tol, dip_tol)
    # an azimuth of −3.0 rad with a declination of 0.5: −3.5 is 2π − 3.5 the short way round
    f.settings = core.Settings(hard_iron_tracking=True, hard_iron_from_rotation=True, declination_rad=0.5,
                               sample_strength_tol_frac=0.3, sample_dip_tol_rad=0.3)
    m = np.array([2000.0 + 30000.0 * math.sin(-3.0), 30000.0 * math.cos(-3.0), -40000.0])
    assert f._hard_iron_innovation(m, np.eye(3), 0.01) == pytest.approx(2 * math.pi - 3.5, abs=1e-9)
    g = _aligned(hard_iron_tracking=True, hard_iron_tau_s=0.5, declination_rad=0.5)  # the slow mean wraps too
    g._hard_iron_t = 1.0
    dip = g.ref_dip_rad
    b_ref = g.ref_field_nt * np.array([math.cos(dip) * math.sin(0.5), math.cos(dip) * math.cos(0.5), -math.sin(dip)])
    g._hard_iron = np.array([1000.0, 0.0, 0.0])
    m = rz(3.5) @ b_ref + g._hard_iron  # the expected field turned 3.5 rad anticlockwise: azimuth −3.0
    out = g._hard_iron_innovation(m, np.eye(3), 0.0)  # (dt 0: the mean stays)
    assert out == pytest.approx(2 * math.pi - 3.5, abs=1e-9)



def test_hard_iron_from_rotation_must_explain_the_strength_offset():
    """A body-fixed h changes the strength by at most |h|: a magnet weaker than the window's strength offset
    |mean − reference| is not used even when it passes the strength tolerance; one exactly at the offset is."""
    f = _aligned(hard_iron_tracking=True, hard_iron_from_rotation=True, hard_iron_min_info=0.5)
    f._hi_rot.A = np.eye(3)
    B = f.ref_field_nt
    lim = f.settings.field_strength_tol_frac * B
    offset = 2.0 * lim
    m = FIELD + np.array([offset, 0.0, 0.0])
    for mean in (B + offset, B - offset):
        off = abs(mean - B)  # (the offset as the filter computes it, to the last bit)
        f._hi_rot.b = np.array([off, 0.0, 0.0])
        assert f._hard_iron_innovation(FIELD + f._hi_rot.b, np.eye(3), 0.01, mean) == pytest.approx(0.0, abs=1e-12)
        f._hi_rot.b = np.array([np.nextafter(off, 0.0), 0.0, 0.0])
        assert f._hard_iron_innovation(FIELD + f._hi_rot.b, np.eye(3), 0.01, mean) is None
    f._hi_rot.b = np.array([1.5 * lim, 0.0, 0.0])  # above the tolerance, below the offset
    assert f._hard_iron_innovation(m, np.eye(3), 0.01, B + offset) is None
    assert f._hard_iron_innovation(m, np.eye(3), 0.01, B) is not None  # no offset given: the tolerance alone

def test_min_eig_sym3_against_numpy():
    rng = np.random.default_rng(4)
    for _ in range(5):
        A = rng.normal(size=(3, 3))
        A = A + A.T
        got = core.min_eig_sym3(A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2])
        assert got == pytest.approx(np.linalg.eigvalsh(A)[0], abs=1e-12)
    assert core.min_eig_sym3(2.5, 0.0, 0.0, 2.5, 0.0, 2.5) == 2.5  # a multiple of I: p = 0
    assert core.min_eig_sym3(1.0, 0.0, 0.0, 2.0, 0.0, 3.0) == pytest.approx(1.0, abs=1e-12)
    assert core.min_eig_sym3(3.0, 0.0, 0.0, 1.0, 0.0, 2.0) == pytest.approx(1.0, abs=1e-12)
    assert core.min_eig_sym3(1.0, 1.0, 0.0, 1.0, 0.0, 5.0) == pytest.approx(0.0, abs=1e-12)
    # a double eigenvalue, where rounding takes r a little beyond ±1: clipped
    assert core.min_eig_sym3(0.1, 0.0, 0.0, -2.4, -2.5, -2.4) == pytest.approx(-4.9, abs=1e-12)
    b3 = 0.3 / 3
    assert core.min_eig_sym3(0.1 + b3, b3, b3, 0.1 + b3, b3, 0.1 + b3) == pytest.approx(0.1, abs=1e-12)


def test_hard_iron_from_rotation_in_the_filter():
    """With hard_iron_from_rotation the magnet is the rotation estimate (None, or weaker than the strength
    tolerance: no innovation) and the compensated field is fused with the sensor's own noise."""
    f = _aligned(hard_iron_tracking=True, hard_iron_from_rotation=True, hard_iron_min_info=0.5,
                 mag_vector_fusion=False, hard_iron_noise_gain=4.0)
    assert isinstance(f._hi_rot, core.HardIronFromRotation) and f._hi_rot.tau_s == 10.0
    assert f._hi_rot.min_info == 0.5 and _aligned()._hi_rot is None
    magnet = np.array([0.0, 4000.0, 0.0])  # the field 4.3 % stronger
    R = np.eye(3)
    assert f._hard_iron_innovation(FIELD + magnet, R, 0.01) is None  # nothing observable yet
    f._hi_rot.A = np.eye(3)
    f._hi_rot.b = np.array([0.0, 1000.0, 0.0])  # observable, but 1,000 nT < 3 % of 44,721
    assert f._hard_iron_innovation(FIELD + magnet, R, 0.01) is None
    f._hi_rot.b = magnet.copy()
    nu = f._hard_iron_innovation(rz(-0.02) @ FIELD + magnet, R, 0.01)
    assert nu == pytest.approx(0.02, abs=1e-12)
    # in the filter: the magnet on for 1 s makes it gyro_only; the compensated field then steers weakly
    g = _aligned(hard_iron_tracking=True, hard_iron_from_rotation=True, hard_iron_min_info=0.5,
                 mag_vector_fusion=False, hard_iron_noise_gain=4.0)
    _run(g, DT, 1.0, field=lambda t: FIELD + magnet)
    assert g.mode == "gyro_only"
    g._hi_rot.A, g._hi_rot.b = np.eye(3) * 1e6, magnet * 1e6
    g._hi_rot._last_t = 0.9375
    g.update_imu(ZERO, LEVEL, DT, t_s=1.0)
    R, P0 = rmat(g.q), g.P.copy()
    m = rz(-0.02) @ FIELD + magnet
    g.update_mag(m, True, t_s=1.0)
    nu_c = ref_innovation(R, P0, m - magnet, g.settings)[0]
    _, _, r_raw = ref_innovation(R, P0, m, g.settings)  # the raw field's leak, its noise without the window's gain
    dx, P = ref_heading_update(R, P0, nu_c, float(R[2] @ P0[:3, :3] @ R[2]) + 4.0 * r_raw)
    assert abs(nu_c) > 0.01
    assert np.allclose(rmat(g.q), R @ rexp(dx[:3]), atol=1e-12)
    assert np.allclose(g.P, P, atol=1e-12)
    t1, m1, q1 = g._hi_rot.items[-1]  # the filter feeds it the sample, its time and the gyro attitude
    assert t1 == 1.0 and np.array_equal(m1, m) and q1 == g._qg


# ---- field re-base ------------------------------------------------------------------------------------------------------
def test_rebase_learns_the_window_means_once_steady():
    f = _aligned(quasi_static_window_s=0.5)
    new = FIELD * 1.25
    f.rebase_field_reference()
    assert f._rebase_pending and len(f._window.items) == 0 and f.mode == "magnetic"
    strengths, dips = [], []
    for k in range(1, 40):
        m = _noisy_field(k, strength_sd=300.0) * 1.25
        _step(f, k * DT, m, True)
        mn = rmat(f.q) @ m
        if f._rebase_pending:
            assert not f.flags.field_inconsistent  # judged by steadiness alone meanwhile
            strengths.append(float(np.linalg.norm(mn)))
            dips.append(math.atan2(-mn[2], math.hypot(mn[0], mn[1])))
            continue
        break
    n = len(f._window.items)
    assert f.n_rebases == 1 and k == 27  # the window spans 0.4 s at its 27th sample
    assert f.ref_field_nt == pytest.approx(np.mean(strengths[-n + 1:] + [float(np.linalg.norm(mn))]), rel=1e-12)
    assert f.ref_dip_rad == pytest.approx(math.atan2(40000.0, 20000.0), abs=1e-9)
    assert f.ref_field_nt == pytest.approx(np.linalg.norm(new), rel=0.01)
    f.rebase_field_reference()  # a second calibration change: counted again
    for j in range(k + 1, k + 40):
        _step(f, j * DT, _noisy_field(j, strength_sd=300.0) * 1.1, True)
    assert f.n_rebases == 2 and not f._rebase_pending
    # a noisy window (strength variance above the limit) is no reference: still pending
    g = _aligned(quasi_static_window_s=0.5)
    g.rebase_field_reference()
    for k in range(1, 40):
        _step(g, k * DT, _noisy_field(k, strength_sd=2000.0) * 1.25, True)
    assert g._rebase_pending and g.n_rebases == 0


def test_rebase_ends_a_field_only_gyro_only_and_not_a_dmc_one():
    f = _disturbed()
    f.rebase_field_reference()
    assert f.mode == "recovering" and f.transitions[-1][3] == "calibration changed: field reference re-based"
    g = _aligned()
    _run(g, DT, 0.5, dmc=lambda t: False)
    g.rebase_field_reference()
    assert g.mode == "gyro_only" and g._rebase_pending
    h = core.HeadingFilter(core.Settings())
    h.rebase_field_reference()  # not aligned: nothing to re-base
    assert not h._rebase_pending


# ---- timing: late and lagging samples, the update period ----------------------------------------------------------------
def test_a_late_sample_is_levelled_with_the_attitude_of_its_time():
    f = _aligned(**ISOLATED, mag_gate_sigma=1e6, hard_iron_from_rotation=True)
    w = (0.3, -0.4, 0.8)
    for k in range(1, 11):
        f.update_imu(w, LEVEL, DT, t_s=k * DT)
    # the attitude at 4/64 s: the current estimate turned back by the gyro's motion since then
    q_then = rmat(f.q) @ rmat(f._qg).T @ rmat(f._history[3][1])
    q_before = rmat(f.q) @ rmat(f._qg).T @ rmat(f._history[2][1])
    assert f._history[3][0] == 4 * DT
    for t_s, R_exp in ((4 * DT, q_then), (4 * DT + 0.5 * DT, q_then), (4 * DT - 1e-9, q_then),
                       (4 * DT - 2e-9, q_before), (0.0, rmat(f.q) @ rmat(f._qg).T @ rmat(f._history[0][1]))):
        g = _copy(f)
        m = rz(0.2) @ FIELD
        g.update_mag(m, t_s=t_s)
        nu = ref_innovation(R_exp, g.P, m, g.settings)[0]
        assert g.internal_states.mag_innovation_rad == pytest.approx(nu, abs=1e-12), t_s
        if t_s == 4 * DT:  # the field pair estimator gets the sample's time and the gyro attitude then
            th, mh, qh = g._hi_rot.items[-1]
            assert th == t_s and np.array_equal(mh, m) and qh == f._history[3][1]
    # a magnetometer lag (mag_delay_s) means the same as a late time stamp
    h = _aligned(**ISOLATED, mag_gate_sigma=1e6, mag_delay_s=6 * DT)
    for k in range(1, 11):
        h.update_imu(w, LEVEL, DT, t_s=k * DT)
    h.update_mag(rz(0.2) @ FIELD)
    nu = ref_innovation(q_then, h.P, rz(0.2) @ FIELD, h.settings)[0]
    assert h.internal_states.mag_innovation_rad == pytest.approx(nu, abs=1e-12)
    # right after alignment there is no history: the current attitude
    e = _aligned(**ISOLATED, mag_gate_sigma=1e6)
    e.update_mag(rz(0.2) @ FIELD, t_s=-0.5)
    assert e.internal_states.mag_innovation_rad == pytest.approx(-0.2, abs=1e-12)


def _copy(f):
    import copy

    return copy.deepcopy(f)


def test_magnetometer_update_period_and_the_clamped_interval():
    g = _aligned(**ISOLATED, mag_update_period_s=0.1)
    g._last_mag_t = 0.0
    g.update_mag(rz(-0.001) @ FIELD, t_s=0.1 - 1e-9)  # exactly the period less the nanosecond slack: taken
    assert g._last_mag_t == 0.1 - 1e-9
    f = _aligned(**ISOLATED, mag_update_period_s=0.1)
    f._last_mag_t = 0.0
    res = []
    for t in (0.05, 0.1 - 5e-10, 0.15, 0.2 - 2e-9, 0.2 + 1e-9):
        f.update_imu(ZERO, LEVEL, DT, t_s=t)
        nu_before = f.internal_states.mag_innovation_rad
        r = f.update_mag(rz(-0.001 * t) @ FIELD, t_s=t)
        res.append((r, f.internal_states.mag_innovation_rad != nu_before))
    assert res == [(False, False), (True, True), (True, False), (True, False), (True, True)]
    assert f._last_mag_t == 0.2 + 1e-9
    # the interval a slew uses is at most 1 s however long the gap
    g = _aligned(**dict(HOLDS, holds_scale_with_outage=False, init_heading_std_rad=0.005, recovery_hold_s=0.5,
                        recovery_slew_rad_s=0.01))
    _run(g, DT, 2.5, dmc=lambda t: t < 2.0)
    g.q = qof(rz(0.5))
    _run(g, 2.5, 4.5)
    assert g.mode == "recovering"
    g.update_imu(ZERO, LEVEL, 3.0, t_s=7.5)
    h0 = g.heading_rad()
    g.update_mag(FIELD, True, t_s=7.5)
    assert math.remainder(g.heading_rad() - h0, 2 * math.pi) == pytest.approx(0.01, rel=1e-5)  # not 3 s × the rate


def test_the_lag_estimator_is_fed_and_read():
    f = _aligned(mag_delay_online=True, mag_delay_max_s=0.02)
    assert isinstance(f._lag, core.MagLagEstimator) and f._lag.grid[-1] == pytest.approx(0.02)
    f.update_imu((0.0, 0.0, 0.5), LEVEL, DT, t_s=DT)
    assert f._lag._i == 1 and f._lag._gt[0] == DT
    f._lag.delay_s = 0.0123
    f.update_mag(FIELD, t_s=DT)
    assert f.mag_delay_s == 0.0123 and len(f._lag._mags) == 1 and f._lag._mags[0][0] == DT
    f.update_imu((0.0, 0.0, 0.5), LEVEL, DT, t_s=2 * DT)
    f.update_mag(FIELD * 1.2, t_s=2 * DT)  # 20 % off the filter's reference: the estimator does not keep it
    assert len(f._lag._mags) == 1
    assert _aligned()._lag is None


def test_dmc_verdict_flag():
    for use, verdict, valid in ((True, None, True), (True, False, False), (True, 0, False), (False, False, True),
                                (True, True, True)):
        f = _aligned(use_dmc=use)
        f.update_mag(FIELD, verdict, t_s=DT)
        assert f.flags.dmc_valid is valid
        assert f.mode == ("magnetic" if valid else "gyro_only")


def test_agreement_from_clear_counts_the_clear_hold():
    """agreement_from_clear: the agreement hold (|ν| ≤ recovery_exit_rad) starts with the clear hold; it restarts
    whenever the heading disagrees or the disturbance returns, and recovering ends once it has lasted its hold."""
    s = dict(HOLDS, holds_scale_with_outage=False, agreement_from_clear=True)

    def back(**kw):
        f = _aligned(**s)
        _run(f, DT, 6.0, **kw)
        return [tr[0] for tr in f.transitions[1:]], f

    times, f = back(dmc=lambda t: not 2.0 <= t < 2.5)
    assert times == [2.0, 3.5, 4.5]  # recovering after the 1 s clear hold, magnetic 2 s after the clear began
    assert f.transitions[-1][2:] == ("magnetic", "magnetometer consistent and its heading agrees")
    times, _ = back(dmc=lambda t: not 2.0 <= t < 2.5, field=lambda t: rz(-0.05) @ FIELD if 2.5 <= t < 3.0 else FIELD)
    assert times == [2.0, 3.5, 5.0]  # 0.05 rad off (outside recovery_exit_rad) until 3.0 s: from then
    times, _ = back(dmc=lambda t: not (2.0 <= t < 2.5 or t == 2.75))
    assert times == [2.0, 2.75 + DT + 1.0, 2.75 + DT + 2.0]  # disturbed again at 2.75 s: both start over
    g = _aligned(**dict(HOLDS, agreement_from_clear=True))  # scaled holds: 0.5 s each, from the same start
    _run(g, DT, 4.0, dmc=lambda t: not 2.0 <= t < 2.5)
    assert [tr[0] for tr in g.transitions[1:]] == [2.0, 3.0, 3.0 + DT]


# ---- boundaries, wraps and the window's inputs -----------------------------------------------------------------------
def test_window_full_from_three_samples():
    w = core._Window(0.625)
    for t in (20.0, 20.25, 20.5):
        w.add(t, 1.0, 1.0, 0.0)
    assert w.full(20.5)


def test_the_innovation_is_wrapped_to_plus_minus_pi():
    f = _aligned(**ISOLATED, declination_rad=0.6, mag_gate_sigma=1e6)
    f.q = (1.0, 0.0, 0.0, 0.0)
    f.update_mag(rz(3.0) @ FIELD)  # azimuth −3.0: −3.6 from the declination, 2π − 3.6 the short way
    assert f.internal_states.mag_innovation_rad == pytest.approx(2 * math.pi - 3.6, abs=1e-12)


def test_the_window_gets_the_magnetometer_yaw_less_the_gyro_yaw():
    """What the quasi-static heading test compares: the filter's yaw plus the innovation (the yaw the magnetometer
    implies) less the integrated gyro yaw, wrapped."""
    for yaw, nu, gyro_yaw in ((0.7, 0.3, -0.4), (2.9, 0.4, -0.5), (-2.9, -0.3, 0.4)):
        f = _aligned(**ISOLATED, mag_gate_sigma=1e-9)
        R = Rotation.from_euler("ZYX", [yaw, 0.2, -0.1]).as_matrix()
        f.q = qof(R)
        f._gyro_yaw = gyro_yaw
        b = rz(-nu) @ FIELD  # azimuth nu in the true frame: the innovation
        f.update_mag(R.T @ b)
        assert f.internal_states.mag_innovation_rad == pytest.approx(nu, abs=1e-12)
        want = math.remainder(yaw + nu - gyro_yaw, 2 * math.pi)
        assert f._window.items[-1][3] == pytest.approx(want, abs=1e-12), (yaw, nu, gyro_yaw)
        assert abs(yaw + nu - gyro_yaw) > math.pi or yaw == 0.7  # the wrap is exercised


def _exact_window(ms):
    """The window's running sums as the filter keeps them (R = I, no sample leaves): means and variances."""
    s = [0.0, 0.0, 0.0, 0.0]
    for m in ms:
        h2 = m[0] * m[0] + m[1] * m[1]
        st = math.sqrt(h2 + m[2] * m[2])
        d = math.atan2(-m[2], math.sqrt(h2))
        s = [s[0] + st, s[1] + st * st, s[2] + d, s[3] + d * d]
    n = len(ms)
    mb, md = s[0] / n, s[2] / n
    return mb, max(0.0, s[1] / n - mb * mb), md, max(0.0, s[3] / n - md * md)


@pytest.mark.parametrize("which", ["strength", "dip", "strength_var", "dip_var", "heading"])
def test_window_limits_are_strict(which):
    """Each window test at exactly its limit passes; a hair below the limit, it fails. The filter stays level and
    unturned (every sample rejected by a vanishing gate), so the window's sums are reproduced exactly here."""
    n = 53  # the first full window: 52 · 1/64 s ≥ 0.8 s
    ref_b, ref_dip = 32768.0, 1.0  # (a power of two: tol · B0 is exact)
    base = dict(ISOLATED, use_field_check=True, adaptive_noise=True, mag_gate_sigma=1e-9, ref_field_nt=ref_b,
                ref_dip_rad=ref_dip, sample_strength_tol_frac=0.5, sample_dip_tol_rad=0.5, field_strength_tol_frac=0.1)

    def sample(k):
        sgn = 1.0 if k % 2 else -1.0
        bs = 34000.0 + (700.0 * sgn if which == "strength_var" else 0.0)
        dip = 1.05 + (0.01 * sgn if which == "dip_var" else 0.0)
        az = 0.0003 * k if which == "heading" else 0.0
        return np.array([bs * math.cos(dip) * math.sin(az), bs * math.cos(dip) * math.cos(az), -bs * math.sin(dip)])

    ms = [sample(k) for k in range(1, n + 1)]
    mb, vb, md, vd = _exact_window(ms)
    dpsi = abs(math.remainder(math.atan2(ms[-1][0], ms[-1][1]) - math.atan2(ms[0][0], ms[0][1]), 2 * math.pi))
    limit = {"strength": ("field_strength_tol_frac", abs(mb - ref_b) / ref_b), "dip": ("field_dip_tol_rad",
             abs(md - ref_dip)), "strength_var": ("quasi_static_var_nt2", vb), "dip_var": ("quasi_static_dip_var_rad2",
             vd), "heading": ("quasi_static_heading_rad", dpsi)}[which]
    if which == "strength":  # the limit is tol · B0: that product is exact
        assert limit[1] * ref_b == abs(mb - ref_b)
    results = []
    for value in (limit[1], np.nextafter(limit[1], 0.0)):
        f = _aligned(**dict(base, **{limit[0]: value}))
        assert f.q == (1.0, 0.0, 0.0, 0.0)
        for k, m in enumerate(ms, start=1):
            f.update_mag(m, t_s=k * DT)
        assert f.q == (1.0, 0.0, 0.0, 0.0) and len(f._window.items) == n
        results.append((f.mode, f.flags.quasi_static, f.internal_states.mag_noise_gain))
    if which in ("strength", "dip"):
        assert [r[0] for r in results] == ["magnetic", "gyro_only"]
    else:
        assert [r[1:] for r in results] == [(True, 1.0), (False, 150.0 if which == "heading" else 200.0)]


def test_the_gate_at_a_test_ratio_of_exactly_one_fuses():
    y = 20000.0
    x = y * math.tan(1.0)
    while math.atan2(x, y) != 1.0:  # a field whose azimuth is exactly 1 rad
        x = np.nextafter(x, math.inf if math.atan2(x, y) < 1.0 else 0.0)
    f = _aligned(**ISOLATED, mag_gate_sigma=1.0, mag_heading_noise_floor_rad=0.5)
    f.P[:3, :3] = np.diag([0.0, 0.0, 0.75])  # S = 0.75 + 0.5² = 1 = ν²
    assert f.update_mag((x, y, -40000.0))
    assert f.internal_states.mag_test_ratio == 1.0 and not f.flags.mag_rejected_gate


def test_no_hard_iron_tracking_while_the_dmc_says_invalid():
    f = _aligned(hard_iron_tracking=True, hard_iron_tau_s=0.25)
    _run(f, DT, 1.5, field=lambda t: FIELD + np.array([6000.0, 2000.0, -1000.0]), dmc=lambda t: False)
    assert f.mode == "gyro_only" and not f._hard_iron.any() and f._hard_iron_t == 0.0
    g = _aligned(hard_iron_tracking=False, hard_iron_tau_s=0.25, disturbed_noise_gain=2.0)
    g._hard_iron_t = 1.0
    g._hard_iron = np.array([6000.0, 2000.0, -1000.0])
    _run(g, DT, 1.5, field=lambda t: FIELD + np.array([6000.0, 2000.0, -1000.0]))
    assert g.mode == "gyro_only" and g._hard_iron_t == 1.0  # not tracked when turned off


@pytest.mark.parametrize("rotation", [False, True])
def test_hard_iron_fusion_noise_with_a_noisy_field(rotation):
    """A noisy field (its strength variance fails the window test: gain 200): the slow-mean magnet's innovation is
    fused with the raw field's adaptive noise × hard_iron_noise_gain; the rotation estimate's with the sensor's own
    noise × hard_iron_noise_gain."""
    kw = dict(hard_iron_tracking=True, hard_iron_tau_s=0.25, hard_iron_noise_gain=3.0, mag_vector_fusion=False,
              hard_iron_from_rotation=rotation, hard_iron_min_info=0.5)
    f = _aligned(**kw)
    magnet = np.array([0.0, 4000.0, 0.0])
    noisy = [rz(-0.02) @ FIELD * (1.0 + (0.03 if k % 2 else -0.03)) + magnet for k in range(200)]
    k = 0
    for k in range(1, 96):
        _step(f, k * DT, noisy[k], True)
    assert f.mode == "gyro_only"
    if rotation:
        f._hi_rot.A, f._hi_rot.b = np.eye(3) * 1e6, magnet * 1e6
    t = 96 * DT
    f.update_imu(ZERO, LEVEL, DT, t_s=t)
    R, P0 = rmat(f.q), f.P.copy()
    m = noisy[96]
    hi = magnet if rotation else f._hard_iron + (DT / 0.25) * ((m - R.T @ FIELD) - f._hard_iron)
    q0 = f.q
    f.update_mag(m, True, t_s=t)
    gain = f.internal_states.mag_noise_gain
    assert gain == 200.0
    nu_c = ref_innovation(R, P0, m - hi, f.settings)[0]
    assert f.q != q0 and abs(nu_c) > 1e-4
    _, _, r_raw = ref_innovation(R, P0, m, f.settings, gain=1.0 if rotation else gain)
    dx, P = ref_heading_update(R, P0, nu_c, float(R[2] @ P0[:3, :3] @ R[2]) + 3.0 * r_raw)
    assert np.allclose(rmat(f.q), R @ rexp(dx[:3]), atol=1e-12)
    assert np.allclose(f.P, P, atol=1e-12)


def _dry_nu(f, m, dmc, t):
    g = _copy(f)
    g.update_imu(ZERO, LEVEL, DT, t_s=t)
    g.update_mag(m, dmc, t_s=t)
    return g.internal_states.mag_innovation_rad


def test_weak_fusion_gate_is_strict():
    f = _disturbed(disturbed_noise_gain=50.0, mag_vector_fusion=False)
    m = rz(-0.2) @ FIELD * 1.08
    nu = abs(_dry_nu(f, m, True, 1.0))
    for gate, weak in ((nu, False), (np.nextafter(nu, 1.0), True)):
        g = _copy(f)
        g.settings = core.Settings(**{**g.settings.__dict__, "disturbed_gate_rad": gate})
        g.update_imu(ZERO, LEVEL, DT, t_s=1.0)
        q0 = g.q
        g.update_mag(m, True, t_s=1.0)
        assert (g.q != q0) is weak


def _at_the_exit_band_and_just_inside_it(f, t):
    """Copies of ``f`` stepped at ``t`` with a field 0.02 rad off, ``recovery_exit_rad`` set to exactly the
    innovation that field gives (inside the band: True) and to the next float below it (outside: False)."""
    m = rz(-0.02) @ FIELD
    nu = abs(_dry_nu(f, m, True, t))
    for band, inside in ((nu, True), (np.nextafter(nu, 0.0), False)):
        g = _copy(f)
        g.settings = core.Settings(**{**g.settings.__dict__, "recovery_exit_rad": band})
        _step(g, t, m, True)
        yield g, inside


def test_recovering_exit_band_is_inclusive():
    f = _aligned(**dict(HOLDS, holds_scale_with_outage=False, mag_vector_fusion=False))
    _run(f, DT, 2.5, dmc=lambda t: t < 2.0)
    _run(f, 2.5, 3.5 + DT)
    assert f.mode == "recovering" and f._inside_gate_since_t is None
    t = 3.5 + 2 * DT
    for g, inside in _at_the_exit_band_and_just_inside_it(f, t):
        assert (g._inside_gate_since_t == t) is inside


def test_agreement_band_during_the_clear_hold_is_inclusive():
    f = _aligned(**dict(HOLDS, holds_scale_with_outage=False, mag_vector_fusion=False, agreement_from_clear=True))
    _run(f, DT, 2.5, dmc=lambda t: t < 2.0)
    assert f.mode == "gyro_only"
    t = 2.5
    for g, inside in _at_the_exit_band_and_just_inside_it(f, t):
        assert g.mode == "gyro_only" and (g._inside_gate_since_t == t) is inside


def test_recovering_after_a_rebase_slews_only_once_the_new_window_is_full():
    """A re-base empties the window: the consistency hold (and so the slew outside the gate) starts only once the
    window is full again."""
    s = dict(HOLDS, init_heading_std_rad=0.005, recovery_hold_s=0.25, quasi_static_var_nt2=1e12,
             quasi_static_dip_var_rad2=10.0)
    f = _aligned(**s)
    _run(f, DT, 1.0, field=lambda t: FIELD * 1.08)
    assert f.mode == "gyro_only"
    f.q = qof(rz(0.5))
    f.rebase_field_reference()
    assert f.mode == "recovering" and len(f._window.items) == 0
    first = None
    for k in range(1, 100):
        t = 1.0 + k * DT
        h0 = f.heading_rad()
        _step(f, t, FIELD * 1.08, True)
        if first is None and abs(math.remainder(f.heading_rad() - h0, 2 * math.pi)) > 1e-6:
            first = k
    # the window is full at its 53rd sample (0.8 s); the hold of 0.25 s more: 16 samples
    assert first == 53 + 16, first


def test_a_field_failure_in_an_outage_counts_until_magnetic_again():
    """The field checks failed in an outage: full holds after it, also for a DMC-only disturbance before the filter
    is magnetic again; once magnetic, a DMC-only outage has scaled holds again."""
    f = _aligned(**dict(HOLDS, quasi_static_window_s=0.25))

    def field(t):
        return FIELD * 1.4 if 2.0 <= t < 2.25 else FIELD

    _run(f, DT, 3.0, field=field)
    assert f.mode == "gyro_only" and f._outage_field_bad
    rec = []
    for k in range(192, 800):
        t = k * DT
        _step(f, t, FIELD, not 4.0 <= t < 4.25 and not 8.0 <= t < 8.25)
        if f.transitions[-1][0] == t:
            rec.append((t, f.transitions[-1][2]))
        if t >= 12.0:
            break
    # recovering (full clear hold), a DMC-only blip at 4.0 s: gyro_only again, full holds (the field failure
    # still counts), magnetic; a DMC-only blip at 8.0 s: scaled holds (0.25 s each)
    modes = [m for _, m in rec]
    assert modes == ["recovering", "gyro_only", "recovering", "magnetic", "gyro_only", "recovering", "magnetic"], rec
    assert rec[1][0] == 4.0 and rec[2][0] == 4.25 + 1.0
    assert rec[4][0] == 8.0 and rec[5][0] == 8.25 + 0.25 and rec[6][0] == 8.5 + DT + 0.25
