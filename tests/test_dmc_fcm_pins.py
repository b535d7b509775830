"""Pins of DMC stage 2 (services/dmc_detector/fcm.py) against the method's definition (docs/methods.md#dmc).

Each check computes the expected value independently: distances with an explicit difference, memberships
from Bezdek's formula μ_ik = 1 / Σ_j (d_ik / d_jk)^(2/(m'−1)), the objective J = Σ μ^m' d², the features as
|feature| / loose threshold clipped to [0, 1], K_ck as the summed membership of the good clusters and
K_c = min(K_c1, K_c2). Small hand-made inputs, so the file runs in a few seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.dmc_detector import core, fcm


def _points(seed=0, n=30):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.05, 0.05], [0.3, 0.1], [0.1, 0.5], [0.7, 0.3], [0.8, 0.8]])
    return np.concatenate([rng.normal(c, 0.04, (n, 2)) for c in centres])


def _ref_memberships(X, V, m):
    d = np.sqrt(((X[None, :, :] - V[:, None, :]) ** 2).sum(-1))  # c×N
    c, n = d.shape
    u = np.empty((c, n))
    for i in range(c):
        u[i] = 1.0 / sum((d[i] / d[j]) ** (2.0 / (m - 1.0)) for j in range(c))
    return u


def _ref_fit(X, u0, m, n_iter):
    """Centre update, objective J(u, v), membership update; n_iter times (one cluster at a time)."""
    u = u0 / u0.sum(0)
    J = []
    for _ in range(n_iter):
        w = u**m
        V = np.array([(w[i][:, None] * X).sum(0) / w[i].sum() for i in range(len(u))])
        d2 = ((X[None, :, :] - V[:, None, :]) ** 2).sum(-1)
        J.append(float((w * d2).sum()))
        u = _ref_memberships(X, V, m)
    return V, u, J


# ---- distances and memberships ------------------------------------------------------------------


def test_squared_distances_are_the_explicit_difference_and_floored_at_a_centre():
    X = _points(1, 4)
    V = np.array([[0.0, 0.0], [1.0, 0.5], [0.2, -0.3]])
    d2 = fcm._sqdist(X, V)
    assert d2.shape == (3, len(X))
    np.testing.assert_allclose(d2, ((X[None] - V[:, None]) ** 2).sum(-1), rtol=1e-12, atol=1e-15)
    on = fcm._sqdist(V[1:2], V)  # a sample exactly on centre 1
    assert 0.0 < on[1, 0] <= 1e-18
    u = fcm.memberships(V[1:2], V)
    assert np.all(np.isfinite(u)) and u[1, 0] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("m", [2.0, 1.7, 3.0])
def test_memberships_follow_bezdeks_formula(m):
    X = _points(2, 6)
    V = np.array([[0.1, 0.1], [0.4, 0.2], [0.2, 0.6], [0.9, 0.9]])
    u = fcm.memberships(X, V, m)
    np.testing.assert_allclose(u, _ref_memberships(X, V, m), rtol=1e-10)
    np.testing.assert_allclose(u.sum(0), 1.0, rtol=1e-12)


def test_memberships_default_fuzzifier_is_two():
    X = _points(3, 5)
    V = np.array([[0.1, 0.1], [0.5, 0.5], [0.9, 0.2]])
    np.testing.assert_allclose(fcm.memberships(X, V), _ref_memberships(X, V, 2.0), rtol=1e-10)


# ---- the FCM iteration --------------------------------------------------------------------------


@pytest.mark.parametrize("m", [2.0, 1.5])
def test_each_iteration_and_its_objective_match_the_reference(m):
    X = _points(4, 12)
    u0 = np.random.default_rng(5).random((5, len(X)))
    r = fcm.fcm_fit(X, 5, m, tol=0.0, max_iter=7, u0=u0)
    V, u, J = _ref_fit(X, u0, m, 7)
    assert r.n_iter == 7 and len(r.objective) == 7 and not r.converged
    np.testing.assert_allclose(r.centres, V, atol=1e-12)
    np.testing.assert_allclose(r.u, u, atol=1e-12)
    np.testing.assert_allclose(r.objective, J, rtol=1e-10)
    assert np.all(np.diff(r.objective) <= 1e-12)  # alternating optimisation never raises J


def test_it_stops_at_the_first_iteration_whose_memberships_move_less_than_tol():
    X = _points(6, 20)
    u0 = np.random.default_rng(7).random((5, len(X)))
    r = fcm.fcm_fit(X, 5, 2.0, tol=0.01, u0=u0)
    assert r.converged and 1 < r.n_iter < 300
    # the reference's memberships one step before the end still moved by ≥ tol, the last step by < tol
    _, u_prev, _ = _ref_fit(X, u0, 2.0, r.n_iter - 1)
    _, u_last, _ = _ref_fit(X, u0, 2.0, r.n_iter)
    _, u_prev2, _ = _ref_fit(X, u0, 2.0, r.n_iter - 2) if r.n_iter > 2 else (None, u0 / u0.sum(0), None)
    assert np.abs(u_last - u_prev).max() < 0.01 <= np.abs(u_prev - u_prev2).max()
    np.testing.assert_allclose(r.u, u_last, atol=1e-10)
    short = fcm.fcm_fit(X, 5, 2.0, tol=0.01, max_iter=r.n_iter - 1, u0=u0)
    assert not short.converged and short.n_iter == r.n_iter - 1
    # memberships never move by 1 or more: tol = 1 ends after one iteration
    one = fcm.fcm_fit(X, 5, 2.0, tol=1.0, u0=u0)
    assert one.converged and one.n_iter == 1 and len(one.objective) == 1


def test_defaults_are_the_papers_c5_m2_eps001_and_seeded():
    X = _points(8, 15)
    d = fcm.fcm_fit(X)
    e = fcm.fcm_fit(X, c=5, m=2.0, tol=0.01, max_iter=300, seed=0)
    assert d.centres.shape == (5, 2)
    np.testing.assert_array_equal(d.centres, e.centres)
    assert d.n_iter == e.n_iter
    # the seed is the initial memberships' RNG: same seed, same first step; another seed, another
    u0 = np.random.default_rng(0).random((5, len(X)))
    np.testing.assert_allclose(fcm.fcm_fit(X, max_iter=1).centres, fcm.fcm_fit(X, max_iter=1, u0=u0).centres)
    assert not np.allclose(fcm.fcm_fit(X, max_iter=1, seed=1).centres, fcm.fcm_fit(X, max_iter=1).centres)


def test_initial_memberships_are_normalised_and_not_modified():
    X = _points(9, 8)
    u0 = np.random.default_rng(3).random((5, len(X)))
    keep = u0.copy()
    a = fcm.fcm_fit(X, 5, 2.0, tol=0.0, max_iter=3, u0=3.0 * u0)
    b = fcm.fcm_fit(X, 5, 2.0, tol=0.0, max_iter=3, u0=u0 / u0.sum(0))
    np.testing.assert_allclose(a.centres, b.centres, atol=1e-12)
    fcm.fcm_fit(X, 5, 2.0, max_iter=2, u0=u0)
    np.testing.assert_array_equal(u0, keep)
    with pytest.raises(ValueError, match="u0"):
        fcm.fcm_fit(X, 5, u0=u0[:, :-1])


def test_argument_checks():
    X = _points(10, 1)  # 5 samples
    assert fcm.fcm_fit(X, c=5, max_iter=2).centres.shape == (5, 2)  # N = c is enough
    with pytest.raises(ValueError, match="N ≥ c"):
        fcm.fcm_fit(X[:4], c=5)
    with pytest.raises(ValueError, match="N ≥ c"):
        fcm.fcm_fit(X[:, 0], c=2)  # not N×d
    with pytest.raises(ValueError, match="fuzzifier"):
        fcm.fcm_fit(X, c=2, m=1.0)
    assert fcm.fcm_fit(X, c=2, m=1.01, max_iter=2).n_iter == 2


# ---- the model: features, credibility, classification ----------------------------------------


LOOSE = core.Thresholds(2000.0, 1000.0, 8.0, 4.0)


def _features(dm, ddm, dh_deg, ddh_deg_s, ready=None):
    dm, ddm = np.atleast_2d(dm).astype(float), np.atleast_2d(ddm).astype(float)
    n = len(dm)
    dh, ddh = np.radians(np.atleast_1d(dh_deg)), np.radians(np.atleast_1d(ddh_deg_s))
    rr = np.ones(n, bool) if ready is None else np.asarray(ready, bool)
    return core.Features(np.arange(n) * 0.1, dm, ddm, dh, ddh, np.zeros(n), np.zeros(n), rr)


def test_compass_features_are_each_compass_over_the_loose_thresholds_clipped():
    f = _features([[500.0, -1500.0], [3000.0, 100.0]], [[-250.0, 400.0], [10.0, -2500.0]], [-2.0, 12.0], [1.0, -3.0])
    model = fcm.FcmModel(np.zeros((5, 4)), "extended", LOOSE)
    x1, x2 = model.compass_features(f)
    np.testing.assert_allclose(x1, [[0.25, 0.25, 0.25, 0.25], [1.0, 0.01, 1.0, 0.75]])
    np.testing.assert_allclose(x2, [[0.75, 0.4, 0.25, 0.25], [0.05, 1.0, 1.0, 0.75]])
    p1, p2 = fcm.FcmModel(np.zeros((5, 2)), "paper", LOOSE).compass_features(f)
    np.testing.assert_allclose(p1, x1[:, [0, 2]])
    np.testing.assert_allclose(p2, x2[:, [0, 2]])
    assert fcm.FEATURE_SETS == {"paper": ("dm", "dh"), "extended": ("dm", "ddm", "dh", "ddh")}


CENTRES = np.array([[0.02, 0.02], [0.15, 0.05], [0.3, 0.3], [0.6, 0.4], [0.9, 0.8]])


def test_credibility_sums_the_good_clusters_and_takes_the_worse_compass():
    f = _features([[100.0, 900.0], [1200.0, 60.0], [40.0, 40.0]], np.zeros((3, 2)), [0.5, 2.0, 4.0], [0.0, 0.0, 0.0])
    for k in (1, 2, 3):
        model = fcm.FcmModel(CENTRES, "paper", LOOSE, n_good_clusters=k)
        x1, x2 = model.compass_features(f)
        k1 = _ref_memberships(x1, CENTRES, 2.0)[:k].sum(0)
        k2 = _ref_memberships(x2, CENTRES, 2.0)[:k].sum(0)
        kc, per = model.credibility(f)
        np.testing.assert_allclose(per, np.stack([k1, k2], -1), rtol=1e-10)
        np.testing.assert_allclose(kc, np.minimum(k1, k2), rtol=1e-10)
        assert (k1 < k2).any() and (k2 < k1).any()  # each compass is the worse one somewhere
    m17 = fcm.FcmModel(CENTRES, "paper", LOOSE, m=1.7)
    x1, x2 = m17.compass_features(f)
    np.testing.assert_allclose(m17.credibility(f)[1][:, 0], _ref_memberships(x1, CENTRES, 1.7)[:2].sum(0), rtol=1e-10)


def test_classify_is_loose_stage1_then_kc_above_kc_min():
    # rows: clean; clean-ish; far from the good clusters; |dΔh| beyond the loose V_dΔh (4°/s) only; |Δm| beyond
    f = _features([[40.0, 40.0], [300.0, 250.0], [1200.0, 900.0], [40.0, 40.0], [2100.0, 40.0]],
                  np.zeros((5, 2)), [0.2, 0.4, 3.0, 0.2, 0.2], [0.0, 0.0, 0.0, 4.5, 0.0])
    model = fcm.FcmModel(CENTRES, "paper", LOOSE, kc_min=0.8)
    kc_all, _ = model.credibility(f)
    valid, stage1, kc = model.classify(f)
    assert list(stage1) == [True, True, True, False, False]
    np.testing.assert_allclose(kc, np.where(stage1, kc_all, 0.0))
    assert kc_all[3] > 0.9  # the paper features do not see dΔh: only stage 1 refuses it
    np.testing.assert_array_equal(valid, stage1 & (kc_all > 0.8))
    assert list(valid) == [True, True, False, False, False]
    # kc_min moves the decision: a kc_min just below the second row's K_c accepts it, just above refuses it
    lo = fcm.FcmModel(CENTRES, "paper", LOOSE, kc_min=float(kc_all[2]) - 1e-6).classify(f)[0]
    hi = fcm.FcmModel(CENTRES, "paper", LOOSE, kc_min=float(kc_all[1]) + 1e-6).classify(f)[0]
    assert lo[2] and not hi[1]
    # valid only when K_c is above kc_min: a K_c equal to it is not enough
    at = fcm.FcmModel(CENTRES, "paper", LOOSE, kc_min=float(kc_all[1])).classify(f)[0]
    assert not at[1] and at[0]


def test_model_checks_its_arguments():
    fcm.FcmModel(CENTRES, "paper", n_good_clusters=1)
    fcm.FcmModel(CENTRES, "paper", n_good_clusters=4)
    for bad in (0, 5):
        with pytest.raises(ValueError, match="n_good_clusters"):
            fcm.FcmModel(CENTRES, "paper", n_good_clusters=bad)
    for bad in (0.0, 1.0):
        with pytest.raises(ValueError, match="kc_min"):
            fcm.FcmModel(CENTRES, "paper", kc_min=bad)
    with pytest.raises(ValueError, match="feature_set"):
        fcm.FcmModel(CENTRES, "nope")
    with pytest.raises(ValueError, match="centres"):
        fcm.FcmModel(CENTRES[:, 0], "paper")
    with pytest.raises(ValueError, match="centres"):
        fcm.FcmModel(CENTRES, "extended")
    m = fcm.FcmModel(CENTRES.tolist(), "paper")
    assert isinstance(m.centres, np.ndarray) and m.kc_min == 0.8 and m.n_good_clusters == 2 and m.m == 2.0
    assert m.loose == fcm.LOOSE == core.Thresholds(2000.0, 1000.0, 8.0, 8.0)
    assert m.feature_settings == core.FeatureSettings()


def test_json_roundtrip_keeps_every_setting(tmp_path):
    fs = core.FeatureSettings(smooth_window_s=0.4, rate_window_s=1.5)
    model = fcm.FcmModel(CENTRES + 1e-9 * np.arange(10).reshape(5, 2), "paper", LOOSE, m=1.7, kc_min=0.65,
                         n_good_clusters=3, training={"drives": ["a:1"]}, feature_settings=fs)
    d = model.to_json()
    assert d["format"] == fcm.MODEL_FORMAT and d["version"] == fcm.MODEL_VERSION and d["features"] == ["dm", "dh"]
    path = model.save(tmp_path / "deep" / "er" / "m.json")
    assert path == tmp_path / "deep" / "er" / "m.json" and path.read_text().endswith("}\n")
    assert len(path.read_text().splitlines()) > 20  # one value a line: a committed model diffs readably
    back = fcm.FcmModel.load(path)
    np.testing.assert_allclose(back.centres, model.centres, atol=1e-8)
    assert (back.feature_set, back.loose, back.m, back.kc_min, back.n_good_clusters) == ("paper", LOOSE, 1.7, 0.65, 3)
    assert back.training == {"drives": ["a:1"]} and back.feature_settings == fs
    bare = {k: v for k, v in d.items() if k not in ("training", "feature_settings")}
    b2 = fcm.FcmModel.from_json(bare)
    assert b2.training == {} and b2.feature_settings == core.FeatureSettings()
    with pytest.raises(ValueError, match="format"):
        fcm.FcmModel.from_json(dict(d, format="other"))
    with pytest.raises(ValueError, match="version"):
        fcm.FcmModel.from_json(dict(d, version=fcm.MODEL_VERSION + 1))
    with pytest.raises(FileNotFoundError, match="magmesh train dmc"):
        fcm.FcmModel.load(tmp_path / "missing.json")


def test_order_by_error_sorts_by_centre_norm_stably():
    c = np.array([[0.5, 0.5], [0.0, 0.1], [0.1, 0.0], [0.9, 0.0], [0.05, 0.0]])
    np.testing.assert_array_equal(fcm.order_by_error(c), c[[4, 1, 2, 0, 3]])  # [0,.1] before [.1,0]: a tie
    np.testing.assert_array_equal(fcm.order_by_error(c.tolist()), c[[4, 1, 2, 0, 3]])
    # many clusters with equal sizes keep their order (a quicksort would shuffle these 40)
    base = np.array([(0.3, 0.4), (0.4, 0.3), (0.0, 0.5), (0.5, 0.0)])
    many = base[np.arange(40) % 4] * np.where(np.arange(40) % 5 == 0, 1.5, 1.0)[:, None]
    small = np.flatnonzero(np.arange(40) % 5 != 0)
    np.testing.assert_array_equal(fcm.order_by_error(many), many[np.r_[small, np.arange(0, 40, 5)]])


# ---- training -----------------------------------------------------------------------------------


def _training_features(seed=0):
    """Five groups of epochs (compass 1 and 2 alike) around known feature fractions, plus epochs to drop."""
    rng = np.random.default_rng(seed)
    groups = [(0.03, 0.03), (0.2, 0.1), (0.1, 0.6), (0.6, 0.3), (0.85, 0.85)]
    dm, dh = [], []
    for g in groups:
        dm.append(np.clip(rng.normal(g[0], 0.02, 60), 0, 0.99))
        dh.append(np.clip(rng.normal(g[1], 0.02, 60), 0, 0.99))
    dm, dh = np.concatenate(dm), np.concatenate(dh)
    n = len(dm)
    err = np.repeat([0.5, 1.0, 6.0, 8.0, 12.0], 60)
    ready = np.ones(n, bool)
    ready[:7] = False  # rate windows not full: not trained on
    dm_nt = np.stack([dm * 2000.0] * 2, 1)
    dm_nt[7:10, 0] = 2500.0  # beyond the loose |Δm| threshold: not trained on
    f = _features(dm_nt, np.zeros((n, 2)), dh * 8.0, np.zeros(n), ready)
    return f, err, groups


def test_train_without_reference_orders_by_centre_size_and_keeps_two():
    f, _, groups = _training_features()
    model = fcm.train([f], "paper", seed=1, training_info={"drives": ["x"]})
    keep = core.threshold_test(f, fcm.LOOSE) & f.rates_ready
    assert keep.sum() == len(keep) - 10
    assert model.training["n_samples"] == 2 * keep.sum()  # both compasses' vectors
    assert model.training["drives"] == ["x"] and model.training["cluster_order"] == "centre_norm"
    assert model.training["c"] == 5 and model.training["seed"] == 1 and model.training["tol"] == 0.01
    assert model.training["converged"] and model.training["n_iter"] >= 1
    norms = np.linalg.norm(model.centres, axis=1)
    assert np.all(np.diff(norms) >= 0) and model.n_good_clusters == 2
    for g in groups:
        assert np.min(np.linalg.norm(model.centres - np.array(g), axis=1)) < 0.05
    # the stored objective is the fit's last J on the kept samples
    x1, x2 = model.compass_features(f)
    X = np.concatenate([x1[keep], x2[keep]])
    res = fcm.fcm_fit(X, seed=1)
    assert model.training["objective"] == round(res.objective[-1], 6)
    assert model.training["n_iter"] == res.n_iter


def test_train_with_reference_orders_by_heading_error_and_keeps_the_small_ones():
    f, err, groups = _training_features(2)
    model = fcm.train([f], "paper", heading_err_deg=[err], kc_min=0.7)  # "small" is < 2° by default
    assert model.kc_min == 0.7 and model.training["cluster_order"] == "heading_error"
    # groups ordered by their error: 0.5°, 1°, 6°, 8°, 12° → the first two (< 2°) make K_c
    for got, want in zip(model.centres, groups, strict=True):
        assert np.linalg.norm(got - np.array(want)) < 0.05
    assert model.n_good_clusters == 2
    ce = model.training["cluster_err_deg"]
    assert ce == sorted(ce) and ce[0] == pytest.approx(0.5, abs=0.3) and ce[-1] == pytest.approx(12.0, abs=0.5)
    assert model.training["good_cluster_deg"] == 2.0
    assert fcm.train([f], "paper", heading_err_deg=[err], good_cluster_deg=7.0).n_good_clusters == 3
    # at least one cluster and never all of them
    assert fcm.train([f], "paper", heading_err_deg=[err], good_cluster_deg=0.1).n_good_clusters == 1
    assert fcm.train([f], "paper", heading_err_deg=[err], good_cluster_deg=100.0).n_good_clusters == 4


def test_train_defaults_and_settings_carried():
    f, _, _ = _training_features(3)
    fs = core.FeatureSettings(smooth_window_s=0.3)
    model = fcm.train([f, f], "paper", feature_settings=fs, loose=LOOSE)
    assert model.feature_settings == fs and model.loose == LOOSE and model.kc_min == 0.8 and model.m == 2.0
    keep = core.threshold_test(f, LOOSE) & f.rates_ready
    assert model.training["n_samples"] == 4 * keep.sum()  # two drives
    ext = fcm.train([f])
    assert ext.feature_set == "extended" and ext.centres.shape == (5, 4) and ext.loose == fcm.LOOSE
    assert ext.feature_settings == core.FeatureSettings()
    assert ext.training["seed"] == 0 and ext.training["tol"] == 0.01 and ext.training["c"] == 5


# ---- the streaming detector ---------------------------------------------------------------------

B = np.array([20000.0, 5000.0, -40000.0])
P = core.CompassParams((0.0, 0.0, 0.0), (1, 0, 0, 0, 1, 0, 0, 0, 1), float(np.linalg.norm(B)))


def _rot_z(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _stream(det, b2_deg, n=60):
    return [det.update(0.02 * i, B, _rot_z(b2_deg) @ B, P, P) for i in range(n)]


def test_detector_refuses_on_kc_alone_and_says_so():
    model = fcm.FcmModel(CENTRES, "paper", LOOSE)
    ok = _stream(fcm.FcmDetector(model), 0.0)
    assert all(d.valid and d.stage1_pass for d in ok) and ok[-1].credibility > 0.9
    assert ok[-1].credibility == pytest.approx(float(model.credibility(_single(ok[-1]))[0][0]), abs=1e-12)
    det = fcm.FcmDetector(model)
    bad = _stream(det, 3.5)  # |Δh| 3.5° < 8°: stage 1 passes, far from the good clusters
    last = bad[-1]
    assert last.stage1_pass and not last.valid and last.failed == ("kc",) and last.ratios["kc"] == last.credibility
    assert last.credibility < 0.8
    raised = [d for d in bad if d.transition == "raised"]
    assert len(raised) == 1
    text, value, thr, unit = det.describe(raised[0])
    assert "K_c" in text and value == raised[0].credibility and thr == 0.8 and unit == ""
    # the kc_min setting overrides the model's
    lenient = fcm.FcmDetector(model, fcm.FcmDetectorSettings(kc_min=last.credibility * 0.5))
    assert lenient.kc_min == pytest.approx(last.credibility * 0.5) and _stream(lenient, 3.5)[-1].valid
    assert fcm.FcmDetector(model).kc_min == 0.8
    at = fcm.FcmDetector(model, fcm.FcmDetectorSettings(kc_min=last.credibility))
    assert not _stream(at, 3.5)[-1].valid  # K_c equal to kc_min is not above it


def _single(d):
    return _features([d.dm_nt], [d.ddm_nt_s], [math.degrees(d.dh_rad)], [math.degrees(d.ddh_rad_s)])


def test_detector_stage1_failure_zeroes_kc_and_uses_the_loose_thresholds():
    model = fcm.FcmModel(CENTRES, "paper", LOOSE)
    det = fcm.FcmDetector(model)
    out = _stream(det, 9.0)  # |Δh| 9° > 8°
    last = out[-1]
    assert not last.stage1_pass and not last.valid and last.credibility == 0.0 and last.failed == ("dh",)
    assert det.settings.thresholds == LOOSE
    text, value, thr, unit = det.describe([d for d in out if d.transition == "raised"][0])
    assert "heading difference" in text and thr == 8.0 and unit == "deg"


def test_detector_applies_the_static_heading_offset_and_the_models_windows():
    fs = core.FeatureSettings(smooth_window_s=0.3, rate_window_s=0.7, max_gap_s=2.0)
    model = fcm.FcmModel(CENTRES, "paper", LOOSE, feature_settings=fs)
    ref = math.radians(3.5)
    det = fcm.FcmDetector(model, fcm.FcmDetectorSettings(dh_ref_rad=ref))
    assert det.settings.features == core.FeatureSettings(0.3, 0.7, ref, 2.0)
    plain = core.ThresholdDetector(core.ThresholdDetectorSettings(LOOSE, core.FeatureSettings(0.3, 0.7, ref, 2.0)))
    a, b = _stream(det, 3.5), _stream(plain, 3.5)
    assert [d.dh_rad for d in a] == [d.dh_rad for d in b]
    assert abs(abs(a[-1].dh_rad) - ref) > math.radians(3.0)  # Δh_r moved Δh away from the raw 3.5°
    hyst = core.HysteresisSettings(raise_after_s=0.0, clear_after_s=0.0)
    assert fcm.FcmDetector(model, fcm.FcmDetectorSettings(hysteresis=hyst)).settings.hysteresis == hyst
