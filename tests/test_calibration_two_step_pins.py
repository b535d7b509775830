"""Pins of the Two-Step calibration (services/calibration/two_step.py) against the method's definition.

Step 1 is the linear least squares ``A X = L`` (L = 1) on centred and scaled samples, with the rows
[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] (2-D: [x², y², 2xy, 2x, 2y]); step 2 decomposes X into the offset
b and the matrix M = R·sqrtm(W) of the quadric (m − b)ᵀW(m − b) = 1, R the geometric-mean radius
det(W)^(−1/2n) (so det M = 1) unless the field strength is given. Each expected value here is computed
independently: numpy's lstsq instead of the normal equations, medians by hand, the quadric written out.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from bench import calibration_synthetic as synthetic
from magmesh import magcal
from services.calibration import two_step


def _cloud(**kw):
    return synthetic.make_cloud(synthetic.CloudSettings(**kw))


def test_normalise_centres_on_the_median_and_scales_by_the_median_distance():
    m = np.array([[1.0, 10.0], [3.0, 14.0], [2.0, 11.0], [100.0, 12.0], [4.0, -50.0]])
    x, norm = two_step.normalise(m)
    np.testing.assert_array_equal(norm.centre, [3.0, 11.0])
    d = np.hypot(m[:, 0] - 3.0, m[:, 1] - 11.0)
    assert norm.scale == pytest.approx(np.sort(d)[2])
    np.testing.assert_allclose(x, (m - [3.0, 11.0]) / norm.scale)
    # any positive spread will do, however small the unit (a cloud in tesla rather than nT)
    small = m * 1e-9
    xs, ns = two_step.normalise(small)
    np.testing.assert_allclose(xs, x, rtol=1e-9)
    assert ns.scale == pytest.approx(norm.scale * 1e-9)
    with pytest.raises(ValueError, match="spread"):
        two_step.normalise(np.ones((10, 3)))
    with pytest.raises(ValueError, match="spread"):
        two_step.normalise(np.array([[np.nan, 0.0, 0.0]] * 5))


def test_design_rows_are_the_quadric_written_out():
    rng = np.random.default_rng(0)
    x3 = rng.normal(size=(7, 3))
    Q = np.array([[1.2, 0.1, -0.2], [0.1, 0.9, 0.05], [-0.2, 0.05, 1.1]])
    g = np.array([0.3, -0.1, 0.2])
    X = np.r_[Q[0, 0], Q[1, 1], Q[2, 2], Q[0, 1], Q[0, 2], Q[1, 2], g]  # u = 2 g
    want = np.einsum("ni,ij,nj->n", x3, Q, x3) + 2 * x3 @ g
    np.testing.assert_allclose(two_step.design_matrix(x3) @ X, want, rtol=1e-12)
    Q2, u2, k = two_step.quadric_from_solution(X, 3)
    np.testing.assert_array_equal(Q2, Q)
    np.testing.assert_array_equal(u2, 2 * g)
    assert k == -1.0
    x2 = rng.normal(size=(6, 2))
    Q = np.array([[1.3, -0.2], [-0.2, 0.8]])
    g = np.array([-0.4, 0.25])
    X = np.r_[Q[0, 0], Q[1, 1], Q[0, 1], g]
    want = np.einsum("ni,ij,nj->n", x2, Q, x2) + 2 * x2 @ g
    np.testing.assert_allclose(two_step.design_matrix(x2) @ X, want, rtol=1e-12)
    Q2, u2, k = two_step.quadric_from_solution(X, 2)
    np.testing.assert_array_equal(Q2, Q)
    np.testing.assert_array_equal(u2, 2 * g)
    assert k == -1.0


def test_solve_weighted_is_least_squares_with_and_without_weights():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(40, 5))
    np.testing.assert_allclose(two_step.solve_weighted(A), np.linalg.lstsq(A, np.ones(40), rcond=None)[0], rtol=1e-9)
    w = rng.uniform(0.0, 2.0, 40)
    w[:6] = 0.0
    sw = np.sqrt(w)
    ref = np.linalg.lstsq(A * sw[:, None], sw, rcond=None)[0]
    np.testing.assert_allclose(two_step.solve_weighted(A, w), ref, rtol=1e-9)
    # zero weight is the same as leaving the row out
    np.testing.assert_allclose(two_step.solve_weighted(A, w), two_step.solve_weighted(A[6:], w[6:]), rtol=1e-9)


def test_model_axes_checks_shape_and_model():
    m = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(two_step.model_axes(m, "2d"), m[:, :2])
    np.testing.assert_array_equal(two_step.model_axes(m.tolist(), "3d"), m)
    with pytest.raises(ValueError, match="N×3"):
        two_step.model_axes(m[:, :2], "3d")
    with pytest.raises(ValueError, match="N×3"):
        two_step.model_axes(m.ravel(), "3d")
    with pytest.raises(ValueError, match="model"):
        two_step.model_axes(m, "4d")
    assert two_step.MODELS == ("2d", "3d")


def test_rmse_is_over_the_samples_with_weight():
    p = magcal.MagParams.from_arrays([0.0, 0.0, 0.0], np.eye(3), 100.0)
    m = np.array([[103.0, 0.0, 0.0], [0.0, 96.0, 0.0], [0.0, 0.0, 100.0], [500.0, 0.0, 0.0]])
    assert two_step.rmse(m, p) == pytest.approx(np.sqrt((9 + 16 + 0 + 400**2) / 4))
    assert two_step.rmse(m, p, np.array([1.0, 0.3, 1.0, 0.0])) == pytest.approx(np.sqrt(25 / 3))
    assert np.isnan(two_step.rmse(m, p, np.zeros(4)))
    p2 = magcal.MagParams.from_arrays([0.0, 0.0, 0.0], np.eye(3), 100.0, "2d", (True, True, False))
    assert two_step.rmse(np.array([[60.0, 80.0, 999.0]]), p2) == pytest.approx(0.0, abs=1e-12)  # horizontal only


def test_the_radius_is_the_geometric_mean_unless_given():
    c = _cloud(noise_nt=0.0, seed=11, n_samples=600)
    free = two_step.fit_ls(c.m_nt, "3d").params
    assert np.linalg.det(free.M) == pytest.approx(1.0, rel=1e-9)  # R = det(W)^(−1/6) ⇒ det(R·sqrtm W) = 1
    fixed = two_step.fit_ls(c.m_nt, "3d", radius_nt=c.radius_nt).params
    assert fixed.field_radius_nt == c.radius_nt
    np.testing.assert_allclose(np.linalg.norm(fixed.apply(c.m_nt), axis=1), c.radius_nt, rtol=1e-7)
    np.testing.assert_allclose(fixed.M / fixed.field_radius_nt, free.M / free.field_radius_nt, rtol=1e-9)
    assert free.model == "3d" and free.observable == (True, True, True)


def test_a_2d_fit_leaves_z_alone():
    c = _cloud(model="2d", noise_nt=0.0, seed=12, n_samples=400)
    p = two_step.fit_ls(c.m_nt, "2d").params
    assert p.model == "2d" and p.observable == (True, True, False)
    assert p.offset[2] == 0.0 and p.M[2, 2] == 1.0 and np.all(p.M[:2, 2] == 0) and np.all(p.M[2, :2] == 0)
    assert np.linalg.det(p.M[:2, :2]) == pytest.approx(1.0, rel=1e-9)  # R = det(W)^(−1/4)
    h = p.apply(c.m_nt)
    np.testing.assert_allclose(np.hypot(h[:, 0], h[:, 1]), p.field_radius_nt, rtol=1e-7)
    np.testing.assert_allclose(h[:, 2], c.m_nt[:, 2])
    fixed = two_step.fit_ls(c.m_nt, "2d", radius_nt=c.radius_nt).params
    assert fixed.field_radius_nt == c.radius_nt
    np.testing.assert_allclose(fixed.offset[:2], c.offset_nt[:2], atol=1e-6 * c.radius_nt)


def test_fit_ls_reports_the_fit_and_refuses_a_non_ellipse():
    c = _cloud(noise_nt=30.0, seed=13, n_samples=500)
    t0 = time.perf_counter()
    r = two_step.fit_ls(c.m_nt, "3d")
    elapsed_ms = 1e3 * (time.perf_counter() - t0)
    assert r.ok and r.method == "ls" and r.model == "3d" and r.n_samples == 500 and r.reason == ""
    assert r.iterations == 1 and r.converged and r.n_gross_rejected == 0 and r.weights is None
    assert r.rmse_nt == pytest.approx(two_step.rmse(c.m_nt, r.params))
    assert 0.0 < r.duration_ms <= elapsed_ms
    # a hyperbola: the least-squares quadric is not an ellipse
    t = np.linspace(-2, 2, 200)
    hyp = np.column_stack([np.cosh(t), np.sinh(t), np.zeros_like(t)]) * 1000.0
    t0 = time.perf_counter()
    bad = two_step.fit_ls(hyp, "2d")
    elapsed_ms = 1e3 * (time.perf_counter() - t0)
    assert not bad.ok and bad.params is None and "no ellipsoid" in bad.reason and bad.method == "ls"
    assert bad.model == "2d" and bad.n_samples == 200 and bad.rmse_nt is None
    assert 0.0 < bad.duration_ms <= elapsed_ms
    # the model defaults to the ellipsoid
    d = two_step.fit_ls(c.m_nt)
    assert d.model == "3d" and d.params.model == "3d"
    np.testing.assert_array_equal(d.params.offset, r.params.offset)
