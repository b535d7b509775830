"""Replay publishers of the bundled real recordings: messages valid, frames and truth consistent."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from magmesh import maths
from schemas import keys, messages
from sim_publishers.replay import core
from sim_publishers.replay.publisher import ReplaySettings, replay_events

DATASETS = [f"broad:{t}" for t in core.broad_trials()] + ["car_circles", "kok:eight", "kok:square"]


def _validate_all(events, vehicle, every: int = 1):
    """Time order and counts of every event; the full encode/decode round trip of every ``every``-th."""
    seq: dict[str, int] = {}
    last_t = -math.inf
    for i, (t, key, mtype, fields) in enumerate(events):
        assert t >= last_t
        last_t = t
        if i % every == 0 or seq.get(key, 0) == 0:
            assert messages.type_for_key(key) == mtype
            assert keys.parse(key).vehicle == vehicle
            msg = messages.make(mtype, vehicle, t, seq.get(key, 0), **fields)
            messages.decode(messages.encode(msg), where=key, expected_type=mtype)
        seq[key] = seq.get(key, 0) + 1
    return seq


@pytest.mark.parametrize("dataset", DATASETS)
def test_every_message_is_valid_and_time_ordered(dataset):
    rec = core.load(dataset)
    seq = _validate_all(core.stream(rec, "real-1"), "real-1", every=5 if dataset.startswith("broad") else 1)
    assert seq[keys.raw_mag("real-1", "1")] == len(rec.mag_t_s)
    assert seq[keys.truth("real-1", "pose")] > 10
    if dataset.startswith("broad"):
        assert {keys.raw_imu("real-1"), keys.truth("real-1", "sources")} <= set(seq)
    if dataset == "car_circles":
        assert seq[keys.raw_gnss("real-1")] == 98
    if dataset.startswith("kok"):
        assert keys.raw_ins("real-1") in seq


def test_broad_field_rotated_by_truth_matches_lab_field_when_undisturbed():
    rec = core.load("broad:02_undisturbed_slow_rotation_B")
    # nearest magnetometer sample for each truth sample
    i = np.searchsorted(rec.mag_t_s, rec.truth_t_s).clip(0, len(rec.mag_t_s) - 1)
    b_enu = np.einsum("nij,nj->ni", core.quat_to_matrices(rec.truth_quat), rec.mag_nt[i])
    err = np.linalg.norm(b_enu - rec.field_earth_enu_nt, axis=1)
    assert np.median(err) < 0.05 * np.linalg.norm(rec.field_earth_enu_nt)
    assert rec.disturbed.mean() < 0.02
    h, _, _ = core.euler_from_matrices(core.quat_to_matrices(rec.truth_quat))
    assert np.all((h >= 0) & (h < 2 * math.pi))


def test_broad_attached_magnet_is_flagged_as_a_block():
    rec = core.load("broad:32_disturbed_attached_magnet_1cm")
    d = rec.disturbed
    assert 0.2 < d.mean() < 0.6
    # the longest disturbed run lasts tens of seconds (the magnet attached for about a minute)
    runs = [len(list(g)) for v, g in itertools.groupby(d) if v]
    assert max(runs) / 10.0 > 15.0


def test_car_frames_are_flu_and_gnss_course_is_consistent():
    rec = core.load("car_circles")
    assert np.median(rec.accel_m_s2[:, 2]) == pytest.approx(9.8, abs=0.6)  # z up: +g at rest
    assert 25_000 < np.median(np.linalg.norm(rec.mag_nt, axis=1)) < 60_000
    g = rec.gnss
    # three laps of a roundabout: the course turns through about 3 × 360°
    moving = g["speed_m_s"] > 1.0
    turn = np.sum(np.abs(maths.angle_diff(g["course_rad"][moving][1:], g["course_rad"][moving][:-1])))
    assert math.degrees(turn) > 700
    # the gyro's yaw rate integrates to the same total turn (z up)
    dt = np.diff(rec.imu_t_s, prepend=rec.imu_t_s[0])
    gyro_turn = abs(np.sum(rec.gyro_rad_s[:, 2] * dt))
    assert math.degrees(gyro_turn) > 700


def test_kok_walk_moves_forward_along_body_x():
    rec = core.load("kok:eight")
    R = core.quat_to_matrices(rec.truth_quat)
    v = rec.ins["vel_enu_m_s"]
    fwd = np.einsum("nji,nj->ni", R, v)  # walk-frame velocity in body FLU
    assert np.median(fwd[:, 0]) > 0.3 and abs(np.median(fwd[:, 1])) < 0.2


def test_publisher_window_and_loop_keep_time_increasing():
    s = ReplaySettings(dataset="kok:eight", start_s=10.0, duration_s=5.0, loop=True)
    ev = list(itertools.islice(replay_events(s, "w-1"), 400))
    t = np.array([e[0] for e in ev])
    assert np.all(np.diff(t) >= 0) and t[0] >= 10.0
    assert t[-1] > 10.0 + 5.0  # second lap continues the clock
    one = list(replay_events(ReplaySettings(dataset="kok:eight", start_s=10.0, duration_s=5.0), "w-1"))
    assert all(10.0 <= e[0] < 15.0 for e in one) and len(one) == 3 * 50
    with pytest.raises(ValueError):
        list(replay_events(ReplaySettings(dataset="nope"), "w-1"))
