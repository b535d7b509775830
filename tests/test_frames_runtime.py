"""Fleet frames (contract v3) in the runtime, without Zenoh: the codec, the input path (streams and vehicles cut
to what a service subscribes to, seq tracked per vehicle and stream, the journal after a restart), the per-vehicle
fallback, and the output side (frames numbered per vehicle, many rows out at once, mirrored with their seqs)."""

import msgpack
import numpy as np
import pytest
import zenoh

from magmesh.frames import SeqTable
from magmesh.runtime import Runner, Service
from schemas import frame, keys
from schemas.messages import SchemaError


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


def _stream(name, msg_type, rows, cols):
    """rows: [(vehicle index, t_s, seq)] sorted by vehicle then time."""
    vi = np.array([r[0] for r in rows], np.uint32)
    return frame.Stream(name, msg_type, vi, np.array([r[1] for r in rows], float),
                        np.array([r[2] for r in rows], np.int64), cols)


def _mag_rows(rows, sensor="1"):
    return _stream(f"mag/{sensor}", "mag", rows, {"sensor": sensor, "b_nt": np.arange(3 * len(rows), dtype=float)
                                                  .reshape(len(rows), 3) + 20000.0})


def _imu_rows(rows):
    n = len(rows)
    return _stream("imu", "imu", rows, {"gyro_rad_s": np.zeros((n, 3)), "accel_m_s2": np.tile([0, 0, 9.81], (n, 1))})


VEH = ["car-1", "car-2", "van-1"]


def _clean_frame(seq, streams, shard="ingest-1"):
    return frame.encode(shard, "clean", seq, VEH, streams)


class _FrameSvc(Service):
    role = "frame_test"
    impl = "t"

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.got = []

    def subscriptions(self):
        return [keys.clean_mag("car-$*", "1"), keys.clean_imu("car-$*")]

    def on_frame(self, fr):
        self.got.append(fr)


class _SampleSvc(Service):
    role = "sample_test"
    impl = "t"

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.got = []

    def subscriptions(self):
        return [keys.clean_mag("*", "1"), keys.clean_imu("*")]

    def on_message(self, info, msg, state):
        self.got.append((info.key, msg["t_s"], msg["seq"], msg.get("b_nt")))


def _runner(svc, tmp_path, monkeypatch):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    r = Runner(svc, sess)
    r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
    return r, sess


FKEY = keys.fleet_frame("ingest-1", "clean")


def test_codec_round_trip_and_structure_checks():
    m = _mag_rows([(0, 1.0, 5), (0, 1.02, 6), (2, 1.0, 0)])
    b = _clean_frame(7, {"mag/1": m, "imu": _imu_rows([(1, 1.0, 3)])})
    f = frame.decode(b)
    assert (f.shard, f.kind, f.seq, f.vehicles) == ("ingest-1", "clean", 7, VEH)
    assert f.t_s == 1.02
    s = f.streams["mag/1"]
    assert s.vi.tolist() == [0, 0, 2] and s.seq.tolist() == [5, 6, 0]
    np.testing.assert_array_equal(s.cols["b_nt"], m.cols["b_nt"])
    msgs = s.messages("car-1", 0, 2)
    assert msgs[1] == {"type": "mag", "version": 1, "vehicle": "car-1", "t_s": 1.02, "seq": 6, "sensor": "1",
                       "b_nt": [20003.0, 20004.0, 20005.0]}
    raw = msgpack.unpackb(b)
    bad = dict(raw, streams={"mag/1": dict(raw["streams"]["mag/1"], vi=np.array([2, 0, 0], "<u4").tobytes())})
    with pytest.raises(SchemaError, match="sorted by vehicle"):
        frame.decode(msgpack.packb(bad))
    bad = dict(raw, streams={"mag/1": dict(raw["streams"]["mag/1"], vi=np.array([0, 0, 9], "<u4").tobytes())})
    with pytest.raises(SchemaError, match="vehicle index beyond"):
        frame.decode(msgpack.packb(bad))
    with pytest.raises(SchemaError, match="reserved"):
        frame.decode(frame.encode("s", "clean", 0, ["fleet"], {}))
    with pytest.raises(SchemaError, match="frame version 3"):
        frame.decode(msgpack.packb(dict(raw, version=2)))


def test_fleet_keys_are_not_vehicles():
    k = keys.fleet_frame("ingest-1", "clean")
    assert k == "magmesh/fleet/ingest-1/clean"
    info = keys.parse(k)
    assert (info.kind, info.rest) == ("fleet", ("ingest-1", "clean"))
    with pytest.raises(keys.KeyError_):
        keys.parse_data(k)
    with pytest.raises(keys.KeyError_, match="reserved"):
        keys.clean_imu("fleet")
    with pytest.raises(keys.KeyError_):
        keys.parse("magmesh/fleet/ingest-1/raw")


def test_seq_table_reads_as_one_dict():
    t = SeqTable(capacity=2)
    t["a"] = 3
    s = t.slots_for(["a", "b", "c"])  # "a" moves from the dict into a slot
    assert s.tolist() == [0, 1, 2] and t["a"] == 3 and "b" not in t and t.get("b", -1) == -1
    t.arr[s[1]] = 9
    assert dict(t) == {"a": 3, "b": 9} and len(t) == 2
    del t["a"]
    assert "a" not in t and t.pop("b") == 9 and len(t) == 0
    t.free_slot("c")
    assert t.slots_for(["d"]).tolist() == [2] and t.generation == 1


def test_seq_table_items_t_is_get_and_get_t_of_every_key():
    """items_t (what a group member's every answer reads) gives what get and get_t give, key by key: keys in the
    dict and in slots, freed slots, times never set (None) and set."""
    t = SeqTable(capacity=2)
    t["d1"] = 4
    t.set_t("d1", 2.5)
    t["d2"] = 7  # (no time)
    s = t.slots_for(["s1", "s2", "s3", "gone"])
    t.arr[s[0]], t.arr[s[1]], t.arr[s[3]] = 10, 11, 12
    t.set_t("s1", 1.25)
    t.free_slot("gone")
    want = sorted((k, t.get(k), t.get_t(k)) for k in t)
    assert sorted(t.items_t()) == want
    assert want == [("d1", 4, 2.5), ("d2", 7, None), ("s1", 10, 1.25), ("s2", 11, None)]


def test_frame_cut_to_subscribed_vehicles_and_streams(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    gnss = frame.Stream("gnss", "gnss", np.array([0], np.uint32), np.array([1.0]), np.array([0]), {})
    r.handle_sample(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (1, 1.0, 0), (2, 1.0, 0)]),
                                           "mag/2": _mag_rows([(0, 1.0, 0)], "2"),
                                           "imu": _imu_rows([(0, 1.0, 0), (2, 1.0, 0)]), "gnss": gnss}))
    (f,) = svc.got
    assert sorted(f.streams) == ["imu", "mag/1"]  # mag/2 and gnss are not subscribed to
    assert f.streams["mag/1"].vi.tolist() == [0, 1]  # van-1 is outside car-$*
    assert f.streams["imu"].vi.tolist() == [0]
    assert r.in_seq[keys.clean_mag("car-2", "1")] == 0 and keys.clean_mag("van-1", "1") not in r.in_seq
    assert r.last_in_t["car-1"] == 1.0 and "van-1" not in r.last_in_t


def test_frame_seq_gaps_counted_per_vehicle_and_stream(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    r.handle_sample(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (0, 1.02, 1), (1, 1.0, 10)])}))
    # car-1 misses seqs 2..4; car-2 continues; inside a frame car-2 skips one (12 → 14)
    r.handle_sample(FKEY, _clean_frame(1, {"mag/1": _mag_rows([(0, 1.1, 5), (1, 1.02, 11), (1, 1.04, 12),
                                                               (1, 1.08, 14)])}))
    k1, k2 = keys.clean_mag("car-1", "1"), keys.clean_mag("car-2", "1")
    assert r.drops[k1]["upstream_gap"] == 3
    assert r.drops[k2]["upstream_gap"] == 1
    assert r.in_seq[k1] == 5 and r.in_seq[k2] == 14
    r.handle_sample(FKEY, _clean_frame(3, {"mag/1": _mag_rows([(0, 1.2, 6)])}))
    assert r.frames_missed == 1 and r.drops[k1]["upstream_gap"] == 3


def test_frame_journal_counts_what_a_restart_missed(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    r.resume_journal()
    r.handle_sample(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (0, 1.02, 1), (1, 1.0, 7)])}))
    # kill -9: a new process of the same instance reads the journal
    svc2 = _FrameSvc(instance="f-1")
    r2, _ = _runner(svc2, tmp_path, monkeypatch)
    r2.resume_journal()
    k1, k2 = keys.clean_mag("car-1", "1"), keys.clean_mag("car-2", "1")
    assert r2.in_seq[k1] == 1 and r2.in_seq[k2] == 7
    r2.handle_sample(FKEY, _clean_frame(4, {"mag/1": _mag_rows([(0, 1.2, 9), (1, 1.2, 8)])}))
    assert r2.drops[k1]["lost_during_restart"] == 7 and r2.drops[k1].get("upstream_gap", 0) == 0
    assert r2.drops[k2].get("lost_during_restart", 0) == 0
    assert r2.restart_gaps[k1] == [[2, 8]]


def test_service_without_on_frame_gets_each_vehicles_samples_in_time_order(tmp_path, monkeypatch):
    svc = _SampleSvc(instance="s-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    r.handle_sample(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (0, 1.02, 1), (2, 1.0, 4)]),
                                           "imu": _imu_rows([(0, 0.99, 0), (0, 1.01, 1)])}))
    car = [g for g in svc.got if "/car-1/" in g[0]]
    assert [g[1] for g in car] == [0.99, 1.0, 1.01, 1.02]
    van = [g for g in svc.got if "/van-1/" in g[0]]
    assert van == [(keys.clean_mag("van-1", "1"), 1.0, 4, [20006.0, 20007.0, 20008.0])]


def test_publish_frame_numbers_rows_per_vehicle_key(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="cal-1")
    r, sess = _runner(svc, tmp_path, monkeypatch)
    r.resume_journal()
    m = _mag_rows([(0, 1.0, -1), (0, 1.02, -1), (2, 1.0, -1)])
    m.seq = None
    assert svc.publish_frame("cal", VEH, {"mag/1": m}) == 3
    m2 = _mag_rows([(0, 1.04, -1), (1, 1.0, -1)])
    m2.seq = None
    svc.publish_frame("cal", VEH, {"mag/1": m2})
    (k0, p0), (k1, p1) = sess.out
    assert k0 == keys.fleet_frame("cal-1", "cal")
    f0, f1 = frame.decode(p0), frame.decode(p1)
    assert (f0.seq, f1.seq) == (0, 1)
    assert f0.streams["mag/1"].seq.tolist() == [0, 1, 0] and f1.streams["mag/1"].seq.tolist() == [2, 0]
    assert r.seq[keys.cal_mag("car-1", "1")] == 2
    prev = r.journal.load()
    assert prev["o" + keys.cal_mag("car-1", "1")] == 2 and prev["o" + keys.cal_mag("van-1", "1")] == 0


def _dmc_cols(n):
    return {"dm_nt": [[1.0, 2.0]] * n, "ddm_nt_s": [[0.0, 0.0]] * n, "dh_rad": [0.01] * n, "ddh_rad_s": [0.0] * n,
            "heading_rad": [1.0] * n, "stage1_pass": [True] * n, "credibility": [1.0] * n, "valid": [True] * n,
            "impl": "threshold", "param_source": ["manifest"] * n}


def test_publish_rows_fast_path_and_mirror(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="dmc-1")
    r, sess = _runner(svc, tmp_path, monkeypatch)
    r.resume_journal()
    veh = ["car-2", "car-1", "car-2"]
    seqs = r.publish_rows("dmc", [keys.dmc(v) for v in veh], veh, [1.0, 1.0, 1.02], _dmc_cols(3), mirror="dmc")
    assert seqs == [0, 0, 1]
    singles = [(k, msgpack.unpackb(p)) for k, p in sess.out if not k.startswith("magmesh/fleet/")]
    assert [(k, m["seq"], m["t_s"]) for k, m in singles] == [(keys.dmc("car-2"), 0, 1.0), (keys.dmc("car-1"), 0, 1.0),
                                                              (keys.dmc("car-2"), 1, 1.02)]
    assert singles[0][1]["dm_nt"] == [1.0, 2.0] and singles[0][1]["impl"] == "threshold"
    (fk, fp), = [(k, p) for k, p in sess.out if k.startswith("magmesh/fleet/")]
    f = frame.decode(fp)
    assert fk == keys.fleet_frame("dmc-1", "dmc")
    st = f.streams["dmc"]
    got = sorted(zip([f.vehicles[i] for i in st.vi.tolist()], st.t_s.tolist(), st.seq.tolist(), strict=True))
    assert got == [("car-1", 1.0, 0), ("car-2", 1.0, 0), ("car-2", 1.02, 1)]
    assert r.journal.load()["o" + keys.dmc("car-2")] == 1
    # the next frames carry the same vehicle list (one object while no vehicle comes: readers keep their state per
    # list), rows of a vehicle not in it a longer one
    sent = []
    monkeypatch.setattr(r, "publish_frame", lambda kind, vehicles, streams_, gated=False: sent.append(vehicles))
    r.publish_rows("dmc", [keys.dmc("car-1")], ["car-1"], [1.04], _dmc_cols(1), mirror="dmc")
    r.publish_rows("dmc", [keys.dmc("car-2")], ["car-2"], [1.04], _dmc_cols(1), mirror="dmc")
    r.publish_rows("dmc", [keys.dmc("van-1")], ["van-1"], [1.04], _dmc_cols(1), mirror="dmc")
    assert sent[0] is sent[1] and sent[0] == f.vehicles and sent[2] == [*f.vehicles, "van-1"]
    # an invalid row (credibility outside [0, 1]) goes through the validating path: refused, counted
    bad = _dmc_cols(1)
    bad["credibility"] = [1.5]
    with pytest.raises(SchemaError):
        r.publish_rows("dmc", [keys.dmc("car-1")], ["car-1"], [1.04], bad)


def test_publish_rows_held_during_a_hand_over_then_mirrored(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="dmc-2")
    r, sess = _runner(svc, tmp_path, monkeypatch)
    r.mode = "standby"
    r.cut = {"car-1": 1.01}
    seqs = r.publish_rows("dmc", [keys.dmc("car-1")] * 2, ["car-1"] * 2, [1.0, 1.02], _dmc_cols(2), mirror="dmc")
    assert seqs == [-1, -1] and sess.out == [] and len(r.held) == 1  # before the cut suppressed, after held
    r.control({"op": "takeover", "seqs": {keys.dmc("car-1"): 41}, "alarms": {}, "raised": {}})
    singles = [(k, msgpack.unpackb(p)) for k, p in sess.out if not k.startswith("magmesh/fleet/")]
    assert [(m["seq"], m["t_s"]) for _, m in singles] == [(42, 1.02)]
    (fp,) = [p for k, p in sess.out if k.startswith("magmesh/fleet/")]
    st = frame.decode(fp).streams["dmc"]
    assert st.seq.tolist() == [42] and st.t_s.tolist() == [1.02]


class _Group:
    """A group member's gate: car-1 held plainly, car-2 being handed over (cut at 1.01 s)."""

    def __init__(self):
        self.calls = []

    def plain(self, v):
        return v == "car-1"

    def plain_many(self, vs):
        return {v: self.plain(v) for v in vs}

    def gate(self, key, msg_type, vehicle, t_s, fields):
        self.calls.append((vehicle, t_s))
        return t_s < 1.01


def test_publish_rows_in_a_group_gates_only_vehicles_in_a_hand_over(tmp_path, monkeypatch):
    svc = _FrameSvc(instance="dmc-1")
    r, sess = _runner(svc, tmp_path, monkeypatch)
    r.group = _Group()
    veh = ["car-1", "car-2", "car-1", "car-2"]
    seqs = r.publish_rows("dmc", [keys.dmc(v) for v in veh], veh, [1.0, 1.0, 1.02, 1.02], _dmc_cols(4), mirror="dmc")
    assert seqs == [0, 0, 1, -1]  # car-2's row after the cut is the new owner's
    assert r.group.calls == [("car-2", 1.0), ("car-2", 1.02)]  # car-1 never went through the gate
    (fp,) = [p for k, p in sess.out if k.startswith("magmesh/fleet/")]
    st = frame.decode(fp).streams["dmc"]
    assert sorted(st.seq.tolist()) == [0, 0, 1] and st.n == 3


def test_a_frames_rows_are_gated_only_for_vehicles_in_a_hand_over(tmp_path, monkeypatch):
    """publish_frame in a group: the rows of plainly held vehicles pass whole (every row of a vehicle in one run),
    each row of a vehicle in a hand-over goes through the gate (car-2: published before its cut at 1.01 s only),
    and a frame whose vehicles are all held plainly is passed on as it is."""
    svc = _FrameSvc(instance="cal-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    r.group = _Group()
    r.group.plain = lambda v: v != "car-2"
    st = _mag_rows([(0, 1.0, -1), (0, 1.02, -1), (1, 1.0, -1), (1, 1.02, -1), (2, 1.0, -1), (2, 1.04, -1)])
    kept = r._gate_frame_rows("cal", "mag/1", VEH, st)
    assert [(VEH[v], t) for v, t in zip(kept.vi.tolist(), kept.t_s.tolist(), strict=True)] == [
        ("car-1", 1.0), ("car-1", 1.02), ("car-2", 1.0), ("van-1", 1.0), ("van-1", 1.04)]
    assert r.group.calls == [("car-2", 1.0), ("car-2", 1.02)]
    only_plain = _mag_rows([(0, 1.0, -1), (2, 1.0, -1)])
    assert r._gate_frame_rows("cal", "mag/1", VEH, only_plain) is only_plain


class _Admit:
    """A group member holding only the vehicles in ``held``; records which frames' vehicle lists it was asked."""

    def __init__(self, held):
        self.held, self.asked = set(held), []

    def admitted(self, vehicles, key_of):
        self.asked.append(tuple(vehicles))
        return np.array([v in self.held for v in vehicles])


def test_a_group_member_passes_over_a_frame_of_none_of_its_vehicles_from_its_header(tmp_path, monkeypatch):
    """In a group, a frame whose vehicles are all another member's is seen from its header (peek), not decoded:
    not handed on, frames and frame gaps still counted, the group asked once per frame; a frame with one held
    vehicle is decoded and cut to it."""
    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    r.group = _Admit(held=["car-2"])
    r.handle_sample(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (1, 1.0, 0)])}))  # (list learnt)
    assert [f.streams["mag/1"].vi.tolist() for f in svc.got] == [[1]]
    decoded = []
    real = frame.decode
    monkeypatch.setattr(frame, "decode", lambda *a, **k: decoded.append(1) or real(*a, **k))
    r.group.held = set()
    r.handle_sample(FKEY, _clean_frame(2, {"mag/1": _mag_rows([(0, 1.02, 1), (1, 1.02, 1)])}))
    assert decoded == [] and len(svc.got) == 1  # not decoded, not handed on
    assert r.frames_in == 2 and r.frames_missed == 1  # frame 1 never came
    assert len(r.group.asked) == 2
    r.group.held = {"car-1"}
    r.handle_sample(FKEY, _clean_frame(3, {"mag/1": _mag_rows([(0, 1.04, 2), (1, 1.04, 2)])}))
    assert decoded == [1] and svc.got[-1].streams["mag/1"].vi.tolist() == [0]
    assert r.frames_in == 3 and r.frames_missed == 1 and len(r.group.asked) == 3  # (asked once for that frame too)
    assert frame.peek(b"\x81\xa4type\xa5frame") is None and frame.peek(b"\xc1") is None


def test_one_stalls_backlog_is_worked_off_not_shed(tmp_path, monkeypatch):
    """A loop that stalled once (a slow first sample) finds frames queued longer than shed_after_s: it has not
    been behind for that long, so it handles them, and the next fresh input ends the spell."""
    import time as _time

    from magmesh import runtime

    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    now = _time.monotonic()
    for i in range(3):
        r.q.put(("S", [(FKEY, _clean_frame(i, {"mag/1": _mag_rows([(0, 1.0 + i, i)])}))],
                 now - runtime.SHED_AFTER_S - 1))
    r.q.put(("S", [(FKEY, _clean_frame(3, {"mag/1": _mag_rows([(0, 4.0, 3)])}))], now))
    r.q.put(("stop",))
    r.loop()
    # (queued together: handled as one run of the key's frames, every row in its order)
    assert [t for f in svc.got for t in f.streams["mag/1"].t_s.tolist()] == [1.0, 2.0, 3.0, 4.0]
    assert r.frames_in == 4 and r.frames_merged == 3 and not r.drops[FKEY].get("upstream_gap")
    assert not r.drops[FKEY].get("shed_behind") and r.frames_shed == 0 and r._behind_since is None


def test_frames_that_queued_together_are_handled_as_one_run_per_key_and_list(tmp_path, monkeypatch):
    """Frames of one key that waited in the queue together reach the service as one frame (each stream's rows by
    vehicle, then time; seqs tracked across them, a lost frame between them still counted); a frame with another
    vehicle list starts a new run, another key's frames make their own, and input that is not a frame keeps its
    place (frames before it are handled before it)."""
    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    other = keys.fleet_frame("ingest-2", "clean")
    f0 = _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (1, 1.0, 5)]), "imu": _imu_rows([(1, 1.0, 0)])})
    f1 = _clean_frame(1, {"mag/1": _mag_rows([(0, 1.02, 1), (1, 1.02, 6)])})
    f3 = _clean_frame(3, {"mag/1": _mag_rows([(0, 1.06, 3)])})  # (frame 2 lost: car-1's seq 2 never came)
    g0 = frame.encode("ingest-2", "clean", 0, ["car-9"], {"mag/1": _mag_rows([(0, 1.0, 0)])})
    longer = frame.encode("ingest-1", "clean", 4, [*VEH, "car-7"], {"mag/1": _mag_rows([(3, 1.08, 0)])})
    r._handle_items([(FKEY, f0), (other, g0), (FKEY, f1), (FKEY, f3), (FKEY, longer)])
    assert [(f.shard, f.seq) for f in svc.got] == [("ingest-1", 3), ("ingest-1", 4), ("ingest-2", 0)]
    run = svc.got[0]
    m = run.streams["mag/1"]
    assert [(run.vehicles[v], t, q) for v, t, q in zip(m.vi.tolist(), m.t_s.tolist(), m.seq.tolist(), strict=True)] \
        == [("car-1", 1.0, 0), ("car-1", 1.02, 1), ("car-1", 1.06, 3), ("car-2", 1.0, 5), ("car-2", 1.02, 6)]
    assert run.streams["imu"].n == 1 and r.frames_merged == 2 and r.frames_in == 5
    assert r.drops[keys.clean_mag("car-1", "1")]["upstream_gap"] == 1  # as if the frames had come one by one
    assert r.frames_missed == 1


def test_a_frame_that_waited_too_long_is_shed_counted_and_its_seqs_tracked(tmp_path, monkeypatch):
    """Overload: once the loop has handled only late input for shed_after_s, a frame queued longer than that goes
    to no handler; its rows are counted lost as shed_behind on the frame key and its seqs are tracked, so the next
    frame shows no gap; a fresh one is handled."""
    import time as _time

    from magmesh import runtime

    svc = _FrameSvc(instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    assert r.shed_after_s == runtime.SHED_AFTER_S > 0
    now = _time.monotonic()
    r._behind_since = now - runtime.SHED_AFTER_S - 0.1  # behind (handling late input only) for that long already
    old = _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0), (0, 1.02, 1), (1, 1.0, 10)]),
                           "imu": _imu_rows([(0, 1.0, 4)])})
    fresh = _clean_frame(1, {"mag/1": _mag_rows([(0, 1.04, 2), (1, 1.02, 11)])})
    r.q.put(("S", [(FKEY, old)], now - runtime.SHED_AFTER_S - 0.5))
    r.q.put(("S", [(FKEY, fresh)], now))
    r.q.put(("stop",))
    r.loop()
    assert len(svc.got) == 1 and svc.got[0].seq == 1  # only the fresh frame reached the service
    assert r.drops[FKEY]["shed_behind"] == 4 and r.frames_shed == 1
    assert "shed_behind" in runtime.LOST_REASONS
    k1, k2 = keys.clean_mag("car-1", "1"), keys.clean_mag("car-2", "1")
    assert r.in_seq[k1] == 2 and r.in_seq[k2] == 11
    assert r.drops[k1].get("upstream_gap", 0) == 0 and r.drops[k2].get("upstream_gap", 0) == 0
    assert r.count_in[FKEY].n == 6  # shed rows were received: in, then counted as lost


def test_shedding_is_a_setting_zero_never_sheds(tmp_path, monkeypatch):
    import time as _time
    from dataclasses import dataclass

    from magmesh import runtime

    @dataclass(frozen=True)
    class _S:
        shed_after_s: float = 0.0

    svc = _FrameSvc(settings=_S(), instance="f-1")
    r, _ = _runner(svc, tmp_path, monkeypatch)
    assert r.shed_after_s == 0.0
    r._behind_since = _time.monotonic() - 3600
    r.q.put(("S", [(FKEY, _clean_frame(0, {"mag/1": _mag_rows([(0, 1.0, 0)])}))], _time.monotonic() - 3600))
    r.q.put(("stop",))
    r.loop()
    assert len(svc.got) == 1 and not r.drops[FKEY].get("shed_behind") and runtime.SHED_AFTER_S > 0


def test_seq_table_finds_one_vehicles_keys_from_its_index():
    """SeqTable.keys_with: a vehicle's keys (slot or dict), none of another vehicle's, none deleted."""
    from magmesh.frames import SeqTable

    t = SeqTable(capacity=2)
    t.slots_for(["magmesh/car-1/clean/mag/1", "magmesh/car-2/clean/mag/1", "magmesh/car-10/clean/imu"])
    t["magmesh/car-1/clean/mag/1"] = 4
    t["magmesh/car-10/clean/imu"] = 7
    t["magmesh/car-1/cal/mag/2"] = 3  # a dict entry
    assert sorted(t.keys_with("magmesh/car-1/")) == ["magmesh/car-1/cal/mag/2", "magmesh/car-1/clean/mag/1"]
    assert t.keys_with("magmesh/car-2/") == []  # a slot with no seq yet
    del t["magmesh/car-1/cal/mag/2"]
    t.free_slot("magmesh/car-1/clean/mag/1")
    assert t.keys_with("magmesh/car-1/") == [] and "car-1" not in t.vidx
    assert t.keys_with("magmesh/car-10/") == ["magmesh/car-10/clean/imu"]
    assert sorted(t) == sorted(k for v in ("car-1", "car-2", "car-10") for k in t.keys_with(f"magmesh/{v}/"))
