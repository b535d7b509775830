"""``heading_fuser --impl vqf``: the same role and ``heading`` contract, computed by VQF.

VQF (Laidig & Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and magnetic
disturbance rejection", Information Fusion 91, 2023; the ``vqf`` package, MIT) run online with its
default parameters. Its quaternion is sensor → ENU with magnetic north, scalar first; the vehicle's
declination turns it to true north, ``q = q_z(−D) ⊗ q_vqf``.

What this adds around the library, so that it can stand in for the EKF in the mesh:

* sampling times: VQF needs fixed ``gyrTs``/``magTs``; they are the median intervals of the first
  samples (mode ``initialising`` meanwhile); a gap restarts the filter, as for the EKF;
* the DMC verdict: while the differential compass says the field is invalid the magnetometer sample is
  not given to VQF (mode ``gyro_only``); VQF's own disturbance rejection also counts as ``gyro_only``;
* a heading 1-σ for the contract: VQF keeps no attitude covariance, so the heading σ is a floor (the
  magnetometer's heading noise) plus VQF's own gyro-bias σ times the time since the field was last
  used (how far an unchecked bias can have turned the heading). Tilt σ is reported as that floor;
* ``rebase_field_reference``: VQF learns its field reference by itself (its norm/dip tests with a
  reference that follows a steady new field); a new calibration just resets that reference.

The wrapper has the interface of :class:`services.heading_fuser.core.HeadingFilter` that the service
uses; the class is :class:`VqfHeadingFuser`.
"""

from __future__ import annotations

import math
import statistics

import numpy as np

from magmesh import maths

from . import core
from .service import HeadingFuser, Settings

_N_TS = 10  # samples whose median interval gives the sampling time


class VqfFilter:
    """Online VQF behind the HeadingFilter interface the heading service drives."""

    HEADING_FLOOR_RAD = 0.02  # 1-σ of a magnetometer-steered heading (≈1°)

    def __init__(self, settings: core.Settings | None = None):
        self.settings = settings or core.Settings()
        self.reset()

    def reset(self) -> None:
        self.vqf = None
        self.mode = "initialising"
        self.t_s = 0.0
        self.q = (1.0, 0.0, 0.0, 0.0)
        self.states = core.InternalStates()
        self.flags = core.Flags()
        self.transitions: list[tuple[float, str, str, str]] = []
        self.n_rebases = 0
        self._imu_t: list[float] = []
        self._mag_t: list[float] = []
        self._last_fused_t: float | None = None
        self._first_mag_t: float | None = None
        d = self.settings.declination_rad
        self._qd = (math.cos(-d / 2), 0.0, 0.0, math.sin(-d / 2))

    # ---- the HeadingFilter interface ------------------------------------------------------------
    @property
    def internal_states(self) -> core.InternalStates:
        return self.states

    @property
    def aligned(self) -> bool:
        return self.mode != "initialising"

    def quaternion(self) -> np.ndarray:
        return np.array(self.q)

    def euler(self) -> tuple[float, float, float]:
        return maths.euler_from_matrix(core._qmat(self.q))

    def heading_rad(self) -> float:
        w, x, y, z = self.q
        return float(maths.yaw_to_heading(math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))))

    def attitude_std(self) -> tuple[float, float, float]:
        return self.states.heading_std_rad, self.HEADING_FLOOR_RAD, self.HEADING_FLOOR_RAD

    def rebase_field_reference(self) -> None:
        if self.vqf is not None:
            self.vqf.setMagRef(0.0, 0.0)  # a zero norm: VQF takes the next steady field as its reference
            self.n_rebases += 1

    def _set_mode(self, mode: str, reason: str) -> None:
        if mode != self.mode:
            self.transitions.append((self.t_s, self.mode, mode, reason))
            self.mode = mode

    def _start(self) -> None:
        from vqf import VQF

        gyr_ts = statistics.median(np.diff(self._imu_t))
        mag_ts = statistics.median(np.diff(self._mag_t)) if len(self._mag_t) > 1 else gyr_ts
        self.vqf = VQF(float(gyr_ts), float(gyr_ts), float(mag_ts))

    def update_imu(self, gyro_rad_s, accel_m_s2, dt_s: float, t_s: float | None = None) -> None:
        self.t_s = self.t_s + dt_s if t_s is None else float(t_s)
        if self.vqf is None:
            self._imu_t.append(self.t_s)
            if len(self._imu_t) > _N_TS and len(self._mag_t) > _N_TS // 2:
                self._start()
            return
        self.vqf.updateGyr(np.ascontiguousarray(gyro_rad_s, dtype=float))
        self.vqf.updateAcc(np.ascontiguousarray(accel_m_s2, dtype=float))
        self._refresh()

    def update_mag(self, mag_nt, dmc_valid: bool | None = None, t_s: float | None = None) -> bool:
        t = self.t_s if t_s is None else float(t_s)
        fl = self.flags
        if self.vqf is None:
            self._mag_t.append(t)
            return False
        fl.dmc_valid = True if (dmc_valid is None or not self.settings.use_dmc) else bool(dmc_valid)
        if not fl.dmc_valid:
            fl.mag_fused = False
            self._set_mode("gyro_only", "DMC says invalid")
            self._refresh()
            return False
        self.vqf.updateMag(np.ascontiguousarray(mag_nt, dtype=float) * 1e-3)  # µT: VQF's norm tests are relative
        if self._first_mag_t is None:
            self._first_mag_t = t
        disturbed = bool(self.vqf.getMagDistDetected())
        fl.mag_fused = not disturbed
        fl.field_inconsistent = disturbed
        if not disturbed:
            self._last_fused_t = t
        if self.mode == "initialising":
            if t - self._first_mag_t >= max(self.settings.init_duration_s, 1.0):
                self._set_mode("magnetic", "aligned")
        elif disturbed:
            self._set_mode("gyro_only", "VQF: magnetic disturbance detected")
        else:
            self._set_mode("magnetic", "VQF: field usable" if self.mode == "gyro_only" else "DMC cleared")
        self._refresh()
        return fl.mag_fused

    def _refresh(self) -> None:
        q = self.vqf.getQuat9D()
        self.q = core._qmul(self._qd, (float(q[0]), float(q[1]), float(q[2]), float(q[3])))
        st = self.states
        since = 0.0 if self._last_fused_t is None else max(0.0, self.t_s - self._last_fused_t)
        bias, bias_sigma = self.vqf.getBiasEstimate()
        st.gyro_bias_rad_s = tuple(float(b) for b in bias)
        st.time_since_mag_fused_s = since
        st.heading_std_rad = math.hypot(self.HEADING_FLOOR_RAD, float(bias_sigma) * since)
        st.mag_innovation_rad = None  # VQF has no innovation test (its delta is a filtered offset)
        st.mag_test_ratio = None
        self.flags.initialising = self.mode == "initialising"
        self.flags.heading_uncertain = self.mode != "magnetic" and st.heading_std_rad > self.settings.heading_alarm_std_rad


class VqfHeadingFuser(HeadingFuser):
    """The heading role computed by VQF (same keys and messages as the EKF)."""

    impl = "vqf"
    Settings = Settings

    def make_filter(self, settings: core.Settings):
        return VqfFilter(settings)
