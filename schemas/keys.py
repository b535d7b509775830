"""The one place where magmesh key expressions are built and parsed.

Every key starts with ``magmesh/``. Per-vehicle keys are ``magmesh/{vehicle}/{kind}/...``;
service keys are ``magmesh/svc/{role}/{instance}[/status]``. Nothing else in the code base
formats a key string by hand: services, tools and tests call these builders.

A *vehicle pattern* may be given wherever a vehicle id is expected when building a
subscription: ``*`` (every vehicle), an exact id, or a Zenoh chunk pattern such as ``car-$*``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from functools import lru_cache

#: entries of each per-key cache (parsed keys, their clean keys, streams, types): a bounded memory per process
#: however many vehicles come and go; keys beyond it are parsed again (MAGMESH_KEY_CACHE sets it)
try:
    KEY_CACHE = max(16, int(os.environ.get("MAGMESH_KEY_CACHE", "") or 8192))
except ValueError:
    KEY_CACHE = 8192

ROOT = "magmesh"
SVC = "svc"
#: the chunk of the fleet frames' keys: ``magmesh/fleet/{shard}/{kind}`` (contract v3, see schemas/frame.py)
FLEET = "fleet"
#: what a fleet frame carries (its key's last chunk)
FRAME_KINDS = ("clean", "cal", "dmc")

# vehicle ids and sensor/source names: one key chunk, no wildcards or Zenoh specials
_ID_RE = re.compile(r"\A[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}\Z")  # \Z: "$" would let a trailing newline in
# patterns additionally allow Zenoh wildcards inside one chunk
_PATTERN_RE = re.compile(r"\A(\*|\*\*|[A-Za-z0-9_.\-$*]{1,64})\Z")

#: per-vehicle stream kinds and how many further chunks they take
KINDS = {
    "raw": None,  # raw/mag/{sensor}, raw/imu, raw/gnss, raw/ins, raw/route, raw/attitude
    "clean": None,  # same sub-keys as raw, after ingest
    "rejects": 0,
    "cal": None,  # cal/mag/{sensor}, cal/params/{sensor}
    "dmc": 0,
    "heading": 0,
    "fix": 1,  # fix/geomag
    "track": 0,
    "alarm": 1,  # alarm/{source}
    "truth": 1,  # truth/{what}
}

#: sub-streams of raw/ and clean/
RAW_STREAMS = ("mag", "imu", "gnss", "ins", "route", "attitude")
#: the chunk of a vehicle's batches (contract v2: many samples of its streams in one message, see schemas/batch.py)
BATCH = "batch"

#: chunks that can never be a vehicle id: ``svc`` starts the service keys, ``fleet`` the fleet frames' keys
#: (reserved since contract v3), ``magmesh`` is the root
RESERVED_VEHICLES = frozenset((SVC, FLEET, ROOT))

#: the longest key the contract allows (ROOT + vehicle + kind + two chunks of at most 64 characters each)
MAX_KEY_LEN = 400

#: the bucket under which counters file keys that do not parse (so made-up keys cannot grow a table)
BAD_KEY = "<bad key>"


class KeyError_(ValueError):
    """A key or key part that does not follow the magmesh key grammar."""


def check_id(value: str, what: str = "vehicle id") -> str:
    if not isinstance(value, str) or not _ID_RE.match(value):
        raise KeyError_(
            f"{what} {value!r} is not valid: use 1-64 characters of letters, digits, '_', '-', '.', "
            "starting with a letter or digit"
        )
    return value


def check_vehicle(value: str) -> str:
    """A vehicle id: :func:`check_id`, and not one of :data:`RESERVED_VEHICLES`."""
    check_id(value, "vehicle id")
    if value in RESERVED_VEHICLES:
        raise KeyError_(f"vehicle id {value!r} is reserved ({', '.join(sorted(RESERVED_VEHICLES))} cannot name a "
                        "vehicle)")
    return value


def check_pattern(value: str, what: str = "vehicle pattern") -> str:
    if not isinstance(value, str) or not _PATTERN_RE.match(value):
        raise KeyError_(f"{what} {value!r} is not a single key chunk or chunk pattern")
    return value


def _v(vehicle: str) -> str:
    """Accept an id or a pattern (for subscriptions)."""
    if isinstance(vehicle, str) and _ID_RE.match(vehicle):
        return check_vehicle(vehicle)
    return check_pattern(vehicle)


def _part(value: str, what: str) -> str:
    if value in ("*", "**"):
        return value
    return check_id(value, what)


# ---- per-vehicle keys -------------------------------------------------------------------------


def raw_mag(vehicle: str, sensor: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/mag/{_part(sensor, 'sensor')}"


def raw_imu(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/imu"


def raw_gnss(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/gnss"


def raw_ins(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/ins"


def raw_route(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/route"


def raw_attitude(vehicle: str) -> str:
    """The vehicle's own attitude estimate (e.g. a flight controller's), with its magnetometer heading."""
    return f"{ROOT}/{_v(vehicle)}/raw/attitude"


def raw_all(vehicle: str = "*") -> str:
    return f"{ROOT}/{_v(vehicle)}/raw/**"


def clean_mag(vehicle: str, sensor: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/mag/{_part(sensor, 'sensor')}"


def clean_imu(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/imu"


def clean_gnss(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/gnss"


def clean_ins(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/ins"


def clean_route(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/route"


def clean_attitude(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/attitude"


def raw_batch(vehicle: str) -> str:
    """A vehicle's batches as its on-board agent publishes them (contract v2)."""
    return f"{ROOT}/{_v(vehicle)}/raw/{BATCH}"


def clean_batch(vehicle: str) -> str:
    """A vehicle's validated batches, published by ingest (contract v2)."""
    return f"{ROOT}/{_v(vehicle)}/clean/{BATCH}"


def clean_all(vehicle: str = "*") -> str:
    return f"{ROOT}/{_v(vehicle)}/clean/**"


@lru_cache(maxsize=KEY_CACHE)
def raw_to_clean(raw_key: str) -> str:
    """``magmesh/v/raw/x/..`` → ``magmesh/v/clean/x/..`` (the ingest mapping)."""
    info = parse(raw_key)
    if info.kind != "raw":
        raise KeyError_(f"{raw_key!r} is not a raw key")
    return "/".join([ROOT, info.vehicle, "clean", *info.rest])


def rejects(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/rejects"


def cal_mag(vehicle: str, sensor: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/cal/mag/{_part(sensor, 'sensor')}"


def cal_params(vehicle: str, sensor: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/cal/params/{_part(sensor, 'sensor')}"


def dmc(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/dmc"


def heading(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/heading"


def fix_geomag(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/fix/geomag"


def track(vehicle: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/track"


def alarm(vehicle: str, source: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/alarm/{_part(source, 'alarm source')}"


def alarms_all(vehicle: str = "*") -> str:
    return f"{ROOT}/{_v(vehicle)}/alarm/**"


def truth(vehicle: str, what: str) -> str:
    return f"{ROOT}/{_v(vehicle)}/truth/{_part(what, 'truth kind')}"


def everything() -> str:
    return f"{ROOT}/**"


# ---- fleet frames (contract v3) ------------------------------------------------------------------


def fleet_frame(shard: str, kind: str) -> str:
    """A shard's frames of one kind: ``magmesh/fleet/{shard}/{kind}`` (kind: clean, cal or dmc)."""
    if kind not in FRAME_KINDS:
        raise KeyError_(f"frame kind {kind!r} is not one of {', '.join(FRAME_KINDS)}")
    return f"{ROOT}/{FLEET}/{_part(shard, 'shard')}/{kind}"


def fleet_frames(kind: str, shard: str = "*") -> str:
    """Every shard's frames of one kind (a subscription)."""
    return fleet_frame(shard, kind)


# ---- service keys -----------------------------------------------------------------------------


def svc_token(role: str, instance: str) -> str:
    return f"{ROOT}/{SVC}/{_part(role, 'role')}/{_part(instance, 'instance')}"


def svc_status(role: str, instance: str) -> str:
    return f"{svc_token(role, instance)}/status"


def svc_control(role: str, instance: str) -> str:
    """Queryable for control requests (hand-over during a live swap, etc.)."""
    return f"{svc_token(role, instance)}/control"


def svc_all() -> str:
    return f"{ROOT}/{SVC}/*/*"


def svc_status_all() -> str:
    return f"{ROOT}/{SVC}/*/*/status"


# ---- parsing ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class KeyInfo:
    """A parsed magmesh key.

    For vehicle keys: ``vehicle``, ``kind`` (raw, clean, rejects, cal, dmc, heading, fix, track,
    alarm, truth), ``rest`` (the remaining chunks, e.g. ``("mag", "1")``).
    For service keys: ``vehicle`` is ``""``, ``kind`` is ``"svc"``, ``rest`` is
    ``(role, instance)`` or ``(role, instance, "status")``. For fleet frames: ``vehicle`` is ``""``, ``kind`` is
    ``"fleet"``, ``rest`` is ``(shard, frame kind)``.
    """

    key: str
    vehicle: str
    kind: str
    rest: tuple[str, ...]

    @property
    def stream(self) -> str:
        """``mag``/``imu``/``gnss``/... for raw, clean and cal keys; else the kind."""
        return self.rest[0] if self.kind in ("raw", "clean", "cal") and self.rest else self.kind

    @property
    def sensor(self) -> str | None:
        if self.kind in ("raw", "clean", "cal") and len(self.rest) == 2:
            return self.rest[1]
        return None

    @property
    def source(self) -> str | None:
        return self.rest[0] if self.kind in ("alarm", "truth", "fix") and self.rest else None


def parse(key: str) -> KeyInfo:
    """Parse a concrete magmesh key; raise :class:`KeyError_` naming what is wrong."""
    if not isinstance(key, str):
        raise KeyError_(f"key must be a string, got {type(key).__name__}")
    return _parse(key)


@lru_cache(maxsize=KEY_CACHE)
def _parse(key: str) -> KeyInfo:
    if len(key) > MAX_KEY_LEN:
        raise KeyError_(f"key {_short(key)} is {len(key)} characters long (max {MAX_KEY_LEN})")
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyError_(f"key {_short(key)} does not start with '{ROOT}/<vehicle>/<kind>'")
    if parts[1] == SVC:
        if len(parts) not in (4, 5) or (len(parts) == 5 and parts[4] not in ("status", "control")):
            raise KeyError_(f"service key {_short(key)} must be {ROOT}/svc/<role>/<instance>[/status|/control]")
        check_id(parts[2], "role")
        check_id(parts[3], "instance")
        return KeyInfo(key, "", "svc", tuple(parts[2:]))
    if parts[1] == FLEET:
        if len(parts) != 4 or parts[3] not in FRAME_KINDS:
            raise KeyError_(f"fleet key {_short(key)} must be {ROOT}/{FLEET}/<shard>/<{'|'.join(FRAME_KINDS)}>")
        check_id(parts[2], "shard")
        return KeyInfo(key, "", FLEET, (parts[2], parts[3]))
    vehicle, kind, rest = parts[1], parts[2], tuple(parts[3:])
    check_vehicle(vehicle)
    if kind not in KINDS:
        raise KeyError_(f"key {_short(key)}: unknown kind {kind!r} (expected one of {', '.join(KINDS)})")
    n = KINDS[kind]
    if n is not None and len(rest) != n:
        raise KeyError_(f"key {key!r}: kind {kind!r} takes {n} further part(s), got {len(rest)}")
    if kind in ("raw", "clean"):
        if rest and rest[0] == BATCH and len(rest) == 1:
            return KeyInfo(key, vehicle, kind, rest)
        if not rest or rest[0] not in RAW_STREAMS:
            raise KeyError_(f"key {key!r}: {kind}/ must be followed by one of {', '.join(RAW_STREAMS)}")
        if rest[0] == "mag" and len(rest) != 2:
            raise KeyError_(f"key {key!r}: {kind}/mag/ takes a sensor id")
        if rest[0] != "mag" and len(rest) != 1:
            raise KeyError_(f"key {key!r}: {kind}/{rest[0]} takes no further parts")
    if kind == "cal" and (len(rest) != 2 or rest[0] not in ("mag", "params")):
        raise KeyError_(f"key {key!r}: cal/ must be cal/mag/<sensor> or cal/params/<sensor>")
    for r in rest:
        check_id(r, "key part")
    return KeyInfo(key, vehicle, kind, rest)


def _short(key: str) -> str:
    return repr(key if len(key) <= 120 else key[:117] + "...")


def parse_data(key: str) -> KeyInfo:
    """Parse a key a service received as data: a per-vehicle key of the contract, never a service key.

    A subscription such as ``magmesh/*/raw/**`` also matches ``magmesh/svc/raw/imu``; that key parses as a
    service key, which is not data. Raise :class:`KeyError_` for it and for anything :func:`parse` refuses.
    """
    info = parse(key)
    if info.kind == SVC:
        raise KeyError_(f"key {_short(key)} is under {ROOT}/{SVC}/ (service keys), not a vehicle's data key: "
                        f"'{SVC}' is reserved and cannot name a vehicle")
    if info.kind == FLEET:
        raise KeyError_(f"key {_short(key)} is a fleet frame's key, not a vehicle's data key: '{FLEET}' is "
                        "reserved and cannot name a vehicle")
    return info


#: which message type a per-vehicle key carries, by kind (raw/clean/cal: by stream)
_STREAM_TYPES = {"mag": "mag", "imu": "imu", "gnss": "gnss", "ins": "ins", "route": "route", "attitude": "attitude",
                 BATCH: "batch"}
_KIND_TYPES = {"rejects": "reject", "dmc": "dmc", "heading": "heading", "fix": "geomag_fix", "track": "track",
               "alarm": "alarm", "truth": "truth"}


def message_type(key: str) -> str:
    """The message type name a data key carries; :class:`KeyError_` for anything else (never another error)."""
    info = parse_data(key)
    if info.kind in ("raw", "clean"):
        return _STREAM_TYPES[info.rest[0]]
    if info.kind == "cal":
        return "mag" if info.rest[0] == "mag" else "cal_params"
    return _KIND_TYPES[info.kind]
