"""Simulated multirotor publishing into the mesh: IMU, magnetometer, RTK GNSS, route, attitude and truth.

Publishes ``raw/route`` (at the start of each leg), ``raw/imu``, ``raw/mag/1`` and ``raw/attitude`` (50 Hz:
the flight controller's complementary-filter heading with the magnetometer heading it fuses), ``raw/gnss``
(10 Hz, rtk_fixed, centimetre noise) and ``truth/pose``, ``truth/sources`` (10 Hz) of
:func:`sim_publishers.multirotor.core.simulate`, paced by sample time at ``speed`` × real time (0 = as fast as
the mesh takes it). With ``loop`` the leg is flown again (seed + lap, a new route id), time running on.

The demo default is the paper's slow ramp (+0.0125 G/s on the magnetometer's y axis from ``onset_s``),
capped at ``disturbance_max_g``, held ``disturbance_hold_s`` and then removed, so alarms rise and clear.

    python -m sim_publishers.multirotor --vehicle drone-1 --set disturbance=slow_ramp --set speed=1
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

from magmesh import declare
from magmesh.declare import Output, setting
from magmesh.runtime import SimPublisher
from schemas import keys

from . import core

EARTH_RADIUS_M = 6378137.0


@dataclass(frozen=True)
class MultirotorPublisherSettings:
    seed: int = setting(1, "noise, wind and glitches of the first leg (leg k uses seed + k)")
    speed: float = setting(1.0, "× real time; 0 = as fast as possible", lo=0)
    loop: bool = setting(False, "fly the leg again when it ends, time running on")
    duration_s: float = setting(150.0, "length of one leg")
    route_length_m: float = setting(1000.0, "A → B, due north from the take-off point")
    disturbance: str = setting("slow_ramp", "the magnetometer disturbance flown into", choices=core.DISTURBANCES)
    onset_s: float = setting(60.0, "time of the leg at which the disturbance starts")
    ramp_rate_g_s: float = setting(0.0, "0: the paper's rate of the chosen ramp")
    disturbance_max_g: float = setting(0.12, "the disturbance grows to at most this")
    disturbance_hold_s: float = setting(20.0, "then held this long and removed (0: stays until the end of the leg)")
    truth: bool = setting(True, "publish truth/pose and truth/sources")
    truth_rate_hz: float = setting(10.0, "truth message rate")

    def __post_init__(self):
        declare.check(self)
        self.sim_settings(0)  # range checks of the simulator

    def sim_settings(self, lap: int) -> core.MultirotorSettings:
        return core.MultirotorSettings(
            seed=self.seed + lap, duration_s=self.duration_s, b_enu_m=(0.0, self.route_length_m, 20.0),
            disturbance=self.disturbance, onset_s=self.onset_s, ramp_rate_g_s=self.ramp_rate_g_s,
            disturbance_max_g=self.disturbance_max_g, disturbance_hold_s=self.disturbance_hold_s)


def _lat_lon(s: core.MultirotorSettings, e_m: float, n_m: float) -> tuple[float, float]:
    """Local ENU → geodetic (spherical Earth, small offsets)."""
    lat = s.origin_lat_deg + math.degrees(n_m / EARTH_RADIUS_M)
    lon = s.origin_lon_deg + math.degrees(e_m / (EARTH_RADIUS_M * math.cos(math.radians(s.origin_lat_deg))))
    return lat, lon


def iter_messages(f: core.Flight, vehicle: str, lap: int = 0, t_offset_s: float = 0.0, truth: bool = True,
                  truth_rate_hz: float = 10.0) -> Iterator[tuple[float, str, str, dict]]:
    """One flight as ``(t_s, key, msg_type, fields)`` in time order."""
    s = f.settings
    k_route, k_imu, k_mag = keys.raw_route(vehicle), keys.raw_imu(vehicle), keys.raw_mag(vehicle, "1")
    k_att, k_gnss = keys.raw_attitude(vehicle), keys.raw_gnss(vehicle)
    k_pose, k_src = keys.truth(vehicle, "pose"), keys.truth(vehicle, "sources")
    truth_every = max(1, int(round(1.0 / (truth_rate_hz * s.dt_s))))
    yield (t_offset_s, k_route, "route",
           dict(a_enu_m=list(s.a_enu_m), b_enu_m=list(s.b_enu_m), route_id=f"leg-{lap}"))
    gi = 0
    dist_on = abs(f.disturbance_nt).sum(axis=1) > 0
    for k in range(len(f.t_s)):
        t = t_offset_s + float(f.t_s[k])
        if gi < len(f.gnss_idx) and f.gnss_idx[gi] == k:
            p, v = f.gnss_pos_enu_m[gi], f.gnss_vel_enu_m_s[gi]
            lat, lon = _lat_lon(s, float(p[0]), float(p[1]))
            yield (t, k_gnss, "gnss", dict(
                lat_deg=lat, lon_deg=lon, alt_m=s.origin_alt_m + float(p[2]), pos_enu_m=p.tolist(),
                vel_enu_m_s=v.tolist(), course_rad=math.atan2(v[0], v[1]) % (2 * math.pi),
                speed_m_s=math.hypot(v[0], v[1]), fix_type="rtk_fixed", num_sats=18, pdop=1.3,
                horiz_std_m=s.gnss_noise_m))
            gi += 1
        yield (t, k_imu, "imu", dict(gyro_rad_s=f.gyro_rad_s[k].tolist(), accel_m_s2=f.accel_m_s2[k].tolist()))
        yield (t, k_mag, "mag", dict(sensor="1", b_nt=f.mag_nt[k].tolist()))
        yield (t, k_att, "attitude", dict(
            heading_rad=float(f.att_heading_rad[k]), pitch_rad=float(f.att_pitch_rad[k]),
            roll_rad=float(f.att_roll_rad[k]), mag_heading_rad=float(f.mag_heading_rad[k]),
            estimator="complementary"))
        if truth and k % truth_every == 0:
            yield (t, k_pose, "truth", dict(
                what="pose", heading_rad=float(f.heading_rad[k]), pitch_rad=float(f.pitch_rad[k]),
                roll_rad=float(f.roll_rad[k]), pos_enu_m=f.pos_enu_m[k].tolist(),
                vel_enu_m_s=f.vel_enu_m_s[k].tolist()))
            yield (t, k_src, "truth", dict(
                what="sources", active_sources=["mag_disturbance"] if dist_on[k] else [],
                disturbed=bool(dist_on[k])))


def multirotor_events(settings: MultirotorPublisherSettings, vehicle: str, max_laps: int | None = None,
                      ) -> Iterator[tuple[float, str, str, dict]]:
    """The publisher's stream without Zenoh: one leg, or legs with time running on."""
    lap = 0
    offset = 0.0
    while True:
        f = core.simulate(settings.sim_settings(lap))
        yield from iter_messages(f, vehicle, lap, offset, settings.truth, settings.truth_rate_hz)
        offset += float(f.t_s[-1]) + f.settings.dt_s
        lap += 1
        if not settings.loop or (max_laps is not None and lap >= max_laps):
            return


class MultirotorPublisher(SimPublisher):
    role = "sim"
    impl = "multirotor"
    vehicle = "drone-1"
    Settings = MultirotorPublisherSettings
    OUTPUTS = (
        Output("magmesh/{vehicle}/raw/route", "the planned line, at the start of each leg"),
        Output("magmesh/{vehicle}/raw/imu", "gyro + accelerometer at 50 Hz"),
        Output("magmesh/{vehicle}/raw/mag/{sensor}", "sensor 1 at 50 Hz"),
        Output("magmesh/{vehicle}/raw/attitude", "the flight controller's heading with the magnetometer heading it "
               "fuses, at 50 Hz"),
        Output("magmesh/{vehicle}/raw/gnss", "rtk_fixed at 10 Hz"),
        *(Output("magmesh/{vehicle}/truth/{what}", f"ground truth: {w}", what=w, when="truth")
          for w in ("pose", "sources")),
    )

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        return multirotor_events(self.settings, self.vehicle)
