"""Mesh test: car simulator → ingest → dmc_detector (FCM) → heading_fuser over a Zenoh router on loopback.

The car drives the urban layout (a steel bridge on its first streets). The fuser must publish valid
``heading`` messages with gap-free sequence numbers, switch to ``gyro_only`` while the DMC says the
magnetic heading is invalid and come back to ``magnetic`` after, and stay close to the simulator's
truth (``truth/pose``) over the drive.
"""

from __future__ import annotations

import math
import time
import tomllib

import numpy as np
import pytest
from meshutil import Collector, open_router, query_status, spawn, stop, wait_alive
from meshutil import free_port as _free_port

from schemas import keys, messages

pytestmark = pytest.mark.mesh


def _manifest(tmp_path) -> str:
    from magmesh.paths import DEPLOY_DIR

    with open(DEPLOY_DIR / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    lines = ["[vehicles.car-1]", 'kind = "car"', f"declination_rad = {car['declination_rad']!r}"]
    for sensor, t in car["mag_params"].items():
        lines += [f'[vehicles.car-1.mag_params."{sensor}"]', f"offset_nt = {list(t['offset_nt'])!r}",
                  f"matrix = {list(t['matrix'])!r}", f"field_radius_nt = {t['field_radius_nt']!r}"]
    p = tmp_path / "mesh.toml"
    p.write_text("\n".join(lines) + "\n")
    return str(p)


def test_heading_switches_to_gyro_at_the_bridge_and_back(tmp_path):
    pytest.importorskip("zenoh")
    port = _free_port()
    router = open_router(port)
    heading = Collector(router, keys.heading("car-1"))
    pose = Collector(router, keys.truth("car-1", "pose"))
    alarms = Collector(router, keys.alarm("car-1", "heading"))
    procs = []
    duration = 150.0
    manifest = _manifest(tmp_path)
    try:
        procs.append(spawn("services.ingest", port, "--instance", "ingest-h", log_path=tmp_path / "ingest.log"))
        procs.append(spawn("services.dmc_detector", port, "--impl", "fcm", "--instance", "dmc-h",
                           "--manifest", manifest, log_path=tmp_path / "dmc.log"))
        procs.append(spawn("services.heading_fuser", port, "--instance", "heading-h", "--manifest", manifest,
                           log_path=tmp_path / "heading.log"))
        for role, inst in (("ingest", "ingest-h"), ("dmc_detector", "dmc-h"), ("heading_fuser", "heading-h")):
            assert wait_alive(router, keys.svc_token(role, inst)), (tmp_path / "heading.log").read_text()[-3000:]
        # 5× real time: the fuser waits for late DMC verdicts up to dmc_timeout_s of sample time, which an
        # as-fast-as-possible replay can exceed
        procs.append(spawn("sim_publishers.car", port, "--vehicle", "car-1", "--instance", "sim-h",
                           "--set", "speed=5", "--set", f"duration_s={duration}", "--set", "layout=urban_a",
                           log_path=tmp_path / "sim.log"))
        deadline = time.monotonic() + 240.0
        while time.monotonic() < deadline:
            got = heading.matching(lambda k, m: True)
            if got and got[-1][1]["t_s"] >= duration - 0.5:
                break
            for p in procs:
                assert p.poll() is None, (tmp_path / "heading.log").read_text()[-3000:]
            time.sleep(0.5)
        time.sleep(0.5)
        st = query_status(router, keys.svc_status("heading_fuser", "heading-h"))
        assert st is not None and st["role"] == "heading_fuser"
    finally:
        for p in reversed(procs):
            stop(p)
        router.close()

    msgs = [m for k, m in heading.items]
    assert msgs and msgs[-1]["t_s"] >= duration - 0.5, (len(msgs), (tmp_path / "heading.log").read_text()[-2000:])
    for m in msgs[:20] + msgs[-20:]:
        messages.validate(m, keys.heading("car-1"), "heading")
    assert [m["seq"] for m in msgs] == list(range(len(msgs)))
    modes = [m["mode"] for m in msgs]
    assert "gyro_only" in modes, "the bridge must switch the fuser to the gyro"
    first_gyro = modes.index("gyro_only")
    assert "magnetic" in modes[first_gyro:], "and back to the magnetometer after it"
    assert all(messages.validate(m, keys.alarm("car-1", "heading"), "alarm") for k, m in alarms.items)
    # accuracy against the simulator's truth (10 Hz) at matching times
    tt = np.array([m["t_s"] for k, m in pose.items])
    th = np.unwrap([m["heading_rad"] for k, m in pose.items])
    t_h = np.array([m["t_s"] for m in msgs])
    inside = (t_h >= tt[0]) & (t_h <= tt[-1])
    truth = np.interp(t_h[inside], tt, th)
    est = np.array([m["heading_rad"] for m in msgs])[inside]
    errs = np.degrees(np.abs(np.remainder(est - truth + math.pi, 2 * math.pi) - math.pi))
    assert inside.sum() > 0.9 * duration * 10
    assert float(np.sqrt(np.mean(errs**2))) < 3.0
