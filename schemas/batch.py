"""Batches (contract version 2): many samples of a vehicle's streams in one message, as column arrays.

A batch travels on ``magmesh/{vehicle}/raw/batch`` (from a vehicle's on-board agent) or
``magmesh/{vehicle}/clean/batch`` (from ingest) with the encoding ``application/msgpack;magmesh/batch/v2``.
It is a msgpack map:

- ``type`` = "batch", ``version`` = 2, ``vehicle`` (the key's vehicle);
- ``t_s``: the latest sample time in the batch, s; ``seq``: counts *batches* on this key (0, 1, 2, ... per
  publishing instance), so a gap in it is a lost batch;
- ``streams``: a map from the stream's name inside the vehicle (``mag/{sensor}``, ``imu``, ``gnss``, ``ins``,
  ``route``, ``attitude``: the key's chunks after ``raw/``) to its columns:
  ``n`` (samples), ``t_s`` and ``seq`` (one per sample: ``seq`` is the sample's own sequence number on its
  stream, exactly as a v1 single sample on ``raw/{stream}`` would carry it), and ``cols``, a map of the
  message type's fields. Numeric columns are little-endian binary arrays: float fields ``<f8`` (n), vec3
  ``<f8`` (n × 3, row-major), fixed-length float arrays ``<f8`` (n × length), integers ``<i8``, booleans
  ``u1`` (0/1); strings are an array of n strings, or one string shared by every sample. A nullable float
  is NaN where null. An optional field is either present for every sample or absent.

:func:`decode` checks the envelope and every column (types, lengths, finiteness, bounds, choices) with numpy
on whole columns; :func:`encode` builds one from numpy columns; :meth:`Batch.messages` unbatches into the
v1 message dicts a per-sample handler takes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from . import keys
from .messages import MAX_STR, MESSAGES, SchemaError

VERSION = 2
#: samples per stream in one batch at most
MAX_SAMPLES = 65536
#: streams one batch may carry
MAX_STREAMS = 64
_TYPES = ("mag", "imu", "gnss", "ins", "route", "attitude")
_NUMERIC = {"float": ("<f8", 1), "vec3": ("<f8", 3), "int": ("<i8", 1), "bool": ("u1", 1)}

_dec = msgspec.msgpack.Decoder()
_enc = msgspec.msgpack.Encoder()


def _width(f) -> tuple[str, int] | None:
    if f.kind in _NUMERIC:
        return _NUMERIC[f.kind]
    if f.kind in ("floats", "mat3"):
        n = 9 if f.kind == "mat3" else f.length
        return ("<f8", n) if n else None
    if f.kind == "bools" and f.length:
        return ("u1", f.length)
    return None


def stream_type(name: str) -> str:
    """Message type of a stream name inside a batch (``mag/1`` → mag); :class:`SchemaError` if unknown."""
    head, _, sensor = name.partition("/")
    if head not in _TYPES or (head == "mag") != bool(sensor):
        raise SchemaError("streams", f"names an unknown stream {name[:64]!r} (expected mag/<sensor>, imu, gnss, "
                          "ins, route or attitude)")
    if sensor:
        try:
            keys.check_id(sensor, "sensor")
        except keys.KeyError_ as e:
            raise SchemaError("streams", str(e)) from None
    return head


@dataclass
class Columns:
    """One stream's samples inside a batch: ``t_s`` (n,), ``seq`` (n,), ``cols`` field → array or list."""

    name: str
    msg_type: str
    t_s: np.ndarray
    seq: np.ndarray
    cols: dict[str, Any]

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    def take(self, mask: np.ndarray) -> Columns:
        """The samples where ``mask`` is true."""
        cols = {}
        for k, v in self.cols.items():
            if isinstance(v, np.ndarray):
                cols[k] = v[mask]
            elif isinstance(v, list):
                cols[k] = [x for x, m in zip(v, mask, strict=True) if m]
            else:
                cols[k] = v
        return Columns(self.name, self.msg_type, self.t_s[mask], self.seq[mask], cols)

    def messages(self, vehicle: str) -> list[dict]:
        """The samples as v1 message dicts (what a per-sample handler takes)."""
        mt = MESSAGES[self.msg_type]
        n = self.n
        ver = mt.version
        t = self.t_s.tolist()
        sq = self.seq.tolist()
        per: list[tuple[str, Any]] = []
        for f in mt.fields:
            if f.name not in self.cols:
                continue
            v = self.cols[f.name]
            if isinstance(v, np.ndarray):
                if f.kind == "bool":
                    vals = v.astype(bool).tolist()
                elif f.kind == "bools":
                    vals = v.astype(bool).tolist()
                elif f.kind == "float" and f.nullable:
                    vals = [None if x != x else x for x in v.tolist()]
                else:
                    vals = v.tolist()
            elif isinstance(v, list):
                vals = v
            else:
                vals = [v] * n
            per.append((f.name, vals))
        out = []
        for i in range(n):
            m = {"type": self.msg_type, "version": ver, "vehicle": vehicle, "t_s": t[i], "seq": sq[i]}
            for name, vals in per:
                m[name] = vals[i]
            out.append(m)
        return out


@dataclass
class Batch:
    vehicle: str
    t_s: float
    seq: int
    streams: dict[str, Columns] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return sum(c.n for c in self.streams.values())


def _bad(fld: str, problem: str, where: str) -> SchemaError:
    return SchemaError(fld, problem, where, "batch")


def _column(f, raw: Any, n: int, sname: str, where: str, check: bool = True) -> Any:
    name = f"{sname}.{f.name}"
    w = _width(f)
    if w is not None:
        dtype, width = w
        if not isinstance(raw, (bytes, bytearray, memoryview)):
            raise _bad(name, f"must be a binary {dtype} column of {n}×{width} values", where)
        if len(raw) != n * width * np.dtype(dtype).itemsize:
            raise _bad(name, f"has {len(raw)} bytes; {n} samples × {width} need {n * width * np.dtype(dtype).itemsize}",
                       where)
        a = np.frombuffer(raw, dtype=dtype)
        if width > 1:
            a = a.reshape(n, width)
        if not check:
            return a
        if dtype == "<f8":
            bad = ~np.isfinite(a)
            if f.nullable and width == 1:
                bad &= ~np.isnan(a)
            if bad.any():
                raise _bad(name, "must contain only finite numbers" + (" (NaN for null)" if f.nullable else ""),
                           where)
            if f.lo is not None and (a < f.lo).any():
                raise _bad(name, f"has values below {f.lo:g}", where)
            if f.hi is not None and (a > f.hi).any():
                raise _bad(name, f"has values above {f.hi:g}", where)
        elif dtype == "<i8":
            if f.lo is not None and (a < f.lo).any():
                raise _bad(name, f"has values below {f.lo:g}", where)
            if f.hi is not None and (a > f.hi).any():
                raise _bad(name, f"has values above {f.hi:g}", where)
        else:  # booleans
            if (a > 1).any():
                raise _bad(name, "must contain only 0 or 1", where)
        return a
    # strings (and other variable-size kinds): one value for all, or one per sample
    if f.kind == "str":
        vals = [raw] if isinstance(raw, str) else raw
        if not isinstance(vals, list) or (not isinstance(raw, str) and len(vals) != n):
            raise _bad(name, f"must be one string or an array of {n} strings", where)
        for v in (vals if check else ()):
            if v is None and f.nullable:
                continue
            if not isinstance(v, str) or len(v) > MAX_STR:
                raise _bad(name, f"must contain strings of at most {MAX_STR} characters", where)
            if f.choices and v not in f.choices:
                raise _bad(name, f"must be one of {', '.join(f.choices)}, got {v[:64]!r}", where)
        return raw
    raise _bad(name, f"field kind {f.kind} cannot travel in a batch", where)


def decode(payload: bytes, where: str = "", check: bool = True) -> Batch:
    """Decode and check a batch; raise :class:`SchemaError` naming the stream and field that is wrong.

    ``check=False`` (a trusted ``clean/batch`` from ingest) reads the structure only: shapes and sizes are
    still checked (a wrong one cannot be read), values are not scanned again.
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) == 0:
        raise _bad("<payload>", "is empty or not bytes", where)
    if len(payload) > 64 * 1024 * 1024:
        raise _bad("<payload>", f"is {len(payload)} bytes (max 64 MiB)", where)
    try:
        m = _dec.decode(payload)
    except Exception as e:
        raise _bad("<payload>", f"is not valid msgpack ({type(e).__name__}: {str(e)[:80]})", where) from None
    if type(m) is not dict:
        raise _bad("<payload>", f"must be a msgpack map, got {type(m).__name__}", where)
    if m.get("type") != "batch":
        raise _bad("type", f"must be 'batch' on this key, got {str(m.get('type'))[:64]!r}", where)
    ver = m.get("version")
    if type(ver) is not int or ver != VERSION:
        raise _bad("version", f"is {str(ver)[:20]}; this decoder reads batch version {VERSION}", where)
    vehicle, t_s, seq = m.get("vehicle"), m.get("t_s"), m.get("seq")
    if not isinstance(vehicle, str) or len(vehicle) > MAX_STR:
        raise _bad("vehicle", "must be a string", where)
    if type(t_s) not in (int, float) or not np.isfinite(t_s):
        raise _bad("t_s", "must be a finite number", where)
    if type(seq) is not int or seq < 0:
        raise _bad("seq", "must be an integer ≥ 0", where)
    streams = m.get("streams")
    if type(streams) is not dict or len(streams) > MAX_STREAMS:
        raise _bad("streams", f"must be a map of at most {MAX_STREAMS} streams", where)
    out = Batch(vehicle, float(t_s), seq)
    for sname, body in streams.items():
        if not isinstance(sname, str):
            raise _bad("streams", "has a non-string stream name", where)
        st = stream_type(sname)
        if type(body) is not dict:
            raise _bad(sname, "must be a map with n, t_s, seq and cols", where)
        n = body.get("n")
        if type(n) is not int or not 0 <= n <= MAX_SAMPLES:
            raise _bad(f"{sname}.n", f"must be an integer in 0..{MAX_SAMPLES}", where)
        tb, sb, cols = body.get("t_s"), body.get("seq"), body.get("cols")
        if not isinstance(tb, (bytes, bytearray)) or len(tb) != 8 * n:
            raise _bad(f"{sname}.t_s", f"must be a binary <f8 column of {n} values", where)
        if not isinstance(sb, (bytes, bytearray)) or len(sb) != 8 * n:
            raise _bad(f"{sname}.seq", f"must be a binary <i8 column of {n} values", where)
        t = np.frombuffer(tb, "<f8")
        if check and not np.isfinite(t).all():
            raise _bad(f"{sname}.t_s", "must contain only finite numbers", where)
        s = np.frombuffer(sb, "<i8")
        if check and n and s.min() < 0:
            raise _bad(f"{sname}.seq", "must contain only integers ≥ 0", where)
        if type(cols) is not dict:
            raise _bad(f"{sname}.cols", "must be a map of columns", where)
        mt = MESSAGES[st]
        parsed: dict[str, Any] = {}
        for f in mt.fields:
            raw = cols.get(f.name, None) if f.name in cols else None
            if f.name not in cols:
                if f.required:
                    raise _bad(f"{sname}.{f.name}", "is missing", where)
                continue
            parsed[f.name] = _column(f, raw, n, sname, where, check)
        if check and st == "mag":
            sensor = parsed.get("sensor")
            want = sname.partition("/")[2]
            if (isinstance(sensor, str) and sensor != want) or (isinstance(sensor, list) and any(x != want for x in sensor)):
                raise _bad(f"{sname}.sensor", f"must be {want!r} (the stream's sensor)", where)
        out.streams[sname] = Columns(sname, st, t, s, parsed)
    return out


def _col_bytes(f, v: Any, n: int) -> Any:
    w = _width(f)
    if w is None:
        return v if isinstance(v, str) else list(v)
    dtype, width = w
    a = np.ascontiguousarray(np.asarray(v), dtype=dtype)
    if a.size != n * width:
        raise ValueError(f"column {f.name}: {a.size} values for {n} samples × {width}")
    return a.tobytes()


def encode(vehicle: str, seq: int, streams: dict[str, Columns | dict]) -> bytes:
    """Encode a batch. ``streams`` maps stream names to :class:`Columns` or to dicts with ``t_s``, ``seq``
    and ``cols`` (arrays or lists); empty streams are left out."""
    body = {}
    t_max = float("-inf")
    for sname, c in streams.items():
        if isinstance(c, Columns):
            t, s, cols = c.t_s, c.seq, c.cols
        else:
            t, s, cols = c["t_s"], c["seq"], c["cols"]
        t = np.ascontiguousarray(t, "<f8")
        n = int(t.shape[0])
        if n == 0:
            continue
        t_max = max(t_max, float(t.max()))
        mt = MESSAGES[stream_type(sname)]
        enc_cols = {f.name: _col_bytes(f, cols[f.name], n) for f in mt.fields if f.name in cols}
        body[sname] = {"n": n, "t_s": t.tobytes(), "seq": np.ascontiguousarray(s, "<i8").tobytes(), "cols": enc_cols}
    return _enc.encode({"type": "batch", "version": VERSION, "vehicle": vehicle,
                        "t_s": t_max if body else 0.0, "seq": int(seq), "streams": body})


def concat(parts: list[Columns]) -> Columns:
    """Samples of one stream from several batches or singles, in the given order."""
    first = parts[0]
    if len(parts) == 1:
        return first
    cols: dict[str, Any] = {}
    for k in first.cols:
        vals = [p.cols.get(k) for p in parts]
        if all(isinstance(v, np.ndarray) for v in vals):
            cols[k] = np.concatenate(vals)
        elif all(isinstance(v, str) for v in vals) and len(set(vals)) == 1:
            cols[k] = vals[0]
        else:
            merged: list = []
            for p, v in zip(parts, vals, strict=True):
                merged.extend([v] * p.n if isinstance(v, str) else list(v))
            cols[k] = merged
    return Columns(first.name, first.msg_type, np.concatenate([p.t_s for p in parts]),
                   np.concatenate([p.seq for p in parts]), cols)


def from_message(msg: dict) -> Columns:
    """One decoded v1 sample as a one-sample column set (for ingest's window of singles)."""
    mt = MESSAGES[msg["type"]]
    name = f"mag/{msg['sensor']}" if msg["type"] == "mag" else msg["type"]
    cols: dict[str, Any] = {}
    for f in mt.fields:
        if f.name not in msg:
            continue
        v = msg[f.name]
        w = _width(f)
        if w is None:
            cols[f.name] = v if f.kind == "str" and isinstance(v, str) else [v]
        elif f.kind == "float" and f.nullable and v is None:
            cols[f.name] = np.array([np.nan])
        else:
            cols[f.name] = np.asarray([v], dtype=w[0]).reshape(1, -1) if w[1] > 1 else np.asarray([v], dtype=w[0])
    return Columns(name, msg["type"], np.array([float(msg["t_s"])]), np.array([int(msg["seq"])], dtype=np.int64), cols)


def stream_name(info: Any) -> str:
    """The name inside a batch of a per-stream key (parsed): raw/mag/1 → ``mag/1``, clean/imu → ``imu``."""
    return "/".join(info.rest)


def stream_key(kind: str, vehicle: str, name: str) -> str:
    """The per-stream key of a stream inside a batch: ``(clean, car-1, mag/1)`` → magmesh/car-1/clean/mag/1."""
    head, _, sensor = name.partition("/")
    if kind == "raw":
        return keys.raw_mag(vehicle, sensor) if head == "mag" else getattr(keys, f"raw_{head}")(vehicle)
    return keys.clean_mag(vehicle, sensor) if head == "mag" else getattr(keys, f"clean_{head}")(vehicle)


def json_schema() -> dict:
    """JSON Schema of the batch envelope (columns are binary: see this module's documentation)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"magmesh batch v{VERSION}",
        "description": "many samples of one vehicle's streams as column arrays (binary little-endian columns)",
        "type": "object",
        "required": ["type", "version", "vehicle", "t_s", "seq", "streams"],
        "properties": {
            "type": {"enum": ["batch"]},
            "version": {"type": "integer", "minimum": VERSION, "maximum": VERSION},
            "vehicle": {"type": "string", "maxLength": MAX_STR},
            "t_s": {"type": "number", "description": "latest sample time in the batch, s"},
            "seq": {"type": "integer", "minimum": 0, "description": "batches on this key"},
            "streams": {"type": "object", "maxProperties": MAX_STREAMS, "additionalProperties": {
                "type": "object", "required": ["n", "t_s", "seq", "cols"],
                "properties": {"n": {"type": "integer", "minimum": 0, "maximum": MAX_SAMPLES},
                               "t_s": {"contentEncoding": "binary", "description": "<f8 × n"},
                               "seq": {"contentEncoding": "binary", "description": "<i8 × n: each sample's seq"},
                               "cols": {"type": "object"}}}},
        },
    }
