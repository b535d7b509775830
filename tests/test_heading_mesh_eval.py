"""The live heading eval's scoring (``bench/eval_heading_mesh.score``) on hand-made message streams."""

from __future__ import annotations

import math

import pytest

from bench.eval_heading_mesh import score


def _streams(err_deg=0.0, gyro_at=(), sources_at=(), alarms=()):
    t = [round(0.1 * i, 1) for i in range(1001)]  # 100 s at 10 Hz
    pose = [{"t_s": x, "heading_rad": (0.01 * x) % (2 * math.pi)} for x in t]
    mode = ["gyro_only" if any(a <= x < b for a, b in gyro_at) else "magnetic" for x in t]
    heading = [{"t_s": x, "heading_rad": (0.01 * x + math.radians(err_deg)) % (2 * math.pi), "mode": m}
               for x, m in zip(t, mode, strict=True)]
    sources = [{"t_s": x, "active_sources": ["bridge"] if any(a <= x < b for a, b in sources_at) else []} for x in t]
    return heading, pose, sources, [{"t_s": ts, "state": st} for ts, st in alarms]


def test_rms_against_truth_across_the_wrap():
    r = score(*_streams(err_deg=2.0))
    assert r["rms_deg"] == pytest.approx(2.0, abs=1e-6) and r["meets"]["rms"]
    r = score(*_streams(err_deg=-3.0))
    assert r["rms_deg"] == pytest.approx(3.0, abs=1e-6) and not r["meets"]["rms"]


def test_magnetic_share_counts_only_the_time_no_source_is_active():
    # gyro-only exactly while the bridge is near: all clear time is magnetic
    r = score(*_streams(gyro_at=[(20, 40)], sources_at=[(20, 40)], alarms=[(20.0, "raised"), (40.0, "cleared")]))
    assert r["clear_frac"] == pytest.approx(0.8, abs=0.01)
    assert r["magnetic_frac_clear"] == 1.0 and r["meets"]["magnetic_clear"]
    # gyro-only for 15 s after the bridge: 15 of 80 clear seconds lost
    r = score(*_streams(gyro_at=[(20, 55)], sources_at=[(20, 40)], alarms=[(20.0, "raised")]))
    assert r["magnetic_frac_clear"] == pytest.approx(65 / 80, abs=0.01) and not r["meets"]["magnetic_clear"]


def test_gyro_within_one_second_of_each_alarm():
    r = score(*_streams(gyro_at=[(20.5, 40)], alarms=[(20.0, "raised"), (40.0, "cleared"), (60.0, "raised")]))
    assert r["dmc_alarms_raised"] == 2 and r["gyro_within_1s"] == 1
    assert r["gyro_late_at_t_s"] == [60.0] and not r["meets"]["gyro_within_1s"]
    r = score(*_streams(gyro_at=[(21.5, 40)], alarms=[(20.0, "raised")]))
    assert r["gyro_within_1s"] == 0, "1.5 s after the alarm is late"
    assert not score(*_streams())["meets"]["gyro_within_1s"], "no alarm at all proves nothing"


def test_nothing_received_is_an_error_not_a_score():
    with pytest.raises(ValueError, match="nothing to score"):
        score([], [], [], [])


@pytest.mark.slow
def test_eval_heading_mesh_command_scores_the_live_heading(tmp_path):
    """``magmesh eval heading --mesh`` on a short drive: real processes, the figures printed as JSON."""
    import json
    import subprocess
    import sys

    from magmesh.paths import REPO

    r = subprocess.run([sys.executable, "-m", "magmesh", "eval", "heading", "--mesh", "--mesh-duration-s", "120",
                        "--json"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads(r.stdout)["mesh"]
    assert m["t_end_s"] >= 119.0 and m["n_heading"] >= 0.9 * 120 * 10, m
    assert m["dmc_alarms_raised"] >= 1 and m["gyro_within_1s"] == m["dmc_alarms_raised"], m
    assert m["rms_deg"] < 3.0, m
