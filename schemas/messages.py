"""magmesh message types: field specifications, msgpack encoding and strict decoding.

Every message is a msgpack map with the header fields ``type``, ``version``, ``vehicle``, ``t_s``
and ``seq``, then the fields of its type. Field names carry their unit (``b_nt``, ``gyro_rad_s``).
Unknown extra fields are kept but never required (forward compatible). :data:`MESSAGES` is the
contract; ``python -m schemas.doc`` renders it as the table in ``schemas/README.md``.

Frames and conventions: navigation frame ENU (x east, y north, z up), local to a vehicle's origin;
body frame FLU (x forward, y left, z up). ``heading_rad`` is the compass heading: clockwise from
true north, in [0, 2π). Pitch is positive nose up, roll positive right side down.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import msgpack

from . import keys as _keys

MAX_STR = 4096
MAX_ARRAY = 100_000


class SchemaError(ValueError):
    """A message that does not follow the contract.

    ``field`` names the offending field (or ``"<payload>"``), ``problem`` says what was wrong.
    """

    def __init__(self, field: str, problem: str, where: str = "", msg_type: str | None = None):
        self.field = field
        self.problem = problem
        self.where = where
        self.msg_type = msg_type
        loc = f" of {where}" if where else ""
        super().__init__(f"field '{field}'{loc} {problem}")


@dataclass(frozen=True)
class Field:
    name: str
    kind: str  # str | int | float | bool | vec3 | floats | mat3 | strs | map | bools
    doc: str
    required: bool = True
    choices: tuple[str, ...] | None = None
    lo: float | None = None
    hi: float | None = None
    length: int | None = None  # exact length for floats/bools/strs
    nullable: bool = False


@dataclass(frozen=True)
class MessageType:
    name: str
    version: int
    doc: str
    keys: tuple[str, ...]  # documentation: the key templates that carry it
    fields: tuple[Field, ...] = field(default_factory=tuple)
    min_version: int = 1


HEADER = (
    Field("type", "str", "message type name (this table's first column)"),
    Field("version", "int", "message type version; decoders reject versions they do not know", lo=1),
    Field("vehicle", "str", "vehicle id (same as the key's vehicle chunk; 'svc' messages use the role)"),
    Field("t_s", "float", "sample time, s (simulation/recording clock of the vehicle)"),
    Field("seq", "int", "sequence number, strictly increasing per publishing stream (key)", lo=0),
)

_F = Field

MESSAGES: dict[str, MessageType] = {}


def _register(mt: MessageType) -> MessageType:
    MESSAGES[mt.name] = mt
    return mt


MAG = _register(
    MessageType(
        "mag",
        1,
        "one 3-axis magnetometer sample (body frame FLU)",
        ("magmesh/{vehicle}/raw/mag/{sensor}", "magmesh/{vehicle}/clean/mag/{sensor}", "magmesh/{vehicle}/cal/mag/{sensor}"),
        (
            _F("sensor", "str", "sensor id, same as the key's last chunk"),
            _F("b_nt", "vec3", "magnetic flux density, nT, body frame"),
            _F("calibrated", "bool", "true on cal/mag: hard/soft iron removed", required=False),
            _F("param_id", "str", "id of the cal/params set that produced this sample", required=False, nullable=True),
            _F("temp_c", "float", "sensor temperature, °C", required=False),
            _F("f_nt", "float", "scalar total-field reading (e.g. an optically pumped sensor of a survey "
               "vehicle), nT; b_nt then carries the co-located vector sensor", required=False, lo=0),
        ),
    )
)

IMU = _register(
    MessageType(
        "imu",
        1,
        "gyro + accelerometer sample (body frame FLU)",
        ("magmesh/{vehicle}/raw/imu", "magmesh/{vehicle}/clean/imu"),
        (
            _F("gyro_rad_s", "vec3", "angular rate, rad/s"),
            _F("accel_m_s2", "vec3", "specific force, m/s² (≈ [0, 0, +9.81] at rest, level)"),
        ),
    )
)

GNSS = _register(
    MessageType(
        "gnss",
        1,
        "GNSS position/velocity fix",
        ("magmesh/{vehicle}/raw/gnss", "magmesh/{vehicle}/clean/gnss"),
        (
            _F("lat_deg", "float", "latitude, degrees (WGS-84)", lo=-90, hi=90),
            _F("lon_deg", "float", "longitude, degrees (WGS-84)", lo=-180, hi=180),
            _F("alt_m", "float", "height above the ellipsoid, m"),
            _F("pos_enu_m", "vec3", "position in the vehicle's local ENU frame, m", required=False),
            _F("vel_enu_m_s", "vec3", "velocity ENU, m/s"),
            _F("course_rad", "float", "course over ground, clockwise from true north, rad"),
            _F("speed_m_s", "float", "horizontal ground speed, m/s", lo=0),
            _F("fix_type", "str", "fix quality", choices=("none", "2d", "3d", "dgps", "rtk_float", "rtk_fixed")),
            _F("num_sats", "int", "satellites used", lo=0),
            _F("pdop", "float", "position dilution of precision", lo=0),
            _F("horiz_std_m", "float", "1-σ horizontal position uncertainty, m", required=False, lo=0),
        ),
    )
)

INS = _register(
    MessageType(
        "ins",
        1,
        "inertial navigation solution (dead reckoning) of a survey vehicle",
        ("magmesh/{vehicle}/raw/ins", "magmesh/{vehicle}/clean/ins"),
        (
            _F("pos_enu_m", "vec3", "dead-reckoned position, local ENU, m"),
            _F("vel_enu_m_s", "vec3", "velocity ENU, m/s"),
            _F("heading_rad", "float", "heading, clockwise from true north, rad"),
        ),
    )
)

ROUTE = _register(
    MessageType(
        "route",
        1,
        "the planned line a vehicle must follow (A → B)",
        ("magmesh/{vehicle}/raw/route", "magmesh/{vehicle}/clean/route"),
        (
            _F("a_enu_m", "vec3", "start point A, local ENU, m"),
            _F("b_enu_m", "vec3", "end point B, local ENU, m"),
            _F("route_id", "str", "id of the route / mission leg"),
        ),
    )
)

ATTITUDE = _register(
    MessageType(
        "attitude",
        1,
        "the vehicle's own attitude estimate (flight controller), with the magnetometer heading it fuses",
        ("magmesh/{vehicle}/raw/attitude", "magmesh/{vehicle}/clean/attitude"),
        (
            _F("heading_rad", "float", "estimated heading, clockwise from true north, rad, [0, 2π)"),
            _F("pitch_rad", "float", "estimated pitch, nose up positive, rad"),
            _F("roll_rad", "float", "estimated roll, right side down positive, rad"),
            _F("mag_heading_rad", "float", "tilt-compensated magnetometer heading (+ declination) the estimator "
               "corrects towards, rad; null when the magnetometer is not used", nullable=True),
            _F("estimator", "str", "estimator kind (complementary, ekf, ...)", required=False),
        ),
    )
)

REJECT = _register(
    MessageType(
        "reject",
        1,
        "an input a service refused, with the reason (t_s: the sample's time when readable, else receive time)",
        ("magmesh/{vehicle}/rejects",),
        (
            _F("key", "str", "key the input arrived on"),
            _F("reason", "str", "what was wrong, a sentence"),
            _F("field", "str", "the offending field, or '<payload>'", nullable=True),
            _F("code", "str", "machine-readable reason", choices=(
                "decode", "schema", "version", "range", "time_order", "duplicate", "key", "other")),
            _F("input_type", "str", "declared message type of the input, if readable", required=False, nullable=True),
            _F("payload_len_bytes", "int", "size of the refused payload, bytes", lo=0),
            _F("service", "str", "instance that refused it"),
        ),
    )
)

ALARM = _register(
    MessageType(
        "alarm",
        1,
        "an alarm transition: raised or cleared",
        ("magmesh/{vehicle}/alarm/{source}",),
        (
            _F("source", "str", "what raised it (dmc, heading, match, track, heading_innovation, mag_anomaly, ...)"),
            _F("state", "str", "transition", choices=("raised", "cleared")),
            _F("severity", "str", "severity", choices=("warning", "critical")),
            _F("reason", "str", "a sentence a person can read"),
            _F("value", "float", "the value that crossed the threshold (unit in `unit`)", nullable=True),
            _F("threshold", "float", "the threshold it crossed", nullable=True),
            _F("unit", "str", "unit of value and threshold", required=False),
            _F("service", "str", "instance that raised it"),
            _F("raised_t_s", "float", "sample time the alarm was raised (on cleared: of the raise)", required=False),
        ),
    )
)

DMC = _register(
    MessageType(
        "dmc",
        1,
        "differential-compass interference state per epoch",
        ("magmesh/{vehicle}/dmc",),
        (
            _F("dm_nt", "floats", "field-strength error Δm_k per compass, nT", length=2),
            _F("ddm_nt_s", "floats", "rate of Δm_k, nT/s", length=2),
            _F("dh_rad", "float", "relative heading difference Δh = h1 − h2 − Δh_r, rad (single: 0; quasistatic: "
               "magnetometer − gyro heading change over its window)"),
            _F("ddh_rad_s", "float", "rate of Δh, rad/s"),
            _F("heading_rad", "float", "magnetic heading of compass 1 after compensation (+ declination), rad"),
            _F("stage1_pass", "bool", "all threshold tests passed"),
            _F("credibility", "float", "credibility K_c in [0, 1] (1/0 for threshold-only detectors; gyro_track: "
               "1 − the heading disagreement / its gate)", lo=0, hi=1),
            _F("valid", "bool", "the magnetic heading is trustworthy at this epoch"),
            _F("impl", "str", "detector implementation (threshold, fcm, single, quasistatic, gyro_track)"),
            _F("param_source", "str", "where compensation parameters came from", choices=("manifest", "cal", "none")),
        ),
    )
)

CAL_PARAMS = _register(
    MessageType(
        "cal_params",
        1,
        "magnetometer calibration parameters: h = M (m − offset)",
        ("magmesh/{vehicle}/cal/params/{sensor}",),
        (
            _F("sensor", "str", "sensor id"),
            _F("param_id", "str", "id of this parameter set"),
            _F("status", "str", "fit outcome", choices=("ok", "refused", "converging", "manifest")),
            _F("reason", "str", "why refused / notes, a sentence", required=False),
            _F("model", "str", "2-D (horizontal ellipse) or 3-D (ellipsoid)", choices=("2d", "3d")),
            _F("method", "str", "fitting method", choices=("ls", "arls", "ekf", "manifest")),
            _F("offset_nt", "vec3", "hard-iron offset, nT"),
            _F("matrix", "floats", "soft-iron/scale/misalignment matrix M, row-major 3×3, unitless", length=9),
            _F("field_radius_nt", "float", "field strength the compensated field is scaled to, nT", lo=0),
            _F("rmse_nt", "float", "residual RMS of |h| − radius, nT", lo=0, nullable=True),
            _F("coverage_frac", "float", "heading/attitude coverage of the samples, 0..1", lo=0, hi=1),
            _F("n_samples", "int", "samples used", lo=0),
            _F("n_gross_rejected", "int", "samples given zero weight as gross errors", lo=0),
            _F("observable", "bools", "which offset components are observable (x, y, z)", length=3),
            _F("fit_t_s", "float", "sample time of the fit, s"),
            _F("fit_duration_ms", "float", "compute time of the fit, ms", lo=0),
        ),
    )
)

HEADING = _register(
    MessageType(
        "heading",
        1,
        "fused attitude and heading",
        ("magmesh/{vehicle}/heading",),
        (
            _F("heading_rad", "float", "heading, clockwise from true north, rad, [0, 2π)"),
            _F("pitch_rad", "float", "pitch, nose up positive, rad"),
            _F("roll_rad", "float", "roll, right side down positive, rad"),
            _F("heading_std_rad", "float", "1-σ heading uncertainty, rad", lo=0),
            _F("pitch_std_rad", "float", "1-σ pitch uncertainty, rad", lo=0),
            _F("roll_std_rad", "float", "1-σ roll uncertainty, rad", lo=0),
            _F("mode", "str", "what steers the heading", choices=("magnetic", "gyro_only", "recovering", "initialising")),
            _F("mag_innovation_rad", "float", "heading innovation of the last magnetometer update, rad", nullable=True),
            _F("mag_test_ratio", "float", "innovation² / (gate² · innovation variance), PX4 style", nullable=True),
            _F("mag_fused", "bool", "the last magnetometer update was used"),
        ),
    )
)

GEOMAG_FIX = _register(
    MessageType(
        "geomag_fix",
        1,
        "geomagnetic matching result (a rejected or ambiguous match is never a fix)",
        ("magmesh/{vehicle}/fix/geomag",),
        (
            _F("status", "str", "outcome", choices=("accepted", "pending", "rejected", "ambiguous")),
            _F("accepted", "bool", "accepted by the M-of-N rule: use it as a position fix"),
            _F("pos_enu_m", "vec3", "matched position at the end of the sequence, map frame, m"),
            _F("ins_pos_enu_m", "vec3", "INS position at the same time, m"),
            _F("hausdorff_nt", "float", "Hausdorff distance of the best match, nT", lo=0),
            _F("margin_nt", "float", "runner-up distance minus best distance, nT", nullable=True),
            _F("search_area_m2", "float", "area searched, m²", lo=0),
            _F("n_samples", "int", "match length N", lo=0),
            _F("correction_enu_m", "vec3", "pos_enu_m − ins_pos_enu_m: the INS correction this match implies, m",
               required=False),
            _F("lambda_nt", "float", "feasibility / SSDA threshold λ finally used, nT", required=False, lo=0),
            _F("feasible_cells", "int", "cells kept by the pre-match (the feasible set U)", required=False, lo=0),
            _F("match_ms", "float", "compute time of the match, ms", required=False, lo=0),
            _F("filtered_correction_enu_m", "vec3", "INS correction of the Kalman filter fed by accepted fixes, at "
               "t_s (add it to the INS position), m", required=False),
            _F("innovation_test_ratio", "float", "filter innovation² / (gate² · variance) of an accepted fix; > 1: "
               "not fused", required=False, nullable=True, lo=0),
        ),
    )
)

TRACK = _register(
    MessageType(
        "track",
        1,
        "cross-track monitoring state",
        ("magmesh/{vehicle}/track",),
        (
            _F("cross_track_m", "float", "distance from the planned line, m", lo=0),
            _F("along_track_m", "float", "progress along A → B, m"),
            _F("progress_frac", "float", "along-track progress / |B − A|"),
            _F("gnss_ok", "bool", "GNSS quality good enough to trust the deviation"),
            _F("heading_innovation_rad", "float", "magnetic heading − attitude heading, rad", nullable=True),
            _F("innovation_sigma_rad", "float", "σ of the innovation on undisturbed flight, rad", nullable=True),
            _F("track_alarm", "bool", "cross-track detector raised"),
            _F("innovation_alarm", "bool", "heading-innovation detector raised"),
            _F("anomaly_alarm", "bool", "combined magnetic-anomaly verdict raised", required=False),
            _F("anomaly_source", "str", "detector that raised the combined verdict", required=False, nullable=True),
            _F("cross_track_signed_m", "float", "signed cross-track distance, + left of A → B, m", required=False),
            _F("cross_track_rate_m_s", "float", "rate of the signed cross-track distance, m/s", required=False),
            _F("track_armed", "bool", "the route leg was acquired and the track detector is testing", required=False),
            _F("innovation_learning", "bool", "σ of the innovation is still being learned", required=False),
            _F("innovation_test_ratio", "float", "heading-innovation test statistic / its threshold", required=False,
               nullable=True),
            _F("route_id", "str", "route the deviation refers to", required=False),
            _F("field_deviation_nt", "float", "field strength minus its undisturbed reference, nT", required=False),
        ),
    )
)

TRUTH = _register(
    MessageType(
        "truth",
        1,
        "simulator or recording ground truth; other fields depend on `what`",
        ("magmesh/{vehicle}/truth/{what}",),
        (
            _F("what", "str", "pose | field | sources | ... (the key's last chunk)"),
            _F("heading_rad", "float", "true heading (pose)", required=False),
            _F("pitch_rad", "float", "true pitch (pose)", required=False),
            _F("roll_rad", "float", "true roll (pose)", required=False),
            _F("pos_enu_m", "vec3", "true position, m (pose)", required=False),
            _F("vel_enu_m_s", "vec3", "true velocity, m/s (pose)", required=False),
            _F("b_earth_nt", "vec3", "undisturbed Earth field at the vehicle, body frame, nT (field)", required=False),
            _F("b_sensor_nt", "floats", "true field at each sensor (before sensor errors), flattened k×3, nT (field)",
               required=False),
            _F("active_sources", "strs", "interference sources acting on the vehicle now (sources)", required=False),
            _F("disturbed", "bool", "any source disturbs the heading by more than the sim's threshold (sources)",
               required=False),
        ),
    )
)


# ---- codec ------------------------------------------------------------------------------------


def _check(f: Field, v: Any, where: str, mtype: str) -> Any:
    def bad(problem: str) -> SchemaError:
        shown = repr(v)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        return SchemaError(f.name, f"{problem}, got {shown}", where, mtype)

    if v is None:
        if f.nullable:
            return None
        raise bad("must not be null")
    k = f.kind
    if k == "str":
        if not isinstance(v, str):
            raise bad("must be a string")
        if len(v) > MAX_STR:
            raise SchemaError(f.name, f"is a string of {len(v)} characters (max {MAX_STR})", where, mtype)
        if f.choices and v not in f.choices:
            raise bad(f"must be one of {', '.join(f.choices)}")
        return v
    if k == "bool":
        if not isinstance(v, bool):
            raise bad("must be a boolean")
        return v
    if k == "int":
        if isinstance(v, bool) or not isinstance(v, int):
            raise bad("must be an integer")
        if f.lo is not None and v < f.lo:
            raise bad(f"must be ≥ {f.lo:g}")
        if f.hi is not None and v > f.hi:
            raise bad(f"must be ≤ {f.hi:g}")
        return v
    if k == "float":
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise bad("must be a number")
        v = float(v)
        if not math.isfinite(v):
            raise bad("must be a finite number")
        if f.lo is not None and v < f.lo:
            raise bad(f"must be ≥ {f.lo:g}")
        if f.hi is not None and v > f.hi:
            raise bad(f"must be ≤ {f.hi:g}")
        return v
    if k in ("vec3", "floats", "mat3"):
        n = 3 if k == "vec3" else (9 if k == "mat3" else f.length)
        if not isinstance(v, (list, tuple)):
            raise bad(f"must be an array of {n or 'some'} finite numbers")
        if len(v) > MAX_ARRAY:
            raise SchemaError(f.name, f"is an array of {len(v)} items (max {MAX_ARRAY})", where, mtype)
        if n is not None and len(v) != n:
            raise bad(f"must be {n} finite numbers")
        out = []
        for x in v:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise bad(f"must be {n or 'an array of'} finite numbers")
            out.append(float(x))
        return out
    if k == "bools":
        if not isinstance(v, (list, tuple)) or (f.length is not None and len(v) != f.length):
            raise bad(f"must be an array of {f.length} booleans")
        if not all(isinstance(x, bool) for x in v):
            raise bad("must contain only booleans")
        return list(v)
    if k == "strs":
        if not isinstance(v, (list, tuple)) or len(v) > 1024:
            raise bad("must be an array of strings (at most 1024)")
        if not all(isinstance(x, str) and len(x) <= 256 for x in v):
            raise bad("must contain only strings of at most 256 characters")
        return list(v)
    if k == "map":
        if not isinstance(v, dict):
            raise bad("must be a map")
        return v
    raise AssertionError(f"unknown field kind {k}")


def validate(msg: Any, where: str = "", expected_type: str | None = None) -> dict:
    """Check a decoded message against the contract; return it (numbers normalised to float).

    Raises :class:`SchemaError` naming the field and the problem. Runs the compiled validator
    (:func:`schemas.streams.fast_validate`); what it refuses goes through :func:`validate_reference`.
    """
    from .streams import fast_validate

    return fast_validate(msg, where, expected_type)


def validate_reference(msg: Any, where: str = "", expected_type: str | None = None) -> dict:
    """The reference validator (pure Python): the same result as :func:`validate`, with the error texts."""
    if not isinstance(msg, dict):
        raise SchemaError("<payload>", f"must be a msgpack map, got {type(msg).__name__}", where)
    for k in msg:
        if not isinstance(k, str):
            raise SchemaError("<payload>", f"has a non-string field name {k!r}", where)
    t = msg.get("type")
    if not isinstance(t, str):
        raise SchemaError("type", f"must be a string message type, got {t!r}"[:120], where)
    mt = MESSAGES.get(t)
    if mt is None:
        raise SchemaError("type", f"names an unknown message type {t[:64]!r}", where, t)
    if expected_type is not None and t != expected_type:
        raise SchemaError("type", f"must be {expected_type!r} on this key, got {t[:64]!r}", where, t)
    ver = msg.get("version")
    if isinstance(ver, bool) or not isinstance(ver, int):
        raise SchemaError("version", f"must be an integer, got {ver!r}"[:120], where, t)
    if not (mt.min_version <= ver <= mt.version):
        raise SchemaError("version", f"is {ver}; this decoder reads {t} versions {mt.min_version}..{mt.version}",
                          where, t)
    out = dict(msg)
    for f in HEADER[2:]:
        if f.name not in msg:
            raise SchemaError(f.name, "is missing", where, t)
        out[f.name] = _check(f, msg[f.name], where, t)
    for f in mt.fields:
        if f.name not in msg:
            if f.required:
                raise SchemaError(f.name, "is missing", where, t)
            continue
        out[f.name] = _check(f, msg[f.name], where, t)
    return out


def encode(msg: dict, check: bool = True) -> bytes:
    """Encode a message to msgpack bytes (validated first unless ``check=False``)."""
    if check:
        msg = validate(msg, expected_type=None)
    return msgpack.packb(msg, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview, where: str = "", expected_type: str | None = None) -> dict:
    """Decode and validate msgpack bytes; raise :class:`SchemaError` on anything wrong.

    Runs the compiled validator (:func:`schemas.streams.fast_decode`, msgspec structs generated from
    :data:`MESSAGES`); a payload it refuses goes through :func:`decode_reference`, which names the problem.
    """
    from .streams import fast_decode

    return fast_decode(payload, where, expected_type)


#: a sentence for msgpack errors that carry no text of their own
_MSGPACK_ERRORS = {"FormatError": "a byte that starts no msgpack value (reserved type code)",
                   "StackError": "nested too deeply", "OutOfData": "the payload ends inside a value"}


def decode_reference(payload: bytes | bytearray | memoryview, where: str = "", expected_type: str | None = None) -> dict:
    """The reference decoder (pure Python): the same result as :func:`decode`, slower, with the error texts."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise SchemaError("<payload>", f"must be bytes, got {type(payload).__name__}", where)
    if len(payload) == 0:
        raise SchemaError("<payload>", "is empty", where)
    if len(payload) > 16 * 1024 * 1024:
        raise SchemaError("<payload>", f"is {len(payload)} bytes (max 16 MiB)", where)
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several exception types for bad bytes
        detail = str(e)[:80] or _MSGPACK_ERRORS.get(type(e).__name__, "malformed bytes")
        raise SchemaError("<payload>", f"is not valid msgpack ({type(e).__name__}: {detail})", where) from None
    return validate_reference(msg, where, expected_type)


def peek_type(payload: bytes) -> str | None:
    """Best-effort type name of a payload, for reject reports; never raises."""
    try:
        m = msgpack.unpackb(payload, raw=False)
        t = m.get("type") if isinstance(m, dict) else None
        return t[:64] if isinstance(t, str) else None
    except Exception:
        return None


def make(msg_type: str, vehicle: str, t_s: float, seq: int, **fields: Any) -> dict:
    """Build a message dict with the header filled in (not validated; :func:`encode` validates)."""
    mt = MESSAGES[msg_type]
    return {"type": msg_type, "version": mt.version, "vehicle": vehicle, "t_s": float(t_s), "seq": int(seq), **fields}


#: which message type a key carries (by kind/stream); the mapping lives with the key grammar
@lru_cache(maxsize=_keys.KEY_CACHE)
def type_for_key(key: str) -> str:
    """Message type of a data key; raises only :class:`schemas.keys.KeyError_` (service keys included)."""
    return _keys.message_type(key)
