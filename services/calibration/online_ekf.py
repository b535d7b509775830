"""Online GNSS-aided hard-iron EKF for a vehicle that cannot tumble its sensor (docs/methods.md#hard-iron-ekf).

State ``x = b = [b_x, b_y, b_z]`` (nT), the hard-iron offset, a random constant (plus an optional
random walk); with ``estimate_mount_yaw`` a fourth state δψ, the constant heading bias of the sensor's
mounting yaw (an improvement over the paper: a 1° mounting error is otherwise forced into the offset,
where it becomes a heading-dependent error). Measurement ``ψ_gnss = ψ_m(b) + δψ``; ∂/∂δψ = 1.
Off by default: on the simulated car it lowered the heading RMS after convergence (worst 1.05° vs 1.54°)
but δψ trades off against the offset until the drive has turned through many headings, so convergence took
190–290 s instead of 55–75 s and the heading before it was worse (up to 3.4° RMS). The compensated field is ``h = M (m − b)`` with the matrix ``M`` of the static fit (or
identity); it is levelled with the vehicle's roll φ and pitch θ, ``l = Ry(−θ) Rx(φ) h``, and gives the
magnetic heading ``ψ_m(b) = atan2(l_y, l_x) + D`` (FLU, clockwise from north, D = declination).

Measurement (Liu et al., §2): ``z = ψ_gnss − ψ_m(b̂)`` wrapped to [−π, π), used only when GNSS
quality is good (fix type, satellites, PDOP) and the vehicle moves fast enough for its course to be
its heading. Jacobian (the three partial derivatives of the heading formula)::

    ∂ψ_m/∂b = [−l_y, l_x, 0] / (l_x² + l_y²) · Ry(−θ) Rx(φ) · (−M)

Update (Joseph form)::

    S = H P Hᵀ + R,   K = P Hᵀ / S,   b ← b + K z,   P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ

``R = σ_ψ² + (σ_v / v)²``: the heading noise (magnetometer noise, sideslip) plus the GNSS course
noise at ground speed v. An innovation beyond ``gate_sigma`` standard deviations is rejected (a
magnetic disturbance, a GNSS outlier), PX4 style.

Observability: with small pitch and roll the heading hardly depends on ``b_z`` (the third column of
H is ≈ sin(tilt)), and what little it does is swamped by the error of the tilt estimate itself: left
free, ``b_z`` drifts towards the vertical field (which makes the heading blind to tilt errors) and
drags ``b_x``, ``b_y`` along through the cross-axis terms of M. So ``b_z`` is estimated only once the
RMS tilt of the fused epochs reaches ``min_tilt_for_vertical_rad`` (never for a car); until then the
third column of H is zeroed and ``b_z`` keeps its prior. A component counts as observable when it is
estimated and its standard deviation has fallen below ``observable_ratio`` of its prior.
:meth:`applied_offset` returns the estimate with every unobservable component held at its prior
value: an unobservable correction is never applied.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magmesh import maths

GOOD_FIX = ("3d", "dgps", "rtk_float", "rtk_fixed")


@dataclass(frozen=True)
class EkfSettings:
    prior_std_nt: float = 5_000.0  # 1 σ of the initial offset estimate, per axis
    random_walk_nt_sqrt_s: float = 30.0  # process noise: hard-iron change (keeps the filter able to follow a step)
    heading_noise_rad: float = math.radians(2.0)  # magnetometer heading noise + sideslip, 1 σ
    gnss_vel_std_m_s: float = 0.10  # GNSS velocity noise, 1 σ (course noise = this / speed)
    min_speed_m_s: float = 3.0  # below this the course is not the heading
    max_yaw_rate_rad_s: float = 0.35  # skip hard turns (sideslip, course lag)
    min_sats: int = 6
    max_pdop: float = 3.0
    gate_sigma: float = 3.0  # innovation gate, standard deviations
    observable_ratio: float = 0.3  # std/prior below this → component observable
    converged_std_nt: float = 300.0  # all observable components below this std → converged
    min_tilt_for_vertical_rad: float = 0.15  # RMS tilt of the fused epochs needed before b_z is estimated
    estimate_mount_yaw: bool = False  # 4th state: constant heading bias δψ (sensor mounting yaw); see module doc
    mount_yaw_prior_std_rad: float = math.radians(3.0)
    mount_yaw_observable_std_rad: float = math.radians(0.3)  # δψ applied once its σ is below this

    def __post_init__(self):
        if self.prior_std_nt <= 0 or self.heading_noise_rad <= 0 or self.gate_sigma <= 0:
            raise ValueError("prior_std_nt, heading_noise_rad and gate_sigma must be > 0")
        if not 0 < self.observable_ratio < 1:
            raise ValueError("observable_ratio must be in (0, 1)")


def gnss_usable(fix_type: str, num_sats: int, pdop: float, speed_m_s: float, st: EkfSettings) -> tuple[bool, str]:
    """Starting condition of a GNSS heading update, with the reason when it fails."""
    if fix_type not in GOOD_FIX:
        return False, f"GNSS fix '{fix_type}' is not good enough"
    if num_sats < st.min_sats:
        return False, f"{num_sats} satellites < {st.min_sats}"
    if pdop > st.max_pdop:
        return False, f"PDOP {pdop:.1f} > {st.max_pdop:g}"
    if speed_m_s < st.min_speed_m_s:
        return False, f"speed {speed_m_s:.1f} m/s < {st.min_speed_m_s:g} m/s"
    return True, ""


class SpeedRate:
    """Forward acceleration from GNSS speed: least-squares slope over the last ``window_s``.

    A two-epoch difference at 5 Hz turns 0.08 m/s of speed noise into ≈ 0.6 m/s² (3.3° of pitch);
    the slope over 1 s cuts it to ≈ 0.1 m/s² at the price of ≈ 0.5 s lag.
    """

    def __init__(self, window_s: float = 1.0):
        self.window_s = window_s
        self.t: list[float] = []
        self.v: list[float] = []

    def update(self, t_s: float, speed_m_s: float) -> float:
        if self.t and t_s < self.t[-1]:  # clock went back: start again
            self.t.clear()
            self.v.clear()
        self.t.append(float(t_s))
        self.v.append(float(speed_m_s))
        while self.t and self.t[0] < t_s - self.window_s:
            self.t.pop(0)
            self.v.pop(0)
        if len(self.t) < 2:
            return 0.0
        t = np.asarray(self.t) - self.t[-1]  # pragma: no mutate (any shift cancels in t − mean; it only conditions)
        v = np.asarray(self.v)
        tc = t - t.mean()
        den = float(tc @ tc)
        return float(tc @ (v - v.mean()) / den) if den > 0 else 0.0


def car_roll_pitch(accel_m_s2, speed_rate_m_s2: float = 0.0, speed_m_s: float = 0.0, yaw_rate_rad_s: float = 0.0):
    """Roll and pitch of a car from its accelerometer with the motion removed (FLU body).

    Forward acceleration (from the GNSS speed rate) and centripetal acceleration (speed × yaw rate,
    towards +y in a left turn) are subtracted before the gravity direction is read; otherwise a
    1 m/s² acceleration reads as a 6° pitch and spoils the levelling.
    """
    a = np.asarray(accel_m_s2, float).copy()
    a[0] -= speed_rate_m_s2
    a[1] -= speed_m_s * yaw_rate_rad_s
    roll, pitch = maths.roll_pitch_from_accel(a)
    return float(roll), float(pitch)


class HardIronEkf:
    """update(...) per GNSS epoch; internal_states, flags, reset() (x-io Fusion shape)."""

    def __init__(self, settings: EkfSettings = EkfSettings(), offset0_nt=(0.0, 0.0, 0.0), matrix=None):
        self.settings = settings
        self.M = np.eye(3) if matrix is None else np.asarray(matrix, float).reshape(3, 3)
        self.reset(offset0_nt)

    def reset(self, offset0_nt=None):
        st = self.settings
        if offset0_nt is not None:
            self.prior = np.asarray(offset0_nt, float).copy()
        self.n = 4 if st.estimate_mount_yaw else 3
        self.xs = np.zeros(self.n)  # [b_x, b_y, b_z (nT), δψ (rad)]
        self.xs[:3] = self.prior
        self.P = np.diag([st.prior_std_nt**2] * 3 + ([st.mount_yaw_prior_std_rad**2] if self.n == 4 else []))
        self.t_last = None
        self.innovation_rad = None
        self.innovation_var_rad2 = None
        self.test_ratio = None
        self.n_fused = 0
        self.n_rejected = 0
        self.n_skipped = 0
        self.skip_reason = ""
        self.fused = False
        self.tilt_sq_sum = 0.0

    @property
    def x(self) -> np.ndarray:
        """Offset estimate, nT."""
        return self.xs[:3]

    @property
    def mount_yaw_rad(self) -> float:
        return float(self.xs[3]) if self.n == 4 else 0.0

    @property
    def mount_yaw_std_rad(self) -> float:
        return float(math.sqrt(self.P[3, 3])) if self.n == 4 else 0.0

    @property
    def tilt_rms_rad(self) -> float:
        return math.sqrt(self.tilt_sq_sum / self.n_fused) if self.n_fused else 0.0

    @property
    def vertical_excited(self) -> bool:
        return self.n_fused >= 10 and self.tilt_rms_rad >= self.settings.min_tilt_for_vertical_rad

    # ---- model -------------------------------------------------------------------------------

    def heading(self, m_nt, offset_nt, roll_rad: float, pitch_rad: float, declination_rad: float):
        """ψ_m and the levelled horizontal field (l_x, l_y) for an offset."""
        h = self.M @ (np.asarray(m_nt, float) - offset_nt)
        R = maths.rot_y(-pitch_rad) @ maths.rot_x(roll_rad)
        lev = R @ h
        return float(maths.wrap_2pi(math.atan2(lev[1], lev[0]) + declination_rad)), lev, R

    def jacobian(self, lev: np.ndarray, R: np.ndarray) -> np.ndarray:
        """H = ∂ψ_m/∂b (1×3) at the levelled field ``lev``."""
        lh2 = lev[0] ** 2 + lev[1] ** 2
        dpsi_dl = np.array([-lev[1], lev[0], 0.0]) / max(lh2, 1e-9)
        return -(dpsi_dl @ R @ self.M)

    # ---- step --------------------------------------------------------------------------------

    def predict(self, t_s: float):
        if self.t_last is not None and t_s >= self.t_last:
            dt = max(0.0, t_s - self.t_last)
            self.P[:3, :3] += np.eye(3) * (self.settings.random_walk_nt_sqrt_s**2) * dt
        self.t_last = t_s

    def update(self, t_s: float, m_nt, course_rad: float | None, roll_rad: float = 0.0, pitch_rad: float = 0.0,
               declination_rad: float = 0.0, speed_m_s: float = 0.0, yaw_rate_rad_s: float = 0.0,
               gnss_ok: bool = True) -> bool:
        """One epoch. ``course_rad=None`` or ``gnss_ok=False`` means no usable GNSS heading (predict only).

        Returns True when the measurement was fused.
        """
        st = self.settings
        self.predict(t_s)
        self.fused = False
        if course_rad is None or not gnss_ok:
            self.n_skipped += 1
            self.skip_reason = "no usable GNSS course"
            return False
        if speed_m_s < st.min_speed_m_s:
            self.n_skipped += 1
            self.skip_reason = f"speed {speed_m_s:.1f} m/s below {st.min_speed_m_s:g} m/s"
            return False
        if abs(yaw_rate_rad_s) > st.max_yaw_rate_rad_s:
            self.n_skipped += 1
            self.skip_reason = f"turning at {math.degrees(yaw_rate_rad_s):.0f}°/s"
            return False
        psi, lev, R = self.heading(m_nt, self.x, roll_rad, pitch_rad, declination_rad)
        H = np.zeros(self.n)
        H[:3] = self.jacobian(lev, R)
        if not self.vertical_excited:
            H[2] = 0.0  # b_z not estimated (see module doc)
        if self.n == 4:
            H[3] = 1.0  # ψ_gnss = ψ_m(b) + δψ
        z = float(maths.wrap_pi(course_rad - psi - self.mount_yaw_rad))  # innovation ψ_gnss − (ψ_m(b̂) + δψ̂)
        r = st.heading_noise_rad**2 + (st.gnss_vel_std_m_s / max(speed_m_s, 0.1)) ** 2
        S = float(H @ self.P @ H + r)
        self.innovation_rad, self.innovation_var_rad2 = z, S
        self.test_ratio = z * z / (st.gate_sigma**2 * S)
        if self.test_ratio > 1.0:
            self.n_rejected += 1
            return False
        K = self.P @ H / S
        self.xs = self.xs + K * z
        IKH = np.eye(self.n) - np.outer(K, H)
        self.P = IKH @ self.P @ IKH.T + np.outer(K, K) * r
        self.n_fused += 1
        self.tilt_sq_sum += roll_rad**2 + pitch_rad**2
        self.fused = True
        return True

    # ---- outputs -----------------------------------------------------------------------------

    @property
    def std_nt(self) -> np.ndarray:
        return np.sqrt(np.diag(self.P)[:3])

    @property
    def observable(self) -> tuple[bool, bool, bool]:
        ratio = self.std_nt / self.settings.prior_std_nt
        obs = [bool(r < self.settings.observable_ratio) for r in ratio]
        obs[2] = obs[2] and self.vertical_excited
        return tuple(obs)

    @property
    def converged(self) -> bool:
        obs = np.array(self.observable)
        return bool(obs.any() and np.all(self.std_nt[obs] < self.settings.converged_std_nt))

    def applied_offset(self) -> np.ndarray:
        """The estimate with unobservable components held at the prior."""
        obs = np.array(self.observable)
        return np.where(obs, self.x, self.prior)

    @property
    def mount_yaw_observable(self) -> bool:
        return self.n == 4 and self.mount_yaw_std_rad < self.settings.mount_yaw_observable_std_rad

    def applied_matrix(self) -> np.ndarray:
        """``Rz(δψ) M``: the compensation matrix with the estimated mounting yaw removed (M itself while δψ is
        not yet known well): the compensated field's heading is then the vehicle's."""
        if not self.mount_yaw_observable:
            return self.M.copy()
        return maths.rot_z(self.mount_yaw_rad) @ self.M

    @property
    def internal_states(self) -> dict:
        return {
            "offset_nt": [float(v) for v in self.x],
            "offset_std_nt": [float(v) for v in self.std_nt],
            "innovation_rad": self.innovation_rad,
            "innovation_var_rad2": self.innovation_var_rad2,
            "test_ratio": self.test_ratio,
            "n_fused": self.n_fused,
            "n_rejected": self.n_rejected,
            "n_skipped": self.n_skipped,
            "tilt_rms_rad": self.tilt_rms_rad,
            "mount_yaw_rad": self.mount_yaw_rad,
            "mount_yaw_std_rad": self.mount_yaw_std_rad,
        }

    @property
    def flags(self) -> dict:
        return {"converged": self.converged, "observable": list(self.observable), "fused": self.fused}
