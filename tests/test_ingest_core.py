"""Ingest validation core, without Zenoh."""

import pytest

from schemas import make
from services.ingest.core import IngestSettings, Rejection, StreamState, accept, check_order, check_ranges

S = IngestSettings()
K = "magmesh/car-1/raw/mag/1"


def mag(t, b=(20000.0, 0.0, -40000.0), seq=0, sensor="1"):
    return make("mag", "car-1", t, seq, sensor=sensor, b_nt=list(b))


def gnss(**kw):
    f = dict(lat_deg=32.0, lon_deg=118.8, alt_m=10.0, vel_enu_m_s=[1.0, 0.0, 0.0], course_rad=1.57, speed_m_s=1.0,
             fix_type="3d", num_sats=10, pdop=1.5)
    f.update(kw)
    return make("gnss", "car-1", 1.0, 0, **f)


def test_good_samples_pass():
    check_ranges(mag(0.0), S, K)
    check_ranges(make("imu", "car-1", 0.0, 0, gyro_rad_s=[0.1, 0, 0], accel_m_s2=[0, 0, 9.8]), S, "magmesh/car-1/raw/imu")
    check_ranges(gnss(), S, "magmesh/car-1/raw/gnss")


@pytest.mark.parametrize("msg,field", [
    (mag(0.0, b=(3e6, 0, 0)), "b_nt"),
    (mag(-1.0), "t_s"),
    (make("imu", "car-1", 0.0, 0, gyro_rad_s=[100.0, 0, 0], accel_m_s2=[0, 0, 9.8]), "gyro_rad_s"),
    (make("imu", "car-1", 0.0, 0, gyro_rad_s=[0, 0, 0], accel_m_s2=[0, 0, 1e4]), "accel_m_s2"),
    (gnss(alt_m=1e6), "alt_m"),
    (gnss(speed_m_s=1000.0), "speed_m_s"),
    (gnss(pdop=500.0), "pdop"),
])
def test_absurd_values_rejected_with_field(msg, field):
    key = {"mag": K, "imu": "magmesh/car-1/raw/imu", "gnss": "magmesh/car-1/raw/gnss"}[msg["type"]]
    with pytest.raises(Rejection) as e:
        check_ranges(msg, S, key)
    assert e.value.field == field and e.value.code == "range" and field in e.value.reason


def test_sensor_must_match_key():
    with pytest.raises(Rejection) as e:
        check_ranges(mag(0.0, sensor="2"), S, K)
    assert e.value.code == "key"


def test_time_order_duplicates_and_gaps():
    st = StreamState()
    for i, t in enumerate([0.0, 0.02, 0.04]):
        check_order(mag(t), st, S, K)
        accept(mag(t, seq=i), st)
    with pytest.raises(Rejection) as e:
        check_order(mag(0.04), st, S, K)
    assert e.value.code == "duplicate"
    with pytest.raises(Rejection) as e:
        check_order(mag(0.01), st, S, K)
    assert e.value.code == "time_order" and "backwards" in e.value.reason
    with pytest.raises(Rejection) as e:
        check_order(mag(1e5), st, S, K)
    assert e.value.code == "time_order" and "jumped" in e.value.reason
    accept(mag(0.10, seq=7), st)  # seq 3..6 never arrived
    assert st.upstream_gaps == 4 and st.accepted == 4


def test_settings_range_checked():
    with pytest.raises(ValueError):
        IngestSettings(max_field_nt=0)
