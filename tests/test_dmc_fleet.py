"""The DMC detector's fleet cores (services/dmc_detector/fleet.py) against the per-vehicle reference.

Every implementation's fleet detector steps many vehicles interleaved in one call and must publish what the
reference detector of each vehicle publishes: features within 1e-9, identical stage-1 / valid / ready /
transition sequences and failing tests, identical ``describe`` sentences (its value to 1e-12), the same latch
state. The fleet pairing
must join, keep waiting and give up exactly what one TimeAligner per vehicle does.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest

from magmesh.align import REASONS, TimeAligner
from services.dmc_detector import core, fcm, fleet
from services.dmc_detector.core import CompassParams
from sim_publishers.car.core import CarSimSettings, paper_streets_settings, simulate

TOL = 1e-9


# ---- scenarios -------------------------------------------------------------------------------------------------------


@dataclass
class Vehicle:
    """One vehicle's paired epochs and what happens to it between epochs (index → events before that epoch)."""

    name: str
    t: np.ndarray
    b_a: np.ndarray
    b_b: np.ndarray
    p_a: CompassParams
    p_b: CompassParams
    declination_rad: float = 0.0
    dh_ref_rad: float = 0.0
    events: dict[int, list[tuple]] = field(default_factory=dict)


def _params(drive, model: str = "3d", err: float = 0.0) -> tuple[CompassParams, CompassParams]:
    e = drive.earth_field_enu_nt
    radius = float(np.hypot(e[0], e[1]) if model == "2d" else np.linalg.norm(e))
    out = []
    for k, s in enumerate(("1", "2")):
        tp = drive.true_params[s]
        off = tp.offset_nt + err * np.array([200.0, -150.0, 80.0]) * (1 + k)
        mat = tp.matrix * (1.0 + 0.004 * err)
        out.append(CompassParams(tuple(off), tuple(mat.ravel()), radius, model, "cal" if err else "manifest"))
    return out[0], out[1]


def _vehicle(name, drive, model="3d", gap_at_s=None, events=None, dh_ref_rad=0.0, repeat_at=None) -> Vehicle:
    t = drive.t_mag_s.copy()
    b_a, b_b = drive.mag_b_nt["1"].copy(), drive.mag_b_nt["2"].copy()
    keep = np.ones(len(t), bool)
    if gap_at_s is not None:  # longer than max_gap_s: the windows restart
        keep &= ~((t > gap_at_s) & (t < gap_at_s + 1.6))
    t, b_a, b_b = t[keep], b_a[keep], b_b[keep]
    if repeat_at is not None:  # one epoch repeated (time not moving forward): the windows restart
        t = np.insert(t, repeat_at, t[repeat_at - 1])
        b_a = np.insert(b_a, repeat_at, b_a[repeat_at - 1], axis=0)
        b_b = np.insert(b_b, repeat_at, b_b[repeat_at - 1], axis=0)
    p_a, p_b = _params(drive, model)
    return Vehicle(name, t, b_a, b_b, p_a, p_b, drive.declination_rad, dh_ref_rad, events or {})


@pytest.fixture(scope="module")
def drives():
    return {
        "urban_a": simulate(CarSimSettings(layout="urban_a", seed=1, duration_s=40.0)),
        "urban_b": simulate(CarSimSettings(layout="urban_b", seed=2, duration_s=40.0)),
        "urban_c": simulate(CarSimSettings(layout="urban_c", seed=3, duration_s=30.0)),
        "clean_200hz": simulate(CarSimSettings(layout="clean", seed=4, duration_s=12.0, mag_rate_hz=200.0)),
        "paper_a": simulate(paper_streets_settings("paper_a", seed=5, duration_s=60.0)),
    }


@pytest.fixture(scope="module")
def fleet_vehicles(drives):
    d = drives
    cal_a = _params(d["urban_a"], err=1.0)
    cal_b = _params(d["urban_b"], err=-1.0)
    return [
        _vehicle("urban_a", d["urban_a"], gap_at_s=21.0,
                 events={900: [("params", cal_a), ("restart",)], 1500: [("adopt", True, 29.5)]}),
        _vehicle("urban_b", d["urban_b"], dh_ref_rad=0.01, repeat_at=700,
                 events={400: [("adopt", True, None)], 1200: [("params", cal_b), ("restart",)],
                         1700: [("adopt", False, None)]}),
        _vehicle("urban_c_2d", d["urban_c"], model="2d", events={600: [("reset",)]}),
        _vehicle("clean_200hz", d["clean_200hz"], gap_at_s=5.0),  # 40 epochs in a smooth window: the rings grow
        _vehicle("paper_a", d["paper_a"], gap_at_s=30.0, events={200: [("adopt", True, 20.0)]}),
        _vehicle("urban_a_late", d["urban_a"], events={50: [("adopt", True, 1.0)]}),
    ]


def _reference(impl: str, model=None, dh_ref_rad=0.0):
    if impl == "threshold":
        return core.ThresholdDetector(core.ThresholdDetectorSettings(features=core.FeatureSettings(dh_ref_rad=dh_ref_rad)))
    if impl == "single":
        return core.SingleCompassDetector(
            core.ThresholdDetectorSettings(features=core.FeatureSettings(dh_ref_rad=dh_ref_rad)))
    return fcm.FcmDetector(model, fcm.FcmDetectorSettings(dh_ref_rad=dh_ref_rad))


def _fleet(impl: str, model=None, capacity=2):
    if impl == "threshold":
        return fleet.FleetDetector(core.ThresholdDetectorSettings(), capacity)
    if impl == "single":
        return fleet.FleetSingleDetector(core.ThresholdDetectorSettings(), capacity)
    return fleet.FleetFcmDetector(model, fcm.FcmDetectorSettings(), capacity)


def run_reference(impl, vehicles, model=None):
    """Each vehicle through its own reference detector: decisions, describe() of transitions, raised_t_s, latch."""
    out = []
    for v in vehicles:
        det = _reference(impl, model, v.dh_ref_rad)
        p_a, p_b = v.p_a, v.p_b
        decisions, described, raised_t = [], {}, []
        for i in range(len(v.t)):
            for ev in v.events.get(i, []):
                if ev[0] == "params":
                    p_a, p_b = ev[1]
                elif ev[0] == "restart":
                    det.restart_features()
                elif ev[0] == "adopt":
                    det.latch.adopt(ev[1], ev[2])
                elif ev[0] == "reset":
                    det.reset()
            d = det.update(float(v.t[i]), v.b_a[i], v.b_b[i], p_a, p_b, v.declination_rad)
            decisions.append(d)
            raised_t.append(det.latch.raised_t_s)
            if d.transition is not None:
                described[i] = det.describe(d)
        out.append({"decisions": decisions, "described": described, "raised_t_s": raised_t,
                    "latch": det.latch.state(), "flags": det.flags, "internal": det.internal_states})
    return out


def run_fleet(impl, vehicles, model=None, seed=0, capacity=2):
    """All vehicles through one fleet detector, frames of 1–5 epochs per vehicle, rows of the vehicles interleaved
    at random (each vehicle's in time order); events fall between frames."""
    rng = np.random.default_rng(seed)
    det = _fleet(impl, model, capacity)
    dummies = [det.add() for _ in range(3)]  # vehicles get slots out of order, and the slot table grows
    det.free(dummies[1])
    slots = [det.add() for _ in vehicles]
    for s, v in zip(slots, vehicles, strict=True):
        det.set_params(s, v.p_a, v.p_b, v.declination_rad, v.dh_ref_rad)
    n_max = max(len(v.t) for v in vehicles)
    event_at = sorted({i for v in vehicles for i in v.events})
    bounds = [0]
    while bounds[-1] < n_max:  # frame boundaries: 1–5 epochs each, every event index is a boundary
        nxt = bounds[-1] + int(rng.integers(1, 6))
        later = [e for e in event_at if bounds[-1] < e < nxt]
        bounds.append(later[0] if later else nxt)
    results = [{"rows": [None] * len(v.t), "out": [], "idx": []} for v in vehicles]
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        for s, v in zip(slots, vehicles, strict=True):
            for ev in v.events.get(lo, []):
                if ev[0] == "params":
                    det.set_params(s, ev[1][0], ev[1][1], v.declination_rad, v.dh_ref_rad)
                elif ev[0] == "restart":
                    det.restart_features(s)
                elif ev[0] == "adopt":
                    det.adopt(s, ev[1], ev[2])
                elif ev[0] == "reset":
                    det.reset(s)
        per = [(k, list(range(lo, min(hi, len(v.t))))) for k, v in enumerate(vehicles)]
        labels = rng.permutation(np.concatenate([np.full(len(ix), k) for k, ix in per]).astype(int))
        nxt = {k: iter(ix) for k, ix in per}
        rows = [(int(k), next(nxt[int(k)])) for k in labels]  # random interleaving, each vehicle in order
        if not rows:
            continue
        out = det.step(np.array([slots[k] for k, _ in rows]), np.array([vehicles[k].t[i] for k, i in rows]),
                       np.array([vehicles[k].b_a[i] for k, i in rows]), np.array([vehicles[k].b_b[i] for k, i in rows]))
        for j, (k, i) in enumerate(rows):
            results[k]["rows"][i] = (out, j)
    return det, slots, results


def assert_same_describe(got, want, where=None):
    """The same sentence, threshold and unit; the value as close as the features (the reference computes it through
    BLAS and numpy's SIMD arctan2, the kernel through plain arithmetic and libm: they differ in the last bits)."""
    assert (got[0], got[2], got[3]) == (want[0], want[2], want[3]), where
    assert (got[1] is None) == (want[1] is None), where
    if want[1] is not None:
        assert abs(got[1] - want[1]) <= 1e-12 * abs(want[1]), where


def assert_agree(det, slots, fl, ref, impl):
    n_tr = 0
    for s, f, r in zip(slots, fl, ref, strict=True):
        for i, d in enumerate(r["decisions"]):
            out, j = f["rows"][i]
            g = det.decision(out, j)
            where = (i, d.t_s)
            assert g.t_s == d.t_s, where
            assert (g.stage1_pass, g.valid, g.ready, g.transition, g.failed) == (
                d.stage1_pass, d.valid, d.ready, d.transition, d.failed), where
            got = g.dm_nt + g.ddm_nt_s + [g.dh_rad, g.ddh_rad_s, g.credibility]
            want = d.dm_nt + d.ddm_nt_s + [d.dh_rad, d.ddh_rad_s, d.credibility]
            assert all(abs(x - y) <= TOL for x, y in zip(got, want, strict=True)), (where, got, want)
            assert abs(math.remainder(g.heading_rad - d.heading_rad, 2 * math.pi)) < TOL, where
            assert g.ratios.keys() == d.ratios.keys(), where
            for name in d.ratios:
                assert abs(g.ratios[name] - d.ratios[name]) < TOL or (
                    math.isnan(g.ratios[name]) and math.isnan(d.ratios[name])), (where, name)
            rt = out.raised_t_s[j]
            assert (math.isnan(rt) and r["raised_t_s"][i] is None) or rt == r["raised_t_s"][i], where
            if d.transition is not None:
                n_tr += 1
                assert_same_describe(det.describe(out, j), r["described"][i], where)
        assert det.latch_state(s) == r["latch"]
        assert det.flags(s) == r["flags"]
        gi, ri = det.internal_states(s), r["internal"]
        assert gi["ratios"].keys() == ri["ratios"].keys()
        assert abs(gi["credibility"] - ri["credibility"]) < TOL
    return n_tr


def _summary(ref):
    ds = [d for r in ref for d in r["decisions"]]
    return {"epochs": len(ds), "transitions": sum(d.transition is not None for d in ds),
            "stage1_fail": sum(not d.stage1_pass for d in ds), "not_ready": sum(not d.ready for d in ds),
            "kc_fail": sum(d.failed == ("kc",) for d in ds),
            "failed_names": {n for d in ds for n in d.failed}}


# an FCM model with every feature and a fuzzifier other than 2 (the committed models use the paper's two features)
EXTENDED = fcm.FcmModel(np.array([[0.03, 0.05, 0.03, 0.05], [0.12, 0.15, 0.1, 0.12], [0.3, 0.35, 0.25, 0.3],
                                  [0.55, 0.6, 0.5, 0.55], [0.85, 0.9, 0.85, 0.9]]), "extended", fcm.LOOSE, m=2.5,
                        kc_min=0.6, n_good_clusters=2)


@pytest.mark.parametrize("impl,model,seed", [("threshold", None, 1), ("single", None, 2), ("fcm", "default", 3),
                                             ("fcm", "extended", 4)])
def test_fleet_detector_agrees_with_the_reference_on_simulated_drives(impl, model, seed, fleet_vehicles):
    m = {"default": fcm.FcmModel.load(), "extended": EXTENDED}.get(model)
    ref = run_reference(impl, fleet_vehicles, m)
    det, slots, fl = run_fleet(impl, fleet_vehicles, m, seed=seed)
    n_tr = assert_agree(det, slots, fl, ref, impl)
    s = _summary(ref)
    # the drives exercise what is compared: raises and clears, failures of stage 1, restarts of the windows
    assert n_tr == s["transitions"] >= 6, s
    assert s["stage1_fail"] > 100 and s["not_ready"] > 50, s
    if impl == "fcm":
        assert s["kc_fail"] > 20, s
    if impl == "single":
        assert s["failed_names"] == {"dm", "ddm"}, s
    assert det._raw.shape[1] > fleet._RAW_CAP0, "the 200 Hz vehicle must have grown the rings"
    assert len(fleet._kernels().step.signatures) == 1


# ---- hand-made epochs: each test failing alone ----------------------------------------------------------------------

R_NT = 50_000.0
IDENTITY = CompassParams((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), R_NT)


def _field(strength, heading_deg):
    """A field of this strength whose level heading is heading_deg (60 % horizontal)."""
    a = np.radians(heading_deg)
    return np.stack([strength * 0.6 * np.cos(a), strength * 0.6 * np.sin(a), np.full_like(a, -0.8 * strength)], -1)


def handmade(kind: str, th: core.Thresholds, seconds=6.0, rate_hz=50.0) -> Vehicle:
    """Epochs on which only ``kind`` fails (``kc``: only FCM's credibility, stage 1 passes; ``none``: nothing)."""
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    osc = np.sin(np.pi * np.maximum(t - 1.0, 0.0))  # 0 for the first second, then 0.5 Hz
    s_a = s_b = np.full(len(t), R_NT)
    h_a = np.full(len(t), 40.0)
    h_b = h_a.copy()
    if kind == "dm":
        s_a = s_b = R_NT + 1.5 * th.dm_nt
    elif kind == "ddm":  # |Δm| ≤ 0.8 V_Δm while its rate reaches ~1.8 V_Δm per second
        s_a = s_b = R_NT + 0.8 * min(th.dm_nt, th.ddm_nt_s) * osc
    elif kind == "dh":
        h_b = h_a - 1.5 * th.dh_deg
    elif kind == "ddh":
        h_b = h_a - 0.8 * min(th.dh_deg, th.ddh_deg_s) * osc
    elif kind == "kc":
        s_a = s_b = R_NT + 0.85 * th.dm_nt
    return Vehicle(f"handmade_{kind}", t, _field(s_a, h_a), _field(s_b, h_b), IDENTITY, IDENTITY)


@pytest.mark.parametrize("impl", ["threshold", "single", "fcm"])
def test_each_threshold_failing_alone(impl):
    m = fcm.FcmModel.load() if impl == "fcm" else None
    th = m.loose if m else core.Thresholds()
    kinds = ["dm", "ddm", "dh", "ddh", "none"] + (["kc"] if impl == "fcm" else [])
    vehicles = [handmade(k, th) for k in kinds]
    ref = run_reference(impl, vehicles, m)
    det, slots, fl = run_fleet(impl, vehicles, m, seed=3)
    assert_agree(det, slots, fl, ref, impl)
    for kind, r in zip(kinds, ref, strict=True):
        failed = {n for d in r["decisions"] for n in d.failed}
        transitions = [d.transition for d in r["decisions"] if d.transition]
        if kind == "none" or (impl == "single" and kind in ("dh", "ddh")):  # single sees compass a alone
            assert failed == set() and transitions == [], (kind, failed)
        elif kind == "kc":  # stage 1 passes throughout, the credibility is too low
            assert failed == {"kc"} and all(d.stage1_pass for d in r["decisions"]), (kind, failed)
        else:  # it fails, and no other threshold test does (FCM's credibility may fail beside it)
            assert kind in failed and failed - {"kc"} == {kind}, (kind, failed)
            assert transitions[0] == "raised", kind
            i = next(i for i, d in enumerate(r["decisions"]) if d.transition == "raised")
            reason = r["described"][i][0]
            assert reason.startswith("Magnetic interference suspected"), reason


# ---- latch state, hand-over, slot lifecycle ------------------------------------------------------------------------


def test_latch_state_restores_into_another_fleet_detector_and_matches_the_reference():
    v = handmade("dm", core.Thresholds(), seconds=2.0)
    ref = core.ThresholdDetector()
    a = fleet.FleetDetector(capacity=1)
    s = a.add()
    a.set_params(s, IDENTITY, IDENTITY)
    half = len(v.t) // 2
    a.step(np.full(half, s), v.t[:half], v.b_a[:half], v.b_b[:half])
    for i in range(half):
        ref.update(float(v.t[i]), v.b_a[i], v.b_b[i], IDENTITY, IDENTITY)
    state = a.latch_state(s)
    assert state == ref.latch.state() and state["raised"] and state["invalid_since"] == 0.0
    b = fleet.FleetDetector(capacity=1)  # a restarted instance: the latch is carried, the windows start again
    sb = b.add()
    b.set_params(sb, IDENTITY, IDENTITY)
    b.restore_latch(sb, state)
    assert b.latch_state(sb) == state
    ref.restart_features()
    out = b.step(np.full(len(v.t) - half, sb), v.t[half:], v.b_a[half:], v.b_b[half:])
    for j, i in enumerate(range(half, len(v.t))):
        d = ref.update(float(v.t[i]), v.b_a[i], v.b_b[i], IDENTITY, IDENTITY)
        assert b.decision(out, j).transition == d.transition and bool(out.ready[j]) == d.ready
    assert b.latch_state(sb) == ref.latch.state()
    b.adopt(sb, False, 12.0)  # adopting "cleared" forgets the raise time, as AlarmLatch.adopt does
    ref.latch.adopt(False, 12.0)
    assert b.latch_state(sb) == ref.latch.state() and b.raised_t_s[sb] != b.raised_t_s[sb]


def test_slots_in_use_and_with_parameters_only():
    det = fleet.FleetDetector(capacity=1)
    s = det.add()
    b = np.array([[3e4, 0.0, -4e4]])
    with pytest.raises(ValueError, match="no compensation parameters"):
        det.step([s], [0.0], b, b)
    det.set_params(s, IDENTITY, IDENTITY)
    with pytest.raises(ValueError, match="not in use"):
        det.step([s, s + 1], [0.0, 0.0], np.vstack([b, b]), np.vstack([b, b]))
    assert det.slots.tolist() == [s]
    # a refused frame changed nothing: the first epoch is still the slot's first
    out = det.step([s], [0.0], b, b)
    assert len(out) == 1 and not out.ready[0] and det.flags(s)["warming"]
    det.free(s)
    with pytest.raises(ValueError, match="not in use"):
        det.step([s], [1.0], b, b)
    assert det.add() == s and det.params(s) is None and det.internal_states(s) == {}
    assert len(det.step([], [], np.zeros((0, 3)), np.zeros((0, 3)))) == 0
    with pytest.raises(ValueError, match="both compasses"):
        det.set_params(s, IDENTITY, None)
    single = fleet.FleetSingleDetector(capacity=1)  # one compass: b is neither needed nor read
    s1 = single.add()
    single.set_params(s1, IDENTITY, None)
    out = single.step([s1], [0.0], b)
    assert out.dm_nt[0, 1] == 0.0 and abs(out.dm_nt[0, 0] - (np.linalg.norm(b) - R_NT)) < 1e-6


def test_service_settings_are_accepted():
    from services.dmc_detector.service import Settings

    det = fleet.FleetDetector(Settings(dm_threshold_nt=500.0, smooth_window_s=0.1), capacity=1)
    assert det.thresholds.dm_nt == 500.0 and det.feature_settings.smooth_window_s == 0.1


# ---- pairing -------------------------------------------------------------------------------------------------------


def _streams(rng, n_vehicles, seconds=8.0):
    """Per vehicle the two compasses' samples (t, b) with jitter, losses, a silent spell and a stream running late
    (frame delay), so that pairs form, samples pass, wait, expire and (with a small max_pending) overflow."""
    out = []
    for v in range(n_vehicles):
        t = np.arange(int(seconds * 50)) * 0.02 + 0.3 * v
        ta = t + (rng.uniform(-0.001, 0.001, t.size) if v % 2 else 0.0)  # even vehicles: ties with compass b
        tb = t + rng.choice([0.0, 0.003, -0.004, 0.009], t.size, p=[0.6, 0.2, 0.15, 0.05])
        keep_a = rng.random(t.size) > 0.05
        keep_b = rng.random(t.size) > 0.05
        if v % 4 < 2:
            keep_b &= ~((t > 3.0) & (t < 6.5))  # compass b silent for 3.5 s: a's samples wait, then expire
        ta, tb = ta[keep_a], np.sort(tb[keep_b])
        out.append({"a": (ta, rng.normal(0, 1e4, (ta.size, 3))), "b": (tb, rng.normal(0, 1e4, (tb.size, 3))),
                    "delay_b": [0, 2, 5][v % 3]})
    return out


@pytest.mark.parametrize("max_pending", [8192, 7])
def test_pair_frame_agrees_with_one_time_aligner_per_vehicle(max_pending):
    rng = np.random.default_rng(11)
    tol, max_wait, frame_s, wall_per_frame = 0.005, 1.0, 0.1, 0.25
    streams = _streams(rng, 7)
    slots = [3, 0, 9, 4, 1, 12, 6]  # slot numbers out of vehicle order
    n_frames = int(12.0 / frame_s)
    refs = [TimeAligner(("1", "2"), tol, max_wait, max_pending) for _ in streams]
    pairer = fleet.FleetPairer(("1", "2"), tol, max_wait, max_pending)
    seen = {r: 0 for r in REASONS}
    for k in range(n_frames):
        now = k * wall_per_frame
        rows = {"a": [], "b": []}
        want_ep, want_gave = [], []
        for v, st in enumerate(streams):
            frame_rows = []
            for name in ("a", "b"):
                t, b = st[name]
                fi = np.floor(t / frame_s).astype(int) + (st["delay_b"] if name == "b" else 0)
                for i in np.flatnonzero(fi == k):
                    rows[name].append((slots[v], t[i], b[i]))
                    frame_rows.append((t[i], 0 if name == "a" else 1, b[i]))
            # the reference pushes the frame's samples in time order, compass a first at equal times
            for t_i, si, b_i in sorted(frame_rows, key=lambda r: (r[0], r[1])):
                joined, gave = refs[v].push(("1", "2")[si], t_i, b_i, now=now)
                want_ep += [(slots[v], j.t_s, j.times["2"], tuple(j.values["1"]), tuple(j.values["2"])) for j in joined]
                want_gave += [(slots[v], ("1", "2").index(g.stream), g.t_s, tuple(g.value), g.reason) for g in gave]
        # the frame: rows sorted by slot, each slot's in time order
        args = []
        for name in ("a", "b"):
            r = sorted(rows[name], key=lambda x: x[0])
            args += [np.array([x[0] for x in r], np.int32), np.array([x[1] for x in r]),
                     np.array([x[2] for x in r]).reshape(-1, 3)]
        ep, gave = pairer.pair(*args, now=now)
        got_ep = [(int(s), t, tb, tuple(ba), tuple(bb)) for s, t, tb, ba, bb in
                  zip(ep.slot, ep.t_s, ep.t_b_s, ep.b_a_nt, ep.b_b_nt, strict=True)]
        assert got_ep == sorted(want_ep, key=lambda e: e[0]), k  # sorted by slot, then time
        got_gave = [(int(s), int(st_), t, tuple(b), REASONS[r]) for s, st_, t, b, r in
                    zip(gave.slot, gave.stream, gave.t_s, gave.b_nt, gave.reason, strict=True)]
        assert got_gave == sorted(want_gave, key=lambda g: g[0]), k  # each slot's in TimeAligner's order
        for g in got_gave:
            seen[g[4]] += 1
        for v, ref in enumerate(refs):
            for si, s in enumerate(("1", "2")):
                w = pairer.waiting.take((pairer.waiting.slot == slots[v]) & (pairer.waiting.stream == si))
                assert w.t_s.tolist() == [q[0] for q in ref.pending[s]], (k, v, s)
                assert w.arrived.tolist() == [q[2] for q in ref.pending[s]], (k, v, s)
            assert pairer.counts(slots[v]) == ref.counts(), (k, v)
    # a tick long after the last frame gives up everything still waiting, as TimeAligner.expire does
    now = n_frames * wall_per_frame + 5.0
    gave = pairer.expire(now)
    want = [(slots[v], ("1", "2").index(g.stream), g.t_s) for v, ref in enumerate(refs) for g in ref.expire(now)]
    assert [(int(s), int(st_), t) for s, st_, t in zip(gave.slot, gave.stream, gave.t_s, strict=True)] == \
        sorted(want, key=lambda g: g[0])
    assert all(pairer.counts(s) == ref.counts() for s, ref in zip(slots, refs, strict=True))
    assert len(pairer.waiting) == 0
    assert seen["passed"] > 20 and seen["expired"] > 10, seen
    if max_pending < 100:
        assert seen["overflow"] > 10, seen
    assert len(fleet._kernels().pair.signatures) == 1


def _one_aligner(frames, max_pending=8192, max_wait_s=1.0):
    """frames: [(now, [(stream, t)...])] for one vehicle; TimeAligner fed in time order, compass a first at ties."""
    ref = TimeAligner(("1", "2"), 0.005, max_wait_s, max_pending)
    pairs, gave_up = [], []
    for now, rows in frames:
        for st, t in sorted(rows, key=lambda r: (r[1], r[0])):
            joined, gave = ref.push(("1", "2")[st], t, [t, float(st), 0.0], now=now)
            pairs += [j.t_s for j in joined]
            gave_up += [(g.reason, ("1", "2").index(g.stream), g.t_s) for g in gave]
    return pairs, gave_up


def _one_pairer(frames, max_pending=8192, max_wait_s=1.0):
    p = fleet.FleetPairer(("1", "2"), 0.005, max_wait_s, max_pending)
    pairs, gave_up = [], []
    for now, rows in frames:
        a = [t for st, t in rows if st == 0]
        b = [t for st, t in rows if st == 1]
        ep, gave = p.pair(np.zeros(len(a), np.int32), a, [[t, 0.0, 0.0] for t in a], np.zeros(len(b), np.int32), b,
                          [[t, 1.0, 0.0] for t in b], now=now)
        pairs += ep.t_s.tolist()
        gave_up += [(REASONS[r], int(st), t) for r, st, t in zip(gave.reason, gave.stream, gave.t_s, strict=True)]
    return pairs, gave_up


def test_pair_frame_push_order_at_equal_times_decides_overflow_and_expiry():
    """Pushing compass a first at equal times is part of the rule: it decides whether a full queue overflows and
    whether an old waiting sample pairs before it expires."""
    # compass a's queue is full (max_pending 7) when a frame brings a and b at the same time
    frames = [(0.0, [(0, 0.02 * k) for k in range(7)]), (0.5, [(0, 0.2), (1, 0.2)])]
    got, want = _one_pairer(frames, max_pending=7), _one_aligner(frames, max_pending=7)
    assert got == want and want[0] == [0.2] and want[1][0] == ("overflow", 0, 0.0), want
    # a compass-b sample waited long; the frame's a at the same time as a new b pairs with it before it expires
    frames = [(0.0, [(1, 1.999)]), (5.0, [(0, 2.0), (1, 2.0)])]
    got, want = _one_pairer(frames), _one_aligner(frames)
    assert got == want == ([2.0], [])
    frames = [(0.0, [(1, 1.999)]), (5.0, [(1, 2.0), (0, 2.001)])]  # b first by time: the old one expires
    got, want = _one_pairer(frames), _one_aligner(frames)
    assert got == want == ([2.001], [("expired", 1, 1.999)])


def test_pair_frame_then_step_equals_aligner_then_update():
    """A frame's raw compass rows through pair_frame and step = TimeAligner + ThresholdDetector per vehicle."""
    rng = np.random.default_rng(5)
    streams = _streams(rng, 3, seconds=4.0)
    det = fleet.FleetDetector(capacity=3)
    pairer = fleet.FleetPairer()
    slots = [det.add() for _ in streams]
    for s in slots:
        det.set_params(s, IDENTITY, IDENTITY)
    refs = [(TimeAligner(("1", "2"), 0.005), core.ThresholdDetector()) for _ in streams]
    got, want = [], []
    for k in range(60):
        args, per = [], [[] for _ in streams]
        for name in ("a", "b"):
            r = []
            for v, st in enumerate(streams):
                t, b = st[name]
                for i in np.flatnonzero(np.floor(t / 0.1).astype(int) == k):
                    r.append((slots[v], t[i], b[i] + [3e4, 0, -4e4]))
                    per[v].append((t[i], name, b[i] + [3e4, 0, -4e4]))
            args += [np.array([x[0] for x in r], np.int32), np.array([x[1] for x in r]),
                     np.array([x[2] for x in r]).reshape(-1, 3)]
        ep, _ = pairer.pair(*args, now=float(k))
        out = det.step(ep.slot, ep.t_s, ep.b_a_nt, ep.b_b_nt)
        got += [(int(s), t, bool(ok)) for s, t, ok in zip(ep.slot, out.t_s, out.valid, strict=True)]
        for v, (al, rd) in enumerate(refs):
            for t_i, name, b_i in sorted(per[v], key=lambda x: (x[0], x[1])):
                for j in al.push("1" if name == "a" else "2", t_i, b_i, now=float(k))[0]:
                    want.append((slots[v], j.t_s, rd.update(j.t_s, j.values["1"], j.values["2"], IDENTITY,
                                                            IDENTITY).valid))
    assert len(got) > 400 and sorted(got) == sorted(want)


# ---- warm-up -------------------------------------------------------------------------------------------------------


def test_warm_entry_point_compiles_every_kernel_once():
    r = subprocess.run([sys.executable, "-m", "services.dmc_detector.fleet", "--warm"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["signatures"] == {"step": 1, "pair": 1}
    assert res["step_s"] > 0 and res["pair_s"] > 0


def test_bench_row_runs_and_the_timed_decisions_agree():
    from bench import cores_bench

    r = cores_bench.dmc_detector(vehicles=(1, 3), epochs=60, repeats=1, ref_epochs=80)
    assert r["same_decisions"] == {"threshold": True, "fcm": True, "single": True}
    assert set(r["fleet_us_per_epoch"]["fcm"]) == {"1", "3"} and r["reference_us_per_epoch"]["single"] > 0
    assert r["pairing_us_per_epoch"]["time_aligner"] > 0 and r["pairing_us_per_epoch"]["pair_frame"]["3"] > 0
