"""Mesh test: car simulator → ingest → calibration over a real Zenoh router on loopback.

Checks that the car's parameters converge on cal/params (ARLS after the initial circle), that
cal/mag carries calibrated samples tagged with the parameter set, that a late joiner gets the
parameters by query, and that a restarted service answers at once from its saved state.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from meshutil import free_port, wait_alive

from schemas import keys, messages

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.mesh


def _spawn(module: str, endpoint: str, env_extra: dict, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO), **env_extra}
    return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint, *args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)


def _query(session, key: str, timeout_s: float = 3.0) -> list[dict]:
    out = []
    for reply in session.get(key, timeout=timeout_s):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
    return out


def test_car_parameters_converge_are_queryable_and_survive_a_restart(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config
    from sim_publishers.car import core as car

    vehicle = "car-t"
    truth = car.true_mag_params(car.CarSimSettings(vehicle_seed=7), 50_000.0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    env = {"MAGMESH_STATE_DIR": str(tmp_path)}
    params: list[dict] = []
    calmag: list[dict] = []
    lock = threading.Lock()

    def on_params(sample):
        with lock:
            params.append(messages.decode(bytes(sample.payload.to_bytes())))

    def on_calmag(sample):
        with lock:
            if len(calmag) < 5000:
                calmag.append(messages.decode(bytes(sample.payload.to_bytes())))

    subs = [router.declare_subscriber(keys.cal_params(vehicle, "*"), on_params),
            router.declare_subscriber(keys.cal_mag(vehicle, "*"), on_calmag)]
    cal_args = ("--instance", "cal-t", "--set", "refit_interval_s=5")
    procs = [_spawn("services.ingest", endpoint, env, "--instance", "ingest-t"),
             _spawn("services.calibration", endpoint, env, *cal_args)]
    try:
        for role, inst in (("ingest", "ingest-t"), ("calibration", "cal-t")):  # services subscribed before the source starts
            assert wait_alive(router, keys.svc_token(role, inst), timeout=60.0), f"{role}/{inst} never came up"
        procs.append(_spawn("sim_publishers.car", endpoint, env, "--vehicle", vehicle, "--instance", "sim-t",
                            "--set", "speed=8", "--set", "duration_s=150", "--set", "truth=false"))
        deadline = time.monotonic() + 60.0
        ok: dict[str, dict] = {}
        while time.monotonic() < deadline and len(ok) < 2:
            with lock:
                for m in params:
                    if m["status"] == "ok":
                        ok[m["sensor"]] = m
            for p in procs[:2]:
                assert p.poll() is None, p.stderr.read().decode()[-3000:]
            time.sleep(0.2)
        assert set(ok) == {"1", "2"}, [(m["sensor"], m["status"], m.get("reason")) for m in params]
        for sid, m in ok.items():
            assert m["method"] in ("arls", "ekf") and m["model"] == "2d"
            assert m["observable"] == [True, True, False]
            err = np.linalg.norm(np.array(m["offset_nt"][:2]) - truth[sid].offset_nt[:2])
            assert err < 1500, (sid, m["offset_nt"], truth[sid].offset_nt)  # 3% of the field or better
        # cal/mag: calibrated, tagged with a published parameter set
        tagged: list[dict] = []
        deadline = time.monotonic() + 30.0
        while not tagged and time.monotonic() < deadline:
            time.sleep(0.2)
            with lock:
                tagged = [m for m in calmag if m.get("param_id") in {p["param_id"] for p in params}]
        assert tagged, "no cal/mag sample tagged with a published parameter set"
        assert all(m["calibrated"] for m in tagged)
        _stop(procs[2])  # source stopped: the sets in use stay put from here on
        time.sleep(1.0)
        # a late joiner: the query answers with the current set of each sensor
        with zenoh.open(build_config(mode="client", connect=[endpoint])) as late:
            replies = [messages.decode(bytes(b)) for b in _query(late, keys.cal_params(vehicle, "*"))]
            assert {r["sensor"] for r in replies} == {"1", "2"}
            st = msgpack.unpackb(_query(late, keys.svc_status("calibration", "cal-t"))[0], raw=False)
            assert st["calibration"]["vehicles"][vehicle]["sensors"]["1"]["params"]["status"] in ("ok",)
        saved_before_restart = {r["sensor"]: r["param_id"] for r in replies}
        # restart: saved parameters come back at once (the source is stopped: no new data)
        _stop(procs[1])
        assert list(tmp_path.glob("calibration/*.json")), "no parameter set saved"
        procs[1] = _spawn("services.calibration", endpoint, env, *cal_args)
        assert wait_alive(router, keys.svc_token("calibration", "cal-t"), timeout=60.0), "restart never came up"
        got: dict[str, str] = {}
        deadline = time.monotonic() + 30.0
        with zenoh.open(build_config(mode="client", connect=[endpoint])) as late:
            while set(got) != {"1", "2"} and time.monotonic() < deadline:
                replies = [messages.decode(bytes(b)) for b in _query(late, keys.cal_params(vehicle, "*"))]
                got = {r["sensor"]: r["param_id"] for r in replies}
                time.sleep(0.2)
        assert got == saved_before_restart, (got, saved_before_restart)
    finally:
        for p in procs:
            _stop(p)
        for s in subs:
            s.undeclare()
        router.close()
