"""Geomagnetic matcher core: Hausdorff scoring against scipy, SSDA exactness, pipeline vs exhaustive, M-of-N."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import directed_hausdorff

from magmesh.geomap import GridMap, load_map, synthetic_paper_map
from magmesh.paths import DATA_DIR
from services.geomag_matcher.core import (
    AcceptSettings,
    GeomagMatcher,
    MatcherSettings,
    MatchResult,
    MatchSettings,
    MofNAcceptor,
    hausdorff,
    match_exhaustive,
    match_sequence,
)
from sim_publishers.survey.core import SurveySettings, simulate


@pytest.fixture(scope="module")
def grid() -> GridMap:
    return synthetic_paper_map(7)


def test_synthetic_map_has_the_paper_statistics(grid):
    assert grid.shape == (150, 150)
    assert grid.dx_m == grid.dy_m == 100.0
    assert abs(grid.values_nt.mean() - 1.8303) < 1e-6
    assert abs(grid.std_nt - 16.8425) < 1e-6
    # spatially correlated: neighbours much closer than independent cells
    lag1 = np.corrcoef(grid.values_nt[:-1].ravel(), grid.values_nt[1:].ravel())[0, 1]
    assert lag1 > 0.8
    assert np.array_equal(grid.values_nt, synthetic_paper_map(7).values_nt)  # deterministic


def test_bilinear_matches_paper_formula_and_nodes(grid):
    v = grid.values_nt
    assert grid.bilinear(10.0, 20.0) == pytest.approx(v[10, 20])
    u, w = 0.3, 0.6
    expect = (1 - u) * (1 - w) * v[10, 20] + u * (1 - w) * v[11, 20] + (1 - u) * w * v[10, 21] + u * w * v[11, 21]
    assert grid.bilinear(10.3, 20.6) == pytest.approx(expect)
    assert grid.cell_mean(10.3, 20.6) == pytest.approx(v[10:12, 20:22].mean())
    # the cubic 'true' surface passes through the nodes too
    assert grid.cubic(10.0, 20.0) == pytest.approx(v[10, 20], abs=1e-6)


def test_set_hausdorff_equals_scipy_and_ordered_is_pointwise():
    rng = np.random.default_rng(3)
    h = rng.normal(0, 10, 15)
    strips = rng.normal(0, 10, (40, 15))
    ours = hausdorff(h, strips, None)
    ref = [max(directed_hausdorff(h[:, None], r[:, None])[0], directed_hausdorff(r[:, None], h[:, None])[0])
           for r in strips]
    assert np.allclose(ours, ref)
    assert np.allclose(hausdorff(h, strips, 0), np.abs(strips - h).max(axis=1))
    # the window interpolates: 0 ≥ ... ≥ set
    w1 = hausdorff(h, strips, 1)
    assert np.all(w1 <= hausdorff(h, strips, 0) + 1e-12) and np.all(w1 >= ours - 1e-12)
    # partial Hausdorff ignores the worst sample
    spiky = h.copy()
    spiky[4] += 500.0
    assert hausdorff(spiky, h[None], 0, rank_frac=14 / 15)[0] == pytest.approx(0.0)


def _paper_case(grid, n, snr, rng):
    c = np.radians(60.0)
    offs = np.arange(n)[:, None] * (1.5 * np.array([np.sin(c), np.cos(c)]))
    true0, ins0 = np.array([65.0, 70.0]), np.array([75.0, 75.0])
    h = grid.cubic(*(true0 + offs).T) + rng.normal(0, grid.std_nt / snr, n)
    return h, grid.to_metres(ins0 + offs), true0


@pytest.mark.parametrize("window", [0, None])
@pytest.mark.parametrize("prematch", ["centre", "corners"])
def test_pipeline_finds_the_exhaustive_answer(grid, window, prematch):
    rng = np.random.default_rng(11)
    s = MatchSettings(n_samples=15, window_samples=window, prematch_score=prematch, lambda_nt=8.4)
    agree = 0
    for _ in range(4):
        h, ins, _ = _paper_case(grid, 15, 16, rng)
        rp = match_sequence(grid, h, ins, s)
        rx = match_exhaustive(grid, h, ins, s)
        assert rp.found and rp.n_abandoned > 0 and rp.n_fine < rx.n_fine
        assert rp.hausdorff_nt >= rx.hausdorff_nt - 1e-9  # the pipeline can only miss the minimum, never beat it
        agree += bool(np.allclose(rp.start_ij, rx.start_ij))
    assert agree >= 3


def test_ssda_never_abandons_a_candidate_below_lambda(grid):
    rng = np.random.default_rng(5)
    h, ins, true0 = _paper_case(grid, 20, 10, rng)
    s = MatchSettings(window_samples=0, lambda_nt=8.4)
    r = match_sequence(grid, h, ins, s)
    assert np.hypot(*(r.start_ij - true0)) < 1.0
    assert r.hausdorff_nt < r.lambda_nt


def test_rotation_search_undoes_an_ins_heading_error(grid):
    rng = np.random.default_rng(8)
    h, ins, true0 = _paper_case(grid, 20, 16, rng)
    b = np.radians(6.0)
    rot = np.array([[np.cos(b), np.sin(b)], [-np.sin(b), np.cos(b)]])  # INS track 6° clockwise
    ins_rot = ins[0] + (ins - ins[0]) @ rot.T
    plain = match_sequence(grid, h, ins_rot, MatchSettings())
    searched = match_sequence(grid, h, ins_rot, MatchSettings(heading_search_deg=8.0, heading_step_deg=2.0))
    assert searched.rotation_deg == pytest.approx(-6.0)
    assert np.hypot(*(searched.start_ij - true0)) < 0.5
    assert searched.hausdorff_nt < plain.hausdorff_nt
    assert searched.margin_nt is not None and searched.margin_nt > 0


def test_lambda_grows_when_nothing_is_feasible(grid):
    rng = np.random.default_rng(2)
    h, ins, _ = _paper_case(grid, 20, 2, rng)  # far noisier than λ allows
    r = match_sequence(grid, h, ins, MatchSettings(lambda_nt=1.0, min_feasible_cells=4))
    assert r.found and r.lambda_nt > 1.0 and r.n_feasible >= 4


def test_wdmam_loads_with_its_coordinates():
    g = load_map(DATA_DIR / "maps" / "map_WDMAM.hdf5")
    assert g.shape == (47, 34)
    assert g.dx_m == pytest.approx(4317.36, abs=0.1)
    assert g.bilinear(3.0, 4.0) == pytest.approx(g.values_nt[3, 4])
    assert np.allclose(g.to_grid(g.to_metres(np.array([[3.5, 7.25]]))), [[3.5, 7.25]])


def _res(end, margin=5.0, d=2.0, found=True):
    end = np.asarray(end, float)
    return MatchResult(found, end, end, end, d, d + margin, margin, 8.0, 1e6)


def test_m_of_n_rule():
    acc = MofNAcceptor(AcceptSettings(m_agree=2, n_window=3, agree_radius_m=100.0, min_margin_nt=0.5))
    ins = np.zeros(2)
    assert acc.update(_res([1000, 0]), ins) == "pending"  # one fix alone is not enough
    assert acc.update(_res([1030, 10]), ins) == "accepted"  # two agree
    assert acc.update(_res([5000, 0]), ins) == "pending"  # an outlier is not accepted
    assert acc.update(_res([1010, 0], margin=0.1), ins) == "ambiguous"
    assert acc.update(_res([1010, 0], d=99.0), ins) == "rejected"
    assert acc.update(_res([1000, 0], found=False), ins) == "rejected"
    assert acc.update(_res([1000, 5]), ins) == "pending"  # the old agreeing fixes have left the window
    assert acc.update(_res([1002, 5]), ins) == "accepted"


def test_streaming_matcher_corrects_the_simulated_ins():
    s = SurveySettings(snr=10.0, seed=4)
    grid = load_map(s.map)
    run = simulate(s, grid)
    m = GeomagMatcher(grid, MatcherSettings(main_field_nt=run.core_field_nt, divergence_alarm_m=1000.0))
    fix_err, ins_err = [], []
    for i in range(run.t_s.size):
        f = m.update(run.t_s[i], run.f_nt[i], run.ins_pos_m[i])
        if f is not None and f.accepted:
            fix_err.append(np.hypot(*(f.result.end_m - run.pos_m[i])))
            ins_err.append(np.hypot(*(run.ins_pos_m[i] - run.pos_m[i])))
    assert len(fix_err) >= 0.8 * m.n_matches >= 30
    assert np.median(ins_err) > 1000.0
    assert np.median(fix_err) < 60.0 and np.percentile(fix_err, 95) < 200.0
    assert m.flags["diverged"]
    corrected = m.corrected_position(run.ins_pos_m[-1])
    assert np.hypot(*(corrected - run.pos_m[-1])) < 200.0


def test_ins_error_filter_tracks_a_drifting_correction_and_gates_outliers():
    from services.geomag_matcher.core import FilterSettings, InsErrorFilter

    kf = InsErrorFilter(FilterSettings(fix_std_m=30.0, gate_sigma=5.0, reset_after_rejections=3))
    rng = np.random.default_rng(4)
    drift = np.array([0.3, -0.2])  # m/s
    c0 = np.array([-1000.0, -500.0])
    for k in range(60):
        t = 25.0 * k
        assert kf.update(t, c0 + drift * t + rng.normal(0, 30.0, 2))
    t = 25.0 * 60
    est = kf.correction_at(t)
    assert np.hypot(*(est - (c0 + drift * t))) < 30.0
    assert np.allclose(kf.x[2:], drift, atol=0.1)
    # a fix 2 km off is gated, three in a row restart the filter there
    far = c0 + drift * t + [2000.0, 0.0]
    assert not kf.update(t, far) and kf.test_ratio > 1.0
    assert not kf.update(t + 25, far) and not kf.update(t + 50, far)
    assert kf.update(t + 75, far)
    assert np.allclose(kf.correction_at(t + 75), far)


def test_ssda_pruning_is_exact_for_every_window_and_rank():
    from services.geomag_matcher.core import _ssda_scores, _strip

    rng = np.random.default_rng(21)
    small = synthetic_paper_map(3, n_cells=40)
    offs = np.cumsum(rng.normal(0.8, 0.3, (12, 2)), axis=0)
    offs -= offs[0]
    starts = rng.uniform(0, 25, (400, 2))
    h = small.bilinear(*(starts[0] + offs).T) + rng.normal(0, 2.0, 12)
    for window in (0, 1, None):
        for rank in (1.0, 0.75):
            s = MatchSettings(n_samples=12, window_samples=window, rank_frac=rank)
            full = hausdorff(h, _strip(small, starts, offs, slice(None), coarse=True), window, rank)
            lam = float(np.quantile(full, 0.2))
            pruned, _ = _ssda_scores(small, h, starts, offs, lam, s, coarse=True)
            kept = np.isfinite(pruned)
            assert np.allclose(pruned[kept], full[kept])
            assert np.all(full[~kept] > lam)  # abandoned only when provably above λ
            assert np.all(kept[full < lam])


def test_demean_survives_an_unknown_constant_bias(grid):
    rng = np.random.default_rng(9)
    hits_plain = hits_demean = 0
    for _ in range(5):
        h, ins, true0 = _paper_case(grid, 20, 16, rng)
        h = h + 25.0  # e.g. a core-field reference 25 nT off
        plain = match_sequence(grid, h, ins, MatchSettings())
        dem = match_sequence(grid, h, ins, MatchSettings(demean=True))
        hits_plain += bool(plain.found and np.hypot(*(plain.start_ij - true0)) < 1.0)
        hits_demean += bool(np.hypot(*(dem.start_ij - true0)) < 1.0)
    assert hits_demean == 5 and hits_plain <= 2


def test_spline_cache_belongs_to_its_map_after_other_maps_are_freed():
    """The bicubic surface of a map is its own, even after maps freed earlier leave their ids to be reused."""
    import gc

    import numpy as np

    from magmesh.geomap import GridMap

    rng = np.random.default_rng(11)
    # the objects alive before the test (the whole session's heap) are set aside, so that each full collection
    # below goes over the maps made here only (the same collection for them, in milliseconds, not seconds)
    gc.freeze()
    try:
        for _ in range(20):
            m = GridMap(rng.normal(0, 50, (30, 30)))
            m.cubic(3.0, 4.0)
            del m
            gc.collect()
        for k in range(5):
            vals = rng.normal(0, 50, (30, 30))
            m = GridMap(vals)
            assert float(m.cubic(3.0, 4.0)) == pytest.approx(vals[3, 4], abs=1e-9), k
            del m
            gc.collect()
    finally:
        gc.unfreeze()
