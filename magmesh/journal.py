"""The seq journal: the last input seq handled and the last output seq sent, per key, surviving a kill -9.

Each value is written in place into a memory-mapped file (one 8-byte slot per key, ~1 µs a write), so it is in
the operating system's page cache the moment it is written: a process killed at any instant leaves exactly
what it had handled and sent. The key of each slot goes to a small JSON index when the key first appears.

A restarted instance reads its journal back (:func:`load`): it continues its output seqs where they stopped
(its consumers see no gap and no re-base), and counts, per input key, every sample it missed while it was down
(``lost_during_restart``: the first seq after the restart minus the last one handled before it, minus one).
A clean stop removes the journal: a planned stop is not a loss to account for.
"""

from __future__ import annotations

import json
import mmap
import os
import struct
import threading
from pathlib import Path

from .paths import write_atomic

SLOTS = 8192  # keys live at once (in + out); a key beyond that is not journalled (counted in ``full``); the slots
# of keys freed as idle (:meth:`Journal.forget`) are used again
_EMPTY = -(2**63)
_FMT = struct.Struct("<q")
#: slots 0..3: slot index of the input key being handled, its seq, outputs sent when it began, outputs sent
_RESERVED = ("~slot", "~seq", "~sent_at_begin", "~sent")


class Journal:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.index_path = self.path.with_suffix(".keys.json")
        # slots given to new keys (or freed) since the index was written: appended lines "slot<TAB>name"
        self.index_log = self.path.with_suffix(".keys.log")
        self._log_fd: int | None = None
        self.slot: dict[str, int] = {}
        self.free: list[int] = []  # slots of forgotten keys
        self.n_slots = 0  # slots ever given out this run
        self.full = 0
        self.mm: mmap.mmap | None = None
        self._view = None  # the slots as a numpy array (frames write many at once, see :meth:`array`)
        self._lock = threading.Lock()  # a new key's slot (the receive thread journals first-received seqs too)

    def load(self) -> dict[str, int]:
        """What a previous run left (empty when it stopped cleanly or never ran)."""
        try:
            names = json.loads(self.index_path.read_text())
            raw = self.path.read_bytes()
        except (OSError, ValueError):
            return {}
        out: dict = {}
        names = names if isinstance(names, list) else []
        try:
            log = self.index_log.read_bytes().decode("utf-8", "replace").split("\n")
        except OSError:
            log = []
        for line in log:
            i, tab, name = line.partition("\t")
            if not tab or not i.isdigit() or int(i) >= SLOTS:
                continue  # (a line torn by a kill in the middle of its write)
            i = int(i)
            if i >= len(names):
                names.extend([""] * (i + 1 - len(names)))
            names[i] = name
        for i, name in enumerate(names):
            if (i + 1) * 8 <= len(raw):
                v = _FMT.unpack_from(raw, i * 8)[0]
                if isinstance(name, str) and (v != _EMPTY or name == "~slot"):
                    out[name] = v
        if names[:4] == list(_RESERVED):
            out["~names"] = names
        else:  # not a journal of this layout: nothing usable about a sample in progress
            for k in _RESERVED:
                out.pop(k, None)
        return out

    def open(self, previous: dict[str, int]) -> None:
        """Start this run's journal, carrying the previous run's values on (a second crash loses nothing).

        Under the lock, and the map published last: a receive thread journalling a first-received seq meanwhile
        either waits or (before the map exists) writes nothing, never a slot or an index this open then resets.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._lock:
            with open(self.path, "wb") as f:
                f.write(_FMT.pack(_EMPTY) * SLOTS)
            fd = os.open(self.path, os.O_RDWR)
            try:
                mm = mmap.mmap(fd, SLOTS * 8)
            finally:
                os.close(fd)
            self.slot, self.free, self.n_slots = {}, [], 0
            carried = [(k, v) for k, v in previous.items() if not k.startswith("~")]
            self.full += max(0, len(carried) - (SLOTS - len(_RESERVED)))
            carried = carried[:SLOTS - len(_RESERVED)]
            for k, v in [(k, _EMPTY if k == "~slot" else 0) for k in _RESERVED] + carried:
                i, self.n_slots = self.n_slots, self.n_slots + 1  # fixed slots 0..3: the sample in progress
                _FMT.pack_into(mm, i * 8, int(v))
                self.slot[k] = i
            self._write_index()
            self.mm = mm

    def _write_index(self) -> None:
        """The slot names, replaced atomically, and the log of later changes emptied (called with the lock
        held: one writer of the temporary file)."""
        names = [""] * self.n_slots  # a free slot has no name (and holds the empty value)
        for k, i in self.slot.items():
            names[i] = k
        write_atomic(self.index_path, json.dumps(names))
        if self._log_fd is not None:
            os.close(self._log_fd)
            self._log_fd = None
        try:
            os.truncate(self.index_log, 0)
        except OSError:
            pass

    def _append_index(self, pairs: list[tuple[int, str]]) -> None:
        """New slot names (or freed slots: an empty name) as appended lines — one short write however many keys
        the journal holds (called with the lock held)."""
        if self._log_fd is None:
            self._log_fd = os.open(self.index_log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.write(self._log_fd, "".join(f"{i}\t{n}\n" for i, n in pairs).encode())

    def set(self, key: str, value: int) -> None:
        mm = self.mm
        if mm is None:
            return
        try:
            i = self.slot.get(key)
            if i is None:
                with self._lock:
                    i = self.slot.get(key)
                    if i is None:
                        if self.free:
                            i = self.free.pop()
                        elif self.n_slots < SLOTS:
                            i, self.n_slots = self.n_slots, self.n_slots + 1
                        else:
                            self.full += 1
                            return
                        _FMT.pack_into(mm, i * 8, int(value))
                        self.slot[key] = i
                        self._append_index([(i, key)])  # a new key: one appended line
                        return
            _FMT.pack_into(mm, i * 8, int(value))
        except (ValueError, OSError):  # closed by a stop in progress: nothing left to account for
            return

    def slot_of(self, name: str) -> int:
        """The slot of ``name`` (given one, holding the empty value, on first use); -1 when none is free."""
        i = self.slot.get(name)
        if i is None:
            self.set(name, _EMPTY)
            i = self.slot.get(name, -1)
        return i

    def slots_of(self, names: list[str]) -> list[int]:
        """:meth:`slot_of` for many names, the index written once (a frame brings hundreds of new keys)."""
        mm = self.mm
        out = []
        new: list[tuple[int, str]] = []
        with self._lock:
            for name in names:
                i = self.slot.get(name)
                if i is None and mm is not None:
                    if self.free:
                        i = self.free.pop()
                    elif self.n_slots < SLOTS:
                        i, self.n_slots = self.n_slots, self.n_slots + 1
                    else:
                        self.full += 1
                        out.append(-1)
                        continue
                    try:
                        _FMT.pack_into(mm, i * 8, _EMPTY)
                    except (ValueError, OSError):
                        out.append(-1)
                        continue
                    self.slot[name] = i
                    new.append((i, name))
                out.append(-1 if i is None else i)
            if new:
                self._append_index(new)
        return out

    def array(self):
        """The slots as a writable numpy int64 array over the map (writes land in the file at once, as
        :meth:`set`'s do); None when the journal is not open."""
        if self.mm is None:
            return None
        if self._view is None:
            import numpy as np

            self._view = np.frombuffer(self.mm, dtype="<i8")
        return self._view

    def forget(self, names: list[str]) -> None:
        """Free the slots of keys whose state the service has freed (idle keys): what they held is no longer
        anything to account for at a restart, and their slots serve new keys."""
        mm = self.mm
        if mm is None:
            return
        with self._lock:
            gone = [n for n in names if n in self.slot and not n.startswith("~")]
            if not gone:
                return
            try:
                freed = []
                for n in gone:
                    i = self.slot.pop(n)
                    _FMT.pack_into(mm, i * 8, _EMPTY)  # emptied before the index forgets it: never misread
                    self.free.append(i)
                    freed.append((i, ""))
                self._append_index(freed)
            except (ValueError, OSError):
                return

    def begin(self, key: str, seq: int, n_sent: int) -> None:
        """A sample starts being handled: its key's slot, its seq, and the outputs sent so far."""
        if key not in self.slot:
            self.set(key, _EMPTY)  # a new key: known as not handled yet
        mm = self.mm
        i = self.slot.get(key)
        if mm is None or i is None:
            return
        try:
            _FMT.pack_into(mm, 8, int(seq))
            _FMT.pack_into(mm, 16, int(n_sent))
            _FMT.pack_into(mm, 0, i)
        except (ValueError, OSError):
            return

    def sent(self, n_sent: int) -> None:
        mm = self.mm
        if mm is not None:
            try:
                _FMT.pack_into(mm, 24, int(n_sent))
            except (ValueError, OSError):
                return

    def in_progress(self, previous: dict[str, int]) -> tuple[str | None, int]:
        """(key, seq) of the sample a previous run was handling when it died (None when there is none)."""
        slot = previous.get("~slot", _EMPTY)
        names = previous.get("~names") or []
        if slot == _EMPTY or not 0 <= slot < len(names) or not names[slot]:
            return None, 0
        return names[slot], previous.get("~seq", 0)

    def remove(self) -> None:
        """A clean stop: nothing to account for at the next start."""
        if self.mm is not None:
            self._view = None  # a numpy view keeps the map exported: drop it before closing
            try:
                self.mm.close()
            except BufferError:  # an array view handed out is still alive somewhere: the map closes with it
                pass
            self.mm = None
        if self._log_fd is not None:
            os.close(self._log_fd)
            self._log_fd = None
        for p in (self.path, self.index_path, self.index_log):
            try:
                p.unlink()
            except OSError:
                pass
