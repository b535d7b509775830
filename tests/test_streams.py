"""Contract v2 in process (no Zenoh): ingest on batches, clean batches out, the runtime's unbatching."""

import msgpack
import numpy as np
import pytest

from magmesh.runtime import Runner, Service
from schemas import batch, keys, messages
from services.ingest.batching import IngestServiceSettings, order_masks
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
        assert "encoding" in kw  # every publisher names its encoding
        return _Pub(self.out, key)


def _ingest(tmp_path, monkeypatch, **settings):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    r = Runner(Ingest(IngestServiceSettings(**settings), instance="ing-t"), sess)
    return r, sess


def _mag_batch(vehicle, seq, t, b1, b2, s0=0):
    n = len(t)
    return batch.encode(vehicle, seq, {
        "mag/1": {"t_s": t, "seq": s0 + np.arange(n), "cols": {"sensor": "1", "b_nt": b1}},
        "mag/2": {"t_s": t, "seq": s0 + np.arange(n), "cols": {"sensor": "2", "b_nt": b2}}})


def _field(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([2e4, 1e3, -4e4]) + rng.normal(0, 50, (n, 3))


@pytest.mark.parametrize("n", [10, 100])  # a vehicle's window (sample by sample) and a long one (on columns)
def test_ingest_validates_a_batch_and_republishes_singles(tmp_path, monkeypatch, n):
    r, s = _ingest(tmp_path, monkeypatch)
    t = 1.0 + np.arange(n) * 0.02
    b1, b2 = _field(n, 1), _field(n, 2)
    b1[4] = [3e6, 0, 0]  # beyond what a magnetometer reads
    t2 = t.copy()
    t2[7] = t2[6]  # a duplicate on sensor 2
    payload = batch.encode("car-1", 0, {
        "mag/1": {"t_s": t, "seq": np.arange(n), "cols": {"sensor": "1", "b_nt": b1}},
        "mag/2": {"t_s": t2, "seq": np.arange(n), "cols": {"sensor": "2", "b_nt": b2}}})
    r.handle_sample(keys.raw_batch("car-1"), payload)
    out = [(k, msgpack.unpackb(p)) for k, p in s.out]
    c1 = [m for k, m in out if k == keys.clean_mag("car-1", "1")]
    c2 = [m for k, m in out if k == keys.clean_mag("car-1", "2")]
    rej = [m for k, m in out if k == keys.rejects("car-1")]
    assert [m["t_s"] for m in c1] == [x for i, x in enumerate(t.tolist()) if i != 4]
    assert [m["seq"] for m in c1] == list(range(n - 1))  # ingest's own numbering on the clean key
    assert [m["t_s"] for m in c2] == [x for i, x in enumerate(t2.tolist()) if i != 7]
    assert all(messages.validate(m) for m in c1 + c2)
    assert c1[0]["b_nt"] == b1[0].tolist()
    assert sorted((m["code"], m["field"]) for m in rej) == [("duplicate", "t_s"), ("range", "b_nt")]
    assert r.drops[keys.raw_mag("car-1", "1")]["rejected:range"] == 1
    assert r.count_in[keys.raw_mag("car-1", "2")].n == n


def test_ingest_batches_out_within_the_window(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch, output="batches", batch_window_s=0.05)
    for i in range(5):  # v1 singles wait for the window
        for sensor in ("1", "2"):
            m = messages.make("mag", "car-1", 1.0 + 0.02 * i, i, sensor=sensor, b_nt=[2e4, 1e3, -4e4 + i])
            r.handle_sample(keys.raw_mag("car-1", sensor), messages.encode(m))
    assert s.out == []
    r.svc._pending["car-1"] = (0.0, r.svc._pending["car-1"][1])  # the window has passed
    r.svc.on_tick()
    assert [k for k, _ in s.out] == [keys.clean_batch("car-1")]
    b = batch.decode(s.out[0][1], check=True)
    assert b.seq == 0 and b.streams["mag/2"].n == 5
    assert b.streams["mag/2"].seq == [0, 1, 2, 3, 4]
    assert b.streams["mag/1"].cols["b_nt"][3] == [2e4, 1e3, -4e4 + 3]
    # a batch input goes out at once, numbered on from the singles
    t = 1.1 + np.arange(4) * 0.02
    r.handle_sample(keys.raw_batch("car-1"), _mag_batch("car-1", 0, t, _field(4), _field(4), s0=5))
    b2 = batch.decode(s.out[-1][1])
    assert b2.seq == 1 and b2.streams["mag/1"].seq == [5, 6, 7, 8]
    assert r.tick_period() == pytest.approx(0.025)


def test_bad_batch_is_refused_whole_with_the_field_named(tmp_path, monkeypatch):
    r, s = _ingest(tmp_path, monkeypatch)
    b1 = _field(3)
    b1[1, 2] = np.nan
    r.handle_sample(keys.raw_batch("car-1"), _mag_batch("car-1", 0, np.arange(3) * 0.1, b1, _field(3)))
    out = [(k, msgpack.unpackb(p)) for k, p in s.out]
    assert [k for k, _ in out] == [keys.rejects("car-1")]
    assert out[0][1]["field"] == "mag/1.b_nt" and out[0][1]["code"] == "schema"


@pytest.mark.parametrize("seed", range(5))
def test_vectorised_order_decisions_equal_the_per_sample_ones(seed):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.choice([0.02, 0.0, -0.03, 0.02, 0.02], 60))
    ok = rng.random(60) > 0.1
    last = float(t[0]) - 0.01 if seed % 2 else None
    dup, back = order_masks(t, ok, last)
    prev = last
    for i in range(60):  # the v1 rule: each sample against the last accepted one
        if not ok[i]:
            assert not (dup[i] and back[i])
            continue
        want_dup = prev is not None and t[i] == prev
        want_back = prev is not None and t[i] < prev
        assert (dup[i], back[i]) == (want_dup, want_back), i
        if not (want_dup or want_back):
            prev = t[i]


class _PerSample(Service):
    role = "probe"
    impl = "probe"

    def __init__(self, **kw):
        super().__init__(**kw)
        self.got = []

    def subscriptions(self):
        return [keys.clean_mag("*", "1"), keys.clean_imu("*")]

    def on_message(self, info, msg, state):
        self.got.append((info.key, msg["t_s"], msg["seq"]))


def test_runtime_unbatches_for_per_sample_services_in_time_order(tmp_path, monkeypatch):
    import zenoh

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    svc = _PerSample(instance="p-1")
    r = Runner(svc, _Session())
    r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
    r.batch_in = True
    payload = batch.encode("car-1", 0, {
        "mag/1": {"t_s": np.array([0.0, 0.02, 0.04]), "seq": np.array([0, 1, 3]),
                  "cols": {"sensor": "1", "b_nt": _field(3)}},
        "mag/2": {"t_s": np.array([0.0]), "seq": np.array([0]), "cols": {"sensor": "2", "b_nt": _field(1)}},
        "imu": {"t_s": np.array([0.01, 0.03]), "seq": np.array([0, 1]),
                "cols": {"gyro_rad_s": np.zeros((2, 3)), "accel_m_s2": np.zeros((2, 3))}}})
    r.handle_sample(keys.clean_batch("car-1"), payload)
    m1, imu = keys.clean_mag("car-1", "1"), keys.clean_imu("car-1")
    assert svc.got == [(m1, 0.0, 0), (imu, 0.01, 0), (m1, 0.02, 1), (imu, 0.03, 1), (m1, 0.04, 3)]
    assert r.drops[m1]["upstream_gap"] == 1  # seq 2 never came
    assert r.count_in[m1].n == 3 and keys.clean_mag("car-1", "2") not in r.count_in  # not subscribed: skipped
    assert r.last_in_t["car-1"] == 0.04


def test_runtime_unbatches_a_long_batch_in_time_order(tmp_path, monkeypatch):
    import zenoh

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    svc = _PerSample(instance="p-2")
    r = Runner(svc, _Session())
    r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
    r.batch_in = True
    n = 60  # 180 samples: ordered on whole columns
    payload = batch.encode("car-1", 0, {
        "mag/1": {"t_s": np.arange(n) * 0.02, "seq": np.arange(n), "cols": {"sensor": "1", "b_nt": _field(n)}},
        "imu": {"t_s": np.arange(2 * n) * 0.01 + 0.001, "seq": np.arange(2 * n),
                "cols": {"gyro_rad_s": np.zeros((2 * n, 3)), "accel_m_s2": np.zeros((2 * n, 3))}}})
    r.handle_sample(keys.clean_batch("car-1"), payload)
    times = [t for _, t, _ in svc.got]
    assert len(times) == 3 * n and times == sorted(times)
    assert [s for k, _, s in svc.got if k == keys.clean_imu("car-1")] == list(range(2 * n))


def test_typed_batch_decode_agrees_with_the_checking_decoder():
    """The one-pass typed decode of a valid batch gives what the checking path gives, and a damaged payload it
    still takes, the checking path takes with the same content; what it cannot take it hands over (so the
    checking path words the error). 400 seeded damaged copies of one batch."""
    from schemas.batch import _decode_typed, _Slow

    rng = np.random.default_rng(11)
    base = batch.encode("car-1", 4, {
        "mag/1": {"t_s": [1.0, 1.02], "seq": [7, 8], "cols": {"sensor": "1", "b_nt": _field(2)}},
        "imu": {"t_s": [1.0, 1.01, 1.02], "seq": [1, 2, 3],
                "cols": {"gyro_rad_s": _field(3) * 1e-4, "accel_m_s2": _field(3) * 1e-4}},
        "gnss": {"t_s": [1.0], "seq": [0], "cols": {
            "lat_deg": [32.0], "lon_deg": [118.8], "alt_m": [10.0], "vel_enu_m_s": [[1.0, 0.0, 0.0]],
            "course_rad": [1.0], "speed_m_s": [1.0], "fix_type": ["3d"], "num_sats": [9], "pdop": [1.2]}}})

    def view(b):
        return (b.vehicle, b.t_s, b.seq, {k: (c.t_s, c.seq, c.cols) for k, c in b.streams.items()})

    assert view(_decode_typed(base)) == view(_checking_decode(base))
    typed_ok = handed_over = 0
    for i in range(400):
        p = bytearray(base)
        for _ in range(int(rng.integers(1, 3))):
            p[int(rng.integers(0, len(p)))] = int(rng.integers(0, 256))
        p = bytes(p)
        try:
            t = _decode_typed(p)
        except (_Slow, messages.SchemaError):
            handed_over += 1
            continue
        typed_ok += 1
        assert view(t) == view(_checking_decode(p)), i
    assert typed_ok > 100 and handed_over > 50


def _checking_decode(p):
    """schemas.batch.decode with its typed fast path switched off."""
    import schemas.batch as sb

    real = sb._decode_typed

    def refuse(_):
        raise sb._Slow

    sb._decode_typed = refuse
    try:
        return sb.decode(p, check=True)
    finally:
        sb._decode_typed = real


def _gnss_cols(n):
    return {"lat_deg": [32.0] * n, "lon_deg": [118.8] * n, "alt_m": [10.0] * n,
            "vel_enu_m_s": [[1.0, 0.0, 0.0]] * n, "course_rad": [1.0] * n, "speed_m_s": [1.0] * n,
            "fix_type": ["3d"] * n, "num_sats": [9] * n, "pdop": [1.2] * n}


def test_binary_batch_decodes_as_the_list_form():
    streams = {"mag/1": {"t_s": [1.0, 1.02], "seq": [7, 8], "cols": {"sensor": "1", "b_nt": _field(2),
                                                                     "temp_c": [20.5, 20.6]}},
               "imu": {"t_s": [1.0, 1.01, 1.02], "seq": [1, 2, 3],
                       "cols": {"gyro_rad_s": _field(3) * 1e-4, "accel_m_s2": _field(3) * 1e-4}},
               "gnss": {"t_s": [1.0], "seq": [0], "cols": _gnss_cols(1)}}
    v2 = batch.decode(batch.encode("car-1", 4, streams))
    p3 = batch.encode("car-1", 4, streams, binary=True)
    assert msgpack.unpackb(p3)["version"] == 3
    v3 = batch.decode(p3)
    arr = batch.decode(p3, arrays=True)
    assert (v3.vehicle, v3.seq, v3.t_s) == (v2.vehicle, v2.seq, v2.t_s)
    for name, c in v2.streams.items():
        c3 = v3.streams[name]
        assert (c3.t_s, c3.seq, c3.cols) == (c.t_s, c.seq, c.cols), name
        assert isinstance(arr.streams[name].t_s, np.ndarray)
    np.testing.assert_array_equal(arr.streams["imu"].cols["gyro_rad_s"], np.asarray(v2.streams["imu"].cols["gyro_rad_s"]))


@pytest.mark.parametrize("change,field", [
    (lambda s: s["mag/1"]["cols"].__setitem__("b_nt", np.array([[1.0, np.nan, 0.0], [1.0, 2.0, 3.0]])), "mag/1.b_nt"),
    (lambda s: s["gnss"]["cols"].__setitem__("lat_deg", [95.0]), "gnss.lat_deg"),
    (lambda s: s["gnss"]["cols"].__setitem__("fix_type", ["4d"]), "gnss.fix_type"),
    (lambda s: s["gnss"]["cols"].pop("pdop"), "gnss.pdop"),
    (lambda s: s["mag/1"]["cols"].__setitem__("sensor", "2"), "mag/1.sensor"),
    (lambda s: s["mag/1"].__setitem__("seq", [7]), "mag/1.t_s"),
])
def test_binary_batch_refused_whole_with_the_field_named(change, field):
    streams = {"mag/1": {"t_s": [1.0, 1.02], "seq": [7, 8], "cols": {"sensor": "1", "b_nt": _field(2)}},
               "gnss": {"t_s": [1.0], "seq": [0], "cols": _gnss_cols(1)}}
    change(streams)
    with pytest.raises(messages.SchemaError) as e:
        batch.decode(batch.encode("car-1", 0, streams, binary=True))
    assert e.value.field == field


def test_ingest_frames_take_binary_batches(tmp_path, monkeypatch):
    from schemas import frame

    r, s = _ingest(tmp_path, monkeypatch, output="frames", batch_window_s=0.05)
    t = 1.0 + np.arange(6) * 0.02
    b1 = _field(6)
    b1[2] = [3e6, 0, 0]  # beyond what a magnetometer reads: refused, the rest goes out
    r.handle_sample(keys.raw_batch("car-1"), batch.encode("car-1", 0, {
        "mag/1": {"t_s": t, "seq": np.arange(6), "cols": {"sensor": "1", "b_nt": b1}}}, binary=True))
    r.handle_sample(keys.raw_batch("car-2"), batch.encode("car-2", 0, {
        "mag/1": {"t_s": t[:2], "seq": [0, 1], "cols": {"sensor": "1", "b_nt": b1[:2]}}}))  # a list batch beside it
    r.svc.frame_flush(force=True)
    (f,) = [frame.decode(p) for k, p in s.out if k.startswith("magmesh/fleet/")]
    st = f.streams["mag/1"]
    assert [f.vehicles[i] for i in st.vi.tolist()] == ["car-1"] * 5 + ["car-2"] * 2
    np.testing.assert_array_equal(st.cols["b_nt"][:5], np.delete(b1, 2, axis=0))
    assert r.drops[keys.raw_mag("car-1", "1")]["rejected:range"] == 1


def test_ingest_frames_refuse_a_binary_batch_whole_at_the_window(tmp_path, monkeypatch):
    """A binary batch's values are checked with the whole window; one bad value refuses that batch — all its
    streams — with the field named, as a list batch is refused at decoding; other batches go out."""
    from schemas import frame

    r, s = _ingest(tmp_path, monkeypatch, output="frames", batch_window_s=0.05)
    t = 1.0 + np.arange(4) * 0.02
    good = {"mag/1": {"t_s": t, "seq": np.arange(4), "cols": {"sensor": "1", "b_nt": _field(4)}},
            "imu": {"t_s": t, "seq": np.arange(4), "cols": {"gyro_rad_s": _field(4) * 1e-4,
                                                            "accel_m_s2": _field(4) * 1e-4}}}
    bad_b = _field(4)
    bad_b[1, 0] = np.inf
    bad = {"mag/1": {"t_s": t + 1, "seq": np.arange(4, 8), "cols": {"sensor": "1", "b_nt": bad_b}},
           "imu": dict(good["imu"], t_s=t + 1, seq=np.arange(4, 8))}
    r.handle_sample(keys.raw_batch("car-1"), batch.encode("car-1", 0, good, binary=True))
    r.handle_sample(keys.raw_batch("car-1"), batch.encode("car-1", 1, bad, binary=True))
    r.handle_sample(keys.raw_batch("car-2"), batch.encode("car-2", 0, good, binary=True))
    r.svc.frame_flush(force=True)
    (f,) = [frame.decode(p) for k, p in s.out if k.startswith("magmesh/fleet/")]
    for name in ("mag/1", "imu"):
        st = f.streams[name]
        assert [f.vehicles[i] for i in st.vi.tolist()] == ["car-1"] * 4 + ["car-2"] * 4, name
    rej = [msgpack.unpackb(p) for k, p in s.out if k == keys.rejects("car-1")]
    assert [(m["code"], m["field"], m["key"]) for m in rej] == [("schema", "mag/1.b_nt", keys.raw_batch("car-1"))]
    assert "must be finite" in rej[0]["reason"]


@pytest.mark.parametrize("rows", [1, 3])
def test_a_frames_last_rows_are_read_without_its_columns(rows):
    """frame.last_rows (what a group member watches the others' outputs with) gives each vehicle's last row per
    stream as the full decode does; it refuses what is not a frame."""
    import numpy as np

    from schemas import frame

    rng = np.random.default_rng(rows)
    nveh = 5
    vi = np.repeat(np.arange(nveh, dtype=np.uint32), rows)[1:]  # vehicle 0 has one row less
    n = vi.size
    t = np.sort(rng.uniform(0, 10, n))
    seq = rng.integers(0, 10_000, n)
    order = np.lexsort((t, vi))
    z = np.zeros(n)
    st = frame.Stream("dmc", "dmc", vi[order], t[order], np.sort(seq)[order], {
        "dm_nt": np.zeros((n, 2)), "ddm_nt_s": np.zeros((n, 2)), "dh_rad": z, "ddh_rad_s": z, "heading_rad": z,
        "stage1_pass": np.ones(n, bool), "credibility": z + 1, "valid": np.ones(n, bool), "impl": "threshold",
        "param_source": "manifest"})
    vehicles = [f"car-{i}" for i in range(nveh)]
    payload = frame.encode("dmc-7", "dmc", 3, vehicles, {"dmc": st})
    shard, kind, got = frame.last_rows(payload)
    full = frame.decode(payload).streams["dmc"]
    want = {}
    for i, q, tt in zip(full.vi.tolist(), full.seq.tolist(), full.t_s.tolist(), strict=True):
        want[vehicles[i]] = ("dmc", q, tt)  # rows sorted by vehicle, then time: the last one stays
    assert (shard, kind) == ("dmc-7", "dmc")
    assert {v: (name, q, tt) for v, name, q, tt in got} == want and len(got) == len(want)
    with pytest.raises(ValueError):
        frame.last_rows(b"\x81\xa4type\xa5batch")


def test_a_frames_vehicle_list_is_read_once_and_bad_bytes_in_it_refuse_the_frame():
    """The decoder reads a shard's vehicle list once per distinct list (the same names object frame after frame);
    bad msgpack inside the list (invalid UTF-8 here) refuses the frame as bad msgpack anywhere does, never a
    decoder's own error (the fuzz suite once found that)."""
    import numpy as np

    from schemas import frame
    from schemas.messages import SchemaError

    z = np.zeros(1)
    st = frame.Stream("dmc", "dmc", np.array([0], np.uint32), np.array([1.0]), np.array([1], np.int64), {
        "dm_nt": np.zeros((1, 2)), "ddm_nt_s": np.zeros((1, 2)), "dh_rad": z, "ddh_rad_s": z, "heading_rad": z,
        "stage1_pass": np.ones(1, bool), "credibility": z + 1, "valid": np.ones(1, bool), "impl": "threshold",
        "param_source": "manifest"})
    payload = frame.encode("dmc-1", "dmc", 0, ["car-1"], {"dmc": st})
    a, b = frame.decode(payload), frame.decode(payload)
    assert a.vehicles == b.vehicles == ["car-1"]
    i = payload.find(b"car-1")
    with pytest.raises(SchemaError, match="not valid msgpack"):
        frame.decode(payload[:i] + b"\xff" + payload[i + 1:])
