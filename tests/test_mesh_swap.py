"""Live swap of the DMC detector while the car drives: every dmc and alarm/dmc sample counted."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest
from meshutil import REPO, Collector, endpoint, free_port, open_client, query_status, stop, wait_alive

from schemas import keys

pytestmark = pytest.mark.mesh


def swap(port: int, role: str, impl: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magmesh", "swap", role, impl, *extra, "--connect", endpoint(port),
                           "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=90)


def test_swap_threshold_to_fcm_and_back_loses_nothing(tmp_path):
    port = free_port()
    sup = subprocess.Popen(
        [sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--endpoint", endpoint(port),
         # the demo's two detectors: swap must pick the car's (dmc-1) and leave the quasi-static one alone
         "--only", "sim-car-1,ingest-1,dmc-1,replay-broad-1,dmc-broad-1", "--duration", "600", "--log-dir", str(tmp_path / "logs"), "--quiet",
         "--set", "sim-car-1.speed=3", "--set", "sim-car-1.loop=false", "--set", "sim-car-1.duration_s=480",
         "--set", "sim-car-1.layout=urban_a"],
        cwd=REPO, stdout=open(tmp_path / "up.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True,
        env={**os.environ, "MAGMESH_STATE_DIR": str(tmp_path / "state")})
    client = open_client(port)
    try:
        dmc = Collector(client, keys.dmc("car-1"))
        alarms = Collector(client, keys.alarm("car-1", "dmc"))
        assert wait_alive(client, keys.svc_token("dmc_detector", "dmc-1"), 60)
        assert wait_alive(client, keys.svc_token("dmc_detector", "dmc-broad-1"), 60)
        broad_pid = query_status(client, keys.svc_status("dmc_detector", "dmc-broad-1"))["pid"]
        # swap while the detector holds alarm/dmc raised: the hand-over must neither repeat nor lose a transition
        assert alarms.wait_for(lambda k, m: m["state"] == "raised", 120), "no alarm raised on the urban drive"
        r1 = swap(port, "dmc_detector", "fcm")
        assert r1.returncode == 0, r1.stdout + r1.stderr
        st = query_status(client, keys.svc_status("dmc_detector", "dmc-1-fcm"))
        assert st["impl"] == "fcm" and st["holds_role"]
        t_after_first = max(m["t_s"] for _, m in dmc.items)
        assert dmc.wait_for(lambda k, m: m["t_s"] > t_after_first + 10, 60)
        r2 = swap(port, "dmc_detector", "threshold")
        assert r2.returncode == 0, r2.stdout + r2.stderr
        t_after_second = max(m["t_s"] for _, m in dmc.items)
        assert dmc.wait_for(lambda k, m: m["t_s"] > t_after_second + 10, 60)
        time.sleep(0.5)
        # a swap that cannot succeed leaves the holder in charge
        r3 = swap(port, "dmc_detector", "no_such_impl", "--instance", "dmc-1-threshold")
        assert r3.returncode == 1, r3.stdout + r3.stderr
        failed = json.loads(r3.stdout)
        assert failed["ok"] is False and failed["holder"] == "dmc-1-threshold", failed
        assert "dmc-1-no_such_impl" in failed["error"], failed  # the refused candidate is named
        holder = query_status(client, keys.svc_status("dmc_detector", "dmc-1-threshold"))
        assert holder["holds_role"] and holder["mode"] == "active"
        t_end = max(m["t_s"] for _, m in dmc.items)
        assert dmc.wait_for(lambda k, m: m["t_s"] > t_end + 3, 60)
        broad = query_status(client, keys.svc_status("dmc_detector", "dmc-broad-1"))
        assert broad["pid"] == broad_pid and broad["impl"] == "quasistatic", "the swaps touched broad-1's detector"
        sup_status = query_status(client, keys.svc_status("supervisor", "main"))
        assert sup_status["processes"]["dmc-broad-1"]["restarts"] == 0, sup_status["processes"]["dmc-broad-1"]
    finally:
        stop(sup, 10)
        client.close()
    items = [m for _, m in dmc.items]
    seqs = [m["seq"] for m in items]
    ts = [m["t_s"] for m in items]
    impls = [m["impl"] for m in items]
    breaks = [(items[i]["seq"], items[i + 1]["seq"], items[i]["impl"], items[i + 1]["impl"], items[i]["t_s"],
               items[i + 1]["t_s"]) for i in range(len(items) - 1) if items[i + 1]["seq"] != items[i]["seq"] + 1]
    assert not breaks, f"dmc seq: gap or duplicate across the swaps (seq, next, impls, t_s): {breaks}"
    assert all(b > a for a, b in zip(ts, ts[1:], strict=False)), "dmc epochs out of order or repeated"
    gaps = [b - a for a, b in zip(ts, ts[1:], strict=False)]
    assert max(gaps) < 0.1, f"an epoch went missing: largest gap {max(gaps):.3f} s"
    order = [impls[0]] + [b for a, b in zip(impls, impls[1:], strict=False) if a != b]
    assert order == ["threshold", "fcm", "threshold"], order
    states = [m["state"] for _, m in alarms.items]
    assert all(a != b for a, b in zip(states, states[1:], strict=False)), f"spurious raise/clear: {states}"
    assert len(states) >= 2 and states[0] == "raised", states
    aseq = [m["seq"] for _, m in alarms.items]
    assert aseq == list(range(aseq[0], aseq[0] + len(aseq))), f"alarm seq: gap or duplicate: {aseq}"
    print(f"\nswap: {len(items)} dmc samples, seq {seqs[0]}..{seqs[-1]} contiguous, implementations {order}, "
          f"{len(states)} alarm transitions; failed swap kept the holder")
