"""MCAP recording: round trip, schemas, counts, key matching, remap and replay timing."""

from __future__ import annotations

import json
import time
from collections import Counter

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from magmesh_cli import recording as rc
from schemas import keys, messages


def _mag(vehicle, sensor, t, seq, b=(1.0, 2.0, 3.0)):
    return messages.make("mag", vehicle, t, seq, sensor=sensor, b_nt=list(b))


def _write_demo(path, n=50, dt=0.01, t0_ns=1_700_000_000_000_000_000):
    with rc.RecordingWriter(path, info={"key_exprs": ["magmesh/**"]}) as w:
        for i in range(n):
            w.write_message(keys.raw_mag("car-1", "1"), _mag("car-1", "1", i * dt, i), t0_ns + int(i * dt * 1e9))
            if i % 5 == 0:
                msg = messages.make("alarm", "car-1", i * dt, i // 5, source="dmc", state="raised",
                                    severity="warning", reason="test", value=1.0, threshold=0.5, service="t")
                w.write_message(keys.alarm("car-1", "dmc"), msg, t0_ns + int(i * dt * 1e9) + 1000)
        w.write(keys.raw_imu("car-1"), b"\xc1not msgpack", t0_ns + 5)
    return w


def test_round_trip_keeps_bytes_times_and_types(tmp_path):
    path = tmp_path / "run.mcap"
    w = _write_demo(path)
    assert w.counts.as_dict()["written"] == 60 and w.counts.as_dict()["unvalidated"] == 1
    recs = list(rc.read_records(path))
    assert len(recs) == 61
    assert [r.receive_ns for r in recs] == sorted(r.receive_ns for r in recs)
    mags = [r for r in recs if r.msg_type == "mag"]
    assert len(mags) == 50
    m7 = mags[7].decode()
    assert m7["seq"] == 7 and m7["t_s"] == pytest.approx(0.07) and m7["b_nt"] == [1.0, 2.0, 3.0]
    assert mags[7].sample_ns == round(0.07 * 1e9)
    bad = [r for r in recs if r.msg_type is None]
    assert len(bad) == 1 and bad[0].payload == b"\xc1not msgpack"
    counts = Counter()
    loaded = rc.load_messages(path, counts=counts)
    assert len(loaded) == 60 and counts == Counter({"undecodable: magmesh/car-1/raw/imu": 1})


def test_file_has_schemas_channel_metadata_and_counts(tmp_path):
    path = tmp_path / "run.mcap"
    _write_demo(path)
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summ = reader.get_summary()
        schemas = {s.name: s for s in summ.schemas.values()}
        assert set(schemas) == {"magmesh.mag", "magmesh.alarm"}
        js = json.loads(schemas["magmesh.mag"].data)
        assert schemas["magmesh.mag"].encoding == "jsonschema"
        assert "b_nt" in js["properties"] and "b_nt" in js["required"] and "t_s" in js["required"]
        chans = {c.topic: c for c in summ.channels.values()}
        assert chans["magmesh/car-1/raw/mag/1"].message_encoding == "msgpack"
        assert chans["magmesh/car-1/raw/mag/1"].metadata["vehicle"] == "car-1"
    s = rc.summarize(path)
    assert s["messages"] == 61 and s["keys"]["magmesh/car-1/alarm/dmc"] == 10
    assert json.loads(s["metadata"]["counts"])["written"] == 60
    assert s["duration_s"] == pytest.approx(0.49, abs=1e-3)


def test_every_message_type_has_a_json_schema():
    for name in messages.MESSAGES:
        js = rc.json_schema(name)
        assert js["type"] == "object" and "seq" in js["required"]


@pytest.mark.parametrize(
    "expr,key,ok",
    [
        ("magmesh/**", "magmesh/car-1/raw/mag/1", True),
        ("magmesh/*/raw/**", "magmesh/car-1/raw/mag/1", True),
        ("magmesh/*/raw/**", "magmesh/car-1/clean/mag/1", False),
        ("magmesh/car-$*/dmc", "magmesh/car-7/dmc", True),
        ("magmesh/car-$*/dmc", "magmesh/drone-1/dmc", False),
        ("magmesh/*/dmc", "magmesh/car-1/dmc/x", False),
        ("magmesh/**/mag/1", "magmesh/car-1/clean/mag/1", True),
        ("magmesh/car-1/**", "magmesh/car-1", True),
    ],
)
def test_keyexpr_matches(expr, key, ok):
    assert rc.keyexpr_matches(expr, key) is ok


def test_key_filter_on_read(tmp_path):
    path = tmp_path / "run.mcap"
    _write_demo(path)
    assert {r.key for r in rc.read_records(path, ["magmesh/*/alarm/**"])} == {"magmesh/car-1/alarm/dmc"}


def test_remap_vehicle_rewrites_key_and_payload():
    r = rc.Remap.parse("car-1=car-9")
    payload = messages.encode(_mag("car-1", "1", 1.0, 3))
    key, out = rc.remap_sample(keys.raw_mag("car-1", "1"), payload, [r])
    assert key == "magmesh/car-9/raw/mag/1"
    msg = messages.decode(out)
    assert msg["vehicle"] == "car-9" and msg["seq"] == 3
    # other vehicles untouched, byte for byte
    other = messages.encode(_mag("car-2", "1", 1.0, 3))
    assert rc.remap_sample(keys.raw_mag("car-2", "1"), other, [r]) == (keys.raw_mag("car-2", "1"), other)


def test_remap_prefix():
    r = rc.Remap.parse("magmesh/car-1/clean=magmesh/car-1/raw")
    payload = messages.encode(_mag("car-1", "1", 1.0, 0))
    key, out = rc.remap_sample("magmesh/car-1/clean/mag/1", payload, [r])
    assert key == "magmesh/car-1/raw/mag/1" and out == payload
    assert r.apply_key("magmesh/car-1/cleaner/x") == "magmesh/car-1/cleaner/x"
    with pytest.raises(ValueError):
        rc.Remap.parse("car-1=magmesh/x")
    with pytest.raises(ValueError):
        rc.Remap.parse("car-1")
    with pytest.raises(ValueError):
        rc.remap_sample("magmesh/car-1/dmc", payload, [rc.Remap.parse("magmesh/car-1/dmc=magmesh/car-1/bogus")])


def test_parse_rate():
    assert rc.parse_rate("max") == 0.0 and rc.parse_rate("2.5") == 2.5
    with pytest.raises(ValueError):
        rc.parse_rate("-1")


@pytest.mark.parametrize("rate", [1.0, 2.0, 4.0])
def test_replay_keeps_original_timing_scaled_by_rate(tmp_path, rate):
    path = tmp_path / "run.mcap"
    _write_demo(path, n=41, dt=0.01)  # 0.40 s of recording
    recs = list(rc.read_records(path))
    rel_s = [(r.receive_ns - recs[0].receive_ns) / 1e9 for r in recs]
    # on a clock the test controls: every sample goes out exactly at its recorded offset / rate
    now = [100.0]
    sent: list[tuple[float, str]] = []
    stats = rc.replay(iter(recs), lambda k, p: sent.append((now[0] - 100.0, k)), rate=rate,
                      clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    assert stats.as_dict()["published"] == len(sent) == 41 + 9 + 1
    assert stats.recorded_span_s == pytest.approx(0.40, abs=1e-3)
    np.testing.assert_allclose([t for t, _ in sent], np.array(rel_s) / rate, atol=1e-9)
    assert [k for _, k in sent] == [r.key for r in recs]
    assert stats.wall_s == pytest.approx(rel_s[-1] / rate, abs=1e-9) and stats.max_late_s == 0.0
    # on the real clock a sample is never sent before its time (later is only load, not checked)
    real: list[float] = []
    t0 = time.monotonic()
    rc.replay(iter(recs), lambda k, p: real.append(time.monotonic() - t0), rate=rate)
    assert all(t >= due - 1e-3 for t, due in zip(real, np.array(rel_s) / rate, strict=True))


def test_replay_max_rate_does_not_wait(tmp_path):
    path = tmp_path / "run.mcap"
    _write_demo(path, n=200, dt=0.05)  # 10 s of recording
    sleeps = []
    stats = rc.replay(rc.read_records(path), lambda k, p: None, rate=0.0, sleep=sleeps.append)
    assert sleeps == [] and stats.as_dict()["published"] == 241  # 10 s of recording, never a sleep


def test_replay_with_fake_clock_applies_remap():
    now = [0.0]
    recs = [rc.Record("magmesh/car-1/dmc", "dmc", msgpack.packb({"vehicle": "car-1"}), int(i * 1e9), 0)
            for i in range(4)]
    out = []
    stats = rc.replay(recs, lambda k, p: out.append((now[0], k, msgpack.unpackb(p)["vehicle"])), rate=0.5,
                      clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s),
                      remaps=[rc.Remap.parse("car-1=car-2")])
    assert [o[0] for o in out] == [0.0, 2.0, 4.0, 6.0]
    assert {o[1] for o in out} == {"magmesh/car-2/dmc"} and {o[2] for o in out} == {"car-2"}
    assert stats.max_late_s == 0.0


def test_liveliness_events_are_stored_apart_from_messages(tmp_path):
    path = tmp_path / "run.mcap"
    with rc.RecordingWriter(path) as w:
        w.write_message(keys.raw_mag("car-1", "1"), _mag("car-1", "1", 0.0, 0), 1_000)
        w.write_liveliness(keys.svc_token("dmc_detector", "dmc-1"), True, 2_000)
        w.write_liveliness(keys.svc_token("dmc_detector", "dmc-1"), False, 3_000)
    assert w.counts.as_dict()["liveliness"] == 2
    assert [r.key for r in rc.read_records(path)] == ["magmesh/car-1/raw/mag/1"]
    assert rc.load_liveliness(path) == [(2e-6, "magmesh/svc/dmc_detector/dmc-1", True),
                                        (3e-6, "magmesh/svc/dmc_detector/dmc-1", False)]
    assert len(rc.load_messages(path)) == 1


def test_json_copy_for_viewers(tmp_path):
    src, dst = tmp_path / "run.mcap", tmp_path / "run.json.mcap"
    _write_demo(src)
    with rc.RecordingWriter(tmp_path / "x.mcap") as w:  # liveliness is not counted as messages
        w.write_liveliness(keys.svc_token("ingest", "i-1"), True, 5)
    assert rc.summarize(tmp_path / "x.mcap")["messages"] == 0
    assert rc.summarize(tmp_path / "x.mcap")["liveliness_events"] == 1
    r = rc.to_json_mcap(src, dst)
    assert r == {"written": 60, "left_out": 1}
    with open(dst, "rb") as fh:
        got = [(c.topic, c.message_encoding, json.loads(m.data), m.log_time)
               for _, c, m in make_reader(fh).iter_messages(log_time_order=True)]
    orig = rc.load_messages(src)
    assert [(g[0], g[2]) for g in got] == orig
    assert {g[1] for g in got} == {"json"}


def test_time_window(tmp_path):
    path = tmp_path / "run.mcap"
    _write_demo(path, n=50, dt=0.01)
    s = rc.summarize(path)
    got = list(rc.time_window(rc.read_records(path, [keys.raw_mag("*", "*")]), s["start_ns"], 0.1, 0.2))
    assert [r.decode()["seq"] for r in got] == list(range(10, 20))
    assert len(list(rc.time_window(rc.read_records(path), s["start_ns"], 0.45))) == 5 + 1  # 45..49 and an alarm
