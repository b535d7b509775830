"""Heading fuser service: clean IMU + calibrated magnetometer + DMC verdict → fused heading.

CONSUMES  magmesh/{vehicle}/clean/imu             gyro + accelerometer (drives the filter's clock)
          magmesh/{vehicle}/cal/mag/{sensor}      calibrated field from the calibration service
          magmesh/{vehicle}/clean/mag/{sensor}    fallback when no cal/mag arrives: compensated here with the
                                                  latest cal/params, else the manifest's ``mag_params``
          magmesh/{vehicle}/cal/params/{sensor}   parameters for that fallback
          magmesh/{vehicle}/dmc                   the DMC's ``valid`` flag (docs/methods.md#dmc)
PRODUCES  magmesh/{vehicle}/heading               heading/pitch/roll, 1-σ, mode, mag innovation and test ratio
          magmesh/{vehicle}/alarm/heading         heading σ past ``heading_alarm_std_rad`` while not magnetic

The filter is :class:`services.heading_fuser.core.HeadingFilter` (``--impl ekf``, the default; run by its compiled
twin :class:`services.heading_fuser.compiled.CompiledHeadingFilter` unless ``compiled = false``) or the
``vqf`` library's VQF (``--impl vqf``, :mod:`services.heading_fuser.vqf_impl`); this file is wiring only.
Manifest vehicle keys used: ``declination_rad``, ``heading_profile`` (a name from
:mod:`services.heading_fuser.profiles`, e.g. ``imu_only``) and ``mag_params.{sensor}`` (offset_nt,
matrix, field_radius_nt). New calibration parameters re-base the filter's field reference.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass, field

from magmesh.magcal import MagParams
from magmesh.runtime import Service
from schemas import keys
from services.physical import refuse_unphysical

from . import core, profiles

MAX_PENDING = 2000


@dataclass(frozen=True)
class Settings(core.Settings):
    """Service settings: every filter setting (see core.Settings) plus the wiring ones below."""

    sensor: str = "1"  # which magnetometer steers the heading
    profile: str = ""  # base settings (profiles.py); "" → the vehicle's heading_profile, else road_vehicle
    publish_period_s: float = 0.1  # heading messages at most this often (sample time; 0: every IMU sample)
    cal_timeout_s: float = 1.0  # without cal/mag for this long, fall back to clean/mag + parameters
    dmc_timeout_s: float = 2.0  # a DMC verdict older than this is ignored (the filter's own checks remain)
    dmc_wait_wall_s: float = 1.0  # a magnetometer sample waits at most this long (wall clock) for its verdict
    mag_wait_s: float = 0.2  # the IMU waits at most this long (sample time) for the magnetometer stream;
    # later samples are levelled with the attitude of their own time (kept for a few seconds)
    max_imu_gap_s: float = 1.0  # a longer gap in the IMU stream restarts the filter
    alarm_clear_frac: float = 0.8  # clear the alarm below this fraction of heading_alarm_std_rad
    compiled: bool = True  # the compiled filter (compiled.py, numba; same results); false: core.HeadingFilter


@dataclass
class VehicleState:
    filter: core.HeadingFilter
    last_imu_t: float | None = None
    last_cal_t: float = -math.inf
    last_pub_t: float = -math.inf
    dmc_valid: bool | None = None
    dmc_credibility: float | None = None
    dmc_t: float = -math.inf
    dmc_hist: deque = field(default_factory=lambda: deque(maxlen=4096))  # (t_s, valid) of recent verdicts
    params: MagParams | None = None
    param_source: str = "none"
    n_transitions_logged: int = 0
    alarm_raised: bool = False
    alarm_raised_t: float | None = None
    pending_mag: deque = field(default_factory=deque)  # (t_s, b_nt, key) waiting for the IMU / DMC verdict
    pending_imu: deque = field(default_factory=deque)  # (t_s, gyro, accel) not yet stepped
    newest_imu_t: float | None = None
    newest_mag_t: float | None = None


class HeadingFuser(Service):
    """The project's quaternion EKF with DMC switching and guarded re-acquisition (core.py)."""

    role = "heading_fuser"
    impl = "ekf"
    Settings = Settings
    CONSUMES = ("clean/imu", "cal/mag/{sensor}", "clean/mag/{sensor}", "cal/params/{sensor}", "dmc")
    ADOPTS_RESTORED_ALARMS = True  # a restored raised heading alarm stays until the filter's σ falls again
    PRODUCES = ("heading", "alarm/heading")

    def subscriptions(self) -> list[str]:
        p, s = self.vehicle_pattern, self.settings.sensor
        return [keys.clean_imu(p), keys.cal_mag(p, s), keys.clean_mag(p, s), keys.cal_params(p, s), keys.dmc(p)]

    def profile_name(self, vehicle: str) -> str:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        return self.settings.profile or str(cfg.get("heading_profile") or profiles.ROAD_VEHICLE)

    def core_settings(self, vehicle: str) -> core.Settings:
        """The profile's settings, then every filter setting given to this service (one that differs
        from the default) on top, then the vehicle's declination."""
        values = profiles.values(self.profile_name(vehicle))
        for f in dataclasses.fields(core.Settings):
            v = getattr(self.settings, f.name)
            if v != f.default and not (isinstance(v, float) and math.isnan(v) and math.isnan(f.default)):
                values[f.name] = v
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        if "declination_rad" in cfg:
            values["declination_rad"] = float(cfg["declination_rad"])
        return core.Settings(**values)

    def make_filter(self, settings: core.Settings):
        """The compiled filter (``compiled``, the default) once its kernels are compiled or cached; until then
        (a cold numba cache) the reference, while a background process compiles them: same results."""
        if self.settings.compiled:
            from . import compiled

            if compiled.kernels_ready():
                return compiled.CompiledHeadingFilter(settings)
            compiled.warm_in_background(self.log)
        return core.HeadingFilter(settings)

    def on_start(self) -> None:
        super().on_start()
        for vehicle in self.vehicles_config:
            name = self.profile_name(vehicle)
            if name not in profiles.PROFILES:
                raise SystemExit(f"heading_fuser: vehicle {vehicle}: unknown heading profile {name!r}; known: "
                                 f"{', '.join(profiles.PROFILES)}")

    def new_vehicle(self, vehicle: str) -> VehicleState:
        st = VehicleState(self.make_filter(self.core_settings(vehicle)))
        st.alarm_raised = self.holds_alarm(vehicle, "heading")  # after a restart: the latch as the mesh knows it
        st.alarm_raised_t = self.held_alarm_raised_t_s(vehicle, "heading")  # its clear names the raise time
        table = ((self.vehicles_config.get(vehicle, {}) or {}).get("mag_params") or {}).get(self.settings.sensor)
        if table:
            try:
                st.params, st.param_source = MagParams.from_message(table), "manifest"
            except (TypeError, ValueError) as e:
                self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, self.settings.sensor, e)
        self.log.info("vehicle %s: heading filter %s started (profile %s, declination %.2f°, fallback parameters: %s)",
                      vehicle, self.impl, self.profile_name(vehicle), math.degrees(st.filter.settings.declination_rad),
                      st.param_source)
        return st

    # ---- inputs -------------------------------------------------------------------------------
    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        kind, stream = info.kind, info.stream
        if info.sensor is not None and info.sensor != self.settings.sensor:
            self.count_drop(info.key, f"not the fused magnetometer (sensor {self.settings.sensor})")
            return
        if kind == "clean" and stream == "imu":
            if state.newest_imu_t is not None and msg["t_s"] <= state.newest_imu_t:
                self.count_drop(info.key, "IMU sample not after the previous one")
                return
            state.newest_imu_t = msg["t_s"]
            state.pending_imu.append((msg["t_s"], msg["gyro_rad_s"], msg["accel_m_s2"]))
            self._drain(info.vehicle, state)
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
                new = MagParams.from_message(msg)
                changed = state.params is not None and not _same_params(state.params, new)
                state.params, state.param_source = new, "cal"
                if changed:
                    # the calibrated field changes scale and direction with the parameters: the field
                    # reference learned under the old ones is re-learned, the magnetometer stays in use
                    self.log.info("vehicle %s: new calibration parameters at t=%.2f s: field reference re-based",
                                  info.vehicle, msg["t_s"])
                    state.filter.rebase_field_reference()
            else:
                self.count_drop(info.key, f"parameters with status {msg['status']!r} not used")
        elif kind == "dmc":
            state.dmc_valid, state.dmc_credibility, state.dmc_t = msg["valid"], msg["credibility"], msg["t_s"]
            state.dmc_hist.append((msg["t_s"], msg["valid"]))
            self._drain(info.vehicle, state)

    def _on_mag(self, info, t: float, b_nt, st: VehicleState) -> None:
        if st.newest_imu_t is None:
            self.count_drop(info.key, "no IMU sample yet")
            return
        st.newest_mag_t = t if st.newest_mag_t is None else max(st.newest_mag_t, t)
        st.pending_mag.append((t, b_nt, info.key, time.monotonic()))
        if len(st.pending_mag) > MAX_PENDING:
            self.count_drop(st.pending_mag.popleft()[2], "neither the IMU nor the DMC verdict reached its time")
        self._drain(info.vehicle, st)

    def _drain(self, vehicle: str, st: VehicleState) -> None:
        """Advance the filter through the waiting IMU and magnetometer samples in time order.

        The streams arrive on separate subscriptions, in bursts when the mesh runs faster than real
        time; the filter must see them interleaved by time (a field sample levelled with an attitude
        seconds off would be wrong). A magnetometer sample waits until the IMU has reached its time and,
        while a DMC stream is alive, until the DMC verdict for its time has arrived; a verdict more than
        ``dmc_timeout_s`` behind the newest IMU sample is not waited for.
        """
        while True:
            mag = st.pending_mag[0] if st.pending_mag else None
            if mag is not None and st.last_imu_t is not None and mag[0] <= st.last_imu_t + 1e-6:
                t = mag[0]
                dmc, ready = None, True
                if st.dmc_hist:
                    if st.dmc_hist[-1][0] >= t - 1e-6:
                        dmc = self._verdict_at(st, t)
                    elif self._verdict_due(st, mag):
                        ready = False  # the verdict for this time is on its way
                if ready:
                    st.pending_mag.popleft()
                    st.filter.update_mag(mag[1], dmc, t_s=t)  # levelled with the attitude of its own time
                    continue
            imu = st.pending_imu[0] if st.pending_imu else None
            if imu is None:
                break
            if mag is not None and mag[0] < imu[0] - 1e-9 and st.last_imu_t is not None and mag[0] <= st.last_imu_t + 1e-6:
                # that magnetometer sample waits for its DMC verdict: the IMU goes on (up to the timeout)
                if self._verdict_due(st, mag) and len(st.pending_imu) < MAX_PENDING:
                    break
            elif (st.newest_mag_t is not None and imu[0] > st.newest_mag_t + 1e-6
                    and st.newest_imu_t - st.newest_mag_t <= self.settings.mag_wait_s
                    and len(st.pending_imu) < MAX_PENDING):
                break  # the magnetometer stream has not reached this time yet: wait a little for it
            st.pending_imu.popleft()
            self._step_imu(vehicle, imu, st)
        self._log_transitions(vehicle, st)

    def _step_imu(self, vehicle: str, imu: tuple, st: VehicleState) -> None:
        t, gyro, accel = imu
        f = st.filter
        dt = 0.0 if st.last_imu_t is None else t - st.last_imu_t
        if dt > self.settings.max_imu_gap_s:
            self.log.warning("vehicle %s: IMU gap of %.2f s at t=%.2f s: restarting the heading filter", vehicle, dt, t)
            f.reset()
            st.n_transitions_logged = 0
            dt = 0.0
        st.last_imu_t = t
        f.update_imu(gyro, accel, dt, t_s=t)
        if f.aligned:
            self._check_alarm(vehicle, t, st)
            if t - st.last_pub_t >= self.settings.publish_period_s - 1e-9:
                st.last_pub_t = t
                self._publish(vehicle, t, st)

    def _verdict_due(self, st: VehicleState, mag: tuple) -> bool:
        """Whether a magnetometer sample still waits for its DMC verdict: while the DMC stream is alive
        and the sample has waited less than ``dmc_wait_wall_s`` of wall-clock time. Bounded in wall
        time, not sample time, so that at any replay speed a verdict that is merely late (a busy
        detector) is still used, and one that never comes holds the heading back at most that long.
        The verdict's own age in sample time (``dmc_timeout_s``) still ends the wait when the
        detector has stopped."""
        if not st.dmc_hist:
            return False
        if mag[0] - st.dmc_hist[-1][0] > self.settings.dmc_timeout_s:
            return False  # the detector has fallen silent: its last verdict is too old to wait on
        return time.monotonic() - mag[3] < self.settings.dmc_wait_wall_s

    @staticmethod
    def _verdict_at(st: VehicleState, t: float) -> bool | None:
        for tv, valid in reversed(st.dmc_hist):
            if tv <= t + 1e-6:
                return valid
        return None

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
                       f"heading uncertainty {math.degrees(h_std):.1f}° after {f.internal_states.time_since_mag_fused_s:.0f} s "
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
                "profile": self.profile_name(vehicle),
                "field_rebases": getattr(f, "n_rebases", 0),
                "dmc_valid": st.dmc_valid,
                "alarm_raised": st.alarm_raised,
            }
        return {"vehicles": out}


REBASE_CHANGE_FRAC = 0.005  # parameters that move the calibrated field by less than this do not re-base


def _same_params(a: MagParams, b: MagParams) -> bool:
    """Whether two parameter sets calibrate alike: the largest change of the calibrated field, over
    raw fields on the sphere of ``a`` (its offset ± radius along each axis), relative to the radius,
    is below :data:`REBASE_CHANGE_FRAC`."""
    import numpy as np

    r = float(a.field_radius_nt) or 50_000.0
    raw = a.offset + r * np.vstack([np.eye(3), -np.eye(3)])
    d = np.linalg.norm(a.apply(raw) - b.apply(raw), axis=1)
    return bool(np.max(d) / r < REBASE_CHANGE_FRAC)
