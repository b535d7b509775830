"""Restarts, in process: the seq journal survives a kill, a restarted instance counts what it missed and
continues its seqs, and a restored raised alarm is never cleared by the restart itself."""

from __future__ import annotations

from magmesh.journal import Journal
from magmesh.runtime import Runner, Service
from schemas import keys, messages


class _Pub:
    def __init__(self, out, key):
        self.out, self.key = out, key

    def put(self, payload):
        self.out.append((self.key, messages.decode(payload)))


class _Session:
    def __init__(self):
        self.out = []

    def declare_publisher(self, key, **kw):
        return _Pub(self.out, key)


class _Relay(Service):
    """Republishes every clean magnetometer sample on cal/mag (one output per input)."""

    role = "relay"
    impl = "relay"

    def on_message(self, info, msg, state):
        self.publish(keys.cal_mag(info.vehicle, "1"), "mag", info.vehicle, msg["t_s"], sensor="1", b_nt=msg["b_nt"])


class _Latch(_Relay):
    ADOPTS_RESTORED_ALARMS = True


def _feed(r: Runner, seqs) -> None:
    for sq in seqs:
        r.handle_sample(keys.clean_mag("car-1", "1"), messages.encode(messages.make(
            "mag", "car-1", 10.0 + 0.02 * sq, sq, sensor="1", b_nt=[20000.0, 1000.0, -40000.0])))


def _runner(tmp_path, monkeypatch, cls=_Relay):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    r = Runner(cls(instance="relay-1"), sess)
    r.restore_alarms()
    r.resume_journal()
    return r, sess


def test_journal_survives_a_kill_and_goes_with_a_clean_stop(tmp_path):
    j = Journal(tmp_path / "x.seq")
    j.open({})
    for i in range(1000):
        j.set("ia", i)
    j.set("ob", 7)
    j.begin("ia", 1000, 5)  # killed while handling input seq 1000, after 5 outputs, before any of its own
    # no close, no flush: a kill -9 leaves the page cache as it is
    got = Journal(tmp_path / "x.seq").load()
    assert {k: v for k, v in got.items() if not k.startswith("~")} == {"ia": 999, "ob": 7}
    assert j.in_progress(got) == ("ia", 1000) and got["~sent_at_begin"] == 5 and got["~sent"] == 0
    j2 = Journal(tmp_path / "x.seq")
    j2.open({k: v for k, v in j2.load().items() if not k.startswith("~")})  # a second crash right after
    assert {k: v for k, v in Journal(tmp_path / "x.seq").load().items() if not k.startswith("~")} == \
        {"ia": 999, "ob": 7}
    j2.remove()
    assert Journal(tmp_path / "x.seq").load() == {}


def test_restart_counts_what_it_missed_and_continues_its_seqs(tmp_path, monkeypatch):
    r, s = _runner(tmp_path, monkeypatch)
    _feed(r, range(0, 50))
    assert r.resumed_from is None and [m["seq"] for _, m in s.out] == list(range(50))
    # killed: nothing of r is closed. A new process of the same instance misses inputs 50..69
    r2, s2 = _runner(tmp_path, monkeypatch)
    assert r2.resumed_from == {"inputs": 1, "outputs": 1}
    _feed(r2, range(70, 80))
    key = keys.clean_mag("car-1", "1")
    assert r2.drops[key]["lost_during_restart"] == 20
    assert r2.drops[key].get("upstream_gap", 0) == 0
    assert [m["seq"] for _, m in s2.out] == list(range(50, 60)), "output seq did not continue"
    _feed(r2, range(82, 83))  # a later gap is an ordinary upstream gap
    assert r2.drops[key]["upstream_gap"] == 2 and r2.drops[key]["lost_during_restart"] == 20
    # killed again: the count of the first restart is carried on, the second adds to it
    r2b, _ = _runner(tmp_path, monkeypatch)
    _feed(r2b, range(90, 91))
    assert r2b.drops[key]["lost_during_restart"] == 27
    r2 = r2b
    # a clean stop: the next start is a fresh one
    r2.clean_stop = True
    r2.close()
    r3, s3 = _runner(tmp_path, monkeypatch)
    _feed(r3, range(200, 201))
    assert r3.resumed_from is None and not r3.drops[key]
    assert [m["seq"] for _, m in s3.out] == [0]


def test_a_kill_after_a_samples_outputs_does_not_count_it_missed(tmp_path, monkeypatch):
    r, s = _runner(tmp_path, monkeypatch)
    _feed(r, range(0, 10))
    # killed inside the handling of input 10, after its output went out (its journal entry not written yet)
    r.journal.begin("i" + keys.clean_mag("car-1", "1"), 10, r.n_sent)
    r.n_sent += 1
    r.journal.sent(r.n_sent)
    r2, _ = _runner(tmp_path, monkeypatch)
    _feed(r2, range(15, 16))
    assert r2.drops[keys.clean_mag("car-1", "1")]["lost_during_restart"] == 4  # 11..14; 10 was handled
    # killed inside the handling of input 16 before any of its outputs: 16 counts as missed
    r2.journal.begin("i" + keys.clean_mag("car-1", "1"), 16, r2.n_sent)
    r3, _ = _runner(tmp_path, monkeypatch)
    _feed(r3, range(20, 21))
    assert r3.drops[keys.clean_mag("car-1", "1")]["lost_during_restart"] == 4 + 4  # 16..19


def test_restored_alarm_is_not_cleared_by_the_restart(tmp_path, monkeypatch):
    r, s = _runner(tmp_path, monkeypatch)
    r.svc.alarm("car-1", "dmc", "raised", "warning", "interference", 2.0, 1.0, 10.0)
    akey = keys.alarm("car-1", "dmc")
    # a latching logic takes the alarm over: the runtime never clears it, the logic does when the condition goes
    r2, s2 = _runner(tmp_path, monkeypatch, _Latch)
    assert r2.svc.holds_alarm("car-1", "dmc") and not r2.reconcile_pending
    _feed(r2, range(0, 2000))  # 40 s of input in which the logic does not speak
    r2.reconcile_alarms()
    assert [m for _, m in s2.out if m["type"] == "alarm"] == [] and akey in r2.raised
    r2.svc.alarm("car-1", "dmc", "cleared", "warning", "field clean again", 0.1, 1.0, 60.0)
    assert [(m["state"], m["seq"]) for _, m in s2.out if m["type"] == "alarm"] == [("cleared", 1)]


def test_restored_alarm_of_a_non_latching_logic_waits_for_input(tmp_path, monkeypatch):
    r, _ = _runner(tmp_path, monkeypatch)
    r.svc.alarm("car-1", "dmc", "raised", "warning", "interference", 2.0, 1.0, 10.0)
    r2, s2 = _runner(tmp_path, monkeypatch)
    alarms = lambda: [m for _, m in s2.out if m["type"] == "alarm"]  # noqa: E731
    r2.reconcile_alarms()
    _feed(r2, range(0, 100))  # 2 s of sample time: not enough to decide
    r2.reconcile_alarms()
    assert alarms() == []
    _feed(r2, range(100, 400))  # 8 s: the logic had its chance to raise it again and did not
    r2.reconcile_alarms()
    assert [m["state"] for m in alarms()] == ["cleared"] and "after a restart" in alarms()[0]["reason"]


def test_a_key_received_but_never_handled_before_a_kill_is_counted_from_its_first_sample(tmp_path, monkeypatch):
    """Samples queued behind a slow start (a JIT compile, a model load) and never handled when the process is
    killed: the first one received is journalled, so the restart counts the key's loss from there, across a
    second crash too, and ranges name which seqs."""
    key = keys.clean_mag("car-1", "1")
    r, _ = _runner(tmp_path, monkeypatch)
    for sq in (30, 31, 32):  # received (reader thread), still queued when killed
        r._note_first_rx(key, messages.encode(messages.make("mag", "car-1", 10.0 + sq, sq, sensor="1",
                                                            b_nt=[20000.0, 1000.0, -40000.0])))
    r2, _ = _runner(tmp_path, monkeypatch)  # killed; the restart receives nothing of the key either
    r2._note_first_rx(key, messages.encode(messages.make("mag", "car-1", 50.0, 50, sensor="1",
                                                         b_nt=[20000.0, 1000.0, -40000.0])))
    r3, s3 = _runner(tmp_path, monkeypatch)  # killed again
    _feed(r3, range(60, 62))
    assert r3.drops[key]["lost_during_restart"] == 30  # seqs 30..59: never handled by any run
    assert r3.restart_gaps[key] == [[30, 59]]
    assert [m["seq"] for _, m in s3.out] == [0, 1]


def test_journal_frees_the_slots_of_forgotten_keys_and_uses_them_again(tmp_path):
    j = Journal(tmp_path / "x.seq")
    j.open({})
    j.set("ia", 5)
    j.set("ib", 6)
    j.forget(["ia", "i-never-seen"])
    assert {k: v for k, v in Journal(tmp_path / "x.seq").load().items() if not k.startswith("~")} == {"ib": 6}
    n = j.n_slots
    j.set("ic", 7)  # takes ia's slot
    assert j.n_slots == n and j.slot["ic"] not in (j.slot["ib"],)
    assert {k: v for k, v in Journal(tmp_path / "x.seq").load().items() if not k.startswith("~")} == \
        {"ib": 6, "ic": 7}
    j.begin("ic", 8, 0)
    assert j.in_progress(Journal(tmp_path / "x.seq").load()) == ("ic", 8)


def test_an_evicted_key_leaves_nothing_behind(tmp_path, monkeypatch):
    """Idle eviction frees a key's first-received seq and its journal entries, so churn of vehicles neither
    grows the process nor fills the journal, and a later restart does not count the idle time as missed."""
    key = keys.clean_mag("car-1", "1")
    r, sess = _runner(tmp_path, monkeypatch)
    r._note_first_rx(key, messages.encode(messages.make("mag", "car-1", 10.0, 0, sensor="1",
                                                        b_nt=[20000.0, 1000.0, -40000.0])))
    _feed(r, range(0, 3))
    assert "i" + key in r.journal.slot and "f" + key in r.journal.slot
    out_key = sess.out[0][0]
    assert "o" + out_key in r.journal.slot
    r.evict_idle(now=1e12)
    r.evict_idle(now=2e12)  # outputs go once seen idle over a whole period
    assert key not in r._first_rx
    assert not [k for k in r.journal.slot if not k.startswith("~")], r.journal.slot
    r2, _ = _runner(tmp_path, monkeypatch)  # killed; the vehicle comes back much later
    _feed(r2, range(1000, 1002))
    assert r2.drops.get(key, {}).get("lost_during_restart", 0) == 0


def test_a_join_loss_right_after_a_restart_is_a_loss_of_the_restart(tmp_path, monkeypatch):
    """A partner held in the join of the process that died never comes back: the sample that waited for it is
    counted lost_during_restart (until the vehicle's first output after the restart), later ones as skipped."""
    key2 = keys.clean_mag("car-1", "2")
    r, _ = _runner(tmp_path, monkeypatch)
    _feed(r, range(0, 3))
    r2, _ = _runner(tmp_path, monkeypatch)  # killed; restarted
    assert r2.recovering == {"car-1": "lost_during_restart"}
    r2.svc.count_join_loss(key2, "car-1", "unpaired")
    assert r2.drops[key2]["lost_during_restart"] == 1 and r2.drops[key2]["unpaired"] == 0
    assert r2.journal.slot.get("l" + key2) is not None
    _feed(r2, range(3, 4))  # an output of car-1: its logic now runs on what this process received
    assert not r2.recovering
    r2.svc.count_join_loss(key2, "car-1", "unpaired")
    assert r2.drops[key2]["unpaired"] == 1 and r2.drops[key2]["lost_during_restart"] == 1


def test_journal_open_beside_receive_threads_loses_no_key_and_keeps_its_layout(tmp_path, monkeypatch):
    """Receive threads journal first-received seqs while the service opens its journal: the open never fails
    (one writer of the index at a time), the reserved slots stay first, and every key set once the journal is
    open is in what a restarted run loads. (The index's rename is slowed to widen the window of a race.)"""
    import os
    import threading
    import time

    import magmesh.journal as journal

    real_replace = os.replace

    def slow_replace(a, b):
        time.sleep(0.002)
        real_replace(a, b)

    monkeypatch.setattr(journal.os, "replace", slow_replace)

    for trial in range(10):
        j = Journal(tmp_path / f"x{trial}.seq")
        go, opened = threading.Event(), threading.Event()
        after_open: list[list[str]] = [[] for _ in range(3)]

        def hammer(n: int, seen: list[str], j=j, go=go, opened=opened) -> None:
            go.wait()
            for i in range(300):
                was_open = opened.is_set()
                k = f"f{n}-{i}"
                j.set(k, i)
                if was_open:
                    seen.append(k)

        threads = [threading.Thread(target=hammer, args=(n, after_open[n])) for n in range(3)]
        for t in threads:
            t.start()
        go.set()
        j.open({"ocarried": 41})
        opened.set()
        for t in threads:
            t.join()
        loaded = Journal(tmp_path / f"x{trial}.seq").load()
        assert loaded["~names"][:4] == ["~slot", "~seq", "~sent_at_begin", "~sent"], loaded["~names"][:6]
        assert loaded["ocarried"] == 41
        missing = [k for seen in after_open for k in seen if k not in loaded]
        assert not missing, f"trial {trial}: {len(missing)} keys set after open are not in the journal"


def test_journal_index_grows_by_appended_lines(tmp_path):
    """A new key costs one appended index line (not a rewrite of every key's name); a restart reads the index
    and its log, a freed slot and a torn last line included."""
    from magmesh.journal import Journal

    j = Journal(tmp_path / "svc.seq")
    j.open({"imagmesh/car-1/clean/imu": 4})
    size0 = j.index_path.stat().st_size
    for i in range(300):
        j.set(f"omagmesh/car-{i}/dmc", i)
    assert j.slots_of(["omagmesh/car-5/dmc", "omagmesh/bus-1/dmc"])[0] == j.slot["omagmesh/car-5/dmc"]
    j.forget(["omagmesh/car-7/dmc"])
    assert j.index_path.stat().st_size == size0  # the index itself was not rewritten
    with open(j.index_log, "ab") as f:
        f.write(b"4000\tomagmesh/car-t")  # killed in the middle of a line
    prev = Journal(tmp_path / "svc.seq").load()
    assert prev["imagmesh/car-1/clean/imu"] == 4 and prev["omagmesh/car-299/dmc"] == 299
    assert "omagmesh/car-7/dmc" not in prev and "omagmesh/bus-1/dmc" not in prev  # empty value: nothing to carry
    j2 = Journal(tmp_path / "svc.seq")
    j2.open(prev)  # the next run starts from a fresh index and an empty log
    assert j2.index_log.read_bytes() == b"" and Journal(tmp_path / "svc.seq").load()["omagmesh/car-3/dmc"] == 3


class _RowRelay(_Relay):
    """The same relay, its outputs through publish_rows (the path the fleet-frame services take per vehicle)."""

    def on_message(self, info, msg, state):
        self.publish_rows("mag", [keys.cal_mag(info.vehicle, "1")], [info.vehicle], [msg["t_s"]],
                          {"sensor": "1", "b_nt": [msg["b_nt"]]})


class _Killed(BaseException):  # not an Exception: nothing in the runtime catches it, as nothing survives a kill
    pass


def test_a_kill_at_a_rows_put_counts_its_input_handled_and_leaves_a_seq_gap(tmp_path, monkeypatch):
    """Killed at the put of a row (publish_rows): the journal has numbered the output, so the input counts as
    handled — the output that never left is the seq gap its consumers see, not also a lost input (the sent
    count written after the loop had counted it twice)."""
    r, s = _runner(tmp_path, monkeypatch, _RowRelay)
    _feed(r, range(0, 10))
    assert [m["seq"] for _, m in s.out] == list(range(10))

    def die(payload):
        raise _Killed

    for c in r._row_cache.values():
        c[0].put = die
    try:
        _feed(r, range(10, 11))
    except _Killed:
        pass
    r2, s2 = _runner(tmp_path, monkeypatch, _RowRelay)
    _feed(r2, range(15, 16))
    assert r2.drops[keys.clean_mag("car-1", "1")]["lost_during_restart"] == 4  # 11..14; 10 was handled
    assert [m["seq"] for _, m in s2.out] == [11]  # 10 was numbered and never left: a gap, not a repeat
