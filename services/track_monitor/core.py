"""Track monitor core: cross-track deviation, heading-innovation and combined magnetic-anomaly detectors.

Pure Python/numpy; never imports zenoh. Method: He, Luo, Wu (docs/methods.md#track).

* Cross-track deviation (eq. 6): d = |(X − A) × (B − A)| / |B − A|, horizontal, from RTK GNSS. The
  track detector raises when d > ``track_threshold_m`` (1 m in the paper, where the mission fails) on
  GNSS good enough to trust it (fix type, satellites, PDOP, stated accuracy, age); it arms only once the
  vehicle has been on the line, and clears with hysteresis (d < ``track_clear_m`` for ``clear_hold_s``).
* Heading innovation e = ψ_mag − ψ_attitude (the flight controller's tilt-compensated magnetometer
  heading minus its complementary-filter heading). The paper's test: |e| > k·σ with k = 5 and σ the
  standard deviation of e on undisturbed flight (``innovation_test = "paper"``). It catches steps and fast
  ramps quickly but false-alarms on short magnetometer bursts and misses slow ramps, which the filter
  follows. The default test (``"robust"``) keeps the k·σ gate but
  - applies it to the running median of e over ``median_window_s`` (bursts shorter than half the window
    cannot raise it), gated at ``median_k_sigma`` times the median's own spread on undisturbed flight and
    held for ``gate_persist_s``; bursts beyond ``burst_sigma`` × the robust (MAD) σ of e are excised and
    the flight controller's recovery from them modelled out; and
  - adds a two-sided CUSUM (Page) on block means of e, clipped at ±``clip_sigma``·σ (Huber) and normalised
    by the learned spread of those block means: g⁺ ← max(0, g⁺ + z − ν), g⁻ ← max(0, g⁻ − z − ν),
    raise when g > h. A slow ramp makes the filter lag the magnetometer by (ramp rate × filter time
    constant), a small persistent bias that the CUSUM accumulates within a few blocks.
  σ is learned from the first ``learn_s`` seconds of flight (assumed undisturbed) unless given.
* The combined verdict (``mag_anomaly``) is the earliest reliable alarm of the two; its reason names the
  detector that fired. It clears only when both detectors have been quiet for ``anomaly_clear_hold_s``
  (a magnetometer that stays disturbed at a constant level leaves the innovation quiet once the filter
  has followed it, so the verdict is held).

Shape (x-io Fusion style): :class:`TrackMonitorSettings`, :class:`TrackMonitor` with ``set_route``,
``update_gnss``, ``update_attitude``, ``internal_states``, ``flags``, ``reset``. Updates return the alarm
transitions (:class:`AlarmEvent`) they caused.
"""

from __future__ import annotations

import dataclasses
import math
from bisect import bisect_left, insort
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from magmesh import declare
from magmesh.declare import setting
from magmesh.latch import AlarmLatch

INNOVATION_TESTS = ("robust", "paper")


@dataclass(frozen=True)
class TrackMonitorSettings:
    # ---- track-deviation detector (paper eq. 6) ----
    track_threshold_m: float = setting(1.0, "raise alarm/track when the cross-track deviation d exceeds this (paper: "
                                       "1 m)", gt=0)
    track_clear_m: float = setting(0.5, "clear when d stays below this for clear_hold_s (< track_threshold_m)", lo=0)
    clear_hold_s: float = setting(2.0, "every detector's hysteresis hold: the clear condition must last this long",
                                  lo=0)
    track_persist_s: float = setting(0.15, "d must exceed the threshold this long (≥ 2 GNSS epochs at 10 Hz)", lo=0)
    arm_within_m: float = setting(1.0, "the track detector arms once d has stayed below this on a route for "
                                  "arm_hold_s")
    arm_hold_s: float = setting(5.0, "... for this long (the leg has been acquired)")
    gnss_fix_types: tuple = setting(("rtk_fixed",), "GNSS fix types good enough to trust d")
    gnss_min_sats: int = setting(6, "satellites a trusted GNSS fix has at least")
    gnss_max_pdop: float = setting(3.0, "PDOP of a trusted GNSS fix at most")
    gnss_max_horiz_std_m: float = setting(0.1, "stated 1-σ accuracy of a trusted GNSS fix at most, when the receiver "
                                          "gives one")
    route_margin_m: float = setting(5.0, "along-track slack before A and beyond B where d is still monitored", lo=0)
    # ---- heading-innovation detector ----
    innovation_test: str = setting("robust", "paper: |e| > kσ per sample; robust: running median + CUSUM (see the "
                                   "module doc)", choices=INNOVATION_TESTS)
    innovation_k_sigma: float = setting(5.0, "gate of the paper's per-sample test (paper: 5σ)", gt=0)
    median_k_sigma: float = setting(6.0, "gate of the robust test's running median, in its own σ (its tails are "
                                    "heavier than Gaussian: tilt-estimate errors and gusts move it for seconds)", gt=0)
    innovation_sigma_rad: float = setting(0.0, "σ of e on undisturbed flight; 0: learn it", lo=0)
    median_sigma_rad: float = setting(0.0, "σ of the running median of e; 0: learn it", lo=0)
    block_sigma_rad: float = setting(0.0, "σ of block means of clipped e; 0: learn it", lo=0)
    warmup_s: float = setting(15.0, "the first seconds of the attitude stream (take-off transients) are not tested",
                              lo=0)
    learn_s: float = setting(30.0, "then σ is learned over this much (assumed undisturbed) flight", gt=0)
    sigma_floor_rad: float = setting(0.001, "lower bound for a learned σ", gt=0)
    median_window_s: float = setting(0.6, "window of the running median of e (robust test)", gt=0)
    gate_persist_s: float = setting(0.3, "the median must stay beyond kσ this long", lo=0)
    block_s: float = setting(0.5, "CUSUM block length", gt=0)
    clip_sigma: float = setting(3.0, "Huber clip of e before block averaging, in σ", gt=0)
    cusum_drift: float = setting(3.0, "CUSUM drift ν, in block σ", lo=0)
    cusum_threshold: float = setting(15.0, "CUSUM threshold h, in block σ", gt=0)
    innovation_clear_sigma: float = setting(2.5, "clear when the median |e| and the block means stay below this, in σ "
                                            "(≤ innovation_k_sigma)", gt=0)
    burst_sigma: float = setting(8.0, "a sample this far (in σ) from the running median is a burst ...")
    burst_min_rad: float = setting(0.035, "... and at least this far (2°; the only gate while σ is learned)")
    burst_max_s: float = setting(0.5, "a burst lasting this long is a step disturbance")
    fc_mag_gain_per_s: float = setting(1.0, "magnetometer gain k of the flight controller's heading filter (0: "
                                       "unknown)")
    max_attitude_gap_s: float = setting(1.0, "a longer gap restarts the median window and the CUSUM")
    # ---- field strength (holds the combined verdict; never raises it: motors modulate |B|, paper §0) ----
    field_k_sigma: float = setting(5.0, "|B| deviates when its running median is this many σ from the reference ...",
                                   gt=0)
    field_min_dev_nt: float = setting(400.0, "... and at least this far (≈ 0.7 % of a 0.6 G field; turns move |B| by "
                                      "the residual hard iron, a few hundred nT)", lo=0)
    field_window_s: float = setting(1.0, "running-median window of |B|", gt=0)
    field_ref_nt: float = setting(0.0, "undisturbed |B| at the magnetometer; 0: learn it (same windows as σ)", lo=0)
    field_sigma_nt: float = setting(0.0, "σ of the running median of |B| on undisturbed flight; 0: learn it", lo=0)
    # ---- combined verdict ----
    anomaly_clear_hold_s: float = setting(10.0, "alarm/mag_anomaly clears once both detectors (and |B|) have been "
                                          "quiet this long", lo=0)

    def __post_init__(self) -> None:
        declare.check(self)
        if not (self.track_clear_m < self.track_threshold_m):
            raise ValueError(f"track_clear_m must be in [0, track_threshold_m), got {self.track_clear_m}")
        if not (self.innovation_clear_sigma <= self.innovation_k_sigma):
            raise ValueError("innovation_clear_sigma must be in (0, innovation_k_sigma]")

    def replace(self, **changes) -> TrackMonitorSettings:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class AlarmEvent:
    """One alarm transition (published on ``alarm/{source}``)."""

    source: str  # track | heading_innovation | mag_anomaly
    state: str  # raised | cleared
    t_s: float
    reason: str
    value: float | None
    threshold: float | None
    unit: str
    severity: str = "warning"
    raised_t_s: float | None = None


# ---- geometry ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    a_enu_m: tuple
    b_enu_m: tuple
    route_id: str

    @property
    def length_m(self) -> float:
        return math.hypot(self.b_enu_m[0] - self.a_enu_m[0], self.b_enu_m[1] - self.a_enu_m[1])


def cross_track(route: Route, pos_enu_m) -> tuple[float, float]:
    """(signed cross-track distance, along-track distance), horizontal, m.

    Eq. 6: |d| = |(X − A) × (B − A)| / |B − A|; the sign is + left of the direction A → B.
    Along-track: (X − A) · (B − A) / |B − A|.
    """
    ax, ay = route.a_enu_m[0], route.a_enu_m[1]
    ux, uy = route.b_enu_m[0] - ax, route.b_enu_m[1] - ay
    n = math.hypot(ux, uy)
    rx, ry = pos_enu_m[0] - ax, pos_enu_m[1] - ay
    return (ux * ry - uy * rx) / n, (ux * rx + uy * ry) / n


def mag_heading(b_nt, roll_rad: float, pitch_rad: float, declination_rad: float = 0.0) -> float:
    """Tilt-compensated magnetometer heading (FLU body field levelled with the given roll and pitch), rad.

    b_level = Ry(−θ) Rx(φ) b;  ψ_m = atan2(b_level,y, b_level,x) + D  (magmesh.maths conventions).
    """
    cp, sp = math.cos(roll_rad), math.sin(roll_rad)
    ct, st = math.cos(pitch_rad), math.sin(pitch_rad)
    by = cp * b_nt[1] - sp * b_nt[2]
    bz = sp * b_nt[1] + cp * b_nt[2]
    bx = ct * b_nt[0] - st * bz
    return (math.atan2(by, bx) + declination_rad) % (2 * math.pi)


def wrap_pi(x: float) -> float:
    return (x + math.pi) % (2 * math.pi) - math.pi


class RunningMedian:
    """Median of the samples of the last ``window_s`` seconds (sorted list + bisect: O(n) per sample in C)."""

    def __init__(self, window_s: float):
        self.window_s = window_s
        self.clear()

    def clear(self) -> None:
        self._q: deque[tuple[float, float]] = deque()
        self._sorted: list[float] = []

    def __len__(self) -> int:
        return len(self._q)

    @property
    def oldest(self) -> float:
        return self._q[0][1]

    @property
    def newest_t_s(self) -> float | None:
        return self._q[-1][0] if self._q else None

    def push(self, t_s: float, x: float) -> float:
        self._q.append((t_s, x))
        insort(self._sorted, x)
        while t_s - self._q[0][0] > self.window_s:
            _, old = self._q.popleft()
            del self._sorted[bisect_left(self._sorted, old)]
        n = len(self._sorted)
        return self._sorted[n // 2] if n % 2 else 0.5 * (self._sorted[n // 2 - 1] + self._sorted[n // 2])


# ---- detectors --------------------------------------------------------------------------------


def _latch(raise_after_s: float, clear_hold_s: float) -> AlarmLatch:
    """A detector's alarm latch (magmesh/latch.py): raise after ``raise_after_s`` of its raise condition, clear after
    ``clear_hold_s`` of its clear condition, holds counted exactly."""
    return AlarmLatch(raise_after_s, clear_hold_s, slack_s=0.0)


class TrackDetector:
    """d > threshold on trusted GNSS (paper §3), with arming and hysteresis."""

    def __init__(self, s: TrackMonitorSettings):
        self.s = s
        self.reset()

    def reset(self) -> None:
        self.armed = False
        self.arm_since_s: float | None = None
        # raised once d has stayed above the threshold on trusted GNSS for track_persist_s; cleared once trusted
        # GNSS has shown the vehicle back below the clear level for clear_hold_s
        self.state = _latch(self.s.track_persist_s, self.s.clear_hold_s)
        self.cross_track_m: float | None = None
        self.cross_track_signed_m: float | None = None
        self.along_track_m: float | None = None
        self.cross_track_rate_m_s: float | None = None
        self.gnss_ok = False
        self.gnss_reason = "no GNSS yet"

    def gnss_quality(self, fix_type: str, num_sats: int, pdop: float, horiz_std_m: float | None) -> tuple[bool, str]:
        s = self.s
        if fix_type not in s.gnss_fix_types:
            return False, f"fix type {fix_type} is not one of {', '.join(s.gnss_fix_types)}"
        if num_sats < s.gnss_min_sats:
            return False, f"{num_sats} satellites (< {s.gnss_min_sats})"
        if pdop > s.gnss_max_pdop:
            return False, f"PDOP {pdop:.1f} (> {s.gnss_max_pdop:g})"
        if horiz_std_m is not None and horiz_std_m > s.gnss_max_horiz_std_m:
            return False, f"stated accuracy {horiz_std_m:.2f} m (> {s.gnss_max_horiz_std_m:g} m)"
        return True, "ok"

    def update(self, route: Route, t_s: float, pos_enu_m, vel_enu_m_s, gnss_ok: bool, gnss_reason: str,
               ) -> list[AlarmEvent]:
        s = self.s
        d_signed, along = cross_track(route, pos_enu_m)
        d = abs(d_signed)
        ux = (route.b_enu_m[0] - route.a_enu_m[0]) / route.length_m
        uy = (route.b_enu_m[1] - route.a_enu_m[1]) / route.length_m
        self.cross_track_m, self.cross_track_signed_m, self.along_track_m = d, d_signed, along
        self.cross_track_rate_m_s = ux * vel_enu_m_s[1] - uy * vel_enu_m_s[0]
        self.gnss_ok, self.gnss_reason = gnss_ok, gnss_reason
        on_leg = -s.route_margin_m <= along <= route.length_m + s.route_margin_m
        events: list[AlarmEvent] = []
        if not self.armed:
            if gnss_ok and on_leg and d < s.arm_within_m:
                if self.arm_since_s is None:
                    self.arm_since_s = t_s
                self.armed = t_s - self.arm_since_s >= s.arm_hold_s
            else:
                self.arm_since_s = None
            return events
        # raise on trusted GNSS off the line; clear only on trusted GNSS showing the vehicle back on it
        change = self.state.update(t_s, gnss_ok and d < s.track_clear_m, gnss_ok and on_leg and d > s.track_threshold_m)
        if change == "raised":
            events.append(AlarmEvent(
                "track", "raised", t_s,
                f"cross-track deviation {d:.2f} m exceeds {s.track_threshold_m:g} m on trusted GNSS "
                f"({along:.0f} m along route {route.route_id})",
                d, s.track_threshold_m, "m", "critical", t_s))
        elif change == "cleared":
            events.append(AlarmEvent(
                "track", "cleared", t_s,
                f"cross-track deviation {d:.2f} m back below {s.track_clear_m:g} m for {s.clear_hold_s:g} s",
                d, s.track_clear_m, "m", "critical", self.state.raised_t_s))
        return events


class InnovationDetector:
    """|ψ_mag − ψ_attitude| > kσ (paper §1), and the robust median + CUSUM version (module doc)."""

    def __init__(self, s: TrackMonitorSettings):
        self.s = s
        self.reset()

    def reset(self) -> None:
        s = self.s
        self.sigma_rad: float | None = s.innovation_sigma_rad or None
        self.block_sigma_rad: float | None = s.block_sigma_rad or None
        self.median_sigma_rad: float | None = s.median_sigma_rad or None
        self.learning = self.sigma_rad is None or (
            s.innovation_test == "robust" and (self.block_sigma_rad is None or self.median_sigma_rad is None))
        if self.learning:  # all are learned from the same window
            self.sigma_rad = self.block_sigma_rad = self.median_sigma_rad = None
        self.learning_samples: list[tuple[float, float, float]] = []
        self._t_first: float | None = None
        self._restart()
        # raised at once when a test fires; cleared once quiet (and not firing) for clear_hold_s
        self.state = _latch(0.0, s.clear_hold_s)
        self.innovation_rad: float | None = None
        self.test_ratio: float | None = None
        self.n_bursts = 0

    def _restart(self) -> None:
        self._window = RunningMedian(self.s.median_window_s)
        self._block_sum = 0.0
        self._block_n = 0
        self._block_t0: float | None = None
        self.block_mean_rad: float | None = None
        self.cusum_pos = 0.0
        self.cusum_neg = 0.0
        self._t_last: float | None = None
        self._t_prev: float | None = None
        self._recovery = 0.0
        self._gate_since_s: float | None = None
        self._burst_t0: float | None = None
        self.burst_s = 0.0
        self.median_rad: float | None = None
        self.corrected_rad: float | None = None

    # σ learning ------------------------------------------------------------------------------
    def _learn_step(self, t_s: float, e_raw: float, e: float, med: float) -> None:
        s = self.s
        if self._t_first is None:
            self._t_first = t_s
        age = t_s - self._t_first
        if age < s.warmup_s:
            return
        self.learning_samples.append((t_s, e_raw if s.innovation_test == "paper" else e, med))
        if age < s.warmup_s + s.learn_s or len(self.learning_samples) < 20:  # (a time jump ends the window early)
            return
        self.apply_sigmas(learn_sigmas(self.learning_samples, s))
        self.learning_samples = []

    def apply_sigmas(self, sig: dict) -> None:
        """Use σ values (from :func:`learn_sigmas`, a previous flight or the settings) and start testing."""
        self.sigma_rad = sig["innovation_sigma_rad"]
        self.median_sigma_rad = sig["median_sigma_rad"]
        self.block_sigma_rad = sig["block_sigma_rad"]
        self.learning = False

    # update ------------------------------------------------------------------------------------
    def update(self, t_s: float, heading_rad: float, mag_heading_rad: float) -> list[AlarmEvent]:
        s = self.s
        e = wrap_pi(mag_heading_rad - heading_rad)  # innovation, rad
        self.innovation_rad = e
        if self._t_last is not None and t_s - self._t_last > s.max_attitude_gap_s:
            self._restart()
        self._t_last = t_s
        # burst excision: a sample that jumps away from the recent median by more than the burst gate is
        # left out, and the pull it gave the flight controller's filter (dψ̂ = k e dt) is modelled and removed
        # from the following samples while the filter recovers (dD/dt = −k D), so the recovery is not
        # mistaken for a disturbance. A jump that lasts burst_max_s is a step: it raises the alarm.
        dt = 0.0 if self._t_prev is None else max(0.0, t_s - self._t_prev)
        self._t_prev = t_s
        kf = s.fc_mag_gain_per_s
        if dt > 0 and kf > 0:
            self._recovery *= math.exp(-kf * dt)
        ec = e + self._recovery
        gate = s.burst_min_rad if self.sigma_rad is None else max(s.burst_min_rad, s.burst_sigma * self.sigma_rad)
        step_fired = False
        if self.median_rad is not None and abs(ec - self.median_rad) > gate:
            if self._burst_t0 is None:
                self._burst_t0 = t_s
                self.n_bursts += 1
            self._recovery += kf * e * dt
            self.burst_s = t_s - self._burst_t0
            step_fired = self.burst_s >= s.burst_max_s
            x = ec if step_fired else self.median_rad
        else:
            self._burst_t0 = None
            self.burst_s = 0.0
            x = ec
        self.corrected_rad = ec
        # running median over the window
        med = self._window.push(t_s, x)
        self.median_rad = med
        e = x
        if self._t_first is None:
            self._t_first = t_s
        if self.learning:
            self._learn_step(t_s, self.innovation_rad, e, med)
            return []
        if t_s - self._t_first < s.warmup_s:
            return []
        sigma, k = self.sigma_rad, s.innovation_k_sigma
        events: list[AlarmEvent] = []
        if s.innovation_test == "paper":
            e = self.innovation_rad  # the paper's test sees every sample as it is
            level = abs(e)
            thr, clear_thr = k * sigma, s.innovation_clear_sigma * sigma
            fired = level > thr
            quiet = level < s.innovation_clear_sigma * sigma
            detail = f"heading innovation {math.degrees(e):+.2f}° exceeds {k:g}σ = {math.degrees(k * sigma):.2f}°"
            self.test_ratio = level / (k * sigma)
        else:
            msig = self.median_sigma_rad
            k = s.median_k_sigma
            # CUSUM on block means of the Huber-clipped innovation
            c = s.clip_sigma * sigma
            if self._block_t0 is None:
                self._block_t0 = t_s
            self._block_sum += min(c, max(-c, e))
            self._block_n += 1
            block_done = t_s - self._block_t0 >= s.block_s - 1e-9
            if block_done:
                m = self._block_sum / self._block_n
                self.block_mean_rad = m
                z = m / self.block_sigma_rad
                self.cusum_pos = max(0.0, self.cusum_pos + z - s.cusum_drift)
                self.cusum_neg = max(0.0, self.cusum_neg - z - s.cusum_drift)
                self._block_sum, self._block_n, self._block_t0 = 0.0, 0, None
            g = max(self.cusum_pos, self.cusum_neg)
            if abs(med) > k * msig:
                if self._gate_since_s is None:
                    self._gate_since_s = t_s
            else:
                self._gate_since_s = None
            # continuing condition: the median stays beyond the gate for gate_persist_s
            gate_fired = self._gate_since_s is not None and t_s - self._gate_since_s >= s.gate_persist_s - 1e-9
            cusum_fired = g > s.cusum_threshold
            fired = gate_fired or cusum_fired or step_fired
            self.test_ratio = max(abs(med) / (k * msig), g / s.cusum_threshold)
            bm = self.block_mean_rad
            quiet = abs(med) < s.innovation_clear_sigma * msig and (
                bm is None or abs(bm) < s.innovation_clear_sigma * self.block_sigma_rad)
            level = abs(med)
            thr, clear_thr = k * msig, s.innovation_clear_sigma * msig
            if step_fired and not gate_fired:
                detail = (f"the magnetometer heading jumped by {math.degrees(e - self._window.oldest):+.2f}° "
                          f"and stayed there {self.burst_s:.2f} s")
            elif gate_fired:
                detail = (f"median heading innovation {math.degrees(med):+.2f}° exceeds {k:g}σ = "
                          f"{math.degrees(k * msig):.2f}°")
            else:
                detail = (f"persistent heading innovation (CUSUM {g:.1f} > {s.cusum_threshold:g} block σ; "
                          f"last block mean {math.degrees(bm or 0.0):+.2f}°)")
        change = self.state.update(t_s, quiet and not fired, fired)
        if change == "raised":
            events.append(AlarmEvent("heading_innovation", "raised", t_s,
                                     f"{detail}: the magnetometer heading disagrees with the attitude",
                                     math.degrees(level), math.degrees(thr), "deg", "warning", t_s))
        elif change == "cleared":
            events.append(AlarmEvent("heading_innovation", "cleared", t_s,
                                     f"heading innovation back within {s.innovation_clear_sigma:g}σ for "
                                     f"{s.clear_hold_s:g} s", math.degrees(level),
                                     math.degrees(clear_thr), "deg", "warning",
                                     self.state.raised_t_s))
            self.cusum_pos = self.cusum_neg = 0.0
        return events


class FieldStrengthMonitor:
    """|B| at the magnetometer against its undisturbed reference (the field-strength error Δm of §1).

    The paper leaves field strength out of its alarms because the motors modulate |B| on a multirotor; here
    it only decides when a disturbance is over: the combined verdict is held while the running median of
    |B| is more than max(k·σ, ``field_min_dev_nt``) from the reference learned on undisturbed flight.
    """

    def __init__(self, s: TrackMonitorSettings):
        self.s = s
        self.reset()

    def reset(self) -> None:
        s = self.s
        self.ref_nt: float | None = s.field_ref_nt or None
        self.sigma_nt: float | None = s.field_sigma_nt or None
        self.learning = self.ref_nt is None or self.sigma_nt is None
        if self.learning:
            self.ref_nt = self.sigma_nt = None
        self.learning_samples: list[float] = []
        self._t_first: float | None = None
        self._window = RunningMedian(self.s.field_window_s)
        self.field_nt: float | None = None
        self.median_nt: float | None = None
        self.deviation_nt: float | None = None
        self.deviating = False

    def apply(self, ref_nt: float, sigma_nt: float) -> None:
        self.ref_nt, self.sigma_nt, self.learning = float(ref_nt), max(float(sigma_nt), 1.0), False

    @property
    def gate_nt(self) -> float | None:
        return None if self.sigma_nt is None else max(self.s.field_k_sigma * self.sigma_nt, self.s.field_min_dev_nt)

    def update(self, t_s: float, b_nt) -> None:
        s = self.s
        f = math.sqrt(b_nt[0] ** 2 + b_nt[1] ** 2 + b_nt[2] ** 2)
        self.field_nt = f
        last = self._window.newest_t_s
        if last is not None and t_s - last > s.max_attitude_gap_s:
            self._window.clear()
        med = self._window.push(t_s, f)
        self.median_nt = med
        if self._t_first is None:
            self._t_first = t_s
        age = t_s - self._t_first
        if self.learning:
            if age >= s.warmup_s:
                self.learning_samples.append(med)
            if age >= s.warmup_s + s.learn_s and len(self.learning_samples) >= 20:
                x = np.asarray(self.learning_samples)
                self.apply(float(np.median(x)), float(np.std(x)))
                self.learning_samples = []
            return
        self.deviation_nt = med - self.ref_nt
        self.deviating = abs(self.deviation_nt) > self.gate_nt


def learn_sigmas(samples: list, s: TrackMonitorSettings) -> dict:
    """σ of the heading innovation on undisturbed flight, from ``(t_s, e, running median)`` samples.

    ``innovation_sigma_rad``: spread of e (paper: standard deviation; robust test: 1.4826·MAD of the
    burst-excised e); ``median_sigma_rad``: standard deviation of the running median (the gated statistic);
    ``block_sigma_rad``: standard deviation of block means of e clipped at ±clip_sigma·σ. Samples may pool
    several flights (time gaps between them only shift block boundaries).
    """
    if len(samples) < 20:
        raise ValueError(f"need at least 20 innovation samples to learn σ, got {len(samples)}")
    t = np.asarray([v[0] for v in samples])
    x = np.asarray([v[1] for v in samples])
    meds = np.asarray([v[2] for v in samples])
    if s.innovation_test == "paper":
        sigma = float(np.std(x))  # the paper's σ: spread of the heading difference on undisturbed flight
    else:
        sigma = float(1.4826 * np.median(np.abs(x - np.median(x))))  # robust to bursts
    sigma = max(sigma, s.sigma_floor_rad)
    steps = np.diff(t)
    dt = float(np.median(steps[steps > 0])) if np.any(steps > 0) else s.block_s
    per_block = max(1, int(round(s.block_s / dt)))
    clipped = np.clip(x, -s.clip_sigma * sigma, s.clip_sigma * sigma)
    nb = len(clipped) // per_block
    means = clipped[: nb * per_block].reshape(nb, per_block).mean(axis=1)
    return {
        "innovation_sigma_rad": sigma,
        "median_sigma_rad": max(float(np.std(meds)), s.sigma_floor_rad),
        "block_sigma_rad": max(float(np.std(means)), s.sigma_floor_rad / 4) if nb >= 4 else sigma,
        "n_samples": int(len(x)),
    }


# ---- the monitor ------------------------------------------------------------------------------


@dataclass
class TrackMonitor:
    """Track, heading-innovation and combined magnetic-anomaly detectors of one vehicle."""

    settings: TrackMonitorSettings = field(default_factory=TrackMonitorSettings)

    def __post_init__(self) -> None:
        self.track = TrackDetector(self.settings)
        self.innovation = InnovationDetector(self.settings)
        self.field = FieldStrengthMonitor(self.settings)
        self.reset()

    def reset(self) -> None:
        self.route: Route | None = None
        self.track.reset()
        self.innovation.reset()
        self.field.reset()
        # raised by the first detector that raises; cleared once both are quiet (and |B| back) for the hold
        self.anomaly = _latch(0.0, self.settings.anomaly_clear_hold_s)
        self.anomaly_source: str | None = None
        self.t_s: float | None = None
        self.n_gnss = 0
        self.n_attitude = 0
        self.n_gnss_untrusted = 0
        self.n_mag = 0

    def set_route(self, a_enu_m, b_enu_m, route_id: str) -> None:
        """A new planned line: the track detector re-arms (alarms already raised stay until cleared)."""
        new = Route(tuple(float(x) for x in a_enu_m), tuple(float(x) for x in b_enu_m), str(route_id))
        if new.length_m < 1e-6:
            raise ValueError(f"route {route_id!r} has A == B")
        if self.route != new:
            self.route = new
            self.track.armed = False
            self.track.arm_since_s = None

    def update_gnss(self, t_s: float, pos_enu_m, vel_enu_m_s, fix_type: str, num_sats: int, pdop: float,
                    horiz_std_m: float | None = None) -> list[AlarmEvent]:
        self.t_s = t_s
        self.n_gnss += 1
        ok, why = self.track.gnss_quality(fix_type, num_sats, pdop, horiz_std_m)
        if not ok:
            self.n_gnss_untrusted += 1
        if self.route is None:
            self.track.gnss_ok, self.track.gnss_reason = ok, why
            return []
        events = self.track.update(self.route, t_s, pos_enu_m, vel_enu_m_s, ok, why)
        return self._combine(events, t_s)

    def update_attitude(self, t_s: float, heading_rad: float, mag_heading_rad: float | None) -> list[AlarmEvent]:
        self.t_s = t_s
        self.n_attitude += 1
        if mag_heading_rad is None:
            return self._combine([], t_s)
        return self._combine(self.innovation.update(t_s, heading_rad, mag_heading_rad), t_s)

    def update_mag(self, t_s: float, b_nt) -> list[AlarmEvent]:
        """A magnetometer sample (body frame, nT): field strength, used to hold the combined verdict."""
        self.n_mag += 1
        self.field.update(t_s, b_nt)
        return self._combine([], t_s) if self.anomaly.raised else []

    def _combine(self, events: list[AlarmEvent], t_s: float) -> list[AlarmEvent]:
        """The combined verdict: raised by the first detector that raises; held until both are quiet and
        the field strength (when known) is back at its undisturbed reference."""
        s = self.settings
        out = list(events)
        first = next((ev for ev in events if ev.state == "raised"), None)
        quiet = not self.track.state.raised and not self.innovation.state.raised and not self.field.deviating
        change = self.anomaly.update(t_s, quiet, first is not None)
        if change == "raised":
            self.anomaly_source = first.source
            name = "track deviation" if first.source == "track" else "heading innovation"
            out.append(AlarmEvent("mag_anomaly", "raised", t_s,
                                  f"magnetic anomaly: the {name} detector fired first ({first.reason})",
                                  first.value, first.threshold, first.unit, "critical", t_s))
        elif change == "cleared":
            fs = "" if self.field.learning else ", field strength back at its reference"
            out.append(AlarmEvent("mag_anomaly", "cleared", t_s,
                                  f"magnetic anomaly cleared: track and heading innovation quiet{fs} for "
                                  f"{s.anomaly_clear_hold_s:g} s (raised by {self.anomaly_source})",
                                  None, None, "", "critical", self.anomaly.raised_t_s))
            self.anomaly_source = None
        return out

    # ---- outputs ------------------------------------------------------------------------------
    @property
    def internal_states(self) -> dict:
        tr, inn = self.track, self.innovation
        return {
            "cross_track_m": tr.cross_track_m,
            "along_track_m": tr.along_track_m,
            "cross_track_rate_m_s": tr.cross_track_rate_m_s,
            "progress_frac": (tr.along_track_m / self.route.length_m
                              if self.route is not None and tr.along_track_m is not None else None),
            "heading_innovation_rad": inn.innovation_rad,
            "innovation_median_rad": inn.median_rad,
            "innovation_sigma_rad": inn.sigma_rad,
            "median_sigma_rad": inn.median_sigma_rad,
            "block_sigma_rad": inn.block_sigma_rad,
            "cusum": max(inn.cusum_pos, inn.cusum_neg),
            "corrected_innovation_rad": inn.corrected_rad,
            "bursts": inn.n_bursts,
            "innovation_test_ratio": inn.test_ratio,
            "gnss_reason": tr.gnss_reason,
            "field_nt": self.field.median_nt,
            "field_ref_nt": self.field.ref_nt,
            "field_deviation_nt": self.field.deviation_nt,
        }

    @property
    def flags(self) -> dict:
        return {
            "route_known": self.route is not None,
            "track_armed": self.track.armed,
            "gnss_ok": self.track.gnss_ok,
            "learning": self.innovation.learning,
            "track_alarm": self.track.state.raised,
            "innovation_alarm": self.innovation.state.raised,
            "anomaly_alarm": self.anomaly.raised,
            "field_learning": self.field.learning,
            "field_deviating": self.field.deviating,
        }
