"""MCAP recordings that Foxglove opens as they are: json messages with jsonschema schemas.

:class:`FoxgloveMcapWriter` has the interface of :class:`magmesh_cli.recording.RecordingWriter` (``write``,
``write_message``, ``write_liveliness``, ``skip``, ``close``, ``counts``, ``info``), so ``magmesh record
--encoding json`` uses it in place of the default exact-bytes msgpack writer. A file holds:

- one channel per magmesh key (topic = the key, message encoding ``json``, schema ``magmesh.<type>`` in
  ``jsonschema`` encoding, channel metadata ``magmesh_type`` / ``vehicle`` / ``kind``), each message the
  decoded magmesh message as JSON;
- the Foxglove well-known channels of :mod:`magmesh_cli.foxglove_types` (``/<vehicle>/log`` foxglove.Log,
  ``/<vehicle>/gnss/fix`` and ``/<vehicle>/geomag/fix`` foxglove.LocationFix, ``/<vehicle>/pose``
  foxglove.PoseInFrame, ``/tf`` foxglove.FrameTransform), channel metadata ``foxglove_derived = true``
  (readers of magmesh recordings skip them: they are views, not mesh traffic);
- payloads that do not decode as magmesh messages on a schema-less channel, message encoding
  ``application/octet-stream``, the bytes unchanged (kept and counted as *unvalidated*, never lost);
- the same ``magmesh_cli.recording`` metadata as a msgpack recording, with ``message_encoding = json``.

A batch (contract v2) is stored as its samples, each on its stream's own key (a replay publishes them as
single samples). ``log_time`` is the receive time, ``publish_time`` the sample time, as in msgpack recordings. Replaying a
json recording re-encodes each message as msgpack (:func:`magmesh_cli.recording.read_records`); JSON keeps
floats exactly (shortest repr round trip), so the replayed messages equal the recorded ones.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from schemas import keys, messages

from .foxglove_types import FOXGLOVE_SCHEMAS, FoxgloveConverter, magmesh_json_schema, to_json_bytes
from .recording import (
    LIVELINESS,
    LIVELINESS_SCHEMA,
    METADATA_NAME,
    RecordCounts,
    open_mcap,
    sample_time_ns,
)
from .tap import decode_samples

MESSAGE_ENCODING = "json"
RAW_ENCODING = "application/octet-stream"
DERIVED_META = "foxglove_derived"


class FoxgloveMcapWriter:
    """Write magmesh samples to a json MCAP with Foxglove types (see the module doc)."""

    def __init__(self, path: str | Path, info: dict | None = None, compression: str = "zstd",
                 converter: FoxgloveConverter | None = None):
        self.path, self._fh, self._writer = open_mcap(path, compression)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str | None], int] = {}
        self.conv = converter or FoxgloveConverter()
        self.counts = RecordCounts()
        self.derived = 0
        self.info = dict(info or {})
        self._closed = False
        self._final: dict = {}

    def _schema_id(self, name: str, schema: dict) -> int:
        sid = self._schemas.get(name)
        if sid is None:
            sid = self._schemas[name] = self._writer.register_schema(
                name, "jsonschema", json.dumps(schema, ensure_ascii=False).encode())
        return sid

    def _channel_id(self, topic: str, msg_type: str | None, derived: str | None = None) -> int:
        ck = (topic, derived or msg_type)
        cid = self._channels.get(ck)
        if cid is not None:
            return cid
        if derived is not None:
            sid = self._schema_id(derived, FOXGLOVE_SCHEMAS[derived])
            cid = self._writer.register_channel(topic, MESSAGE_ENCODING, sid, {DERIVED_META: "true"})
        else:
            meta = {"magmesh_type": msg_type or ""}
            try:
                info = keys.parse(topic)
                meta.update(vehicle=info.vehicle, kind=info.kind)
            except keys.KeyError_:
                meta.update(vehicle="", kind="")
            if msg_type is None:
                cid = self._writer.register_channel(topic, RAW_ENCODING, 0, meta)
            else:
                schema = LIVELINESS_SCHEMA if msg_type == LIVELINESS else magmesh_json_schema(msg_type)
                sid = self._schema_id(f"magmesh.{msg_type}", schema)
                cid = self._writer.register_channel(topic, MESSAGE_ENCODING, sid, meta)
        self._channels[ck] = cid
        return cid

    def write(self, key: str, payload: bytes, receive_ns: int | None = None, msg: dict | None = None) -> bool:
        """Store one received sample (as JSON when it decodes; a batch as its samples, each on its stream's
        key); return True when it was valid."""
        if self._closed:
            raise RuntimeError(f"recording {self.path} is closed")
        receive_ns = time.time_ns() if receive_ns is None else int(receive_ns)
        if msg is not None:
            samples = [(key, msg)]
        else:
            try:
                samples = decode_samples(key, bytes(payload))
            except (messages.SchemaError, keys.KeyError_, KeyError):
                samples = None
        if samples is None:
            self._writer.add_message(self._channel_id(key, None), log_time=receive_ns, data=bytes(payload),
                                     publish_time=0, sequence=0)
            self.counts.unvalidated[key] += 1
            return False
        for skey, m in samples:
            seq = int(m["seq"]) % (2**32)
            self._writer.add_message(self._channel_id(skey, m["type"]), log_time=receive_ns, data=to_json_bytes(m),
                                     publish_time=sample_time_ns(m["t_s"]), sequence=seq)
            self.counts.written[skey] += 1
            for out in self.conv.convert(skey, m, receive_ns):
                self._writer.add_message(self._channel_id(out.topic, None, derived=out.schema), log_time=receive_ns,
                                         data=to_json_bytes(out.msg), publish_time=receive_ns, sequence=seq)
                self.derived += 1
        return True

    def write_message(self, key: str, msg: dict, receive_ns: int | None = None) -> None:
        self.write(key, b"", receive_ns, msg=messages.validate(msg, where=key))

    def write_liveliness(self, token: str, alive: bool, receive_ns: int | None = None) -> None:
        receive_ns = time.time_ns() if receive_ns is None else int(receive_ns)
        self._writer.add_message(self._channel_id(token, LIVELINESS), log_time=receive_ns,
                                 data=to_json_bytes({"alive": bool(alive), "token": token}),
                                 publish_time=receive_ns, sequence=0)
        self.counts.liveliness += 1

    def skip(self, key: str, reason: str) -> None:
        self.counts.skipped[f"{reason}: {key}"] += 1

    def close(self) -> dict:
        if self._closed:
            return dict(self._final)
        self._closed = True
        counts = self._final = self.counts.as_dict()
        counts["foxglove_messages"] = self.derived
        counts["foxglove_skipped"] = dict(self.conv.skipped)
        meta = {
            "format": "magmesh recording 1",
            "message_encoding": MESSAGE_ENCODING,
            "log_time": "receive time, ns since the Unix epoch",
            "publish_time": "sample time t_s, ns (clamped at 0)",
            **{k: v if isinstance(v, str) else json.dumps(v) for k, v in self.info.items()},
            "counts": json.dumps(counts),
        }
        self._writer.add_metadata(METADATA_NAME, meta)
        self._writer.finish()
        self._fh.close()
        return counts

    def __enter__(self) -> FoxgloveMcapWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def export(src: str | Path, dst: str | Path, key_exprs=None, converter: FoxgloveConverter | None = None) -> dict:
    """Convert any magmesh recording (msgpack or json) to a json MCAP with Foxglove types; return the counts."""
    from .recording import read_records

    with FoxgloveMcapWriter(dst, info={"tool": "magmesh mcap to-json --foxglove", "source": str(src)},
                            converter=converter) as w:
        for rec in read_records(src, key_exprs, liveliness=True):
            if rec.msg_type == LIVELINESS:
                import msgpack

                ev = msgpack.unpackb(rec.payload, raw=False)
                w.write_liveliness(rec.key, bool(ev.get("alive")), rec.receive_ns)
            else:
                w.write(rec.key, rec.payload, rec.receive_ns)
    return w.close()
