"""Batches (contract version 2; binary form since contract version 3): many samples of a vehicle's streams in one
message, as column arrays.

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
  message type's fields, each an array of n values of the field's v1 type (a vec3 field: n arrays of 3
  numbers). A string field may instead be one string shared by every sample. An optional field is either
  present for every sample or absent.

The binary form (``version`` = 3, encoding ``application/msgpack;magmesh/batch/v3``; an on-board agent may
send either form) is the same map, except that ``t_s`` (float64), ``seq`` (int64) and each numeric column are
msgpack binary values holding the n values as little-endian bytes: a ``float`` field n float64 (NaN stands for
null where the field is nullable), ``int`` n int64, ``bool`` n bytes of 0 or 1, ``vec3`` / ``floats`` of length
L / ``mat3`` n × 3 / L / 9 float64, row-major; string and other fields as in version 2. It carries the same
samples and constraints; a batch with a value outside them (not finite, out of bounds) is refused whole.

:func:`decode` checks the envelope and every column in compiled code: each stream's columns are decoded into a
``msgspec.Struct`` generated from the message type (the same constraints as a v1 sample: types, lengths,
finiteness, bounds, choices). A binary batch's values are checked on whole columns; ingest's fleet frames check
them over a whole window of batches at once (:func:`binary_problems`), so no Python object is made per sample
(a 50 ms window of a car, 12 samples: ~31 µs of ingest's CPU in binary form against ~50 µs as lists).
:func:`encode` builds one from lists or numpy columns; :meth:`Columns.messages` unbatches into the v1
message dicts a per-sample handler takes; :meth:`Columns.array` gives a column as a numpy array.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache, lru_cache
from typing import Annotated, Any, Literal, Union

import msgspec
import numpy as np

from . import keys
from .messages import MAX_STR, MESSAGES, SchemaError

VERSION = 2
#: the binary form of a batch: the same map, with ``t_s``, ``seq`` and numeric columns as little-endian bytes
BINARY_VERSION = 3
VERSIONS = (VERSION, BINARY_VERSION)
#: samples per stream in one batch at most
MAX_SAMPLES = 65536
#: streams one batch may carry
MAX_STREAMS = 64
_TYPES = ("mag", "imu", "gnss", "ins", "route", "attitude")

_dec = msgspec.msgpack.Decoder()
_enc = msgspec.msgpack.Encoder()


@cache
def _stream_struct(msg_type: str) -> type[msgspec.Struct]:
    """Typed columns of one message type: every field an array of its v1 type (strings may be one value)."""
    from .streams import Finite, _field_type

    cols = []
    for f in MESSAGES[msg_type].fields:
        ft = _field_type(f)
        col = Annotated[list[ft], msgspec.Meta(max_length=MAX_SAMPLES)]
        if f.kind == "str":
            col = Union[ft, col]  # noqa: UP007 - runtime type construction
        if f.required:
            cols.append((f.name, col))
        else:
            cols.append((f.name, Union[col, msgspec.UnsetType], msgspec.UNSET))  # noqa: UP007
    cols_t = msgspec.defstruct(f"{msg_type}_columns", cols, kw_only=True)
    return msgspec.defstruct(f"{msg_type}_stream", [
        ("n", Annotated[int, msgspec.Meta(ge=0, le=MAX_SAMPLES)]),
        ("t_s", Annotated[list[Finite], msgspec.Meta(max_length=MAX_SAMPLES)]),
        ("seq", Annotated[list[Annotated[int, msgspec.Meta(ge=0)]], msgspec.Meta(max_length=MAX_SAMPLES)]),
        ("cols", cols_t)], kw_only=True)


@lru_cache(maxsize=4096)
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
    """One stream's samples inside a batch: ``t_s`` and ``seq`` (lists of n), ``cols`` field → list of n
    values (or one string shared by all samples)."""

    name: str
    msg_type: str
    t_s: list
    seq: list
    cols: dict[str, Any]

    @property
    def n(self) -> int:
        return len(self.t_s)

    def array(self, name: str) -> np.ndarray:
        """A numeric column (``t_s``, ``seq`` or a field) as a numpy array (n or n × width)."""
        if name == "t_s":
            return np.asarray(self.t_s, float)
        if name == "seq":
            return np.asarray(self.seq, np.int64)
        v = self.cols[name]
        return np.asarray(v, float) if not isinstance(v, str) else np.full(self.n, v)

    def take(self, mask) -> Columns:
        """The samples where ``mask`` (n booleans) is true."""
        m = np.asarray(mask, bool).tolist()
        cols = {k: (v if isinstance(v, str) else [x for x, k_ in zip(v, m, strict=True) if k_])
                for k, v in self.cols.items()}
        return Columns(self.name, self.msg_type, [x for x, k_ in zip(self.t_s, m, strict=True) if k_],
                       [x for x, k_ in zip(self.seq, m, strict=True) if k_], cols)

    def messages(self, vehicle: str) -> list[dict]:
        """The samples as v1 message dicts (what a per-sample handler takes)."""
        ver = MESSAGES[self.msg_type].version
        n = self.n
        per = [(k, [v] * n if isinstance(v, str) else v) for k, v in self.cols.items()]
        out = []
        mt = self.msg_type
        for i in range(n):
            m = {"type": mt, "version": ver, "vehicle": vehicle, "t_s": self.t_s[i], "seq": self.seq[i]}
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


def decode_map(payload: bytes, where: str, kind: str) -> dict:
    """``payload`` as an untyped msgpack map, or the :class:`SchemaError` of a ``kind`` message (batch, frame)
    saying why it is not one."""
    try:
        m = _dec.decode(payload)
    except Exception as e:
        raise SchemaError("<payload>", f"is not valid msgpack ({type(e).__name__}: {str(e)[:80]})", where,
                          kind) from None
    if type(m) is not dict:
        raise SchemaError("<payload>", f"must be a msgpack map, got {type(m).__name__}", where, kind)
    return m


def _where_in(e: Exception, sname: str) -> str:
    text = str(e)
    if "`$." not in text:
        return sname
    path = text.split("`$.", 1)[1].split("`", 1)[0]
    parts = [p.split("[", 1)[0] for p in path.split(".")]
    if "missing required field `" in text:
        parts.append(text.split("missing required field `", 1)[1].split("`", 1)[0])
    if parts and parts[0] == "cols" and len(parts) > 1:
        return f"{sname}.{parts[1]}"
    return f"{sname}.{parts[0]}"


@cache
def _envelope_decoder() -> msgspec.msgpack.Decoder:
    from .streams import Finite

    env = msgspec.defstruct("batch_envelope", [
        ("type", Literal["batch"]), ("version", Literal[VERSION]),
        ("vehicle", Annotated[str, msgspec.Meta(max_length=MAX_STR)]), ("t_s", Finite),
        ("seq", Annotated[int, msgspec.Meta(ge=0)]),
        ("streams", Annotated[dict[str, msgspec.Raw], msgspec.Meta(max_length=MAX_STREAMS)])])
    return msgspec.msgpack.Decoder(env)


@lru_cache(maxsize=16)
def _stream_decoder(msg_type: str) -> msgspec.msgpack.Decoder:
    return msgspec.msgpack.Decoder(_stream_struct(msg_type))


#: stream names already checked (stream_type), by name: most batches name the same few
_TYPES_SEEN: dict[str, str] = {}


class _Slow(Exception):
    """The typed one-pass decode could not take this payload: the checking decoder decides (and words the error)."""


def _decode_typed(payload: bytes) -> Batch:
    """A valid batch in one typed pass over the bytes per stream (msgspec's C decoder); anything it refuses is
    left to the checking decoder, which names the field."""
    if len(payload) > 64 * 1024 * 1024:
        raise _Slow
    try:
        e = _envelope_decoder().decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError):
        raise _Slow from None
    out = Batch(e.vehicle, float(e.t_s), e.seq)
    unset = msgspec.UNSET
    for sname, raw in e.streams.items():
        st = _TYPES_SEEN.get(sname) or stream_type(sname)
        try:
            s = _stream_decoder(st).decode(raw)
        except (msgspec.ValidationError, msgspec.DecodeError):
            raise _Slow from None
        n = s.n
        if len(s.t_s) != n or len(s.seq) != n:
            raise _Slow
        cols = {}
        c = s.cols
        for k in c.__struct_fields__:
            v = getattr(c, k)
            if v is unset:
                continue
            if not isinstance(v, str) and len(v) != n:
                raise _Slow
            cols[k] = v
        if st == "mag":
            sensor = cols.get("sensor")
            want = sname.partition("/")[2]
            if (isinstance(sensor, str) and sensor != want) or (isinstance(sensor, list) and any(x != want for x in sensor)):
                raise _Slow
        out.streams[sname] = Columns(sname, st, s.t_s, s.seq, cols)
        if len(_TYPES_SEEN) < 4096:
            _TYPES_SEEN[sname] = st
    return out


@cache
def _envelope3_decoder() -> msgspec.msgpack.Decoder:
    from .streams import Finite

    stream = msgspec.defstruct("batch3_stream", [
        ("n", Annotated[int, msgspec.Meta(ge=0, le=MAX_SAMPLES)]), ("t_s", bytes), ("seq", bytes),
        ("cols", dict[str, Any])])
    env = msgspec.defstruct("batch3_envelope", [
        ("type", Literal["batch"]), ("version", Literal[BINARY_VERSION]),
        ("vehicle", Annotated[str, msgspec.Meta(max_length=MAX_STR)]), ("t_s", Finite),
        ("seq", Annotated[int, msgspec.Meta(ge=0)]),
        ("streams", Annotated[dict[str, stream], msgspec.Meta(max_length=MAX_STREAMS)])])
    return msgspec.msgpack.Decoder(env)


@lru_cache(maxsize=256)
def _list_column_type(msg_type: str, name: str) -> Any:
    """The v2 (list) column type of a field, for the columns a binary batch sends as lists."""
    from .streams import _field_type

    f = {f.name: f for f in MESSAGES[msg_type].fields}[name]
    col = Annotated[list[_field_type(f)], msgspec.Meta(max_length=MAX_SAMPLES)]
    return Union[_field_type(f), col] if f.kind == "str" else col  # noqa: UP007


@lru_cache(maxsize=16)
def _required(msg_type: str) -> frozenset:
    return frozenset(f.name for f in MESSAGES[msg_type].fields if f.required)


@lru_cache(maxsize=16)
def _binary_spec(msg_type: str) -> dict:
    """Per field of a message type: (field, numpy dtype, row width) for the binary kinds, (field, None, 0) else."""
    from .frame import _layout

    out = {}
    for f in MESSAGES[msg_type].fields:
        lay = _layout(f)
        out[f.name] = (f, lay[0], lay[1]) if lay is not None else (f, None, 0)
    return out


@dataclass
class RawColumns:
    """A binary batch's stream with its structure checked but its values not yet: ``t_s``, ``seq`` and the
    binary fields are the payload's bytes (little-endian); :func:`binary_problems` checks the values, on a
    whole window of them at once (ingest's frames)."""

    name: str
    msg_type: str
    n: int
    t_s: bytes
    seq: bytes
    cols: dict[str, Any]


def _decode_binary(payload: bytes, where: str, arrays: bool, deferred: bool = False) -> Batch:
    """A batch of version 3: numeric columns (and ``t_s``, ``seq``) as little-endian bytes. The structure
    (lengths, required fields, string columns, the magnetometer's sensor) is checked here; the values (finite,
    in bounds) here too unless ``deferred`` — then the streams are :class:`RawColumns` and the caller checks
    the values with :func:`binary_problems`."""
    try:
        e = _envelope3_decoder().decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError) as ex:
        raise _bad("<payload>", f"is not a valid binary batch: {ex}", where) from None
    out = Batch(e.vehicle, float(e.t_s), e.seq)
    for sname, s in e.streams.items():
        st = _TYPES_SEEN.get(sname) or stream_type(sname)
        n = s.n
        if len(s.t_s) != 8 * n or len(s.seq) != 8 * n:
            raise _bad(f"{sname}.t_s", f"t_s and seq must hold n = {n} little-endian 8-byte values", where)
        spec = _binary_spec(st)
        cols: dict[str, Any] = {}
        for name, v in s.cols.items():
            fs = spec.get(name)
            if fs is None:
                continue  # a field this version does not know: ignored (forward compatible)
            f, dt, w = fs
            if dt is not None and type(v) is bytes:
                if len(v) != n * w * (1 if dt == "u1" else 8):
                    raise _bad(f"{sname}.{name}", f"must hold n = {n} rows of {w} {dt} values", where)
                cols[name] = v
                continue
            if f.kind == "str":
                if type(v) is str:
                    ok = len(v) <= MAX_STR and (not f.choices or v in f.choices)
                else:
                    ok = type(v) is list and len(v) == n and all(
                        type(x) is str and len(x) <= MAX_STR and (not f.choices or x in f.choices) for x in v)
                if not ok:
                    raise _bad(f"{sname}.{name}", "must be one string or n strings" + (
                        f" of {', '.join(f.choices)}" if f.choices else ""), where)
                cols[name] = v
                continue
            try:
                v = msgspec.convert(v, _list_column_type(st, name), strict=True)
            except msgspec.ValidationError as ex:
                raise _bad(f"{sname}.{name}", f"is not valid: {ex}", where) from None
            if len(v) != n:
                raise _bad(f"{sname}.{name}", f"must hold n = {n} values", where)
            cols[name] = v
        missing = _required(st) - cols.keys()
        if missing:
            raise _bad(f"{sname}.{sorted(missing)[0]}", "is missing (a required field)", where)
        if st == "mag":
            sensor = cols.get("sensor")
            want = sname.partition("/")[2]
            if (isinstance(sensor, str) and sensor != want) or (isinstance(sensor, list) and any(x != want for x in sensor)):
                raise _bad(f"{sname}.sensor", f"must be {want!r} (the stream's sensor)", where)
        if deferred:
            out.streams[sname] = RawColumns(sname, st, n, s.t_s, s.seq, cols)
            continue
        t = np.frombuffer(s.t_s, "<f8")
        sq = np.frombuffer(s.seq, "<i8")
        arrs = {}
        for name, v in cols.items():
            f, dt, w = spec[name]
            if type(v) is bytes:
                a = np.frombuffer(v, dt)
                arrs[name] = a.reshape(n, w) if (w > 1 or f.kind in ("vec3", "floats", "mat3")) else a
        for fld, _rows, sentence in binary_problems(st, t, sq, arrs):
            raise _bad(f"{sname}.{fld}", sentence, where)
        for name, a in arrs.items():
            if spec[name][0].kind == "bool":
                a = a.view(bool)
            cols[name] = a if arrays else a.tolist()
        out.streams[sname] = Columns(sname, st, t if arrays else t.tolist(), sq if arrays else sq.tolist(), cols)
    return out


#: the streams the fast binary decoder (:func:`fast_binary`) knows by name: a vehicle's usual ones. A batch
#: naming another (a third magnetometer) goes through :func:`decode`, with the same decisions
FAST_STREAMS = ("mag/1", "mag/2", "imu", "gnss", "ins", "route", "attitude")


def looks_binary(payload: bytes) -> bool:
    """Whether ``payload`` says it is a binary batch (version 3) near its start, as :func:`decode` tells them."""
    return len(payload) > 24 and bytes(payload[:64]).find(b"\xa7version\x03") >= 0


@cache
def fast_binary() -> tuple[msgspec.msgpack.Decoder, tuple]:
    """A typed decoder of the binary batches of the usual layout, checked in compiled code: streams among
    :data:`FAST_STREAMS`, every number column as little-endian bytes, every string column one string or a list
    of strings (of its choices), required fields present, no field unknown. Anything else fails it (and goes
    through :func:`decode`). What a type cannot say is left to the caller, as :func:`decode` checks it: each
    column's byte length against ``n``, a magnetometer's sensor against its stream's name, and the values (by
    :func:`binary_problems`, as for any binary batch).

    Returns the decoder and, per stream field of its ``streams`` struct in order, ``(stream name, message type,
    ((field, bytes per row, or −1 for a string), ...))``."""
    from .streams import Finite

    specs, fields_ = [], []
    for sname in FAST_STREAMS:
        st = stream_type(sname)
        cols, lay = [], []
        for f in MESSAGES[st].fields:
            _, dt, w = _binary_spec(st)[f.name]
            if dt is not None:
                t, rb = bytes, w * (1 if dt == "u1" else 8)
            else:  # (the table's other kinds have no binary layout; none is in these streams)
                assert f.kind == "str", f"{st}.{f.name}: a kind the fast decoder does not lay out"
                one = Literal[f.choices] if f.choices else Annotated[str, msgspec.Meta(max_length=MAX_STR)]
                t, rb = Union[one, Annotated[list[one], msgspec.Meta(max_length=MAX_SAMPLES)]], -1  # noqa: UP007
            cols.append((f.name, t) if f.required else (f.name, Union[t, msgspec.UnsetType], msgspec.UNSET))  # noqa: UP007
            lay.append((f.name, rb))
        cols.sort(key=len)  # (required fields first, as a struct needs)
        order = [c[0] for c in cols]
        lay.sort(key=lambda x: order.index(x[0]))
        cols_t = msgspec.defstruct(f"fast3_{st}_cols", cols, forbid_unknown_fields=True)
        stream_t = msgspec.defstruct(f"fast3_{st}_stream", [
            ("n", Annotated[int, msgspec.Meta(ge=0, le=MAX_SAMPLES)]), ("t_s", bytes), ("seq", bytes),
            ("cols", cols_t)], forbid_unknown_fields=True)
        attr = sname.replace("/", "_")
        fields_.append((attr, Union[stream_t, msgspec.UnsetType], msgspec.UNSET))  # noqa: UP007
        specs.append((sname, st, tuple(lay)))
    streams_t = msgspec.defstruct("fast3_streams", fields_, forbid_unknown_fields=True,
                                  rename={a: n for (a, _, _), n in zip(fields_, FAST_STREAMS, strict=True)})
    env = msgspec.defstruct("fast3_envelope", [
        ("type", Literal["batch"]), ("version", Literal[BINARY_VERSION]),
        ("vehicle", Annotated[str, msgspec.Meta(max_length=MAX_STR)]), ("t_s", Finite),
        ("seq", Annotated[int, msgspec.Meta(ge=0)]), ("streams", streams_t)])
    return msgspec.msgpack.Decoder(env), tuple(specs)


def binary_problems(msg_type: str, t_s: np.ndarray, seq: np.ndarray, cols: dict[str, np.ndarray]
                    ) -> list[tuple[str, np.ndarray, str]]:
    """The value checks of a binary batch's columns, on any number of rows at once: ``[(field, bad rows,
    sentence)]`` for each check some row fails (``t_s`` finite, ``seq`` ≥ 0, numbers finite — NaN is a null of
    a nullable field —, bounds, booleans 0 or 1)."""
    with np.errstate(all="ignore"):
        return _binary_problems(msg_type, t_s, seq, cols)


def _binary_problems(msg_type: str, t_s: np.ndarray, seq: np.ndarray, cols: dict[str, np.ndarray]
                     ) -> list[tuple[str, np.ndarray, str]]:
    out = []
    if t_s.size and not math.isfinite(float(np.add.reduce(t_s))):
        out.append(("t_s", ~np.isfinite(t_s), "must be finite numbers"))
    if seq.size and int(seq.min()) < 0:
        out.append(("seq", seq < 0, "must be integers ≥ 0"))
    spec = _binary_spec(msg_type)
    for name, a in cols.items():
        f, dt, w = spec[name]
        if not a.size:
            continue
        rows = a if a.ndim == 1 else a.reshape(a.shape[0], -1)
        if dt == "<f8":
            if not math.isfinite(float(np.add.reduce(rows, axis=None))):
                bad = np.isinf(rows) if f.nullable else ~np.isfinite(rows)
                bad = bad if bad.ndim == 1 else bad.any(axis=1)
                if bad.any():
                    out.append((name, bad, "must be finite numbers" + (" (or NaN for null)" if f.nullable else "")))
            if f.lo is not None or f.hi is not None:
                with np.errstate(invalid="ignore"):
                    lo = (rows < f.lo) if f.lo is not None else np.zeros(rows.shape, bool)
                    hi = (rows > f.hi) if f.hi is not None else np.zeros(rows.shape, bool)
                lo = lo if lo.ndim == 1 else lo.any(axis=1)
                hi = hi if hi.ndim == 1 else hi.any(axis=1)
                if lo.any():
                    out.append((name, lo, f"must be ≥ {f.lo:g}"))
                if hi.any():
                    out.append((name, hi, f"must be ≤ {f.hi:g}"))
        elif f.kind == "bool":
            bad = rows > 1
            if bad.any():
                out.append((name, bad if bad.ndim == 1 else bad.any(axis=1), "must be booleans (bytes 0 or 1)"))
        elif dt == "<i8":
            lo = (rows < f.lo) if f.lo is not None else np.zeros(rows.shape, bool)
            hi = (rows > f.hi) if f.hi is not None else np.zeros(rows.shape, bool)
            if lo.any():
                out.append((name, lo, f"must be ≥ {f.lo:g}"))
            if hi.any():
                out.append((name, hi, f"must be ≤ {f.hi:g}"))
    return out


def decode(payload: bytes, where: str = "", check: bool = True, arrays: bool = False,
           deferred: bool = False) -> Batch:
    """Decode and check a batch; raise :class:`SchemaError` naming the stream and field that is wrong.

    ``check=False`` (a trusted ``clean/batch`` from ingest) reads the structure only. A valid batch is decoded
    in one typed pass (about 4 µs for a vehicle's 50 ms window against 13 µs decoding then converting); one
    that fails it goes through the checking path, which finds the field and says what is wrong. A binary batch
    (version 3) has its columns checked whole; with ``arrays`` they stay numpy arrays over the payload, else
    they become lists as version 2's; with ``deferred`` its streams are :class:`RawColumns` whose values the
    caller checks (ingest's frames: a window at once).
    """
    if isinstance(payload, (bytes, bytearray, memoryview)) and looks_binary(payload):
        return _decode_binary(bytes(payload), where, arrays, deferred)
    if check and isinstance(payload, (bytes, bytearray, memoryview)) and len(payload):
        try:
            return _decode_typed(payload)
        except _Slow:
            pass
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) == 0:
        raise _bad("<payload>", "is empty or not bytes", where)
    if len(payload) > 64 * 1024 * 1024:
        raise _bad("<payload>", f"is {len(payload)} bytes (max 64 MiB)", where)
    m = decode_map(payload, where, "batch")
    if m.get("type") != "batch":
        raise _bad("type", f"must be 'batch' on this key, got {str(m.get('type'))[:64]!r}", where)
    ver = m.get("version")
    if type(ver) is not int or ver not in VERSIONS:
        raise _bad("version", f"is {str(ver)[:20]}; this decoder reads batch versions {VERSION} (lists) and "
                   f"{BINARY_VERSION} (binary columns)", where)
    if ver == BINARY_VERSION:
        return _decode_binary(bytes(payload), where, arrays, deferred)
    vehicle, t_s, seq = m.get("vehicle"), m.get("t_s"), m.get("seq")
    if not isinstance(vehicle, str) or len(vehicle) > MAX_STR:
        raise _bad("vehicle", "must be a string", where)
    if type(t_s) not in (int, float) or not math.isfinite(t_s):
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
        if check:
            try:
                s = msgspec.convert(body, _stream_struct(st), strict=True)
            except msgspec.ValidationError as e:
                raise _bad(_where_in(e, sname), f"is not valid: {e}", where) from None
            n = s.n
            cols = {k: getattr(s.cols, k) for k in s.cols.__struct_fields__
                    if getattr(s.cols, k) is not msgspec.UNSET}
            ts, sq = s.t_s, s.seq
        else:
            n, ts, sq, cols = body.get("n"), body.get("t_s"), body.get("seq"), body.get("cols")
            if type(n) is not int or type(ts) is not list or type(sq) is not list or type(cols) is not dict:
                raise _bad(sname, "must be a map with n, t_s, seq and cols", where)
        if len(ts) != n or len(sq) != n:
            raise _bad(f"{sname}.t_s", f"t_s and seq must hold n = {n} values", where)
        for k, v in cols.items():
            if not isinstance(v, str) and (not isinstance(v, list) or len(v) != n):
                raise _bad(f"{sname}.{k}", f"must hold n = {n} values", where)
        if check and st == "mag":
            sensor = cols.get("sensor")
            want = sname.partition("/")[2]
            if (isinstance(sensor, str) and sensor != want) or (isinstance(sensor, list) and any(x != want for x in sensor)):
                raise _bad(f"{sname}.sensor", f"must be {want!r} (the stream's sensor)", where)
        out.streams[sname] = Columns(sname, st, ts, sq, cols)
    return out


def _plain_col(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, str):
        return v
    return list(v)


def encode(vehicle: str, seq: int, streams: dict[str, Columns | dict], binary: bool = False) -> bytes:
    """Encode a batch. ``streams`` maps stream names to :class:`Columns` or to dicts with ``t_s``, ``seq``
    and ``cols`` (lists or numpy arrays); empty streams are left out. ``binary``: version 3 (numeric columns
    as little-endian bytes)."""
    if binary:
        return _encode_binary(vehicle, seq, streams)
    body = {}
    t_max = float("-inf")
    for sname, c in streams.items():
        if isinstance(c, Columns):
            t, s, cols = c.t_s, c.seq, c.cols
        else:
            t, s, cols = c["t_s"], c["seq"], c["cols"]
        t = _plain_col(t)
        n = len(t)
        if n == 0:
            continue
        t_max = max(t_max, max(t))
        stream_type(sname)
        body[sname] = {"n": n, "t_s": t, "seq": _plain_col(s), "cols": {k: _plain_col(v) for k, v in cols.items()}}
    return _enc.encode({"type": "batch", "version": VERSION, "vehicle": vehicle,
                        "t_s": t_max if body else 0.0, "seq": int(seq), "streams": body})


def _encode_binary(vehicle: str, seq: int, streams: dict[str, Columns | dict]) -> bytes:
    from .frame import _bin_col

    body = {}
    t_max = float("-inf")
    for sname, c in streams.items():
        if isinstance(c, Columns):
            t, s, cols = c.t_s, c.seq, c.cols
        else:
            t, s, cols = c["t_s"], c["seq"], c["cols"]
        t = np.ascontiguousarray(t, "<f8")
        n = t.shape[0]
        if n == 0:
            continue
        t_max = max(t_max, float(t.max()))
        st = stream_type(sname)
        fields = {f.name: f for f in MESSAGES[st].fields}
        body[sname] = {"n": n, "t_s": t.tobytes(), "seq": np.ascontiguousarray(s, "<i8").tobytes(),
                       "cols": {k: _bin_col(v, fields[k]) for k, v in cols.items() if k in fields}}
    return _enc.encode({"type": "batch", "version": BINARY_VERSION, "vehicle": vehicle,
                        "t_s": t_max if body else 0.0, "seq": int(seq), "streams": body})


def concat(parts: list[Columns]) -> Columns:
    """Samples of one stream from several batches or singles, in the given order."""
    first = parts[0]
    if len(parts) == 1:
        return first
    cols: dict[str, Any] = {}
    for k, v0 in first.cols.items():
        vals = [p.cols.get(k) for p in parts]
        if isinstance(v0, str) and all(v == v0 for v in vals):
            cols[k] = v0
        else:
            merged: list = []
            for p, v in zip(parts, vals, strict=True):
                merged.extend([v] * p.n if isinstance(v, str) else v)
            cols[k] = merged
    t: list = []
    s: list = []
    for p in parts:
        t.extend(p.t_s)
        s.extend(p.seq)
    return Columns(first.name, first.msg_type, t, s, cols)


def from_message(msg: dict) -> Columns:
    """One decoded v1 sample as a one-sample column set (for ingest's window of singles)."""
    name = f"mag/{msg['sensor']}" if msg["type"] == "mag" else msg["type"]
    cols = {f.name: (msg[f.name] if f.kind == "str" and isinstance(msg[f.name], str) else [msg[f.name]])
            for f in MESSAGES[msg["type"]].fields if f.name in msg}
    return Columns(name, msg["type"], [msg["t_s"]], [msg["seq"]], cols)


def stream_name(info: Any) -> str:
    """The name inside a batch of a per-stream key (parsed): raw/mag/1 → ``mag/1``, clean/imu → ``imu``."""
    return "/".join(info.rest)


@lru_cache(maxsize=keys.KEY_CACHE)
def stream_key(kind: str, vehicle: str, name: str) -> str:
    """The per-stream key of a stream inside a batch: ``(clean, car-1, mag/1)`` → magmesh/car-1/clean/mag/1."""
    head, _, sensor = name.partition("/")
    if kind == "raw":
        return keys.raw_mag(vehicle, sensor) if head == "mag" else getattr(keys, f"raw_{head}")(vehicle)
    return keys.clean_mag(vehicle, sensor) if head == "mag" else getattr(keys, f"clean_{head}")(vehicle)


def json_schema() -> dict:
    """JSON Schema of the batch envelope (each stream's columns: arrays of the v1 field types)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"magmesh batch v{VERSION}",
        "description": "many samples of one vehicle's streams as column arrays",
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
                               "t_s": {"type": "array", "items": {"type": "number"}},
                               "seq": {"type": "array", "items": {"type": "integer", "minimum": 0},
                                       "description": "each sample's seq on its own stream"},
                               "cols": {"type": "object"}}}},
        },
    }
