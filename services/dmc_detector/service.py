"""DMC detector: recognises dynamic magnetic interference from two compasses (docs/methods.md#dmc).

Consumes  magmesh/{vehicle}/clean/mag/1, clean/mag/2   the two compasses of the DMC, paired by time
          magmesh/{vehicle}/cal/params/{sensor}        static compensation; overrides the manifest's
Produces  magmesh/{vehicle}/dmc                        features, credibility and validity per epoch
          magmesh/{vehicle}/alarm/dmc                  raised / cleared, with hysteresis

Until ``cal/params`` arrive, the compensation comes from the mesh manifest's vehicle table
(``mag_params.{sensor}`` with offset_nt, matrix, field_radius_nt; ``declination_rad``; optional
``dh_ref_rad``). A 2-D (horizontal) ``cal/params`` set does not replace a 3-D one already held: its
field strength is the horizontal one, which pitch and roll move by hundreds of nT. A vehicle with no
parameters has its epochs counted as dropped, never guessed at.
This module holds the ``threshold`` implementation; the other implementations of the role subclass
:class:`DmcDetectorService` in ``impls.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magmesh.align import TimeAligner
from magmesh.runtime import Service
from schemas import keys
from services.physical import refuse_unphysical

from . import core
from .core import CompassParams, FeatureSettings, HysteresisSettings, Thresholds


@dataclass(frozen=True)
class Settings:
    sensor_a: str = "1"  # the reference compass (its heading is published)
    sensor_b: str = "2"
    pair_tolerance_s: float = 0.005  # samples of the two compasses closer than this form an epoch
    pair_max_wait_s: float = 10.0  # wall-clock seconds a compass sample waits for its partner (then counted)
    dm_threshold_nt: float = Thresholds.dm_nt  # V_Δm
    ddm_threshold_nt_s: float = Thresholds.ddm_nt_s  # V_dΔm
    dh_threshold_deg: float = Thresholds.dh_deg  # V_Δh
    ddh_threshold_deg_s: float = Thresholds.ddh_deg_s  # V_dΔh
    smooth_window_s: float = FeatureSettings.smooth_window_s
    rate_window_s: float = FeatureSettings.rate_window_s
    raise_after_s: float = HysteresisSettings.raise_after_s
    clear_after_s: float = HysteresisSettings.clear_after_s
    severity: str = "warning"  # of alarm/dmc

    def __post_init__(self):
        if self.severity not in ("warning", "critical"):
            raise ValueError(f"severity must be warning or critical, got {self.severity!r}")
        keys.check_id(self.sensor_a, "sensor_a")
        keys.check_id(self.sensor_b, "sensor_b")
        self.thresholds()  # range checks
        self.feature_settings()
        self.hysteresis()

    def thresholds(self) -> Thresholds:
        return Thresholds(self.dm_threshold_nt, self.ddm_threshold_nt_s, self.dh_threshold_deg,
                          self.ddh_threshold_deg_s)

    def feature_settings(self, dh_ref_rad: float = 0.0) -> FeatureSettings:
        return FeatureSettings(self.smooth_window_s, self.rate_window_s, dh_ref_rad)

    def hysteresis(self) -> HysteresisSettings:
        return HysteresisSettings(self.raise_after_s, self.clear_after_s)


@dataclass
class VehicleState:
    aligner: TimeAligner  # joins the two compasses by sample time (magmesh/align.py)
    detector: Any
    declination_rad: float = 0.0
    params: dict[str, CompassParams] = field(default_factory=dict)
    param_origin: dict[str, str] = field(default_factory=dict)  # sensor → "manifest" | "cal"
    ignored_2d: dict[str, str] = field(default_factory=dict)  # sensor → 2-D cal/params id not used (3-D held)
    warned_2d: bool = False
    epochs: int = 0
    n_valid: int = 0
    warned_no_params: bool = False


class DmcDetectorService(Service):
    """Common wiring of every two-compass implementation: pairing, parameters, publishing."""

    role = "dmc_detector"
    impl = "threshold"
    Settings = Settings
    CONSUMES = ("clean/mag/{sensor}", "cal/params/{sensor}")
    ADOPTS_RESTORED_ALARMS = True  # the latch takes the mesh's alarm state (_adopt_published_alarm)
    PRODUCES = ("dmc", "alarm/dmc")

    # ---- hooks for implementations ---------------------------------------------------------
    def make_detector(self, vehicle: str, dh_ref_rad: float) -> Any:
        s = self.settings
        return core.ThresholdDetector(core.ThresholdDetectorSettings(
            s.thresholds(), s.feature_settings(dh_ref_rad), s.hysteresis()))

    # ---- service --------------------------------------------------------------------------
    @property
    def sensors(self) -> tuple[str, str]:
        return (self.settings.sensor_a, self.settings.sensor_b)

    @property
    def required_sensors(self) -> tuple[str, ...]:
        """Sensors whose compensation parameters an epoch needs."""
        return self.sensors

    def subscriptions(self) -> list[str]:
        p = self.vehicle_pattern
        return [keys.clean_mag(p, s) for s in self.sensors] + [keys.cal_params(p, s) for s in self.sensors]

    def new_vehicle(self, vehicle: str) -> VehicleState:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        dh_ref = float(cfg.get("dh_ref_rad", 0.0))
        st = VehicleState(TimeAligner(self.sensors, self.settings.pair_tolerance_s,
                                      float(getattr(self.settings, "pair_max_wait_s", 10.0))),
                          self.make_detector(vehicle, dh_ref),
                          declination_rad=float(cfg.get("declination_rad", 0.0)))
        self._load_manifest_params(vehicle, cfg, st)
        return st

    def _load_manifest_params(self, vehicle: str, cfg: dict, st: VehicleState) -> None:
        for sensor, table in (cfg.get("mag_params") or {}).items():
            sensor = str(sensor)
            if sensor in self.required_sensors:
                try:
                    st.params[sensor] = CompassParams.from_mapping(table, param_id="manifest")
                    st.param_origin[sensor] = "manifest"
                except (KeyError, ValueError, TypeError) as e:
                    self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, sensor, e)

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        if info.sensor not in self.sensors:
            self.count_drop(info.key, "sensor_not_used")
            return
        if info.kind == "cal":
            self._on_params(info, msg, state)
            return
        joined, gave = state.aligner.push(info.sensor, msg["t_s"], msg["b_nt"])
        for g in gave:  # its partner never came (passed), came too late (expired), or too many waited
            self.count_join_loss(keys.clean_mag(info.vehicle, g.stream), info.vehicle,
                                 "unpaired" if g.reason == "passed" else f"unpaired_{g.reason}")
        a, b = self.sensors
        for j in joined:
            self._on_epoch(info, state, j.t_s, np.asarray(j.values[a], float), np.asarray(j.values[b], float))

    def _on_params(self, info, msg: dict, state: VehicleState) -> None:
        if msg["status"] not in ("ok", "manifest"):
            self.log.info("vehicle %s sensor %s: ignoring cal/params %s with status %s", info.vehicle, info.sensor,
                          msg["param_id"], msg["status"])
            return
        try:
            p = CompassParams.from_mapping(msg)
        except (KeyError, ValueError) as e:
            self.count_drop(info.key, "unusable_params")
            self.log.error("vehicle %s sensor %s: unusable cal/params: %s", info.vehicle, info.sensor, e)
            return
        current = state.params.get(info.sensor)
        if p.model == "2d" and current is not None and current.model == "3d":
            # a horizontal fit leaves z uncalibrated, so its Δm can only be the horizontal field strength,
            # which moves with every bit of pitch and roll (B_v sin θ ≈ 300 nT per half degree) and
            # raises false alarms; the 3-D set already held is the better reference for these tests
            state.ignored_2d[info.sensor] = p.param_id
            if not state.warned_2d:
                state.warned_2d = True
                self.log.info("vehicle %s: 2-D cal/params (%s) kept out of the interference tests: a 3-D set is "
                              "held", info.vehicle, p.param_id)
            return
        if current == p:
            return
        state.params[info.sensor] = p
        state.param_origin[info.sensor] = "cal" if msg["status"] == "ok" else "manifest"
        # new compensation: the feature windows restart so no rate spans two parameter sets
        state.detector.restart_features()
        self.log.info("vehicle %s sensor %s: compensation %s from cal/params", info.vehicle, info.sensor,
                      p.param_id)

    def _param_source(self, state: VehicleState) -> str:
        origins = {state.param_origin.get(s) for s in self.required_sensors}
        return "cal" if origins == {"cal"} else "manifest"

    def _on_epoch(self, info, state: VehicleState, t_s: float, b_a, b_b) -> None:
        if not self._have_params(info, state):
            return
        a, b = self.sensors
        d = state.detector.update(t_s, b_a, b_b, state.params[a], state.params[b], state.declination_rad)
        self._publish(info.vehicle, state, d, self._param_source(state))

    def _have_params(self, info, state: VehicleState) -> bool:
        missing = [s for s in self.required_sensors if s not in state.params]
        if not missing:
            return True
        self.count_drop(info.key, "no_compensation_params")
        if not state.warned_no_params:
            state.warned_no_params = True
            self.log.warning("vehicle %s: no compensation parameters for sensor(s) %s (manifest mag_params or "
                             "cal/params); epochs are dropped until they arrive", info.vehicle, ", ".join(missing))
        return False

    def _adopt_published_alarm(self, vehicle: str, state: VehicleState) -> None:
        """After a live swap the runtime carries on the previous holder's alarm state; align the latch
        with it so this instance clears an alarm it did not raise itself (and never raises one twice)."""
        rt = self._runtime
        if getattr(rt, "mode", "active") != "active":
            return
        published = getattr(rt, "alarm_published", {}).get(keys.alarm(vehicle, "dmc"))
        latch = state.detector.latch
        if published is None or (published == "raised") == latch.raised:
            return
        raised_msg = getattr(rt, "raised", {}).get(keys.alarm(vehicle, "dmc")) or {}
        latch.adopt(published == "raised", raised_msg.get("raised_t_s", raised_msg.get("t_s")))
        self.log.info("vehicle %s: alarm state %s adopted from the mesh", vehicle, published)

    def _publish(self, vehicle: str, state: VehicleState, d: core.Decision, param_source: str) -> None:
        state.epochs += 1
        state.n_valid += int(d.valid)
        self.publish(keys.dmc(vehicle), "dmc", vehicle, d.t_s, dm_nt=d.dm_nt, ddm_nt_s=d.ddm_nt_s, dh_rad=d.dh_rad,
                     ddh_rad_s=d.ddh_rad_s, heading_rad=d.heading_rad, stage1_pass=d.stage1_pass,
                     credibility=d.credibility, valid=d.valid, impl=self.impl, param_source=param_source)
        if d.transition is None:
            self._adopt_published_alarm(vehicle, state)
        else:
            reason, value, threshold, unit = state.detector.describe(d)
            raised_t = state.detector.latch.raised_t_s
            extra = {"raised_t_s": raised_t} if raised_t is not None else {}
            self.alarm(vehicle, "dmc", d.transition, self.settings.severity, reason, value, threshold, d.t_s,
                       unit=unit, **extra)

    def status_extra(self) -> dict:
        out = {}
        for v, st in list(self.vehicle_states.items()):
            if st is None:
                continue
            det = st.detector
            out[v] = {"epochs": st.epochs, "valid_frac": round(st.n_valid / st.epochs, 4) if st.epochs else None,
                      "params": {s: {"origin": st.param_origin.get(s), "param_id": p.param_id, "model": p.model}
                                 for s, p in st.params.items()},
                      "cal_params_2d_not_used": dict(st.ignored_2d),
                      "aligner": st.aligner.counts(),
                      "flags": det.flags, "internal_states": det.internal_states}
        return {"detector": out}


class ThresholdDmcDetector(DmcDetectorService):
    """Stage 1 only: the four threshold tests of the differential compass (docs/methods.md#dmc)."""

    impl = "threshold"
