"""The calibration service's fleet form (services/calibration/fleet.py) against the per-vehicle reference
(core.VehicleCalibration + SensorCalibrator, online_ekf.HardIronEkf): simulated car drives interleaved in frames of
20 ms (gaps, a clock reset, a hard-iron step, a manifest set, faster IMU and GNSS), the same fits and parameter
sets, compensated fields and EKF estimates; the fit budget; the service's frame and single-sample paths."""

from __future__ import annotations

import math
import os

import msgpack
import numpy as np
import pytest
import zenoh

from magmesh import magcal, maths
from magmesh.runtime import Runner
from schemas import frame, keys, messages
from services.calibration import fleet as F
from services.calibration.core import (
    USABLE,
    CalibrationSettings,
    OnlineSettings,
    ParamRecord,
    SensorCalibrator,
    VehicleCalibration,
)
from sim_publishers.car import core as car

STREAMS = ("mag/1", "mag/2", "imu", "gnss")
GNSS_FIELDS = ("speed_m_s", "course_rad", "fix_type", "num_sats", "pdop", "lat_deg", "lon_deg", "alt_m")


def _pid(p: str | None) -> str | None:
    """A parameter-set id without its wall-clock part (core.new_param_id)."""
    return None if p is None else p.rsplit("-", 1)[0]


def _drive(name: str, seed: int, duration_s: float, step_nt=None, step_t_s=None, gap=None, replay_s=None, **sim):
    """A vehicle's messages as (arrival s, t_s, stream, fields): ``gap`` drops a span of every stream, ``replay_s``
    starts the drive over (its clock goes back) after the end, for that long."""
    d = car.simulate(seed=seed, duration_s=duration_s, **sim)
    if step_nt is not None:  # a hard-iron change (both sensors): what the online EKF is for
        for sid in d.mag_b_nt:
            b = d.mag_b_nt[sid].copy()
            b[d.t_mag_s >= step_t_s] += np.asarray(step_nt, float)
            d.mag_b_nt[sid] = b

    def rows(t_off):
        for t, key, _tp, f in car.iter_messages(d, name, truth=False):
            stream = "mag/" + f["sensor"] if "/mag/" in key else key.rsplit("/", 1)[1]
            yield t_off + t, t, stream, f

    out = [r for r in rows(0.0) if gap is None or not gap[0] <= r[1] < gap[1]]
    if replay_s:
        t_end = out[-1][0] + 0.5
        out += [r for r in rows(t_end) if r[1] < replay_s]
    return d, out


def _frames(vehicles: list[str], msgs: dict[str, list], window_s: float = 0.02) -> list[dict]:
    """Frames of ``window_s`` of arrival time: {stream: [(vehicle index, t_s, fields)]}, each vehicle's rows in
    its own order (sorted by vehicle, then time, as ingest's frames)."""
    rows = []
    for vi, name in enumerate(vehicles):
        for k, (arr, t, stream, f) in enumerate(msgs[name]):
            rows.append((int(math.floor(arr / window_s)), vi, k, t, stream, f))
    rows.sort(key=lambda r: (r[0], r[1], r[2]))
    frames: list[dict] = []
    last = None
    for fi, vi, _k, t, stream, f in rows:
        if fi != last:
            frames.append({s: [] for s in STREAMS})
            last = fi
        frames[-1][stream].append((vi, t, f))
    return frames


def _reference(name, msgs, cs, onl, initial=None):
    """The per-vehicle reference, fed as the service feeds it: fit when due, compensate with the set in use."""
    vc = VehicleCalibration(name, cs, onl, initial)
    for sid in initial or {}:
        vc.sensor(sid)
    events, comp = [], {"1": [], "2": []}
    for _arr, t, stream, f in msgs:
        if stream.startswith("mag/"):
            sid = f["sensor"]
            sc = vc.on_mag(sid, t, f["b_nt"])
            if sc.due(t):
                a = sc.fit(t)
                events.append((sid, "fit", t, a.accepted, a.reason, a.record))
            cur = sc.current
            usable = cur is not None and cur.status in USABLE
            comp[sid].append((t, cur.params.apply(f["b_nt"]) if usable else None, cur.param_id if usable else None))
        elif stream == "imu":
            vc.on_imu(t, f["gyro_rad_s"], f["accel_m_s2"])
        else:
            events += [(sid, "ekf", t, True, rec.reason, rec) for sid, rec in vc.on_gnss(t, f)]
    return vc, events, comp


def _fleet_inputs(fc, vehicles, fr, vslots, initial=None):
    inputs = []
    for sname in STREAMS:
        rws = fr[sname]
        if not rws:
            continue
        vi = np.array([r[0] for r in rws], np.int64)
        for x in np.unique(vi).tolist():
            if x not in vslots:
                vslots[x] = fc.add_vehicle(vehicles[x], True, None, (initial or {}).get(vehicles[x]))
        vs = np.array([vslots[x] for x in vi.tolist()], np.int64)
        t = np.array([r[1] for r in rws])
        if sname.startswith("mag/"):
            sid = sname[4:]
            for i in np.flatnonzero(fc.sensor_slots(vs, sid) < 0).tolist():
                fc.add_sensor(int(vs[i]), sid)
            inputs.append(F.MagIn(sid, vi, fc.sensor_slots(vs, sid), t, np.array([r[2]["b_nt"] for r in rws])))
        elif sname == "imu":
            inputs.append(F.ImuIn(vi, vs, t, np.array([r[2]["gyro_rad_s"] for r in rws]),
                                  np.array([r[2]["accel_m_s2"] for r in rws])))
        else:
            inputs.append(F.GnssIn(vi, vs, t, {k: [r[2][k] for r in rws] for k in GNSS_FIELDS}))
    return inputs


def _run_fleet(fc, vehicles, frames, initial=None, after_step=None):
    vslots: dict[int, int] = {}
    events = {n: [] for n in vehicles}
    comp = {n: {"1": [], "2": []} for n in vehicles}
    for fr in frames:
        inputs = _fleet_inputs(fc, vehicles, fr, vslots, initial)
        st = fc.step(inputs)
        mi = 0
        for x in inputs:
            if isinstance(x, F.MagIn):
                assert len(st.h[mi]) == len(x.t_s)  # every row comes out
                pids = st.param_ids(mi)
                for r in range(len(x.t_s)):
                    use = bool(st.usable[mi][r])
                    comp[vehicles[int(x.vi[r])]][x.sid].append((float(x.t_s[r]), st.h[mi][r].copy() if use else None,
                                                                pids[r]))
                mi += 1
        for e in st.events:
            events[e.vehicle].append((e.sensor, e.kind, e.t_s, e.attempt.accepted if e.attempt else True,
                                      e.attempt.reason if e.attempt else e.record.reason, e.record))
        if after_step is not None:
            after_step(fc, st)
    return vslots, events, comp


def _same_record(a: ParamRecord, b: ParamRecord, exact: bool) -> None:
    assert (a.status, a.method, a.params.model, a.params.observable) == (b.status, b.method, b.params.model,
                                                                        b.params.observable)
    assert _pid(a.param_id) == _pid(b.param_id)
    assert (a.n_samples, a.n_gross_rejected, a.fit_t_s) == (b.n_samples, b.n_gross_rejected, b.fit_t_s)
    if exact and a.status == "ok":  # a fitted set: the same call on the same window
        assert a.params.offset_nt == b.params.offset_nt and a.params.matrix == b.params.matrix
        assert (a.params.field_radius_nt, a.rmse_nt, a.coverage_frac) == (b.params.field_radius_nt, b.rmse_nt,
                                                                          b.coverage_frac)
    else:  # an EKF set, or a refusal (it carries the set in use): the kernel agrees with numpy to rounding
        np.testing.assert_allclose(a.params.offset, b.params.offset, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.params.M, b.params.M, rtol=1e-12, atol=0)


def _compare(vehicles, ref, fleet_events, fleet_comp, fc, vslots):
    for vi, name in enumerate(vehicles):
        vc, ev_r, comp_r = ref[name]
        ev_f = fleet_events[name]
        assert len(ev_r) == len(ev_f), name
        for a, b in zip(ev_r, ev_f, strict=True):
            assert a[:4] == b[:4], (name, a[:4], b[:4])
            if a[1] == "fit":
                assert a[4] == b[4]
                _same_record(a[5], b[5], exact=True)
            else:
                _same_record(a[5], b[5], exact=False)
        sensors = fc.sensors(vslots[vi])
        for sid in ("1", "2"):
            ra, fa = comp_r[sid], fleet_comp[name][sid]
            assert len(ra) == len(fa)
            assert [x[0] for x in ra] == [x[0] for x in fa]
            assert [_pid(x[2]) for x in ra] == [_pid(x[2]) for x in fa]
            assert [x[1] is None for x in ra] == [x[1] is None for x in fa]
            h_r = np.array([x[1] for x in ra if x[1] is not None])
            h_f = np.array([x[1] for x in fa if x[1] is not None])
            assert np.max(np.abs(h_f - h_r) / np.linalg.norm(h_r, axis=1)[:, None]) < 1e-9
            s = sensors[sid]
            sc = vc.sensors[sid]
            np.testing.assert_array_equal(fc.window(s), sc.window())  # float32 in both, to the bit
            np.testing.assert_array_equal(fc.window_times(s), np.asarray(sc.t))
            assert fc.sensor_entry(s) == {**sc.internal_states, "current_param_id": fc.sensor_entry(s)[
                "current_param_id"]} and _pid(fc.sensor_entry(s)["current_param_id"]) == _pid(
                sc.internal_states["current_param_id"])
            ekf, est = vc.onl[sid].ekf, fc.ekf_estimate(s)
            assert (est["n_fused"], est["n_rejected"], est["n_skipped"], est["epochs"]) == (
                ekf.n_fused, ekf.n_rejected, ekf.n_skipped, len(vc.onl[sid].epochs))
            np.testing.assert_allclose(est["x"], ekf.x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(est["P"], ekf.P, rtol=1e-9, atol=1e-9 * ekf.P.max())
            np.testing.assert_allclose(est["prior"], ekf.prior, rtol=1e-9, atol=1e-9)
            np.testing.assert_array_equal(est["M"], ekf.M)
            st = fc.ekf_states(s)
            ref_st = {**ekf.internal_states, **ekf.flags}
            assert st.keys() == ref_st.keys() and st["observable"] == list(ref_st["observable"])
            assert (st["converged"], st["fused"]) == (ref_st["converged"], ref_st["fused"])
        assert fc.gnss_reason(vslots[vi]) == vc.gnss_reason


@pytest.fixture(scope="module")
def drives():
    """Three cars interleaved: a hard-iron step (EKF sets that replace fits and restart the window), a gap
    and a manifest set, a replay that starts over (clock back) with a 400 Hz IMU and 25 Hz GNSS."""
    _, a = _drive("car-a", 1, 170.0, step_nt=(1500.0, -1000.0, 0.0), step_t_s=90.0)
    db, b = _drive("car-b", 2, 120.0, gap=(40.0, 52.0))
    _, c = _drive("car-c", 3, 75.0, replay_s=30.0, imu_rate_hz=200.0, gnss_rate_hz=20.0)
    p = db.true_params["2"]
    manifest = {"car-b": {"2": ParamRecord(magcal.MagParams.from_arrays(p.offset_nt, p.matrix, p.field_radius_nt),
                                           "2-manifest", "manifest", "manifest")}}
    return ["car-a", "car-b", "car-c"], {"car-a": a, "car-b": b, "car-c": c}, manifest


def test_fleet_equals_the_reference_on_interleaved_drives(drives):
    vehicles, msgs, manifest = drives
    cs, onl = CalibrationSettings(), OnlineSettings()
    ref = {n: _reference(n, msgs[n], cs, onl, manifest.get(n)) for n in vehicles}
    fc = F.FleetCalibration(cs, onl, fit_budget_frac=0.0, capacity=2)  # slots grow while vehicles arrive
    vslots, ev, comp = _run_fleet(fc, vehicles, _frames(vehicles, msgs), manifest)
    _compare(vehicles, ref, ev, comp, fc, vslots)
    # the drives did what they are for
    kinds = {n: [(e[1], e[5].status if e[5] else None, e[3]) for e in ref[n][1]] for n in vehicles}
    assert any(k == ("ekf", "ok", True) for k in kinds["car-a"])  # the step: EKF sets replace fitted ones
    assert any(k == ("fit", "ok", True) for k in kinds["car-a"])
    assert ref["car-b"][0].sensors["2"].current.status in ("ok", "manifest")
    assert fc.IT.shape[1] >= 256 and fc.ST.shape[1] >= 32  # the IMU and speed rings grew for car-c
    sched = fc.scheduler_status()
    assert sched["fits_delayed"] == 0 and sched["fit_lag_s"]["max"] == 0.0 and sched["fits_waiting"] == 0


def test_tilt_from_the_accelerometer_equals_the_reference(drives):
    """ekf_tilt = accel: roll and pitch from the IMU window with the GNSS speed rate removed (the replayed car with
    a 200 Hz IMU and 20 Hz GNSS)."""
    _, msgs, _ = drives
    cs, onl = CalibrationSettings(), OnlineSettings(tilt_source="accel")
    ref = {"car-c": _reference("car-c", msgs["car-c"], cs, onl)}
    fc = F.FleetCalibration(cs, onl)
    vslots, ev, comp = _run_fleet(fc, ["car-c"], _frames(["car-c"], {"car-c": msgs["car-c"]}))
    _compare(["car-c"], ref, ev, comp, fc, vslots)
    assert ref["car-c"][0].onl["1"].ekf.tilt_sq_sum > 0  # the tilt was not zero


def test_a_tight_budget_delays_fits_but_runs_every_one_and_drops_nothing(drives, monkeypatch):
    vehicles, msgs, _ = drives
    clock = {"wall": 0.0, "cpu": 0.0}
    real = F.fit_window

    def costly(*a, **kw):  # each fit takes 0.2 s of CPU on the fake clock
        clock["cpu"] += 0.2
        return real(*a, **kw)

    monkeypatch.setattr(F, "fit_window", costly)
    fc = F.FleetCalibration(CalibrationSettings(), OnlineSettings(), fit_budget_frac=0.05,
                            wall=lambda: clock["wall"], cpu=lambda: clock["cpu"])
    rows_in = rows_out = 0
    order_ok = []

    def tick(fc, st):
        clock["wall"] += 0.02
        nonlocal rows_in, rows_out
        rows_out += sum(len(h) for h in st.h)

    frames = _frames(vehicles, msgs)
    rows_in = sum(len(fr["mag/1"]) + len(fr["mag/2"]) for fr in frames)
    _run_fleet(fc, vehicles, frames, after_step=tick)
    assert rows_out == rows_in  # every magnetometer row was compensated (or counted unusable), none held
    st = fc.scheduler_status()
    assert st["fits_delayed"] > 0 and st["fit_lag_s"]["max"] > 5.0
    # 6 sensors due every 5 s need 0.24 s of CPU per s; 0.05 of a core gives 0.05: fits wait, the most
    # overdue first, and all of them run once the budget allows
    while fc.queue:
        before = {s: float(fc.SF[s, F.F_LAST_T] - fc.SF[s, F.F_DUE_T]) for s in fc.queue}
        clock["wall"] += 5.0
        ran = [e for e in fc.run_queued() if e.kind == "fit"]
        slots = [fc.sensors(e.vslot)[e.sensor] for e in ran]
        order_ok.append([before[s] for s in slots] == sorted((before[s] for s in slots), reverse=True))
        assert ran
    assert all(order_ok) and not fc.queue
    assert not fc.SI[:, F.I_PENDING].any()
    total = fc.n_fits.sum()
    assert st["fits"] < total and total == fc.fits_run
    # spent within the budget: 0.05 of the wall time, plus at most one fit of debt and the 1 s bank
    assert clock["cpu"] <= 0.05 * clock["wall"] + 0.2 + 0.05 + 1e-9
    for v in range(len(vehicles)):
        for sid, s in fc.sensors(v).items():
            assert fc.n_fits[s] >= 1, (v, sid)


def test_unlimited_budget_fits_at_the_due_row_even_with_a_clock():
    """fit_budget_frac = 0: no budget, whatever the clocks say."""
    fc = F.FleetCalibration(fit_budget_frac=0.0, wall=lambda: 0.0, cpu=lambda: 0.0)
    assert fc.unlimited and fc._allow_now()
    with pytest.raises(ValueError):
        F.FleetCalibration(fit_budget_frac=-1.0)
    with pytest.raises(ValueError):
        F.FleetCalibration(online=OnlineSettings(ekf=OnlineSettings().ekf.__class__(estimate_mount_yaw=True)))


def test_window_bound_and_float32_storage_agree_with_the_reference():
    rng = np.random.default_rng(5)
    cs = CalibrationSettings(sample_interval_s=0.0, window_max_samples=50, window_s=30.0)
    assert cs.window_capacity == 50 and CalibrationSettings().window_capacity == 12_002
    sc = SensorCalibrator("1", cs)
    fc = F.FleetCalibration(cs, OnlineSettings(enabled=False))
    s = fc.add_sensor(fc.add_vehicle("v", online=False), "1")
    t = np.cumsum(rng.uniform(0.001, 0.2, 400))
    t[250:] -= 20.0  # a clock that goes back: both start again
    b = rng.normal(0.0, 3e4, (400, 3)) + 1e-3 * rng.normal(size=(400, 3))
    for i in range(400):
        sc.update(float(t[i]), b[i])
        fc.step([F.MagIn("1", np.zeros(1, np.int64), np.array([s]), t[i:i + 1], b[i:i + 1])])
        np.testing.assert_array_equal(fc.window(s), sc.window())
    assert len(sc.t) <= 50
    assert sc.window().dtype == np.float64 and np.array_equal(sc.window(), sc.window().astype(np.float32))


def test_slots_are_reused_fresh_after_a_vehicle_leaves():
    cs, onl = CalibrationSettings(), OnlineSettings()
    _, msgs = _drive("car-r", 4, 30.0)
    fc = F.FleetCalibration(cs, onl, capacity=1)
    _run_fleet(fc, ["car-r"], _frames(["car-r"], {"car-r": msgs}))
    fc.free_vehicle(0)
    # the same drive again in the freed slots gives what a fresh reference gives
    ref = {"car-r": _reference("car-r", msgs, cs, onl)}
    vslots, ev, comp = _run_fleet(fc, ["car-r"], _frames(["car-r"], {"car-r": msgs}))
    assert vslots == {0: 0}
    _compare(["car-r"], ref, ev, comp, fc, vslots)


def test_declinations_are_the_reference_values():
    d = F.Declinations()
    rng = np.random.default_rng(2)
    lat = np.r_[rng.uniform(-80, 80, 20), 32.045, 31.995]  # two on rounding ties
    lon = np.r_[rng.uniform(-180, 180, 20), 118.735, -0.005]
    alt = np.r_[rng.uniform(-100, 4000, 20), 160.0, 50.0]
    got = d(lat, lon, alt)
    want = [maths.declination_rad(maths.earth_field_enu_nt(round(a, 2), round(o, 2), round(h, -2)))
            for a, o, h in zip(lat.tolist(), lon.tolist(), alt.tolist(), strict=True)]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    x = np.r_[rng.uniform(-90, 90, 5000), np.arange(-2000, 2000) * 0.005]
    la, _, al = F.Declinations.cells(x, x, x * 50)
    assert la.tolist() == [round(v, 2) for v in x.tolist()]
    assert al.tolist() == [round(v, -2) for v in (x * 50).tolist()]
    n = d.batches
    d(np.array([32.071]), np.array([118.714]), np.array([180.0]))  # next door: computed with the first cell
    assert d.batches == n


def test_warm_compiles_or_loads_every_kernel():
    r = F.warm()
    assert r["first_call_s"] >= 0 and F._compiled
    assert F.main(["--warm"]) == 0


# ---- the service: frames and single samples ------------------------------------------------------------------


class _Pub:
    def __init__(self, out, key):
        self.out, self.key = out, key

    def put(self, payload, **kw):
        self.out.append((self.key, payload))


class _Session:
    def __init__(self):
        self.out = []

    def declare_publisher(self, key, **kw):
        return _Pub(self.out, key)


def _service(tmp_path, inst, **settings):
    from services.calibration.service import Calibration, Settings

    os.environ["MAGMESH_STATE_DIR"] = str(tmp_path)
    svc = Calibration(Settings(fit_budget_frac=0.0, **settings), instance=inst)
    sess = _Session()
    r = Runner(svc, sess)
    r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
    svc.on_start()
    return r, sess


def _stream_key(v, sname):
    return {"imu": keys.clean_imu(v), "gnss": keys.clean_gnss(v)}.get(sname) or keys.clean_mag(v, sname[4:])


def test_service_frames_and_single_samples_give_the_same_outputs(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    vehicles = ["car-s", "car-t"]
    _, a = _drive("car-s", 1, 70.0)
    _, b = _drive("car-t", 2, 60.0, gap=(20.0, 25.0))
    frames = _frames(vehicles, {"car-s": a, "car-t": b})
    r1, s1 = _service(tmp_path / "1", "cal-1")
    seqs: dict[str, int] = {}
    for fr in frames:  # singles, each vehicle's in its own order
        for vi, t, _j, sname, f in sorted((vi, t, STREAMS.index(sn), sn, f) for sn in STREAMS for vi, t, f in fr[sn]):
            key = _stream_key(vehicles[vi], sname)
            seqs[key] = seqs.get(key, -1) + 1
            mt = "mag" if sname.startswith("mag") else sname
            r1.handle_sample(key, messages.encode(messages.make(mt, vehicles[vi], t, seqs[key], **f)))
    r2, s2 = _service(tmp_path / "2", "cal-2")
    seqs = {}
    fkey = keys.fleet_frame("ingest-1", "clean")
    for n, fr in enumerate(frames):  # the same samples as ingest's frames
        out = {}
        for sname in STREAMS:
            rws = fr[sname]
            if not rws:
                continue
            sq = []
            for vi, _t, _f in rws:
                k = _stream_key(vehicles[vi], sname)
                seqs[k] = seqs.get(k, -1) + 1
                sq.append(seqs[k])
            mt = "mag" if sname.startswith("mag") else sname
            cols = {}
            for fld in messages.MESSAGES[mt].fields:
                vals = [x[2].get(fld.name) for x in rws]
                if all(v is not None for v in vals):
                    cols[fld.name] = vals if isinstance(vals[0], str) else np.asarray(vals)
            out[sname] = frame.Stream(sname, mt, np.array([x[0] for x in rws], np.uint32),
                                      np.array([x[1] for x in rws]), np.array(sq, np.int64), cols)
        r2.handle_sample(fkey, frame.encode("ingest-1", "clean", n, vehicles, out))
    r1.svc.on_tick()
    r2.svc.on_tick()
    assert r1.last_error is None and r2.last_error is None

    def params(out):
        return [(k, m["t_s"], m["seq"], m["status"], m["method"], _pid(m["param_id"]), m["offset_nt"], m["matrix"])
                for k, m in ((k, msgpack.unpackb(p)) for k, p in out if "/cal/params/" in k)]

    p1, p2 = params(s1.out), params(s2.out)
    assert len(p1) >= 8 and p1 == p2  # the same sets, in the same order, with the same seqs
    single = {}
    for k, p in s1.out:
        if "/cal/mag/" in k:
            m = msgpack.unpackb(p)
            assert m["calibrated"] is True
            single[(k, m["seq"])] = (m["t_s"], m["b_nt"], _pid(m["param_id"]))
    framed = {}
    for k, p in s2.out:
        if k.startswith("magmesh/fleet/"):
            assert k == keys.fleet_frame("cal-2", "cal")
            f = frame.decode(p)
            assert f.kind == "cal"
            for sn, st in f.streams.items():
                pid = st.cols["param_id"]
                assert st.cols["calibrated"].all() and st.cols["sensor"] == sn[4:]
                for i in range(st.n):
                    key = keys.cal_mag(f.vehicles[st.vi[i]], sn[4:])
                    framed[(key, int(st.seq[i]))] = (float(st.t_s[i]), st.cols["b_nt"][i].tolist(),
                                                     _pid(pid if isinstance(pid, str) else pid[i]))
        else:
            assert "/cal/mag/" not in k  # no single cal/mag message from frames
    assert framed == single and len(framed) > 10_000
    for k in {k for k, _ in framed}:  # rows numbered per per-vehicle key, from 0 without a gap
        seqs_k = sorted(s for kk, s in framed if kk == k)
        assert seqs_k == list(range(len(seqs_k)))
    drops = lambda r: {k: dict(v) for k, v in r.drops.items() if v}  # noqa: E731
    assert drops(r1) == drops(r2) and drops(r1)
    st1, st2 = r1.svc.status_extra()["calibration"], r2.svc.status_extra()["calibration"]
    assert st1["summary"] == st2["summary"]
    for v in vehicles:
        a, b = st1["vehicles"][v], st2["vehicles"][v]
        for sid in ("1", "2"):
            for e in (a["sensors"][sid], b["sensors"][sid]):
                e["current_param_id"] = _pid(e["current_param_id"])
        assert a == b
    assert st2["fits"]["fits"] > 0 and st2["fits"]["fit_lag_s"]["max"] == 0.0
    # frames (read-only columns) and single samples run one compiled specialisation: the warm-up covers both
    assert len(F._run.signatures) == 1 and len(F._merge.signatures) == 1


def test_bench_row_runs_small(tmp_path, monkeypatch):
    """The ``magmesh bench cores`` row on a tiny fleet (the figures come from the full row, not from here)."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    from bench import cores_bench

    r = cores_bench.calibration_service(vehicles=4, warm_s=1.0, frames=20, repeats=1, singles_frames=2,
                                        cold_frames=10, full_window_s=40.0)
    assert r["frame_us_per_sample"] > 0 and r["singles_us_per_sample"] > 0 and r["fit_ms_full_window"] > 0
    assert r["samples_per_s"] == 4 * 205 and r["expected_core_share"] > r["fit_budget_frac"]


def _tiny_frame(n: int, vehicles: list[str]) -> bytes:
    vi = np.arange(len(vehicles), dtype=np.uint32)
    m = frame.Stream("mag/1", "mag", vi, np.full(len(vi), 0.02 * n), np.full(len(vi), n, np.int64),
                     {"sensor": "1", "b_nt": np.tile([2e4, 1e3, -4e4], (len(vi), 1))})
    return frame.encode("ingest-1", "clean", n, vehicles, {"mag/1": m})


def test_service_gives_back_the_slots_of_vehicles_it_no_longer_holds(tmp_path):
    r, _ = _service(tmp_path, "cal-3")
    svc = r.svc
    fkey = keys.fleet_frame("ingest-1", "clean")
    r.handle_sample(fkey, _tiny_frame(0, ["car-1", "car-2", "car-3"]))
    held = {v: s.vslot for v, s in svc.vehicle_states.items()}
    assert sorted(held) == ["car-1", "car-2", "car-3"] and not r.last_error
    r.vehicle_state.pop("car-2")  # a group member forgets a vehicle it handed over
    svc.on_tick()
    assert held["car-2"] in svc.fleet._free_v and svc.fleet.vnames[held["car-2"]] is None
    svc.evict_vehicle("car-3", r.vehicle_state.pop("car-3"))  # the runtime evicts an idle one
    assert held["car-3"] in svc.fleet._free_v
    r.handle_sample(fkey, _tiny_frame(1, ["car-1", "car-2", "car-3"]))  # they come back: fresh slots, fresh state
    assert sorted(svc.vehicle_states) == ["car-1", "car-2", "car-3"] and not r.last_error
    for v in ("car-2", "car-3"):
        s = svc.fleet.sensors(svc.vehicle_states[v].vslot)["1"]
        assert svc.fleet.SI[s, F.I_W_N] == 1 and svc.fleet.n_fits[s] == 1
    s1 = svc.fleet.sensors(svc.vehicle_states["car-1"].vslot)["1"]
    assert svc.fleet.SI[s1, F.I_W_N] == 1  # 20 ms apart: decimated (0.05 s), the first sample stays alone
    svc.on_tick()
    assert r.drops[keys.clean_mag("car-1", "1")]["no_usable_params"] == 2  # no set yet: counted at the tick


@pytest.mark.mesh
def test_mesh_ingest_frames_through_calibration(tmp_path):
    """Car simulator → ingest (output = frames) → calibration over a real router: the parameters converge on the
    per-vehicle cal/params keys and the compensated samples arrive as cal frames tagged with a published set."""
    import subprocess
    import sys
    import threading
    import time

    from meshutil import REPO, free_port, wait_alive

    from magmesh.zconf import build_config

    vehicle = "car-f"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    env = {**os.environ, "PYTHONPATH": str(REPO), "MAGMESH_STATE_DIR": str(tmp_path)}
    params, rows = [], []
    lock = threading.Lock()

    def on_params(sample):
        with lock:
            params.append(messages.decode(bytes(sample.payload.to_bytes())))

    def on_frame(sample):
        f = frame.decode(bytes(sample.payload.to_bytes()))
        with lock:
            for sn, st in f.streams.items():
                pid = st.cols["param_id"]
                rows.extend((f.vehicles[st.vi[i]], sn, int(st.seq[i]), pid if isinstance(pid, str) else pid[i])
                            for i in range(st.n))

    subs = [router.declare_subscriber(keys.cal_params(vehicle, "*"), on_params),
            router.declare_subscriber(keys.fleet_frame("*", "cal"), on_frame)]

    def spawn(module, *args):
        return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint, *args], cwd=REPO, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    procs = [spawn("services.ingest", "--instance", "ingest-f", "--set", "output=frames"),
             spawn("services.calibration", "--instance", "cal-f")]
    try:
        for role, inst in (("ingest", "ingest-f"), ("calibration", "cal-f")):
            assert wait_alive(router, keys.svc_token(role, inst), timeout=60.0), f"{role}/{inst} never came up"
        procs.append(spawn("sim_publishers.car", "--vehicle", vehicle, "--instance", "sim-f", "--set", "speed=8",
                           "--set", "duration_s=150", "--set", "truth=false"))
        deadline = time.monotonic() + 90.0
        ok: dict[str, dict] = {}
        while time.monotonic() < deadline and len(ok) < 2:
            with lock:
                ok = {m["sensor"]: m for m in params if m["status"] == "ok"}
            for p in procs[:2]:
                assert p.poll() is None, p.stderr.read().decode()[-3000:]
            time.sleep(0.2)
        assert set(ok) == {"1", "2"}, [(m["sensor"], m["status"], m.get("reason")) for m in params]
        time.sleep(1.0)
        with lock:
            published = {m["param_id"] for m in params}
            tagged = [r for r in rows if r[3] in published]
            mine = [r for r in rows if r[0] == vehicle]
        assert tagged and len(mine) == len(rows) > 1000
        for sid in ("1", "2"):  # each per-vehicle cal/mag stream numbered from 0 without a gap
            seqs = sorted(r[2] for r in mine if r[1] == f"mag/{sid}")
            assert seqs == list(range(len(seqs)))
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(timeout=5)
        for s in subs:
            s.undeclare()
        router.close()


def test_param_id_codes_stay_bounded_and_right():
    fc = F.FleetCalibration(capacity=2)
    s = [fc.add_sensor(fc.add_vehicle(f"v{i}", online=False), "1") for i in range(2)]
    for k in range(3000):  # many sets over time: the code table starts again, the sets in use keep their ids
        fc._set_current(s[k % 2], ParamRecord(magcal.MagParams(), f"1-ls-{k}", "ok", "ls"))
        assert len(fc._pid_list) <= 4 * len(fc.cur_pid) + 1024
    for x in s:
        assert fc._pid_list[fc.cur_code[x]] == fc.cur_pid[x] == fc.records[x].param_id
    one = np.zeros(1, np.int64)
    st = fc.step([F.MagIn("1", np.array([0, 1]), np.array(s), np.array([1.0, 1.0]), np.ones((2, 3)))])
    assert st.param_ids(0) == ["1-ls-2998", "1-ls-2999"] and st.param_id_column(0) == ["1-ls-2998", "1-ls-2999"]
    st = fc.step([F.MagIn("1", one, np.array(s[:1]), np.array([2.0]), np.ones((1, 3)))])
    assert st.param_id_column(0) == "1-ls-2998"


def test_a_new_fit_budget_share_takes_effect_and_no_limit_stays_no_limit():
    """A group member's share of the role's budget (calibration service: fit_budget_frac / members): the token
    bucket refills at the new rate from the change on, keeps no more banked than the new burst, and a budget of 0
    (no limit) is not turned into one."""
    clock = {"wall": 0.0}
    fc = F.FleetCalibration(fit_budget_frac=0.04, wall=lambda: clock["wall"], cpu=lambda: 0.0)
    clock["wall"] = 10.0
    fc._refill()
    assert fc.tokens == pytest.approx(0.04)  # (at most the 1 s bank)
    fc.set_fit_budget(0.02)
    assert fc.fit_budget_frac == 0.02 and fc.tokens == pytest.approx(0.02)
    fc.tokens = 0.0
    clock["wall"] = 10.5
    fc._refill()
    assert fc.tokens == pytest.approx(0.01)
    free = F.FleetCalibration(fit_budget_frac=0.0)
    free.set_fit_budget(0.02)
    assert free.unlimited and free._allow_now()
