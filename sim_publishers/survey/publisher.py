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

from magmesh import declare
from magmesh.declare import Output, setting
from magmesh.runtime import SimPublisher
from schemas import keys

from . import core


@dataclass(frozen=True)
class SurveyPublisherSettings:
    map: str = setting("synthetic:7", "map spec; the matcher must use the same map (manifest vehicle table `map`)")
    sensor: str = setting("1", "the sensor id of the scalar + vector magnetometer")
    speed: float = setting(1.0, "× real time; 0 = as fast as possible", lo=0)
    loop: bool = setting(False, "keep flying the pattern")
    loop_laps: int = setting(100, "laps simulated when looping")
    laps: int = setting(1, "laps when not looping")
    speed_m_s: float = setting(30.0, "ground speed")
    period_s: float = setting(5.0, "sample period (the paper: 5 s)")
    snr: float = setting(10.0, "σ_map / σ_noise: the anomaly map's spread over the measurement noise")
    ins_error0_e_m: float = setting(1000.0, "INS position error at the start, east")
    ins_error0_n_m: float = setting(500.0, "INS position error at the start, north")
    ins_drift_e_m_s: float = setting(0.25, "INS drift rate, east")
    ins_drift_n_m_s: float = setting(-0.15, "INS drift rate, north")
    ins_heading_bias_deg: float = setting(0.0, "INS heading error (dead-reckoned track rotated clockwise)")
    ins_walk_m_sqrt_s: float = setting(0.5, "INS position random walk")
    lat_deg: float = setting(45.4, "where the map lies (IGRF core field): latitude")
    lon_deg: float = setting(-75.7, "where the map lies: longitude")
    alt_m: float = setting(300.0, "where the map lies: altitude")
    truth: bool = setting(True, "publish truth/pose")
    seed: int = setting(1, "noise and INS errors")

    def __post_init__(self):
        declare.check(self)
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
    OUTPUTS = (
        Output("magmesh/{vehicle}/raw/mag/{sensor}", "f_nt, the scalar total field, and b_nt, the co-located vector "
               "sensor"),
        Output("magmesh/{vehicle}/raw/ins", "dead-reckoned position, velocity and heading"),
        Output("magmesh/{vehicle}/truth/{what}", "ground truth: pose", what="pose", when="truth"),
    )

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        self.log.info("%s on map %s at %s× real time; %s", self.vehicle, self.settings.map,
                      self.settings.speed or "max", core.scale_check(self.settings.sim_settings()))
        return survey_events(self.settings, self.vehicle)

    def status_extra(self) -> dict:
        return {"map": self.settings.map, "snr": self.settings.snr, "period_s": self.settings.period_s}
