"""Simulated car publishing into the mesh: two magnetometers (a differential compass), IMU, GNSS, truth.

Publishes ``raw/mag/1``, ``raw/mag/2`` (50 Hz), ``raw/imu`` (100 Hz), ``raw/gnss`` (5 Hz) and the ground truth
``truth/pose``, ``truth/field``, ``truth/sources`` (10 Hz) of :func:`sim_publishers.car.core.simulate`,
paced by sample time at ``speed`` × real time (0 = as fast as the mesh takes it). With ``loop`` the drive
restarts when it ends (a new route from ``seed + lap``, the same car), time running on.

    python -m sim_publishers.car --vehicle car-1 --set layout=urban_a --set seed=1 --set speed=1
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields

from magmesh import declare
from magmesh.declare import Output, setting
from magmesh.runtime import SimPublisher

from . import core


@dataclass(frozen=True)
class CarPublisherSettings:
    layout: str = setting("urban_a", "interference layout", choices=tuple(core.LAYOUTS))
    seed: int = setting(1, "route and noise of the first lap (lap k uses seed + k)")
    vehicle_seed: int = setting(7, "hard/soft iron of the car's magnetometers (the manifest's mag_params match 7)")
    duration_s: float = setting(300.0, "length of one drive")
    speed: float = setting(1.0, "× real time; 0 = as fast as possible", lo=0)
    loop: bool = setting(False, "restart the drive when it ends, time running on")
    same_route_each_lap: bool = setting(False, "loop the identical drive instead of a new route per lap")
    truth: bool = setting(True, "publish truth/pose, truth/field, truth/sources")
    mag_rate_hz: float = setting(50.0, "magnetometer sample rate")
    imu_rate_hz: float = setting(100.0, "IMU sample rate")
    gnss_rate_hz: float = setting(5.0, "GNSS fix rate")
    truth_rate_hz: float = setting(10.0, "truth message rate")
    mag_noise_nt: float = setting(30.0, "magnetometer noise, 1-σ per axis")
    profile: str = setting("default", "paper_streets: HMR3300 compasses at 8 Hz, congested streets "
                           "(core.PAPER_STREETS)", choices=("default", "paper_streets"))

    def __post_init__(self):
        declare.check(self)
        self.sim_settings(0)  # range checks of the simulator

    def sim_settings(self, lap: int) -> core.CarSimSettings:
        own = {"seed": self.seed + (0 if self.same_route_each_lap else lap), "vehicle_seed": self.vehicle_seed,
               "layout": self.layout, "duration_s": self.duration_s, "imu_rate_hz": self.imu_rate_hz,
               "gnss_rate_hz": self.gnss_rate_hz}
        sensor = {"mag_rate_hz": self.mag_rate_hz, "truth_rate_hz": self.truth_rate_hz,
                  "mag_noise_nt": self.mag_noise_nt}
        if self.profile == "paper_streets":
            # the profile's sensor figures, unless a setting was given explicitly (differs from its default)
            dflt = {f.name: f.default for f in fields(self)}
            sensor = {k: v for k, v in sensor.items() if v != dflt[k]}
            return core.paper_streets_settings(**{**own, **sensor})
        return core.CarSimSettings(**own, **sensor)


def car_events(settings: CarPublisherSettings, vehicle: str, max_laps: int | None = None,
               on_lap=None, first_drive: core.CarDrive | None = None) -> Iterator[tuple[float, str, str, dict]]:
    """The publisher's stream without Zenoh: one drive, or laps of drives with time running on.

    ``first_drive``: lap 0 already simulated (the publisher does it before the pacing clock starts)."""
    lap = 0
    offset = 0.0
    while True:
        drive = first_drive if (lap == 0 and first_drive is not None) else core.simulate(settings.sim_settings(lap))
        if on_lap is not None:
            on_lap(lap, drive)
        yield from core.iter_messages(drive, vehicle, t_offset_s=offset, truth=settings.truth)
        # the next lap starts one magnetometer period after this lap's last sample
        offset += float(drive.t_mag_s[-1]) + 1.0 / drive.settings.mag_rate_hz
        lap += 1
        if not settings.loop or (max_laps is not None and lap >= max_laps):
            return


class CarPublisher(SimPublisher):
    role = "sim"
    impl = "car"
    vehicle = "car-1"
    Settings = CarPublisherSettings
    OUTPUTS = (
        Output("magmesh/{vehicle}/raw/mag/{sensor}", "sensors 1 and 2, the differential compass, at mag_rate_hz"),
        Output("magmesh/{vehicle}/raw/imu", "gyro + accelerometer at imu_rate_hz"),
        Output("magmesh/{vehicle}/raw/gnss", "GNSS fixes at gnss_rate_hz"),
        *(Output("magmesh/{vehicle}/truth/{what}", f"ground truth: {w}", what=w, when="truth")
          for w in ("pose", "field", "sources")),
    )

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._lap = -1
        self._zones: list[dict] = []
        self._first: core.CarDrive | None = None

    def on_start(self) -> None:
        # simulate the first drive before publishing starts, so the stream is paced from its first sample
        self._first = core.simulate(self.settings.sim_settings(0))

    def _on_lap(self, lap: int, drive: core.CarDrive) -> None:
        self._lap = lap
        self._zones = [{"name": s.name, "kind": s.kind, "centre_enu_m": [round(float(x), 1) for x in s.centre_enu_m]}
                       for s in drive.sources]
        self.log.info("lap %d: layout %s, seed %d, %.0f s, sources %s", lap, drive.settings.layout,
                      drive.settings.seed, drive.duration_s, ", ".join(z["name"] for z in self._zones) or "none")

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        self.log.info("car %s on layout %s at %s× real time%s", self.vehicle, self.settings.layout,
                      self.settings.speed or "max", ", looping" if self.settings.loop else "")
        first, self._first = self._first, None
        return car_events(self.settings, self.vehicle, on_lap=self._on_lap, first_drive=first)

    def status_extra(self) -> dict:
        return {"layout": self.settings.layout, "seed": self.settings.seed, "lap": self._lap, "sources": self._zones}
