"""Ingest on batches (contract v2): v2 batches validated once, vectorised; clean batches out within a window.

A ``raw/batch`` is decoded and checked column by column (:func:`schemas.batch.decode`: types, lengths,
finiteness, bounds, choices), then each stream's physical ranges (the streams table, :func:`schemas.streams.
limit_masks`) and time order are tested on whole columns with numpy. What fails is refused per sample — one
reject report per stream and reason, counted per sample — and the rest is accepted. A stream whose batch holds
something the vectorised test does not decide (a time jump, a sample dated ahead of the stream's clock) goes
through the per-sample path instead, which gives exactly the v1 decisions.

With ``output = "batches"`` accepted samples, from batches and from v1 single samples alike, are published as
one ``clean/batch`` per vehicle at most ``batch_window_s`` after the first of them arrived (a batch input is
published at once, with whatever singles of its vehicle were waiting). With ``output = "singles"`` (the
default) every accepted sample is republished alone on its ``clean/`` key, as in contract v1.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from magmesh.declare import setting
from magmesh.runtime import SHED_AFTER_S
from schemas import batch as batches
from schemas import keys, streams
from schemas.batch import looks_binary

from .core import IngestSettings, Rejection, StreamState, accept, check_order, check_ranges

#: a stream with at most this many samples in a batch is checked sample by sample (numpy's per-call cost
#: outweighs its speed on a few samples); a longer one on whole columns
SMALL = 32
#: refused seqs a stream remembers since its last accepted sample (as ``Ingest.on_message``)
REFUSED_SEQS_MAX = 1024


@dataclass(frozen=True)
class IngestServiceSettings(IngestSettings):
    output: str = setting("singles", "singles: one clean/ message per sample (v1); batches: clean/batch per vehicle "
                          "(v2); frames: one fleet frame of every vehicle per window (v3, magmesh/fleet/{instance}/clean)",
                          choices=("singles", "batches", "frames"))
    batch_window_s: float = setting(0.01, "longest wall-clock wait of an accepted sample before its batch or frame "
                                    "goes out", gt=0, hi=5.0)
    shed_after_s: float = setting(SHED_AFTER_S, "output=frames: a window whose input waited longer than this in the "
                                  "input queue (overload) is checked and counted but not sent: its samples counted "
                                  "lost as shed_behind on the frame key; 0 = never shed", lo=0)


def order_masks(t: np.ndarray, ok: np.ndarray, last_t: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Duplicates and time going backwards on one stream's column, decided as the per-sample test would:
    each sample against the latest earlier sample that was accepted (``ok``: not refused otherwise)."""
    prev_src = np.where(ok, t, -np.inf)
    run = np.maximum.accumulate(prev_src)
    prev = np.empty_like(t)
    prev[0] = -np.inf if last_t is None else last_t
    if t.shape[0] > 1:
        prev[1:] = np.maximum(run[:-1], prev[0])
    return t == prev, t < prev


class BatchingIngest:
    """The batch half of the ingest service (mixed into :class:`services.ingest.service.Ingest`)."""

    settings: IngestServiceSettings

    @property
    def batch_output(self) -> bool:
        """True with ``output = "batches"`` (a plain :class:`IngestSettings` means singles)."""
        return getattr(self.settings, "output", "singles") == "batches"

    @property
    def _pending(self) -> dict[str, tuple[float, dict[str, list[batches.Columns]]]]:
        """vehicle → (monotonic time of its first waiting sample, stream name → columns waiting)."""
        d = self.__dict__.get("_pending_d")
        if d is None:
            d = self.__dict__["_pending_d"] = {}
        return d

    # ---- input -------------------------------------------------------------------------------------
    def on_batch_input(self, info: Any, payload: bytes, state: Any) -> None:
        key = info.key
        self._rt.batches_in += 1
        frames = self.frame_output
        if frames and looks_binary(payload):  # decoded with its window's others (framing.py)
            self.frame_raw(key, info, payload)
            return
        b = self._rt.decode_batch(key, info, payload, check=True, deferred=frames)
        if b is None:
            return
        if frames:  # decided with the whole window (framing.py), a binary batch's values checked there too
            self.frame_batch(key, info.vehicle, b, len(payload))
            return
        now = time.monotonic()
        for name, c in b.streams.items():
            if c.n:
                self._stream_columns(info.vehicle, name, c, state, now, b.seq)
        self.flush(info.vehicle)

    def _stream_columns(self, vehicle: str, name: str, c: batches.Columns, state: Any, now: float,
                        bseq: int) -> None:
        s = self.settings
        skey = batches.stream_key("raw", vehicle, name)
        self._rt.count_in[skey].n += c.n
        st = state.streams.get(skey)
        if st is None:
            st = state.streams[skey] = StreamState()
        if c.n <= SMALL:
            self._small(vehicle, name, skey, c, st, now)
            return
        t = c.array("t_s")
        refused: list[tuple[str, str, np.ndarray, str]] = []
        bad_t = t < 0
        if bad_t.any():
            refused.append(("range", "t_s", bad_t, "must be ≥ 0"))
        arrays = {lim.field: c.array(lim.field) for lim in streams.LIMITS.get(c.msg_type, ()) if lim.field in c.cols}
        for fld, mask, sentence in streams.limit_masks(c.msg_type, arrays, c.n, s):
            refused.append(("range", fld, mask, sentence))
        ok = np.ones(c.n, bool)
        for _, _, m, _ in refused:
            ok &= ~m
        dup, back = order_masks(t, ok, st.last_t_s)
        ok_t = t[ok & ~dup & ~back]
        prev_last = st.last_t_s
        jumps = np.diff(np.concatenate([[prev_last], ok_t])) if prev_last is not None and ok_t.size else (
            np.diff(ok_t) if ok_t.size > 1 else np.zeros(0))
        ahead = False
        if prev_last is not None and st.last_wall is not None and ok_t.size:
            from .core import ahead_limit_s

            ahead = float(ok_t[-1]) - prev_last > ahead_limit_s(c.msg_type, st, s, now)
        if (jumps > s.max_time_jump_s).any() or ahead or st.contra_n:
            # not decided by the columns: each sample through the v1 path (same decisions, same clock rules)
            self._per_sample(vehicle, skey, c, st, now)
            return
        if dup.any():
            refused.append(("duplicate", "t_s", dup & ok, "repeats the previous sample's t_s"))
        if back.any():
            refused.append(("time_order", "t_s", back & ok, "went backwards"))
        for code, fld, mask, sentence in refused:
            k = int(mask.sum())
            if not k:
                continue
            i = int(np.argmax(mask))
            self.reject(skey, code, f"field '{fld}' of {skey} {sentence}: {k} of {c.n} samples of batch {bseq} "
                        f"(first at t_s = {float(t[i]):.6f} s)", fld, 0, vehicle, float(t[i]), c.msg_type)
            if k > 1:
                self.count_drop(skey, f"rejected:{code}", k - 1)
        keep = ok & ~dup & ~back
        # refused seqs, as on the per-sample path: delivered and counted as rejected, so no gap of the stream. By
        # segment: those received before the j-th accepted sample (j = 0 starts from the stream's own set)
        segments: dict[int, set] = {0: set(st.refused_seqs)} if st.refused_seqs else {}
        if not keep.all():
            all_seq, before = c.array("seq"), np.cumsum(keep) - keep
            for r in np.flatnonzero(~keep).tolist():
                seg = segments.setdefault(int(before[r]), set())
                if len(seg) < REFUSED_SEQS_MAX:
                    seg.add(int(all_seq[r]))
        if not keep.any():
            st.refused_seqs = segments.get(0, set())
            return
        acc = c if keep.all() else c.take(keep)
        seq = acc.array("seq")
        if acc.n > 1 or st.last_seq is not None:
            prev = np.concatenate([[st.last_seq], seq[:-1]]) if st.last_seq is not None else seq[:-1]
            gaps = (seq[-len(prev):] - prev - 1) if len(prev) else np.zeros(0, np.int64)
            big = (gaps > s.seq_jump_max) | (gaps < -1)
            st.seq_rebases += int(big.sum())
            counted = (gaps > 0) & ~big
            lost = int(gaps[counted].sum())
            off = 0 if st.last_seq is not None else 1  # gaps[j - off]: the gap before the j-th accepted sample
            for j, seg in segments.items():
                if 0 <= j - off and j < seq.shape[0] and counted[j - off]:
                    lo, hi = int(prev[j - off]), int(seq[j])
                    lost -= sum(1 for q in seg if lo < q < hi)
            st.upstream_gaps += lost
            st.last_seq = None  # accept() below counts nothing more for the last sample
        accept({"seq": int(seq[-1]), "t_s": float(acc.t_s[-1])}, st, now, s)
        st.refused_seqs = segments.get(seq.shape[0], set())  # refused after the last accepted sample
        st.accepted += acc.n - 1
        self.pend(vehicle, name, acc)

    def _small(self, vehicle: str, name: str, skey: str, c: batches.Columns, st: StreamState, now: float) -> None:
        """A few samples (a vehicle's window): the v1 rules sample by sample on the columns, no dicts built."""
        s = self.settings
        mt = c.msg_type
        lim_fields = [lim.field for lim in streams.LIMITS.get(mt, ()) if lim.field in c.cols]
        cols = c.cols
        keep = []
        info = None
        for i in range(c.n):
            t = c.t_s[i]
            m = {"type": mt, "t_s": t, "seq": c.seq[i]}
            for f in lim_fields:
                m[f] = cols[f][i]
            try:
                if t < 0:
                    raise Rejection("range", "t_s", f"field 't_s' of {skey} must be ≥ 0, got {t:g}")
                p = streams.limit_problem(m, s)
                if p is not None:
                    raise Rejection("range", p[0], f"field '{p[0]}' of {skey} {p[1]}")
                check_order(m, st, s, skey, now)
            except Rejection as r:
                if info is None:
                    info = keys.parse(skey)
                if not self.time_refusal(info, m, st, r):
                    if len(st.refused_seqs) < REFUSED_SEQS_MAX:
                        st.refused_seqs.add(int(m["seq"]))
                    continue
            accept(m, st, now, s)
            keep.append(i)
        if not keep:
            return
        self.pend(vehicle, name, c if len(keep) == c.n else c.take([i in keep for i in range(c.n)]))

    def _per_sample(self, vehicle: str, skey: str, c: batches.Columns, st: StreamState, now: float) -> None:
        info = keys.parse(skey)
        for m in c.messages(vehicle):
            try:
                check_ranges(m, self.settings, skey)
                check_order(m, st, self.settings, skey, now)
            except Rejection as r:
                if not self.time_refusal(info, m, st, r):
                    if len(st.refused_seqs) < REFUSED_SEQS_MAX:
                        st.refused_seqs.add(int(m["seq"]))
                    continue
            accept(m, st, now, self.settings)
            self.emit(info, m)

    # ---- output ------------------------------------------------------------------------------------
    def emit(self, info: Any, msg: dict) -> None:
        """An accepted v1 sample: republished alone, or kept for its vehicle's next clean batch."""
        if not self.batch_output:
            self.republish(keys.raw_to_clean(info.key), msg)
            return
        self.pend(info.vehicle, batches.stream_name(info), batches.from_message(msg))

    def pend(self, vehicle: str, name: str, cols: batches.Columns) -> None:
        if not self.batch_output:
            kind_key = batches.stream_key("clean", vehicle, name)
            for m in cols.messages(vehicle):
                self.republish(kind_key, m)
            return
        p = self._pending.get(vehicle)
        if p is None:
            p = self._pending[vehicle] = (time.monotonic(), {})
        p[1].setdefault(name, []).append(cols)

    def flush(self, vehicle: str | None = None) -> None:
        """Publish the clean batch of ``vehicle`` now, or (None) of every vehicle whose window has passed."""
        if vehicle is not None:
            p = self._pending.pop(vehicle, None)
            if p is not None:
                self._publish(vehicle, p[1])
            return
        if not self._pending:
            return
        due = time.monotonic() - self.settings.batch_window_s
        for v in [v for v, p in self._pending.items() if p[0] <= due]:
            self._publish(v, self._pending.pop(v)[1])

    def _publish(self, vehicle: str, parts: dict[str, list[batches.Columns]]) -> None:
        cols = {name: batches.concat(lst) for name, lst in parts.items()}
        self.publish_batch(keys.clean_batch(vehicle), vehicle, cols)

    @property
    def tick_override_s(self) -> float | None:
        """The runtime's tick runs the window's flush at half the window."""
        return self.settings.batch_window_s / 2 if (self.batch_output or self.frame_output) else None
