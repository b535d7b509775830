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
import time
from typing import Any

import numpy as np

from schemas import batch as batches
from schemas import frame as fleetframe
from schemas.messages import MESSAGES

from . import fleet

#: a window holding this many rows is decided and published at once
FLUSH_ROWS = 200_000


class _Acc:
    """One stream's rows of the open window as flat lists, extended per input (no object per sample)."""

    __slots__ = ("msg_type", "vi", "slot", "t", "seq", "now", "cols", "n", "fields", "shared")

    def __init__(self, msg_type: str):
        self.msg_type = msg_type
        self.vi: list[int] = []
        self.slot: list[int] = []
        self.t: list[float] = []
        self.seq: list[int] = []
        self.now: list[float] = []
        self.cols: dict[str, list] = {}
        self.n = 0
        self.fields = {f.name: f for f in MESSAGES[msg_type].fields}
        self.shared: dict[str, str | None] = {}  # a str field's one value over every row so far (None: they differ)

    def add(self, vi: int, slot: int, t: list, seq: list, cols: dict, now: float) -> None:
        n = len(t)
        n0 = self.n
        self.vi.extend([vi] * n)
        self.slot.extend([slot] * n)
        self.t.extend(t)
        self.seq.extend(seq)
        self.now.extend([now] * n)
        if n0 and len(cols) == len(self.cols) and all(k in self.cols for k in cols):
            # the same fields as the rows before (the common case): extend them, no blanks to fill
            shared = self.shared
            for name, v in cols.items():
                if isinstance(v, str):
                    if shared.get(name, v) != v:
                        shared[name] = None
                    self.cols[name].extend([v] * n)
                else:
                    if name in shared:
                        shared[name] = None
                    self.cols[name].extend(v)
            self.n = n0 + n
            return
        for name, v in cols.items():
            f = self.fields.get(name)
            if f is None:
                continue
            col = self.cols.get(name)
            if col is None:  # a field the earlier rows lack: blanks for them
                col = self.cols[name] = [_blank(f)] * n0
                if f.kind == "str":
                    self.shared[name] = None if n0 else (v if isinstance(v, str) else None)
            if isinstance(v, str):
                if self.shared.get(name) != v:
                    self.shared[name] = None
                col.extend([v] * n)
            else:
                self.shared[name] = None
                col.extend(v)
        self.n = n0 + n
        for name, col in self.cols.items():  # a field these rows lack: blanks
            if len(col) < self.n:
                col.extend([_blank(self.fields[name])] * (self.n - len(col)))
                self.shared[name] = None

    def column(self, name: str) -> Any:
        """The window's column: an array for the numeric kinds, one string when every row shares it, else a list."""
        f = self.fields[name]
        col = self.cols[name]
        if f.kind == "str":
            s = self.shared.get(name)
            return s if s is not None else col
        if f.kind == "bool":
            return col if any(x is None for x in col) else np.asarray(col, np.uint8)
        if f.kind in ("float", "vec3", "mat3") or (f.kind == "floats" and f.length):
            if f.nullable:
                blank = _blank(f)
                col = [blank if x is None else x for x in col]
            return np.asarray(col, float)
        return col


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
                "rows": 0, "since": None}
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
    def frame_single(self, info: Any, msg: dict) -> None:
        """A decoded v1 sample into the window."""
        fr = self._fr()
        vi, s = self._frame_slot(fr, info.vehicle, info.key)
        cols = {f.name: [msg[f.name]] for f in MESSAGES[msg["type"]].fields if f.name in msg}
        self._frame_add(fr, batches.stream_name(info), msg["type"], vi, s, [msg["t_s"]], [msg["seq"]], cols,
                        time.monotonic())

    def frame_batch(self, vehicle: str, b: Any) -> None:
        """A decoded, checked v2 batch into the window, stream by stream."""
        fr = self._fr()
        now = time.monotonic()
        count_in = self._rt.count_in
        for name, c in b.streams.items():
            if not c.n:
                continue
            raw_key = batches.stream_key("raw", vehicle, name)
            count_in[raw_key].n += c.n
            vi, s = self._frame_slot(fr, vehicle, raw_key)
            self._frame_add(fr, name, c.msg_type, vi, s, c.t_s, c.seq, c.cols, now)

    def _frame_add(self, fr: dict, name: str, msg_type: str, vi: int, slot: int, t: list, seq: list, cols: dict,
                   now: float) -> None:
        acc = fr["window"].get(name)
        if acc is None:
            acc = fr["window"][name] = _Acc(msg_type)
        acc.add(vi, slot, t, seq, cols, now)
        fr["rows"] += len(t)
        if fr["since"] is None:
            fr["since"] = now
        if fr["rows"] >= FLUSH_ROWS:
            self.frame_flush(force=True)

    # ---- the window -------------------------------------------------------------------------------
    def frame_flush(self, force: bool = False) -> None:
        fr = self._fr()
        if fr["since"] is None or (not force and time.monotonic() - fr["since"] < self.settings.batch_window_s):
            return
        window, fr["window"], fr["rows"], fr["since"] = fr["window"], {}, 0, None
        out: dict[str, fleetframe.Stream] = {}
        for name, acc in window.items():
            try:
                st = self._decide(fr, name, acc)
            except Exception as e:  # noqa: BLE001 - the window's samples of this stream are lost, and counted so
                self._rt.last_error = f"{type(e).__name__}: {e}"[:500]
                self._rt.log_limited("frame-decide", "deciding a window of %s failed: %s", name, e)
                vs = fr["vehicles"]
                for i, k in zip(*np.unique(np.asarray(acc.vi), return_counts=True), strict=True):
                    self.count_drop(batches.stream_key("raw", vs[int(i)], name), "handler_error", int(k))
                continue
            if st is not None and st.n:
                out[name] = st
        if out:
            self.publish_frame("clean", fr["vehicles"], out)

    def _decide(self, fr: dict, name: str, acc: _Acc) -> fleetframe.Stream | None:
        mt = acc.msg_type
        n = acc.n
        t = np.array(acc.t, float)
        seq = np.array(acc.seq, np.int64)
        slot = np.array(acc.slot, np.int32)
        vi = np.array(acc.vi, np.uint32)
        now = np.array(acc.now, float)
        cols = {k: acc.column(k) for k in acc.cols}
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

    def frame_evict_vehicle(self, vehicle: str) -> None:
        fr = self.__dict__.get("_fr_d")
        if fr is None or vehicle not in fr["vidx"] or fr["rows"]:
            return  # (with rows in the open window the indices stay until the next eviction round)
        vs = [v for v in fr["vehicles"] if v != vehicle]
        fr["vehicles"], fr["vidx"] = vs, {v: i for i, v in enumerate(vs)}

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
