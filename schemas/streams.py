"""The streams table: for every magmesh stream its key, message type, fields, physical ranges and encoding.

One row per stream (:data:`STREAMS`): the key template and its builder in :mod:`schemas.keys`, the message
type of :data:`schemas.messages.MESSAGES` it carries (field names with units), who publishes it, the
physical ranges ingest enforces on it (:data:`LIMITS`, defaults of ``services.ingest`` settings) and the
Zenoh encoding every put on it carries (:func:`encoding_for_key`). ``schemas/README.md``, ingest's range
checks, ``services/physical.py``, the MCAP schemas and the JSON Schemas (:func:`json_schema`) are derived
from this module and :mod:`schemas.messages`; nothing else knows a key string, a range or an encoding.

Typed validation runs in compiled code: each message type becomes a ``msgspec.Struct`` (:func:`struct_for`)
whose field types carry the contract's constraints (lengths, bounds, finiteness, choices), so a payload is
checked by msgspec's C decoder (:func:`fast_decode`). msgspec was chosen because it does typed msgpack,
constraints and JSON Schema from one type definition, with no code generation step; the Python validator of
:mod:`schemas.messages` stays as the reference and writes the error message when a payload fails.

Batches (contract version 2) are described by :data:`BATCH_STREAMS`; see :mod:`schemas.batch`.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, lru_cache
from typing import Annotated, Any, Literal, Optional, Union

import msgspec

from . import keys, messages
from .messages import HEADER, MAX_ARRAY, MAX_STR, MESSAGES, Field, SchemaError

#: the wire contract's version: 1 = single samples; 2 adds batches (column arrays) beside them; 3 adds fleet
#: frames (many vehicles' samples as binary columns, the services' own hop) and reserves the chunk ``fleet``
CONTRACT_VERSION = 3
#: Zenoh encoding prefix of every magmesh payload
MEDIA_TYPE = "application/msgpack"


@dataclass(frozen=True)
class Limit:
    """A physical range ingest enforces on a field.

    ``how``: ``norm`` (Euclidean norm ≤ bound), ``abs`` (every component's |x| ≤ bound), ``max`` (value ≤
    bound), ``between`` (lo ≤ value ≤ hi, bound is a (lo, hi) pair). ``setting`` names the ingest setting
    that overrides the default; ``scale`` multiplies the setting (e.g. velocity: 1.5 × the speed limit).
    """

    field: str
    how: str
    setting: str
    scale: float = 1.0
    what: str = ""
    unit: str = ""


@dataclass(frozen=True)
class Stream:
    """One stream of the contract."""

    name: str  # e.g. "raw/mag", "dmc"
    template: str  # the key with {placeholders}
    builder: Callable[..., str]  # the key builder in schemas.keys
    msg_type: str
    publisher: str
    meaning: str
    limits: tuple[Limit, ...] = ()
    batchable: bool = False  # may travel inside a v2 batch (raw/ and clean/ sensor streams)

    @property
    def encoding(self) -> str:
        return encoding_name(self.msg_type)


#: default physical limits (ingest settings of the same names override them)
LIMIT_DEFAULTS: dict[str, Any] = {
    "max_field_nt": 2.0e6,  # |b| above this is not a magnetometer reading (sensor full scale ~0.8–8 mT)
    "max_gyro_rad_s": 40.0,  # ~2300 °/s
    "max_accel_m_s2": 300.0,  # ~30 g
    "max_speed_m_s": 400.0,
    "alt_range_m": (-1000.0, 60000.0),
    "max_pdop": 100.0,
    "max_pos_m": 1.0e7,  # local ENU coordinates
}

_L = Limit
#: physical ranges per message type of the raw/clean streams
LIMITS: dict[str, tuple[Limit, ...]] = {
    "mag": (_L("b_nt", "norm", "max_field_nt", what="a magnetometer can read", unit="nT"),),
    "imu": (_L("gyro_rad_s", "norm", "max_gyro_rad_s", unit="rad/s"),
            _L("accel_m_s2", "norm", "max_accel_m_s2", unit="m/s²")),
    "gnss": (_L("alt_m", "between", "alt_range_m", unit="m"), _L("speed_m_s", "max", "max_speed_m_s", unit="m/s"),
             _L("vel_enu_m_s", "norm", "max_speed_m_s", 1.5, unit="m/s"), _L("pdop", "max", "max_pdop"),
             _L("pos_enu_m", "abs", "max_pos_m", unit="m")),
    "ins": (_L("pos_enu_m", "abs", "max_pos_m", unit="m"), _L("vel_enu_m_s", "abs", "max_pos_m", unit="m/s")),
    "route": (_L("a_enu_m", "abs", "max_pos_m", unit="m"), _L("b_enu_m", "abs", "max_pos_m", unit="m")),
    "attitude": (),
}

_RAW_META = {
    "mag": ("raw_mag", "clean_mag", "magmesh/{vehicle}/%s/mag/{sensor}", "vehicles, simulators, replays",
            "magnetometer samples as measured"),
    "imu": ("raw_imu", "clean_imu", "magmesh/{vehicle}/%s/imu", "vehicles", "gyro + accelerometer"),
    "gnss": ("raw_gnss", "clean_gnss", "magmesh/{vehicle}/%s/gnss", "vehicles", "GNSS fixes"),
    "ins": ("raw_ins", "clean_ins", "magmesh/{vehicle}/%s/ins", "survey vehicles", "dead-reckoned INS navigation"),
    "route": ("raw_route", "clean_route", "magmesh/{vehicle}/%s/route", "mission planners", "the planned line A → B"),
    "attitude": ("raw_attitude", "clean_attitude", "magmesh/{vehicle}/%s/attitude", "flight controllers",
                 "the vehicle's own attitude estimate"),
}


def _build() -> dict[str, Stream]:
    out: dict[str, Stream] = {}
    for st, (rb, _cb, tmpl, who, meaning) in _RAW_META.items():
        out[f"raw/{st}"] = Stream(f"raw/{st}", tmpl % "raw", getattr(keys, rb), st, who, meaning, LIMITS[st], True)
    for st, (_rb, cb, tmpl, _who, meaning) in _RAW_META.items():
        out[f"clean/{st}"] = Stream(f"clean/{st}", tmpl % "clean", getattr(keys, cb), st, "ingest",
                                    f"{meaning}, validated", LIMITS[st], True)
    rows = [
        ("rejects", "magmesh/{vehicle}/rejects", keys.rejects, "reject", "any service",
         "every refused input, with the reason"),
        ("cal/mag", "magmesh/{vehicle}/cal/mag/{sensor}", keys.cal_mag, "mag", "calibration",
         "compensated field (`calibrated` true, `param_id`)"),
        ("cal/params", "magmesh/{vehicle}/cal/params/{sensor}", keys.cal_params, "cal_params", "calibration",
         "current parameters; also answered by query"),
        ("dmc", "magmesh/{vehicle}/dmc", keys.dmc, "dmc", "dmc_detector",
         "interference features and validity per epoch"),
        ("heading", "magmesh/{vehicle}/heading", keys.heading, "heading", "heading_fuser",
         "fused attitude and heading"),
        ("fix/geomag", "magmesh/{vehicle}/fix/geomag", keys.fix_geomag, "geomag_fix", "geomag_matcher",
         "geomagnetic matching result"),
        ("track", "magmesh/{vehicle}/track", keys.track, "track", "track_monitor", "cross-track monitoring state"),
        ("alarm", "magmesh/{vehicle}/alarm/{source}", keys.alarm, "alarm", "services",
         "alarm transitions (raised / cleared)"),
        ("truth", "magmesh/{vehicle}/truth/{what}", keys.truth, "truth", "simulators, replays", "ground truth"),
    ]
    for name, tmpl, b, t, who, meaning in rows:
        out[name] = Stream(name, tmpl, b, t, who, meaning, LIMITS.get(t, ()) if name == "cal/mag" else ())
    for kind, who, meaning in (
            ("clean", "ingest (output = frames)", "validated samples of a shard of vehicles per window (contract v3)"),
            ("cal", "calibration (on frames)", "compensated magnetometer samples of a shard, per input frame"),
            ("dmc", "dmc_detector (on frames)", "the detector's verdicts of a shard, per input frame")):
        out[f"fleet/{kind}"] = Stream(f"fleet/{kind}", f"magmesh/fleet/{{shard}}/{kind}", keys.fleet_frame, "frame",
                                      who, meaning)
    return out


#: every stream of the contract, by name
STREAMS: dict[str, Stream] = _build()


def stream_for_key(key: str) -> Stream:
    """The table row of a concrete data key (raises :class:`schemas.keys.KeyError_` for anything else)."""
    return _stream_for_key(key)


@lru_cache(maxsize=keys.KEY_CACHE)
def _stream_for_key(key: str) -> Stream:
    info = keys.parse(key)
    if info.kind == keys.SVC:
        raise keys.KeyError_(f"{key[:120]!r} is a service key, not a stream")
    if info.kind == keys.FLEET:
        return STREAMS[f"fleet/{info.rest[1]}"]
    if info.kind in ("raw", "clean", "cal"):
        name = f"{info.kind}/{info.rest[0]}"
    elif info.kind == "fix":
        name = f"fix/{info.rest[0]}"
    else:
        name = info.kind
    st = STREAMS.get(name)
    if st is None:
        raise keys.KeyError_(f"key {key[:120]!r} names no stream of the contract")
    return st


def type_for_key(key: str) -> str:
    return stream_for_key(key).msg_type


# ---- encodings --------------------------------------------------------------------------------


def encoding_name(msg_type: str, version: int | None = None) -> str:
    """``application/msgpack;magmesh/{type}/v{version}``: what every put of this type carries."""
    if msg_type == "batch":  # (the binary form: version 3)
        v = BATCH_VERSION if version is None else version
    elif msg_type == "frame":
        v = FRAME_VERSION if version is None else version
    else:
        v = MESSAGES[msg_type].version if version is None else version
    return f"{MEDIA_TYPE};magmesh/{msg_type}/v{v}"


def parse_encoding(enc: str) -> tuple[str, int] | None:
    """``(type, version)`` of a magmesh encoding string, or None when it is not one."""
    head, sep, schema = str(enc).partition(";")
    if head != MEDIA_TYPE or not sep:
        return None
    parts = schema.split("/")
    if len(parts) != 3 or parts[0] != "magmesh" or not parts[2].startswith("v") or not parts[2][1:].isdigit():
        return None
    return parts[1], int(parts[2][1:])


def encoding_for_key(key: str) -> str:
    """The encoding of a put on a concrete key (a service's status reply: ``magmesh/status/v1``)."""
    info = keys.parse(key)
    if info.kind == keys.SVC:
        return f"{MEDIA_TYPE};magmesh/{'status' if info.rest[-1] == 'status' else 'control'}/v1"
    if info.kind in ("raw", "clean") and info.rest and info.rest[0] == BATCH_CHUNK:
        return encoding_name("batch")
    return stream_for_key(key).encoding


# ---- typed structs (compiled validation) ------------------------------------------------------

_DBL_MAX = sys.float_info.max
#: a finite float (NaN fails both bounds, ±inf fails one)
Finite = Annotated[float, msgspec.Meta(ge=-_DBL_MAX, le=_DBL_MAX)]


def _float_type(f: Field):
    lo = -_DBL_MAX if f.lo is None else float(f.lo)
    hi = _DBL_MAX if f.hi is None else float(f.hi)
    return Annotated[float, msgspec.Meta(ge=lo, le=hi, description=f.doc)]


def _field_type(f: Field):
    k = f.kind
    if k == "str":
        t = Literal[f.choices] if f.choices else Annotated[str, msgspec.Meta(max_length=MAX_STR)]
        t = Annotated[t, msgspec.Meta(description=f.doc)]
    elif k == "bool":
        t = Annotated[bool, msgspec.Meta(description=f.doc)]
    elif k == "int":
        kw = {}
        if f.lo is not None:
            kw["ge"] = int(f.lo)
        if f.hi is not None:
            kw["le"] = int(f.hi)
        t = Annotated[int, msgspec.Meta(description=f.doc, **kw)]
    elif k == "float":
        t = _float_type(f)
    elif k in ("vec3", "floats", "mat3"):
        n = 3 if k == "vec3" else (9 if k == "mat3" else f.length)
        kw = dict(min_length=n, max_length=n) if n is not None else dict(max_length=MAX_ARRAY)
        t = Annotated[list[Finite], msgspec.Meta(description=f.doc, **kw)]
    elif k == "bools":
        kw = dict(min_length=f.length, max_length=f.length) if f.length else {}
        t = Annotated[list[bool], msgspec.Meta(description=f.doc, **kw)]
    elif k == "strs":
        t = Annotated[list[Annotated[str, msgspec.Meta(max_length=256)]],
                      msgspec.Meta(max_length=1024, description=f.doc)]
    elif k == "map":
        t = Annotated[dict[str, Any], msgspec.Meta(description=f.doc)]
    else:  # pragma: no cover - the table is checked by the tests
        raise AssertionError(f"unknown field kind {k}")
    if f.nullable:
        t = Optional[t]  # noqa: UP045 - runtime type construction
    return t


@cache
def struct_for(msg_type: str) -> type[msgspec.Struct]:
    """The msgspec Struct of a message type: header + fields, with the contract's constraints."""
    mt = MESSAGES[msg_type]
    flds: list[tuple] = [
        ("type", Literal[msg_type]),
        ("version", Annotated[int, msgspec.Meta(ge=mt.min_version, le=mt.version, description=HEADER[1].doc)]),
        ("vehicle", Annotated[str, msgspec.Meta(max_length=MAX_STR, description=HEADER[2].doc)]),
        ("t_s", Annotated[Finite, msgspec.Meta(description=HEADER[3].doc)]),
        ("seq", Annotated[int, msgspec.Meta(ge=0, description=HEADER[4].doc)]),
    ]
    for f in mt.fields:
        t = _field_type(f)
        if f.required:
            flds.append((f.name, t))
        else:
            flds.append((f.name, Union[t, msgspec.UnsetType], msgspec.UNSET))  # noqa: UP007
    return msgspec.defstruct(msg_type, flds, kw_only=True, forbid_unknown_fields=False, omit_defaults=True)


@cache
def json_schema(msg_type: str) -> dict:
    """The JSON Schema (draft 2020-12) of one message type, as generated from the contract."""
    if msg_type == "batch":
        from . import batch

        return batch.json_schema()
    if msg_type == "frame":
        from . import frame

        return frame.json_schema()
    sch = msgspec.json.schema(struct_for(msg_type))
    name = msg_type
    body = sch.get("$defs", {}).get(name, sch)
    body = _drop_inf_bounds(dict(body))
    body["additionalProperties"] = True  # unknown extra fields are kept (forward compatible)
    body["title"] = f"magmesh {msg_type} v{MESSAGES[msg_type].version}"
    body["description"] = MESSAGES[msg_type].doc
    body["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return body


def _drop_inf_bounds(node: Any) -> Any:
    """The ±DBL_MAX bounds that make a float finite in msgspec mean "any number" to a JSON Schema reader."""
    if isinstance(node, dict):
        return {k: _drop_inf_bounds(v) for k, v in node.items()
                if not (k in ("minimum", "maximum") and abs(v) == _DBL_MAX)}
    if isinstance(node, list):
        return [_drop_inf_bounds(v) for v in node]
    return node


_untyped = msgspec.msgpack.Decoder()
_MAX_PAYLOAD = 16 * 1024 * 1024


def fast_decode(payload: bytes, where: str = "", expected_type: str | None = None) -> dict:
    """Decode and validate one v1 message with the compiled validator; same result and errors as
    :func:`schemas.messages.decode` (on a failure the reference validator names the field and the problem)."""
    try:
        if len(payload) > _MAX_PAYLOAD:
            raise ValueError
        obj = _untyped.decode(payload)
        t = obj["type"] if type(obj) is dict else None
        if expected_type is not None and t != expected_type:
            raise ValueError
        s = msgspec.convert(obj, struct_for(t), strict=True)
    except Exception:
        # slow path: the reference validator writes the error (and is the judge of anything msgspec refuses)
        return messages.decode_reference(payload, where, expected_type)
    out = dict(obj)
    for name in s.__struct_fields__:
        v = getattr(s, name)
        if v is not msgspec.UNSET:
            out[name] = v
    return out


def fast_validate(msg: Any, where: str = "", expected_type: str | None = None) -> dict:
    """:func:`schemas.messages.validate` in compiled code (same result); the reference writes any error."""
    try:
        t = msg["type"] if type(msg) is dict else None
        if expected_type is not None and t != expected_type:
            raise ValueError
        if any(type(k) is not str for k in msg):
            raise ValueError
        s = msgspec.convert(msg, struct_for(t), strict=True)
    except Exception:
        return messages.validate_reference(msg, where, expected_type)
    out = dict(msg)
    for name in s.__struct_fields__:
        v = getattr(s, name)
        if v is not msgspec.UNSET:
            out[name] = v
    return out


def validation_error(e: Exception, where: str, msg_type: str | None) -> SchemaError:
    """A msgspec validation error as a :class:`SchemaError` naming the field."""
    text = str(e)
    field = "<payload>"
    if "`$." in text:
        field = text.split("`$.", 1)[1].split("`", 1)[0].split("[", 1)[0].split(".", 1)[0]
    return SchemaError(field, text, where, msg_type)


# ---- batches (contract version 2) --------------------------------------------------------------

#: the key chunk of batches: ``magmesh/{vehicle}/raw/batch`` and ``magmesh/{vehicle}/clean/batch``
BATCH_CHUNK = "batch"
#: version of the batch message type
BATCH_VERSION = 2
#: streams a batch may carry, by their name inside the batch (``mag/{sensor}`` for magnetometers)
BATCH_STREAMS = tuple(s for s in _RAW_META)
#: version of the frame message type (contract version 3; schemas/frame.py)
FRAME_VERSION = 3


# ---- physical ranges, from the table --------------------------------------------------------------


def limit_value(lim: Limit, settings: Any = None) -> Any:
    """The bound of a limit: the setting of that name on ``settings`` (ingest's), else the table's default."""
    v = getattr(settings, lim.setting, None) if settings is not None else None
    if v is None:
        v = LIMIT_DEFAULTS[lim.setting]
    if lim.how == "between":
        return (float(v[0]), float(v[1]))
    return float(v) * lim.scale


def _sentence(lim: Limit, bound: Any, value: float | None = None) -> str:
    u = f" {lim.unit}" if lim.unit else ""
    shown = "" if value is None else f" {value:.4g}{u}"
    if lim.how == "norm":
        return f"has a norm{shown} beyond {'the ' if lim.what else ''}{bound:.4g}{u}{' ' + lim.what if lim.what else ''}"
    if lim.how == "abs":
        return f"is beyond ±{bound:.3g}{u}"
    if lim.how == "max":
        return f"is{shown}, beyond {bound:g}{u}"
    return f"is{shown}, outside {bound[0]:g}..{bound[1]:g}{u}"


def limit_problem(msg: dict, settings: Any = None) -> tuple[str, str] | None:
    """``(field, sentence)`` of the first physical limit a decoded v1 sample breaks, or None."""
    for lim in LIMITS.get(msg["type"], ()):
        v = msg.get(lim.field)
        if v is None:
            continue
        b = limit_value(lim, settings)
        if lim.how == "norm":
            x = sum(c * c for c in v) ** 0.5
            if x > b:
                return lim.field, _sentence(lim, b, x)
        elif lim.how == "abs":
            if max(abs(c) for c in v) > b:
                return lim.field, _sentence(lim, b)
        elif lim.how == "max":
            if v > b:
                return lim.field, _sentence(lim, b, v)
        elif not (b[0] <= v <= b[1]):
            return lim.field, _sentence(lim, b, v)
    return None


def limit_masks(msg_type: str, cols: dict, n: int, settings: Any = None) -> list[tuple[str, Any, str]]:
    """Vectorised :func:`limit_problem` over a batch's columns: ``[(field, bad_mask, sentence)]`` for every
    limit that some sample breaks (numpy boolean masks of length n)."""
    import numpy as np

    out = []
    for lim in LIMITS.get(msg_type, ()):
        a = cols.get(lim.field)
        if a is None or not isinstance(a, np.ndarray):
            continue
        b = limit_value(lim, settings)
        if lim.how == "norm":
            bad = np.einsum("ij,ij->i", a, a) > b * b
        elif lim.how == "abs":
            bad = (np.abs(a) > b).any(axis=1) if a.ndim == 2 else np.abs(a) > b
        elif lim.how == "max":
            bad = a > b
        else:
            bad = (a < b[0]) | (a > b[1])
        if bad.any():
            out.append((lim.field, bad, _sentence(lim, b)))
    return out
