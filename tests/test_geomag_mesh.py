"""Mesh test: survey simulator → ingest → geomag_matcher over a real Zenoh router on loopback."""

from __future__ import annotations

import numpy as np
import pytest

from schemas import keys

pytestmark = pytest.mark.mesh


def test_survey_vehicle_fixes_correct_the_drifting_ins(tmp_path):
    pytest.importorskip("zenoh")
    import meshutil as mu

    port = mu.free_port()
    router = mu.open_router(port)
    fixes = mu.Collector(router, keys.fix_geomag("survey-t"))
    truth = mu.Collector(router, keys.truth("survey-t", "pose"))
    alarms = mu.Collector(router, keys.alarm("survey-t", "match"))
    procs = [
        mu.spawn("services.ingest", port, "--instance", "ingest-t", log_path=tmp_path / "ingest.log"),
        mu.spawn("services.geomag_matcher", port, "--instance", "geomag-t", "--vehicles", "survey-$*",
                 log_path=tmp_path / "geomag.log"),
    ]
    try:
        assert mu.wait_alive(router, keys.svc_token("ingest", "ingest-t"))
        assert mu.wait_alive(router, keys.svc_token("geomag_matcher", "geomag-t")), (tmp_path / "geomag.log").read_text()
        procs.append(mu.spawn("sim_publishers.survey", port, "--vehicle", "survey-t", "--set", "speed=100",
                              "--instance", "sim-t", log_path=tmp_path / "sim.log"))
        accepted = [m for _, m in fixes.wait_for(lambda k, m: m["accepted"] and m["seq"] >= 12, timeout=40.0)]
        assert accepted, (tmp_path / "geomag.log").read_text()[-2000:]
        # the status queryable reports the matcher's internal states
        status = mu.query_status(router, keys.svc_status("geomag_matcher", "geomag-t"))
        assert status is not None and status["matchers"]["survey-t"]["n_accepted"] >= 8
        assert status["vehicles"] == ["survey-t"]
    finally:
        for p in procs:
            mu.stop(p)
        router.close()
    all_fixes = [m for _, m in fixes.matching(lambda k, m: True)]
    accepted = [m for m in all_fixes if m["accepted"]]
    assert len(accepted) >= 8, f"only {len(accepted)} accepted of {len(all_fixes)} fixes"
    assert all(f["status"] == "accepted" for f in accepted)
    pose = {round(m["t_s"], 3): m["pos_enu_m"] for _, m in truth.matching(lambda k, m: True)}
    fix_err, ins_err, filt_err = [], [], []
    for f in accepted:
        p = pose.get(round(f["t_s"], 3))
        assert p is not None, "no truth at the fix time"
        fix_err.append(np.hypot(f["pos_enu_m"][0] - p[0], f["pos_enu_m"][1] - p[1]))
        ins_err.append(np.hypot(f["ins_pos_enu_m"][0] - p[0], f["ins_pos_enu_m"][1] - p[1]))
        c = f["filtered_correction_enu_m"]
        filt_err.append(np.hypot(f["ins_pos_enu_m"][0] + c[0] - p[0], f["ins_pos_enu_m"][1] + c[1] - p[1]))
    # the INS starts ~1.1 km off; accepted fixes and the filtered INS are within a cell or two of the truth
    assert np.median(ins_err) > 1000.0
    assert np.median(fix_err) < 150.0, fix_err
    assert np.median(filt_err) < 150.0, filt_err
    # divergence between INS and accepted fixes exceeds the default 1000 m: alarm/match raised
    assert any(m["state"] == "raised" for _, m in alarms.matching(lambda k, m: True))
