"""``magmesh eval dmc``: the reduced evaluation in the default suite, the full one under ``-m slow``."""

from __future__ import annotations

import argparse
import json

import pytest

from bench import eval_dmc


def _args(**kw) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    eval_dmc.add_arguments(p)
    a = p.parse_args([])
    for k, v in kw.items():
        setattr(a, k, v)
    return a


def _check(r: dict) -> None:
    json.dumps(r)  # plain Python types only
    u = r["fcm_unseen"]
    assert u["rp_pct"] >= eval_dmc.GOAL["rp_pct"], u
    assert u["mp_pct"] <= eval_dmc.GOAL["mp_pct"], u
    assert u["wp_deg"] <= eval_dmc.GOAL["wp_deg"], u
    assert u["meets_goal"] and u["missed_zones"] == 0
    assert not set(u["drives"]) & set(u["trained_on"]), "fcm_unseen must exclude the training drives"
    assert any(not d.startswith("urban_a") for d in u["drives"]), "unseen layouts must be included"
    names = [row["name"] for row in r["table1_threshold_sweep"]]
    assert names[:4] == ["paper_set1", "paper_set2", "paper_set3", "paper_set4"]
    # tightening the thresholds lowers the recognition rate (the paper's Table 1 trend)
    rps = [row["rp_pct"] for row in r["table1_threshold_sweep"][:4]]
    assert rps == sorted(rps, reverse=True)
    assert {row["name"] for row in r["table2_single"]} == set(names)
    assert "[" not in eval_dmc.format_text(r).split("\n")[0]


def test_eval_dmc_quick_meets_goal():
    r = eval_dmc.run(_args(quick=True, no_speed=True, no_quasistatic=True))
    _check(r)
    assert len(r["drives"]["unseen"]) == len(eval_dmc.UNSEEN_QUICK)


@pytest.mark.slow
def test_eval_dmc_full(request):
    if "slow" not in (request.config.getoption("-m") or ""):
        pytest.skip("full evaluation: run with -m slow")
    r = eval_dmc.run(_args())
    _check(r)
    s = r["fcm_speed"]
    assert s["max_centre_diff_vs_loop"] < 1e-9
    if s.get("skfuzzy_ms") is not None:
        assert s["max_centre_diff_vs_skfuzzy"] < 1e-9
    q = {row["name"]: row for row in r["quasistatic"]}
    assert q["default"]["mp_pct"] <= q["paper_form"]["mp_pct"]
