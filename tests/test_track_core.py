"""Track monitor core and multirotor simulator: geometry, detectors, hysteresis, reduced evaluation."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from bench import eval_track
from services.track_monitor.core import (
    Route,
    TrackMonitor,
    TrackMonitorSettings,
    cross_track,
    learn_sigmas,
    mag_heading,
)
from sim_publishers.multirotor.core import GAUSS_NT, MultirotorSettings, disturbance_g, simulate

RTK = ("rtk_fixed", 18, 1.3, 0.015)


def test_cross_track_matches_the_cross_product_formula():
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b, x = rng.uniform(-500, 500, (3, 3))
        d_signed, along = cross_track(Route(tuple(a), tuple(b), "r"), x)
        ab, ax = (b - a)[:2], (x - a)[:2]
        ref = abs(np.cross(np.append(ax, 0), np.append(ab, 0))[2]) / np.linalg.norm(ab)  # eq. 6, horizontal
        assert abs(abs(d_signed) - ref) < 1e-9
        assert abs(along - ax @ ab / np.linalg.norm(ab)) < 1e-9
    # sign: + left of the direction of travel (route due north: west is left)
    assert cross_track(Route((0, 0, 0), (0, 100, 0), "r"), (-2.0, 50.0, 0))[0] == pytest.approx(2.0)


def _fly_line(mon, offsets, t0=0.0, dt=0.1, fix=RTK):
    events = []
    for i, off in enumerate(offsets):
        t = t0 + i * dt
        events += mon.update_gnss(t, (off, 5.0 * t, 20.0), (0.0, 5.0, 0.0), *fix)
    return events


def test_track_alarm_raises_on_trusted_gnss_and_clears_with_hysteresis():
    mon = TrackMonitor(TrackMonitorSettings())
    mon.set_route((0, 0, 20), (0, 2000, 20), "leg")
    offsets = [0.0] * 100 + list(np.linspace(0, 1.6, 40)) + [1.6] * 20 + [0.3] * 40
    ev = _fly_line(mon, offsets)
    raised = [e for e in ev if e.source == "track" and e.state == "raised"]
    assert len(raised) == 1
    t_cross = 0.1 * (100 + int(np.argmax(np.linspace(0, 1.6, 40) > 1.0)))
    assert t_cross <= raised[0].t_s <= t_cross + 0.3  # persistence of 0.15 s at 10 Hz
    assert raised[0].value > 1.0 and raised[0].threshold == 1.0 and raised[0].unit == "m"
    anomaly = [e for e in ev if e.source == "mag_anomaly" and e.state == "raised"]
    assert len(anomaly) == 1 and "track deviation" in anomaly[0].reason
    cleared = [e for e in ev if e.source == "track" and e.state == "cleared"]
    assert len(cleared) == 1 and cleared[0].t_s - 0.1 * 160 >= 2.0 - 1e-9  # held 2 s below 0.5 m
    # the combined verdict is held longer than the detector
    assert not any(e.source == "mag_anomaly" and e.state == "cleared" for e in ev)
    assert mon.flags["anomaly_alarm"]


@pytest.mark.parametrize("fix", [("rtk_float", 18, 1.3, 0.1), ("dgps", 9, 1.8, 0.5), ("rtk_fixed", 4, 1.3, 0.02),
                                 ("rtk_fixed", 18, 6.0, 0.02)])
def test_track_alarm_needs_gnss_good_enough_to_trust(fix):
    mon = TrackMonitor(TrackMonitorSettings())
    mon.set_route((0, 0, 20), (0, 2000, 20), "leg")
    _fly_line(mon, [0.0] * 100)  # armed on RTK
    assert mon.flags["track_armed"]
    ev = _fly_line(mon, [2.0] * 50, t0=10.0, fix=fix)
    assert not any(e.source == "track" for e in ev)
    assert not mon.flags["gnss_ok"]


def test_track_detector_arms_only_after_acquiring_the_leg():
    mon = TrackMonitor(TrackMonitorSettings())
    mon.set_route((0, 0, 20), (0, 2000, 20), "leg")
    ev = _fly_line(mon, [3.0] * 50 + [0.0] * 30 + [3.0] * 10)  # off the line, then on it < 5 s, then off
    assert not ev and not mon.flags["track_armed"]
    mon.set_route((0, 0, 20), (0, 2000, 20), "leg")  # same route: no re-arm needed, no change
    assert not mon.flags["track_armed"]


def _feed_innovation(mon, e_deg, t0=0.0, dt=0.02):
    events = []
    for i, e in enumerate(e_deg):
        events += mon.update_attitude(t0 + i * dt, 1.0, 1.0 + math.radians(e))
    return events


@pytest.mark.parametrize("test", ["paper", "robust"])
def test_innovation_detector_learns_sigma_and_raises_on_a_step(test):
    rng = np.random.default_rng(5)
    s = TrackMonitorSettings(innovation_test=test, warmup_s=2.0, learn_s=20.0, fc_mag_gain_per_s=0.0)
    mon = TrackMonitor(s)
    quiet = rng.normal(0, 0.3, 1500)  # 30 s at 50 Hz
    assert not _feed_innovation(mon, quiet)
    assert not mon.flags["learning"]
    assert math.degrees(mon.innovation.sigma_rad) == pytest.approx(0.3, rel=0.15)
    step = rng.normal(0, 0.3, 200) + 4.0
    ev = _feed_innovation(mon, step, t0=30.0)
    raised = [e for e in ev if e.source == "heading_innovation" and e.state == "raised"]
    assert len(raised) == 1 and raised[0].t_s - 30.0 < 0.6
    assert any(e.source == "mag_anomaly" and "heading innovation" in e.reason for e in ev)


def test_robust_innovation_test_ignores_a_short_burst_that_the_paper_test_reports():
    rng = np.random.default_rng(6)
    res = {}
    for test in ("paper", "robust"):
        mon = TrackMonitor(TrackMonitorSettings(innovation_test=test, warmup_s=2.0, learn_s=20.0,
                                                fc_mag_gain_per_s=0.0))
        e = rng.normal(0, 0.3, 3000)
        e[2000:2010] += 10.0  # a 0.2 s burst of 10°
        ev = _feed_innovation(mon, e)
        res[test] = [x for x in ev if x.source == "heading_innovation" and x.state == "raised"]
    assert res["paper"] and not res["robust"]


def test_combined_verdict_is_held_while_the_field_strength_is_off():
    rng = np.random.default_rng(8)
    s = TrackMonitorSettings(warmup_s=2.0, learn_s=20.0, fc_mag_gain_per_s=0.0, anomaly_clear_hold_s=5.0)
    mon = TrackMonitor(s)
    dt = 0.02
    ev = []

    def run(t0, n, e_deg, field_nt):
        out = []
        for i in range(n):
            t = t0 + i * dt
            b = np.array([field_nt * 0.6, 0.0, -field_nt * 0.8]) + rng.normal(0, 20, 3)
            out += mon.update_mag(t, b)
            out += mon.update_attitude(t, 1.0, 1.0 + math.radians(e_deg + rng.normal(0, 0.3)))
        return out

    ev += run(0.0, 1500, 0.0, 60000.0)  # 30 s undisturbed: σ and |B| reference learned
    assert not mon.flags["learning"] and not mon.flags["field_learning"]
    ev += run(30.0, 100, 4.0, 61500.0)  # 2 s: heading jumps, field off by 1500 nT
    assert mon.flags["anomaly_alarm"]
    ev += run(32.0, 1000, 0.0, 61500.0)  # 20 s: the filter followed (innovation quiet), field still off
    assert not mon.flags["innovation_alarm"] and mon.flags["field_deviating"]
    assert mon.flags["anomaly_alarm"]
    ev += run(52.0, 500, 0.0, 60000.0)  # 10 s: field back
    cleared = [e for e in ev if e.source == "mag_anomaly" and e.state == "cleared"]
    assert len(cleared) == 1 and 52.0 + 5.0 <= cleared[0].t_s <= 52.0 + 7.0
    assert "field strength back" in cleared[0].reason


def test_mag_heading_levels_the_field_like_the_flight_controller():
    s = MultirotorSettings(seed=9, duration_s=20.0)
    f = simulate(s)
    decl = math.radians(s.declination_deg)
    for k in range(0, len(f.t_s), 97):
        got = mag_heading(f.mag_nt[k], f.att_roll_rad[k], f.att_pitch_rad[k], decl)
        assert abs(math.remainder(got - f.mag_heading_rad[k], 2 * math.pi)) < 1e-9
    # a level, undisturbed field gives the true heading
    from magmesh.maths import body_to_enu
    from sim_publishers.multirotor.core import earth_field_enu
    for psi in (0.3, 2.0, 4.5):
        b = body_to_enu(psi, 0.0, 0.0).T @ earth_field_enu(s)
        assert abs(math.remainder(mag_heading(b, 0.0, 0.0, decl) - psi, 2 * math.pi)) < 1e-9


def test_learn_sigmas_needs_samples_and_pools_them():
    s = TrackMonitorSettings()
    with pytest.raises(ValueError):
        learn_sigmas([(0.0, 0.0, 0.0)] * 5, s)
    rng = np.random.default_rng(1)
    x = rng.normal(0, 0.01, 2000)
    sig = learn_sigmas([(i * 0.02, v, 0.0) for i, v in enumerate(x)], s)
    assert sig["innovation_sigma_rad"] == pytest.approx(0.01, rel=0.1)
    assert sig["block_sigma_rad"] == pytest.approx(0.01 / math.sqrt(25), rel=0.3)


def test_settings_are_checked():
    with pytest.raises(ValueError):
        TrackMonitorSettings(innovation_test="magic")
    with pytest.raises(ValueError):
        TrackMonitorSettings(track_clear_m=2.0)
    with pytest.raises(ValueError):
        MultirotorSettings(disturbance="storm")


# ---- simulator ----------------------------------------------------------------------------------


def test_disturbance_profiles_follow_the_paper_rates():
    t = np.array([0.0, 60.0, 61.0, 70.0])
    fast = disturbance_g(MultirotorSettings(disturbance="fast_ramp", onset_s=60.0), t)
    slow = disturbance_g(MultirotorSettings(disturbance="slow_ramp", onset_s=60.0), t)
    assert fast.tolist() == pytest.approx([0, 0, 0.06, 0.5])  # capped at disturbance_max_g
    assert slow.tolist() == pytest.approx([0, 0, 0.0125, 0.125])
    step = disturbance_g(MultirotorSettings(disturbance="step", onset_s=60.0, step_g=0.2,
                                            disturbance_hold_s=5.0), np.array([59.0, 60.0, 64.0, 66.0]))
    assert step.tolist() == pytest.approx([0, 0.2, 0.2, 0])


def test_simulator_is_seeded_and_flies_the_line_when_undisturbed():
    s = MultirotorSettings(seed=4, duration_s=60.0)
    f1, f2 = simulate(s), simulate(s)
    assert np.array_equal(f1.mag_nt, f2.mag_nt) and np.array_equal(f1.pos_enu_m, f2.pos_enu_m)
    assert not np.array_equal(simulate(s.replace(seed=5)).mag_nt, f1.mag_nt)
    after = f1.t_s > 10
    assert np.abs(f1.true_cross_track_m()[after]).max() < 1.0
    speed = np.linalg.norm(f1.vel_enu_m_s[after, :2], axis=1)
    assert abs(np.median(speed) - s.cruise_speed_m_s) < 0.5
    # Earth field ≈ 0.6 G at the magnetometer
    assert np.median(np.linalg.norm(f1.b_earth_body_nt, axis=1)) == pytest.approx(0.6 * GAUSS_NT, rel=1e-6)
    # the flight controller's heading stays within a degree or two of the truth
    err = np.degrees(np.angle(np.exp(1j * (f1.att_heading_rad - f1.heading_rad))))
    assert np.abs(err[after]).max() < 3.0


def test_a_heading_error_rotates_the_produced_acceleration_and_the_track_drifts():
    """Eq. 5: with the magnetometer disturbed, the estimated heading drifts from the true one, the
    airframe turns, and the vehicle leaves the line in the direction the rotation predicts."""
    s = MultirotorSettings(seed=2, duration_s=110.0, disturbance="slow_ramp", onset_s=60.0)
    f = simulate(s)
    err = np.degrees(np.angle(np.exp(1j * (f.att_heading_rad - f.heading_rad))))
    k0 = int(60.0 / s.dt_s)
    assert abs(err[k0 - 50: k0].mean()) < 1.5
    assert abs(err[int(80.0 / s.dt_s)]) > 20.0  # the filter followed the disturbed magnetometer
    assert np.abs(f.true_cross_track_m()[int(100.0 / s.dt_s):]).max() > 1.0


# ---- reduced evaluation (the full one is in test_track_eval_full, marked slow) --------------------


def test_reduced_evaluation_meets_the_goals():
    p = argparse.ArgumentParser()
    eval_track.add_arguments(p)
    args = p.parse_args(["--undisturbed", "8", "--undisturbed-duration", "120", "--train", "3",
                         "--after-onset", "15", "--seed", "3"])
    r = eval_track.run(args)
    assert r["combined_delay_s"]["fast"] is not None and r["combined_delay_s"]["fast"] <= 3.0
    assert r["combined_delay_s"]["slow"] is not None and r["combined_delay_s"]["slow"] <= 5.0
    assert r["false_alarms"] == 0
    for kind in ("fast", "slow"):
        assert r["tables"][kind]["false_alarms_before_onset"]["combined"] == 0
        assert r["tables"][kind]["delay_s"]["combined"]["missed"] == 0
    # the paper's threshold detector trips on magnetometer bursts during undisturbed flight
    assert r["false_alarms_by_detector"]["threshold"] > 0
    assert "Combined worst delay" in eval_track.format_text(r)


@pytest.mark.slow
@pytest.mark.parametrize("argv", [[], ["--undisturbed", "60", "--seed", "21"]])
def test_track_eval_full(argv):
    p = argparse.ArgumentParser()
    eval_track.add_arguments(p)
    r = eval_track.run(p.parse_args(argv))
    assert r["undisturbed"]["flights"] >= 20
    assert r["goals_met"], eval_track.format_text(r)
