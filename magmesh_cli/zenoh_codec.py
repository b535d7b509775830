"""A codec for zenoh-cli (``pip install zenoh-cli``): print magmesh messages as JSON, put JSON as magmesh messages.

zenoh-cli 0.7 finds codecs through the entry-point groups ``zenoh_cli.codecs.decoders`` and
``zenoh_cli.codecs.encoders``; magmesh registers both under the name ``magmesh`` (``pyproject.toml``), so
once magmesh is installed::

    zenoh --mode client --connect tcp/127.0.0.1:7447 subscribe -k 'magmesh/**' --decoder magmesh --line '{key} {value}'
    zenoh --mode client --connect tcp/127.0.0.1:7447 put -k magmesh/car-1/raw/imu --encoder magmesh \\
        -v '{"type":"imu","version":1,"vehicle":"car-1","t_s":1.0,"seq":1,"gyro_rad_s":[0,0,0],"accel_m_s2":[0,0,9.81]}'

The decoder prints one JSON object per sample: the validated message; a batch (contract v2) as
``{"type": "batch", "vehicle", "t_s", "seq", "samples": [{"key": ..., <message>}, ...]}``; a service status as
its map. A msgpack map that breaks the contract is printed with ``"_invalid"`` saying what is wrong (a
monitor should show bad data, not hide it); bytes that are not msgpack raise, and zenoh-cli reports the
failure and goes on. The encoder validates before it encodes: a JSON message that breaks the contract is
refused with the field and the problem.
"""

from __future__ import annotations

import base64
import json

import msgpack

from schemas import keys, messages


def _default(o):
    if isinstance(o, (bytes, bytearray, memoryview)):
        return {"_base64": base64.b64encode(bytes(o)).decode()}
    raise TypeError(f"cannot show {type(o).__name__}")


def _dumps(obj) -> str:
    return json.dumps(obj, ensure_ascii=False, separators=(",", ":"), default=_default)


def decode(key, payload: bytes) -> str:
    """zenoh-cli decoder: a magmesh payload → one line of JSON."""
    from .tap import decode_samples

    key = str(key)
    payload = bytes(payload)
    try:
        info = keys.parse(key)
    except keys.KeyError_:
        info = None
    if info is not None and info.kind != "svc":
        try:
            samples = decode_samples(key, payload)
        except (messages.SchemaError, keys.KeyError_, KeyError) as e:
            problem = str(e)
        else:
            if len(samples) == 1 and samples[0][0] == key:
                return _dumps(samples[0][1])
            head = msgpack.unpackb(payload, raw=False)
            return _dumps({"type": "batch", "vehicle": head.get("vehicle"), "t_s": head.get("t_s"),
                           "seq": head.get("seq"), "samples": [{"key": k, **m} for k, m in samples]})
    else:
        problem = None
    try:
        raw = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as e:
        raise ValueError(f"{key}: {len(payload)} bytes that are not msgpack ({type(e).__name__})") from None
    if problem is not None:
        raw = {"_invalid": problem, **raw} if isinstance(raw, dict) else {"_invalid": problem, "_value": raw}
    return _dumps(raw)


def encode(key, value: str) -> bytes:
    """zenoh-cli encoder: a JSON magmesh message → validated msgpack bytes."""
    try:
        msg = json.loads(value)
    except ValueError as e:
        raise ValueError(f"the value is not JSON: {e}") from None
    key = str(key) if key is not None else ""
    expected = None
    try:
        expected = messages.type_for_key(key)
    except (keys.KeyError_, KeyError):
        pass
    checked = messages.validate(msg, where=key, expected_type=expected)
    return messages.encode(checked, check=False)
