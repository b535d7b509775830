"""The alarm latch (magmesh/latch.py): the one raise/clear rule with hysteresis of every service's alarms."""

from __future__ import annotations

import inspect

import pytest

from magmesh.latch import AlarmLatch


def test_raise_and_clear_each_after_their_hold_of_an_uninterrupted_condition():
    la = AlarmLatch(0.5, 2.0)
    assert [la.update(t, False) for t in (0.0, 0.25)] == [None, None] and not la.raised
    assert la.update(0.375, True) is None  # interrupted: the raise hold starts again
    assert [la.update(t, False) for t in (1.0, 1.25, 1.5)] == [None, None, "raised"] and la.raised_t_s == 1.5
    assert [la.update(t, True) for t in (2.0, 3.0)] == [None, None]
    assert la.update(3.5, False) is None and la.raised  # the clear hold starts again too
    assert [la.update(t, True) for t in (4.0, 5.5, 6.0)] == [None, None, "cleared"]
    assert not la.raised and la.raised_t_s == 1.5  # the raise time stays until the next raise


def test_between_the_raise_and_the_clear_condition_nothing_changes():
    """Separate conditions (a raise level above a clear level): a value in between keeps the state, so a value near
    either threshold cannot make the alarm flap."""
    la = AlarmLatch()
    level = [0.5, 1.2, 0.9, 1.1, 0.95, 0.7, 1.3]  # raise above 1.0, clear below 0.8
    got = [la.update(float(t), x < 0.8, x > 1.0) for t, x in enumerate(level)]
    assert got == [None, "raised", None, None, None, "cleared", "raised"]


def test_the_slack_decides_a_hold_met_only_to_rounding():
    t0, t1 = 0.3, 2.3  # t1 - t0 = 1.9999999999999998 s
    exact, slack = AlarmLatch(2.0, 0.0, slack_s=0.0), AlarmLatch(2.0, 0.0)
    for la in (exact, slack):
        la.update(t0, False)
    assert exact.update(t1, False) is None and slack.update(t1, False) == "raised"


def test_adopt_keeps_the_timers_and_reset_forgets_everything():
    la = AlarmLatch(1.0, 1.0)
    for t in (0.0, 0.5, 1.0, 1.5):
        la.update(t, True)
    la.adopt(True, 0.25)  # a state decided elsewhere: valid for 1.5 s already
    assert la.raised and la.update(2.0, True) == "cleared"
    la.adopt(True, 3.0)
    la.adopt(False, 3.0)
    assert la.raised_t_s is None and la.state() == {"raised": False, "raised_t_s": None, "invalid_since": None,
                                                    "valid_since": 0.0}
    la.reset()
    assert la.state() == {"raised": False, "raised_t_s": None, "invalid_since": None, "valid_since": None}
    with pytest.raises(ValueError):
        AlarmLatch(-1.0, 0.0)


def test_every_alarm_with_hysteresis_uses_it():
    """The services whose alarms have raise/clear hysteresis in Python build them on this latch (the DMC fleet kernel
    and the heading join are the same rule compiled: tests/test_dmc_fleet.py and tests/test_heading_frames.py hold
    them to it)."""
    from services.dmc_detector import core as dmc_core
    from services.geomag_matcher import service as geomag
    from services.track_monitor import core as track

    assert isinstance(dmc_core.AlarmLatch(), AlarmLatch) and isinstance(dmc_core.ThresholdDetector().latch, AlarmLatch)
    mon = track.TrackMonitor()
    assert all(isinstance(x, AlarmLatch) for x in (mon.track.state, mon.innovation.state, mon.anomaly))
    assert isinstance(geomag.VehicleMatch(8).alarm, AlarmLatch)
    for mod in (dmc_core, geomag, track):
        src = inspect.getsource(mod)
        assert "clear_step" not in src and "class _Hysteresis" not in src and "class AlarmLatch" not in src
