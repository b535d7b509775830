"""The implementations of the ``dmc_detector`` role, by name.

``threshold``    stage 1: four threshold tests on the two compasses             (service.py)
``fcm``          loose stage 1, then fuzzy c-means credibility K_c > 0.8         (trained centres)
``single``       one compass: |Δm| and dΔm only, the paper's Table 2 baseline
``quasistatic``  one magnetometer + gyro: window variance and heading-change test
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magmesh import runtime
from schemas import keys
from services.physical import refuse_unphysical

from . import core, fcm, fleet, quasistatic
from .core import HysteresisSettings
from .service import DmcDetectorService, Settings, ThresholdDmcDetector, VehicleState

# ---- fcm ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FcmSettings:
    sensor_a: str = "1"
    sensor_b: str = "2"
    pair_tolerance_s: float = 0.005
    model_path: str = ""  # trained centres; "" = models/dmc_fcm_v1.json
    kc_min: float = 0.0  # valid when K_c > kc_min; 0 = the model's (0.8, the paper's)
    raise_after_s: float = HysteresisSettings.raise_after_s
    clear_after_s: float = HysteresisSettings.clear_after_s
    severity: str = "warning"

    def __post_init__(self):
        if self.severity not in ("warning", "critical"):
            raise ValueError(f"severity must be warning or critical, got {self.severity!r}")
        if not 0 <= self.kc_min < 1:
            raise ValueError(f"kc_min must be in [0, 1), got {self.kc_min}")
        keys.check_id(self.sensor_a, "sensor_a")
        keys.check_id(self.sensor_b, "sensor_b")

    def hysteresis(self) -> HysteresisSettings:
        return HysteresisSettings(self.raise_after_s, self.clear_after_s)


class FcmDmcDetector(DmcDetectorService):
    """Loose stage-1 thresholds, then the fuzzy c-means credibility K_c from trained centres."""

    impl = "fcm"
    Settings = FcmSettings

    def on_start(self) -> None:
        path = Path(self.settings.model_path) if self.settings.model_path else fcm.DEFAULT_MODEL
        self.model = fcm.FcmModel.load(path)
        self.log.info("FCM model %s: %s features, %d centres, trained on %s", path, self.model.feature_set,
                      len(self.model.centres), ", ".join(self.model.training.get("drives", [])) or "?")
        super().on_start()

    def make_fleet(self):
        if not hasattr(self, "model"):
            self.on_start()
        s = self.settings
        return fleet.FleetFcmDetector(self.model, fcm.FcmDetectorSettings(s.hysteresis(), s.kc_min or None, 0.0),
                                      capacity=64)

    def status_extra(self) -> dict:
        out = super().status_extra()
        if hasattr(self, "model"):
            out["model"] = {"feature_set": self.model.feature_set, "kc_min": self.model.kc_min,
                            "training": self.model.training}
        return out


# ---- single -------------------------------------------------------------------------------------


class SingleDmcDetector(DmcDetectorService):
    """One compass (sensor_a) only: |Δm| < V_Δm and |dΔm| < V_dΔm. The heading-difference tests are absent."""

    impl = "single"
    CONSUMES = ("clean/mag/{sensor}", "cal/params/{sensor}")

    @property
    def required_sensors(self) -> tuple[str, ...]:
        return (self.settings.sensor_a,)

    def subscriptions(self) -> list[str]:
        p, a = self.vehicle_pattern, self.settings.sensor_a
        return [keys.clean_mag(p, a), keys.cal_params(p, a)]

    def make_fleet(self):
        s = self.settings
        return fleet.FleetSingleDetector(core.ThresholdDetectorSettings(
            s.thresholds(), s.feature_settings(), s.hysteresis()), capacity=64)

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        if info.sensor != self.settings.sensor_a:
            self.count_drop(info.key, "sensor_not_used")
            return
        if info.kind == "cal":
            self._on_params(info, msg, state)
            return
        b = np.asarray(msg["b_nt"], float)
        self._on_epoch(info, state, msg["t_s"], b, b)

    def _frame_epochs(self, fr):
        """One compass: every sample of it is an epoch."""
        sa = fr.streams.get(f"mag/{self.settings.sensor_a}")
        if sa is None:
            return None
        slot = self._frame_slots(fr, [sa])[sa.vi]
        b = np.ascontiguousarray(sa.cols["b_nt"], float)
        return fleet.Epochs(slot, sa.t_s, sa.t_s, b, b)


# ---- quasistatic --------------------------------------------------------------------------------


@dataclass(frozen=True)
class QuasiStaticServiceSettings:
    sensor: str = "1"
    window_s: float = quasistatic.QuasiStaticSettings.window_s
    var_threshold_nt2: float = quasistatic.QuasiStaticSettings.var_threshold_nt2
    dpsi_threshold_deg: float = quasistatic.QuasiStaticSettings.dpsi_threshold_deg
    variance_of: str = quasistatic.QuasiStaticSettings.variance_of
    dm_threshold_nt: float = quasistatic.QuasiStaticSettings.dm_threshold_nt
    level: str = quasistatic.QuasiStaticSettings.level
    max_imu_lag_s: float = quasistatic.QuasiStaticSettings.max_imu_lag_s
    raise_after_s: float = HysteresisSettings.raise_after_s
    clear_after_s: float = HysteresisSettings.clear_after_s
    severity: str = "warning"

    def __post_init__(self):
        if self.severity not in ("warning", "critical"):
            raise ValueError(f"severity must be warning or critical, got {self.severity!r}")
        keys.check_id(self.sensor, "sensor")
        self.core()

    def core(self) -> quasistatic.QuasiStaticSettings:
        return quasistatic.QuasiStaticSettings(
            window_s=self.window_s, var_threshold_nt2=self.var_threshold_nt2,
            dpsi_threshold_deg=self.dpsi_threshold_deg, variance_of=self.variance_of,
            dm_threshold_nt=self.dm_threshold_nt, level=self.level, max_imu_lag_s=self.max_imu_lag_s,
            hysteresis=HysteresisSettings(self.raise_after_s, self.clear_after_s))


class QuasiStaticDmcDetector(DmcDetectorService):
    """One magnetometer + gyro: sliding-window variance and magnetometer-vs-gyro heading change (docs/methods.md#quasi-static)."""

    impl = "quasistatic"
    Settings = QuasiStaticServiceSettings
    CONSUMES = ("clean/mag/{sensor}", "clean/imu", "cal/params/{sensor}")

    @property
    def sensors(self) -> tuple[str, str]:
        return (self.settings.sensor, self.settings.sensor)

    @property
    def required_sensors(self) -> tuple[str, ...]:
        return (self.settings.sensor,)

    def subscriptions(self) -> list[str]:
        p, a = self.vehicle_pattern, self.settings.sensor
        return [keys.clean_mag(p, a), keys.clean_imu(p), keys.cal_params(p, a)]

    on_frame = None  # per vehicle only: the runtime hands each vehicle's frame rows to on_message

    def new_vehicle(self, vehicle: str) -> VehicleState:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        st = VehicleState(None, self.make_detector(vehicle, 0.0), declination_rad=float(cfg.get("declination_rad", 0.0)))
        self._load_manifest_params(vehicle, cfg, st)
        return st

    def make_fleet(self):
        return None

    def make_detector(self, vehicle: str, dh_ref_rad: float):
        return quasistatic.QuasiStaticDetector(self.settings.core())

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        if info.stream != "imu" and info.sensor != self.settings.sensor:
            self.count_drop(info.key, "sensor_not_used")
            return
        if info.kind == "cal":
            self._on_params(info, msg, state)
            return
        if info.stream == "imu":
            decisions = state.detector.add_imu(msg["t_s"], msg["gyro_rad_s"], msg["accel_m_s2"])
        else:
            if not self._have_params(info, state):
                return
            decisions = state.detector.add_mag(msg["t_s"], msg["b_nt"], state.params[self.settings.sensor],
                                               state.declination_rad)
        for d in decisions:
            self._publish(info.vehicle, state, d, self._param_source(state))


IMPLEMENTATIONS: dict[str, type[DmcDetectorService]] = {
    "threshold": ThresholdDmcDetector,
    "fcm": FcmDmcDetector,
    "single": SingleDmcDetector,
    "quasistatic": QuasiStaticDmcDetector,
}
DEFAULT_IMPL = "threshold"
__all__ = ["IMPLEMENTATIONS", "DEFAULT_IMPL", "Settings", "pop_impl_arg"]


def pop_impl_arg(argv: list[str]) -> tuple[str, list[str]]:
    """Take ``--impl NAME`` / ``--impl=NAME`` out of argv; an unknown name exits with the known ones."""
    return runtime.pop_impl_arg(argv, "dmc_detector", IMPLEMENTATIONS, DEFAULT_IMPL)
