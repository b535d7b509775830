"""Pins of the paper's ARLS iteration (services/calibration/arls.py with ``refine=False``).

The geometric refinement that follows by default can hide a broken IGG loop, so here it is off and the
algebraic iteration alone must behave as the paper shows: gross errors get weight ≈ 0, plain LS is pulled
off by them and ARLS is not. An independent re-weighted least-squares loop written here from the formulas
(V = A X − L, IGG-III weights of v / σ̂, X = (AᵀPA)⁻¹AᵀPL until X stops changing) must reach the same X.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench import calibration_synthetic as synthetic
from magmesh import magcal
from services.calibration import arls, two_step

ALGEBRAIC = arls.ArlsSettings(refine=False)


def _paper_2d_cloud(seed: int, n: int = 1500):
    """The paper's 2-D experiment: level rotation, gross errors of 10 % of the field in samples 700–900."""
    c = synthetic.make_cloud(synthetic.CloudSettings(model="2d", n_samples=n, noise_nt=50.0, seed=seed))
    m = c.m_nt.copy()
    gross = np.zeros(n, bool)
    gross[700:901] = True
    rng = np.random.default_rng(100 + seed)
    d = rng.normal(size=2)
    d /= np.linalg.norm(d)
    m[gross, :2] += 0.10 * c.settings.field_nt * d
    return c, m, gross


def _paper_3d_cloud(seed: int):
    c = synthetic.make_cloud(synthetic.CloudSettings(model="3d", n_samples=3000, noise_nt=50.0, gross_frac=0.20,
                                                     gross_size_rel=0.20, seed=seed))
    return c, c.m_nt, c.gross


def _design(x: np.ndarray) -> np.ndarray:
    """Rows of A for the quadric xᵀQx + uᵀx = 1 (independent of two_step.design_matrix)."""
    if x.shape[1] == 2:
        X, Y = x.T
        return np.column_stack([X**2, Y**2, 2 * X * Y, 2 * X, 2 * Y])
    X, Y, Z = x.T
    return np.column_stack([X**2, Y**2, Z**2, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z])


def _centre(X: np.ndarray, n: int) -> np.ndarray:
    if n == 2:
        Q = np.array([[X[0], X[2]], [X[2], X[1]]])
        u = X[3:5]
    else:
        Q = np.array([[X[0], X[3], X[4]], [X[3], X[1], X[5]], [X[4], X[5], X[2]]])
        u = X[6:9]
    return -np.linalg.solve(Q, u)


def _reference_arls(m: np.ndarray, model: str, k0=1.5, k1=3.0, tol=1e-7, max_it=50):
    """IGG-III re-weighted LS by the paper's formulas, with sqrt-weighted lstsq (not normal equations)."""
    mm = m[:, :2] if model == "2d" else m
    centre = np.median(mm, axis=0)
    scale = np.median(np.linalg.norm(mm - centre, axis=1))
    x = (mm - centre) / scale
    A = _design(x)
    L = np.ones(len(A))
    X = np.linalg.lstsq(A, L, rcond=None)[0]
    X_ls = X.copy()
    p = np.ones(len(A))
    for _ in range(max_it):
        v = A @ X - L
        sig = 1.4826 * np.median(np.abs(v - np.median(v)))
        a = np.abs(v / sig)
        p = np.where(a <= k0, 1.0, np.where(a <= k1, (k0 / a) * ((k1 - a) / (k1 - k0)) ** 2, 0.0))
        sw = np.sqrt(p)
        X_new = np.linalg.lstsq(A * sw[:, None], L * sw, rcond=None)[0]
        done = np.linalg.norm(X_new - X) / np.linalg.norm(X) < tol
        X = X_new
        if done:
            break
    n = x.shape[1]
    return centre + scale * _centre(X, n), centre + scale * _centre(X_ls, n), p


def _offset_err_pct(params, c) -> float:
    return magcal.offset_error_pct(params.offset, c.offset_nt, c.radius_nt)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_2d_gross_errors_weighted_zero_ls_pulled_off_arls_not(seed):
    c, m, gross = _paper_2d_cloud(seed)
    ra = arls.fit_arls(m, "2d", settings=ALGEBRAIC)
    rl = two_step.fit_ls(m, "2d")
    assert ra.ok and rl.ok and ra.converged
    # the gross errors carry (almost) no weight, the clean samples keep theirs
    # (a few displaced along the ellipse itself stay on it: those keep their weight)
    assert np.mean(ra.weights[gross] == 0.0) > 0.95 and np.mean(ra.weights[gross]) < 0.05
    assert np.mean(ra.weights[~gross]) > 0.95
    # n_gross_rejected is the number of zero weights, bounded on both sides by the 201 injected
    assert ra.n_gross_rejected == int(np.count_nonzero(ra.weights == 0))
    assert 0.95 * gross.sum() <= ra.n_gross_rejected <= gross.sum() + 0.02 * (~gross).sum()
    # LS is pulled off by the burst, ARLS is not (offset error in % of the field)
    e_ls, e_arls = _offset_err_pct(rl.params, c), _offset_err_pct(ra.params, c)
    assert e_ls > 1.0, e_ls
    assert e_arls < 0.3, e_arls
    assert e_arls < e_ls / 5


@pytest.mark.parametrize("seed", [0, 1])
def test_paper_3d_twenty_percent_gross_errors(seed):
    c, m, gross = _paper_3d_cloud(seed)
    ra = arls.fit_arls(m, "3d", settings=ALGEBRAIC)
    rl = two_step.fit_ls(m, "3d")
    assert ra.ok and ra.converged
    assert np.mean(ra.weights[gross] == 0.0) > 0.9
    assert 0.9 * gross.sum() <= ra.n_gross_rejected <= gross.sum() + 0.02 * (~gross).sum()
    e_ls, e_arls = _offset_err_pct(rl.params, c), _offset_err_pct(ra.params, c)
    assert e_ls > 2.0 and e_arls < 0.5, (e_ls, e_arls)


@pytest.mark.parametrize("model,cloud", [("2d", _paper_2d_cloud), ("3d", _paper_3d_cloud)])
def test_the_iteration_matches_an_independent_reweighted_ls(model, cloud):
    c, m, gross = cloud(3)
    ra = arls.fit_arls(m, model, settings=ALGEBRAIC)
    off_ref, off_ls_ref, p_ref = _reference_arls(m, model)
    sl = slice(0, 2) if model == "2d" else slice(0, 3)
    np.testing.assert_allclose(ra.params.offset[sl], off_ref, atol=1e-4 * c.radius_nt)
    # same weights: the same samples rejected
    assert np.count_nonzero((ra.weights == 0) != (p_ref == 0)) <= 2
    np.testing.assert_allclose(ra.weights, p_ref, atol=1e-3)
    # and its first step is plain LS
    rl = two_step.fit_ls(m, model)
    np.testing.assert_allclose(rl.params.offset[sl], off_ls_ref, atol=1e-6 * c.radius_nt)
    assert np.linalg.norm(off_ref - off_ls_ref) > 0.01 * c.radius_nt  # the re-weighting moved it


def test_clean_data_rejects_almost_nothing_and_equals_ls():
    c = synthetic.make_cloud(synthetic.CloudSettings(model="3d", n_samples=2000, noise_nt=50.0, seed=9))
    ra = arls.fit_arls(c.m_nt, "3d", settings=ALGEBRAIC)
    rl = two_step.fit_ls(c.m_nt, "3d")
    # IGG-III with k1 = 3 on Gaussian residuals zeroes ~0.3 %; never a large share of clean data
    assert ra.n_gross_rejected <= 0.02 * len(c.m_nt)
    assert np.mean(ra.weights == 1.0) > 0.8
    assert np.linalg.norm(ra.params.offset - rl.params.offset) < 0.002 * c.radius_nt
    assert _offset_err_pct(ra.params, c) < 0.1


def test_k0_k1_shape_the_weights():
    # a tighter k1 rejects more of the same cloud; k0 below which the weight is exactly 1
    c, m, gross = _paper_2d_cloud(4)
    wide = arls.fit_arls(m, "2d", settings=arls.ArlsSettings(refine=False, k0=1.5, k1=6.0))
    tight = arls.fit_arls(m, "2d", settings=arls.ArlsSettings(refine=False, k0=1.0, k1=2.0))
    assert tight.n_gross_rejected > wide.n_gross_rejected
    assert np.mean(tight.weights[~gross] == 1.0) < np.mean(wide.weights[~gross] == 1.0)


def test_iterations_stop_when_x_stops_changing():
    c, m, gross = _paper_2d_cloud(5)
    one = arls.fit_arls(m, "2d", settings=arls.ArlsSettings(refine=False, max_iterations=1))
    full = arls.fit_arls(m, "2d", settings=ALGEBRAIC)
    assert one.iterations == 1 and one.converged is False
    assert full.converged and 2 <= full.iterations < ALGEBRAIC.max_iterations
    # one re-weighting is not yet the answer: the converged fit is closer to the truth
    assert _offset_err_pct(full.params, c) < _offset_err_pct(one.params, c)


# ---- the robust scale, the settings, the geometric refinement, the result ------------------------


def test_robust_sigma_is_1_4826_mad_floored_relative_to_the_median_residual():
    rng = np.random.default_rng(11)
    v = 7.0 + rng.normal(0.0, 2.0, 2001)  # a non-zero median: the MAD is about it, not about 0
    want = 1.4826 * np.median(np.abs(v - np.median(v)))
    assert arls.robust_sigma(v) == pytest.approx(want, rel=1e-12)
    assert arls.robust_sigma(v) == pytest.approx(2.0, rel=0.05)  # a consistent estimate of σ
    # more than half the residuals equal: MAD 0, the floor min_sigma_rel · median |v| applies
    tied = np.r_[np.full(5, 1e-3), 1.0, -2.0]
    assert arls.robust_sigma(tied) == pytest.approx(1e-6 * 1e-3, rel=1e-9)
    assert arls.robust_sigma(tied, min_sigma_rel=1e-2) == pytest.approx(1e-5, rel=1e-9)
    assert arls.robust_sigma(np.zeros(9)) > 0.0  # perfect data still divides


def test_settings_need_0_lt_k0_lt_k1_and_an_iteration():
    for k0, k1 in ((0.0, 3.0), (2.0, 2.0), (3.0, 2.0), (-1.0, 3.0)):
        with pytest.raises(ValueError, match="k0"):
            arls.ArlsSettings(k0=k0, k1=k1)
    with pytest.raises(ValueError, match="max_iterations"):
        arls.ArlsSettings(max_iterations=0)
    arls.ArlsSettings(k0=0.01, k1=0.02, max_iterations=1)
    d = arls.ArlsSettings()
    assert (d.k0, d.k1, d.refine) == (1.5, 3.0, True)  # the paper's k0 = 1.0–1.5, k1 ≈ 3; refinement on


def _weighted_geometric_fit(m, w, n, start):
    """min Σ w_i (|S (m_i − b)| − 1)² over b and symmetric S, by scipy (independent of the Gauss–Newton)."""
    from scipy.optimize import least_squares

    iu = np.triu_indices(n)

    def unpack(p):
        S = np.zeros((n, n))
        S[iu] = p[n:]
        return p[:n], S + np.triu(S, 1).T

    def res(p):
        b, S = unpack(p)
        return np.sqrt(w) * (np.linalg.norm((m - b) @ S, axis=1) - 1.0)

    b0, S0 = start
    return unpack(least_squares(res, np.r_[b0, S0[iu]], x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15).x)


@pytest.mark.parametrize("model,noise", [("3d", 1500.0), ("2d", 1000.0)])
def test_refinement_reaches_the_weighted_geometric_fit(model, noise):
    """With refine on, the answer is the minimum of the IGG-weighted geometric residual (its own final
    weights), which the algebraic ARLS alone is not: under strong noise the two differ measurably."""
    c = synthetic.make_cloud(synthetic.CloudSettings(model=model, n_samples=800, noise_nt=noise, gross_frac=0.1,
                                                     seed=21))
    n = 3 if model == "3d" else 2
    ref = arls.fit_arls(c.m_nt, model)
    alg = arls.fit_arls(c.m_nt, model, settings=ALGEBRAIC)
    assert ref.ok and alg.ok
    ls = two_step.fit_ls(c.m_nt, model).params
    b, S = _weighted_geometric_fit(c.m_nt[:, :n], ref.weights, n,
                                   (ls.offset[:n], ls.M[:n, :n] / ls.field_radius_nt))
    S_ref = ref.params.M[:n, :n] / ref.params.field_radius_nt
    S_alg = alg.params.M[:n, :n] / alg.params.field_radius_nt
    # (measured: 8e-7 / 2e-7 of the field and 8e-6 / 7e-7 of S in 3-D / 2-D; a Jacobian without the
    # symmetric cross terms lands 1e-5 / 2e-5 away)
    assert np.linalg.norm(ref.params.offset[:n] - b) < 4e-6 * c.radius_nt
    assert np.abs(S_ref - S).max() < 1.5e-5 * np.abs(S).max()
    assert np.linalg.norm(alg.params.offset[:n] - b) > 5e-5 * c.radius_nt  # the refinement did something
    assert np.abs(S_alg - S).max() > 5e-4 * np.abs(S).max()
    # the weights are IGG-III of the final geometric residuals over their robust scale
    r = np.linalg.norm((c.m_nt[:, :n] - ref.params.offset[:n]) @ S_ref, axis=1) - 1.0
    np.testing.assert_allclose(ref.weights, arls.igg3_weights(r / arls.robust_sigma(r), 1.5, 3.0), atol=1e-3)
    assert ref.n_gross_rejected == int(np.count_nonzero(ref.weights == 0))
    # fewer Gauss–Newton steps do not reach it
    one = arls.fit_arls(c.m_nt, model, settings=arls.ArlsSettings(refine_iterations=1))
    assert np.abs(one.params.M[:n, :n] / one.params.field_radius_nt - S).max() > np.abs(S_ref - S).max()


@pytest.mark.parametrize("model", ["3d", "2d"])
def test_refined_parameters_radius_and_embedding(model):
    c = synthetic.make_cloud(synthetic.CloudSettings(model=model, n_samples=600, noise_nt=20.0, seed=22))
    n = 3 if model == "3d" else 2
    free = arls.fit_arls(c.m_nt, model).params
    fixed = arls.fit_arls(c.m_nt, model, radius_nt=c.radius_nt).params
    assert np.linalg.det(free.M[:n, :n]) == pytest.approx(1.0, rel=1e-9)  # geometric-mean radius
    assert fixed.field_radius_nt == c.radius_nt
    np.testing.assert_allclose(fixed.M[:n, :n] / fixed.field_radius_nt, free.M[:n, :n] / free.field_radius_nt,
                               rtol=1e-9)
    h = fixed.apply(c.m_nt)
    strength = np.linalg.norm(h[:, :n], axis=1)
    assert abs(np.median(strength) - c.radius_nt) < 1e-3 * c.radius_nt
    assert magcal.offset_error_pct(free.offset, c.offset_nt, c.radius_nt) < 0.05
    assert free.model == model
    if model == "2d":
        assert free.observable == (True, True, False) and free.offset[2] == 0.0 and free.M[2, 2] == 1.0
        assert np.all(free.M[:2, 2] == 0) and np.all(free.M[2, :2] == 0)
    else:
        assert free.observable == (True, True, True)


def test_result_fields_and_refusals():
    import time

    c, m, gross = _paper_2d_cloud(6, n=1000)
    t0 = time.perf_counter()
    r = arls.fit_arls(m, "2d", settings=ALGEBRAIC)
    elapsed_ms = 1e3 * (time.perf_counter() - t0)
    assert r.ok and r.method == "arls" and r.model == "2d" and r.n_samples == 1000 and r.reason == ""
    assert 0.0 < r.duration_ms <= elapsed_ms
    h = r.params.apply(m)
    resid = np.hypot(h[:, 0], h[:, 1]) - r.params.field_radius_nt
    keep = r.weights > 0
    assert r.rmse_nt == pytest.approx(np.sqrt(np.mean(resid[keep] ** 2)), rel=1e-9)  # over the kept samples
    assert r.rmse_nt < np.sqrt(np.mean(resid**2))
    # a hyperbola is no ellipse: refused with a reason, no parameters
    t = np.linspace(-2, 2, 300)
    hyp = np.column_stack([np.cosh(t), np.sinh(t), np.zeros_like(t)]) * 1000.0
    t0 = time.perf_counter()
    bad = arls.fit_arls(hyp, "2d")
    elapsed_ms = 1e3 * (time.perf_counter() - t0)
    assert not bad.ok and bad.params is None and "no ellipsoid" in bad.reason and not bad.converged
    assert bad.method == "arls" and bad.model == "2d" and bad.n_samples == 300 and bad.iterations >= 1
    assert 0.0 < bad.duration_ms <= elapsed_ms
    # too few samples keep a weight: 10 samples for 5 unknowns cannot leave 2 × 5 non-zero weights
    few = c.m_nt[::100][:10].copy()
    few[0, :2] += 5000.0
    r_few = arls.fit_arls(few, "2d")
    assert not r_few.ok and "too few samples" in r_few.reason
    assert arls.fit_arls(c.m_nt[::50], "2d").ok  # 20 clean samples do
    # samples on a line: the very first (plain LS) solve is singular, no iteration ran
    t = np.linspace(-1.0, 1.0, 64)
    line = np.column_stack([1000.0 * t, 2000.0 * t, np.zeros_like(t)])
    r_line = arls.fit_arls(line, "2d")
    assert not r_line.ok and r_line.iterations == 0 and r_line.converged is False
    # the algebraic fit honours a given field strength too
    alg_r = arls.fit_arls(m, "2d", radius_nt=c.radius_nt, settings=ALGEBRAIC).params
    assert alg_r.field_radius_nt == c.radius_nt
    c3 = synthetic.make_cloud(synthetic.CloudSettings(model="3d", n_samples=400, noise_nt=20.0, seed=24))
    d = arls.fit_arls(c3.m_nt)  # the model defaults to the ellipsoid
    assert d.model == "3d" and d.params.model == "3d"
    np.testing.assert_array_equal(d.params.offset, arls.fit_arls(c3.m_nt, "3d").params.offset)


def test_a_high_scale_floor_keeps_every_sample_in_both_loops():
    """σ̂ is floored at ``min_sigma_rel`` × median |v| in the algebraic and the geometric loop alike: with a
    floor of 100 × the median residual no residual is large, every weight stays 1 and ARLS is least squares
    (algebraic) or the unweighted geometric fit (refined)."""
    c, m, gross = _paper_2d_cloud(7, n=800)
    st = arls.ArlsSettings(min_sigma_rel=100.0, refine=False)
    alg = arls.fit_arls(m, "2d", settings=st)
    assert alg.n_gross_rejected == 0 and np.all(alg.weights == 1.0)
    np.testing.assert_allclose(alg.params.offset, two_step.fit_ls(m, "2d").params.offset, atol=1e-6 * c.radius_nt)
    ref = arls.fit_arls(m, "2d", settings=arls.ArlsSettings(min_sigma_rel=100.0))
    assert ref.n_gross_rejected == 0 and np.all(ref.weights == 1.0)
    ls = two_step.fit_ls(m, "2d").params
    b, S = _weighted_geometric_fit(m[:, :2], np.ones(len(m)), 2, (ls.offset[:2], ls.M[:2, :2] / ls.field_radius_nt))
    assert np.linalg.norm(ref.params.offset[:2] - b) < 2e-5 * c.radius_nt
    assert np.linalg.norm(arls.fit_arls(m, "2d").params.offset[:2] - b) > 1e-3 * c.radius_nt  # the default rejects
