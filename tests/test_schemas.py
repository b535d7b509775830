"""Wire contract: key grammar, round trips of every message type, typed errors for bad input."""

import math

import msgpack
import pytest

from schemas import MESSAGES, SchemaError, decode, encode, keys, make, messages

VALUE = {
    "str": "x",
    "int": 3,
    "float": 1.5,
    "bool": True,
    "vec3": [1.0, -2.0, 3.5],
    "map": {"a": 1},
    "strs": ["a", "b"],
}


def sample_fields(mt):
    out = {}
    for f in mt.fields:
        if f.choices:
            v = f.choices[0]
        elif f.kind in ("floats", "mat3"):
            v = [0.5] * (f.length or (9 if f.kind == "mat3" else 4))
        elif f.kind == "bools":
            v = [True] * (f.length or 2)
        else:
            v = VALUE[f.kind]
        if f.kind in ("float", "int") and f.lo is not None:
            v = type(v)(max(v, f.lo))
        if f.kind in ("float", "int") and f.hi is not None:
            v = type(v)(min(v, f.hi))
        out[f.name] = v
    return out


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_round_trip_every_type(name):
    mt = MESSAGES[name]
    msg = make(name, "car-1", 12.25, 7, **sample_fields(mt))
    back = decode(encode(msg))
    assert back == msg
    # only required fields
    req = {f.name: v for f, v in zip(mt.fields, sample_fields(mt).values(), strict=False) if f.required}
    assert decode(encode(make(name, "car-1", 0.0, 0, **req)))["type"] == name


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_missing_required_field_is_named(name):
    mt = MESSAGES[name]
    req = [f for f in mt.fields if f.required]
    if not req:
        pytest.skip("no required fields")
    fields = sample_fields(mt)
    del fields[req[0].name]
    payload = msgpack.packb(make(name, "car-1", 0.0, 0, **fields))
    with pytest.raises(SchemaError) as e:
        decode(payload, where="k")
    assert e.value.field == req[0].name and "missing" in str(e.value)


def test_unknown_extra_fields_are_kept_not_required():
    m = make("mag", "car-1", 1.0, 1, sensor="1", b_nt=[1, 2, 3], future_field_x=5)
    assert decode(msgpack.packb(m))["future_field_x"] == 5


@pytest.mark.parametrize(
    "payload,field,words",
    [
        (b"", "<payload>", "empty"),
        (b"\xc1\xc1garbage", "<payload>", "not valid msgpack"),
        (msgpack.packb([1, 2, 3]), "<payload>", "map"),
        (msgpack.packb({"type": "nope", "version": 1}), "type", "unknown"),
        (msgpack.packb({"type": "mag", "version": 99, "vehicle": "v", "t_s": 0.0, "seq": 0}), "version", "99"),
        (msgpack.packb({"type": "mag", "version": "1"}), "version", "integer"),
        (msgpack.packb(make("mag", "v", 0.0, 0, sensor="1", b_nt=[math.nan, 0, 0])), "b_nt", "finite"),
        (msgpack.packb(make("mag", "v", 0.0, 0, sensor="1", b_nt=[math.inf, 0, 0])), "b_nt", "finite"),
        (msgpack.packb(make("mag", "v", 0.0, 0, sensor="1", b_nt=[1, 2])), "b_nt", "3"),
        (msgpack.packb(make("mag", "v", 0.0, 0, sensor="1", b_nt="abc")), "b_nt", "array"),
        (msgpack.packb(make("mag", "v", 0.0, -1, sensor="1", b_nt=[1, 2, 3])), "seq", "≥ 0"),
        (msgpack.packb(make("mag", "v", math.nan, 0, sensor="1", b_nt=[1, 2, 3])), "t_s", "finite"),
        (msgpack.packb(make("imu", "v", 0.0, 0, gyro_rad_s=[0, 0, True], accel_m_s2=[0, 0, 9.8])), "gyro_rad_s", ""),
        (msgpack.packb(make("mag", "v", 0.0, 0, sensor="x" * 5000, b_nt=[1, 2, 3])), "sensor", "5000"),
        (msgpack.packb({**make("mag", "v", 0.0, 0, sensor="1", b_nt=[1, 2, 3]), 5: 1}), "<payload>", "map key"),
    ],
)
def test_bad_payloads_raise_typed_errors(payload, field, words):
    with pytest.raises(SchemaError) as e:
        decode(payload, where="magmesh/v/raw/mag/1")
    assert e.value.field == field
    assert words in str(e.value)
    assert "magmesh/v/raw/mag/1" in str(e.value) or field in ("<payload>",)


def test_expected_type_enforced():
    p = encode(make("imu", "v", 0.0, 0, gyro_rad_s=[0, 0, 0], accel_m_s2=[0, 0, 9.8]))
    with pytest.raises(SchemaError, match="must be 'mag'"):
        decode(p, expected_type="mag")


def test_keys_build_and_parse():
    k = keys.raw_mag("car-1", "2")
    assert k == "magmesh/car-1/raw/mag/2"
    info = keys.parse(k)
    assert (info.vehicle, info.kind, info.stream, info.sensor) == ("car-1", "raw", "mag", "2")
    assert keys.raw_to_clean(k) == "magmesh/car-1/clean/mag/2"
    assert keys.parse(keys.alarm("car-1", "dmc")).source == "dmc"
    assert keys.parse(keys.svc_status("dmc_detector", "dmc-1")).kind == "svc"
    assert messages.type_for_key(keys.cal_params("v", "1")) == "cal_params"
    assert messages.type_for_key(keys.dmc("v")) == "dmc"
    assert keys.alarms_all() == "magmesh/*/alarm/**"


@pytest.mark.parametrize("bad", ["magmesh", "other/car/raw/imu", "magmesh/car-1/raw/foo", "magmesh/car 1/raw/imu",
                                 "magmesh/car-1/raw/mag", "magmesh/car-1/alarm", "magmesh/*/raw/imu",
                                 "magmesh/car-1/cal/x/1", "magmesh/" + "a" * 70 + "/dmc"])
def test_bad_keys_are_refused(bad):
    with pytest.raises(keys.KeyError_):
        keys.parse(bad)


@pytest.mark.parametrize("bad", ["", "a/b", "*", "a b", "$x", "-lead", "x" * 65])
def test_bad_ids_are_refused(bad):
    with pytest.raises(keys.KeyError_):
        keys.check_id(bad)


def test_contract_table_is_up_to_date():
    from pathlib import Path

    from schemas import doc

    assert (Path(__file__).resolve().parent.parent / "schemas" / "README.md").read_text() == doc.render(), \
        "run: python -m schemas.doc > schemas/README.md"


# ---- the streams table, typed structs, encodings, batches -------------------------------------------

import numpy as np  # noqa: E402

from schemas import batch, streams  # noqa: E402


def _fill(template: str) -> str:
    return template.format(vehicle="car-1", sensor="2", source="dmc", what="pose")


@pytest.mark.parametrize("name", sorted(n for n in streams.STREAMS if not n.startswith("fleet/")))
def test_streams_table_rows_agree_with_key_builders_and_types(name):
    st = streams.STREAMS[name]
    args = [a for a in ("car-1", "2" if "{sensor}" in st.template else None,
                        "dmc" if "{source}" in st.template else None, "pose" if "{what}" in st.template else None)
            if a is not None]
    key = st.builder(*args)
    assert key == _fill(st.template)
    assert streams.stream_for_key(key) is st
    assert messages.type_for_key(key) == st.msg_type == streams.type_for_key(key)
    assert streams.encoding_for_key(key) == f"application/msgpack;magmesh/{st.msg_type}/v1"
    assert streams.parse_encoding(st.encoding) == (st.msg_type, MESSAGES[st.msg_type].version)


@pytest.mark.parametrize("kind", ["clean", "cal", "dmc"])
def test_fleet_frame_rows_of_the_streams_table(kind):
    st = streams.STREAMS[f"fleet/{kind}"]
    key = st.builder("ingest-1", kind)
    assert key == st.template.format(shard="ingest-1") == f"magmesh/fleet/ingest-1/{kind}"
    assert streams.stream_for_key(key) is st and st.msg_type == "frame"
    assert streams.encoding_for_key(key) == "application/msgpack;magmesh/frame/v3"
    assert streams.parse_encoding(st.encoding) == ("frame", 3)
    assert streams.json_schema("frame")["title"] == "magmesh frame v3"


def test_every_message_type_has_a_stream_and_batch_keys_have_theirs():
    assert {s.msg_type for s in streams.STREAMS.values()} == set(MESSAGES) | {"frame"}
    assert streams.encoding_for_key(keys.clean_batch("car-1")) == "application/msgpack;magmesh/batch/v2"
    assert keys.parse(keys.raw_batch("car-1")).rest == ("batch",)
    assert streams.parse_encoding("application/json;magmesh/mag/v1") is None


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_compiled_decoder_equals_reference(name):
    mt = MESSAGES[name]
    msg = make(name, "car-1", 12.25, 7, **sample_fields(mt))
    payload = encode(msg)
    assert streams.fast_decode(payload, expected_type=name) == decode(payload) == msg
    schema = streams.json_schema(name)
    assert schema["title"] == f"magmesh {name} v{mt.version}"
    assert set(schema["required"]) >= {"type", "version", "vehicle", "t_s", "seq"} | {
        f.name for f in mt.fields if f.required}


@pytest.mark.parametrize("bad,field", [
    (make("mag", "v", 0.0, 0, sensor="1", b_nt=[math.nan, 0, 0]), "b_nt"),
    (make("mag", "v", 0.0, 0, sensor="1", b_nt=[1, 2]), "b_nt"),
    (make("imu", "v", 0.0, 0, gyro_rad_s=[0, 0, True], accel_m_s2=[0, 0, 9.8]), "gyro_rad_s"),
    (make("gnss", "v", 0.0, 0, lat_deg=91.0, lon_deg=0.0, alt_m=0.0, vel_enu_m_s=[0, 0, 0], course_rad=0.0,
          speed_m_s=0.0, fix_type="3d", num_sats=5, pdop=1.0), "lat_deg"),
    (make("dmc", "v", 0.0, 0, **{**sample_fields(MESSAGES["dmc"]), "param_source": "guess"}), "param_source"),
])
def test_compiled_decoder_refuses_what_the_reference_refuses(bad, field):
    with pytest.raises(SchemaError) as e:
        streams.fast_decode(msgpack.packb(bad), where="k")
    assert e.value.field == field


def _cols(n, t0=0.0):
    rng = np.random.default_rng(3)
    return {"mag/1": {"t_s": t0 + np.arange(n) * 0.02, "seq": np.arange(n), "cols": {
                "sensor": "1", "b_nt": rng.normal(size=(n, 3)) * 2e4}},
            "imu": {"t_s": t0 + np.arange(2 * n) * 0.01, "seq": 10 + np.arange(2 * n), "cols": {
                "gyro_rad_s": rng.normal(size=(2 * n, 3)), "accel_m_s2": rng.normal(size=(2 * n, 3))}}}


def test_batch_round_trip_and_unbatching_gives_valid_v1_messages():
    c = _cols(5)
    b = batch.decode(batch.encode("car-1", 4, c), where="k")
    assert (b.vehicle, b.seq, b.n) == ("car-1", 4, 15)
    assert b.t_s == pytest.approx(0.09)
    msgs = b.streams["imu"].messages("car-1")
    assert [m["seq"] for m in msgs] == list(range(10, 20))
    for m in msgs + b.streams["mag/1"].messages("car-1"):
        assert decode(encode(m)) == m  # every unbatched sample is a valid v1 message
    assert msgs[3]["gyro_rad_s"] == c["imu"]["cols"]["gyro_rad_s"][3].tolist()
    assert b.streams["mag/1"].array("b_nt").shape == (5, 3)


@pytest.mark.parametrize("spoil,field", [
    (lambda c: c["mag/1"]["cols"]["b_nt"].__setitem__((2, 1), np.nan), "mag/1.b_nt"),
    (lambda c: c["mag/1"]["cols"].pop("b_nt"), "mag/1.b_nt"),
    (lambda c: c["mag/1"]["cols"].__setitem__("sensor", "2"), "mag/1.sensor"),
    (lambda c: c.__setitem__("foo", c.pop("imu")), "streams"),
])
def test_bad_batches_name_stream_and_field(spoil, field):
    c = _cols(4)
    spoil(c)
    try:
        payload = batch.encode("car-1", 0, c)
    except SchemaError as e:  # the encoder refuses an unknown stream name itself
        assert e.field == field
        return
    with pytest.raises(SchemaError) as e:
        batch.decode(payload, where="magmesh/car-1/raw/batch")
    assert e.value.field == field


def test_batch_refuses_wrong_column_length_and_version():
    c = _cols(4)
    p = msgpack.unpackb(batch.encode("car-1", 0, c))
    p["streams"]["imu"]["cols"]["accel_m_s2"] = p["streams"]["imu"]["cols"]["accel_m_s2"][:-1]
    with pytest.raises(SchemaError, match="n = 8"):
        batch.decode(msgpack.packb(p))
    p = msgpack.unpackb(batch.encode("car-1", 0, c))
    p["version"] = 1
    with pytest.raises(SchemaError) as e:
        batch.decode(msgpack.packb(p))
    assert e.value.field == "version"


def test_vectorised_limits_agree_with_per_sample_limits():
    rng = np.random.default_rng(8)
    b = rng.normal(size=(200, 3)) * 1.5e6  # some beyond the 2e6 nT limit
    masks = streams.limit_masks("mag", {"b_nt": b}, 200)
    per = np.array([streams.limit_problem(make("mag", "v", 0.0, 0, sensor="1", b_nt=x.tolist())) is not None
                    for x in b])
    assert per.any() and not per.all()
    assert len(masks) == 1 and masks[0][0] == "b_nt"
    assert np.array_equal(masks[0][1], per)
