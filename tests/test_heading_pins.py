"""Pins of the heading fuser's method through its public API (services/heading_fuser/core.py, service.py).

- The innovation gate rejects a magnetometer heading far outside ν² ≤ gate² · S and fuses one inside it;
  the reported test ratio is ν² / (gate² · S).
- The tilt uncertainty leaks into the magnetic azimuth ∝ tan(inclination): with the same horizontal field
  and the same attitude covariance, a steep field's innovation variance is larger by tan²(dip) · σ_tilt².
- The DMC switch: with a clean field, a DMC verdict "invalid" alone puts the filter (and the service) in
  gyro_only, and the same drive with every verdict valid never leaves the magnetic mode.
"""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from magmesh import maths
from magmesh.paths import DEPLOY_DIR
from schemas import keys
from schemas.messages import make, validate
from services.heading_fuser import core

BH_NT = 20000.0
DT = 0.01
# an accelerometer reading off g by more than the rejection limit: the tilt covariance is not reduced
UNUSED_ACCEL = (0.0, 0.0, maths.G0 + 3.0)
LEVEL_ACCEL = (0.0, 0.0, maths.G0)


def _field(heading_offset_rad: float = 0.0, dip_rad: float = math.radians(60.0)) -> np.ndarray:
    """Body-frame field of a level sensor, its horizontal part turned by ``heading_offset_rad``."""
    bz = -BH_NT * math.tan(dip_rad)
    return np.array([BH_NT * math.cos(heading_offset_rad), BH_NT * math.sin(heading_offset_rad), bz])


def _aligned(settings: core.Settings, field: np.ndarray, accel=LEVEL_ACCEL) -> core.HeadingFilter:
    f = core.HeadingFilter(settings)
    f.update_imu((0.0, 0.0, 0.0), accel, DT)
    f.update_mag(field)
    assert f.mode == "magnetic"
    return f


def _heading_change_deg(f: core.HeadingFilter, h0: float) -> float:
    return math.degrees(float(maths.angle_diff(f.heading_rad(), h0)))


ISOLATED = dict(init_duration_s=0.0, adaptive_noise=False, mag_vector_fusion=False, use_field_check=False)


# ---- the innovation gate --------------------------------------------------------------------------


@pytest.mark.parametrize("offset_deg", [40.0, -60.0, 150.0])
def test_gate_rejects_a_heading_far_outside_it(offset_deg):
    f = _aligned(core.Settings(**ISOLATED), _field())
    for _ in range(50):  # settle the heading covariance on the aligned field
        f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        assert f.update_mag(_field())
    h0 = f.heading_rad()
    f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
    fused = f.update_mag(_field(math.radians(offset_deg)))
    st = f.internal_states
    assert abs(math.degrees(st.mag_innovation_rad)) == pytest.approx(abs(offset_deg), abs=0.5)
    assert st.mag_test_ratio == pytest.approx(st.mag_innovation_rad**2 / (5.0**2 * st.mag_innovation_var_rad2))
    assert st.mag_test_ratio > 1.0
    assert f.flags.mag_rejected_gate and not fused and not f.flags.mag_fused
    assert abs(_heading_change_deg(f, h0)) < 0.01  # the heading did not move towards it


def test_gate_fuses_a_heading_inside_it_and_the_gate_width_decides():
    f = _aligned(core.Settings(**ISOLATED), _field())
    for _ in range(50):
        f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        f.update_mag(_field())
    S = f.internal_states.mag_innovation_var_rad2
    inside = 0.5 * 5.0 * math.sqrt(S)  # half the gate
    h0 = f.heading_rad()
    f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
    assert f.update_mag(_field(inside))
    assert not f.flags.mag_rejected_gate and f.internal_states.mag_test_ratio < 1.0
    assert abs(_heading_change_deg(f, h0)) > 0.01  # it moved the heading
    # the same innovation against a gate of 1 σ: rejected (the gate width is the setting, not a constant)
    g = _aligned(core.Settings(**ISOLATED, mag_gate_sigma=1.0), _field())
    for _ in range(50):
        g.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        g.update_mag(_field())
    S1 = g.internal_states.mag_innovation_var_rad2
    g.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
    assert not g.update_mag(_field(2.0 * math.sqrt(S1)))
    assert g.flags.mag_rejected_gate


def test_persistent_gate_rejections_end_in_recovering():
    s = core.Settings(**ISOLATED, rejection_timeout_s=1.0)
    f = _aligned(s, _field())
    modes = []
    for _ in range(300):  # 3 s of a heading 90° off, far outside the gate
        f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        f.update_mag(_field(math.radians(90.0)))
        modes.append(f.mode)
    assert modes[50] == "magnetic"
    assert "recovering" in modes
    assert any(to == "recovering" and "gate" in why for _, _, to, why in f.transitions)


# ---- the tilt leak --------------------------------------------------------------------------------


def _innovation_var_after_alignment(dip_deg: float, tilt_std_rad: float) -> tuple[float, core.HeadingFilter]:
    s = core.Settings(**ISOLATED, init_tilt_std_rad=tilt_std_rad, init_heading_std_rad=0.05)
    f = _aligned(s, _field(dip_rad=math.radians(dip_deg)), accel=UNUSED_ACCEL)
    f.update_imu((0.0, 0.0, 0.0), UNUSED_ACCEL, DT)
    assert f.flags.accel_ignored
    f.update_mag(_field(dip_rad=math.radians(dip_deg)))
    return f.internal_states.mag_innovation_var_rad2, f


@pytest.mark.parametrize("dip_deg", [45.0, 65.0, 75.0])
def test_tilt_uncertainty_leaks_into_the_azimuth_with_tan_dip(dip_deg):
    sigma = 0.05
    S_flat, f_flat = _innovation_var_after_alignment(0.0, sigma)
    S_steep, f_steep = _innovation_var_after_alignment(dip_deg, sigma)
    # same horizontal field, same covariance: the difference is the leak tan²(dip) σ_tilt²
    expected = math.tan(math.radians(dip_deg)) ** 2 * sigma**2
    assert S_steep - S_flat == pytest.approx(expected, rel=0.05)
    # and it grows with the tilt uncertainty
    S_steep_small, _ = _innovation_var_after_alignment(dip_deg, sigma / 2)
    S_flat_small, _ = _innovation_var_after_alignment(0.0, sigma / 2)
    assert S_steep_small - S_flat_small == pytest.approx(expected / 4, rel=0.05)


def test_tilt_leak_widens_the_gate_for_a_steep_field():
    # an innovation of 25°: outside the gate of a level field, inside that of a 75° dip with 0.05 rad tilt σ
    for dip_deg, accepted in ((0.0, False), (75.0, True)):
        s = core.Settings(**ISOLATED, init_tilt_std_rad=0.05, init_heading_std_rad=0.02)
        f = _aligned(s, _field(dip_rad=math.radians(dip_deg)), accel=UNUSED_ACCEL)
        f.update_imu((0.0, 0.0, 0.0), UNUSED_ACCEL, DT)
        fused = f.update_mag(_field(math.radians(25.0), dip_rad=math.radians(dip_deg)))
        assert fused is accepted, (dip_deg, f.internal_states.mag_test_ratio)


# ---- the DMC switch ---------------------------------------------------------------------------------


def test_filter_dmc_verdict_alone_switches_to_gyro_only_and_back():
    s = core.Settings(init_duration_s=0.0, clear_hold_s=0.5, recovery_hold_s=0.5)
    f = _aligned(s, _field())
    modes = []
    for i in range(600):
        t = (i + 1) * DT
        f.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        f.update_mag(_field(), dmc_valid=not (1.0 <= t < 2.0))
        modes.append(f.mode)
        assert not f.flags.field_inconsistent  # the field itself is clean throughout
    assert set(modes[:95]) == {"magnetic"}
    assert set(modes[101:195]) == {"gyro_only"}
    switch = [(to, why) for _, fr, to, why in f.transitions if to == "gyro_only"]
    assert switch == [("gyro_only", "DMC says invalid")]
    assert modes[-1] == "magnetic"
    # with use_dmc off the same verdicts change nothing
    g = _aligned(core.Settings(init_duration_s=0.0, use_dmc=False), _field())
    for i in range(300):
        g.update_imu((0.0, 0.0, 0.0), LEVEL_ACCEL, DT)
        g.update_mag(_field(), dmc_valid=not (1.0 <= (i + 1) * DT < 2.0))
        assert g.mode == "magnetic"


@pytest.fixture(scope="module")
def clean_drive():
    from sim_publishers.car.core import iter_messages, simulate

    with open(DEPLOY_DIR / "mesh.toml", "rb") as f:
        vehicles = tomllib.load(f)["vehicles"]
    d = simulate(duration_s=60.0, layout="clean", seed=2)
    msgs = []
    for t, key, typ, fields in iter_messages(d, "car-1", truth=False):
        info = keys.parse(key)
        if info.stream in ("imu", "mag"):
            msgs.append((t, keys.parse(keys.raw_to_clean(key)), validate(make(typ, "car-1", t, 0, **fields))))
    return vehicles, d, msgs


def _run_service(vehicles, msgs, t_mag, invalid):
    from services.heading_fuser.service import HeadingFuser, Settings

    dmc_key = keys.parse(keys.dmc("car-1"))
    allm = list(msgs)
    for t in t_mag:
        v = not invalid(float(t))
        allm.append((float(t), dmc_key, validate(make(
            "dmc", "car-1", float(t), 0, dm_nt=[0.0, 0.0], ddm_nt_s=[0.0, 0.0], dh_rad=0.0, ddh_rad_s=0.0,
            heading_rad=0.0, stage1_pass=v, credibility=1.0 if v else 0.0, valid=v, impl="fcm",
            param_source="manifest"))))
    allm.sort(key=lambda x: x[0])
    svc = HeadingFuser(Settings(), instance="t", vehicles_config=vehicles)
    out = []
    svc.publish = lambda key, typ, veh, t, **f: out.append((t, f["mode"]))
    svc.alarm = lambda *a, **k: None
    svc.count_drop = lambda key, reason, n=1: None
    st = svc.new_vehicle("car-1")
    for _, info, msg in allm:
        svc.on_message(info, msg, st)
    return out, st


def test_service_gyro_only_comes_from_the_dmc_verdict_on_a_clean_field(clean_drive):
    vehicles, d, msgs = clean_drive
    # every verdict valid: the clean drive never leaves the magnetic heading (the field check stays quiet)
    out, st = _run_service(vehicles, msgs, d.t_mag_s, lambda t: False)
    modes = {m for t, m in out if t > 5.0}
    assert modes == {"magnetic"}, modes
    # the DMC says invalid from 25 s to 35 s: gyro_only then, for that reason, and only then
    out, st = _run_service(vehicles, msgs, d.t_mag_s, lambda t: 25.0 <= t < 35.0)
    gyro = [t for t, m in out if m == "gyro_only"]
    assert gyro, "the DMC verdict did not switch the heading to the gyro"
    assert 25.0 <= min(gyro) <= 25.5 and max(gyro) <= 37.0, (min(gyro), max(gyro))
    reasons = [why for _, _, to, why in st.filter.transitions if to == "gyro_only"]
    assert reasons == ["DMC says invalid"]
    assert [m for t, m in out if t > 50.0] and {m for t, m in out if t > 50.0} == {"magnetic"}
