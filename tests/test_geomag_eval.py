"""The geomagnetic evaluation: the paper's Table 1 (reduced in the default suite, full with -m slow)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from scipy.stats import binom

from bench import eval_geomag as ev
from magmesh.geomap import synthetic_paper_map
from services.geomag_matcher.core import MatchSettings


def _settings(grid):
    return MatchSettings(lambda_nt=ev.PAPER_LAMBDA * grid.std_nt, search_radius_m=30 * grid.dx_m)


def test_table1_reduced_close_to_the_paper():
    grid = synthetic_paper_map(7)
    runs = 10
    t = ev.table1(grid, runs, seed=5, settings=_settings(grid), check_exhaustive=1)
    # A count is too low when the paper's rate would give it or less in under 1 % of samples of `runs`
    # (one-sided binomial). Cells where even 0 of 10 is that likely (a 6 % or 15 % rate) cannot fail alone:
    # they are checked pooled, the summed count against the sum of the paper's binomials.
    alpha = 0.01
    checked = 0
    pooled_obs = 0
    pooled = np.array([1.0])  # distribution of the pooled count under the paper's rates
    for (n, snr), paper in ev.PAPER_TABLE1.items():
        c = t["cells"][f"N={n},SNR={snr}"]
        for kind, rate in zip(("exact", "sub"), paper, strict=True):
            p = rate / 100.0
            if binom.cdf(0, runs, p) < alpha:
                assert binom.cdf(c[kind], runs, p) >= alpha, (n, snr, kind, c, rate)
                checked += 1
            else:
                pooled_obs += c[kind]
                pooled = np.convolve(pooled, binom.pmf(np.arange(runs + 1), runs, p))
    assert checked >= 20  # of the 24 counts, all but the low-rate ones are checked one by one
    assert pooled.size > 1 and pooled[: pooled_obs + 1].sum() >= alpha, (pooled_obs, pooled)
    assert t["exhaustive_agree"] >= t["exhaustive_checked"] - 1


def test_speed_protocol_same_answer_and_pruning():
    grid = synthetic_paper_map(7)
    sp = ev.speed(grid, seed=1, settings=_settings(grid), scipy_candidates=200, set_metric=False, repeats=1)
    o = sp["ordered"]
    assert o["same_answer"]
    assert o["ssda_abandoned"] > 0.95 * o["prematch_cells"]
    assert o["fine_candidates_pipeline"] < 0.02 * o["fine_candidates_exhaustive"]
    assert sp["scipy_naive"]["max_abs_diff_vs_ours_nt"] < 1e-9  # same Hausdorff distance as scipy
    assert o["error_m"] < 200.0


def test_real_data_protocols_run_and_beat_chance():
    w = ev.wdmam_table(runs=4, seed=3, settings=_settings(synthetic_paper_map(7)))
    assert w["cells"]["N=20,SNR=20"]["sub"] >= 3
    walk = ev.walk_matching("square")
    assert walk["windows"] > 20
    assert walk["median_error_m"] < 0.5 * walk["random_guess_median_error_m"]


@pytest.mark.slow
def test_full_evaluation_meets_the_goals(request):
    if "slow" not in (request.config.getoption("-m") or ""):
        pytest.skip("full evaluation: run with -m slow")
    p = argparse.ArgumentParser()
    ev.add_arguments(p)
    r = ev.run(p.parse_args([]))
    assert set(r["table1"]) == {f"N={n},SNR={s}" for n in ev.NS for s in ev.SNRS}
    assert r["goal_table1_met"], ev.format_text(r)
    assert r["speed"]["ordered"]["same_answer"]
