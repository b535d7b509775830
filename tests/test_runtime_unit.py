"""Runtime behaviour without Zenoh: alarm idempotence, restored alarm state and its reconciliation."""

import time

import msgpack

from magmesh.runtime import Runner, Service
from schemas import keys


class _Pub:
    def __init__(self, out, key):
        self.out, self.key = out, key

    def put(self, payload):
        self.out.append((self.key, msgpack.unpackb(payload)))


class _Session:
    def __init__(self):
        self.out = []

    def declare_publisher(self, key, **kw):
        return _Pub(self.out, key)


class _Svc(Service):
    role = "test_role"
    impl = "t"


def _runner(tmp_path, monkeypatch, instance="t-1"):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    return Runner(_Svc(instance=instance), sess), sess


def test_alarm_published_only_on_change(tmp_path, monkeypatch):
    r, s = _runner(tmp_path, monkeypatch)
    svc = r.svc
    for state in ("cleared", "raised", "raised", "cleared", "cleared", "raised"):
        svc.alarm("car-1", "dmc", state, "warning", "reason sentence", 1.0, 0.5, 1.0)
    states = [m["state"] for k, m in s.out]
    assert states == ["raised", "cleared", "raised"]
    assert [m["seq"] for k, m in s.out] == [0, 1, 2]


def test_restart_restores_alarm_state_and_clears_what_is_no_longer_seen(tmp_path, monkeypatch):
    r, s = _runner(tmp_path, monkeypatch)
    r.svc.alarm("car-1", "dmc", "raised", "warning", "interference", 2.0, 1.0, 10.0)
    # a new process of the same instance
    r2, s2 = _runner(tmp_path, monkeypatch)
    r2.restore_alarms()
    key = keys.alarm("car-1", "dmc")
    assert key in r2.raised and r2.seq[key] == 0 and r2.reconcile_at is not None
    r2.svc.alarm("car-1", "dmc", "raised", "warning", "interference", 2.0, 1.0, 11.0)  # seen again: not repeated
    assert s2.out == []
    r2.reconcile_alarms()
    assert s2.out == []  # the logic raised it again: it stays raised
    r3, s3 = _runner(tmp_path, monkeypatch)
    r3.restore_alarms()
    r3.reconcile_alarms()  # a restart alone clears nothing: the restarted logic has seen no input yet
    assert s3.out == [] and key in r3.raised
    r3.first_in_t["car-1"], r3.last_in_t["car-1"] = 100.0, 104.0  # 4 s of input: less than alarm_reconcile_s
    r3.out_since_start["car-1"] = 50
    r3.reconcile_alarms()
    assert s3.out == []
    r3.last_in_t["car-1"] = 105.5  # enough input to decide, and nothing raised it again: cleared, seq continues
    r3.reconcile_alarms()
    assert [(m["state"], m["seq"]) for _, m in s3.out] == [("cleared", 1)]
    assert "5.5 s of input" in s3.out[0][1]["reason"]
    r4, s4 = _runner(tmp_path, monkeypatch)
    r4.restore_alarms()
    assert r4.reconcile_at is None and not r4.raised
    r4.reconcile_alarms()  # nothing to do, no error
    assert s4.out == []


def test_restored_alarm_cleared_by_the_logic_before_reconcile(tmp_path, monkeypatch):
    r, _ = _runner(tmp_path, monkeypatch)
    r.svc.alarm("car-1", "dmc", "raised", "warning", "interference", 2.0, 1.0, 10.0)
    r2, s2 = _runner(tmp_path, monkeypatch)
    r2.restore_alarms()
    r2.svc.alarm("car-1", "dmc", "cleared", "warning", "fine again", 0.1, 1.0, 12.0)
    assert [m["state"] for _, m in s2.out] == ["cleared"]
    time.sleep(0.01)
    r2.reconcile_alarms()  # the raised set is empty by now: nothing more
    assert len(s2.out) == 1


# ---- the input path: keys, seq, sizes, bounded state ------------------------------------------------------


def _ingest(tmp_path, monkeypatch, **settings):
    from services.ingest.core import IngestSettings
    from services.ingest.service import Ingest

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    return Runner(Ingest(IngestSettings(**settings), instance="ingest-t"), sess), sess


def _imu(vehicle, t, seq, **extra):
    from schemas import make

    return msgpack.packb(make("imu", vehicle, t, seq, gyro_rad_s=[0.01, 0.0, 0.0], accel_m_s2=[0.0, 0.1, 9.8],
                              **extra), use_bin_type=True)


def _out(sess, key):
    return [m for k, m in sess.out if k == key]


def test_service_keys_and_reserved_names_are_refused_not_fatal(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    for key in ("magmesh/svc/raw/imu", "magmesh/svc/clean/imu", "magmesh/svc/clean/gnss", "magmesh/svc/raw/mag/1",
                "magmesh/magmesh/raw/imu", "magmesh/car-1\n/raw/imu", "magmesh/car-1/raw/imu/", "magmesh/car-1/Raw/imu"):
        r.handle_sample(key, _imu("svc", 1.0, 0))
    st = r.status()
    assert st["rejected"] == {"key": 8} and st["lost_total"] == 0 and not r.vehicle_state
    assert set(r.count_in) == {keys.BAD_KEY} and r.count_in[keys.BAD_KEY].n == 8
    # the two keys that name a usable vehicle are reported on its rejects key; the rest are counted and logged
    assert sorted(m["key"] for m in _out(s, keys.rejects("car-1"))) == ["magmesh/car-1/Raw/imu",
                                                                         "magmesh/car-1/raw/imu/"]
    assert not any("/svc/" in k or "magmesh/magmesh" in k for k, _ in s.out)


def test_a_refused_foreign_sample_does_not_move_the_streams_seq(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    key = keys.raw_imu("car-1")
    for i in range(100):
        r.handle_sample(key, _imu("car-1", 10.0 + 0.01 * i, 22_000 + i))
    # a foreign sample on the same key, refused (dated in the past), with a seq far below the stream's
    r.handle_sample(key, _imu("car-1", 1.0, 0))
    for i in range(100, 200):
        r.handle_sample(key, _imu("car-1", 10.0 + 0.01 * i, 22_000 + i))
    st = r.status()
    assert st["rejected"] == {"time_order": 1}
    assert st["lost_total"] == 0 and "upstream_gap" not in st["drops"].get(key, {})
    assert len(_out(s, keys.clean_imu("car-1"))) == 200
    # a real gap is still counted as lost, exactly
    r.handle_sample(key, _imu("car-1", 20.0, 22_205))
    assert r.status()["lost"] == {"upstream_gap": 5}


def test_a_forged_huge_seq_is_one_rebase_not_a_billion_lost(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    key = keys.raw_imu("car-1")
    for i in range(50):
        r.handle_sample(key, _imu("car-1", 0.01 * i, i))
    r.handle_sample(key, _imu("car-1", 0.505, 10**9))  # well-formed, in time: accepted, seq forged
    for i in range(51, 100):
        r.handle_sample(key, _imu("car-1", 0.01 * i, i))
    st = r.status()
    assert st["lost_total"] == 0, st["lost"]
    assert st["rebases"] == {"seq_jump": 1, "seq_back": 1}
    assert st["seq_rebases"] == 2 and not st["upstream_gaps"]
    assert st["drops_total"] < 10


def test_payload_size_is_checked_before_decoding_and_big_unknown_fields_never_go_out(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    key = keys.raw_imu("car-1")
    r.handle_sample(key, _imu("car-1", 1.0, 0, blob="x" * (1 << 20)))  # 1 MB extra field: refused whole
    (rej,) = _out(s, keys.rejects("car-1"))
    assert rej["code"] == "decode" and rej["field"] == "<payload>" and "bytes" in rej["reason"]
    assert rej["payload_len_bytes"] > 1 << 20
    r.handle_sample(key, _imu("car-1", 2.0, 1, blob="x" * 20_000))  # under the size limit: trimmed
    r.handle_sample(key, _imu("car-1", 3.0, 2, note="fw 1.2"))  # small unknown field: kept (forward compatible)
    clean = _out(s, keys.clean_imu("car-1"))
    assert [m["t_s"] for m in clean] == [2.0, 3.0]
    assert "blob" not in clean[0] and clean[1]["note"] == "fw 1.2"
    assert r.status()["skipped"] == {"extra_fields_dropped": 1}
    assert max(len(msgpack.packb(m)) for _, m in s.out) < 4096


def test_a_sample_dated_an_hour_ahead_is_refused_and_the_stream_keeps_flowing(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    key = keys.raw_imu("car-1")
    for i in range(100):
        r.handle_sample(key, _imu("car-1", 0.01 * i, i))
    r.handle_sample(key, _imu("car-1", 0.995 + 3500.0, 7))  # from another publisher: its own seq
    for i in range(100, 199):
        r.handle_sample(key, _imu("car-1", 0.01 * i, i))
    (rej,) = _out(s, keys.rejects("car-1"))
    assert rej["code"] == "time_order" and "ahead" in rej["reason"]
    assert len(_out(s, keys.clean_imu("car-1"))) == 199
    assert r.status()["lost_total"] == 0 and r.vehicle_state["car-1"].streams[key].last_t_s == 1.98


def test_a_clock_that_really_jumped_is_rebased_after_a_bounded_number_of_samples(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch, rebase_after=10)
    key = keys.raw_imu("car-1")
    for i in range(50):
        r.handle_sample(key, _imu("car-1", 5000.0 + 0.01 * i, i))
    for i in range(50, 100):  # the source restarted its clock at 0
        r.handle_sample(key, _imu("car-1", 0.01 * i, i))
    clean = _out(s, keys.clean_imu("car-1"))
    assert len(clean) == 50 + 41 and clean[50]["t_s"] == 0.01 * 59
    st = r.status()
    assert st["rebases"] == {"clock": 1} and st["clock_rebases"] == 1
    assert st["rejected"] == {"time_order": 9}


def test_idle_vehicles_and_keys_are_evicted_counted_and_status_stays_bounded(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch, evict_idle_s=30.0)
    for v in range(300):
        for i in range(3):
            r.handle_sample(keys.raw_imu(f"made-up-{v}"), _imu(f"made-up-{v}", 1.0 + i, i * 2))  # 1 gap each
    r.handle_sample(keys.raw_imu("made-up-0"), _imu("made-up-0", 0.5, 9))  # and one refusal
    st = r.status()
    assert st["vehicles_total"] == 300 and len(st["vehicles"]) <= 50
    assert len(st["in"]) == 50 and st["in_keys"] == 300 and st["in_total"] == 901
    assert len(st["drops"]) <= 50 and st["lost"] == {"upstream_gap": 600}
    assert len(msgpack.packb(st)) < 64 << 10
    r.evict_idle(time.monotonic() + 1.0)  # not idle long enough: nothing goes
    assert len(r.vehicle_state) == 300
    r.evict_idle(time.monotonic() + 31.0)
    r.evict_idle(time.monotonic() + 62.0)  # outputs are freed once seen unchanged for the idle time
    assert not r.vehicle_state and not r.count_in and not r.in_seq and not r.key_seen and not r.drops
    assert not r.publishers and not r.count_out and not r.seq
    st = r.status()
    assert st["evicted"] == {"keys": 300, "vehicles": 300, "publishers": 301}  # clean + one rejects
    assert st["lost"] == {"upstream_gap": 600} and st["rejected"] == {"time_order": 1} and st["in_total"] == 901
    # a vehicle that comes back starts afresh
    r.handle_sample(keys.raw_imu("made-up-7"), _imu("made-up-7", 10.0, 100))
    assert list(r.vehicle_state) == ["made-up-7"]


def test_a_failing_handler_is_counted_as_lost_and_the_loop_goes_on(tmp_path, monkeypatch):
    class Broken(Service):
        role, impl = "broken", "b"

        def subscriptions(self):
            return [keys.clean_imu("*")]

        def on_message(self, info, msg, state):
            raise ZeroDivisionError("boom")

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    r = Runner(Broken(instance="b-1"), _Session())
    for i in range(3):
        r.handle_sample(keys.clean_imu("car-1"), _imu("car-1", 1.0 + i, i))
    st = r.status()
    assert st["lost"] == {"handler_error": 3} and "ZeroDivisionError" in st["last_error"]
    assert r.in_seq[keys.clean_imu("car-1")] == 2


def test_drop_reasons_are_lost_skipped_or_rejected():
    from magmesh.runtime import drop_category

    assert [drop_category(x) for x in ("upstream_gap", "handler_error", "queue_overflow", "rejected:range",
                                       "alarm_state_unchanged", "calibrated stream cal/mag in use",
                                       "no_usable_params")] == ["lost", "lost", "lost", "rejected", "skipped",
                                                                "skipped", "skipped"]


def test_alarm_log_survives_a_kill_and_compacts(tmp_path, monkeypatch):
    """Each transition is one appended line (no rewrite of every vehicle's state); a new process of the instance
    reads snapshot + log; a torn last line is ignored; compaction keeps the state."""
    from magmesh import alarmstore

    r, s = _runner(tmp_path, monkeypatch)
    for i, v in enumerate(["car-1", "car-2", "car-3"]):
        r.svc.alarm(v, "dmc", "raised", "warning", "interference", 2.0, 1.0, 10.0 + i)
    r.svc.alarm("car-2", "dmc", "cleared", "warning", "ok again", None, None, 14.0)
    f = r._alarm_file()
    assert not f.exists() and len(f.with_suffix(".log").read_bytes().splitlines()) == 4
    with open(f.with_suffix(".log"), "ab") as fh:
        fh.write(b'{"k":"magmesh/car-9/alarm/dmc","s":"rai')  # killed in the middle of a write
    r2, _ = _runner(tmp_path, monkeypatch)
    r2.restore_alarms()
    assert sorted(r2.raised) == [keys.alarm("car-1", "dmc"), keys.alarm("car-3", "dmc")]
    assert r2.alarm_published[keys.alarm("car-2", "dmc")] == "cleared" and r2.seq[keys.alarm("car-2", "dmc")] == 1
    assert r2.raised[keys.alarm("car-3", "dmc")]["t_s"] == 12.0
    r2._persist_alarms()  # compaction: snapshot written, log emptied, same state
    assert f.exists() and f.with_suffix(".log").read_bytes() == b""
    assert alarmstore.load(f)["published"] == r2.alarm_published
    # an older line than the snapshot's seq changes nothing
    with open(f.with_suffix(".log"), "ab") as fh:
        fh.write(b'{"k":"magmesh/car-2/alarm/dmc","s":"raised","q":0,"m":{}}\n')
    assert alarmstore.load(f)["published"][keys.alarm("car-2", "dmc")] == "cleared"
