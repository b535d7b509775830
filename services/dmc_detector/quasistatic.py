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

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from magmesh import maths
from magmesh.magcal import MagParams

from .core import AlarmLatch, Decision, HysteresisSettings, compass_heading, reason_sentence


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

    def __post_init__(self):
        for name in ("gate_deg", "blend_tau_s", "bias_tau_s", "reseed_after_s", "reacquire_after_s",
                     "reacquire_dm_nt", "reacquire_dh_deg", "trust_dm_nt", "trust_dh_deg"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not 0 < self.gate_deg < 90:
            raise ValueError(f"gate_deg must be in (0, 90), got {self.gate_deg}")
        if not self.bias_init_s >= 0:
            raise ValueError(f"bias_init_s must be ≥ 0, got {self.bias_init_s}")


@dataclass
class GyroTrackResult:
    valid: np.ndarray  # N bool
    ref_heading_rad: np.ndarray  # N: ψ_ref after the epoch (nan before the first trusted epoch)
    innovation_rad: np.ndarray  # N: ψ_compass − ψ_ref (predicted), wrapped to (−π, π]
    trusted: np.ndarray  # N bool: stage 1 passed and the heading agreed (ψ_ref learned from it)
    reseeds: int


def gyro_heading(t_gyro_s, gyro_rad_s, t_s) -> np.ndarray:
    """Gyro heading ψ_g (rad, unwrapped, 0 at the first gyro sample) at times t_s: the trapezoid integral of
    dψ/dt = −ω_z (a near-level vehicle, FLU body axes, heading clockwise), interpolated."""
    tg = np.asarray(t_gyro_s, float)
    rate = -np.asarray(gyro_rad_s, float)[:, 2]
    psi = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tg))])
    return np.interp(np.asarray(t_s, float), tg, psi)


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
    tight = (dm < s.reacquire_dm_nt) & (dh < s.reacquire_dh_deg)
    weight = 1.0 / (1.0 + (dm / s.trust_dm_nt) ** 2 + (dh / s.trust_dh_deg) ** 2)
    tg = np.asarray(t_gyro_s, float)
    if tg.size < 2 or np.asarray(gyro_rad_s).shape != (tg.size, 3):
        raise ValueError(f"gyro_track_batch needs ≥ 2 gyro samples as t (n,) and rates (n, 3), got {tg.shape} and "
                         f"{np.asarray(gyro_rad_s).shape}")
    pg = gyro_heading(tg, gyro_rad_s, t)
    still = tg < tg[0] + s.bias_init_s
    b = float(np.median(-np.asarray(gyro_rad_s, float)[still, 2])) if still.any() else 0.0
    valid = np.zeros(n, bool)
    trusted = np.zeros(n, bool)
    ref = np.full(n, np.nan)
    innov = np.zeros(n)
    gate = math.radians(s.gate_deg)
    est: float | None = None
    disagree_s = tight_s = 0.0
    reseeds = 0
    for i in range(n):
        if est is None:
            if stage1[i]:
                est = float(psi_m[i])
                valid[i] = trusted[i] = True
                ref[i] = est
            continue
        dt = t[i] - t[i - 1]
        est += (pg[i] - pg[i - 1]) - b * dt
        nu = math.remainder(psi_m[i] - est, 2.0 * math.pi)
        innov[i] = nu
        agree = abs(nu) < gate
        valid[i] = agree
        if stage1[i] and agree:
            trusted[i] = True
            est += min(dt / s.blend_tau_s, 1.0) * weight[i] * nu
            b -= dt / s.bias_tau_s * weight[i] * nu
            disagree_s = tight_s = 0.0
        elif stage1[i]:
            disagree_s += dt
            tight_s = tight_s + dt if tight[i] else 0.0
            if disagree_s >= s.reseed_after_s or tight_s >= s.reacquire_after_s:
                est = float(psi_m[i])
                disagree_s = tight_s = 0.0
                reseeds += 1
        else:
            tight_s = 0.0
        ref[i] = est
    return GyroTrackResult(valid, np.mod(ref, 2.0 * math.pi), innov, trusted, reseeds)
