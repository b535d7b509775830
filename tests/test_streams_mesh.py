"""Contracts v2 and v3 on a real mesh: v1 singles and batches (list or binary columns) through ingest (clean
batches, or fleet frames) to the DMC detector, with every sample an outside subscriber receives carrying an
encoding that names its type and version."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
from meshutil import free_port, open_client, open_router, query_status, spawn, stop, wait_alive
from test_dmc_mesh import _manifest

from schemas import batch, keys, messages, streams

pytestmark = pytest.mark.mesh

N = 150  # epochs per vehicle (3 s at 50 Hz)


class _Tap:
    """Every sample on magmesh/** with its encoding, as an outside subscriber sees it."""

    def __init__(self, session):
        import zenoh

        self.items: list[tuple[str, str, bytes]] = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(keys.everything(), zenoh.handlers.FifoChannel(100_000))
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        while True:
            try:
                s = self.sub.recv()
            except Exception:
                return
            with self.lock:
                self.items.append((str(s.key_expr), str(s.encoding), s.payload.to_bytes()))

    def on(self, key):
        with self.lock:
            return [(e, p) for k, e, p in self.items if k == key]


def _field(n, seed):
    rng = np.random.default_rng(seed)
    return np.array([2.2e4, 1.5e3, -4.1e4]) + rng.normal(0, 30, (n, 3))


@pytest.mark.parametrize("output,binary", [("batches", False), ("frames", True)])
def test_v1_singles_and_batches_reach_dmc_with_encodings(tmp_path, output, binary):
    import zenoh

    port = free_port()
    router = open_router(port)
    tap = _Tap(router)
    env = {"MAGMESH_STATE_DIR": str(tmp_path / "state")}
    procs = [spawn("services.ingest", port, "--instance", "ing-v2", "--set", f"output={output}",
                   log_path=tmp_path / "ingest.log", env=env),
             spawn("services.dmc_detector", port, "--instance", "dmc-v2", "--manifest", _manifest(tmp_path),
                   log_path=tmp_path / "dmc.log", env=env)]
    client = None
    try:
        assert wait_alive(router, keys.svc_token("ingest", "ing-v2")), (tmp_path / "ingest.log").read_text()
        assert wait_alive(router, keys.svc_token("dmc_detector", "dmc-v2")), (tmp_path / "dmc.log").read_text()
        client = open_client(port)
        opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        # car-1: today's v1 single-sample msgpack, exactly as an outside client would send it
        p1 = {s: client.declare_publisher(keys.raw_mag("car-1", s), **opts) for s in ("1", "2")}
        # car-2: a vehicle agent's v2 batches, 10 epochs each; one sample beyond a magnetometer's range
        p2 = client.declare_publisher(keys.raw_batch("car-2"), encoding=zenoh.Encoding(
            streams.encoding_name("batch", 3 if binary else 2)), **opts)
        time.sleep(1.0)
        f = {s: _field(N, i) for i, s in enumerate(("1", "2"))}
        bad = f["2"].copy()
        bad[33] = [5e6, 0, 0]
        t = 10.0 + np.arange(N) * 0.02
        for i in range(N):
            for s in ("1", "2"):
                p1[s].put(msgpack.packb({"type": "mag", "version": 1, "vehicle": "car-1", "t_s": float(t[i]),
                                         "seq": i, "sensor": s, "b_nt": f[s][i].tolist()}))
        for j in range(0, N, 10):
            sl = slice(j, j + 10)
            p2.put(batch.encode("car-2", j // 10, {
                "mag/1": {"t_s": t[sl], "seq": np.arange(N)[sl], "cols": {"sensor": "1", "b_nt": f["1"][sl]}},
                "mag/2": {"t_s": t[sl], "seq": np.arange(N)[sl], "cols": {"sensor": "2", "b_nt": bad[sl]}}},
                binary=binary))
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if len(tap.on(keys.dmc("car-1"))) >= N and len(tap.on(keys.dmc("car-2"))) >= N - 1:
                break
            assert all(p.poll() is None for p in procs), (tmp_path / "dmc.log").read_text()[-2000:]
            time.sleep(0.3)
        st = query_status(router, keys.svc_status("dmc_detector", "dmc-v2"))
        ist = query_status(router, keys.svc_status("ingest", "ing-v2"))
        status_reply = [r.ok for r in router.get(keys.svc_status("ingest", "ing-v2"), timeout=3.0) if r.ok]
    finally:
        if client is not None:
            client.close()
        for p in reversed(procs):
            stop(p)

    d1 = [msgpack.unpackb(p) for _, p in tap.on(keys.dmc("car-1"))]
    d2 = [msgpack.unpackb(p) for _, p in tap.on(keys.dmc("car-2"))]
    assert [m["t_s"] for m in d1] == t.tolist()  # every v1 epoch, through clean batches
    assert [m["t_s"] for m in d2] == [x for i, x in enumerate(t.tolist()) if i != 33]
    assert all(messages.validate(m, expected_type="dmc") for m in d1 + d2)
    rej = [msgpack.unpackb(p) for _, p in tap.on(keys.rejects("car-2"))]
    assert [(m["code"], m["field"]) for m in rej] == [("range", "b_nt")]
    assert ist["drops"][keys.raw_mag("car-2", "2")] == {"rejected:range": 1}
    unpaired = sum(d.get("unpaired", 0) for k, d in st["drops"].items() if k.startswith("magmesh/car-2/"))
    assert unpaired == 1  # sensor 1's sample whose partner was refused: counted, not lost silently
    if output == "batches":
        clean = tap.on(keys.clean_batch("car-1"))
        assert clean and all(batch.decode(p).vehicle == "car-1" for _, p in clean)
    else:
        from schemas import frame

        fr = [frame.decode(p) for _, p in tap.on(keys.fleet_frame("ing-v2", "clean"))]
        rows = {v: sum(int((s.vi == f.vehicles.index(v)).sum()) for f in fr if v in f.vehicles
                       for s in f.streams.values()) for v in ("car-1", "car-2")}  # (a frame may lack a vehicle)
        assert rows == {"car-1": 2 * N, "car-2": 2 * N - 1}, rows  # every accepted sample, in frames
        mirrored = [frame.decode(p) for _, p in tap.on(keys.fleet_frame("dmc-v2", "dmc"))]
        assert sum(f.streams["dmc"].n for f in mirrored) == len(d1) + len(d2)  # the verdicts, mirrored
    assert not tap.on(keys.clean_mag("car-1", "1"))  # no singles on clean/
    # every sample on the mesh names its type and version; the outside v1 client's car-1 samples carry none
    seen_types = set()
    with tap.lock:
        items = list(tap.items)
    for key, enc, payload in items:
        if key.startswith("magmesh/car-1/raw/"):
            continue
        parsed = streams.parse_encoding(enc)
        assert parsed is not None, (key, enc)
        want = streams.encoding_for_key(key)
        if key == keys.raw_batch("car-2"):  # the vehicle's agent names the form it sends
            want = streams.encoding_name("batch", 3 if binary else 2)
        assert enc == want, (key, enc, want)
        mtype = parsed[0]
        seen_types.add(mtype)
        if mtype != "batch":
            assert msgpack.unpackb(payload)["type"] == mtype
    assert {"batch", "dmc", "reject"} | ({"frame"} if output == "frames" else set()) <= seen_types
    assert str(status_reply[0].encoding) == "application/msgpack;magmesh/status/v1"
