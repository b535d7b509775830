"""Report: every figure renders from a synthetic run, the HTML references the PNGs, summary figures are right."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from figcheck import assert_figure_drawn

from magmesh.geomap import synthetic_paper_map
from magmesh_cli import report
from magmesh_cli.report import data as rdata
from magmesh_cli.report import summary as rsum
from schemas import keys, messages


class _Seq:
    def __init__(self):
        self.n = {}

    def __call__(self, key_, mtype, vehicle, t, **f):
        key = key_
        s = self.n.get(key, 0)
        self.n[key] = s + 1
        msg = messages.make(mtype, vehicle, t, s, **f)
        return key, messages.validate(msg, where=key)


def synthetic_run(seed: int = 3, duration_s: float = 60.0, rate_hz: float = 10.0):
    """A car with two compasses, calibration, DMC, heading, truth, alarms; a survey vehicle; a drone."""
    rng = np.random.default_rng(seed)
    mk = _Seq()
    out = []
    v = "car-1"
    t = np.arange(0, duration_s, 1 / rate_hz)
    heading_true = np.radians(10.0 * t) % (2 * math.pi)
    disturbed = (t > 20) & (t < 30)
    offset = np.array([3000.0, -2000.0, 0.0])
    for i, ti in enumerate(t):
        h = heading_true[i]
        b_true = np.array([20000 * math.cos(h), -20000 * math.sin(h), -40000.0])
        dist = np.array([8000.0, 3000.0, 0]) if disturbed[i] else np.zeros(3)
        for s in ("1", "2"):
            b = np.diag([1.2, 0.8, 1.0]) @ b_true + offset + dist * (1.0 if s == "1" else 0.3) + rng.normal(0, 50, 3)
            out.append(mk(keys.clean_mag(v, s), "mag", v, ti, sensor=s, b_nt=b.tolist()))
        err = math.radians(25.0) if disturbed[i] else rng.normal(0, math.radians(1.0))
        kc = 0.1 if disturbed[i] else 0.95
        out.append(mk(keys.dmc(v), "dmc", v, ti, dm_nt=[float(dist[0]), 0.3 * float(dist[0])], ddm_nt_s=[0.0, 0.0],
                      dh_rad=0.1 if disturbed[i] else 0.0, ddh_rad_s=0.0, heading_rad=float((h + err) % (2 * math.pi)),
                      stage1_pass=not disturbed[i], credibility=kc, valid=not disturbed[i], impl="fcm",
                      param_source="cal"))
        mode = "gyro_only" if disturbed[i] else ("initialising" if ti < 2 else "magnetic")
        out.append(mk(keys.heading(v), "heading", v, ti, heading_rad=float((h + rng.normal(0, 0.02)) % (2 * math.pi)),
                      pitch_rad=0.0, roll_rad=0.0, heading_std_rad=0.02, pitch_std_rad=0.01, roll_std_rad=0.01,
                      mode=mode, mag_innovation_rad=0.0, mag_test_ratio=0.1, mag_fused=not disturbed[i]))
        out.append(mk(keys.truth(v, "pose"), "truth", v, ti, what="pose", heading_rad=float(h),
                      pos_enu_m=[float(ti), 0.0, 0.0]))
        out.append(mk(keys.truth(v, "sources"), "truth", v, ti, what="sources", disturbed=bool(disturbed[i]),
                      active_sources=["bridge"] if disturbed[i] else []))
    for s in ("1", "2"):
        M = np.diag([1 / 1.2, 1 / 0.8, 1.0]).ravel().tolist()
        out.append(mk(keys.cal_params(v, s), "cal_params", v, 5.0, sensor=s, param_id=f"p{s}", status="ok",
                      model="2d", method="arls", offset_nt=offset.tolist(), matrix=M, field_radius_nt=20000.0,
                      rmse_nt=60.0, coverage_frac=1.0, n_samples=300, n_gross_rejected=0,
                      observable=[True, True, False], fit_t_s=5.0, fit_duration_ms=3.0))
    a = dict(source="dmc", severity="warning", reason="DMC credibility below 0.8", value=0.1, threshold=0.8,
             service="dmc-1")
    out.append(mk(keys.alarm(v, "dmc"), "alarm", v, 20.6, state="raised", **a))
    out.append(mk(keys.alarm(v, "dmc"), "alarm", v, 30.2, state="cleared", **a))
    out.append(mk(keys.alarm(v, "dmc"), "alarm", v, 45.0, state="raised", **a))  # a false one, never cleared
    out.append(mk(keys.rejects(v), "reject", v, 3.0, key=keys.raw_mag(v, "1"), reason="NaN", field="b_nt",
                  code="schema", payload_len_bytes=40, service="ingest-1"))
    # survey vehicle with geomagnetic fixes on the synthetic paper map
    grid = synthetic_paper_map(7)
    sv = "survey-1"
    pos0 = np.array([6500.0, 7000.0])
    vel = 30.0 * np.array([math.sin(math.radians(60)), math.cos(math.radians(60))])
    for i in range(60):
        ts = 5.0 * i
        p = pos0 + vel * ts
        ins = p + np.array([600.0, 400.0]) + 0.5 * ts
        f = 50000.0 + float(grid.sample_m(p[None])[0]) + rng.normal(0, 1)
        out.append(mk(keys.clean_mag(sv, "1"), "mag", sv, ts, sensor="1", b_nt=[f, 0.0, 0.0], f_nt=f))
        out.append(mk(keys.clean_ins(sv), "ins", sv, ts, pos_enu_m=[*ins.tolist(), 0.0], vel_enu_m_s=[*vel, 0.0],
                      heading_rad=math.radians(60)))
        out.append(mk(keys.truth(sv, "pose"), "truth", sv, ts, what="pose", pos_enu_m=[*p.tolist(), 0.0]))
        if i >= 20 and i % 5 == 0:
            ok = i >= 30
            out.append(mk(keys.fix_geomag(sv), "geomag_fix", sv, ts, status="accepted" if ok else "pending",
                          accepted=ok, pos_enu_m=[*(p + rng.normal(0, 30, 2)).tolist(), 0.0],
                          ins_pos_enu_m=[*ins.tolist(), 0.0], hausdorff_nt=2.0, margin_nt=3.0,
                          search_area_m2=4e6, n_samples=20))
    # drone on a planned line, drifting off after 30 s
    dv = "drone-1"
    out.append(mk(keys.clean_route(dv), "route", dv, 0.0, a_enu_m=[0.0, 0.0, 10.0], b_enu_m=[200.0, 0.0, 10.0],
                  route_id="leg-1"))
    for i in range(300):
        ts = 0.2 * i
        d = max(0.0, ts - 30.0) * 0.1
        out.append(mk(keys.track(dv), "track", dv, ts, cross_track_m=d, along_track_m=3.0 * ts,
                      progress_frac=3.0 * ts / 200, gnss_ok=True, heading_innovation_rad=0.01,
                      innovation_sigma_rad=0.01, track_alarm=d > 1.0, innovation_alarm=False))
        out.append(mk(keys.clean_gnss(dv), "gnss", dv, ts, lat_deg=0.0, lon_deg=0.0, alt_m=10.0,
                      pos_enu_m=[3.0 * ts, d, 10.0], vel_enu_m_s=[3.0, 0.0, 0.0], course_rad=math.pi / 2,
                      speed_m_s=3.0, fix_type="rtk_fixed", num_sats=20, pdop=0.9))
    ta = dict(source="track", severity="critical", reason="cross-track deviation above 1 m", value=1.05,
              threshold=1.0, service="track-1")
    out.append(mk(keys.alarm(dv, "track"), "alarm", dv, 40.2, state="raised", **ta))
    out.sort(key=lambda km: km[1]["t_s"])
    return out, grid


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    msgs, grid = synthetic_run()
    out = tmp_path_factory.mktemp("report")
    index = report.build_report(msgs, out, title="synthetic run", grid=grid,
                                liveliness=[(1.7e9, "magmesh/svc/dmc_detector/dmc-1", True)])
    return out, index, msgs


def test_report_renders_every_figure_and_html_references_them(rendered):
    out, index, _ = rendered
    page = index.read_text()
    expected = ["car-1_field", "car-1_dmc", "car-1_heading", "car-1_calibration", "survey-1_geomag",
                "drone-1_track", "drone-1_track_map", "timeline"]
    srcs = set(re.findall(r"<img src='([^']+)'", page))
    for name in expected:
        assert_figure_drawn(out / f"{name}.png")
        assert f"{name}.png" in srcs
    for src in srcs:
        assert (out / src).exists()
    assert "magmesh/svc/dmc_detector/dmc-1" in page and "synthetic run" in page


def test_summary_figures(rendered):
    out, _, _ = rendered
    s = json.loads((out / "summary.json").read_text())["vehicles"]
    car = s["car-1"]
    assert car["alarms"] == {"dmc": 2}
    assert car["alarms_vs_truth"]["episodes"] == 1 and car["alarms_vs_truth"]["detected"] == 1
    assert car["alarms_vs_truth"]["median_delay_s"] == pytest.approx(0.6, abs=0.15)
    assert car["alarms_vs_truth"]["false_alarms"] == 1
    assert car["heading"]["rms_deg"] == pytest.approx(math.degrees(0.02), rel=0.2)
    assert car["heading"]["mode_frac"]["gyro_only"] == pytest.approx(0.165, abs=0.02)
    dmc = car["dmc"]
    # 25° error whenever disturbed (flagged invalid), ~1° otherwise: RP ≈ 100%, MP ≈ 0
    assert dmc["rp_pct"] > 95 and dmc["mp_pct"] < 2 and dmc["wp_deg"] < 2
    cal = {c["sensor"]: c for c in car["calibration"]}
    assert cal["1"]["spread_before_pct"] > 30 and cal["2"]["spread_after_pct"] < 10
    assert car["rejects"] == 1
    geo = s["survey-1"]["geomag"]
    assert geo["accepted"] == 6 and geo["fix_error_m_median"] < 100 < geo["ins_error_m_median"]
    assert s["drone-1"]["track"]["max_cross_track_m"] == pytest.approx(2.98, abs=0.05)


def test_correlation_surface_minimum_at_true_shift():
    grid = synthetic_paper_map(7)
    rng = np.random.default_rng(1)
    true = np.array([6500.0, 7000.0]) + np.arange(20)[:, None] * np.array([130.0, 75.0])
    h = grid.sample_m(true) + rng.normal(0, 0.5, 20)
    ins = true - np.array([300.0, -200.0])  # INS off by whole cells
    sx, sy, d = report.plots.correlation_surface(grid, h, ins, radius_cells=6)
    i, j = np.unravel_index(np.nanargmin(d), d.shape)
    assert (sx[i], sy[j]) == (300.0, -200.0)


def test_alarm_intervals_and_bool_intervals():
    msgs, _ = synthetic_run(duration_s=40)
    run = rdata.group(msgs)["car-1"]
    al = run.alarms()
    assert [(a.start, a.end, a.cleared) for a in al][0] == (20.6, 30.2, True)
    assert rdata.bool_intervals(np.arange(6.0), np.array([0, 1, 1, 0, 1, 1], bool)) == [(1.0, 3.0), (4.0, 5.0)]
    assert rsum.alarm_vs_truth(run)["detected"] == 1


def test_empty_run_still_writes_a_page(tmp_path):
    index = report.build_report([], tmp_path, title="nothing")
    assert "No vehicle messages" in index.read_text()


def test_report_command_on_a_recording(tmp_path, rendered):
    from magmesh_cli import cli
    from magmesh_cli import recording as rc

    _, _, msgs = rendered
    path = tmp_path / "run.mcap"
    with rc.RecordingWriter(path) as w:
        for key, msg in msgs:
            if key.startswith("magmesh/survey-1/"):  # keep it small: one vehicle
                w.write_message(key, msg, 1_800_000_000_000_000_000 + int(msg["t_s"] * 1e9))
        w.write_liveliness(keys.svc_token("geomag_matcher", "geomag-1"), True, 1_800_000_000_000_000_000)
    out = tmp_path / "rep"
    assert cli.main(["report", str(path), "-o", str(out), "--map", "synthetic:7", "--no-progress"]) == 0
    page = (out / "index.html").read_text()
    assert "survey-1_geomag.png" in page
    assert_figure_drawn(out / "survey-1_geomag.png")
    assert "magmesh/svc/geomag_matcher/geomag-1" in page and "run.mcap" in page
    s = json.loads((out / "summary.json").read_text())["vehicles"]
    assert set(s) == {"survey-1"} and s["survey-1"]["geomag"]["accepted"] == 6


def test_heading_figure_falls_back_to_the_dmc_heading(tmp_path, rendered):
    _, _, msgs = rendered
    no_fused = [(k, m) for k, m in msgs if k.startswith("magmesh/car-1/") and not k.endswith("/heading")]
    report.build_report(no_fused, tmp_path)
    assert_figure_drawn(tmp_path / "car-1_heading.png")
    s = json.loads((tmp_path / "summary.json").read_text())["vehicles"]["car-1"]
    assert s["heading"] is None and s["dmc"]["all_rms_deg"] > 5.0  # 25° while disturbed


def test_plotted_keys_skip_imu_and_raw_duplicates():
    ks = ["magmesh/c-1/raw/imu", "magmesh/c-1/clean/imu", "magmesh/c-1/raw/mag/1", "magmesh/c-1/clean/mag/1",
          "magmesh/c-1/raw/mag/2", "magmesh/c-1/dmc", "magmesh/d-1/raw/attitude", "magmesh/svc/ingest/i-1",
          "magmesh/d-1/track"]
    assert rdata.plotted_keys(ks) == ["magmesh/c-1/clean/mag/1", "magmesh/c-1/dmc", "magmesh/c-1/raw/mag/2",
                                      "magmesh/d-1/track"]
    assert rdata.plotted_keys(ks, vehicles=["d-1"]) == ["magmesh/d-1/track"]
