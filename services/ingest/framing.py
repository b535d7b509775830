"""Ingest on fleet frames (contract v3, ``output = "frames"``): a window of every vehicle's samples decided in one
compiled call, published as one frame.

Each input — a v1 single sample or a v2 batch, already decoded and checked against the contract by the
runtime and :func:`schemas.batch.decode` — is appended to the window as it is. When the window is due
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
from schemas import keys
from schemas.messages import MESSAGES

from . import fleet

#: a window holding this many rows is decided and published at once
FLUSH_ROWS = 200_000


class _Piece:
    __slots__ = ("vi", "slot", "t", "seq", "cols", "now", "n", "vehicle")

    def __init__(self, vehicle: str, vi: int, slot: int, t: list, seq: list, cols: dict, now: float):
        self.vehicle, self.vi, self.slot, self.t, self.seq, self.cols, self.now = vehicle, vi, slot, t, seq, cols, now
        self.n = len(t)


def _column(f: Any, pieces: list[_Piece], n: int) -> Any:
    """One field's values over the window's pieces: an array for numeric kinds (NaN where a row lacks an
    optional field), one string when every row shares it, else a list (None where a row lacks it)."""
    vals = [p.cols.get(f.name) for p in pieces]
    if all(v is None for v in vals):
        return None
    if f.kind == "str":
        if all(isinstance(v, str) for v in vals) and len({*vals}) == 1:
            return vals[0]
        out: list = []
        for p, v in zip(pieces, vals, strict=True):
            out.extend([v] * p.n if isinstance(v, str) or v is None else v)
        return out
    width = {"vec3": 3, "mat3": 9, "floats": f.length}.get(f.kind)
    numeric = f.kind == "float" or (width is not None and f.kind != "floats") or (f.kind == "floats" and f.length)
    out = []
    if numeric and f.kind != "bool":
        blank = math.nan if width is None else [math.nan] * width
        for p, v in zip(pieces, vals, strict=True):
            if v is None:
                out.extend([blank] * p.n)
            elif f.nullable:
                out.extend(blank if x is None else x for x in v)
            else:
                out.extend(v)
        return np.asarray(out, float)
    if f.kind == "bool" and all(v is not None for v in vals):
        for v in vals:
            out.extend(v)
        return np.asarray(out, np.uint8)
    for p, v in zip(pieces, vals, strict=True):
        out.extend([None] * p.n if v is None else v)
    return out


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
                "rows": 0, "since": None, "rebases": 0}
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
        name = batches.stream_name(info)
        vi, s = self._frame_slot(fr, info.vehicle, info.key)
        cols = {f.name: [msg[f.name]] for f in MESSAGES[msg["type"]].fields if f.name in msg}
        self._frame_add(fr, name, _Piece(info.vehicle, vi, s, [msg["t_s"]], [msg["seq"]], cols, time.monotonic()))

    def frame_batch(self, vehicle: str, b: Any) -> None:
        """A decoded, checked v2 batch into the window, stream by stream."""
        fr = self._fr()
        now = time.monotonic()
        for name, c in b.streams.items():
            if not c.n:
                continue
            raw_key = batches.stream_key("raw", vehicle, name)
            self._rt.count_in[raw_key].n += c.n
            vi, s = self._frame_slot(fr, vehicle, raw_key)
            self._frame_add(fr, name, _Piece(vehicle, vi, s, c.t_s, c.seq, c.cols, now))

    def _frame_add(self, fr: dict, name: str, p: _Piece) -> None:
        fr["window"].setdefault(name, []).append(p)
        fr["rows"] += p.n
        if fr["since"] is None:
            fr["since"] = p.now
        if fr["rows"] >= FLUSH_ROWS:
            self.frame_flush(force=True)

    # ---- the window -------------------------------------------------------------------------------
    def frame_flush(self, force: bool = False) -> None:
        fr = self._fr()
        if fr["since"] is None or (not force and time.monotonic() - fr["since"] < self.settings.batch_window_s):
            return
        window, fr["window"], fr["rows"], fr["since"] = fr["window"], {}, 0, None
        out: dict[str, fleetframe.Stream] = {}
        for name, pieces in window.items():
            try:
                st = self._decide(fr, name, pieces)
            except Exception as e:  # noqa: BLE001 - the window's samples of this stream are lost, and counted so
                self._rt.last_error = f"{type(e).__name__}: {e}"[:500]
                self._rt.log_limited("frame-decide", "deciding a window of %s failed: %s", name, e)
                for p in pieces:
                    self.count_drop(batches.stream_key("raw", p.vehicle, name), "handler_error", p.n)
                continue
            if st is not None and st.n:
                out[name] = st
        if out:
            self.publish_frame("clean", fr["vehicles"], out)

    def _decide(self, fr: dict, name: str, pieces: list[_Piece]) -> fleetframe.Stream | None:
        mt = batches.stream_type(name)
        ns = np.fromiter((p.n for p in pieces), np.int64, len(pieces))
        n = int(ns.sum())
        t = np.fromiter((x for p in pieces for x in p.t), float, n)
        seq = np.fromiter((x for p in pieces for x in p.seq), np.int64, n)
        slot = np.repeat(np.fromiter((p.slot for p in pieces), np.int32, len(pieces)), ns)
        vi = np.repeat(np.fromiter((p.vi for p in pieces), np.uint32, len(pieces)), ns)
        now = np.repeat(np.fromiter((p.now for p in pieces), float, len(pieces)), ns)
        fields = MESSAGES[mt].fields
        cols = {}
        for f in fields:
            c = _column(f, pieces, n)
            if c is not None:
                cols[f.name] = c
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
        acc = d.accepted
        if (d.code == fleet.ACCEPTED_REBASE).any():
            k = int((d.code == fleet.ACCEPTED_REBASE).sum())
            for _ in range(k):
                self._rt.count_rebase("clock")
            self.log.warning("%s: %d stream clock(s) re-based after %d consistent samples refused on time", name, k,
                             self.settings.rebase_after)
        if not acc.all():
            self._frame_rejects(fr, name, mt, pieces, ns, d, cols, t)
        idx = np.flatnonzero(acc)
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

    def _frame_rejects(self, fr: dict, name: str, mt: str, pieces: list[_Piece], ns: np.ndarray, d: Any,
                       cols: dict, t: np.ndarray) -> None:
        """One reject report per stream key and code of the window (the first refused sample's sentence, with
        the count), every refused sample counted."""
        owner = np.repeat(np.arange(len(pieces)), ns)
        first: dict[tuple[int, int], list] = {}
        for i in np.flatnonzero(d.refused).tolist():
            c = int(d.code[i])
            k = (pieces[int(owner[i])].slot, c)
            e = first.get(k)
            if e is None:
                first[k] = [i, 1]
            else:
                e[1] += 1
        for (_, _c), (i, count) in first.items():
            p = pieces[int(owner[i])]
            raw_key = batches.stream_key("raw", p.vehicle, name)
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
            self.reject(raw_key, r.code, r.reason + more, r.field, 0, p.vehicle, float(t[i]), mt)
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
        if fr is None or vehicle not in fr["vidx"] or any(fr["window"].values()):
            return  # (a vehicle with rows in the open window keeps its index until the next eviction round)
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

    @staticmethod
    def frame_key(instance: str) -> str:
        return keys.fleet_frame(instance, "clean")
