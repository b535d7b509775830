"""magmesh messages as Foxglove sees them: JSON Schemas per key and Foxglove's well-known types.

Pure Python (no Zenoh, no WebSocket): :class:`FoxgloveConverter` turns one decoded magmesh message into the
messages Foxglove's built-in panels understand without configuration, and is shared by the live server
(``magmesh foxglove``) and the JSON MCAP writer (``magmesh record --encoding json``).

- every magmesh key is a channel of its own (topic = the key, encoding ``json``, schema ``magmesh.<type>``
  in ``jsonschema`` encoding): Plot and Raw Messages panels work on any field;
- alarms also go to ``/<vehicle>/log`` as ``foxglove.Log`` (Log panel): raised critical → ERROR, raised
  warning → WARNING, cleared → INFO;
- GNSS (``clean/gnss``) goes to ``/<vehicle>/gnss/fix`` and accepted geomagnetic fixes (``fix/geomag``) to
  ``/<vehicle>/geomag/fix`` as ``foxglove.LocationFix`` (Map panel);
- the fused attitude (``heading``) goes to ``/<vehicle>/pose`` as ``foxglove.PoseInFrame`` and to ``/tf`` as
  ``foxglove.FrameTransform`` from ``<vehicle>/enu`` to ``<vehicle>/base_link`` (3D panel), at the vehicle's
  last known local position (GNSS ``pos_enu_m`` or INS).

Frames: magmesh's navigation frame is ENU and its body frame FLU, as in ROS (REP 103), so orientations
are passed on unchanged as the body → ENU quaternion. A geomagnetic fix is a position in the vehicle's
local ENU frame; it becomes latitude/longitude through the frame's origin, learned from the vehicle's
GNSS (``lat_deg``/``lon_deg`` with ``pos_enu_m``) or given (``origins``, e.g. the manifest's vehicle
``lat_deg``/``lon_deg``). Without an origin a fix is skipped and counted (``skipped["geomag fix: no
origin"]``). Foxglove timestamps are the receive time by default (``stamp="receive"``): the vehicle's
sample clock ``t_s`` of a simulator starts near 0, which the 3D panel cannot line up with live time; with
``stamp="sample"`` they are ``t_s``.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field

from magmesh import maths
from schemas import keys, messages

SCHEMA_PREFIX = "magmesh."
#: schema of service status messages (magmesh/svc/<role>/<instance>/status): a free-form map
STATUS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "magmesh.status",
    "description": "a magmesh service's status (rates, rejects, drops, mode): a map",
    "type": "object",
}


def magmesh_json_schema(msg_type: str) -> dict:
    """JSON Schema of one magmesh message type: from the streams table when it exists, else generated from
    :data:`schemas.messages.MESSAGES` (the same generator the msgpack recordings use)."""
    try:
        from schemas import streams  # type: ignore[attr-defined]

        return streams.json_schema(msg_type)
    except (ImportError, AttributeError):
        from .recording import json_schema

        return json_schema(msg_type)


# ---- Foxglove well-known schemas (jsonschema encoding) -----------------------------------------

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0,
                                                                       "maximum": 999999999}},
    "required": ["sec", "nsec"],
}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}, "required": list("xyz")}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}, "required": list("xyzw")}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT},
         "required": ["position", "orientation"]}


def _schema(name: str, desc: str, props: dict) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": name, "description": desc,
            "type": "object", "properties": props, "required": list(props)}


FOXGLOVE_SCHEMAS: dict[str, dict] = {
    "foxglove.Log": _schema("foxglove.Log", "A log message", {
        "timestamp": _TIME,
        "level": {"type": "integer", "enum": [0, 1, 2, 3, 4, 5],
                  "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL"},
        "message": {"type": "string"},
        "name": {"type": "string", "description": "process or node name"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    }),
    "foxglove.LocationFix": _schema("foxglove.LocationFix", "A navigation satellite fix for any GNSS", {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "latitude": {"type": "number", "description": "degrees, + north of the equator"},
        "longitude": {"type": "number", "description": "degrees, + east of the prime meridian"},
        "altitude": {"type": "number", "description": "m above the WGS 84 ellipsoid"},
        "position_covariance": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9,
                                "description": "m², ENU, row-major"},
        "position_covariance_type": {"type": "integer", "enum": [0, 1, 2, 3],
                                     "description": "0 UNKNOWN, 1 APPROXIMATED, 2 DIAGONAL_KNOWN, 3 KNOWN"},
    }),
    "foxglove.PoseInFrame": _schema("foxglove.PoseInFrame", "A timestamped pose in a named frame", {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE,
    }),
    "foxglove.FrameTransform": _schema("foxglove.FrameTransform",
                                       "A transform between two reference frames in 3D space", {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
        "translation": _VEC3, "rotation": _QUAT,
    }),
}

LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
COV_UNKNOWN, COV_APPROXIMATED, COV_DIAGONAL_KNOWN = 0, 1, 2
TF_TOPIC = "/tf"


def foxglove_time(ns: int) -> dict:
    ns = max(0, int(ns))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def body_to_enu_quaternion(heading_rad: float, pitch_rad: float, roll_rad: float) -> dict:
    """Foxglove/ROS ``{x, y, z, w}`` of the FLU body → ENU rotation (magmesh conventions, maths.py)."""
    w, x, y, z = maths.quat_from_euler(heading_rad, pitch_rad, roll_rad)
    return {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


def origin_from_fix(lat_deg: float, lon_deg: float, alt_m: float, pos_enu_m) -> tuple[float, float, float]:
    """The geodetic origin of a local ENU frame, from one point known in both (inverse of
    :func:`maths.enu_to_geodetic`, by fixed-point iteration: converges to < 1e-9° in 3 steps over km)."""
    lat0, lon0, alt0 = float(lat_deg), float(lon_deg), float(alt_m) - float(pos_enu_m[2])
    for _ in range(4):
        lat, lon, _alt = maths.enu_to_geodetic(pos_enu_m, lat0, lon0, alt0)
        lat0 += float(lat_deg) - float(lat)
        lon0 += float(lon_deg) - float(lon)
    return lat0, lon0, alt0


def topic_name(vehicle: str, what: str) -> str:
    return f"/{vehicle}/{what}"


@dataclass(frozen=True)
class Out:
    """One Foxglove message: ``topic``, ``schema`` (a key of :data:`FOXGLOVE_SCHEMAS`) and the JSON dict."""

    topic: str
    schema: str
    msg: dict


@dataclass
class _Vehicle:
    origin: tuple[float, float, float] | None = None
    origin_from_gnss: bool = False
    pos_enu_m: tuple[float, float, float] | None = None


@dataclass
class FoxgloveConverter:
    """Turns decoded magmesh messages into Foxglove well-known messages (see the module doc).

    ``origins``: vehicle → (lat_deg, lon_deg, alt_m) of its local ENU frame, used until (or instead of)
    one learned from its GNSS. ``skipped`` counts what was deliberately not converted, by reason.
    """

    origins: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    stamp: str = "receive"
    skipped: Counter = field(default_factory=Counter)
    _vehicles: dict[str, _Vehicle] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.stamp not in ("receive", "sample"):
            raise ValueError(f"stamp must be 'receive' or 'sample', got {self.stamp!r}")

    def _veh(self, vehicle: str) -> _Vehicle:
        v = self._vehicles.get(vehicle)
        if v is None:
            v = self._vehicles[vehicle] = _Vehicle(origin=self.origins.get(vehicle))
        return v

    def origin(self, vehicle: str) -> tuple[float, float, float] | None:
        return self._veh(vehicle).origin

    def convert(self, key: str, msg: dict, receive_ns: int) -> list[Out]:
        """The Foxglove messages one magmesh message on ``key`` gives (often none)."""
        info = keys.parse(key)
        t = msg.get("type")
        ts = foxglove_time(receive_ns if self.stamp == "receive" else messages_time_ns(msg))
        veh = self._veh(info.vehicle)
        if t == "alarm":
            return [Out(topic_name(info.vehicle, "log"), "foxglove.Log", alarm_log(key, msg, ts))]
        if t == "gnss":
            if msg.get("pos_enu_m") is not None:
                if info.kind == "clean":
                    veh.pos_enu_m = tuple(msg["pos_enu_m"])
                if not veh.origin_from_gnss:
                    veh.origin = origin_from_fix(msg["lat_deg"], msg["lon_deg"], msg["alt_m"], msg["pos_enu_m"])
                    veh.origin_from_gnss = True
            if info.kind != "clean":
                return []  # raw GNSS is shown once, after ingest (the same fix twice would clutter the Map)
            return [Out(topic_name(info.vehicle, "gnss/fix"), "foxglove.LocationFix", gnss_fix(info.vehicle, msg, ts))]
        if t == "ins":
            if info.kind == "clean":
                veh.pos_enu_m = tuple(msg["pos_enu_m"])
            return []
        if t == "geomag_fix":
            if not msg.get("accepted"):
                return []  # pending / rejected / ambiguous matches are never fixes
            if veh.origin is None:
                self.skipped["geomag fix: no origin"] += 1
                return []
            lat, lon, alt = maths.enu_to_geodetic(msg["pos_enu_m"], *veh.origin)
            std = msg.get("fix_std_m")
            return [Out(topic_name(info.vehicle, "geomag/fix"), "foxglove.LocationFix", {
                "timestamp": ts, "frame_id": f"{info.vehicle}/geomag",
                "latitude": float(lat), "longitude": float(lon), "altitude": float(alt),
                "position_covariance": _diag_cov(std) if std else [0.0] * 9,
                "position_covariance_type": COV_DIAGONAL_KNOWN if std else COV_UNKNOWN,
            })]
        if t == "heading":
            q = body_to_enu_quaternion(msg["heading_rad"], msg["pitch_rad"], msg["roll_rad"])
            p = veh.pos_enu_m or (0.0, 0.0, 0.0)
            pos = {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}
            enu = f"{info.vehicle}/enu"
            return [
                Out(topic_name(info.vehicle, "pose"), "foxglove.PoseInFrame",
                    {"timestamp": ts, "frame_id": enu, "pose": {"position": pos, "orientation": q}}),
                Out(TF_TOPIC, "foxglove.FrameTransform",
                    {"timestamp": ts, "parent_frame_id": enu, "child_frame_id": f"{info.vehicle}/base_link",
                     "translation": pos, "rotation": q}),
            ]
        return []


def messages_time_ns(msg: dict) -> int:
    t = msg.get("t_s")
    if t is None or not math.isfinite(t) or t <= 0:
        return 0
    return int(round(t * 1e9))


def _diag_cov(horiz_std_m: float) -> list[float]:
    h2 = float(horiz_std_m) ** 2
    # vertical: GNSS is typically ~2× worse vertically than horizontally
    return [h2, 0.0, 0.0, 0.0, h2, 0.0, 0.0, 0.0, 4.0 * h2]


def alarm_log(key: str, msg: dict, ts: dict) -> dict:
    raised = msg["state"] == "raised"
    level = (LOG_ERROR if msg["severity"] == "critical" else LOG_WARNING) if raised else LOG_INFO
    unit = msg.get("unit") or ""
    parts = [f"{msg['source']} {msg['state']} ({msg['severity']}): {msg['reason']}"]
    if msg.get("value") is not None:
        thr = f" (threshold {msg['threshold']:g}{' ' + unit if unit else ''})" if msg.get("threshold") is not None else ""
        parts.append(f"value {msg['value']:g}{' ' + unit if unit else ''}{thr}")
    return {"timestamp": ts, "level": level, "message": "; ".join(parts), "name": msg["service"],
            "file": key, "line": 0}


def gnss_fix(vehicle: str, msg: dict, ts: dict) -> dict:
    std = msg.get("horiz_std_m")
    return {
        "timestamp": ts, "frame_id": f"{vehicle}/gnss",
        "latitude": msg["lat_deg"], "longitude": msg["lon_deg"], "altitude": msg["alt_m"],
        "position_covariance": _diag_cov(std) if std is not None else [0.0] * 9,
        "position_covariance_type": COV_DIAGONAL_KNOWN if std is not None else COV_UNKNOWN,
    }


def magmesh_channel(key: str) -> tuple[str, dict]:
    """Schema name and JSON Schema of a magmesh key's own channel (raises :class:`schemas.keys.KeyError_`
    for keys outside the contract)."""
    info = keys.parse(key)
    if info.kind == "svc":
        return STATUS_SCHEMA["title"], STATUS_SCHEMA
    t = messages.type_for_key(key)
    return f"{SCHEMA_PREFIX}{t}", magmesh_json_schema(t)


def to_json_bytes(obj: dict) -> bytes:
    return json.dumps(obj, ensure_ascii=False, separators=(",", ":")).encode()
