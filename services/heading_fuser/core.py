"""Heading fuser core: an error-state quaternion EKF AHRS with adaptive magnetometer noise, a gyro
fallback while the magnetic heading is invalid, and a guarded re-acquisition of the magnetic heading.

Pure numpy; never imports zenoh. Usable on its own::

    f = HeadingFilter(Settings(declination_rad=0.05))
    for gyro, accel, mag in samples:
        f.update(gyro, accel, mag, dt_s=0.01)          # mag may be None (no sample this step)
        heading, pitch, roll = f.euler()

Method (docs/methods.md#heading, Liu et al.; #dmc, Hao et al.):

* Attitude quaternion ``q`` (body FLU → ENU) propagated with the bias-corrected gyro,
  ``q_{k+1} = q_k ⊗ exp(½ (ω − b_g) T)`` — the closed form of §2's ``(I + T/2 · Ω(ω)) q`` (eq. 2.1).
  The filter is written in error-state (multiplicative) form: the EKF state is the small body-frame
  rotation error ``δθ`` and the gyro bias ``b_g`` (6 states), the standard way to keep the quaternion
  unit-norm and the covariance 3-dimensional in attitude.
* Accelerometer update: measured gravity direction against ``Rᵀ e_up`` (eq. 2.2), with the noise
  inflated by the deviation of |a| from g and skipped beyond ``accel_rejection_m_s2``.
* Magnetometer update: the paper fuses the field vector; this filter fuses the field's **heading**
  only — the azimuth of the field rotated into ENU by the current attitude against the declination —
  so that a disturbed magnetometer can never tilt the attitude (the practice of PX4 ekf2 and x-io Fusion).
  The tilt uncertainty that leaks into that azimuth (∝ tan of the field inclination) is added to the
  measurement variance (eq. 2.3).
* Quasi-static field detection (§2): over a sliding window of ``quasi_static_window_s`` the field is
  quasi-static when the variance of its strength stays below ``quasi_static_var_nt2`` **and** the
  heading change seen by the magnetometer agrees with the gyro's within ``quasi_static_heading_rad``.
  The paper tests the variance of the body-frame components, which any turn of the vehicle fails; the
  strength and the field's dip are invariant to the vehicle's own rotation, so this filter tests them
  instead (the strength variance and the dip variance).
* Adaptive magnetometer noise (§2, reconstructed): ``R_m = R_m0`` when quasi-static, else
  ``R_m = k · R_m0`` with ``k1`` (variance test failed) or ``k2`` (heading-change test failed).
* Absolute field consistency: strength and dip against the reference field (given, or learned at
  alignment); a field off by more than the tolerances is not fused at all.
* Innovation gate (PX4 style): test ratio ``ν² / (gate² · S)``; a sample above 1 is not fused.
* DMC switching (§1): while the differential compass says the magnetic heading is invalid the filter
  runs on the gyro alone (mode ``gyro_only``); when it clears, mode ``recovering``.
* Guarded re-acquisition (improvement over PX4/ArduPilot yaw resets): in ``recovering`` the
  magnetometer must be consistent (strength, dip, quasi-static) for ``recovery_hold_s`` before it may
  steer the heading, and then only at most ``recovery_slew_rad_s`` while its innovation is outside
  the gate: never a sudden yaw jump towards a field that may still be disturbed. Back to ``magnetic``
  once the innovation has been inside the gate for ``recovery_hold_s`` — counted from the clear of the
  disturbance (``agreement_from_clear``: during the clear hold the magnetometer is watched, not fused).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, fields

import numpy as np

from magmesh import maths

log = logging.getLogger("magmesh.heading_fuser.core")

MODES = ("initialising", "magnetic", "gyro_only", "recovering")
_EYE6 = np.eye(6)


@dataclass(frozen=True)
class Settings:
    """Filter settings. Units in the names; ranges checked in ``__post_init__``.

    Defaults suit a road vehicle (automotive MEMS IMU at ~100 Hz, calibrated magnetometer at ~50 Hz);
    ``bench/heading_broad.broad_settings`` shows the values for a handheld board.
    """

    # process noise
    gyro_noise_rad_s_rt_hz: float = 0.0005  # angle random walk density (plus model error), rad/s/√Hz
    gyro_rate_noise_frac_rt_hz: float = 0.0  # extra rate noise ∝ |ω| (scale-factor/misalignment), 1/√Hz
    gyro_bias_walk_rad_s2_rt_hz: float = 5e-5  # bias random walk density, rad/s²/√Hz
    gyro_bias_init_std_rad_s: float = 0.01  # initial 1-σ gyro bias
    # initial attitude uncertainty
    init_tilt_std_rad: float = 0.05
    init_heading_std_rad: float = 0.2
    init_duration_s: float = 1.0  # average accel + mag over this long before aligning (0: first sample)
    # accelerometer
    accel_noise_m_s2: float = 1.0  # 1-σ of the gravity direction, as specific force
    accel_noise_per_rate_m_s2_per_rad_s: float = 10.0  # accel σ grows with |ω| (lever arm, centripetal)
    accel_rejection_m_s2: float = 2.0  # skip the accel update when ||a| − g| exceeds this
    accel_update_period_s: float = 0.0  # at most one accel update per this period (0: every sample)
    # gravity under linear acceleration: the accelerometer low-passed in the gyro-integrated
    # (inertial) frame, where gravity is constant and a bounded motion's acceleration averages out
    gravity_lpf_tau_s: float = 0.0  # its time constant (0: the raw accelerometer is gravity)
    gravity_lpf_noise_m_s2: float = 0.3  # 1-σ of that estimate as specific force
    gravity_lpf_order: int = 1  # 1: first-order low-pass; 2: second-order Butterworth of the same time constant
    gravity_lpf_in_estimate: bool = False  # low-pass in the frame of the filter's own attitude (VQF's), not the gyro's
    # (VQF's: −40 dB/decade, a 1 Hz back-and-forth acceleration attenuated ~9× more than by the first-order one)
    # rest detection (gyro and accelerometer quiet): then the accelerometer is gravity, and the gyro's
    # zero rate observes its bias; the sensor noise is learned online while at rest
    rest_detection: bool = False
    rest_gyro_rad_s: float = 0.035  # low-passed |ω| below this (2°/s) ...
    rest_accel_m_s2: float = 0.5  # ... and |a − low-passed a| below this ...
    rest_min_s: float = 1.5  # ... for this long: at rest
    rest_filter_tau_s: float = 0.5  # the low-pass of that test
    rest_accel_noise_m_s2: float = 0.1  # accelerometer 1-σ at rest (prior; learned online)
    rest_gyro_noise_rad_s: float = 0.005  # per-sample gyro 1-σ at rest (prior; learned online)
    # magnetometer
    mag_noise_nt: float = 150.0  # 1-σ per axis of the (calibrated) field
    mag_heading_noise_floor_rad: float = 0.01  # floor on the heading-measurement σ
    mag_gate_sigma: float = 5.0  # innovation gate, standard deviations (PX4 EKF2_MAG_GATE)
    mag_update_period_s: float = 0.0  # at most one mag update per this period (0: every sample)
    mag_delay_s: float = 0.0  # the magnetometer's lag behind the gyro (see estimate_mag_delay_s)
    mag_delay_online: bool = False  # estimate that lag causally from gyro + magnetometer (MagLagEstimator)
    mag_delay_max_s: float = 0.05  # the largest lag considered
    declination_rad: float = 0.0  # magnetic declination, east positive
    ref_field_nt: float = 0.0  # reference field strength (0: learn at alignment)
    ref_dip_rad: float = float("nan")  # reference dip, down positive (nan: learn at alignment)
    field_strength_tol_frac: float = 0.03  # window-mean |(|m| − B0)| / B0 above this: disturbed
    field_dip_tol_rad: float = 0.06  # window-mean |dip − dip0| above this: disturbed (3.4°)
    sample_strength_tol_frac: float = 0.15  # one sample this far off is not fused
    sample_dip_tol_rad: float = 0.26  # one sample this far off is not fused (15°)
    use_field_check: bool = True
    mag_vector_fusion: bool = True  # fuse the whole field direction when it passes every check
    # quasi-static detection and adaptive noise (§2)
    adaptive_noise: bool = True
    quasi_static_window_s: float = 1.0
    quasi_static_var_nt2: float = 0.8e6  # the paper's var_initial = 0.8 µT²
    quasi_static_dip_var_rad2: float = 3e-4  # dip variance limit, rad² (≈ 1° σ)
    quasi_static_heading_rad: float = 0.035  # the paper's Δψ_initial, ≈ 2°
    adaptive_gain_variance: float = 200.0  # k1
    adaptive_gain_heading: float = 150.0  # k2
    # DMC switching and recovery (§1)
    use_dmc: bool = True
    clear_hold_s: float = 1.0  # disturbance must be absent this long before leaving gyro_only
    recovery_hold_s: float = 2.0  # consistency needed before the mag may steer; then inside the gate
    recovery_slew_rad_s: float = 0.07  # max heading correction rate while re-acquiring (≈ 4°/s)
    recovery_noise_gain: float = 10.0  # R_m multiplier while recovering
    disturbed_noise_gain: float = 0.0  # >0: in gyro_only without a DMC veto, fuse with R_m × this (weakly)
    disturbed_gate_rad: float = 0.35  # ... only innovations smaller than this
    hard_iron_tracking: bool = False  # in gyro_only without a DMC veto: track a new body-fixed magnet
    hard_iron_tau_s: float = 10.0  # its averaging time constant
    hard_iron_noise_gain: float = 10.0  # R_m multiplier for the field with the tracked magnet removed
    # ... the magnet estimated from the sensor's own rotation instead (HardIronFromRotation: the gyro-integrated
    # rotation between two field samples 0.2 s apart carries the older into the newer once the body-fixed
    # field is removed; least squares forgetting over hard_iron_tau_s), used once the rotation seen makes it
    # observable about every axis (the information matrix's smallest eigenvalue ≥ hard_iron_min_info)
    hard_iron_from_rotation: bool = False
    hard_iron_min_info: float = 2.0
    recovery_exit_rad: float = 0.035  # back to magnetic once |innovation| stays below this for recovery_hold_s
    # a gyro_only stretch that only the DMC verdict caused (the field checks never failed in it) is judged over
    # by that independent detector: both holds after it last as long as the stretch did, within
    # [min_hold_s, clear_hold_s] and [min_hold_s, recovery_hold_s] (a 0.3 s kerb-side blip does not cost 3 s)
    holds_scale_with_outage: bool = True
    min_hold_s: float = 0.2
    # the agreement test of recovering starts when the disturbance clears: during the clear hold the magnetometer's
    # heading is watched (not fused) against the gyro-held estimate, and that time counts towards the agreement hold
    # (false: it starts only once recovering has begun)
    agreement_from_clear: bool = True
    rejection_timeout_s: float = 5.0  # persistent gate rejections this long in magnetic → recovering
    # alarm
    heading_alarm_std_rad: float = 0.087  # heading σ above this while not magnetic raises the flag (5°)
    # the gravity low-pass in the estimate's own frame (gravity_lpf_in_estimate) closes a loop: a tilt correction
    # reaches the low-pass's output only with its lag (≈ gravity_lpf_tau_s = τ), so the update observes the tilt
    # error of about τ ago; with the second-order low-pass a tilt gain k (per second) above 2/τ makes the loop
    # unstable (a tilt oscillation of period ≈ 2π τ/√2 that grows), and near it barely damped. That update's noise
    # is floored so that its gain per update, on the largest horizontal tilt variance, stays at most
    # 1 − exp(−T k_max) with k_max = gravity_lpf_loop_gain / τ (T: the time since the last accelerometer update);
    # 0: no limit
    gravity_lpf_loop_gain: float = 0.0
    # the quasi-static heading test (quasi_static_heading_rad) on the field as the gyro-only attitude carries it: its
    # turn about the vertical over the window. False: the change of (magnetometer Euler yaw − integrated nav-frame yaw
    # rate), which a rotation that is not about the vertical alone moves too (that integral depends on the path)
    heading_test_gyro_frame: bool = False
    # recovering's (and the clear hold's) agreement test on the mean innovation over the hold (|mean| ≤
    # recovery_exit_rad after recovery_hold_s of usable samples), not on every sample staying inside: a magnetometer
    # whose heading noise in motion exceeds recovery_exit_rad otherwise never agrees until the sensor rests
    recovery_exit_mean: bool = False

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (bool, str)) or f.name in ("ref_dip_rad",):
                continue
            if not isinstance(v, (int, float)) or (isinstance(v, float) and math.isnan(v)):
                raise ValueError(f"setting {f.name} must be a number, got {v!r}")
            if v < 0 and f.name != "declination_rad":
                raise ValueError(f"setting {f.name} must be ≥ 0, got {v!r}")
        if self.mag_gate_sigma <= 0:
            raise ValueError(f"setting mag_gate_sigma must be > 0, got {self.mag_gate_sigma}")
        if self.quasi_static_window_s <= 0:
            raise ValueError("setting quasi_static_window_s must be > 0")
        if self.gravity_lpf_order not in (1, 2):
            raise ValueError(f"setting gravity_lpf_order must be 1 or 2, got {self.gravity_lpf_order!r}")


ATTITUDE_VAR_MAX_RAD2 = 1.0  # the attitude error's variance never grows beyond (1 rad)² per axis


@dataclass
class InternalStates:
    """Continuous diagnostics of the last update (read-only outputs, x-io Fusion style)."""

    mag_innovation_rad: float | None = None  # heading innovation of the last mag sample
    mag_innovation_var_rad2: float | None = None  # its predicted variance S
    mag_test_ratio: float | None = None  # ν² / (gate² S)
    mag_noise_gain: float = 1.0  # current adaptive multiplier on R_m
    field_strength_error_frac: float = 0.0  # (|m| − B0) / B0
    field_dip_error_rad: float = 0.0  # dip − dip0
    accel_error_m_s2: float = 0.0  # |a| − g
    time_since_mag_fused_s: float = 0.0
    gyro_only_duration_s: float = 0.0
    heading_std_rad: float = 0.0
    gyro_bias_rad_s: tuple = (0.0, 0.0, 0.0)


@dataclass
class Flags:
    """Boolean state (x-io Fusion style)."""

    initialising: bool = True
    mag_fused: bool = False  # the last magnetometer sample was used
    mag_rejected_gate: bool = False  # the last one failed the innovation gate
    field_inconsistent: bool = False  # strength or dip off the reference
    quasi_static: bool = True  # §2 window test passed
    dmc_valid: bool = True  # last DMC verdict (true when no DMC)
    accel_ignored: bool = False
    heading_uncertain: bool = False  # heading σ above heading_alarm_std_rad while not magnetic


def butterworth2(tau_s: float, dt: float) -> tuple[float, float, float, float, float]:
    """(b0, b1, b2, a1, a2) of a second-order Butterworth low-pass with time constant tau_s at step dt (VQF's
    filterCoeffs: cutoff √2 / (2π τ), bilinear transform); y = b0 x + s0, s0 ← b1 x − a1 y + s1, s1 ← b2 x − a2 y."""
    fc = (math.sqrt(2.0) / (2.0 * math.pi)) / tau_s
    c = math.tan(math.pi * fc * dt)
    d = c * c + math.sqrt(2.0) * c + 1.0
    b0 = c * c / d
    return b0, 2.0 * b0, b0, 2.0 * (c * c - 1.0) / d, (1.0 - math.sqrt(2.0) * c + c * c) / d


def min_eig_sym3(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float) -> float:
    """Smallest eigenvalue of a symmetric 3×3 matrix (closed form; the compiled filter uses the same)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) * (a00 - q) + (a11 - q) * (a11 - q) + (a22 - q) * (a22 - q) + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p == 0.0:
        return q
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = max(-1.0, min(1.0, r))
    return q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)


class HardIronFromRotation:
    """A body-fixed field (a magnet that moves with the sensor) from the sensor's rotation alone.

    Field samples are kept one per ``spacing_s``; each new one is paired with the oldest kept one at least
    0.8 ``baseline_s`` older. With ``M`` the gyro-integrated rotation between their times, a constant field
    seen from the turning body satisfies ``m₁ − h = M (m₀ − h)``, so ``(I − M) h = m₁ − M m₀``: the normal
    equations are accumulated with forgetting over ``tau_s`` (pairs that turned less than ``min_turn_rad``
    only decay them). ``h`` is observable about the axes the body turned about: :meth:`estimate` gives it once
    the smallest eigenvalue of the information matrix reaches ``min_info``, else None. A homogeneous field that
    changes (the sensor carried elsewhere) is not body-fixed and leaves ``h`` near zero.
    """

    def __init__(self, tau_s: float, min_info: float, baseline_s: float = 0.2, spacing_s: float = 0.05,
                 min_turn_rad: float = 0.05):
        self.tau_s, self.min_info = tau_s, min_info
        self.baseline_s, self.spacing_s, self.min_turn_rad = baseline_s, spacing_s, min_turn_rad
        self.A = np.zeros((3, 3))
        self.b = np.zeros(3)
        self.items: deque = deque()  # (t, m, qg)
        self._last_t = -math.inf

    def add(self, t: float, m: np.ndarray, qg: tuple) -> None:
        if t - self._last_t < self.spacing_s - 1e-9:
            return
        a = min(1.0, (t - self._last_t) / self.tau_s) if math.isfinite(self._last_t) else 0.0
        self._last_t = t
        items = self.items
        items.append((t, m, qg))
        while len(items) > 1 and items[1][0] <= t - self.baseline_s:
            items.popleft()
        t0, m0, q0 = items[0]
        if t - t0 < 0.8 * self.baseline_s:
            return
        self.A = (1.0 - a) * self.A
        self.b = (1.0 - a) * self.b
        w1, x1, y1, z1 = qg
        rel = _qmul((w1, -x1, -y1, -z1), q0)  # q₁* ⊗ q₀: M = R(q₁)ᵀ R(q₀)
        if 2.0 * math.acos(min(1.0, abs(rel[0]))) < self.min_turn_rad:
            return
        Md = _qmat(rel)
        M = np.eye(3) - Md
        r0 = m - Md @ m0
        self.A = self.A + M.T @ M
        self.b = self.b + M.T @ r0

    def estimate(self) -> np.ndarray | None:
        A = self.A
        if min_eig_sym3(A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2]) < self.min_info:
            return None
        return np.linalg.solve(A, self.b)


def _skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _quat_exp(rv0: float, rv1: float, rv2: float) -> tuple:
    a = math.sqrt(rv0 * rv0 + rv1 * rv1 + rv2 * rv2)
    if a < 1e-9:
        return 1.0, 0.5 * rv0, 0.5 * rv1, 0.5 * rv2
    s = math.sin(0.5 * a) / a
    return math.cos(0.5 * a), rv0 * s, rv1 * s, rv2 * s


def _qmul(p, q) -> tuple:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def _qmat(q) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class _Window:
    """Sliding-window sums over time for the quasi-static test (O(1) per sample)."""

    def __init__(self, length_s: float):
        self.length_s = length_s
        self.items: deque = deque()
        self.s = np.zeros(4)  # strength, strength², dip, dip²

    def add(self, t: float, strength: float, dip: float, mag_minus_gyro: float, field_g=(0.0, 0.0, 0.0)) -> None:
        self.items.append((t, strength, dip, mag_minus_gyro, field_g))
        self.s += (strength, strength * strength, dip, dip * dip)
        while self.items and t - self.items[0][0] > self.length_s:
            _, b, d, _, _ = self.items.popleft()
            self.s -= (b, b * b, d, d * d)

    def full(self, t: float) -> bool:
        return len(self.items) >= 3 and t - self.items[0][0] >= 0.8 * self.length_s

    def stats(self, nav_from_gyro: np.ndarray | None = None) -> tuple[float, float, float, float, float]:
        """(mean strength nT, strength variance nT², mean dip rad, dip variance rad², |Δψ_m − Δψ_g| rad).

        ``nav_from_gyro`` (the estimate's rotation times the gyro-only one's inverse, now): Δψ is the turn about
        the vertical, over the window, of the field as the gyro alone carries it (stored in the gyro-only frame);
        without it, the change of (magnetometer Euler yaw − integrated nav-frame yaw rate), which a rotation
        that is not about the vertical alone moves too (the integral of the vertical rate is path-dependent)."""
        n = len(self.items)
        mb, md = self.s[0] / n, self.s[2] / n
        var_b = max(0.0, self.s[1] / n - mb * mb)
        var_d = max(0.0, self.s[3] / n - md * md)
        if nav_from_gyro is None:
            # Δψ_m − Δψ_g = change over the window of (magnetometer yaw − integrated gyro yaw)
            return mb, var_b, md, var_d, abs(math.remainder(self.items[-1][3] - self.items[0][3], 2 * math.pi))
        a = nav_from_gyro[:2] @ np.asarray(self.items[0][4])
        b = nav_from_gyro[:2] @ np.asarray(self.items[-1][4])
        return mb, var_b, md, var_d, abs(math.remainder(math.atan2(b[0], b[1]) - math.atan2(a[0], a[1]), 2 * math.pi))

    def clear(self) -> None:
        self.items.clear()
        self.s[:] = 0.0


class HeadingFilter:
    """Quaternion error-state EKF AHRS with magnetic disturbance handling (see module docstring)."""

    def __init__(self, settings: Settings | None = None):
        self.settings = settings or Settings()
        self.reset()

    # ---- state --------------------------------------------------------------------------------
    def reset(self) -> None:
        s = self.settings
        self.q = (1.0, 0.0, 0.0, 0.0)  # body → ENU
        self.bias = np.zeros(3)
        self.P = np.diag([s.init_tilt_std_rad**2] * 2 + [s.init_heading_std_rad**2] + [s.gyro_bias_init_std_rad_s**2] * 3)
        self.t_s = 0.0
        self.mode = "initialising"
        self.states = InternalStates()
        self.flags = Flags()
        self.ref_field_nt = s.ref_field_nt
        self.ref_dip_rad = s.ref_dip_rad
        # alignment averages: samples rotated by the gyro into the frame of the first one, so that a
        # body turning during the averaging is aligned at the end of it, not half-way through
        self._init_q = (1.0, 0.0, 0.0, 0.0)
        self._init_acc = np.zeros(3)
        self._init_mag = np.zeros(3)
        self._init_n = [0, 0]
        self._init_t0: float | None = None
        self._window = _Window(s.quasi_static_window_s)
        self._history: deque = deque(maxlen=1024)  # (t_s, gyro-only q, gyro yaw) for late mag samples
        self._qg = (1.0, 0.0, 0.0, 0.0)  # attitude integrated from the gyro alone (never corrected)
        self._hard_iron = np.zeros(3)  # tracked extra hard iron while the field is off its reference
        self._hard_iron_t = 0.0
        self._hi_rot = HardIronFromRotation(s.hard_iron_tau_s, s.hard_iron_min_info) if s.hard_iron_from_rotation else None
        self._gyro_yaw = 0.0  # integrated gyro heading (CCW yaw), for the §2 heading-change test
        self._last_accel_t = -1e9
        self._last_mag_t = -1e9
        self._last_fused_t = 0.0
        self._mode_since_t = 0.0
        self._clear_since_t: float | None = None
        self._consistent_since_t: float | None = None
        self._inside_gate_since_t: float | None = None
        self._inside_sum, self._inside_n = 0.0, 0  # the innovations since then (recovery_exit_mean)
        self._rejected_since_t: float | None = None
        self._gyro_only_since_t: float | None = None
        self._left_magnetic_t: float | None = None  # when the filter last left magnetic mode
        self._outage_field_bad = False  # the field checks failed since the filter last entered magnetic
        self._outage_s: float | None = None  # how long ago that was, once the DMC cleared (None: full holds)
        self.transitions: list[tuple[float, str, str, str]] = []  # (t_s, from, to, reason)
        self.mag_delay_s = s.mag_delay_s
        self._lag = MagLagEstimator(s.mag_delay_max_s) if s.mag_delay_online else None
        self._acc_lp_i: np.ndarray | None = None  # accelerometer low-passed in the gyro-integrated frame
        self._acc_lp_s = (np.zeros(3), np.zeros(3))  # the second-order low-pass's two states
        self._rest_gyro_lp = [0.0, 0.0, 0.0]
        self._rest_acc_lp: list | None = None
        self._rest_since_t: float | None = None
        self.at_rest = False
        self._noise_gyro_var = s.rest_gyro_noise_rad_s**2  # learned at rest
        self._rebase_pending = False  # the field reference is to be learned again (rebase_field_reference)
        self.n_rebases = 0
        self._noise_acc_var = s.rest_accel_noise_m_s2**2

    @property
    def internal_states(self) -> InternalStates:
        return self.states

    @property
    def aligned(self) -> bool:
        return self.mode != "initialising"

    def quaternion(self) -> np.ndarray:
        return np.array(self.q)

    def euler(self) -> tuple[float, float, float]:
        """(heading, pitch, roll) in rad; heading clockwise from true north in [0, 2π)."""
        return maths.euler_from_matrix(_qmat(self.q))

    def heading_rad(self) -> float:
        w, x, y, z = self.q
        return float(maths.yaw_to_heading(math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))))

    def attitude_std(self) -> tuple[float, float, float]:
        """1-σ (heading, pitch, roll) uncertainty, rad, from the attitude covariance in ENU."""
        R = _qmat(self.q)
        Pn = R @ self.P[:3, :3] @ R.T  # nav-frame rotation-error covariance
        h = math.sqrt(max(Pn[2, 2], 0.0))
        # pitch is a rotation about the horizontal right axis, roll about the horizontal forward axis
        fwd = R[:, 0].copy()
        fwd[2] = 0.0
        n = math.hypot(fwd[0], fwd[1])
        fwd = fwd / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])
        right = np.array([fwd[1], -fwd[0], 0.0])
        return h, math.sqrt(max(right @ Pn @ right, 0.0)), math.sqrt(max(fwd @ Pn @ fwd, 0.0))

    def _agreement_add(self, t: float, nu: float) -> bool:
        """One usable innovation into the agreement hold: it starts the hold when none runs (returns False), else it
        is added to the hold's sum and count (returns True)."""
        if self._inside_gate_since_t is None:
            self._inside_gate_since_t, self._inside_sum, self._inside_n = t, nu, 1
            return False
        self._inside_sum += nu
        self._inside_n += 1
        return True

    def _hold(self, full_s: float) -> float:
        """A hold after gyro_only: ``full_s``, or, when only the DMC's verdict kept the magnetometer out, the
        time since the filter left magnetic mode (at least ``min_hold_s``)."""
        if self._outage_s is None:
            return full_s
        return min(full_s, max(self.settings.min_hold_s, self._outage_s))

    def _set_mode(self, mode: str, reason: str) -> None:
        if mode == self.mode:
            return
        log.debug("t=%.2f s: %s → %s (%s)", self.t_s, self.mode, mode, reason)
        self.transitions.append((self.t_s, self.mode, mode, reason))
        if self.mode == "magnetic":
            self._left_magnetic_t = self.t_s
            self._outage_s = None
        elif mode == "magnetic":
            self._outage_field_bad = False
        if mode == "gyro_only":
            self._gyro_only_since_t = self.t_s
        elif mode == "magnetic":
            self._gyro_only_since_t = None
            self._hard_iron = np.zeros(3)
            self._hard_iron_t = 0.0
        self.mode = mode
        self._mode_since_t = self.t_s
        self._consistent_since_t = None
        self._inside_gate_since_t = None
        self._rejected_since_t = None
        self._clear_since_t = None

    # ---- alignment ----------------------------------------------------------------------------
    def align(self, accel_m_s2, mag_nt) -> None:
        """Set the attitude from one (averaged) accel + mag pair (docs/methods.md#heading, initial attitude)."""
        up = np.asarray(accel_m_s2, float)  # pragma: no mutate (dtype: only its direction is used, in floats)
        up = up / np.linalg.norm(up)
        m = np.asarray(mag_nt, float)  # pragma: no mutate (dtype: the cross product with a float converts)
        east = np.cross(m, up)  # north × up = east
        east /= np.linalg.norm(east)
        north = np.cross(up, east)
        R_mag = np.vstack([east, north, up])  # rows: ENU axes in body → body → magnetic ENU
        q = maths.quat_from_matrix(R_mag)
        # a field of declination D (east positive) has azimuth D, so v_true = Rz(−D) v_magnetic
        qd = _quat_exp(0.0, 0.0, -self.settings.declination_rad)
        self.q = _qmul(qd, tuple(q))
        mn = _qmat(self.q) @ m
        if not self.ref_field_nt:
            self.ref_field_nt = float(np.linalg.norm(m))
        if not math.isfinite(self.ref_dip_rad):
            self.ref_dip_rad = math.atan2(-mn[2], math.hypot(mn[0], mn[1]))
        self._set_mode("magnetic", "aligned")
        self._last_fused_t = self.t_s

    # ---- the update ---------------------------------------------------------------------------
    def update(self, gyro_rad_s, accel_m_s2, mag_nt=None, dt_s: float = 0.01, dmc_valid: bool | None = None):
        """One IMU step, then the magnetometer sample if any. Returns the mode."""
        self.update_imu(gyro_rad_s, accel_m_s2, dt_s)
        if mag_nt is not None:
            self.update_mag(mag_nt, dmc_valid)
        return self.mode

    def update_imu(self, gyro_rad_s, accel_m_s2, dt_s: float, t_s: float | None = None) -> None:
        """One gyro + accelerometer step of ``dt_s``; ``t_s`` (optional) sets the filter's clock to
        the sample's own time, e.g. a stream's timestamps, which ``update_mag``'s ``t_s`` then shares."""
        s = self.settings
        self.t_s = self.t_s + dt_s if t_s is None else float(t_s)
        if self.mode == "initialising":
            if self._init_n[0] or self._init_n[1]:
                g = gyro_rad_s
                self._init_q = _qmul(self._init_q, _quat_exp(g[0] * dt_s, g[1] * dt_s, g[2] * dt_s))
            self._init_acc += _qmat(self._init_q) @ np.asarray(accel_m_s2, float)
            self._init_n[0] += 1
            return
        self._predict(gyro_rad_s, dt_s)
        self._history.append((self.t_s, self._qg, self._gyro_yaw))
        if self._lag is not None:
            self._lag.add_gyro(self.t_s, gyro_rad_s)
        rate = math.sqrt(gyro_rad_s[0] ** 2 + gyro_rad_s[1] ** 2 + gyro_rad_s[2] ** 2)
        acc = accel_m_s2  # pragma: no mutate (read only when the gravity low-pass sets it again)
        if s.rest_detection:
            self._detect_rest(gyro_rad_s, accel_m_s2, dt_s)
        if s.gravity_lpf_tau_s > 0.0:
            acc = self._gravity_lpf(accel_m_s2, dt_s)
        if self.t_s - self._last_accel_t >= s.accel_update_period_s - 1e-9:
            interval = self.t_s - self._last_accel_t
            self._last_accel_t = self.t_s
            if self.at_rest:
                self._fuse_accel(accel_m_s2, 0.0, math.sqrt(self._noise_acc_var))
                self._zero_rate(gyro_rad_s)
            elif s.gravity_lpf_tau_s > 0.0:
                loop = s.gravity_lpf_loop_gain > 0.0 and s.gravity_lpf_in_estimate
                floor = self._lpf_loop_floor(interval) if loop else 0.0
                self._fuse_accel(acc, 0.0, s.gravity_lpf_noise_m_s2, floor)
            else:
                self._fuse_accel(accel_m_s2, rate)
        st = self.states
        st.time_since_mag_fused_s = self.t_s - self._last_fused_t
        st.gyro_only_duration_s = 0.0 if self._gyro_only_since_t is None else self.t_s - self._gyro_only_since_t
        up = _qmat(self.q)[2]
        h_std = math.sqrt(max(float(up @ self.P[:3, :3] @ up), 0.0))
        st.heading_std_rad = h_std
        self.flags.heading_uncertain = self.mode != "magnetic" and h_std > s.heading_alarm_std_rad

    def _predict(self, gyro, dt: float) -> None:
        s = self.settings
        b = self.bias
        w0, w1, w2 = gyro[0] - b[0], gyro[1] - b[1], gyro[2] - b[2]
        dq = _quat_exp(w0 * dt, w1 * dt, w2 * dt)
        qg = _qmul(self._qg, dq)
        ng = math.sqrt(qg[0] * qg[0] + qg[1] * qg[1] + qg[2] * qg[2] + qg[3] * qg[3])
        self._qg = (qg[0] / ng, qg[1] / ng, qg[2] / ng, qg[3] / ng)
        q = _qmul(self.q, dq)
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        self.q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
        qw, qx, qy, qz = self.q
        # nav-frame yaw rate = third row of R times body rate (for the quasi-static heading test)
        self._gyro_yaw += ((2 * (qx * qz - qw * qy)) * w0 + (2 * (qy * qz + qw * qx)) * w1
                           + (1 - 2 * (qx * qx + qy * qy)) * w2) * dt
        # error-state transition (eq. 2.1 linearised): δθ' = (I − [ω T]×) δθ − T δb
        F = np.eye(6)
        F[:3, :3] -= _skew((w0 * dt, w1 * dt, w2 * dt))
        F[0, 3] = F[1, 4] = F[2, 5] = -dt
        P = F @ self.P @ F.T
        qg = (s.gyro_noise_rad_s_rt_hz**2 + s.gyro_rate_noise_frac_rt_hz**2 * (w0 * w0 + w1 * w1 + w2 * w2)) * dt
        qb = s.gyro_bias_walk_rad_s2_rt_hz**2 * dt
        P[0, 0] += qg
        P[1, 1] += qg
        P[2, 2] += qg
        P[3, 3] += qb
        P[4, 4] += qb
        P[5, 5] += qb
        # I − [ω T]× is no rotation: it grows P by 1 + |ω T|² per step across ω, which the updates do not hold
        # back in fast turns sampled slowly (15 rad/s at 48 Hz: ×100 per second, 1e15 rad² in a minute, then a
        # singular update); the attitude block is scaled back to ATTITUDE_VAR_MAX_RAD2 (a congruence: P stays
        # positive semi-definite)
        m = max(P[0, 0], P[1, 1], P[2, 2])
        if m > ATTITUDE_VAR_MAX_RAD2:
            k = math.sqrt(ATTITUDE_VAR_MAX_RAD2 / m)
            P[:3, :] *= k
            P[:, :3] *= k
        self.P = P

    def _inject(self, dx: np.ndarray) -> None:
        self.q = _qmul(self.q, _quat_exp(dx[0], dx[1], dx[2]))
        n = math.sqrt(sum(c * c for c in self.q))
        self.q = tuple(c / n for c in self.q)
        self.bias = self.bias + dx[3:]

    def _gravity_lpf(self, accel, dt: float) -> np.ndarray:
        """The accelerometer low-passed in the gyro-integrated frame, returned in the body frame now.

        Gravity is constant in that frame and the specific force of a bounded motion (a translation
        back and forth, a tap) averages out over ``gravity_lpf_tau_s``; the gyro's drift over that
        time is what remains (bias-corrected gyro: a few hundredths of a degree)."""
        s = self.settings
        # the gyro-only frame drifts with the gyro's scale and misalignment errors in fast turns, and the
        # average then mixes gravity seen from frames turned apart; the filter's own attitude is corrected
        # (its heading corrections turn about the vertical and leave gravity where it is)
        Rg = _qmat(self.q if s.gravity_lpf_in_estimate else self._qg)
        a_i = Rg @ np.asarray(accel, float)  # pragma: no mutate (dtype: the float matrix product converts)
        if s.gravity_lpf_order == 2:
            b0, b1, b2, a1, a2 = butterworth2(s.gravity_lpf_tau_s, dt)
            if self._acc_lp_i is None or self.at_rest:  # at rest the accelerometer is gravity: restart there
                self._acc_lp_i = a_i
                self._acc_lp_s = (a_i * (1.0 - b0), a_i * (b2 - a2))  # the states of a constant input a_i
            else:
                s0, s1 = self._acc_lp_s
                y = b0 * a_i + s0
                self._acc_lp_s = (b1 * a_i - a1 * y + s1, b2 * a_i - a2 * y)
                self._acc_lp_i = y
        elif self._acc_lp_i is None or self.at_rest:
            self._acc_lp_i = a_i  # at rest the accelerometer is gravity: restart the average there
        else:
            self._acc_lp_i = self._acc_lp_i + min(1.0, dt / s.gravity_lpf_tau_s) * (a_i - self._acc_lp_i)
        return Rg.T @ self._acc_lp_i

    def _detect_rest(self, gyro, accel, dt: float) -> None:
        """Rest: low-passed |ω| and the accelerometer's deviation from its low-pass both small for
        ``rest_min_s``. While at rest the gyro and accelerometer noise variances are learned."""
        s = self.settings
        k = min(1.0, dt / s.rest_filter_tau_s)
        gl, b = self._rest_gyro_lp, self.bias
        if self._rest_acc_lp is None:
            self._rest_acc_lp = [accel[0], accel[1], accel[2]]
        al = self._rest_acc_lp
        for i in range(3):
            gl[i] += k * (gyro[i] - gl[i])
            al[i] += k * (accel[i] - al[i])
        da0, da1, da2 = accel[0] - al[0], accel[1] - al[1], accel[2] - al[2]
        dg0, dg1, dg2 = gl[0] - b[0], gl[1] - b[1], gl[2] - b[2]
        quiet = (dg0 * dg0 + dg1 * dg1 + dg2 * dg2 < s.rest_gyro_rad_s**2
                 and da0 * da0 + da1 * da1 + da2 * da2 < s.rest_accel_m_s2**2)
        if not quiet:
            self._rest_since_t = None
            self.at_rest = False
            return
        if self._rest_since_t is None:
            self._rest_since_t = self.t_s
        self.at_rest = self.t_s - self._rest_since_t >= s.rest_min_s
        if self.at_rest:
            kn = min(1.0, dt / 10.0)  # noise variances averaged over ~10 s of rest
            e0, e1, e2 = gyro[0] - gl[0], gyro[1] - gl[1], gyro[2] - gl[2]
            self._noise_gyro_var += kn * ((e0 * e0 + e1 * e1 + e2 * e2) / 3.0 - self._noise_gyro_var)
            self._noise_acc_var += kn * ((da0 * da0 + da1 * da1 + da2 * da2) / 3.0 - self._noise_acc_var)

    def _zero_rate(self, gyro) -> None:
        """At rest the gyro measures its bias: z = ω, H = [0, I], R = the learned per-sample noise."""
        r = self._noise_gyro_var
        Pbb = self.P[3:, 3:]
        S = Pbb + np.eye(3) * r
        K = np.linalg.solve(S, self.P[3:, :]).T  # (6, 3): P Hᵀ S⁻¹
        dx = K @ (np.asarray(gyro, float) - self.bias)
        self._inject(dx)
        P = self.P - K @ self.P[3:, :]
        self.P = 0.5 * (P + P.T)

    def _lpf_loop_floor(self, interval_s: float) -> float:
        """The smallest 1-σ (rad) of the low-passed gravity fused in the estimate's own frame that keeps the tilt
        loop through the low-pass well inside its stability limit (``gravity_lpf_loop_gain``): a gain per update of
        at most k = 1 − exp(−T k_max) on the largest horizontal tilt variance λ needs σ² ≥ λ (1 − k) / k."""
        s = self.settings
        k = 1.0 - math.exp(-interval_s * s.gravity_lpf_loop_gain / s.gravity_lpf_tau_s)
        if k >= 1.0:
            return 0.0
        Rh = _qmat(self.q)[:2]
        Pn = Rh @ self.P[:3, :3] @ Rh.T  # the nav-frame tilt (east, north) covariance
        a, b, c = Pn[0, 0], Pn[0, 1], Pn[1, 1]
        lam = 0.5 * (a + c) + math.sqrt(0.25 * (a - c) * (a - c) + b * b)
        return math.sqrt(max(lam, 0.0) * (1.0 - k) / k)

    def _fuse_accel(self, accel, rate_rad_s: float = 0.0, noise_m_s2: float | None = None,
                    floor_rad: float = 0.0) -> None:
        s = self.settings
        a = np.asarray(accel, float)  # pragma: no mutate (dtype: a / na converts)
        na = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        err = na - maths.G0
        self.states.accel_error_m_s2 = err
        if abs(err) > s.accel_rejection_m_s2 or na < 1e-6:
            self.flags.accel_ignored = True
            return
        self.flags.accel_ignored = False
        z = a / na
        qw, qx, qy, qz = self.q
        g = np.array([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)])  # Rᵀ e_up
        # (eq. 2.2) g_true ≈ g + [g]× δθ  →  H = [[g]×, 0]
        H = np.zeros((3, 6))
        H[:, :3] = _skew(g)
        base = s.accel_noise_m_s2 if noise_m_s2 is None else noise_m_s2
        sig = max((base + 2.0 * abs(err) + s.accel_noise_per_rate_m_s2_per_rad_s * rate_rad_s) / maths.G0, floor_rad)
        PHt = self.P @ H.T
        S = H @ PHt + np.eye(3) * sig * sig
        K = np.linalg.solve(S, PHt.T).T
        # never let gravity move the heading: zero the gain of the rotation about the nav vertical
        R = _qmat(self.q)
        up_b = R[2]  # nav up expressed in body
        K[:3] -= np.outer(up_b, up_b @ K[:3])
        dx = K @ (z - g)  # pragma: no mutate (K g = 0, g being in the null space of Hᵀ: z + g gives the same step)
        self._inject(dx)
        # Joseph form: K is not the optimal gain after the projection above
        A = _EYE6 - K @ H
        P = A @ self.P @ A.T + (sig * sig) * (K @ K.T)
        self.P = 0.5 * (P + P.T)

    def update_mag(self, mag_nt, dmc_valid: bool | None = None, t_s: float | None = None) -> bool:
        """Fuse one calibrated magnetometer sample (nT, body FLU). Returns whether it was fused.

        ``t_s`` is the sample's own time on the clock of ``update_imu``'s ``dt_s`` sum (default: the
        filter's current time); the windows, rates and hold times of the checks run on it, so samples
        handed over in bursts are timed right. Feed samples in time order, after the IMU step of
        their time.
        """
        s = self.settings
        m = np.asarray(mag_nt, float)  # pragma: no mutate (dtype: every use is a float product or sum)
        fl, st = self.flags, self.states
        t = self.t_s if t_s is None else float(t_s)
        if self.mode == "initialising":
            if self._init_t0 is None:
                self._init_t0 = t
            self._init_mag += _qmat(self._init_q) @ m
            self._init_n[1] += 1
            if t - self._init_t0 >= s.init_duration_s - 1e-9 and self._init_n[0]:
                Rt = _qmat(self._init_q).T  # first frame → current body frame
                self.align(Rt @ (self._init_acc / self._init_n[0]), Rt @ (self._init_mag / self._init_n[1]))
                self._last_mag_t = t
                fl.initialising = False
            return False
        if self._lag is not None:
            self._lag.add_mag(t, m, self.ref_field_nt)
            self.mag_delay_s = self._lag.delay_s
        if t - self._last_mag_t < s.mag_update_period_s - 1e-9:
            return fl.mag_fused
        dt_mag = max(0.0, min(t - self._last_mag_t, 1.0))
        self._last_mag_t = t
        R = _qmat(self.q)
        # a delayed sample is levelled with the attitude at its own time (PX4 EKF2_MAG_DELAY); the
        # heading error about the nav vertical is the same then and now, so H below uses R of now
        t_att = t - self.mag_delay_s  # the attitude at the sample's own time (late or lagging samples)
        q_m, gyro_yaw_m, qg_m = (self._attitude_at(t_att) if t_att < self.t_s - 1e-9
                                 else (self.q, self._gyro_yaw, self._qg))
        R_m = _qmat(q_m)
        if self._hi_rot is not None:
            self._hi_rot.add(t_att, m, qg_m)
        mn = R_m @ m
        x, y = mn[0], mn[1]
        h2 = x * x + y * y
        strength = math.sqrt(h2 + mn[2] * mn[2])
        dip = math.atan2(-mn[2], math.sqrt(h2))
        azimuth = math.atan2(x, y)  # clockwise from north
        # ---- checks ----
        st.field_strength_error_frac = (strength - self.ref_field_nt) / self.ref_field_nt
        st.field_dip_error_rad = dip - self.ref_dip_rad
        sample_bad = s.use_field_check and (
            abs(st.field_strength_error_frac) > s.sample_strength_tol_frac or abs(st.field_dip_error_rad) > s.sample_dip_tol_rad
        )
        fl.dmc_valid = True if (dmc_valid is None or not s.use_dmc) else bool(dmc_valid)
        # magnetometer yaw = estimated yaw + azimuth error of the field (the innovation below)
        nu = math.remainder(azimuth - s.declination_rad, 2 * math.pi)
        mag_yaw = math.atan2(R_m[1, 0], R_m[0, 0]) + nu
        field_g = _qmat(qg_m) @ m if s.heading_test_gyro_frame else (0.0, 0.0, 0.0)
        self._window.add(t, strength, dip, math.remainder(mag_yaw - gyro_yaw_m, 2 * math.pi), field_g)
        gain = 1.0
        fl.quasi_static = True
        window_bad = False
        mb = self.ref_field_nt  # the window's mean strength (the reference until the window is full)
        if self._window.full(t):
            mb, var_b, md, var_d, dpsi = self._window.stats(R @ _qmat(self._qg).T if s.heading_test_gyro_frame else None)
            window_bad = s.use_field_check and (
                abs(mb - self.ref_field_nt) > s.field_strength_tol_frac * self.ref_field_nt
                or abs(md - self.ref_dip_rad) > s.field_dip_tol_rad
            )
            var_fail = var_b > s.quasi_static_var_nt2 or var_d > s.quasi_static_dip_var_rad2
            head_fail = dpsi > s.quasi_static_heading_rad
            fl.quasi_static = not (var_fail or head_fail)
            if s.adaptive_noise:
                gain = max(s.adaptive_gain_variance if var_fail else 1.0, s.adaptive_gain_heading if head_fail else 1.0)
        if self._rebase_pending:
            # a new calibration: the reference is learned again from the next quasi-static window; until
            # then the field is judged by its steadiness and the innovation gate alone
            sample_bad = window_bad = False
            if self._window.full(t) and not (var_fail or head_fail):
                self._set_reference(mb, md, "re-based after a calibration change")
        fl.field_inconsistent = window_bad or sample_bad
        window_ok = self._window.full(t) and not window_bad
        disturbed = window_bad or not fl.dmc_valid
        # ---- innovation (eq. 2.3): φ_z = azimuth − D, H = e_upᵀ R (body error → nav yaw) ----
        Hr = R[2]
        Pn = R @ self.P[:3, :3] @ R.T
        var_m = s.mag_noise_nt**2 / max(h2, 1.0)
        leak = 0.0
        if h2 > 1.0:  # tilt error leaks into the azimuth ∝ tan(inclination)
            # ∂azimuth/∂(φ_east, φ_north) of a nav-frame tilt φ (its sign irrelevant for the variance): a tilt about
            # the horizontal field's own direction swings its vertical part sideways, one across it does not
            j = (mn[2] / h2) * np.array([x, y])
            leak = float(j @ Pn[:2, :2] @ j)
        r = max(var_m, s.mag_heading_noise_floor_rad**2) * gain + leak
        if self.mode == "recovering":
            r *= s.recovery_noise_gain
        st.mag_noise_gain = gain
        PHt = self.P[:, :3] @ Hr
        S = float(Hr @ PHt[:3]) + r
        ratio = nu * nu / (s.mag_gate_sigma**2 * S)
        st.mag_innovation_rad, st.mag_innovation_var_rad2, st.mag_test_ratio = nu, S, ratio
        fl.mag_rejected_gate = ratio > 1.0
        usable = not fl.mag_rejected_gate and not sample_bad
        # ---- mode logic (§1) ----
        fused = fused_weak = False
        if window_bad:  # (reset on entering magnetic: "the field checks failed since the filter left it")
            self._outage_field_bad = True
        if self.mode == "magnetic":
            if disturbed:
                self._set_mode("gyro_only", "DMC says invalid" if not fl.dmc_valid else "field strength/dip off reference")
            elif not usable:
                if self._rejected_since_t is None:
                    self._rejected_since_t = t
                elif t - self._rejected_since_t > s.rejection_timeout_s:
                    self._set_mode("recovering", "innovation outside the gate for too long")
            else:
                self._rejected_since_t = None
                fused = True
        elif self.mode == "gyro_only":
            if disturbed:
                self._clear_since_t = None
                self._inside_gate_since_t = None
                # with no DMC verdict against it, a field that is merely off its reference may still
                # steer the heading very weakly (§2's adaptive noise taken to its limit)
                gain_weak = s.disturbed_noise_gain
                if s.hard_iron_tracking and fl.dmc_valid:
                    # a magnet that moves with the sensor adds a constant body-frame field: track it
                    # as the slow mean of (measured − expected) field and fuse what remains when that
                    # is consistent with the reference (the vehicle's rotation separates the two)
                    nu_c = self._hard_iron_innovation(m, R_m, dt_mag, mb)
                    if nu_c is not None:
                        nu, gain_weak = nu_c, s.hard_iron_noise_gain
                        if self._hi_rot is not None:
                            # the window's tests judged the raw field, whose strength and dip the magnet
                            # removed here makes vary as the body turns: the compensated field has the
                            # sensor's own noise, not the adaptive multiple
                            r = max(var_m, s.mag_heading_noise_floor_rad**2) + leak
                weak = gain_weak > 0.0 and fl.dmc_valid and abs(nu) < s.disturbed_gate_rad
                if weak:
                    r_weak = r * gain_weak
                    S = float(Hr @ PHt[:3]) + r_weak
                    fused_weak = True
            else:
                if self._clear_since_t is None:
                    self._clear_since_t = t
                    since = self._left_magnetic_t
                    scaled = s.holds_scale_with_outage and not self._outage_field_bad and since is not None
                    self._outage_s = t - since if scaled else None
                if s.agreement_from_clear:
                    # recovering's agreement test runs from here, on the estimate the gyro alone has carried (the
                    # magnetometer is watched, not fused); recovering then needs only the rest of its hold
                    if not usable or (not s.recovery_exit_mean and abs(nu) > s.recovery_exit_rad):
                        self._inside_gate_since_t = None
                    else:
                        self._agreement_add(t, nu)
                if t - self._clear_since_t >= self._hold(s.clear_hold_s):
                    inside_since = self._inside_gate_since_t
                    self._set_mode("recovering", "disturbance cleared")
                    self._inside_gate_since_t = inside_since
        elif self.mode == "recovering":
            if disturbed:
                self._set_mode("gyro_only", "disturbed again while recovering")
            else:
                if window_ok:
                    if self._consistent_since_t is None:
                        self._consistent_since_t = t
                else:
                    self._consistent_since_t = None
                consistent = self._consistent_since_t is not None and t - self._consistent_since_t >= s.recovery_hold_s
                if usable:
                    fused = True
                    if not s.recovery_exit_mean and abs(nu) > s.recovery_exit_rad:
                        self._inside_gate_since_t = None
                    elif self._agreement_add(t, nu) and t - self._inside_gate_since_t >= self._hold(s.recovery_hold_s):
                        if not s.recovery_exit_mean or abs(self._inside_sum / self._inside_n) <= s.recovery_exit_rad:
                            self._set_mode("magnetic", "magnetometer consistent and its heading agrees")
                        else:  # the mean over the hold is off: judge the next hold afresh
                            self._inside_gate_since_t = None
                            self._agreement_add(t, nu)
                else:
                    self._inside_gate_since_t = None
                    if consistent and not sample_bad and fl.quasi_static:
                        self._slew(nu, Hr, dt_mag)
        if fused_weak:
            K = PHt / S
            self._inject(K * nu)
            self.P = self.P - np.outer(K, PHt)
            self.P = 0.5 * (self.P + self.P.T)
        if fused:
            if s.mag_vector_fusion and self.mode == "magnetic" and fl.quasi_static and not fl.field_inconsistent:
                self._fuse_mag_vector(m, R_m, max(var_m, s.mag_heading_noise_floor_rad**2) * h2 / strength**2)
            else:
                K = PHt / S
                dx = K * nu
                if self.mode == "recovering":
                    # re-acquisition never steps the heading faster than recovery_slew_rad_s
                    step, limit = abs(float(Hr @ dx[:3])), s.recovery_slew_rad_s * dt_mag
                    if step > limit:
                        dx *= limit / step
                self._inject(dx)
                self.P = self.P - np.outer(K, PHt)
                self.P = 0.5 * (self.P + self.P.T)
            self._last_fused_t = t
        fl.mag_fused = fused
        return fused

    def _set_reference(self, strength_nt: float, dip_rad: float, why: str) -> None:
        log.debug("t=%.2f s: field reference %.0f nT / %.1f° → %.0f nT / %.1f° (%s)", self.t_s, self.ref_field_nt,
                  math.degrees(self.ref_dip_rad), strength_nt, math.degrees(dip_rad), why)
        self.ref_field_nt, self.ref_dip_rad = float(strength_nt), float(dip_rad)
        self._rebase_pending = False
        self.n_rebases += 1

    def rebase_field_reference(self) -> None:
        """The magnetometer's calibration changed: learn the field reference (strength, dip) again.

        Until a quasi-static window has given the new reference, the field is not judged against the
        old one (which belonged to the old calibration); a gyro-only mode held only because the field
        was off that reference ends (the DMC's verdict still counts). A filter not yet aligned learns
        it at alignment anyway."""
        if not self.aligned:
            return
        self._rebase_pending = True
        self._window.clear()
        if self.mode == "gyro_only" and self.flags.dmc_valid:
            self._set_mode("recovering", "calibration changed: field reference re-based")

    def _fuse_mag_vector(self, m: np.ndarray, R_m: np.ndarray, var_unit: float) -> None:
        """Field-direction update (§2's magnetometer observation) for a field that passed every check.

        Measurement: the unit field in the body frame against ``R_mᵀ u_ref`` (u_ref: the reference
        field direction in ENU from the dip and declination); H = [[h]×, 0] as for gravity.
        Used only while the field is consistent and quasi-static: then it also steadies roll and
        pitch under linear acceleration, when the accelerometer alone cannot.
        """
        D, dip = self.settings.declination_rad, self.ref_dip_rad
        u_ref = np.array([math.cos(dip) * math.sin(D), math.cos(dip) * math.cos(D), -math.sin(dip)])
        h = R_m.T @ u_ref
        z = m / np.linalg.norm(m)
        H = np.zeros((3, 6))
        H[:, :3] = _skew(h)
        PHt = self.P @ H.T
        S = H @ PHt + np.eye(3) * var_unit
        K = np.linalg.solve(S, PHt.T).T
        self._inject(K @ (z - h))  # pragma: no mutate (K h = 0, h being in the null space of Hᵀ: z + h gives the same step)
        A = _EYE6 - K @ H
        P = A @ self.P @ A.T + var_unit * (K @ K.T)
        self.P = 0.5 * (P + P.T)

    def _hard_iron_innovation(self, m: np.ndarray, R_m: np.ndarray, dt: float,
                              mean_strength_nt: float | None = None) -> float | None:
        """Heading innovation of the field with the tracked extra hard iron removed, or None while the
        compensated field is not yet consistent with the reference. ``mean_strength_nt``: the window's
        mean field strength (None: the reference's)."""
        s = self.settings
        D, dip = s.declination_rad, self.ref_dip_rad
        if mean_strength_nt is None:
            mean_strength_nt = self.ref_field_nt
        if self._hi_rot is not None:  # from the rotation alone
            hard_iron = self._hi_rot.estimate()
            # a body-fixed field weaker than the strength tolerance cannot be what put the field off its
            # reference (a homogeneous field that changed, the sensor carried elsewhere, leaves it small)
            # nor one weaker than the window's strength offset: a body-fixed h changes |b + h| by at most |h|, so
            # a field |mean − reference| off its reference in strength is not explained by a smaller h (the board
            # carried to a stronger field and moved through its gradient gives h of a few % that explains nothing)
            if hard_iron is None or math.sqrt(float(hard_iron @ hard_iron)) < max(
                    s.field_strength_tol_frac * self.ref_field_nt, abs(mean_strength_nt - self.ref_field_nt)):
                return None
        else:  # the slow mean of measured − expected field
            b_ref = self.ref_field_nt * np.array([math.cos(dip) * math.sin(D), math.cos(dip) * math.cos(D),
                                                  -math.sin(dip)])
            a = min(1.0, dt / s.hard_iron_tau_s)
            self._hard_iron = (1.0 - a) * self._hard_iron + a * (m - R_m.T @ b_ref)
            self._hard_iron_t += dt
            if self._hard_iron_t < s.hard_iron_tau_s:
                return None
            hard_iron = self._hard_iron
        mn = R_m @ (m - hard_iron)
        h = math.hypot(mn[0], mn[1])
        strength = math.sqrt(h * h + mn[2] * mn[2])
        if (abs(strength / self.ref_field_nt - 1.0) > s.sample_strength_tol_frac
                or abs(math.atan2(-mn[2], h) - dip) > s.sample_dip_tol_rad):
            return None
        return math.remainder(math.atan2(mn[0], mn[1]) - D, 2 * math.pi)

    def _attitude_at(self, t: float) -> tuple:
        """(quaternion, integrated gyro yaw, gyro-only attitude) at an earlier time t: the current estimate
        (with every correction so far) turned back by the gyro's own motion since t, q_t = q ⊗ q_g,now⁻¹ ⊗ q_g,t."""
        entry = self._history[0] if self._history else None
        for e in reversed(self._history):
            if e[0] <= t + 1e-9:
                entry = e
                break
        if entry is None:
            return self.q, self._gyro_yaw, self._qg
        gw, gx, gy_, gz = self._qg
        rel = _qmul((gw, -gx, -gy_, -gz), entry[1])
        return _qmul(self.q, rel), entry[2], entry[1]

    def _slew(self, nu: float, Hr: np.ndarray, dt: float) -> None:
        """Rate-limited heading correction towards a consistent magnetometer outside the gate."""
        step = max(-self.settings.recovery_slew_rad_s * dt, min(self.settings.recovery_slew_rad_s * dt, nu))
        # rotate about the nav vertical by `step`: δθ_body = Rᵀ e_up · step
        self._inject(np.concatenate([Hr * step, np.zeros(3)]))


class MagLagEstimator:
    """Causal estimate of the magnetometer's lag behind the gyro, from the sensors alone.

    A constant field seen from a rotating body turns with the body's inverse rotation; a magnetometer
    that lags by ``d`` shows at time t the field of time t − d. Over a baseline of ``baseline_s``
    between two field samples (times t₀ < t₁) and for each candidate lag on a grid of ``step_s``, the
    gyro-integrated rotation between t₀ − d and t₁ − d must carry the older sample into the newer::

        m(t₁) − h = M_d (m(t₀) − h),    M_d = R_g(t₁ − d)ᵀ R_g(t₀ − d)

    with ``h`` a body-fixed offset (an uncalibrated hard iron) that is solved for jointly, per
    candidate, by linear least squares (normal equations accumulated sample by sample, so memory and
    time per sample are constant). The lag is the candidate with the smallest residual, refined by a
    parabola through its neighbours. Comparing rotations over a baseline instead of the field's
    derivative keeps the magnetometer's noise from being amplified by the sample rate. Only pairs that
    turned by at least ``min_turn_rad`` (half of ``min_rate_rad_s`` over the baseline) and whose strength
    is within 10 % of the reference count (a disturbed field adds nothing); one pair per ``period_s``. It
    reports 0 until ``min_samples`` pairs were seen. The gyro ring buffer (``n_buf`` samples) must span
    up to twice ``baseline_s`` plus ``max_delay_s``: 512 samples do up to ~1.1 kHz.
    """

    def __init__(self, max_delay_s: float = 0.05, step_s: float = 0.001, min_rate_rad_s: float = 0.5,
                 min_samples: int = 200, period_s: float = 0.05, baseline_s: float = 0.2,
                 n_buf: int = 512):
        self.grid = np.arange(0.0, max_delay_s + 1e-12, step_s)
        self.step_s = step_s
        g = len(self.grid)
        self.A = np.zeros((g, 3, 3))  # Σ Mᵀ M, M = I − M_d
        self.b = np.zeros((g, 3))  # Σ Mᵀ r₀, r₀ = m₁ − M_d m₀
        self.c = np.zeros(g)  # Σ |r₀|²
        self.cost = np.zeros(g)
        self.n = 0
        self.min_rate = min_rate_rad_s
        self.min_turn_rad = min_rate_rad_s * baseline_s * 0.5
        self.min_samples = min_samples
        self.baseline_s = baseline_s
        self.delay_s = 0.0
        self.offset_nt = np.zeros(3)  # the body-fixed offset h at that lag
        self.period_s = period_s  # at most one pair per this period (the cost of the estimate)
        self._n_buf = n_buf
        self._gt = np.full(n_buf, -np.inf)  # ring buffer of gyro times and gyro-integrated attitudes
        self._gq = np.zeros((n_buf, 4))
        self._i = 0
        self._q = (1.0, 0.0, 0.0, 0.0)
        self._t_prev: float | None = None
        self._w_prev: tuple | None = None
        self._mags: deque = deque()
        self._last_t = -math.inf

    def add_gyro(self, t: float, gyro) -> None:
        """One gyro sample (rad/s), the rate at time t; the interval since the previous sample is
        integrated with the mean of the two rates (trapezoid: no half-sample lag of its own)."""
        dt = 0.0 if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        g0 = self._w_prev if self._w_prev is not None else gyro
        self._w_prev = (gyro[0], gyro[1], gyro[2])
        if dt > 0.0:
            h = 0.5 * dt
            q = _qmul(self._q, _quat_exp((g0[0] + gyro[0]) * h, (g0[1] + gyro[1]) * h, (g0[2] + gyro[2]) * h))
            n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
            self._q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
        j = self._i % self._n_buf
        self._gt[j] = t
        self._gq[j] = self._q
        self._i += 1

    def _attitudes_at(self, times: np.ndarray, gt: np.ndarray, gq: np.ndarray) -> np.ndarray:
        """Gyro-integrated attitude at each time (normalised linear interpolation), rows (w, x, y, z)."""
        idx = np.clip(np.searchsorted(gt, times), 1, len(gt) - 1)
        t0, t1 = gt[idx - 1], gt[idx]
        f = np.clip((times - t0) / np.maximum(t1 - t0, 1e-9), 0.0, 1.0)[:, None]
        q = gq[idx - 1] * (1.0 - f) + gq[idx] * f
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    def add_mag(self, t: float, m: np.ndarray, ref_nt: float) -> None:
        """One field sample (nT) at time t; ``ref_nt`` the reference strength (0: not checked)."""
        m = np.asarray(m, float)  # pragma: no mutate (dtype: every use is a float product or sum)
        if ref_nt and abs(math.sqrt(float(m @ m)) / ref_nt - 1.0) > 0.1:
            return
        mags = self._mags
        mags.append((t, m))
        while len(mags) > 1 and mags[1][0] <= t - self.baseline_s:
            mags.popleft()
        if t - self._last_t < self.period_s or self._i < 2:
            return
        t0, m0 = mags[0]
        if t - t0 < 0.8 * self.baseline_s or t - t0 > 2.0 * self.baseline_s:
            return
        k = min(self._i, self._n_buf)
        order = (np.arange(self._i - k, self._i)) % self._n_buf  # the filled part, oldest first
        gt = self._gt[order]
        if t0 - self.grid[-1] < gt[0] or t > gt[-1] + 1e-6:
            return
        self._last_t = t
        gq = self._gq[order]
        q1 = self._attitudes_at(t - self.grid, gt, gq)
        q0 = self._attitudes_at(t0 - self.grid, gt, gq)
        # M_d = R(q1)ᵀ R(q0) = R(q1* ⊗ q0)
        w1, x1, y1, z1 = q1.T
        w0, x0, y0, z0 = q0.T
        w = w1 * w0 + x1 * x0 + y1 * y0 + z1 * z0
        x = w1 * x0 - x1 * w0 - y1 * z0 + z1 * y0
        y = w1 * y0 + x1 * z0 - y1 * w0 - z1 * x0
        z = w1 * z0 - x1 * y0 + y1 * x0 - z1 * w0
        if 2.0 * math.acos(min(1.0, abs(float(w[0])))) < self.min_turn_rad:
            return
        Md = np.empty((len(w), 3, 3))
        Md[:, 0, 0] = 1 - 2 * (y * y + z * z)
        Md[:, 0, 1] = 2 * (x * y - w * z)
        Md[:, 0, 2] = 2 * (x * z + w * y)
        Md[:, 1, 0] = 2 * (x * y + w * z)
        Md[:, 1, 1] = 1 - 2 * (x * x + z * z)
        Md[:, 1, 2] = 2 * (y * z - w * x)
        Md[:, 2, 0] = 2 * (x * z - w * y)
        Md[:, 2, 1] = 2 * (y * z + w * x)
        Md[:, 2, 2] = 1 - 2 * (x * x + y * y)
        r0 = m - Md @ m0
        M = np.eye(3) - Md
        Mt = np.transpose(M, (0, 2, 1))
        self.A += Mt @ M
        self.b += np.einsum("gij,gj->gi", Mt, r0)
        self.c += np.einsum("gi,gi->g", r0, r0)
        self.n += 1
        if self.n >= self.min_samples and self.n % 10 == 0:
            self._solve()

    def _solve(self) -> None:
        # least-squares residual with the best offset h per candidate: c − bᵀ A⁻¹ b (A regularised:
        # the offset along an axis the body never turned about is not observable)
        eps = 1e-9 * np.trace(self.A, axis1=1, axis2=2)[:, None, None] + 1e-12
        h = np.linalg.solve(self.A + eps * np.eye(3), self.b[:, :, None])[:, :, 0]
        c = self.c - np.einsum("gi,gi->g", self.b, h)
        self.cost = c
        j = int(np.argmin(c))
        self.offset_nt = h[j]
        frac = 0.0
        if 0 < j < len(c) - 1:
            den = c[j - 1] - 2 * c[j] + c[j + 1]
            frac = 0.5 * (c[j - 1] - c[j + 1]) / den if den > 0 else 0.0
        self.delay_s = float(max(0.0, self.grid[j] + frac * self.step_s))


def estimate_mag_delay_s(gyro_rad_s, mag_nt, rate_hz: float, max_delay_s: float = 0.05) -> float:
    """Lag of a magnetometer behind the gyro, from the sensor data alone (no ground truth).

    A constant field seen from a rotating body obeys ṁ(t) = −ω(t − d) × m(t) when the magnetometer
    lags by d. The lag is the whole-sample shift minimising the residual of that equation, refined
    by a parabola through the three best shifts. Needs some rotation in the data.
    """
    w = np.asarray(gyro_rad_s, float)  # pragma: no mutate (dtype: the cross product with float m converts)
    m = np.asarray(mag_nt, float)  # pragma: no mutate (dtype: np.gradient returns floats)
    dm = np.gradient(m, axis=0) * rate_hz
    kmax = max(1, int(round(max_delay_s * rate_hz)))
    shifts = np.arange(0, kmax + 1)
    cost = np.empty(len(shifts))
    for j, k in enumerate(shifts):
        wk = w[: len(w) - k] if k else w
        r = dm[k:] + np.cross(wk, m[k:])
        cost[j] = np.mean(np.sum(r * r, axis=1))
    j = int(np.argmin(cost))
    frac = 0.0
    if 0 < j < len(cost) - 1:
        c0, c1, c2 = cost[j - 1], cost[j], cost[j + 1]
        den = c0 - 2 * c1 + c2
        frac = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    return float(max(0.0, (shifts[j] + frac) / rate_hz))


def magnetic_heading(mag_nt, accel_m_s2, declination_rad: float = 0.0):
    """Tilt-compensated magnetometer-only heading (rad), the baseline a single compass gives."""
    return maths.tilt_compensated_heading(mag_nt, accel_m_s2, declination_rad)
