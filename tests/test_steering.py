"""Who may steer the open demo: state changes are accepted only from the instance that holds the role.

One mesh of real processes (car simulator, ingest, calibration, DMC detector, an alarm toggler, under
``magmesh up``) and an outside client on the same endpoint playing the attacker:

- a forged ``cal/params`` (not published by the calibration service) is refused by the DMC detector, reported
  on ``rejects`` as untrusted, while the calibration service's own parameters are adopted;
- a forged "cleared" for an alarm its holder still holds raised does not remove it from the supervisor's list,
  a forged "raised" does not add one; the holder's own "cleared" does remove it.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import pytest
from meshutil import REPO, Collector, endpoint, free_port, open_client, query_status, stop, wait_alive

from schemas import keys, messages

pytestmark = pytest.mark.mesh

TOGGLE_PERIOD_S = 12.0


def port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def wait_until(pred, timeout: float):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.1)
    return pred()


def alarm(vehicle: str, source: str, state: str, service: str) -> bytes:
    return messages.encode(messages.make("alarm", vehicle, time.time(), 50, source=source, state=state,
                                         severity="warning", reason="forged", value=0.0, threshold=0.5,
                                         service=service))


def forged_params(seq: int) -> bytes:
    return messages.encode(messages.make(
        "cal_params", "car-1", 5.0, seq, sensor="1", param_id="forged-1", status="ok", model="3d", method="arls",
        offset_nt=[5000.0, -3000.0, 2000.0], matrix=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], field_radius_nt=50000.0,
        rmse_nt=10.0, coverage_frac=1.0, n_samples=500, n_gross_rejected=0, observable=[True, True, True],
        fit_t_s=5.0, fit_duration_ms=1.0))


def test_only_the_holder_steers(tmp_path):
    port = free_port()
    sup = subprocess.Popen(
        [sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--endpoint", endpoint(port),
         "--only", "sim-car-1,ingest-1,calibration-1,dmc-1", "--duration", "240",
         "--log-dir", str(tmp_path / "logs"), "--quiet", "--set", "sim-car-1.speed=1"],
        cwd=REPO, stdout=open(tmp_path / "up.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True,
        env={**os.environ, "MAGMESH_STATE_DIR": str(tmp_path / "state")})
    toggler = client = None
    try:
        assert wait_until(lambda: sup.poll() is not None or port_open(port), 60) and sup.poll() is None, \
            (tmp_path / "up.log").read_text()[-2000:]
        client = open_client(port)
        toggler = subprocess.Popen(
            [sys.executable, str(REPO / "tests" / "alarm_toggler.py"), "--connect", endpoint(port), "--instance",
             "toggler-1", "--set", "vehicle=car-9", "--set", f"period_s={TOGGLE_PERIOD_S}", "--set", "count=2"],
            cwd=REPO, stdout=open(tmp_path / "toggler.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True,
            env={**os.environ, "MAGMESH_STATE_DIR": str(tmp_path / "state")})
        rejects = Collector(client, keys.rejects("car-1"))
        for role, inst in (("dmc_detector", "dmc-1"), ("calibration", "calibration-1"),
                           ("alarm_toggler", "toggler-1")):
            assert wait_alive(client, keys.svc_token(role, inst), 90), f"{inst} never came up"

        # ---- cal/params: the calibration service's set is adopted, a forged one is not
        def det_params():
            st = query_status(client, keys.svc_status("dmc_detector", "dmc-1")) or {}
            return ((st.get("detector") or {}).get("car-1") or {}).get("params", {}).get("1")

        # the detector starts from the manifest (param_id "manifest"); the calibration service's set is "1-manifest"
        genuine = wait_until(lambda: (p := det_params()) and p["param_id"] == "1-manifest" and p, 60)
        assert genuine, f"the calibration service's own set was not adopted: {det_params()}"
        client.put(keys.cal_params("car-1", "1"), forged_params(10_000))
        hits = rejects.wait_for(lambda k, m: isinstance(m, dict) and m.get("code") == "other"
                                and m.get("reason", "").startswith("untrusted")
                                and m.get("service") == "dmc-1", 20)
        assert hits, "the forged cal/params were not refused as untrusted"
        assert "only a calibration service" in hits[0][1]["reason"]
        time.sleep(1.0)
        assert det_params()["param_id"] == "1-manifest", "the DMC detector adopted forged calibration parameters"

        # ---- the supervisor's list of raised alarms follows the holder
        toggle = keys.alarm("car-9", "toggle")

        def sup_status():
            return query_status(client, keys.svc_status("supervisor", "main")) or {}

        assert wait_until(lambda: toggle in sup_status().get("alarms_raised", []), 60), "the toggler never raised"
        ignored0 = sup_status()["alarms_ignored"]
        client.put(toggle, alarm("car-9", "toggle", "cleared", "toggler-1"))  # the holder's name, not the holder
        forged_raise = keys.alarm("car-9", "forged")
        client.put(forged_raise, alarm("car-9", "forged", "raised", "toggler-1"))
        # both forgeries reached the supervisor (counted as not confirmed) and changed nothing
        assert wait_until(lambda: sup_status().get("alarms_ignored", 0) >= ignored0 + 2, 10), sup_status()
        st = sup_status()
        assert toggle in st["alarms_raised"], "a forged 'cleared' removed an alarm its holder still holds"
        assert forged_raise not in st["alarms_raised"], "a forged 'raised' entered the supervisor's list"
        # the holder's own clear is taken
        assert wait_until(lambda: toggle not in sup_status().get("alarms_raised", [toggle]),
                          TOGGLE_PERIOD_S + 30), "the holder's 'cleared' was not taken"
        print(f"\nsteering: forged cal/params refused ({hits[0][1]['reason'][:90]}...); supervisor ignored "
              f"{sup_status()['alarms_ignored'] - ignored0} forged alarm transitions, took the holder's clear")
    finally:
        if client is not None:
            client.close()
        if toggler is not None:
            stop(toggler)
        stop(sup, 15)
