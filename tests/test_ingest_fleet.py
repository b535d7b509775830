"""Ingest's per-sample rules over a fleet window (services/ingest/fleet.py) against the per-sample path.

The reference is the service's own ``Ingest.on_message`` (its code, run on a host object without Zenoh, its
receive clock replaced by each row's ``now``): every row must get the same decision and, when refused, the same
code, field and sentence, and every stream the same :class:`StreamState` afterwards, field by field. The pure
:func:`services.ingest.fleet.reference_step` (the bench's reference) is held to the same.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hst

import services.ingest.service as ingest_service
from schemas import keys, make
from services.ingest import fleet
from services.ingest.core import IngestSettings, StreamState, VehicleState
from services.ingest.fleet import (
    ACCEPTED,
    ACCEPTED_REBASE,
    KIND_CODE,
    KINDS,
    REFUSED_AHEAD,
    REFUSED_BACKWARDS,
    REFUSED_DUPLICATE,
    REFUSED_JUMP,
    REFUSED_RANGE,
    REFUSED_SEQS_MAX,
    FleetStreams,
    range_ok_mask,
    reference_step,
)
from services.ingest.service import Ingest

S = IngestSettings()

# ---- messages -------------------------------------------------------------------------------------------------

GOOD = {
    "mag": dict(b_nt=[2.0e4, 1.0e3, -4.0e4]),
    "imu": dict(gyro_rad_s=[0.01, 0.0, 0.0], accel_m_s2=[0.0, 0.1, 9.8]),
    "gnss": dict(lat_deg=32.0, lon_deg=118.8, alt_m=10.0, pos_enu_m=[5.0, 6.0, 0.0], vel_enu_m_s=[1.0, 0.0, 0.0],
                 course_rad=1.57, speed_m_s=1.0, fix_type="3d", num_sats=10, pdop=1.5),
    "ins": dict(pos_enu_m=[100.0, 20.0, 0.0], vel_enu_m_s=[1.0, 0.5, 0.0], heading_rad=0.3),
    "route": dict(a_enu_m=[0.0, 0.0, 0.0], b_enu_m=[500.0, 10.0, 0.0], route_id="leg-1"),
    "attitude": dict(heading_rad=0.5, pitch_rad=0.01, roll_rad=-0.02, mag_heading_rad=0.49),
}
#: values beyond a physical range, per kind (attitude has none: only t_s < 0)
BAD = {
    "mag": [dict(b_nt=[3.0e6, 0.0, 0.0])],
    "imu": [dict(gyro_rad_s=[100.0, 0.0, 0.0]), dict(accel_m_s2=[0.0, 0.0, 1.0e4])],
    "gnss": [dict(alt_m=1.0e6), dict(speed_m_s=1000.0), dict(pdop=500.0), dict(pos_enu_m=[2.0e7, 0.0, 0.0]),
             dict(vel_enu_m_s=[700.0, 0.0, 0.0])],
    "ins": [dict(pos_enu_m=[0.0, -2.0e7, 0.0]), dict(vel_enu_m_s=[0.0, 0.0, 2.0e7])],
    "route": [dict(b_enu_m=[2.0e7, 0.0, 0.0])],
    "attitude": [],
}
#: the columns range_ok is computed from, per kind
COLS = {"mag": ("b_nt",), "imu": ("gyro_rad_s", "accel_m_s2"),
        "gnss": ("alt_m", "speed_m_s", "vel_enu_m_s", "pdop", "pos_enu_m"), "ins": ("pos_enu_m", "vel_enu_m_s"),
        "route": ("a_enu_m", "b_enu_m"), "attitude": ()}


def _key(vehicle: str, kind: str, sensor: str = "1") -> str:
    return keys.raw_mag(vehicle, sensor) if kind == "mag" else getattr(keys, f"raw_{kind}")(vehicle)


def _msg(key: str, kind: str, t: float, seq: int, fault: str | None = None, rng=None) -> dict:
    f = dict(GOOD[kind])
    if kind == "mag":
        f["sensor"] = key.rsplit("/", 1)[-1]
    if fault == "range" and BAD[kind]:
        f.update(BAD[kind][int(rng.integers(len(BAD[kind])))])
    if fault == "sensor":
        f["sensor"] = "other"
    return make(kind, key.split("/")[1], t, seq, **f)


# ---- the two paths -------------------------------------------------------------------------------------------


class _Host:
    """Runs ``Ingest.on_message`` and ``Ingest.time_refusal`` themselves, recording what they do."""

    on_message = Ingest.on_message
    time_refusal = Ingest.time_refusal
    frame_output = False  # single samples decided one by one (the path the kernel must agree with)
    batch_output = False

    def __init__(self, settings: IngestSettings):
        self.settings = settings
        self.log = logging.getLogger("test_ingest_fleet")
        self._rt = SimpleNamespace(count_rebase=self._rebased)
        self.vehicles: dict[str, VehicleState] = {}
        self.events: list = []

    def _rebased(self, what: str) -> None:
        assert what == "clock"
        self.events.append("rebase")

    def reject(self, key, code, reason, field, payload_len, vehicle=None, t_s=None, input_type=None):
        self.events.append(("refused", code, field, reason))

    def emit(self, info, msg):
        self.events.append("accepted")

    def stream(self, key: str) -> StreamState:
        return self.vehicles[key.split("/")[1]].streams[key]

    def run(self, key: str, msg: dict, now: float, monkeypatch) -> tuple:
        """One sample; (accepted, rebased, (code, field, reason) | None)."""
        self.events = []
        monkeypatch.setattr(ingest_service, "time", SimpleNamespace(monotonic=lambda: now))
        vs = self.vehicles.setdefault(msg["vehicle"], VehicleState())
        self.on_message(keys.parse(key), msg, vs)
        refused = [e[1:] for e in self.events if isinstance(e, tuple)]
        assert len(refused) <= 1
        return "accepted" in self.events, "rebase" in self.events, refused[0] if refused else None


def _range_ok(rows: list[tuple], settings: IngestSettings) -> np.ndarray:
    """range_ok as a window's caller computes it: on columns per kind (limit_masks, t_s ≥ 0), plus the
    magnetometer's sensor against its key."""
    ok = np.ones(len(rows), bool)
    by_kind: dict[str, list[int]] = {}
    for i, (_, msg, _) in enumerate(rows):
        by_kind.setdefault(msg["type"], []).append(i)
    for kind, idx in by_kind.items():
        ms = [rows[i][1] for i in idx]
        cols = {c: np.array([m[c] for m in ms], float) for c in COLS[kind]}
        good = range_ok_mask(kind, np.array([m["t_s"] for m in ms]), cols, settings)
        if kind == "mag":
            good &= np.array([m["sensor"] == rows[i][0].rsplit("/", 1)[-1] for i, m in zip(idx, ms, strict=True)])
        ok[idx] = good
    return ok


def _compare(rows: list[tuple], settings: IngestSettings, monkeypatch, splits: list[int] | None = None,
             fs: FleetStreams | None = None, slots: dict | None = None, host: _Host | None = None) -> dict:
    """Run ``rows`` ((key, msg, now) in arrival order) through the service's on_message, reference_step and the
    kernel (in calls split at ``splits``); assert they agree row by row and stream by stream after every call."""
    fs = FleetStreams(settings, capacity=4) if fs is None else fs
    slots = {} if slots is None else slots
    host = _Host(settings) if host is None else host
    pure = {k: copy.deepcopy(host.stream(k)) for k in slots}  # reference_step's own copies
    n = len(rows)
    bounds = [0, *sorted(set(splits or [])), n]
    counts = dict.fromkeys(fleet.CODE_NAMES, 0)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if a == b:
            continue
        part = rows[a:b]
        for key, _, _ in part:
            if key not in slots:
                slots[key] = fs.add()
        d = fs.decide(np.array([slots[k] for k, _, _ in part]), np.array([KIND_CODE[m["type"]] for _, m, _ in part]),
                      np.array([m["t_s"] for _, m, _ in part]), np.array([m["seq"] for _, m, _ in part]),
                      _range_ok(part, settings), np.array([now for _, _, now in part]))
        for j, (key, msg, now) in enumerate(part):
            accepted, rebased, rej = host.run(key, msg, now, monkeypatch)
            c = int(d.code[j])
            counts[fleet.CODE_NAMES[c]] += 1
            where = f"row {a + j} ({key}, t_s = {msg['t_s']!r}, seq {msg['seq']}, now {now!r})"
            assert (c <= ACCEPTED_REBASE) == accepted, f"{where}: kernel {fleet.CODE_NAMES[c]}, service {rej}"
            assert (c == ACCEPTED_REBASE) == rebased, where
            if rej is not None:
                r = fs.rejection(d, j, key, msg)
                assert (r.code, r.field, r.reason) == rej, where
            st = pure.setdefault(key, StreamState())
            rc, rr = reference_step(msg, st, settings, key, now)
            assert rc == c, f"{where}: reference_step {fleet.CODE_NAMES[rc]}, kernel {fleet.CODE_NAMES[c]}"
            assert (rr is None) == (rej is None) and (rr is None or (rr.code, rr.field, rr.reason) == rej), where
        for key, slot in slots.items():
            got, want = fs.get(slot), host.stream(key)
            assert got == want, f"after rows {a}..{b - 1}, {key}:\nkernel  {got}\nservice {want}"
            assert pure[key] == want, key
    return counts


# ---- generated fleets ------------------------------------------------------------------------------------------

FAULTS = ("dup", "back", "jump", "hour_ahead", "restart_back", "restart_ahead", "range", "neg_t", "sensor",
          "seq_gap", "seq_jump", "seq_back", "foreign", "dup_seq")


def _stream_rows(rng, key: str, kind: str, n: int) -> list[tuple]:
    """One stream's rows (key, msg, arrival time) in order: a pace (real time, replay at 10×, as fast as
    possible, a slow stream arriving bunched) with faults at random rows."""
    pace = rng.choice(["realtime", "x10", "afap", "bunched"])
    step_s = 20.0 if pace == "bunched" else float(rng.choice([0.005, 0.01, 0.02, 0.1, 1.0]))
    wall_per_t = {"realtime": 1.0, "x10": 0.1, "afap": 0.0, "bunched": 0.05}[pace]
    p_fault = float(rng.choice([0.0, 0.05, 0.2, 0.4]))
    t_base = float(rng.choice([0.0, rng.uniform(0, 1e3), rng.uniform(0, 1e6)]))
    arrival = float(rng.uniform(0, 2.0))
    seq = int(rng.integers(0, 1000))
    rows = []
    k = 0  # samples of the normal timeline so far
    prev_t = t_base
    for _ in range(n):
        t = t_base + k * step_s
        fault = rng.choice(FAULTS) if rng.random() < p_fault else None
        if fault == "sensor" and kind != "mag":
            fault = "range"
        msg_seq = seq
        advance = True
        if fault == "dup":
            t, advance = prev_t, False
        elif fault == "dup_seq":  # a repeated sample, seq and all
            t, msg_seq, advance = prev_t, max(seq - 1, 0), False
        elif fault == "back":
            t, advance = prev_t - float(rng.uniform(0.001, 5.0)), False
        elif fault == "jump":
            t, advance = prev_t + 3600.0 + float(rng.uniform(1.0, 1000.0)), False
        elif fault == "hour_ahead":
            t, advance = prev_t + 3500.0, False
        elif fault in ("restart_back", "restart_ahead"):  # the source's clock moves for good
            shift = float(rng.uniform(50.0, 3000.0))
            t_base += -shift if fault == "restart_back" else shift
            t = t_base + k * step_s
        elif fault == "neg_t":
            t, advance = -float(rng.uniform(0.0, 10.0)), False
        elif fault == "seq_gap":
            seq += int(rng.integers(1, 6))
            msg_seq = seq
        elif fault == "seq_jump":
            seq += 20_000
            msg_seq = seq
        elif fault == "seq_back":
            seq = int(rng.integers(0, 5))
            msg_seq = seq
        elif fault == "foreign":  # another publisher on the key: its own seq, dated in the past
            t, msg_seq, advance = prev_t - float(rng.uniform(1.0, 100.0)), int(rng.integers(0, 10**6)), False
        rows.append((key, _msg(key, kind, t, msg_seq, fault, rng), arrival))
        if fault != "foreign" and fault != "dup_seq":
            seq += 1
        if advance:
            k += 1
            prev_t = t
        if pace == "afap":
            arrival += float(rng.uniform(1e-6, 1e-4))
        elif pace == "bunched":
            arrival += 0.04 if rng.random() < 0.4 else float(rng.uniform(0.8, 1.2))
        else:
            arrival += step_s * wall_per_t * float(rng.uniform(0.5, 1.5))
    return rows


def _fleet_rows(rng, vehicles: int, per_stream: tuple[int, int]) -> list[tuple]:
    """Every vehicle's streams, interleaved by arrival time (each stream's own order kept); now = arrival."""
    streams = []
    for v in range(vehicles):
        vid = f"car-{v}"
        for kind in rng.choice(KINDS, size=int(rng.integers(1, 4)), replace=False):
            sensors = ("1", "2") if kind == "mag" else ("1",)
            for s in sensors:
                streams.append(_stream_rows(rng, _key(vid, str(kind), s), str(kind),
                                            int(rng.integers(*per_stream))))
    flat = [(arr, j, i, key, msg) for i, rows in enumerate(streams) for j, (key, msg, arr) in enumerate(rows)]
    order = sorted(range(len(flat)), key=lambda q: (flat[q][0], flat[q][1], flat[q][2]))
    return [(flat[q][3], flat[q][4], flat[q][0]) for q in order]


@pytest.mark.parametrize("seed", range(6))
def test_kernel_decides_a_fleet_as_the_service_does(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    rows = _fleet_rows(rng, vehicles=12, per_stream=(20, 150))
    splits = np.cumsum(rng.integers(1, 400, size=len(rows))).tolist()  # calls of 1..400 rows, state carried
    counts = _compare(rows, S, monkeypatch, [s for s in splits if s < len(rows)])
    assert counts["accepted"] > len(rows) // 3, counts


def test_every_decision_is_reached_across_the_generated_fleets(monkeypatch):
    counts = dict.fromkeys(fleet.CODE_NAMES, 0)
    for seed in (101, 102):
        rng = np.random.default_rng(seed)
        for k, v in _compare(_fleet_rows(rng, vehicles=10, per_stream=(20, 120)), S, monkeypatch,
                             list(range(97, 10_000, 97))).items():
            counts[k] += v
    assert min(counts.values()) > 0, counts


@pytest.mark.parametrize("seed,settings", [
    (7, IngestSettings(rebase_after=3, seq_jump_max=50)),
    (8, IngestSettings(rebase_after=2.5, max_ahead_s={"mag": 1.0, "imu": 0.5, "gnss": 5.0}, max_clock_rate=20)),
    (9, IngestSettings(max_time_jump_s=100, seq_jump_max=3.5, max_ahead_s={"route": 30.0, "attitude": 2.0})),
])
def test_kernel_follows_the_settings(seed, settings, monkeypatch):
    rng = np.random.default_rng(seed)
    rows = _fleet_rows(rng, vehicles=8, per_stream=(20, 120))
    _compare(rows, settings, monkeypatch, list(range(50, len(rows), 173)))


def test_500_slots_four_samples_each_per_call(monkeypatch):
    """The fleet window's shape: 500 streams, 4 samples each per call, many calls."""
    rng = np.random.default_rng(21)
    kinds = [KINDS[i % 4] for i in range(500)]
    ks = [_key(f"bus-{i}", kinds[i]) for i in range(500)]
    rows = []
    for w in range(6):  # 20 ms windows; in each, the streams' samples interleaved
        for j in range(4):
            for i in range(500):
                t = 100.0 + 0.005 * (4 * w + j) + (i % 7)
                fault = "range" if rng.random() < 0.01 else None
                if rng.random() < 0.02:
                    t += float(rng.choice([-0.004, -0.005, 3500.0]))
                rows.append((ks[i], _msg(ks[i], kinds[i], t, 4 * w + j, fault, rng), 5.0 + 0.02 * w + 1e-5 * j))
    _compare(rows, S, monkeypatch, list(range(2000, len(rows), 2000)))


def test_refused_seqs_beyond_the_cap_and_the_arena_growing(monkeypatch):
    """1,500 refused samples between two accepted ones (the set keeps 1,024), on 3 streams at once."""
    rows = []
    ks = [_key("car-1", "imu"), _key("car-2", "imu"), _key("car-3", "gnss")]
    for k in ks:
        rows.append((k, _msg(k, k.rsplit("/", 1)[-1], 10.0, 0), 1.0))
    for j in range(1500):
        for k in ks:
            # duplicates with fresh seqs, some repeated (a set: counted once)
            rows.append((k, _msg(k, k.rsplit("/", 1)[-1], 10.0, 1 + (j if j % 5 else j // 2)), 1.0 + 1e-4 * j))
    for i, k in enumerate(ks):
        rows.append((k, _msg(k, k.rsplit("/", 1)[-1], 10.5, 3000 + i), 1.2))
        rows.append((k, _msg(k, k.rsplit("/", 1)[-1], 10.6, 3005 + i), 1.3))
    fs = FleetStreams(S, capacity=2)
    _compare(rows, S, monkeypatch, [1, 2000, 4000], fs=fs)
    assert fs.ref_seq.shape[0] >= 3 * REFUSED_SEQS_MAX  # the arena grew from 256 nodes


def test_state_set_mid_stream_then_carried_on(monkeypatch):
    """A slot set from the service's StreamState half way (restarted kernel state) decides the rest alike."""
    rng = np.random.default_rng(31)
    rows = _fleet_rows(rng, vehicles=5, per_stream=(40, 100))
    half = len(rows) // 2
    host = _Host(S)
    _compare(rows[:half], S, monkeypatch, host=host)
    fs = FleetStreams(S, capacity=3)
    slots = {}
    for vs in host.vehicles.values():
        for key, st in vs.streams.items():
            slots[key] = fs.add()
            fs.set(slots[key], st)
            assert fs.get(slots[key]) == st
    _compare(rows[half:], S, monkeypatch, [37, 301], fs=fs, slots=slots, host=host)


# ---- short adversarial sequences (hypothesis) ------------------------------------------------------------------

_DT = [0.0, -0.01, -1.0, 0.01, 0.02, 0.5, 2.0, 20.0, 59.0, 3500.0, 3700.0, -3000.0, 1e-9]
_DSEQ = [1, 1, 1, 0, 2, 5, -1, -3, 20_000, 10**9]
_DNOW = [0.0, 1e-5, 0.01, 0.3, 1.0, 1.2, 30.0, -0.2]  # a receive clock that steps back: never here, still alike


@settings(max_examples=120, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(hst.lists(hst.tuples(hst.integers(0, 2), hst.sampled_from(_DT), hst.sampled_from(_DSEQ),
                            hst.sampled_from(_DNOW), hst.booleans()), min_size=1, max_size=60),
       hst.integers(1, 20))
def test_short_adversarial_sequences(steps, split):
    s = IngestSettings(rebase_after=3, seq_jump_max=100)
    ks = [_key("car-1", "mag"), _key("car-1", "gnss"), _key("car-2", "imu")]
    t = [10.0, 10.0, 10.0]
    q = [5, 5, 5]
    now = 100.0
    rows = []
    for which, dt, dseq, dnow, bad in steps:
        k = ks[which]
        t[which] = max(t[which] + dt, 0.0)
        q[which] = max(q[which] + dseq, 0)
        now += dnow
        rows.append((k, _msg(k, "mag" if which == 0 else ("gnss" if which == 1 else "imu"), t[which], q[which],
                              "range" if bad else None, np.random.default_rng(0)), now))
    with pytest.MonkeyPatch.context() as mp:
        _compare(rows, s, mp, list(range(split, len(rows), split)))


# ---- the slots themselves ----------------------------------------------------------------------------------------


def test_a_slot_holds_every_field_of_stream_state():
    assert {f.name for f in dataclasses.fields(StreamState)} == set(fleet.STATE_FIELDS)
    fs = FleetStreams(S, capacity=1)
    assert fs.get(fs.add()) == StreamState()


def test_set_and_get_round_trip_and_free_and_reuse():
    rng = np.random.default_rng(5)
    fs = FleetStreams(S, capacity=2)
    slots = [fs.add() for _ in range(5)]  # capacity doubles
    assert fs.capacity >= 5 and len(fs) == 5
    states = []
    for slot in slots:
        st = StreamState(last_t_s=float(rng.uniform(0, 100)), last_seq=int(rng.integers(0, 10**12)),
                         accepted=int(rng.integers(0, 1000)), upstream_gaps=3, seq_rebases=1,
                         last_wall=float(rng.uniform(0, 5)), rate=2.5, rate_learned=True, win_t_s=1.0,
                         win_wall=0.5, contra_n=2, contra_last_t_s=7.0, clock_rebases=4,
                         refused_seqs={int(x) for x in rng.integers(0, 10**6, size=int(rng.integers(0, 400)))},
                         step_s=0.02)
        fs.set(slot, st)
        states.append(st)
    assert [fs.get(s) for s in slots] == states
    fs.free(slots[1])
    with pytest.raises(ValueError):
        fs.get(slots[1])
    again = fs.add()
    assert again == slots[1] and fs.get(again) == StreamState()
    assert [fs.get(s) for s in slots if s != again] == [st for s, st in zip(slots, states, strict=True) if s != again]
    fs.set(slots[0], StreamState())
    assert fs.get(slots[0]) == StreamState()


def test_bad_input_is_refused_with_a_reason():
    fs = FleetStreams(S, capacity=4)
    a = fs.add()
    ok = dict(kind=[0], t_s=[1.0], seq=[0], range_ok=[True], now=[0.0])
    with pytest.raises(ValueError, match="not in use"):
        fs.decide(slot=[a + 1], **ok)
    with pytest.raises(ValueError, match="kind"):
        fs.decide(slot=[a], **{**ok, "kind": [6]})
    with pytest.raises(ValueError, match="seq"):
        fs.decide(slot=[a], **{**ok, "seq": [-1]})
    with pytest.raises(ValueError, match="finite"):
        fs.decide(slot=[a], **{**ok, "t_s": [math.nan]})
    with pytest.raises(ValueError, match="one length"):
        fs.decide(slot=[a, a], **ok)
    with pytest.raises(ValueError):
        fs.set(a, StreamState(last_t_s=math.inf))
    assert fs.decide([], [], [], [], [], []).code.shape == (0,)
    assert fs.get(a) == StreamState()  # nothing decided


def test_each_refusal_code_and_its_sentence():
    fs = FleetStreams(S, capacity=1)
    a = fs.add()
    k = _key("car-1", "imu")
    # two samples 1 s apart teach the clock 1x; then each refusal once, and a sample in time
    t = [1.0, 2.0, 2.0, 1.5, 5000.0, 3502.0, -2.0, 2.01]
    d = fs.decide([a] * 8, [1] * 8, t, list(range(8)), [True] * 6 + [False, True], [0.0] + [1.0] * 7)
    assert d.code.tolist() == [ACCEPTED, ACCEPTED, REFUSED_DUPLICATE, REFUSED_BACKWARDS, REFUSED_JUMP,
                               REFUSED_AHEAD, REFUSED_RANGE, ACCEPTED]
    reasons = [fs.rejection(d, i, k).reason for i in range(2, 7)]
    assert reasons == [
        f"sample of {k} at t_s = 2.000000 s repeats the previous one",
        f"field 't_s' of {k} went backwards: 1.500000 s after 2.000000 s",
        f"field 't_s' of {k} jumped 4998 s ahead (more than 3600 s)",
        f"field 't_s' of {k} is 3500 s after the stream's last sample, 0 s of receive time later (at most 12.5 s "
        "for imu samples): dated ahead of the stream's clock",
        f"field 't_s' of {k} must be ≥ 0, got -2"]
    st = fs.get(a)
    assert st.rate_learned and st.rate == 1.0
    assert st.upstream_gaps == 0 and st.accepted == 3  # seqs 2..6 were refused, not lost
    with pytest.raises(ValueError, match="accepted"):
        fs.rejection(d, 0, k)
    with pytest.raises(ValueError, match="message"):
        fs.rejection(fs.decide([a], [1], [3.0], [8], [False], [1.5]), 0, k)


def test_warm_entry_point():
    assert fleet.main(["--warm"]) == 0
    assert fleet.main([]) == 2


def test_bench_row_runs_and_both_paths_decide_alike():
    from bench import cores_bench

    r = cores_bench.ingest_rules(slots=20, per_slot=4, calls=3, repeats=1)
    assert r["same_decisions"] is True
    assert r["reference_us_per_sample"] > 0 and r["kernel_us_per_sample"] > 0


# ---- v2 batches: a refused sample's seq is no gap of its stream, as on the v1 path -----------------------------


class _Pub:
    def put(self, payload, **kw):
        pass


class _Session:
    def declare_publisher(self, key, **kw):
        return _Pub()


@pytest.mark.parametrize("n,jump", [(10, False), (100, False), (100, True)])  # _small, columns, _per_sample
def test_v2_batches_count_refused_seqs_as_the_v1_path_does(tmp_path, monkeypatch, n, jump):
    """Ingest's batch paths leave the seq accounting of the v1 path: a refused sample is counted as rejected,
    not also as an upstream gap (the batch paths used to skip remembering refused seqs)."""
    from magmesh.runtime import Runner
    from schemas import batch, messages
    from services.ingest.batching import IngestServiceSettings

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    key = keys.raw_imu("car-1")
    g, a = [0.01, 0.0, 0.0], [0.0, 0.1, 9.8]

    def rows(t0: float, s0: int) -> list[tuple[float, int, list]]:
        out = []
        for i in range(n):
            t, gyro = t0 + 0.01 * i, g
            if i == n // 3:
                gyro = [100.0, 0.0, 0.0]  # out of range
            if i == n // 2:
                t = out[-1][0]  # the previous t_s again
            if i == n // 2 + 2:
                t = out[-1][0] - 0.005  # backwards
            if jump and i == n // 4:
                t += 5000.0  # beyond max_time_jump_s: the per-sample path
            if i >= n - 2:
                gyro = [0.0, 0.0, 100.0]  # the last two refused: their seqs carried to the next batch
            out.append((t, s0 + i + (3 if i > n // 2 else 0), gyro))  # three seqs really missing
        return out

    parts = [rows(1.0, 100), [(1.0 + 0.01 * n - 0.02, 100 + n + 3, g)], rows(1.0 + 0.01 * n, 100 + n + 4)]
    r1 = Runner(Ingest(IngestServiceSettings(), instance="ing-v1"), _Session())
    r2 = Runner(Ingest(IngestServiceSettings(), instance="ing-v2"), _Session())
    for p, part in enumerate(parts):
        for t, q, gyro in part:
            r1.handle_sample(key, messages.encode(make("imu", "car-1", t, q, gyro_rad_s=gyro, accel_m_s2=a)))
        if len(part) == 1:  # a single between the batches, on both
            r2.handle_sample(key, messages.encode(make("imu", "car-1", *part[0][:2], gyro_rad_s=g, accel_m_s2=a)))
        else:
            r2.handle_sample(keys.raw_batch("car-1"), batch.encode("car-1", p, {"imu": {
                "t_s": np.array([x[0] for x in part]), "seq": np.array([x[1] for x in part]),
                "cols": {"gyro_rad_s": np.array([x[2] for x in part]), "accel_m_s2": np.tile(a, (len(part), 1))}}}))
        s1, s2 = r1.vehicle_state["car-1"].streams[key], r2.vehicle_state["car-1"].streams[key]
        seq_fields = ("accepted", "last_seq", "upstream_gaps", "seq_rebases", "refused_seqs", "last_t_s")
        assert [getattr(s2, f) for f in seq_fields] == [getattr(s1, f) for f in seq_fields], (p, s1, s2)
    assert s1.upstream_gaps == 6 and s1.accepted > 0  # the real gaps only (3 in each batch)
