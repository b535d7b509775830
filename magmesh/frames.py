"""The runtime's side of fleet frames (contract v3, :mod:`schemas.frame`): per-stream seq tracking in arrays.

A frame carries hundreds of vehicles' samples; the runtime tracks each vehicle's streams exactly as it does for
single samples (the last seq handled per per-vehicle key, gaps counted as loss, the journal written so a
restart after kill -9 counts what it missed), but with one numpy operation per stream and frame instead of a
Python step per sample. :class:`SeqTable` is the runtime's ``in_seq`` map (key → last seq handled): a dict for
keys handled one sample at a time, arrays for the keys frames carry, one mapping over both.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, MutableMapping

import numpy as np

from schemas import keys

#: "no seq handled yet" in the arrays
NONE = np.iinfo(np.int64).min


@functools.lru_cache(maxsize=1 << 14)
def stream_key(kind: str, vehicle: str, name: str) -> str:
    """The per-vehicle key of a frame stream's rows: (clean, car-1, mag/1) → magmesh/car-1/clean/mag/1;
    (cal, car-1, mag/1) → magmesh/car-1/cal/mag/1; (dmc, car-1, dmc) → magmesh/car-1/dmc. Raises
    ``keys.KeyError_`` for a name no key may carry. (The last 16,384 keys kept: a group member builds one for
    each row it watches.)"""
    if kind == "dmc":
        return keys.dmc(vehicle)
    head, _, sensor = name.partition("/")
    if kind == "cal":
        return keys.cal_mag(vehicle, sensor)
    return keys.clean_mag(vehicle, sensor) if head == "mag" else getattr(keys, f"clean_{head}")(vehicle)


def _vehicle_part(k: str) -> str:
    """The second chunk of a key (``magmesh/{vehicle}/...``: the vehicle), or the key itself."""
    a = k.find("/")
    b = k.find("/", a + 1)
    return k[a + 1:b] if 0 <= a < b else k


class SeqTable(MutableMapping):
    """key → last input seq handled. Keys that frames carry live in slots of an array (``slots_for``), the rest
    in a dict; both read and write like one dict (the group, restart and eviction code uses it so)."""

    def __init__(self, capacity: int = 1024):
        self.d: dict[str, int] = {}
        self.slot: dict[str, int] = {}
        self.names: list[str | None] = []
        self.arr = np.full(capacity, NONE, np.int64)
        #: the sample time of each key's last seq (nan: not known), beside it: a group member's answers carry both,
        #: from which another member estimates what it handled after its last answer (group_member._mesh_state)
        self.tarr = np.full(capacity, np.nan)
        self.td: dict[str, float] = {}
        self.free: list[int] = []
        self.generation = 0  # bumped when a slot is freed: cached slot arrays must be rebuilt
        #: vehicle -> its keys that have a slot or a dict entry (``keys_with``: a take-over clears one vehicle's
        #: keys; a scan of every key per vehicle took seconds when a group member took 500 new vehicles)
        self.vidx: dict[str, set[str]] = {}

    # ---- the arrays -----------------------------------------------------------------------------
    def slots_for(self, names: list[str]) -> np.ndarray:
        """The slot of each key (given one on first use; a dict value moves into it)."""
        out = np.empty(len(names), np.int64)
        slot = self.slot
        for i, k in enumerate(names):
            s = slot.get(k)
            if s is None:
                s = self._new_slot(k)
            out[i] = s
        return out

    def _new_slot(self, k: str) -> int:
        if self.free:
            s = self.free.pop()
        else:
            s = len(self.names)
            self.names.append(None)
            if s >= self.arr.shape[0]:
                grown = np.full(max(2 * self.arr.shape[0], s + 1), NONE, np.int64)
                grown[:self.arr.shape[0]] = self.arr
                self.arr = grown
                grown_t = np.full(grown.shape[0], np.nan)
                grown_t[:self.tarr.shape[0]] = self.tarr
                self.tarr = grown_t
        self.names[s] = k
        self.slot[k] = s
        self.vidx.setdefault(_vehicle_part(k), set()).add(k)
        v = self.d.pop(k, None)
        self.arr[s] = NONE if v is None else int(v)
        self.tarr[s] = self.td.pop(k, np.nan)
        return s

    def free_slot(self, k: str) -> None:
        s = self.slot.pop(k, None)
        if s is not None:
            if k not in self.d:
                self._unindex(k)
            self.names[s] = None
            self.arr[s] = NONE
            self.tarr[s] = np.nan
            self.free.append(s)
            self.generation += 1

    def set_t(self, k: str, t: float) -> None:
        """The sample time of key ``k``'s last seq."""
        s = self.slot.get(k)
        if s is None:
            self.td[k] = float(t)
        else:
            self.tarr[s] = t

    def get_t(self, k: str) -> float | None:
        s = self.slot.get(k)
        v = self.td.get(k) if s is None else float(self.tarr[s])
        return None if v is None or v != v else v

    def items_t(self) -> list[tuple[str, int, float | None]]:
        """(key, seq, sample time or None) of every key with a seq: ``get`` and ``get_t`` of each key at once."""
        td = self.td
        out = [(k, v, td.get(k)) for k, v in list(self.d.items())]
        n = len(self.names)
        out += [(k, v, t) for k, v, t in zip(list(self.names), self.arr[:n].tolist(), self.tarr[:n].tolist(),
                                              strict=False) if k is not None and v != NONE]
        return [(k, v, None if t is None or t != t else t) for k, v, t in out]

    # ---- the mapping ----------------------------------------------------------------------------
    def __getitem__(self, k: str) -> int:
        s = self.slot.get(k)
        if s is None:
            return self.d[k]
        v = self.arr[s]
        if v == NONE:
            raise KeyError(k)
        return int(v)

    def get(self, k: str, default=None):
        s = self.slot.get(k)
        if s is None:
            return self.d.get(k, default)
        v = self.arr[s]
        return default if v == NONE else int(v)

    def keys_with(self, pre: str) -> list[str]:
        """The keys held (with a seq) that start with ``pre`` = ``magmesh/{vehicle}/``: from the vehicle's index,
        not a scan of every key."""
        ks = self.vidx.get(_vehicle_part(pre))
        return [k for k in list(ks) if k.startswith(pre) and k in self] if ks else []

    def _unindex(self, k: str) -> None:
        v = _vehicle_part(k)
        ks = self.vidx.get(v)
        if ks is not None:
            ks.discard(k)
            if not ks:
                del self.vidx[v]

    def __setitem__(self, k: str, v: int) -> None:
        s = self.slot.get(k)
        if s is None:
            if k not in self.d:
                self.vidx.setdefault(_vehicle_part(k), set()).add(k)
            self.d[k] = v
        else:
            self.arr[s] = int(v)

    def __delitem__(self, k: str) -> None:
        s = self.slot.get(k)
        if s is None:
            del self.d[k]
            self.td.pop(k, None)
            self._unindex(k)
            return
        if self.arr[s] == NONE:
            raise KeyError(k)
        self.arr[s] = NONE
        self.tarr[s] = np.nan

    def __contains__(self, k: object) -> bool:
        s = self.slot.get(k)  # type: ignore[arg-type]
        if s is None:
            return k in self.d
        return bool(self.arr[s] != NONE)

    def __iter__(self) -> Iterator[str]:
        yield from list(self.d)
        for k, s in list(self.slot.items()):
            if self.arr[s] != NONE:
                yield k

    def __len__(self) -> int:
        n = len(self.d)
        if self.slot:
            idx = np.fromiter(self.slot.values(), np.int64, len(self.slot))
            n += int((self.arr[idx] != NONE).sum())
        return n


class StreamKeys:
    """Per (frame kind, stream name): the per-vehicle keys of a frame's vehicles and their seq slots, rebuilt
    only when the vehicle list (or the table's slots) changes."""

    __slots__ = ("vehicles", "keys", "slots", "wanted", "generation", "jslots")

    def __init__(self, vehicles: list[str], kind: str, name: str, table: SeqTable, wants) -> None:
        self.vehicles = vehicles
        self.keys = [stream_key(kind, v, name) for v in vehicles]
        self.wanted = np.fromiter((wants(k) for k in self.keys), bool, len(self.keys))
        # slots only for the keys this service handles (an unwanted vehicle takes no slot)
        self.slots = np.full(len(vehicles), -1, np.int64)
        idx = np.flatnonzero(self.wanted)
        if idx.size:
            self.slots[idx] = table.slots_for([self.keys[i] for i in idx.tolist()])
        self.generation = table.generation
        self.jslots: np.ndarray | None = None
