"""Pins of the DMC detector's stage 1 (services/dmc_detector/core.py) against an independent reference.

The inputs are built in closed form from what each compass should see (its heading ψ_k, a field-strength
scale, the vertical field), passed through the inverse of a non-trivial static compensation, and the
expected features are computed here by explicit loops straight from the method's definitions:

    Δm_k = |h_k| − R_k   (the horizontal strength for a 2-D calibration)     dΔm_k its windowed rate
    Δh   = ψ_1 − ψ_2 − Δh_r                                                    dΔh  its windowed rate

Stage 1 passes only when |Δm_k| < V_Δm for both compasses (the worse one decides), |dΔm_k| < V_dΔm,
|Δh| < V_Δh and |dΔh| < V_dΔh. Each test is shown to trigger on its own, with the other three passing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from magmesh import maths
from services.dmc_detector import core
from services.dmc_detector.core import CompassParams, FeatureSettings, Thresholds

RATE_HZ = 50.0
DECL = math.radians(-1.0)
BH_NT, BZ_NT = 33000.0, -35000.0  # horizontal and vertical Earth field at the site
B3_NT = math.hypot(BH_NT, BZ_NT)
TH = Thresholds()  # V_Δm 1000 nT, V_dΔm 1000 nT/s, V_Δh 3°, V_dΔh 3°/s
FS = FeatureSettings()  # smooth 0.2 s, rate 0.5 s apart


def _params(seed: int, model: str) -> CompassParams:
    rng = np.random.default_rng(seed)
    M = np.eye(3) + rng.normal(0, 0.03, (3, 3))
    off = rng.normal(0, 800.0, 3)
    return CompassParams(tuple(off), tuple(M.ravel()), BH_NT if model == "2d" else B3_NT, model=model)


P1_3D, P2_3D = _params(1, "3d"), _params(2, "3d")
P1_2D, P2_2D = _params(3, "2d"), _params(4, "2d")


def _reading(p: CompassParams, psi, scale, bz_nt) -> np.ndarray:
    """The raw reading whose compensation is the level FLU field of heading ψ (N×3), strength × scale."""
    psi, scale, bz = (np.broadcast_to(np.asarray(a, float), np.shape(psi)) for a in (psi, scale, bz_nt))
    h = np.stack([scale * BH_NT * np.cos(psi - DECL), scale * BH_NT * np.sin(psi - DECL), scale * bz], axis=-1)
    return np.linalg.solve(p.M, h.T).T + np.asarray(p.offset_nt)


def _ref_features(t, dm, dh):
    """Windowed features by explicit loops: means over (t − smooth, t], rates to the newest mean at or
    before t − rate, ready once smooth + rate of input has been seen."""
    n = len(t)
    dm_s = np.array([dm[[k for k in range(i + 1) if t[k] > t[i] - FS.smooth_window_s]].mean(axis=0)
                     for i in range(n)])
    dh_s = np.array([math.atan2(*(lambda w: (np.sin(dh[w]).sum(), np.cos(dh[w]).sum()))(
        [k for k in range(i + 1) if t[k] > t[i] - FS.smooth_window_s])) for i in range(n)])
    ddm = np.zeros((n, 2))
    ddh = np.zeros(n)
    ready = np.zeros(n, bool)
    for i in range(n):
        js = [k for k in range(i + 1) if t[k] <= t[i] - FS.rate_window_s]
        if js and t[i] - t[0] >= FS.history_s - 1e-9:
            j = js[-1]
            ready[i] = True
            ddm[i] = (dm_s[i] - dm_s[j]) / (t[i] - t[j])
            ddh[i] = float(maths.angle_diff(dh_s[i], dh_s[j])) / (t[i] - t[j])
    return ddm, ddh, ready


def _expected_failed(dm, ddm, dh, ddh, ready):
    """Names of the failing tests per epoch, from the reference features and the thresholds."""
    out = []
    for i in range(len(dh)):
        f = set()
        if max(abs(dm[i, 0]), abs(dm[i, 1])) >= TH.dm_nt:
            f.add("dm")
        if ready[i] and max(abs(ddm[i, 0]), abs(ddm[i, 1])) >= TH.ddm_nt_s:
            f.add("ddm")
        if abs(math.degrees(dh[i])) >= TH.dh_deg:
            f.add("dh")
        if ready[i] and abs(math.degrees(ddh[i])) >= TH.ddh_deg_s:
            f.add("ddh")
        out.append(f)
    return out


def _scenario(duration_s, psi1, psi2, s1, s2, bz=BZ_NT, model="3d", dh_ref_rad=0.0):
    """Run batch and streaming forms on a built scenario; return (t, batch features, decisions, reference)."""
    t = np.arange(int(round(duration_s * RATE_HZ))) / RATE_HZ
    psi1, psi2, s1, s2, bz = (np.broadcast_to(np.asarray(f(t) if callable(f) else f, float), t.shape)
                              for f in (psi1, psi2, s1, s2, bz))
    p1, p2 = (P1_2D, P2_2D) if model == "2d" else (P1_3D, P2_3D)
    b1, b2 = _reading(p1, psi1, s1, bz), _reading(p2, psi2, s2, bz)
    # the reference: strengths and headings as built, never read back through the core
    if model == "2d":
        dm = np.stack([(s1 - 1.0) * BH_NT, (s2 - 1.0) * BH_NT], axis=1)
    else:
        dm = np.stack([s1 * np.hypot(BH_NT, bz) - B3_NT, s2 * np.hypot(BH_NT, bz) - B3_NT], axis=1)
    dh = np.asarray(maths.angle_diff(psi1 - psi2, dh_ref_rad), float)
    ddm, ddh, ready = _ref_features(t, dm, dh)
    fs = FeatureSettings(dh_ref_rad=dh_ref_rad)
    fb = core.features_batch(t, b1, b2, p1, p2, DECL, fs)
    det = core.ThresholdDetector(core.ThresholdDetectorSettings(thresholds=TH, features=fs))
    decisions = [det.update(float(t[i]), b1[i], b2[i], p1, p2, DECL) for i in range(len(t))]
    ref = {"dm": dm, "ddm": ddm, "dh": dh, "ddh": ddh, "ready": ready,
           "failed": _expected_failed(dm, ddm, dh, ddh, ready)}
    return t, fb, decisions, ref


def _check_against_reference(fb, decisions, ref):
    np.testing.assert_allclose(fb.dm_nt, ref["dm"], atol=1e-6)
    np.testing.assert_allclose(fb.dh_rad, ref["dh"], atol=1e-9)
    np.testing.assert_array_equal(fb.rates_ready, ref["ready"])
    np.testing.assert_allclose(fb.ddm_nt_s, ref["ddm"], atol=1e-5)
    np.testing.assert_allclose(fb.ddh_rad_s, ref["ddh"], atol=1e-9)
    ok = core.threshold_test(fb, TH)
    np.testing.assert_array_equal(ok, [not f for f in ref["failed"]])
    for i, d in enumerate(decisions):
        assert set(d.failed) == ref["failed"][i], (i, d.failed, ref["failed"][i])
        assert d.stage1_pass == (not ref["failed"][i]) and d.valid == d.stage1_pass
        np.testing.assert_allclose(d.dm_nt, ref["dm"][i], atol=1e-6)
        assert d.dh_rad == pytest.approx(ref["dh"][i], abs=1e-9)


PSI = math.radians(40.0)


# ---- each test on its own -----------------------------------------------------------------------


@pytest.mark.parametrize("worse", [0, 1])
def test_dm_alone_and_the_worse_compass_decides(worse):
    # one compass 500 nT strong (passes alone), the other 1500 nT (fails): the worse one decides, either way round
    s = [1.0 + 500.0 / B3_NT, 1.0 + 1500.0 / B3_NT]
    if worse == 0:
        s = s[::-1]
    t, fb, decisions, ref = _scenario(2.0, PSI, PSI, s[0], s[1])
    _check_against_reference(fb, decisions, ref)
    assert all(f == {"dm"} for f in ref["failed"])
    assert all(d.failed == ("dm",) for d in decisions)
    assert max(abs(v) for v in decisions[-1].dm_nt) == pytest.approx(1500.0, abs=1e-6)
    # and the stronger compass alone at 500 nT passes
    _, fb, decisions, ref = _scenario(2.0, PSI, PSI, 1.0 + 500.0 / B3_NT, 1.0 - 500.0 / B3_NT)
    _check_against_reference(fb, decisions, ref)
    assert all(d.stage1_pass for d in decisions)


def test_dm_fails_on_a_weak_field_too():
    _, fb, decisions, ref = _scenario(2.0, PSI, PSI, 1.0, 1.0 - 1200.0 / B3_NT)
    _check_against_reference(fb, decisions, ref)
    assert all(d.failed == ("dm",) for d in decisions)
    assert decisions[-1].dm_nt[1] == pytest.approx(-1200.0, abs=1e-6)


@pytest.mark.parametrize("compass", [0, 1])
def test_ddm_alone(compass):
    # Δm of one compass ramps −900 → +900 nT at 1500 nT/s: |Δm| < 1000 throughout, the rate 1.5× its threshold
    ramp = lambda t: 1.0 + (-900.0 + 1500.0 * t) / B3_NT  # noqa: E731
    s1, s2 = (ramp, 1.0) if compass == 0 else (1.0, ramp)
    t, fb, decisions, ref = _scenario(1.2, PSI, PSI, s1, s2)
    _check_against_reference(fb, decisions, ref)
    ready = ref["ready"]
    assert ready.sum() >= 20
    assert all(d.failed == ("ddm",) for d, r in zip(decisions, ready, strict=True) if r)
    assert all(d.stage1_pass for d, r in zip(decisions, ready, strict=True) if not r)  # rate unknown: not failing
    assert decisions[-1].ddm_nt_s[compass] == pytest.approx(1500.0, rel=0.04)  # window edges: ±1 sample


def test_dh_alone():
    # compass 2 reads 5° more than compass 1, equal strengths: only |Δh| fails
    _, fb, decisions, ref = _scenario(2.0, PSI, PSI + math.radians(5.0), 1.0, 1.0)
    _check_against_reference(fb, decisions, ref)
    assert all(d.failed == ("dh",) for d in decisions)
    assert math.degrees(decisions[-1].dh_rad) == pytest.approx(-5.0, abs=1e-9)


def test_ddh_alone():
    # Δh ramps −2.8° → +2.7° at 5°/s: |Δh| < 3° throughout, the rate above its 3°/s
    psi2 = lambda t: PSI + np.radians(2.8 - 5.0 * t)  # noqa: E731
    t, fb, decisions, ref = _scenario(1.1, PSI, psi2, 1.0, 1.0)
    _check_against_reference(fb, decisions, ref)
    ready = ref["ready"]
    assert ready.sum() >= 15
    assert all(d.failed == ("ddh",) for d, r in zip(decisions, ready, strict=True) if r)
    assert all(d.stage1_pass for d, r in zip(decisions, ready, strict=True) if not r)
    assert math.degrees(decisions[-1].ddh_rad_s) == pytest.approx(5.0, abs=0.2)  # window edges: ±1 sample


def test_a_clean_turn_passes_every_test():
    # both compasses turn together at 20°/s, no disturbance: every feature ~0, all four tests pass
    turn = lambda t: PSI + math.radians(20.0) * t  # noqa: E731
    _, fb, decisions, ref = _scenario(3.0, turn, turn, 1.0, 1.0)
    _check_against_reference(fb, decisions, ref)
    assert all(d.stage1_pass for d in decisions)
    assert max(abs(d.dh_rad) for d in decisions) < 1e-9


# ---- Δh_r, the 2-D strength, the threshold boundary ------------------------------------------------


def test_dh_ref_is_subtracted_with_its_sign():
    # compass 2 mounted 4° clockwise of compass 1: ψ1 − ψ2 = −4°
    psi2 = PSI + math.radians(4.0)
    # Δh_r = −4° compensates the mounting exactly
    _, fb, decisions, ref = _scenario(2.0, PSI, psi2, 1.0, 1.0, dh_ref_rad=math.radians(-4.0))
    _check_against_reference(fb, decisions, ref)
    assert all(d.stage1_pass for d in decisions)
    assert max(abs(d.dh_rad) for d in decisions) < 1e-9
    # Δh_r = +1°: Δh = −4° − 1° = −5° (fails); the opposite sign would give −3° + 0 … −3°
    _, fb, decisions, ref = _scenario(2.0, PSI, psi2, 1.0, 1.0, dh_ref_rad=math.radians(1.0))
    _check_against_reference(fb, decisions, ref)
    assert math.degrees(decisions[-1].dh_rad) == pytest.approx(-5.0, abs=1e-9)
    assert all(d.failed == ("dh",) for d in decisions)
    # Δh_r = −2°: Δh = −2° (passes); with the sign flipped it would be −6° and fail
    _, fb, decisions, ref = _scenario(2.0, PSI, psi2, 1.0, 1.0, dh_ref_rad=math.radians(-2.0))
    _check_against_reference(fb, decisions, ref)
    assert math.degrees(decisions[-1].dh_rad) == pytest.approx(-2.0, abs=1e-9)
    assert all(d.stage1_pass for d in decisions)


def test_2d_strength_ignores_the_vertical_field():
    # a 2-D calibration: the vertical field swings by ±8000 nT (a tilted or passing source seen only in z);
    # the horizontal strength, and so Δm, stays at its radius
    bz = lambda t: BZ_NT + 8000.0 * np.sin(2 * np.pi * 0.5 * t)  # noqa: E731
    _, fb, decisions, ref = _scenario(3.0, PSI, PSI, 1.0, 1.0, bz=bz, model="2d")
    _check_against_reference(fb, decisions, ref)
    assert np.abs(fb.dm_nt).max() < 1e-6
    assert all(d.stage1_pass for d in decisions)
    # the horizontal strength 1200 nT over the radius of compass 1 fails, whatever z does
    _, fb, decisions, ref = _scenario(2.0, PSI, PSI, 1.0 + 1200.0 / BH_NT, 1.0, bz=bz, model="2d")
    _check_against_reference(fb, decisions, ref)
    assert decisions[-1].dm_nt[0] == pytest.approx(1200.0, abs=1e-6)
    assert all("dm" in d.failed for d in decisions)


def test_3d_strength_is_the_total_field():
    # a 3-D calibration sees the same vertical change as a strength change (|h| − R with the full norm)
    _, fb, decisions, ref = _scenario(2.0, PSI, PSI, 1.0, 1.0, bz=BZ_NT - 3000.0)
    _check_against_reference(fb, decisions, ref)
    expected = math.hypot(BH_NT, BZ_NT - 3000.0) - B3_NT
    assert decisions[-1].dm_nt == pytest.approx([expected, expected], abs=1e-6)
    assert expected > TH.dm_nt and all(d.failed == ("dm",) for d in decisions)


@pytest.mark.parametrize("name,col", [("dm", 0), ("ddm", 1), ("dh", 2), ("ddh", 3)])
def test_each_threshold_is_strict_and_alone(name, col):
    """|feature| = threshold fails, a hair below passes; only the named test moves."""
    thr = {"dm": TH.dm_nt, "ddm": TH.ddm_nt_s, "dh": TH.dh_deg, "ddh": TH.ddh_deg_s}[name]
    for value, sign in ((thr, 1.0), (thr, -1.0), (thr * (1 - 1e-9), 1.0), (thr * (1 - 1e-9), -1.0)):
        f = core.Features(np.zeros(2), np.zeros((2, 2)), np.zeros((2, 2)), np.zeros(2), np.zeros(2), np.zeros(2),
                          np.zeros(2), np.ones(2, bool))
        v = sign * value
        if name == "dm":
            f.dm_nt[:, 1] = v  # compass 2 only: the worse compass decides
        elif name == "ddm":
            f.ddm_nt_s[:, 0] = v
        elif name == "dh":
            f.dh_rad[:] = math.radians(v)
        else:
            f.ddh_rad_s[:] = math.radians(v)
        r = core.test_ratios(f, TH)
        assert r[0, col] == pytest.approx(value / thr, rel=1e-12)
        assert np.all(np.delete(r[0], col) == 0.0)
        assert bool(core.threshold_test(f, TH)[0]) == (value < thr)


def test_single_compass_baseline_sees_compass_one_only():
    # compass 2 disturbed by 1500 nT and turned 5°: the single-compass baseline does not look at it
    s2 = 1.0 + 1500.0 / B3_NT
    t = np.arange(100) / RATE_HZ
    b1 = _reading(P1_3D, np.full(100, PSI), np.ones(100), np.full(100, BZ_NT))
    b2 = _reading(P2_3D, np.full(100, PSI + 0.1), np.full(100, s2), np.full(100, BZ_NT))
    single = core.SingleCompassDetector()
    ds = [single.update(float(t[i]), b1[i], b2[i], P1_3D, P2_3D, DECL) for i in range(100)]
    assert all(d.stage1_pass for d in ds)
    b1d = _reading(P1_3D, np.full(100, PSI), np.full(100, 1.0 + 1500.0 / B3_NT), np.full(100, BZ_NT))
    single.reset()
    ds = [single.update(float(t[i]), b1d[i], b2[i], P1_3D, P2_3D, DECL) for i in range(100)]
    assert all(d.failed == ("dm",) for d in ds)


# ---- what an alarm says -----------------------------------------------------------------------------


def test_alarm_description_names_the_failing_tests_worst_first_with_values():
    # |Δm| 2000 nT (2× its threshold) and |Δh| 4° (1.33×): both named, Δm first, with value and threshold
    det = core.ThresholdDetector(core.ThresholdDetectorSettings(
        thresholds=TH, hysteresis=core.HysteresisSettings(raise_after_s=0.1, clear_after_s=0.2)))
    assert det.flags == {"alarm_raised": False, "valid": False, "warming": True} and det.internal_states == {}
    t = np.arange(100) / RATE_HZ
    b1 = _reading(P1_3D, np.full(100, PSI), np.full(100, 1.0 + 2000.0 / B3_NT), np.full(100, BZ_NT))
    b2 = _reading(P2_3D, np.full(100, PSI + math.radians(4.0)), np.ones(100), np.full(100, BZ_NT))
    ds = [det.update(float(t[i]), b1[i], b2[i], P1_3D, P2_3D, DECL) for i in range(100)]
    raised = [d for d in ds if d.transition == "raised"]
    assert len(raised) == 1 and raised[0].t_s == pytest.approx(0.1, abs=1e-9)
    d = raised[0]
    assert d.failed == ("dm", "dh")
    assert d.ratios["dm"] == pytest.approx(2.0, rel=1e-9) and d.ratios["dh"] == pytest.approx(4.0 / 3.0, rel=1e-9)
    reason, value, thr, unit = det.describe(d)
    assert (value, thr, unit) == (pytest.approx(2000.0, rel=1e-9), TH.dm_nt, "nT")
    assert reason == ("Magnetic interference suspected: field-strength error |Δm| 2e+03 nT exceeds 1e+03 nT; "
                      "relative heading difference |Δh| 4 deg exceeds 3 deg.")
    assert det.flags == {"alarm_raised": True, "valid": False, "warming": False}
    assert det.internal_states == {"ratios": ds[-1].ratios, "credibility": 0.0}
    # the field comes back: cleared after clear_after_s, and the reason says so
    b1c = _reading(P1_3D, np.full(100, PSI), np.ones(100), np.full(100, BZ_NT))
    b2c = _reading(P2_3D, np.full(100, PSI), np.ones(100), np.full(100, BZ_NT))
    ds = [det.update(2.0 + float(t[i]), b1c[i], b2c[i], P1_3D, P2_3D, DECL) for i in range(100)]
    cleared = [d for d in ds if d.transition == "cleared"]
    # the 2000 nT step back is itself a rate (dΔm) until the rate windows are past it: then clear_after_s more
    assert len(cleared) == 1 and 2.0 + FS.history_s - 0.1 <= cleared[0].t_s <= 2.0 + FS.history_s + 0.2 + 1e-9
    assert {d.failed for d in ds if not d.stage1_pass} == {("ddm",), ("ddm", "ddh")}  # the 4° step back too
    assert det.describe(cleared[0]) == ("Magnetic heading is trustworthy again: every interference test passes.",
                                        None, None, "")
    assert det.flags["alarm_raised"] is False and det.internal_states["credibility"] == 1.0


# ---- the rest of the core: batch edges, pairing, baseline, parameters, latch ------------------------


def _ref_ready(t, sw, rw):
    """Ready per the definition: smooth + rate of input seen, and a mean rate_window_s back exists."""
    return np.array([t[i] - t[0] >= sw + rw - 1e-9 and any(t[k] <= t[i] - rw for k in range(i + 1))
                     for i in range(len(t))])


def test_batch_headings_default_declination_and_empty_input():
    t = np.arange(60) / RATE_HZ
    b1 = _reading(P1_3D, np.full(60, PSI), np.ones(60), np.full(60, BZ_NT))
    b2 = _reading(P2_3D, np.full(60, PSI + 0.05), np.ones(60), np.full(60, BZ_NT))
    f = core.features_batch(t, b1, b2, P1_3D, P2_3D, DECL)
    np.testing.assert_allclose(f.heading_rad, PSI, atol=1e-9)
    np.testing.assert_allclose(f.heading2_rad, PSI + 0.05, atol=1e-9)
    f0 = core.features_batch(t, b1, b2, P1_3D, P2_3D)  # declination defaults to 0
    np.testing.assert_allclose(f0.heading_rad, PSI - DECL, atol=1e-9)
    e = core.features_batch(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), P1_3D, P2_3D)
    assert len(e.t_s) == 0 and e.dm_nt.shape == (0, 2) and e.rates_ready.shape == (0,)


def test_a_gap_of_exactly_max_gap_does_not_restart_the_windows():
    # times in exact binary fractions: a step of 1.0 s is max_gap_s, not above it
    s = FeatureSettings(smooth_window_s=0.25, rate_window_s=0.5, max_gap_s=1.0)
    t = np.r_[np.arange(8) * 0.25, 1.75 + 1.0 + np.arange(8) * 0.25]
    b = _reading(P1_3D, np.full(len(t), PSI), np.ones(len(t)), np.full(len(t), BZ_NT))
    f = core.features_batch(t, b, b, P1_3D, P1_3D, DECL, s)
    assert f.rates_ready[8], "a gap equal to max_gap_s must not restart the windows"
    t2 = t.copy()
    t2[8:] += 0.25  # now above it: restart
    f2 = core.features_batch(t2, b, b, P1_3D, P1_3D, DECL, s)
    assert not f2.rates_ready[8] and f2.rates_ready[11]
    tr = core.FeatureTracker(s)
    assert [bool(tr.update(float(ti), b[i], b[i], P1_3D, P1_3D, DECL).rates_ready[0]) for i, ti in enumerate(t2)] \
        == list(f2.rates_ready)


@pytest.mark.parametrize("sw,rw,dt", [(0.25, 0.5, 0.25), (0.001, 0.5, 0.3), (0.2, 0.5, 0.02)])
def test_ready_boundary_batch_streaming_and_definition_agree(sw, rw, dt):
    s = FeatureSettings(smooth_window_s=sw, rate_window_s=rw)
    t = np.arange(12) * dt
    b = _reading(P1_3D, np.full(12, PSI), np.ones(12), np.full(12, BZ_NT))
    f = core.features_batch(t, b, b, P1_3D, P1_3D, DECL, s)
    tr = core.FeatureTracker(s)
    stream = [bool(tr.update(float(ti), b[i], b[i], P1_3D, P1_3D, DECL).rates_ready[0]) for i, ti in enumerate(t)]
    np.testing.assert_array_equal(f.rates_ready, _ref_ready(t, sw, rw))
    assert stream == list(f.rates_ready)


def test_pairer_tolerance_drops_and_pending_limit():
    with pytest.raises(ValueError):
        core.Pairer(("1", "1"))
    with pytest.raises(ValueError):
        core.Pairer(("1",))
    with pytest.raises(ValueError):
        core.Pairer(("1", "2"), tolerance_s=-0.1)
    exact = core.Pairer(("1", "2"), tolerance_s=0.0)  # zero tolerance: equal times only
    assert exact.push("1", 1.0, [1, 0, 0]) == ([], 0)
    pairs, d = exact.push("2", 1.0, [2, 0, 0])
    assert d == 0 and len(pairs) == 1 and pairs[0][0] == 1.0
    p = core.Pairer(("1", "2"), tolerance_s=0.25)
    with pytest.raises(ValueError):
        p.push("3", 0.0, [0, 0, 0])
    assert p.push("1", 0.0, [1, 0, 0]) == ([], 0)
    pairs, d = p.push("2", 0.25, [2, 0, 0])  # |Δt| = tolerance: still a pair, at the first sensor's time
    assert d == 0 and [(pt, list(a), list(b)) for pt, a, b in pairs] == [(0.0, [1, 0, 0], [2, 0, 0])]
    for ti in (1.0, 1.25, 1.5):
        p.push("1", ti, [1, 0, 0])
    pairs, d = p.push("2", 1.75, [2, 0, 0])  # 1.0 and 1.25 can never pair now; 1.5 is exactly in tolerance
    assert d == 2 and len(pairs) == 1 and pairs[0][0] == 1.5
    q = core.Pairer(("1", "2"), tolerance_s=0.01, max_pending=3)
    assert [q.push("1", float(i), [0, 0, 0])[1] for i in range(3)] == [0, 0, 0]  # exactly max_pending held
    assert q.push("1", 3.0, [0, 0, 0])[1] == 1 and len(q.pending["1"]) == 3
    q.reset()
    assert all(len(v) == 0 for v in q.pending.values())


def test_single_compass_baseline_publishes_compass_one_features_only():
    single = core.SingleCompassDetector()
    t = np.arange(100) / RATE_HZ
    ramp = 1.0 + (-900.0 + 1500.0 * t) / B3_NT
    b1 = _reading(P1_3D, np.full(100, PSI), np.full(100, 1.0 + 1200.0 / B3_NT), np.full(100, BZ_NT))
    b2 = _reading(P2_3D, np.full(100, PSI + 0.2), ramp, np.full(100, BZ_NT))
    ds = [single.update(float(t[i]), b1[i], b2[i], P1_3D, P2_3D) for i in range(100)]  # default declination 0
    d = ds[-1]
    assert d.dm_nt == [pytest.approx(1200.0, abs=1e-6), 0.0] and d.ddm_nt_s[1] == 0.0
    assert d.ratios == {"dm": pytest.approx(1.2, rel=1e-9), "ddm": pytest.approx(0.0, abs=1e-9)}
    assert d.failed == ("dm",) and d.dh_rad == 0.0
    assert d.heading_rad == pytest.approx(PSI - DECL, abs=1e-9)
    # its rate test: compass 1 ramping at 1500 nT/s fails dΔm alone
    single.reset()
    b1r = _reading(P1_3D, np.full(60, PSI), ramp[:60], np.full(60, BZ_NT))
    ds = [single.update(float(t[i]), b1r[i], b2[i], P1_3D, P2_3D, DECL) for i in range(60)]
    assert ds[-1].failed == ("ddm",) and ds[-1].ratios["ddm"] == pytest.approx(1.5, rel=0.04)
    r = core.single_compass_ratios(core.features_batch(t[:60], b1r, b1r, P1_3D, P1_3D, DECL), TH)
    assert r.shape == (60, 2) and r[-1, 1] == pytest.approx(1.5, rel=0.04) and r[-1, 0] < 1.0


def test_compass_params_radius_model_and_mapping():
    eye = tuple(np.eye(3).ravel())
    assert CompassParams((0, 0, 0), eye, 0.5).field_radius_nt == 0.5  # any positive radius
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError):
            CompassParams((0, 0, 0), eye, bad)
    with pytest.raises(ValueError):
        CompassParams((0, 0, 0), eye, 1.0, model="1d")
    m = {"offset_nt": [1, 2, 3], "matrix": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "field_radius_nt": 40000}
    p = CompassParams.from_mapping(m)
    assert p.param_id == "manifest" and p.model == "3d" and p.matrix == (2.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0)
    assert CompassParams.from_mapping({**m, "param_id": "1-arls-7"}).param_id == "1-arls-7"
    assert CompassParams.from_mapping({**m, "param_id": "x"}, param_id="given").param_id == "given"


def test_thresholds_scaled_and_latch_batch_and_state():
    th = Thresholds(1000.0, 500.0, 3.0, 2.0).scaled(0.5)
    assert (th.dm_nt, th.ddm_nt_s, th.dh_deg, th.ddh_deg_s) == (500.0, 250.0, 1.5, 1.0)
    hs = core.HysteresisSettings(raise_after_s=0.3, clear_after_s=1.0)
    t = np.arange(0, 6, 0.1)
    valid = ~((t > 1.0) & (t < 3.0))
    latch = core.AlarmLatch(hs)
    looped = np.array([(latch.update(float(ti), bool(v)), latch.raised)[1] for ti, v in zip(t, valid, strict=True)])
    np.testing.assert_array_equal(core.latch_batch(t, valid, hs), looped)
    assert looped.any() and not looped[0] and not looped[-1]
    st = latch.state()
    assert st == {"raised": False, "raised_t_s": pytest.approx(1.4, abs=1e-9), "invalid_since": None,
                  "valid_since": pytest.approx(3.0, abs=1e-9)}
    latch.adopt(True, 7.5)
    assert latch.raised and latch.raised_t_s == 7.5
    latch.adopt(False, 9.0)
    assert not latch.raised and latch.raised_t_s is None
    det = core.ThresholdDetector()
    det.update(0.0, [BH_NT, 0, BZ_NT], [BH_NT, 0, BZ_NT], P1_3D, P2_3D)
    det.reset()
    assert det.last is None and det.internal_states == {} and det.flags["warming"]
