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
    r3.reconcile_alarms()  # nothing raised it since the restart: cleared, seq continues
    assert [(m["state"], m["seq"]) for _, m in s3.out] == [("cleared", 1)]
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
