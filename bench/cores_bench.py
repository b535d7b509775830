"""``magmesh bench cores``: each pure core against its Python peer on the same input, in one run.

- ingest validation: decode + validate one message vs a bare ``msgpack.unpackb`` (the floor);
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

    a, b = _median_time(ours, repeats) / n * 1e6, _median_time(floor, repeats) / n * 1e6
    return {"decode_validate_us": round(a, 2), "msgpack_unpack_only_us": round(b, 2), "overhead_ratio": round(a / b, 2)}


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
    for name, fn in (("ingest_validation", ingest_validation), ("calibration_fit", calibration_fit), ("fcm", fcm),
                     ("ekf_update", ekf_update), ("hausdorff_match", hausdorff)):
        say(f"cores: {name}")
        out[name] = fn()
    return out
