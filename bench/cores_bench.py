"""``magmesh bench cores``: each pure core against its Python peer on the same input, in one run.

- ingest validation: decode + validate one message vs a bare ``msgpack.unpackb`` (the floor), and the
  reference (pure Python) validator beside the compiled one;
- ingest wire: the ingest service in process (no Zenoh), CPU per sample for v1 single samples against v2
  batches (a batch per vehicle per 20 ms), each sample decoded, validated and republished;
- calibration fit: LS and ARLS on 10,000 samples (3-D, 20 % gross errors) vs ``scipy.optimize.least_squares``
  fitting the same ellipsoid geometrically;
- FCM on 10,000 × 2 samples vs scikit-fuzzy's ``cmeans`` (same start);
- EKF update: the heading fuser vs the ``ahrs`` EKF and x-io ``imufusion`` (C) on the same BROAD slice, µs/sample;
- Hausdorff match: pre-match + SSDA + fine pipeline vs exhaustive search vs naive scipy ``directed_hausdorff``.
Times are medians (or minima where stated) of repeats in this process; ratios are taken in the same run.
"""

from __future__ import annotations

import statistics
import time

import numpy as np


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
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

    class _Pub:
        def put(self, payload, **kw):
            pass

    class _Session:
        def declare_publisher(self, key, **kw):
            return _Pub()

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
        r = Runner(Ingest(IngestServiceSettings(output=output), instance="cores-ingest"), _Session())
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


def calibration_fit(repeats: int = 5) -> dict:
    from scipy.optimize import least_squares

    from services.calibration import arls, synthetic, two_step

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


def fcm() -> dict:
    from bench.eval_dmc import fcm_speed

    return fcm_speed()


def ekf_update(n: int = 20_000) -> dict:
    from bench import heading_broad as hb

    trial = hb.load_trial(hb.trial_files()[0]).sliced(n)
    out = {"trial": trial.name, "samples": n}
    for name, fn in (("magmesh", lambda: hb.run_magmesh(trial)), ("ahrs_ekf", lambda: hb.run_ahrs_ekf(trial)),
                     ("imufusion", lambda: hb.run_imufusion(trial))):
        out[f"{name}_us_per_sample"] = round(_median_time(fn, 1) / n * 1e6, 2)
    out["speedup_vs_ahrs_ekf"] = round(out["ahrs_ekf_us_per_sample"] / out["magmesh_us_per_sample"], 2)
    out["speedup_vs_imufusion"] = round(out["imufusion_us_per_sample"] / out["magmesh_us_per_sample"], 2)
    return out


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
                     ("calibration_fit", calibration_fit), ("fcm", fcm),
                     ("ekf_update", ekf_update), ("hausdorff_match", hausdorff)):
        say(f"cores: {name}")
        out[name] = fn()
    return out
