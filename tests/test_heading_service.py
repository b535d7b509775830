"""The heading service's wiring without a mesh: a simulated drive's messages handed to ``on_message``,
in time order and in the bursts a mesh delivers when it runs faster than real time."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from magmesh.paths import DEPLOY_DIR
from schemas import keys
from schemas.messages import make, validate
from services.heading_fuser.service import HeadingFuser, Settings

DURATION_S = 120.0


@pytest.fixture(scope="module")
def drive_messages():
    from services.dmc_detector import core as dmc_core
    from services.dmc_detector import fcm
    from sim_publishers.car.core import iter_messages, simulate

    with open(DEPLOY_DIR / "mesh.toml", "rb") as f:
        vehicles = tomllib.load(f)["vehicles"]
    car = vehicles["car-1"]
    d = simulate(duration_s=DURATION_S, layout="urban_a", seed=1)
    p1 = dmc_core.CompassParams.from_mapping(car["mag_params"]["1"])
    p2 = dmc_core.CompassParams.from_mapping(car["mag_params"]["2"])
    feats = dmc_core.features_batch(d.t_mag_s, d.mag_b_nt["1"], d.mag_b_nt["2"], p1, p2, car["declination_rad"])
    valid = np.asarray(fcm.FcmModel.load().classify(feats)[0], bool)
    msgs = []
    for t, key, typ, fields in iter_messages(d, "car-1", truth=False):
        info = keys.parse(key)
        if info.stream in ("imu", "mag"):
            msgs.append((t, keys.parse(keys.raw_to_clean(key)), validate(make(typ, "car-1", t, 0, **fields))))
    dmc_key = keys.parse(keys.dmc("car-1"))
    for t, v in zip(d.t_mag_s, valid, strict=True):
        msgs.append((float(t), dmc_key, validate(make(
            "dmc", "car-1", float(t), 0, dm_nt=[0.0, 0.0], ddm_nt_s=[0.0, 0.0], dh_rad=0.0, ddh_rad_s=0.0,
            heading_rad=0.0, stage1_pass=bool(v), credibility=1.0 if v else 0.0, valid=bool(v), impl="fcm",
            param_source="manifest"))))
    msgs.sort(key=lambda x: x[0])
    return vehicles, d, msgs, valid


def _run(vehicles, msgs):
    svc = HeadingFuser(Settings(), instance="t", vehicles_config=vehicles)
    out, drops = [], {}
    svc.publish = lambda key, typ, veh, t, **f: out.append((t, f))
    svc.alarm = lambda *a, **k: None
    svc.count_drop = lambda key, reason, n=1: drops.__setitem__(reason, drops.get(reason, 0) + n)
    st = svc.new_vehicle("car-1")
    for _, info, msg in msgs:
        svc.on_message(info, msg, st)
    return out, drops, st


def _rms_vs_truth(out, d) -> float:
    t = np.array([t for t, _ in out])
    h = np.array([f["heading_rad"] for _, f in out])
    truth = np.interp(t, d.t_mag_s, np.unwrap(d.truth.heading_rad))
    e = np.remainder(h - truth + math.pi, 2 * math.pi) - math.pi
    return float(np.degrees(np.sqrt(np.mean(e**2))))


def test_service_in_time_order_and_in_bursts_agree(drive_messages):
    vehicles, d, msgs, valid = drive_messages
    out, drops, st = _run(vehicles, msgs)
    assert (~valid).any(), "the drive must meet interference the DMC recognises"
    modes = [f["mode"] for _, f in out]
    assert "gyro_only" in modes and "magnetic" in modes[modes.index("gyro_only"):]
    rms = _rms_vs_truth(out, d)
    assert rms < 2.5
    assert len(out) >= 0.95 * DURATION_S / Settings().publish_period_s
    # the same messages in 2-s bursts per stream (all IMU, then magnetometers, then DMC verdicts)
    order = {"imu": 0, "mag": 1, "dmc": 2}
    bursty = sorted(msgs, key=lambda x: (int(x[0] // 2.0), order[x[1].stream], x[0]))
    out_b, drops_b, _ = _run(vehicles, bursty)
    assert abs(_rms_vs_truth(out_b, d) - rms) < 0.2
    assert [f["mode"] for _, f in out_b].count("gyro_only") > 0
    # dropped: sensor 2 (not fused) and the magnetometer samples before the first IMU sample only
    assert sum(n for r, n in drops_b.items() if "not the fused" not in r) <= 2, drops_b
