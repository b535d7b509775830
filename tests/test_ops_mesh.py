"""Mesh tests of the operator tools on a loopback router: record a live run, replay it through a swapped
detector, report on it; replay a BROAD trial through ingest and a detector."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from figcheck import assert_figure_drawn
from meshutil import free_port, wait_alive

from magmesh_cli import recording as rc
from schemas import keys, messages

REPO = Path(__file__).resolve().parent.parent
MANIFEST = REPO / "deploy" / "mesh.toml"
pytestmark = pytest.mark.mesh


def _spawn(module: str, endpoint: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint, *args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()


class _Recorder:
    """magmesh record running in a thread of the test process."""

    def __init__(self, endpoint: str, path: Path, key_exprs=()):
        from magmesh.zconf import build_config
        from magmesh_cli.commands.record import record

        self.stop = threading.Event()
        self.ready = threading.Event()
        self.progress: dict = {}
        self.counts: dict | None = None
        conf = build_config(connect=[endpoint])

        def target():
            self.counts = record(conf, path, key_exprs, stop=self.stop, ready=self.ready,
                                 on_progress=self.progress.update)

        self.thread = threading.Thread(target=target, daemon=True)
        self.thread.start()
        assert self.ready.wait(10), "recorder did not start"

    def finish(self) -> dict:
        self.stop.set()
        self.thread.join(15)
        assert self.counts is not None, "recorder did not finish"
        return self.counts


def _manifest_settings(process: str) -> list[str]:
    """``--set k=v`` arguments of a process entry of the demo manifest (the settings the demo runs with)."""
    import tomllib

    with open(MANIFEST, "rb") as f:
        procs = {p["name"]: p for p in tomllib.load(f).get("process", [])}
    return [a for k, v in procs[process].get("settings", {}).items() for a in ("--set", f"{k}={v}")]


def _wait_services(router, *role_instance: tuple[str, str]) -> None:
    for role, inst in role_instance:  # liveliness is declared after the service's subscriptions
        assert wait_alive(router, keys.svc_token(role, inst), timeout=60.0), f"{role}/{inst} never came up"


def _wait_for(cond, timeout_s: float, procs=()) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        for p in procs:
            assert p.poll() is None, p.stderr.read().decode()[-3000:]
        time.sleep(0.2)
    return False


def _contiguous_seq(path: Path) -> dict[str, tuple[int, int]]:
    """key → (messages, gaps in seq): a reliable recording of one publisher run has no gaps."""
    seqs = defaultdict(list)
    for key, m in rc.load_messages(path):
        seqs[key].append(m["seq"])
    out = {}
    for k, s in seqs.items():
        s.sort()
        out[k] = (len(s), sum(1 for a, b in zip(s, s[1:], strict=False) if b != a + 1))
    return out


def test_record_replay_through_a_swapped_detector_and_report(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config
    from magmesh_cli.commands.replay import replay_to_mesh
    from magmesh_cli.commands.report import make_report

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    drive, rerun = tmp_path / "drive.mcap", tmp_path / "rerun.mcap"
    manifest = ["--manifest", str(MANIFEST)]
    procs = [_spawn("services.ingest", endpoint, "--instance", "ingest-t"),
             _spawn("services.dmc_detector", endpoint, "--impl", "threshold", "--instance", "dmc-threshold",
                    *manifest)]
    try:
        _wait_services(router, ("ingest", "ingest-t"), ("dmc_detector", "dmc-threshold"))
        rec = _Recorder(endpoint, drive)
        sim = _spawn("sim_publishers.car", endpoint, "--vehicle", "car-1", "--instance", "sim-t",
                     "--set", "speed=8", "--set", "duration_s=30", *manifest)
        procs.append(sim)
        # the 30 s drive at 8× real time (50 Hz compasses), through ingest and the detector
        n_dmc = lambda: rec.progress.get("per_key", {}).get(keys.dmc("car-1"), 0)  # noqa: E731
        assert _wait_for(lambda: n_dmc() >= 1450, 60, procs), f"{n_dmc()} dmc epochs"
        # the rest of the drive still in flight: wait for it to be recorded (not a fixed sleep)
        n_key = lambda k: rec.progress.get("per_key", {}).get(k, 0)  # noqa: E731
        _wait_for(lambda: n_key(keys.clean_mag("car-1", "1")) >= 1500
                  and n_key(keys.clean_mag("car-1", "1")) == n_key(keys.raw_mag("car-1", "1")), 60)
        counts = rec.finish()
        _stop([sim])
        procs.remove(sim)
        # -- the recording holds everything the mesh said, nothing lost ----------------------------
        per_key = counts["per_key"]
        assert counts["unvalidated"] == 0 and counts["skipped"] == 0
        assert per_key.get(keys.clean_mag("car-1", "1"), 0) >= 1500
        assert counts["liveliness"] >= 3  # ingest, detector, simulator
        seq = _contiguous_seq(drive)
        assert all(gaps == 0 for _, gaps in seq.values()), {k: v for k, v in seq.items() if v[1]}
        assert seq[keys.clean_mag("car-1", "1")][0] == seq[keys.raw_mag("car-1", "1")][0]
        # -- swap the detector: the threshold one goes, the single-compass one comes ----------------
        old = procs.pop(1)
        _stop([old])
        procs.append(_spawn("services.dmc_detector", endpoint, "--impl", "single", "--instance", "dmc-single",
                            *manifest))
        _wait_services(router, ("dmc_detector", "dmc-single"))
        rec2 = _Recorder(endpoint, rerun, [keys.dmc("car-1"), keys.alarms_all("car-1")])
        stats = replay_to_mesh(build_config(connect=[endpoint]), drive, rate=0.0,
                               key_exprs=[keys.clean_all("car-1")], wait_subscribers_s=5.0)
        n_clean = sum(n for k, n in per_key.items() if rc.keyexpr_matches(keys.clean_all("car-1"), k))
        assert stats.as_dict()["published"] == n_clean
        assert _wait_for(lambda: rec2.progress.get("written", 0) >= 0.95 * per_key[keys.clean_mag("car-1", "1")],
                         30, procs)
        time.sleep(1.0)
        counts2 = rec2.finish()
    finally:
        _stop(procs)
        router.close()
    rerun_dmc = [m for k, m in rc.load_messages(rerun) if k == keys.dmc("car-1")]
    assert {m["impl"] for m in rerun_dmc} == {"single"}
    # one epoch per compass-1 sample of the original drive
    assert len(rerun_dmc) == pytest.approx(per_key[keys.clean_mag("car-1", "1")], rel=0.05)
    assert counts2["skipped"] == 0
    # -- a report of the drive with the new detector's output -----------------------------------------
    index = make_report([drive, rerun], tmp_path / "report", exclude=[keys.dmc("*"), keys.alarms_all("*")])
    page = index.read_text()
    for name in ("car-1_field.png", "car-1_dmc.png"):
        assert name in page
        assert_figure_drawn(tmp_path / "report" / name)
    assert "dmc-single" in page  # the swap is visible in the services table


def test_broad_trial_through_the_mesh_gives_heading_and_alarms(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config
    from magmesh_cli.report.data import group, heading_error

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    path = tmp_path / "broad.mcap"
    manifest = ["--manifest", str(MANIFEST)]
    procs = [_spawn("services.ingest", endpoint, "--instance", "ingest-b"),
             _spawn("services.dmc_detector", endpoint, "--impl", "quasistatic", "--instance", "dmc-qs", *manifest,
                    *_manifest_settings("dmc-broad-1")),
             _spawn("services.heading_fuser", endpoint, "--instance", "heading-b", *manifest)]
    try:
        _wait_services(router, ("ingest", "ingest-b"), ("dmc_detector", "dmc-qs"), ("heading_fuser", "heading-b"))
        rec = _Recorder(endpoint, path)
        # the 1 cm magnet trial from 20 s to 60 s (the magnet is attached at about 38 s), 8× real time
        sim = _spawn("sim_publishers.replay", endpoint, "--vehicle", "broad-1", "--instance", "replay-b",
                     "--set", "dataset=broad:32_disturbed_attached_magnet_1cm", "--set", "speed=8",
                     "--set", "rate_hz=50", "--set", "start_s=20", "--set", "duration_s=40")
        procs.append(sim)
        n_head = lambda: rec.progress.get("per_key", {}).get(keys.heading("broad-1"), 0)  # noqa: E731
        # 40 s of sample time at ≤ 10 Hz: wait for most of it, then until the stream stops growing
        assert _wait_for(lambda: n_head() >= 300, 60, procs[:3]), f"{n_head()} heading messages"
        last = {"n": -1, "since": time.monotonic()}

        def settled() -> bool:  # unchanged for 2.5 s (the recorder reports once a second)
            if n_head() != last["n"]:
                last.update(n=n_head(), since=time.monotonic())
            return time.monotonic() - last["since"] > 2.5

        _wait_for(settled, 20)
        n_mag = lambda: rec.progress.get("per_key", {}).get(keys.clean_mag("broad-1", "1"), 0)  # noqa: E731
        _wait_for(lambda: n_mag() >= 1900, 30)
        counts = rec.finish()
    finally:
        _stop(procs)
        router.close()
    per_key = counts["per_key"]
    assert per_key.get(keys.clean_mag("broad-1", "1"), 0) >= 1900  # 40 s at 285.7 Hz / 6
    assert per_key.get(keys.truth("broad-1", "sources"), 0) >= 390
    run = group(rc.load_messages(path))["broad-1"]
    alarms = run.alarms()
    dmc_alarms = [a for a in alarms if a.source == "dmc"]
    assert dmc_alarms, "no DMC alarm on the attached magnet"
    # raised within a few seconds of the magnet's arrival, as the truth marks it
    src = run.truth("sources")
    ts = np.array([m["t_s"] for m in src])
    dist = np.array([m["disturbed"] for m in src], bool)
    onset = next(t0 for t0, _ in run.disturbed_intervals() if dist[(ts >= t0) & (ts < t0 + 10.0)].mean() > 0.5)
    assert onset - 1.0 <= dmc_alarms[0].start <= onset + 5.0, (onset, dmc_alarms[0].start)
    # the heading follows the optical truth before the magnet and stops trusting the magnetometer after it
    t, err = heading_error(run)
    before = (t > 28.0) & (t < onset - 1.0)
    assert before.sum() > 50 and np.sqrt(np.mean(np.degrees(err[before]) ** 2)) < 10.0
    modes_after = {m["mode"] for m in run.messages("heading") if m["t_s"] > onset + 3.0}
    assert modes_after - {"magnetic"}, modes_after


def test_rerun_a_recording_through_a_detector_in_a_private_mesh(tmp_path):
    pytest.importorskip("zenoh")
    from magmesh_cli.commands.rerun import rerun
    from sim_publishers.replay import core

    # 20 s of BROAD trial 32 around the magnet's arrival, as ingest would have published it
    rec = core.load("broad:32_disturbed_attached_magnet_1cm", rate_hz=50)
    src, out = tmp_path / "clean.mcap", tmp_path / "rerun.mcap"
    seq: dict[str, int] = defaultdict(int)
    with rc.RecordingWriter(src) as w:
        for t, key, mtype, fields in core.stream(rec, "broad-1"):
            if 28.0 <= t < 48.0:
                key = keys.raw_to_clean(key) if "/raw/" in key else key
                w.write_message(key, messages.make(mtype, "broad-1", t, seq[key], **fields), int(1.8e18 + t * 1e9))
                seq[key] += 1
    res = rerun(src, ["services.dmc_detector --impl quasistatic " + " ".join(_manifest_settings("dmc-broad-1"))],
                out, manifest=MANIFEST)
    n_mag = seq[keys.clean_mag("broad-1", "1")]
    assert res["replay"]["published"] == n_mag + seq[keys.clean_imu("broad-1")]
    per_key = res["recorded"]["per_key"]
    # one decision per magnetometer sample; the replayed inputs are received but not written
    assert per_key[keys.dmc("broad-1")] == n_mag
    assert not any("/clean/" in k for k in per_key)
    assert res["recorded"]["skipped"] == res["replay"]["published"]
    alarms = [m for k, m in rc.load_messages(out) if k == keys.alarm("broad-1", "dmc")]
    assert alarms and alarms[0]["state"] == "raised" and 37.0 < alarms[0]["t_s"] < 42.0


def test_record_command_stops_on_sigint_and_prints_its_counts(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "cli.mcap"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "magmesh", "record", "magmesh/t-1/**", "-o", str(out),
                             "--mode", "peer", "--listen", endpoint, "-q"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        with zenoh.open(build_config(connect=[endpoint])) as s:
            pub = s.declare_publisher(keys.raw_mag("t-1", "1"), congestion_control=zenoh.CongestionControl.BLOCK,
                                      reliability=zenoh.Reliability.RELIABLE)
            assert _wait_for(lambda: pub.matching_status.matching, 15), "recorder did not subscribe"
            for i in range(200):
                pub.put(messages.encode(messages.make("mag", "t-1", i * 0.01, i, sensor="1", b_nt=[1.0, 2.0, 3.0])))
            pub.put(b"not msgpack")
            s.put(keys.raw_mag("t-2", "1"), b"other vehicle: not subscribed")
            time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=20)
    assert proc.returncode == 0, stderr.decode()[-2000:]
    text = stdout.decode()
    assert "recorded 200 messages on 1 keys" in text and "not valid magmesh messages: 1" in text
    assert rc.summarize(out)["keys"] == {"magmesh/t-1/raw/mag/1": 201}


def test_overlapping_key_expressions_keep_each_sample_once(tmp_path):
    zenoh = pytest.importorskip("zenoh")
    from magmesh.zconf import build_config
    from magmesh_cli.commands.record import record

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    stop, ready, out = threading.Event(), threading.Event(), tmp_path / "o.mcap"
    res = {}
    th = threading.Thread(target=lambda: res.update(c=record(
        build_config(connect=[endpoint]), out, ["magmesh/**", "magmesh/*/dmc"], stop=stop, ready=ready,
        exclude=["magmesh/*/raw/**"])), daemon=True)
    th.start()
    try:
        assert ready.wait(10)
        with zenoh.open(build_config(connect=[endpoint])) as s:
            time.sleep(1.0)
            for i in range(50):
                m = messages.make("dmc", "v-1", i * 0.1, i, dm_nt=[0.0, 0.0], ddm_nt_s=[0.0, 0.0], dh_rad=0.0,
                                  ddh_rad_s=0.0, heading_rad=0.0, stage1_pass=True, credibility=1.0, valid=True,
                                  impl="threshold", param_source="manifest")
                s.put(keys.dmc("v-1"), messages.encode(m))
                s.put(keys.raw_mag("v-1", "1"), messages.encode(
                    messages.make("mag", "v-1", i * 0.1, i, sensor="1", b_nt=[1.0, 2.0, 3.0])))
            time.sleep(1.0)
        stop.set()
        th.join(15)
    finally:
        router.close()
    c = res["c"]
    assert c["per_key"] == {"magmesh/v-1/dmc": 50}
    assert c["skipped_per_reason"] == {"duplicate (overlapping key expressions): magmesh/v-1/dmc": 50,
                                       "excluded: magmesh/v-1/raw/mag/1": 50}
