"""Ingest's per-sample time and sequence rules over a whole fleet window, in one compiled call.

A fleet window holds every vehicle's samples of a few tens of ms (hundreds of vehicles, ~100,000 samples/s in
all). :class:`FleetStreams` keeps the state of many *stream slots* (one per vehicle and stream key: the fields
of :class:`services.ingest.core.StreamState`) in numpy arrays, and :meth:`FleetStreams.decide` applies to each
row of a window exactly what :meth:`services.ingest.service.Ingest.on_message` applies to a decoded v1 sample:

- the physical ranges (:func:`services.ingest.core.check_ranges`), given as ``range_ok`` (computed beforehand
  on whole columns, e.g. with :func:`range_ok_mask`);
- :func:`~services.ingest.core.check_order`: a duplicate, time going backwards, a jump beyond
  ``max_time_jump_s``, a sample dated ahead of the stream's clock (:func:`~services.ingest.core.ahead_limit_s`);
- a refusal on time counted towards a re-base (:func:`~services.ingest.core.note_refusal`): after
  ``rebase_after`` consistent ones the clock is forgotten (:func:`~services.ingest.core.rebase`) and that
  sample accepted;
- a refused sample's seq remembered (at most :data:`REFUSED_SEQS_MAX` since the last accepted sample), so that
  it is no gap of the stream;
- :func:`~services.ingest.core.accept`: seq gaps net of refused seqs, seq re-bases, the learned clock rate.

Rows of one slot are decided in the order given (arrival order); rows of different slots may interleave. The
kernel is a numba function compiled on first use and cached on disk (``python -m services.ingest.fleet --warm``
compiles it ahead). It decides; the sentences of refused rows are written in Python
(:meth:`FleetStreams.rejection`), word for word those of the per-sample path. :func:`reference_step` is that
per-sample path in pure Python (the reference the kernel is tested and benchmarked against).

What stays with the caller, as in ``Ingest.on_message``: a magnetometer sample whose ``sensor`` field names
another sensor than its key is refused by ``check_ranges`` with code ``key``; give such a row ``range_ok =
False`` (its sentence, from :meth:`FleetStreams.rejection` with the row's message, then says ``key``). A row
decided :data:`ACCEPTED_REBASE` is the one ``Ingest.time_refusal`` logs and counts as a clock re-base.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from schemas.streams import LIMITS, limit_masks

from .core import (
    IngestSettings,
    Rejection,
    StreamState,
    accept,
    check_order,
    check_ranges,
    note_refusal,
    rebase,
)

#: stream kinds by their code in :meth:`FleetStreams.decide`'s ``kind`` column
KINDS = ("mag", "imu", "gnss", "ins", "route", "attitude")
KIND_CODE = {k: i for i, k in enumerate(KINDS)}

# decision codes, one per row
ACCEPTED = 0
ACCEPTED_REBASE = 1  # refused on time, but the one that re-based a clock that really jumped: accepted
REFUSED_RANGE = 2  # range_ok was False (check_ranges: code "range", or "key" for a mag sensor mismatch)
REFUSED_DUPLICATE = 3  # same t_s as the stream's last accepted sample (code "duplicate")
REFUSED_BACKWARDS = 4  # earlier than the stream's last accepted sample (code "time_order")
REFUSED_JUMP = 5  # more than max_time_jump_s after it (code "time_order")
REFUSED_AHEAD = 6  # dated ahead of the stream's clock (code "time_order")
CODE_NAMES = ("accepted", "accepted_rebase", "range", "duplicate", "backwards", "jump", "ahead")

#: refused seqs remembered per stream since its last accepted sample (as ``Ingest.on_message``)
REFUSED_SEQS_MAX = 1024

#: one stream slot; a float field that is None in :class:`StreamState` is NaN here (times are finite)
STATE_DTYPE = np.dtype([
    ("last_t_s", "f8"), ("last_wall", "f8"), ("rate", "f8"), ("win_t_s", "f8"), ("win_wall", "f8"),
    ("contra_last_t_s", "f8"), ("step_s", "f8"),
    ("last_seq", "i8"), ("accepted", "i8"), ("upstream_gaps", "i8"), ("seq_rebases", "i8"),
    ("clock_rebases", "i8"), ("contra_n", "i8"),
    ("ref_head", "i8"), ("ref_n", "i8"),  # the refused seqs: a list in the arena, and how many
    ("has_seq", "?"), ("rate_learned", "?"), ("in_use", "?"),
], align=True)

_OPTIONAL_FLOATS = ("last_t_s", "last_wall", "win_t_s", "win_wall", "contra_last_t_s")
_INT_FIELDS = ("accepted", "upstream_gaps", "seq_rebases", "clock_rebases", "contra_n")
#: the StreamState fields a slot holds (all of them; a test checks that none is missing)
STATE_FIELDS = (*_OPTIONAL_FLOATS, "rate", "step_s", "last_seq", *_INT_FIELDS, "rate_learned", "refused_seqs")

_I64_MAX = np.iinfo(np.int64).max


# ---- the kernel (plain Python here; compiled by numba on first use, see _kernel) ---------------------------


def _ahead_limit_py(st, ahead_s, max_rate, now):
    """:func:`services.ingest.core.ahead_limit_s` for a slot whose clock has started (last_wall set)."""
    dt = max(0.0, now - st.last_wall)
    if st.rate_learned:
        rate = min(max(st.rate, 1.0), max_rate)
    else:
        span = st.last_wall - st.win_wall if not math.isnan(st.win_wall) else 0.0
        if span > 0 and not math.isnan(st.last_t_s) and not math.isnan(st.win_t_s):
            rate = min(max((st.last_t_s - st.win_t_s) / span, 1.0), max_rate)
        else:
            rate = max_rate
    return ahead_s + rate * (2.0 * dt + 0.5) + 2.0 * min(st.step_s, 3.0 * ahead_s)


def _add_refused_py(st, seq, ref_seq, ref_next, ref_free):
    """Add ``seq`` to the slot's set of refused seqs (a list in the arena; needs one free node)."""
    node = st.ref_head
    while node >= 0:
        if ref_seq[node] == seq:
            return
        node = ref_next[node]
    node = ref_free[0]
    ref_free[0] = ref_next[node]
    ref_seq[node] = seq
    ref_next[node] = st.ref_head
    st.ref_head = node
    st.ref_n += 1


def _accept_py(st, t_s, seq, now, seq_jump_max, max_rate, ref_seq, ref_next, ref_free):
    """:func:`services.ingest.core.accept` (with the receive time and the settings)."""
    if st.has_seq:
        gap = seq - st.last_seq - 1
        if gap > seq_jump_max or gap < -1:
            st.seq_rebases += 1
        elif gap > 0:
            known = 0  # refused seqs inside the gap: delivered and counted as rejected, not lost
            node = st.ref_head
            while node >= 0:
                if st.last_seq < ref_seq[node] < seq:
                    known += 1
                node = ref_next[node]
            st.upstream_gaps += gap - known
    head = st.ref_head
    if head >= 0:  # the refused seqs go back to the arena's free list
        tail = head
        while ref_next[tail] >= 0:
            tail = ref_next[tail]
        ref_next[tail] = ref_free[0]
        ref_free[0] = head
        st.ref_head = -1
        st.ref_n = 0
    st.last_seq = seq
    st.has_seq = True
    if not math.isnan(st.last_t_s) and t_s > st.last_t_s:
        st.step_s = t_s - st.last_t_s
    st.last_t_s = t_s
    st.accepted += 1
    st.contra_n = 0
    st.contra_last_t_s = np.nan
    st.last_wall = now
    if math.isnan(st.win_wall):
        st.win_t_s = t_s
        st.win_wall = now
    elif now - st.win_wall >= 1.0:
        r = (t_s - st.win_t_s) / (now - st.win_wall)
        st.rate = min(max(r, 0.5 * st.rate, 1.0), max_rate)
        st.rate_learned = True
        st.win_t_s = t_s
        st.win_wall = now


def _decide_rows_py(state, ref_seq, ref_next, ref_free, fpar, ipar, ahead_by_kind, slot, kind, t_s, seq,
                    range_ok, now, start, code, prev_t_s, prev_wall, limit_s):
    """Decide rows ``start..`` in order; returns the first row not decided (< len only when the refused-seq
    arena has no free node left: the caller grows it and calls again from there)."""
    max_jump_s = fpar[0]
    max_rate = fpar[1]
    seq_jump_max = ipar[0]
    rebase_after = ipar[1]
    refused_max = ipar[2]
    n = slot.shape[0]
    for i in range(start, n):
        if ref_free[0] < 0:
            return i
        st = state[slot[i]]
        t = t_s[i]
        nw = now[i]
        ahead_s = ahead_by_kind[kind[i]]
        last = st.last_t_s
        prev_t_s[i] = last
        prev_wall[i] = st.last_wall
        limit_s[i] = np.nan
        c = ACCEPTED
        if not range_ok[i]:
            c = REFUSED_RANGE
        elif not math.isnan(last):
            if t == last:
                c = REFUSED_DUPLICATE
            elif t < last:
                c = REFUSED_BACKWARDS
            elif t - last > max_jump_s:
                c = REFUSED_JUMP
            elif not math.isnan(st.last_wall):
                lim = _ahead_limit(st, ahead_s, max_rate, nw)
                limit_s[i] = lim
                if t - last > lim:
                    c = REFUSED_AHEAD
        if c >= REFUSED_BACKWARDS:  # refused on time: note_refusal
            prev = st.contra_last_t_s
            if not math.isnan(prev) and 0.0 < t - prev <= ahead_s:
                st.contra_n += 1
            else:
                st.contra_n = 1
            st.contra_last_t_s = t
            if st.contra_n >= rebase_after:  # the clock really jumped: rebase, then accept this sample
                st.last_t_s = np.nan
                st.last_wall = np.nan
                st.rate = 1.0
                st.rate_learned = False
                st.step_s = 0.0
                st.win_t_s = np.nan
                st.win_wall = np.nan
                st.contra_n = 0
                st.contra_last_t_s = np.nan
                st.clock_rebases += 1
                c = ACCEPTED_REBASE
        if c >= REFUSED_RANGE:
            if st.ref_n < refused_max:
                _add_refused(st, seq[i], ref_seq, ref_next, ref_free)
        else:
            _accept(st, t, seq[i], nw, seq_jump_max, max_rate, ref_seq, ref_next, ref_free)
        code[i] = c
    return n


# the compiled functions, set by _kernel() on first use (numba loads in ~0.4 s: importing this module does not)
_ahead_limit = _add_refused = _accept = _decide_rows = None


def _kernel():
    """The compiled kernel (compiled on first use in a process, or loaded from numba's on-disk cache)."""
    global _ahead_limit, _add_refused, _accept, _decide_rows
    if _decide_rows is None:
        import numba

        _ahead_limit = numba.njit(cache=True)(_ahead_limit_py)
        _add_refused = numba.njit(cache=True)(_add_refused_py)
        _accept = numba.njit(cache=True)(_accept_py)
        _decide_rows = numba.njit(cache=True)(_decide_rows_py)
    return _decide_rows


# ---- the state of many streams -----------------------------------------------------------------------------


@dataclass
class Decisions:
    """What :meth:`FleetStreams.decide` returns: per row its code and what a refusal's sentence names."""

    code: np.ndarray  # int8: ACCEPTED ... REFUSED_AHEAD
    prev_t_s: np.ndarray  # the stream's last accepted t_s when the row was decided (NaN: none)
    prev_wall_s: np.ndarray  # its receive time (monotonic s; NaN: none)
    limit_s: np.ndarray  # the ahead limit in force (s of sample time past prev_t_s; NaN: not checked)
    kind: np.ndarray  # the inputs the sentences name
    t_s: np.ndarray
    now: np.ndarray

    @property
    def accepted(self) -> np.ndarray:
        return self.code <= ACCEPTED_REBASE

    @property
    def refused(self) -> np.ndarray:
        return self.code >= REFUSED_RANGE


def range_ok_mask(msg_type: str, t_s: np.ndarray, cols: Mapping[str, np.ndarray],
                  settings: IngestSettings | None = None) -> np.ndarray:
    """``range_ok`` of one stream kind's rows: ``t_s ≥ 0`` and every physical range of the streams table
    (:func:`schemas.streams.limit_masks`) over the columns (``cols``: field → array, rows first)."""
    t = np.asarray(t_s, np.float64)
    ok = t >= 0
    arrays = {lim.field: np.asarray(cols[lim.field], np.float64) for lim in LIMITS.get(msg_type, ())
              if lim.field in cols}
    for _, bad, _ in limit_masks(msg_type, arrays, t.shape[0], settings):
        ok &= ~bad
    return ok


def _int_param(x, up: bool) -> int:
    """An integer threshold equivalent to comparing an integer with ``x`` (``>`` when ``up`` is False: floor;
    ``>=`` when True: ceil), clamped to int64."""
    v = math.ceil(x) if up else math.floor(x)
    return int(min(v, _I64_MAX))


class FleetStreams:
    """The ingest state of many streams (slots) in numpy arrays, decided by one compiled call per window.

    ``add()`` gives a free slot (with a new :class:`StreamState`'s values), ``free(slot)`` releases it (an
    evicted key), ``get(slot)`` / ``set(slot, st)`` read and write one slot as a :class:`StreamState`.
    Capacity grows by doubling when every slot is taken.
    """

    def __init__(self, settings: IngestSettings, capacity: int = 1024):
        if capacity < 1:
            raise ValueError(f"capacity must be ≥ 1, got {capacity}")
        self.settings = settings
        self.state = np.zeros(capacity, STATE_DTYPE)
        self._free_slots: list[int] = list(range(capacity - 1, -1, -1))
        # the refused seqs of all slots: one linked list per slot in a shared arena of nodes
        self.ref_seq = np.zeros(0, np.int64)
        self.ref_next = np.zeros(0, np.int64)
        self.ref_free = np.array([-1], np.int64)  # head of the free list
        self._grow_arena(max(256, capacity))
        self._fpar = np.array([settings.max_time_jump_s, settings.max_clock_rate], np.float64)
        self._ipar = np.array([_int_param(settings.seq_jump_max, up=False), _int_param(settings.rebase_after, up=True),
                               REFUSED_SEQS_MAX], np.int64)
        self._ahead = np.array([settings.max_ahead_s.get(k, 10.0) for k in KINDS], np.float64)

    @property
    def capacity(self) -> int:
        return self.state.shape[0]

    def __len__(self) -> int:
        return self.capacity - len(self._free_slots)

    # ---- slots -------------------------------------------------------------------------------------------
    def add(self) -> int:
        """A free slot, holding a new stream's state."""
        if not self._free_slots:
            n = self.capacity
            self.state = np.concatenate([self.state, np.zeros(n, STATE_DTYPE)])
            self._free_slots = list(range(2 * n - 1, n - 1, -1))
        slot = self._free_slots.pop()
        r = self.state[slot]
        for f in _OPTIONAL_FLOATS:
            r[f] = np.nan
        r["rate"], r["step_s"] = 1.0, 0.0
        for f in (*_INT_FIELDS, "last_seq", "ref_n"):
            r[f] = 0
        r["ref_head"] = -1
        r["has_seq"] = r["rate_learned"] = False
        r["in_use"] = True
        return slot

    def free(self, slot: int) -> None:
        """Release a slot (its refused seqs go back to the arena)."""
        self._check_slot(slot)
        self._clear_refused(slot)
        self.state[slot]["in_use"] = False
        self._free_slots.append(int(slot))

    def get(self, slot: int) -> StreamState:
        """One slot as a :class:`StreamState` (a copy)."""
        self._check_slot(slot)
        r = self.state[slot]

        def opt(name: str) -> float | None:
            x = float(r[name])
            return None if math.isnan(x) else x

        return StreamState(
            last_t_s=opt("last_t_s"), last_seq=int(r["last_seq"]) if r["has_seq"] else None,
            accepted=int(r["accepted"]), upstream_gaps=int(r["upstream_gaps"]), seq_rebases=int(r["seq_rebases"]),
            last_wall=opt("last_wall"), rate=float(r["rate"]), rate_learned=bool(r["rate_learned"]),
            win_t_s=opt("win_t_s"), win_wall=opt("win_wall"), contra_n=int(r["contra_n"]),
            contra_last_t_s=opt("contra_last_t_s"), clock_rebases=int(r["clock_rebases"]),
            refused_seqs=set(self._refused(slot)), step_s=float(r["step_s"]))

    def set(self, slot: int, st: StreamState) -> None:
        """Write a :class:`StreamState` into a slot (times finite; seqs ≥ 0, as the contract has them)."""
        self._check_slot(slot)
        for f in _OPTIONAL_FLOATS:
            v = getattr(st, f)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"StreamState.{f} must be finite or None, got {v!r}")
        if (st.win_t_s is None) != (st.win_wall is None):
            raise ValueError("StreamState.win_t_s and win_wall are set together (or both None)")
        if st.last_seq is not None and not 0 <= st.last_seq <= _I64_MAX:
            raise ValueError(f"StreamState.last_seq must be in [0, 2**63), got {st.last_seq!r}")
        if any(not -_I64_MAX <= q <= _I64_MAX for q in st.refused_seqs):
            raise ValueError("StreamState.refused_seqs must be 64-bit integers")
        r = self.state[slot]
        for f in _OPTIONAL_FLOATS:
            v = getattr(st, f)
            r[f] = np.nan if v is None else float(v)
        r["rate"], r["step_s"] = float(st.rate), float(st.step_s)
        for f in _INT_FIELDS:
            r[f] = int(getattr(st, f))
        r["has_seq"] = st.last_seq is not None
        r["last_seq"] = 0 if st.last_seq is None else int(st.last_seq)
        r["rate_learned"] = bool(st.rate_learned)
        self._clear_refused(slot)
        for q in st.refused_seqs:
            if self.ref_free[0] < 0:
                self._grow_arena(self.ref_seq.shape[0])
            node = int(self.ref_free[0])
            self.ref_free[0] = self.ref_next[node]
            self.ref_seq[node] = q
            self.ref_next[node] = r["ref_head"]
            r["ref_head"] = node
            r["ref_n"] += 1

    def _check_slot(self, slot: int) -> None:
        if not (0 <= slot < self.capacity and self.state[slot]["in_use"]):
            raise ValueError(f"slot {slot} is not in use")

    def _refused(self, slot: int) -> list[int]:
        out, node = [], int(self.state[slot]["ref_head"])
        while node >= 0:
            out.append(int(self.ref_seq[node]))
            node = int(self.ref_next[node])
        return out

    def _clear_refused(self, slot: int) -> None:
        r = self.state[slot]
        head = int(r["ref_head"])
        if head < 0:
            return
        tail = head
        while self.ref_next[tail] >= 0:
            tail = int(self.ref_next[tail])
        self.ref_next[tail] = self.ref_free[0]
        self.ref_free[0] = head
        r["ref_head"], r["ref_n"] = -1, 0

    def _grow_arena(self, more: int) -> None:
        n = self.ref_seq.shape[0]
        self.ref_seq = np.concatenate([self.ref_seq, np.zeros(more, np.int64)])
        nxt = np.arange(n + 1, n + more + 1, dtype=np.int64)
        nxt[-1] = self.ref_free[0]  # the new nodes lead to the old free list (empty when growing)
        self.ref_next = np.concatenate([self.ref_next, nxt])
        self.ref_free[0] = n

    # ---- deciding --------------------------------------------------------------------------------------
    def decide(self, slot, kind, t_s, seq, range_ok, now) -> Decisions:
        """Decide N rows (arrival order per slot) as ``Ingest.on_message`` would, updating the slots.

        ``slot`` int32[N], ``kind`` int8[N] (:data:`KIND_CODE`), ``t_s`` f8[N], ``seq`` int64[N] (≥ 0),
        ``range_ok`` bool[N] (the physical ranges and ``t_s ≥ 0``: :func:`range_ok_mask`), ``now`` f8[N] (each
        row's receive time, monotonic s). Inputs of other dtypes are converted.
        """
        slot = np.ascontiguousarray(slot, np.int32)
        kind = np.ascontiguousarray(kind, np.int8)
        t_s = np.ascontiguousarray(t_s, np.float64)
        seq = np.ascontiguousarray(seq, np.int64)
        range_ok = np.ascontiguousarray(range_ok, np.bool_)
        now = np.ascontiguousarray(now, np.float64)
        n = slot.shape[0]
        if any(a.shape != (n,) for a in (kind, t_s, seq, range_ok, now)):
            raise ValueError("decide: slot, kind, t_s, seq, range_ok and now must be 1-D of one length")
        code = np.empty(n, np.int8)
        prev_t, prev_wall, limit = np.empty(n), np.empty(n), np.empty(n)
        if n:
            if slot.min() < 0 or slot.max() >= self.capacity or not self.state["in_use"][slot].all():
                raise ValueError("decide: a row names a slot that is not in use")
            if kind.min() < 0 or kind.max() >= len(KINDS):
                raise ValueError(f"decide: kind codes are 0..{len(KINDS) - 1} ({', '.join(KINDS)})")
            if seq.min() < 0:
                raise ValueError("decide: seq must be ≥ 0")
            if not (np.isfinite(t_s).all() and np.isfinite(now).all()):
                raise ValueError("decide: t_s and now must be finite")
            k = _kernel()
            start = 0
            while True:
                start = k(self.state, self.ref_seq, self.ref_next, self.ref_free, self._fpar, self._ipar,
                          self._ahead, slot, kind, t_s, seq, range_ok, now, start, code, prev_t, prev_wall, limit)
                if start >= n:
                    break
                self._grow_arena(self.ref_seq.shape[0])
        return Decisions(code, prev_t, prev_wall, limit, kind, t_s, now)

    def rejection(self, d: Decisions, i: int, where: str, msg: Mapping | None = None) -> Rejection:
        """The :class:`Rejection` (code, field, sentence) the per-sample path gives refused row ``i``.

        ``where`` is the stream's key. A range refusal names the field and its value: pass the row's message
        (type, t_s and the fields of its limits; ``sensor`` for mag), or nothing when its ``t_s`` is < 0.
        """
        c = int(d.code[i])
        t = float(d.t_s[i])
        prev = float(d.prev_t_s[i])
        if c == REFUSED_RANGE:
            if msg is None:
                if t < 0:
                    return Rejection("range", "t_s", f"field 't_s' of {where} must be ≥ 0, got {t:g}")
                raise ValueError(f"row {i}: a range refusal's sentence needs the row's message")
            try:
                check_ranges(dict(msg), self.settings, where)
            except Rejection as r:
                return r
            raise ValueError(f"row {i}: range_ok was False, but check_ranges finds nothing wrong with {where}'s "
                             f"sample at t_s = {t:.6f} s")
        if c == REFUSED_DUPLICATE:
            return Rejection("duplicate", "t_s", f"sample of {where} at t_s = {t:.6f} s repeats the previous one")
        if c == REFUSED_BACKWARDS:
            return Rejection("time_order", "t_s", f"field 't_s' of {where} went backwards: {t:.6f} s after "
                             f"{prev:.6f} s")
        if c == REFUSED_JUMP:
            return Rejection("time_order", "t_s", f"field 't_s' of {where} jumped {t - prev:.4g} s ahead "
                             f"(more than {self.settings.max_time_jump_s:g} s)")
        if c == REFUSED_AHEAD:
            now, wall, lim = float(d.now[i]), float(d.prev_wall_s[i]), float(d.limit_s[i])
            return Rejection("time_order", "t_s", f"field 't_s' of {where} is {t - prev:.4g} s after the stream's "
                             f"last sample, {now - wall:.3g} s of receive time later (at most {lim:.4g} s for "
                             f"{KINDS[int(d.kind[i])]} samples): dated ahead of the stream's clock")
        raise ValueError(f"row {i} was accepted ({CODE_NAMES[c]})")


# ---- the per-sample reference ------------------------------------------------------------------------------


def reference_step(msg: dict, st: StreamState, settings: IngestSettings, where: str,
                   now: float) -> tuple[int, Rejection | None]:
    """One decoded v1 sample through ``Ingest.on_message``'s rules in pure Python: its decision code and, when
    refused, the :class:`Rejection`. Changes ``st`` exactly as the service does."""
    try:
        check_ranges(msg, settings, where)
        check_order(msg, st, settings, where, now)
    except Rejection as r:
        if r.code == "time_order":
            t, last = msg["t_s"], st.last_t_s
            c = REFUSED_BACKWARDS if t < last else (REFUSED_JUMP if t - last > settings.max_time_jump_s
                                                    else REFUSED_AHEAD)
            if note_refusal(msg, st, settings):
                rebase(st)
                accept(msg, st, now, settings)
                return ACCEPTED_REBASE, None
        else:
            c = REFUSED_DUPLICATE if r.code == "duplicate" else REFUSED_RANGE
        if len(st.refused_seqs) < REFUSED_SEQS_MAX:
            st.refused_seqs.add(msg["seq"])
        return c, r
    accept(msg, st, now, settings)
    return ACCEPTED, None


# ---- warm-up -----------------------------------------------------------------------------------------------


def warm() -> dict:
    """Compile (or load from the on-disk cache) the kernel; what it took."""
    t0 = time.perf_counter()
    import numba  # noqa: F401 - timed apart: part of any first call, not of the kernel

    t1 = time.perf_counter()
    k = _kernel()
    fs = FleetStreams(IngestSettings(), capacity=2)
    a = fs.add()
    fs.decide(np.array([a, a], np.int32), np.zeros(2, np.int8), np.array([0.0, 0.01]), np.array([0, 1]),
              np.ones(2, bool), np.array([0.0, 0.01]))
    s = k.stats
    t2 = time.perf_counter()
    return {"first_call_s": round(t2 - t0, 3), "numba_import_s": round(t1 - t0, 3),
            "compile_or_load_s": round(t2 - t1, 3), "cache_hits": sum(s.cache_hits.values()),
            "cache_misses": sum(s.cache_misses.values()), "cache_dir": str(getattr(s, "cache_path", ""))}


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m services.ingest.fleet",
                                 description="ingest's per-sample rules over a fleet window (numba kernel)")
    ap.add_argument("--warm", action="store_true", help="compile the kernel into numba's on-disk cache, or "
                    "load it from there, and say how long it took")
    a = ap.parse_args(argv)
    if not a.warm:
        ap.print_help()
        return 2
    r = warm()
    how = "loaded from the cache" if r["cache_hits"] and not r["cache_misses"] else "compiled and cached"
    print(f"ingest fleet kernel {how} in {r['first_call_s']:.2f} s (importing numba {r['numba_import_s']:.2f} s, "
          f"the kernel {r['compile_or_load_s']:.2f} s; {r['cache_dir']})")
    return 0


if __name__ == "__main__":
    from services.ingest import fleet as _fleet  # the module's own kernel (and cache), not a __main__ copy

    sys.exit(_fleet.main())
