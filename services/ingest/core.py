"""Ingest validation core: physical ranges, time order and duplicates per stream. Pure Python/numpy.

Schema, types, finiteness and versions are checked by :func:`schemas.messages.decode`; this core checks
what a well-formed message can still get wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass(frozen=True)
class IngestSettings:
    max_field_nt: float = 2.0e6  # |b| above this is not a magnetometer reading (sensor full scale ~0.8–8 mT)
    max_gyro_rad_s: float = 40.0  # ~2300 °/s
    max_accel_m_s2: float = 300.0  # ~30 g
    max_speed_m_s: float = 400.0
    alt_range_m: tuple = (-1000.0, 60000.0)
    max_pdop: float = 100.0
    max_pos_m: float = 1.0e7  # local ENU coordinates
    max_time_jump_s: float = 3600.0  # a sample this far ahead of the previous one on its stream is refused
    tick_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("max_field_nt", "max_gyro_rad_s", "max_accel_m_s2", "max_speed_m_s", "max_time_jump_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")


@dataclass
class StreamState:
    last_t_s: float | None = None
    last_seq: int | None = None
    accepted: int = 0
    upstream_gaps: int = 0  # samples missing according to the publisher's seq


@dataclass
class VehicleState:
    streams: dict[str, StreamState] = field(default_factory=dict)


class Rejection(Exception):
    def __init__(self, code: str, field: str | None, reason: str):
        super().__init__(reason)
        self.code = code
        self.field = field
        self.reason = reason


def _norm(v) -> float:
    return math.sqrt(sum(x * x for x in v))


def check_ranges(msg: dict, s: IngestSettings, where: str) -> None:
    """Raise :class:`Rejection` when a value is outside its physical range."""
    t = msg["type"]

    def bad(fld: str, what: str) -> Rejection:
        return Rejection("range", fld, f"field '{fld}' of {where} {what}")

    if msg["t_s"] < 0:
        raise bad("t_s", f"must be ≥ 0, got {msg['t_s']:g}")
    if t == "mag":
        n = _norm(msg["b_nt"])
        if n > s.max_field_nt:
            raise bad("b_nt", f"has |b| = {n:.4g} nT, beyond the {s.max_field_nt:.4g} nT a magnetometer can read")
        if msg["sensor"] != where.rsplit("/", 1)[-1]:
            raise Rejection("key", "sensor", f"field 'sensor' of {where} is {msg['sensor'][:64]!r}, "
                            "but the key names another sensor")
    elif t == "imu":
        g = _norm(msg["gyro_rad_s"])
        if g > s.max_gyro_rad_s:
            raise bad("gyro_rad_s", f"has |ω| = {g:.4g} rad/s, beyond {s.max_gyro_rad_s:g} rad/s")
        a = _norm(msg["accel_m_s2"])
        if a > s.max_accel_m_s2:
            raise bad("accel_m_s2", f"has |a| = {a:.4g} m/s², beyond {s.max_accel_m_s2:g} m/s²")
    elif t == "gnss":
        if not (s.alt_range_m[0] <= msg["alt_m"] <= s.alt_range_m[1]):
            raise bad("alt_m", f"is {msg['alt_m']:.4g} m, outside {s.alt_range_m[0]:g}..{s.alt_range_m[1]:g} m")
        if msg["speed_m_s"] > s.max_speed_m_s:
            raise bad("speed_m_s", f"is {msg['speed_m_s']:.4g} m/s, beyond {s.max_speed_m_s:g} m/s")
        if _norm(msg["vel_enu_m_s"]) > s.max_speed_m_s * 1.5:
            raise bad("vel_enu_m_s", f"has a speed beyond {s.max_speed_m_s * 1.5:g} m/s")
        if msg["pdop"] > s.max_pdop:
            raise bad("pdop", f"is {msg['pdop']:.4g}, beyond {s.max_pdop:g}")
        if "pos_enu_m" in msg and max(abs(x) for x in msg["pos_enu_m"]) > s.max_pos_m:
            raise bad("pos_enu_m", f"is beyond ±{s.max_pos_m:.3g} m")
    elif t in ("ins", "route"):
        for fld in ("pos_enu_m", "a_enu_m", "b_enu_m", "vel_enu_m_s"):
            if fld in msg and max(abs(x) for x in msg[fld]) > s.max_pos_m:
                raise bad(fld, f"is beyond ±{s.max_pos_m:.3g}")


def check_order(msg: dict, st: StreamState, s: IngestSettings, where: str) -> None:
    """Raise :class:`Rejection` for duplicates and time going backwards on one stream."""
    t = msg["t_s"]
    if st.last_t_s is not None:
        if t == st.last_t_s:
            raise Rejection("duplicate", "t_s", f"sample of {where} at t_s = {t:.6f} s repeats the previous one")
        if t < st.last_t_s:
            raise Rejection("time_order", "t_s", f"field 't_s' of {where} went backwards: {t:.6f} s after "
                            f"{st.last_t_s:.6f} s")
        if t - st.last_t_s > s.max_time_jump_s:
            raise Rejection("time_order", "t_s", f"field 't_s' of {where} jumped {t - st.last_t_s:.4g} s ahead "
                            f"(more than {s.max_time_jump_s:g} s)")


def accept(msg: dict, st: StreamState) -> None:
    """Record an accepted sample; count publisher-side gaps from seq."""
    seq = msg["seq"]
    if st.last_seq is not None and seq > st.last_seq + 1:
        st.upstream_gaps += seq - st.last_seq - 1
    st.last_seq = seq
    st.last_t_s = msg["t_s"]
    st.accepted += 1
