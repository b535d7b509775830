"""Mesh test: survey simulator → ingest → geomag_matcher over a real Zenoh router on loopback."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from schemas import keys, messages

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.mesh


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(module: str, endpoint: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint, *args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def test_survey_vehicle_fixes_correct_the_drifting_ins():
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    fixes: list[dict] = []
    truth: dict[float, list] = {}
    alarms: list[dict] = []
    lock = threading.Lock()

    def on_fix(sample):
        with lock:
            fixes.append(messages.decode(bytes(sample.payload.to_bytes())))

    def on_truth(sample):
        m = messages.decode(bytes(sample.payload.to_bytes()))
        with lock:
            truth[round(m["t_s"], 3)] = m["pos_enu_m"]

    def on_alarm(sample):
        with lock:
            alarms.append(messages.decode(bytes(sample.payload.to_bytes())))

    subs = [router.declare_subscriber(keys.fix_geomag("survey-t"), on_fix),
            router.declare_subscriber(keys.truth("survey-t", "pose"), on_truth),
            router.declare_subscriber(keys.alarm("survey-t", "match"), on_alarm)]
    procs = [
        _spawn("services.ingest", endpoint, "--instance", "ingest-t"),
        _spawn("services.geomag_matcher", endpoint, "--instance", "geomag-t"),
    ]
    try:
        time.sleep(2.0)  # services up and subscribed before the source starts
        procs.append(_spawn("sim_publishers.survey", endpoint, "--vehicle", "survey-t", "--set", "speed=100",
                            "--instance", "sim-t"))
        deadline = time.monotonic() + 40.0
        while time.monotonic() < deadline:
            with lock:
                n_acc = sum(f["accepted"] for f in fixes)
            if n_acc >= 8:
                break
            for p in procs[:2]:
                assert p.poll() is None, p.stderr.read().decode()[-2000:]
            time.sleep(0.2)
        # the status queryable reports the matcher's internal states
        import msgpack

        replies = list(router.get(keys.svc_status("geomag_matcher", "geomag-t"), timeout=5.0))
        status = msgpack.unpackb(replies[0].ok.payload.to_bytes(), raw=False)
        assert status["matchers"]["survey-t"]["n_accepted"] >= 8
        assert "survey-t" in status["vehicles"]
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
        for s in subs:
            s.undeclare()
        router.close()
    accepted = [f for f in fixes if f["accepted"]]
    assert len(accepted) >= 8, f"only {len(accepted)} accepted of {len(fixes)} fixes"
    assert all(f["status"] == "accepted" for f in accepted)
    fix_err, ins_err = [], []
    for f in accepted:
        p = truth.get(round(f["t_s"], 3))
        assert p is not None, "no truth at the fix time"
        fix_err.append(np.hypot(f["pos_enu_m"][0] - p[0], f["pos_enu_m"][1] - p[1]))
        ins_err.append(np.hypot(f["ins_pos_enu_m"][0] - p[0], f["ins_pos_enu_m"][1] - p[1]))
    # the INS starts ~1.1 km off; accepted fixes are within a cell or two of the truth
    assert np.median(ins_err) > 1000.0
    assert np.median(fix_err) < 150.0, fix_err
    # divergence between INS and accepted fixes exceeds the default 1000 m: alarm/match raised
    assert any(a["state"] == "raised" for a in alarms)
