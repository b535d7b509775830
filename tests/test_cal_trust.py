"""Who may set calibration parameters, when a consumer runs behind.

A consumer adopts a ``cal/params`` set only when a live calibration instance reports having published it. Under
overload a consumer's queue holds a set for seconds while the calibration service has already published newer
ones on the same key: the older set was genuine when sent and must still be adopted (calibration parameters are
never dropped), while a set nobody published is still refused. One router, two in-process runtimes on real Zenoh
sessions: a calibration instance answering status, and a DMC-role consumer checking sets.
"""

from __future__ import annotations

import threading

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


def _serve_status(runner: Runner, session, stop: threading.Event) -> threading.Thread:
    import zenoh

    q = session.declare_queryable(keys.svc_status(runner.svc.role, runner.svc.instance), zenoh.handlers.FifoChannel(16))

    def loop():
        while not stop.is_set():
            item = q.try_recv()
            if item is None:
                stop.wait(0.01)
                continue
            runner._answer_status(item)

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
