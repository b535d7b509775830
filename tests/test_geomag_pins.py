"""Pins of the geomagnetic matcher's method (services/geomag_matcher/core.py) on small hand-made maps.

- settings: every bound checked, each alone;
- scoring: the K-th ranked term (K = ⌈rank_frac·N⌉), the windowed directed terms and the two directions of
  the Hausdorff distance, worked by hand;
- the search area (strip on the map, radius), the INS offsets in grid units, the pre-match strip (cell mean)
  and the fine strip (bilinear);
- SSDA: a candidate is abandoned once more than N − K terms exceed λ, the survivors get their full
  distance, and the cost counted is the terms computed;
- the pipeline: an exact planted strip is found at distance 0 on the fine lattice, λ grows until enough
  cells are feasible and stops at its maximum, the runner-up is the best start beyond the exclusion radius;
- the INS heading search: the rotation that matched, its tie-break, the counts summed over rotations;
- M-of-N acceptance at its limits; the INS-error Kalman filter against the closed-form step;
- the streaming matcher: buffering, match cadence, the main field removed, the search centred on the
  corrected INS, the divergence alarm.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magmesh.geomap import GridMap
from services.geomag_matcher import core
from services.geomag_matcher.core import (
    AcceptSettings,
    FilterSettings,
    GeomagMatcher,
    InsErrorFilter,
    MatcherSettings,
    MatchResult,
    MatchSettings,
    MofNAcceptor,
    directed_terms,
    hausdorff,
    match_exhaustive,
    match_sequence,
)


def _smooth_map(n=24, dx=100.0, dy=100.0, x0=0.0, y0=0.0, seed=1) -> GridMap:
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v = np.zeros((n, n))
    for _ in range(6):
        a, b, p, q = rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.6), rng.uniform(0, 6), rng.uniform(0, 6)
        v += rng.uniform(10, 30) * np.sin(a * i + p) * np.cos(b * j + q)
    return GridMap(v, x0_m=x0, y0_m=y0, dx_m=dx, dy_m=dy)


GRID = _smooth_map()
OFFS = np.arange(12)[:, None] * np.array([0.8, 0.5])  # INS increments, grid units


def _planted(grid=GRID, start=(8 + 1 / 3, 6 + 2 / 3), offs=OFFS):
    start = np.asarray(start)
    h = grid.bilinear(*(start + offs).T)
    ins = grid.to_metres(start + offs)
    return h, ins, start


# ---- settings -------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [dict(n_samples=1), dict(window_samples=-1), dict(rank_frac=0.0),
                                 dict(rank_frac=1.01), dict(lambda_nt=0.0), dict(lambda_growth=1.0),
                                 dict(prematch_score="edges"), dict(subdivisions=0), dict(subdivisions=17),
                                 dict(search_radius_m=-1.0), dict(heading_search_deg=-0.5),
                                 dict(heading_search_deg=45.5), dict(heading_step_deg=0.0)])
def test_match_settings_reject_each_bad_value(bad):
    with pytest.raises(ValueError):
        MatchSettings(**bad)


def test_match_settings_accept_their_limits():
    MatchSettings(n_samples=2, window_samples=0, rank_frac=1.0, subdivisions=1, search_radius_m=0.0,
                  heading_search_deg=45.0)
    MatchSettings(window_samples=None, rank_frac=0.01, subdivisions=16, lambda_growth=1.01, lambda_nt=1e-6,
                  prematch_score="corners", heading_search_deg=0.0, heading_step_deg=0.01)


def test_accept_and_filter_settings_are_checked():
    AcceptSettings(m_agree=1, n_window=1)
    AcceptSettings(m_agree=3, n_window=3)
    for bad in (dict(m_agree=0), dict(m_agree=4, n_window=3), dict(agree_radius_m=0.0)):
        with pytest.raises(ValueError):
            AcceptSettings(**bad)
    FilterSettings(drift_rate_noise_m_s2=0.0)
    for bad in (dict(fix_std_m=0.0), dict(drift_rate_noise_m_s2=-1e-6), dict(gate_sigma=0.0)):
        with pytest.raises(ValueError):
            FilterSettings(**bad)


# ---- scoring --------------------------------------------------------------------------------------


def test_kth_ranked_term():
    h = np.zeros(5)
    r = np.array([[5.0, 1.0, 3.0, 2.0, 4.0]])  # window 0: the terms are |h − r|
    for rank, ref in ((1.0, 5.0), (0.8, 4.0), (0.6, 3.0), (0.61, 4.0), (0.4, 2.0), (0.2, 1.0), (0.01, 1.0)):
        assert hausdorff(h, r, 0, rank)[0] == ref, rank
    assert core._kth(np.array([[9.0, 7.0, 8.0], [1.0, 3.0, 2.0]]), 2 / 3).tolist() == [8.0, 2.0]


def test_directed_terms_with_a_window():
    a = np.array([0.0, 10.0, 20.0])
    b = np.array([20.0, 10.0, 0.0])
    assert directed_terms(a, b, 0).tolist() == [20.0, 0.0, 20.0]
    assert directed_terms(a, b, 1).tolist() == [10.0, 0.0, 10.0]
    assert directed_terms(a, b, 2).tolist() == [0.0, 0.0, 0.0]
    assert directed_terms(a, b, None).tolist() == [0.0, 0.0, 0.0]
    # batched strips
    bb = np.stack([b, a])
    assert directed_terms(np.broadcast_to(a, bb.shape), bb, 1).tolist() == [[10.0, 0.0, 10.0], [0.0, 0.0, 0.0]]


def test_hausdorff_takes_the_larger_direction():
    a = np.array([0.0, 0.0, 0.0, 0.0])
    b = np.array([[0.0, 7.0, 0.0, 0.0]])
    # a → b: every a_i has a b_j = 0 at hand: 0; b → a: 7 has nothing nearer than 0: 7
    assert hausdorff(a, b, None)[0] == 7.0
    assert hausdorff(b[0], a[None], None)[0] == 7.0
    # windowed: both directions counted, with the window
    a2 = np.array([0.0, 0.0, 5.0, 5.0])
    b2 = np.array([[0.0, 5.0, 5.0, 5.0]])
    assert directed_terms(a2, b2[0], 1).max() == 0.0  # a2 → b2 within one sample: covered
    assert directed_terms(b2[0], a2, 1).max() == 0.0
    b3 = np.array([[5.0, 0.0, 0.0, 5.0]])  # a2 → b3 within one sample: 0; b3 → a2: the first 5 sees only 0s
    assert directed_terms(a2, b3[0], 1).max() == 0.0 and hausdorff(a2, b3, 1)[0] == 5.0
    b4 = np.array([[5.0, 5.0, 0.0, 0.0]])
    assert hausdorff(a2, b4, 1)[0] == 5.0 and hausdorff(a2, b4, None)[0] == 0.0
    assert hausdorff(a2, b4, 0)[0] == 5.0
    # the reverse direction alone decides: a ⊂ b's values but b has one more value
    a5 = np.array([1.0, 1.0, 1.0])
    b5 = np.array([[1.0, 4.0, 1.0]])
    assert directed_terms(a5, b5[0], 1).max() == 0.0 and hausdorff(a5, b5, 1)[0] == 3.0


# ---- geometry of the search -----------------------------------------------------------------------


def test_offsets_are_ins_increments_in_grid_units():
    g = GridMap(np.zeros((5, 5)), x0_m=1000.0, y0_m=-500.0, dx_m=50.0, dy_m=200.0)
    ins = np.array([[1100.0, 0.0, 9.0], [1200.0, 400.0, 9.0], [1050.0, -200.0, 9.0]])
    assert core._offsets_ij(g, ins).tolist() == [[0.0, 0.0], [2.0, 2.0], [-1.0, -1.0]]


def test_search_box_keeps_the_whole_strip_on_the_map_and_inside_the_radius():
    g = GridMap(np.zeros((20, 10)), dx_m=100.0, dy_m=50.0)
    ext = np.array([[0.0, 0.0], [3.5, -2.2], [-1.5, 1.0]])
    lo, hi = core._search_box(g, np.array([10.0, 5.0]), 0.0, ext)
    # starts i with i − 1.5 ≥ 0 and i + 3.5 ≤ 19; j with j − 2.2 ≥ 0 and j + 1 ≤ 9
    assert lo.tolist() == [2, 3] and hi.tolist() == [15, 8]
    lo, hi = core._search_box(g, np.array([10.0, 5.0]), 250.0, ext)  # ±2.5 cells in i, ±5 in j
    assert lo.tolist() == [8, 3] and hi.tolist() == [12, 8]
    lo, hi = core._search_box(g, np.array([10.4, 5.0]), 250.0, np.zeros((2, 2)))
    assert lo.tolist() == [8, 0] and hi.tolist() == [12, 9]
    assert lo.dtype.kind == "i" and hi.dtype.kind == "i"


def test_strips_are_cell_means_for_the_prematch_and_bilinear_for_the_fine_match():
    g = GRID
    starts = np.array([[3.5, 4.5], [10.25, 2.75]])
    offs = np.array([[0.0, 0.0], [1.0, 0.5], [2.2, 1.7]])
    coarse = core._strip(g, starts, offs, slice(None), coarse=True)
    fine = core._strip(g, starts, offs, slice(None), coarse=False)
    v = g.values_nt
    for c in range(2):
        for k in range(3):
            p = starts[c] + offs[k]
            i, j = int(p[0]), int(p[1])
            assert coarse[c, k] == pytest.approx(v[i:i + 2, j:j + 2].mean())
            assert fine[c, k] == pytest.approx(g.bilinear(p[0], p[1]))
    assert core._strip(g, starts, offs, np.array([2]), coarse=False)[:, 0] == pytest.approx(fine[:, 2])


# ---- SSDA -----------------------------------------------------------------------------------------


def _ssda_case(window, rank, lam_q=0.3, seed=4):
    rng = np.random.default_rng(seed)
    g = _smooth_map(16, seed=seed)
    offs = np.cumsum(rng.normal(0.6, 0.2, (8, 2)), axis=0)
    offs -= offs[0]
    starts = rng.uniform(0, 9, (150, 2))
    h = g.bilinear(*(starts[0] + offs).T) + rng.normal(0, 1.0, 8)
    s = MatchSettings(n_samples=8, window_samples=window, rank_frac=rank)
    full = hausdorff(h, core._strip(g, starts, offs, slice(None), coarse=True), window, rank)
    lam = float(np.quantile(full, lam_q))
    return g, h, starts, offs, s, full, lam


@pytest.mark.parametrize("window,rank", [(0, 1.0), (1, 1.0), (None, 1.0), (0, 0.75), (None, 0.75), (2, 0.5)])
def test_ssda_abandons_exactly_the_candidates_with_too_many_terms_over_lambda(window, rank):
    g, h, starts, offs, s, full, lam = _ssda_case(window, rank)
    scores, evals = core._ssda_scores(g, h, starts, offs, lam, s, coarse=True)
    # the reference: terms of the directed distance h → strip; a candidate is abandoned when more than N − K
    # of them exceed λ (every term is a lower bound of the distance's K-th ranked term)
    r = core._strip(g, starts, offs, slice(None), coarse=True)
    terms = directed_terms(np.broadcast_to(h, r.shape), r, window)
    k = math.ceil(rank * 8 - 1e-9)
    abandoned = (terms > lam).sum(axis=1) > 8 - k
    assert np.array_equal(~np.isfinite(scores), abandoned)
    assert 0 < abandoned.sum() < len(starts)
    assert np.allclose(scores[~abandoned], full[~abandoned], rtol=0, atol=1e-12)
    # the cost: at least the full distance of every survivor, less than scoring every candidate twice over
    per = 1 if window == 0 else 2
    assert evals >= (~abandoned).sum() * 8 * per
    width = 8 if window is None else min(8, 2 * window + 1)
    assert evals < len(starts) * 8 * width + len(starts) * 8 * per


def test_ssda_cost_is_counted_term_by_term():
    g, h, starts, offs, s, full, lam = _ssda_case(0, 1.0)
    scores, evals = core._ssda_scores(g, h, starts, offs, 1e9, s, coarse=True)  # nothing abandoned
    assert np.allclose(scores, full) and evals == 150 * 8 + 150 * 8
    scores, evals = core._ssda_scores(g, h, starts, offs, -1.0, s, coarse=True)  # all abandoned at once
    assert np.all(np.isinf(scores)) and evals == 150
    g, h, starts, offs, s, full, lam = _ssda_case(1, 1.0)
    _, evals = core._ssda_scores(g, h, starts, offs, 1e9, s, coarse=True)
    # window 1: the end samples see 2 columns, the 6 inner ones 3; then the full distance both ways
    assert evals == 150 * (2 * 2 + 6 * 3) + 150 * 8 * 2
    g, h, starts, offs, s, full, lam = _ssda_case(None, 1.0)
    _, evals = core._ssda_scores(g, h, starts, offs, 1e9, s, coarse=True)
    assert evals == 150 * 8 * 8 + 150 * 8 * 2


def test_ssda_with_demean_scores_every_candidate_on_demeaned_strips():
    g, h, starts, offs, _, _, _ = _ssda_case(0, 1.0)
    s = MatchSettings(n_samples=8, window_samples=0, demean=True)
    hd = h - h.mean()
    scores, evals = core._ssda_scores(g, hd, starts, offs, -1.0, s, coarse=True)
    r = core._strip(g, starts, offs, slice(None), coarse=True)
    ref = np.abs(hd - (r - r.mean(axis=1, keepdims=True))).max(axis=1)
    assert np.allclose(scores, ref) and evals == 150 * 8
    assert np.allclose(core._prepare(h, s), hd) and np.array_equal(core._prepare(h, MatchSettings()), h)


# ---- the pipeline ---------------------------------------------------------------------------------

PLANT = MatchSettings(n_samples=12, lambda_nt=12.0, subdivisions=3, search_radius_m=600.0,
                      runner_up_exclusion_m=150.0)


def test_pipeline_finds_an_exact_planted_strip_on_the_fine_lattice():
    h, ins, start = _planted()
    r = match_sequence(GRID, h, ins + [250.0, -180.0], PLANT, centre_m=GRID.to_metres(start + [1.2, -0.7]))
    assert r.found and r.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(r.start_ij, start) and np.allclose(r.end_ij, start + OFFS[-1])
    assert np.allclose(r.end_m, GRID.to_metres(start + OFFS[-1]))
    assert r.rotation_deg == 0.0 and r.lambda_nt == 12.0
    # the counts: the search box is ±6 cells around the centre (9.53, 5.97): nodes 4..15 and 0..11, less the
    # starts whose strip (8.8 cells long in i) would leave the 24-node map: nodes 4..14, 10 × 11 cells;
    # 16 fine points per feasible cell at most (shared edges)
    assert r.n_prematch == 10 * 11 and 4 <= r.n_feasible < r.n_prematch and r.n_abandoned > 0
    assert r.n_fine <= r.n_feasible * 16 and r.n_fine > 0
    assert r.search_area_m2 == pytest.approx(10 * 11 * 100.0 * 100.0)
    assert r.runner_up_nt is not None and r.runner_up_nt > 0 and r.margin_nt == pytest.approx(r.runner_up_nt)
    x = match_exhaustive(GRID, h, ins, PLANT, centre_m=GRID.to_metres(start + [1.2, -0.7]))
    assert np.allclose(x.start_ij, start) and x.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert x.n_fine == (10 * 3 + 1) * (11 * 3 + 1) and x.term_evaluations == x.n_fine * 12
    assert x.search_area_m2 == r.search_area_m2
    assert r.term_evaluations < x.term_evaluations


def test_the_runner_up_is_the_best_start_beyond_the_exclusion_radius():
    g = GridMap(np.zeros((6, 6)))
    starts = np.array([[1.0, 1.0], [1.0, 2.0], [4.0, 4.0], [1.0, 3.5], [0.0, 0.0]])
    scores = np.array([0.5, 0.6, 2.0, 3.0, np.inf])
    excl = MatchSettings(runner_up_exclusion_m=100.0)
    r = core._finish(g, starts, scores, np.array([[0.0, 0.0], [1.0, 2.0]]), 8.0, excl, 1.0)
    # (1, 2) is exactly 100 m away: not beyond; (0, 0) was abandoned (inf); (4, 4) and (1, 3.5) are beyond
    assert r.runner_up_nt == 2.0 and r.margin_nt == pytest.approx(1.5)
    assert r.start_ij.tolist() == [1.0, 1.0] and r.end_ij.tolist() == [2.0, 3.0]
    assert r.end_m.tolist() == [200.0, 300.0] and r.hausdorff_nt == 0.5 and r.lambda_nt == 8.0
    r = core._finish(g, starts[:2], scores[:2], np.zeros((1, 2)), 8.0, excl, 1.0)
    assert r.runner_up_nt is None and r.margin_nt == pytest.approx(7.5)  # λ − best: a lower bound
    r = core._finish(g, starts[:2], np.array([9.0, 9.5]), np.zeros((1, 2)), 8.0, MatchSettings(), 1.0)
    assert r.margin_nt == 0.0


def test_a_strip_that_does_not_fit_is_no_match():
    h, ins, start = _planted()
    long = np.arange(30)[:, None] * np.array([1.0, 0.0])  # 29 cells: longer than the 24-node map
    r = match_sequence(GRID, np.zeros(30), GRID.to_metres(long), MatchSettings(n_samples=30))
    assert not r.found and r.reason == "the strip does not fit on the map inside the search area"
    assert r.hausdorff_nt == math.inf
    assert np.all(np.isnan(r.start_ij)) and r.runner_up_nt is None and r.margin_nt is None
    x = match_exhaustive(GRID, np.zeros(30), GRID.to_metres(long), MatchSettings(n_samples=30))
    assert not x.found and "does not fit" in x.reason
    # a search area off the map
    r = match_sequence(GRID, h, ins, PLANT, centre_m=(-5000.0, -5000.0))
    assert not r.found and "does not fit" in r.reason


def test_lambda_grows_by_its_factor_until_enough_cells_are_feasible():
    h, ins, start = _planted()
    noisy = h + np.array([8.0, -8.0] * 6)
    s = MatchSettings(n_samples=12, lambda_nt=1.0, lambda_growth=2.0, search_radius_m=600.0, min_feasible_cells=3)
    r = match_sequence(GRID, noisy, ins, s)
    assert r.found and r.n_feasible >= 3
    lam = math.log2(r.lambda_nt)
    assert lam == int(lam) and r.lambda_nt >= 8.0  # 1, 2, 4, 8, ...: no cell is below 8 nT of the ±8 nT noise
    # the previous λ had fewer feasible cells
    prev = match_sequence(GRID, noisy, ins, dataclasses.replace(s, lambda_nt=r.lambda_nt / 2,
                                                                max_lambda_nt=r.lambda_nt / 2))
    assert prev.n_feasible < 3 and prev.lambda_nt == r.lambda_nt / 2
    # λ stops growing at max_lambda_nt: no match, with the λ reached and the cost so far
    s2 = MatchSettings(n_samples=12, lambda_nt=1.0, lambda_growth=2.0, max_lambda_nt=4.0, search_radius_m=600.0)
    r2 = match_sequence(GRID, noisy, ins, s2)
    assert not r2.found and r2.lambda_nt == 4.0 and "no cell scored below λ = 4 nT" in r2.reason
    # box ±6 cells around (8.33, 6.67): nodes 3..14 and 1..12, 11 × 11 cells
    assert r2.n_prematch == 121 and r2.n_abandoned == 121 and r2.term_evaluations > 0
    assert r2.search_area_m2 == pytest.approx(121 * 1e4)


def test_lambda_does_not_grow_when_enough_cells_are_feasible():
    h, ins, start = _planted()
    r = match_sequence(GRID, h, ins, dataclasses.replace(PLANT, min_feasible_cells=1))
    assert r.lambda_nt == 12.0
    r = match_sequence(GRID, h, ins, MatchSettings(n_samples=12, lambda_nt=6.0, search_radius_m=600.0,
                                                   min_feasible_cells=10 ** 6))  # more than there are cells
    assert r.found and r.lambda_nt < 6.0 * 2 ** 7


def test_corners_prematch_scores_a_cell_by_its_four_corners():
    h, ins, start = _planted()
    s = MatchSettings(n_samples=12, lambda_nt=6.0, prematch_score="corners", search_radius_m=600.0)
    r = match_sequence(GRID, h, ins, s)
    assert r.found and np.allclose(r.start_ij, start) and r.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert r.n_prematch == 121  # cells (their 12 × 12 nodes are what is scored)
    # a cell is feasible when the mean of its corners' distances is below λ (reference computed here)
    offs = core._offsets_ij(GRID, ins)
    centre = GRID.to_grid(ins[0])
    lo, hi = core._search_box(GRID, centre, 600.0, offs)
    ni, nj = np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1)
    NI, NJ = np.meshgrid(ni, nj, indexing="ij")
    nodes = np.stack([NI.ravel(), NJ.ravel()], axis=-1).astype(float)
    d = hausdorff(h, core._strip(GRID, nodes, offs, slice(None), coarse=True), 0).reshape(ni.size, nj.size)
    cell = 0.25 * (d[:-1, :-1] + d[1:, :-1] + d[:-1, 1:] + d[1:, 1:])
    assert r.n_feasible == int(np.sum(cell < r.lambda_nt))


def test_heading_search_rotates_the_track_clockwise_and_prefers_no_rotation_on_a_tie():
    h, ins, start = _planted()
    b = math.radians(4.0)
    rot = np.array([[math.cos(b), math.sin(b)], [-math.sin(b), math.cos(b)]])  # 4° clockwise
    ins_rot = ins[0] + (ins - ins[0]) @ rot.T
    s = dataclasses.replace(PLANT, heading_search_deg=4.0, heading_step_deg=2.0)
    r = match_sequence(GRID, h, ins_rot, s)
    assert r.rotation_deg == -4.0 and r.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(r.start_ij, start)
    single = match_sequence(GRID, h, ins, PLANT)
    # the counts are those of all five rotations (0, ±2°, ±4°), each searched around the same centre
    each = []
    for a in (0.0, 2.0, -2.0, 4.0, -4.0):
        c, sn = math.cos(math.radians(a)), math.sin(math.radians(a))
        turned = ins_rot[0] + (ins_rot - ins_rot[0]) @ np.array([[c, sn], [-sn, c]]).T
        each.append(match_sequence(GRID, h, turned, PLANT, centre_m=ins_rot[0]))
    assert r.n_prematch == sum(e.n_prematch for e in each) and r.n_fine == sum(e.n_fine for e in each)
    assert r.n_abandoned == sum(e.n_abandoned for e in each)
    assert r.term_evaluations == sum(e.term_evaluations for e in each)
    assert each[4].hausdorff_nt == pytest.approx(0.0, abs=1e-9) and each[0].hausdorff_nt > 0.1
    assert r.runner_up_nt is not None and r.margin_nt == pytest.approx(r.runner_up_nt - r.hausdorff_nt)
    # the same track unrotated: 0° wins
    r0 = match_sequence(GRID, h, ins, s)
    assert r0.rotation_deg == 0.0 and np.allclose(r0.start_ij, start)
    # the runner-up over rotations is no worse than the best rotation's own
    assert r0.runner_up_nt <= single.runner_up_nt + 1e-12


def test_heading_search_with_nothing_found_returns_the_unrotated_attempt():
    h, ins, start = _planted()
    s = MatchSettings(n_samples=12, lambda_nt=0.5, max_lambda_nt=0.6, heading_search_deg=2.0,
                      heading_step_deg=2.0, search_radius_m=300.0)
    r = match_sequence(GRID, h + 50.0, ins, s)
    assert not r.found and r.rotation_deg == 0.0 and "no cell scored" in r.reason


def test_match_exhaustive_scores_every_fine_start_and_demeans():
    h, ins, start = _planted()
    s = MatchSettings(n_samples=12, subdivisions=2, search_radius_m=300.0, demean=True)
    x = match_exhaustive(GRID, h + 40.0, ins, s, chunk=7)  # a constant bias, small chunks
    assert x.n_fine == (5 * 2 + 1) ** 2  # 5 × 5 cells; the planted start (thirds) is not on this lattice
    assert x.hausdorff_nt > 1e-3 and np.hypot(*(x.start_ij - start)) < 0.5
    xs = match_exhaustive(GRID, h + 40.0, ins, dataclasses.replace(s, subdivisions=3), chunk=5)
    assert np.allclose(xs.start_ij, start) and xs.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert xs.n_fine == (5 * 3 + 1) ** 2 and xs.lambda_nt == s.lambda_nt


# ---- M-of-N ---------------------------------------------------------------------------------------


def _res(end, margin=5.0, d=2.0, found=True):
    end = np.asarray(end, float)
    return MatchResult(found, end, end, end, d, None if margin is None else d + margin, margin, 8.0, 1e6)


def test_m_of_n_limits():
    acc = MofNAcceptor(AcceptSettings(m_agree=2, n_window=3, agree_radius_m=100.0, min_margin_nt=0.5,
                                      max_hausdorff_nt=30.0))
    ins = np.array([10.0, 20.0, 5.0])
    assert acc.update(_res([1010, 20], d=30.0), ins) == "pending"  # at the distance limit: not rejected
    assert acc.agreeing == 1 and acc.last_status == "pending"
    assert acc.update(_res([1110, 20], margin=0.5), ins) == "pending"  # at the margin limit; 100 m: not agreeing
    assert acc.agreeing == 1
    assert acc.update(_res([1111, 20], margin=None), ins) == "accepted"  # no margin known: not ambiguous
    assert acc.agreeing == 2
    assert acc.update(_res([1109, 20], d=30.01), ins) == "rejected" and acc.agreeing == 0
    assert acc.update(_res([1109, 20], margin=0.49), ins) == "ambiguous" and acc.agreeing == 0
    acc.reset()
    assert acc.last_status == "pending" and acc.agreeing == 0
    assert acc.update(_res([1109, 20]), ins) == "pending"
    one = MofNAcceptor(AcceptSettings(m_agree=1, n_window=1))
    assert one.update(_res([0, 0]), ins) == "accepted"


def test_m_of_n_counts_agreement_by_the_correction_not_the_position():
    acc = MofNAcceptor(AcceptSettings(m_agree=2, n_window=2, agree_radius_m=50.0))
    assert acc.update(_res([1000, 0]), np.array([0.0, 0.0])) == "pending"
    # 3 km further on, the same INS correction (+1000, 0): agrees
    assert acc.update(_res([4000, 0]), np.array([3000.0, 0.0])) == "accepted"
    assert acc.update(_res([4000, 0]), np.array([4000.0, 0.0])) == "pending"  # correction 0: does not


# ---- INS-error filter -----------------------------------------------------------------------------


def test_ins_error_filter_step_is_the_kalman_closed_form():
    fs = FilterSettings(fix_std_m=20.0, drift_rate_noise_m_s2=0.01, init_drift_std_m_s=0.5, gate_sigma=5.0)
    kf = InsErrorFilter(fs)
    assert kf.correction_at(0.0) is None
    assert kf.update(10.0, [100.0, -50.0, 7.0])
    assert kf.x.tolist() == [100.0, -50.0, 0.0, 0.0] and kf.test_ratio == 0.0
    assert np.allclose(np.diag(kf.P), [400.0, 400.0, 0.25, 0.25]) and kf.t_s == 10.0
    # predict 30 s: c + ċ dt, P ← F P Fᵀ + Q with the integrated random walk
    dt = 30.0
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    q = 0.01 ** 2
    Q = np.zeros((4, 4))
    for a, b in ((0, 2), (1, 3)):
        Q[a, a], Q[a, b], Q[b, a], Q[b, b] = q * dt ** 3 / 3, q * dt ** 2 / 2, q * dt ** 2 / 2, q * dt
    P = F @ kf.P @ F.T + Q
    x = F @ kf.x
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    z = np.array([130.0, -40.0])
    S = H @ P @ H.T + 400.0 * np.eye(2)
    nu = z - H @ x
    ratio = float(nu @ np.linalg.inv(S) @ nu) / 25.0
    K = P @ H.T @ np.linalg.inv(S)
    assert kf.update(10.0 + dt, z)
    assert kf.test_ratio == pytest.approx(ratio, rel=1e-12)
    assert np.allclose(kf.x, x + K @ nu, rtol=1e-12)
    assert np.allclose(kf.P, (np.eye(4) - K @ H) @ P, rtol=1e-10)
    assert np.allclose(kf.P, kf.P.T, rtol=0, atol=0)
    # prediction without an update; a time before the last fix does not run backwards
    c = kf.correction_at(70.0)
    assert np.allclose(c, kf.x[:2] + kf.x[2:] * 30.0)
    assert np.allclose(kf.correction_at(0.0), kf.x[:2])
    kf.reset()
    assert kf.x is None and kf.t_s is None and kf.rejections == 0 and kf.test_ratio is None


def test_ins_error_filter_gate_and_restart():
    fs = FilterSettings(fix_std_m=10.0, drift_rate_noise_m_s2=0.0, init_drift_std_m_s=1e-6, gate_sigma=3.0,
                        reset_after_rejections=2)
    kf = InsErrorFilter(fs)
    kf.update(0.0, [0.0, 0.0])
    # S = P + R = 100 + 100 per axis (no drift, no process noise): ratio = ν² / (200 · 9)
    assert kf.update(0.0, [math.sqrt(1800.0) - 1e-6, 0.0]) and kf.test_ratio < 1.0
    kf = InsErrorFilter(fs)
    kf.update(0.0, [0.0, 0.0])
    assert not kf.update(0.0, [math.sqrt(1800.0) + 1e-3, 0.0]) and kf.test_ratio > 1.0 and kf.rejections == 1
    assert kf.x.tolist() == [0.0, 0.0, 0.0, 0.0]  # not fused
    assert kf.update(0.0, [1.0, 0.0]) and kf.rejections == 0  # a good fix ends the run of rejections
    assert not kf.update(0.0, [500.0, 0.0]) and not kf.update(0.0, [500.0, 0.0]) and kf.rejections == 2
    assert kf.update(5.0, [500.0, 3.0])  # two in a row: restart at the new fix
    assert kf.x.tolist() == [500.0, 3.0, 0.0, 0.0] and kf.rejections == 0 and kf.t_s == 5.0


# ---- the streaming matcher ------------------------------------------------------------------------


def _feed(m, h, ins, t0=0.0, main=0.0):
    out = []
    for k in range(len(h)):
        out.append(m.update(t0 + k, h[k] + main, ins[k]))
    return out


def test_streaming_matcher_buffers_matches_every_few_samples_and_removes_the_main_field():
    start = np.array([6.0, 4.0])
    offs = np.arange(22)[:, None] * np.array([0.4, 0.2])  # every 5 samples a whole cell: starts on the lattice
    h = GRID.bilinear(*(start + offs).T)
    truth = GRID.to_metres(start + offs)
    ins = truth + [150.0, -120.0]  # the INS is off by a constant
    ms = MatcherSettings(match=MatchSettings(n_samples=12, lambda_nt=12.0, search_radius_m=600.0),
                         accept=AcceptSettings(m_agree=2, n_window=3), match_every_samples=5,
                         divergence_alarm_m=190.0, main_field_nt=48000.0)
    m = GeomagMatcher(GRID, ms)
    fixes = _feed(m, h, ins, main=48000.0)
    assert all(f is None for f in fixes[:11]) and m.flags["collecting"] is False
    assert m.internal_states["buffered_samples"] == 12
    at = [k for k, f in enumerate(fixes) if f is not None]
    assert at == [11, 16, 21]  # the 12th sample, then every 5th
    f0, f1, f2 = (fixes[k] for k in at)
    assert f0.status == "pending" and f1.status == "accepted" and f2.status == "accepted"
    for f, k in zip((f0, f1, f2), at, strict=True):
        assert f.result.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
        assert np.allclose(f.correction_m, [-150.0, 120.0]) and np.allclose(f.ins_end_m, ins[k])
        assert f.divergence_m == pytest.approx(math.hypot(150.0, 120.0)) and f.t_s == float(k)
    assert f1.fused and f1.test_ratio == 0.0 and np.allclose(f1.filtered_correction_m, [-150.0, 120.0])
    assert f0.filtered_correction_m is None and not f0.fused and f0.test_ratio is None
    assert m.n_matches == 3 and m.n_accepted == 2 and m.last_accepted is f2 and m.last_fix is f2
    st = m.internal_states
    assert st["n_matches"] == 3 and st["n_accepted"] == 2 and st["last_hausdorff_nt"] == pytest.approx(0.0, abs=1e-9)
    assert st["last_lambda_nt"] == 12.0 and st["last_feasible_cells"] == f2.result.n_feasible
    assert st["divergence_m"] == pytest.approx(192.09, abs=0.01) and m.flags["diverged"]
    assert m.flags["last_status"] == "accepted" and st["last_match_ms"] > 0
    assert np.allclose(m.corrected_position(ins[-1]), truth[-1])
    assert np.allclose(m.corrected_position(ins[-1], t_s=30.0), truth[-1], atol=1e-6)
    m.reset()
    assert m.corrected_position(ins[-1]) is None and m.internal_states["buffered_samples"] == 0
    assert m.flags == {"collecting": True, "diverged": False, "last_status": None}
    assert m.internal_states["last_margin_nt"] is None and m.internal_states["last_hausdorff_nt"] is None


def test_streaming_matcher_searches_around_the_corrected_ins_once_a_fix_was_accepted():
    start = np.array([4.0, 3.0])
    offs = np.arange(24)[:, None] * np.array([0.5, 0.25])  # the 13th sample at (10, 6): on the lattice
    h = GRID.bilinear(*(start + offs).T)
    truth = GRID.to_metres(start + offs)
    ins = truth + [-450.0, 0.0]  # 4.5 cells off: inside a 500 m radius of the raw INS at first ...
    ms = MatcherSettings(match=MatchSettings(n_samples=12, lambda_nt=12.0, search_radius_m=500.0),
                         accept=AcceptSettings(m_agree=1, n_window=1), match_every_samples=12,
                         divergence_alarm_m=500.0)
    m = GeomagMatcher(GRID, ms)
    fixes = [f for f in _feed(m, h[:12], ins[:12]) if f is not None]
    assert len(fixes) == 1 and fixes[0].accepted and not m.flags["diverged"]
    assert fixes[0].result.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    # ... then the INS jumps another 400 m: the raw INS start is 8.5 cells away (outside the radius), the
    # corrected one 4 cells: the match is still found, and is now 850 m from the INS (diverged)
    jumped = ins[12:] - [400.0, 0.0]
    more = [f for f in _feed(m, h[12:], jumped, t0=12.0) if f is not None]
    assert len(more) == 1 and more[0].result.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(more[0].correction_m, [850.0, 0.0]) and m.flags["diverged"]
    fresh = GeomagMatcher(GRID, ms)  # the same samples searched around the raw INS: the truth is out of reach
    [f] = [f for f in _feed(fresh, h[12:], jumped) if f is not None]
    assert not (f.result.found and f.result.hausdorff_nt < 1e-6)


# ---- details the cases above leave open -----------------------------------------------------------


def test_no_match_result_fields():
    r = match_sequence(GRID, np.zeros(30), GRID.to_metres(np.arange(30)[:, None] * np.array([1.0, 0.0])),
                       MatchSettings(n_samples=30))
    assert r.found is False and r.lambda_nt == 8.4 and r.search_area_m2 == 0.0
    for v in (r.start_ij, r.end_ij, r.end_m):
        assert v.shape == (2,) and np.all(np.isnan(v))
    AcceptSettings(agree_radius_m=0.5)


def test_ambiguous_ends_a_run_of_agreeing_fixes():
    acc = MofNAcceptor(AcceptSettings(m_agree=2, n_window=3, min_margin_nt=0.5))
    acc.update(_res([0, 0]), np.zeros(2))
    assert acc.update(_res([0, 0]), np.zeros(2)) == "accepted" and acc.agreeing == 2
    assert acc.update(_res([0, 0], margin=0.1), np.zeros(2)) == "ambiguous" and acc.agreeing == 0


def test_filter_reset_leaves_a_zero_covariance():
    kf = InsErrorFilter()
    kf.update(0.0, [1.0, 2.0])
    kf.reset()
    assert kf.P.shape == (4, 4) and not kf.P.any()


def _line_matcher(every=12, **kw):
    ms = MatcherSettings(match=MatchSettings(n_samples=12, lambda_nt=12.0, search_radius_m=100.0),
                         accept=AcceptSettings(m_agree=1, n_window=1), match_every_samples=every, **kw)
    return GeomagMatcher(GRID, ms)


# a straight line two cells a sample from node (1, 8): the second INS position is two cells from the first
LINE_START = np.array([1.0, 8.0])
LINE = np.arange(24)[:, None] * np.array([1.0, 0.0])  # one cell a sample, 24 samples
LINE_FAST = np.arange(12)[:, None] * np.array([2.0, 0.0])


def test_the_search_is_centred_on_the_first_ins_position_of_the_strip():
    h = GRID.bilinear(*(LINE_START + LINE_FAST).T)
    ins3 = np.column_stack([GRID.to_metres(LINE_START + LINE_FAST), np.full(12, 35.0)])  # with a height
    m = _line_matcher()
    [f] = [f for f in _feed(m, h, ins3) if f is not None]
    # a 100 m radius: nodes within one cell of the first INS position; the second one is two cells on
    assert f.result.found and f.result.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    assert f.correction_m.shape == (2,) and np.allclose(f.correction_m, 0.0) and f.ins_end_m.shape == (2,)
    assert np.allclose(m.acceptor._history[-1], f.correction_m)  # the acceptor judged the published correction
    assert m.corrected_position(ins3[-1]).shape == (2,)
    # the next strip, searched around the first INS position corrected by the accepted fix
    h2 = GRID.bilinear(*(LINE_START + LINE_FAST).T)
    [f2] = [f for f in _feed(m, h2, ins3, t0=12.0) if f is not None]
    assert f2.result.hausdorff_nt == pytest.approx(0.0, abs=1e-9)


def test_the_first_match_waits_for_the_cadence_when_it_is_longer_than_the_strip():
    h = GRID.bilinear(*(LINE_START + LINE[:15]).T)
    m = _line_matcher(every=15)
    fixes = _feed(m, h, GRID.to_metres(LINE_START + LINE[:15]))
    assert [k for k, f in enumerate(fixes) if f is not None] == [14]


def test_a_failed_match_publishes_nan_corrections_and_the_fresh_state_is_zero():
    m = _line_matcher()
    st = m.internal_states
    assert st["divergence_m"] == 0.0 and st["last_match_ms"] == 0.0 and st["n_matches"] == 0
    ins = GRID.to_metres(np.array([[30.0, 30.0]] * 12))  # off the map: nothing fits
    [f] = [f for f in _feed(m, np.zeros(12), ins) if f is not None]
    assert not f.result.found and f.status == "rejected" and not f.accepted
    assert f.correction_m.shape == (2,) and np.all(np.isnan(f.correction_m)) and math.isnan(f.divergence_m)
    assert m.internal_states["divergence_m"] == 0.0 and m.internal_states["last_hausdorff_nt"] is None


def test_divergence_alarm_is_strictly_beyond_its_distance():
    h = GRID.bilinear(*(LINE_START + LINE_FAST).T)
    truth = GRID.to_metres(LINE_START + LINE_FAST)
    ms = MatcherSettings(match=MatchSettings(n_samples=12, lambda_nt=12.0, search_radius_m=600.0),
                         accept=AcceptSettings(m_agree=1, n_window=1), match_every_samples=12,
                         divergence_alarm_m=500.0)
    m = GeomagMatcher(GRID, ms)
    [f] = [f for f in _feed(m, h, truth - [300.0, 400.0]) if f is not None]
    assert f.accepted and f.divergence_m == 500.0 and not m.flags["diverged"]
    m = GeomagMatcher(GRID, dataclasses.replace(ms, divergence_alarm_m=499.0))
    _feed(m, h, truth - [300.0, 400.0])
    assert m.flags["diverged"]


def test_match_time_is_reported_in_milliseconds():
    import time

    h = GRID.bilinear(*(LINE_START + LINE_FAST).T)
    ins = GRID.to_metres(LINE_START + LINE_FAST)
    m = _line_matcher()
    _feed(m, h[:11], ins[:11])
    t0 = time.perf_counter()
    m.update(11.0, h[11], ins[11])
    outer_ms = (time.perf_counter() - t0) * 1e3
    assert 1e-3 * outer_ms < m.internal_states["last_match_ms"] <= outer_ms


def test_corrected_position_predicts_the_drift_to_the_time_asked():
    m = _line_matcher()
    assert m.corrected_position((0.0, 0.0)) is None
    m.filter.update(0.0, [100.0, 0.0])
    m.filter.update(100.0, [200.0, 0.0])  # a drift of about 1 m/s east
    c_now = m.corrected_position((0.0, 0.0, 50.0))
    c_later = m.corrected_position((0.0, 0.0, 50.0), t_s=200.0)
    assert c_now.shape == (2,) and np.allclose(c_now, m.filter.correction_at(100.0))
    assert np.allclose(c_later, m.filter.correction_at(200.0)) and c_later[0] > c_now[0] + 20.0


def test_exhaustive_search_is_centred_on_the_first_ins_position():
    h = GRID.bilinear(*(LINE_START + LINE_FAST).T)
    ins = GRID.to_metres(LINE_START + LINE_FAST)
    x = match_exhaustive(GRID, h, ins, MatchSettings(n_samples=12, search_radius_m=100.0))
    assert np.allclose(x.start_ij, LINE_START) and x.hausdorff_nt == pytest.approx(0.0, abs=1e-9)


def test_filter_settings_small_values_and_the_gate_at_exactly_one():
    FilterSettings(fix_std_m=0.5, gate_sigma=0.5)
    # P = R = 16 per axis, no drift, no process noise: S = 32 I; ν = (4, 4): νᵀS⁻¹ν = 1 = gate² (gate 1)
    kf = InsErrorFilter(FilterSettings(fix_std_m=4.0, drift_rate_noise_m_s2=0.0, gate_sigma=1.0))
    kf.update(0.0, [0.0, 0.0, 9.0])  # a third component is ignored
    assert kf.update(0.0, [4.0, 4.0, 9.0]) and kf.test_ratio == 1.0  # at the gate: fused
    assert kf.x[0] == pytest.approx(2.0) and kf.x[1] == pytest.approx(2.0)


@pytest.mark.parametrize("window,rank", [(None, 1.0), (1, 0.75)])
def test_exhaustive_search_is_the_minimum_over_the_fine_lattice(window, rank):
    h, ins, start = _planted()
    h = h + np.linspace(-3.0, 3.0, 12)  # not exact: the minimum is a real comparison
    s = MatchSettings(n_samples=12, window_samples=window, rank_frac=rank, subdivisions=2, search_radius_m=250.0)
    x = match_exhaustive(GRID, h, ins, s, chunk=13)
    # reference: every lattice start i/2, j/2 of the box around (8.33, 6.67) ± 2.5 cells: nodes 6..10 and 5..9
    gi, gj = np.meshgrid(np.arange(12, 21) / 2, np.arange(10, 19) / 2, indexing="ij")
    starts = np.stack([gi.ravel(), gj.ravel()], axis=-1)
    strips = GRID.bilinear(starts[:, :1] + OFFS[None, :, 0], starts[:, 1:] + OFFS[None, :, 1])
    d = hausdorff(h, strips, window, rank)
    assert x.n_fine == len(starts) and x.term_evaluations == len(starts) * 12 * 2
    assert x.hausdorff_nt == pytest.approx(d.min()) and np.allclose(x.start_ij, starts[np.argmin(d)])
    assert x.search_area_m2 == pytest.approx(4 * 4 * 1e4)


@pytest.mark.parametrize("dx,dy", [(100.0, 50.0), (50.0, 100.0)])
def test_exhaustive_search_needs_a_whole_cell_on_each_axis(dx, dy):
    g = _smooth_map(dx=dx, dy=dy)
    start = np.array([8.0, 8.0])
    h = g.bilinear(*(start + OFFS).T)
    ins = g.to_metres(start + OFFS)
    x = match_exhaustive(g, h, ins, MatchSettings(n_samples=12, search_radius_m=60.0))  # < 1 cell on one axis
    assert x.found is False and x.reason == "the strip does not fit on the map inside the search area"
    assert match_exhaustive(g, h, ins, MatchSettings(n_samples=12, search_radius_m=100.0)).found


def test_heading_search_of_one_degree_and_around_the_given_centre():
    h, ins, start = _planted()
    b = math.radians(1.0)
    rot = np.array([[math.cos(b), math.sin(b)], [-math.sin(b), math.cos(b)]])
    ins_rot = ins[0] + (ins - ins[0]) @ rot.T
    s = dataclasses.replace(PLANT, heading_search_deg=1.0, heading_step_deg=1.0, search_radius_m=150.0)
    r = match_sequence(GRID, h, ins_rot, s)
    assert r.rotation_deg == -1.0 and r.hausdorff_nt == pytest.approx(0.0, abs=1e-9)
    # the INS 500 m off; the search centred on the given (corrected) position finds the start, the INS alone not
    off = ins_rot + [500.0, 0.0]
    r = match_sequence(GRID, h, off, s, centre_m=ins_rot[0])
    assert r.rotation_deg == -1.0 and np.allclose(r.start_ij, start)
    assert not np.allclose(match_sequence(GRID, h, off, s).start_ij, start)
