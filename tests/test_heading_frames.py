"""The heading fuser on fleet frames (contract v3): the compiled join against its Python reference, and the whole
service fed frames (``on_frame``) against the same frames handed to it sample by sample (``on_message``, the
runtime's per-vehicle fallback), in process with a fake session and a fake wall clock.

The drives are simulated cars (urban layout: bridges, trucks, the car's own loads) with DMC verdicts from the FCM
model, several vehicles in every frame, frames of the three kinds arriving in shifting orders and delays, a
calibration change, a calibration stream that pauses (the clean fallback), a verdict stream that stops (the
wall-clock wait runs out), an IMU gap (a filter restart) and a long spell of invalid verdicts (the heading alarm).
"""

from __future__ import annotations

import math
import time
import tomllib

import msgpack
import numpy as np
import pytest
import zenoh

from magmesh.latch import AlarmLatch
from magmesh.magcal import MagParams
from magmesh.paths import DEPLOY_DIR
from magmesh.runtime import Runner
from schemas import frame, keys, messages
from services.heading_fuser import compiled, fleet
from services.heading_fuser.service import HeadingFuser, Settings

DURATION_S = 60.0
WINDOW_S = 0.02
VEHICLES = ("car-1", "car-2", "car-3")
T_NEW_PARAMS_S = 30.0
NEW_PARAMS_FOR = ("car-1", "car-2")  # cal/params with a 6 % stronger calibrated field (car-1 on cal/mag too)
NO_VERDICTS_S = (20.0, 22.0)  # car-2: the detector sends nothing (the samples wait 1 s of wall time, then go on)
IMU_GAP_S = (45.0, 46.5)  # car-2: no IMU samples (the filter restarts)
CAL_PAUSE_S = (15.0, 25.0)  # car-3: calibration sends nothing (clean/mag with parameters after cal_timeout_s)
INVALID_S = (26.0, 42.0)  # car-3: every verdict invalid (gyro only long enough for the heading alarm)
SETTINGS = dict(heading_alarm_std_rad=0.008)  # a 0.46° alarm threshold: raised and cleared on these drives


# =========================================================================================================
# the join against its reference
# =========================================================================================================
def _random_pushes(rng, n_slots: int, n: int):
    """Interleaved pushes of ``n_slots`` vehicles: IMU at 100 Hz, cal/clean magnetometer at 50 Hz and verdicts,
    with jitter, late and repeated samples, silent spells, gaps, and a wall clock that sometimes jumps."""
    rows = []
    t = np.zeros(n_slots)
    now = 100.0
    for _ in range(n):
        k = int(rng.integers(n_slots))
        now += float(rng.choice([0.0, 0.001, 0.02, 0.6, 1.5], p=[0.5, 0.3, 0.15, 0.04, 0.01]))
        u = rng.random()
        if u < 0.45:
            t[k] += float(rng.choice([0.01, 0.0, -0.01, 1.3], p=[0.9, 0.03, 0.03, 0.04]))
            rows.append((k, fleet.R_IMU, t[k], rng.normal(size=3), rng.normal(size=3), now))
        elif u < 0.75:
            code = fleet.R_CAL if rng.random() < 0.5 else fleet.R_CLEAN
            tm = t[k] + float(rng.choice([0.0, 0.005, 0.03, -0.05, 0.25], p=[0.4, 0.2, 0.2, 0.1, 0.1]))
            rows.append((k, code, tm, rng.normal(size=3) * 2e4, np.zeros(3), now))
        else:
            tv = t[k] + float(rng.choice([0.0, -0.02, 0.02, -3.0], p=[0.5, 0.2, 0.2, 0.1]))
            rows.append((k, fleet.R_DMC, tv, np.array([float(rng.random() < 0.7), rng.random(), 0.0]), np.zeros(3),
                         now))
    return rows


@pytest.mark.parametrize("seed,max_pending,per_call", [(1, fleet.MAX_PENDING, 1), (2, 12, 1), (3, 12, 37),
                                                       (4, 200, 400), (5, 3, 5)])
def test_join_kernel_gives_the_reference_events_and_counts(seed, max_pending, per_call):
    """Same events (kind, time, values, dt, verdict, restart) and counts as the per-sample rule in Python, slot by
    slot, whether rows come one per call or many (rings grown on the way, the event buffer too)."""
    rng = np.random.default_rng(seed)
    n_slots = 5
    cfg = dict(cal_timeout_s=0.3, dmc_timeout_s=2.0, dmc_wait_wall_s=1.0, mag_wait_s=0.2, max_imu_gap_s=1.0)
    j = fleet.FleetJoin(2, max_pending=max_pending, **cfg)
    slots = [j.add() for _ in range(n_slots)]
    refs = [fleet.ReferenceJoin(max_pending=max_pending, **cfg) for _ in range(n_slots)]
    M = np.array([[1.02, 0.01, 0.0], [0.0, 0.98, 0.02], [0.01, 0.0, 1.0]])
    for k in (1, 3, 4):
        j.set_params(slots[k], (100.0, -50.0, 20.0), M)
        refs[k].params = ((100.0, -50.0, 20.0), M.tolist())
    pushes = _random_pushes(rng, n_slots, 6000)
    got: list[list] = [[] for _ in range(n_slots)]
    want: list[list] = [[] for _ in range(n_slots)]
    for i in range(0, len(pushes), per_call):
        chunk = pushes[i:i + per_call]
        now = chunk[-1][5]  # one wall-clock reading per call (a frame's)
        ev = j.push(np.array([slots[p[0]] for p in chunk], np.int64), np.array([p[1] for p in chunk], np.int8),
                    np.array([p[2] for p in chunk]), np.array([p[3] for p in chunk]), np.array([p[4] for p in chunk]),
                    now)
        for r in range(ev.n):
            k = slots.index(int(ev.slot[r]))
            got[k].append((int(ev.kind[r]), float(ev.t_s[r]), tuple(ev.a[r].tolist()), tuple(ev.b[r].tolist()),
                           float(ev.dt_s[r]), int(ev.dmc[r]), int(ev.reset[r]), float(ev.gap_s[r])))
        for k, code, t, v, w, _ in chunk:
            for e in refs[k].push(code, float(t), v.tolist(), w.tolist(), now):
                kind, te, a, b, dt, dmc, reset, gap = e
                want[k].append((kind, float(te), tuple(float(x) for x in a), tuple(float(x) for x in b), dt, dmc,
                                reset, gap))
    for k in range(n_slots):
        assert got[k] == want[k], k
        assert j.counts(slots[k]) == {n: c for n, c in _ref_counts(refs[k]).items() if c}
        assert [p[0] for p in j.pending_mag(slots[k])] == [p[0] for p in refs[k].pending_mag]
        assert j.pending_imu(slots[k]) == len(refs[k].pending_imu)
    total = {}
    for r in refs:
        for n, c in _ref_counts(r).items():
            total[n] = total.get(n, 0) + c
    # the rule's branches were met: samples refused at the door, verdicts waited out, queues full
    assert sum(len(g) for g in got) > 3000, total
    assert total["imu_not_after_previous"] and total["mag_without_verdict"] and total["clean_mag_while_cal_in_use"]
    assert total["clean_mag_without_params"]
    if max_pending < 100:
        assert total["mag_queue_overflow"], total
    assert any(e[6] for g in got for e in g)  # a filter restart


def _ref_counts(r: fleet.ReferenceJoin) -> dict[str, int]:
    out: dict[str, int] = {}
    for c, n in enumerate(r.counts):
        out[fleet.COUNTERS[c]] = out.get(fleet.COUNTERS[c], 0) + n
    return out


def test_join_reports_each_given_up_sample_once_on_its_stream():
    j = fleet.FleetJoin(4, max_pending=3)
    k = j.add()
    push = lambda code, t, now=0.0: j.push(np.array([k]), np.array([code], np.int8), np.array([t]),  # noqa: E731
                                           np.ones((1, 3)), np.ones((1, 3)), now)
    push(fleet.R_CAL, 0.0)  # before any IMU sample
    push(fleet.R_CLEAN, 0.5)  # cal/mag in use
    push(fleet.R_IMU, 1.0)
    push(fleet.R_IMU, 1.0)  # not after the previous one
    push(fleet.R_CLEAN, 3.0)  # no parameters
    push(fleet.R_DMC, 1.0)
    for i in range(5):  # waiting for the IMU: the queue holds 3, the oldest two go
        push(fleet.R_CAL, 2.0 + 0.02 * i)
    slots, counts = j.take_drops()
    assert slots.tolist() == [k]
    got = {fleet.DROPS[c]: int(n) for c, n in enumerate(counts[0]) if n}
    assert got == {("cal", "no IMU sample yet"): 1, ("clean", "calibrated stream cal/mag in use"): 1,
                   ("imu", "IMU sample not after the previous one"): 1,
                   ("clean", "no calibration parameters yet (cal/params or manifest mag_params)"): 1,
                   ("cal", "neither the IMU nor the DMC verdict reached its time"): 2}
    assert j.take_drops()[0].size == 0  # reported once
    assert [p[0] for p in j.pending_mag(k)] == [2.04, 2.06, 2.08]


def test_a_sample_waiting_for_its_verdict_holds_the_imu_back_within_bounds():
    j = fleet.FleetJoin(1, max_pending=5, dmc_wait_wall_s=1.0)
    k = j.add()

    def push(code, t, now):
        ev = j.push(np.array([k]), np.array([code], np.int8), np.array([t]), np.full((1, 3), 7.0), np.ones((1, 3)), now)
        return [(int(ev.kind[i]), round(float(ev.t_s[i]), 3), int(ev.dmc[i])) for i in range(ev.n)]

    assert push(fleet.R_IMU, 0.0, 0.0) == [(0, 0.0, -1)]
    assert push(fleet.R_DMC, 0.0, 0.0) == []
    assert push(fleet.R_CAL, 0.0, 0.0) == [(1, 0.0, 1)]  # its verdict is there
    assert push(fleet.R_IMU, 0.01, 0.0) == []  # ahead of the magnetometer stream: waits (mag_wait_s)
    assert push(fleet.R_CAL, 0.02, 0.0) == [(0, 0.01, -1)]
    assert push(fleet.R_IMU, 0.02, 0.0) == [(0, 0.02, -1)]  # the sample at 0.02 waits for its verdict now
    got = [push(fleet.R_IMU, 0.02 + 0.01 * i, 0.1) for i in range(1, 6)]
    assert got[:4] == [[], [], [], []]  # the IMU waits behind it
    assert got[4] == [(0, 0.03, -1)]  # ... until MAX_PENDING IMU samples wait: then it goes on
    assert j.counts(k) == {"imu_past_waiting_mag": 1}
    assert push(fleet.R_DMC, 0.02, 0.5) == [(1, 0.02, 1)]  # the late verdict: used, levelled at 0.02
    assert push(fleet.R_CAL, 0.04, 0.5) == [(0, 0.04, -1)]  # the IMU up to it; it waits for its verdict
    assert push(fleet.R_IMU, 0.08, 1.49) == []  # still within the wall-clock wait
    # waited 1 s: on without its verdict; the IMU then waits for the magnetometer stream (its queue is full: one goes)
    assert push(fleet.R_IMU, 0.09, 1.5) == [(1, 0.04, -1), (0, 0.05, -1)]
    assert push(fleet.R_CAL, 0.1, 1.5) == [(0, 0.06, -1), (0, 0.07, -1), (0, 0.08, -1), (0, 0.09, -1)]
    assert j.counts(k) == {"imu_past_waiting_mag": 1, "mag_without_verdict": 1}
    assert j.dmc(k) == (True, 7.0, 0.02)


# =========================================================================================================
# the service: frames against samples
# =========================================================================================================
@pytest.fixture(scope="module")
def drives():
    from services.dmc_detector import core as dmc_core
    from services.dmc_detector import fcm
    from sim_publishers.car.core import simulate

    with open(DEPLOY_DIR / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    cfg = {v: car for v in VEHICLES}
    p1 = dmc_core.CompassParams.from_mapping(car["mag_params"]["1"])
    p2 = dmc_core.CompassParams.from_mapping(car["mag_params"]["2"])
    model = fcm.FcmModel.load()
    out = {}
    for i, v in enumerate(VEHICLES):
        d = simulate(duration_s=DURATION_S, layout="urban_a", seed=21 + i)
        feats = dmc_core.features_batch(d.t_mag_s, d.mag_b_nt["1"], d.mag_b_nt["2"], p1, p2, car["declination_rad"])
        valid = np.asarray(model.classify(feats)[0], bool)
        if v == "car-3":
            valid = valid & ~((d.t_mag_s >= INVALID_S[0]) & (d.t_mag_s < INVALID_S[1]))
        out[v] = (d, valid)
    return cfg, out


def _new_params(cfg, vehicle: str) -> dict:
    p = cfg[vehicle]["mag_params"]["1"]
    return dict(sensor="1", param_id="p-new", status="ok", model="3d", method="arls", offset_nt=list(p["offset_nt"]),
                matrix=[1.06 * x for x in p["matrix"]], field_radius_nt=float(p["field_radius_nt"]), rmse_nt=100.0,
                coverage_frac=1.0, n_samples=2000, n_gross_rejected=0, observable=[True, True, True],
                fit_t_s=T_NEW_PARAMS_S, fit_duration_ms=5.0)


def _dmc_cols(valid: np.ndarray) -> dict:
    n = len(valid)
    return {"dm_nt": np.zeros((n, 2)), "ddm_nt_s": np.zeros((n, 2)), "dh_rad": np.zeros(n), "ddh_rad_s": np.zeros(n),
            "heading_rad": np.zeros(n), "stage1_pass": valid.astype(np.uint8),
            "credibility": valid.astype(float), "valid": valid.astype(np.uint8), "impl": "fcm",
            "param_source": ["manifest"] * n}


def _scenario(cfg, drives, seed: int, vehicles=VEHICLES, duration_s: float = DURATION_S):
    """The inputs in arrival order: ("tick",) advances the wall clock by one window, ("put", key, payload)."""
    rng = np.random.default_rng(seed)
    n_win = int(round(duration_s / WINDOW_S))
    base = {v: MagParams.from_message(cfg[v]["mag_params"]["1"]) for v in vehicles}
    new = {v: MagParams.from_message(_new_params(cfg, v)) for v in vehicles}

    # per kind and window: rows of each vehicle (vehicle index, arrays)
    def rows_of(kind: str, w: int) -> dict:
        streams: dict[str, list] = {}
        for vi, v in enumerate(vehicles):
            d, valid = drives[v]
            t_imu, t_mag = d.t_imu_s, d.t_mag_s
            i_imu = np.arange(2 * w, min(2 * w + 2, len(t_imu)))
            i_mag = np.arange(w, min(w + 1, len(t_mag)))
            if v == "car-2":
                i_imu = i_imu[~((t_imu[i_imu] >= IMU_GAP_S[0]) & (t_imu[i_imu] < IMU_GAP_S[1]))]
            if kind == "clean":
                streams.setdefault("imu", []).append((vi, t_imu[i_imu], {"gyro_rad_s": d.gyro_rad_s[i_imu],
                                                                          "accel_m_s2": d.accel_m_s2[i_imu]}))
                for s in ("1", "2"):
                    streams.setdefault(f"mag/{s}", []).append((vi, t_mag[i_mag], {"sensor": s,
                                                                                  "b_nt": d.mag_b_nt[s][i_mag]}))
            elif kind == "cal":
                tm = t_mag[i_mag]
                keep = (tm >= 2.0) if v != "car-2" else np.zeros(len(tm), bool)
                if v == "car-3":
                    keep &= ~((tm >= CAL_PAUSE_S[0]) & (tm < CAL_PAUSE_S[1]))
                i = i_mag[keep]
                if not len(i):
                    continue
                p = new[v] if t_mag[i[0]] >= T_NEW_PARAMS_S and v in NEW_PARAMS_FOR else base[v]
                streams.setdefault("mag/1", []).append((vi, t_mag[i], {
                    "sensor": "1", "b_nt": p.apply(d.mag_b_nt["1"][i]), "calibrated": np.ones(len(i), np.uint8),
                    "param_id": "p-new" if p is new[v] else "manifest"}))
            else:
                tm = t_mag[i_mag]
                keep = np.ones(len(tm), bool)
                if v == "car-2":
                    keep = ~((tm >= NO_VERDICTS_S[0]) & (tm < NO_VERDICTS_S[1]))
                i = i_mag[keep]
                streams.setdefault("dmc", []).append((vi, t_mag[i], _dmc_cols(valid[i])))
        return streams

    seqs: dict[tuple, int] = {}
    fseq = {"clean": 0, "cal": 0, "dmc": 0}
    shard = {"clean": "ingest-1", "cal": "cal-1", "dmc": "dmc-1"}

    def encode(kind: str, w: int) -> bytes | None:
        out = {}
        for name, parts in rows_of(kind, w).items():
            parts = [p for p in parts if len(p[1])]
            if not parts:
                continue
            vi = np.concatenate([np.full(len(p[1]), p[0], np.uint32) for p in parts])
            t = np.concatenate([p[1] for p in parts])
            sq = []
            for p in parts:
                k = (kind, name, p[0])
                s0 = seqs.get(k, 0)
                sq.append(np.arange(s0, s0 + len(p[1])))
                seqs[k] = s0 + len(p[1])
            cols = {}
            for c, v0 in parts[0][2].items():
                if isinstance(v0, str):
                    vals = {p[2][c] for p in parts}
                    cols[c] = v0 if len(vals) == 1 else [p[2][c] for p in parts for _ in range(len(p[1]))]
                elif isinstance(v0, list):
                    cols[c] = [x for p in parts for x in p[2][c]]
                else:
                    cols[c] = np.concatenate([p[2][c] for p in parts])
            out[name] = frame.Stream(name, frame.stream_type(name), vi, t, np.concatenate(sq), cols)
        if not out:
            return None
        fseq[kind] += 1
        return frame.encode(shard[kind], kind, fseq[kind] - 1, list(vehicles), out)

    # delivery: each kind's frames in order, the cal and dmc frames shifted by a delay that changes now and then
    def slots_for(max_delay: int) -> list[int]:
        out, delay, last = [], 0, 0
        for w in range(n_win):
            if rng.random() < 0.05:
                delay = int(rng.integers(0, max_delay + 1))
            last = max(last, w + delay)
            out.append(last)
        return out

    at: dict[int, list] = {}
    for kind, slots in (("clean", list(range(n_win))), ("cal", slots_for(1)), ("dmc", slots_for(3))):
        for w, s in enumerate(slots):
            at.setdefault(s, []).append((kind, w))
    params_slot = int(round(T_NEW_PARAMS_S / WINDOW_S))
    inputs = []
    for s in range(max(at) + 1):
        inputs.append(("tick",))
        if s == params_slot:
            for v in NEW_PARAMS_FOR:
                msg = messages.make("cal_params", v, T_NEW_PARAMS_S, 0, **_new_params(cfg, v))
                inputs.append(("put", keys.cal_params(v, "1"), messages.encode(msg)))
        group = at.get(s, [])
        order = rng.permutation(len(group))  # e.g. a window's verdicts before or after the frame they cover
        by_kind: dict[str, list] = {}
        for i in order.tolist():
            by_kind.setdefault(group[i][0], []).append(group[i][1])
        for kind in [group[i][0] for i in order.tolist()]:
            ws = by_kind.get(kind)
            if not ws:
                continue
            for w in sorted(ws):  # one key's frames stay in order
                p = encode(kind, w)
                if p is not None:
                    inputs.append(("put", keys.fleet_frame(shard[kind], kind), p))
            by_kind[kind] = []
    return inputs


class _Pub:
    def __init__(self, out, key):
        self.out, self.key = out, key

    def put(self, payload):
        self.out.append((self.key, payload))


class _Session:
    def __init__(self):
        self.out = []

    def declare_publisher(self, key, **kw):
        return _Pub(self.out, key)


def _run(cls, cfg, inputs, monkeypatch, frames: bool, instance: str, **settings):
    import time as _time

    clock = [1000.0]
    monkeypatch.setattr(_time, "monotonic", lambda: clock[0])
    svc = cls(Settings(**{**SETTINGS, **settings}), instance=instance, vehicles_config=cfg)
    if not frames:
        svc.on_frame = None  # the runtime hands each vehicle's rows of a frame to on_message, in time order
    sess = _Session()
    r = Runner(svc, sess)
    r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
    svc.on_start()
    for item in inputs:
        if item[0] == "tick":
            clock[0] += WINDOW_S
        else:
            r.handle_sample(item[1], item[2])
    svc.on_tick()  # what the runtime's tick does: the samples given up since the last report are counted
    assert not any("handler_error" in d for d in r.drops.values()), r.last_error
    return svc, r, sess.out


def _outputs(out):
    heading, alarms = {}, []
    for k, p in out:
        if k.startswith("magmesh/fleet/"):
            continue
        m = msgpack.unpackb(p)
        if m["type"] == "heading":
            heading.setdefault(m["vehicle"], []).append(m)
        elif m["type"] == "alarm":
            m.pop("service")
            alarms.append(m)
    return heading, alarms


def _assert_same(a, b):
    ha, aa = _outputs(a)
    hb, ab = _outputs(b)
    assert sorted(ha) == sorted(hb)
    for v in ha:
        x, y = ha[v], hb[v]
        assert [(m["t_s"], m["seq"], m["mode"], m["mag_fused"]) for m in x] == \
               [(m["t_s"], m["seq"], m["mode"], m["mag_fused"]) for m in y], v
        for f in ("heading_rad", "pitch_rad", "roll_rad", "heading_std_rad", "pitch_std_rad", "roll_std_rad",
                  "mag_innovation_rad", "mag_test_ratio"):
            fa = np.array([np.nan if m[f] is None else m[f] for m in x])
            fb = np.array([np.nan if m[f] is None else m[f] for m in y])
            assert np.array_equal(np.isnan(fa), np.isnan(fb)), (v, f)
            d = np.abs(fa - fb)[~np.isnan(fa)]
            if f == "heading_rad":
                d = np.minimum(d, 2 * math.pi - d)
            assert d.size == 0 or d.max() < 1e-9, (v, f, d.max())
    key = lambda m: (m["vehicle"], m["state"], m["t_s"], m.get("raised_t_s"))  # noqa: E731
    assert [key(m) for m in aa] == [key(m) for m in ab]
    for m, n in zip(aa, ab, strict=True):
        assert abs(m["value"] - n["value"]) < 1e-12 and m["reason"] == n["reason"]
    return ha, aa


def test_frames_and_samples_give_the_same_heading_messages(drives, monkeypatch, caplog):
    caplog.set_level("INFO", logger="magmesh")
    cfg, dr = drives
    inputs = _scenario(cfg, dr, seed=7)
    svc_f, r_f, out_f = _run(HeadingFuser, cfg, inputs, monkeypatch, True, "hf-frames")
    svc_s, r_s, out_s = _run(HeadingFuser, cfg, inputs, monkeypatch, False, "hf-samples")
    assert svc_f.filters is not None and all(isinstance(st.filter, fleet.SlotFilter)
                                             for st in svc_f.vehicle_states.values())
    heading, alarms = _assert_same(out_f, out_s)
    # the same samples given up, on the same keys, for the same reasons
    drops = lambda r: {(k, why): n for k, d in r.drops.items() for why, n in d.items() if n}  # noqa: E731
    assert drops(r_f) == drops(r_s)
    for v in VEHICLES:
        a, b = svc_f.vehicle_states[v], svc_s.vehicle_states[v]
        assert svc_f.join.counts(a.slot) == svc_s.join.counts(b.slot)
        assert a.filter.transitions == b.filter.transitions and a.filter.transitions  # stepped in bulk / row by row
    # what the scenario is made of happened
    period = Settings().publish_period_s
    for v in VEHICLES:
        t = np.array([m["t_s"] for m in heading[v]])
        assert len(t) > 0.9 * DURATION_S / period and np.all(np.diff(t) >= period - 1e-9)  # one per period
    modes = {m["mode"] for ms in heading.values() for m in ms}
    assert {"magnetic", "gyro_only", "recovering"} <= modes, modes
    assert [a["state"] for a in alarms if a["vehicle"] == "car-3"][:2] == ["raised", "cleared"], alarms
    st = {v: svc_f.vehicle_states[v] for v in VEHICLES}
    assert st["car-1"].filter.n_rebases >= 1  # car-2's filter restarted since (the IMU gap): its log says it
    assert sum("car-2: new calibration parameters" in r.getMessage() for r in caplog.records) == 2  # both services
    assert st["car-1"].param_source == "cal"
    c2 = svc_f.join.counts(st["car-2"].slot)
    assert c2.get("mag_without_verdict", 0) > 10, c2  # the verdicts that never came: waited for, then counted
    assert c2.get("clean_mag_while_cal_in_use", 0) == 0
    c3 = svc_f.join.counts(st["car-3"].slot)
    assert c3["clean_mag_while_cal_in_use"] < (DURATION_S - 2.0) * 50 - 400  # the pause used clean/mag
    t2 = np.array([m["t_s"] for m in heading["car-2"]])
    assert not ((t2 > IMU_GAP_S[0]) & (t2 < IMU_GAP_S[1])).any()
    assert any(to == "magnetic" and why == "aligned" for t, _, to, why in st["car-2"].filter.transitions
               if t >= IMU_GAP_S[1])  # restarted after the gap
    # the heading follows the truth (the frames are no worse than the samples, and both are right)
    for v in VEHICLES:
        d = dr[v][0]
        t = np.array([m["t_s"] for m in heading[v]])
        h = np.array([m["heading_rad"] for m in heading[v]])
        ok = t > 5.0
        truth = np.interp(t[ok], d.t_mag_s, np.unwrap(d.truth.heading_rad))
        e = np.degrees(np.abs(np.remainder(h[ok] - truth + math.pi, 2 * math.pi) - math.pi))
        assert np.median(e) < 3.0, (v, np.median(e))
    status = svc_f.status_extra()["vehicles"]
    assert status["car-2"]["join"] == c2 and status["car-1"]["field_rebases"] >= 1


def test_frame_path_matches_the_per_sample_service_it_replaces(drives, monkeypatch):
    """The per-sample rules as the service ran them before frames (the Python join, one compiled filter per
    vehicle, ``_step_imu``/``_check_alarm``/``_publish``) on one vehicle's samples in time order: the new
    service's on_message gives the same messages."""
    import time as _time

    cfg, dr = drives
    v = "car-3"
    d, valid = dr[v]
    msgs = []
    for i, t in enumerate(d.t_imu_s.tolist()):
        msgs.append((t, 1, keys.parse(keys.clean_imu(v)), {"type": "imu", "t_s": t, "gyro_rad_s": d.gyro_rad_s[i].tolist(),
                                                           "accel_m_s2": d.accel_m_s2[i].tolist(), "seq": i}))
    for i, t in enumerate(d.t_mag_s.tolist()):
        if CAL_PAUSE_S[0] <= t < CAL_PAUSE_S[1]:
            msgs.append((t, 0, keys.parse(keys.clean_mag(v, "1")), {"type": "mag", "t_s": t, "sensor": "1",
                                                                     "b_nt": d.mag_b_nt["1"][i].tolist(), "seq": i}))
        else:
            b = MagParams.from_message(cfg[v]["mag_params"]["1"]).apply(d.mag_b_nt["1"][i])
            msgs.append((t, 0, keys.parse(keys.cal_mag(v, "1")), {"type": "mag", "t_s": t, "sensor": "1",
                                                                   "b_nt": b.tolist(), "seq": i}))
        if i % 50 != 7 and not 10.0 <= t < 13.0:  # some verdicts never come
            msgs.append((t + 0.015, 2, keys.parse(keys.dmc(v)), {"type": "dmc", "t_s": t, "valid": bool(valid[i]),
                                                                  "credibility": float(valid[i]), "seq": i}))
    msgs.sort(key=lambda m: (m[0], m[1]))
    clock = [0.0]
    monkeypatch.setattr(_time, "monotonic", lambda: clock[0])
    s = Settings(**SETTINGS)
    svc = HeadingFuser(s, instance="t", vehicles_config=cfg)
    out, alarms = [], []
    svc.publish = lambda key, typ, veh, t, **f: out.append((t, f))
    svc.alarm = lambda veh, src, state, sev, reason, value, thr, t, **k: alarms.append((state, t, value, reason))
    svc.count_drop = lambda *a, **k: None
    st = svc.new_vehicle(v)
    assert isinstance(st.filter, fleet.SlotFilter)
    for tw, _, info, msg in msgs:
        clock[0] = tw * 0.9  # the wall clock a little slower than the drive: some verdict waits run out
        svc.on_message(info, msg, st)
    old_out, old_alarms = _old_service(svc, v, msgs, clock)
    assert [(t, f["mode"], f["mag_fused"]) for t, f in out] == [(t, f["mode"], f["mag_fused"]) for t, f in old_out]
    for f in ("heading_rad", "heading_std_rad", "pitch_rad", "roll_rad"):
        a = np.array([x[f] for _, x in out])
        b = np.array([x[f] for _, x in old_out])
        assert np.max(np.abs(a - b)) < 1e-9, f
    assert alarms == old_alarms and [a[0] for a in alarms][:2] == ["raised", "cleared"]
    assert svc.join.counts(st.slot).get("mag_without_verdict", 0) > 0
    assert [tr[1:] for tr in st.filter.transitions] == [tr[1:] for tr in _OLD_TRANSITIONS[-len(st.filter.transitions):]]


_OLD_TRANSITIONS: list = []


def _old_service(svc: HeadingFuser, v: str, msgs, clock):
    """The service's rules before fleet frames: ReferenceJoin + CompiledHeadingFilter + _step_imu's outputs, the
    alarm by the project's latch (magmesh/latch.py: the compiled join's rule is held to it here)."""
    s = svc.settings
    f = compiled.CompiledHeadingFilter(svc.core_settings(v))
    j = fleet.ReferenceJoin(s.cal_timeout_s, s.dmc_timeout_s, s.dmc_wait_wall_s, s.mag_wait_s, s.max_imu_gap_s)
    p = MagParams.from_message(svc.vehicles_config[v]["mag_params"]["1"])
    j.params = (p.offset.tolist(), p.M.tolist())
    out, alarms = [], []
    latch, last_pub = AlarmLatch(0.0, 0.0), -math.inf  # the project's latch: at once both ways
    for tw, _, info, msg in msgs:
        clock[0] = tw * 0.9
        if info.kind == "clean" and info.stream == "imu":
            code, val, w = fleet.R_IMU, msg["gyro_rad_s"], msg["accel_m_s2"]
        elif info.kind == "dmc":
            code, val, w = fleet.R_DMC, (1.0 if msg["valid"] else 0.0, msg["credibility"], 0.0), (0.0, 0.0, 0.0)
        else:
            code, val, w = (fleet.R_CAL if info.kind == "cal" else fleet.R_CLEAN), msg["b_nt"], (0.0, 0.0, 0.0)
        for kind, t, a, b, dt, dmc, reset, _ in j.push(code, msg["t_s"], val, w, clock[0]):
            if kind == fleet.E_MAG:
                f.update_mag(a, None if dmc < 0 else bool(dmc), t_s=t)
                continue
            if reset:
                f.reset()
            f.update_imu(a, b, dt, t_s=t)
            if not f.aligned:
                continue
            h_std = f.internal_states.heading_std_rad
            change = latch.update(t, f.mode == "magnetic" or h_std < s.alarm_clear_frac * s.heading_alarm_std_rad,
                                  f.flags.heading_uncertain)
            if change == "raised":
                alarms.append(("raised", t, h_std, f"heading uncertainty {math.degrees(h_std):.1f}° after "
                               f"{f.internal_states.time_since_mag_fused_s:.0f} s without a usable magnetometer "
                               f"(mode {f.mode})"))
            elif change == "cleared":
                alarms.append(("cleared", t, h_std, f"heading uncertainty back to {math.degrees(h_std):.1f}° "
                               f"(mode {f.mode})"))
            if t - last_pub >= s.publish_period_s - 1e-9:
                last_pub = t
                hd, pt, rl = f.euler()
                hs, ps, rs = f.attitude_std()
                out.append((t, {"heading_rad": hd, "pitch_rad": pt, "roll_rad": rl, "heading_std_rad": hs,
                                "pitch_std_rad": ps, "roll_std_rad": rs, "mode": f.mode,
                                "mag_fused": f.flags.mag_fused}))
    _OLD_TRANSITIONS[:] = f.transitions
    return out, alarms


@pytest.mark.parametrize("impl", ["reference", "vqf"])
def test_vehicles_with_a_filter_of_their_own_take_frames_too(drives, monkeypatch, impl):
    """The reference filter (``compiled = false``) and VQF keep a filter per vehicle, stepped row by row from the
    same join: frames and samples agree for them as well."""
    cfg, dr = drives
    inputs = _scenario(cfg, dr, seed=3, vehicles=("car-1", "car-3"), duration_s=12.0)
    if impl == "vqf":
        pytest.importorskip("vqf")
        from services.heading_fuser.vqf_impl import VqfHeadingFuser as cls

        extra = {}
    else:
        cls, extra = HeadingFuser, {"compiled": False}
    svc_f, _, out_f = _run(cls, cfg, inputs, monkeypatch, True, "own-f", **extra)
    _, _, out_s = _run(cls, cfg, inputs, monkeypatch, False, "own-s", **extra)
    assert svc_f.filters is None and svc_f.on_frame is not None
    heading, _ = _assert_same(out_f, out_s)
    assert min(len(h) for h in heading.values()) > 0.8 * 12.0 / Settings().publish_period_s


def test_bench_row_runs_small():
    from bench import cores_bench

    r = cores_bench.heading_service(vehicles=3, windows=60, repeats=1)
    assert r["vehicles"] == 3 and r["input_samples"] > 0 and r["us_per_input_sample"] > 0
    assert r["heading_messages"] > 0


# =========================================================================================================
# a real mesh on frames
# =========================================================================================================
@pytest.mark.mesh
@pytest.mark.slow
def test_heading_on_frames_in_a_mesh(tmp_path):
    """Car simulator → ingest (``output = frames``) → DMC detector (FCM) and calibration → heading fuser over a
    router on loopback: the fuser takes the clean, cal and dmc frames and publishes its usual messages (gap-free
    seqs, gyro only at the bridge and back, close to the truth). ~40 s here."""
    from meshutil import Collector, free_port, open_router, query_status, spawn, stop, wait_alive
    from test_heading_mesh import _manifest

    port = free_port()
    router = open_router(port)
    heading = Collector(router, keys.heading("car-1"))
    pose = Collector(router, keys.truth("car-1", "pose"))
    duration = 120.0
    manifest = _manifest(tmp_path)
    procs = []
    try:
        procs.append(spawn("services.ingest", port, "--instance", "ingest-hf", "--set", "output=frames",
                           log_path=tmp_path / "ingest.log"))
        procs.append(spawn("services.dmc_detector", port, "--impl", "fcm", "--instance", "dmc-hf", "--manifest",
                           manifest, log_path=tmp_path / "dmc.log"))
        procs.append(spawn("services.calibration", port, "--instance", "cal-hf", "--manifest", manifest,
                           log_path=tmp_path / "cal.log"))
        procs.append(spawn("services.heading_fuser", port, "--instance", "heading-hf", "--manifest", manifest,
                           log_path=tmp_path / "heading.log"))
        for role, inst in (("ingest", "ingest-hf"), ("dmc_detector", "dmc-hf"), ("calibration", "cal-hf"),
                           ("heading_fuser", "heading-hf")):
            assert wait_alive(router, keys.svc_token(role, inst)), (tmp_path / "heading.log").read_text()[-3000:]
        procs.append(spawn("sim_publishers.car", port, "--vehicle", "car-1", "--instance", "sim-hf", "--set",
                           "speed=5", "--set", f"duration_s={duration}", "--set", "layout=urban_a",
                           log_path=tmp_path / "sim.log"))
        deadline = time.monotonic() + 240.0
        while time.monotonic() < deadline:
            got = heading.matching(lambda k, m: True)
            if got and got[-1][1]["t_s"] >= duration - 0.5:
                break
            for p in procs:
                assert p.poll() is None, (tmp_path / "heading.log").read_text()[-3000:]
            time.sleep(0.5)
        time.sleep(0.5)
        st = query_status(router, keys.svc_status("heading_fuser", "heading-hf"))
    finally:
        for p in reversed(procs):
            stop(p)
        router.close()
    log = (tmp_path / "heading.log").read_text()
    # frames every 20 ms of wall time (24 s at 5x) of three kinds: the inputs came as frames
    assert st is not None and st["frames_in"] > 0.5 * duration / 5 / 0.02, (st and st["frames_in"], log[-2000:])
    msgs = [m for _, m in heading.items]
    assert msgs and msgs[-1]["t_s"] >= duration - 0.5, (len(msgs), log[-2000:])
    assert [m["seq"] for m in msgs] == list(range(len(msgs)))
    modes = [m["mode"] for m in msgs]
    assert "gyro_only" in modes and "magnetic" in modes[modes.index("gyro_only"):], "the bridge, and back"
    tt = np.array([m["t_s"] for _, m in pose.items])
    th = np.unwrap([m["heading_rad"] for _, m in pose.items])
    t_h = np.array([m["t_s"] for m in msgs])
    inside = (t_h >= tt[0]) & (t_h <= tt[-1])
    est = np.array([m["heading_rad"] for m in msgs])[inside]
    errs = np.degrees(np.abs(np.remainder(est - np.interp(t_h[inside], tt, th) + math.pi, 2 * math.pi) - math.pi))
    assert inside.sum() > 0.9 * duration * 10
    assert float(np.sqrt(np.mean(errs**2))) < 3.0
    vst = st["vehicles"]["car-1"]
    assert vst["param_source"] in ("manifest", "cal") and vst["waiting"]["mag"] < 50
