"""Ingest on fleet frames (contract v3, ``output = "frames"``): a window of every vehicle's samples decided in one
compiled call, published as one frame.

Each input — a v1 single sample or a v2 batch, already decoded and checked against the contract by the
runtime and :func:`schemas.batch.decode` — is appended to its streams' flat column lists (no object per
sample). When the window is due
(``batch_window_s`` after its first sample, or when it holds ``FLUSH_ROWS`` rows) each stream's rows are
decided together: the physical ranges on whole columns (:func:`services.ingest.fleet.range_ok_mask`), then time
order, duplicates, the stream clocks and seq gaps by :class:`services.ingest.fleet.FleetStreams`, which decides
every row exactly as the per-sample path does. Refused rows are reported on ``rejects`` once per stream, code
and window (the sentence of the first, with the count), and counted per sample; accepted rows go out as one
``magmesh/fleet/{instance}/clean`` frame, each row numbered on its per-vehicle clean key.
"""

from __future__ import annotations

import math
import operator
import time
from typing import Any

import msgspec
import numpy as np

from schemas import batch as batches
from schemas import frame as fleetframe
from schemas import keys
from schemas.messages import MESSAGES

from . import fleet

#: a window holding this many rows is decided and published at once
FLUSH_ROWS = 200_000
#: or this many bytes of binary batches not yet decoded (:meth:`FramingIngest.frame_raw`)
FLUSH_RAW_BYTES = 16 * 1024 * 1024


class _Acc:
    """One stream's rows of the open window. Rows of list inputs (v1 singles, v2 batches) extend flat lists;
    rows of binary batches (version 3) come as numpy arrays and are kept as they are: one concatenation per
    column at the flush, no object per sample either way."""

    __slots__ = ("msg_type", "p_vi", "p_slot", "p_n", "p_now", "p_bid", "t", "seq", "cols", "n", "fields", "shared",
                 "binary")

    def __init__(self, msg_type: str):
        self.msg_type = msg_type
        self.p_vi: list[int] = []  # per input: vehicle index, stream slot, rows, receive time
        self.p_slot: list[int] = []
        self.p_n: list[int] = []
        self.p_now: list[float] = []
        self.p_bid: list[int] = []  # the window's batch the input came in (-1: a single sample)
        self.binary = False  # some input's values are still to be checked (binary batches: binary_problems)
        self.t: list = []  # parts: flat lists (extended while list inputs follow each other) or arrays
        self.seq: list = []
        self.cols: dict[str, list] = {}  # field -> parts, each covering the same rows as t's
        self.n = 0
        self.fields = {f.name: f for f in MESSAGES[msg_type].fields}
        self.shared: dict[str, str | None] = {}  # a str field's one value over every row so far (None: they differ)

    def add_run(self, vis: list, slots: list, ns: list, nows: list, bids: list, ss: list, lay: tuple,
                rows: list[tuple]) -> int:
        """Binary inputs of the fast layout (:func:`schemas.batch.fast_binary`), in their order of arrival: per
        input its vehicle index, slot, rows, receive time, batch and stream struct (one list each), ``rows``
        their columns as :func:`_run_rows` checked them. Adds the rows :meth:`add` would add one by one, each
        column's bytes joined at once. Returns the rows added."""
        self.p_vi.extend(vis)
        self.p_slot.extend(slots)
        self.p_n.extend(ns)
        self.p_now.extend(nows)
        self.p_bid.extend(bids)
        n0 = self.n
        total = sum(ns)
        self.n = n0 + total
        self.binary = True
        self.t.append(b"".join(map(_T_S, ss)))
        self.seq.append(b"".join(map(_SEQ, ss)))
        unset = msgspec.UNSET
        mine = self.cols
        shared = self.shared
        for k, (name, rb) in enumerate(lay):
            vals = [r[k] for r in rows]
            parts = mine.get(name)
            if parts is None:
                if vals.count(unset) == len(vals):
                    continue  # no row has it, nor had any before: no column
                f = self.fields[name]
                parts = mine[name] = [(_blank(f), n0)] if n0 else []
                if f.kind == "str":
                    v0 = vals[0]
                    shared[name] = None if n0 else v0 if type(v0) is str else None
            if rb > 0 and unset not in vals:  # every input's bytes
                parts.append(b"".join(vals))
                continue
            v0 = vals[0]
            if type(v0) is str and vals.count(v0) == len(vals):  # one string for the whole run
                if name in shared and shared[name] != v0:
                    shared[name] = None
                parts.append((v0, total))
                continue
            for v, n in zip(vals, ns, strict=True):  # input by input, as add() does
                tv = type(v)
                if v is unset:
                    parts.append((_blank(self.fields[name]), n))
                    if name in shared:
                        shared[name] = None
                elif tv is bytes:
                    parts.append(v)
                elif tv is str:
                    if name in shared and shared[name] != v:
                        shared[name] = None
                    parts.append((v, n))
                else:
                    if name in shared:
                        shared[name] = None
                    _extend(parts, v)
        return total

    def add(self, vi: int, slot: int, t: Any, seq: Any, cols: dict, now: float, n: int, bid: int) -> None:
        """One input's rows: ``t``/``seq`` and the columns as lists (v1, v2) or bytes (a binary batch); a
        string column may be one string for every row (kept as such: no list is built for it)."""
        self.p_vi.append(vi)
        self.p_slot.append(slot)
        self.p_n.append(n)
        self.p_now.append(now)
        self.p_bid.append(bid)
        n0 = self.n
        self.n = n0 + n
        if type(t) is bytes:
            self.binary = True
            self.t.append(t)
            self.seq.append(seq)
        else:
            _extend(self.t, t)
            _extend(self.seq, seq)
        mine = self.cols
        shared = self.shared
        known = 0
        for name, v in cols.items():
            parts = mine.get(name)
            if parts is None:
                f = self.fields.get(name)
                if f is None:
                    continue
                parts = mine[name] = [(_blank(f), n0)] if n0 else []  # the earlier rows lack it: blanks
                if f.kind == "str":
                    shared[name] = None if n0 else v if type(v) is str else None
            known += 1
            tv = type(v)
            if tv is str:
                if name in shared and shared[name] != v:
                    shared[name] = None
                parts.append((v, n))
            elif tv is bytes:
                parts.append(v)
            else:
                if name in shared:
                    shared[name] = None
                _extend(parts, v)
        if known != len(mine):
            for name, parts in mine.items():  # a field these rows lack: blanks
                if name not in cols:
                    parts.append((_blank(self.fields[name]), n))
                    if name in shared:
                        shared[name] = None

    def rows(self) -> tuple[np.ndarray, ...]:
        """(vehicle index, slot, receive time, batch, t_s, seq) per row."""
        ns = np.array(self.p_n, np.int64)
        return (np.repeat(np.array(self.p_vi, np.uint32), ns), np.repeat(np.array(self.p_slot, np.int32), ns),
                np.repeat(np.array(self.p_now, float), ns), np.repeat(np.array(self.p_bid, np.int64), ns),
                _cat(self.t, "<f8", 1), _cat(self.seq, "<i8", 1))

    def column(self, name: str) -> Any:
        """The window's column: an array for the numeric kinds, one string when every row shares it, else a list."""
        f = self.fields[name]
        parts = self.cols[name]
        if f.kind == "str":
            s = self.shared.get(name)
            if s is not None:
                return s
            return _flat(parts)
        if f.kind == "bool":
            parts = [np.frombuffer(part, "u1").astype(bool).tolist() if type(part) is bytes else part
                     for part in parts]
            flat = _flat(parts)
            return flat if any(x is None for x in flat) else np.asarray(flat, np.uint8)
        w = {"vec3": 3, "mat3": 9, "floats": f.length}.get(f.kind, 1)
        if f.kind in ("float", "vec3", "mat3") or (f.kind == "floats" and f.length):
            if f.nullable:
                blank = _blank(f)
                parts = [[blank if x is None else x for x in part] if type(part) is list else
                         (blank if part[0] is None else part[0], part[1]) if type(part) is tuple else part
                         for part in parts]
            return _cat(parts, "<f8", w)
        if f.kind == "int" and not any(type(p) is tuple and p[0] is None for p in parts):
            return _cat(parts, "<i8", 1).tolist()
        return _flat(parts)


def _run_rows(ss: list, ns: list, spec: tuple) -> list[tuple] | None:
    """The columns of each input of a stream's run (``ss`` their stream structs, ``ns`` their rows; ``spec``: the
    stream's ``(name, message type, layout)`` in :func:`schemas.batch.fast_binary`), or None when some input's
    byte lengths do not hold its ``n`` rows or a magnetometer's sensor is not its stream's — the checks
    :func:`schemas.batch.decode` makes, on the whole run at once."""
    want = {8: [8 * n for n in ns]}
    if list(map(len, map(_T_S, ss))) != want[8] or list(map(len, map(_SEQ, ss))) != want[8]:
        return None
    astuple = msgspec.structs.astuple
    rows = [astuple(s.cols) for s in ss]
    unset = msgspec.UNSET
    sname, _, lay = spec
    for k, (name, rb) in enumerate(lay):
        vals = [r[k] for r in rows]
        if rb > 0:
            absent = vals.count(unset)
            if absent == len(vals):
                continue  # an optional field no input has
            w = want.get(rb)
            if w is None:
                w = want[rb] = [rb * n for n in ns]
            if absent:
                lens = [len(v) if v is not unset else m for v, m in zip(vals, w, strict=True)]
            else:
                lens = list(map(len, vals))
            if lens != w:
                return None
        elif list in map(type, vals) and any(type(v) is list and len(v) != n for v, n in zip(vals, ns, strict=True)):
            return None  # (the types looked at in C first: a string column is mostly one string per input)
        if name == "sensor" and sname.startswith("mag/") and vals.count(sname[4:]) != len(vals):
            return None
    return rows


_VEHICLE, _STREAMS = operator.attrgetter("vehicle"), operator.attrgetter("streams")
_T_S, _SEQ = operator.attrgetter("t_s"), operator.attrgetter("seq")
_FIRST = operator.itemgetter(0, 1)


def _extend(parts: list, v: list) -> None:
    """Rows of a list input: extend the last part when it is a flat list, else start one."""
    if parts and type(parts[-1]) is list:
        parts[-1].extend(v)
    else:
        parts.append(list(v))


def _flat(parts: list) -> list:
    """A column's parts as one flat list of row values."""
    out: list = []
    for p in parts:
        tp = type(p)
        if tp is tuple:
            out.extend([p[0]] * p[1])
        elif tp is list:
            out.extend(p)
        else:
            out.extend(p.tolist())
    return out


def _cat(parts: list, dtype: str, width: int) -> np.ndarray:
    """One array from parts that are flat lists (rows), arrays, little-endian bytes or (value, count) runs."""
    def arr(p: Any) -> np.ndarray:
        tp = type(p)
        if tp is bytes:
            a = np.frombuffer(p, dtype)
            return a.reshape(-1, width) if width > 1 else a
        if tp is tuple:
            return np.asarray([p[0]] * p[1], dtype).reshape((p[1], width) if width > 1 else p[1])
        return np.asarray(p, dtype)

    if not parts:
        return np.zeros((0, width) if width > 1 else 0, dtype)
    if all(type(p) is bytes for p in parts):
        return arr(b"".join(parts))
    if len(parts) == 1:
        return arr(parts[0])
    return np.concatenate([arr(p) for p in parts])


def _blank(f: Any) -> Any:
    """What a row without optional field ``f`` holds in its column (NaN for numbers, else None)."""
    if f.kind == "float":
        return math.nan
    if f.kind in ("vec3", "mat3") or (f.kind == "floats" and f.length):
        return [math.nan] * {"vec3": 3, "mat3": 9}.get(f.kind, f.length or 0)
    return None


class FramingIngest:
    """The frame half of the ingest service (mixed into :class:`services.ingest.service.Ingest`)."""

    @property
    def frame_output(self) -> bool:
        return getattr(self.settings, "output", "singles") == "frames"

    def _fr(self) -> dict:
        d = self.__dict__.get("_fr_d")
        if d is None:
            d = self.__dict__["_fr_d"] = {
                "fs": fleet.FleetStreams(self.settings), "slot": {}, "vehicles": [], "vidx": {}, "window": {},
                "rows": 0, "since": None, "batches": [], "raw": [], "raw_bytes": 0, "names": {}, "queued": None}
        return d

    def _frame_slot(self, fr: dict, vehicle: str, raw_key: str) -> tuple[int, int]:
        vi = fr["vidx"].get(vehicle)
        if vi is None:
            vi = fr["vidx"][vehicle] = len(fr["vehicles"])
            fr["vehicles"] = [*fr["vehicles"], vehicle]  # a new list: consumers see the change
        s = fr["slot"].get(raw_key)
        if s is None:
            s = fr["slot"][raw_key] = fr["fs"].add()
        return vi, s

    # ---- input ----------------------------------------------------------------------------------
    def _note_queued(self, fr: dict) -> None:
        """The window's oldest input by when it was queued (the runtime's queue): a window whose input waited
        longer than ``shed_after_s`` while the stage stays behind is shed (:meth:`frame_flush`)."""
        q = self._rt.cur_queued_at
        if q is not None and (fr["queued"] is None or q < fr["queued"]):
            fr["queued"] = q

    def frame_single(self, info: Any, msg: dict) -> None:
        """A decoded v1 sample into the window."""
        fr = self._fr()
        self._note_queued(fr)
        if fr["raw"]:
            self._settle(fr)  # binary batches that came before this input go in before it
        vi, s = self._frame_slot(fr, info.vehicle, info.key)
        cols = {f.name: [msg[f.name]] for f in MESSAGES[msg["type"]].fields if f.name in msg}
        self._frame_add(fr, batches.stream_name(info), msg["type"], vi, s, [msg["t_s"]], [msg["seq"]], cols,
                        time.monotonic(), 1, -1)

    def frame_raw(self, key: str, info: Any, payload: bytes) -> None:
        """A binary batch (version 3) as it came: decoded with the others of its window when the window is read
        or another kind of input comes (:meth:`_settle`), in one typed pass each."""
        fr = self._fr()
        self._note_queued(fr)
        now = time.monotonic()
        fr["raw"].append((key, info, payload, now))
        fr["raw_bytes"] += len(payload)
        if fr["since"] is None:
            fr["since"] = now
        if fr["raw_bytes"] >= FLUSH_RAW_BYTES:
            self.frame_flush(force=True)

    def _settle(self, fr: dict) -> None:
        """The binary batches :meth:`frame_raw` kept, into the window in their order of arrival: all at once when
        every one is of the usual layout and holds (:meth:`_settle_fast`), else batch by batch, each the fast way
        or through the general path (:meth:`frame_batch`), which decides and reports it as before."""
        raw = fr["raw"]
        if not raw:
            return
        fr["raw"], fr["raw_bytes"] = [], 0
        if self._settle_fast(fr, raw):
            return
        for item in raw:
            if not self._settle_fast(fr, [item]):
                key, info, payload, now = item
                b = self._rt.decode_batch(key, info, payload, check=True, deferred=True)
                if b is not None:
                    self.frame_batch(key, info.vehicle, b, len(payload), now)

    def _settle_fast(self, fr: dict, raw: list) -> bool:
        """Binary batches of the usual layout (:func:`schemas.batch.fast_binary`: structure checked by msgspec, byte
        lengths and sensors here on each stream's run of batches at once) into the window, each stream's run
        joined; False, with nothing changed, when one of them is not of that layout or does not hold."""
        dec, layout = batches.fast_binary()
        decode = dec.decode
        try:
            es = [decode(item[2]) for item in raw]
        except (msgspec.ValidationError, msgspec.DecodeError):
            return False
        vehicles = [item[1].vehicle for item in raw]
        if list(map(_VEHICLE, es)) != vehicles:
            return False
        # per stream (index into layout): each batch's struct of it, or UNSET (transposed in C, no step per batch)
        by_col = list(zip(*map(msgspec.structs.astuple, map(_STREAMS, es))))
        names = fr["names"]
        pers = [names.get(v) for v in vehicles]
        if None in pers:
            return self._settle_batches(fr, raw, es, layout)
        unset = msgspec.UNSET
        streams: list[tuple] = []  # (first batch holding it, j, batches holding it or None for all, structs, rows)
        for j, col in enumerate(by_col):
            if unset not in col:
                ns = [s.n for s in col]
                if 0 not in ns:
                    streams.append((0, j, None, list(col), ns))
                    continue
            elif col.count(unset) == len(col):
                continue
            idx = [i for i, s in enumerate(col) if s is not unset and s.n]
            if idx:
                streams.append((idx[0], j, idx, [col[i] for i in idx], [col[i].n for i in idx]))
        slots_of = {}
        for _, j, idx, _, _ in streams:
            sl = [p[j] for p in pers] if idx is None else [pers[i][j] for i in idx]
            if None in sl:  # a stream of a vehicle not seen before: slots made batch by batch, in arrival order
                return self._settle_batches(fr, raw, es, layout)
            slots_of[j] = sl
        checked = {}
        for _, j, _, ss, ns in streams:
            rows = _run_rows(ss, ns, layout[j])
            if rows is None:  # some batch's lengths are wrong
                return False
            checked[j] = rows
        # every batch holds: in the window, in order (vehicle indices and slots as on arrival)
        blist = fr["batches"]
        bid0 = len(blist)
        blist.extend([(item[0], item[1].vehicle, len(item[2]), e.t_s) for item, e in zip(raw, es, strict=True)])
        nows = [item[3] for item in raw]
        count_in = self._rt.count_in
        window = fr["window"]
        streams.sort(key=_FIRST)  # (the window's streams made in the order their first rows came, as batch by batch)
        for _, j, idx, ss, ns in streams:
            sl = slots_of[j]
            for (key, _, _), n in zip(sl, ns, strict=True):
                count_in[key].n += n
            if idx is None:
                t_now, bids = nows, list(range(bid0, bid0 + len(raw)))
            else:
                t_now, bids = [nows[i] for i in idx], [bid0 + i for i in idx]
            name, mt, lay = layout[j]
            acc = window.get(name)
            if acc is None:
                acc = window[name] = _Acc(mt)
            fr["rows"] += acc.add_run([x[1] for x in sl], [x[2] for x in sl], ns, t_now, bids, ss, lay, checked[j])
        return True

    def _settle_batches(self, fr: dict, raw: list, es: list, layout: tuple) -> bool:
        """:meth:`_settle_fast` batch by batch (decoded: ``es``), when some of them bring a vehicle or a stream
        not seen before: its vehicle index and stream slots are made as the batches come."""
        astuple = msgspec.structs.astuple
        unset = msgspec.UNSET
        got: list[tuple] = []  # per batch: (key, vehicle, payload bytes, t_s, now, its streams [(index, struct)])
        by_stream: dict[int, list] = {}  # stream (index into layout) -> the struct of each batch holding it
        for (key, info, payload, now), e in zip(raw, es, strict=True):
            present = [(j, s) for j, s in enumerate(astuple(e.streams)) if s is not unset and s.n]
            for j, s in present:
                r = by_stream.get(j)
                if r is None:
                    r = by_stream[j] = []
                r.append(s)
            got.append((key, info.vehicle, len(payload), e.t_s, now, present))
        checked = {}
        for j, ss in by_stream.items():
            rows = _run_rows(ss, [s.n for s in ss], layout[j])
            if rows is None:  # some batch's lengths are wrong
                return False
            checked[j] = rows
        blist = fr["batches"]
        count_in = self._rt.count_in
        names = fr["names"]
        runs: dict[int, list] = {j: [] for j in by_stream}
        for key, vehicle, plen, t_b, now, present in got:
            bid = len(blist)
            blist.append((key, vehicle, plen, t_b))
            per = names.get(vehicle)
            for j, s in present:
                slot = per[j] if per is not None else None
                if slot is None:
                    slot = self._stream_slot(fr, vehicle, j, layout)
                    per = names[vehicle]
                count_in[slot[0]].n += s.n
                runs[j].append((slot[1], slot[2], s.n, now, bid, s))
        window = fr["window"]
        for j, run in runs.items():
            name, mt, lay = layout[j]
            acc = window.get(name)
            if acc is None:
                acc = window[name] = _Acc(mt)
            vis, slots, ns, nows, bids, ss = (list(x) for x in zip(*run, strict=True))
            fr["rows"] += acc.add_run(vis, slots, ns, nows, bids, ss, lay, checked[j])
        return True

    def _stream_slot(self, fr: dict, vehicle: str, j: int, layout: tuple) -> tuple[str, int, int]:
        """(raw key, vehicle index, slot) of a vehicle's stream ``layout[j]``, remembered per vehicle until an
        eviction moves an index or frees a slot."""
        per = fr["names"].get(vehicle)
        if per is None:
            per = fr["names"][vehicle] = [None] * len(layout)
        got = per[j]
        if got is None:
            raw_key = batches.stream_key("raw", vehicle, layout[j][0])
            got = per[j] = (raw_key, *self._frame_slot(fr, vehicle, raw_key))
        return got

    def frame_batch(self, key: str, vehicle: str, b: Any, payload_len: int, now: float | None = None) -> None:
        """A decoded v2 batch, or a binary one with its structure checked, into the window, stream by stream."""
        fr = self._fr()
        self._note_queued(fr)
        if fr["raw"]:
            self._settle(fr)  # binary batches that came before this input go in before it
        if now is None:
            now = time.monotonic()
        count_in = self._rt.count_in
        bid = len(fr["batches"])
        fr["batches"].append((key, vehicle, payload_len, b.t_s))
        for name, c in b.streams.items():
            n = c.n
            if not n:
                continue
            raw_key = batches.stream_key("raw", vehicle, name)
            count_in[raw_key].n += n
            vi, s = self._frame_slot(fr, vehicle, raw_key)
            self._frame_add(fr, name, c.msg_type, vi, s, c.t_s, c.seq, c.cols, now, n, bid)

    def _frame_add(self, fr: dict, name: str, msg_type: str, vi: int, slot: int, t: Any, seq: Any, cols: dict,
                   now: float, n: int, bid: int) -> None:
        acc = fr["window"].get(name)
        if acc is None:
            acc = fr["window"][name] = _Acc(msg_type)
        acc.add(vi, slot, t, seq, cols, now, n, bid)
        fr["rows"] += n
        if fr["since"] is None:
            fr["since"] = now
        if fr["rows"] >= FLUSH_ROWS:
            self.frame_flush(force=True)

    # ---- the window -------------------------------------------------------------------------------
    def tick_due_at(self) -> float | None:
        """When the open frame window is due (monotonic s; None: no window open, or not on frames): the runtime's
        loop ticks then, so a window goes out ``batch_window_s`` after its first sample, not up to a tick later."""
        fr = self.__dict__.get("_fr_d")
        since = fr["since"] if fr is not None else None
        return None if since is None else since + self.settings.batch_window_s

    def frame_flush(self, force: bool = False) -> None:
        fr = self._fr()
        if fr["since"] is None or (not force and time.monotonic() - fr["since"] < self.settings.batch_window_s):
            return
        self._settle(fr)
        window, fr["window"], fr["rows"], fr["since"] = fr["window"], {}, 0, None
        queued, fr["queued"] = fr["queued"], None
        blist, fr["batches"] = fr["batches"], []
        out: dict[str, fleetframe.Stream] = {}
        rows = {}
        refused: dict[int, tuple[str, str]] = {}  # batch -> (field, sentence): a binary batch with a bad value
        for name, acc in window.items():
            rows[name] = r = acc.rows()
            cols = {k: acc.column(k) for k in acc.cols}
            rows[name] = (*r, cols)
            if acc.binary:
                arrs = {k: v for k, v in cols.items() if isinstance(v, np.ndarray)}
                for fld, bad, sentence in batches.binary_problems(acc.msg_type, r[4], r[5], arrs):
                    for b in np.unique(r[3][bad]).tolist():
                        if b >= 0 and b not in refused:
                            refused[b] = (f"{name}.{fld}", sentence)
        for b, (fld, sentence) in refused.items():  # refused whole, as a list batch would be at decoding
            key, vehicle, plen, t_b = blist[b]
            self.reject(key, "schema", f"field '{fld}' of {key} {sentence}", fld, plen, vehicle, None, "batch")
        for name, acc in window.items():
            try:
                st = self._decide(fr, name, acc, rows[name], refused)
            except Exception as e:  # noqa: BLE001 - the window's samples of this stream are lost, and counted so
                self._rt.last_error = f"{type(e).__name__}: {e}"[:500]
                self._rt.log_limited("frame-decide", "deciding a window of %s failed: %s", name, e)
                vs = fr["vehicles"]
                for i, k in zip(acc.p_vi, acc.p_n, strict=True):
                    self.count_drop(batches.stream_key("raw", vs[int(i)], name), "handler_error", int(k))
                continue
            if st is not None and st.n:
                out[name] = st
        if not out:
            return
        if self._rt.shedding(queued):
            self._rt.log_limited("shed", "running behind: a window's input queued %.1f s ago (shed_after_s %g): "
                                 "not sent, counted as shed_behind", time.monotonic() - queued, self._rt.shed_after_s)
            # overload: the window's input waited too long in the queue; its samples are checked and counted as
            # every window's are (their seqs move on, so nothing shows later as a gap), but not sent: counted lost
            # as shed_behind on the frame's key, so the stages after catch up instead of working off stale input
            self.count_drop(keys.fleet_frame(self.shard, "clean"), "shed_behind", sum(st.n for st in out.values()))
            self._rt.frames_shed += 1
            return
        self.publish_frame("clean", fr["vehicles"], out)

    def _decide(self, fr: dict, name: str, acc: _Acc, rows: tuple, refused: dict) -> fleetframe.Stream | None:
        mt = acc.msg_type
        vi, slot, now, bid, t, seq, cols = rows
        if refused:  # the rows of batches refused whole are no samples of their streams
            keep = ~np.isin(bid, np.fromiter(refused, np.int64, len(refused)))
            if not keep.all():
                vi, slot, now, t, seq = vi[keep], slot[keep], now[keep], t[keep], seq[keep]
                cols = {k: (v[keep] if isinstance(v, np.ndarray) else v if isinstance(v, str)
                            else [x for x, k_ in zip(v, keep.tolist(), strict=True) if k_]) for k, v in cols.items()}
        n = t.shape[0]
        if not n:
            return None
        ok = fleet.range_ok_mask(mt, t, {k: v for k, v in cols.items() if isinstance(v, np.ndarray)}, self.settings)
        if mt == "mag":  # the sensor must be the key's (a v1 single says it itself)
            want = name.partition("/")[2]
            sens = cols.get("sensor")
            if isinstance(sens, list):
                ok &= np.fromiter((x == want for x in sens), bool, n)
            elif sens is not None and sens != want:
                ok[:] = False
        kind = np.full(n, fleet.KIND_CODE[mt], np.int8)
        d = fr["fs"].decide(slot, kind, t, seq, ok, now)
        accepted = d.accepted
        rebased = d.code == fleet.ACCEPTED_REBASE
        if rebased.any():
            k = int(rebased.sum())
            for _ in range(k):
                self._rt.count_rebase("clock")
            self.log.warning("%s: %d stream clock(s) re-based after %d consistent samples refused on time", name, k,
                             self.settings.rebase_after)
        if not accepted.all():
            self._frame_rejects(fr, name, mt, vi, slot, d, cols, t)
        idx = np.flatnonzero(accepted)
        if not idx.size:
            return None
        order = idx[np.argsort(vi[idx], kind="stable")]
        sub = {}
        for k, c in cols.items():
            if isinstance(c, np.ndarray):
                sub[k] = c[order]
            elif isinstance(c, str):
                sub[k] = c
            else:
                sub[k] = [c[i] for i in order.tolist()]
        return fleetframe.Stream(name, mt, vi[order], t[order], None, sub)

    def _frame_rejects(self, fr: dict, name: str, mt: str, vi: np.ndarray, slot: np.ndarray, d: Any,
                       cols: dict, t: np.ndarray) -> None:
        """One reject report per stream key and code of the window (the first refused sample's sentence, with
        the count), every refused sample counted."""
        first: dict[tuple[int, int], list] = {}
        for i in np.flatnonzero(d.refused).tolist():
            k = (int(slot[i]), int(d.code[i]))
            e = first.get(k)
            if e is None:
                first[k] = [i, 1]
            else:
                e[1] += 1
        for i, count in first.values():
            vehicle = fr["vehicles"][int(vi[i])]
            raw_key = batches.stream_key("raw", vehicle, name)
            msg = {"type": mt, "t_s": float(t[i])}
            for f in MESSAGES[mt].fields:
                v = cols.get(f.name)
                if v is None:
                    continue
                if isinstance(v, np.ndarray):
                    x = v[i]
                    msg[f.name] = x.tolist() if v.ndim == 2 else (bool(x) if v.dtype == np.uint8 else float(x))
                else:
                    msg[f.name] = v if isinstance(v, str) else v[i]
            r = fr["fs"].rejection(d, i, raw_key, msg)
            more = f" ({count} samples of this window refused so)" if count > 1 else ""
            self.reject(raw_key, r.code, r.reason + more, r.field, 0, vehicle, float(t[i]), mt)
            if count > 1:
                self.count_drop(raw_key, f"rejected:{r.code}", count - 1)

    # ---- state ----------------------------------------------------------------------------------
    def frame_evict_key(self, key: str) -> None:
        fr = self.__dict__.get("_fr_d")
        if fr is None:
            return
        s = fr["slot"].pop(key, None)
        if s is not None:
            fr["fs"].free(s)
            fr["names"].pop(key.split("/")[1], None)  # (its remembered slots)

    def frame_evict_vehicle(self, vehicle: str) -> None:
        fr = self.__dict__.get("_fr_d")
        if fr is None or vehicle not in fr["vidx"] or fr["rows"]:
            return  # (with rows in the open window the indices stay until the next eviction round)
        vs = [v for v in fr["vehicles"] if v != vehicle]
        fr["vehicles"], fr["vidx"] = vs, {v: i for i, v in enumerate(vs)}
        fr["names"].clear()  # the remembered vehicle indices moved

    def frame_streams(self) -> list[tuple[str, int, int, int]]:
        """``(key, upstream_gaps, seq_rebases, clock_rebases)`` of each stream decided on frames (for status)."""
        fr = self.__dict__.get("_fr_d")
        if fr is None or not fr["slot"]:
            return []
        items = list(fr["slot"].items())
        idx = np.fromiter((s for _, s in items), np.int64, len(items))
        st = fr["fs"].state[idx]
        return list(zip([k for k, _ in items], st["upstream_gaps"].tolist(), st["seq_rebases"].tolist(),
                        st["clock_rebases"].tolist(), strict=True))
