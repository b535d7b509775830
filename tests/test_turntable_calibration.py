"""The turntable simulator's calibration search (bench/turntable_calibration.py) and the rows' place against the
paper (bench/eval_dmc.py): the loss, the plausibility bounds, the command's mistakes."""

import json
import subprocess
import sys

import pytest

from bench import eval_dmc
from bench import turntable_calibration as C


def _row(rp, mp, wp95, paper):
    return ("dmc", 1, rp, mp, wp95, paper)


def test_loss_is_zero_inside_the_papers_ranges_and_grows_outside():
    p = eval_dmc.PAPER_TABLE1[0]  # RP 81.3-82.9, MP 18.6-20.5, WP 12.9-15.5
    inside = [_row(82.0, 19.0, 14.0, p)]
    assert C.loss(inside, 1.0) == 0.0
    # 5 points of RP below the range is one unit; 2 points of MP above it is one; 0.1 deg of undisturbed error too
    assert C.loss([_row(76.3, 19.0, 14.0, p)], 1.0) == pytest.approx(1.0)
    assert C.loss([_row(82.0, 22.5, 14.0, p)], 1.0) == pytest.approx(1.0)
    assert C.loss(inside, 1.3) == pytest.approx(1.0)
    assert C.loss([_row(float("nan"), 19.0, 14.0, p)], 1.0) == 100.0  # nothing accepted: heavily penalised


def test_bounds_keep_the_sources_plausible():
    wild = {"closest_m": (0.01, 0.005), "magnet_moment_am2": (80.0, 40.0), "cabinet_moment_am2": (900.0, 5.0),
            "quiet_turn_probability": 0.0, "dwell_exponent": 0.01, "height_span_m": 3.0, "approach_start_m": 0.2,
            "turn_s": 5.0, "cal_offset_err_nt": 100.0, "cal_matrix_err": 0.01, "unit": 30.0}
    o = C._bounded(wild)
    assert o["closest_m"][0] >= C.LIMITS["closest_m"] and o["closest_m"][1] > o["closest_m"][0]
    assert max(o["magnet_moment_am2"]) <= C.LIMITS["magnet_am2"]
    assert max(o["cabinet_moment_am2"]) <= C.LIMITS["cabinet_am2"]
    assert o["cabinet_moment_am2"][0] <= o["cabinet_moment_am2"][1]
    assert o["quiet_turn_probability"] >= C.LIMITS["quiet"] and o["turn_s"] >= C.LIMITS["turn_s"][0]
    assert o["approach_start_m"] >= C.LIMITS["approach_m"][0]


def test_the_search_is_seeded_and_the_defaults_fit_the_calibration_runs():
    a = C.search(2, 2, seed=4)
    b = C.search(2, 2, seed=4)
    assert a == b
    # the simulator's defaults are a fit of this search: on the calibration runs their loss is small
    from sim_publishers.car.turntable import TurntableSettings

    d = TurntableSettings()
    settings = {k: getattr(d, k) for k in C.FREE if k != "unit"}
    assert d.mag_resolution_nt == eval_dmc.FIELD_UNIT_NT
    assert C.evaluate({**settings, "unit": eval_dmc.FIELD_UNIT_NT}) < 5.0


def test_a_bad_start_gets_one_clear_line_and_exit_2():
    r = subprocess.run([sys.executable, "-m", "bench.turntable_calibration", "--start", json.dumps({"turn_s": 60})],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "--start must be" in r.stderr


def test_baseline_rows_say_how_far_outside_the_paper_they_lie():
    row = {"rp_pct": 80.3, "mp_pct": 19.0, "wp_deg": 7.0, "wp_p95_deg": 16.0, "paper": eval_dmc.PAPER_TABLE1[0]}
    eval_dmc._against_paper(row)
    assert row["inside_paper_range"] == {"rp_pct": False, "mp_pct": True, "wp_deg": False, "wp_p95_deg": False}
    assert row["outside_paper_by"] == {"rp_pct": 1.0, "mp_pct": 0.0, "wp_deg": 5.9, "wp_p95_deg": 0.5}
