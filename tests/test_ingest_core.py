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


def test_sample_ahead_of_the_streams_clock_is_refused_without_moving_it():
    from services.ingest.core import ahead_limit_s

    st = StreamState()
    for i in range(100):  # 100 Hz, received in real time
        check_order(mag(0.01 * i), st, S, K, now=0.01 * i)
        accept(mag(0.01 * i, seq=i), st, 0.01 * i, S)
    assert ahead_limit_s("mag", st, S, 1.0) == pytest.approx(10.0 + 1.0 * (2 * 0.01 + 0.5) + 2 * 0.01)
    with pytest.raises(Rejection) as e:
        check_order(mag(0.99 + 3500.0), st, S, K, now=1.0)
    assert e.value.code == "time_order" and "ahead of the stream's clock" in e.value.reason
    assert st.last_t_s == pytest.approx(0.99)
    check_order(mag(1.0), st, S, K, now=1.0)  # the real stream goes on
    # the gap a silent stream may bridge grows with receive time: 60 s of silence, then 60 s later in sample time
    check_order(mag(61.0), st, S, K, now=61.0)


def test_a_faster_stream_clock_is_learned():
    st = StreamState()
    for i in range(300):  # a replay at 20x: 0.2 s of sample time per 0.01 s of receive time
        t = 0.2 * i
        check_order(mag(t), st, S, K, now=0.01 * i)
        accept(mag(t, seq=i), st, 0.01 * i, S)
    assert 15 < st.rate < 25
    check_order(mag(st.last_t_s + 18.0), st, S, K, now=0.01 * 299)  # within its clock at ~20x (a 1x clock: 10.5 s)


def test_a_slow_stream_of_a_fast_source_is_accepted_from_its_second_sample():
    """One sample a second of receive time, 20 s of sample time apart (a survey aircraft simulated at 20x, as in
    the demo's survey-2): its rate is unknown until a second of receive time has passed, so its second sample
    is not refused as ahead of a 1x clock, and once learned (~20x) the clock keeps accepting it."""
    st = StreamState()
    for i in range(30):
        check_order(mag(20.0 * i), st, S, K, now=1.0 * i)
        accept(mag(20.0 * i, seq=i), st, 1.0 * i, S)
    assert st.rate_learned and 15 < st.rate < 25
    with pytest.raises(Rejection) as e:  # and the learned clock still refuses a sample far ahead of it
        check_order(mag(st.last_t_s + 500.0), st, S, K, now=30.0)
    assert "ahead of the stream's clock" in e.value.reason
    # two samples bunched by a loaded network (40 ms apart in receive time, 20 s apart in sample time), with the
    # rate learned low from a delayed delivery (a step of 20 s over 1.9 s)
    st.rate = 10.5
    check_order(mag(st.last_t_s + 20.0), st, S, K, now=29.04)
    accept(mag(st.last_t_s + 20.0, seq=30), st, 29.04, S)
    check_order(mag(st.last_t_s + 20.0), st, S, K, now=29.08)


def test_refused_samples_are_not_counted_as_gaps_of_their_stream():
    st = StreamState()
    accept(mag(0.0, seq=0), st)
    st.refused_seqs.update({1, 2})  # delivered, refused (counted as rejected)
    accept(mag(0.3, seq=4), st)  # seq 3 never arrived
    assert st.upstream_gaps == 1 and not st.refused_seqs


def test_rebase_only_after_consistent_refusals():
    from services.ingest.core import note_refusal, rebase

    s = IngestSettings(rebase_after=5)
    st = StreamState()
    accept(mag(100.0, seq=0), st, 0.0, s)
    # refusals that disagree with each other (a forger's random times) never add up
    assert not any(note_refusal(mag(t), st, s) for t in (1.0, 5000.0, 2.0, 9000.0, 3.0, 7000.0, 4.0))
    # a restarted source: consistent times, each a little after the previous
    flags = [note_refusal(mag(0.01 * i), st, s) for i in range(1, 6)]
    assert flags == [False, False, False, False, True]
    rebase(st)
    assert st.last_t_s is None and st.clock_rebases == 1
    check_order(mag(0.06), st, s, K, now=1.0)
    # an accepted sample in between resets the run
    accept(mag(0.06, seq=1), st, 1.0, s)
    assert not note_refusal(mag(9.0), st, s) and st.contra_n == 1


def test_seq_jumps_are_bounded():
    st = StreamState()
    accept(mag(0.0, seq=0), st)
    accept(mag(0.1, seq=10**9), st)
    accept(mag(0.2, seq=1), st)
    accept(mag(0.3, seq=5), st)
    assert st.upstream_gaps == 3 and st.seq_rebases == 2


def test_max_ahead_settings_checked_and_merged():
    assert IngestSettings(max_ahead_s={"imu": 1.0}).max_ahead_s["imu"] == 1.0
    assert IngestSettings(max_ahead_s={"imu": 1.0}).max_ahead_s["gnss"] == 60.0
    for bad in ({"imus": 1.0}, {"imu": -1}, {"imu": "x"}, [1.0]):
        with pytest.raises(ValueError):
            IngestSettings(max_ahead_s=bad)
