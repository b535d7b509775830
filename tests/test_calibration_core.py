"""Calibration cores: Two-Step LS, ARLS (IGG-III), sufficiency, online EKF, service logic (no mesh)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from bench import calibration_synthetic as synthetic
from magmesh import magcal
from schemas import messages
from services.calibration import arls, online_ekf, sufficiency, two_step
from services.calibration.core import CalibrationSettings, ParamRecord, SensorCalibrator


def _cloud(**kw) -> synthetic.Cloud:
    return synthetic.make_cloud(synthetic.CloudSettings(**kw))


# ---- Two-Step LS ------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["3d", "2d"])
def test_ls_recovers_noise_free_truth_exactly(model):
    c = _cloud(model=model, noise_nt=0.0, seed=4)
    res = two_step.fit_ls(c.m_nt, model)
    assert res.ok
    assert magcal.offset_error_pct(res.params.offset, c.offset_nt, c.radius_nt) < 1e-6
    sl = slice(0, 2) if model == "2d" else slice(0, 3)
    assert magcal.matrix_error_pct(res.params.M[sl, sl], res.params.field_radius_nt, c.M[sl, sl], c.radius_nt) < 1e-6
    assert res.rmse_nt < 1e-3 * c.radius_nt


def test_decomposition_matches_an_independent_geometric_fit():
    """scipy's least_squares on |S (m − b)| = 1 (S symmetric) must find the same ellipsoid."""
    c = _cloud(noise_nt=0.0, seed=2, n_samples=800)
    res = two_step.fit_ls(c.m_nt, "3d")

    def resid(p):
        S = np.array([[p[3], p[4], p[5]], [p[4], p[6], p[7]], [p[5], p[7], p[8]]])
        return np.linalg.norm((c.m_nt - p[:3]) @ S, axis=1) - 1.0

    s0 = 1.0 / np.median(np.linalg.norm(c.m_nt - c.m_nt.mean(0), axis=1))
    p0 = np.r_[c.m_nt.mean(0), s0, 0, 0, s0, 0, s0]
    ref = least_squares(resid, p0, x_scale="jac", xtol=1e-14, ftol=1e-14).x
    S_ref = np.array([[ref[3], ref[4], ref[5]], [ref[4], ref[6], ref[7]], [ref[5], ref[7], ref[8]]])
    assert np.allclose(res.params.offset, ref[:3], atol=1e-3 * c.radius_nt)
    S_ours = magcal.symmetric_part(res.params.M) / res.params.field_radius_nt
    assert np.allclose(S_ours, magcal.symmetric_part(S_ref), rtol=1e-4)


def test_apply_roundtrip_gives_constant_field_strength():
    c = _cloud(noise_nt=0.0, seed=7)
    p = two_step.fit_ls(c.m_nt, "3d").params
    r = magcal.field_strength_residual(c.m_nt, p)
    assert np.max(np.abs(r)) < 1e-6 * p.field_radius_nt
    p_fixed = two_step.fit_ls(c.m_nt, "3d", radius_nt=c.radius_nt).params
    assert abs(np.median(np.linalg.norm(p_fixed.apply(c.m_nt), axis=1)) - c.radius_nt) < 1e-3


# ---- ARLS -------------------------------------------------------------------------------------


def test_igg3_weight_function():
    w = arls.igg3_weights(np.array([0.0, 1.0, 1.5, 2.0, 3.0, 3.5, -2.0]), 1.5, 3.0)
    assert w[0] == w[1] == w[2] == 1.0
    assert w[3] == pytest.approx((1.5 / 2.0) * ((3.0 - 2.0) / 1.5) ** 2)
    assert w[4] == 0.0 and w[5] == 0.0
    assert w[6] == w[3]
    with pytest.raises(ValueError):
        arls.ArlsSettings(k0=3.0, k1=2.0)


@pytest.mark.parametrize("model,size", [("3d", 0.20), ("2d", 0.10)])
def test_arls_meets_goal_with_20pct_gross_errors_where_ls_fails(model, size):
    worst_arls = worst_ls = 0.0
    for seed in range(3):
        c = _cloud(model=model, gross_frac=0.20, gross_size_rel=size, seed=seed)
        sl = slice(0, 2) if model == "2d" else slice(0, 3)
        ra = arls.fit_arls(c.m_nt, model)
        rl = two_step.fit_ls(c.m_nt, model)
        for res, acc in ((ra, "a"), (rl, "l")):
            oe = magcal.offset_error_pct(res.params.offset, c.offset_nt, c.radius_nt)
            me = magcal.matrix_error_pct(res.params.M[sl, sl], res.params.field_radius_nt, c.M[sl, sl], c.radius_nt)
            if acc == "a":
                worst_arls = max(worst_arls, oe, me)
            else:
                worst_ls = max(worst_ls, oe, me)
        # most injected samples are found, few clean ones lost
        assert ra.n_gross_rejected >= 0.8 * c.gross.sum()
        assert np.count_nonzero(ra.weights[~c.gross] == 0) < 0.02 * (~c.gross).sum()
    assert worst_arls < 1.0, worst_arls
    assert worst_ls > 1.0, worst_ls


def test_arls_equals_ls_quality_on_clean_data():
    c = _cloud(seed=5)
    ra, rl = arls.fit_arls(c.m_nt, "3d"), two_step.fit_ls(c.m_nt, "3d")
    ea = magcal.offset_error_pct(ra.params.offset, c.offset_nt, c.radius_nt)
    el = magcal.offset_error_pct(rl.params.offset, c.offset_nt, c.radius_nt)
    assert ea < 0.05 and el < 0.05
    assert ra.converged


def test_real_full_sphere_calibrates_to_under_one_percent_spread():
    from bench import eval_calibration as ev

    m = ev.load_real("hmc5883l_full_sphere")
    res = arls.fit_arls(m[sufficiency.balanced_subset(m, "3d", sufficiency.SufficiencySettings())], "3d")
    assert res.ok and ev._spread(m, res.params) < 0.01


# ---- sufficiency ------------------------------------------------------------------------------


def test_sufficiency_refuses_an_arc_and_a_flat_cloud():
    st = sufficiency.SufficiencySettings()
    c2 = _cloud(model="2d", seed=1)
    th = np.arctan2(c2.h_nt[:, 1], c2.h_nt[:, 0])
    arc = c2.m_nt[(th > 0) & (th < math.radians(90))]
    v = sufficiency.check_samples(arc, "2d", st)
    assert not v.ok and "full circle" in v.reason
    assert sufficiency.check_samples(c2.m_nt, "2d", st).ok
    # a level rotation does not cover the sphere: no 3-D fit
    v3 = sufficiency.check_samples(c2.m_nt, "3d", st)
    assert not v3.ok and "attitude" in v3.reason


def test_a_tumbled_cloud_is_refused_as_a_2d_fit():
    c = _cloud(model="3d", seed=2)
    res = arls.fit_arls(c.m_nt, "2d")
    # the algebra fits some ellipse to the projection; the fit check must refuse it for the tilt
    assert res.ok, res.reason
    v = sufficiency.check_fit(c.m_nt, res.params, sufficiency.SufficiencySettings(), res.weights)
    assert not v.ok and "tilts" in v.reason, v
    sc = SensorCalibrator("1", CalibrationSettings(model="auto", sample_interval_s=0.0))
    for i, m in enumerate(c.m_nt):
        sc.update(0.05 * i, m)
    a = sc.fit(0.05 * len(c.m_nt))
    assert a.accepted and sc.current.params.model == "3d"  # auto picks the ellipsoid


def test_balanced_subset_caps_samples_per_direction():
    c = _cloud(model="2d", seed=3)
    parked = np.repeat(c.m_nt[:1], 5000, axis=0)
    m = np.vstack([parked, c.m_nt])
    st = sufficiency.SufficiencySettings()
    idx = sufficiency.balanced_subset(m, "2d", st)
    assert np.count_nonzero(idx < 5000) <= st.max_per_bin
    res = arls.fit_arls(m[idx], "2d")
    assert magcal.offset_error_pct(res.params.offset, c.offset_nt, c.radius_nt) < 0.1


# ---- sensor calibrator ------------------------------------------------------------------------


def test_sensor_calibrator_refuses_then_fits_then_keeps_the_better_set():
    c = _cloud(model="2d", seed=6, n_samples=2000)
    sc = SensorCalibrator("1", CalibrationSettings(model="2d", sample_interval_s=0.0))
    t = np.arange(len(c.m_nt)) * 0.05
    th = np.arctan2(c.h_nt[:, 1], c.h_nt[:, 0])
    quarter = np.flatnonzero((th > 0) & (th < 1.2))[:300]
    for i in quarter:
        sc.update(t[i], c.m_nt[i])
    a = sc.fit(t[quarter[-1]])
    assert not a.accepted and sc.current is None and a.record.status == "refused" and a.reason
    for i in range(len(c.m_nt)):
        sc.update(t[-1] + 1 + t[i], c.m_nt[i])
    a = sc.fit(2 * t[-1] + 1)
    assert a.accepted and sc.current.status == "ok" and sc.current.params.model == "2d"
    assert sc.current.params.observable == (True, True, False)
    first = sc.current.param_id
    a = sc.fit(2 * t[-1] + 2)  # the same data: not better by 5%, kept
    assert not a.accepted and sc.current.param_id == first


def test_param_record_message_validates_and_roundtrips():
    c = _cloud(seed=8)
    res = arls.fit_arls(c.m_nt, "3d")
    rec = ParamRecord(res.params, "1-arls-x", "ok", "arls", res.rmse_nt, 0.9, len(c.m_nt), res.n_gross_rejected,
                      12.5, res.duration_ms)
    msg = messages.make("cal_params", "car-1", 12.5, 0, **rec.message_fields("1"))
    messages.decode(messages.encode(msg), expected_type="cal_params")
    back = ParamRecord.from_json(rec.to_json())
    assert back.params.offset_nt == rec.params.offset_nt and back.params.M.tolist() == rec.params.M.tolist()
    assert magcal.MagParams.from_message(msg).offset_nt == rec.params.offset_nt


# ---- online EKF -------------------------------------------------------------------------------


def test_ekf_gnss_gates():
    st = online_ekf.EkfSettings()
    assert online_ekf.gnss_usable("3d", 10, 1.5, 10.0, st)[0]
    assert not online_ekf.gnss_usable("2d", 10, 1.5, 10.0, st)[0]
    assert not online_ekf.gnss_usable("3d", 4, 1.5, 10.0, st)[0]
    assert not online_ekf.gnss_usable("3d", 10, 5.0, 10.0, st)[0]
    assert "speed" in online_ekf.gnss_usable("3d", 10, 1.5, 1.0, st)[1]


def test_ekf_jacobian_matches_finite_differences():
    ekf = online_ekf.HardIronEkf(matrix=np.array([[1.05, 0.02, 0.01], [0.02, 0.97, 0.0], [0.01, 0.0, 1.0]]))
    m = np.array([25000.0, -9000.0, -36000.0])
    b = np.array([1500.0, -700.0, 300.0])
    roll, pitch = 0.05, -0.08
    psi, lev, R = ekf.heading(m, b, roll, pitch, 0.1)
    H = ekf.jacobian(lev, R)
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1.0
        num = (ekf.heading(m, b + d, roll, pitch, 0.1)[0] - ekf.heading(m, b - d, roll, pitch, 0.1)[0]) / 2.0
        assert H[i] == pytest.approx(num, rel=1e-4, abs=1e-12)


def test_ekf_on_simulated_car_converges_without_a_vertical_correction():
    from bench import eval_calibration as ev
    from sim_publishers.car import core as car

    drive = car.simulate(seed=2, duration_s=240.0)
    r = ev.run_ekf_on_drive(drive, "1", matrix=drive.true_params["1"].matrix)
    ekf = r["ekf"]
    assert r["t_conv"] is not None and r["t_conv"] < 150
    assert ekf.observable == (True, True, False)
    assert ekf.applied_offset()[2] == 0.0  # the unobservable vertical component is never applied
    # within 1.5% of the horizontal field (≈ 0.9° of heading at worst)
    b_h = float(np.hypot(*drive.earth_field_enu_nt[:2]))
    assert np.linalg.norm(ekf.x[:2] - drive.true_params["1"].offset_nt[:2]) < 0.015 * b_h
    offs = ev._at(drive.t_mag_s, r["t"], r["offset"], np.zeros(3))
    err = ev.heading_errors_deg(drive, "1", offs, drive.true_params["1"].matrix)
    sel = ~drive.truth.disturbed & (drive.t_mag_s > r["t_conv"])
    assert np.sqrt(np.mean(err[sel] ** 2)) < 2.0


def test_ekf_mount_yaw_state_recovers_a_rotated_mounting():
    from bench import eval_calibration as ev
    from magmesh import maths
    from sim_publishers.car import core as car

    drive = car.simulate(seed=3, duration_s=240.0)
    M_rot = maths.rot_z(math.radians(-2.0)) @ drive.true_params["1"].matrix  # reads 2° low
    st = online_ekf.EkfSettings(estimate_mount_yaw=True)
    r = ev.run_ekf_on_drive(drive, "1", settings=st, offset0=drive.true_params["1"].offset_nt, matrix=M_rot)
    ekf = r["ekf"]
    assert math.degrees(ekf.mount_yaw_rad) == pytest.approx(2.0, abs=0.5)
    assert math.degrees(ekf.mount_yaw_std_rad) < 1.0
    expected = maths.rot_z(ekf.mount_yaw_rad) @ M_rot if ekf.mount_yaw_observable else M_rot
    assert np.allclose(ekf.applied_matrix(), expected)


def test_vehicle_logic_on_the_car_circle_with_and_without_a_manifest_set():
    from services.calibration.core import OnlineSettings, VehicleCalibration
    from sim_publishers.car import core as car

    drive = car.simulate(seed=1, duration_s=60.0)
    manifest = {sid: ParamRecord(magcal.MagParams.from_arrays(p.offset_nt, p.matrix, p.field_radius_nt), f"{sid}-manifest",
                                 "manifest", "manifest") for sid, p in drive.true_params.items()}
    for initial in (None, manifest):
        vc = VehicleCalibration("car", CalibrationSettings(), OnlineSettings(), initial)
        published = []
        for t_s, key, _type, f in car.iter_messages(drive, "car", truth=False):
            if "/mag/" in key:
                sc = vc.on_mag(f["sensor"], t_s, f["b_nt"])
                if sc.due(t_s):
                    a = sc.fit(t_s)
                    if a.accepted:
                        published.append((t_s, a.record.status, a.record.method))
            elif key.endswith("/imu"):
                vc.on_imu(t_s, f["gyro_rad_s"], f["accel_m_s2"])
            elif key.endswith("/gnss"):
                published += [(t_s, r.status, r.method) for _, r in vc.on_gnss(t_s, f)]
        first_ok = min(t for t, st, m in published if st == "ok" and m == "arls")
        assert first_ok <= drive.calib_turn_t_s[1] + 5.0
        converging = [p for p in published if p[1] == "converging"]
        assert (len(converging) == 0) == (initial is not None)  # never displaces a trusted set
        for sid in ("1", "2"):
            assert vc.sensors[sid].current.status == "ok" and vc.sensors[sid].current.params.model == "2d"


def test_calibrator_restarts_its_window_when_the_clock_goes_back():
    c = _cloud(model="2d", seed=9, n_samples=600)
    sc = SensorCalibrator("1", CalibrationSettings(model="2d", sample_interval_s=0.0))
    for i, m in enumerate(c.m_nt):
        sc.update(100.0 + 0.05 * i, m)
    assert len(sc.t) == 600
    sc.update(0.0, c.m_nt[0])  # a replay starting over
    assert len(sc.t) == 1 and sc.due(5.0)
    rate = online_ekf.SpeedRate()
    for k in range(6):
        rate.update(10.0 + 0.2 * k, 5.0 + 0.2 * k)  # 1 m/s²
    assert rate.update(11.2, 6.2) == pytest.approx(1.0)
    assert rate.update(0.0, 3.0) == 0.0
