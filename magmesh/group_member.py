"""Elastic roles: one instance's side of a role group (``--group NAME``; the manifest's ``instances = N``).

The members of group ``NAME`` of role ``R`` are the live instances ``magmesh/svc/R/NAME-*`` (liveliness). Each
vehicle belongs to one member, by rendezvous hashing over the members that are not leaving
(:mod:`magmesh.groups`); every member computes the same owner. An instance handles the inputs of the vehicles it
holds only (the others are skipped by design, counted in ``group.not_owned``), and moves vehicles as the
membership changes, per vehicle, with the live-swap protocol (cut at an agreed sample time) run by the new owner:

- **hand-over** (a member joined, or the holder is leaving the group): the new owner warms on the vehicle
  (handles its input, publishes nothing) for ``warmup_s`` of sample time (:data:`WARMUP_S`), then asks the holder
  to release it to itself (``g_release``): the holder chooses a cut ``lead_s`` ahead of the input it has handled,
  and no earlier than the new owner's first input plus ``warmup_s``, and publishes only before it; the new owner
  holds its own outputs at or after the cut (those it made while warming too); once the holder has passed the
  cut (or its input stalled for ``stall_s``) it takes the holder's seq per key and alarm states for the vehicle,
  publishes what it held, and tells the holder (``g_done``, again each round until it answers). Subscribers see
  every epoch once, seq continuing. The holder keeps its outputs from the cut on (it stops handling the vehicle
  there) until told: if the new owner goes (or stops taking the vehicle) without having published any, the holder
  takes the vehicle back and publishes them (what it did not handle meanwhile is an input gap it counts); a
  vehicle already promised to one member is not released to another. A member warms on at most ``MAX_WARMING`` vehicles at once (a warming vehicle costs its work twice).
- **failure** (the holder's liveliness is gone, e.g. kill -9): the new owner takes the vehicle at once from what
  the dead members left in the state directory: their seq journals (last output seq per key, last input seq
  handled, the vehicle's drop counts) and alarm files (a raised alarm stays raised until the new owner's logic decides). Every input the
  dead holder had not handled before the new owner's first one is counted as ``lost_in_takeover`` on its key;
  a vehicle for which nothing was persisted is counted in ``group.unrecovered``. A holder killed after passing the
  cut of a hand-over (it journals that) leaves the hand-over to complete from its journal: the new owner publishes
  the outputs it held from the cut on, nothing lost. A dead member whose journal is not where this member looks
  (another host, another state directory) is taken over from what the mesh showed (:meth:`GroupMember._mesh_state`:
  its fleet frames' last seq and time per output key, its alarm transitions, its last ``g_state`` answer's input
  seqs and counts, and each input key's rate up to its last output).
- **duplicates** (two members took one new vehicle before they saw each other): the one the rule does not pick
  among the holders drops it at once (``group.duplicates_dropped``).

A member decides to take a vehicle nobody holds only in a round in which every live member answered (a member
slow to answer under load is never taken for one holding nothing), and takes a member for gone only when its
liveliness token went and it does not answer a query either (a token can lapse while its member goes on
serving). All state changes run in the runtime's main loop (posted as events, ordered with the input); the
coordination thread only queries.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from schemas import keys

from . import groups, zconf

log = logging.getLogger("magmesh.group")

#: cal/params samples kept per key for vehicles not held here, replayed when one is taken (a new owner must not
#: wait for the next parameter set to be published)
PARAMS_CACHE_MAX = 100_000
WARM_BUFFER = 4096  # outputs kept per warming vehicle
SETTLE_S = 1.0  # after its start a member takes no vehicle for this long (the membership is learnt first)
#: vehicles one member warms on (or awaits the cut of) at once. A warming vehicle is handled twice (by its holder
#: and its new owner); seen with 30 cars on 2 cores: a restarted member warming on its 16 vehicles at once, and
#: every member then fell tens of seconds behind its input
MAX_WARMING = 4
#: sample time a new owner warms on a vehicle before the cut, and the least span between its first input and the
#: cut: long enough for a service's decisions to depend only on input both instances have seen. The DMC detector's
#: feature windows take 0.7 s and its alarm clears after 3 s of valid epochs (raises after 0.3 s): with less, a
#: new owner's latch could clear later than the holder's would have (seen with 3 s: a clear 3.6 s late)
WARMUP_S = 5.0
#: while this member may be cut off (it saw members go and does not hear their vehicles), a held vehicle whose
#: outputs paused this long (wall time) has its next outputs held until a complete round after them: when a link
#: between hosts comes back, a member that was cut off from the vehicle's input (and taken for gone by the others,
#: one of which took the vehicle over and went on) must not publish from its stale state first
PAUSE_S = 1.0
#: input heard this long before a holder was seen gone still counts as heard since, so the take is not put off by a
#: round (under load a round takes up to seconds: taking a round later, take-overs of the 30-car eval went from
#: 0.29-0.43 s to 0.2-3.7 s); a member cut off by a link outage heard its last input a lease (1 s or more) before
#: it saw the others go
HEARD_MARGIN_S = 0.5
#: the last samples of each input key of another member's vehicles kept as received (one reference each, decoded
#: only at a take-over): a member taking a vehicle from what the mesh showed reads from them the seq its holder had
#: reached at its last output's sample time. 128 is 2.5 s of a 50 Hz compass (take-overs take 0.1-1.2 s here); an
#: estimate from the key's rate was one sample off now and then, sample times being those of a real clock
HEARD_KEEP = 128
#: keys kept so at most (a bound on memory: about 25 MB of 200-byte samples; keys beyond it use the rate's estimate)
HEARD_KEYS_MAX = 1024
#: a dead member's last alarm transition that the mesh never showed is published again by its successor only when it
#: was written (wall time) at least this long after the successor's alarm watch was first read (one put before was
#: not watched for)
REPUBLISH_MARGIN_S = 0.5


#: how often (wall s) a round asks the others for their ``held`` table (every input key's seq and sample time of every
#: vehicle they hold, the part of an answer that grows with the fleet); the other rounds ask for membership and
#: hand-overs only. Asked every round (0.2 s), building, encoding and reading it took about 30 % of a core across the
#: four stages' members at 600 vehicles, two per stage (``magmesh bench mesh``); a failover from the mesh estimates
#: what its holder handled after the last table from the key's rate (:meth:`GroupMember._mesh_state`). Asked only
#: while another live member keeps its seq journal elsewhere: a failover from a member journalled on this host reads
#: the journal
HELD_PERIOD_S = 1.0

#: how often (wall s) a settled member runs its round: no hand-over, take-over, pause or warm-up under way here, every
#: member answering, and the membership and this member's holdings unchanged for :data:`STEADY_AFTER_S`; otherwise a
#: round every ``period_s`` (0.2 s). A settled round still costs a query to every other member and a pass over every
#: vehicle seen (about 0.7 % of a core per member at 500 vehicles, two per stage, at 0.2 s). What must not wait wakes
#: the round at once: a liveliness token that comes or goes (a member joining, stopping or killed) and a hand-over
#: request or a leave (``g_release``, ``g_done``, ``g_leave``). What may wait up to this long: another member's leave
#: seen in its answers, and a membership change whose token lapsed without a change of answers
IDLE_PERIOD_S = 1.0
STEADY_AFTER_S = 3.0

#: the drop counts a member's seq journal keeps per key, by the letter of their entries (magmesh/runtime.py)
_JOURNALLED = {"upstream_gap": "u", "lost_during_restart": "l", "lost_in_takeover": "t"}


@functools.lru_cache(maxsize=1 << 14)
def vehicle_of(key: str) -> str | None:
    """The vehicle a data key names (None for a key that names none; the last 16,384 keys' answers kept: every
    round reads it for each key a member handles)."""
    parts = key.split("/", 3)
    return parts[1] if len(parts) >= 3 and parts[0] == keys.ROOT and parts[1] != keys.SVC else None


def _pending(sub: Any):
    """The samples a channel holds now (none for no subscriber)."""
    while sub is not None:
        smp = sub.try_recv()
        if smp is None:
            return
        yield smp


_BATCH_SUFFIX = "/" + keys.BATCH


def _is_params(key: str) -> bool:
    parts = key.split("/")
    return len(parts) > 3 and parts[2] == "cal" and parts[3] == "params"


def _notifying(base: type, name: str) -> Callable:
    """``base``'s method ``name``, then the container's ``on_change`` (every method that changes a set or dict)."""
    method = getattr(base, name)

    def changed(self: Any, *a: Any, **kw: Any) -> Any:
        out = method(self, *a, **kw)
        self._on()
        return out

    changed.__name__ = name
    return changed


class _TrackedSet(set):
    """A set of a member's holdings that calls ``on_change`` after every change: a frame's admitted mask
    (:meth:`GroupMember.admitted`) is kept per vehicle list and made again only when one of them changed."""

    def __init__(self, on_change: Callable[[], None]):
        super().__init__()
        self._on = on_change


class _TrackedDict(dict):
    """A dict of a member's holdings that calls ``on_change`` after every change (see :class:`_TrackedSet`)."""

    def __init__(self, on_change: Callable[[], None]):
        super().__init__()
        self._on = on_change


for _name in ("add", "discard", "remove", "pop", "clear", "update", "difference_update", "intersection_update",
              "symmetric_difference_update", "__ior__", "__iand__", "__isub__", "__ixor__"):
    setattr(_TrackedSet, _name, _notifying(set, _name))
for _name in ("__setitem__", "__delitem__", "pop", "popitem", "setdefault", "clear", "update", "__ior__"):
    setattr(_TrackedDict, _name, _notifying(dict, _name))


#: how long (s) a member takes another member's seq journal as there or not on this host (:meth:`_observe`)
JOURNAL_CHECK_S = 5.0

#: vehicle lists whose admitted masks and heard times a member keeps (a service's frames carry one list per
#: upstream shard, the same object frame after frame: schemas/frame.py)
LISTS_KEPT = 64


class GroupMember:
    def __init__(self, rt: Any, name: str, warmup_s: float = WARMUP_S, lead_s: float = 0.5, stall_s: float = 2.0,
                 period_s: float = 0.2):
        self.rt = rt
        self._gen = 0  # bumped by every change of the holdings (owned, seen, warming, arm, release, passed)
        self._adm: dict[int, tuple[list, int, Any, int]] = {}  # id(list) -> (list, _gen, mask, not owned)
        self._plain_set: tuple[int, set[str]] | None = None  # (_gen, vehicles held with no hand-over under way)
        self._heard_lists: dict[int, list] = {}  # id(list) -> [list, when a frame of it was last heard, its set]
        self.rt = rt
        self.name = keys.check_id(name, "group name")
        self.role = rt.svc.role
        self.me = rt.svc.instance
        self.warmup_s, self.lead_s, self.stall_s, self.period_s = warmup_s, lead_s, stall_s, period_s
        self.members: list[str] = [self.me]
        self.live: set[str] = {self.me}
        self.leaving = False
        self.ready = False  # one complete coordination round done: the others' holdings are known
        self.complete = False  # the last round heard every live member
        self.holdings: dict[str, str] = {}  # vehicle -> the other member holding it (last round)
        self.owned: set[str] = _TrackedSet(self._changed)
        self.seen: set[str] = _TrackedSet(self._changed)
        self.warming: dict[str, str] = _TrackedDict(self._changed)  # vehicle -> the holder it is handed over from
        #: vehicle -> (holder, cut, since) awaiting the takeover
        self.arm: dict[str, tuple[str, float, float]] = _TrackedDict(self._changed)
        self.held: list[tuple] = []
        #: after a hand-over: outputs before the cut were the holder's
        self.post_cut: dict[str, float] = _TrackedDict(self._changed)
        self.release: dict[str, float] = _TrackedDict(self._changed)  # vehicle -> cut: this instance hands it over
        self.release_to: dict[str, str] = {}  # vehicle -> the member it is handed over to
        #: outputs of a vehicle being handed over at or after its cut: published only if the hand-over fails (the
        #: new owner went before taking it), dropped when the new owner confirms (g_done)
        self.release_buf: dict[str, deque] = {}
        self.done_pending: dict[str, str] = {}  # vehicle taken over -> its former holder, until it confirmed g_done
        self.passed: set[str] = _TrackedSet(self._changed)
        self.progress: dict[str, tuple[Any, float]] = {}
        self.params_cache: dict[str, bytes] = {}
        #: outputs of a warming vehicle (not published), kept for a while: those at or after the cut the holder
        #: chooses are published by this instance once it holds the vehicle, however far ahead of the holder it was
        self.warm_buf: dict[str, deque] = {}
        self.stats = {"not_owned": 0, "handovers_in": 0, "handovers_out": 0, "failovers": 0, "unrecovered": 0,
                      "duplicates_dropped": 0, "suppressed": 0, "takeover_s_max": 0.0, "last_takeover_s": None,
                      "rounds": 0, "rounds_incomplete": 0, "liveliness_lapses": 0, "reclaimed": 0,
                      "failovers_from_mesh": 0, "held_after_pause": 0, "duplicates_behind": 0,
                      "alarms_sent_again": 0, "output_watch": False}
        # what the mesh showed of the vehicles other members hold, for a failover from a member whose journal is not
        # on this host (another host, or another state directory): see _mesh_state
        self.seen_out: dict[str, dict[str, tuple[int, float]]] = {}  # vehicle -> output key -> (seq, t_s) last seen
        self.seen_alarm: dict[str, tuple[int, dict]] = {}  # alarm key -> (seq, message) of the last transition seen
        self.snap: dict[str, dict] = {}  # member -> its vehicles' input seqs and counts, from its last g_state answer
        self.in_rate: dict[str, tuple[float, int, float, int]] = {}  # input key -> (t0, seq0, t1, seq1) of two answers
        self._out_sub: Any = None
        self._out_kexpr: str | None = None  # the role's fleet frames, watched while a member is elsewhere
        self._alarm_sub: Any = None
        self._alarm_watch_t: tuple[float, float] | None = None  # alarm watch: (first read, last read), wall s
        self._stop = threading.Event()
        self._wake = threading.Event()  # a round now: a token came or went, a hand-over was asked for (IDLE_PERIOD_S)
        self._steady_since = time.monotonic()  # the membership and holdings last changed (see _busy)
        self._steady_key: tuple = ()
        self.idle_period_s = max(period_s, IDLE_PERIOD_S)
        self.round_s = period_s  # the wait before the next round (status)
        self.settled = False  # as of the last round: nothing under way (see _busy; magmesh/frame_subs.py reads it)
        self._thread: threading.Thread | None = None
        self._dead_since: dict[str, float] = {}  # member -> when its liveliness was seen gone
        self._leaving_seen: set[str] = set()
        self._lapsed: set[str] = set()  # members whose token went but that still answer (kept as live)
        self._journal_seen: dict[str, tuple[bool, float]] = {}  # shard -> (its journal is here, when looked)
        self._held_asked = float("-inf")  # when a round last asked the others for their held tables (monotonic s)
        self.last_holder: dict[str, str] = {}  # vehicle -> the other member last seen holding it
        self._tokens: set[str] = set()  # live instances of the role (liveliness tokens)
        self._token_sub: Any = None
        self._token_q: deque = deque()  # (instance, gone) as the token subscriber's callback got them
        self._files_cache: tuple | None = None  # (state dir, live set, when listed, journals, alarm files): _state_files
        self._started = time.monotonic()
        self.skipped_early = 0  # counted by the reader threads (see skips)
        #: vehicle -> when its input last reached this member while another held it (monotonic s; noted by the
        #: reader threads and the frame filter): a vehicle whose holder went is taken once its input has come since
        #: (or at once when one of its alarms is held raised), so a member cut off from the vehicles (a link outage
        #: between hosts) takes no more of the others' vehicles than it hears
        self.heard_t: dict[str, float] = {}
        self.heard_buf: dict[str, deque] = {}  # input key -> its last HEARD_KEEP payloads skipped here (see skips)
        self._raised_checked: dict[str, float | None] = {}  # vehicle -> the going (since) its raised alarms were sought for
        self.last_out: dict[str, float] = {}  # vehicle -> when its last output passed the gate (monotonic s)
        self.paused: dict[str, int] = {}  # vehicle -> the round its outputs were held in after a pause (PAUSE_S)
        #: since when vehicles of members seen gone are not heard here (this member may be the one cut off): the
        #: pause rule applies only then
        self.cut_off_since: float | None = None
        self.pause_buf: dict[str, deque] = {}

    def _changed(self) -> None:
        self._gen += 1

    # ---- reader threads ---------------------------------------------------------------------------
    def skips(self, key: str, payload: Any = None) -> bool:
        """Whether an input is another member's (a vehicle seen before and neither held, warming nor being
        handed over here): dropped before it is queued, so this member's loop carries only its own vehicles
        (a take-over is not delayed behind the others' samples). Parameter sets always go on (kept for a take);
        a sample skipped just before this member takes its vehicle over is counted by the take-over's seq gap.
        ``payload`` (Zenoh's, of a skipped sample): the last :data:`HEARD_KEEP` of the key are kept undecoded
        (:meth:`_heard_seq`), batches not (only single samples are read back)."""
        v = vehicle_of(key)
        # in the order a vehicle goes through them (warming, taking, held, releasing): each state change enters
        # the next before it leaves the last, so a check made while the loop moves it still finds it
        if v is None or v not in self.seen or v in self.warming or v in self.arm or v in self.owned \
                or v in self.release or _is_params(key):
            return False
        self.heard_t[v] = time.monotonic()
        self.skipped_early += 1
        # (a batch is never read back: _heard_seq reads the seq of single samples only)
        if payload is not None and not key.endswith(_BATCH_SUFFIX):
            buf = self.heard_buf.get(key)
            if buf is None and len(self.heard_buf) < HEARD_KEYS_MAX:
                # (one reader thread per subscription: a key is only ever appended to by one)
                buf = self.heard_buf[key] = deque(maxlen=HEARD_KEEP)
            if buf is not None:
                buf.append(payload.to_bytes())
        return True

    def holds(self, vehicle: Any) -> bool:
        """Whether this member speaks for ``vehicle`` now (alarm queries): it holds it, or hands it over and has
        not passed the cut (from there on the new owner's outputs count, alarm transitions included: a holder
        answering its own raised state after the new owner published a clear made the supervisor take the clear
        for unconfirmed)."""
        return vehicle in self.owned or (vehicle in self.release and vehicle not in self.passed)

    # ---- main loop side ---------------------------------------------------------------------------
    def admits(self, key: str, payload: bytes | None = None) -> bool:
        """Whether the input on ``key`` is handled here (its vehicle is held, warming or being handed over)."""
        v = vehicle_of(key)
        if v is None:
            return True  # not a vehicle key: the input path refuses it with its reason
        if v in self.owned or v in self.warming or v in self.arm or (v in self.release and v not in self.passed):
            # (a holder past the cut handles no more of the vehicle: its journal then says what it published, or
            # kept from the cut on, which is what a new owner taking it from there after a kill -9 must know)
            return True
        if v not in self.seen:
            # a vehicle nobody held in the last round every member answered: its owner by the rule takes it at
            # once (whether the latest round was complete or not: a member slow to answer under load holds no
            # vehicle this one has never seen, unless the rule gives it to that member; if two members' views of
            # the membership differ, the duplicate is dropped in the next complete round). Waiting for a complete
            # round instead dropped the vehicle's first samples at every member (seen: 4,070 samples at 200
            # vehicles, load 16)
            take = self.ready and not self.leaving and v not in self.holdings \
                and groups.owner(v, self.members) == self.me
            if take:  # nobody holds it: its owner takes it at once (held before it is seen: see skips)
                self._failover(v, self._dead_state(v), None)
            if len(self.seen) < 1_000_000:
                self.seen.add(v)
            if take:
                return True
        if payload is not None and _is_params(key) and (key in self.params_cache or
                                                        len(self.params_cache) < PARAMS_CACHE_MAX):
            self.params_cache[key] = payload
        self.stats["not_owned"] += 1
        return False

    def admitted(self, vehicles: list[str], key_of: Callable[[str], str]) -> Any:
        """:meth:`admits` for every vehicle of a fleet frame at once (a numpy bool mask), and :meth:`admits` itself
        only for a vehicle not seen before (its owner may take it now). ``key_of`` gives a vehicle's key of the
        frame's stream (for those). A frame's vehicle list is the same object frame after frame: its mask is kept
        and made again only when the holdings changed (``_gen``), and the time it was heard is noted per list (read
        by :meth:`_heard_at`) — a few µs a frame where a set lookup per vehicle took 50-100 µs at 300 vehicles."""
        import numpy as np

        now = time.monotonic()
        h = self._heard_lists.get(id(vehicles))
        if h is not None and h[0] is vehicles:
            h[1] = now
        else:
            if len(self._heard_lists) >= LISTS_KEPT:  # the oldest list's times into heard_t, then forgotten
                old = min(self._heard_lists, key=lambda i: self._heard_lists[i][1])
                lst, t, _ = self._heard_lists.pop(old)
                for v in lst:
                    if self.heard_t.get(v, float("-inf")) < t:
                        self.heard_t[v] = t
            self._heard_lists[id(vehicles)] = [vehicles, now, None]
        c = self._adm.get(id(vehicles))
        if c is not None and c[0] is vehicles and c[1] == self._gen:
            self.stats["not_owned"] += c[3]
            return c[2]
        seen = self.seen
        new = [v for v in vehicles if v not in seen] if not seen.issuperset(vehicles) else []
        for v in new:
            self.admits(key_of(v))  # (counts it as not owned when it is not taken)
        here = self.owned | self.warming.keys() | self.arm.keys() | (self.release.keys() - self.passed)
        mask = np.fromiter((v in here for v in vehicles), bool, len(vehicles))
        mask.flags.writeable = False  # (kept for the frames after: a reader must not change it)
        not_owned = len(vehicles) - int(mask.sum())
        self.stats["not_owned"] += not_owned - sum(1 for v in new if v not in here)
        if len(self._adm) >= LISTS_KEPT:
            self._adm.clear()
        self._adm[id(vehicles)] = (vehicles, self._gen, mask, not_owned)
        return mask

    def _heard_at(self, v: str) -> float | None:
        """When input of vehicle ``v`` last reached this member while another held it (monotonic s; None: never):
        single samples (:meth:`skips`) and fleet frames (:meth:`admitted`, per vehicle list)."""
        t = self.heard_t.get(v)
        for h in list(self._heard_lists.values()):
            if t is not None and h[1] <= t:
                continue
            if h[2] is None:
                h[2] = frozenset(h[0])
            if v in h[2]:
                t = h[1]
        return t

    def plain(self, vehicle: str) -> bool:
        """Whether every output of ``vehicle`` is this instance's to publish now, whatever its time: it holds the
        vehicle and no hand-over of it is under way (what :meth:`gate` would say for any ``t_s``)."""
        return vehicle in self.owned and vehicle not in self.post_cut and vehicle not in self.release \
            and vehicle not in self.arm and vehicle not in self.warming and self._flowing(vehicle)

    def plain_many(self, vehicles: Any) -> dict[str, bool]:
        """:meth:`plain` for each of ``vehicles`` (a frame's, once each): the vehicles held with no hand-over under
        way are kept as one set until the holdings change, and while this member is not cut off and no output is
        held after a pause, flowing is one time for them all (what :meth:`_flowing` notes vehicle by vehicle)."""
        c = self._plain_set
        if c is None or c[0] != self._gen:
            held = self.owned - self.post_cut.keys() - self.release.keys() - self.arm.keys() - self.warming.keys()
            c = self._plain_set = (self._gen, held)
        held = c[1]
        if self.cut_off_since is not None or self.paused:
            return {v: v in held and self._flowing(v) for v in vehicles}
        out = {v: v in held for v in vehicles}
        self.last_out.update(dict.fromkeys((v for v, ok in out.items() if ok), time.monotonic()))
        return out

    def _flowing(self, v: str) -> bool:
        """Whether an output of held vehicle ``v`` goes out now: False while its outputs are held after a pause
        (:data:`PAUSE_S`), until a complete round after it has shown no other member holding ``v`` with outputs
        ahead of this one's (:meth:`_round`)."""
        if v in self.paused:
            return False
        now = time.monotonic()
        last = self.last_out.get(v)
        self.last_out[v] = now
        if last is not None and now - last > PAUSE_S and self.cut_off_since is not None:
            self.paused[v] = self.stats["rounds"]
            self.stats["held_after_pause"] += 1
            return False
        return True

    def gate(self, key: str, msg_type: str, vehicle: str, t_s: float, fields: dict) -> bool:
        """Whether an output of ``vehicle`` at sample time ``t_s`` is this instance's to publish now."""
        cut = self.release.get(vehicle)
        if cut is not None:
            if t_s < cut:
                return True
            if vehicle not in self.passed:
                self._set_passed(vehicle, True)  # the new owner publishes from the cut on
            buf = self.release_buf.get(vehicle)  # (kept until it confirms: published here if it never takes it)
            if buf is None:
                buf = self.release_buf[vehicle] = deque(maxlen=WARM_BUFFER)
            buf.append((key, msg_type, vehicle, t_s, fields))
            return False
        a = self.arm.get(vehicle)
        if a is not None:
            if t_s >= a[1]:
                self.held.append((key, msg_type, vehicle, t_s, fields))
            else:
                self.stats["suppressed"] += 1
            return False
        if vehicle in self.owned:
            pc = self.post_cut.get(vehicle)
            if pc is not None:
                if t_s < pc:
                    self.stats["suppressed"] += 1
                    return False
                del self.post_cut[vehicle]
            if not self._flowing(vehicle):
                buf = self.pause_buf.get(vehicle)
                if buf is None:
                    buf = self.pause_buf[vehicle] = deque(maxlen=WARM_BUFFER)
                buf.append((key, msg_type, vehicle, t_s, fields))
                return False
            return True
        if vehicle in self.warming:
            buf = self.warm_buf.get(vehicle)
            if buf is None:
                buf = self.warm_buf[vehicle] = deque(maxlen=WARM_BUFFER)
            buf.append((key, msg_type, vehicle, t_s, fields))
            return False
        self.stats["suppressed"] += 1  # not held
        return False

    def control(self, req: dict) -> dict:
        op = req.get("op")
        if op == "g_state":
            pass
        elif op == "g_release":  # a new owner takes these vehicles over: this holder chooses the cut
            lead = float(req.get("lead_s", self.lead_s))
            to = str(req.get("from", ""))
            nb = req.get("not_before")
            for v in list(req.get("vehicles", [])):
                if v in self.release:
                    continue  # already agreed (with this member: the first cut stands; with another: not this one)
                if v not in self.owned:
                    return {"ok": False, "error": f"{self.me} does not hold {v}"}
                # ahead of every input handled here: each output before it is this holder's, the rest the new one's;
                # and no earlier than the new owner's warm-up allows (its first input plus warmup_s)
                t = self.rt.last_in_t.get(v)
                cut = (t if t is not None else 0.0) + lead
                if isinstance(nb, (int, float)) and not isinstance(nb, bool) and nb > cut:
                    cut = float(nb)
                self._set_passed(v, False)
                # (released before it stops being held: the reader threads never see it as another's, see skips)
                self.release[v] = cut
                self.release_to[v] = to
                self.owned.discard(v)
                self.stats["handovers_out"] += 1
        elif op == "g_done":  # the new owner has the vehicles: forget them
            for v in req.get("vehicles", []):
                if v in self.release:
                    del self.release[v]
                    self.release_to.pop(v, None)
                    self.release_buf.pop(v, None)
                    self._set_passed(v, False)
                    self._forget(v)
        elif op == "g_leave":  # leave the group: the others take every vehicle over (hand-over)
            self.leaving = True
            self.members = [m for m in self.members if m != self.me]
        else:
            return {"ok": False, "error": f"unknown group op {op!r} (known: g_state, g_release, g_done, g_leave)"}
        if op != "g_state":
            self._wake.set()  # a hand-over or a leave moves on in the next round: not after an idle period
        return {"ok": True, **self.state(held=op != "g_state" or bool(req.get("held", True)))}

    def state(self, held: bool = True) -> dict:
        rt = self.rt
        hand = {}
        for v, cut in list(self.release.items()):
            pre = f"{keys.ROOT}/{v}/"
            # past the cut: an output at or after it came, or its input went a lead beyond it (a logic that
            # publishes nothing for a while still lets the vehicle go)
            last_in_t = rt.last_in_t.get(v)
            passed = v in self.passed or (last_in_t if last_in_t is not None else float("-inf")) >= cut + self.lead_s
            with rt.lock:
                raised = {k: m for k, m in list(rt.raised.items()) if k.startswith(pre)}
            hand[v] = {"seqs": {k: s for k, s in list(rt.seq.items()) if k.startswith(pre)},
                       "drops": {k: dict(d) for k, d in list(rt.drops.items()) if k.startswith(pre)},
                       "alarms": {k: s for k, s in list(rt.alarm_published.items()) if k.startswith(pre)},
                       "raised": raised, "last_in_t": last_in_t, "passed": passed, "cut": cut,
                       "to": self.release_to.get(v)}
        out = {"group": self.name, "instance": self.me, "leaving": self.leaving, "owned": sorted(list(self.owned)),
               "taking": sorted(set(self.warming) | set(self.arm)), "releasing": hand}
        if held:
            out["held"] = self._held()
        return out

    def _held(self) -> dict:
        """Per vehicle held here: the last input seq handled per key, the sample time of the last input and the
        journalled drop counts. The others keep the latest answer, for a failover that finds no journal of this
        member on their host (:meth:`_mesh_state`)."""
        rt = self.rt
        owned = self.owned
        out: dict[str, dict] = {}
        in_seq, last_in_t = getattr(rt, "in_seq", {}), getattr(rt, "last_in_t", {})
        items = getattr(in_seq, "items_t", None)
        for k, sq, t in (items() if items is not None else [(k, s, None) for k, s in list(in_seq.items())]):
            v = vehicle_of(k)
            if v in owned and sq is not None:
                h = out.get(v)
                if h is None:
                    h = out[v] = {"t": last_in_t.get(v), "in": {}, "drops": {}}
                h["in"][k] = [int(sq), h["t"] if t is None else t]
        for k, d in list(getattr(rt, "drops", {}).items()):
            v = vehicle_of(k)
            h = out.get(v)
            if h is not None:
                c = {r: int(n) for r, n in list(d.items()) if r in _JOURNALLED and n}
                if c:
                    h["drops"][k] = c
        return out

    def status(self) -> dict:
        return {"name": self.name, "members": list(self.members), "leaving": self.leaving, "ready": self.ready,
                "vehicles": sorted(self.owned)[:1000], "vehicles_total": len(self.owned),
                "seen": sorted(self.seen)[:1000], "seen_total": len(self.seen),
                "warming": sorted(self.warming), "taking": sorted(self.arm), "releasing": sorted(self.release),
                "round_s": self.round_s, "settled": self.settled,
                **self.stats, "not_owned": self.stats["not_owned"] + self.skipped_early}

    def _clear_vehicle(self, v: str) -> None:
        """Forget what this instance knew of ``v``'s streams (seq tracking, times): a later take starts clean."""
        rt = self.rt
        pre = f"{keys.ROOT}/{v}/"
        for k in rt.in_seq.keys_with(pre):
            del rt.in_seq[k]
        rt.first_in_t.pop(v, None)
        rt.last_in_t.pop(v, None)

    def _forget(self, v: str) -> None:
        """A vehicle handed over (or held by another): its state, raised alarms, alarm states and drop counts are
        not ours (the counts went with it: see :meth:`_drop_counts`)."""
        rt = self.rt
        self.owned.discard(v)
        self.post_cut.pop(v, None)
        self._end_pause(v)
        rt.vehicle_state.pop(v, None)
        self._clear_vehicle(v)
        pre = f"{keys.ROOT}/{v}/"
        self._drop_counts(v)
        for k in [k for k in rt.alarm_published if k.startswith(pre)]:
            del rt.alarm_published[k]
        with rt.lock:
            for k in [k for k in rt.raised if k.startswith(pre)]:
                del rt.raised[k]
        rt.reconcile_pending = {k: x for k, x in rt.reconcile_pending.items() if not k.startswith(pre)}
        rt._persist_alarms()

    def _set_passed(self, v: str, passed: bool) -> None:
        """Whether this holder has passed the cut of ``v``'s hand-over (published all of it before the cut, and
        nothing from it on): journalled, so that a new owner whose holder is killed there takes the vehicle over
        with the outputs it held from the cut on instead of counting them lost (see :meth:`_failover`)."""
        j, name = getattr(self.rt, "journal", None), f"p{keys.ROOT}/{v}/"
        if passed:
            self.passed.add(v)
            if j is not None:
                j.set(name, 1)
        else:
            self.passed.discard(v)
            if j is not None and name in j.slot:  # (also one an earlier life of this member left)
                j.forget([name])

    def _drop_counts(self, v: str) -> None:
        """Forget ``v``'s drop counts here, journal included: they went with the vehicle to another member (a
        hand-over carries them, a take-over reads them from the journal), so a restart of this instance must not
        bring them back (counted twice)."""
        rt = self.rt
        pre = f"{keys.ROOT}/{v}/"
        gone = [k for k in rt.drops if k.startswith(pre)]
        for k in gone:
            del rt.drops[k]  # (group totals stay exact)
        if rt.journal is not None and gone:
            rt.journal.forget([c + k for k in gone for c in "ult"])

    def _end_pause(self, v: str) -> None:
        """The outputs of ``v`` held after a pause: published if this member still holds it, else dropped (the
        member holding it published its own)."""
        self.paused.pop(v, None)
        held = list(self.pause_buf.pop(v, ()))
        if v in self.owned:
            self.last_out[v] = time.monotonic()
            if held:
                self.rt._release_held(held)
        else:
            self.last_out.pop(v, None)  # (a vehicle taken again later starts with no pause)
            self.stats["suppressed"] += len(held)

    def _behind(self, v: str) -> bool | None:
        """Whether another member's outputs of ``v`` (seen in its frames) went further than this one's: True when
        one of them is ahead on some key and none of this member's is ahead; False for the reverse; None when
        neither or both (the rule decides)."""
        seen = self.seen_out.get(v)
        if not seen:
            return None
        seq = self.rt.seq
        theirs = mine = False
        for k, (sq, _t) in list(seen.items()):
            s = seq.get(k, -1)
            theirs = theirs or sq > s
            mine = mine or s > sq
        return None if theirs == mine else theirs

    def _drop_duplicate(self, v: str, behind: bool = False) -> None:
        if v in self.owned:
            self._forget(v)
            self.stats["duplicates_dropped"] += 1
            self.stats["duplicates_behind"] += behind
            log.warning("%s: %s is held by another member %s: dropped here", self.me, v,
                        "whose outputs went further" if behind else "the rule prefers")

    def _reclaim(self, v: str) -> None:
        """A hand-over that did not happen (the new owner went, or dropped the vehicle, before taking it): this
        holder keeps the vehicle and publishes what it kept from the cut on (nothing was published by the other)."""
        if v not in self.release:
            return
        self.owned.add(v)  # (first: see skips)
        del self.release[v]
        self.release_to.pop(v, None)
        self._set_passed(v, False)
        buf = list(self.release_buf.pop(v, ()))
        self.stats["reclaimed"] += 1
        self.stats["handovers_out"] -= 1
        log.warning("%s: the hand-over of %s did not happen: kept here (%d outputs from the cut on published here)",
                    self.me, v, len(buf))
        self.rt._release_held(buf)

    def _release_lost(self, v: str, to: str, since: float | None) -> None:
        """The member ``v`` was being handed over to is gone (or restarted) before confirming: if it published
        anything of ``v`` (its journal's output seqs beyond this holder's), it took the vehicle and died with it —
        taken from what it persisted, as for any dead holder; else the hand-over did not happen: kept here."""
        if v not in self.release or self.release_to.get(v) != to:
            return
        other = self._dead_state(v, only=to)
        rt = self.rt
        if any(int(s) > rt.seq.get(k, -1) for k, s in other["seqs"].items()):
            del self.release[v]
            self.release_to.pop(v, None)
            self.release_buf.pop(v, None)
            self._set_passed(v, False)
            self.stats["handovers_out"] -= 1
            self._failover(v, other, since)
        else:
            self._reclaim(v)

    def _replay_params(self, v: str) -> None:
        pre = f"{keys.ROOT}/{v}/"
        for k in [k for k in self.params_cache if k.startswith(pre)]:
            payload = self.params_cache.pop(k)
            self.rt.in_seq.pop(k, None)
            self.rt.handle_sample(k, payload)

    def _begin_warm(self, v: str, holder: str) -> None:
        if v in self.owned or v in self.warming or v in self.arm or v in self.release:
            return
        rt = self.rt
        rt.vehicle_state.pop(v, None)
        self._clear_vehicle(v)  # the warm-up span counts from the next input
        # what a restart of this instance restored of the vehicle is not its own any more (another member held it
        # since): its join losses are no restart's, its first input no gap of one
        rt.recovering.pop(v, None)
        pre = f"{keys.ROOT}/{v}/"
        for k in [k for k in rt.resumed_in if k.startswith(pre)]:
            rt.resumed_in.discard(k)
        # and its counts: the member that took it over from this instance's journal took them, and the hand-over
        # brings them back (kept here too, they were counted twice)
        self._drop_counts(v)
        self.warming[v] = holder
        self._replay_params(v)

    def _arm(self, v: str, holder: str, cut: float) -> None:
        """The holder publishes ``v`` before ``cut``: hold this instance's outputs at or after it (those made
        while warming included)."""
        if v not in self.warming:
            return
        buf = self.warm_buf.pop(v, ())
        self.held.extend(x for x in buf if x[3] >= cut)
        self.arm[v] = (holder, float(cut), time.monotonic())  # (set before warming ends: see skips)
        del self.warming[v]

    def _cancel(self, v: str) -> None:
        self.warming.pop(v, None)
        self.warm_buf.pop(v, None)
        self.arm.pop(v, None)
        self.held = [h for h in self.held if h[2] != v]

    def _adopt(self, v: str, seqs: dict, alarms: dict, raised: dict, drops: dict | None = None) -> None:
        rt = self.rt
        pre = f"{keys.ROOT}/{v}/"
        for k, d in (drops or {}).items():
            if not k.startswith(pre):
                continue
            for reason, n in d.items():  # the vehicle's counts come with it
                rt.drops[k][reason] = max(int(n), rt.drops[k].get(reason, 0)) if reason == "lost_in_takeover" \
                    else rt.drops[k].get(reason, 0) + int(n)
                c = _JOURNALLED.get(reason)
                if rt.journal is not None and c is not None:  # (a kill of this member must not lose them)
                    rt.journal.set(c + k, rt.drops[k][reason])
        for k, s in seqs.items():
            rt.seq[k] = max(int(s), rt.seq.get(k, -1))
            if rt.journal is not None:
                rt.journal.set("o" + k, rt.seq[k])
        for k in [k for k in rt.alarm_published if k.startswith(pre)]:
            del rt.alarm_published[k]
        rt.alarm_published.update({k: s for k, s in alarms.items() if k.startswith(pre)})
        rt.alarm_adopted += 1
        with rt.lock:
            for k in [k for k in rt.raised if k.startswith(pre)]:
                del rt.raised[k]
            rt.raised.update({k: m for k, m in raised.items() if k.startswith(pre)})
        rt._persist_alarms()

    def _takeover(self, v: str, hand: dict, holder: str | None = None) -> None:
        """Hand-over, last step: continue the holder's seqs and alarm states, publish what was held; the holder is
        told in the next round (it keeps the vehicle's outputs from the cut on until then)."""
        a = self.arm.get(v)
        if a is None:
            return
        if holder is not None:
            self.done_pending[v] = holder
        self._adopt(v, hand.get("seqs", {}), hand.get("alarms", {}), hand.get("raised", {}), hand.get("drops"))
        self.last_out[v] = time.monotonic()  # (a pause counts from the take)
        self.owned.add(v)  # (held before it stops being armed: see skips)
        del self.arm[v]
        self.post_cut[v] = a[1]
        mine = [h for h in self.held if h[2] == v]
        self.held = [h for h in self.held if h[2] != v]
        self.rt._release_held(mine)
        self.stats["handovers_in"] += 1

    def _failover(self, v: str, dead: dict, since: float | None) -> None:
        """Take ``v`` from what the members that are not live persisted (journal and alarm file)."""
        if v in self.owned:
            return
        counts = {k: dict(d) for k, d in dead.get("counts", {}).items()}
        for k, n in dead["lost"].items():
            counts.setdefault(k, {})["lost_in_takeover"] = n
        a = self.arm.get(v)
        if a is not None and dead["found"] and a[0] in dead.get("passed", ()):
            # the holder died past the cut: it published every output before it and none from it on, and this
            # member holds those from the cut on: the hand-over completes from its journal, nothing lost
            self._takeover(v, {"seqs": dead["seqs"], "alarms": dead["alarms"], "raised": dead["raised"],
                               "drops": counts})
            self._took(since, v)
            return
        self.owned.add(v)  # (first: the reader threads queue its samples from now on, see skips)
        # a pause counts from the take: taken while cut off from the vehicle (one of its alarms held raised), its
        # first outputs when the link comes back are held until a round has shown who went further
        self.last_out[v] = time.monotonic()
        self._cancel(v)
        if self.release.pop(v, None) is not None:  # (a hand-over of it from here is over)
            self.release_to.pop(v, None)
            self.release_buf.pop(v, None)
            self._set_passed(v, False)
        rt = self.rt
        rt.vehicle_state.pop(v, None)
        # what this instance's own run before a restart handled of v (its journal, resume_journal) and nobody
        # handled since: a restarted member that takes back a vehicle no survivor took counts the gap from there
        pre = f"{keys.ROOT}/{v}/"
        resumed = {k: rt.in_seq[k] for k in rt.resumed_in if k.startswith(pre) and k in rt.in_seq}
        self._clear_vehicle(v)
        for k, s in resumed.items():
            if int(dead["inputs"].get(k, -1)) < s:
                rt.in_seq[k] = s
                rt.recovering[v] = "lost_during_restart"
        if dead["found"]:
            self._adopt(v, dead["seqs"], dead["alarms"], dead["raised"], counts)
            if dead.get("last_alarm"):
                self._republish_unseen(dead["last_alarm"])
            if dead.get("t_out") is not None:  # (taken from what the mesh showed: outputs up to there went out)
                self.post_cut[v] = math.nextafter(float(dead["t_out"]), math.inf)
                self.stats["failovers_from_mesh"] += 1
            for k, s in dead["inputs"].items():
                if k in resumed and resumed[k] > int(s):
                    continue  # handled later by this instance's run before its restart: that gap is the restart's
                rt.in_seq[k] = int(s)
                rt.resumed_in.discard(k)
                rt.takeover_in.add(k)  # the first gap on it is lost_in_takeover (runtime._accepted)
                if dead.get("mesh"):
                    rt.takeover_est.add(k)
            if dead["inputs"]:
                rt.recovering[v] = "lost_in_takeover"  # what its joins held died with it (count_join_loss)
            if dead["raised"] and not rt.svc.ADOPTS_RESTORED_ALARMS:
                rt.reconcile_pending.update({k: v for k in dead["raised"]})
                rt.reconcile_at = time.monotonic() + 0.5
        elif since is not None:  # a holder died and left nothing for this vehicle
            self.stats["unrecovered"] += 1
        self.owned.add(v)
        self._replay_params(v)
        self._took(since, v)

    def _republish_unseen(self, last: dict) -> None:
        """A dead member's last alarm transitions (from its alarm file: message and when it was written, before its
        put) that the mesh never showed while this member watched: published again, seq and all. A kill -9 between
        the write and the put leaving the process lost the transition for every subscriber (seen once in ten
        kills of 30 cars: a clear never received, then "raised" twice); one that did go out and was seen here is
        not sent again. The watch is read first: a transition put before the kill came over the same link as the
        news of the member's going, so it is here unless the links were congested (then it is sent twice, with one
        seq). One written before this member watched (:data:`REPUBLISH_MARGIN_S`) is left: nothing can tell."""
        from schemas import messages

        self._observe_alarms()  # (what arrived since the round's look)
        watched = self._alarm_watch_t
        for k, e in last.items():
            m, w = e.get("m"), e.get("w")
            seen = self.seen_alarm.get(k)
            if not isinstance(m, dict) or not isinstance(w, float | int) or watched is None \
                    or w < watched[0] + REPUBLISH_MARGIN_S \
                    or (seen is not None and seen[0] >= int(m.get("seq", -1))):
                continue
            try:
                payload = messages.encode(m)
            except Exception as ex:  # noqa: BLE001 - a file another version wrote: logged, not sent
                self.rt.last_error = f"could not publish {k} again: {ex}"[:500]
                continue
            self.rt._publisher(k).put(payload)
            self.rt.count_out[k].n += 1
            self.stats["alarms_sent_again"] += 1
            log.warning("%s: %s %s (seq %s) of a member that is gone was never seen on the mesh: published again",
                        self.me, k, m.get("state"), m.get("seq"))

    def _took(self, since: float | None, v: str) -> None:
        if since is not None:
            self.stats["failovers"] += 1
            took = time.monotonic() - since
            self.stats["last_takeover_s"] = round(took, 3)
            self.stats["takeover_s_max"] = round(max(self.stats["takeover_s_max"], took), 3)
            log.info("%s: took %s over from a member that is gone (%.2f s after it was seen gone)", self.me, v, took)

    # ---- coordination thread --------------------------------------------------------------------
    def start(self) -> None:
        import zenoh

        # membership follows the tokens as they come and go (a poll under load can miss a live member and take
        # it for dead); one query seeds it, the subscriber's history covers what the query missed
        def on_token(smp: Any) -> None:  # (Zenoh's thread: noted, and the round woken; nothing else)
            self._token_q.append((str(smp.key_expr).split("/")[-1], smp.kind == zenoh.SampleKind.DELETE))
            self._wake.set()

        self._token_sub = self.rt.session.liveliness().declare_subscriber(
            keys.svc_token(self.role, "*"), on_token, history=True)
        try:
            for rep in self.rt.session.liveliness().get(keys.svc_token(self.role, "*"), timeout=2.0):
                if rep.ok is not None:
                    self._tokens.add(str(rep.ok.key_expr).split("/")[-1])
        except Exception as e:  # noqa: BLE001 - the subscriber fills the membership in
            self.rt.last_error = f"group membership query failed: {type(e).__name__}: {e}"[:500]
        self._observe_outputs(zenoh)
        self._started = time.monotonic()
        try:
            self._round()  # membership and holdings known before the first input is judged
        except Exception as e:  # noqa: BLE001 - the thread's rounds carry on
            self.rt.last_error = f"group round failed: {type(e).__name__}: {e}"[:500]
        self._thread = threading.Thread(target=self._run, daemon=True, name="magmesh-group")
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        for sub in (self._token_sub, self._out_sub, self._alarm_sub):
            try:
                if sub is not None:
                    sub.undeclare()
            except Exception:  # noqa: BLE001 - a closing session
                pass

    def _observe_outputs(self, zenoh: Any) -> None:
        """Watch what the other members publish: the role's fleet frames (each vehicle's output seqs and sample times)
        and alarm transitions, the newest kept in ring channels drained once a round (:meth:`_observe`). A member
        that dies on another host leaves no journal here: what subscribers saw of it is where its successor goes on
        (:meth:`_mesh_state`)."""
        from schemas import streams

        outs = getattr(type(self.rt.svc), "OUTPUTS", ()) or ()
        kinds, sources = set(), set()
        fleet_t, alarm_t = "magmesh/fleet/{shard}/", streams.STREAMS["alarm"].template
        for o in outs:
            t = getattr(o, "template", "")
            if t.startswith(fleet_t) and "{" not in t[len(fleet_t):]:
                kinds.add(t[len(fleet_t):])
            elif t == alarm_t and getattr(o, "source", None):
                sources.add(o.source)
        if len(kinds) == 1:
            self._out_kexpr = keys.fleet_frames(next(iter(kinds)))
        try:
            if len(sources) == 1:
                self._alarm_sub = self.rt.session.declare_subscriber(
                    keys.alarm("*", next(iter(sources))), zenoh.handlers.RingChannel(4096))
        except Exception as e:  # noqa: BLE001 - a failover then finds only journals on this host
            self.rt.last_error = f"group output watch failed: {type(e).__name__}: {e}"[:500]

    def _watch_outputs(self) -> None:
        """The frames watch is declared while another live member keeps its journal elsewhere (another host,
        another state directory: a failover from it reads what the mesh showed) and undeclared while every other
        member's journal is on this host, where a failover reads it: a member does not take in the others' whole
        output (at 1,000 vehicles, two ingest members' clean frames are megabytes a second) for nothing. A member
        that joins from elsewhere is watched from the next round, seconds before it holds a vehicle (it warms
        first). Own frames are never delivered to it (``allowed_origin``: remote sessions only)."""
        if self._out_kexpr is None:
            return
        need = any(not self._journalled_here(m) for m in self.live if m != self.me)
        try:
            if need and self._out_sub is None:
                import zenoh

                self._out_sub = self.rt.session.declare_subscriber(
                    self._out_kexpr, zenoh.handlers.RingChannel(4096), allowed_origin=zenoh.Locality.REMOTE)
                self.stats["output_watch"] = True
            elif not need and self._out_sub is not None:
                sub, self._out_sub = self._out_sub, None
                sub.undeclare()
                self.stats["output_watch"] = False
        except Exception as e:  # noqa: BLE001 - a failover then finds only journals on this host
            self.rt.last_error = f"group output watch failed: {type(e).__name__}: {e}"[:500]

    def _observe(self) -> None:
        """Take in what the watch channels hold: per vehicle of another member, the last seq and sample time of each
        output key; per alarm key, its last transition."""
        from schemas import frame

        from .frames import stream_key

        # newest first: a vehicle's row per stream is taken from the newest frame that has one (last_rows' taken).
        # Frames of this member, and of members whose seq journal is on this host (a failover from them reads the
        # journal, where every output is written before it is put), are passed over from their shard alone.
        got = [(str(smp.key_expr), smp) for smp in _pending(self._out_sub)]
        taken: dict = {}
        for key, smp in reversed(got):
            parts = key.split("/")  # (magmesh/fleet/{shard}/{kind}: the shard from the key, no payload copied)
            keyed = len(parts) == 4 and parts[1] == keys.FLEET
            if keyed and self._journalled_here(parts[2]):
                continue
            p = smp.payload.to_bytes()
            if not keyed and self._journalled_here(frame.shard_of(p)):
                continue
            try:
                shard, kind, rows = frame.last_rows(p, taken)
            except ValueError:  # not a frame of this contract: nothing learnt from it
                continue
            if shard == self.me:
                continue
            for v, name, sq, ts in rows:
                try:
                    k = stream_key(kind, v, name)
                except keys.KeyError_:  # a vehicle no key may name: no output of a member (ingest refuses it)
                    continue
                d = self.seen_out.get(v)
                if d is None:
                    d = self.seen_out[v] = {}
                old = d.get(k)
                if old is None or sq >= old[0]:
                    d[k] = (sq, ts)
        self._observe_alarms()

    def _journalled_here(self, shard: str | None) -> bool:
        """Whether the member publishing frames of ``shard`` is this one or keeps its seq journal on this host
        (looked up once per :data:`JOURNAL_CHECK_S` per shard)."""
        if shard is None:
            return False
        if shard == self.me:
            return True
        now = time.monotonic()
        c = self._journal_seen.get(shard)
        if c is None or now - c[1] >= JOURNAL_CHECK_S:
            from .paths import state_dir

            here = (state_dir() / "journal" / f"{self.role}.{shard}.seq").exists() \
                if shard.startswith(f"{self.name}-") else False
            if len(self._journal_seen) > 4096:
                self._journal_seen.clear()
            c = self._journal_seen[shard] = (here, now)
        return c[0]

    def _observe_alarms(self) -> None:
        """The alarm watch's part of :meth:`_observe` (also called by a take-over on the main loop: a channel read
        and dict updates, safe beside the group thread's)."""
        from schemas import messages

        if self._alarm_sub is None:
            return
        now = time.time()
        for smp in _pending(self._alarm_sub):
            try:
                m = messages.decode(smp.payload.to_bytes(), expected_type="alarm")
            except Exception:  # noqa: BLE001 - refused as the alarm stream's readers refuse it
                continue
            if m.get("service") == self.me:
                continue
            k = str(smp.key_expr)
            old = self.seen_alarm.get(k)
            if old is None or int(m["seq"]) >= old[0]:
                self.seen_alarm[k] = (int(m["seq"]), m)
        w = self._alarm_watch_t
        self._alarm_watch_t = (now if w is None else w[0], now)  # (watched since, read up to)

    def _note_answers(self, states: dict[str, dict]) -> None:
        """Keep each member's latest ``held`` answer, and per input key two answers' (sample time, seq) apart: the
        key's rate, with which a failover estimates what the dead member handled after its last answer."""
        for inst, st in states.items():
            held = st.get("held")
            if not isinstance(held, dict):
                continue
            self.snap[inst] = held
            for h in held.values():
                for k, (sq, t) in h.get("in", {}).items():
                    if t is None:
                        continue
                    r = self.in_rate.get(k)
                    if r is None:
                        self.in_rate[k] = (t, sq, t, sq)
                    elif sq != r[3] and t > r[2]:
                        self.in_rate[k] = (r[2], r[3], t, sq)

    def _post(self, fn: Callable[[], None]) -> None:
        try:
            self.rt.q.put(("g", fn), timeout=1.0)
        except Exception:  # noqa: BLE001 - a full queue: the next round posts it again
            pass

    def _call(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` in the main loop and wait for its result (None when it did not run in time)."""
        box: list = []
        done = threading.Event()

        def run() -> None:
            try:
                box.append(fn())
            finally:
                done.set()

        self._post(run)
        return box[0] if done.wait(timeout) and box else None

    def _run(self) -> None:
        zconf.os_thread_name("mm-group")
        while not self._stop.is_set():
            self.settled = not self._busy()
            self.round_s = self.idle_period_s if self.settled else self.period_s
            self._wake.wait(self.round_s)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self._round()
            except Exception as e:  # noqa: BLE001 - coordination must never stop the service
                self.rt.last_error = f"group round failed: {type(e).__name__}: {e}"[:500]

    def _busy(self) -> bool:
        """Whether the next round comes after ``period_s`` rather than :data:`IDLE_PERIOD_S`: something is under way
        here, a member did not answer, or the membership or holdings changed in the last :data:`STEADY_AFTER_S`."""
        now = time.monotonic()
        key = (tuple(sorted(self.live)), tuple(self.members), self._gen, len(self.holdings))
        if key != self._steady_key:
            self._steady_key, self._steady_since = key, now
        return (not self.ready or not self.complete or self.leaving or bool(
            self.warming or self.arm or self.release or self.release_to or self.paused or self.done_pending
            or self._lapsed or self._leaving_seen or self._token_q)
            or self._out_sub is not None or self.cut_off_since is not None
            or now - self._steady_since < STEADY_AFTER_S
            or any(now - t < STEADY_AFTER_S for t in list(self._dead_since.values())))

    def _live_members(self) -> set[str]:
        q = self._token_q
        while q:
            inst, gone = q.popleft()
            if gone:
                self._tokens.discard(inst)
            else:
                self._tokens.add(inst)
        pre = f"{self.name}-"
        return {self.me} | {i for i in self._tokens if i.startswith(pre)}

    def _query(self, inst: str, req: dict, timeout: float = 1.0) -> dict | None:
        return zconf.control_request(self.rt.session, self.role, inst, req, timeout)

    def _round(self) -> None:
        self._watch_outputs()
        self._observe()
        live = self._live_members()
        now = time.monotonic()
        states: dict[str, dict] = {}
        # a member whose token went is gone only if it does not answer either: a token can lapse under load (its
        # session to the router renewed) while the member goes on serving its vehicles (seen: a member taken for
        # dead for 6 s, and both it and the member that took its vehicles published them)
        for m in sorted(self.live - live - {self.me}):
            st = self._query(m, {"op": "g_state"}, timeout=0.5)
            if st is not None:
                states[m] = st
                live.add(m)
                if m not in self._lapsed:
                    self._lapsed.add(m)
                    self.stats["liveliness_lapses"] += 1
                    log.warning("%s: the liveliness token of %s went, but it answers: still a member", self.me, m)
            else:
                log.info("%s: %s is gone (no liveliness token, no answer)", self.me, m)
        self._lapsed &= live
        for m in live - self.live:
            log.info("%s: %s joined", self.me, m)
        for m in self.live - live:
            self._dead_since.setdefault(m, now)
        for m in live:
            self._dead_since.pop(m, None)
        self.live = live
        # the held tables serve a failover from what the mesh showed (_mesh_state): asked for only while another
        # live member keeps its seq journal elsewhere (a failover from a member journalled here reads its journal;
        # building, sending and reading the tables was most of a settled round's cost)
        ask_held = now - self._held_asked >= HELD_PERIOD_S and \
            any(not self._journalled_here(m) for m in live if m != self.me)
        if ask_held:
            self._held_asked = now
        for inst in sorted(live - {self.me} - set(states)):
            st = self._query(inst, {"op": "g_state", "held": ask_held or inst not in self.snap})
            if st is not None:
                states[inst] = st
        self._note_answers(states)
        for inst, st in states.items():
            if st.get("leaving"):
                self._leaving_seen.add(inst)
        self._leaving_seen &= live
        complete = len(states) == len(live) - 1
        self.stats["rounds"] += 1
        self.stats["rounds_incomplete"] += not complete
        members = sorted(m for m in live if m not in self._leaving_seen and not (m == self.me and self.leaving))
        holders: dict[str, set[str]] = {}
        holdings: dict[str, str] = {}
        for inst, st in states.items():
            for v in st.get("owned", []):
                holders.setdefault(v, set()).add(inst)
            for v in st.get("releasing", {}):
                holdings[v] = inst  # mid hand-over: that holder stays the one to take it from
        for v, hs in holders.items():
            if v not in holdings:
                holdings[v] = groups.owner(v, hs)
        self.members = members
        if complete or not self.ready:
            self.holdings = holdings
        self.complete = complete
        first = not self.ready
        # (the first rounds after the start: the tokens of the others may still be on their way)
        self.ready = self.ready or (complete and now - self._started >= SETTLE_S)
        if first:
            return
        for v, h in holdings.items():
            self.last_holder[v] = h
        # vehicles this member hands over: the member taking one went, or no longer takes it, before confirming
        for v, to in list(self.release_to.items()):
            if to not in live:
                s = self._dead_since.get(to)
                self._post(lambda v=v, to=to, s=s: self._release_lost(v, to, s))
            elif to in states and v not in states[to].get("taking", []) and v not in states[to].get("owned", []):
                self._post(lambda v=v, to=to: self._release_lost(v, to, None))
        warm_slots = MAX_WARMING - len(self.warming) - len(self.arm)
        unheard = 0
        # vehicles with alarm state or drop counts here (once a round, not a scan per vehicle)
        stated = {vehicle_of(k) for k in list(self.rt.alarm_published)} | {vehicle_of(k) for k in list(self.rt.drops)}
        for v in list(self.seen):
            mine = not self.leaving and groups.owner(v, members) == self.me
            if v in self.arm:
                holder, cut, since = self.arm[v]
                st = states.get(holder)
                if holder not in live:
                    s = self._dead_since.get(holder)
                    self._post(lambda v=v, s=s: self._failover(v, self._dead_state(v), s))
                    continue
                hand = (st or {}).get("releasing", {}).get(v)
                if hand is None:
                    if st is not None and v in st.get("owned", []):  # the holder kept it (took us for gone)
                        self._post(lambda v=v: v in self.arm and self._cancel(v))
                    elif st is not None:  # the holder lost it (restarted): take it
                        self._post(lambda v=v: self._failover(v, self._dead_state(v), None))
                    continue
                t = hand.get("last_in_t")
                if v not in self.progress or self.progress[v][0] != t:
                    self.progress[v] = (t, now)
                # a holder that is only slow (its loop behind) is waited for; it is passed over only when the
                # vehicle's input itself stopped before the cut (nothing more will come before it)
                stalled = now - self.progress[v][1] >= self.stall_s and \
                    self.rt.last_in_t.get(v, float("-inf")) < cut
                if hand.get("passed") or stalled:
                    self.progress.pop(v, None)
                    self._post(lambda v=v, hand=hand, h=holder: self._takeover(v, hand, h))
                continue
            if v in self.owned:
                others = holders.get(v, set())
                if complete and others:
                    # two holders (a split healed, or views of the membership that differed): the one whose outputs
                    # went further keeps it (the other's state is stale: it was cut off from the input), else the rule
                    behind = self._behind(v)
                    if behind or (behind is None and groups.owner(v, others | {self.me}) != self.me):
                        self._post(lambda v=v, b=bool(behind): self._drop_duplicate(v, b))
                        continue
                r0 = self.paused.get(v)
                if r0 is not None and complete and self.stats["rounds"] >= r0 + 2:
                    self._post(lambda v=v: v in self.paused and self._end_pause(v))
                continue
            if complete and v in holdings and v not in self.warming and v not in self.release:
                # alarm state or drop counts restored from an earlier life of this instance, for a vehicle another
                # member holds: that member took it over from this instance's journal, its counts included
                if v in stated:
                    self._post(lambda v=v: v not in self.owned and v not in self.warming and v not in self.arm
                               and self._forget(v))
            if v in self.warming:
                h = self.warming[v]
                if h not in live:
                    s = self._dead_since.get(h)
                    self._post(lambda v=v, s=s: self._failover(v, self._dead_state(v), s))
                    continue
                hand = (states.get(h) or {}).get("releasing", {}).get(v)
                if hand is not None and hand.get("to") == self.me:
                    # agreed before (its reply was lost): take the cut the holder chose, even if the rule has
                    # moved the vehicle meanwhile (the holder publishes only before it: this member must take it)
                    self._call(lambda v=v, h=h, c=hand["cut"]: self._arm(v, h, c))
                    continue
                if not mine or hand is not None or (complete and h != holdings.get(v)):
                    # the rule moved it elsewhere, the holder hands it to another member, or no longer holds it
                    # (restarted): look again next round
                    self._post(lambda v=v: v in self.warming and self._cancel(v))
                    continue
                t0, t1 = self.rt.first_in_t.get(v), self.rt.last_in_t.get(v)
                if t0 is not None and t1 is not None and t1 - t0 >= self.warmup_s:
                    r = self._query(h, {"op": "g_release", "lead_s": self.lead_s, "vehicles": [v], "from": self.me,
                                        "not_before": t0 + self.warmup_s})
                    hand = (r or {}).get("releasing", {}).get(v)
                    if hand is not None and hand.get("to") == self.me:
                        self._call(lambda v=v, h=h, c=hand["cut"]: self._arm(v, h, c))
                continue
            if not mine or v in self.release:
                continue
            holder = holdings.get(v)
            if holder is not None:
                if warm_slots > 0:  # the others wait for a later round (MAX_WARMING)
                    warm_slots -= 1
                    self._post(lambda v=v, h=holder: self._begin_warm(v, h))
            elif complete:
                s = self._dead_since.get(self.last_holder.get(v, ""))
                if self._hears(v, s, now):
                    self._post(lambda v=v, s=s: self._failover(v, self._dead_state(v), s))
                elif s is not None and now - s > PAUSE_S:
                    unheard += 1  # (not heard for a while after its holder went: a round or two is normal)
        if unheard:
            if self.cut_off_since is None:
                self.cut_off_since = now
                log.warning("%s: %d vehicles of members seen gone are not heard here: this member may be cut off "
                            "(outputs after a pause held until a round shows who went further)", self.me, unheard)
        elif not self.paused:
            self.cut_off_since = None
        # hand-overs done: each former holder told (again each round until it confirms), so it forgets the vehicle
        done: dict[str, list[str]] = {}
        for v, h in list(self.done_pending.items()):
            if h not in live:
                self.done_pending.pop(v, None)
            else:
                done.setdefault(h, []).append(v)
        for h, vs in done.items():
            if self._query(h, {"op": "g_done", "vehicles": vs}) is not None:
                for v in vs:
                    if self.done_pending.get(v) == h:
                        del self.done_pending[v]

    def _hears(self, v: str, since: float | None, now: float) -> bool:
        """Whether this member takes ``v`` over now that its holder went (seen at ``since``, when known): its input
        has reached this member since (:attr:`heard_t`, :data:`HEARD_MARGIN_S`; within the last :data:`PAUSE_S` when
        the holder's going was not seen), or one of its alarms is held raised (answered for at once, input or not)."""
        t = self._heard_at(v)
        if t is not None and t >= (since - HEARD_MARGIN_S if since is not None else now - PAUSE_S):
            return True
        if v in self._raised_checked and self._raised_checked[v] == since:
            return False  # (sought once per going: the journals and the mesh are read no more each round)
        self._raised_checked[v] = since
        if len(self._raised_checked) > 100_000:
            self._raised_checked.clear()
        pre = f"{keys.ROOT}/{v}/"
        return any(k.startswith(pre) and m.get("state") == "raised" for k, (_s, m) in list(self.seen_alarm.items())) \
            or bool(self._dead_state(v)["raised"])

    def _state_files(self, d: Any, fresh: bool = False) -> tuple[list, list]:
        """The group's seq journals and alarm files in the state directory ``d``. Listed again when the live
        members changed or a second passed (or ``fresh``), else kept: :meth:`_dead_state` runs for every vehicle
        taken at first sight, and listing the directories for each of 500 new vehicles held a member's loop up for
        a second. Only the files of members that are not live are read, and a member's files are written while it
        is live: a listing made since the live members last changed has every one of them."""
        now = time.monotonic()
        live = frozenset(self.live)
        c = self._files_cache
        if fresh or c is None or c[0] != d or c[1] != live or now - c[2] >= 1.0:
            journals = sorted((d / "journal").glob(f"{self.role}.{self.name}-*.seq"))
            alarms = sorted({f.with_suffix(".json") for pat in ("json", "log")
                             for f in (d / "alarms").glob(f"{self.role}.{self.name}-*.{pat}")})
            c = self._files_cache = (d, live, now, journals, alarms)
        return c[3], c[4]

    def _dead_state(self, v: str, only: str | None = None) -> dict:
        """What the members of the group that are not live persisted about vehicle ``v``: seq journals (the
        sample a member was handling when killed counts as handled when an output went out after it began) and
        alarm files (the latest transition any of them published). ``only``: what that one member persisted,
        live or not (a member restarted since)."""
        from .journal import Journal
        from .paths import state_dir

        pre = f"{keys.ROOT}/{v}/"
        out: dict = {"seqs": {}, "inputs": {}, "lost": {}, "counts": {}, "alarms": {}, "raised": {}, "found": False,
                     "passed": set(), "last_alarm": {}}
        alarm_seq: dict[str, int] = {}
        first_rx: dict[str, int] = {}
        d = state_dir()
        journals, alarm_files = self._state_files(d, fresh=only is not None)
        for f in journals:
            inst = f.name[len(self.role) + 1:-len(".seq")]
            if (inst != only) if only is not None else (inst in self.live):
                continue
            j = Journal(f)
            prev = j.load()
            ikey, pseq = j.in_progress(prev)
            if ikey is not None and prev.get("~sent", 0) > prev.get("~sent_at_begin", 0):
                prev[ikey] = max(prev.get(ikey, pseq), pseq)
            for k, s in prev.items():
                if k[:1] == "f" and k[1:].startswith(pre):  # received, never handled there
                    if ("i" + k[1:]) not in prev:
                        first_rx[k[1:]] = min(int(s), first_rx.get(k[1:], int(s)))
                        out["found"] = True
                elif k[:1] in "oit" and k[1:].startswith(pre):
                    tgt = out["seqs"] if k[0] == "o" else out["inputs"] if k[0] == "i" else out["lost"]
                    tgt[k[1:]] = max(int(s), tgt.get(k[1:], -1))
                    out["found"] = True
                elif k == "p" + pre:  # it had passed the cut of a hand-over of v (see _set_passed)
                    out["passed"].add(inst)
                elif k[:1] in "ul" and k[1:].startswith(pre):  # its other counts (the holder's, carried along:
                    # the largest, as a member that handed the vehicle on forgot its own)
                    reason = "upstream_gap" if k[0] == "u" else "lost_during_restart"
                    cnt = out["counts"].setdefault(k[1:], {})
                    cnt[reason] = max(int(s), cnt.get(reason, 0))
        for k, s in first_rx.items():  # a key no dead member handled is missed from the first seq any received
            out["inputs"].setdefault(k, s - 1)
        from .alarmstore import load

        for f in alarm_files:
            inst = f.name[len(self.role) + 1:-len(".json")]
            if (inst != only) if only is not None else (inst in self.live):
                continue
            data = load(f)
            seqs = data.get("seqs", {})
            for k, state in data.get("published", {}).items():
                if not k.startswith(pre):
                    continue
                s = int(seqs.get(k, -1))
                if s >= alarm_seq.get(k, -2):  # the latest transition any of them published
                    alarm_seq[k] = s
                    out["alarms"][k] = state
                    out["seqs"][k] = max(s, out["seqs"].get(k, -1))
                    if state == "raised" and k in data.get("raised", {}):
                        out["raised"][k] = data["raised"][k]
                    else:
                        out["raised"].pop(k, None)
                    last = data.get("last", {}).get(k)
                    if last is not None and isinstance(last.get("m"), dict) and last["m"].get("seq") == s:
                        out["last_alarm"][k] = last
                    else:
                        out["last_alarm"].pop(k, None)
                    out["found"] = True
        if not out["found"] and only is None:
            return self._mesh_state(v, out)
        return out

    def _heard_seq(self, key: str, t_out: float) -> int | None:
        """The seq of the last sample on ``key`` at or before sample time ``t_out`` among those this member
        skipped (:meth:`skips`), or None when they do not reach back that far (or are not single samples)."""
        import msgpack

        best = None
        for p in list(self.heard_buf.get(key, ())):  # (a copy: a reader thread appends meanwhile)
            try:
                m = msgpack.unpackb(p)
            except Exception:  # noqa: BLE001 - garbage is the input path's to refuse
                continue
            if not isinstance(m, dict) or m.get("type") == "batch":
                continue
            s, t = m.get("seq"), m.get("t_s")
            if type(s) is int and isinstance(t, float | int) and not isinstance(t, bool) and t <= t_out \
                    and (best is None or s > best):
                best = s
        return best

    def _mesh_state(self, v: str, out: dict) -> dict:
        """What the mesh showed of vehicle ``v`` whose holder left nothing on this host (it ran on another host, or
        with another state directory): the last output seq and sample time of each of its keys as the holder's
        fleet frames carried them, the last alarm transitions it published, and from its last ``g_state`` answer
        with a held table (:data:`HELD_PERIOD_S` and a round old at most) the input seqs it had handled and its drop
        counts. What it handled after that answer is read from the samples of each input key heard here up to the last output's sample time (``t_out``,
        :meth:`_heard_seq`), or estimated from the key's rate when those do not reach back so far: inputs
        after it were not handled, or died in its joins, and count as ``lost_in_takeover``; outputs at or before it
        were published and are not published again (``t_out``, see :meth:`_failover`)."""
        pre = f"{keys.ROOT}/{v}/"
        outs = dict(self.seen_out.get(v, {}))
        for k, (sq, _t) in outs.items():
            out["seqs"][k] = max(sq, out["seqs"].get(k, -1))
        t_out = max((t for _s, t in outs.values()), default=None)
        for k, (sq, m) in list(self.seen_alarm.items()):
            if k.startswith(pre):
                out["alarms"][k] = m["state"]
                out["seqs"][k] = max(sq, out["seqs"].get(k, -1))
                if m["state"] == "raised":
                    out["raised"][k] = m
        holder = self.last_holder.get(v)
        snap = (self.snap.get(holder) or {}).get(v) if holder is not None else None
        if snap is not None:
            for k, (sq, t_k) in snap.get("in", {}).items():
                est = int(sq)
                r = self.in_rate.get(k)
                if t_out is not None and t_k is not None and t_out > t_k and not _is_params(k):
                    heard = self._heard_seq(k, t_out)
                    if heard is not None:  # the sample at the last output's time, as heard here
                        est = max(est, heard)
                    elif r is not None and r[2] > r[0]:
                        # the key's samples from its last one answered up to the last output's sample time
                        est += int(math.floor((t_out - t_k) * (r[3] - r[1]) / (r[2] - r[0]) + 0.5))
                out["inputs"][k] = est
            for k, c in snap.get("drops", {}).items():
                if not k.startswith(pre):
                    continue
                for reason, n in c.items():
                    if reason == "lost_in_takeover":
                        out["lost"][k] = max(int(n), out["lost"].get(k, 0))
                    elif reason in _JOURNALLED:
                        out["counts"].setdefault(k, {})[reason] = int(n)
        if outs or out["alarms"] or snap is not None:
            out["found"] = True
            out["mesh"] = True
            out["t_out"] = t_out
        return out
