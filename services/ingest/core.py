"""Ingest validation core: physical ranges, time order and duplicates per stream. Pure Python/numpy.

Schema, types, finiteness and versions are checked by :func:`schemas.messages.decode`; this core checks
what a well-formed message can still get wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from magmesh import declare
from magmesh.declare import setting
from schemas.streams import LIMIT_DEFAULTS, limit_problem

#: how far (s of sample time) a sample may run ahead of its stream's clock, by stream kind; see
#: :func:`ahead_limit_s`. A route is sent once per leg, so it may legitimately come much later in sample time.
MAX_AHEAD_S = {"mag": 10.0, "imu": 10.0, "gnss": 60.0, "ins": 60.0, "attitude": 30.0, "route": 600.0}


@dataclass(frozen=True)
class IngestSettings:
    # physical ranges: defaults from the streams table (schemas/streams.py LIMITS / LIMIT_DEFAULTS)
    max_field_nt: float = setting(LIMIT_DEFAULTS["max_field_nt"], "a magnetometer sample whose |b| exceeds this is "
                                  "refused (not a reading: sensor full scale is about 0.8–8 mT)", gt=0)
    max_gyro_rad_s: float = setting(LIMIT_DEFAULTS["max_gyro_rad_s"], "an IMU sample whose |ω| exceeds this is "
                                    "refused (about 2300 °/s)", gt=0)
    max_accel_m_s2: float = setting(LIMIT_DEFAULTS["max_accel_m_s2"], "an IMU sample whose |a| exceeds this is "
                                    "refused (about 30 g)", gt=0)
    max_speed_m_s: float = setting(LIMIT_DEFAULTS["max_speed_m_s"], "a GNSS speed above this is refused (the "
                                   "velocity vector may reach 1.5 × this)", gt=0)
    alt_range_m: tuple = setting(LIMIT_DEFAULTS["alt_range_m"], "a GNSS altitude outside (lowest, highest) is "
                                 "refused")
    max_pdop: float = setting(LIMIT_DEFAULTS["max_pdop"], "a GNSS fix with a PDOP above this is refused")
    max_pos_m: float = setting(LIMIT_DEFAULTS["max_pos_m"], "a local ENU coordinate (GNSS, INS, route) beyond ± this "
                               "is refused (an INS velocity component too, in m/s)")
    max_time_jump_s: float = setting(3600.0, "a sample this far ahead of the previous one on its stream is refused",
                                     gt=0)
    max_ahead_s: dict = setting(dict(MAX_AHEAD_S), "a sample further ahead of its stream's clock than this (s, by "
                                "stream kind; a JSON object overrides the kinds it names) is refused; the clock runs "
                                "at the stream's own learned rate (replays run faster)")
    max_clock_rate: float = setting(10000.0, "fastest sample-time-per-wall-time rate a stream's clock is believed to "
                                    "run", gt=0)
    rebase_after: int = setting(10, "this many consecutive, mutually consistent refusals on time: the clock really "
                                "jumped (re-based)", gt=0)
    seq_jump_max: int = setting(10_000, "a seq jump beyond this is a counter re-base, not that many lost samples",
                                gt=0)
    evict_idle_s: float = setting(600.0, "state of a key or vehicle silent this long is freed (counted)", gt=0)
    tick_s: float = setting(1.0, "period of the service's tick with output = singles (batches and frames go out "
                            "from a tick at half batch_window_s)")

    def __post_init__(self) -> None:
        declare.check(self)
        if not isinstance(self.max_ahead_s, dict):
            raise ValueError(f"max_ahead_s must be a map of stream kind to seconds, got {self.max_ahead_s!r}")
        unknown = sorted(set(self.max_ahead_s) - set(MAX_AHEAD_S))
        if unknown:
            raise ValueError(f"max_ahead_s: unknown stream kind(s) {', '.join(map(str, unknown))}; "
                             f"known: {', '.join(MAX_AHEAD_S)}")
        merged = {**MAX_AHEAD_S, **self.max_ahead_s}
        for k, v in merged.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"max_ahead_s[{k!r}] must be a number of seconds > 0, got {v!r}")
        object.__setattr__(self, "max_ahead_s", {k: float(v) for k, v in merged.items()})


@dataclass
class StreamState:
    last_t_s: float | None = None
    last_seq: int | None = None
    accepted: int = 0
    upstream_gaps: int = 0  # samples missing according to the publisher's seq
    seq_rebases: int = 0  # seq jumps beyond the bound (or backwards): counted once each, not as loss
    # the stream's clock: receive time (monotonic s) of the last accepted sample and its learned rate
    last_wall: float | None = None
    rate: float = 1.0
    rate_learned: bool = False  # a window of at least 1 s of receive time has set ``rate``
    win_t_s: float | None = None
    win_wall: float | None = None
    # consecutive refusals on time that agree with each other (a clock that really jumped)
    contra_n: int = 0
    contra_last_t_s: float | None = None
    clock_rebases: int = 0
    # seqs refused since the last accepted sample: delivered (and counted as rejected), so no gap of the stream
    refused_seqs: set = field(default_factory=set)
    step_s: float = 0.0  # the last step in sample time between accepted samples (a slow stream's own cadence)


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
    if t == "mag" and msg["sensor"] != where.rsplit("/", 1)[-1]:
        raise Rejection("key", "sensor", f"field 'sensor' of {where} is {msg['sensor'][:64]!r}, "
                        "but the key names another sensor")
    p = limit_problem(msg, s)  # the ranges of the streams table
    if p is not None:
        raise bad(p[0], p[1])


def ahead_limit_s(msg_type: str, st: StreamState, s: IngestSettings, now: float) -> float:
    """How far past the stream's last accepted sample a sample received at ``now`` may be dated.

    The stream's clock runs at its learned rate (sample seconds per wall second, at least 1: a replay at 10×
    runs 10 s per s) since the last accepted sample was received; a sample may lead it by the kind's
    ``max_ahead_s`` plus twice the elapsed wall time and half a second of jitter at that rate.
    """
    dt = max(0.0, now - st.last_wall) if st.last_wall is not None else 0.0
    if st.rate_learned:
        rate = min(max(st.rate, 1.0), s.max_clock_rate)
    else:
        # before a second of receive time has taught the rate: the rate of what was accepted so far, and with one
        # sample only, unknown (at most max_clock_rate) -- a slow stream of a fast source (one sample a second,
        # 20 s of sample time apart) must not be refused for ever by a 1x clock it never gets to correct
        span = st.last_wall - st.win_wall if st.last_wall is not None and st.win_wall is not None else 0.0
        if span > 0 and st.last_t_s is not None and st.win_t_s is not None:
            rate = min(max((st.last_t_s - st.win_t_s) / span, 1.0), s.max_clock_rate)
        else:
            rate = s.max_clock_rate
    # plus two of the stream's own steps: a slow stream's samples (20 s apart at one a second) may arrive
    # bunched by a loaded network or host without being ahead of anything
    ahead = s.max_ahead_s.get(msg_type, 10.0)
    return ahead + rate * (2.0 * dt + 0.5) + 2.0 * min(st.step_s, 3.0 * ahead)


def check_order(msg: dict, st: StreamState, s: IngestSettings, where: str, now: float | None = None) -> None:
    """Raise :class:`Rejection` for duplicates, time going backwards, and (given the receive time ``now``) a
    sample too far ahead of its stream's clock. Nothing here changes the stream's state."""
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
        if now is not None and st.last_wall is not None:
            lim = ahead_limit_s(msg["type"], st, s, now)
            if t - st.last_t_s > lim:
                raise Rejection("time_order", "t_s", f"field 't_s' of {where} is {t - st.last_t_s:.4g} s after the "
                                f"stream's last sample, {now - st.last_wall:.3g} s of receive time later (at most "
                                f"{lim:.4g} s for {msg['type']} samples): dated ahead of the stream's clock")


def note_refusal(msg: dict, st: StreamState, s: IngestSettings) -> bool:
    """Record a sample refused on time; True when the stream has contradicted its clock ``rebase_after`` times
    in a row with samples that agree with each other — its clock really jumped and should be re-based."""
    t = msg["t_s"]
    prev = st.contra_last_t_s
    consistent = prev is not None and 0.0 < t - prev <= s.max_ahead_s.get(msg["type"], 10.0)
    st.contra_n = st.contra_n + 1 if consistent else 1
    st.contra_last_t_s = t
    return st.contra_n >= s.rebase_after


def rebase(st: StreamState) -> None:
    """Forget the stream's clock (the next accepted sample starts it again); counted."""
    st.last_t_s = None
    st.last_wall = None
    st.rate = 1.0
    st.rate_learned = False
    st.step_s = 0.0
    st.win_t_s = st.win_wall = None
    st.contra_n = 0
    st.contra_last_t_s = None
    st.clock_rebases += 1


def accept(msg: dict, st: StreamState, now: float | None = None, s: IngestSettings | None = None) -> None:
    """Record an accepted sample: its time (and receive time ``now``, which teaches the stream's clock rate);
    count publisher-side gaps from seq, a jump beyond ``seq_jump_max`` counted once as a re-base."""
    seq = msg["seq"]
    jump_max = s.seq_jump_max if s is not None else 10_000
    if st.last_seq is not None:
        gap = seq - st.last_seq - 1
        if gap > jump_max or gap < -1:
            st.seq_rebases += 1
        elif gap > 0:
            st.upstream_gaps += gap - sum(1 for r in st.refused_seqs if st.last_seq < r < seq)
    st.refused_seqs.clear()
    st.last_seq = seq
    t = msg["t_s"]
    if st.last_t_s is not None and t > st.last_t_s:
        st.step_s = t - st.last_t_s
    st.last_t_s = t
    st.accepted += 1
    st.contra_n = 0
    st.contra_last_t_s = None
    if now is not None:
        st.last_wall = now
        if st.win_wall is None:
            st.win_t_s, st.win_wall = t, now
        elif now - st.win_wall >= 1.0:
            r = (t - st.win_t_s) / (now - st.win_wall)
            hi = s.max_clock_rate if s is not None else 10000.0
            # a faster clock is believed at once, a slower one by halves (bursts of delivery are not a slow-down)
            st.rate = min(max(r, 0.5 * st.rate, 1.0), hi)
            st.rate_learned = True
            st.win_t_s, st.win_wall = t, now
