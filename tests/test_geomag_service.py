"""geomag_matcher wiring without Zenoh: the survey stream through on_message, publications captured."""

from __future__ import annotations

import numpy as np

from schemas import keys, messages
from services.geomag_matcher.service import GeomagMatcherService, Settings
from sim_publishers.survey.publisher import SurveyPublisherSettings, survey_events


class Captured(GeomagMatcherService):
    """The service with its runtime calls recorded instead of sent."""

    def __init__(self, **kw):
        super().__init__(Settings(**kw), "geomag-test", "*", {})
        self.sent: list[tuple[str, dict]] = []
        self.alarms: list[dict] = []
        self.drops: dict[str, int] = {}
        self._states: dict = {}

    def publish(self, key, msg_type, vehicle, t_s, **fields):
        msg = messages.validate(messages.make(msg_type, vehicle, t_s, len(self.sent), **fields))
        self.sent.append((key, msg))
        return msg

    def alarm(self, vehicle, source, state, severity, reason, value, threshold, t_s, unit="", **extra):
        self.alarms.append(dict(source=source, state=state, value=value, t_s=t_s))

    def count_drop(self, key, reason, n=1):
        self.drops[reason] = self.drops.get(reason, 0) + n

    @property
    def vehicle_states(self):
        return self._states

    def feed(self, key: str, msg_type: str, vehicle: str, t_s: float, fields: dict) -> None:
        clean = keys.raw_to_clean(key)
        msg = messages.validate(messages.make(msg_type, vehicle, t_s, 0, **fields))
        st = self._states.get(vehicle)
        if st is None:
            st = self._states[vehicle] = self.new_vehicle(vehicle)
        self.on_message(keys.parse(clean), msg, st)


def _stream(**kw):
    s = SurveyPublisherSettings(**kw)
    return [e for e in survey_events(s, "survey-9") if keys.parse(e[1]).kind == "raw"], s


def test_fixes_published_with_status_and_correction():
    events, _ = _stream(seed=3)
    svc = Captured()
    for t, key, mtype, fields in events[:240]:
        svc.feed(key, mtype, "survey-9", t, fields)
    fixes = [m for k, m in svc.sent if k == keys.fix_geomag("survey-9")]
    assert len(fixes) >= 15
    acc = [f for f in fixes if f["accepted"]]
    assert len(acc) >= 0.7 * len(fixes)
    for f in fixes:
        assert f["accepted"] == (f["status"] == "accepted")
        assert f["n_samples"] == 20 and f["search_area_m2"] > 0
    c = np.array([f["correction_enu_m"][:2] for f in acc])
    # the simulated INS starts (1000, 500) m off: the corrections undo it
    assert np.all(np.hypot(c[:, 0] + 1000.0, c[:, 1] + 500.0) < 300.0)
    assert [a["state"] for a in svc.alarms] == ["raised"]
    assert svc.status_extra()["matchers"]["survey-9"]["n_accepted"] == len(acc)


def test_field_before_ins_waits_and_vector_only_vehicles_are_counted():
    events, _ = _stream(seed=2)
    svc = Captured(match_every_samples=1)
    # swap each INS/mag pair: the field sample arrives before the INS sample of its time
    swapped = []
    for i in range(0, 2 * 40, 2):
        swapped += [events[i + 1], events[i]]
    for t, key, mtype, fields in swapped:
        svc.feed(key, mtype, "survey-9", t, fields)
    assert svc.status_extra()["matchers"]["survey-9"]["n_matches"] == 40 - 20 + 1
    svc.feed(keys.raw_mag("car-9", "1"), "mag", "car-9", 1.0, {"sensor": "1", "b_nt": [1.0, 2.0, 3.0]})
    assert svc.drops.get("no_scalar_field") == 1
    assert "car-9" not in svc.status_extra()["matchers"]


def test_clock_going_back_restarts_the_vehicle():
    events, _ = _stream(seed=2)
    svc = Captured()
    for t, key, mtype, fields in events[:100]:
        svc.feed(key, mtype, "survey-9", t, fields)
    before = svc.status_extra()["matchers"]["survey-9"]["n_matches"]
    assert before > 0
    for t, key, mtype, fields in events[:10]:  # the source restarted at t = 0
        svc.feed(key, mtype, "survey-9", t, fields)
    st = svc.status_extra()["matchers"]["survey-9"]
    assert st["n_matches"] == 0 and st["buffered_samples"] == 5
