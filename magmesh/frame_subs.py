"""Which shards' fleet frames a group member receives: every shard's, or only its own co-partitioned shard's.

A service takes the per-vehicle streams of a stage before it in that stage's fleet frames
(``magmesh/fleet/{shard}/{kind}``, one shard per upstream instance). Subscribed to every shard (``*``), a member of a
group of N receives N frames for each it needs: when the stage before it is a group with the same member numbers
(co-partitioned: magmesh/groups.py), ``ingest-2``'s frames carry exactly the vehicles ``dmc-2`` holds, and the
others' frames are received, copied and passed over from their header. Zenoh filters by key at the router, so a
member that subscribes to its own shard only receives only that: the other frames cost neither it nor the link.

A member narrows to its own shard (per frame kind) only when that is safe, and widens at once when it may not be:

- **narrow** when, for a kind, every shard whose frames came since the last change has the number of a member of
  this group (the same numbers, none missing or extra), the frames carrying this member's vehicles came from the
  shard with its own number only, this member's group is settled (no hand-over, take-over or warm-up, every
  member answering: :meth:`GroupMember._busy`), and that held for :data:`NARROW_AFTER_S` since the last change;
- **wide** again at once when any liveliness token of the mesh comes or goes (a member of any stage joining,
  stopping or killed: a vehicle may then move to another upstream shard, and a take-over upstream must find this
  member listening) or this member's group is no longer settled.

A switch declares the new subscriptions before it undeclares the old, and each new reader starts only once the old
readers have handed on everything their channels held, so frames stay in order; a frame both delivered is taken
once (its seq no newer than the last taken on its key, within :data:`DEDUPE_S` of the switch: counted as
``duplicates_dropped``). The switch thread never waits on a round (a round can wait a second on a member's answer).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from schemas import keys

from . import groups, zconf

log = logging.getLogger("magmesh.frames")

#: settled this long (no token change, group settled, the frames seen since as described) before a member narrows
NARROW_AFTER_S = 3.0
#: after a switch, a frame whose seq is not newer than the last taken on its key is a second delivery (dropped)
DEDUPE_S = 2.0
CHECK_S = 0.25  # how often the switch thread looks (and at once when a token comes or goes)


class FrameSubscriptions:
    """A group member's fleet-frame subscriptions (one per kind, wide or narrowed to shards) and their readers."""

    def __init__(self, rt: Any, kinds: list[str]):
        self.rt = rt
        self.kinds = list(kinds)
        self.subs: dict[str, tuple[Any, threading.Event]] = {}  # key expression -> (subscriber, reader drained)
        self.narrow: dict[str, str] = {}  # kind -> the one shard received (kinds absent: every shard)
        now = time.monotonic()
        self.changed_at = now  # a liveliness token came or went, or the subscriptions were widened
        self.mine_from: dict[str, dict[str, float]] = {k: {} for k in self.kinds}  # kind -> shard -> last frame of
        self.seen_from: dict[str, dict[str, float]] = {k: {} for k in self.kinds}  # mine / of any vehicles
        self.dedupe_until = 0.0
        self.switched_at = float("-inf")  # the last switch (monotonic s)
        self.stats = {"narrowed": 0, "widened": 0, "duplicates_dropped": 0}
        self._wide = threading.Event()  # widen now (a token came or went)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._token_sub: Any = None

    # ---- main loop (runtime._frame_in) ----
    def noted(self, kind: str, shard: str, mine: bool, now: float) -> None:
        """A frame of ``shard`` was taken in (``mine``: it carried a vehicle this member handles)."""
        d = self.seen_from.get(kind)
        if d is not None:
            d[shard] = now
            if mine:
                self.mine_from[kind][shard] = now

    def duplicate(self, key: str, seq: int, last: int | None) -> bool:
        """Whether a frame is a second delivery of one taken (only within DEDUPE_S of a switch)."""
        if last is None or seq > last or time.monotonic() >= self.dedupe_until:
            return False
        self.stats["duplicates_dropped"] += 1
        return True

    # ---- subscriptions ----
    def start(self) -> None:
        for kind in self.kinds:
            self._declare(keys.fleet_frames(kind), ())
        self._token_sub = self.rt.session.liveliness().declare_subscriber(keys.svc_token("*", "*"), self._on_token)
        t = threading.Thread(target=self._run, daemon=True, name="magmesh-frames")
        t.start()
        self.rt.threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self._wide.set()

    def _on_token(self, _smp: Any) -> None:  # (Zenoh's thread: noted, the switch thread woken; nothing else)
        self.changed_at = time.monotonic()
        self._wide.set()

    def _declare(self, kexpr: str, after: tuple) -> None:
        import zenoh

        from .runtime import FIFO_CAPACITY

        sub = self.rt.session.declare_subscriber(kexpr, zenoh.handlers.FifoChannel(FIFO_CAPACITY))
        done = threading.Event()
        self.subs[kexpr] = (sub, done)
        # the channel itself: what it holds is still read after the subscriber is undeclared
        self.rt._spawn(self.rt._reader, sub.handler, "s", after, done)

    def _switch(self, narrow: dict[str, str]) -> None:
        want = {keys.fleet_frame(narrow[k], k) if k in narrow else keys.fleet_frames(k) for k in self.kinds}
        with self._lock:
            old = {k: v for k, v in self.subs.items() if k not in want}
            new = [k for k in sorted(want) if k not in self.subs]
            if not old and not new:
                self.narrow = dict(narrow)
                return
            self.switched_at = time.monotonic()
            self.dedupe_until = self.switched_at + DEDUPE_S
            after = tuple(done for _, done in old.values())
            for k in new:
                self._declare(k, after)
            for k, (sub, _) in old.items():
                del self.subs[k]
                try:
                    sub.undeclare()
                except Exception as e:  # noqa: BLE001 - closing: the session goes with it
                    log.debug("undeclaring %s: %s", k, e)
            widened = not narrow or not narrow.items() >= self.narrow.items()  # (narrowed: kinds only added)
            self.narrow = dict(narrow)
        if widened:
            self.stats["widened"] += 1
        else:
            self.stats["narrowed"] += 1
        log.info("%s: fleet frames now from %s", self.rt.svc.instance,
                 ", ".join(f"{k}: {narrow.get(k, '*')}" for k in self.kinds))

    # ---- the switch thread ----
    def _run(self) -> None:
        zconf.os_thread_name("mm-frames")
        while not self._stop.is_set():
            woken = self._wide.wait(CHECK_S)
            if self._stop.is_set():
                return
            try:
                if woken:
                    self._wide.clear()
                    if self.narrow:
                        self._switch({})
                    continue
                self._step(time.monotonic())
            except Exception as e:  # noqa: BLE001 - subscriptions stay as they are; the next look tries again
                self.rt.last_error = f"frame subscriptions: {type(e).__name__}: {e}"[:500]

    def _settled(self) -> bool:
        g = self.rt.group
        return g is not None and g.ready and g.complete and g.settled and not g.leaving

    def _step(self, now: float) -> None:
        g = self.rt.group
        if not self._settled():
            if self.narrow:
                self.changed_at = now
                self._switch({})
            return
        since = self.changed_at
        if now - since < NARROW_AFTER_S or not g.owned or len(self.narrow) == len(self.kinds):
            return
        mine_slot = groups.slot(g.me)
        slots = {groups.slot(m) for m in g.members}
        narrow = dict(self.narrow)  # (kinds narrowed before stay so: their other shards are no longer seen)
        for kind in self.kinds:
            if kind in narrow:
                continue
            shards = {s for s, t in list(self.seen_from[kind].items()) if t >= since}
            mine = {s for s, t in list(self.mine_from[kind].items()) if t >= since}
            if len(shards) < 2 or {groups.slot(s) for s in shards} != slots or len(mine) != 1:
                continue  # not co-partitioned with this group (or nothing to save): every shard
            (s,) = mine
            if groups.slot(s) == mine_slot and all(groups.slot(x) != groups.slot(s) or x == s for x in shards):
                narrow[kind] = s
        if len(narrow) > len(self.narrow):
            self._switch(narrow)

    def status(self) -> dict:
        return {"narrow": dict(self.narrow), **self.stats}
