"""The foundation end to end: real processes under `magmesh up` on loopback.

car simulator → ingest → dmc_detector → alarm/dmc, watched by an external Zenoh client.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import msgpack
import pytest
from meshutil import REPO, Collector, endpoint, free_port, open_client, query_status, stop, wait_alive

from schemas import keys, messages

pytestmark = pytest.mark.mesh

ALARM_FIELDS = {"type", "version", "vehicle", "t_s", "seq", "source", "state", "severity", "reason", "value",
                "threshold", "service"}


def up(port: int, tmp_path, *sets: str, only="sim-car-1,ingest-1,dmc-1", duration=240) -> subprocess.Popen:
    args = [sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--endpoint", endpoint(port),
            "--only", only, "--duration", str(duration), "--log-dir", str(tmp_path / "logs"), "--quiet"]
    for s in sets:
        args += ["--set", s]
    return subprocess.Popen(args, cwd=REPO, stdout=open(tmp_path / "up.log", "ab"), stderr=subprocess.STDOUT,
                            env={**os.environ, "MAGMESH_STATE_DIR": str(tmp_path / "state")},
                            start_new_session=True)


def sources_intervals(items, name):
    """[(start, end)] sample-time intervals in which truth/sources lists a source of kind `name`."""
    out, start, last = [], None, None
    for _, m in sorted(items, key=lambda km: km[1]["t_s"]):
        active = any(a.split("_")[0] == name for a in m.get("active_sources", []))
        if active and start is None:
            start = m["t_s"]
        if not active and start is not None:
            out.append((start, last))
            start = None
        last = m["t_s"]
    if start is not None:
        out.append((start, last))
    return out


@pytest.fixture(scope="module")
def bridge_run(tmp_path_factory):
    """urban_a as fast as the mesh takes it: the bridge comes ~70 s into the drive."""
    tmp = tmp_path_factory.mktemp("bridge")
    port = free_port()
    sup = up(port, tmp, "sim-car-1.speed=0", "sim-car-1.loop=false", "sim-car-1.duration_s=110",
             "sim-car-1.layout=urban_a")
    client = open_client(port)
    alarms = Collector(client, keys.alarms_all())
    truth = Collector(client, keys.truth("car-1", "sources"))
    rejects = Collector(client, keys.rejects("*"))
    dmc = Collector(client, keys.dmc("car-1"))
    try:
        assert wait_alive(client, keys.svc_token("dmc_detector", "dmc-1"), 60), "detector never came up"
        assert wait_alive(client, keys.svc_token("ingest", "ingest-1"), 60), "ingest never came up"
        # garbage on a raw key while the mesh runs
        pub = client.declare_publisher(keys.raw_mag("car-1", "9"))
        for bad in (b"\x00garbage", msgpack.packb({"type": "mag", "version": 7}),
                    msgpack.packb(messages.make("mag", "car-1", 1.0, 0, sensor="9", b_nt=[float("nan"), 0, 0]))):
            pub.put(bad)
        # the drive ends at 110 s of sample time
        assert truth.wait_for(lambda k, m: m["t_s"] >= 109.0, 240), "the drive did not finish in time"
        assert dmc.wait_for(lambda k, m: m["t_s"] >= 108.0, 60)
        time.sleep(1.0)
        status = query_status(client, keys.svc_status("ingest", "ingest-1"))
        yield dict(alarms=alarms, truth=truth, rejects=rejects, dmc=dmc, status=status, port=port, client=client)
    finally:
        stop(sup, 10)
        client.close()


def test_bridge_raises_and_clears_dmc_alarm(bridge_run):
    bridges = sources_intervals(bridge_run["truth"].items, "bridge")
    assert bridges, "the simulated drive should cross the bridge"
    b0, b1 = bridges[0]
    dmc_alarms = [m for k, m in bridge_run["alarms"].items if k == keys.alarm("car-1", "dmc")]
    raised = [m for m in dmc_alarms if m["state"] == "raised" and b0 - 1.0 <= m["t_s"] <= b1 + 1.0]
    assert raised, f"no alarm/dmc raised on the bridge ({b0:.1f}–{b1:.1f} s); alarms: {dmc_alarms}"
    cleared = [m for m in dmc_alarms if m["state"] == "cleared" and b1 <= m["t_s"] <= b1 + 15.0]
    assert cleared, f"alarm/dmc not cleared within 15 s after the bridge ended at {b1:.1f} s"
    # alternation: never two raises or two clears in a row, seq contiguous
    states = [m["state"] for m in dmc_alarms]
    assert all(a != b for a, b in zip(states, states[1:], strict=False)), states
    seqs = [m["seq"] for m in dmc_alarms]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


def test_external_client_gets_full_alarm_messages(bridge_run):
    msgs = [m for _, m in bridge_run["alarms"].items]
    assert msgs
    for m in msgs:
        assert ALARM_FIELDS <= set(m), set(m) ^ ALARM_FIELDS
        assert m["type"] == "alarm" and m["state"] in ("raised", "cleared") and m["severity"] in ("warning", "critical")
        assert isinstance(m["reason"], str) and len(m["reason"]) > 10
        messages.validate(m)


def test_dmc_state_every_epoch_no_gap(bridge_run):
    seqs = [m["seq"] for _, m in bridge_run["dmc"].items]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "dmc sequence has gaps or duplicates"
    assert len(seqs) > 100 * 50 * 0.9  # ~50 Hz over the ~110 s drive


def test_garbage_goes_to_rejects_and_mesh_keeps_running(bridge_run):
    rej = [m for k, m in bridge_run["rejects"].items if m.get("key") == keys.raw_mag("car-1", "9")]
    codes = sorted(m["code"] for m in rej)
    assert codes == ["decode", "schema", "version"], rej
    assert all(m["reason"] for m in rej)
    st = bridge_run["status"]
    assert st["rejects"] >= 3
    assert st["drops"][keys.raw_mag("car-1", "9")] == {"rejected:decode": 1, "rejected:schema": 1,
                                                       "rejected:version": 1}
    # the rest of the stream went through untouched
    assert st["in"][keys.raw_mag("car-1", "1")]["n"] == st["out"][keys.clean_mag("car-1", "1")]["n"]


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("clean")
    port = free_port()
    sup = up(port, tmp, "sim-car-1.speed=2", "sim-car-1.loop=false", "sim-car-1.duration_s=200",
             "sim-car-1.layout=clean")
    client = open_client(port)
    try:
        assert wait_alive(client, keys.svc_token("dmc_detector", "dmc-1"), 60)
        yield dict(sup=sup, client=client, port=port, tmp=tmp)
    finally:
        stop(sup, 10)
        client.close()


def test_clean_drive_raises_no_alarm_and_restart_after_sigkill(clean_run):
    client = clean_run["client"]
    alarms = Collector(client, keys.alarms_all())
    dmc = Collector(client, keys.dmc("car-1"))
    assert dmc.wait_for(lambda k, m: m["t_s"] > 30, 60)
    # status CLI lists the services
    out = subprocess.run([sys.executable, "-m", "magmesh", "status", "--connect", endpoint(clean_run["port"]), "--json"],
                         cwd=REPO, capture_output=True, text=True, timeout=30)
    listed = {(s["role"], s["instance"]) for s in json.loads(out.stdout)["services"]}
    assert {("ingest", "ingest-1"), ("dmc_detector", "dmc-1"), ("sim", "sim-car-1"), ("supervisor", "main")} <= listed
    # SIGKILL the detector: the supervisor restarts it (how fast is the bench's figure, not a test's)
    st = query_status(client, keys.svc_status("dmc_detector", "dmc-1"))
    assert st is not None, "the detector did not answer its status query"
    os.kill(st["pid"], signal.SIGKILL)
    t_kill = time.monotonic()
    token = keys.svc_token("dmc_detector", "dmc-1")
    gone = time.monotonic() + 30
    while time.monotonic() < gone and any(r.ok for r in client.liveliness().get(token, timeout=0.5)):
        time.sleep(0.02)
    assert wait_alive(client, token, 60), "the detector did not come back after SIGKILL"
    back_s = time.monotonic() - t_kill
    st2 = None
    deadline = time.monotonic() + 30
    while st2 is None and time.monotonic() < deadline:
        st2 = query_status(client, keys.svc_status("dmc_detector", "dmc-1"))
    assert st2 is not None and st2["pid"] != st["pid"], (st["pid"], st2)
    sup_st = query_status(client, keys.svc_status("supervisor", "main"))
    proc = sup_st["processes"]["dmc-1"]
    assert proc["restarts"] == 1
    # the restarted detector serves again: new epochs arrive after the kill
    t_last = max(m["t_s"] for _, m in dmc.items)
    assert dmc.wait_for(lambda k, m: m["t_s"] > t_last + 5, 60), "no dmc output after the restart"
    print(f"\ndetector killed with SIGKILL: process restarted after {proc['last_restart_delay_s']:.2f} s, "
          f"serving again (liveliness) after {back_s:.2f} s")
    assert not [m for _, m in alarms.items if m["state"] == "raised"], "the clean drive must raise no alarm"
