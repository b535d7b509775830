"""Group membership maths: which live instance of a role owns which vehicle (pure, no Zenoh).

The instances of a role that run as one group (``--group NAME``; the manifest's ``instances = N``) share the
fleet: each vehicle belongs to exactly one live member, chosen by rendezvous (highest-random-weight) hashing.
Every member computes the same owner from the same membership, without talking to the others, and a change of
membership moves only the vehicles that must move: a joining member takes about ``1/N`` of the vehicles (only
from the others, never between them), a leaving one gives away only its own.

The weight of (vehicle, member) is the first 8 bytes of BLAKE2b over the vehicle's name and the member's slot:
stable across processes, hosts and Python versions (unlike ``hash()``, which is salted per process). A member's
slot is its number (``dmc-2`` → ``2``; a name without one is its own slot): the members of one group differ only
there, and the groups of different stages with the same number of members give each vehicle to the members of the
same number — ``ingest-2``'s frames then carry exactly the vehicles ``dmc-2`` and ``heading-2`` hold, so a member
handles one upstream member's frames, not a part of every one's (co-partitioned stages).
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Iterable


def slot(member: str) -> str:
    """A member's slot: the number its name ends with (``dmc-2`` → ``2``), else the whole name."""
    head, sep, tail = member.rpartition("-")
    return tail if sep and head and tail.isdigit() else member


@functools.lru_cache(maxsize=1 << 16)
def weight(vehicle: str, member: str) -> int:
    """The rendezvous weight of ``member`` for ``vehicle`` (64 bits, the same everywhere): of its slot. (Every
    round of every member asks for each vehicle's owner: the last 65,536 weights are kept, ~15 MB at most.)"""
    h = hashlib.blake2b(f"{vehicle}\x00{slot(member)}".encode(), digest_size=8)
    return int.from_bytes(h.digest(), "big")


def owner(vehicle: str, members: Iterable[str]) -> str | None:
    """The member that owns ``vehicle`` (None when there is no member). Ties (never seen in 64 bits) go to the
    smaller name, so the rule stays a function of the membership set alone."""
    best = None
    best_w = -1
    for m in members:
        w = weight(vehicle, m)
        if w > best_w or (w == best_w and best is not None and m < best):
            best, best_w = m, w
    return best


def assignment(vehicles: Iterable[str], members: Iterable[str]) -> dict[str, str | None]:
    """``{vehicle: owner}`` for every vehicle."""
    ms = sorted(set(members))
    return {v: owner(v, ms) for v in vehicles}


def by_member(assign: dict[str, str | None], members: Iterable[str] = ()) -> dict[str, list[str]]:
    """The vehicles of each member (members without a vehicle listed too), sorted."""
    out: dict[str, list[str]] = {m: [] for m in members}
    for v, m in assign.items():
        if m is not None:
            out.setdefault(m, []).append(v)
    return {m: sorted(vs) for m, vs in sorted(out.items())}


def moved(before: dict[str, str | None], after: dict[str, str | None]) -> dict[str, tuple[str | None, str | None]]:
    """The vehicles whose owner differs between two assignments: ``{vehicle: (old owner, new owner)}``."""
    return {v: (before.get(v), o) for v, o in after.items() if before.get(v) != o}


def summarize(members: dict[str, dict | None]) -> dict:
    """The assignment as the members report it: ``members`` maps an instance to the ``group`` part of its
    status (None when it did not answer). Gives each member's vehicles (None for one that did not answer),
    every vehicle a member has seen that no member holds (``unowned``: between owners, or served by nobody)
    and every vehicle two members hold at once (``duplicates``)."""
    vehicles: dict[str, list[str] | None] = {}
    count: dict[str, int] = {}
    seen: set[str] = set()
    for inst, g in sorted(members.items()):
        if not isinstance(g, dict):
            vehicles[inst] = None
            continue
        own = [str(v) for v in g.get("vehicles", []) or []]
        vehicles[inst] = sorted(own)
        for v in set(own) | {str(x) for x in g.get("releasing", []) or []}:
            count[v] = count.get(v, 0) + 1
        seen.update(str(v) for v in g.get("seen", []) or [])
    return {"vehicles": vehicles, "unowned": sorted(seen - set(count)),
            "duplicates": sorted(v for v, n in count.items() if n > 1)}
