"""DMC detector core: features (batch = streaming), pairing, thresholds, hysteresis, service wiring."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magmesh import maths
from schemas import keys, messages
from services.dmc_detector import core
from services.dmc_detector.core import CompassParams, FeatureSettings, Thresholds

B_ENU = np.array([-600.0, 33000.0, -35000.0])  # a mid-latitude Earth field, nT
IDENTITY = CompassParams((0.0, 0.0, 0.0), (1, 0, 0, 0, 1, 0, 0, 0, 1), float(np.linalg.norm(B_ENU)))


def synthetic_drive(seed=0, n=3000, rate_hz=50.0, source_at_s=(30.0, 40.0), moment_am2=(8000.0, 8000.0, 2000.0),
                    noise_nt=25.0):
    """A level vehicle turning slowly, two compasses 0.10 m apart on body x; a dipole beside the road."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    heading = np.radians(10.0) + 0.15 * np.sin(t / 7.0)
    speed = 10.0
    pos = np.stack([speed * t, np.zeros(n), np.zeros(n)], axis=1)
    b1 = np.empty((n, 3))
    b2 = np.empty((n, 3))
    truth_err = np.zeros(n)
    src = None
    if source_at_s is not None:
        src = np.array([speed * 0.5 * (source_at_s[0] + source_at_s[1]), 4.0, 1.0])
    for i in range(n):
        R = maths.body_to_enu(heading[i])
        fwd = R @ np.array([0.05, 0, 0])
        p1, p2 = pos[i] + fwd, pos[i] - fwd
        f1, f2 = B_ENU.copy(), B_ENU.copy()
        if src is not None:
            f1 = f1 + maths.dipole_field_nt(moment_am2, src, p1)
            f2 = f2 + maths.dipole_field_nt(moment_am2, src, p2)
        b1[i] = R.T @ f1
        b2[i] = R.T @ f2
        truth_err[i] = abs(float(maths.angle_diff(core.compass_heading(b1[i], maths.declination_rad(B_ENU)),
                                                  heading[i])))
    b1 += rng.normal(0, noise_nt, b1.shape)
    b2 += rng.normal(0, noise_nt, b2.shape)
    return t, b1, b2, heading, truth_err


def test_features_batch_equals_streaming():
    t, b1, b2, _, _ = synthetic_drive(n=1500)
    t = t.copy()
    t[700:] += 2.0  # a gap: windows restart
    s = FeatureSettings()
    fb = core.features_batch(t, b1, b2, IDENTITY, IDENTITY, 0.1, s)
    tr = core.FeatureTracker(s)
    for i in range(len(t)):
        f = tr.update(float(t[i]), b1[i], b2[i], IDENTITY, IDENTITY, 0.1)
        assert bool(f.rates_ready[0]) == bool(fb.rates_ready[i]), i
        np.testing.assert_allclose(f.dm_nt[0], fb.dm_nt[i], atol=1e-6)
        np.testing.assert_allclose(f.ddm_nt_s[0], fb.ddm_nt_s[i], atol=1e-6)
        assert abs(f.dh_rad[0] - fb.dh_rad[i]) < 1e-9
        assert abs(f.ddh_rad_s[0] - fb.ddh_rad_s[i]) < 1e-9
    # after the gap the rates need history_s of input again
    k = 700
    assert not fb.rates_ready[k] and fb.rates_ready[k + int(s.history_s * 50) + 1]


def test_compensation_and_heading():
    rng = np.random.default_rng(3)
    M = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    off = np.array([1200.0, -800.0, 300.0])
    p = CompassParams(tuple(off), tuple(M.ravel()), float(np.linalg.norm(B_ENU)))
    for hdg in np.radians([0, 45, 170, 300]):
        h = maths.body_to_enu(hdg).T @ B_ENU
        m = np.linalg.solve(M, h) + off  # the sensor reading whose compensation is h
        np.testing.assert_allclose(p.apply(m), h, atol=1e-6)
        assert abs(p.strength(p.apply(m)) - p.field_radius_nt) < 1e-6
        assert abs(maths.angle_diff(core.compass_heading(p.apply(m), maths.declination_rad(B_ENU)), hdg)) < 1e-9
    with pytest.raises(ValueError):
        CompassParams((0, 0, 0), (1, 0, 0), 1.0)
    with pytest.raises(ValueError):
        CompassParams((0, 0, 0), tuple(np.eye(3).ravel()), -5.0)


def test_threshold_detects_source_and_passes_clean():
    th = Thresholds()
    t, b1, b2, _, err = synthetic_drive(seed=1)
    decl = maths.declination_rad(B_ENU)
    f = core.features_batch(t, b1, b2, IDENTITY, IDENTITY, decl)
    ok = core.threshold_test(f, th)
    bad = err > math.radians(5)
    assert bad.sum() > 50, "the synthetic source must disturb the heading"
    assert (~ok[bad]).mean() > 0.9, "disturbed epochs must be recognised as invalid"
    far = (t < 20) | (t > 50)
    assert ok[far].mean() > 0.99
    t, b1, b2, _, err = synthetic_drive(seed=2, source_at_s=None)
    f = core.features_batch(t, b1, b2, IDENTITY, IDENTITY, decl)
    assert core.threshold_test(f, th).mean() > 0.995
    assert err.max() < math.radians(0.5)


def test_latch_hysteresis_does_not_flap():
    hs = core.HysteresisSettings(raise_after_s=0.3, clear_after_s=2.0)
    t = np.arange(0, 20, 0.02)
    valid = np.ones(len(t), bool)
    valid[(t > 5) & (t < 10)] = False
    valid[(t > 7) & (t < 7.5)] = True  # a short valid spell inside the zone: no clear
    valid[(t > 14) & (t < 14.2)] = False  # a blip shorter than raise_after_s: no raise
    latch = core.AlarmLatch(hs)
    transitions = [(float(ti), tr) for ti, v in zip(t, valid, strict=False) if (tr := latch.update(float(ti), bool(v)))]
    assert [tr for _, tr in transitions] == ["raised", "cleared"]
    assert abs(transitions[0][0] - 5.32) < 0.03
    assert abs(transitions[1][0] - 12.0) < 0.05


def test_pairer_any_arrival_order():
    rng = np.random.default_rng(0)
    t = np.arange(200) * 0.02
    events = [("1", ti, [ti, 0, 0]) for ti in t] + [("2", ti + 1e-4, [ti, 1, 0]) for ti in t if ti != t[50]]
    # interleave the two streams randomly but keep each in time order
    s1 = [e for e in events if e[0] == "1"]
    s2 = [e for e in events if e[0] == "2"]
    order = rng.permutation([0] * len(s1) + [1] * len(s2))
    merged, i1, i2 = [], 0, 0
    for o in order:
        if o == 0:
            merged.append(s1[i1])
            i1 += 1
        else:
            merged.append(s2[i2])
            i2 += 1
    p = core.Pairer(("1", "2"), 0.005)
    pairs, dropped = [], 0
    for sensor, ti, b in merged:
        out, d = p.push(sensor, ti, b)
        pairs += out
        dropped += d
    assert len(pairs) == 199
    assert all(pb[0] == pa[0] and pa[1] == 0 and pb[1] == 1 for _, pa, pb in pairs)
    assert [pt for pt, _, _ in pairs] == sorted(pt for pt, _, _ in pairs)
    # the unpaired sample of sensor 1 is dropped and counted (once sensor 2 has moved past it)
    assert dropped + sum(len(q) for q in p.pending.values()) == 1


class _FakeRuntime:
    """Stands in for magmesh.runtime.Runner: records what the service publishes (validated)."""

    def __init__(self):
        self.out = []
        self.drops = {}
        self.seq = {}
        self.mode = "active"
        self.alarm_published = {}
        self.raised = {}
        self.alarm_adopted = 0
        self.vehicle_state = {}

    def publish(self, key, msg_type, vehicle, t_s, fields):
        seq = self.seq.get(key, -1) + 1
        self.seq[key] = seq
        msg = messages.validate(messages.make(msg_type, vehicle, t_s, seq, **fields), key, msg_type)
        self.out.append((key, msg))
        return msg

    def publish_rows(self, msg_type, keys_, vehicles, t_s, cols, mirror=None):
        t_s = list(t_s)
        cols = {f: (c.tolist() if isinstance(c, np.ndarray) else c) for f, c in cols.items()}
        return [self.publish(k, msg_type, v, float(t_s[i]),
                             {f: (c if isinstance(c, str) else c[i]) for f, c in cols.items()})["seq"]
                for i, (k, v) in enumerate(zip(keys_, vehicles, strict=True))]

    def raised_alarm(self, key):
        return dict(self.raised.get(key) or {})

    def publish_alarm(self, key, vehicle, t_s, fields):
        return self.publish(key, "alarm", vehicle, t_s, fields)

    def count_drop(self, key, reason, n=1):
        self.drops[reason] = self.drops.get(reason, 0) + n

    def state_for(self, vehicle):
        raise NotImplementedError


def _run_service(svc, t, b1, b2, vehicle="car-1", cal=None):
    rt = _FakeRuntime()
    svc._rt = rt
    state = svc.new_vehicle(vehicle)
    if cal is not None:
        k = keys.cal_params(vehicle, "1")
        svc.on_message(keys.parse(k), cal, state)
    for i in range(len(t)):
        for sensor, b in (("2", b2[i]), ("1", b1[i])):  # sensor 2 first: pairing must not care
            k = keys.clean_mag(vehicle, sensor)
            msg = messages.make("mag", vehicle, float(t[i]), i, sensor=sensor, b_nt=[float(x) for x in b])
            svc.on_message(keys.parse(k), msg, state)
    return rt, state


def _vehicles_config():
    table = {"offset_nt": [0.0, 0.0, 0.0], "matrix": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
             "field_radius_nt": float(np.linalg.norm(B_ENU))}
    return {"car-1": {"declination_rad": maths.declination_rad(B_ENU), "mag_params": {"1": table, "2": table}}}


def test_service_publishes_dmc_and_one_alarm_pair():
    from services.dmc_detector.service import ThresholdDmcDetector

    svc = ThresholdDmcDetector(vehicles_config=_vehicles_config())
    t, b1, b2, heading, _ = synthetic_drive(seed=4)
    rt, state = _run_service(svc, t, b1, b2)
    dmc = [m for k, m in rt.out if k == keys.dmc("car-1")]
    alarms = [m for k, m in rt.out if k == keys.alarm("car-1", "dmc")]
    assert len(dmc) == len(t)
    assert [m["seq"] for m in dmc] == list(range(len(t)))
    assert all(m["param_source"] == "manifest" and m["impl"] == "threshold" for m in dmc)
    assert [a["state"] for a in alarms] == ["raised", "cleared"]
    assert "exceeds" in alarms[0]["reason"] and alarms[0]["value"] > alarms[0]["threshold"]
    assert 25 < alarms[0]["t_s"] < 35 and alarms[1]["t_s"] > alarms[0]["t_s"] + 3
    assert alarms[1]["raised_t_s"] == alarms[0]["t_s"]
    hd = np.array([m["heading_rad"] for m in dmc])
    valid = np.array([m["valid"] for m in dmc])
    err_deg = np.degrees(np.abs(maths.angle_diff(hd[valid], heading[valid])))
    assert np.mean(err_deg > 5.0) < 0.005 and np.median(err_deg) < 0.5


def test_service_no_params_drops_and_cal_params_take_over():
    from services.dmc_detector.service import ThresholdDmcDetector

    t, b1, b2, _, _ = synthetic_drive(seed=5, n=200, source_at_s=None)
    svc = ThresholdDmcDetector(vehicles_config={})
    rt, _ = _run_service(svc, t, b1, b2, vehicle="car-9")
    assert not rt.out and rt.drops["no_compensation_params"] == len(t)

    svc = ThresholdDmcDetector(vehicles_config=_vehicles_config())
    cal = messages.make("cal_params", "car-1", 0.0, 0, sensor="1", param_id="fit-7", status="ok", model="3d",
                        method="arls", offset_nt=[0.0, 0.0, 0.0], matrix=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                        field_radius_nt=float(np.linalg.norm(B_ENU)), rmse_nt=10.0, coverage_frac=1.0,
                        n_samples=500, n_gross_rejected=0, observable=[True, True, False], fit_t_s=0.0,
                        fit_duration_ms=1.0)
    rt, state = _run_service(svc, t, b1, b2, cal=cal)
    assert state.params["1"].param_id == "fit-7" and state.param_origin["1"] == "cal"
    assert {m["param_source"] for k, m in rt.out if k == keys.dmc("car-1")} == {"manifest"}  # sensor 2 still manifest


def test_service_adopts_alarm_state_handed_over_in_a_swap():
    """A new holder that never saw the disturbance still clears the alarm the previous holder raised."""
    from services.dmc_detector.service import ThresholdDmcDetector

    svc = ThresholdDmcDetector(vehicles_config=_vehicles_config())
    rt = _FakeRuntime()
    akey = keys.alarm("car-1", "dmc")
    rt.mode = "active"
    rt.alarm_published = {akey: "raised"}
    rt.raised = {akey: {"t_s": 12.0, "state": "raised"}}
    orig = rt.publish

    def publish(key, msg_type, vehicle, t_s, fields):
        msg = orig(key, msg_type, vehicle, t_s, fields)
        if msg_type == "alarm":
            rt.alarm_published[key] = msg["state"]
        return msg

    rt.publish = publish
    svc._rt = rt
    state = svc.new_vehicle("car-1")
    t, b1, b2, _, _ = synthetic_drive(seed=9, n=400, source_at_s=None)
    for i in range(len(t)):
        for sensor, b in (("1", b1[i]), ("2", b2[i])):
            msg = messages.make("mag", "car-1", float(t[i]), i, sensor=sensor, b_nt=[float(x) for x in b])
            svc.on_message(keys.parse(keys.clean_mag("car-1", sensor)), msg, state)
    alarms = [m for k, m in rt.out if k == akey]
    assert [a["state"] for a in alarms] == ["cleared"]
    clear = svc.settings.clear_after_s
    assert clear - 0.05 <= alarms[0]["t_s"] <= clear + 0.1 and alarms[0]["raised_t_s"] == 12.0


@pytest.mark.parametrize("late_start", [400, 1333])
def test_late_started_detector_agrees_after_warmup(late_start):
    """What a live swap relies on: an instance started later, warmed on the same stream, publishes the
    same dmc content for every epoch once it has seen history_s of input."""
    t, b1, b2, _, _ = synthetic_drive(seed=10, n=2500)
    a = core.ThresholdDetector()
    b = core.ThresholdDetector()
    warm = int(np.ceil(a.settings.features.history_s * 50)) + 1
    da = [a.update(float(t[i]), b1[i], b2[i], IDENTITY, IDENTITY, 0.1) for i in range(len(t))]
    db = [b.update(float(t[i]), b1[i], b2[i], IDENTITY, IDENTITY, 0.1) for i in range(late_start, len(t))]
    for x, y in zip(da[late_start + warm:], db[warm:], strict=True):
        assert (x.valid, x.stage1_pass, x.credibility) == (y.valid, y.stage1_pass, y.credibility)
        np.testing.assert_allclose(x.dm_nt + x.ddm_nt_s + [x.dh_rad, x.ddh_rad_s, x.heading_rad],
                                   y.dm_nt + y.ddm_nt_s + [y.dh_rad, y.ddh_rad_s, y.heading_rad], rtol=0, atol=1e-6)



def test_2d_cal_params_do_not_replace_a_3d_set():
    from services.dmc_detector.service import ThresholdDmcDetector

    t, b1, b2, _, _ = synthetic_drive(seed=12, n=100, source_at_s=None)
    cal2d = messages.make("cal_params", "car-1", 0.0, 0, sensor="1", param_id="fit-2d", status="ok", model="2d",
                          method="arls", offset_nt=[0.0, 0.0, 0.0], matrix=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                          field_radius_nt=float(np.hypot(B_ENU[0], B_ENU[1])), rmse_nt=10.0, coverage_frac=1.0,
                          n_samples=500, n_gross_rejected=0, observable=[True, True, False], fit_t_s=0.0,
                          fit_duration_ms=1.0)
    svc = ThresholdDmcDetector(vehicles_config=_vehicles_config())
    rt, state = _run_service(svc, t, b1, b2, cal=cal2d)
    assert state.params["1"].param_id == "manifest" and state.ignored_2d == {"1": "fit-2d"}
    # with no 3-D set held, a 2-D set is used (horizontal field strength)
    table = dict(_vehicles_config()["car-1"]["mag_params"]["2"])
    svc = ThresholdDmcDetector(vehicles_config={"car-1": {"mag_params": {"2": table}}})
    rt, state = _run_service(svc, t, b1, b2, cal=cal2d)
    assert state.params["1"].param_id == "fit-2d" and state.params["1"].model == "2d"
    assert len([1 for k, _ in rt.out if k == keys.dmc("car-1")]) == len(t)
