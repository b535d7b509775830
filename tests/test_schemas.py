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
