"""The compiled heading filter (services/heading_fuser/compiled.py) against the reference core.HeadingFilter.

Every case runs the same calls through both and compares after every call: heading within 1e-9 rad (the
two differ only in the order numpy's BLAS/LAPACK sums small matrix products, ≈1e-15 rad in practice),
identical modes, flags, mode changes and update_mag return values. Each hand-made case also checks that the
reference really took the branch it is about (so the comparison is not vacuous).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magmesh import maths
from services.heading_fuser import compiled, core, profiles

TOL_RAD = 1e-9
IMU, MAG, REBASE, RESET = 0, 1, 2, 3


@pytest.fixture(autouse=True, scope="module")
def _kernels():
    """Load the kernels once: after the background warm-up that conftest.py starts on a cold cache (compiling
    them here too would only compete with it for the cores)."""
    if compiled._WARMING is not None:
        compiled._WARMING.wait(timeout=600)
    compiled.warm()


# ---- harness ------------------------------------------------------------------------------------------------
def _hd(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2 * math.pi))


def _row(kind, t=math.nan, a=(0.0, 0.0, 0.0), b=(0.0, 0.0, 0.0), dt=0.0, dmc=-1):
    return (kind, float(t), tuple(float(v) for v in a), tuple(float(v) for v in b), float(dt), int(dmc))


def _call(f, row):
    kind, t, a, b, dt, dmc = row
    ts = None if math.isnan(t) else t
    if kind == IMU:
        f.update_imu(a, b, dt, t_s=ts)
        return False
    if kind == MAG:
        return f.update_mag(a, None if dmc < 0 else bool(dmc), t_s=ts)
    if kind == REBASE:
        f.rebase_field_reference()
    else:
        f.reset()
    return False


_FLAG_NAMES = tuple(x.name for x in dataclasses.fields(core.Flags))  # every field a bool


def _trace_row(ref, ret):
    """The reference after a row, as a fleet slot is checked against it: (mode, mag_fused, return value, heading)."""
    return ref.mode, ref.flags.mag_fused, bool(ret), ref.heading_rad()


def _snapshot(f, ret):
    st = f.internal_states
    fl = f.flags  # a flat dataclass of bools: its fields' values as a tuple (what dataclasses.astuple gives)
    return (f.heading_rad(), f.mode, tuple(getattr(fl, n) for n in _FLAG_NAMES), bool(ret), st.mag_innovation_rad,
            st.heading_std_rad, f.euler(), f.attitude_std())


def run_both(settings, rows, every: int = 1) -> dict:
    """Run the rows through the reference and the compiled single-vehicle filter; compare after every call
    (every ``every``-th for the slower attributes). Returns what the reference went through."""
    ref, cmp_ = core.HeadingFilter(settings), compiled.CompiledHeadingFilter(settings)
    seen = {"modes": set(), "rejected": 0, "at_rest": 0, "uncertain": 0, "fused": 0, "max_diff": 0.0}
    trace = []  # the reference after each row (_trace_row)
    for i, row in enumerate(rows):
        r1, r2 = _call(ref, row), _call(cmp_, row)
        trace.append(_trace_row(ref, r1))
        assert ref.mode == cmp_.mode, (i, row, ref.mode, cmp_.mode, ref.transitions[-3:], cmp_.transitions[-3:])
        assert bool(r1) == bool(r2), (i, row)
        d = _hd(ref.heading_rad(), cmp_.heading_rad())
        seen["max_diff"] = max(seen["max_diff"], d)
        assert d <= TOL_RAD, (i, d)
        if i % every == 0 or row[0] != IMU:
            s1, s2 = _snapshot(ref, r1), _snapshot(cmp_, r2)
            assert s1[2] == s2[2], (i, s1[2], s2[2])  # flags
            if s1[4] is None or s2[4] is None:
                assert s1[4] is None and s2[4] is None
            else:
                assert abs(s1[4] - s2[4]) <= TOL_RAD
            assert abs(s1[5] - s2[5]) <= TOL_RAD
            assert all(abs(math.remainder(x - y, 2 * math.pi)) <= TOL_RAD for x, y in zip(s1[6], s2[6], strict=False))
            assert np.allclose(s1[7], s2[7], rtol=1e-7, atol=1e-12)
            assert ref.at_rest == cmp_.at_rest and ref.n_rebases == cmp_.n_rebases
            assert abs(ref.mag_delay_s - cmp_.mag_delay_s) <= 1e-9
        seen["modes"].add(ref.mode)
        seen["rejected"] += ref.flags.mag_rejected_gate and row[0] == MAG
        seen["at_rest"] += bool(ref.at_rest)
        seen["uncertain"] += ref.flags.heading_uncertain
        seen["fused"] += bool(r1) and row[0] == MAG
    assert [tr[1:] for tr in ref.transitions] == [tr[1:] for tr in cmp_.transitions]
    assert all(abs(a[0] - b[0]) < 1e-12 for a, b in zip(ref.transitions, cmp_.transitions, strict=False))
    seen["transitions"] = list(ref.transitions)
    seen["mag_delay_s"] = ref.mag_delay_s
    seen["n_rebases"] = ref.n_rebases
    seen["reference"] = ref
    seen["trace"] = trace
    return seen


def _arrays(rows):
    kind = np.array([r[0] for r in rows], np.int8)
    t = np.array([r[1] for r in rows])
    a = np.array([r[2] for r in rows])
    b = np.array([r[3] for r in rows])
    dt = np.array([r[4] for r in rows])
    dmc = np.array([r[5] for r in rows], np.int8)
    return kind, t, a, b, dt, dmc


def run_fleet_rows(fleet, slot, rows):
    """The rows through one slot of a fleet, one step call per stretch between re-bases/resets: per-row
    (heading, mode, mag_fused, return value)."""
    out = []
    i = 0
    while i < len(rows):
        if rows[i][0] == REBASE:
            fleet.rebase_field_reference(slot)
            out.append(None)
            i += 1
            continue
        if rows[i][0] == RESET:
            fleet.reset(slot)
            out.append(None)
            i += 1
            continue
        j = i
        while j < len(rows) and rows[j][0] in (IMU, MAG):
            j += 1
        kind, t, a, b, dt, dmc = _arrays(rows[i:j])
        o = fleet.step(np.full(j - i, slot), kind, t, a, b, dt, dmc)
        out += list(zip(o.heading_rad, o.mode, o.mag_fused, o.mag_return, strict=False))
        i = j
    return out


def reference_trace(settings, rows):
    """The reference filter after each row: (mode, mag_fused, return value, heading)."""
    ref = core.HeadingFilter(settings)
    trace = []
    for row in rows:
        trace.append(_trace_row(ref, _call(ref, row)))
    return trace


def check_fleet_matches_reference(settings, rows, trace=None):
    """The rows through a fleet slot against the reference after each row (``trace``: the reference's from
    :func:`run_both` on the same settings and rows — the reference is deterministic — or run here)."""
    if trace is None:
        trace = reference_trace(settings, rows)
    assert len(trace) == len(rows)
    fleet = compiled.FleetHeading(2)
    slot = fleet.add(settings)
    res = run_fleet_rows(fleet, slot, rows)
    for i in range(len(rows)):
        ref_mode, ref_fused, ret, ref_heading = trace[i]
        if res[i] is None:
            continue
        h, mode, fused, r = res[i]
        assert compiled.MODES[mode] == ref_mode, (i, ref_mode, compiled.MODES[mode])
        assert bool(fused) == ref_fused and bool(r) == ret, i
        assert _hd(h, ref_heading) <= TOL_RAD, i


# ---- data ---------------------------------------------------------------------------------------------------
FIELD_ENU_NT = np.array([-3000.0, 33000.0, -35000.0])
DECL = maths.declination_rad(FIELD_ENU_NT)


def synth_rows(duration_s, rate_hz=100.0, mag_every=2, yaw_rate=0.2, seed=1, extra_field=None, dmc=None,
               mag_shift_rad=None, rest=None, clock=True):
    """A level body turning about up. ``extra_field(t)`` adds to the ENU field; ``dmc(t)`` gives a verdict
    (−1/0/1); ``mag_shift_rad(t)`` turns the measured field about the vertical (a heading offset the field
    checks cannot see); ``rest(t)`` True: the body does not turn then."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * rate_hz)
    rows, heading = [], 0.4
    for i in range(n):
        t = i / rate_hz
        r = 0.0 if (rest is not None and rest(t)) else (yaw_rate(t) if callable(yaw_rate) else yaw_rate)
        gyro = np.array([0.0, 0.0, r]) + rng.normal(0, 0.002, 3)
        acc = np.array([0.0, 0.0, maths.G0]) + rng.normal(0, 0.05, 3)
        rows.append(_row(IMU, t if clock else math.nan, gyro, acc, 0.0 if i == 0 else 1.0 / rate_hz))
        if i % mag_every == 0:
            b = FIELD_ENU_NT + (0.0 if extra_field is None else extra_field(t))
            h = heading + (0.0 if mag_shift_rad is None else mag_shift_rad(t))
            m = maths.body_to_enu(h).T @ b + rng.normal(0, 50.0, 3)
            rows.append(_row(MAG, t if clock else math.nan, m, dmc=-1 if dmc is None else dmc(t)))
        heading -= r / rate_hz
    return rows


def broad_rows(name_prefix: str, start: int, n: int):
    from bench import heading_broad as hb

    path = next(p for p in hb.trial_files() if p.name.startswith(name_prefix))
    tr = hb.load_trial(path)
    g, a, m = tr.gyro_rad_s[start:start + n], tr.accel_m_s2[start:start + n], tr.mag_nt[start:start + n]
    dt = 1.0 / tr.rate_hz
    rows = []
    for i in range(len(g)):
        rows.append(_row(IMU, math.nan, g[i], a[i], 0.0 if i == 0 else dt))
        rows.append(_row(MAG, math.nan, m[i]))
    return rows


def drive_rows(seed: int, layout: str, duration_s: float, dmc_flip_frac: float = 0.0, gap=None, late_every=0,
               rebase_at=None, reset_at=None, dmc_from=None):
    """A simulated car drive (sim_publishers.car): IMU 100 Hz and compass 1 (true calibration) 50 Hz on the
    streams' own time stamps, the DMC verdict from the truth's disturbance flag (some flipped), optionally a
    gap in the streams, magnetometer samples that arrive late (after later IMU samples: levelled with the
    attitude of their own time), a re-base and a reset."""
    from sim_publishers.car.core import simulate

    d = simulate(seed=seed, layout=layout, duration_s=duration_s)
    rng = np.random.default_rng(seed)
    mag = d.true_params["1"].apply(d.mag_b_nt["1"])
    valid = (~d.truth.disturbed).astype(int)
    flip = rng.random(len(valid)) < dmc_flip_frac
    valid[flip] = 1 - valid[flip]
    ti, tm = d.t_imu_s, d.t_mag_s
    keep_i = np.ones(len(ti), bool)
    keep_m = np.ones(len(tm), bool)
    if gap is not None:
        keep_i &= ~((ti >= gap[0]) & (ti < gap[1]))
        keep_m &= ~((tm >= gap[0]) & (tm < gap[1]))
    events = [(ti[i], 0, i) for i in np.flatnonzero(keep_i)]
    for k in np.flatnonzero(keep_m):
        t_arr = tm[k] + (0.035 if late_every and k % late_every == 0 else 0.0)  # the sample waits 35 ms
        events.append((t_arr + 1e-7, 1, k))
    events.sort()
    rows, t_prev, done = [], None, set()
    for t_ev, kind, k in events:
        if rebase_at is not None and t_ev >= rebase_at and "rebase" not in done:
            rows.append(_row(REBASE))
            done.add("rebase")
        if reset_at is not None and t_ev >= reset_at and "reset" not in done:
            rows.append(_row(RESET))
            done.add("reset")
            t_prev = None
        if kind == 0:
            dt = 0.0 if t_prev is None else ti[k] - t_prev
            t_prev = ti[k]
            rows.append(_row(IMU, ti[k], d.gyro_rad_s[k], d.accel_m_s2[k], dt))
        elif t_prev is not None:
            v = valid[k] if dmc_from is None or tm[k] >= dmc_from else -1
            rows.append(_row(MAG, tm[k], mag[k], dmc=v))
    return rows, float(d.declination_rad)


# ---- BROAD --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("prefix,start,n", [("07_", 7000, 5500), ("10_", 9800, 2500), ("30_", 34500, 4500),
                                            ("36_", 9900, 6000)])
def test_broad_excerpts_agree_with_the_reference(prefix, start, n):
    rows = broad_rows(prefix, start, n)
    seen = run_both(profiles.settings(profiles.IMU_ONLY), rows, every=23)
    assert seen["max_diff"] <= TOL_RAD
    if prefix == "07_":
        assert seen["mag_delay_s"] > 0.005  # the online lag estimate ran (and agreed)
    if prefix in ("30_", "36_"):
        assert "gyro_only" in seen["modes"], seen["transitions"]


def test_a_broad_trial_in_one_batch_call_matches_the_reference_replay():
    from bench import heading_broad as hb

    path = next(p for p in hb.trial_files() if p.name.startswith("36_"))
    tr = hb.load_trial(path)
    tr = hb.Trial(tr.name, tr.rate_hz, tr.gyro_rad_s[9000:14000], tr.accel_m_s2[9000:14000], tr.mag_nt[9000:14000],
                  tr.quat_true[9000:14000], tr.movement[9000:14000])
    s = profiles.settings(profiles.IMU_ONLY)
    q_ref, info_ref = hb.run_magmesh(tr, s, impl="reference")
    q_cmp, info_cmp = hb.run_magmesh(tr, s, impl="compiled")
    assert np.max(hb.heading_errors_rad(q_cmp, q_ref)) <= TOL_RAD
    assert info_ref["mode_frac"] == info_cmp["mode_frac"] and info_ref["transitions"] == info_cmp["transitions"]


# ---- simulated drives ---------------------------------------------------------------------------------------
DRIVE_CASES = {
    "road_vehicle": dict(profile="road_vehicle", kw={}, drive=dict(dmc_flip_frac=0.01, late_every=7)),
    "road_vehicle_rebase_gap": dict(profile="road_vehicle", kw={"holds_scale_with_outage": False},
                                    drive=dict(gap=(20.0, 20.6), rebase_at=32.0, dmc_from=5.0)),
    "imu_only": dict(profile="imu_only", kw={}, drive=dict(reset_at=40.0)),
    "everything": dict(profile="road_vehicle",
                       kw=dict(hard_iron_tracking=True, disturbed_noise_gain=20.0, rest_detection=True,
                               gravity_lpf_tau_s=2.0, gravity_lpf_order=2, mag_delay_s=0.01, accel_update_period_s=0.03,
                               mag_update_period_s=0.04, gyro_rate_noise_frac_rt_hz=0.01, mag_vector_fusion=False,
                               use_dmc=True, rejection_timeout_s=1.0, ref_field_nt=0.0),
                       drive=dict(dmc_flip_frac=0.02, late_every=5)),
}


@pytest.mark.parametrize("case", list(DRIVE_CASES))
def test_simulated_drives_agree_with_the_reference(case):
    c = DRIVE_CASES[case]
    rows, decl = drive_rows(3, "urban_a", 60.0, **c["drive"])
    s = profiles.settings(c["profile"], declination_rad=decl, **c["kw"])
    seen = run_both(s, rows, every=9)
    assert len(seen["transitions"]) >= (1 if case == "imu_only" else 2), seen["transitions"]
    if case in ("road_vehicle_rebase_gap", "everything"):
        check_fleet_matches_reference(s, rows, seen["trace"])  # the reference's run above, not a second one


# ---- many slots in one call ---------------------------------------------------------------------------------
def test_interleaved_slots_give_exactly_the_single_slot_results():
    rng = np.random.default_rng(5)
    cases = []
    rows_a, decl = drive_rows(4, "urban_b", 30.0, dmc_flip_frac=0.02, late_every=9)
    cases.append((profiles.settings("road_vehicle", declination_rad=decl), rows_a))
    cases.append((profiles.settings("imu_only"), broad_rows("07_", 0, 4000)))
    cases.append((profiles.settings("road_vehicle", hard_iron_tracking=True, disturbed_noise_gain=10.0,
                                    gravity_lpf_tau_s=1.5),
                  synth_rows(20.0, extra_field=lambda t: np.array([0.0, 4000.0, 0.0]) * (8 < t < 14))))
    cases.append((profiles.settings("imu_only", mag_delay_max_s=0.08), synth_rows(15.0, rate_hz=200.0, mag_every=1)))
    # alone, each in a fleet of its own
    alone = []
    for s, rows in cases:
        fl = compiled.FleetHeading(1)
        k = fl.add(s)
        alone.append(fl.step(np.full(len(rows), k), *_arrays(rows)))
    # together: one fleet (grown from capacity 1, small rings that must grow), rows of the slots interleaved at
    # random, each slot's own rows in order, in one call
    fleet = compiled.FleetHeading(1, window_capacity=4, field_capacity=4)
    slots = [fleet.add(s) for s, _ in cases]
    order = np.concatenate([np.full(len(r), i) for i, (_, r) in enumerate(cases)])
    rng.shuffle(order)
    pos = [0] * len(cases)
    rows_all, idx = [], []
    for c in order:
        rows_all.append(cases[c][1][pos[c]])
        idx.append((c, pos[c]))
        pos[c] += 1
    slot_col = np.array([slots[c] for c, _ in idx])
    out = fleet.step(slot_col, *_arrays(rows_all))
    for c in range(len(cases)):
        sel = np.array([j for j, (cc, _) in enumerate(idx) if cc == c])
        for name in ("heading_rad", "mode", "mag_fused", "mag_return", "heading_std_rad", "quaternion", "reason"):
            a, b = getattr(out, name)[sel], getattr(alone[c], name)
            assert np.array_equal(a, b, equal_nan=True), (c, name)
    # and the single-slot results are the reference's
    check_fleet_matches_reference(*cases[2])


def test_fleet_slots_free_reset_and_accessors():
    fleet = compiled.FleetHeading(2)
    s = core.Settings(declination_rad=DECL, init_duration_s=0.0)
    a, b = fleet.add(s), fleet.add(s)
    rows = synth_rows(3.0)
    fleet.step(np.full(len(rows), a), *_arrays(rows))
    assert fleet.mode(a) == "magnetic" and fleet.mode(b) == "initialising"
    assert fleet.last_transition(a)[1:] == ("initialising", "magnetic", "aligned")
    assert fleet.last_transition(b) is None
    h, p, r = fleet.euler(a)
    assert 0 <= h < 2 * math.pi and fleet.attitude_std(a)[0] > 0
    assert isinstance(fleet.internal_states(a), core.InternalStates) and fleet.flags(a).dmc_valid
    fleet.free(b)
    c = fleet.add(s)  # the freed slot is used again
    assert c == b and fleet.mode(c) == "initialising"
    d = fleet.add(s)  # grows
    assert fleet.capacity >= 3 and fleet.mode(a) == "magnetic"
    with pytest.raises(KeyError):
        fleet.step(np.array([7]), np.array([0]), np.array([0.0]), np.zeros((1, 3)), np.zeros((1, 3)),
                   np.array([0.01]), np.array([-1]))
    fleet.reset(a)
    assert fleet.mode(a) == "initialising" and fleet.mode_changes(a) == 0 and d == 2


# ---- hand-made branch cases ---------------------------------------------------------------------------------
def test_gate_rejection_then_recovery_slew_and_reacquisition():
    # the measured field turns 40° about the vertical at t = 10 s (strength and dip unchanged: only the gate
    # sees it), for good: rejected for rejection_timeout_s → recovering → slew → magnetic again
    s = core.Settings(declination_rad=DECL, rejection_timeout_s=2.0, recovery_hold_s=1.0)
    rows = synth_rows(40.0, mag_shift_rad=lambda t: math.radians(40.0) * (t >= 10.0))
    seen = run_both(s, rows)
    reasons = [tr[3] for tr in seen["transitions"]]
    assert seen["rejected"] > 10
    assert "innovation outside the gate for too long" in reasons
    assert reasons[-1] == "magnetometer consistent and its heading agrees", reasons


@pytest.mark.parametrize("agreement_from_clear", [True, False])
def test_dmc_outage_holds_scaled_and_full_holds_after_a_field_disturbance(agreement_from_clear):
    # a 0.3 s DMC-only blip (scaled holds), then a field disturbance 20–24 s (full holds), then a DMC-invalid
    # stretch with weak fusion of the off-reference field and hard-iron tracking of a body-fixed magnet; the
    # agreement hold counted from the clear hold's start and from recovering's
    def dmc(t):
        return 0 if (5.0 <= t < 5.3 or 27.0 <= t < 28.0) else 1

    def extra(t):
        return np.array([0.0, 6000.0, 2000.0]) if 13.0 <= t < 17.0 else np.zeros(3)

    s = core.Settings(declination_rad=DECL, disturbed_noise_gain=20.0, hard_iron_tracking=True, hard_iron_tau_s=2.0,
                      agreement_from_clear=agreement_from_clear)
    rows = synth_rows(34.0, dmc=dmc, extra_field=extra, yaw_rate=lambda t: 0.3 * math.sin(0.2 * t))
    seen = run_both(s, rows)
    reasons = [tr[3] for tr in seen["transitions"]]
    assert "DMC says invalid" in reasons and "field strength/dip off reference" in reasons
    assert reasons.count("disturbance cleared") >= 2 and seen["uncertain"] == 0


def test_rebase_while_gyro_only_and_heading_uncertain_alarm():
    s = core.Settings(declination_rad=DECL, heading_alarm_std_rad=math.radians(0.5), gyro_noise_rad_s_rt_hz=0.005)
    rows = synth_rows(30.0, dmc=lambda t: 0 if 10.0 <= t < 20.0 else 1)
    i = next(k for k, r in enumerate(rows) if r[1] >= 15.0)
    rows.insert(i, _row(REBASE))
    rows = [_row(REBASE)] + rows  # before alignment: nothing to do
    seen = run_both(s, rows)
    assert seen["uncertain"] > 0 and seen["n_rebases"] >= 1


def test_rest_detection_learns_noise_and_bias():
    s = profiles.settings(profiles.IMU_ONLY, declination_rad=DECL)
    rows = synth_rows(16.0, rate_hz=100.0, mag_every=1, rest=lambda t: 3.0 <= t < 9.0 or t >= 12.0, clock=False)
    seen = run_both(s, rows, every=3)
    assert seen["at_rest"] > 300


def test_lag_estimate_on_a_board_turned_every_way():
    from scipy.spatial.transform import Rotation

    rate = 285.714
    t = np.arange(int(14.0 * rate)) / rate

    def att(tt):
        a = np.column_stack([2.0 * np.sin(0.5 * tt) + 0.5 * np.sin(2.1 * tt), 0.6 * np.sin(0.8 * tt + 1),
                             0.7 * np.sin(0.6 * tt + 2) + 0.3 * np.sin(3.3 * tt)])
        return Rotation.from_euler("ZYX", a)

    h = 1e-5
    rng = np.random.default_rng(3)
    gyro = (att(t - h).inv() * att(t + h)).as_rotvec() / (2 * h) + rng.normal(0, 0.002, (len(t), 3))
    acc = att(t).inv().apply([0.0, 0.0, maths.G0]) + rng.normal(0, 0.05, (len(t), 3))
    mag = att(t - 0.02).inv().apply([100.0, 15800.0, -40800.0]) + rng.normal(0, 700.0, (len(t), 3))
    rows = []
    for i in range(len(t)):
        rows.append(_row(IMU, math.nan, gyro[i], acc[i], 0.0 if i == 0 else 1.0 / rate))
        rows.append(_row(MAG, math.nan, mag[i]))
    seen = run_both(profiles.settings(profiles.IMU_ONLY), rows, every=11)
    assert seen["mag_delay_s"] > 0.005  # the estimate ran: its value is test_heading_lag.py's subject


def test_hard_iron_from_rotation_on_a_board_turned_every_way():
    """A magnet fixed to the board from t = 8 s (6 µT): the field leaves its reference, the magnet is estimated
    from the rotation alone and the field without it steers the heading (imu_only's hard_iron_from_rotation)."""
    from scipy.spatial.transform import Rotation

    rate = 200.0
    t = np.arange(int(30.0 * rate)) / rate

    def att(tt):
        a = np.column_stack([2.0 * np.sin(0.3 * tt) + 0.5 * np.sin(1.7 * tt), 0.5 * np.sin(0.7 * tt + 1),
                             0.6 * np.sin(0.5 * tt + 2) + 0.3 * np.sin(2.3 * tt)])
        return Rotation.from_euler("ZYX", a)

    h = 1e-5
    rng = np.random.default_rng(4)
    magnet = np.array([2000.0, -3000.0, 4800.0])
    gyro = (att(t - h).inv() * att(t + h)).as_rotvec() / (2 * h) + rng.normal(0, 0.002, (len(t), 3))
    acc = att(t).inv().apply([0.0, 0.0, maths.G0]) + rng.normal(0, 0.05, (len(t), 3))
    mag = att(t).inv().apply([100.0, 15800.0, -40800.0]) + np.outer(t >= 8.0, magnet) + rng.normal(0, 300.0, (len(t), 3))
    rows = []
    for i in range(len(t)):
        rows.append(_row(IMU, math.nan, gyro[i], acc[i], 0.0 if i == 0 else 1.0 / rate))
        rows.append(_row(MAG, math.nan, mag[i]))
    s = profiles.settings(profiles.IMU_ONLY, mag_delay_online=False)
    assert s.hard_iron_from_rotation
    seen = run_both(s, rows, every=13)
    assert "gyro_only" in seen["modes"]
    est = seen["reference"]._hi_rot.estimate()
    assert est is not None and np.linalg.norm(est - magnet) < 600.0, est


def test_explicit_align_and_the_service_api():
    f, g = core.HeadingFilter(core.Settings()), compiled.CompiledHeadingFilter(core.Settings())
    for x in (f, g):
        x.align((0.3, -0.2, 9.8), (15000.0, 20000.0, -40000.0))
    assert np.allclose(f.quaternion(), g.quaternion(), atol=1e-15) and f.transitions[0][1:] == g.transitions[0][1:]
    assert g.aligned and g.mode == "magnetic" and g.ref_field_nt == f.ref_field_nt
    assert g.update((0.0, 0.0, 0.1), (0.0, 0.0, 9.8), (15000.0, 20000.0, -40000.0), dt_s=0.01) == f.update(
        (0.0, 0.0, 0.1), (0.0, 0.0, 9.8), (15000.0, 20000.0, -40000.0), dt_s=0.01)
    assert _hd(f.heading_rad(), g.heading_rad()) < 1e-12
    assert np.allclose(f.P, g.P, rtol=1e-12, atol=1e-18) and np.allclose(f.bias, g.bias, atol=1e-15)


def test_the_service_uses_the_compiled_filter_and_the_reference_on_request():
    from services.heading_fuser.service import HeadingFuser, Settings

    svc = HeadingFuser(Settings(), instance="t", vehicles_config={"car-1": {}})
    compiled.warm()
    assert isinstance(svc.make_filter(core.Settings()), compiled.CompiledHeadingFilter)
    svc = HeadingFuser(Settings(compiled=False), instance="t", vehicles_config={"car-1": {}})
    assert type(svc.make_filter(core.Settings())) is core.HeadingFilter


def test_warm_entry_point_and_cache_probe():
    assert compiled.main(["--warm", "--quiet"]) == 0
    assert compiled.kernels_ready()
    assert compiled.main([]) == 2
