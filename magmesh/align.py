"""The time aligner: joins a vehicle's streams by sample time, with a bounded wall-clock wait. Pure Python.

Streams reach a service through separate subscriptions (or, in contract v2, inside one batch), so a sample
may arrive before the samples of the other streams it belongs with. Two components cover the joins magmesh
services make, and both count everything they give up on, by stream and reason:

- :class:`TimeAligner` — an N-way join: one sample of every stream within ``tolerance_s`` of each other forms
  a :class:`Joined` set (the DMC detector's two compasses; a magnetometer sample and its DMC verdict).
- :class:`CoverWait` — a sample of one stream waits until another stream's time has reached it (so the other
  stream can be interpolated there: a field sample waiting for the INS).

A sample is given up when it can never be joined (``passed``: every other stream has moved past it), when it
has waited ``max_wait_s`` of *wall-clock* time (``expired``: the other stream is late or silent — at any
replay speed the wait is the same real time, never a span of sample time), or when ``max_pending`` samples
of its stream are already waiting (``overflow``). Given-up samples are returned (a caller may still use them
alone, e.g. a heading fuser that goes on without a verdict), and counted in :attr:`gave_up`.
Each stream's samples must arrive in time order (ingest guarantees it on clean data).

The heading fuser's three-way join (IMU, magnetometer, DMC verdict) is a compiled specialisation of these two,
many vehicles per call (``services/heading_fuser/fleet.py``, whose docstring states its rule): a magnetometer
sample waits for the IMU to cover its time (a :class:`CoverWait`) and for its verdict (a wall-clock bounded
wait, as here; one that does not come is counted and the sample used without it); the IMU in turn waits for the
magnetometer stream, bounded in sample time.
"""

from __future__ import annotations

import time
from collections import defaultdict, deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

REASONS = ("passed", "expired", "overflow")


@dataclass(frozen=True)
class Joined:
    """One sample of every stream: ``t_s`` is the reference (first) stream's sample time."""

    t_s: float
    values: dict[Hashable, Any]
    times: dict[Hashable, float]


@dataclass(frozen=True)
class GaveUp:
    stream: Hashable
    t_s: float
    value: Any
    reason: str  # passed | expired | overflow


class _Counts:
    def __init__(self) -> None:
        self.gave_up: dict[str, dict[Hashable, int]] = {r: defaultdict(int) for r in REASONS}
        self.joined = 0

    def counts(self) -> dict:
        """``{"joined": n, "gave_up": {reason: {stream: n}}, "gave_up_total": n}`` (status-friendly)."""
        g = {r: {str(k): v for k, v in d.items() if v} for r, d in self.gave_up.items()}
        return {"joined": self.joined, "gave_up": {r: d for r, d in g.items() if d},
                "gave_up_total": sum(sum(d.values()) for d in g.values())}


class TimeAligner(_Counts):
    """Joins samples of ``streams`` whose times lie within ``tolerance_s`` of each other."""

    def __init__(self, streams: tuple[Hashable, ...], tolerance_s: float, max_wait_s: float = 10.0,
                 max_pending: int = 8192, clock: Callable[[], float] = time.monotonic):
        super().__init__()
        if len(streams) < 2 or len(set(streams)) != len(streams):
            raise ValueError(f"need at least two different streams, got {streams!r}")
        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be ≥ 0, got {tolerance_s}")
        if not max_wait_s > 0:
            raise ValueError(f"max_wait_s must be > 0 (wall-clock seconds), got {max_wait_s}")
        self.streams = tuple(streams)
        self.tolerance_s = float(tolerance_s)
        self.max_wait_s = float(max_wait_s)
        self.max_pending = int(max_pending)
        self.clock = clock
        self.pending: dict[Hashable, deque] = {s: deque() for s in self.streams}  # (t_s, value, arrived)
        self._passed: list[GaveUp] = []  # given up while joining, returned with the next expire()

    def reset(self) -> None:
        for q in self.pending.values():
            q.clear()

    @property
    def waiting(self) -> int:
        return sum(len(q) for q in self.pending.values())

    def push(self, stream: Hashable, t_s: float, value: Any, now: float | None = None
             ) -> tuple[list[Joined], list[GaveUp]]:
        """Add one sample; returns the sets it completed and the samples given up meanwhile."""
        q = self.pending.get(stream)
        if q is None:
            raise ValueError(f"stream {stream!r} is not one of {self.streams}")
        now = self.clock() if now is None else now
        gave: list[GaveUp] = []
        q.append((float(t_s), value, now))
        if len(q) > self.max_pending:
            t0, v0, _ = q.popleft()
            gave.append(self._give_up(stream, t0, v0, "overflow"))
        joined = self._join()
        gave += self.expire(now)
        return joined, gave

    def _join(self) -> list[Joined]:
        out: list[Joined] = []
        tol = self.tolerance_s
        pend = self.pending
        while all(pend[s] for s in self.streams):
            heads = [pend[s][0][0] for s in self.streams]
            hi = max(heads)
            if hi - min(heads) <= tol:
                vals, times = {}, {}
                for s in self.streams:
                    t, v, _ = pend[s].popleft()
                    vals[s], times[s] = v, t
                self.joined += 1
                out.append(Joined(heads[0], vals, times))
                continue
            # a head more than the tolerance older than another stream's head can never be joined
            for s, h in zip(self.streams, heads, strict=True):
                if h < hi - tol:
                    t, v, _ = pend[s].popleft()
                    self._passed.append(self._give_up(s, t, v, "passed"))
        return out

    def expire(self, now: float | None = None) -> list[GaveUp]:
        """Give up samples that waited ``max_wait_s`` of wall-clock time (also call it from a tick)."""
        now = self.clock() if now is None else now
        out, self._passed = self._passed, []
        lim = now - self.max_wait_s
        for s, q in self.pending.items():
            while q and q[0][2] <= lim:
                t, v, _ = q.popleft()
                out.append(self._give_up(s, t, v, "expired"))
        return out

    def _give_up(self, stream: Hashable, t: float, v: Any, reason: str) -> GaveUp:
        self.gave_up[reason][stream] += 1
        return GaveUp(stream, t, v, reason)


class CoverWait(_Counts):
    """Samples of one stream wait until another stream's time reaches theirs (released in time order)."""

    def __init__(self, max_wait_s: float = 10.0, max_pending: int = 8192, stream: Hashable = "primary",
                 clock: Callable[[], float] = time.monotonic):
        super().__init__()
        if not max_wait_s > 0:
            raise ValueError(f"max_wait_s must be > 0 (wall-clock seconds), got {max_wait_s}")
        self.max_wait_s = float(max_wait_s)
        self.max_pending = int(max_pending)
        self.stream = stream
        self.clock = clock
        self.pending: deque = deque()  # (t_s, value, arrived)
        self.covered_t: float | None = None

    def reset(self) -> None:
        self.pending.clear()
        self.covered_t = None

    def push(self, t_s: float, value: Any, now: float | None = None) -> tuple[list[tuple[float, Any]], list[GaveUp]]:
        """Add a sample; returns the samples released (time ≤ the other stream's) and those given up."""
        now = self.clock() if now is None else now
        self.pending.append((float(t_s), value, now))
        gave = []
        if len(self.pending) > self.max_pending:
            t, v, _ = self.pending.popleft()
            gave.append(self._give_up(t, v, "overflow"))
        rel = self._release()
        return rel, gave + self.expire(now)

    def advance(self, t_other: float, now: float | None = None) -> tuple[list[tuple[float, Any]], list[GaveUp]]:
        """The other stream reached ``t_other``: release what it now covers."""
        if self.covered_t is None or t_other > self.covered_t:
            self.covered_t = float(t_other)
        return self._release(), self.expire(now)

    def _release(self) -> list[tuple[float, Any]]:
        out = []
        c = self.covered_t
        while self.pending and c is not None and self.pending[0][0] <= c:
            t, v, _ = self.pending.popleft()
            self.joined += 1
            out.append((t, v))
        return out

    def expire(self, now: float | None = None) -> list[GaveUp]:
        now = self.clock() if now is None else now
        lim = now - self.max_wait_s
        out = []
        while self.pending and self.pending[0][2] <= lim:
            t, v, _ = self.pending.popleft()
            out.append(self._give_up(t, v, "expired"))
        return out

    def _give_up(self, t: float, v: Any, reason: str) -> GaveUp:
        self.gave_up[reason][self.stream] += 1
        return GaveUp(self.stream, t, v, reason)
