"""Heading fuser service: clean IMU + calibrated magnetometer + DMC verdict → fused heading.

CONSUMES  magmesh/{vehicle}/clean/imu             gyro + accelerometer (drives the filter's clock)
          magmesh/{vehicle}/cal/mag/{sensor}      calibrated field from the calibration service
          magmesh/{vehicle}/clean/mag/{sensor}    fallback when no cal/mag arrives: compensated here with the
                                                  latest cal/params, else the manifest's ``mag_params``
          magmesh/{vehicle}/cal/params/{sensor}   parameters for that fallback
          magmesh/{vehicle}/dmc                   the DMC's ``valid`` flag (ALGORITHMS.md §1)
PRODUCES  magmesh/{vehicle}/heading               heading/pitch/roll, 1-σ, mode, mag innovation and test ratio
          magmesh/{vehicle}/alarm/heading         heading σ past ``heading_alarm_std_rad`` while not magnetic

The filter is :class:`services.heading_fuser.core.HeadingFilter`; this file is wiring only. Manifest
vehicle keys used: ``declination_rad`` and ``mag_params.{sensor}`` (offset_nt, matrix, field_radius_nt).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field

from magmesh.magcal import MagParams
from magmesh.runtime import Service
from schemas import keys
from services.physical import refuse_unphysical

from . import core


MAX_PENDING_MAG = 500


@dataclass(frozen=True)
class Settings(core.Settings):
    """Service settings: every filter setting (see core.Settings) plus the wiring ones below."""

    sensor: str = "1"  # which magnetometer steers the heading
    publish_period_s: float = 0.1  # heading messages at most this often (sample time; 0: every IMU sample)
    cal_timeout_s: float = 1.0  # without cal/mag for this long, fall back to clean/mag + parameters
    dmc_timeout_s: float = 2.0  # a DMC verdict older than this is ignored (the filter's own checks remain)
    max_imu_gap_s: float = 1.0  # a longer gap in the IMU stream restarts the filter
    alarm_clear_frac: float = 0.8  # clear the alarm below this fraction of heading_alarm_std_rad


@dataclass
class VehicleState:
    filter: core.HeadingFilter
    last_imu_t: float | None = None
    last_cal_t: float = -math.inf
    last_pub_t: float = -math.inf
    dmc_valid: bool | None = None
    dmc_credibility: float | None = None
    dmc_t: float = -math.inf
    params: MagParams | None = None
    param_source: str = "none"
    n_transitions_logged: int = 0
    alarm_raised: bool = False
    alarm_raised_t: float | None = None
    pending_mag: deque = field(default_factory=deque)  # (t_s, b_nt, key) waiting for the IMU to reach t_s


class HeadingFuser(Service):
    role = "heading_fuser"
    impl = "ekf"
    Settings = Settings
    CONSUMES = ("clean/imu", "cal/mag/{sensor}", "clean/mag/{sensor}", "cal/params/{sensor}", "dmc")
    PRODUCES = ("heading", "alarm/heading")

    def subscriptions(self) -> list[str]:
        p, s = self.vehicle_pattern, self.settings.sensor
        return [keys.clean_imu(p), keys.cal_mag(p, s), keys.clean_mag(p, s), keys.cal_params(p, s), keys.dmc(p)]

    def core_settings(self, vehicle: str) -> core.Settings:
        names = {f.name for f in dataclasses.fields(core.Settings)}
        values = {n: getattr(self.settings, n) for n in names}
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        if "declination_rad" in cfg:
            values["declination_rad"] = float(cfg["declination_rad"])
        return core.Settings(**values)

    def new_vehicle(self, vehicle: str) -> VehicleState:
        st = VehicleState(core.HeadingFilter(self.core_settings(vehicle)))
        table = ((self.vehicles_config.get(vehicle, {}) or {}).get("mag_params") or {}).get(self.settings.sensor)
        if table:
            try:
                st.params, st.param_source = MagParams.from_message(table), "manifest"
            except (TypeError, ValueError) as e:
                self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, self.settings.sensor, e)
        self.log.info("vehicle %s: heading filter started (declination %.2f°, fallback parameters: %s)", vehicle,
                      math.degrees(st.filter.settings.declination_rad), st.param_source)
        return st

    # ---- inputs -------------------------------------------------------------------------------
    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        kind, stream = info.kind, info.stream
        if kind == "clean" and stream == "imu":
            self._on_imu(info, msg, state)
        elif kind == "cal" and stream == "mag":
            state.last_cal_t = msg["t_s"]
            self._on_mag(info, msg["t_s"], msg["b_nt"], state)
        elif kind == "clean" and stream == "mag":
            if msg["t_s"] - state.last_cal_t <= self.settings.cal_timeout_s:
                self.count_drop(info.key, "calibrated stream cal/mag in use")
            elif state.params is None:
                self.count_drop(info.key, "no calibration parameters yet (cal/params or manifest mag_params)")
            else:
                self._on_mag(info, msg["t_s"], state.params.apply(msg["b_nt"]), state)
        elif kind == "cal" and stream == "params":
            if msg["status"] in ("ok", "manifest"):
                state.params, state.param_source = MagParams.from_message(msg), "cal"
            else:
                self.count_drop(info.key, f"parameters with status {msg['status']!r} not used")
        elif kind == "dmc":
            state.dmc_valid, state.dmc_credibility, state.dmc_t = msg["valid"], msg["credibility"], msg["t_s"]

    def _on_imu(self, info, msg: dict, st: VehicleState) -> None:
        t = msg["t_s"]
        f = st.filter
        if st.last_imu_t is not None:
            dt = t - st.last_imu_t
            if dt <= 0.0:
                self.count_drop(info.key, "IMU sample not after the previous one")
                return
            if dt > self.settings.max_imu_gap_s:
                self.log.warning("vehicle %s: IMU gap of %.2f s at t=%.2f s: restarting the heading filter",
                                 info.vehicle, dt, t)
                f.reset()
                st.n_transitions_logged = 0
                st.pending_mag.clear()
                dt = 0.0
        else:
            dt = 0.0
        st.last_imu_t = t
        f.update_imu(msg["gyro_rad_s"], msg["accel_m_s2"], dt, t_s=t)
        # magnetometer samples are fused in time order, after the IMU step of their time
        while st.pending_mag and st.pending_mag[0][0] <= t + 1e-6:
            tm, b, _ = st.pending_mag.popleft()
            self._fuse_mag(info.vehicle, tm, b, st)
        self._log_transitions(info.vehicle, st)
        if f.aligned:
            self._check_alarm(info.vehicle, t, st)
            if t - st.last_pub_t >= self.settings.publish_period_s - 1e-9:
                st.last_pub_t = t
                self._publish(info.vehicle, t, st)

    def _on_mag(self, info, t: float, b_nt, st: VehicleState) -> None:
        if st.last_imu_t is None:
            self.count_drop(info.key, "no IMU sample yet")
            return
        if t > st.last_imu_t + 1e-6:  # the IMU has not reached this sample's time yet: wait for it
            st.pending_mag.append((t, b_nt, info.key))
            if len(st.pending_mag) > MAX_PENDING_MAG:
                self.count_drop(st.pending_mag.popleft()[2], "no IMU sample reached its time")
            return
        self._fuse_mag(info.vehicle, t, b_nt, st)

    def _fuse_mag(self, vehicle: str, t: float, b_nt, st: VehicleState) -> None:
        dmc = st.dmc_valid if abs(t - st.dmc_t) <= self.settings.dmc_timeout_s else None
        st.filter.update_mag(b_nt, dmc, t_s=t)
        self._log_transitions(vehicle, st)

    # ---- outputs ------------------------------------------------------------------------------
    def _publish(self, vehicle: str, t: float, st: VehicleState) -> None:
        f = st.filter
        heading, pitch, roll = f.euler()
        h_std, p_std, r_std = f.attitude_std()
        s = f.internal_states
        self.publish(
            keys.heading(vehicle), "heading", vehicle, t,
            heading_rad=heading, pitch_rad=pitch, roll_rad=roll,
            heading_std_rad=h_std, pitch_std_rad=p_std, roll_std_rad=r_std,
            mode=f.mode, mag_innovation_rad=s.mag_innovation_rad, mag_test_ratio=s.mag_test_ratio,
            mag_fused=f.flags.mag_fused,
        )

    def _check_alarm(self, vehicle: str, t: float, st: VehicleState) -> None:
        f, s = st.filter, self.settings
        h_std = f.internal_states.heading_std_rad
        if not st.alarm_raised and f.flags.heading_uncertain:
            st.alarm_raised, st.alarm_raised_t = True, t
            self.alarm(vehicle, "heading", "raised", "warning",
                       f"heading uncertainty {math.degrees(h_std):.1f}° after {f.internal_states.gyro_only_duration_s:.0f} s "
                       f"without a usable magnetometer (mode {f.mode})",
                       h_std, s.heading_alarm_std_rad, t, unit="rad")
        elif st.alarm_raised and (f.mode == "magnetic" or h_std < s.alarm_clear_frac * s.heading_alarm_std_rad):
            st.alarm_raised = False
            self.alarm(vehicle, "heading", "cleared", "warning",
                       f"heading uncertainty back to {math.degrees(h_std):.1f}° (mode {f.mode})",
                       h_std, s.heading_alarm_std_rad, t, unit="rad", raised_t_s=st.alarm_raised_t)

    def _log_transitions(self, vehicle: str, st: VehicleState) -> None:
        tr = st.filter.transitions
        while st.n_transitions_logged < len(tr):
            t, a, b, why = tr[st.n_transitions_logged]
            self.log.info("vehicle %s: t=%.2f s heading mode %s → %s (%s)", vehicle, t, a, b, why)
            st.n_transitions_logged += 1
        if len(tr) > 1000:  # keep the list short on long runs
            del tr[:500]
            st.n_transitions_logged -= 500

    def status_extra(self) -> dict:
        out = {}
        for vehicle, st in self.vehicle_states.items():
            f = st.filter
            out[vehicle] = {
                "mode": f.mode,
                "heading_deg": round(math.degrees(f.heading_rad()), 2) if f.aligned else None,
                "heading_std_deg": round(math.degrees(f.internal_states.heading_std_rad), 2),
                "mag_test_ratio": f.internal_states.mag_test_ratio,
                "param_source": st.param_source,
                "dmc_valid": st.dmc_valid,
                "alarm_raised": st.alarm_raised,
            }
        return {"vehicles": out}
