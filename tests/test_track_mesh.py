"""Mesh test: multirotor simulator → ingest → track monitor over a real Zenoh router on loopback.

The demo's slow ramp (+0.0125 G/s from 60 s) must raise alarm/mag_anomaly within 5 s of the onset, and
the track stream must carry the cross-track deviation and detector states.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

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


def test_slow_ramp_raises_mag_anomaly_within_the_goal(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config

    vehicle = "drone-t"
    onset = 60.0
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    env = {"MAGMESH_STATE_DIR": str(tmp_path)}
    alarms: list[dict] = []
    tracks: list[dict] = []
    lock = threading.Lock()

    def on_alarm(sample):
        with lock:
            alarms.append(messages.decode(bytes(sample.payload.to_bytes())))

    def on_track(sample):
        with lock:
            tracks.append(messages.decode(bytes(sample.payload.to_bytes())))

    subs = [router.declare_subscriber(keys.alarms_all(vehicle), on_alarm),
            router.declare_subscriber(keys.track(vehicle), on_track)]
    procs = [_spawn("services.ingest", endpoint, env, "--instance", "ingest-t"),
             _spawn("services.track_monitor", endpoint, env, "--instance", "track-t")]
    try:
        for role, inst in (("ingest", "ingest-t"), ("track_monitor", "track-t")):  # services subscribed before the source starts
            assert wait_alive(router, keys.svc_token(role, inst), timeout=60.0), f"{role}/{inst} never came up"
        procs.append(_spawn("sim_publishers.multirotor", endpoint, env, "--vehicle", vehicle, "--instance", "sim-t",
                            "--set", "speed=8", "--set", "duration_s=75", "--set", "truth=false",
                            "--set", "disturbance=slow_ramp", "--set", f"onset_s={onset}"))
        deadline = time.monotonic() + 60.0
        raised = None
        while time.monotonic() < deadline and raised is None:
            with lock:
                raised = next((a for a in alarms if a["source"] == "mag_anomaly" and a["state"] == "raised"), None)
            for p in procs[:2]:
                assert p.poll() is None, p.stderr.read().decode()[-3000:]
            time.sleep(0.2)
        with lock:
            seen = [(a["source"], a["state"], round(a["t_s"], 2)) for a in alarms]
        assert raised is not None, seen
        assert onset <= raised["t_s"] <= onset + 5.0, seen
        assert "detector fired first" in raised["reason"]
        assert not any(a["t_s"] < onset for a in alarms), seen  # no false alarm before the onset
        with lock:
            tr = list(tracks)
        assert len(tr) > 100
        last = tr[-1]
        assert last["route_id"] == "leg-0" and last["track_armed"] and last["gnss_ok"]
        assert 0.0 <= last["cross_track_m"] < 5.0 and last["along_track_m"] > 100.0
        assert last["innovation_sigma_rad"] is not None and not last["innovation_learning"]
        assert any(t["anomaly_alarm"] for t in tr)
        assert "field_deviation_nt" in last  # the magnetometer stream reached the field-strength monitor
    finally:
        for p in procs:
            _stop(p)
        for s in subs:
            s.undeclare()
        router.close()
