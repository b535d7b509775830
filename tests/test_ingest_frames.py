"""Ingest on fleet frames (output = frames, contract v3), in process: the same decisions as the per-sample path,
one frame per window, rejects reported and counted."""

import math

import msgpack
import numpy as np
import pytest

from magmesh.runtime import Runner
from schemas import batch, frame, keys, messages
from services.ingest.batching import IngestServiceSettings
from services.ingest.service import Ingest


class _Pub:
    def __init__(self, out, key):
        self.out, self.key = out, key

    def put(self, payload):
        self.out.append((self.key, bytes(payload)))


class _Session:
    def __init__(self):
        self.out = []

    def declare_publisher(self, key, **kw):
        assert "encoding" in kw
        return _Pub(self.out, key)


def _ingest(tmp_path, monkeypatch, name, **settings):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path / name))
    sess = _Session()
    return Runner(Ingest(IngestServiceSettings(**settings), instance="ing-t"), sess), sess


def _inputs(seed: int):
    """A shuffled mix of v1 singles and v2/v3 batches of three vehicles, with bad samples of every kind."""
    rng = np.random.default_rng(seed)
    out = []
    for vi, v in enumerate(["car-1", "car-2", "bus-7"]):
        t = 10.0 + vi + np.cumsum(rng.choice([0.02, 0.02, 0.02, 0.0, -0.05, 0.02], 40))
        b = np.array([2e4, 1e3, -4e4]) + rng.normal(0, 50, (40, 3))
        b[rng.integers(0, 40, 2)] = [5e6, 0.0, 0.0]  # beyond any magnetometer
        t[rng.integers(5, 40)] += 7200.0  # an hour ahead
        g = rng.normal(0, 0.1, (40, 3))
        g[rng.integers(0, 40)] = [99.0, 0, 0]
        imu_t = 10.0 + vi + np.arange(40) * 0.01
        i = 0
        bseq = 0
        while i < 40:
            k = int(rng.integers(1, 6))
            if rng.random() < 0.5:  # singles
                for j in range(i, min(i + k, 40)):
                    out.append((keys.raw_mag(v, "1"), messages.encode(messages.make(
                        "mag", v, float(t[j]), j, sensor="1", b_nt=b[j].tolist()), check=False)))
                    out.append((keys.raw_imu(v), messages.encode(messages.make(
                        "imu", v, float(imu_t[j]), j, gyro_rad_s=g[j].tolist(), accel_m_s2=[0.0, 0.0, 9.8]),
                        check=False)))
            else:
                sl = slice(i, min(i + k, 40))
                out.append((keys.raw_batch(v), batch.encode(v, bseq, {
                    "mag/1": {"t_s": t[sl], "seq": np.arange(40)[sl], "cols": {"sensor": "1", "b_nt": b[sl]}},
                    "imu": {"t_s": imu_t[sl], "seq": np.arange(40)[sl],
                            "cols": {"gyro_rad_s": g[sl], "accel_m_s2": np.tile([0.0, 0.0, 9.8], (sl.stop - i, 1))}}},
                    binary=bool(rng.random() < 0.5))))  # list (v2) or binary (v3) columns
                bseq += 1
            i += k
    order = rng.permutation(len(out))
    # keep each vehicle's inputs in their own order (interleave vehicles only)
    by_v: dict[str, list] = {}
    for k, p in out:
        by_v.setdefault(k.split("/")[1], []).append((k, p))
    mixed, ptr = [], {v: 0 for v in by_v}
    for o in order:
        v = list(by_v)[o % len(by_v)]
        if ptr[v] < len(by_v[v]):
            mixed.append(by_v[v][ptr[v]])
            ptr[v] += 1
    for v, lst in by_v.items():
        mixed.extend(lst[ptr[v]:])
    return mixed


@pytest.mark.parametrize("seed", range(4))
def test_frames_carry_what_singles_carry(tmp_path, monkeypatch, seed):
    inputs = _inputs(seed)
    r1, s1 = _ingest(tmp_path, monkeypatch, "singles")
    r2, s2 = _ingest(tmp_path, monkeypatch, "frames", output="frames", batch_window_s=0.05)
    for k, p in inputs:
        r1.handle_sample(k, p)
        r2.handle_sample(k, p)
    r2.svc.frame_flush(force=True)
    singles = [(k, msgpack.unpackb(p)) for k, p in s1.out if "/clean/" in k]
    frames = [frame.decode(p) for k, p in s2.out if k == keys.fleet_frame("ing-t", "clean")]
    assert len(frames) == 1 and frames[0].seq == 0
    f = frames[0]
    got = []
    for name, st in f.streams.items():
        for i in range(st.n):
            v = f.vehicles[int(st.vi[i])]
            key = keys.clean_mag(v, "1") if name == "mag/1" else keys.clean_imu(v)
            m = st.messages(v, i, i + 1)[0]
            got.append((key, m["t_s"], m["seq"], m.get("b_nt") or m.get("gyro_rad_s")))
    want = [(k, m["t_s"], m["seq"], m.get("b_nt") or m.get("gyro_rad_s")) for k, m in singles]
    assert sorted(got) == sorted(want) and len(want) > 100
    # the same refusals, by key and code, counted per sample
    def refused(r):
        return {(k, c): n for k, d in r.drops.items() for c, n in d.items() if c.startswith("rejected:")}
    assert refused(r2) == refused(r1) and sum(refused(r1).values()) >= 6
    rej = [msgpack.unpackb(p) for k, p in s2.out if k.endswith("/rejects")]
    assert {m["code"] for m in rej} >= {"range", "time_order"}
    assert all(messages.validate(m) for m in rej)


def test_frame_rows_sorted_by_vehicle_and_numbered_per_key(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch, "f", output="frames")
    for i in range(3):
        for v in ("car-2", "car-1"):
            r.handle_sample(keys.raw_mag(v, "1"), messages.encode(messages.make(
                "mag", v, 1.0 + 0.02 * i, 100 + i, sensor="1", b_nt=[2e4, 0.0, -4e4], temp_c=20.0 + i)))
    r.handle_sample(keys.raw_mag("car-1", "1"), messages.encode(messages.make(
        "mag", "car-1", 1.5, 103, sensor="1", b_nt=[2e4, 0.0, -4e4])))  # no temperature on this one
    r.svc.frame_flush(force=True)
    (f,) = [frame.decode(p) for k, p in s.out]
    st = f.streams["mag/1"]
    assert f.vehicles == ["car-2", "car-1"] and st.vi.tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert st.seq.tolist() == [0, 1, 2, 0, 1, 2, 3]  # ingest's own numbering per clean key
    msgs = st.messages("car-1", 3, 7)
    assert [m.get("temp_c") for m in msgs] == [20.0, 21.0, 22.0, None] and "temp_c" not in msgs[3]
    assert math.isnan(st.cols["temp_c"][6])
    assert r.tick_period() == pytest.approx(0.005)


def _plain(a: np.ndarray) -> list:
    """A column as a list that compares equal when the arrays are equal, NaN included."""
    return [repr(x) for x in a.tolist()]


def _tamper(payload: bytes, fn) -> bytes:
    m = msgpack.unpackb(payload)
    fn(m)
    return msgpack.packb(m)


def _binary_inputs(seed: int):
    """Binary batches of four vehicles, most of the usual layout, some not (another magnetometer, an unknown field,
    a string column per row, an optional column on some batches only) and some wrong (a short column, the key's
    vehicle not the payload's, a NaN, another sensor's name, garbage), with v1 singles and v2 batches of the same streams between them."""
    rng = np.random.default_rng(seed)
    out = []
    seqs: dict[str, int] = {}
    for w in range(12):
        for v in ("car-1", "car-2", "bus-7", "van-3"):
            t0 = 10.0 + w * 0.06
            tm, ti = t0 + np.array([0.0, 0.02, 0.04]), t0 + np.arange(6) * 0.01
            sm, si = np.arange(3 * w, 3 * w + 3), np.arange(6 * w, 6 * w + 6)
            b = np.array([2e4, 1e3, -4e4]) + rng.normal(0, 50, (3, 3))
            st = {"mag/1": {"t_s": tm, "seq": sm, "cols": {"sensor": "1", "b_nt": b}},
                  "mag/2": {"t_s": tm, "seq": sm, "cols": {"sensor": "2", "b_nt": b + 10}},
                  "imu": {"t_s": ti, "seq": si, "cols": {"gyro_rad_s": rng.normal(0, 0.1, (6, 3)),
                                                         "accel_m_s2": np.tile([0.0, 0.0, 9.8], (6, 1))}}}
            u = rng.random()
            if u < 0.3:
                st["gnss"] = {"t_s": tm[:1], "seq": [w], "cols": {
                    "lat_deg": [48.1], "lon_deg": [11.5], "alt_m": [500.0], "vel_enu_m_s": [[1.0, 2.0, 0.0]],
                    "course_rad": [0.4], "speed_m_s": [2.2], "fix_type": "3d" if u < 0.15 else ["rtk_fixed"],
                    "num_sats": [9], "pdop": [1.4]}}
            elif u < 0.4:
                st["mag/1"]["cols"]["temp_c"] = [21.0, 21.5, 22.0]  # an optional column on some batches
            elif u < 0.45:
                st["mag/3"] = {"t_s": tm, "seq": sm, "cols": {"sensor": "3", "b_nt": b}}  # not a usual stream
            elif u < 0.5:
                st["imu"]["cols"]["gyro_rad_s"][2, 1] = np.nan
            p = batch.encode(v, seqs.get(v, 0), st, binary=True)
            seqs[v] = seqs.get(v, 0) + 1
            u = rng.random()
            if u < 0.04:
                p = _tamper(p, lambda m: m["streams"]["mag/2"]["cols"].update(b_nt=m["streams"]["mag/2"]["cols"]["b_nt"][:-8]))
            elif u < 0.08:
                p = _tamper(p, lambda m: m.update(vehicle="someone-else"))
            elif u < 0.12:
                p = _tamper(p, lambda m: m["streams"]["imu"]["cols"].update(new_field=b"\x00" * 48))
            elif u < 0.14:
                p = p[:40]
            elif u < 0.18:
                p = _tamper(p, lambda m: m["streams"]["mag/1"]["cols"].update(sensor=["1", "1", "1"]))
            elif u < 0.21:
                p = _tamper(p, lambda m: m["streams"]["mag/2"]["cols"].update(sensor="1"))  # not its stream's
            out.append((keys.raw_batch(v), p))
            if rng.random() < 0.15:  # a v1 single of the same stream, later than the batch
                out.append((keys.raw_mag(v, "1"), messages.encode(messages.make(
                    "mag", v, float(tm[-1]) + 0.01, 10_000 + w, sensor="1", b_nt=b[0].tolist()), check=False)))
            if rng.random() < 0.1:  # and a v2 batch of list columns
                out.append((keys.raw_batch(v), batch.encode(v, seqs[v], {"imu": {
                    "t_s": ti + 0.005, "seq": si + 50_000, "cols": {"gyro_rad_s": np.zeros((6, 3)),
                                                                   "accel_m_s2": np.tile([0.0, 0.0, 9.8], (6, 1))}}})))
                seqs[v] += 1
    return out


@pytest.mark.parametrize("seed", range(3))
def test_binary_batches_kept_whole_then_joined_decide_as_one_by_one(tmp_path, monkeypatch, seed):
    """Binary batches are kept as they come and decoded with their window (framing.py _settle): the frames, the
    refusals with their sentences and the counts are those of decoding each batch on arrival (the general path)."""
    from services.ingest import batching

    inputs = _binary_inputs(seed)
    runs = {}
    for name, fast in (("arrival", False), ("window", True)):
        r, s = _ingest(tmp_path, monkeypatch, name, output="frames", batch_window_s=0.05)
        with monkeypatch.context() as m:
            if not fast:
                m.setattr(batching, "looks_binary", lambda p: False)  # each batch decoded on arrival
            for i, (k, p) in enumerate(inputs):
                r.handle_sample(k, p)
                if i % 5 == 4:
                    r.svc.frame_flush(force=True)
            r.svc.frame_flush(force=True)
        frames = []
        for k, p in s.out:
            if k == keys.fleet_frame("ing-t", "clean"):
                f = frame.decode(p)
                frames.append({n: (st.n, [f.vehicles[int(i)] for i in st.vi], st.t_s.tolist(), st.seq.tolist(),
                                   {c: (_plain(v) if isinstance(v, np.ndarray) else v) for c, v in st.cols.items()})
                               for n, st in f.streams.items()})
        rej = [(k, msgpack.unpackb(p)["code"], msgpack.unpackb(p)["reason"]) for k, p in s.out if k.endswith("/rejects")]
        runs[name] = (frames, rej, {k: dict(d) for k, d in r.drops.items()}, {k: c.n for k, c in r.count_in.items()})
    (f1, rej1, d1, c1), (f2, rej2, d2, c2) = runs["arrival"], runs["window"]
    assert len(f1) >= 10 and sum(len(x) for x in f1) > 30, len(f1)
    assert f2 == f1
    assert rej2 == rej1 and {c for _, c, _ in rej1} >= {"schema", "key"}
    assert d2 == d1 and c2 == c1


def test_a_frame_window_goes_out_when_due_not_a_tick_later(tmp_path, monkeypatch):
    """The runtime's loop wakes at the open window's deadline (Ingest.tick_due_at), not at its next periodic tick:
    a batch arriving just after a tick is published ``batch_window_s`` later, not up to half a window more. Wall
    clock on a shared machine: the best of up to three tries counts (a loop that waits for its tick never gets
    under 0.6 s, however quiet the machine)."""
    import threading
    import time

    p = batch.encode("car-1", 0, {"imu": {"t_s": [1.0, 1.01], "seq": [0, 1], "cols": {
        "gyro_rad_s": [[0.0, 0.0, 0.0]] * 2, "accel_m_s2": [[0.0, 0.0, 9.8]] * 2}}}, binary=True)

    def once(k: int) -> float:
        r, s = _ingest(tmp_path, monkeypatch, f"due-{k}", output="frames", batch_window_s=0.4)
        assert r.tick_period() == pytest.approx(0.2)
        r.svc.on_start()  # (the compiled window kernel loaded, as a started service has it)
        r.svc.frame_flush(force=True)
        th = threading.Thread(target=r.loop, daemon=True)
        t0 = time.monotonic()
        th.start()
        time.sleep(0.22)  # just after the loop's first tick (0.2 s): periodic ticks alone would flush at 0.8 s
        t_in = time.monotonic()
        r.q.put(("S", [(keys.raw_batch("car-1"), p)], time.monotonic()))
        while not s.out and time.monotonic() - t0 < 5:
            time.sleep(0.005)
        t_out = time.monotonic()
        r.stop_event.set()
        th.join(2)
        assert [k for k, _ in s.out] == [keys.fleet_frame("ing-t", "clean")]
        return t_out - t_in

    took = []
    for k in range(3):
        took.append(once(k))
        if 0.39 <= took[-1] < 0.52:
            break
    assert 0.39 <= min(took) < 0.52, took


def test_a_window_whose_input_waited_too_long_is_shed_and_counted_its_seqs_tracked(tmp_path, monkeypatch):
    """Overload: a window whose input waited longer than shed_after_s in the queue is checked (its seqs move on)
    but not sent; its samples are counted lost as shed_behind on the frame key. The next window goes out, and
    shows no upstream gap for what was shed."""
    import threading
    import time

    from magmesh import runtime

    r, s = _ingest(tmp_path, monkeypatch, "shed", output="frames", batch_window_s=0.05)
    assert r.shed_after_s == runtime.SHED_AFTER_S > 0

    def imu(seq0, t0):
        return batch.encode("car-1", seq0, {"imu": {"t_s": [t0, t0 + 0.01], "seq": [seq0, seq0 + 1], "cols": {
            "gyro_rad_s": [[0.0, 0.0, 0.0]] * 2, "accel_m_s2": [[0.0, 0.0, 9.8]] * 2}}}, binary=True)

    r.svc.on_start()
    th = threading.Thread(target=r.loop, daemon=True)
    th.start()
    r._behind_since = time.monotonic() - runtime.SHED_AFTER_S - 0.1  # behind for that long already (overload)
    r.q.put(("S", [(keys.raw_batch("car-1"), imu(0, 1.0))], time.monotonic() - runtime.SHED_AFTER_S - 1))
    time.sleep(0.3)
    assert s.out == []
    r.q.put(("S", [(keys.raw_batch("car-1"), imu(2, 1.02))], time.monotonic()))
    t0 = time.monotonic()
    while not s.out and time.monotonic() - t0 < 5:
        time.sleep(0.005)
    r.stop_event.set()
    th.join(2)
    fkey = keys.fleet_frame("ing-t", "clean")
    assert [k for k, _ in s.out] == [fkey]
    assert r.drops[fkey]["shed_behind"] == 2 and r.frames_shed == 1
    st = r.svc.status_extra()
    assert st["upstream_gaps"] in (0, {}, []), st["upstream_gaps"]
    f = frame.decode(s.out[0][1])
    # what went out is the second batch, numbered on the clean key from 0: the consumers see no gap either
    assert f.streams["imu"].t_s.tolist() == [1.02, 1.03] and f.streams["imu"].seq.tolist() == [0, 1]
