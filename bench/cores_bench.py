"""``magmesh bench cores``: each pure core against its Python peer on the same input, in one run.

- ingest validation: decode + validate one message vs a bare ``msgpack.unpackb`` (the floor), and the
  reference (pure Python) validator beside the compiled one;
- ingest wire: the ingest service in process (no Zenoh), CPU per sample for v1 single samples against v2
  batches (a batch per vehicle per 20 ms), each sample decoded, validated and republished;
- ingest frames at 500 vehicles: the ingest service in process on v3 binary batches (one per vehicle per 60 ms, as
  bench/fleet.py's fleet puts them), a clean fleet frame out every 10 ms, CPU µs per sample;
- ingest rules, per sample: ingest's time and sequence rules (ranges, order, stream clocks, seq gaps) on a fleet
  window of 500 streams x 4 samples, the per-sample Python path against one compiled call per window;
- DMC detector, per epoch: the per-vehicle reference detectors (threshold, fcm, single; one ``update`` per epoch)
  against the fleet kernel stepping 1, 50 and 500 vehicles x 2 epochs per call (CPU µs per epoch), the numpy
  alternative for the stateless part, and the two compasses' pairing (TimeAligner per sample vs one call per frame);
- calibration fit: LS and ARLS on 10,000 samples (3-D, 20 % gross errors) vs ``scipy.optimize.least_squares``
  fitting the same ellipsoid geometrically;
- calibration service work per sample at 500 vehicles: the service fed fleet frames built like ingest's (decode,
  fleet core, cal frame out; CPU µs per sample, fits apart), the CPU share that makes at 500 vehicles with the fit
  budget, one fit on a full window, beside the same service on v1 singles and the per-vehicle reference;
- FCM on 10,000 × 2 samples vs scikit-fuzzy's ``cmeans`` (same start);
- EKF update: the heading fuser vs the ``ahrs`` EKF and x-io ``imufusion`` (C) on the same BROAD slice, µs/sample;
- heading EKF, per sample: the reference, the compiled filter (one call per sample, a whole slice per call, and a
  fleet of 500 vehicles stepped per call) beside ``vqf``'s batched C++ on the same slice;
- heading service work per sample at 500 vehicles: the heading fuser in process taking the clean, cal and dmc fleet
  frames of 500 simulated cars (decode, join, filters, output rules, heading messages), CPU µs per input sample;
- Hausdorff match: pre-match + SSDA + fine pipeline vs exhaustive search vs naive scipy ``directed_hausdorff``.
Times are medians (or minima where stated) of repeats in this process; ratios are taken in the same run.
"""

from __future__ import annotations

import statistics
import time

import numpy as np


class _DroppingSession:
    """What a service in process gets for a Zenoh session: publishers that drop what they are given."""

    class _Pub:
        def put(self, payload, **kw):
            pass

    def declare_publisher(self, key, **kw):
        return self._Pub()


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _median_cpu_time(fn, repeats: int) -> float:
    """Median CPU time of this process (less sensitive than wall time to other processes on the cores)."""
    ts = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        ts.append(time.process_time() - t0)
    return statistics.median(ts)


def ingest_validation(n: int = 20_000, repeats: int = 5) -> dict:
    import msgpack

    from schemas import messages

    pay = [messages.encode(messages.make("mag", "car-1", i * 0.02, i, sensor="1", b_nt=[2e4 + i, 100.0, -4e4]))
           for i in range(n)]

    def ours():
        for p in pay:
            messages.decode(p, where="magmesh/car-1/raw/mag/1", expected_type="mag")

    def floor():
        for p in pay:
            msgpack.unpackb(p)

    def reference():
        for p in pay:
            messages.decode_reference(p, where="magmesh/car-1/raw/mag/1", expected_type="mag")

    a, b = _median_time(ours, repeats) / n * 1e6, _median_time(floor, repeats) / n * 1e6
    r = _median_time(reference, repeats) / n * 1e6
    return {"decode_validate_us": round(a, 2), "msgpack_unpack_only_us": round(b, 2), "overhead_ratio": round(a / b, 2),
            "reference_validator_us": round(r, 2), "compiled_speedup": round(r / a, 2)}


def ingest_wire(vehicles: int = 50, windows: int = 100, repeats: int = 3) -> dict:
    """CPU time per sample through the ingest service (decode, validate, time order, republish), v1 vs v2."""
    import os
    import tempfile

    from magmesh.runtime import Runner
    from schemas import batch, keys, messages
    from services.ingest.batching import IngestServiceSettings
    from services.ingest.service import Ingest

    os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-cores-"))


    v1, v2 = [], []
    for w in range(windows):  # per vehicle and 20 ms: 2 magnetometer samples, 2 IMU samples
        for v in range(vehicles):
            vid = f"bench-{v:04d}"
            t = 1.0 + 0.02 * w
            imu = [messages.make("imu", vid, t + 0.01 * k, 2 * w + k, gyro_rad_s=[0.0, 0.0, 0.1],
                                 accel_m_s2=[0.0, 0.1, 9.8]) for k in range(2)]
            mags = [messages.make("mag", vid, t, w, sensor=s, b_nt=[2e4, 1e3 + w, -4e4]) for s in ("1", "2")]
            v1 += [(keys.raw_imu(vid), messages.encode(m)) for m in imu]
            v1 += [(keys.raw_mag(vid, m["sensor"]), messages.encode(m)) for m in mags]
            v2.append((keys.raw_batch(vid), batch.encode(vid, w, {
                **{f"mag/{m['sensor']}": batch.from_message(m) for m in mags},
                "imu": batch.concat([batch.from_message(m) for m in imu])})))
    n = vehicles * windows * 4

    def run(data, output):
        r = Runner(Ingest(IngestServiceSettings(output=output), instance="cores-ingest"), _DroppingSession())
        t0 = time.process_time()
        for k, payload in data:
            r.handle_sample(k, payload)
        r.svc.flush()
        return (time.process_time() - t0) / n * 1e6

    a = statistics.median(run(v1, "singles") for _ in range(repeats))
    b = statistics.median(run(v1, "batches") for _ in range(repeats))
    c = statistics.median(run(v2, "batches") for _ in range(repeats))
    return {"v1_in_singles_out_us_per_sample": round(a, 2), "v1_in_batches_out_us_per_sample": round(b, 2),
            "v2_in_batches_out_us_per_sample": round(c, 2), "messages_per_sample_v1": 1.0,
            "messages_per_sample_v2": 0.25, "v2_over_v1_cpu_ratio": round(c / a, 2)}


def ingest_frames(vehicles: int = 500, windows: int = 60, warmup_windows: int = 20, repeats: int = 3,
                  window_s: float = 0.05, frame_s: float = 0.01) -> dict:
    """CPU time per sample of the ingest service on fleet frames (``output = "frames"``), in process (no Zenoh; a
    publisher that drops what it is given): ``vehicles`` vehicles each putting one binary batch (contract v3)
    per ``window_s`` as bench/fleet.py's v3 fleet does (its window rounded to whole magnetometer epochs: 10 ms
    IMU ticks, both magnetometers every second tick, GNSS every 20th; each vehicle replays the drive from its own
    offset), their batches spread evenly over the window, and a ``clean`` frame flushed every ``frame_s`` (so a
    frame holds the batches of one ``frame_s`` slice of the vehicles). CPU time of the batches' handling (fast
    decode, the window's columns, the fleet rules, the frame out) after ``warmup_windows`` windows; µs per raw
    sample, medians of ``repeats`` runs, and the share of one core that is at the fleet's sample rate."""
    import os
    import tempfile

    import msgspec

    from bench.fleet import load_drive, window_ticks
    from magmesh.runtime import Runner
    from schemas import keys
    from services.ingest import fleet as ifleet
    from services.ingest.batching import IngestServiceSettings
    from services.ingest.service import Ingest

    os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-cores-"))
    ifleet.warm()
    W = window_ticks(window_s)
    per_window = max(1, round(W * 0.01 / frame_s))  # frames flushed per vehicle window
    n_win = warmup_windows + windows
    d = load_drive(duration_s=30.0)
    le = lambda x, dt="<f8": np.ascontiguousarray(x, dt).tobytes()  # noqa: E731
    mag1, mag2, gyro, acc = (le(x) for x in (d.mag_b_nt["1"], d.mag_b_nt["2"], d.gyro_rad_s, d.accel_m_s2))
    g = d.gnss
    n_mag, n_imu, n_g = len(d.mag_b_nt["1"]), len(d.gyro_rad_s), len(g.t_s)
    enc = msgspec.msgpack.Encoder().encode
    ids = [f"bench-{v:04d}" for v in range(vehicles)]
    bkeys = [keys.raw_batch(v) for v in ids]
    t0 = 1000.0
    payloads = []  # per window, per frame slice: [(key, payload)]
    n_samples = []  # raw samples per window
    for w in range(n_win):
        tick0 = w * W
        ticks = list(range(tick0, tick0 + W))
        mticks = [k for k in ticks if k % 2 == 0]
        gticks = [k for k in ticks if k % 20 == 0]
        nm = len(mticks)
        t_imu, t_mag = le([t0 + k * 0.01 for k in ticks]), le([t0 + k * 0.01 for k in mticks])
        s_imu, s_mag = le(ticks, "<i8"), le([k // 2 for k in mticks], "<i8")
        slices = [[] for _ in range(per_window)]
        for vi in range(vehicles):
            o_imu = (tick0 + vi * 74) % n_imu
            o_mag = (tick0 // 2 + vi * 37) % n_mag
            if o_imu + W > n_imu:
                o_imu = 0
            if o_mag + nm > n_mag:
                o_mag = 0
            st = {"mag/1": {"n": nm, "t_s": t_mag, "seq": s_mag,
                            "cols": {"sensor": "1", "b_nt": mag1[o_mag * 24:(o_mag + nm) * 24]}},
                  "mag/2": {"n": nm, "t_s": t_mag, "seq": s_mag,
                            "cols": {"sensor": "2", "b_nt": mag2[o_mag * 24:(o_mag + nm) * 24]}},
                  "imu": {"n": W, "t_s": t_imu, "seq": s_imu,
                          "cols": {"gyro_rad_s": gyro[o_imu * 24:(o_imu + W) * 24],
                                   "accel_m_s2": acc[o_imu * 24:(o_imu + W) * 24]}}}
            if gticks:
                js = [(k // 20 + vi) % n_g for k in gticks]
                st["gnss"] = {"n": len(gticks), "t_s": le([t0 + k * 0.01 for k in gticks]),
                              "seq": le([k // 20 for k in gticks], "<i8"), "cols": {
                                  "lat_deg": le(g.lat_deg[js]), "lon_deg": le(g.lon_deg[js]), "alt_m": le(g.alt_m[js]),
                                  "pos_enu_m": le(g.pos_enu_m[js]), "vel_enu_m_s": le(g.vel_enu_m_s[js]),
                                  "course_rad": le(g.course_rad[js]), "speed_m_s": le(g.speed_m_s[js]),
                                  "fix_type": [str(g.fix_type[j]) for j in js], "num_sats": le(g.num_sats[js], "<i8"),
                                  "pdop": le(g.pdop[js])}}
            slices[vi * per_window // vehicles].append((bkeys[vi], enc({
                "type": "batch", "version": 3, "vehicle": ids[vi], "t_s": t0 + (tick0 + W - 1) * 0.01, "seq": w,
                "streams": st})))
        payloads.append(slices)
        n_samples.append(vehicles * (W + 2 * nm + len(gticks)))
    n = sum(n_samples[warmup_windows:])


    def run() -> tuple[float, int]:
        r = Runner(Ingest(IngestServiceSettings(output="frames", batch_window_s=frame_s), instance="cores-ingest"),
                   _DroppingSession())
        r.svc.on_start()
        spent = 0.0
        for w, slices in enumerate(payloads):
            t = time.process_time()
            for sl in slices:
                for k, p in sl:
                    r.handle_sample(k, p)
                r.svc.frame_flush(force=True)
            if w >= warmup_windows:
                spent += time.process_time() - t
        assert not any(r.drops.values()) and not r.rejects_total, (dict(r.drops), r.last_error)
        return spent, r.frames_out

    runs = [run() for _ in range(repeats)]
    total = statistics.median(x[0] for x in runs)
    us = total / n * 1e6
    rate = sum(n_samples) / len(n_samples) / (W * 0.01)
    return {"vehicles": vehicles, "window_ticks": W, "frames_per_window": per_window, "windows": windows,
            "frames_out": runs[0][1], "samples": n, "us_per_sample": round(us, 3), "samples_per_s": round(rate),
            "cpu_share_of_one_core": round(us * rate / 1e6, 3)}


def ingest_rules(slots: int = 500, per_slot: int = 4, calls: int = 50, repeats: int = 3) -> dict:
    """Ingest's per-sample rules on a fleet window: :func:`services.ingest.fleet.reference_step` on each decoded
    sample (what ``Ingest.on_message`` runs) against :meth:`services.ingest.fleet.FleetStreams.decide` on the
    window (``slots`` streams x ``per_slot`` samples a call; 1 % out of range, 1 % duplicates); µs per sample,
    medians over calls (state carried from call to call, fresh for each repeat)."""
    from schemas import keys, make
    from services.ingest import fleet
    from services.ingest.core import IngestSettings, StreamState

    first = fleet.warm()  # compile (or load from the cache) before timing; reported
    s = IngestSettings()
    good = {"mag": dict(sensor="1", b_nt=[2.0e4, 1.0e3, -4.0e4]),
            "imu": dict(gyro_rad_s=[0.01, 0.0, 0.0], accel_m_s2=[0.0, 0.1, 9.8]),
            "gnss": dict(lat_deg=32.0, lon_deg=118.8, alt_m=10.0, pos_enu_m=[5.0, 6.0, 0.0],
                         vel_enu_m_s=[1.0, 0.0, 0.0], course_rad=1.57, speed_m_s=1.0, fix_type="3d", num_sats=10,
                         pdop=1.5),
            "ins": dict(pos_enu_m=[100.0, 20.0, 0.0], vel_enu_m_s=[1.0, 0.5, 0.0], heading_rad=0.3)}
    bad = {"mag": {"b_nt": [3.0e6, 0.0, 0.0]}, "imu": {"gyro_rad_s": [100.0, 0.0, 0.0]}, "gnss": {"pdop": 500.0},
           "ins": {"pos_enu_m": [2.0e7, 0.0, 0.0]}}
    cols_of = {"mag": ("b_nt",), "imu": ("gyro_rad_s", "accel_m_s2"),
               "gnss": ("alt_m", "speed_m_s", "vel_enu_m_s", "pdop", "pos_enu_m"), "ins": ("pos_enu_m", "vel_enu_m_s")}
    kinds = [("mag", "imu", "gnss", "ins")[i % 4] for i in range(slots)]
    skeys = [keys.raw_mag(f"bench-{i:04d}", "1") if k == "mag" else getattr(keys, f"raw_{k}")(f"bench-{i:04d}")
             for i, k in enumerate(kinds)]
    rng = np.random.default_rng(7)
    n = slots * per_slot
    windows = []
    for w in range(calls):  # rows in arrival order: the streams' samples interleaved
        msgs, now = [], []
        for j in range(per_slot):
            for i in range(slots):
                t = 10.0 + (i % 13) + 0.005 * (per_slot * w + j)
                u = rng.random()
                if u < 0.01 and (w or j):
                    t -= 0.005  # the previous sample again
                f = {**good[kinds[i]], **(bad[kinds[i]] if 0.01 <= u < 0.02 else {})}
                msgs.append(make(kinds[i], skeys[i].split("/")[1], t, per_slot * w + j, **f))
                now.append(1.0 + 0.02 * w + 1e-6 * (j * slots + i))
        slot = np.tile(np.arange(slots, dtype=np.int32), per_slot)
        kind = np.array([fleet.KIND_CODE[kinds[i]] for i in slot], np.int8)
        t_s = np.array([m["t_s"] for m in msgs])
        by_kind = {}
        for k in cols_of:
            idx = np.flatnonzero(kind == fleet.KIND_CODE[k])
            by_kind[k] = (idx, {c: np.array([msgs[q][c] for q in idx], float) for c in cols_of[k]})
        windows.append((msgs, slot, kind, t_s, np.array([m["seq"] for m in msgs], np.int64), np.array(now), by_kind))

    def reference():
        states = [StreamState() for _ in range(slots)]
        per, codes = [], []
        for msgs, slot, _, _, _, now, _ in windows:
            t0 = time.perf_counter()
            c = [fleet.reference_step(m, states[q], s, skeys[q], nw)[0]
                 for m, q, nw in zip(msgs, slot.tolist(), now.tolist(), strict=True)]
            per.append((time.perf_counter() - t0) / n * 1e6)
            codes += c
        return per, codes

    def kernel(oks: list | None):
        """decide() per call; with ``oks`` None the range masks are computed (and timed) in the call too."""
        fs = fleet.FleetStreams(s, capacity=slots)
        for _ in range(slots):
            fs.add()
        per, codes = [], []
        for w, (_, slot, kind, t_s, seq, now, by_kind) in enumerate(windows):
            t0 = time.perf_counter()
            if oks is None:  # the physical ranges on each kind's columns first
                ok = np.empty(n, bool)
                for k, (idx, cols) in by_kind.items():
                    ok[idx] = fleet.range_ok_mask(k, t_s[idx], cols, s)
            else:
                ok = oks[w]
            d = fs.decide(slot, kind, t_s, seq, ok, now)
            per.append((time.perf_counter() - t0) / n * 1e6)
            codes += d.code.tolist()
        return per, codes

    oks = []
    for _, _, _, t_s, _, _, by_kind in windows:
        ok = np.empty(n, bool)
        for k, (idx, cols) in by_kind.items():
            ok[idx] = fleet.range_ok_mask(k, t_s[idx], cols, s)
        oks.append(ok)
    ref_t, ker_t, full_t = [], [], []
    agree = True
    for _ in range(repeats):
        a, ca = reference()
        b, cb = kernel(oks)
        c, cc = kernel(None)
        ref_t, ker_t, full_t = ref_t + a, ker_t + b, full_t + c
        agree = agree and ca == cb == cc
    r, k, f = statistics.median(ref_t), statistics.median(ker_t), statistics.median(full_t)
    return {"slots": slots, "samples_per_slot_per_call": per_slot, "calls": calls,
            "reference_us_per_sample": round(r, 3), "kernel_us_per_sample": round(k, 4),
            "kernel_with_range_masks_us_per_sample": round(f, 4), "speedup": round(r / k, 1),
            "speedup_with_range_masks": round(r / f, 1), "same_decisions": agree,
            "kernel_first_call_s": first["first_call_s"], "kernel_from_cache": bool(first["cache_hits"])}


def dmc_detector(vehicles: tuple[int, ...] = (1, 50, 500), epochs_per_call: int = 2, epochs: int = 40_000,
                 repeats: int = 5, ref_epochs: int = 1500) -> dict:
    """DMC detector, per epoch: the per-vehicle reference (``ThresholdDetector.update``, ``FcmDetector``,
    ``SingleCompassDetector``: one call per epoch, what the service runs) against one
    :meth:`services.dmc_detector.fleet.FleetDetector.step` per frame of ``vehicles`` × ``epochs_per_call``
    epochs (rows sorted by vehicle then time, windows full), CPU µs per epoch, medians of ``repeats`` runs of
    about ``epochs`` epochs each. Beside it: the stateless part (compensation, strengths, headings, Δh) done in
    numpy over the frame instead (timed alone, the design the kernel was measured against), the pairing
    (one TimeAligner per vehicle fed sample by sample against :func:`fleet.pair_frame` per frame), whether
    the fleet's decisions equal the reference's on the timed drive, and the kernels' first call."""
    import math

    from magmesh.align import TimeAligner
    from services.dmc_detector import core, fcm
    from services.dmc_detector import fleet as dfleet
    from sim_publishers.car.core import CarSimSettings, simulate

    first = dfleet.warm()  # compile (or load from numba's disk cache) before timing; reported
    d = simulate(CarSimSettings(layout="urban_a", seed=5, duration_s=40.0))
    radius = float(np.linalg.norm(d.earth_field_enu_nt))
    pa, pb = (core.CompassParams(tuple(d.true_params[s].offset_nt), tuple(d.true_params[s].matrix.ravel()), radius)
              for s in ("1", "2"))
    decl = float(d.declination_rad)
    ba, bb, n_drive = d.mag_b_nt["1"], d.mag_b_nt["2"], len(d.t_mag_s)
    model = fcm.FcmModel.load()
    impls = {
        "threshold": (core.ThresholdDetector, lambda cap: dfleet.FleetDetector(core.ThresholdDetectorSettings(), cap)),
        "fcm": (lambda: fcm.FcmDetector(model), lambda cap: dfleet.FleetFcmDetector(model, None, cap)),
        "single": (core.SingleCompassDetector,
                   lambda cap: dfleet.FleetSingleDetector(core.ThresholdDetectorSettings(), cap)),
    }

    def cpu(fn) -> float:
        t0 = time.process_time()
        fn()
        return time.process_time() - t0

    def prepass(params, slot, t, b_a, b_b):
        """Compensation, strengths, headings and Δh of a frame in numpy (each row with its slot's parameters)."""
        p = params[slot]
        hd = []
        for base, b in ((dfleet.P_A, b_a), (dfleet.P_B, b_b)):
            v = b - p[:, base + dfleet.P_OFF:base + dfleet.P_OFF + 3]
            h = np.einsum("nij,nj->ni", p[:, base + dfleet.P_MAT:base + dfleet.P_MAT + 9].reshape(-1, 3, 3), v)
            strength = np.where(p[:, base + dfleet.P_2D] != 0, np.hypot(h[:, 0], h[:, 1]), np.sqrt((h * h).sum(1)))
            _dm = strength - p[:, base + dfleet.P_R]
            hd.append((np.arctan2(h[:, 1], h[:, 0]) + p[:, dfleet.P_DECL]) % (2 * math.pi))
        return (hd[0] - (hd[1] + p[:, dfleet.P_DHREF]) + math.pi) % (2 * math.pi) - math.pi

    out: dict = {"epochs_per_call_per_vehicle": epochs_per_call, "reference_us_per_epoch": {},
                 "fleet_us_per_epoch": {}, "speedup": {}, "same_decisions": {},
                 "numpy_stateless_part_alone_us_per_epoch": {}}
    t_ref = 100.0 + np.arange(ref_epochs) * 0.02
    for name, (make_ref, make_fleet) in impls.items():
        per = []
        for _ in range(repeats):
            ref = make_ref()
            decs = []
            per.append(cpu(lambda ref=ref, decs=decs: decs.extend(
                ref.update(float(t_ref[i]), ba[i], bb[i], pa, pb, decl) for i in range(ref_epochs))) / ref_epochs)
        out["reference_us_per_epoch"][name] = round(statistics.median(per) * 1e6, 2)
        det = make_fleet(1)  # the same epochs through the fleet detector, one frame of epochs_per_call at a time
        s0 = det.add()
        det.set_params(s0, pa, pb, decl)
        got = []
        for k in range(0, ref_epochs, epochs_per_call):
            sl = slice(k, min(k + epochs_per_call, ref_epochs))
            o = det.step(np.full(sl.stop - k, s0), t_ref[sl], ba[sl], bb[sl])
            got += [(bool(v), int(c)) for v, c in zip(o.valid, o.transition, strict=True)]
        codes = {None: 0, "raised": 1, "cleared": 2}
        out["same_decisions"][name] = got == [(dd.valid, codes[dd.transition]) for dd in decs]
        out["fleet_us_per_epoch"][name] = {}
        for n_v in vehicles:
            rows = n_v * epochs_per_call
            calls = max(10, epochs // rows)
            warm_calls = int(math.ceil(1.0 / (0.02 * epochs_per_call)))  # 1 s of input first: the windows fill
            slot = np.repeat(np.arange(n_v, dtype=np.int32), epochs_per_call)
            frames = []
            for k in range(warm_calls + calls):
                j = k * epochs_per_call + np.tile(np.arange(epochs_per_call), n_v)
                idx = (37 * slot + j) % n_drive
                frames.append((slot, 100.0 + 0.02 * j, np.ascontiguousarray(ba[idx]), np.ascontiguousarray(bb[idx])))
            per = []
            for _ in range(repeats):
                det = make_fleet(n_v)
                for _v in range(n_v):
                    det.set_params(det.add(), pa, pb, decl)
                for f in frames[:warm_calls]:
                    det.step(*f)
                timed = frames[warm_calls:]
                per.append(cpu(lambda det=det, timed=timed: [det.step(*f) for f in timed]) / (calls * rows))
            out["fleet_us_per_epoch"][name][str(n_v)] = round(statistics.median(per) * 1e6, 3)
            if name == "threshold":  # the alternative design: the stateless part in numpy, timed alone
                per = [cpu(lambda det=det, timed=timed: [prepass(det._params, *f) for f in timed]) / (calls * rows)
                       for _ in range(repeats)]
                out["numpy_stateless_part_alone_us_per_epoch"][str(n_v)] = round(statistics.median(per) * 1e6, 3)
        out["speedup"][name] = {k: round(out["reference_us_per_epoch"][name] / v, 1)
                                for k, v in out["fleet_us_per_epoch"][name].items()}
    # pairing: a frame's two compass streams (epochs_per_call samples each per vehicle, jitter within tolerance)
    out["pairing_us_per_epoch"] = {"time_aligner": None, "pair_frame": {}}
    rng = np.random.default_rng(3)
    for n_v in vehicles:
        calls = max(10, epochs // (n_v * epochs_per_call))
        slot = np.repeat(np.arange(n_v, dtype=np.int32), epochs_per_call)
        fr = []
        for k in range(calls):
            t = 100.0 + 0.02 * (k * epochs_per_call + np.tile(np.arange(epochs_per_call), n_v))
            fr.append((slot, t, ba[: len(t)], slot, t + rng.uniform(-0.002, 0.002, len(t)), bb[: len(t)], float(k)))
        per = []
        for _ in range(repeats):
            w = dfleet.Samples.empty()

            def run(w=w, fr=fr):
                for f in fr:
                    _, w, _ = dfleet.pair_frame(w, *f[:6], now=f[6])

            per.append(cpu(run) / (calls * n_v * epochs_per_call))
        out["pairing_us_per_epoch"]["pair_frame"][str(n_v)] = round(statistics.median(per) * 1e6, 3)
        if n_v == max(vehicles):  # the reference: one aligner per vehicle, every sample pushed (a, then b)
            per = []
            ref_fr = fr[: max(2, calls // 5)]
            for _ in range(repeats):
                al = [TimeAligner(("1", "2"), 0.005) for _ in range(n_v)]

                def run_ref(al=al, fr=ref_fr):
                    for f in fr:
                        sl, ta, tb = f[0].tolist(), f[1].tolist(), f[4].tolist()
                        for i, v in enumerate(sl):
                            al[v].push("1", ta[i], f[2][i], now=f[6])
                            al[v].push("2", tb[i], f[5][i], now=f[6])

                per.append(cpu(run_ref) / (len(ref_fr) * n_v * epochs_per_call))
            out["pairing_us_per_epoch"]["time_aligner"] = round(statistics.median(per) * 1e6, 3)
    out["kernels_first_call_s"] = {k: round(v, 3) for k, v in first.items() if k.endswith("_s")}
    return out


def calibration_fit(repeats: int = 5) -> dict:
    from scipy.optimize import least_squares

    from bench import calibration_synthetic as synthetic
    from services.calibration import arls, two_step

    cloud = synthetic.make_cloud(synthetic.CloudSettings(n_samples=10_000, gross_frac=0.2, seed=99))
    m = cloud.m_nt
    t_ls = _median_time(lambda: two_step.fit_ls(m, "3d"), repeats)
    t_arls = _median_time(lambda: arls.fit_arls(m, "3d"), repeats)

    def geometric():  # the peer: |L (m − b)| = 1 by nonlinear least squares, L lower-triangular
        def res(x):
            b = x[:3]
            L = np.array([[x[3], 0, 0], [x[6], x[4], 0], [x[7], x[8], x[5]]])
            return np.linalg.norm((m - b) @ L.T, axis=1) - 1.0

        k = 1.0 / np.linalg.norm(m - m.mean(0), axis=1).mean()
        least_squares(res, np.array([*m.mean(0), k, k, k, 0.0, 0.0, 0.0]), method="lm")

    t_geo = _median_time(geometric, max(1, repeats // 2))
    return {"ls_ms": round(t_ls * 1e3, 2), "arls_ms": round(t_arls * 1e3, 2),
            "scipy_least_squares_ms": round(t_geo * 1e3, 2), "arls_speedup_vs_scipy": round(t_geo / t_arls, 2)}


def calibration_service(vehicles: int = 500, warm_s: float = 12.0, frames: int = 250, repeats: int = 5,
                        singles_frames: int = 10, cold_frames: int = 250, full_window_s: float = 620.0) -> dict:
    """Calibration service work per sample at ``vehicles`` vehicles (two magnetometers at 50 Hz, IMU 100 Hz, GNSS
    5 Hz each; a car turning through full circles now and then): the service in process (no Zenoh) fed fleet
    frames built like ingest's (20 ms, rows sorted by vehicle then time, binary columns), each decoded, cut to
    its streams, seq-tracked, handled by ``on_frame`` (the fleet core: windows, compensation, GNSS EKF) and its
    ``cal`` frame encoded. CPU µs per sample, medians of ``repeats`` blocks of ``frames`` frames after ``warm_s``
    s of sample time, every vehicle starting with a parameter set (the steady state of a fleet whose sets were
    saved), with the fits' own CPU time apart (they take ``fit_budget_frac`` of a core, the default, whenever
    more are due than that pays for); ``cold_start``: no set anywhere, every sensor's EKF publishing a
    converging set every 5 s. Beside it: one fit on a full 600 s window of a simulated car, what fits at every
    ``refit_interval_s`` would cost at this fleet size and how often each sensor is refitted within the budget;
    the same service fed the same samples as v1 singles, and the per-vehicle reference (VehicleCalibration,
    no publishing) per sample. ``expected_core_share``: the frame work at the fleet's sample rate plus the fit
    budget."""
    import math
    import os
    import tempfile

    from magmesh.runtime import Runner
    from schemas import frame, keys, messages
    from services.calibration import fleet as cfleet
    from services.calibration.core import (
        CalibrationSettings,
        OnlineSettings,
        SensorCalibrator,
        VehicleCalibration,
    )
    from services.calibration.service import Calibration, Settings

    os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-cores-"))
    first = cfleet.warm()


    rng = np.random.default_rng(11)
    V = vehicles
    names = [f"bench-{v:04d}" for v in range(V)]
    b_earth = np.array([0.0, 33_000.0, -38_000.0])  # body-level field at heading 0 (north, down), nT
    offs = rng.uniform(-3000.0, 3000.0, (2, V, 3))
    offs[:, :, 2] = 0.0
    soft = np.eye(3) + rng.normal(0.0, 0.03, (2, V, 3, 3))
    soft = 0.5 * (soft + np.swapaxes(soft, 2, 3))
    phase = rng.uniform(0, 2 * math.pi, V)
    period = rng.uniform(40.0, 90.0, V)
    lat0, lon0 = 32.0 + rng.uniform(0, 0.3, V), 118.7 + rng.uniform(0, 0.3, V)

    def heading(t):  # a drive that turns through full circles now and then: yaw rate 0.3 sin(2π t / period)
        return (0.3 * period / (2 * math.pi)) * (1 - np.cos(2 * math.pi * t / period + phase)) + phase

    def frame_payload(k: int) -> tuple[bytes, int]:
        t = 0.02 * k
        vi = np.arange(V, dtype=np.uint32)
        psi = heading(t)
        c, s = np.cos(psi), np.sin(psi)
        # body-frame field of a level car heading psi (FLU, clockwise from north)
        bb = np.stack([c * b_earth[1], s * b_earth[1], np.full(V, b_earth[2])], axis=1)
        streams = {}
        for j, sid in enumerate(("1", "2")):
            m = np.einsum("vij,vj->vi", np.linalg.inv(soft[j]), bb) + offs[j] + rng.normal(0, 30.0, (V, 3))
            streams[f"mag/{sid}"] = frame.Stream(f"mag/{sid}", "mag", vi, np.full(V, t), np.full(V, k, np.int64),
                                                 {"sensor": sid, "b_nt": m})
        vi2 = np.repeat(vi, 2)
        ti = np.tile([t, t + 0.01], V)
        yaw = 0.3 * np.sin(2 * math.pi * ti / np.repeat(period, 2) + np.repeat(phase, 2))
        gyro = np.stack([np.zeros(2 * V), np.zeros(2 * V), yaw], axis=1) + rng.normal(0, 1e-3, (2 * V, 3))
        acc = np.tile([0.0, 0.0, 9.81], (2 * V, 1)) + rng.normal(0, 0.02, (2 * V, 3))
        streams["imu"] = frame.Stream("imu", "imu", vi2, ti, np.repeat(2 * k, 2 * V) + np.tile([0, 1], V),
                                      {"gyro_rad_s": gyro, "accel_m_s2": acc})
        g = np.flatnonzero((np.arange(V) + k) % 10 == 0)  # 5 Hz, staggered over the fleet
        n = 2 * V + 2 * V
        if g.size:
            sp = 12.0 + rng.normal(0, 0.05, g.size)
            crs = heading(t)[g] % (2 * math.pi)
            streams["gnss"] = frame.Stream("gnss", "gnss", g.astype(np.uint32), np.full(g.size, t),
                                           np.full(g.size, k // 10, np.int64), {
                "lat_deg": lat0[g] + 1e-6 * k, "lon_deg": lon0[g], "alt_m": np.full(g.size, 20.0),
                "vel_enu_m_s": np.stack([sp * np.sin(crs), sp * np.cos(crs), np.zeros(g.size)], axis=1),
                "course_rad": crs, "speed_m_s": sp, "fix_type": "3d", "num_sats": np.full(g.size, 12, np.int64),
                "pdop": np.full(g.size, 1.2)})
            n += g.size
        return frame.encode("bench-ingest", "clean", k, names, streams), n

    import zenoh

    fkey = keys.fleet_frame("bench-ingest", "clean")

    def service(trusted: bool):
        """The service in process; ``trusted``: every vehicle starts with a parameter set (a fleet whose sets
        were saved or come from the manifest: the EKF then publishes only on a clear change)."""
        cfg = {}
        if trusted:
            for v, name in enumerate(names):
                cfg[name] = {"mag_params": {sid: {"offset_nt": offs[j, v].tolist(), "matrix": soft[j, v].ravel().tolist(),
                                                  "field_radius_nt": float(np.linalg.norm(b_earth)), "model": "2d",
                                                  "observable": [True, True, False]}
                                            for j, sid in enumerate(("1", "2"))}}
        svc = Calibration(Settings(persist=False), instance="cores-cal", vehicles_config=cfg)
        r = Runner(svc, _DroppingSession())
        r._sub_exprs = [zenoh.KeyExpr(x) for x in svc.subscriptions()]  # what Runner.run declares
        svc.on_start()
        return svc, r

    def timed(svc, r, k0: int, n_frames: int) -> tuple[float, float]:
        data = [frame_payload(k0 + i) for i in range(n_frames)]
        fit0 = svc.fleet.fit_cpu_s
        t0 = time.process_time()
        for p, _n in data:
            r.handle_sample(fkey, p)
        cpu = time.process_time() - t0
        n = sum(x[1] for x in data)
        return (cpu - (svc.fleet.fit_cpu_s - fit0)) / n * 1e6, cpu / n * 1e6

    # cold start: no set anywhere, every sensor's EKF publishing a converging set every 5 s (timed after the first
    # second: every vehicle and slot created)
    svc, r = service(False)
    for k in range(50):
        r.handle_sample(fkey, frame_payload(k)[0])
    cold_us = timed(svc, r, 50, cold_frames)[0]
    # steady state: sets in use, windows filling, fits within the budget
    svc, r = service(True)
    n_warm = int(warm_s / 0.02)
    for k in range(n_warm):
        r.handle_sample(fkey, frame_payload(k)[0])
    blocks = []
    k = n_warm
    for _ in range(repeats):
        blocks.append(timed(svc, r, k, frames))
        k += frames
    stream_us = statistics.median(b[0] for b in blocks)
    total_us = statistics.median(b[1] for b in blocks)
    rate = V * (2 * 50 + 100 + 5)  # samples/s
    sched = svc.fleet.scheduler_status()

    # one fit on a full window (a simulated car, 600 s at the default decimation)
    from sim_publishers.car.core import simulate

    d = simulate(seed=1, duration_s=full_window_s)
    cal = SensorCalibrator("1", CalibrationSettings())
    for t, b in zip(d.t_mag_s, d.mag_b_nt["1"], strict=True):
        cal.update(t, b)
    cal.fit(d.t_mag_s[-1])
    full = cal.window()
    fit_s = _median_time(lambda: cfleet.fit_window("1", full, 700.0, cal.current, CalibrationSettings()), 5)
    sensors = 2 * V
    budget = Settings().fit_budget_frac

    # the same service on v1 singles, and the per-vehicle reference core, per sample
    msgs = []
    for i in range(singles_frames):
        f = frame.decode(frame_payload(k + i)[0])
        for name, st in f.streams.items():
            g_vi, a, b = st.groups()
            for v, x, y in zip(g_vi.tolist(), a.tolist(), b.tolist(), strict=True):
                key = keys.clean_mag(names[v], name[4:]) if name.startswith("mag/") else \
                    (keys.clean_imu(names[v]) if name == "imu" else keys.clean_gnss(names[v]))
                msgs += [(key, m) for m in st.messages(names[v], x, y)]
    enc = [(key, messages.encode(m)) for key, m in msgs]
    t0 = time.process_time()
    for key, p in enc:
        r.handle_sample(key, p)
    singles_us = (time.process_time() - t0) / len(enc) * 1e6
    # the reference with the declination the service found (its IGRF lookups are not what is timed)
    ref = {v: VehicleCalibration(v, CalibrationSettings(), OnlineSettings(), declination_rad=-0.1) for v in names}
    t0 = time.process_time()
    for _key, m in msgs:
        vc = ref[m["vehicle"]]
        if m["type"] == "mag":
            sc = vc.on_mag(m["sensor"], m["t_s"], m["b_nt"])
            cur = sc.current
            if cur is not None:
                cur.params.apply(m["b_nt"])
        elif m["type"] == "imu":
            vc.on_imu(m["t_s"], m["gyro_rad_s"], m["accel_m_s2"])
        else:
            vc.on_gnss(m["t_s"], m)
    ref_us = (time.process_time() - t0) / len(msgs) * 1e6
    return {"vehicles": V, "samples_per_s": rate, "frames_timed": frames * repeats,
            "frame_us_per_sample": round(stream_us, 3), "frame_us_per_sample_with_fits": round(total_us, 3),
            "frame_us_per_sample_cold_start": round(cold_us, 3),
            "core_share_of_one_core_without_fits": round(stream_us * rate / 1e6, 3),
            "fit_budget_frac": budget,
            "expected_core_share": round(stream_us * rate / 1e6 + budget, 3),
            "fit_ms_full_window": round(fit_s * 1e3, 2), "window_samples": len(full),
            "fits_due_per_s": round(sensors / CalibrationSettings().refit_interval_s, 1),
            "fit_demand_core_share": round(sensors / CalibrationSettings().refit_interval_s * fit_s, 2),
            "refit_interval_within_budget_s": round(max(CalibrationSettings().refit_interval_s,
                                                        sensors * fit_s / budget), 1),
            "fit_lag_s_in_run": sched["fit_lag_s"], "fits_in_run": sched["fits"],
            "singles_us_per_sample": round(singles_us, 2), "reference_core_us_per_sample": round(ref_us, 2),
            "frame_speedup_vs_singles": round(singles_us / stream_us, 1),
            "kernels_first_call_s": first["first_call_s"], "kernels_from_cache": bool(first["cache_hits"]),
            "load_average_1min": round(os.getloadavg()[0], 2)}


def fcm() -> dict:
    from bench.eval_dmc import fcm_speed

    return fcm_speed()


def ekf_update(n: int = 20_000) -> dict:
    from bench import heading_broad as hb

    trial = hb.load_trial(hb.trial_files()[0]).sliced(n)
    out = {"trial": trial.name, "samples": n}
    for name, fn in (("magmesh", lambda: hb.run_magmesh(trial, impl="reference")),
                     ("ahrs_ekf", lambda: hb.run_ahrs_ekf(trial)), ("imufusion", lambda: hb.run_imufusion(trial))):
        out[f"{name}_us_per_sample"] = round(_median_time(fn, 1) / n * 1e6, 2)
    out["speedup_vs_ahrs_ekf"] = round(out["ahrs_ekf_us_per_sample"] / out["magmesh_us_per_sample"], 2)
    out["speedup_vs_imufusion"] = round(out["imufusion_us_per_sample"] / out["magmesh_us_per_sample"], 2)
    return out


def heading_ekf(n: int = 20_000, n_reference: int = 4_000, repeats: int = 5, slots: int = 500,
                fleet_samples: int = 1200, frame_samples: int = 6) -> dict:
    """The heading EKF per sample (one IMU step + its magnetometer sample, BROAD trial 02, ``imu_only``):
    the reference (:class:`core.HeadingFilter`), the compiled filter called once per sample
    (``CompiledHeadingFilter``), the compiled filter over the whole slice in one call, and a fleet of
    ``slots`` vehicles stepped together (each call a frame of ``frame_samples`` samples of every vehicle, rows
    interleaved by vehicle; timed after each vehicle's first second, its alignment) — beside ``vqf``'s compiled ``updateBatch`` on the same slice. Medians of
    ``repeats`` runs of CPU time, µs per sample; every compiled kernel is loaded before timing."""
    from bench import heading_broad as hb
    from services.heading_fuser import compiled, profiles

    compiled.warm()
    trial = hb.load_trial(hb.trial_files()[0]).sliced(n)
    settings = profiles.settings(profiles.IMU_ONLY)
    g, a, m = trial.gyro_rad_s, trial.accel_m_s2, trial.mag_nt
    dt = 1.0 / trial.rate_hz
    ref = trial.sliced(n_reference)
    t_ref = _median_cpu_time(lambda: hb.run_magmesh(ref, settings, impl="reference"), max(1, repeats // 2)) / n_reference

    def single():
        f = compiled.CompiledHeadingFilter(settings)
        gl, al, ml = g.tolist(), a.tolist(), m.tolist()
        for i in range(n):
            f.update_imu(gl[i], al[i], dt if i else 0.0)
            f.update_mag(ml[i])

    def batched():
        compiled.run_recording(settings, g, a, m, dt)

    # the fleet: every vehicle replays the slice's first fleet_samples samples, frame by frame
    k = fleet_samples
    kind, t, ra, rb, rdt, rdmc, _, _ = compiled.recording_rows(g[:k], a[:k], m[:k], dt)  # 2 rows per sample
    frames = []
    for f0 in range(0, k, frame_samples):
        r0, r1 = 2 * f0, 2 * min(k, f0 + frame_samples)
        rows = r1 - r0
        idx = np.tile(np.arange(r0, r1), slots)
        frames.append((f0, (np.repeat(np.arange(slots), rows), kind[idx], t[idx], ra[idx], rb[idx], rdt[idx],
                            rdmc[idx])))
    skip = int(round(trial.rate_hz))  # the first second aligns (cheap rows): the fleet's timing starts after it
    timed = slots * sum(min(k, f0 + frame_samples) - f0 for f0, _ in frames if f0 >= skip)

    def fleet() -> float:  # CPU s for the frames after the first second (alignment is cheap: not timed)
        fl = compiled.FleetHeading(slots)
        for _ in range(slots):
            fl.add(settings)
        spent = 0.0
        for f0, fr in frames:
            t0 = time.process_time()
            fl.step(*fr, full_output=True)
            if f0 >= skip:
                spent += time.process_time() - t0
        return spent

    def vqf():
        hb.run_vqf(trial)

    single()  # the first call of each path loads its kernels
    out = {"trial": trial.name, "profile": profiles.IMU_ONLY, "samples": n, "reference_samples": n_reference,
           "fleet_slots": slots, "fleet_samples_per_slot": k, "fleet_frame_samples": frame_samples,
           "reference_us_per_sample": round(t_ref * 1e6, 2),
           "compiled_single_call_us_per_sample": round(_median_cpu_time(single, repeats) / n * 1e6, 3),
           "compiled_batched_us_per_sample": round(_median_cpu_time(batched, repeats) / n * 1e6, 3),
           "compiled_fleet_us_per_sample": round(statistics.median(fleet() for _ in range(repeats)) / timed * 1e6, 3),
           "vqf_batched_us_per_sample": round(_median_cpu_time(vqf, repeats) / n * 1e6, 3)}
    out["batched_speedup_vs_reference"] = round(out["reference_us_per_sample"] / out["compiled_batched_us_per_sample"], 1)
    return out


def heading_service(vehicles: int = 500, windows: int = 250, warmup_windows: int = 100, repeats: int = 3) -> dict:
    """The heading service's work per input sample at ``vehicles`` vehicles, in process (no Zenoh; a publisher that
    drops what it is given): every 20 ms a ``clean`` frame (per vehicle 2 IMU, 1 + 1 magnetometer samples, a GNSS
    fix every 10th window), then the ``cal`` frame (both magnetometers compensated) and the ``dmc`` frame (one
    verdict) of the same window, encoded as ingest, calibration and the DMC detector send them. Every vehicle
    drives a simulated car (the same drive, each from its own starting point; every verdict valid). CPU time of
    the frames' handling (decode, seq tracking, join, filters, output rules, heading messages) after
    ``warmup_windows`` windows (alignment); µs per input sample the service takes (IMU, clean and calibrated
    magnetometer 1, verdicts: 250 a vehicle-second), medians of ``repeats`` runs, and the share of one core
    that is at 50 windows a second."""
    import os
    import tempfile
    import tomllib

    from magmesh.magcal import MagParams
    from magmesh.paths import DEPLOY_DIR
    from magmesh.runtime import Runner
    from schemas import frame, keys
    from services.heading_fuser import compiled
    from services.heading_fuser import fleet as hfleet
    from services.heading_fuser.service import HeadingFuser, Settings
    from sim_publishers.car.core import simulate

    os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-cores-"))
    with open(DEPLOY_DIR / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    n_win = warmup_windows + windows
    spread = 200  # starting points: vehicle v starts (v mod spread) windows into the drive
    d = simulate(duration_s=(n_win + spread) * 0.02 + 1.0, layout="urban_a", seed=3)
    p = {s: MagParams.from_message(car["mag_params"][s]) for s in ("1", "2")}
    names = [f"bench-{v:04d}" for v in range(vehicles)]
    start = np.arange(vehicles) % spread
    vi = np.arange(vehicles, dtype=np.uint32)

    def stream(name, msg_type, t, seq, cols, rows_per=1):
        return frame.Stream(name, msg_type, np.repeat(vi, rows_per), t, seq, cols)

    payloads = []
    for w in range(n_win):
        t0 = 0.02 * w
        im = (2 * (start + w))[:, None] + np.arange(2)[None, :]  # 2 IMU samples per vehicle
        mg = start + w
        t_imu = (t0 + 0.01 * np.arange(2))[None, :].repeat(vehicles, 0).ravel()
        t_mag = np.full(vehicles, t0)
        seq_imu = (2 * w + np.arange(2))[None, :].repeat(vehicles, 0).ravel()
        seq_mag = np.full(vehicles, w, np.int64)
        clean = {"mag/1": stream("mag/1", "mag", t_mag, seq_mag, {"sensor": "1", "b_nt": d.mag_b_nt["1"][mg]}),
                 "mag/2": stream("mag/2", "mag", t_mag, seq_mag, {"sensor": "2", "b_nt": d.mag_b_nt["2"][mg]}),
                 "imu": stream("imu", "imu", t_imu, seq_imu, {"gyro_rad_s": d.gyro_rad_s[im.ravel()],
                                                              "accel_m_s2": d.accel_m_s2[im.ravel()]}, 2)}
        if w % 10 == 0:
            g = {"lat_deg": np.full(vehicles, 32.06), "lon_deg": np.full(vehicles, 118.8),
                 "alt_m": np.full(vehicles, 10.0), "pos_enu_m": np.zeros((vehicles, 3)),
                 "vel_enu_m_s": np.zeros((vehicles, 3)), "course_rad": np.zeros(vehicles),
                 "speed_m_s": np.zeros(vehicles), "fix_type": "3d", "num_sats": np.full(vehicles, 9, np.int64),
                 "pdop": np.ones(vehicles), "horiz_std_m": np.ones(vehicles)}
            clean["gnss"] = stream("gnss", "gnss", t_mag, np.full(vehicles, w // 10, np.int64), g)
        cal = {f"mag/{s}": stream(f"mag/{s}", "mag", t_mag, seq_mag, {
            "sensor": s, "b_nt": p[s].apply(d.mag_b_nt[s][mg]), "calibrated": np.ones(vehicles, np.uint8),
            "param_id": "manifest"}) for s in ("1", "2")}
        one = np.ones(vehicles)
        dmc = {"dmc": stream("dmc", "dmc", t_mag, seq_mag, {
            "dm_nt": np.zeros((vehicles, 2)), "ddm_nt_s": np.zeros((vehicles, 2)), "dh_rad": np.zeros(vehicles),
            "ddh_rad_s": np.zeros(vehicles), "heading_rad": np.zeros(vehicles), "stage1_pass": one.astype(np.uint8),
            "credibility": one, "valid": one.astype(np.uint8), "impl": "threshold", "param_source": "manifest"})}
        payloads.append([(keys.fleet_frame("ingest-1", "clean"), frame.encode("ingest-1", "clean", w, names, clean)),
                         (keys.fleet_frame("cal-1", "cal"), frame.encode("cal-1", "cal", w, names, cal)),
                         (keys.fleet_frame("dmc-1", "dmc"), frame.encode("dmc-1", "dmc", w, names, dmc))])
    n_in = windows * vehicles * (2 + 1 + 1 + 1)  # what it takes: imu, clean mag/1, cal mag/1, dmc


    def run() -> tuple[float, float, int]:
        svc = HeadingFuser(Settings(), instance="cores-heading",
                           vehicles_config={v: car for v in names})
        r = Runner(svc, _DroppingSession())
        import zenoh

        r._sub_exprs = [zenoh.KeyExpr(k) for k in svc.subscriptions()]
        svc.on_start()
        step_cpu = [0.0]
        fleet_step = compiled.FleetHeading.step

        def timed_step(self, *a, **k):
            t = time.process_time()
            try:
                return fleet_step(self, *a, **k)
            finally:
                step_cpu[0] += time.process_time() - t

        spent = 0.0
        for w, frames in enumerate(payloads):
            if w == warmup_windows:
                compiled.FleetHeading.step = timed_step
                sent0 = sum(c.n for k, c in r.count_out.items() if k.endswith("/heading"))
            t = time.process_time()
            for k, pl in frames:
                r.handle_sample(k, pl)
            if w >= warmup_windows:
                spent += time.process_time() - t
        compiled.FleetHeading.step = fleet_step
        assert not any("handler_error" in x for x in r.drops.values()), r.last_error
        sent = sum(c.n for k, c in r.count_out.items() if k.endswith("/heading")) - sent0
        return spent, step_cpu[0], sent

    hfleet.warm()
    compiled.warm()
    runs = [run() for _ in range(repeats)]
    total = statistics.median(x[0] for x in runs)
    filt = statistics.median(x[1] for x in runs)
    us = total / n_in * 1e6
    return {"vehicles": vehicles, "windows": windows, "input_samples": n_in,
            "input_samples_per_vehicle_s": 250, "heading_messages": runs[0][2],
            "us_per_input_sample": round(us, 3),
            "filter_us_per_input_sample": round(filt / n_in * 1e6, 3),
            "rest_us_per_input_sample": round((total - filt) / n_in * 1e6, 3),
            "cpu_share_of_one_core": round(total / (windows * 0.02), 3)}


def hausdorff() -> dict:
    from bench.eval_geomag import PAPER_LAMBDA, speed
    from magmesh.geomap import synthetic_paper_map
    from services.geomag_matcher.core import MatchSettings

    grid = synthetic_paper_map(7)
    base = MatchSettings(lambda_nt=PAPER_LAMBDA * grid.std_nt, search_radius_m=30 * grid.dx_m)
    return speed(grid, 1, base, scipy_candidates=1000)


def run_all(progress=None) -> dict:
    say = progress or (lambda s: None)
    out = {}
    for name, fn in (("ingest_validation", ingest_validation), ("ingest_wire", ingest_wire),
                     ("ingest_frames_500_vehicles", ingest_frames),
                     ("ingest_rules_per_sample", ingest_rules),
                     ("dmc_detector_per_epoch", dmc_detector),
                     ("calibration_fit", calibration_fit),
                     ("calibration_service_per_sample_500_vehicles", calibration_service), ("fcm", fcm),
                     ("ekf_update", ekf_update), ("heading_ekf", heading_ekf),
                     ("heading_service_per_sample", heading_service), ("hausdorff_match", hausdorff)):
        say(f"cores: {name}")
        out[name] = fn()
    return out
