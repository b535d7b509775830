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
    from services.heading_fuser import profiles

    q, info = hb.run_magmesh(trial, profiles.settings(profiles.IMU_ONLY))
    mine = hb.heading_rms_deg(q, trial)
    peers = {name: hb.heading_rms_deg(fn(trial), trial) for name, fn in hb.PEERS.items()}
    assert np.isfinite([mine, *peers.values()]).all()
    assert mine < min(peers.values()), (mine, peers)
    assert info["mode_frac"]["gyro_only"] > 0.1  # the attached magnet was recognised


@pytest.fixture(scope="module")
def trial02_slice():
    from bench import heading_broad as hb

    # 40 s of rest, then 50 s of slow rotations: enough to tell a right convention from a wrong one
    return hb.load_trial(hb.BROAD_DIR / "02_undisturbed_slow_rotation_B.hdf5").sliced(int(90 * 285.714))


@pytest.mark.parametrize("peer", ["vqf", "imufusion", "ahrs_ekf"])
def test_each_peer_is_sane_on_undisturbed_trial_02(trial02_slice, peer):
    """A peer in the wrong frame or units is tens of degrees off here (imufusion's ENU option: 90°)."""
    from bench import heading_broad as hb

    assert trial02_slice.movement.sum() > 10_000
    q = hb.PEERS[peer](trial02_slice)
    assert q.shape == (len(trial02_slice.gyro_rad_s), 4)
    rms = hb.heading_rms_deg(q, trial02_slice)
    assert rms < 3.0, (peer, rms)


@pytest.mark.parametrize("peer", ["vqf", "imufusion", "ahrs_ekf"])
def test_each_peer_reads_a_static_board_lying_in_enu_as_yaw_zero(peer):
    """Body axes = ENU (x east, y north, z up), still: every peer must converge to yaw ≈ 0 (the field's
    own declination in BROAD's lab, 0.36°)."""
    from bench import heading_broad as hb

    n, rate = 3000, 100.0
    field_nt = np.array([100.0, 15800.0, -40800.0])
    trial = hb.Trial("static", rate, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile(field_nt, (n, 1)),
                     np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.ones(n, bool))
    q = hb.PEERS[peer](trial)
    err = np.degrees(hb.heading_errors_rad(q[-100:], trial.quat_true[-100:]))
    assert np.all(err < 1.0), (peer, err.max())


def test_eval_reports_every_trial_or_why_it_skipped_it(tmp_path):
    from bench import heading_broad as hb

    src = hb.load_trial(hb.BROAD_DIR / "02_undisturbed_slow_rotation_B.hdf5").sliced(int(50 * 285.714))
    import scipy.io

    n = len(src.gyro_rad_s)
    scipy.io.savemat(tmp_path / "02_as_mat.mat", {
        "imu_gyr": src.gyro_rad_s, "imu_acc": src.accel_m_s2, "imu_mag": src.mag_nt / hb.UT_TO_NT,
        "opt_quat": src.quat_true, "movement": src.movement.reshape(n, 1), "sampling_rate": src.rate_hz})
    scipy.io.savemat(tmp_path / "notatrial.mat", {"x": np.zeros(3)})
    (tmp_path / "broken.hdf5").write_bytes(b"not hdf5")
    skipped: dict = {}
    r = E.evaluate_broad(tmp_path, None, peers=True, skipped=skipped)
    assert set(r) == {"02_as_mat"}
    assert set(r["02_as_mat"]) >= {"profile", "magmesh", "vqf", "imufusion", "ahrs_ekf"}
    assert set(skipped) == {"notatrial", "broken"}
    assert "missing" in skipped["notatrial"] and "imu_gyr" in skipped["notatrial"]
    assert "not readable" in skipped["broken"]


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
