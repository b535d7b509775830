"""Recordings of magmesh traffic as MCAP files, and their replay schedule.

MCAP (https://mcap.dev) is the log container of ROS 2 and Foxglove. A magmesh recording holds:

- one *channel per key* (topic = the Zenoh key), message encoding ``msgpack`` (the wire bytes,
  unchanged), channel metadata ``magmesh_type`` / ``vehicle`` / ``kind``;
- one *schema per message type* (``magmesh.<type>`` in ``jsonschema`` encoding, generated from the
  contract in :mod:`schemas.messages`), so any MCAP tool can tell what the bytes mean; payloads that do
  not decode as a magmesh message are kept too, on a channel without schema, and counted;
- ``log_time`` = receive time (ns since the Unix epoch), ``publish_time`` = the message's sample time
  ``t_s`` (ns, clamped at 0; the exact float stays in the payload), ``sequence`` = the message ``seq``
  (mod 2³²);
- a ``magmesh_cli.recording`` metadata record (who recorded what, the key expressions, the counts).

Pure Python (mcap, msgpack): no Zenoh here. :func:`replay` drives any ``publish(key, payload)``
function with the original timing, scaled by ``rate`` (0 = as fast as possible).
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import msgpack
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from schemas import keys, messages

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "magmesh."
METADATA_NAME = "magmesh_cli.recording"
#: pseudo message type of service liveliness events (token appeared / disappeared); not replayed
LIVELINESS = "liveliness"
LIVELINESS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": f"{SCHEMA_PREFIX}{LIVELINESS}",
    "description": "a magmesh service liveliness token appeared (alive=true) or disappeared (msgpack map)",
    "type": "object",
    "properties": {"alive": {"type": "boolean"}, "token": {"type": "string"}},
    "required": ["alive", "token"],
}
PROFILE = "magmesh"

_JSON_KIND = {
    "str": {"type": "string"},
    "int": {"type": "integer"},
    "float": {"type": "number"},
    "bool": {"type": "boolean"},
    "vec3": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "mat3": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
    "floats": {"type": "array", "items": {"type": "number"}},
    "bools": {"type": "array", "items": {"type": "boolean"}},
    "strs": {"type": "array", "items": {"type": "string"}},
    "map": {"type": "object"},
}


def json_schema(msg_type: str) -> dict:
    """JSON Schema of one magmesh message type: the streams table's (:func:`schemas.streams.json_schema`,
    generated from the contract), titled for MCAP."""
    from schemas import streams

    if msg_type in ("batch", "frame"):  # the envelopes of contract v2 / v3
        js = streams.json_schema(msg_type)
        return {**js, "title": f"{SCHEMA_PREFIX}{js['title'].removeprefix('magmesh ')}",
                "description": js["description"] + " (msgpack map on the wire)"}
    mt = messages.MESSAGES[msg_type]
    return {**streams.json_schema(msg_type), "title": f"{SCHEMA_PREFIX}{mt.name} v{mt.version}",
            "description": mt.doc + " (msgpack map on the wire)"}


def sample_time_ns(t_s: float | None) -> int:
    """MCAP ``publish_time`` for a sample time: ns, clamped to ≥ 0 (MCAP times are unsigned)."""
    if t_s is None or not math.isfinite(t_s) or t_s <= 0:
        return 0
    return min(int(round(t_s * 1e9)), 2**64 - 1)


# ---- key expressions --------------------------------------------------------------------------


def _chunk_matches(pattern: str, chunk: str) -> bool:
    if pattern == "*":
        return True
    if "$*" not in pattern:
        return pattern == chunk
    parts = pattern.split("$*")
    if not chunk.startswith(parts[0]) or not chunk.endswith(parts[-1]):
        return False
    pos = len(parts[0])
    end = len(chunk) - len(parts[-1])
    for mid in parts[1:-1]:
        i = chunk.find(mid, pos, end)
        if i < 0:
            return False
        pos = i + len(mid)
    return pos <= end


def keyexpr_matches(expr: str, key: str) -> bool:
    """Whether a concrete key matches a Zenoh key expression (``*``, ``**``, ``$*``)."""
    pat = expr.split("/")
    chunks = key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(chunks)
        if pat[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(chunks) + 1))
        return j < len(chunks) and _chunk_matches(pat[i], chunks[j]) and match(i + 1, j + 1)

    return match(0, 0)


def matches_any(exprs: Sequence[str] | None, key: str) -> bool:
    return not exprs or any(keyexpr_matches(e, key) for e in exprs)


# ---- writing ----------------------------------------------------------------------------------


#: message types several publishers share a key for (each with its own seq): no seq-gap counting
MULTI_PUBLISHER_TYPES = frozenset({"reject"})
#: a seq jump larger than this is not counted as missed samples
SEQ_GAP_MAX = 100_000


@dataclass
class RecordCounts:
    """What a recording saw, per key: every received sample is counted in exactly one bucket."""

    written: Counter = field(default_factory=Counter)  # valid magmesh messages
    unvalidated: Counter = field(default_factory=Counter)  # kept, but did not decode as a magmesh message
    skipped: Counter = field(default_factory=Counter)  # not written (e.g. delete samples), with reason keys
    liveliness: int = 0  # service appear/disappear events
    #: samples never received: gaps in a key's seq (lost on the way, e.g. while the link reconnected)
    missed: Counter = field(default_factory=Counter)

    @property
    def total(self) -> int:
        return sum(self.written.values()) + sum(self.unvalidated.values()) + sum(self.skipped.values())

    def as_dict(self) -> dict:
        return {
            "written": int(sum(self.written.values())),
            "unvalidated": int(sum(self.unvalidated.values())),
            "skipped": int(sum(self.skipped.values())),
            "liveliness": int(self.liveliness),
            "keys": len(set(self.written) | set(self.unvalidated)),
            "per_key": {k: int(v) for k, v in sorted((self.written + self.unvalidated).items())},
            "skipped_per_reason": {k: int(v) for k, v in sorted(self.skipped.items())},
            "missed": int(sum(self.missed.values())),
            "missed_per_key": {k: int(v) for k, v in sorted(self.missed.items())},
        }


def open_mcap(path: str | Path, compression: str = "zstd") -> tuple[Path, BinaryIO, Writer]:
    """A new MCAP file (its folder made if needed), started with magmesh's profile: (path, file, writer)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "wb")
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
    writer = Writer(fh, compression=comp)
    writer.start(profile=PROFILE, library="magmesh")
    return path, fh, writer


def _decode_any(key: str, payload: bytes) -> dict | None:
    """A received payload as a message (header fields at least), or None when it is not a valid one: a v1
    message, a batch (contract v2, binary form v3) or a fleet frame (v3) — checked by their own decoders."""
    try:
        return messages.decode(payload, where=key)
    except messages.SchemaError:
        pass
    try:
        info = keys.parse(key)
    except keys.KeyError_:
        return None
    from schemas import batch as batches
    from schemas import frame as fleetframe

    try:
        if info.kind == keys.FLEET:
            f = fleetframe.decode(payload, where=key)
            return {"type": "frame", "version": fleetframe.VERSION, "vehicle": "", "t_s": f.t_s, "seq": f.seq}
        if info.kind in ("raw", "clean") and info.rest == (keys.BATCH,):
            b = batches.decode(payload, where=key)
            return {"type": "batch", "version": batches.VERSION, "vehicle": b.vehicle, "t_s": b.t_s, "seq": b.seq}
    except messages.SchemaError:
        return None
    return None


class RecordingWriter:
    """Write magmesh samples to an MCAP file (see the module doc for the layout).

    ``write(key, payload, receive_ns)`` stores the payload bytes as received; use as a context manager
    or call :meth:`close` (which also writes the counts into the file's metadata).
    """

    def __init__(self, path: str | Path, info: dict | None = None, compression: str = "zstd"):
        self.path, self._fh, self._writer = open_mcap(path, compression)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str | None], int] = {}
        self.counts = RecordCounts()
        self.info = dict(info or {})
        self.first_receive_ns: int | None = None
        self.last_receive_ns: int | None = None
        self._closed = False
        self._last_seq: dict[str, int] = {}

    def _schema_id(self, msg_type: str) -> int:
        sid = self._schemas.get(msg_type)
        if sid is None:
            js = LIVELINESS_SCHEMA if msg_type == LIVELINESS else json_schema(msg_type)
            data = json.dumps(js, ensure_ascii=False).encode()
            sid = self._writer.register_schema(f"{SCHEMA_PREFIX}{msg_type}", SCHEMA_ENCODING, data)
            self._schemas[msg_type] = sid
        return sid

    def _channel_id(self, key: str, msg_type: str | None) -> int:
        ck = (key, msg_type)
        cid = self._channels.get(ck)
        if cid is None:
            meta = {"magmesh_type": msg_type or ""}
            try:
                info = keys.parse(key)
                meta.update(vehicle=info.vehicle, kind=info.kind)
            except keys.KeyError_:
                meta.update(vehicle="", kind="")
            sid = self._schema_id(msg_type) if msg_type else 0
            cid = self._writer.register_channel(key, MESSAGE_ENCODING, sid, meta)
            self._channels[ck] = cid
        return cid

    def write(self, key: str, payload: bytes, receive_ns: int | None = None, msg: dict | None = None) -> bool:
        """Store one received sample; return True when it decoded as a valid magmesh message.

        Payloads that do not decode are stored on a schema-less channel and counted as *unvalidated*.
        """
        if self._closed:
            raise RuntimeError(f"recording {self.path} is closed")
        receive_ns = time.time_ns() if receive_ns is None else int(receive_ns)
        payload = bytes(payload)
        if msg is None:
            msg = _decode_any(key, payload)
        msg_type = msg["type"] if msg is not None else None
        cid = self._channel_id(key, msg_type)
        t_s = msg["t_s"] if msg is not None else None
        seq = int(msg["seq"]) % (2**32) if msg is not None else 0
        self._writer.add_message(cid, log_time=receive_ns, data=payload, publish_time=sample_time_ns(t_s),
                                 sequence=seq)
        if msg is not None and msg_type not in MULTI_PUBLISHER_TYPES:
            # a gap in seq: samples published that never arrived (counted, never silent); a jump back (a
            # restarted publisher) or beyond SEQ_GAP_MAX (a forged seq) starts the count again
            last = self._last_seq.get(key)
            sq = int(msg["seq"])
            if last is not None and last + 1 < sq <= last + SEQ_GAP_MAX:
                self.counts.missed[key] += sq - last - 1
            self._last_seq[key] = sq
        (self.counts.written if msg is not None else self.counts.unvalidated)[key] += 1
        if self.first_receive_ns is None:
            self.first_receive_ns = receive_ns
        self.last_receive_ns = receive_ns
        return msg is not None

    def write_message(self, key: str, msg: dict, receive_ns: int | None = None) -> None:
        """Encode (validating) and store one message dict."""
        self.write(key, messages.encode(msg), receive_ns, msg=messages.validate(msg, where=key))

    def write_liveliness(self, token: str, alive: bool, receive_ns: int | None = None) -> None:
        """Store a service liveliness event (token ``magmesh/svc/{role}/{instance}`` appeared or went)."""
        receive_ns = time.time_ns() if receive_ns is None else int(receive_ns)
        cid = self._channel_id(token, LIVELINESS)
        payload = msgpack.packb({"alive": bool(alive), "token": token}, use_bin_type=True)
        self._writer.add_message(cid, log_time=receive_ns, data=payload, publish_time=receive_ns, sequence=0)
        self.counts.liveliness += 1

    def skip(self, key: str, reason: str) -> None:
        """Count a sample that was received but not stored (never dropped silently)."""
        self.counts.skipped[f"{reason}: {key}"] += 1

    def close(self) -> dict:
        """Finish the file (summary, index, metadata with counts); return the counts."""
        if self._closed:
            return self.counts.as_dict()
        self._closed = True
        meta = {
            "format": "magmesh recording 1",
            "message_encoding": MESSAGE_ENCODING,
            "log_time": "receive time, ns since the Unix epoch",
            "publish_time": "sample time t_s, ns (clamped at 0)",
            **{k: v if isinstance(v, str) else json.dumps(v) for k, v in self.info.items()},
            "counts": json.dumps(self.counts.as_dict()),
        }
        self._writer.add_metadata(METADATA_NAME, meta)
        self._writer.finish()
        self._fh.close()
        return self.counts.as_dict()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- reading ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Record:
    """One stored sample."""

    key: str
    msg_type: str | None  # None: the payload did not decode when recorded
    payload: bytes
    receive_ns: int  # MCAP log_time
    sample_ns: int  # MCAP publish_time

    def decode(self) -> dict:
        """The message dict (validated; raises :class:`schemas.messages.SchemaError`)."""
        return messages.decode(self.payload, where=self.key)


def read_records(path: str | Path, key_exprs: Sequence[str] | None = None,
                 liveliness: bool = False) -> Iterator[Record]:
    """The samples of a recording in receive-time order, optionally only keys matching ``key_exprs``.

    Service liveliness events are left out unless ``liveliness`` is true.
    """
    selected: dict[int, bool] = {}  # per channel: one key-expression test per channel, not per message
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            ok = selected.get(channel.id)
            if ok is None:
                # Foxglove views in a json recording (magmesh_cli.foxglove_mcap) are not mesh traffic
                ok = selected[channel.id] = (channel.metadata.get("foxglove_derived") != "true"
                                             and matches_any(key_exprs, channel.topic))
            if not ok:
                continue
            msg_type = channel.metadata.get("magmesh_type") or None
            if msg_type is None and schema is not None and schema.name.startswith(SCHEMA_PREFIX):
                msg_type = schema.name[len(SCHEMA_PREFIX):]
            if msg_type == LIVELINESS and not liveliness:
                continue
            data = bytes(message.data)
            if channel.message_encoding == "json":  # a json recording: back to the wire encoding
                data = msgpack.packb(json.loads(data), use_bin_type=True)
            yield Record(channel.topic, msg_type, data, int(message.log_time), int(message.publish_time))


def load_messages(path: str | Path, key_exprs: Sequence[str] | None = None,
                  counts: Counter | None = None, progress: bool = False) -> list[tuple[str, dict]]:
    """Decoded ``(key, message)`` pairs of a recording; undecodable payloads are counted in ``counts``."""
    out: list[tuple[str, dict]] = []
    records: Iterable[Record] = read_records(path, key_exprs)
    if progress:
        from tqdm import tqdm

        records = tqdm(records, total=summarize(path)["messages"], unit="msg", desc=f"reading {Path(path).name}")
    for rec in records:
        try:
            out.append((rec.key, rec.decode()))
        except messages.SchemaError:
            if counts is not None:
                counts[f"undecodable: {rec.key}"] += 1
    return out


def load_liveliness(path: str | Path) -> list[tuple[float, str, bool]]:
    """Service liveliness events ``(receive time s since the epoch, token key, alive)``."""
    out = []
    for rec in read_records(path, liveliness=True):
        if rec.msg_type == LIVELINESS:
            ev = msgpack.unpackb(rec.payload, raw=False)
            out.append((rec.receive_ns / 1e9, rec.key, bool(ev.get("alive"))))
    return out


def summarize(path: str | Path) -> dict:
    """Keys, counts, time span and recording metadata of a file (read from its summary section)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summ = reader.get_summary()
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    per_key: dict[str, int] = {}
    n_live = 0
    start = end = None
    if summ is not None and summ.statistics is not None:
        st = summ.statistics
        for cid, n in st.channel_message_counts.items():
            ch = summ.channels[cid]
            if ch.metadata.get("foxglove_derived") == "true":
                continue
            if ch.metadata.get("magmesh_type") == LIVELINESS:
                n_live += int(n)
                continue
            per_key[ch.topic] = per_key.get(ch.topic, 0) + int(n)
        if st.message_count:
            start, end = st.message_start_time, st.message_end_time
    return {
        "path": str(path),
        "messages": int(sum(per_key.values())),
        "keys": dict(sorted(per_key.items())),
        "start_ns": start,
        "end_ns": end,
        "duration_s": (end - start) / 1e9 if start is not None else 0.0,
        "liveliness_events": n_live,
        "metadata": meta.get(METADATA_NAME, {}),
    }


def to_json_mcap(src: str | Path, dst: str | Path, key_exprs: Sequence[str] | None = None) -> dict:
    """Copy a recording with JSON-encoded messages (for viewers without msgpack, e.g. Foxglove).

    Same channels, schemas, log and publish times; undecodable payloads and liveliness events are left out
    and counted. Returns ``{"written": n, "left_out": m}``.
    """
    n = left = 0
    with open(dst, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="", library="magmesh")
        schemas_: dict[str, int] = {}
        chans: dict[str, int] = {}
        for rec in read_records(src, key_exprs):
            try:
                msg = rec.decode()
            except messages.SchemaError:
                left += 1
                continue
            t = msg["type"]
            if t not in schemas_:
                schemas_[t] = w.register_schema(f"{SCHEMA_PREFIX}{t}", SCHEMA_ENCODING,
                                                json.dumps(json_schema(t), ensure_ascii=False).encode())
            if rec.key not in chans:
                chans[rec.key] = w.register_channel(rec.key, "json", schemas_[t], {"magmesh_type": t})
            w.add_message(chans[rec.key], log_time=rec.receive_ns, data=json.dumps(msg).encode(),
                          publish_time=rec.sample_ns, sequence=int(msg["seq"]) % (2**32))
            n += 1
        w.finish()
    return {"written": n, "left_out": left}


# ---- remapping and replay ----------------------------------------------------------------------


@dataclass(frozen=True)
class Remap:
    """Rename keys on replay.

    ``old=new`` where both are vehicle ids renames the vehicle (key chunk and the message's ``vehicle``
    field); where they contain ``/`` it replaces a chunk-aligned key prefix, e.g.
    ``magmesh/car-1/clean=magmesh/car-9/clean``.
    """

    old: str
    new: str

    @classmethod
    def parse(cls, text: str) -> Remap:
        if text.count("=") != 1:
            raise ValueError(f"remap {text!r} must be old=new")
        old, new = (s.strip().rstrip("/") for s in text.split("="))
        if not old or not new:
            raise ValueError(f"remap {text!r} must be old=new with both sides non-empty")
        if ("/" in old) != ("/" in new):
            raise ValueError(f"remap {text!r}: map a vehicle id to a vehicle id or a key prefix to a key prefix")
        if "/" not in old:
            keys.check_id(old)
            keys.check_id(new)
        return cls(old, new)

    @property
    def is_vehicle(self) -> bool:
        return "/" not in self.old

    def apply_key(self, key: str) -> str:
        if self.is_vehicle:
            parts = key.split("/")
            if len(parts) > 2 and parts[0] == keys.ROOT and parts[1] == self.old:
                parts[1] = self.new
                return "/".join(parts)
            return key
        if key == self.old or key.startswith(self.old + "/"):
            return self.new + key[len(self.old):]
        return key


def remap_sample(key: str, payload: bytes, remaps: Sequence[Remap]) -> tuple[str, bytes]:
    """Apply remaps to a key and, when the vehicle changed, to the payload's ``vehicle`` field."""
    new_key = key
    for r in remaps:
        new_key = r.apply_key(new_key)
    if new_key == key:
        return key, payload
    try:
        new_vehicle = keys.parse(new_key).vehicle
    except keys.KeyError_ as e:
        raise ValueError(f"remapping {key!r} gave {new_key!r}, which is not a magmesh key: {e}") from None
    try:
        msg = msgpack.unpackb(payload, raw=False)
    except Exception:
        return new_key, payload
    if isinstance(msg, dict) and new_vehicle and msg.get("vehicle") != new_vehicle:
        msg["vehicle"] = new_vehicle
        payload = msgpack.packb(msg, use_bin_type=True)
    return new_key, payload


def time_window(records: Iterable[Record], start_ns: int, start_s: float = 0.0, end_s: float = 0.0) -> Iterator[Record]:
    """Records received in [start_s, end_s) seconds after ``start_ns`` (``end_s`` 0: to the end)."""
    lo = start_ns + int(round(start_s * 1e9))
    hi = start_ns + int(round(end_s * 1e9)) if end_s > 0 else None
    for r in records:
        if r.receive_ns >= lo and (hi is None or r.receive_ns < hi):
            yield r


def parse_rate(text: str | float) -> float:
    """``--rate``: a positive speed factor (1.0 = real time) or ``max`` (0: as fast as possible)."""
    if isinstance(text, str) and text.strip().lower() in ("max", "inf", "0"):
        return 0.0
    rate = float(text)
    if not math.isfinite(rate) or rate < 0:
        raise ValueError(f"rate must be a positive number or 'max', got {text!r}")
    return rate


@dataclass
class ReplayStats:
    published: Counter = field(default_factory=Counter)
    wall_s: float = 0.0
    recorded_span_s: float = 0.0
    max_late_s: float = 0.0  # largest lag behind the schedule

    def as_dict(self) -> dict:
        return {
            "published": int(sum(self.published.values())),
            "keys": len(self.published),
            "wall_s": float(self.wall_s),
            "recorded_span_s": float(self.recorded_span_s),
            "max_late_s": float(self.max_late_s),
            "per_key": {k: int(v) for k, v in sorted(self.published.items())},
        }


def replay(
    records: Iterable[Record],
    publish: Callable[[str, bytes], None],
    rate: float = 1.0,
    remaps: Sequence[Remap] = (),
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    should_stop: Callable[[], bool] = lambda: False,
    on_progress: Callable[[int], None] | None = None,
) -> ReplayStats:
    """Publish recorded samples with their original receive-time spacing divided by ``rate``.

    ``rate`` 0 publishes as fast as ``publish`` returns. Samples are never skipped to catch up: when
    publishing falls behind, the lag is reported as ``max_late_s``.
    """
    stats = ReplayStats()
    t0_rec: int | None = None
    start = t0_wall = clock()
    last_rec = 0
    for rec in records:
        if should_stop():
            break
        if t0_rec is None:
            # the schedule starts when the first sample is in hand (reading a file has a start-up cost)
            t0_rec = rec.receive_ns
            t0_wall = clock()
        last_rec = rec.receive_ns
        if rate > 0:
            due = t0_wall + (rec.receive_ns - t0_rec) / 1e9 / rate
            now = clock()
            if due > now:
                sleep(due - now)
            else:
                stats.max_late_s = max(stats.max_late_s, now - due)
        key, payload = remap_sample(rec.key, rec.payload, remaps)
        publish(key, payload)
        stats.published[key] += 1
        if on_progress is not None:
            on_progress(1)
    stats.wall_s = clock() - start
    stats.recorded_span_s = (last_rec - t0_rec) / 1e9 if t0_rec is not None else 0.0
    return stats
