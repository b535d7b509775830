"""The shared service runner: everything a magmesh process needs besides its own logic.

A service subclasses :class:`Service` (or :class:`SimPublisher` for a data source), declares what it
consumes and produces, and implements ``on_message``. :func:`main` does the rest:

- Zenoh configuration from the standard flags (:mod:`magmesh.zconf`);
- subscriptions received through FIFO channel handlers, drained by one reader thread each into the
  service's own bounded queue (back-pressure, never loss); the service's logic runs in one main loop
  that also publishes — nothing is called from inside a Zenoh callback;
- decoding and validation of every input; bad inputs are counted and reported on ``rejects``;
- publishers declared reliable with blocking congestion control, ``seq`` filled per key;
- a liveliness token ``magmesh/svc/{role}/{instance}`` and a status queryable ``.../status``;
- the currently raised alarms answered by query for late joiners;
- per-vehicle state created on first sample; sharding by ``--vehicles PATTERN``;
- structured logging; clean stop on SIGINT/SIGTERM within 2 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
import tomllib
import traceback
from collections import defaultdict, deque
from collections.abc import Callable, Iterator
from typing import Any

import msgpack
import numpy as np

from schemas import batch as batches
from schemas import frame as fleetframe
from schemas import keys, messages, streams
from schemas.keys import KeyInfo
from schemas.messages import SchemaError

from . import __version__, declare, zconf
from .frames import NONE as _NO_SEQ
from .frames import SeqTable, StreamKeys

#: samples a reader thread hands to the main loop at once (what has arrived, up to this many)
READ_BATCH = 64
#: queued input samples and frames the loop takes in one turn (:meth:`Runner.loop`): what waited together is handled
#: together, a key's frames as one run
DRAIN_ITEMS = 256
#: a mirrored frame kind's vehicle list is started anew once it would name more than twice the vehicles this
#: instance holds, and this many (``_mirror_rows``)
MIRROR_LIST_MIN = 64
QUEUE_CAPACITY = 65536 // READ_BATCH  # queue entries (each a batch of at most READ_BATCH samples, or a query)
ALARM_HISTORY = 64  # alarm / cal-params samples each publisher keeps for late joiners and miss recovery
_HEADER_NAMES = frozenset(("type", "version", "vehicle", "t_s", "seq"))
#: the contract's field names per message type (anything else in an input is an unknown extra field)
_KNOWN_FIELDS = {name: _HEADER_NAMES | {f.name for f in mt.fields} for name, mt in messages.MESSAGES.items()}
FIFO_CAPACITY = 4096
STOP_GRACE_S = 1.5
CAL_CONFIRM_TIMEOUT_S = 2.0  # a status query confirming cal/params waits this long; its answers count this long
CAL_REASK_S = 0.3  # a parked cal/params set (see Runner.cal_params_admit) is asked about again this often
CAL_GIVE_UP_S = 10.0  # a parked set no answer has reported this long after it came is refused (untrusted)
CAL_PARKED_MAX = 64  # parked sets per key (the oldest beyond it is refused: a flood, not a backlog)
CAL_RECENT = 16  # parameter sets a calibration instance remembers per key besides the last (cal_params_recent)

# ---- the input path's bounds (see Runner.handle_sample) ---------------------------------------
#: largest payload accepted per message type, checked before decoding (a contract-legal message is far smaller)
MAX_PAYLOAD_BYTES = {"truth": 1 << 20, "cal_params": 64 << 10, "reject": 64 << 10, "alarm": 64 << 10,
                     "batch": 16 << 20}
MAX_PAYLOAD_DEFAULT = 32 << 10
#: unknown extra fields (forward compatibility) are kept up to this many encoded bytes in all, else all dropped
MAX_EXTRA_BYTES = 1024
#: a seq jump beyond this is a re-base of the publisher's counter (counted once), not that many lost samples
SEQ_JUMP_MAX = 10_000
#: per-vehicle and per-key state is freed after this long without input (services may set ``evict_idle_s``)
EVICT_IDLE_S = 600.0
#: a fleet frame that waited longer than this in the input queue, once the stage has been handling such stale
#: input for this long already (overload: the stage stays behind), is shed: its seq is tracked and journaled as
#: usual, its rows are not handled and are counted lost as ``shed_behind``, so a stage catches up when the load
#: drops instead of working off seconds of stale input; the backlog of one stall (a slow first sample, a pause)
#: is worked off, not shed (services may set ``shed_after_s``; 0 never sheds). Ingest with fleet frames out
#: sheds a window the same way (checked and counted, not sent). Messages on per-vehicle keys (alarms, calibration
#: parameters, a v1/v2 consumer's samples) are never shed.
SHED_AFTER_S = 2.0


def shed_after_setting() -> Any:
    """The ``shed_after_s`` setting of a service that takes fleet frames (one declaration for all of them)."""
    return declare.setting(SHED_AFTER_S, "a fleet frame that waited longer than this in the input queue, once the "
                           "stage has handled such late input for this long (it stays behind: overload), is shed: "
                           "its rows counted lost as shed_behind, not handled; 0 = never shed", lo=0)
#: status replies list at most this many keys per table (the largest), plus totals over all keys
STATUS_TOP_KEYS = 50
#: the same kind of log line at most once per this many seconds (the rest are counted in the next one)
LOG_EVERY_S = 10.0
#: drop reasons that are loss: what could not be delivered or recovered. ``rejected:*`` are refusals; every
#: other reason is a skip by design (e.g. a stream not used, an alarm state unchanged)
LOST_REASONS = frozenset(("upstream_gap", "handler_error", "queue_overflow", "invalid_output",
                          "lost_during_restart", "lost_in_takeover", "shed_behind"))


_ENCODINGS: dict[str, Any] = {}
_CLEAN_BATCH = f"/clean/{keys.BATCH}"
_RAW_BATCH = f"/raw/{keys.BATCH}"
_FLEET = f"{keys.ROOT}/{keys.FLEET}/"
_ROW_ENC = None  # msgspec encoder of per-vehicle rows (publish_rows), made on first use
_ROW_TYPES: dict = {}  # a message's field names -> a msgspec struct encoding its map in that order


def _row_type(hdr: tuple):
    """The struct type whose msgpack is the map ``dict(zip(hdr, values))`` (the same bytes, built without a dict:
    a third of the time per row at 25,000 rows a second)."""
    t = _ROW_TYPES.get(hdr)
    if t is None:
        import msgspec

        t = _ROW_TYPES[hdr] = msgspec.defstruct("Row", [(h, object) for h in hdr], gc=False)
    return t


def _encoding(key: str) -> Any:
    """The Zenoh encoding of a put or reply on ``key``: ``application/msgpack;magmesh/{type}/v{version}``."""
    enc = _ENCODINGS.get(key)
    if enc is None:
        import zenoh

        try:
            name = streams.encoding_for_key(key)
        except keys.KeyError_:
            name = streams.MEDIA_TYPE  # a key outside the contract (a test's or a tool's): msgpack, no schema
        enc = zenoh.Encoding(name)
        if len(_ENCODINGS) < 65536:
            _ENCODINGS[key] = enc
    return enc


def _invalid_rows(msg_type: str, cols: dict, t_s: list, n: int) -> bool:
    """Whether some row breaks the contract's numeric constraints (non-finite, out of range, wrong width):
    such rows go through the validating single-message path (which refuses them, counted invalid_output)."""
    try:
        if not np.isfinite(np.asarray(t_s, float)).all():
            return True
        for f in messages.MESSAGES[msg_type].fields:
            c = cols.get(f.name)
            if c is None:
                if f.required:
                    return True
                continue
            if isinstance(c, str):  # one value for every row
                c = [c]
            if f.kind in ("float", "vec3", "floats", "mat3"):
                a = np.asarray([math_nan if x is None else x for x in c] if f.nullable and not isinstance(
                    c, np.ndarray) else c, float)
                if f.kind != "float":
                    w = 3 if f.kind == "vec3" else (9 if f.kind == "mat3" else f.length)
                    if a.ndim != 2 or (w is not None and a.shape[1] != w):
                        return True
                fin = np.isfinite(a)
                if f.nullable:
                    fin |= np.isnan(a)
                if not fin.all():
                    return True
                if f.lo is not None and (a < f.lo).any():
                    return True
                if f.hi is not None and (a > f.hi).any():
                    return True
            elif f.kind == "str" and f.choices and any(x not in f.choices for x in c):
                return True
    except (TypeError, ValueError):
        return True
    return False


math_nan = float("nan")


class _FrameRows:
    """One vehicle's rows of a frame stream, read like a batch's columns by the per-sample fallback."""

    __slots__ = ("name", "msg_type", "st", "a", "b", "t_s", "seq", "cols")

    def __init__(self, name: str, st: Any, a: int, b: int):
        self.name, self.msg_type, self.st, self.a, self.b = name, st.msg_type, st, a, b
        self.t_s = st.t_s[a:b].tolist()
        self.seq = st.seq[a:b].tolist()
        self.cols = st.cols

    @property
    def n(self) -> int:
        return self.b - self.a

    def messages(self, vehicle: str) -> list[dict]:
        return self.st.messages(vehicle, self.a, self.b)


def _is_dmc_key(kexpr: str) -> bool:
    parts = kexpr.split("/")
    return len(parts) == 3 and parts[0] == keys.ROOT and parts[2] == "dmc" and parts[1] not in (keys.SVC, keys.FLEET)


def frame_kinds_for(subscriptions: list[str]) -> list[str]:
    """The fleet frame kinds (clean, cal, dmc) that carry the per-vehicle streams of these subscriptions."""
    out = []
    for kexpr in subscriptions:
        parts = kexpr.split("/")
        if len(parts) < 3 or parts[0] != keys.ROOT or parts[1] in (keys.SVC, keys.FLEET):
            continue
        kind = parts[2]
        if kind == "clean":
            k = "clean"
        elif kind == "cal" and (len(parts) < 4 or parts[3] in ("mag", "*", "**")):
            k = "cal"
        elif kind == "dmc":
            k = "dmc"
        else:
            continue
        if k not in out:
            out.append(k)
    return out


def _mergeable(a: tuple[Any, Any], b: tuple[Any, Any]) -> bool:
    """Whether two decoded frames of one key can be handled as one (:meth:`Runner.handle_frames`): the same
    vehicle list (the same object: a publisher's list is kept until a vehicle comes), the same group holdings and,
    for every stream both carry, the same columns."""
    fa, ma = a
    fb, mb = b
    if fb.vehicles is not fa.vehicles or (ma is not mb and (ma is None or mb is None or not np.array_equal(ma, mb))):
        return False
    return all(fa.streams[n].cols.keys() == st.cols.keys() for n, st in fb.streams.items() if n in fa.streams)


def drop_category(reason: str) -> str:
    """``lost`` | ``rejected`` | ``skipped`` for a drop reason (see :data:`LOST_REASONS`)."""
    if reason in LOST_REASONS:
        return "lost"
    if reason.startswith("rejected:"):
        return "rejected"
    return "skipped"


WATCH_SETTLE_S = 1.0  # a new per-vehicle publisher puts every row this long, then only while a subscriber matches


class _Watch:
    """Whether any subscriber matches a per-vehicle output key, kept current by Zenoh's matching listener.

    A fleet's per-vehicle outputs (``dmc``, ``heading``: one message per vehicle per sample) are for whoever
    watches that vehicle; the services that take them all read the fleet frames. A row of a key no subscriber
    matches is numbered and journaled as always, but neither built nor put (a put Zenoh would route nowhere still
    costs the encoding and the call): at 500 vehicles those are 25,000 puts a second. A subscriber that comes
    flips ``on`` within milliseconds (the listener's callback) and receives from then on; its first message
    carries the key's seq where it stands, so it sees no gap. A new publisher's matching status is not known at
    once (a client learns it from its router a moment later), so a key is put for its first
    :data:`WATCH_SETTLE_S` whatever the status says, then follows it (:meth:`settle`). A publisher without
    matching support (a test double) counts as watched."""

    __slots__ = ("on", "_pub", "_listener", "_calls")

    def __init__(self, pub: Any):
        self.on = True
        self._pub = None
        self._listener = None
        self._calls = 0
        declare = getattr(pub, "declare_matching_listener", None)
        if declare is None:
            return
        try:
            self._listener = declare(self._set)
            self._pub = pub
        except Exception:  # noqa: BLE001 - an advanced publisher or a closing session: always put
            self._listener = None

    def settle(self) -> None:
        """From now on follow the matching status (called :data:`WATCH_SETTLE_S` after the publisher came)."""
        if self._pub is None:
            return
        calls = self._calls
        try:
            now = bool(self._pub.matching_status.matching)
        except Exception:  # noqa: BLE001 - a closing session
            return
        if self._calls == calls:  # (a callback since the read has the newer state)
            self.on = now

    def _set(self, status: Any) -> None:  # (a Zenoh thread)
        self._calls += 1
        self.on = bool(status.matching)

    def close(self) -> None:
        self._pub = None
        if self._listener is not None:
            try:
                self._listener.undeclare()
            except Exception:  # noqa: BLE001 - a closing session
                pass
            self._listener = None


class Service:
    """Base class of a magmesh service. Constructors have no side effects; see :func:`main`."""

    role: str = "service"
    impl: str = "service"
    Settings: type | None = None
    #: the streams taken and published (magmesh/declare.py): the subscriptions, status and --help derive from them
    INPUTS: tuple[declare.Input, ...] = ()
    OUTPUTS: tuple[declare.Output, ...] = ()
    #: raw/batch payloads (contract v2) reach on_message undecoded: the service validates them (ingest)
    RAW_BATCHES: bool = False
    #: decode inputs before on_message (ingest turns this off to validate raw bytes itself)
    DECODE_INPUTS: bool = True
    #: the logic takes a restored raised alarm as its own (see :meth:`holds_alarm`) and clears it itself when the
    #: condition goes; otherwise the runtime clears one the restarted logic does not raise again once it has seen
    #: enough input (``alarm_reconcile_s`` of sample time and ``alarm_reconcile_outputs`` outputs for the vehicle)
    ADOPTS_RESTORED_ALARMS: bool = False

    def __init__(self, settings: Any = None, instance: str | None = None, vehicle_pattern: str = "*",
                 vehicles_config: dict | None = None):
        self.settings = settings if settings is not None else (self.Settings() if self.Settings else None)
        self.instance = instance or f"{self.impl}-{os.getpid()}"
        self.vehicle_pattern = keys.check_pattern(vehicle_pattern)
        self.vehicles_config = vehicles_config or {}
        self.log = logging.getLogger(f"magmesh.{self.role}.{self.instance}")
        self._rt: Runner | None = None
        self.group: str | None = None  # a role group's name (--group): vehicles shared with its live members

    # ---- hooks --------------------------------------------------------------------------------
    def subscriptions(self) -> list[str]:
        return declare.subscriptions(self)

    def new_vehicle(self, vehicle: str) -> Any:
        return None

    def on_message(self, info: KeyInfo, msg: Any, state: Any) -> None:
        pass

    def on_tick(self) -> None:
        pass

    def status_extra(self) -> dict:
        return {}

    def queryables(self) -> dict[str, Callable[[str, dict], list[tuple[str, dict]]]]:
        return {}

    def on_start(self) -> None:
        pass

    def on_stop(self) -> None:
        pass

    # ---- API for subclasses -------------------------------------------------------------------
    def publish(self, key: str, msg_type: str, vehicle: str, t_s: float, **fields: Any) -> dict:
        """Publish one message on ``key``; returns the message sent (with its seq)."""
        return self._runtime.publish(key, msg_type, vehicle, t_s, fields)

    def republish(self, key: str, msg: dict) -> dict | None:
        """Publish an already validated input message's fields on another key, with this service's seq."""
        return self._runtime.republish(key, msg)

    #: a service that takes whole batches (contract v2) defines ``on_batch(info, batch, state)``: ``info`` is
    #: the batch key's, ``batch`` a :class:`schemas.batch.Batch` holding only the streams the service subscribes
    #: to (columns as numpy arrays). Without it, the runtime hands each sample of a batch to ``on_message`` in
    #: sample-time order, exactly as if it had arrived alone.
    on_batch: Callable | None = None

    def publish_batch(self, key: str, vehicle: str, cols: dict) -> int:
        """Publish validated samples of a vehicle's streams as one batch (``clean/batch``); returns samples sent."""
        return self._runtime.publish_batch(key, vehicle, cols)

    #: a service that takes whole fleet frames (contract v3) defines ``on_frame(frame)``: ``frame`` is a
    #: :class:`schemas.frame.Frame` holding only the streams and vehicles the service subscribes to (and, in a
    #: group, holds), rows sorted by vehicle then time, seq already tracked per vehicle and stream. Without it, the
    #: runtime hands each vehicle's samples of a frame to ``on_batch`` / ``on_message`` as if they had come alone.
    on_frame: Callable | None = None
    #: take fleet frames for the per-vehicle clean/, cal/mag and dmc streams subscribed to (ingest does not)
    FRAME_INPUT: bool = True

    def publish_frame(self, kind: str, vehicles: list[str], streams_: dict) -> int:
        """Publish rows of many vehicles as one fleet frame on ``magmesh/fleet/{shard}/{kind}`` (``streams_``: name →
        :class:`schemas.frame.Stream` with ``seq`` filled, or None to number each vehicle's rows here on its own
        per-vehicle key); returns the rows sent."""
        return self._runtime.publish_frame(kind, vehicles, streams_)

    def publish_rows(self, msg_type: str, keys_: list[str], vehicles: list[str], t_s: Any, cols: dict,
                     mirror: str | None = None) -> list[int]:
        """Publish one v1 message per row on its per-vehicle key (``cols``: field → n values, or one string); the
        fast path of many outputs at once (a frame's epochs). ``mirror``: the rows sent also go out as one fleet
        frame of that kind, with the same seqs. Returns each row's seq (-1: held back or suppressed)."""
        return self._runtime.publish_rows(msg_type, keys_, vehicles, t_s, cols, mirror)

    @property
    def shard(self) -> str:
        """This instance's shard name: the key chunk of the frames it publishes."""
        return self.instance

    def alarm(self, vehicle: str, source: str, state: str, severity: str, reason: str,
              value: float | None, threshold: float | None, t_s: float, unit: str = "", **extra: Any) -> dict:
        """Publish an alarm transition on ``magmesh/{vehicle}/alarm/{source}``."""
        fields = dict(source=source, state=state, severity=severity, reason=reason,
                      value=None if value is None else float(value),
                      threshold=None if threshold is None else float(threshold),
                      service=self.instance, **extra)
        if unit:
            fields["unit"] = unit
        return self._runtime.publish_alarm(keys.alarm(vehicle, source), vehicle, t_s, fields)

    def reject(self, key: str, code: str, reason: str, field: str | None, payload_len: int,
               vehicle: str | None = None, t_s: float | None = None, input_type: str | None = None) -> None:
        """Count a refused input and report it on ``magmesh/{vehicle}/rejects``."""
        self._runtime.reject(key, code, reason, field, payload_len, vehicle, t_s, input_type)

    def count_drop(self, key: str, reason: str, n: int = 1) -> None:
        self._runtime.count_drop(key, reason, n)

    def count_join_loss(self, key: str, vehicle: str, reason: str) -> None:
        """A sample a join gave up (its partner never came). Right after a restart or a takeover, before the
        vehicle's first output, its partner was held by the process that died: that is a loss of the restart
        (``lost_during_restart``) or the takeover (``lost_in_takeover``), not a skip; otherwise ``reason``."""
        self._runtime.count_join_loss(key, vehicle, reason)

    def state_for(self, vehicle: str) -> Any:
        return self._runtime.state_for(vehicle)

    def holds_alarm(self, vehicle: str, source: str) -> bool:
        """Whether the mesh's alarm ``source`` of ``vehicle`` stands raised as this instance holds it (restored
        after a restart, or taken over in a swap): a logic that latches its alarms starts its latch from this."""
        rt = self._rt
        return rt is not None and getattr(rt, "alarm_published", {}).get(keys.alarm(vehicle, source)) == "raised"

    def held_alarm_raised_t_s(self, vehicle: str, source: str) -> float | None:
        """When the alarm :meth:`holds_alarm` reports was raised (its ``t_s``; a clear names it), else None."""
        rt = self._rt
        if rt is None or not self.holds_alarm(vehicle, source):
            return None
        with rt.lock:
            msg = rt.raised.get(keys.alarm(vehicle, source))
        t = msg.get("t_s") if isinstance(msg, dict) else None
        return float(t) if isinstance(t, (int, float)) and not isinstance(t, bool) else None

    @property
    def vehicle_states(self) -> dict[str, Any]:
        return self._runtime.vehicle_state

    @property
    def group_share(self) -> float:
        """This instance's share of its role's fleet: 1 alone, 1/N as one of N live members of a group (what a
        budget set for the role, such as calibration's ``fit_budget_frac``, gives each member)."""
        g = getattr(self._rt, "group", None)
        n = len(g.members) if g is not None else 1
        return 1.0 / max(1, n)

    @property
    def _runtime(self) -> Runner:
        if self._rt is None:
            raise RuntimeError("service is not running: start it with magmesh.runtime.main or Runner")
        return self._rt


class SimPublisher(Service):
    """A data source: ``produce()`` yields ``(t_s, key, msg_type, fields)`` in time order.

    The runner paces the stream by ``t_s`` at ``settings.speed`` × real time (0 = as fast as the mesh
    takes it). ``self.vehicle`` is the vehicle id given by ``--vehicle``.
    """

    role = "sim"
    vehicle: str = "sim-1"

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        return iter(())


# ---- settings ---------------------------------------------------------------------------------


def _coerce(tp: Any, value: Any, name: str) -> Any:
    tp_s = tp if isinstance(tp, str) else getattr(tp, "__name__", str(tp))
    if isinstance(value, str):
        if tp_s in ("bool",):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"setting {name}: {value!r} is not a boolean")
        if tp_s in ("int",):
            return int(value)
        if tp_s in ("float",):
            return float(value)
        if tp_s in ("str",):
            return value
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    if tp_s == "float" and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp_s.startswith("tuple") and isinstance(value, list):
        return tuple(value)
    return value


def build_settings(cls: type | None, values: dict) -> Any:
    """Build a Settings dataclass from a dict; unknown names are an error that lists the known ones, a value its
    declaration does not allow a :class:`magmesh.declare.SettingError` naming setting, value and allowed range."""
    if cls is None:
        if values:
            raise ValueError(f"this service takes no settings, got {sorted(values)}")
        return None
    flds = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(flds))
    if unknown:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)}; known: {', '.join(flds)}")
    kw = {}
    for k, v in values.items():
        try:
            kw[k] = _coerce(flds[k].type, v, k)
        except ValueError:
            raise declare.SettingError(k, v, f"is not {declare.type_name(flds[k].type)}") from None
    declare.check_values(cls, kw)
    return cls(**kw)


def settings_help(cls: type | None) -> str:
    """The settings table of ``--help`` (magmesh/declare.py)."""
    return declare.settings_table(cls)


_PRIMS = (float, int, str, bool, type(None))


def _plain(v: Any) -> Any:
    """Plain msgpack-able values (numpy scalars/arrays, dataclasses and tuples converted)."""
    t = type(v)
    if t in _PRIMS:
        return v
    if t is dict:
        return {str(k): (x if type(x) in _PRIMS else _plain(x)) for k, x in v.items()}
    if t is list and all(type(x) in _PRIMS for x in v):
        return v
    if dataclasses.is_dataclass(v):
        return {k: _plain(x) for k, x in dataclasses.asdict(v).items()}
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    try:
        import numpy as np

        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, np.ndarray):
            return v.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(v)


# ---- the runner -------------------------------------------------------------------------------


def _n(c: Any) -> int:
    return c.n


def _sum(d: dict) -> int:
    return sum(d.values())


def _rss_kb() -> int | None:
    """This process's resident memory, in KiB (None where /proc is not there)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _top(d: dict, weight: Callable[[Any], int], n: int = STATUS_TOP_KEYS) -> list:
    """The ``n`` largest entries of a per-key table (status replies stay bounded however many keys there are)."""
    items = list(d.items())
    if len(items) <= n:
        return items
    return heapq.nlargest(n, items, key=lambda kv: weight(kv[1]))


class _Counter:
    __slots__ = ("n", "n_prev", "rate")

    def __init__(self) -> None:
        self.n = 0
        self.n_prev = 0
        self.rate = 0.0


def reject_code(e: SchemaError) -> str:
    """The reject code of a payload the contract refused: version, decode (not a message at all) or schema."""
    return "version" if e.field == "version" else ("decode" if e.field == "<payload>" else "schema")


def _cal_id(msg: dict) -> list:
    """What identifies a parameter set in the calibration instances' status: ``[param_id, seq, t_s]``."""
    return [msg.get("param_id"), msg.get("seq"), msg.get("t_s")]


def _cal_note(reply: Any, seen: dict[str, list[list]]) -> None:
    """Add to ``seen`` (by key) the sets one calibration instance's status reply reports having published."""
    if reply.ok is None:
        return
    try:
        st = msgpack.unpackb(reply.ok.payload.to_bytes())
    except Exception:  # noqa: BLE001 - a garbage answer confirms nothing
        return
    if not (isinstance(st, dict) and st.get("role") == "calibration" and isinstance(st.get("cal_params_sent"), dict)):
        return
    recent = st.get("cal_params_recent")
    recent = recent if isinstance(recent, dict) else {}
    for k, last in st["cal_params_sent"].items():
        older = recent.get(k)
        seen.setdefault(k, []).extend([last, *(older if isinstance(older, list) else ())])


class Runner:
    """Runs one :class:`Service` on an open Zenoh session."""

    def __init__(self, service: Service, session: Any):
        self.svc = service
        self.session = session
        self.q: queue.Queue = queue.Queue(maxsize=QUEUE_CAPACITY)
        self.stop_event = threading.Event()
        self.lock = threading.Lock()
        self.started_mono = time.monotonic()
        self.started_wall = time.time()
        self.publishers: dict[str, Any] = {}
        self.seq: SeqTable = SeqTable()  # output key -> last seq sent (frames number many keys at once)
        self.count_in: dict[str, _Counter] = defaultdict(_Counter)
        self.count_out: dict[str, _Counter] = defaultdict(_Counter)
        self.drops: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        self.rejects_total = 0
        self.last_error: str | None = None
        self.vehicle_state: dict[str, Any] = {}
        self.raised: dict[str, dict] = {}
        self.last_rate_mono = time.monotonic()
        self.subs: list[Any] = []
        self.qables: list[Any] = []
        self.threads: list[threading.Thread] = []
        self.token = None
        self.extra_qables: dict[str, Callable] = {}
        # live hand-over (see magmesh/swap.py): active | standby | retiring | retired
        self.mode = "active"
        self.cut: dict[str, float] = {}
        self.held: list[tuple[str, str, str, float, dict]] = []
        self.passed_cut: set[str] = set()
        self.alarm_published: dict[str, str] = {}  # alarm key -> last state published ("raised"/"cleared")
        self.alarm_adopted = 0  # bumped whenever alarm states come from elsewhere (restart, swap, hand-over)
        self.suppressed = 0
        self.in_seq: SeqTable = SeqTable()  # input key -> last seq handled (frames track many keys at once)
        self.params_sent: dict[str, list] = {}  # cal/params key -> [param_id, seq, t_s] last published
        # the sets published before it on each key, newest first (CAL_RECENT of them): a consumer running behind
        # (a queue under overload) still confirms a set that was genuine when sent, though a newer one followed
        self.params_recent: dict[str, deque] = {}
        # the sets the live calibration instances last reported having published, by key (the last and the
        # recent ones before it)
        self._cal_sent: dict[str, list[list]] = {}
        self._cal_sent_t = float("-inf")  # when they reported it (monotonic s): a report is used for 2 s
        # cal/params sets waiting for such a report (cal_params_admit), by key, oldest first: [info, msg, give-up
        # time]; the status query asking for them (at most one in flight: its replies, what they reported so far)
        # and when to ask again
        self._cal_parked: dict[str, list[list]] = {}
        self._cal_ask: tuple[Any, dict] | None = None
        self._cal_next_ask = 0.0
        self.journal = None  # magmesh.journal.Journal: last input/output seq per key, survives kill -9
        self.resumed_in: set[str] = set()  # input keys whose first gap after a restart is lost_during_restart
        self.restart_gaps: dict[str, list[list[int]]] = {}  # input key -> [first, last] seq missed by a restart
        # input key -> seq of the first sample received (journalled as "f"): a key received but not yet handled
        # when the process dies is counted from there at the restart, not silently skipped
        self._first_rx: dict[str, int] = {}
        self._refused_seqs: dict[str, set[int]] = {}  # input key -> seqs refused since its last accepted sample
        self._rx_lock = threading.Lock()
        self.takeover_in: set[str] = set()  # input keys taken from a dead group member: first gap is lost_in_takeover
        #: of those, keys whose last seq handled is estimated from what the mesh showed (a member on another host):
        #: a first sample at or below it is no re-base (the dead member handled it, or the estimate's rounding)
        self.takeover_est: set[str] = set()
        # vehicle -> lost_during_restart | lost_in_takeover: resumed from a journal, no output yet (count_join_loss)
        self.recovering: dict[str, str] = {}
        self.group = None  # magmesh.group_member.GroupMember when the service runs in a group (--group)
        self.frame_subs = None  # magmesh.frame_subs.FrameSubscriptions: a group member's fleet-frame subscriptions
        self._frame_resumed = False  # the frame being taken in is the first of its key since a narrowing
        self.resumed_from: dict | None = None  # what the journal of the run before a crash said
        self.clean_stop = False
        self.n_sent = 0  # outputs sent by this process (the journal's witness of a sample handled when killed)
        self.alarm_declared: dict[str, str] = {}  # alarm key -> last state the service logic declared
        self.reconcile_at: float | None = None
        self.reconcile_pending: dict[str, str] = {}  # restored raised alarm key -> vehicle, not yet decided
        self.out_since_start: dict[str, int] = {}  # vehicle -> outputs published (while reconciling only)
        self._first_in_t: dict[str, float] = {}
        self._last_in_t: dict[str, float] = {}
        # frames: each vehicle's times kept in arrays per vehicle list and written into the dicts above when they
        # are read (swap cuts, group hand-overs, eviction), not once per vehicle per frame
        self._times_pending: dict[int, list] = {}
        # input-path bookkeeping: what the sample being handled did, when keys and vehicles were last heard
        self._cur_key: str | None = None
        self._cur_rejected = False
        self.key_seen: dict[str, float] = {}
        self._vehicle_seen: dict[str, float] = {}
        self._out_idle: dict[str, tuple[int, float]] = {}
        self.evicted: dict[str, int] = defaultdict(int)  # what eviction freed: vehicles, keys
        self.evicted_drops: dict[str, int] = defaultdict(int)  # drop counts of evicted keys, by reason
        self.evicted_in = 0
        self.evicted_out = 0
        self.rebases: dict[str, int] = defaultdict(int)  # seq / clock re-bases, each counted once
        self._next_evict = time.monotonic() + 1.0
        self._log_last: dict[str, tuple[float, int]] = {}
        self.batch_in = False  # clean batches are unbatched here (set in start())
        self.batches_in = 0
        self.batches_out = 0
        self._sub_exprs: list[Any] = []
        self._wants: dict[str, bool] = {}
        # fleet frames (contract v3): per (frame key, stream) the vehicles' keys and seq slots; frames in and out
        self._fkeys: dict[tuple[str, str], StreamKeys] = {}
        self.frames_in = 0
        self.frames_out = 0
        self.frames_shed = 0  # frames shed because they waited longer than shed_after_s (their rows: drops)
        self.cur_queued_at: float | None = None  # when the input being handled was queued (monotonic s)
        self._behind_since: float | None = None  # since when the loop has handled only late input (shedding)
        self.frames_missed = 0  # frames whose seq never arrived (their samples show as per-stream seq gaps)
        self.frame_seq_in: dict[str, int] = {}
        self._ofkeys: dict[tuple[str, str, str], tuple] = {}  # output frame rows: per (kind, name) keys and slots
        # publish_rows: key -> [publisher, journal slot, out counter, _Watch (whether any subscriber matches the key)]
        self._row_cache: dict[str, list] = {}
        self.unwatched: dict[str, int] = defaultdict(int)  # rows numbered but not put: no subscriber (per type)
        self._unsettled: deque = deque()  # (when, _Watch) of new publishers whose matching status is not known yet
        self._raw_batch_keys: dict[str, KeyInfo] = {}  # raw/batch keys already checked (a service taking them)
        self.mirrors: dict[str, str] = {}  # message type -> frame kind its rows are mirrored in (publish_rows)
        self._mirror_lists: dict[str, tuple[list[str], dict[str, int]]] = {}  # kind -> its frames' vehicle list
        self._pending_ev: list = []  # an event taken from the queue while draining input, handled next
        self.frames_merged = 0  # frames handled within a run of their key's frames (handle_frames)
        service._rt = self

    # ---- output ---------------------------------------------------------------------------
    def _publisher(self, key: str) -> Any:
        pub = self.publishers.get(key)
        if pub is None:
            import zenoh

            # every put names its message type and version (schemas/streams.py)
            opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE,
                        encoding=_encoding(key))
            kind = keys.parse(key).kind
            if (kind == "alarm" or (kind == "cal" and "/cal/params/" in key)) and isinstance(self.session, zenoh.Session):
                # state that must never be missed: the last sample stays cached for late joiners (history), and
                # heartbeats let an AdvancedSubscriber detect and recover a missed sample
                from zenoh import ext

                if kind == "alarm":
                    # sent at once (not batched) and ahead of queued data: an overloaded member killed 150 ms after
                    # an alarm put had not got it out (its outputs queued seconds deep), and the member taking
                    # its vehicles over continued from it (a transition lost to subscribers)
                    opts.update(express=True, priority=zconf.control_priority())

                pub = ext.declare_advanced_publisher(
                    self.session, key, cache=ext.CacheConfig(max_samples=ALARM_HISTORY),
                    sample_miss_detection=ext.MissDetectionConfig(heartbeat=0.5), publisher_detection=True, **opts)
            else:
                pub = self.session.declare_publisher(key, **opts)
            self.publishers[key] = pub
        return pub

    def publish(self, key: str, msg_type: str, vehicle: str, t_s: float, fields: dict) -> dict | None:
        if msg_type == "alarm":
            self.alarm_declared[key] = fields.get("state")
        elif self.recovering and msg_type != "reject":
            self.recovering.pop(vehicle, None)  # its logic runs on what this process received
        if self.group is not None and msg_type != "reject" and not self.group.gate(key, msg_type, vehicle, t_s, fields):
            return None  # a vehicle this member does not publish for (now): see magmesh/group_member.py
        if self.mode == "active" and self.cut and msg_type != "reject":
            # just took the role over: epochs before the cut were published by the previous holder
            cut = self.cut.get(vehicle)
            if cut is not None:
                if t_s < cut:
                    self.suppressed += 1
                    return None
                del self.cut[vehicle]
        elif self.mode != "active" and msg_type != "reject":
            cut = self.cut.get(vehicle)
            if self.mode == "standby":
                if cut is not None and t_s >= cut:
                    self.held.append((key, msg_type, vehicle, t_s, fields))
                else:
                    self.suppressed += 1
                return None
            if self.mode == "retiring":
                if cut is None or t_s >= cut:
                    self.passed_cut.add(vehicle)
                    self.held.append((key, msg_type, vehicle, t_s, fields))
                    return None
            elif self.mode == "retired":
                self.suppressed += 1
                return None
        if msg_type == "alarm":
            state = fields.get("state")
            if self.alarm_published.get(key, "cleared") == state:
                self.count_drop(key, "alarm_state_unchanged")
                return None
        return self._send(key, msg_type, vehicle, t_s, fields)

    def _send(self, key: str, msg_type: str, vehicle: str, t_s: float, fields: dict, trusted: bool = False) -> dict:
        seq = self.seq.get(key, -1) + 1
        msg = messages.make(msg_type, vehicle, t_s, seq, **(fields if trusted else _plain(fields)))
        # validated unless the fields come from a message validated on input (a service never emits what the
        # contract forbids)
        payload = messages.encode(msg, check=not trusted)
        if msg_type == "alarm":  # the holder's own state first: an alarm query it answers after the put agrees
            self.seq[key] = seq
            self._alarm_sent(key, msg)
        elif msg_type == "cal_params":  # what this instance set, for consumers to confirm (cal_params_trusted)
            before = self.params_sent.get(key)
            if before is not None:
                self.params_recent.setdefault(key, deque(maxlen=CAL_RECENT)).appendleft(before)
            self.params_sent[key] = [msg.get("param_id"), seq, t_s]
        if self.journal is not None:
            # before the put: a kill between the two never sends one seq twice, and leaves the input handled with
            # its output numbered; an output that never left the process is then a seq gap its consumers see,
            # never also a lost input (the sent count after the put left a window where both were counted)
            self.journal.set("o" + key, seq)
            self.journal.sent(self.n_sent + 1)
        self._publisher(key).put(payload)
        self.seq[key] = seq
        self.count_out[key].n += 1
        self.n_sent += 1
        if self.reconcile_pending and msg_type not in ("alarm", "reject"):
            self.out_since_start[vehicle] = self.out_since_start.get(vehicle, 0) + 1
        return msg

    def publish_batch(self, key: str, vehicle: str, cols: dict) -> int:
        """One batch of already validated samples (``{stream name: Columns}``) on ``key``.

        Each sample's ``seq`` in the batch is this publisher's count on the sample's own stream key (the same
        number a single sample republished there would carry), so a consumer sees gaps per stream, and the
        batch's own ``seq`` counts batches on ``key``. During a hand-over the samples go one by one through the
        gated path, so the cut stays exact.
        """
        kind = keys.parse(key).kind
        if self.mode != "active" or self.cut or self.group is not None:
            n = 0
            for name, c in cols.items():
                skey = batches.stream_key(kind, vehicle, name)
                for m in c.messages(vehicle):
                    n += self.republish(skey, m) is not None
            return n
        out = {}
        n = 0
        for name, c in cols.items():
            if c.n == 0:
                continue
            skey = batches.stream_key(kind, vehicle, name)
            s0 = self.seq.get(skey, -1) + 1
            out[name] = batches.Columns(c.name, c.msg_type, c.t_s, list(range(s0, s0 + c.n)), c.cols)
            self.seq[skey] = s0 + c.n - 1
            self.count_out[skey].n += c.n
            n += c.n
        if not out:
            return 0
        seq = self.seq.get(key, -1) + 1
        self._publisher(key).put(batches.encode(vehicle, seq, out))
        self.seq[key] = seq
        self.count_out[key].n += 1
        self.batches_out += 1
        return n

    # ---- fleet frames and many rows out (contract v3) ------------------------------------------------
    def _gated(self) -> bool:
        """Whether outputs may be held back or suppressed now (a hand-over in progress, or a group member)."""
        return self.mode != "active" or bool(self.cut) or self.group is not None

    def publish_frame(self, kind: str, vehicles: list[str], streams_: dict, gated: bool = False) -> int:
        """One fleet frame of this instance's shard (``gated``: its rows already went through the gate). A stream whose ``seq`` is None has its rows numbered here,
        per vehicle, on their per-vehicle keys (the numbers single samples there would carry, journalled as
        theirs). While outputs are gated (hand-over, group) each row goes through the same per-vehicle gate as a
        single message: a row held back goes out later alone on its per-vehicle key."""
        from .frames import stream_key

        out: dict[str, fleetframe.Stream] = {}
        rows = 0
        for name, st in streams_.items():
            if st.n == 0:
                continue
            if self._gated() and not gated:
                st = self._gate_frame_rows(kind, name, vehicles, st)
                if st is None or st.n == 0:
                    continue
            if st.seq is None:
                g_vi, starts, ends = st.groups()
                ok = self._ofkeys.get((kind, name))
                if ok is None or ok[0] != vehicles or ok[3] != self.seq.generation:
                    ks = [stream_key(kind, v, name) for v in vehicles]
                    ok = (list(vehicles), ks, self.seq.slots_for(ks), self.seq.generation,
                          np.full(len(ks), -1, np.int64))
                    self._ofkeys[(kind, name)] = ok
                slots = ok[2][g_vi]
                prev = self.seq.arr[slots]
                prev = np.where(prev == _NO_SEQ, -1, prev)
                counts = ends - starts
                seq = np.repeat(prev + 1 - starts, counts) + np.arange(st.n)
                self.seq.arr[slots] = prev + counts
                st = fleetframe.Stream(st.name, st.msg_type, st.vi, st.t_s, seq, st.cols)
                self._journal_out(ok, g_vi, prev + counts)
            out[name] = st
            rows += st.n
        if not out:
            return 0
        fkey = keys.fleet_frame(self.svc.shard, kind)
        fseq = self.seq.get(fkey, -1) + 1
        payload = fleetframe.encode(self.svc.shard, kind, fseq, vehicles, out)
        if self.journal is not None:
            self.journal.set("o" + fkey, fseq)
        self._publisher(fkey).put(payload)
        self.seq[fkey] = fseq
        self.count_out[fkey].n += rows
        self.frames_out += 1
        self.n_sent += 1
        return rows

    def _journal_out(self, ok: tuple, g_vi: np.ndarray, last: np.ndarray) -> None:
        j = self.journal
        arr = j.array() if j is not None else None
        if arr is None:
            return
        js = ok[4][g_vi]
        missing = js < 0
        if missing.any():
            idx = g_vi[missing]
            ok[4][idx] = j.slots_of(["o" + ok[1][i] for i in idx.tolist()])
            js = ok[4][g_vi]
        good = js >= 0
        arr[js[good]] = last[good]

    def _plain_many(self, vehicles: list[str]) -> dict[str, bool]:
        """Per vehicle of ``vehicles`` (each once): whether every output of it goes out now, whatever its time (this
        instance is active, and no hand-over of it is under way)."""
        vs = dict.fromkeys(vehicles)
        if self.mode != "active":
            return dict.fromkeys(vs, False)
        blocked = (self.cut.keys() | self.recovering.keys()) & vs.keys() if (self.cut or self.recovering) else ()
        ask = [v for v in vs if v not in blocked] if blocked else vs
        out = self.group.plain_many(ask) if self.group is not None else dict.fromkeys(ask, True)
        for v in blocked:
            out[v] = False
        return out

    def _gate_frame_rows(self, kind: str, name: str, vehicles: list[str], st: Any) -> Any:
        """The rows of a frame that are this instance's to publish now (see :meth:`publish`); rows to hold are
        kept as single messages on their per-vehicle keys (published when the hand-over completes). Vehicles with
        no hand-over under way keep all their rows without a per-row step."""
        from .frames import stream_key

        g_vi, starts, ends = st.groups()
        gi = g_vi.tolist()
        plain = self._plain_many([vehicles[i] for i in gi])
        ok = np.fromiter((plain[vehicles[i]] for i in gi), bool, len(gi))
        if ok.all():
            return st
        keep = np.repeat(ok, ends - starts)  # (each vehicle's rows are one run: rows are sorted by vehicle)
        for i in np.flatnonzero(~keep).tolist():
            v = vehicles[int(st.vi[i])]
            k = stream_key(kind, v, name)
            t = float(st.t_s[i])
            fields = {f: x for f in st.cols if (x := st.column(f, i)) is not fleetframe.ABSENT}
            # the row as the message it would be alone: the gate holds it, suppresses it, or lets it through
            verdict = self._gate(k, st.msg_type, v, t, fields)
            keep[i] = verdict
        return st.take(keep) if not keep.all() else st

    def _gate(self, key: str, msg_type: str, vehicle: str, t_s: float, fields: dict) -> bool:
        """:meth:`publish`'s hand-over and group rules for one output: True = publish now; False = suppressed or
        held (a held one is published later through :meth:`publish`)."""
        if self.group is not None and not self.group.gate(key, msg_type, vehicle, t_s, fields):
            return False
        if self.mode == "active" and self.cut:
            cut = self.cut.get(vehicle)
            if cut is not None:
                if t_s < cut:
                    self.suppressed += 1
                    return False
                del self.cut[vehicle]
            return True
        if self.mode != "active":
            cut = self.cut.get(vehicle)
            if self.mode == "standby":
                if cut is not None and t_s >= cut:
                    self.held.append((key, msg_type, vehicle, t_s, fields))
                else:
                    self.suppressed += 1
                return False
            if self.mode == "retiring":
                if cut is None or t_s >= cut:
                    self.passed_cut.add(vehicle)
                    self.held.append((key, msg_type, vehicle, t_s, fields))
                    return False
                return True
            self.suppressed += 1
            return False
        return True

    def publish_rows(self, msg_type: str, keys_: list[str], vehicles: list[str], t_s: list, cols: dict,
                     mirror: str | None = None) -> list[int]:
        """One v1 message per row on its per-vehicle key; returns each row's seq (-1: not sent now — held back
        or suppressed by a hand-over). ``mirror``: also publish the rows sent as one fleet frame of that kind
        (with the same seqs), for the services that take frames; rows held back are mirrored when released."""
        global _ROW_ENC
        n = len(keys_)
        out = [-1] * n
        if not n:
            return out
        uns = self._unsettled
        if uns and uns[0][0] <= time.monotonic():
            now = time.monotonic()
            while uns and uns[0][0] <= now:
                uns.popleft()[1].settle()
        if mirror:
            self.mirrors[msg_type] = mirror
        names = list(cols)
        given, t_given = cols, t_s  # (numpy columns stay as they are for the mirrored frame)
        bad = _invalid_rows(msg_type, cols, t_s, n)
        t_s = t_s.tolist() if isinstance(t_s, np.ndarray) else t_s
        colv: list = []

        def lists() -> list:  # the columns as lists, made when a row is built (not for unwatched keys)
            if not colv:
                colv.extend(c.tolist() if isinstance(c, np.ndarray) else ([c] * n if isinstance(c, str) else c)
                            for c in (given[f] for f in names))
            return colv

        rows = range(n)
        if self.reconcile_pending or bad:
            slow, rows = list(range(n)), ()
        elif self._gated() or self.recovering:  # rows of vehicles in a hand-over (or just resumed) one by one
            plain = self._plain_many(vehicles)
            slow = [i for i in range(n) if not plain[vehicles[i]]]
            if slow:
                rows = [i for i in range(n) if plain[vehicles[i]]]
        else:
            slow = []
        for i in slow:
            m = self.publish(keys_[i], msg_type, vehicles[i], float(t_s[i]),
                             {f: c[i] for f, c in zip(names, lists(), strict=True)})
            if m is not None:
                out[i] = m["seq"]
        if rows:
            if _ROW_ENC is None:
                import msgspec

                _ROW_ENC = msgspec.msgpack.Encoder()
            enc = _ROW_ENC.encode
            ver = messages.MESSAGES[msg_type].version
            cache, j = self._row_cache, self.journal
            seq = self.seq.d  # (per-vehicle output keys never have an array slot: see below)
            arr = j.array() if j is not None else None
            new = [k for k in dict.fromkeys(keys_) if k not in cache]
            if new:  # first rows of these keys: publishers and journal slots (the index written once)
                js = j.slots_of(["o" + k for k in new]) if j is not None else [-1] * len(new)
                for k, jslot in zip(new, js, strict=True):
                    if k in self.seq.slot:  # a key numbered in frames too: back into the dict
                        v = self.seq.get(k)
                        self.seq.free_slot(k)
                        if v is not None:
                            seq[k] = v
                    pub = self._publisher(k)
                    w = _Watch(pub)
                    cache[k] = [pub, jslot, self.count_out[k], w]
                    self._unsettled.append((time.monotonic() + WATCH_SETTLE_S, w))
            first = j is not None
            for i in rows:  # numbered and journalled first, put below
                k = keys_[i]
                c = cache[k]
                s = seq.get(k, -1) + 1
                if arr is not None and c[1] >= 0:
                    arr[c[1]] = s  # before the put, as _send journals (a kill between never repeats a seq)
                if first:  # and the sent count with it, as _send does: after a kill here the input being handled
                    # is handled (its output numbered: a seq gap if it never left), never also a lost input
                    # (the count written after the loop left a window where both were counted)
                    j.sent(self.n_sent + 1)
                    first = False
                seq[k] = s
                c[2].n += 1
                out[i] = s
            self.n_sent += len(rows)
            if j is not None:
                j.sent(self.n_sent)
        if mirror:
            # the fleet frame before the per-vehicle puts: a kill between them leaves outputs numbered that never
            # went out (seq gaps, as a kill between the journal and a put does), never a row published on its
            # key but missing from the frames, from which a member on another host goes on after a kill
            # (group_member._mesh_state: it would number that output again)
            self._mirror_rows(mirror, msg_type, vehicles, t_given, given, out)
        if rows:
            row = _row_type(("type", "version", "vehicle", "t_s", "seq", *names))
            vals = None  # each row's field values, in names' order: made at the first row built
            skipped = 0
            for i in rows:
                c = cache[keys_[i]]
                if c[3].on:
                    if vals is None:
                        vals = list(zip(*lists(), strict=True))
                    c[0].put(enc(row(msg_type, ver, vehicles[i], t_s[i], out[i], *vals[i])))
                else:  # nobody subscribes to this vehicle's key now: numbered, not built or put (see _Watch)
                    skipped += 1
            if skipped:
                self.unwatched[msg_type] += skipped
        return out

    def _mirror_rows(self, kind: str, msg_type: str, vehicles: list[str], t_s: list, cols: dict,
                     seqs: list[int]) -> None:
        sq = np.asarray(seqs, np.int64)
        sent = sq >= 0
        if not sent.any():
            return
        idx = np.flatnonzero(sent).tolist()
        # the frame's vehicle list: one list object kept per kind, grown as vehicles come (a new object then), so
        # frame after frame carries the same list and its readers keep their per-list state (schemas/frame.py
        # _checked_vehicles, _stream_keys, _frame_times) instead of reading a new list of names each frame
        vl = self._mirror_lists.get(kind)
        if vl is None:
            vl = self._mirror_lists[kind] = ([], {})
        names, index = vl
        fresh = [v for v in dict.fromkeys(vehicles[i] for i in idx) if v not in index]
        if fresh:
            if len(names) + len(fresh) > max(MIRROR_LIST_MIN, 2 * len(self.vehicle_state)):
                names, index = [], {}  # (vehicles gone for good are left out: started anew)
                fresh = list(dict.fromkeys(vehicles[i] for i in idx))
            index.update(zip(fresh, range(len(names), len(names) + len(fresh)), strict=True))
            names = [*names, *fresh]  # (a new list object: readers key their state by the list)
            self._mirror_lists[kind] = (names, index)
        vi = np.fromiter((index[vehicles[i]] for i in idx), np.uint32, len(idx))
        order = np.argsort(vi, kind="stable")
        idx_a = np.asarray(idx)[order]
        fcols = {}
        for f, c in cols.items():
            if isinstance(c, np.ndarray):
                fcols[f] = c[idx_a]
            elif isinstance(c, str):
                fcols[f] = c
            else:
                vals = [c[i] for i in idx_a.tolist()]
                fcols[f] = vals[0] if vals and all(isinstance(x, str) and x == vals[0] for x in vals) else vals
        st = fleetframe.Stream(msg_type, msg_type, vi[order], np.asarray(t_s, float)[idx_a], sq[idx_a], fcols)
        self.publish_frame(kind, names, {msg_type: st}, gated=True)

    def _release_held(self, held: list) -> int:
        """Publish outputs held during a hand-over; those of a mirrored type go out as one frame too."""
        sent: dict[str, list] = {}
        for item in held:
            m = self.publish(*item)
            if m is not None and item[1] in self.mirrors:
                sent.setdefault(item[1], []).append(m)
        for mt, msgs in sent.items():
            fields = [f.name for f in messages.MESSAGES[mt].fields]
            cols = {f: [m.get(f) for m in msgs] for f in fields if all(f in m for m in msgs)}
            self._mirror_rows(self.mirrors[mt], mt, [m["vehicle"] for m in msgs], [m["t_s"] for m in msgs], cols,
                              [m["seq"] for m in msgs])
        return len(held)

    def republish(self, key: str, msg: dict) -> dict | None:
        """Publish the fields of an already validated input message on another key (no re-validation)."""
        fields = {k: v for k, v in msg.items() if k not in _HEADER_NAMES}
        if self.mode != "active" or self.cut or self.group is not None:  # hand-over possible: the gated path
            return self.publish(key, msg["type"], msg["vehicle"], msg["t_s"], fields)
        return self._send(key, msg["type"], msg["vehicle"], msg["t_s"], fields, trusted=True)

    def raised_alarm(self, key: str) -> dict:
        """The raised alarm held on ``key`` (its last "raised" message; {} when none is held)."""
        with self.lock:
            return dict(self.raised.get(key) or {})

    def publish_alarm(self, key: str, vehicle: str, t_s: float, fields: dict) -> dict | None:
        return self.publish(key, "alarm", vehicle, t_s, fields)

    def _alarm_sent(self, key: str, msg: dict) -> None:
        self.alarm_published[key] = msg["state"]
        with self.lock:
            if msg["state"] == "raised":
                self.raised[key] = msg
            else:
                self.raised.pop(key, None)
        self.svc.log.info("alarm %s %s: %s", key, msg["state"], msg["reason"])
        try:  # one appended line (magmesh/alarmstore.py); now and then the whole state as a new snapshot
            if self._alarms().record(key, msg["state"], msg["seq"], msg):
                self._persist_alarms()
        except OSError as e:
            self.last_error = f"could not persist alarm state: {e}"

    # ---- alarm state across restarts --------------------------------------------------------
    def _alarm_file(self):
        from .paths import state_dir

        d = state_dir() / "alarms"
        d.mkdir(parents=True, exist_ok=True)
        return d / f"{self.svc.role}.{self.svc.instance}.json"

    def _alarms(self):
        store = self.__dict__.get("_alarm_store")
        if store is None:
            from .alarmstore import AlarmStore

            store = self.__dict__["_alarm_store"] = AlarmStore(self._alarm_file())
        return store

    def _persist_alarms(self) -> None:
        """Alarm states and their seq survive a crash: a restart neither repeats nor forgets a transition. The
        whole state as a new snapshot (each transition is also appended as it is sent, see _alarm_sent)."""
        try:
            with self.lock:
                raised = dict(self.raised)
            akeys = [k for k in self.alarm_published]
            self._alarms().compact({"published": dict(self.alarm_published), "raised": raised,
                                    "seqs": {k: self.seq[k] for k in akeys if k in self.seq}})
        except OSError as e:
            self.last_error = f"could not persist alarm state: {e}"

    def restore_alarms(self) -> None:
        from .alarmstore import load

        data = load(self._alarm_file())
        if not data["published"]:
            return
        self.alarm_published = {k: v for k, v in data.get("published", {}).items()}
        self.alarm_adopted += 1
        with self.lock:
            self.raised = dict(data.get("raised", {}))
        for k, v in data.get("seqs", {}).items():
            self.seq[k] = int(v)
        if self.raised:
            self.svc.log.info("restored %d raised alarm(s) from before the restart", len(self.raised))
            if not self.svc.ADOPTS_RESTORED_ALARMS:
                # each stays raised until the restarted logic has seen enough input to decide (reconcile_alarms)
                self.reconcile_pending = {k: m.get("vehicle") for k, m in self.raised.items()}
                self.reconcile_at = time.monotonic() + 0.5

    # ---- seq journal across restarts (magmesh/journal.py) ---------------------------------------
    def resume_journal(self) -> None:
        """Read what the run before a crash handled and sent; continue its output seqs; count what was missed."""
        from .journal import Journal
        from .paths import state_dir

        try:
            self.journal = Journal(state_dir() / "journal" / f"{self.svc.role}.{self.svc.instance}.seq")
            prev = self.journal.load() if self.mode == "active" else {}
            # the sample being handled when the process died: handled if any output went out after it began
            # (a kill between its outputs and its journal entry must not count it as missed)
            ikey, pseq = self.journal.in_progress(prev)
            if ikey is not None and prev.get("~sent", 0) > prev.get("~sent_at_begin", 0):
                prev[ikey] = max(prev.get(ikey, pseq), pseq)
            prev = {k: v for k, v in prev.items() if not k.startswith("~")}
            self.journal.open(prev)
            with self._rx_lock:  # keys this run received before its journal was open
                for k, sq in self._first_rx.items():
                    if sq is not None and ("i" + k) not in prev and ("f" + k) not in prev:
                        self.journal.set("f" + k, sq)
        except OSError as e:
            self.journal = None
            self.last_error = f"seq journal unavailable: {e}"
            self.svc.log.error("%s: after a crash of this run, its output seqs restart from 0 and what it missed "
                               "goes uncounted", self.last_error)
            return
        if not prev:
            return
        n_in = n_out = 0
        for k, v in prev.items():
            if k[:1] == "o":
                self.seq[k[1:]] = max(self.seq.get(k[1:], -1), int(v))
                n_out += 1
            elif k[:1] == "i":
                self.in_seq[k[1:]] = int(v)
                self.resumed_in.add(k[1:])
                self.recovering[k[1:].split("/")[1]] = "lost_during_restart"
                n_in += 1
            elif k[:1] == "f" and ("i" + k[1:]) not in prev:  # received, never handled: missed from there on
                self.in_seq[k[1:]] = int(v) - 1
                self.resumed_in.add(k[1:])
                self.recovering[k[1:].split("/")[1]] = "lost_during_restart"
                n_in += 1
            elif k[:1] == "l":  # samples missed in earlier restarts of this run of the mesh
                self.drops[k[1:]]["lost_during_restart"] = int(v)
            elif k[:1] == "u":  # and samples that never reached it, counted before the crash
                self.drops[k[1:]]["upstream_gap"] = int(v)
        self.resumed_from = {"inputs": n_in, "outputs": n_out}
        self.svc.log.info("resumed after a crash: %d input and %d output seqs from the journal", n_in, n_out)

    def remove_journal(self) -> None:
        j, self.journal = self.journal, None
        if j is not None:
            j.remove()

    def reconcile_alarms(self) -> None:
        """After a restart: clear a restored raised alarm only once the restarted logic has seen enough input for
        its vehicle to decide (``alarm_reconcile_s`` seconds of sample time and ``alarm_reconcile_outputs``
        outputs), and has not raised it again. A restart alone never clears anything; an alarm whose logic has
        declared it (raised or cleared) since is the logic's again."""
        self.reconcile_at = None
        s = self.svc.settings
        need_s = float(getattr(s, "alarm_reconcile_s", 5.0) or 5.0)
        need_n = int(getattr(s, "alarm_reconcile_outputs", 10) or 10)
        with self.lock:
            raised = dict(self.raised)
        for key, vehicle in list(self.reconcile_pending.items()):
            msg = raised.get(key)
            if msg is None or key in self.alarm_declared:
                del self.reconcile_pending[key]  # cleared meanwhile, or decided by the logic itself
                continue
            span = self.last_in_t.get(vehicle, 0.0) - self.first_in_t.get(vehicle, float("inf"))
            if span < need_s or self.out_since_start.get(vehicle, 0) < need_n:
                continue
            del self.reconcile_pending[key]
            fields = {k: v for k, v in msg.items() if k not in ("type", "version", "vehicle", "t_s", "seq")}
            fields.update(state="cleared", service=self.svc.instance,
                          reason=f"cleared after a restart of {self.svc.instance}: the condition is not seen in "
                                 f"{span:.1f} s of input since")
            t = self.last_in_t.get(vehicle, msg["t_s"])
            self.publish(key, "alarm", vehicle, max(t, msg["t_s"]), fields)
        if self.reconcile_pending:
            self.reconcile_at = time.monotonic() + 0.5
        else:
            self.out_since_start.clear()

    # ---- who may steer: calibration parameters -------------------------------------------------
    def cal_params_trusted(self, key: str, msg: dict) -> bool:
        """Adopt ``cal/params`` only as published by a calibration service instance: the rule, answered now.

        The rule: a live instance of role ``calibration`` must report, in its status, this very parameter set
        (same ``param_id``, ``seq`` and ``t_s``) as the last it published on this key (``cal_params_sent``) or as
        one of the :data:`CAL_RECENT` it published there before (``cal_params_recent``): a consumer whose queue
        runs behind (overload) adopts a set that was genuine when sent although a newer one has followed, which
        it adopts in its turn. A put no instance published (a forged or stray parameter set) is refused and
        reported on ``rejects`` (code ``other``, reason "untrusted: ..."). On the secured mesh only services may
        publish ``cal/`` or answer status at all (router ACL), so the check cannot be fooled there.

        This asks and waits (up to :data:`CAL_CONFIRM_TIMEOUT_S`, refusing when no answer reports the set in
        that time). The input path does not: it parks a set the last answers do not report and confirms it
        without blocking the loop (:meth:`cal_params_admit`).
        """
        import zenoh

        if not isinstance(self.session, zenoh.Session) or self.svc.role == "calibration":
            return True
        if self._cal_reported(key, msg):
            return True
        why = "no live calibration service instance reports having published this parameter set"
        try:
            deadline = time.monotonic() + CAL_CONFIRM_TIMEOUT_S
            while why and time.monotonic() < deadline:
                seen: dict[str, list[list]] = {}
                for r in self._cal_query():
                    _cal_note(r, seen)
                self._cal_sent, self._cal_sent_t = seen, time.monotonic()
                if _cal_id(msg) in seen.get(key, ()):
                    why = None
                if why:  # a status asked a moment before the put was sent: ask once more
                    time.sleep(0.05)
        except Exception as e:  # noqa: BLE001 - no confirmation, no adoption
            why = f"confirmation failed ({type(e).__name__})"
        if why is None:
            return True
        self._cal_refuse(key, msg, why)
        return False

    def _cal_reported(self, key: str, msg: dict) -> bool:
        """Whether the calibration instances' last answers (while fresh) report this set on ``key``: one answer
        confirms every set they had sent when they answered (hundreds arrive together when a fleet's vehicles
        first appear)."""
        return (time.monotonic() - self._cal_sent_t < CAL_CONFIRM_TIMEOUT_S
                and _cal_id(msg) in self._cal_sent.get(key, ()))

    def _cal_query(self, handler: Any = None) -> Any:
        """Ask the live calibration instances what they published (``cal_params_sent`` and ``_recent``)."""
        return self.session.get(f"{keys.ROOT}/{keys.SVC}/calibration/*/status?only=cal_params_sent,"
                                "cal_params_recent", handler, timeout=CAL_CONFIRM_TIMEOUT_S,
                                # ahead of data (Zenoh keeps a queue per priority; the reply takes the query's):
                                # under overload a link holds seconds of queued frames
                                priority=zconf.control_priority())

    def _cal_refuse(self, key: str, msg: dict, why: str) -> None:
        """Refuse a parameter set as untrusted (reported on ``rejects``, counted ``rejected:other``)."""
        self.reject(key, "other", f"untrusted: calibration parameters on {key} (param_id "
                    f"{str(msg.get('param_id'))[:64]!r}, seq {msg.get('seq')}) not adopted: {why}; only a calibration "
                    f"service instance may set them", "param_id", 0, msg.get("vehicle"), msg.get("t_s"), "cal_params")

    def cal_params_admit(self, info: KeyInfo, msg: dict) -> bool:
        """The input path's step for ``cal/params`` (the rule of :meth:`cal_params_trusted`, without waiting):
        True to dispatch ``msg`` now; False when it is parked to be confirmed later (or refused).

        A set the last answers report, with none parked before it on its key, goes on at once. Any other is
        parked (per key, in arrival order) and the calibration instances are asked from the loop
        (:meth:`_cal_poll`: one query in flight, again every :data:`CAL_REASK_S`; the loop goes on handling
        input meanwhile). When answers report a parked set it is dispatched then, as if it had just come; the
        sets parked before it on its key are superseded: counted ``cal_params_superseded`` (skipped by design:
        the key's parameters are the newer genuine set's, nothing is lost) when reported too, refused as
        untrusted when not (as :meth:`cal_params_trusted` would). A set no answer has reported
        :data:`CAL_GIVE_UP_S` after it came (answers that do not report it, or none) is refused as untrusted.
        Status shows how many sets wait (``cal_params_pending``).
        """
        import zenoh

        if not isinstance(self.session, zenoh.Session) or self.svc.role == "calibration":
            return True
        key = info.key
        parked = self._cal_parked.get(key)
        if self._cal_reported(key, msg):
            if parked:
                self._cal_supersede(key, self._cal_parked.pop(key), self._cal_sent.get(key, ()))
            return True
        if parked is None:
            parked = self._cal_parked[key] = []
        parked.append([info, msg, time.monotonic() + CAL_GIVE_UP_S])
        if len(parked) > CAL_PARKED_MAX:
            self._cal_settled(key, parked.pop(0)[1], f"more than {CAL_PARKED_MAX} parameter sets wait for "
                              "confirmation on this key")
        return False

    def _cal_settled(self, key: str, msg: dict, why: str | None) -> None:
        """A parked set that is not dispatched: refused as untrusted (``why``), else superseded. Either way its
        seq is no gap of the key's stream, and the sample being handled (if any) is not the one refused."""
        cur, self._cur_key = self._cur_key, None
        try:
            if why is None:
                self.count_drop(key, "cal_params_superseded")
            else:
                self._cal_refuse(key, msg, why)
        finally:
            self._cur_key = cur
        if type(msg.get("seq")) is int:
            r = self._refused_seqs.setdefault(key, set())
            if len(r) < 1024:
                r.add(msg["seq"])

    def _cal_supersede(self, key: str, older: list[list], reported: Any) -> None:
        """The parked sets before a set of ``key`` being adopted (see :meth:`cal_params_admit`)."""
        for _, m, _ in older:
            self._cal_settled(key, m, None if _cal_id(m) in reported else
                              "a newer set on this key is confirmed, this one is not reported")

    def _cal_poll(self) -> None:
        """The main loop's step for parked ``cal/params`` sets: read the answers of the query in flight; once it
        is done, dispatch what they report and refuse what has waited :data:`CAL_GIVE_UP_S`; ask again every
        :data:`CAL_REASK_S` while sets wait. Never blocks."""
        import zenoh

        now = time.monotonic()
        if self._cal_ask is not None:
            handler, seen = self._cal_ask
            try:
                while (r := handler.try_recv()) is not None:
                    _cal_note(r, seen)
                return  # the query is still open
            except Exception:  # noqa: BLE001 - closed (zenoh.ZError): every instance answered, or the timeout passed
                pass
            self._cal_ask = None
            self._cal_sent, self._cal_sent_t = seen, time.monotonic()
            for key in list(self._cal_parked):
                parked, reported = self._cal_parked[key], seen.get(key, ())
                j = max((i for i, (_, m, _) in enumerate(parked) if _cal_id(m) in reported), default=-1)
                if j >= 0:
                    self._cal_supersede(key, parked[:j], reported)
                    info, m, _ = parked[j]
                    del parked[:j + 1]
                    self._cur_key, self._cur_rejected = key, False
                    try:
                        self.dispatch(info, m)
                    except Exception as e:  # noqa: BLE001 - as for any input (handle_sample)
                        self._handler_failed(key, e)
                    finally:
                        self._cur_key = None
                while parked and parked[0][2] <= now:
                    self._cal_settled(key, parked.pop(0)[1], f"no live calibration service instance reported "
                                      f"having published it within {CAL_GIVE_UP_S:g} s")
                if not parked:
                    del self._cal_parked[key]
        if self._cal_parked and now >= self._cal_next_ask:
            self._cal_next_ask = now + CAL_REASK_S
            try:
                self._cal_ask = (self._cal_query(zenoh.handlers.FifoChannel(16)), {})
            except Exception as e:  # noqa: BLE001 - no answers this round; the give-up time still applies
                self.last_error = f"cal/params confirmation query failed: {type(e).__name__}: {e}"[:500]

    def reject(self, key: str, code: str, reason: str, field: str | None, payload_len: int,
               vehicle: str | None, t_s: float | None, input_type: str | None) -> None:
        self.rejects_total += 1
        if key == self._cur_key:
            self._cur_rejected = True  # the sample being handled was refused: it moves no stream's seq or clock
        parsed = True
        try:
            info = keys.parse_data(key)
        except keys.KeyError_:
            parsed = False
        # a key outside the contract is counted in one bucket: made-up keys cannot grow the table
        self.drops[key if parsed else keys.BAD_KEY][f"rejected:{code}"] += 1
        if vehicle is None:
            if parsed:
                vehicle = info.vehicle
            else:
                # a malformed key may still name a valid vehicle: report it there
                parts = key.split("/") if isinstance(key, str) else []
                try:
                    vehicle = keys.check_vehicle(parts[1]) if len(parts) > 1 and parts[0] == keys.ROOT else None
                except keys.KeyError_:
                    vehicle = None
        if not vehicle:
            self.log_limited("reject-unroutable", "rejected input on %s (%s): %s", str(key)[:200], code, reason)
            return
        try:
            self.publish(keys.rejects(vehicle), "reject", vehicle, t_s if t_s is not None else time.time(),
                         dict(key=key[:4096], reason=reason[:4096], field=field, code=code, input_type=input_type,
                              payload_len_bytes=int(payload_len), service=self.svc.instance))
        except (SchemaError, keys.KeyError_) as e:  # pragma: no cover - reject of a reject
            self.svc.log.warning("could not report reject on %s: %s", key[:200], e)

    def count_drop(self, key: str, reason: str, n: int = 1) -> None:
        self.drops[key][reason] += n

    def count_join_loss(self, key: str, vehicle: str, reason: str) -> None:
        how = self.recovering.get(vehicle) if self.recovering else None
        if how == "lost_in_takeover":
            self._lost_in_takeover(key, 1)
        elif how == "lost_during_restart":
            self._lost_during_restart(key, 1)
        else:
            self.count_drop(key, reason)

    def count_rebase(self, what: str) -> None:
        """A stream's seq or clock was re-based (one event, however large the jump)."""
        self.rebases[what] += 1

    def log_limited(self, what: str, fmt: str, *args: Any) -> None:
        """Log a warning of kind ``what`` at most once per :data:`LOG_EVERY_S`; the rest are counted."""
        now = time.monotonic()
        last, n = self._log_last.get(what, (float("-inf"), 0))
        if now - last >= LOG_EVERY_S:
            more = f" (+{n} more like it in the last {LOG_EVERY_S:g} s)" if n else ""
            self.svc.log.warning(fmt + more, *args)
            self._log_last[what] = (now, 0)
        else:
            self._log_last[what] = (last, n + 1)

    def state_for(self, vehicle: str) -> Any:
        st = self.vehicle_state.get(vehicle, _MISSING)
        if st is _MISSING:
            st = self.svc.new_vehicle(vehicle)
            self.vehicle_state[vehicle] = st
            if len(self.vehicle_state) <= 100 or len(self.vehicle_state) % 1000 == 0:
                self.svc.log.info("new vehicle %s (%d served)", vehicle, len(self.vehicle_state))
        return st

    # ---- input ----------------------------------------------------------------------------
    def _data_reader(self, handle: Any, after: tuple = (), done: threading.Event | None = None) -> None:
        """Samples of one subscription into the queue: whatever has arrived, up to :data:`READ_BATCH` at once
        (one queue operation for many samples; the loop handles them in arrival order). ``after``: start only once
        these readers are drained (a subscription replacing others: magmesh/frame_subs.py); ``done`` is set when
        this one is (its channel closed and emptied)."""
        try:
            for e in after:
                while not e.wait(0.2):
                    if self.stop_event.is_set():
                        return
            self._data_read(handle)
        finally:
            if done is not None:
                done.set()

    def _data_read(self, handle: Any) -> None:
        first = self._first_rx
        while not self.stop_event.is_set():
            try:
                item = handle.recv()
            except Exception:  # channel closed: session is closing
                return
            batch = []
            while item is not None:
                k = str(item.key_expr)
                if k.startswith(_FLEET):  # a fleet frame: many vehicles, filtered in the main loop
                    batch.append((k, item.payload.to_bytes()))
                elif self.group is not None and self.group.skips(k, item.payload):
                    pass  # another group member's vehicle: never queued (magmesh/group_member.py)
                else:
                    p = item.payload.to_bytes()
                    if k not in first:
                        self._note_first_rx(k, p)
                    batch.append((k, p))
                if len(batch) >= READ_BATCH:
                    break
                try:
                    item = handle.try_recv()
                except Exception:  # noqa: BLE001 - closing: what was read still goes in
                    item = None
            if not batch:
                continue
            ev = ("S", batch, time.monotonic())  # when it was queued: a frame too long in the queue is shed
            while not self.stop_event.is_set():
                try:
                    self.q.put(ev, timeout=0.2)
                    break
                except queue.Full:
                    continue

    def _reader(self, handle: Any, kind: str, after: tuple = (), done: threading.Event | None = None) -> None:
        if kind == "s":
            self._data_reader(handle, after, done)
            return
        while not self.stop_event.is_set():
            try:
                item = handle.recv()
            except Exception:  # channel closed: session is closing
                return
            if kind == "status":
                self._answer_status(item)
                continue
            if kind == "alarms":
                self._answer_alarms(item)
                continue
            ev = ("q", kind, item)
            while not self.stop_event.is_set():
                try:
                    self.q.put(ev, timeout=0.2)
                    break
                except queue.Full:
                    continue

    def _note_first_rx(self, key: str, payload: bytes) -> None:
        """The first sample received on ``key`` (reader thread, once per key): its seq goes to the journal as
        "f" unless the journal already knows the key (handled, or carried over from the run before a crash)."""
        try:
            m = msgpack.unpackb(payload)
            seq = m.get("seq") if isinstance(m, dict) and m.get("type") != "batch" else None
        except Exception:  # noqa: BLE001 - garbage is the input path's to refuse
            seq = None
        with self._rx_lock:
            if key in self._first_rx:
                return
            self._first_rx[key] = seq if isinstance(seq, int) and not isinstance(seq, bool) else None
            j = self.journal
            if j is not None and self._first_rx[key] is not None and ("i" + key) not in j.slot \
                    and ("f" + key) not in j.slot:
                j.set("f" + key, self._first_rx[key])

    def _spawn(self, target: Callable, *args: Any) -> None:
        what = {"s": "data", "__control__": "control"}.get(args[1], args[1]) if len(args) > 1 else "worker"

        def named() -> None:
            zconf.os_thread_name(f"mm-read-{what}" if target == self._reader else f"mm-{what}")
            target(*args)

        t = threading.Thread(target=named, daemon=True, name=f"magmesh-{what}")
        t.start()
        self.threads.append(t)

    def handle_sample(self, key: str, payload: bytes, shed: bool = False) -> None:
        """One received sample, end to end; nothing an input causes reaches the service's loop.

        A batch path calls this once per sample (or :meth:`check_input` then :meth:`dispatch`). ``shed``: it
        waited too long in the queue (:data:`SHED_AFTER_S`); a fleet frame is then shed, anything else handled.
        """
        if key.startswith(_FLEET):
            self._cur_key, self._cur_rejected = key, False
            try:
                self.handle_frame(key, payload, shed)
            except Exception as e:  # noqa: BLE001 - a failure met on an input is counted as lost, never fatal
                self._handler_failed(key, e)
            finally:
                self._cur_key = None
            return
        if self.group is not None and not self.group.admits(key, payload):
            return  # a vehicle another member of the group serves (skipped by design, counted in the group's status)
        self._cur_key, self._cur_rejected = key, False
        try:
            if self.batch_in and key.endswith(_CLEAN_BATCH):
                self.handle_batch(key, payload)
                return
            if self.svc.RAW_BATCHES and key.endswith(_RAW_BATCH):
                info = self._raw_batch_keys.get(key)
                if info is not None and len(payload) <= MAX_PAYLOAD_BYTES["batch"]:
                    # a vehicle's raw batch seen before (its key checked then): what check_input and dispatch
                    # do for a batch, without their general steps
                    now = time.monotonic()
                    self.count_in[key].n += 1
                    self.key_seen[key] = now
                    self.vehicle_seen[info.vehicle] = now
                    self.svc.on_message(info, payload, self.state_for(info.vehicle))
                    return
            got = self.check_input(key, payload)
            if got is not None:
                self.dispatch(*got)
        except Exception as e:  # noqa: BLE001 - a failure met on an input is counted as lost, never fatal
            self._handler_failed(key, e)
        finally:
            self._cur_key = None

    # ---- batches (contract v2) ---------------------------------------------------------------
    def wants(self, key: str) -> bool:
        """Whether one of the service's subscriptions covers the per-stream ``key`` (cached)."""
        w = self._wants.get(key)
        if w is None:
            import zenoh

            ke = zenoh.KeyExpr(key)
            w = any(s.intersects(ke) for s in self._sub_exprs)
            if len(self._wants) < 65536:
                self._wants[key] = w
        return w

    def decode_batch(self, key: str, info: KeyInfo, payload: bytes, check: bool, deferred: bool = False) -> Any:
        """A batch message of ``info.vehicle``, or None once it is rejected (bad payload, or another vehicle's);
        ``check=False`` for batches a service already validated (clean/batch from ingest); ``deferred``: a binary
        batch's values are left to the caller (schemas.batch.binary_problems)."""
        try:
            b = batches.decode(payload, where=key, check=check, deferred=deferred)
        except SchemaError as e:
            self.reject(key, reject_code(e), str(e), e.field, len(payload), info.vehicle, None, "batch")
            return None
        if b.vehicle != info.vehicle:
            self.reject(key, "key", f"field 'vehicle' of {key} is {b.vehicle[:64]!r}, but the key names vehicle "
                        f"{info.vehicle!r}", "vehicle", len(payload), info.vehicle, b.t_s, "batch")
            return None
        return b

    def handle_batch(self, key: str, payload: bytes) -> None:
        """A ``clean/batch`` from ingest: trusted (validated there), so only its structure is read. Its samples
        go to ``on_batch`` whole, or one by one to ``on_message`` in sample-time order; each stream's seq and
        time are tracked as for single samples."""
        try:
            info = keys.parse_data(key)
        except keys.KeyError_ as e:
            self.count_in[keys.BAD_KEY].n += 1
            self.reject(key, "key", str(e), None, len(payload), None, None, None)
            return
        self.count_in[key].n += 1
        self.batches_in += 1
        now = time.monotonic()
        self.key_seen[key] = now
        self.vehicle_seen[info.vehicle] = now
        b = self.decode_batch(key, info, payload, check=False)
        if b is None:
            return
        wanted: list[tuple[KeyInfo, Any]] = []
        for name, c in b.streams.items():
            skey = batches.stream_key("clean", info.vehicle, name)
            if c.n == 0 or not self.wants(skey):
                continue
            wanted.append((keys.parse(skey), c))
            self._batch_accepted(skey, info.vehicle, c)
        if not wanted:
            return
        self._dispatch_streams(key, info, b, wanted)

    def _dispatch_streams(self, key: str, info: KeyInfo, b: Any, wanted: list[tuple[KeyInfo, Any]]) -> None:
        """A vehicle's samples of several streams (a batch's, or its rows of a frame) to ``on_batch`` whole, or
        one by one to ``on_message`` in sample-time order."""
        svc = self.svc
        state = self.state_for(info.vehicle)
        if svc.on_batch is not None:
            b.streams = {c.name: c for _, c in wanted}
            try:
                svc.on_batch(info, b, state)
            except Exception as e:  # noqa: BLE001 - counted as lost on the batch key, never fatal
                self._handler_failed(key, e)
            return
        per = [(si, c.messages(info.vehicle)) for si, c in wanted]
        if len(per) == 1:
            order = [(0, i) for i in range(len(per[0][1]))]
        elif sum(c.n for _, c in wanted) <= 64:  # a vehicle's window: a plain sort beats numpy's call cost
            order = [(j, i) for _, j, i in sorted((t, j, i) for j, (_, c) in enumerate(wanted)
                                                 for i, t in enumerate(c.t_s))]
        else:
            import numpy as np

            t_all = np.concatenate([np.asarray(c.t_s, float) for _, c in wanted])
            src = np.concatenate([np.full(c.n, j) for j, (_, c) in enumerate(wanted)])
            idx = np.concatenate([np.arange(c.n) for _, c in wanted])
            o = np.argsort(t_all, kind="stable")
            order = zip(src[o].tolist(), idx[o].tolist(), strict=True)
        on_message = svc.on_message
        for j, i in order:
            si, msgs = per[j]
            try:
                on_message(si, msgs[i], state)
            except Exception as e:  # noqa: BLE001
                self._handler_failed(si.key, e)

    def _batch_accepted(self, skey: str, vehicle: str, c: Any) -> None:
        last = self.in_seq.get(skey)
        s0, s1 = int(c.seq[0]), int(c.seq[-1])
        if last is not None:
            gap = s0 - last - 1
            if gap > self.seq_jump_max:
                self.count_rebase("seq_jump")
            elif gap > 0:
                if skey in self.takeover_in:
                    self._lost_in_takeover(skey, gap)
                else:
                    self.drops[skey]["upstream_gap"] += gap
            elif gap < 0 and skey not in self.takeover_est:
                self.count_rebase("seq_back")
        if self.group is not None:  # a group member's vehicles may be taken from its journal after a kill -9
            self.takeover_in.discard(skey)
            self.takeover_est.discard(skey)
            if self.journal is not None:
                self.journal.set("i" + skey, s1)
        inner = s1 - s0 + 1 - c.n  # ingest numbers the samples of a stream consecutively
        if inner > 0:
            self.drops[skey]["upstream_gap"] += inner
        self.in_seq[skey] = s1
        if self.group is not None:  # (its answers to the group carry it: group_member._held)
            self.in_seq.set_t(skey, float(c.t_s[-1]))
        self.count_in[skey].n += c.n
        self.key_seen[skey] = time.monotonic()
        t0, t1 = float(min(c.t_s)), float(max(c.t_s))
        if vehicle not in self.first_in_t:
            self.first_in_t[vehicle] = t0
        if t1 > self.last_in_t.get(vehicle, float("-inf")):
            self.last_in_t[vehicle] = t1

    def _lost_during_restart(self, key: str, n: int) -> None:
        """Inputs missed while this instance was down (or held by the process that died): counted, and
        journalled, so the count survives the next crash too."""
        self.drops[key]["lost_during_restart"] += n
        if self.journal is not None:
            self.journal.set("l" + key, self.drops[key]["lost_during_restart"])

    def _lost_in_takeover(self, key: str, gap: int) -> None:
        """Inputs a dead group member had not handled when this one took its vehicle: counted, and journalled
        (the count moves on with the vehicle, through a hand-over or the next failover)."""
        self.drops[key]["lost_in_takeover"] += gap
        if self.journal is not None:
            self.journal.set("t" + key, self.drops[key]["lost_in_takeover"])

    def _handler_failed(self, key: str, e: Exception, n: int = 1) -> None:
        self.last_error = f"{type(e).__name__}: {e}"[:500]
        self.log_limited("handler-error", "handling a sample on %s failed: %s\n%s", str(key)[:200], e,
                         traceback.format_exc(limit=4))
        try:
            info = keys.parse(key)
            k = info.key if info.kind != keys.SVC else keys.BAD_KEY
        except Exception:  # noqa: BLE001
            k = keys.BAD_KEY
        self.count_drop(k, "handler_error", n)

    # ---- fleet frames (contract v3) ----------------------------------------------------------------
    def handle_frame(self, key: str, payload: bytes, shed: bool = False) -> None:
        """A fleet frame: decoded once, cut to the vehicles and streams this service takes (and, in a group,
        holds), each vehicle's stream seq tracked as for single samples (gaps counted as loss, the journal
        written after the handler), then handed to ``on_frame`` whole or to the per-vehicle handlers.
        ``shed``: the same, but the rows go to no handler and are counted lost as ``shed_behind``."""
        got = self._frame_in(key, payload)
        if got is not None:
            self._frame_rows(key, got[0], got[1], shed)

    def handle_frames(self, key: str, payloads: list[bytes]) -> None:
        """Frames of one key that waited in the queue together, in their order: each decoded, checked and counted
        as alone (:meth:`_frame_in`), then each run of them that carries the same vehicle list, the same group
        holdings and the same columns handled as one frame (:meth:`_frame_rows`): each stream's rows in one
        array, each vehicle's in time order, seqs tracked across them as across frames. A service that fell
        behind its input so pays a frame's fixed costs (decoding aside) once per run, not once per frame."""
        run: list[tuple[Any, Any]] = []
        for p in payloads:
            self._cur_key, self._cur_rejected = key, False
            try:
                got = self._frame_in(key, p)
            except Exception as e:  # noqa: BLE001 - counted as lost, as handle_sample does
                self._handler_failed(key, e)
                continue
            if got is None:
                continue
            if run and not _mergeable(run[0], got):
                self._frame_run(key, run)
                run = []
            run.append(got)
        if run:
            self._frame_run(key, run)
        self._cur_key = None

    def _frame_run(self, key: str, run: list[tuple[Any, Any]]) -> None:
        self._cur_key, self._cur_rejected = key, False
        try:
            if len(run) == 1:
                self._frame_rows(key, run[0][0], run[0][1], False)
                return
            frs = [f for f, _ in run]
            streams: dict[str, fleetframe.Stream] = {}
            for name in dict.fromkeys(n for f in frs for n in f.streams):
                parts = [f.streams[name] for f in frs if name in f.streams and f.streams[name].n]
                if not parts:
                    continue
                st = fleetframe.concat(parts) if len(parts) > 1 else parts[0]
                if len(parts) > 1:
                    st = st.take(np.argsort(st.vi, kind="stable"))  # (each part by vehicle, then time)
                streams[name] = st
            last = frs[-1]
            self.frames_merged += len(run) - 1
            self._frame_rows(key, fleetframe.Frame(last.shard, last.kind, max(f.t_s for f in frs), last.seq,
                                                   last.vehicles, streams), run[0][1], False)
        except Exception as e:  # noqa: BLE001 - counted as lost on the frame key, never fatal
            self._handler_failed(key, e)

    def _frame_in(self, key: str, payload: bytes) -> tuple[Any, Any] | None:
        """A frame decoded, checked and counted (its seq): ``(frame, the group's admitted mask or None)``, or None
        when it is refused or holds none of this member's vehicles."""
        info = keys.parse(key)
        kind = info.rest[1]
        fs = self.frame_subs
        if fs is not None:
            # a key not received for a while because this member narrowed its subscriptions: the frames between
            # were skipped by design (none of its vehicles), not missed
            self._frame_resumed = self.key_seen.get(key, float("inf")) < fs.switched_at
        now = self.key_seen[key] = time.monotonic()
        admitted = None
        if self.group is not None:
            pk = fleetframe.peek(payload)
            if pk is not None and pk[0] == info.rest[0] and pk[1] == kind:
                if fs is not None and fs.duplicate(key, pk[2], self.frame_seq_in.get(key)):
                    return None  # delivered again while the subscriptions changed (magmesh/frame_subs.py)
                # in a group, a frame of none of this member's vehicles (co-partitioned stages: another member's
                # upstream shard) is seen from its header alone; its owner decodes and checks the rest
                admitted = self._group_admitted(pk[3], kind, pk[4])
                if fs is not None:
                    fs.noted(kind, pk[0], bool(admitted.any()), now)
                if not admitted.any():
                    self._frame_seen(key, pk[2])
                    return None
        try:
            fr = fleetframe.decode(payload, where=key)
        except SchemaError as e:
            self.rejects_total += 1
            self.count_in[key].n += 1
            self.drops[key][f"rejected:{reject_code(e)}"] += 1
            self.log_limited("frame-refused", "refused a frame on %s: %s", key[:200], e)
            return None
        if fr.kind != kind or fr.shard != info.rest[0]:
            self.rejects_total += 1
            self.count_in[key].n += 1
            self.drops[key]["rejected:key"] += 1
            self.log_limited("frame-refused", "refused a frame on %s: it says shard %r, kind %r", key[:200],
                             fr.shard[:64], fr.kind)
            return None
        self._frame_seen(key, fr.seq)
        if self.group is not None and admitted is None:
            admitted = self._group_admitted(fr.vehicles, kind, list(fr.streams))
        if admitted is not None and not admitted.any():
            return None  # another group member's vehicles only (co-partitioned stages: another member's shard)
        return fr, admitted

    def _frame_rows(self, key: str, fr: Any, admitted: Any, shed: bool) -> None:
        """A decoded frame (or a run of them, :meth:`handle_frames`) cut to the streams and vehicles this service
        takes, seq-tracked, handed to the service and journalled."""
        kind = fr.kind
        now = time.monotonic()
        taken: dict[str, fleetframe.Stream] = {}
        done: list[tuple[StreamKeys, np.ndarray, np.ndarray]] = []
        vmask = np.zeros(len(fr.vehicles), bool)
        for name, st in fr.streams.items():
            if st.n == 0:
                continue
            sk = self._stream_keys(key, kind, name, fr.vehicles)
            want = sk.wanted if admitted is None else (sk.wanted & admitted)
            if not want.any():
                continue
            rows = want[st.vi]
            if not rows.all():
                st = st.take(rows)
                if st.n == 0:
                    continue
            g_vi, starts, ends = st.groups()
            self._frame_seqs(sk, st, g_vi, starts, ends)
            self.count_in[key].n += st.n
            vmask[g_vi] = True
            taken[name] = st
            done.append((sk, g_vi, st.seq[ends - 1]))
        if not taken:
            return
        self._frame_times(fr.vehicles, vmask, taken, now)
        sub = fleetframe.Frame(fr.shard, kind, fr.t_s, fr.seq, fr.vehicles, taken)
        if shed:
            self.drops[key]["shed_behind"] += sub.n
            self.frames_shed += 1
        elif self.svc.on_frame is not None:
            try:
                self.svc.on_frame(sub)
            except Exception as e:  # noqa: BLE001 - counted as lost on the frame key, never fatal
                self._handler_failed(key, e, sub.n)
        else:
            self._frame_per_vehicle(key, kind, sub)
        self._journal_frame(done)

    def _stream_keys(self, key: str, kind: str, name: str, vehicles: list[str]) -> StreamKeys:
        sk = self._fkeys.get((key, name))
        if sk is None or sk.generation != self.in_seq.generation or sk.vehicles != vehicles:
            sk = StreamKeys(vehicles, kind, name, self.in_seq, self.wants)
            if len(self._fkeys) > 4096:
                self._fkeys.clear()
            self._fkeys[(key, name)] = sk
        return sk

    def _frame_seen(self, key: str, seq: int) -> None:
        """A frame taken in on ``key``: counted, and the frames missed before it (a gap in its seq)."""
        self.frames_in += 1
        last = self.frame_seq_in.get(key)
        if last is not None and seq > last + 1 and not self._frame_resumed:
            self.frames_missed += seq - last - 1
        self.frame_seq_in[key] = seq

    def _group_admitted(self, vehicles: list[str], kind: str, stream_names: list[str]) -> np.ndarray:
        """Which of a frame's vehicles this group member handles now (held, warming or being handed over)."""
        name = stream_names[0] if stream_names else "imu"
        from .frames import stream_key

        return self.group.admitted(vehicles, lambda v: stream_key(kind, v, name))

    def _frame_seqs(self, sk: StreamKeys, st: Any, g_vi: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> None:
        """Seq tracking of each vehicle's rows of one stream, as :meth:`_accepted` does sample by sample."""
        tab = self.in_seq
        slots = sk.slots[g_vi]
        first = st.seq[starts]
        lastq = st.seq[ends - 1]
        prev = tab.arr[slots]
        has = prev != _NO_SEQ
        gap = np.where(has, first - np.where(has, prev, 0) - 1, 0)
        inner = (lastq - first + 1) - (ends - starts)  # each publisher numbers a vehicle's stream consecutively
        odd = np.flatnonzero((gap != 0) | (inner != 0))
        special = self.resumed_in or self.takeover_in
        for j in odd.tolist():
            k = sk.keys[int(g_vi[j])]
            gp = int(gap[j])
            if gp > self.seq_jump_max:
                self.count_rebase("seq_jump")
            elif gp > 0:
                if k in self.takeover_in:
                    self._lost_in_takeover(k, gp)
                elif k in self.resumed_in:
                    self._lost_during_restart(k, gp)
                    if len(self.restart_gaps) < STATUS_TOP_KEYS or k in self.restart_gaps:
                        self.restart_gaps.setdefault(k, []).append([int(prev[j]) + 1, int(first[j]) - 1])
                else:
                    self.drops[k]["upstream_gap"] += gp
                    if self.journal is not None:
                        self.journal.set("u" + k, self.drops[k]["upstream_gap"])
            elif gp < 0 and k not in self.takeover_est:
                self.count_rebase("seq_back")
            if inner[j] > 0:
                self.drops[k]["upstream_gap"] += int(inner[j])
        if special:
            for i in g_vi.tolist():
                k = sk.keys[i]
                self.resumed_in.discard(k)
                self.takeover_in.discard(k)
                self.takeover_est.discard(k)
        tab.arr[slots] = lastq
        tab.tarr[slots] = st.t_s[ends - 1]

    def _frame_times(self, vehicles: list[str], vmask: np.ndarray, taken: dict, now: float) -> None:
        """Each vehicle's first and latest input sample time and when it was last heard (swap cuts, group
        hand-overs, eviction): gathered in arrays for the frame's vehicle list, written into the per-vehicle
        maps when those are next read."""
        p = self._times_pending.get(id(vehicles))
        if p is None or p[0] is not vehicles:
            if p is not None or len(self._times_pending) > 64:  # (another list once had this id: its times first)
                self._sync_times()
            n = len(vehicles)
            p = self._times_pending[id(vehicles)] = [vehicles, np.full(n, np.inf), np.full(n, -np.inf),
                                                     np.full(n, -np.inf)]
        t_min, t_max, seen = p[1], p[2], p[3]
        for st in taken.values():
            np.minimum.at(t_min, st.vi, st.t_s)
            np.maximum.at(t_max, st.vi, st.t_s)
        seen[vmask] = now

    def _sync_times(self) -> None:
        """Write what frames gathered into the per-vehicle time maps."""
        pending, self._times_pending = self._times_pending, {}
        first, last, seen = self._first_in_t, self._last_in_t, self._vehicle_seen
        for vehicles, t_min, t_max, heard in pending.values():
            for i in np.flatnonzero(heard > -np.inf).tolist():
                v = vehicles[i]
                if v not in first:
                    first[v] = float(t_min[i])
                t = float(t_max[i])
                if t > last.get(v, -np.inf):
                    last[v] = t
                seen[v] = float(heard[i])

    @property
    def first_in_t(self) -> dict[str, float]:
        """Each vehicle's first input sample time."""
        if self._times_pending:
            self._sync_times()
        return self._first_in_t

    @property
    def last_in_t(self) -> dict[str, float]:
        """Each vehicle's latest input sample time (a swap's or hand-over's cut is chosen from it)."""
        if self._times_pending:
            self._sync_times()
        return self._last_in_t

    @property
    def vehicle_seen(self) -> dict[str, float]:
        """When each vehicle was last heard (monotonic s; eviction)."""
        if self._times_pending:
            self._sync_times()
        return self._vehicle_seen

    def _journal_frame(self, done: list) -> None:
        """After the handler: each vehicle's stream is handled up to its last seq in the frame (a kill -9
        before this line counts the frame's samples as missed at the restart)."""
        j = self.journal
        arr = j.array() if j is not None else None
        if arr is None:
            return
        for sk, g_vi, lastq in done:
            if sk.jslots is None or sk.jslots.shape[0] != len(sk.keys):
                sk.jslots = np.full(len(sk.keys), -1, np.int64)
            js = sk.jslots[g_vi]
            missing = js < 0
            if missing.any():
                idx = g_vi[missing]
                sk.jslots[idx] = j.slots_of(["i" + sk.keys[i] for i in idx.tolist()])
                js = sk.jslots[g_vi]
            ok = js >= 0
            arr[js[ok]] = lastq[ok]

    def _frame_per_vehicle(self, key: str, kind: str, fr: Any) -> None:
        """A frame for a service without ``on_frame``: each vehicle's rows as if its batch had come alone."""
        from .frames import stream_key

        per: dict[int, list] = {}
        for name, st in fr.streams.items():
            g_vi, starts, ends = st.groups()
            for i, a, b in zip(g_vi.tolist(), starts.tolist(), ends.tolist(), strict=True):
                per.setdefault(i, []).append((name, st, a, b))
        for i, parts in per.items():
            v = fr.vehicles[i]
            wanted = []
            for name, st, a, b in parts:
                wanted.append((keys.parse(stream_key(kind, v, name)), _FrameRows(name, st, a, b)))
            vinfo = keys.parse(wanted[0][0].key)
            self._dispatch_streams(key, vinfo, batches.Batch(v, float(fr.t_s), fr.seq), wanted)

    @property
    def seq_jump_max(self) -> int:
        return int(getattr(self.svc.settings, "seq_jump_max", SEQ_JUMP_MAX) or SEQ_JUMP_MAX)

    def _behind(self, queued_at: float, shed_after: float) -> bool:
        """Whether input queued at ``queued_at`` is shed: it waited longer than ``shed_after`` and every input
        handled for ``shed_after`` before it had waited that long too (a stage that stays behind). A stall's
        backlog is worked off in less, so it is handled, not shed."""
        now = time.monotonic()
        if now - queued_at <= shed_after:
            self._behind_since = None
            return False
        if self._behind_since is None:
            self._behind_since = now
        return now - self._behind_since >= shed_after

    def shedding(self, queued_at: float | None) -> bool:
        """Whether a window whose oldest input was queued at ``queued_at`` is shed now (ingest's frames): late by
        more than ``shed_after_s`` while the loop has been behind for that long (see :meth:`_behind`)."""
        shed_after = self.shed_after_s
        now = time.monotonic()
        return bool(shed_after and queued_at is not None and now - queued_at > shed_after
                    and self._behind_since is not None and now - self._behind_since >= shed_after)

    @property
    def shed_after_s(self) -> float:
        v = getattr(self.svc.settings, "shed_after_s", None)
        return SHED_AFTER_S if v is None else max(0.0, float(v))

    @property
    def evict_idle_s(self) -> float:
        return float(getattr(self.svc.settings, "evict_idle_s", EVICT_IDLE_S) or EVICT_IDLE_S)

    def check_input(self, key: str, payload: bytes) -> tuple[KeyInfo, Any] | None:
        """Key, size, decoding and header checks of one input; a refusal is reported and gives None."""
        try:
            info = keys.parse_data(key)
            mtype = keys.message_type(key)
        except keys.KeyError_ as e:
            self.count_in[keys.BAD_KEY].n += 1
            self.reject(key, "key", str(e), None, len(payload), None, None, None)
            return None
        now = time.monotonic()
        self.count_in[key].n += 1
        self.key_seen[key] = now
        self.vehicle_seen[info.vehicle] = now
        limit = MAX_PAYLOAD_BYTES.get(mtype, MAX_PAYLOAD_DEFAULT)
        if len(payload) > limit:
            self.reject(key, "decode", f"payload of {key} is {len(payload)} bytes, more than the {limit} bytes a "
                        f"{mtype} message may take: not decoded", "<payload>", len(payload), info.vehicle, None, None)
            return None
        if mtype == "batch":  # contract v2 raw batches: validated by the service that takes them (ingest)
            if self.svc.RAW_BATCHES:
                if info.kind == "raw" and len(self._raw_batch_keys) < 65536:
                    self._raw_batch_keys[key] = info
                return info, payload
            self.count_drop(key, "batch_not_consumed")
            return None
        if not self.svc.DECODE_INPUTS:
            return info, payload
        try:
            msg = messages.decode(payload, where=key, expected_type=mtype)
        except SchemaError as e:
            self.reject(key, reject_code(e), str(e), e.field, len(payload), info.vehicle, None,
                        messages.peek_type(payload))
            return None
        if msg["vehicle"] != info.vehicle:
            self.reject(key, "key", f"field 'vehicle' of {key} is {msg['vehicle'][:64]!r}, "
                        f"but the key names vehicle {info.vehicle!r}", "vehicle", len(payload),
                        info.vehicle, msg["t_s"], msg["type"])
            return None
        known = _KNOWN_FIELDS.get(mtype)
        extra = [k for k in msg if k not in known] if known is not None else []
        if extra and len(msgpack.packb({k: msg[k] for k in extra}, use_bin_type=True)) > MAX_EXTRA_BYTES:
            for k in extra:  # forward-compatible extras are kept only while small: never amplified downstream
                del msg[k]
            self.count_drop(key, "extra_fields_dropped")
        if mtype == "cal_params" and not self.cal_params_admit(info, msg):
            return None
        return info, msg

    def dispatch(self, info: KeyInfo, msg: Any) -> None:
        """Hand one checked input to the service; an accepted sample then moves its stream's seq tracking."""
        svc = self.svc
        state = self.state_for(info.vehicle)
        if self.journal is not None and isinstance(msg, dict):
            self.journal.begin("i" + info.key, msg["seq"], self.n_sent)  # see resume_journal
        try:
            svc.on_message(info, msg, state)
        except SchemaError as e:
            self.last_error = f"{type(e).__name__}: {e}"[:500]
            self.log_limited("output-invalid", "output failed validation while handling %s: %s", info.key, e)
            self.count_drop(info.key, "handler_error")
        except Exception as e:  # noqa: BLE001
            self._handler_failed(info.key, e)
        if not self._cur_rejected and isinstance(msg, dict):
            self._accepted(info, msg)
        elif isinstance(msg, dict) and type(msg.get("seq")) is int:
            # refused, but delivered: its seq is no gap of the stream (it is counted as rejected already)
            r = self._refused_seqs.setdefault(info.key, set())
            if len(r) < 1024:
                r.add(msg["seq"])

    def _accepted(self, info: KeyInfo, msg: dict) -> None:
        """Seq and time bookkeeping of an accepted input (a refused one never moves them)."""
        key, sq = info.key, msg["seq"]
        last = self.in_seq.get(key)
        refused = self._refused_seqs.pop(key, None) if self._refused_seqs else None
        if last is not None:
            gap = sq - last - 1
            if refused and gap > 0:
                gap -= sum(1 for r in refused if last < r < sq)
            if gap > self.seq_jump_max:
                # one forged or reset counter is one event, not a billion lost samples
                self.count_rebase("seq_jump")
                self.log_limited("seq-rebase", "seq of %s jumped from %d to %d: re-based, not counted as loss",
                                 key, last, sq)
            elif gap > 0:  # lost before it reached us (or while this instance was down): visible, not silent
                if key in self.takeover_in:  # not handled by a group member that died holding the vehicle
                    self._lost_in_takeover(key, gap)
                elif key in self.resumed_in:
                    self._lost_during_restart(key, gap)
                    if len(self.restart_gaps) < STATUS_TOP_KEYS or key in self.restart_gaps:
                        self.restart_gaps.setdefault(key, []).append([last + 1, sq - 1])  # which ones, for status
                else:
                    self.drops[key]["upstream_gap"] += gap
                    if self.journal is not None:  # a count of loss survives this process's own restart too
                        self.journal.set("u" + key, self.drops[key]["upstream_gap"])
            elif gap < 0 and key not in self.takeover_est:
                self.count_rebase("seq_back")  # a publisher that restarted its counter (or a repeat)
        self.in_seq[key] = sq
        if self.group is not None:  # (its answers to the group carry it: group_member._held)
            self.in_seq.set_t(key, msg["t_s"])
        if self.resumed_in:
            self.resumed_in.discard(key)
        if self.takeover_in:
            self.takeover_in.discard(key)
            self.takeover_est.discard(key)
        if self.journal is not None:
            self.journal.set("i" + key, sq)
        t, v = msg["t_s"], info.vehicle
        if v not in self.first_in_t:
            self.first_in_t[v] = t
        if t > self.last_in_t.get(v, float("-inf")):
            self.last_in_t[v] = t

    # ---- bounded state ----------------------------------------------------------------------
    def _protected(self, key: str) -> bool:
        """Alarm and calibration-parameter publishers are never evicted (late joiners read their history)."""
        parts = key.split("/")
        return len(parts) > 2 and (parts[2] == "alarm" or (parts[2] == "cal" and len(parts) > 3 and parts[3] == "params"))

    def _fold_drops(self, key: str) -> None:
        d = self.drops.pop(key, None)
        for r, n in (d or {}).items():
            self.evicted_drops[r] += n

    def evict_idle(self, now: float | None = None) -> int:
        """Free the state of keys and vehicles silent for ``evict_idle_s``; their counts go to the totals."""
        now = time.monotonic() if now is None else now
        cutoff = now - self.evict_idle_s
        n0 = sum(self.evicted.values())
        for k in [k for k, t in list(self.key_seen.items()) if t < cutoff]:
            del self.key_seen[k]
            self._raw_batch_keys.pop(k, None)
            c = self.count_in.pop(k, None)
            self.evicted_in += c.n if c is not None else 0
            self.in_seq.pop(k, None)
            with self._rx_lock:
                self._first_rx.pop(k, None)
            self.resumed_in.discard(k)
            self.takeover_in.discard(k)
            self.takeover_est.discard(k)
            self._refused_seqs.pop(k, None)
            if self.journal is not None:
                self.journal.forget([p + k for p in "iflut"])
            self._fold_drops(k)
            hook = getattr(self.svc, "evict_key", None)
            if hook is not None:
                hook(k)
            self.evicted["keys"] += 1
        with self.lock:
            raised_vehicles = {k.split("/")[1] for k in self.raised}
        # a vehicle with a raised alarm keeps its state however long it is silent
        for v in [v for v, t in list(self.vehicle_seen.items()) if t < cutoff and v not in raised_vehicles]:
            del self.vehicle_seen[v]
            st = self.vehicle_state.pop(v, _MISSING)
            pre = f"{keys.ROOT}/{v}/"
            for table in (self.in_seq, self.seq):  # a frame-tracked key's slot serves another key later
                for k in [k for k in table.slot if k.startswith(pre)]:
                    if table is self.in_seq or not self._protected(k):
                        table.free_slot(k)
            self.first_in_t.pop(v, None)
            self.last_in_t.pop(v, None)
            self.recovering.pop(v, None)
            if st is not _MISSING:
                hook = getattr(self.svc, "evict_vehicle", None)
                if hook is not None:
                    hook(v, st)
                self.evicted["vehicles"] += 1
        for k, c in list(self.count_out.items()):
            n_then, since = self._out_idle.get(k, (-1, now))
            if c.n != n_then:
                self._out_idle[k] = (c.n, now)
                continue
            if since >= cutoff or self._protected(k):
                continue
            pub = self.publishers.pop(k, None)
            rc = self._row_cache.pop(k, None)
            if rc is not None:
                rc[3].close()
            if pub is not None and hasattr(pub, "undeclare"):
                try:
                    pub.undeclare()
                except Exception:  # noqa: BLE001 - a closing session
                    pass
            self.evicted_out += c.n
            del self.count_out[k]
            self.seq.pop(k, None)
            self._out_idle.pop(k, None)
            self._fold_drops(k)
            if self.journal is not None:
                self.journal.forget(["o" + k])
            self.evicted["publishers"] += 1
        n = sum(self.evicted.values()) - n0
        if n:
            self.svc.log.info("freed the state of %d idle key(s)/vehicle(s) (silent for %g s)", n, self.evict_idle_s)
        return n

    def counters(self) -> dict:
        """Drops by category: lost, rejected, skipped (each by reason, with totals), evicted keys included."""
        cats: dict[str, dict[str, int]] = {"lost": defaultdict(int), "rejected": defaultdict(int),
                                           "skipped": defaultdict(int)}
        for v in list(self.drops.values()):
            for r, n in list(v.items()):
                cats[drop_category(r)][r] += n
        for r, n in list(self.evicted_drops.items()):
            cats[drop_category(r)][r] += n
        out: dict = {}
        for c in ("lost", "rejected", "skipped"):
            out[f"{c}_total"] = sum(cats[c].values())
            out[c] = {r.removeprefix("rejected:"): n for r, n in sorted(cats[c].items())}
        return out

    # ---- queries --------------------------------------------------------------------------
    def status(self) -> dict:
        now = time.monotonic()
        with self.lock:
            dt = now - self.last_rate_mono
            if dt >= 1.0:
                for c in list(self.count_in.values()) + list(self.count_out.values()):
                    c.rate = (c.n - c.n_prev) / dt
                    c.n_prev = c.n
                self.last_rate_mono = now
            st = {
                "type": "status",
                "version": 1,
                "role": self.svc.role,
                "impl": self.svc.impl,
                "instance": self.svc.instance,
                "pid": os.getpid(),
                "host": os.uname().nodename,
                "magmesh_version": __version__,
                "uptime_s": round(now - self.started_mono, 3),
                "rss_kb": _rss_kb(),
                "py_heap_blocks": sys.getallocatedblocks(),  # Python objects' memory blocks (a leak shows here)
                "vehicle_pattern": self.svc.vehicle_pattern,
                **self.counters(),
                "rebases": dict(self.rebases),
                "evicted": dict(self.evicted),
                "vehicles": sorted(self.vehicle_state)[:STATUS_TOP_KEYS],
                "vehicles_total": len(self.vehicle_state),
                "consumes": declare.consumes(self.svc),
                "produces": declare.produces(self.svc),
                "in": {k: {"n": c.n, "rate_hz": round(c.rate, 2)} for k, c in _top(self.count_in, _n)},
                "out": {k: {"n": c.n, "rate_hz": round(c.rate, 2)} for k, c in _top(self.count_out, _n)},
                "in_keys": len(self.count_in),
                "out_keys": len(self.count_out),
                "in_total": sum(c.n for c in list(self.count_in.values())) + self.evicted_in,
                "batches_in": self.batches_in,  # contract v2: in_total counts batches and their samples
                "batches_out": self.batches_out,
                "frames_in": self.frames_in,  # contract v3: in/out count a frame key's rows
                "frames_out": self.frames_out,
                "frames_missed": self.frames_missed,
                "frames_shed": self.frames_shed,
                "frames_merged": self.frames_merged,  # frames handled within a run of queued frames of their key
                # a group member's frame subscriptions: the kinds narrowed to one upstream shard (magmesh/frame_subs.py)
                "frame_subs": self.frame_subs.status() if self.frame_subs is not None else None,
                "out_total": sum(c.n for c in list(self.count_out.values())) + self.evicted_out,
                # per-vehicle rows numbered (in out) but not put while no subscriber matched their key: skipped by
                # design, nothing lost (a subscriber that comes sees the key's seq from where it stands)
                "out_unwatched": dict(self.unwatched),
                "rejects": self.rejects_total,
                "drops": {k: dict(v) for k, v in _top(self.drops, _sum)},
                "drops_total": sum(sum(v.values()) for v in list(self.drops.values())) + sum(self.evicted_drops.values()),
                "queue_depth": self.q.qsize(),
                "last_error": self.last_error,
                "settings": _plain(self.svc.settings) if self.svc.settings is not None else {},
                "alarms_raised": sorted(self.raised),
                "mode": self.mode,
                "holds_role": self.mode in ("active", "retiring"),
                "suppressed": self.suppressed,
                "cal_params_sent": dict(list(self.params_sent.items())[:4096]),
                "cal_params_pending": sum(len(v) for v in list(self._cal_parked.values())),  # wait for confirmation
                "resumed_from_journal": self.resumed_from,
                "restart_gaps": {k: v[-10:] for k, v in self.restart_gaps.items()},  # seq ranges lost_during_restart
            }
            if self.group is not None:
                st["group"] = self.group.status()
        try:
            st.update(_plain(self.svc.status_extra()))
        except Exception as e:  # status must always answer
            st["status_extra_error"] = f"{type(e).__name__}: {e}"
        return st

    def _answer_status(self, query: Any) -> None:
        """The status; with the selector parameter ``only=name[,name...]`` just those entries (a service checking
        calibration parameters asks for ``cal_params_sent`` alone, not for every vehicle's state)."""
        try:
            only = None
            try:
                params = dict(query.parameters) if query.parameters is not None else {}
                only = params.get("only")
            except Exception:  # noqa: BLE001 - a selector this runtime cannot read: the whole status
                only = None
            if only:
                names = [n for n in str(only).split(",") if n][:16]
                with self.lock:
                    st = {"type": "status", "version": 1, "role": self.svc.role, "instance": self.svc.instance}
                    if "cal_params_sent" in names:
                        st["cal_params_sent"] = dict(list(self.params_sent.items())[:65536])
                    if "cal_params_recent" in names:
                        st["cal_params_recent"] = {k: list(v) for k, v in list(self.params_recent.items())[:65536]}
                payload = msgpack.packb(st, use_bin_type=True)
            else:
                payload = msgpack.packb(self.status(), use_bin_type=True)
            skey = keys.svc_status(self.svc.role, self.svc.instance)
            query.reply(skey, payload, encoding=_encoding(skey))  # at the query's priority (Zenoh's rule)
        except Exception as e:
            self.last_error = f"status reply failed: {e}"
        finally:
            query.drop()

    def _answer_alarms(self, query: Any) -> None:
        import zenoh

        try:
            if self.mode not in ("active", "retiring"):  # only the instance holding the role speaks for its alarms
                return
            qke = query.key_expr
            with self.lock:
                raised = list(self.raised.items())
            for key, msg in raised:
                if self.group is not None and not self.group.holds(msg.get("vehicle")):
                    continue  # a group member speaks only for the vehicles it holds (not one restored or handed over)
                if qke.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, messages.encode(msg, check=False), encoding=_encoding(key))
        except Exception as e:
            self.last_error = f"alarm reply failed: {e}"
        finally:
            query.drop()

    def control(self, req: dict) -> dict:
        """Hand-over control, run in the main loop so it is ordered with message handling."""
        op = req.get("op")
        if isinstance(op, str) and op.startswith("g_"):
            if self.group is None:
                return {"ok": False, "error": f"{self.svc.instance} is not in a group"}
            return self.group.control(req)
        if op == "state":
            pass
        elif op == "arm":  # new instance: hold outputs at or after the cut
            self.cut = {k: float(v) for k, v in req["cut"].items()}
        elif op == "retire":  # old instance: publish only before the cut, hold the rest
            self.cut = {k: float(v) for k, v in req["cut"].items()}
            self.passed_cut = set()
            self.mode = "retiring"
        elif op == "takeover":  # new instance: continue the old one's seq and alarm state, then publish
            for k, v in req.get("seqs", {}).items():
                self.seq[k] = max(int(v), self.seq.get(k, -1))
            self.alarm_published = dict(req.get("alarms", {}))
            self.alarm_adopted += 1
            with self.lock:
                self.raised = {k: m for k, m in req.get("raised", {}).items()}
            self.mode = "active"
            held, self.held = self.held, []
            self._release_held(held)
            # the cut stays until this instance's own outputs pass it (it may still lag behind the old holder)
            self.svc.log.info("took over the role: %d held outputs published", len(held))
        elif op == "release":  # old instance: the new one has taken over; publish nothing more
            self.mode = "retired"
            self.held = []
        elif op == "resume":  # old instance: the hand-over failed; publish what was held and carry on
            self.mode = "active"
            held, self.held = self.held, []
            self._release_held(held)
            self.cut = {}
            self.svc.log.warning("hand-over aborted: resumed with %d held outputs", len(held))
        else:
            return {"ok": False, "error": f"unknown control op {op!r}"}
        with self.lock:
            raised = dict(self.raised)
        return {"ok": True, "mode": self.mode, "instance": self.svc.instance, "impl": self.svc.impl,
                "seqs": dict(self.seq), "alarms": dict(self.alarm_published), "raised": raised,
                "first_in_t": dict(self.first_in_t), "last_in_t": dict(self.last_in_t),
                "held": len(self.held), "passed_cut": sorted(self.passed_cut),
                "ready": self.mode == "retiring" and set(self.cut) <= self.passed_cut}

    def _handle_control(self, query: Any) -> None:
        try:
            req = msgpack.unpackb(query.payload.to_bytes()) if query.payload is not None else {}
            result = self.control(req)
        except Exception as e:
            result = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        try:
            ckey = keys.svc_control(self.svc.role, self.svc.instance)
            query.reply(ckey, msgpack.packb(result, use_bin_type=True), encoding=_encoding(ckey))
        finally:
            query.drop()

    def handle_query(self, name: str, query: Any) -> None:
        if name == "__control__":
            self._handle_control(query)
            return
        fn = self.extra_qables[name]
        try:
            params = dict(query.parameters) if query.parameters is not None else {}
            for key, msg in fn(str(query.key_expr), params):
                query.reply(key, messages.encode(msg) if isinstance(msg, dict) else bytes(msg), encoding=_encoding(key))
        except Exception as e:
            self.last_error = f"query {name} failed: {e}"
            try:
                query.reply_err(f"{type(e).__name__}: {e}".encode())
            except Exception:
                pass
        finally:
            query.drop()

    # ---- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        import zenoh

        svc = self.svc
        subs = list(svc.subscriptions())
        self._sub_exprs = [zenoh.KeyExpr(k) for k in subs]
        # contract v2: a service consuming clean/ streams also takes the vehicle's clean batches (ingest's
        # output = batches), unbatched for it here; nothing in the service changes
        for kexpr in list(subs):
            parts = kexpr.split("/")
            if len(parts) >= 4 and parts[0] == keys.ROOT and parts[2] == "clean":
                bk = f"{keys.ROOT}/{parts[1]}/clean/{keys.BATCH}"
                if not any(zenoh.KeyExpr(s).includes(zenoh.KeyExpr(bk)) for s in subs):
                    subs.append(bk)
        any_batch = zenoh.KeyExpr(f"{keys.ROOT}/*/clean/{keys.BATCH}")
        self.batch_in = svc.DECODE_INPUTS and any(zenoh.KeyExpr(s).intersects(any_batch) for s in subs)
        # contract v3: the per-vehicle clean/, cal/mag and dmc streams also travel in fleet frames (ingest's
        # output = frames, calibration's and the detector's frames); a service subscribed to them takes those
        # frames too, filtered here to the vehicles and streams it subscribes to
        frame_kinds: list[str] = []
        if svc.FRAME_INPUT and svc.DECODE_INPUTS:
            kinds = frame_kinds_for(svc.subscriptions())
            frame_kinds = list(kinds)
            if not svc.group:  # (a group member's: magmesh/frame_subs.py, below)
                for kind in kinds:
                    subs.append(keys.fleet_frames(kind))
            if "dmc" in kinds:
                # the detector publishes every verdict per vehicle (for outside users) and in its dmc frames with
                # the same seq: a service takes them from the frames only, never twice
                subs = [k for k in subs if not _is_dmc_key(k)]
        for kexpr in subs:
            sub = self.session.declare_subscriber(kexpr, zenoh.handlers.FifoChannel(FIFO_CAPACITY))
            self.subs.append(sub)
            self._spawn(self._reader, sub, "s")
        qs = self.session.declare_queryable(keys.svc_status(svc.role, svc.instance), zenoh.handlers.FifoChannel(64))
        self.qables.append(qs)
        self._spawn(self._reader, qs, "status")
        qc = self.session.declare_queryable(keys.svc_control(svc.role, svc.instance), zenoh.handlers.FifoChannel(16))
        self.qables.append(qc)
        self._spawn(self._reader, qc, "__control__")
        qa = self.session.declare_queryable(keys.alarms_all(svc.vehicle_pattern), zenoh.handlers.FifoChannel(64))
        self.qables.append(qa)
        self._spawn(self._reader, qa, "alarms")
        for kexpr, fn in svc.queryables().items():
            self.extra_qables[kexpr] = fn
            qx = self.session.declare_queryable(kexpr, zenoh.handlers.FifoChannel(256))
            self.qables.append(qx)
            self._spawn(self._reader, qx, kexpr)
        if self.mode == "active":
            self.restore_alarms()
        self.resume_journal()
        svc.on_start()
        self.token = self.session.liveliness().declare_token(keys.svc_token(svc.role, svc.instance))
        if svc.group:
            from .group_member import GroupMember

            self.group = GroupMember(self, svc.group)
            if frame_kinds:
                # every shard's frames, or only its own co-partitioned shard's once that is safe
                from .frame_subs import FrameSubscriptions

                self.frame_subs = FrameSubscriptions(self, frame_kinds)
                self.frame_subs.start()
            self.group.start()
        svc.log.info("started %s/%s (impl %s) on %s", svc.role, svc.instance, svc.impl,
                     ", ".join(svc.subscriptions()) or "no subscriptions")

    def tick_period(self) -> float | None:
        override = getattr(self.svc, "tick_override_s", None)  # e.g. ingest's batch window
        if override:
            return float(override)
        s = self.svc.settings
        t = getattr(s, "tick_s", None) if s is not None else None
        return float(t) if t else None

    def loop(self) -> None:
        zconf.os_thread_name("mm-main")
        tick = self.tick_period()
        next_tick = time.monotonic() + (tick or 0)
        due_at = getattr(self.svc, "tick_due_at", None)  # a service's next deadline: the tick runs then, not later
        shed_after = self.shed_after_s
        while not self.stop_event.is_set():
            if tick and due_at is not None:
                due = due_at()
                if due is not None and due < next_tick:
                    next_tick = due
            timeout = max(0.0, next_tick - time.monotonic()) if tick else 0.5
            if self._cal_parked or self._cal_ask is not None:
                timeout = min(timeout, 0.05)  # parked cal/params wait for answers (_cal_poll)
            if self._pending_ev:
                ev = self._pending_ev.pop()
            else:
                try:
                    ev = self.q.get(timeout=timeout)
                except queue.Empty:
                    ev = None
            if ev is not None:
                if ev[0] == "S":
                    self.cur_queued_at = ev[2]
                    if shed_after and self._behind(ev[2], shed_after):
                        self.log_limited("shed", "running behind: input queued %.1f s ago (shed_after_s %g): "
                                         "fleet frames shed, counted as shed_behind", time.monotonic() - ev[2],
                                         shed_after)
                        for k, p in ev[1]:
                            self.handle_sample(k, p, shed=True)
                    else:
                        items = list(ev[1])
                        # input that queued meanwhile goes with it (frames of one key then handled as one run);
                        # anything else (a query, a group step, input to shed) waits for the next turn, in order
                        while len(items) < DRAIN_ITEMS:
                            try:
                                nxt = self.q.get_nowait()
                            except queue.Empty:
                                break
                            if nxt[0] != "S" or (shed_after and self._behind(nxt[2], shed_after)):
                                self._pending_ev.append(nxt)
                                break
                            items.extend(nxt[1])
                        self._handle_items(items)
                    self.cur_queued_at = None
                elif ev[0] == "s":
                    self.handle_sample(ev[1], ev[2])
                elif ev[0] == "q":
                    self.handle_query(ev[1], ev[2])
                elif ev[0] == "g":  # a group membership step (magmesh/group_member.py), ordered with the input
                    try:
                        ev[1]()
                    except Exception as e:  # noqa: BLE001
                        self.last_error = f"group step failed: {type(e).__name__}: {e}"[:500]
                        self.svc.log.error("group step failed: %s\n%s", e, traceback.format_exc(limit=4))
                elif ev[0] == "stop":
                    break
            if self._cal_parked or self._cal_ask is not None:
                try:
                    self._cal_poll()
                except Exception as e:  # noqa: BLE001 - a failure settling a parked set must never stop the loop
                    self.last_error = f"cal/params confirmation failed: {type(e).__name__}: {e}"[:500]
            if tick and time.monotonic() >= next_tick:
                next_tick = time.monotonic() + tick
                self._safe_tick()
            if self.reconcile_at is not None and time.monotonic() >= self.reconcile_at and self.mode == "active":
                self.reconcile_alarms()
            if time.monotonic() >= self._next_evict:
                self._next_evict = time.monotonic() + min(5.0, max(0.2, self.evict_idle_s / 4))
                try:
                    self.evict_idle()
                except Exception as e:  # noqa: BLE001 - freeing memory must never stop the service
                    self.last_error = f"eviction failed: {type(e).__name__}: {e}"

    def _handle_items(self, items: list[tuple[str, bytes]]) -> None:
        """Queued input in order; consecutive fleet frames (no other input between them) grouped by key, each
        key's frames in their order and handled as runs (:meth:`handle_frames`). Frames of different keys come
        from different publishers, between which Zenoh keeps no order either."""
        seg: dict[str, list[bytes]] = {}
        for k, p in items:
            if k.startswith(_FLEET):
                seg.setdefault(k, []).append(p)
                continue
            if seg:
                self._handle_segment(seg)
                seg = {}
            self.handle_sample(k, p)
        if seg:
            self._handle_segment(seg)

    def _handle_segment(self, seg: dict[str, list[bytes]]) -> None:
        for k, ps in seg.items():
            if len(ps) == 1:
                self.handle_sample(k, ps[0])
            else:
                self.handle_frames(k, ps)

    def _safe_tick(self) -> None:
        try:
            self.svc.on_tick()
        except Exception as e:
            self.last_error = f"{type(e).__name__}: {e}"
            self.svc.log.error("tick failed: %s\n%s", e, traceback.format_exc(limit=4))

    def run_publisher(self) -> None:
        """Main loop of a :class:`SimPublisher`: pace produce() by sample time."""
        svc = self.svc
        speed = float(getattr(svc.settings, "speed", 1.0) or 0.0)
        t0_sample = None
        t0_wall = time.monotonic()
        for t_s, key, msg_type, fields in svc.produce():
            if self.stop_event.is_set():
                break
            if t0_sample is None:  # the clock starts at the first sample, however long producing it took
                t0_sample = t_s
                t0_wall = time.monotonic()
            if speed > 0:
                due = t0_wall + (t_s - t0_sample) / speed
                delay = due - time.monotonic()
                if delay > 0 and self.stop_event.wait(delay):
                    break
            try:
                self.publish(key, msg_type, svc.vehicle, t_s, fields)
            except SchemaError as e:
                self.last_error = str(e)
                self.count_drop(key, "invalid_output")
                svc.log.error("not published: %s", e)
        svc.log.info("source finished")

    def stop(self) -> None:
        self.stop_event.set()
        try:
            self.q.put_nowait(("stop",))
        except queue.Full:
            pass

    def close(self) -> None:
        svc = self.svc
        try:
            svc.on_stop()
        except Exception as e:
            svc.log.error("on_stop failed: %s", e)
        if self.frame_subs is not None:
            self.frame_subs.stop()
        if self.group is not None:
            self.group.stop()
        store = self.__dict__.get("_alarm_store")
        if store is not None and store.appended:  # the log folded into the snapshot
            self._persist_alarms()
            store.close()
        if self.clean_stop and not (self.group is not None and (self.group.owned or self.group.release)):
            self.remove_journal()  # (a group member stopped holding vehicles leaves it to the member taking them)
        try:
            if self.token is not None:
                self.token.undeclare()
        except Exception:
            pass


_MISSING = object()


# ---- process entry point ----------------------------------------------------------------------


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return json.dumps({"t": round(record.created, 3), "level": record.levelname, "logger": record.name,
                           "msg": record.getMessage()})


def setup_logging(level: str = "INFO", as_json: bool = False) -> None:
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(_JsonFormatter() if as_json else logging.Formatter(
        "%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [h]
    root.setLevel(level.upper())


def _program_name(cls: type[Service]) -> str:
    """``python -m PACKAGE`` as the user typed it (not ``__main__.py``)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    name = getattr(spec, "name", None) or ""
    if name.endswith(".__main__"):
        return f"python -m {name[: -len('.__main__')]}"
    return f"python -m {cls.__module__.rsplit('.', 1)[0]}"


def pop_impl_arg(argv: list[str], role: str, implementations: dict, default: str) -> tuple[str, list[str]]:
    """Take ``--impl NAME`` / ``--impl=NAME`` out of a role's argv (the last one wins: a swap appends its own);
    an unknown name exits with the known ones."""
    impl, rest, i = default, [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--impl" and i + 1 < len(argv):
            impl, i = argv[i + 1], i + 2
            continue
        if a.startswith("--impl="):
            impl = a.split("=", 1)[1]
        else:
            rest.append(a)
        i += 1
    if impl not in implementations:
        raise SystemExit(f"{role}: unknown --impl {impl!r}; known: {', '.join(implementations)}")
    return impl, rest


def make_parser(cls: type[Service], implementations: dict[str, type] | None = None) -> argparse.ArgumentParser:
    """The command line of a service. ``implementations`` (name -> class) adds ``--impl`` for a role with
    several (the chosen one's settings are listed)."""
    doc = (sys.modules[cls.__module__].__doc__ or cls.__doc__ or "").strip()
    epilog = (f"role: {cls.role}   implementation: {cls.impl}\n{declare.streams_help(cls)}\n\n"
              f"settings of {cls.impl} (--set NAME=VALUE):\n{settings_help(cls.Settings)}")
    if implementations:
        lines = [f"  {n:<12} {((c.__doc__ or '').strip().splitlines() or [''])[0]}" for n, c in implementations.items()]
        epilog += ("\n\nimplementations (--impl NAME; --impl NAME --help lists its settings):\n" + "\n".join(lines))
    p = argparse.ArgumentParser(prog=_program_name(cls), description=doc, epilog=epilog,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    if implementations:
        p.add_argument("--impl", choices=list(implementations), default=cls.impl,
                       help=f"the implementation to run (default {cls.impl}): {', '.join(implementations)}")
    zconf.add_zenoh_args(p)
    g = p.add_argument_group("magmesh")
    g.add_argument("--instance", default=None, help="instance name (default: <impl>-<pid>)")
    if issubclass(cls, SimPublisher):
        g.add_argument("--vehicle", default=cls.vehicle, help="vehicle id to publish as")
    else:
        g.add_argument("--vehicles", default="*", metavar="PATTERN",
                       help="serve only vehicles matching this key-chunk pattern (sharding), default *")
        g.add_argument("--group", default=None, metavar="NAME",
                       help="share the vehicles with the other live instances NAME-* of this role: each vehicle is "
                            "served by one of them, moved on a join, leave or failure (off by default)")
    g.add_argument("--standby", action="store_true",
                   help="start warm but silent, waiting to take the role over (used by magmesh swap)")
    g.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a setting (repeatable)")
    g.add_argument("--settings-json", default=None, help="settings as one JSON object")
    g.add_argument("--manifest", default=None, help="mesh manifest (TOML) to read vehicle tables from")
    g.add_argument("--log-level", default=os.environ.get("MAGMESH_LOG_LEVEL", "INFO"))
    g.add_argument("--log-json", action="store_true", help="log one JSON object per line")
    return p


def service_from_args(cls: type[Service], args: argparse.Namespace) -> Service:
    values: dict[str, Any] = {}
    if args.settings_json:
        try:
            values.update(json.loads(args.settings_json))
        except (ValueError, TypeError) as e:
            raise SystemExit(f"{cls.role} ({cls.impl}): --settings-json is not one JSON object of settings: {e}") from None
    for item in args.set:
        k, sep, v = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected NAME=VALUE")
        values[k.strip()] = v
    try:
        settings = build_settings(cls.Settings, values)
    except (ValueError, TypeError) as e:  # one paragraph: service, setting, value, what is allowed
        raise SystemExit(f"{cls.role} ({cls.impl}): {' '.join(str(e).split())}. Every setting with its unit and "
                         f"range: {_program_name(cls)} --help") from None
    vehicles_config = {}
    if args.manifest:
        with open(args.manifest, "rb") as f:
            vehicles_config = tomllib.load(f).get("vehicles", {})
    if issubclass(cls, SimPublisher):
        svc = cls(settings, args.instance, "*", vehicles_config)
        svc.vehicle = keys.check_id(args.vehicle)
        if svc.instance == f"{cls.impl}-{os.getpid()}" and args.instance is None:
            svc.instance = f"{cls.impl}-{svc.vehicle}"
    else:
        svc = cls(settings, args.instance, args.vehicles, vehicles_config)
        if getattr(args, "group", None):
            try:
                keys.check_id(args.group, "group name")
            except keys.KeyError_ as e:
                raise SystemExit(f"--group: {e}") from None
            if args.instance is None or not args.instance.startswith(args.group + "-"):
                raise SystemExit(f"--group {args.group}: the instance name must be {args.group}-<n> (give --instance "
                                 f"{args.group}-1, ...): the members of the group are found by that name")
            svc.group = args.group
    return svc


def run(svc: Service, conf: Any, ready: threading.Event | None = None, standby: bool = False) -> None:
    """Open a session, run ``svc`` until stopped (SIGINT/SIGTERM or its source ends), close."""
    import zenoh

    session = zenoh.open(conf)
    runner = Runner(svc, session)
    if standby:
        runner.mode = "standby"

    def _on_signal(signum: int, frame: Any) -> None:
        svc.log.info("signal %d: stopping", signum)
        runner.clean_stop = True  # a planned stop: the seq journal goes (nothing to account for at the next start)
        runner.stop()
        # a hard deadline: never hang on exit
        timer = threading.Timer(STOP_GRACE_S, lambda: (runner.remove_journal(), os._exit(0)))
        timer.daemon = True
        timer.start()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _on_signal)
        signal.signal(signal.SIGTERM, _on_signal)
    try:
        runner.start()
        # what start-up made (modules, compiled kernels, tables) lives as long as the process: out of the
        # collector's way, so its full collections stay short under a fleet's allocation rate
        import gc

        gc.freeze()
        if ready is not None:
            ready.set()
        if isinstance(svc, SimPublisher):
            pub_thread = threading.Thread(target=runner.run_publisher, daemon=True)
            pub_thread.start()
            while pub_thread.is_alive() and not runner.stop_event.is_set():
                pub_thread.join(0.2)
            if not runner.stop_event.is_set():
                # the source ended: keep answering status until stopped
                runner.loop()
        else:
            runner.loop()
        runner.clean_stop = runner.stop_event.is_set()
    finally:
        runner.stop()
        runner.close()
        session.close()
        # the threads that wait in Zenoh (readers, the group's coordination) end once the session is closed: wait
        # for them, so that none is still inside the library when the interpreter finalises (a daemon thread
        # stopped there can abort the process: "FATAL: exception not rethrown")
        deadline = time.monotonic() + 2.0
        group_thread = runner.group._thread if runner.group is not None else None
        for t in [*runner.threads, *([group_thread] if group_thread is not None else [])]:
            t.join(max(0.0, deadline - time.monotonic()))
        svc.log.info("stopped")


def main(cls: type[Service], argv: list[str] | None = None, implementations: dict[str, type] | None = None) -> None:
    parser = make_parser(cls, implementations)
    args = parser.parse_args(argv)
    setup_logging(args.log_level, args.log_json)
    svc = service_from_args(cls, args)
    try:
        conf = zconf.config_from_args(args)
    except Exception as e:
        raise SystemExit(f"{cls.impl}: bad Zenoh configuration: {e}") from None
    run(svc, conf, standby=args.standby)
