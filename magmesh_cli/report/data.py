"""Turn a list of ``(key, message)`` pairs into per-vehicle arrays for plots and the summary table.

Pure numpy; no Zenoh, no matplotlib. Times are sample times ``t_s`` of the vehicle's clock.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from magmesh import maths
from schemas import keys


@dataclass
class Interval:
    """An alarm from raise to clear (``end`` is the end of the run when it never cleared)."""

    source: str
    start: float
    end: float
    cleared: bool
    severity: str
    reason: str
    key: str


@dataclass
class VehicleRun:
    vehicle: str
    by_key: dict[str, list[dict]] = field(default_factory=lambda: defaultdict(list))

    # ---- selection ----------------------------------------------------------------------------
    def keys_of(self, kind: str, stream: str | None = None) -> list[str]:
        out = []
        for k in sorted(self.by_key):
            info = keys.parse(k)
            if info.kind == kind and (stream is None or info.stream == stream):
                out.append(k)
        return out

    def messages(self, kind: str, stream: str | None = None) -> list[dict]:
        ms = [m for k in self.keys_of(kind, stream) for m in self.by_key[k]]
        ms.sort(key=lambda m: m["t_s"])
        return ms

    def one(self, key: str) -> list[dict]:
        return self.by_key.get(key, [])

    @property
    def t_range(self) -> tuple[float, float]:
        ts = [m["t_s"] for ms in self.by_key.values() for m in (ms[0], ms[-1]) if ms]
        return (min(ts), max(ts)) if ts else (0.0, 0.0)

    # ---- streams as arrays --------------------------------------------------------------------
    def mag_sensors(self, kind: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """sensor → (t, b_nt N×3) for raw/clean/cal mag keys."""
        out = {}
        for k in self.keys_of(kind, "mag"):
            ms = self.by_key[k]
            if ms:
                out[keys.parse(k).sensor] = (np.array([m["t_s"] for m in ms]),
                                             np.array([m["b_nt"] for m in ms], float))
        return out

    def field(self, name: str, kind: str, stream: str | None = None, default=np.nan) -> tuple[np.ndarray, np.ndarray]:
        ms = self.messages(kind, stream)
        t = np.array([m["t_s"] for m in ms], float)
        v = [m.get(name, default) for m in ms]
        v = [default if x is None else x for x in v]
        return t, np.array(v, float)

    def truth(self, what: str) -> list[dict]:
        return self.one(keys.truth(self.vehicle, what))

    def alarms(self) -> list[Interval]:
        t_end = self.t_range[1]
        out: list[Interval] = []
        for k in self.keys_of("alarm"):
            open_: dict | None = None
            for m in sorted(self.by_key[k], key=lambda m: (m["t_s"], m["seq"])):
                if m["state"] == "raised" and open_ is None:
                    open_ = m
                elif m["state"] == "cleared" and open_ is not None:
                    out.append(Interval(open_["source"], open_["t_s"], m["t_s"], True, open_["severity"],
                                        open_["reason"], k))
                    open_ = None
            if open_ is not None:
                out.append(Interval(open_["source"], open_["t_s"], max(t_end, open_["t_s"]), False,
                                    open_["severity"], open_["reason"], k))
        out.sort(key=lambda a: a.start)
        return out

    def disturbed_intervals(self) -> list[tuple[float, float]]:
        """Intervals where truth/sources says the field is disturbed."""
        ms = self.truth("sources")
        t = np.array([m["t_s"] for m in ms if "disturbed" in m])
        d = np.array([bool(m["disturbed"]) for m in ms if "disturbed" in m])
        return bool_intervals(t, d)


#: streams no figure uses (the report leaves them unread)
UNPLOTTED_STREAMS = ("imu", "attitude")


def plotted_keys(recorded: list[str], vehicles=None) -> list[str]:
    """The recorded keys the report reads: not IMU/attitude, and ``raw/x`` only where no ``clean/x`` exists."""
    parsed = []
    for k in recorded:
        try:
            info = keys.parse(k)
        except keys.KeyError_:
            continue
        if info.kind == "svc" or (vehicles and info.vehicle not in vehicles):
            continue
        if info.kind in ("raw", "clean") and info.stream in UNPLOTTED_STREAMS:
            continue
        parsed.append(info)
    clean = {(i.vehicle, i.rest) for i in parsed if i.kind == "clean"}
    return sorted(i.key for i in parsed if not (i.kind == "raw" and (i.vehicle, i.rest) in clean))


def group(messages: Iterable[tuple[str, dict]]) -> dict[str, VehicleRun]:
    """Per-vehicle runs from decoded ``(key, message)`` pairs; service keys are ignored."""
    runs: dict[str, VehicleRun] = {}
    for key, msg in messages:
        try:
            info = keys.parse(key)
        except keys.KeyError_:
            continue
        if info.kind == "svc" or not info.vehicle:
            continue
        run = runs.get(info.vehicle)
        if run is None:
            run = runs[info.vehicle] = VehicleRun(info.vehicle)
        run.by_key[key].append(msg)
    for run in runs.values():
        for ms in run.by_key.values():
            ms.sort(key=lambda m: m["t_s"])
    return dict(sorted(runs.items()))


def bool_intervals(t: np.ndarray, flag: np.ndarray) -> list[tuple[float, float]]:
    """Intervals [t_start, t_end] where ``flag`` is true (each run ends at its last true sample's successor)."""
    t = np.asarray(t, float)
    flag = np.asarray(flag, bool)
    out = []
    if len(t) == 0:
        return out
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flag.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=False):
        end = t[b] if b < len(t) else t[-1]
        out.append((float(t[a]), float(end)))
    return out


def interp_angle(t_query: np.ndarray, t: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Interpolate angles (rad) without jumping across the wrap; NaN outside ``t``."""
    if len(t) < 2:
        return np.full(len(t_query), np.nan)
    u = np.unwrap(angle)
    out = np.interp(t_query, t, u)
    out[(t_query < t[0]) | (t_query > t[-1])] = np.nan
    return maths.wrap_2pi(out)


def heading_error(run: VehicleRun, source: str = "heading") -> tuple[np.ndarray, np.ndarray] | None:
    """(t, error rad in [−π, π)) of the ``heading`` (or ``dmc``) stream against truth/pose."""
    pose = [m for m in run.truth("pose") if "heading_rad" in m]
    t_est, h_est = run.field("heading_rad", source)
    if len(pose) < 2 or len(t_est) == 0:
        return None
    tt = np.array([m["t_s"] for m in pose])
    ht = np.array([m["heading_rad"] for m in pose])
    # truth gaps (cameras lost the board) longer than 1 s are not bridged
    gaps = np.flatnonzero(np.diff(tt) > 1.0)
    h_true = interp_angle(t_est, tt, ht)
    for g in gaps:
        h_true[(t_est > tt[g]) & (t_est < tt[g + 1])] = np.nan
    err = maths.angle_diff(h_est, h_true)
    ok = np.isfinite(err)
    return t_est[ok], err[ok]


def rms(x) -> float:
    x = np.asarray(x, float)
    return float(math.sqrt(np.mean(x * x))) if x.size else float("nan")
