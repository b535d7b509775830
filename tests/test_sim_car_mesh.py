"""Mesh test: the car simulator as a process publishing through a Zenoh router on loopback."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
from meshutil import free_port as _free_port

from schemas import keys, messages

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.mesh


def _spawn(endpoint: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "sim_publishers.car", "--connect", endpoint, *args], cwd=REPO,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)


def test_car_publisher_streams_every_message_in_order_and_paces_real_time():
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    got: dict[str, list[tuple[float, int, float]]] = {}  # key → (t_s, seq, wall time)
    bad: list[str] = []
    lock = threading.Lock()

    def on_sample(sample):
        key = str(sample.key_expr)
        try:
            m = messages.decode(bytes(sample.payload.to_bytes()), key, messages.type_for_key(key))
        except Exception as e:  # noqa: BLE001 — collected and asserted below
            bad.append(f"{key}: {e}")
            return
        with lock:
            got.setdefault(key, []).append((m["t_s"], m["seq"], time.monotonic()))

    sub = router.declare_subscriber(keys.everything(), on_sample)
    procs = []
    try:
        # as fast as possible: a 20 s drive, every message, in order
        procs.append(_spawn(endpoint, "--vehicle", "car-m", "--instance", "car-fast", "--set", "speed=0",
                            "--set", "duration_s=20", "--set", "layout=urban_b"))
        expected = {keys.raw_mag("car-m", "1"): 1001, keys.raw_mag("car-m", "2"): 1001, keys.raw_imu("car-m"): 2001,
                    keys.raw_gnss("car-m"): 101, keys.truth("car-m", "pose"): 201,
                    keys.truth("car-m", "field"): 201, keys.truth("car-m", "sources"): 201}
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            with lock:
                if all(len(got.get(k, [])) >= n for k, n in expected.items()):
                    break
            assert procs[0].poll() is None, procs[0].stderr.read().decode()[-3000:]
            time.sleep(0.1)
        # the status queryable names the layout
        st = [msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)
              for r in router.get(keys.svc_status("sim", "car-fast"), timeout=3.0) if r.ok is not None]
        assert st and st[0]["layout"] == "urban_b"
        _stop(procs[0])
        assert not bad, bad[:3]
        with lock:
            for key, n in expected.items():
                rows = got.get(key, [])
                assert len(rows) == n, (key, len(rows), n)
                assert [r[1] for r in rows] == list(range(n)), key  # seq from 0, none lost or reordered
                assert all(b[0] > a[0] for a, b in zip(rows, rows[1:], strict=False)), key
            got.clear()

        # real time: 4 s of drive take about 4 s of wall time
        procs.append(_spawn(endpoint, "--vehicle", "car-r", "--instance", "car-rt", "--set", "speed=1",
                            "--set", "duration_s=4", "--set", "truth=false"))
        key = keys.raw_mag("car-r", "1")
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            with lock:
                if len(got.get(key, [])) >= 201:
                    break
            time.sleep(0.1)
        with lock:
            rows = got.get(key, [])
        assert len(rows) == 201
        wall = rows[-1][2] - rows[0][2]
        assert wall > 3.5, wall  # paced: never faster than real time (slower is load, not checked)
    finally:
        for p in procs:
            _stop(p)
        sub.undeclare()
        router.close()
