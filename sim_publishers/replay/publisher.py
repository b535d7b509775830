"""Replay a bundled real recording into the mesh as if it were a vehicle.

Publishes ``raw/imu``, ``raw/mag/{sensor}``, ``raw/gnss`` / ``raw/ins`` where the recording has them, and
the recording's ground truth on ``truth/pose``, ``truth/field``, ``truth/sources`` (see
:mod:`sim_publishers.replay.core`). Paced by sample time at ``speed`` × real time (0 = as fast as the mesh
takes it); ``loop`` repeats the recording with time running on.

    python -m sim_publishers.replay --vehicle broad-32 --set dataset=broad:32_disturbed_attached_magnet_1cm
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from magmesh import declare
from magmesh.declare import Output, setting
from magmesh.runtime import SimPublisher

from . import core


@dataclass(frozen=True)
class ReplaySettings:
    dataset: str = setting("broad:32_disturbed_attached_magnet_1cm", "the recording: broad:<trial> | car_circles | "
                           "kok:eight | kok:square")
    speed: float = setting(1.0, "× real time; 0 = as fast as possible", lo=0)
    loop: bool = setting(False, "repeat the recording, time running on")
    seed: int = setting(0, "the data is recorded, nothing is random; kept for the publisher interface")
    rate_hz: float = setting(100.0, "BROAD: IMU/mag block-averaged to about this rate (285.7 Hz recorded)", gt=0)
    truth_rate_hz: float = setting(10.0, "BROAD: truth messages per second", gt=0)
    start_s: float = setting(0.0, "play from this recording time", lo=0)
    duration_s: float = setting(0.0, "play this long (0 = to the end)", lo=0)
    sensor: str = setting("1", "the sensor id the magnetometer is published as")

    def __post_init__(self):
        declare.check(self)


def replay_events(settings: ReplaySettings, vehicle: str) -> Iterator[tuple[float, str, str, dict]]:
    """The publisher's stream without Zenoh: recording samples in ``[start_s, start_s + duration_s)``, looped."""
    rec = core.load(settings.dataset, settings.rate_hz, settings.truth_rate_hz)
    ss = core.StreamSettings(sensor=settings.sensor)
    end = settings.start_s + settings.duration_s if settings.duration_s > 0 else float("inf")
    events = [e for e in core.stream(rec, vehicle, ss) if settings.start_s <= e[0] < end]
    if not events:
        return
    t_first, t_last = events[0][0], events[-1][0]
    period = t_last - t_first + (t_last - t_first) / max(1, len(events))  # one mean sample gap between laps
    lap = 0
    while True:
        offset = lap * period
        for t, key, mtype, fields in events:
            yield t + offset, key, mtype, fields
        lap += 1
        if not settings.loop:
            return


class ReplayPublisher(SimPublisher):
    role = "sim"
    impl = "replay"
    vehicle = "replay-1"
    Settings = ReplaySettings
    OUTPUTS = (
        Output("magmesh/{vehicle}/raw/imu", "the recording's IMU"),
        Output("magmesh/{vehicle}/raw/mag/{sensor}", "its magnetometer, as sensor `sensor`"),
        Output("magmesh/{vehicle}/raw/gnss", "its GNSS, where it has one"),
        Output("magmesh/{vehicle}/raw/ins", "its INS, where it has one"),
        *(Output("magmesh/{vehicle}/truth/{what}", f"the recording's ground truth: {w}", what=w)
          for w in ("pose", "field", "sources")),
    )

    def produce(self) -> Iterator[tuple[float, str, str, dict]]:
        self.log.info("replaying %s as vehicle %s at %s× real time", self.settings.dataset, self.vehicle,
                      self.settings.speed or "max")
        return replay_events(self.settings, self.vehicle)

    def status_extra(self) -> dict:
        return {"dataset": self.settings.dataset}
