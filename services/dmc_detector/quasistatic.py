"""Quasi-static magnetic field detection for a vehicle with one magnetometer (docs/methods.md#quasi-static).

Pure numpy; never imports zenoh. Liu et al. (AIRCAS): over a sliding window of length L the field is
quasi-static (Earth field + the vehicle's own, i.e. trustworthy for heading) when

    var(m_x), var(m_y), var(m_z) < var_initial       and      |Δψ_m − Δψ_g| < Δψ_initial

with Δψ_m the heading change over the window from the magnetometer and Δψ_g the same change from
the gyro. The paper's settings: open road var_initial = 0.8 µT², Δψ_initial = 0.5°; garage 8 µT², 2°.

In a car the body-frame components change whenever the car turns, so the component variance test
fails in every turn whatever the field. ``variance_of = "magnitude"`` (the default here) tests the
variance of the compensated field strength |h| instead, which turning does not change; ``"components"``
is the paper's form. The gyro heading rate is the rate about the body's up axis, dψ/dt = −ω_z (FLU,
heading clockwise), consistent with the level magnetometer heading it is compared with.

Added here: the field-strength test |Δm| = ||h| − R| < ``dm_threshold_nt`` of §1, which catches a
disturbance that stays constant while the vehicle stands in it (quasi-static, but wrong);
``dm_threshold_nt = 0`` gives the paper's two tests alone.

Input pairing is by time: a magnetometer epoch is decided once the gyro stream has reached its time
(or fell ``max_imu_lag_s`` behind, then the epoch is decided with the gyro data there is and counted).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from magmesh import maths
from magmesh.magcal import MagParams

from .core import (
    TEST_NAMES,
    AlarmLatch,
    Decision,
    FeatureTracker,
    HysteresisSettings,
    ThresholdDetectorSettings,
    compass_heading,
    reason_sentence,
    test_ratios,
    test_value_and_threshold,
)


@dataclass(frozen=True)
class QuasiStaticSettings:
    window_s: float = 1.0  # sliding window L
    var_threshold_nt2: float = 0.8e6  # var_initial (0.8 µT² = 0.8e6 nT²)
    dpsi_threshold_deg: float = 2.5  # Δψ_initial (the paper: 0.5 open road, 2 garage; a car leaning in turns needs 2.5)
    variance_of: str = "magnitude"  # "magnitude" (|h|) or "components" (the paper's m_x, m_y, m_z)
    dm_threshold_nt: float = 1500.0  # added test |Δm| = ||h| − R| < this; 0 switches it off (the paper)
    level: str = "body"  # "body": a near-level vehicle (ψ̇ = −ω_z, level compass); "accel": levelled by the accelerometer
    max_imu_lag_s: float = 10.0  # decide a magnetometer epoch without gyro data after this much sample time
    hysteresis: HysteresisSettings = HysteresisSettings()

    def __post_init__(self):
        if not 0 < self.window_s <= 60:
            raise ValueError(f"window_s must be in (0, 60] s, got {self.window_s}")
        if not (self.var_threshold_nt2 > 0 and self.dpsi_threshold_deg > 0):
            raise ValueError("var_threshold_nt2 and dpsi_threshold_deg must be positive")
        if self.level not in ("body", "accel"):
            raise ValueError(f"level must be 'body' or 'accel', got {self.level!r}")
        if self.dm_threshold_nt < 0:
            raise ValueError("dm_threshold_nt must be ≥ 0 (0: off)")
        if self.variance_of not in ("magnitude", "components"):
            raise ValueError(f"variance_of must be 'magnitude' or 'components', got {self.variance_of!r}")


class QuasiStaticDetector:
    """Per vehicle. ``add_imu`` per IMU sample, ``add_mag`` per magnetometer sample → decisions."""

    impl = "quasistatic"

    def __init__(self, settings: QuasiStaticSettings | None = None):
        self.settings = settings or QuasiStaticSettings()
        self.latch = AlarmLatch(self.settings.hysteresis)
        self.reset()

    def reset(self):
        self._gyro: deque[tuple[float, float, np.ndarray]] = deque()  # (t, integrated gyro heading ψ_g, accel)
        self._psi_g = 0.0
        self._last_imu: tuple[float, float] | None = None  # (t, heading rate)
        self._mag: deque[tuple[float, np.ndarray, float, float]] = deque()  # (t, h, |h|−R, ψ_m) in window
        self._pending: deque = deque()  # mag epochs waiting for the gyro
        self.latch.reset()
        self.last: Decision | None = None
        self.n_imu_lagged = 0

    def restart_features(self):
        self._mag.clear()

    # ---- inputs ---------------------------------------------------------------------------
    def add_imu(self, t_s: float, gyro_rad_s, accel_m_s2) -> list[Decision]:
        w = np.asarray(gyro_rad_s, float)
        a = np.asarray(accel_m_s2, float)
        if self.settings.level == "accel":
            # rate about the measured up direction (a board or phone turned every way)
            na = float(np.linalg.norm(a))
            rate = -float(w @ (a / na)) if na > 1.0 else -float(w[2])
        else:
            # rate about the body's up axis: a near-level vehicle, like the level compass heading it is
            # compared with (the accelerometer's "up" tilts with the centripetal acceleration of every
            # turn and would mis-scale the rate by several per cent)
            rate = -float(w[2])
        if self._last_imu is not None and t_s > self._last_imu[0]:
            t0, r0 = self._last_imu
            if t_s - t0 < 1.0:
                self._psi_g += 0.5 * (r0 + rate) * (t_s - t0)  # trapezoid
        self._last_imu = (t_s, rate)
        self._gyro.append((t_s, self._psi_g, a))
        horizon = t_s - self.settings.window_s - self.settings.max_imu_lag_s - 1.0
        while len(self._gyro) > 2 and self._gyro[1][0] < horizon:
            self._gyro.popleft()
        return self._drain(t_s)

    def add_mag(self, t_s: float, b_nt, params: MagParams, declination_rad: float = 0.0) -> list[Decision]:
        h = params.apply(b_nt)
        self._pending.append((t_s, h, float(params.strength(h) - params.field_radius_nt), declination_rad))
        imu_t = self._last_imu[0] if self._last_imu else -math.inf
        return self._drain(imu_t, mag_t=t_s)

    def _drain(self, imu_t: float, mag_t: float | None = None) -> list[Decision]:
        out = []
        while self._pending:
            t = self._pending[0][0]
            lagged = mag_t is not None and mag_t - t > self.settings.max_imu_lag_s
            if t > imu_t and not lagged:
                break
            if t > imu_t:
                self.n_imu_lagged += 1
            out.append(self._decide(*self._pending.popleft()))
        return out

    def _psi_g_at(self, t: float) -> float | None:
        g = self._gyro
        if not g or t < g[0][0]:
            return None
        ts = [x[0] for x in g]
        i = int(np.searchsorted(ts, t))
        if i >= len(g):
            return g[-1][1]
        if ts[i] == t or i == 0:
            return g[i][1]
        (t0, p0, _), (t1, p1, _) = g[i - 1], g[i]
        return p0 + (p1 - p0) * (t - t0) / (t1 - t0)

    def _accel_at(self, t: float) -> np.ndarray | None:
        """The newest accelerometer sample at or before t (else the oldest kept)."""
        best = None
        for tg, _, a in self._gyro:
            if tg > t:
                break
            best = a
        if best is None and self._gyro:
            best = self._gyro[0][2]
        return best

    # ---- the test -------------------------------------------------------------------------
    def _decide(self, t_s: float, h: np.ndarray, dm: float, declination_rad: float) -> Decision:
        s = self.settings
        acc = self._accel_at(t_s) if s.level == "accel" else None
        if acc is not None and np.linalg.norm(acc) > 1.0:
            psi_m = float(maths.tilt_compensated_heading(h, acc, declination_rad))
        else:
            psi_m = float(compass_heading(h, declination_rad))
        if self._mag and t_s <= self._mag[-1][0]:
            self._mag.clear()
        self._mag.append((t_s, h, dm, psi_m))
        while self._mag and self._mag[0][0] < t_s - s.window_s:
            self._mag.popleft()
        full = t_s - self._mag[0][0] >= 0.9 * s.window_s and len(self._mag) >= 3
        if s.variance_of == "magnitude":
            var = float(np.var([x[2] for x in self._mag]))
        else:
            var = float(np.max(np.var(np.array([x[1] for x in self._mag]), axis=0)))
        dpsi = 0.0
        t0 = self._mag[0][0]
        g0, g1 = self._psi_g_at(t0), self._psi_g_at(t_s)
        if full and g0 is not None and g1 is not None:
            dpsi_m = float(maths.angle_diff(psi_m, self._mag[0][3]))
            dpsi = float(maths.wrap_pi(dpsi_m - (g1 - g0)))
        ratios = {"var": var / s.var_threshold_nt2 if full else 0.0,
                  "dpsi": abs(math.degrees(dpsi)) / s.dpsi_threshold_deg}
        if s.dm_threshold_nt > 0:
            ratios["dm"] = abs(dm) / s.dm_threshold_nt
        failed = tuple(sorted((k for k, v in ratios.items() if v >= 1.0), key=lambda k: -ratios[k]))
        valid = not failed
        transition = self.latch.update(t_s, valid)
        self.last = Decision(t_s=t_s, dm_nt=[dm, 0.0], ddm_nt_s=[0.0, 0.0], dh_rad=dpsi, ddh_rad_s=0.0,
                             heading_rad=psi_m, stage1_pass=valid, credibility=1.0 if valid else 0.0, valid=valid,
                             ready=full, ratios=ratios, failed=failed, transition=transition)
        return self.last

    def describe(self, d: Decision) -> tuple[str, float | None, float | None, str]:
        s = self.settings
        if d.transition == "cleared" or not d.failed:
            return reason_sentence((), {}, {}), None, None, ""
        limits = {"var": (d.ratios["var"] * s.var_threshold_nt2, s.var_threshold_nt2, "nT²"),
                  "dpsi": (d.ratios["dpsi"] * s.dpsi_threshold_deg, s.dpsi_threshold_deg, "deg"),
                  "dm": (d.ratios.get("dm", 0.0) * s.dm_threshold_nt, s.dm_threshold_nt, "nT")}
        reason = reason_sentence(d.failed, d.ratios, {k: limits[k][:2] for k in d.failed})
        return (reason, *limits[d.failed[0]])

    @property
    def internal_states(self) -> dict:
        d = self.last
        return {"imu_lagged_epochs": self.n_imu_lagged, **({"ratios": d.ratios} if d else {})}

    @property
    def flags(self) -> dict:
        d = self.last
        return {"alarm_raised": self.latch.raised, "valid": bool(d and d.valid), "warming": bool(d is None or not d.ready)}


# ---- second stage of the DMC: the heading checked against the gyro's --------------------------

#: how the reference heading is carried: pulled towards each trusted epoch, or fitted to many (GyroTrackSettings)
REFERENCES = ("blend", "consensus")


@dataclass(frozen=True)
class GyroTrackSettings:
    """A DMC second stage of magmesh's own: the compass heading is checked against a reference heading carried
    by the gyro from the last trusted compass headings (docs/methods.md#dmc-gyro-track). Units in the names."""

    gate_deg: float = 4.0  # valid when |ψ_compass − ψ_ref| < this
    blend_tau_s: float = 5.0  # ψ_ref is pulled towards trusted compass headings with this time constant
    bias_tau_s: float = 300.0  # and the gyro's bias corrected with this one
    reseed_after_s: float = 20.0  # stage 1 passing yet disagreeing this long: ψ_ref taken from the compass again
    reacquire_after_s: float = 2.0  # … or this long while the tight tests below pass too
    reacquire_dm_nt: float = 400.0  # tight field-strength test |Δm| (the paper's tightest set, 40 units)
    reacquire_dh_deg: float = 3.0  # tight heading-difference test |Δh| (its tightest set)
    bias_init_s: float = 2.0  # gyro bias: median rate over the first seconds of the record (the vehicle at rest)
    trust_dm_nt: float = 600.0  # a trusted epoch's pull on ψ_ref and b is 1 / (1 + (|Δm|/this)² + (|Δh|/trust_dh_deg)²)
    trust_dh_deg: float = 2.0
    max_gyro_gap_s: float = 0.5  # gyro samples further apart (shed, lost, a stalled stream): ψ_ref is lost, seeded again
    max_init_bias_rad_s: float = 0.01  # the rest window's median rate is the bias only when the vehicle stood still:
    # |median| below this (0.57 °/s, above a MEMS gyro's bias) and the rates' spread below half of it; else 0
    # how ψ_ref is carried (docs/methods.md#dmc-gyro-track): "blend" pulls it towards each trusted compass heading
    # (the settings above); "consensus" fits it to the stage-1 epochs of the last consensus_window_s, robustly (the
    # settings below; blend_tau_s, bias_tau_s, reseed/reacquire and trust_* are the blend's only)
    reference: str = "blend"
    consensus_window_s: float = 250.0  # ψ_m − ψ_g of the stage-1 epochs this far back make up the fit: a line in t
    consensus_recent_s: float = 150.0  # a lost fit is found again among the stage-1 epochs this recent
    consensus_scale_deg: float = 1.5  # Tukey biweight scale of the fit: epochs further off than this have no weight
    consensus_inlier_deg: float = 1.0  # an epoch within this of the line supports it …
    consensus_min_support: int = 6  # … and a line with fewer supporters is lost (nothing valid until found again)
    consensus_bias_prior_deg_s: float = 0.05  # the line's slope (the gyro's bias) is held to its start by this 1-σ
    consensus_bin_s: float = 0.5  # the fit keeps one stage-1 epoch per this much time (bounded work per epoch)

    def __post_init__(self):
        for name in ("gate_deg", "blend_tau_s", "bias_tau_s", "reseed_after_s", "reacquire_after_s",
                     "reacquire_dm_nt", "reacquire_dh_deg", "trust_dm_nt", "trust_dh_deg", "max_gyro_gap_s",
                     "max_init_bias_rad_s", "consensus_window_s", "consensus_recent_s", "consensus_scale_deg",
                     "consensus_inlier_deg", "consensus_bias_prior_deg_s"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not 0 < self.gate_deg < 90:
            raise ValueError(f"gate_deg must be in (0, 90), got {self.gate_deg}")
        if not self.bias_init_s >= 0:
            raise ValueError(f"bias_init_s must be ≥ 0, got {self.bias_init_s}")
        if self.reference not in REFERENCES:
            raise ValueError(f"reference must be one of {', '.join(REFERENCES)}, got {self.reference!r}")
        if not (isinstance(self.consensus_min_support, int) and self.consensus_min_support >= 2):
            raise ValueError(f"consensus_min_support must be an integer ≥ 2, got {self.consensus_min_support!r}")
        if not (self.consensus_bin_s >= 0 and math.isfinite(self.consensus_bin_s)):
            raise ValueError(f"consensus_bin_s must be ≥ 0, got {self.consensus_bin_s!r}")
        if self.consensus_recent_s > self.consensus_window_s:
            raise ValueError(f"consensus_recent_s ({self.consensus_recent_s}) must not exceed consensus_window_s "
                             f"({self.consensus_window_s})")


@dataclass
class GyroTrackResult:
    valid: np.ndarray  # N bool
    ref_heading_rad: np.ndarray  # N: ψ_ref after the epoch (nan before the first trusted epoch)
    innovation_rad: np.ndarray  # N: ψ_compass − ψ_ref (predicted), wrapped to (−π, π]
    trusted: np.ndarray  # N bool: stage 1 passed and the heading agreed (ψ_ref learned from it)
    reseeds: int


class GyroTrack:
    """The second stage's state for one vehicle, one epoch per :meth:`step` (``gyro_track_batch`` runs the same
    steps over a recording, ``GyroTrackDetector`` one by one as the epochs arrive): the reference heading ψ_ref,
    the gyro bias b and the disagreement clocks. ``bias_rad_s``: b to start from (the rate at rest)."""

    def __init__(self, settings: GyroTrackSettings | None = None, bias_rad_s: float = 0.0):
        self.settings = settings or GyroTrackSettings()
        self.bias_rad_s = float(bias_rad_s)
        self.est: float | None = None  # ψ_ref (rad, unwrapped), None before the first stage-1 pass
        self.reseeds = 0
        self.lost = 0  # epochs at which ψ_ref was lost to a gap in the gyro (seeded again from the compass)
        self._prev: tuple[float, float] | None = None  # (t, ψ_g) of the previous epoch
        self._disagree_s = self._tight_s = 0.0
        self._gate = math.radians(self.settings.gate_deg)
        self._fit = OffsetConsensus(self.settings) if self.settings.reference == "consensus" else None

    def step(self, t_s: float, psi_m_rad: float, psi_g_rad: float, stage1: bool, dm_nt: float,
             dh_deg: float, gyro_ok: bool = True) -> tuple[bool, bool, float, float]:
        """One epoch: compass heading ψ_m, gyro heading ψ_g (unwrapped, any origin) at t_s, the stage-1 verdict,
        the worse compass's |Δm| and |Δh| in degrees → (valid, trusted, innovation ψ_m − ψ_ref (rad), ψ_ref (rad;
        nan before the first stage-1 pass)). ``gyro_ok`` false: the gyro does not cover the time since the
        previous epoch (a gap, or not there yet): ψ_ref is lost, and this epoch is judged as the first one."""
        if self._fit is not None:
            return self._step_consensus(float(t_s), float(psi_m_rad), float(psi_g_rad), bool(stage1), gyro_ok)
        s = self.settings
        t, pg = float(t_s), float(psi_g_rad)
        prev, self._prev = self._prev, (t, pg)
        if not gyro_ok and self.est is not None:
            self.est = None
            self._disagree_s = self._tight_s = 0.0
            self.lost += 1
        if self.est is None:
            if stage1:
                self.est = float(psi_m_rad)
                return True, True, 0.0, self.est
            return False, False, 0.0, math.nan
        dt = t - prev[0]
        est = self.est + (pg - prev[1]) - self.bias_rad_s * dt
        nu = math.remainder(float(psi_m_rad) - est, 2.0 * math.pi)
        agree = abs(nu) < self._gate
        trusted = False
        if stage1 and agree:
            trusted = True
            w = 1.0 / (1.0 + (dm_nt / s.trust_dm_nt) ** 2 + (dh_deg / s.trust_dh_deg) ** 2)
            est += min(dt / s.blend_tau_s, 1.0) * w * nu
            self.bias_rad_s -= dt / s.bias_tau_s * w * nu
            self._disagree_s = self._tight_s = 0.0
        elif stage1:
            self._disagree_s += dt
            tight = dm_nt < s.reacquire_dm_nt and dh_deg < s.reacquire_dh_deg
            self._tight_s = self._tight_s + dt if tight else 0.0
            if self._disagree_s >= s.reseed_after_s or self._tight_s >= s.reacquire_after_s:
                est = float(psi_m_rad)
                self._disagree_s = self._tight_s = 0.0
                self.reseeds += 1
        else:
            self._tight_s = 0.0
        self.est = est
        return agree, trusted, nu, est

    def _step_consensus(self, t: float, psi_m: float, pg: float, stage1: bool, gyro_ok: bool):
        """The "consensus" reference: ψ_ref = ψ_g + the line fitted to ψ_m − ψ_g of recent stage-1 epochs."""
        fit = self._fit
        if self._prev is None:  # the slope's prior: the bias the record started with (a live detector sets it late)
            fit.slope0 = fit.slope = -self.bias_rad_s
        self._prev = (t, pg)
        if not gyro_ok and (fit.n or fit.offset is not None):  # ψ_g jumps across a gap: the fit no longer holds
            fit.clear()
            self.lost += 1
        had = fit.offset is not None
        offset = fit.step(t, math.remainder(psi_m - pg, 2.0 * math.pi), stage1)
        self.bias_rad_s = -fit.slope
        if offset is None:
            self.est = None
            return False, False, 0.0, math.nan
        self.reseeds += had and fit.found_again
        est = pg + offset
        nu = math.remainder(psi_m - est, 2.0 * math.pi)
        agree = abs(nu) < self._gate
        self.est = est
        return agree, stage1 and agree, nu, est


class OffsetConsensus:
    """The offset c = ψ_m − ψ_g between compass and gyro headings, fitted over the stage-1 epochs of the last
    ``consensus_window_s`` as a line c(t) = offset + slope · (t − now) (the slope: minus the gyro's bias) by
    iteratively re-weighted least squares with Tukey's biweight (scale ``consensus_scale_deg``) and a Gaussian prior
    on the slope. Undisturbed epochs agree on one line; disturbed ones that stage 1 let through scatter about it
    (a source's bend differs from one approach to the next), so they carry little or no weight. When fewer than
    ``consensus_min_support`` epochs lie within ``consensus_inlier_deg`` of the line it is found again: the offset
    the most recent stage-1 epochs agree on most (a mode search over ``consensus_recent_s``). Pure numpy, one
    :meth:`step` per epoch, bounded work (one epoch per ``consensus_bin_s`` kept)."""

    ITERATIONS = 3
    #: the slope prior's weight is λ = (this / its 1-σ)²: a slope one σ off its start costs as much as one epoch 1° off
    PRIOR_RESIDUAL_RAD = math.radians(1.0)

    def __init__(self, settings: GyroTrackSettings):
        s = settings
        self.window_s, self.recent_s, self.bin_s = s.consensus_window_s, s.consensus_recent_s, s.consensus_bin_s
        self.k = math.radians(s.consensus_scale_deg)
        self.h = math.radians(s.consensus_inlier_deg)
        self.min_support = s.consensus_min_support
        self.lam = (self.PRIOR_RESIDUAL_RAD / math.radians(s.consensus_bias_prior_deg_s)) ** 2
        self.slope0 = self.slope = 0.0  # the slope's prior and its fit (GyroTrack sets both from the bias at rest)
        self._t: deque[float] = deque()
        self._c: deque[float] = deque()
        self.offset: float | None = None  # at the last step's time
        self._t_last: float | None = None
        self.found_again = False  # the last step had to find the line again

    @property
    def n(self) -> int:
        return len(self._t)

    def clear(self):
        self._t.clear()
        self._c.clear()
        self.offset = None

    def _residuals(self, ts, cs) -> np.ndarray:
        return maths.wrap_pi(cs - self.offset - self.slope * ts)

    def _support(self, ts, cs) -> int:
        return int(np.count_nonzero(np.abs(self._residuals(ts, cs)) < self.h))

    def step(self, t: float, c: float, stage1: bool) -> float | None:
        """One epoch at t with offset c (rad) and its stage-1 verdict → the fitted offset at t (None: no line)."""
        self.found_again = False
        if self.offset is not None and self._t_last is not None:
            self.offset += self.slope * (t - self._t_last)
        self._t_last = t
        if stage1 and not (self._t and self.bin_s > 0 and t // self.bin_s == self._t[-1] // self.bin_s):
            self._t.append(t)
            self._c.append(c)
        while self._t and self._t[0] < t - self.window_s:
            self._t.popleft()
            self._c.popleft()
        if len(self._t) < self.min_support:
            self.offset = None
            return None
        ts = np.fromiter(self._t, float, len(self._t)) - t
        cs = np.fromiter(self._c, float, len(self._c))
        if self.offset is None or self._support(ts, cs) < self.min_support:
            if not self._find(ts, cs):
                self.offset = None
                return None
            self.found_again = True
        for _ in range(self.ITERATIONS):
            r = self._residuals(ts, cs)
            u = r / self.k
            w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
            sw = float(w.sum())
            if sw <= 0.0:
                break
            swt, swtt = float(w @ ts), float(w @ (ts * ts))
            det = sw * (swtt + self.lam) - swt * swt
            if det <= 0.0:
                break
            ra, rb = float(w @ r), float(w @ (r * ts)) - self.lam * (self.slope - self.slope0)
            self.offset += ((swtt + self.lam) * ra - swt * rb) / det
            self.slope += (sw * rb - swt * ra) / det
        if self._support(ts, cs) < self.min_support:
            self.offset = None
            return None
        return self.offset

    def _find(self, ts, cs) -> bool:
        """The offset most recent stage-1 epochs agree on (within consensus_inlier_deg, the current slope): the
        epoch with the most such neighbours (the latest on a tie) sets it."""
        rec = ts > -self.recent_s
        tr, cr = ts[rec], cs[rec]
        if tr.size < self.min_support:
            return False
        d = cr[:, None] - cr[None, :] - self.slope * (tr[:, None] - tr[None, :])
        near = np.abs(maths.wrap_pi(d)) < self.h
        cnt = near.sum(axis=1)
        j = int(np.flatnonzero(cnt == cnt.max())[-1])
        if cnt[j] < self.min_support:
            return False
        self.offset = float(cr[j] - self.slope * tr[j])
        return True


def gyro_heading(t_gyro_s, gyro_rad_s, t_s) -> np.ndarray:
    """Gyro heading ψ_g (rad, unwrapped, 0 at the first gyro sample) at times t_s: the trapezoid integral of
    dψ/dt = −ω_z (a near-level vehicle, FLU body axes, heading clockwise), interpolated."""
    tg = np.asarray(t_gyro_s, float)
    rate = -np.asarray(gyro_rad_s, float)[:, 2]
    psi = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tg))])
    return np.interp(np.asarray(t_s, float), tg, psi)


def initial_bias(rates_rad_s, settings: GyroTrackSettings) -> float:
    """The gyro's bias to start from: the median of −ω_z over the rest window, if the vehicle stood still then (the
    median within ``max_init_bias_rad_s`` and the median absolute deviation within half of it); else 0 (a stream
    joined while the car turned would take its turn rate for a bias and carry the heading off)."""
    r = np.asarray(rates_rad_s, float)
    if not r.size:
        return 0.0
    m = float(np.median(r))
    lim = settings.max_init_bias_rad_s
    return m if abs(m) <= lim and float(np.median(np.abs(r - m))) <= 0.5 * lim else 0.0


def gyro_covers(t_gyro_s, t_s, max_gap_s: float) -> np.ndarray:
    """Per epoch: whether the gyro covers the time since the previous epoch — no two gyro samples further apart than
    ``max_gap_s`` in (t_{i−1}, t_i], and t_i within the gyro's samples (the first epoch: within them)."""
    tg = np.asarray(t_gyro_s, float)
    t = np.asarray(t_s, float)
    ok = (t >= tg[0]) & (t <= tg[-1]) if tg.size else np.zeros(t.size, bool)
    for j in np.flatnonzero(np.diff(tg) > max_gap_s).tolist():
        a, b = tg[j], tg[j + 1]
        lo = int(np.searchsorted(t, a, side="right"))  # t_i > a
        hi = int(np.searchsorted(t, b, side="left"))  # t_{i−1} < b  ⇔  i ≤ hi
        ok[lo:min(hi, t.size - 1) + 1] = False
    return ok


def gyro_track_batch(f, stage1, t_gyro_s, gyro_rad_s, settings: GyroTrackSettings | None = None) -> GyroTrackResult:
    """Second stage over a recording, causal (epoch i depends on epochs ≤ i and the gyro up to t_i).

    ``f``: DMC features (core.Features) of the paired epochs; ``stage1``: the stage-1 verdict per epoch (bool N).
    ψ_ref is propagated by the gyro between epochs, ψ_ref += Δψ_g − b·Δt. An epoch is *valid* when its compass
    heading lies within ``gate_deg`` of ψ_ref, whether stage 1 passed or not: a strong field that leaves the
    heading right is no reason to drop it, and one that bends the heading without changing the strength is
    caught. Only epochs that pass stage 1 *and* agree are *trusted*: ψ_ref and the bias b learn from them
    (first-order blends, ``blend_tau_s`` and ``bias_tau_s``), each with the weight
    w = 1 / (1 + (|Δm|/``trust_dm_nt``)² + (|Δh|/``trust_dh_deg``)²), so that a field already a little off (a bend
    creeping in as a bus draws alongside) barely moves ψ_ref: the adaptive magnetometer noise of Liu et al.
    (R inflated when the field looks disturbed), as a weight. When stage 1 passes while the heading disagrees
    for ``reseed_after_s`` (the gyro has drifted away), or for ``reacquire_after_s`` with the tight |Δm| and
    |Δh| tests passing too, ψ_ref is re-seeded from the compass. Before the first stage-1 pass nothing is valid."""
    s = settings or GyroTrackSettings()
    t = np.asarray(f.t_s, float)
    n = t.size
    psi_m = np.asarray(f.heading_rad, float)
    stage1 = np.asarray(stage1, bool)
    dm = np.max(np.abs(f.dm_nt), axis=-1)
    dh = np.degrees(np.abs(f.dh_rad))
    tg = np.asarray(t_gyro_s, float)
    if tg.size < 2 or np.asarray(gyro_rad_s).shape != (tg.size, 3):
        raise ValueError(f"gyro_track_batch needs ≥ 2 gyro samples as t (n,) and rates (n, 3), got {tg.shape} and "
                         f"{np.asarray(gyro_rad_s).shape}")
    pg = gyro_heading(tg, gyro_rad_s, t)
    still = tg < tg[0] + s.bias_init_s
    track = GyroTrack(s, initial_bias(-np.asarray(gyro_rad_s, float)[still, 2], s))
    valid = np.zeros(n, bool)
    trusted = np.zeros(n, bool)
    ref = np.full(n, np.nan)
    innov = np.zeros(n)
    ok = gyro_covers(tg, t, s.max_gyro_gap_s)
    step = track.step
    for i in range(n):
        valid[i], trusted[i], innov[i], ref[i] = step(t[i], psi_m[i], pg[i], stage1[i], dm[i], dh[i], ok[i])
    return GyroTrackResult(valid, np.mod(ref, 2.0 * math.pi), innov, trusted, track.reseeds)


@dataclass(frozen=True)
class GyroTrackDetectorSettings:
    """The live ``gyro_track`` detector: stage 1 (the four threshold tests), then :class:`GyroTrackSettings`."""

    stage1: ThresholdDetectorSettings = ThresholdDetectorSettings()
    track: GyroTrackSettings = GyroTrackSettings()
    max_imu_lag_s: float = 10.0  # an epoch is decided without the gyro reaching it after this much sample time

    def __post_init__(self):
        if not (self.max_imu_lag_s > 0 and math.isfinite(self.max_imu_lag_s)):
            raise ValueError(f"max_imu_lag_s must be a positive finite number, got {self.max_imu_lag_s!r}")


class GyroTrackDetector:
    """The DMC thresholds, then the compass heading checked against a heading the gyro carries (the second stage
    of :func:`gyro_track_batch`, epoch by epoch). Per vehicle: ``add_imu`` per IMU sample, ``update`` per paired
    compass epoch; each returns the decisions it could make. An epoch waits until the gyro has reached its time
    (and the gyro's bias at rest is known, ``bias_init_s`` after the first gyro sample); one still waiting
    ``max_imu_lag_s`` of compass time later is decided with the gyro data there is and counted
    (``imu_lagged_epochs``). The decisions are those of ``gyro_track_batch`` over the same epochs and gyro."""

    impl = "gyro_track"

    def __init__(self, settings: GyroTrackDetectorSettings | None = None):
        self.settings = settings or GyroTrackDetectorSettings()
        self.latch = AlarmLatch(self.settings.stage1.hysteresis)
        self.tracker = FeatureTracker(self.settings.stage1.features)
        self.reset()

    def reset(self):
        self.tracker.reset()
        self.latch.reset()
        self.track = GyroTrack(self.settings.track)
        self._gt: list[float] = []  # gyro sample times, and ψ_g there (trapezoid integral of −ω_z): the
        self._gp: list[float] = []  # newest max_imu_lag_s + 1 s of them, for epochs that arrive after the gyro
        self._last_rate: tuple[float, float] | None = None  # (t, −ω_z) of the newest gyro sample
        self._psi_g = 0.0
        self._bias_until: float | None = None  # the rest window's end (first gyro t + bias_init_s)
        self._rest_rates: list[float] | None = []  # −ω_z in the rest window; None once the bias is set
        self._trimmed = False
        self._gyro_gaps: deque[tuple[float, float]] = deque()  # (a, b): consecutive gyro samples further apart
        self._first_gyro_t: float | None = None
        self._prev_uncovered = False
        self._pending: deque = deque()  # (features, stage-1 ratios) of epochs waiting for the gyro
        self.last: Decision | None = None
        self.n_imu_lagged = 0

    def restart_features(self):
        """Parameters changed: the feature windows restart; ψ_ref, the bias and the alarm keep their state."""
        self.tracker.reset()

    # ---- inputs ---------------------------------------------------------------------------
    def add_imu(self, t_s: float, gyro_rad_s, accel_m_s2=None) -> list[Decision]:
        t = float(t_s)
        rate = -float(gyro_rad_s[2])
        if self._last_rate is not None:
            t0, r0 = self._last_rate
            if t <= t0:
                return []  # not newer than the last sample: the integral only runs forward
            self._psi_g += 0.5 * (r0 + rate) * (t - t0)
            if t - t0 > self.settings.track.max_gyro_gap_s:
                self._gyro_gaps.append((t0, t))
        else:
            self._first_gyro_t = t
        self._last_rate = (t, rate)
        self._gt.append(t)
        self._gp.append(self._psi_g)
        if self._bias_until is None:
            self._bias_until = t + self.settings.track.bias_init_s
        if self._rest_rates is not None:
            if t < self._bias_until:
                self._rest_rates.append(rate)
            else:
                self.track.bias_rad_s = initial_bias(self._rest_rates, self.settings.track)
                self._rest_rates = None
        out = self._drain()
        self._trim()
        return out

    def update(self, t_s: float, b1_nt, b2_nt, p1: MagParams, p2: MagParams,
               declination_rad: float = 0.0) -> list[Decision]:
        f = self.tracker.update(t_s, b1_nt, b2_nt, p1, p2, declination_rad)
        ratios = dict(zip(TEST_NAMES, (float(x) for x in test_ratios(f, self.settings.stage1.thresholds)[0]),
                          strict=True))
        self._pending.append((f, ratios))
        return self._drain(mag_t=float(t_s))

    def _drain(self, mag_t: float | None = None) -> list[Decision]:
        out = []
        ready_t = self._gt[-1] if self._gt and self._rest_rates is None else -math.inf
        while self._pending:
            t = float(self._pending[0][0].t_s[0])
            if t > ready_t:
                if mag_t is None or mag_t - t <= self.settings.max_imu_lag_s:
                    break
                self.n_imu_lagged += 1
            out.append(self._decide(*self._pending.popleft()))
        return out

    def _trim(self):
        """Forget gyro samples older than max_imu_lag_s + 1 s before the newest (and before any waiting epoch)."""
        horizon = self._gt[-1] - self.settings.max_imu_lag_s - 1.0
        if self._pending:
            horizon = min(horizon, float(self._pending[0][0].t_s[0]))
        i = bisect.bisect_left(self._gt, horizon) - 1  # keep the sample before the horizon
        if i > 256 and i > len(self._gt) // 2:  # in chunks: a list's front is cheap to cut only now and then
            del self._gt[:i], self._gp[:i]
            self._trimmed = True

    def _psi_g_at(self, t: float) -> float:
        """ψ_g at t, linear between gyro samples, held beyond them (np.interp's rule, as the batch form). An epoch
        older than the samples kept is counted with the lagged ones."""
        gt, gp = self._gt, self._gp
        if not gt:
            return 0.0
        if t >= gt[-1]:
            return gp[-1]
        i = bisect.bisect_left(gt, t)
        if i == 0:
            self.n_imu_lagged += t < gt[0] and self._trimmed  # before the samples kept (not before the first)
            return gp[0]
        if gt[i] == t:
            return gp[i]
        t0, t1 = gt[i - 1], gt[i]
        return gp[i - 1] + (gp[i] - gp[i - 1]) * (t - t0) / (t1 - t0)

    def _gyro_covers(self, t: float) -> bool:
        """Whether the gyro covers (previous epoch, t] (as :func:`gyro_covers` over a whole recording). An epoch
        decided without it (the gyro not there yet: ``max_imu_lag_s``) left no gyro heading to go on from, so the
        next one is not covered either."""
        covered = self._covers(t)
        ok = covered and not self._prev_uncovered
        self._prev_uncovered = not covered
        return ok

    def _covers(self, t: float) -> bool:
        if self._first_gyro_t is None or t < self._first_gyro_t or t > self._gt[-1] or \
                (self._trimmed and t < self._gt[0]):
            return False
        tp = self.track._prev[0] if self.track._prev is not None else -math.inf
        gaps = self._gyro_gaps
        while gaps and gaps[0][1] <= tp:  # (epochs come in time order: a gap ended before the last one is done)
            gaps.popleft()
        return not any(a < t and b > tp for a, b in gaps)

    # ---- the decision ---------------------------------------------------------------------
    def _decide(self, f, ratios: dict) -> Decision:
        tr = self.settings.track
        t = float(f.t_s[0])
        stage1 = all(v < 1.0 for v in ratios.values())
        dm = float(np.max(np.abs(f.dm_nt[0])))
        dh = abs(math.degrees(float(f.dh_rad[0])))
        valid, _trusted, nu, _ref = self.track.step(t, float(f.heading_rad[0]), self._psi_g_at(t), stage1, dm, dh,
                                                    self._gyro_covers(t))
        ratios = dict(ratios)
        if self.track.est is not None:
            ratios["track"] = abs(math.degrees(nu)) / tr.gate_deg
        failed = () if valid else tuple(sorted((k for k, v in ratios.items() if v >= 1.0), key=lambda k: -ratios[k]))
        credibility = max(0.0, 1.0 - ratios["track"]) if "track" in ratios else 0.0
        transition = self.latch.update(t, valid)
        self.last = Decision(
            t_s=t, dm_nt=[float(x) for x in f.dm_nt[0]], ddm_nt_s=[float(x) for x in f.ddm_nt_s[0]],
            dh_rad=float(f.dh_rad[0]), ddh_rad_s=float(f.ddh_rad_s[0]), heading_rad=float(f.heading_rad[0]),
            stage1_pass=stage1, credibility=credibility if valid else min(credibility, 0.5), valid=bool(valid),
            ready=bool(f.rates_ready[0]) and self.track.est is not None, ratios=ratios, failed=failed,
            transition=transition)
        return self.last

    def describe(self, d: Decision) -> tuple[str, float | None, float | None, str]:
        """(reason, value, threshold, unit) for an alarm transition at decision ``d``."""
        if d.transition == "cleared" or not d.failed:
            return reason_sentence((), {}, {}), None, None, ""
        th, gate = self.settings.stage1.thresholds, self.settings.track.gate_deg

        def vt(name: str) -> tuple[float, float, str]:
            if name == "track":
                return d.ratios[name] * gate, gate, "deg"
            return test_value_and_threshold(name, d.ratios[name], th)

        units = {n: vt(n)[:2] for n in d.failed}
        return (reason_sentence(d.failed, d.ratios, units), *vt(d.failed[0]))

    @property
    def internal_states(self) -> dict:
        d = self.last
        out = {"imu_lagged_epochs": self.n_imu_lagged, "reseeds": self.track.reseeds, "lost_to_gyro_gaps": self.track.lost,
               "gyro_bias_rad_s": self.track.bias_rad_s,
               "ref_heading_rad": None if self.track.est is None else math.remainder(self.track.est, 2 * math.pi)}
        return {**out, **({"ratios": d.ratios} if d else {})}

    @property
    def flags(self) -> dict:
        d = self.last
        return {"alarm_raised": self.latch.raised, "valid": bool(d and d.valid), "warming": bool(d is None or not d.ready)}
