"""Smoke version of `magmesh bench mesh`: the benchmark runs end to end and accounts for every message."""

import pytest

from bench.mesh_bench import bench, format_text

pytestmark = pytest.mark.mesh


# the v1 wire's whole bench is in the slow suite (48 s here); the v2 case runs v1 single-sample vehicles through
# ingest too, and the default suite's mesh tests carry v1 clients end to end
# (the DMC's outputs counted on its fleet frames, the default, and on every vehicle's dmc key)
@pytest.mark.parametrize("wire,sink", [("v2", "frames"), pytest.param("v2", "keys", marks=pytest.mark.slow),
                                       pytest.param("v1", "keys", marks=pytest.mark.slow)])
def test_bench_mesh_smoke(wire, sink):
    res = bench([2], duration_s=2.0, repeat=1, stages=("ingest", "dmc_detector"), limit_vehicles=2, wire=wire,
                v1_ingest=wire == "v2" and sink == "frames", warmup_s=3.0, sink=sink, overload=sink == "frames")
    assert res["sink"] == sink
    row = res["scaling"][0]
    assert row["lost"] == 0, row
    assert row["outputs"] >= 0.99 * row["expected_outputs"] > 0
    assert res["saturation"]["limit"]["sustained_samples_s"] > 0 and res["ratio_to_limit"] > 0
    assert set(row["cpu_pct"]) >= {"ingest", "dmc_detector", "fleet"}
    # the same split by kind of thread: each stage's main loop worked, and no kind exceeds the process's whole
    th = row["cpu_threads_pct"]
    assert set(th) == {"ingest", "dmc_detector"}, th
    for stage, kinds in th.items():
        assert kinds.get("main", 0) > 0 and "zenoh" in kinds, (stage, kinds)
        assert sum(kinds.values()) <= row["cpu_pct"][stage] + 2.0, (stage, kinds, row["cpu_pct"])
    assert row["wire"] == wire
    assert row["startup_p99_ms"] is not None and row["startup_p99_ms"] > 0  # the warm-up's latency, apart
    if wire != "v1":  # from each batch's real put, and from when it was due (adds the fleet's own lag)
        lag = row["fleet_last_put_lag_ms"]
        assert lag is not None and lag["p99"] >= lag["p50"] >= 0, row
        assert row["due_latency_ms_p99"] >= row["latency_ms_p99"] > 0, row
    if wire == "v2" and sink == "frames":  # v1 single-sample vehicles through one ingest, clean batches counted sample by sample
        lim = res["saturation"]["limit"]
        # the limit relays the same batches as fast as the relays go: on a loaded machine some are shed (Zenoh's
        # dropping congestion control; seen: 27,377 of 31,044 at load 15), and what did not come out is lost
        assert lim["outputs"] >= 0.5 * lim["expected_outputs"] > 0, lim
        assert lim["lost"] == max(0, lim["expected_outputs"] - lim["outputs"]), lim
        ing = res["v1_ingest"][0]
        assert ing["kind"] == "ingest" and ing["lost"] == 0 and ing["outputs"] >= 0.99 * ing["expected_outputs"] > 0
    text = format_text(res)
    assert "CPU % by kind of thread at 2 vehicles: ingest" in text, text
    print("\n" + text)


def test_bench_cores_smoke():
    from bench import cores_bench

    iv = cores_bench.ingest_validation(n=500, repeats=1)
    assert iv["decode_validate_us"] > iv["msgpack_unpack_only_us"] > 0
    iw = cores_bench.ingest_wire(vehicles=2, windows=5, repeats=1)
    assert iw["v1_in_singles_out_us_per_sample"] > 0 and iw["v2_in_batches_out_us_per_sample"] > 0
    cf = cores_bench.calibration_fit(repeats=1)
    assert cf["arls_ms"] > 0 and cf["scipy_least_squares_ms"] > 0


def test_latency_counts_from_each_batch_s_real_put():
    """A sample's latency runs from when its batch was put (the fleet's put log), not from when it was due."""
    import numpy as np

    from bench.fleet import publish_time, window_index
    from bench.mesh_bench import put_lag

    start, win = 100.0, 0.05  # windows of 6 ticks: samples at 100.00 … 100.05 are window 0, due at 100.05
    ts = np.array([100.0, 100.05, 100.06, 100.11, 100.06])
    assert window_index(ts, start, win).tolist() == [0, 0, 1, 1, 1]
    assert np.allclose(publish_time(ts, start, win), [100.05, 100.05, 100.11, 100.11, 100.11])
    log = np.array([[0.001, 0.002], [0.030, np.nan]], np.float32)  # window × vehicle: s after due
    vn = np.array([0, 1, 0, 0, 1])  # the last: not in the log (NaN) -> counted from its due time
    assert np.allclose(put_lag(ts, vn, start, win, log), [0.001, 0.002, 0.030, 0.030, 0.0])
    assert np.allclose(put_lag(ts, np.array([0, 5, -1, 0, 0]), start, win, log), [0.001, 0, 0, 0.030, 0.030])
    assert not put_lag(ts, vn, start, win, None).any()


def test_a_terminated_bench_stops_every_process_it_started():
    """SIGTERM (kill, a job's timeout) ends ``magmesh bench mesh`` as Ctrl-C does: its stages run in sessions of
    their own and the load generator beside them, and none may be left running (they were, killed outright)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from meshutil import REPO

    p = subprocess.Popen([sys.executable, "-m", "magmesh", "bench", "mesh", "--vehicles", "2", "--duration", "60",
                          "--stages", "ingest,dmc_detector", "--no-overload", "--no-v1-ingest"], cwd=REPO,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)

    def children() -> set[int]:
        out = set()
        for t in Path(f"/proc/{p.pid}/task").glob("*/children"):
            out |= {int(x) for x in t.read_text().split()}
        return out

    try:
        started: set[int] = set()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(started) < 3 and p.poll() is None:  # both stages and the fleet
            started |= children()
            time.sleep(0.2)
        assert len(started) >= 3, f"the bench started {len(started)} processes (rc {p.poll()})"
        os.kill(p.pid, signal.SIGTERM)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, (p.returncode, err[-2000:])
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{c}").exists() for c in started):
        time.sleep(0.2)
    left = [c for c in started if Path(f"/proc/{c}").exists()
            and Path(f"/proc/{c}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()]
    assert not left, f"left running: {left}"
