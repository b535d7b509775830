"""The calibration evaluation (bench/eval_calibration.py): a reduced run in the default suite that
asserts the issue's goals, and the full run under ``-m slow``."""

from __future__ import annotations

import argparse
import json

import pytest

from bench import eval_calibration as ev

HEADLINE = ("arls_offset_err_pct", "arls_matrix_err_pct", "ls_offset_err_pct", "real_spread", "online_heading_rms_deg")


def _run(*argv: str) -> dict:
    p = argparse.ArgumentParser()
    ev.add_arguments(p)
    return ev.run(p.parse_args(list(argv)))


def _check_goals(r: dict) -> None:
    for k in HEADLINE:
        assert k in r
    json.dumps(r, allow_nan=False)  # plain Python only, strict JSON
    assert r["arls_offset_err_pct"] <= ev.GOAL_PCT and r["arls_matrix_err_pct"] <= ev.GOAL_PCT
    assert r["ls_offset_err_pct"] > ev.GOAL_PCT  # where LS fails
    for name, v in r["real_spread"].items():
        assert v["arls"] < v["ls"], name
    assert r["online_heading_rms_deg"] <= ev.GOAL_HEADING_DEG
    assert not r["online"]["vertical_observable_any"]  # a car never makes b_z observable
    assert ev.format_text(r)


def test_reduced_evaluation_meets_the_goals():
    r = _run("--seeds", "3", "--samples", "2000", "--car-seeds", "1", "--car-duration", "200", "--no-service",
             "--timing-repeats", "2")
    _check_goals(r)


@pytest.mark.slow
def test_full_evaluation_meets_the_goals(request):
    if "slow" not in (request.config.getoption("-m") or ""):
        pytest.skip("full evaluation: run with -m slow")
    r = _run()
    _check_goals(r)
    for mode in ("online", "static"):
        for sid, v in r["service_logic"][mode]["sensors"].items():
            assert v["first_ok_s"] is not None and v["first_ok_s"] <= v["calib_turn_end_s"] + 10, (mode, sid)
            assert v["heading_rms_deg"] <= ev.GOAL_HEADING_DEG, (mode, sid)
    step = r["service_logic_hard_iron_step"]
    for sid, v in step["online"]["sensors"].items():  # the online EKF follows a hard-iron step, static fits do not
        assert v["heading_rms_deg_from_step_plus_60s"] < step["static"]["sensors"][sid]["heading_rms_deg_from_step_plus_60s"]
        assert "ekf" in v["methods"]
