"""A read-only tap on the mesh for the ecosystem bridges (Foxglove, ROS 2): subscribe, drain, hand over.

Samples are taken from FIFO channels by the caller's thread (never in a Zenoh callback: a slow consumer
must not stall the session) and handed to ``on_sample(key, payload, receive_ns)`` in arrival order per key
expression. Delete samples are counted, not handed over.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence

from schemas import keys, messages

FIFO_CAPACITY = 16384
IDLE_SLEEP_S = 0.0005
MAX_IDLE_SLEEP_S = 0.005


def run_tap(session, key_exprs: Sequence[str], on_sample: Callable[[str, bytes, int], None],
            stop: threading.Event, duration_s: float = 0.0, on_tick: Callable[[], None] | None = None,
            tick_s: float = 1.0, ready: threading.Event | None = None) -> Counter:
    """Drain subscriptions on ``key_exprs`` until ``stop`` is set or ``duration_s`` passes (0: no limit).

    Overlapping key expressions would deliver a sample twice: give disjoint ones. Returns counts
    (``received``, ``deletes``).
    """
    import zenoh

    counts: Counter = Counter()
    subs = [session.declare_subscriber(e, zenoh.handlers.FifoChannel(FIFO_CAPACITY)) for e in key_exprs]
    if ready is not None:
        ready.set()
    t_end = time.monotonic() + duration_s if duration_s and duration_s > 0 else None
    next_tick = time.monotonic() + tick_s
    idle = IDLE_SLEEP_S
    try:
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            n = 0
            for sub in subs:
                while True:
                    s = sub.try_recv()
                    if s is None:
                        break
                    n += 1
                    if s.kind != zenoh.SampleKind.PUT:
                        counts["deletes"] += 1
                        continue
                    counts["received"] += 1
                    on_sample(str(s.key_expr), s.payload.to_bytes(), time.time_ns())
            if n == 0:
                time.sleep(idle)
                idle = min(idle * 1.5, MAX_IDLE_SLEEP_S)
            else:
                idle = IDLE_SLEEP_S
            if on_tick is not None and time.monotonic() >= next_tick:
                next_tick = time.monotonic() + tick_s
                on_tick()
    finally:
        for sub in subs:
            sub.undeclare()
    return counts


def decode_samples(key: str, payload: bytes) -> list[tuple[str, dict]]:
    """The validated v1 messages a payload carries, each with its per-stream key: one for a single sample,
    every sample of a batch (contract v2, ``raw/batch`` / ``clean/batch``) on its stream's own key, in order.

    Raises :class:`schemas.messages.SchemaError` when the payload is not a valid magmesh message and
    :class:`schemas.keys.KeyError_` when the key is outside the contract.
    """
    info = keys.parse(key)
    if info.kind in ("raw", "clean") and info.rest and info.rest[0] == keys.BATCH:
        from schemas import batch

        b = batch.decode(payload, where=key)
        out = []
        for name, cols in b.streams.items():
            skey = batch.stream_key(info.kind, info.vehicle, name)
            out.extend((skey, m) for m in cols.messages(info.vehicle))
        return out
    return [(key, messages.decode(payload, where=key))]
