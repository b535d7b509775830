"""DMC stage 2 (fuzzy c-means), the other detector implementations, and their services."""

from __future__ import annotations

import numpy as np
import pytest

from magmesh import maths
from schemas import keys, messages
from services.dmc_detector import core, fcm, quasistatic
from tests.test_dmc_core import IDENTITY, _FakeRuntime, _run_service, _vehicles_config, synthetic_drive


def _blobs(seed=0, n=400):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.05, 0.05], [0.3, 0.1], [0.1, 0.5], [0.7, 0.3], [0.8, 0.8]])
    return np.concatenate([rng.normal(c, 0.05, (n, 2)) for c in centres]), centres


def _loop_fcm(X, u0, m, n_iter):
    """Textbook FCM, one sample and one cluster at a time (independent of the vectorised code)."""
    c, n = u0.shape
    u = u0 / u0.sum(0)
    V = np.zeros((c, X.shape[1]))
    for _ in range(n_iter):
        for i in range(c):
            w = u[i] ** m
            V[i] = (w[:, None] * X).sum(0) / w.sum()
        un = np.empty_like(u)
        for k in range(n):
            d = [np.linalg.norm(X[k] - V[i]) for i in range(c)]
            for i in range(c):
                un[i, k] = 1.0 / sum((d[i] / d[j]) ** (2.0 / (m - 1.0)) for j in range(c))
        u = un
    return V, u


@pytest.mark.parametrize("m", [2.0, 1.7])
def test_fcm_agrees_with_loop_implementation(m):
    X, _ = _blobs(n=40)
    u0 = np.random.default_rng(1).random((5, len(X)))
    r = fcm.fcm_fit(X, 5, m, tol=0.0, max_iter=15, u0=u0)
    V, u = _loop_fcm(X, u0, m, 15)
    np.testing.assert_allclose(r.centres, V, atol=1e-10)
    np.testing.assert_allclose(r.u, u, atol=1e-10)


def test_fcm_agrees_with_skfuzzy_same_start():
    skfuzzy = pytest.importorskip("skfuzzy")
    X, _ = _blobs(n=2000)
    u0 = np.random.default_rng(2).random((5, len(X)))
    u0 /= u0.sum(0)
    mine = fcm.fcm_fit(X, 5, 2.0, tol=0.0, max_iter=25, u0=u0)
    cntr, u, *_ = skfuzzy.cmeans(X.T, 5, 2.0, error=0.0, maxiter=25, init=u0.copy())
    np.testing.assert_allclose(mine.centres, cntr, atol=1e-9)
    np.testing.assert_allclose(mine.u, u, atol=1e-9)


def test_fcm_converges_finds_centres_and_objective_decreases():
    X, centres = _blobs()
    r = fcm.fcm_fit(X, 5, 2.0, tol=0.01, seed=3)
    assert r.converged and r.n_iter < 100
    assert np.all(np.diff(r.objective) <= 1e-9)  # J_m never increases
    found = fcm.order_by_error(r.centres)
    for c in centres:
        assert np.min(np.linalg.norm(found - c, axis=1)) < 0.05
    u = fcm.memberships(X, r.centres)
    np.testing.assert_allclose(u.sum(0), 1.0)
    np.testing.assert_allclose(u, r.u, atol=0.011)  # the fixed-centre update of a converged fit
    with pytest.raises(ValueError):
        fcm.fcm_fit(X[:3], 5)


def _features_for(x_dm_frac, x_dh_frac, model):
    n = len(x_dm_frac)
    th = model.loose
    return core.Features(np.arange(n) * 0.02, np.stack([x_dm_frac * th.dm_nt] * 2, axis=1), np.zeros((n, 2)),
                         np.radians(x_dh_frac * th.dh_deg), np.zeros(n), np.zeros(n), np.zeros(n), np.ones(n, bool))


def test_credibility_and_model_roundtrip(tmp_path):
    centres = np.array([[0.02, 0.02], [0.1, 0.05], [0.3, 0.2], [0.6, 0.4], [0.9, 0.8]])
    model = fcm.FcmModel(centres, "paper", training={"drives": ["x"]})
    f = _features_for(np.array([0.02, 0.1, 0.6, 0.9, 1.5]), np.array([0.02, 0.05, 0.4, 0.8, 0.1]), model)
    kc, per = model.credibility(f)
    assert kc[0] > 0.99 and kc[1] > 0.9 and kc[2] < 0.2 and kc[3] < 0.1
    valid, stage1, kc2 = model.classify(f)
    assert list(valid) == [True, True, False, False, False]
    assert not stage1[4] and kc2[4] == 0.0  # |Δm| beyond the loose threshold fails stage 1
    p = model.save(tmp_path / "m.json")
    back = fcm.FcmModel.load(p)
    np.testing.assert_allclose(back.centres, model.centres)
    assert back.feature_set == "paper" and back.n_good_clusters == 2 and back.loose == model.loose
    bad = model.to_json()
    bad["version"] = 99
    with pytest.raises(ValueError, match="version"):
        fcm.FcmModel.from_json(bad)
    with pytest.raises(ValueError):
        fcm.FcmModel(np.zeros((5, 3)), "paper")


def test_fcm_detector_streaming_matches_batch_and_flags_source():
    t, b1, b2, _, err = synthetic_drive(seed=6)
    f = core.features_batch(t, b1, b2, IDENTITY, IDENTITY, 0.0)
    model = fcm.train([f], "extended", heading_err_deg=[np.degrees(err)])
    valid_b, _, kc_b = model.classify(f)
    det = fcm.FcmDetector(model)
    out = [det.update(float(t[i]), b1[i], b2[i], IDENTITY, IDENTITY, 0.0) for i in range(len(t))]
    assert [d.valid for d in out] == list(valid_b)
    np.testing.assert_allclose([d.credibility for d in out], kc_b, atol=1e-9)
    bad = err > np.radians(5)
    assert not valid_b[bad].any()
    assert valid_b[(t < 20) | (t > 50)].mean() > 0.95


def test_single_compass_ignores_differential_tests():
    det = core.SingleCompassDetector()
    t, b1, b2, _, _ = synthetic_drive(seed=7, source_at_s=None)
    b2 = b2 + np.array([0.0, 3000.0, 0.0])  # compass 2 broken: the single detector must not care
    out = [det.update(float(t[i]), b1[i], b2[i], IDENTITY, IDENTITY, 0.0) for i in range(len(t))]
    assert all(d.valid for d in out[50:])
    assert set(out[-1].ratios) == {"dm", "ddm"} and out[-1].dm_nt[1] == 0.0 and out[-1].dh_rad == 0.0


def test_quasistatic_detects_change_not_turns():
    # a level car turning at 10°/s with a perfect gyro; a disturbance ramps in at t = 20..24 s
    rate = np.radians(10.0)
    t_mag = np.arange(0, 40, 0.02)
    t_imu = np.arange(0, 40, 0.01)
    b_h = np.array([33000.0, 0.0])
    heading = rate * t_mag
    dist = np.clip((t_mag - 20) / 4, 0, 1) * ((t_mag < 30) | (t_mag > 60))
    # a disturbance fixed in the world (ENU), seen in the turning body frame
    extra = np.stack([maths.body_to_enu(h).T @ (d * np.array([6000.0, 4000.0, 0.0])) for h, d in zip(heading, dist, strict=False)])
    b = np.stack([b_h[0] * np.cos(heading), b_h[0] * np.sin(heading), np.full_like(heading, -35000.0)], 1) + extra
    p = core.CompassParams((0, 0, 0), (1, 0, 0, 0, 1, 0, 0, 0, 1), float(np.linalg.norm([33000.0, 35000.0])))
    for variance_of, turns_ok in (("magnitude", True), ("components", False)):
        det = quasistatic.QuasiStaticDetector(quasistatic.QuasiStaticSettings(variance_of=variance_of))
        out = []
        i = j = 0
        while i < len(t_mag):
            if j < len(t_imu) and t_imu[j] <= t_mag[i]:
                out += det.add_imu(float(t_imu[j]), [0.0, 0.0, -rate], [0.0, 0.0, 9.81])
                j += 1
            else:
                out += det.add_mag(float(t_mag[i]), b[i], p)
                i += 1
        valid = np.array([d.valid for d in out])
        tt = np.array([d.t_s for d in out])
        quiet = (tt > 2) & (tt < 19)
        assert (valid[quiet].mean() > 0.99) == turns_ok, variance_of
        assert not valid[(tt > 22) & (tt < 30)].any()  # ramp: variance/heading change; then |Δm|


def test_fcm_and_quasistatic_services_publish_valid_messages(tmp_path):
    from services.dmc_detector.impls import IMPLEMENTATIONS, FcmSettings, pop_impl_arg

    t, b1, b2, _, err = synthetic_drive(seed=8)
    f = core.features_batch(t, b1, b2, IDENTITY, IDENTITY, 0.0)
    path = fcm.train([f], "paper", heading_err_deg=[np.degrees(err)]).save(tmp_path / "model.json")
    svc = IMPLEMENTATIONS["fcm"](FcmSettings(model_path=str(path)), vehicles_config=_vehicles_config())
    svc.on_start()
    rt, _ = _run_service(svc, t, b1, b2)
    dmc = [m for k, m in rt.out if k == keys.dmc("car-1")]
    alarms = [m for k, m in rt.out if k == keys.alarm("car-1", "dmc")]
    assert len(dmc) == len(t) and {m["impl"] for m in dmc} == {"fcm"}
    assert [a["state"] for a in alarms] == ["raised", "cleared"]
    assert 0.0 <= min(m["credibility"] for m in dmc) and max(m["credibility"] for m in dmc) <= 1.0

    svc = IMPLEMENTATIONS["single"](vehicles_config={"car-1": {"mag_params": _vehicles_config()["car-1"]["mag_params"]}})
    assert svc.subscriptions() == [keys.clean_mag("*", "1"), keys.cal_params("*", "1")]
    rt, _ = _run_service(svc, t, b1, b2)
    assert len([1 for k, _ in rt.out if k == keys.dmc("car-1")]) == len(t)

    qs = IMPLEMENTATIONS["quasistatic"](vehicles_config=_vehicles_config())
    rt = _FakeRuntime()
    qs._rt = rt
    st = qs.new_vehicle("car-1")
    for i in range(len(t)):
        imu = messages.make("imu", "car-1", float(t[i]), i, gyro_rad_s=[0.0, 0.0, 0.0], accel_m_s2=[0.0, 0.0, 9.81])
        qs.on_message(keys.parse(keys.clean_imu("car-1")), imu, st)
        mag = messages.make("mag", "car-1", float(t[i]), i, sensor="1", b_nt=[float(x) for x in b1[i]])
        qs.on_message(keys.parse(keys.clean_mag("car-1", "1")), mag, st)
    assert len([1 for k, _ in rt.out if k == keys.dmc("car-1")]) == len(t)

    assert pop_impl_arg(["--impl", "fcm", "--set", "a=1"]) == ("fcm", ["--set", "a=1"])
    assert pop_impl_arg(["--impl=single"]) == ("single", [])
    assert pop_impl_arg(["--impl", "threshold", "--impl", "fcm"])[0] == "fcm"  # a swap appends its --impl
    with pytest.raises(SystemExit):
        pop_impl_arg(["--impl", "nope"])


def test_committed_model_loads():
    model = fcm.FcmModel.load()
    assert model.feature_set in fcm.FEATURE_SETS and len(model.centres) == 5
    assert model.training.get("drives"), "the committed model says what it was trained on"
