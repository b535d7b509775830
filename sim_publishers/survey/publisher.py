"""Simulated survey vehicle publishing into the mesh: scalar + vector magnetometer, drifting INS, truth.

Publishes ``raw/mag/{sensor}`` (``f_nt`` the scalar total field, ``b_nt`` the co-located vector
sensor), ``raw/ins`` (dead-reckoned position, velocity, heading) and ``truth/pose`` every
``period_s`` of :func:`sim_publishers.survey.core.simulate`, paced by sample time at ``speed`` ×
real time (0 = as fast as the mesh takes it). With ``loop`` the vehicle keeps flying its pattern
(up to ``loop_laps`` laps, the INS drifting on).

    python -m sim_publishers.survey --vehicle survey-1 --set speed=10 --set loop=true
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from magmesh.runtime import SimPublisher
from schemas import keys

from . import core


@dataclass(frozen=True)
class SurveyPublisherSettings:
    map: str = "synthetic:7"  # map spec; the matcher must use the same map (manifest vehicle table `map`)
    sensor: str = "1"
    speed: float = 1.0  # × real time; 0 = as fast as possible
    loop: bool = False  # keep flying the pattern
    loop_laps: int = 100  # laps simulated when looping
    laps: int = 1  # laps when not looping
    speed_m_s: float = 30.0
    period_s: float = 5.0
    snr: float = 10.0
    ins_error0_e_m: float = 1000.0
    ins_error0_n_m: float = 500.0
    ins_drift_e_m_s: float = 0.25
    ins_drift_n_m_s: float = -0.15
    ins_heading_bias_deg: float = 0.0  # INS heading error (dead-reckoned track rotated clockwise)
    ins_walk_m_sqrt_s: float = 0.5  # INS position random walk
    lat_deg: float = 45.4
    lon_deg: float = -75.7
    alt_m: float = 300.0
    truth: bool = True
    seed: int = 1

    def __post_init__(self):
        if self.speed < 0:
            raise ValueError(f"speed must be ≥ 0, got {self.speed}")
        keys.check_id(self.sensor, "sensor")
        self.sim_settings()

    def sim_settings(self) -> core.SurveySettings:
        return core.SurveySettings(
            map=self.map, speed_m_s=self.speed_m_s, period_s=self.period_s, snr=self.snr,
            laps=self.loop_laps if self.loop else self.laps,
            ins_error0_m=(self.ins_error0_e_m, self.ins_error0_n_m),
            ins_drift_m_s=(self.ins_drift_e_m_s, self.ins_drift_n_m_s),
            ins_heading_bias_deg=self.ins_heading_bias_deg, ins_walk_m_sqrt_s=self.ins_walk_m_sqrt_s,
            lat_deg=self.lat_deg, lon_deg=self.lon_deg, alt_m=self.alt_m, seed=self.seed,
        )


def survey_events(settings: SurveyPublisherSettings, vehicle: str) -> Iterator[tuple[float, str, str, dict]]:
    """The publisher's stream without Zenoh: (t_s, key, msg_type, fields) in time order."""
    run = core.simulate(settings.sim_settings())
    k_mag = keys.raw_mag(vehicle, settings.sensor)
    k_ins = keys.raw_ins(vehicle)
    k_truth = keys.truth(vehicle, "pose")
    for i in range(run.t_s.size):
        t = float(run.t_s[i])
        vel = [float(run.vel_m_s[i, 0]), float(run.vel_m_s[i, 1]), 0.0]
        hdg = float(run.heading_rad[i])
        # INS first: a field sample can be placed on the INS track as soon as it arrives
        yield t, k_ins, "ins", {"pos_enu_m": [float(run.ins_pos_m[i, 0]), float(run.ins_pos_m[i, 1]), settings.alt_m],
                                "vel_enu_m_s": vel, "heading_rad": hdg}
        yield t, k_mag, "mag", {"sensor": settings.sensor, "b_nt": [float(x) for x in run.b_body_nt[i]],
                                "f_nt": float(run.f_nt[i])}
        if settings.truth:
            yield t, k_truth, "truth", {"what": "pose", "pos_enu_m": [float(run.pos_m[i, 0]), float(run.pos_m[i, 1]),
                                                                      settings.alt_m],
                                        "vel_enu_m_s": vel, "heading_rad": hdg, "pitch_rad": 0.0, "roll_rad": 0.0}


class SurveyPublisher(SimPublisher):
    role = "sim"
    impl = "survey"
    vehicle = "survey-1"
    Settings = SurveyPublisherSettings
    CONSUMES = ()
    PRODUCES = ("raw/mag/{sensor} (f_nt)", "raw/ins", "truth/pose")

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        self.log.info("%s on map %s at %s× real time; %s", self.vehicle, self.settings.map,
                      self.settings.speed or "max", core.scale_check(self.settings.sim_settings()))
        return survey_events(self.settings, self.vehicle)

    def status_extra(self) -> dict:
        return {"map": self.settings.map, "snr": self.settings.snr, "period_s": self.settings.period_s}
