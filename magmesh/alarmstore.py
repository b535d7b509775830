"""Alarm states that survive a crash: a snapshot plus an append-only log of transitions.

Every alarm transition an instance publishes is appended as one line to ``{name}.log`` (one ``os.write`` to a
file opened for appending: in the page cache the moment it returns, so a kill -9 loses nothing written). The
state — per alarm key the last state published, its seq, and the message of each alarm held raised — is the
snapshot ``{name}.json`` with the log's lines applied in order (a line whose seq is older than what is known
for its key changes nothing; a torn last line is ignored). :meth:`AlarmStore.compact` writes a new snapshot
atomically and empties the log; it runs when the log grows long and at a clean stop. So a transition costs one
short write however many vehicles an instance serves, instead of rewriting every vehicle's state.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from .paths import write_atomic

#: transitions appended before the snapshot is rewritten
COMPACT_EVERY = 2000


def _empty() -> dict:
    return {"published": {}, "raised": {}, "seqs": {}, "last": {}}


def _apply(state: dict, key: str, st: str, seq: int, msg: dict | None, wall: float | None = None) -> None:
    known = state["seqs"].get(key)
    if known is not None and seq < known:
        return
    state["published"][key] = st
    state["seqs"][key] = seq
    if st == "raised" and msg is not None:
        state["raised"][key] = msg
    else:
        state["raised"].pop(key, None)
    if msg is not None and wall is not None:  # (from the log only: a snapshot keeps no cleared message)
        state["last"][key] = {"m": msg, "w": wall}
    else:
        state["last"].pop(key, None)


def load(path: Path) -> dict:
    """``{"published": {key: state}, "raised": {key: message}, "seqs": {key: seq}, "last": {key: {"m": message,
    "w": wall time}}}`` of a snapshot path (``….json``) and its log (empty when neither exists). ``last``: the
    message of each key's last transition and when it was written, for a transition still in the log."""
    path = Path(path)
    state = _empty()
    try:
        data = json.loads(path.read_text())
        if isinstance(data, dict):
            for k in state:
                v = data.get(k)
                if isinstance(v, dict):
                    state[k] = dict(v)
    except (OSError, ValueError):
        pass
    try:
        lines = path.with_suffix(".log").read_bytes().split(b"\n")
    except OSError:
        return state
    for line in lines:
        if not line:
            continue
        try:
            e = json.loads(line)
            w = e.get("w")
            _apply(state, str(e["k"]), str(e["s"]), int(e["q"]), e.get("m"), float(w) if w is not None else None)
        except (ValueError, KeyError, TypeError):
            continue  # a line torn by a kill in the middle of its write
    return state


class AlarmStore:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.log_path = self.path.with_suffix(".log")
        self._fd: int | None = None
        self.appended = 0

    def record(self, key: str, state: str, seq: int, msg: dict | None) -> bool:
        """Append one transition; True when the log has grown long enough to compact."""
        if self._fd is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        # every transition's message and the wall time it was written (before its put): a group member taking the
        # vehicle over after a kill -9 publishes it again if the mesh never showed it (magmesh/group_member.py)
        line = json.dumps({"k": key, "s": state, "q": int(seq), "m": msg, "w": round(time.time(), 3)},
                          separators=(",", ":")).encode() + b"\n"
        os.write(self._fd, line)
        self.appended += 1
        return self.appended >= COMPACT_EVERY

    def compact(self, state: dict) -> None:
        """Write ``state`` as the snapshot (atomically) and empty the log."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(self.path, json.dumps(state))
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        try:
            os.truncate(self.log_path, 0)
        except OSError:
            pass
        self.appended = 0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
