"""geomag_matcher wiring without Zenoh: the survey stream through on_message, publications captured."""

from __future__ import annotations

import numpy as np

from schemas import keys, messages
from services.geomag_matcher.service import GeomagMatcherService, Settings
from sim_publishers.survey.publisher import SurveyPublisherSettings, survey_events


class Captured(GeomagMatcherService):
    """The service with its runtime calls recorded instead of sent."""

    def __init__(self, vehicles: dict | None = None, **kw):
        super().__init__(Settings(**kw), "geomag-test", "*", vehicles or {})
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


def _stream(vehicle: str = "survey-9", **kw):
    s = SurveyPublisherSettings(**kw)
    return [e for e in survey_events(s, vehicle) if keys.parse(e[1]).kind == "raw"], s


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


WDMAM_AIRCRAFT = dict(map="maps/map_WDMAM.hdf5", speed_m_s=150.0, period_s=20.0, ins_error0_e_m=5000.0,
                      ins_error0_n_m=3000.0, ins_drift_e_m_s=1.0, ins_drift_n_m_s=-0.5, ins_walk_m_sqrt_s=5.0)


def test_vehicle_table_picks_the_real_map_and_its_settings():
    events, s = _stream("survey-w", snr=10.0, seed=1, **WDMAM_AIRCRAFT)
    vehicles = {"survey-w": {"map": "maps/map_WDMAM.hdf5", "lat_deg": s.lat_deg, "lon_deg": s.lon_deg,
                             "geomag": {"lambda_nt": 49.0, "search_radius_m": 20000.0, "agree_radius_m": 3000.0,
                                        "runner_up_exclusion_m": 8600.0, "max_hausdorff_nt": 200.0,
                                        "fix_std_m": 1000.0, "divergence_alarm_m": 5000.0}}}
    svc = Captured(vehicles)
    for t, key, mtype, fields in events:
        svc.feed(key, mtype, "survey-w", t, fields)
    truth = {e[0]: e[3]["pos_enu_m"] for e in survey_events(SurveyPublisherSettings(snr=10.0, seed=1, **WDMAM_AIRCRAFT),
                                                              "survey-w") if e[2] == "truth"}
    acc = [m for k, m in svc.sent if m["accepted"]]
    assert len(acc) >= 15
    st = svc.vehicle_states["survey-w"].matcher.settings
    assert st.match.lambda_nt == 49.0 and st.accept.agree_radius_m == 3000.0
    fix_err = [np.hypot(m["pos_enu_m"][0] - truth[m["t_s"]][0], m["pos_enu_m"][1] - truth[m["t_s"]][1]) for m in acc]
    ins_err = [np.hypot(m["ins_pos_enu_m"][0] - truth[m["t_s"]][0], m["ins_pos_enu_m"][1] - truth[m["t_s"]][1])
               for m in acc]
    # 4.3 km cells: fixes within about a third of a cell, the INS 1.5 cells off
    assert np.median(fix_err) < 2000.0 < 5000.0 < np.median(ins_err)


def test_unusable_map_is_reported_not_fatal():
    events, _ = _stream(seed=2)
    svc = Captured({"survey-9": {"map": "maps/no_such_map.npz"}})
    for t, key, mtype, fields in events[:20]:
        svc.feed(key, mtype, "survey-9", t, fields)
    assert svc.drops["vehicle_map_or_settings_unusable"] == 10
    assert not svc.sent
