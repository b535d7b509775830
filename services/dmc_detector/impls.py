"""The implementations of the ``dmc_detector`` role, by name.

``threshold``    stage 1: four threshold tests on the two compasses             (service.py)
``fcm``          loose stage 1, then fuzzy c-means credibility K_c > 0.8         (trained centres)
``single``       one compass: |Δm| and dΔm only, the paper's Table 2 baseline
``quasistatic``  one magnetometer + gyro: window variance and heading-change test
``gyro_track``   stage 1, then each compass heading checked against a heading the gyro carries from trusted
                 epochs (magmesh's own second stage; two compasses + gyro)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magmesh import declare, runtime
from magmesh.declare import Input, setting
from schemas import keys
from services.physical import refuse_unphysical

from . import core, fcm, fleet, quasistatic
from .core import HysteresisSettings
from .service import (
    DmcDetectorService,
    Settings,
    ThresholdDmcDetector,
    VehicleState,
    clear_after_setting,
    pair_tolerance_setting,
    raise_after_setting,
    severity_setting,
)

# ---- fcm ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FcmSettings:
    sensor_a: str = setting("1", "the reference compass (its heading is published)")
    sensor_b: str = setting("2", "the second compass of the differential pair")
    pair_tolerance_s: float = pair_tolerance_setting()
    model_path: str = setting("", "trained centres (JSON); \"\" = models/dmc_fcm_v1.json")
    kc_min: float = setting(0.0, "an epoch is valid when its credibility K_c exceeds this; 0 = the model's (0.8, the "
                            "paper's)", lo=0, lt=1)
    raise_after_s: float = raise_after_setting()
    clear_after_s: float = clear_after_setting()
    severity: str = severity_setting()
    shed_after_s: float = runtime.shed_after_setting()

    def __post_init__(self):
        declare.check(self)
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
    INPUTS = (
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "the one compass tested", sensors="sensor_a"),
        Input("magmesh/{vehicle}/cal/params/{sensor}", "its static compensation; overrides the manifest's mag_params",
              sensors="sensor_a"),
    )

    @property
    def required_sensors(self) -> tuple[str, ...]:
        return (self.settings.sensor_a,)

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


_QS = quasistatic.QuasiStaticSettings


@dataclass(frozen=True)
class QuasiStaticServiceSettings:
    sensor: str = setting("1", "the magnetometer tested")
    window_s: float = setting(_QS.window_s, "sliding window L of the variance and heading-change tests", gt=0, hi=60)
    var_threshold_nt2: float = setting(_QS.var_threshold_nt2, "var_initial: the field's variance over the window "
                                       "stays below this when undisturbed (0.8 µT² = 0.8e6 nT²)", gt=0)
    dpsi_threshold_deg: float = setting(_QS.dpsi_threshold_deg, "Δψ_initial: magnetometer and gyro heading changes "
                                        "over the window agree within this (the paper: 0.5 open road, 2 garage; a car "
                                        "leaning in turns needs 2.5)", gt=0)
    variance_of: str = setting(_QS.variance_of, "magnitude: the variance of |h|; components: of m_x, m_y, m_z (the "
                               "paper's)", choices=("magnitude", "components"))
    dm_threshold_nt: float = setting(_QS.dm_threshold_nt, "added test |Δm| = ||h| − R| < this; 0 switches it off (the "
                                     "paper)", lo=0)
    level: str = setting(_QS.level, "body: a near-level vehicle (ψ̇ = −ω_z, level compass); accel: levelled by the "
                         "accelerometer", choices=("body", "accel"))
    max_imu_lag_s: float = setting(_QS.max_imu_lag_s, "a magnetometer epoch is decided without gyro data after this "
                                   "much sample time")
    raise_after_s: float = raise_after_setting()
    clear_after_s: float = clear_after_setting()
    severity: str = severity_setting()
    shed_after_s: float = runtime.shed_after_setting()

    def __post_init__(self):
        declare.check(self)
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
    INPUTS = (
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "the magnetometer tested", sensors="sensor"),
        Input("magmesh/{vehicle}/clean/imu", "the gyro whose heading change the magnetometer's must match"),
        Input("magmesh/{vehicle}/cal/params/{sensor}", "its static compensation; overrides the manifest's mag_params",
              sensors="sensor"),
    )

    @property
    def sensors(self) -> tuple[str, str]:
        return (self.settings.sensor, self.settings.sensor)

    @property
    def required_sensors(self) -> tuple[str, ...]:
        return (self.settings.sensor,)

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


# ---- gyro_track -------------------------------------------------------------------------------


_GT = quasistatic.GyroTrackSettings


@dataclass(frozen=True)
class GyroTrackServiceSettings(Settings):
    """The threshold implementation's settings (stage 1), then the second stage's."""

    gate_deg: float = setting(_GT.gate_deg, "an epoch is valid when its compass heading is within this of the heading "
                              "the gyro carries from trusted epochs", gt=0, lt=90)
    blend_tau_s: float = setting(_GT.blend_tau_s, "the carried heading is pulled towards trusted compass headings "
                                 "with this time constant", gt=0)
    bias_tau_s: float = setting(_GT.bias_tau_s, "the gyro's bias is corrected from trusted epochs with this time "
                                "constant", gt=0)
    bias_init_s: float = setting(_GT.bias_init_s, "the gyro's bias starts as its median rate over the first this many "
                                 "seconds of its stream (the vehicle standing)", lo=0)
    reseed_after_s: float = setting(_GT.reseed_after_s, "stage 1 passing while the headings disagree this long: the "
                                    "carried heading is taken from the compass again (the gyro drifted)", gt=0)
    reacquire_after_s: float = setting(_GT.reacquire_after_s, "… or this long while the tight tests pass too", gt=0)
    reacquire_dm_nt: float = setting(_GT.reacquire_dm_nt, "the tight field-strength test |Δm| of re-acquisition", gt=0)
    reacquire_dh_deg: float = setting(_GT.reacquire_dh_deg, "the tight heading-difference test |Δh| of re-acquisition",
                                      gt=0)
    trust_dm_nt: float = setting(_GT.trust_dm_nt, "a trusted epoch pulls with weight 1 / (1 + (|Δm|/this)² + "
                                 "(|Δh|/trust_dh_deg)²)", gt=0)
    trust_dh_deg: float = setting(_GT.trust_dh_deg, "see trust_dm_nt", gt=0)
    max_gyro_gap_s: float = setting(_GT.max_gyro_gap_s, "gyro samples further apart than this (shed, lost, a stalled "
                                    "stream) lose the carried heading: it is taken from the compass again at the "
                                    "next epoch stage 1 passes", gt=0)
    max_init_bias_rad_s: float = setting(_GT.max_init_bias_rad_s, "the rest window's median rate is taken for the "
                                         "gyro's bias only if within this and steady (else 0: the stream was joined "
                                         "while the vehicle moved)", gt=0)
    reference: str = setting(_GT.reference, "how the reference heading is carried: blend (pulled towards each "
                             "trusted compass heading; the settings above) or consensus (fitted to the stage-1 epochs of "
                             "the last consensus_window_s, robustly: a source that bends the heading alike for minutes "
                             "is not taken for it; chosen on the turntable, docs/methods.md#dmc-gyro-track)",
                             choices=quasistatic.REFERENCES)
    consensus_window_s: float = setting(_GT.consensus_window_s, "consensus: the stage-1 epochs this far back make up "
                                        "the fit", gt=0)
    consensus_recent_s: float = setting(_GT.consensus_recent_s, "consensus: a lost fit is found again among the "
                                        "stage-1 epochs this recent (at most consensus_window_s)", gt=0)
    consensus_scale_deg: float = setting(_GT.consensus_scale_deg, "consensus: epochs further than this from the fit "
                                         "have no weight in it (Tukey's biweight)", gt=0)
    consensus_inlier_deg: float = setting(_GT.consensus_inlier_deg, "consensus: an epoch within this of the fit "
                                          "supports it", gt=0)
    consensus_min_support: int = setting(_GT.consensus_min_support, "consensus: a fit fewer epochs support is lost "
                                         "(nothing valid until found again)", unit="epochs", lo=2)
    consensus_bias_prior_deg_s: float = setting(_GT.consensus_bias_prior_deg_s, "consensus: the gyro bias the fit "
                                                "learns is held to its value at rest by this (1-σ)", gt=0)
    consensus_bin_s: float = setting(_GT.consensus_bin_s, "consensus: one stage-1 epoch per this much time is kept "
                                     "(bounded work per epoch)", lo=0)
    max_imu_lag_s: float = setting(10.0, "a compass epoch is decided without the gyro reaching it after this much "
                                   "compass time (counted as imu_lagged_epochs)", gt=0)

    def __post_init__(self):
        super().__post_init__()
        self.core()

    def core(self, dh_ref_rad: float = 0.0) -> quasistatic.GyroTrackDetectorSettings:
        return quasistatic.GyroTrackDetectorSettings(
            core.ThresholdDetectorSettings(self.thresholds(), self.feature_settings(dh_ref_rad), self.hysteresis()),
            quasistatic.GyroTrackSettings(**{f: getattr(self, f) for f in _GT.__dataclass_fields__}),
            self.max_imu_lag_s)


class GyroTrackDmcDetector(DmcDetectorService):
    """Stage 1 on the two compasses, then each epoch's compass heading checked against the heading the gyro
    carries from the last trusted epochs (docs/methods.md#dmc-gyro-track): valid when they agree, whatever the
    field tests said; a bend the field tests miss is caught."""

    impl = "gyro_track"
    Settings = GyroTrackServiceSettings
    INPUTS = (
        *DmcDetectorService.INPUTS[:1],
        Input("magmesh/{vehicle}/clean/imu", "the gyro that carries the reference heading between trusted epochs"),
        *DmcDetectorService.INPUTS[1:],
    )

    on_frame = None  # per vehicle only: the runtime hands each vehicle's frame rows to on_message

    def make_fleet(self):
        return None

    def make_detector(self, vehicle: str, dh_ref_rad: float):
        return quasistatic.GyroTrackDetector(self.settings.core(dh_ref_rad))

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if info.stream == "imu":
            if refuse_unphysical(self, info, msg):
                return
            for d in state.detector.add_imu(msg["t_s"], msg["gyro_rad_s"], msg["accel_m_s2"]):
                self._publish(info.vehicle, state, d, self._param_source(state))
            return
        super().on_message(info, msg, state)

    def _on_epoch(self, info, state: VehicleState, t_s: float, b_a, b_b) -> None:
        if not self._have_params(info, state):
            return
        a, b = self.sensors
        for d in state.detector.update(t_s, b_a, b_b, state.params[a], state.params[b], state.declination_rad):
            self._publish(info.vehicle, state, d, self._param_source(state))


IMPLEMENTATIONS: dict[str, type[DmcDetectorService]] = {
    "threshold": ThresholdDmcDetector,
    "fcm": FcmDmcDetector,
    "single": SingleDmcDetector,
    "quasistatic": QuasiStaticDmcDetector,
    "gyro_track": GyroTrackDmcDetector,
}
DEFAULT_IMPL = "threshold"
__all__ = ["IMPLEMENTATIONS", "DEFAULT_IMPL", "Settings", "pop_impl_arg"]


def pop_impl_arg(argv: list[str]) -> tuple[str, list[str]]:
    """Take ``--impl NAME`` / ``--impl=NAME`` out of argv; an unknown name exits with the known ones."""
    return runtime.pop_impl_arg(argv, "dmc_detector", IMPLEMENTATIONS, DEFAULT_IMPL)
