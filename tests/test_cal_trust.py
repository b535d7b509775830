"""Who may set calibration parameters, when a consumer runs behind.

A consumer adopts a ``cal/params`` set only when a live calibration instance reports having published it. Under
overload a consumer's queue holds a set for seconds while the calibration service has already published newer
ones on the same key: the older set was genuine when sent and must still be adopted (calibration parameters are
never dropped), while a set nobody published is still refused. The input path never waits for that answer: a
set not confirmed yet is parked and confirmed from the loop, which goes on handling input. One router, two
in-process runtimes on real Zenoh sessions: a calibration instance answering status (at once, or late like an
overloaded link), and a DMC-role consumer checking sets.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import msgpack
from meshutil import free_port, open_client, open_router

from magmesh import runtime
from magmesh.runtime import Runner, Service
from schemas import keys

FIELDS = dict(sensor="1", status="ok", model="3d", method="arls", offset_nt=[5000.0, -3000.0, 2000.0],
              matrix=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], field_radius_nt=50000.0, rmse_nt=10.0, coverage_frac=1.0,
              n_samples=500, n_gross_rejected=0, observable=[True, True, True], fit_t_s=5.0, fit_duration_ms=1.0)


class _Cal(Service):
    role = "calibration"
    impl = "t"


class _Dmc(Service):
    role = "dmc_detector"
    impl = "t"

    def __init__(self, **kw):
        super().__init__(**kw)
        self.got: list[tuple[str, object, float]] = []  # (type, param_id or seq, when handled)

    def on_message(self, info, msg, state):
        self.got.append((msg["type"], msg.get("param_id", msg["seq"]), time.monotonic()))


def _serve_status(runner: Runner, session, stop: threading.Event, delay: list[float] | None = None) -> threading.Thread:
    """Answer the runner's status queries, each ``delay[0]`` s after it came (a link holding queued frames)."""
    import zenoh

    q = session.declare_queryable(keys.svc_status(runner.svc.role, runner.svc.instance), zenoh.handlers.FifoChannel(16))
    held: deque = deque()

    def loop():
        while not stop.is_set():
            item = q.try_recv()
            if item is not None:
                held.append((time.monotonic() + (delay[0] if delay else 0.0), item))
            while held and held[0][0] <= time.monotonic():
                runner._answer_status(held.popleft()[1])
            if item is None:
                stop.wait(0.01)

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    return t


def test_a_set_superseded_while_queued_is_still_adopted_a_forged_one_is_not(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    port = free_port()
    router = open_router(port)
    cal_s, dmc_s = open_client(port), open_client(port)
    stop = threading.Event()
    try:
        cal = Runner(_Cal(instance="cal-1"), cal_s)
        _serve_status(cal, cal_s, stop)
        key = keys.cal_params("car-1", "1")
        sent = [cal._send(key, "cal_params", "car-1", 10.0 + i, dict(FIELDS, param_id=f"p{i}"))
                for i in range(runtime.CAL_RECENT + 3)]
        dmc = Runner(_Dmc(instance="dmc-1"), dmc_s)
        # the newest, one superseded a moment ago and the oldest still remembered are genuine
        for m in (sent[-1], sent[-2], sent[-1 - runtime.CAL_RECENT]):
            assert dmc.cal_params_trusted(key, m), m["param_id"]
        assert dmc.rejects_total == 0
        # older than what the calibration instance remembers, or never published: refused and counted
        too_old = sent[-2 - runtime.CAL_RECENT]
        forged = dict(sent[-1], param_id="forged", seq=sent[-1]["seq"] + 1)
        assert not dmc.cal_params_trusted(key, too_old)
        assert not dmc.cal_params_trusted(key, forged)
        assert dmc.rejects_total == 2
        assert dict(dmc.drops[key]) == {"rejected:other": 2}
        # another vehicle's key confirms nothing of this one
        other = dict(sent[-1], vehicle="car-2")
        assert not dmc.cal_params_trusted(keys.cal_params("car-2", "1"), other)
    finally:
        stop.set()
        for s in (cal_s, dmc_s, router):
            s.close()


def _imu(vehicle, t, seq):
    from schemas import make

    return msgpack.packb(make("imu", vehicle, t, seq, gyro_rad_s=[0.01, 0.0, 0.0], accel_m_s2=[0.0, 0.1, 9.8]),
                         use_bin_type=True)


def _mesh(tmp_path, monkeypatch, delay):
    """A calibration instance answering status ``delay[0]`` s late, and a DMC-role consumer running its loop."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    port = free_port()
    router = open_router(port)
    cal_s, dmc_s = open_client(port), open_client(port)
    stop = threading.Event()
    cal = Runner(_Cal(instance="cal-1"), cal_s)
    _serve_status(cal, cal_s, stop, delay)
    dmc = Runner(_Dmc(instance="dmc-1"), dmc_s)
    t = threading.Thread(target=dmc.loop, daemon=True)
    t.start()

    def close():
        dmc.stop()
        t.join(5)
        stop.set()
        for s in (cal_s, dmc_s, router):
            s.close()
    return cal, dmc, close


def _put(dmc, key, msg):
    from schemas import messages

    dmc.q.put(("s", key, messages.encode(msg)))


def _until(cond, timeout):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.02)
    return cond()


def test_a_set_confirmed_late_is_adopted_and_the_loop_goes_on_meanwhile(tmp_path, monkeypatch):
    delay = [1.0]  # every status answer comes a second after the query: the link holds a second of frames
    cal, dmc, close = _mesh(tmp_path, monkeypatch, delay)
    try:
        key = keys.cal_params("car-1", "1")
        p0 = cal._send(key, "cal_params", "car-1", 10.0, dict(FIELDS, param_id="p0"))
        t0 = time.monotonic()
        _put(dmc, key, p0)
        put_at = {}
        pending_seen = 0
        imu_key = keys.raw_imu("car-1")
        for i in range(30):  # other input every 50 ms while the set waits for its confirmation
            put_at[i] = time.monotonic()
            dmc.q.put(("s", imu_key, _imu("car-1", 10.0 + 0.01 * i, i)))
            pending_seen = max(pending_seen, dmc.status()["cal_params_pending"])
            time.sleep(0.05)
        assert _until(lambda: any(g[1] == "p0" for g in dmc.svc.got), 5.0)
        adopted_at = next(g[2] for g in dmc.svc.got if g[1] == "p0")
        imu_lag = [g[2] - put_at[g[1]] for g in dmc.svc.got if g[0] == "imu"]
        assert len(imu_lag) == 30
        # the confirmation came late (the answer took a second) and the loop was never held up meanwhile
        print(f"adopted after {adopted_at - t0:.3f} s, input lag max {max(imu_lag) * 1e3:.1f} ms")
        assert 0.9 <= adopted_at - t0 < 3.0, adopted_at - t0
        assert max(imu_lag) < 0.5, max(imu_lag)
        assert pending_seen == 1 and dmc.status()["cal_params_pending"] == 0
        assert dmc.rejects_total == 0 and dmc.status()["lost_total"] == 0
        assert dmc.in_seq.get(key) == p0["seq"]
    finally:
        close()


def test_a_forged_set_is_refused_after_the_give_up_time_and_a_superseded_one_is_skipped(tmp_path, monkeypatch):
    monkeypatch.setattr(runtime, "CAL_GIVE_UP_S", 1.5)
    delay = [0.6]
    cal, dmc, close = _mesh(tmp_path, monkeypatch, delay)
    try:
        key = keys.cal_params("car-1", "1")
        p1, p2 = (cal._send(key, "cal_params", "car-1", 10.0 + i, dict(FIELDS, param_id=f"p{i}")) for i in (1, 2))
        # two genuine sets queued behind each other, both waiting: the newer is adopted, the older superseded
        _put(dmc, key, p1)
        _put(dmc, key, p2)
        assert _until(lambda: any(g[1] == "p2" for g in dmc.svc.got), 5.0)
        assert [g[1] for g in dmc.svc.got] == ["p2"]
        assert dict(dmc.drops[key]) == {"cal_params_superseded": 1}
        assert runtime.drop_category("cal_params_superseded") == "skipped"
        # a forged set parked behind a genuine one does not supersede it: the genuine one is adopted, the
        # forged one refused once the give-up time has passed with answers that do not report it
        p3 = cal._send(key, "cal_params", "car-1", 13.0, dict(FIELDS, param_id="p3"))
        forged = dict(p3, param_id="forged", seq=p3["seq"] + 1)
        t0 = time.monotonic()
        _put(dmc, key, p3)
        _put(dmc, key, forged)
        assert _until(lambda: dmc.rejects_total == 1, 6.0)
        refused_after = time.monotonic() - t0
        assert [g[1] for g in dmc.svc.got] == ["p2", "p3"]
        print(f"forged set refused after {refused_after:.3f} s")
        assert refused_after >= 1.5, refused_after
        st = dmc.status()
        assert dict(dmc.drops[key]) == {"cal_params_superseded": 1, "rejected:other": 1}
        assert st["cal_params_pending"] == 0 and st["lost_total"] == 0
        # a set whose answers never come (none within the give-up time) is refused too, not adopted
        delay[0] = 30.0
        p4 = cal._send(key, "cal_params", "car-1", 14.0, dict(FIELDS, param_id="p4"))
        _put(dmc, key, p4)
        assert _until(lambda: dmc.rejects_total == 2, 8.0)
        assert "p4" not in [g[1] for g in dmc.svc.got]
    finally:
        close()
