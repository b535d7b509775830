"""Fleet frames (contract version 3): the samples of many vehicles in one message, as binary column arrays.

A frame travels on ``magmesh/fleet/{shard}/{kind}`` with the encoding ``application/msgpack;magmesh/frame/v3``.
``shard`` names the publishing instance's share of the fleet (an ingest instance publishes the vehicles it
validated), ``kind`` what the samples are: ``clean`` (validated by ingest), ``cal`` (compensated by
calibration), ``dmc`` (the detector's verdicts, for the heading fuser). Frames are the services' own hop: what
outside users subscribe to per vehicle (alarms, ``dmc``, ``heading``, fixes, calibration parameters) stays on
the per-vehicle keys. A frame is a msgpack map:

- ``type`` = "frame", ``version`` = 3, ``shard`` and ``kind`` (the key's chunks);
- ``t_s``: the latest sample time in the frame, s; ``seq``: counts *frames* on this key (0, 1, 2, ... per
  publishing instance, continued across its restarts), so a gap in it is a lost frame;
- ``vehicles``: the vehicle ids of the shard; a row names its vehicle by its index in this list;
- ``streams``: a map from the stream's name (``mag/{sensor}``, ``imu``, ``gnss``, ``ins``, ``route``,
  ``attitude``; ``dmc`` in a dmc frame) to its rows, sorted by vehicle index and, within a vehicle, by sample
  time: ``n`` (rows), ``vi`` (vehicle index per row: little-endian uint32, n × 4 bytes), ``t_s`` (float64),
  ``seq`` (int64: the sample's own sequence number on its per-vehicle stream — the number a single sample on
  ``magmesh/{vehicle}/{kind}/{stream}`` from the same publisher would carry — so a consumer counts gaps per
  vehicle and stream), and ``cols``, the message type's fields: a ``float`` field is n float64 (NaN stands for
  null), ``int`` n int64, ``bool`` n uint8, ``vec3`` / ``floats`` of length L / ``mat3`` n × 3 / L / 9 float64
  (row-major), a ``str`` field one string shared by every row or a list of n strings, any other kind a list of
  n values; a field absent from the map is absent from every row. Binary columns are little-endian bytes.

:func:`decode` checks the structure (lengths, indices, order, names) — frames are published by services and
hold values they validated, so no value is checked again — and gives numpy arrays that view the payload
without copying. :func:`encode` builds one; :meth:`Stream.messages` turns a vehicle's rows back into v1 message
dicts for a per-sample handler.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import msgspec
import numpy as np

from . import keys
from .batch import decode_map
from .batch import stream_type as batch_stream_type
from .messages import MAX_STR, MESSAGES, SchemaError

VERSION = 3
#: what a frame may carry: the key's last chunk
KINDS = ("clean", "cal", "dmc")
#: rows per stream in one frame at most
MAX_ROWS = 1 << 22
#: vehicles one frame may name
MAX_VEHICLES = 1 << 16
MAX_STREAMS = 64

#: what :meth:`Stream.column` gives for an optional field a row does not carry
ABSENT = type("Absent", (), {"__repr__": lambda self: "ABSENT", "__bool__": lambda self: False})()

_dec = msgspec.msgpack.Decoder()
_enc = msgspec.msgpack.Encoder()

#: numpy dtype and row width per field kind (binary columns); kinds absent here travel as lists
_BIN = {"float": ("<f8", 1), "int": ("<i8", 1), "bool": ("u1", 1), "vec3": ("<f8", 3), "mat3": ("<f8", 9)}


def _layout(f) -> tuple[str, int] | None:
    if f.kind == "floats":
        return ("<f8", f.length) if f.length else None
    return _BIN.get(f.kind)


@lru_cache(maxsize=64)
def _fields(msg_type: str) -> dict:
    return {f.name: f for f in MESSAGES[msg_type].fields}


@lru_cache(maxsize=4096)
def stream_type(name: str) -> str:
    """Message type of a stream name inside a frame (``mag/1`` → mag, ``dmc`` → dmc); SchemaError if unknown.
    The sample streams are named as in a batch (:func:`schemas.batch.stream_type`)."""
    if name == "dmc":
        return "dmc"
    try:
        return batch_stream_type(name)
    except SchemaError as e:
        if "unknown stream" not in e.problem:
            raise
        raise SchemaError("streams", f"names an unknown stream {name[:64]!r} (expected mag/<sensor>, imu, gnss, "
                          "ins, route, attitude or dmc)") from None


@dataclass
class Stream:
    """One stream's rows in a frame: ``vi`` (vehicle index), ``t_s``, ``seq`` as numpy arrays of n, ``cols``
    field → numpy array (n, or n × width), a list of n values, or one string shared by every row."""

    name: str
    msg_type: str
    vi: np.ndarray
    t_s: np.ndarray
    seq: np.ndarray
    cols: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.vi.shape[0])

    def take(self, idx) -> Stream:
        """The rows ``idx`` (an index array or a boolean mask), in that order."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        cols = {}
        for k, v in self.cols.items():
            if isinstance(v, np.ndarray):
                cols[k] = v[idx]
            elif isinstance(v, str):
                cols[k] = v
            else:
                cols[k] = [v[i] for i in idx.tolist()]
        return Stream(self.name, self.msg_type, self.vi[idx], self.t_s[idx],
                      None if self.seq is None else self.seq[idx], cols)

    def groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(vehicle index, start, end)`` of each vehicle's run of rows (rows are sorted by vehicle)."""
        n = self.n
        if n == 0:
            z = np.zeros(0, np.int64)
            return z, z, z
        vi = self.vi
        starts = np.flatnonzero(np.concatenate(([True], vi[1:] != vi[:-1])))
        ends = np.concatenate((starts[1:], [n]))
        return vi[starts].astype(np.int64), starts, ends

    def column(self, name: str, i: int) -> Any:
        """Row ``i`` of a column as the v1 field value (:data:`ABSENT` where the row lacks an optional field)."""
        v = self.cols[name]
        if isinstance(v, str):
            return v
        f = _fields(self.msg_type).get(name)
        if isinstance(v, np.ndarray):
            x = v[i]
            if v.ndim == 2:
                if f is not None and not f.required and np.isnan(x).all():
                    return ABSENT
                return x.tolist()
            if v.dtype == np.uint8:
                return bool(x)
            x = x.item()
            if isinstance(x, float) and math.isnan(x) and f is not None:
                return None if f.nullable else ABSENT
            return x
        x = v[i]
        if x is None and f is not None and not f.required and not f.nullable:
            return ABSENT
        return x

    def messages(self, vehicle: str, start: int = 0, end: int | None = None) -> list[dict]:
        """Rows ``start:end`` (one vehicle's) as v1 message dicts of ``vehicle`` (an optional field a row lacks —
        NaN or nil in its column — is left out of that row's message; a nullable one is nil)."""
        end = self.n if end is None else end
        mt = self.msg_type
        ver = MESSAGES[mt].version
        fields = MESSAGES[mt].fields
        per = []
        for f in fields:
            v = self.cols.get(f.name)
            if v is None:
                continue
            if isinstance(v, str):
                per.append((f.name, [v] * (end - start)))
                continue
            if isinstance(v, np.ndarray):
                seg = v[start:end]
                vals = seg.tolist()
                if v.ndim == 1 and v.dtype == np.uint8:
                    vals = [bool(x) for x in vals]
                elif v.dtype.kind == "f":
                    blank = np.isnan(seg) if v.ndim == 1 else np.isnan(seg).all(axis=1)
                    if blank.any():
                        fill = None if f.nullable else ABSENT
                        if f.required and not f.nullable:
                            fill = math.nan if v.ndim == 1 else None
                        vals = [fill if b else x for x, b in zip(vals, blank.tolist(), strict=True)]
            else:
                vals = list(v[start:end])
                if not f.required and not f.nullable:
                    vals = [ABSENT if x is None else x for x in vals]
            per.append((f.name, vals))
        ts = self.t_s[start:end].tolist()
        sq = self.seq[start:end].tolist()
        out = []
        for i in range(end - start):
            m = {"type": mt, "version": ver, "vehicle": vehicle, "t_s": ts[i], "seq": sq[i]}
            for name, vals in per:
                x = vals[i]
                if x is not ABSENT:
                    m[name] = x
            out.append(m)
        return out


@dataclass
class Frame:
    shard: str
    kind: str
    t_s: float
    seq: int
    vehicles: list[str]
    streams: dict[str, Stream] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return sum(s.n for s in self.streams.values())


def _bad(fld: str, problem: str, where: str) -> SchemaError:
    return SchemaError(fld, problem, where, "frame")


def _col(v: Any, f, n: int, sname: str, where: str) -> Any:
    lay = _layout(f)
    if lay is not None and isinstance(v, (bytes, bytearray, memoryview)):
        dt, w = lay
        a = np.frombuffer(v, dtype=dt)
        if a.shape[0] != n * w:
            raise _bad(f"{sname}.{f.name}", f"must hold n = {n} rows of {w} {dt} values, got {a.shape[0]} values",
                       where)
        return a.reshape(n, w) if w > 1 or f.kind in ("vec3", "floats", "mat3") else a
    if isinstance(v, str):
        if f.kind != "str" or len(v) > MAX_STR:
            raise _bad(f"{sname}.{f.name}", "must be a column, not one string", where)
        return v
    if isinstance(v, list):
        if len(v) != n:
            raise _bad(f"{sname}.{f.name}", f"must hold n = {n} values", where)
        if lay is not None and any(x is None for x in v):
            return v  # rows without an optional field: kept as a list (None where a row lacks it)
        if lay is not None:  # a binary kind sent as a list (a tool's frame): read it as an array
            try:
                a = np.asarray(v, dtype=np.dtype(lay[0]).newbyteorder("="))
            except (TypeError, ValueError):
                raise _bad(f"{sname}.{f.name}", "holds values of the wrong type", where) from None
            if a.ndim != (2 if f.kind in ("vec3", "floats", "mat3") else 1) or (a.ndim == 2 and a.shape[1] != lay[1]):
                raise _bad(f"{sname}.{f.name}", "holds rows of the wrong width", where)
            return a
        return v
    raise _bad(f"{sname}.{f.name}", "must be binary, a list or a string", where)


@lru_cache(maxsize=64)
def _checked_vehicles(names: tuple) -> list:
    """The vehicle list of a frame, checked once, and one list object for every frame that carries the same
    vehicles: a service keys what it gathers per vehicle list by the list itself (magmesh/runtime.py
    ``_frame_times``, ``_stream_keys``), so frames of one shard share its state instead of starting anew each
    time. (Never mutated by a reader.)"""
    for v in names:
        keys.check_vehicle(v)
    return list(names)


class _Envelope(msgspec.Struct):
    """A frame's map with its vehicle list left as msgpack bytes (every other value read as the untyped decoder
    reads it; a field not there is None, as ``dict.get`` gives)."""

    type: Any = None
    version: Any = None
    shard: Any = None
    kind: Any = None
    t_s: Any = None
    seq: Any = None
    vehicles: msgspec.Raw = msgspec.Raw(b"\xc0")  # (nil: not there)
    streams: Any = None


_env_dec = msgspec.msgpack.Decoder(_Envelope)
#: a vehicle list's msgpack bytes -> its names, as a tuple of the strings first decoded from them: a shard's
#: frames carry the same list frame after frame, so it is neither decoded into new strings nor hashed again
_VEHICLE_BYTES: dict[bytes, tuple] = {}


def decode(payload: bytes, where: str = "") -> Frame:
    """Decode a frame and check its structure; raise :class:`SchemaError` naming what is wrong."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) == 0:
        raise _bad("<payload>", "is empty or not bytes", where)
    try:
        env = _env_dec.decode(payload)
    except Exception:  # not a map with string keys (or not msgpack): the untyped decoder says what it is
        env = None
    names = vehicles = raw_vehicles = None
    if env is not None:
        raw_vehicles = bytes(env.vehicles)
        names = _VEHICLE_BYTES.get(raw_vehicles)
        if names is None:
            try:
                vehicles = _dec.decode(raw_vehicles)
            except Exception:  # (the envelope leaves the list unread: bad msgpack there is the whole payload's)
                env = raw_vehicles = None
    if env is not None:
        m = {"type": env.type, "version": env.version, "shard": env.shard, "kind": env.kind, "t_s": env.t_s,
             "seq": env.seq, "streams": env.streams}
    else:
        m = decode_map(payload, where, "frame")
        vehicles = m.get("vehicles")
    if m.get("type") != "frame":
        raise _bad("type", f"must be 'frame' on this key, got {str(m.get('type'))[:64]!r}", where)
    ver = m.get("version")
    if type(ver) is not int or ver != VERSION:
        raise _bad("version", f"is {str(ver)[:20]}; this decoder reads frame version {VERSION}", where)
    shard, kind, t_s, seq = m.get("shard"), m.get("kind"), m.get("t_s"), m.get("seq")
    if not isinstance(shard, str) or len(shard) > 64:
        raise _bad("shard", "must be a string", where)
    if kind not in KINDS:
        raise _bad("kind", f"must be one of {', '.join(KINDS)}", where)
    if type(t_s) not in (int, float) or not math.isfinite(t_s):
        raise _bad("t_s", "must be a finite number", where)
    if type(seq) is not int or seq < 0:
        raise _bad("seq", "must be an integer ≥ 0", where)
    if names is None:
        if type(vehicles) is not list or len(vehicles) > MAX_VEHICLES or any(type(v) is not str for v in vehicles):
            raise _bad("vehicles", f"must be a list of at most {MAX_VEHICLES} vehicle ids", where)
        names = tuple(vehicles)
    try:
        vehicles = _checked_vehicles(names)
    except keys.KeyError_ as e:
        raise _bad("vehicles", str(e), where) from None
    if raw_vehicles is not None and raw_vehicles not in _VEHICLE_BYTES:
        if len(_VEHICLE_BYTES) >= 64:
            _VEHICLE_BYTES.clear()
        _VEHICLE_BYTES[raw_vehicles] = names
    body = m.get("streams")
    if type(body) is not dict or len(body) > MAX_STREAMS:
        raise _bad("streams", f"must be a map of at most {MAX_STREAMS} streams", where)
    out = Frame(shard, kind, float(t_s), seq, vehicles)
    nv = len(vehicles)
    for sname, s in body.items():
        if not isinstance(sname, str):
            raise _bad("streams", "has a non-string stream name", where)
        st = stream_type(sname)
        if (kind == "dmc") != (st == "dmc") or (kind == "cal" and st != "mag"):
            raise _bad("streams", f"a {kind} frame cannot carry stream {sname!r} (clean: sample streams, cal: "
                       "mag/<sensor>, dmc: dmc)", where)
        if type(s) is not dict:
            raise _bad(sname, "must be a map with n, vi, t_s, seq and cols", where)
        n, vi, ts, sq, cols = s.get("n"), s.get("vi"), s.get("t_s"), s.get("seq"), s.get("cols")
        if type(n) is not int or not 0 <= n <= MAX_ROWS or type(cols) is not dict:
            raise _bad(sname, "must be a map with n, vi, t_s, seq and cols", where)
        arrs = []
        for what, v, dt in (("vi", vi, "<u4"), ("t_s", ts, "<f8"), ("seq", sq, "<i8")):
            if not isinstance(v, (bytes, bytearray, memoryview)) or len(v) != n * np.dtype(dt).itemsize:
                raise _bad(f"{sname}.{what}", f"must be n = {n} binary {dt} values", where)
            arrs.append(np.frombuffer(v, dtype=dt))
        vi_a, t_a, s_a = arrs
        if n:
            if int(vi_a.max()) >= nv:
                raise _bad(f"{sname}.vi", f"names a vehicle index beyond the {nv} vehicles", where)
            if (np.diff(vi_a.astype(np.int64)) < 0).any():
                raise _bad(f"{sname}.vi", "must be sorted by vehicle", where)
        fields = _fields(st)
        out_cols = {}
        for k, v in cols.items():
            f = fields.get(k)
            if f is None:
                continue  # a field this version does not know: ignored (forward compatible)
            out_cols[k] = _col(v, f, n, sname, where)
        out.streams[sname] = Stream(sname, st, vi_a, t_a, s_a, out_cols)
    return out


class _Peek(msgspec.Struct):
    type: Any = None
    version: Any = None
    shard: Any = None
    kind: Any = None
    seq: Any = None
    vehicles: msgspec.Raw = msgspec.Raw(b"\xc0")
    streams: dict[str, msgspec.Raw] | None = None


_peek_dec = msgspec.msgpack.Decoder(_Peek)


def peek(payload: bytes) -> tuple[str, str, int, list[str], list[str]] | None:
    """(shard, kind, seq, vehicles, stream names) of a frame whose vehicle list :func:`decode` has read (and
    checked) before, read without its rows: what a group member needs to see that a frame holds none of its
    vehicles (a few µs where decoding it takes tens to hundreds). None for any other payload: :func:`decode`
    then reads it and says what is wrong."""
    try:
        p = _peek_dec.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    if p.type != "frame" or type(p.version) is not int or p.version != VERSION or p.kind not in KINDS \
            or not isinstance(p.shard, str) or type(p.seq) is not int or p.seq < 0 or p.streams is None:
        return None
    names = _VEHICLE_BYTES.get(bytes(p.vehicles))
    if names is None:
        return None
    return p.shard, p.kind, p.seq, _checked_vehicles(names), list(p.streams)


class _Head(msgspec.Struct):
    n: int
    vi: bytes
    t_s: bytes
    seq: bytes


class _Heads(msgspec.Struct):
    shard: str
    kind: str
    vehicles: msgspec.Raw
    streams: dict[str, _Head]


_heads_dec = msgspec.msgpack.Decoder(_Heads)


class _ShardOnly(msgspec.Struct):
    shard: Any = None


_shard_dec = msgspec.msgpack.Decoder(_ShardOnly)


def shard_of(payload: bytes) -> str | None:
    """The shard a frame says it comes from, read without anything else (None: not a map, or no string shard)."""
    try:
        s = _shard_dec.decode(payload).shard
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    return s if isinstance(s, str) else None


_names_dec = msgspec.msgpack.Decoder(list[str])
#: a vehicle list's msgpack bytes -> its names, for :func:`last_rows` (unchecked: a reader builds keys with checks)
_HEAD_VEHICLES: dict[bytes, list[str]] = {}


def last_rows(payload: bytes, taken: dict | None = None) -> tuple[str, str, list[tuple[str, str, int, float]]]:
    """(shard, kind, [(vehicle, stream, seq, t_s)]) of each vehicle's last row per stream of a frame, read without
    its columns or checks (a few µs: what a group member watches the others' outputs with); raises ValueError on
    a payload that is not a frame. ``taken`` (a dict the caller keeps for a run of frames read newest first):
    rows of a vehicle and stream a frame read before gave are left out."""
    try:
        h = _heads_dec.decode(payload)
        raw = bytes(h.vehicles)
        vehicles = _HEAD_VEHICLES.get(raw)
        if vehicles is None:
            vehicles = _names_dec.decode(raw)
            if len(_HEAD_VEHICLES) >= 64:
                _HEAD_VEHICLES.clear()
            _HEAD_VEHICLES[raw] = vehicles
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise ValueError(f"not a frame: {e}") from None
    out = []
    nv = len(vehicles)
    for name, st in h.streams.items():
        n = st.n
        if n <= 0 or len(st.vi) != 4 * n or len(st.seq) != 8 * n or len(st.t_s) != 8 * n:
            continue
        vi = np.frombuffer(st.vi, "<u4")
        sq, ts = np.frombuffer(st.seq, "<i8"), np.frombuffer(st.t_s, "<f8")
        last = np.flatnonzero(np.r_[vi[1:] != vi[:-1], True])  # rows are sorted by vehicle, then time
        last = last[vi[last] < nv]
        if taken is not None:
            done = taken.get((h.shard, h.kind, name, raw))
            if done is None:
                done = taken[(h.shard, h.kind, name, raw)] = np.zeros(nv, bool)
            v_last = vi[last]
            last = last[~done[v_last]]
            done[v_last] = True
        for i, q, t in zip(vi[last].tolist(), sq[last].tolist(), ts[last].tolist(), strict=True):
            out.append((vehicles[i], name, q, t))
    return h.shard, h.kind, out


def _bin_col(v: Any, f) -> Any:
    if isinstance(v, str):
        return v
    lay = _layout(f)
    if lay is None:
        return v.tolist() if isinstance(v, np.ndarray) else list(v)
    if not isinstance(v, np.ndarray):
        if f.kind == "float":
            v = [math.nan if x is None else x for x in v]
        elif any(x is None for x in v):  # rows without this optional field: a list keeps them apart
            return list(v)
    return np.ascontiguousarray(v, dtype=lay[0]).tobytes()


def encode(shard: str, kind: str, seq: int, vehicles: list[str], streams: dict[str, Stream]) -> bytes:
    """Encode a frame; each stream's rows must already be sorted by vehicle index, then time."""
    body = {}
    t_max = -math.inf
    for sname, s in streams.items():
        n = s.n
        if n == 0:
            continue
        fields = {f.name: f for f in MESSAGES[s.msg_type].fields}
        t_max = max(t_max, float(s.t_s.max()))
        body[sname] = {"n": n, "vi": np.ascontiguousarray(s.vi, "<u4").tobytes(),
                       "t_s": np.ascontiguousarray(s.t_s, "<f8").tobytes(),
                       "seq": np.ascontiguousarray(s.seq, "<i8").tobytes(),
                       "cols": {k: _bin_col(v, fields[k]) for k, v in s.cols.items() if k in fields}}
    return _enc.encode({"type": "frame", "version": VERSION, "shard": shard, "kind": kind,
                        "t_s": t_max if body else 0.0, "seq": int(seq), "vehicles": list(vehicles),
                        "streams": body})


def concat(parts: list[Stream]) -> Stream:
    """Rows of one stream from several pieces, in the given order (vehicle indices must already agree)."""
    first = parts[0]
    if len(parts) == 1:
        return first
    cols: dict[str, Any] = {}
    for k, v0 in first.cols.items():
        vals = [p.cols.get(k) for p in parts]
        if isinstance(v0, str) and all(v == v0 for v in vals):
            cols[k] = v0
        elif all(isinstance(v, np.ndarray) for v in vals):
            cols[k] = np.concatenate(vals)
        else:
            merged: list = []
            for p, v in zip(parts, vals, strict=True):
                merged.extend([v] * p.n if isinstance(v, str) else (v.tolist() if isinstance(v, np.ndarray) else v))
            cols[k] = merged
    return Stream(first.name, first.msg_type, np.concatenate([p.vi for p in parts]),
                  np.concatenate([p.t_s for p in parts]), np.concatenate([p.seq for p in parts]), cols)


def json_schema() -> dict:
    """JSON Schema of the frame envelope (columns are binary or lists; see the module's description)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"magmesh frame v{VERSION}",
        "description": "the samples of a shard of vehicles as binary column arrays (contract v3)",
        "type": "object",
        "required": ["type", "version", "shard", "kind", "t_s", "seq", "vehicles", "streams"],
        "properties": {
            "type": {"enum": ["frame"]},
            "version": {"type": "integer", "minimum": VERSION, "maximum": VERSION},
            "shard": {"type": "string", "maxLength": 64},
            "kind": {"enum": list(KINDS)},
            "t_s": {"type": "number", "description": "latest sample time in the frame, s"},
            "seq": {"type": "integer", "minimum": 0, "description": "frames on this key"},
            "vehicles": {"type": "array", "items": {"type": "string"}, "maxItems": MAX_VEHICLES},
            "streams": {"type": "object", "maxProperties": MAX_STREAMS, "additionalProperties": {
                "type": "object", "required": ["n", "vi", "t_s", "seq", "cols"],
                "properties": {"n": {"type": "integer", "minimum": 0, "maximum": MAX_ROWS},
                               "vi": {"description": "uint32 little-endian, vehicle index per row"},
                               "t_s": {"description": "float64 little-endian, sample time per row, s"},
                               "seq": {"description": "int64 little-endian, each sample's seq on its own stream"},
                               "cols": {"type": "object"}}}},
        },
    }
