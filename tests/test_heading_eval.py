"""The heading evaluation, reduced (default suite) and full (``-m slow``)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from bench import eval_heading as E


def test_sim_drive_fuser_beats_single_compass_and_plain_ekf():
    r = E.evaluate_drive("urban_a", 1, duration_s=150.0)
    fuser, mag, ekf = r["fuser"], r["mag_only"], r["ekf"]
    assert r["zone_frac"] > 0.02, "the drive must cross interference zones"
    assert fuser["rms_deg"] <= E.GOAL_SIM_RMS_DEG
    assert fuser["rms_deg"] < 0.5 * mag["rms_deg"]
    assert fuser["rms_deg"] < ekf["rms_deg"]
    assert fuser["zone_rms_deg"] < mag["zone_rms_deg"]
    assert fuser["mode_frac"]["gyro_only"] > 0.0  # the DMC switched it to the gyro somewhere
    assert fuser["unaligned_frac"] < 0.02


def test_broad_slice_with_peers():
    from bench import heading_broad as hb

    trial = hb.load_trial(hb.BROAD_DIR / "32_disturbed_attached_magnet_1cm.hdf5").sliced(int(100 * 285.714))
    assert trial.movement.sum() > 10_000
    q, info = hb.run_magmesh(trial, hb.broad_settings_for(trial))
    mine = hb.heading_rms_deg(q, trial)
    fusion = hb.heading_rms_deg(hb.run_imufusion(trial), trial)
    ekf = hb.heading_rms_deg(hb.run_ahrs_ekf(trial), trial)
    assert np.isfinite([mine, fusion, ekf]).all()
    assert mine < min(fusion, ekf), (mine, fusion, ekf)
    assert info["mode_frac"]["gyro_only"] > 0.1  # the attached magnet was recognised


def test_heading_error_metric_matches_a_pure_yaw_offset():
    from bench import heading_broad as hb
    from magmesh import maths

    rng = np.random.default_rng(3)
    q_true = np.array([maths.quat_from_euler(*rng.uniform(-1, 1, 3)) for _ in range(20)])
    offset = maths.quat_from_euler(maths.yaw_to_heading(0.1), 0.0, 0.0)  # 0.1 rad about up
    q_est = hb.quat_mul_rows(np.repeat(offset[None], 20, axis=0), q_true)
    assert np.allclose(hb.heading_errors_rad(q_est, q_true), 0.1, atol=1e-9)


@pytest.mark.slow
def test_full_heading_evaluation_meets_the_goals():
    args = argparse.Namespace(quick=False, seeds=None, layouts=",".join(E.LAYOUTS), duration_s=300.0,
                              broad_dir=None, broad_max_s=None, no_sim=False, no_broad=False)
    r = E.run(args)
    assert r["sim_rms_deg"] <= E.GOAL_SIM_RMS_DEG, r["sim_summary"]["fuser"]
    assert set(r["broad"]) >= {"32_disturbed_attached_magnet_1cm", "36_disturbed_attached_magnet_5cm"}
    assert all(r["broad_goal"].values()), {k: r["broad"][k] for k in r["broad"]}
    assert E.format_text(r)
