"""Track monitor service wiring and the multirotor publisher's stream, without Zenoh."""

from __future__ import annotations

import math

import pytest

from schemas import keys, messages
from services.track_monitor.service import Settings, TrackMonitorService
from sim_publishers.multirotor.publisher import MultirotorPublisherSettings, multirotor_events


class _FakeRuntime:
    """Collects what the service publishes; enough of Runner for on_message."""

    def __init__(self):
        self.out: list[tuple[str, dict]] = []
        self.drops: dict[tuple[str, str], int] = {}
        self.vehicle_state: dict = {}

    def publish(self, key, msg_type, vehicle, t_s, fields):
        msg = messages.make(msg_type, vehicle, t_s, len(self.out), **fields)
        messages.validate(msg, key, messages.type_for_key(key))
        self.out.append((key, msg))
        return msg

    def publish_alarm(self, key, vehicle, t_s, fields):
        return self.publish(key, "alarm", vehicle, t_s, fields)

    def count_drop(self, key, reason, n=1):
        self.drops[(key, reason)] = self.drops.get((key, reason), 0) + n

    def reject(self, *args):
        self.count_drop(args[0], "rejected")


def _feed(svc: TrackMonitorService, events, vehicle: str, drop_mag_heading: bool) -> _FakeRuntime:
    """Deliver the publisher's raw stream as ingest would (clean keys) to the keys the service subscribes."""
    rt = svc._rt = _FakeRuntime()
    subscribed = {k.replace("*", vehicle, 1) for k in svc.subscriptions()}
    for t_s, raw_key, msg_type, fields in events:
        key = keys.raw_to_clean(raw_key) if keys.parse(raw_key).kind == "raw" else raw_key
        if key not in subscribed:
            continue
        if drop_mag_heading and msg_type == "attitude":
            fields = {**fields, "mag_heading_rad": None}
        msg = messages.validate(messages.make(msg_type, vehicle, t_s, 0, **fields), key, msg_type)
        st = rt.vehicle_state.get(vehicle)
        if st is None:
            st = rt.vehicle_state[vehicle] = svc.new_vehicle(vehicle)
        svc.on_message(keys.parse(key), msg, st)
    return rt


@pytest.mark.parametrize("drop_mag_heading", [False, True])
def test_service_raises_mag_anomaly_on_the_slow_ramp(tmp_path, monkeypatch, drop_mag_heading):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    pub = MultirotorPublisherSettings(duration_s=75.0, onset_s=60.0, truth=False)
    events = list(multirotor_events(pub, "drone-x"))
    # without the flight controller's magnetometer heading the service levels the field itself with the
    # attitude's roll/pitch and the vehicle's declination (the simulator's -3°)
    svc = TrackMonitorService(settings=Settings(persist_sigma=False), instance="track-x",
                              vehicles_config={"drone-x": {"declination_rad": math.radians(-3.0)}})
    rt = _feed(svc, events, "drone-x", drop_mag_heading)
    alarms = [m for k, m in rt.out if m["type"] == "alarm"]
    anomaly = [a for a in alarms if a["source"] == "mag_anomaly" and a["state"] == "raised"]
    assert anomaly and 60.0 <= anomaly[0]["t_s"] <= 65.0, [(a["source"], a["state"], a["t_s"]) for a in alarms]
    assert not any(a["t_s"] < 60.0 for a in alarms)
    tracks = [m for k, m in rt.out if m["type"] == "track"]
    assert len(tracks) > 500 and tracks[-1]["track_armed"] and not tracks[-1]["innovation_learning"]
    assert "field_deviation_nt" in tracks[-1]
    assert not rt.drops, rt.drops


def test_publisher_stream_is_valid_time_ordered_and_loops_with_time_running_on():
    pub = MultirotorPublisherSettings(duration_s=12.0, loop=True, truth=True)
    last: dict[str, float] = {}
    routes = []
    n = 0
    for t_s, key, msg_type, fields in multirotor_events(pub, "drone-x", max_laps=2):
        msg = messages.validate(messages.make(msg_type, "drone-x", t_s, 0, **fields), key,
                                messages.type_for_key(key))
        assert t_s > last.get(key, -1.0), key  # ingest refuses time going backwards or repeating
        last[key] = t_s
        if msg_type == "route":
            routes.append(msg["route_id"])
        if msg_type == "gnss":
            assert msg["fix_type"] == "rtk_fixed" and msg["horiz_std_m"] <= 0.02
        n += 1
    assert routes == ["leg-0", "leg-1"]
    assert last[keys.raw_attitude("drone-x")] > 24.0 - 0.1
    assert n > 3 * 50 * 24  # imu, mag and attitude at 50 Hz, GNSS and truth at 10 Hz
    with pytest.raises(ValueError):
        MultirotorPublisherSettings(disturbance="storm")
