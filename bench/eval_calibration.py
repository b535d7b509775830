"""Calibration evaluation: Two-Step LS vs ARLS (IGG-III), real clouds, online hard-iron EKF.

``magmesh eval calibration [--json]``.

1. **Simulated clouds** (bench/calibration_synthetic.py, seeded, known truth): hard iron up to
   5 × |B|, soft iron ±30% (diagonal) with ±10% cross-axis terms, 50 nT noise, gross errors on 0%,
   10%, 20% of the samples in 4 bursts, each of 20% of |B| in 3-D and 10% of |B| in 2-D (the
   paper's sizes). Errors: offset ``100·|b̂ − b|/|B|``; matrix: spectral-norm relative error of the
   identifiable shape ``sqrtm(MᵀM)/R`` (magmesh.magcal.matrix_error_pct). Worst over seeds.
   Goal: ARLS within 1% (offset and matrix) with 20% gross errors, where LS fails.
2. **Real clouds** (data/calibration, see data/README.md): HMC5883L full sphere (3-D), HMC5883L
   rotation about z (2-D), VN-100 car driving circles (2-D). Spread of the calibrated field strength
   ``std/median`` over the recorded samples, for LS and ARLS fitted on the recorded samples and on
   the same samples with injected gross errors (20% of the samples, 4 bursts, 20% (3-D) / 10% (2-D)
   of the median measured |m|). Both methods see the same coverage-balanced subset (sufficiency.py).
3. **Online EKF** on the simulated car (sim_publishers/car, layout urban_a): the GNSS-aided hard-iron
   EKF alone, started from a zero offset and identity matrix (no static fit): time until the
   observable offset components are converged, final offset error (horizontal), and the heading RMS
   of the compensated field after convergence, outside the sim's interference zones (truth
   ``disturbed`` flags), levelled with the true attitude so that only the calibration is measured.
   Also the full service logic (VehicleCalibration fed the drive's messages in time order): when the
   first parameter set appears and the heading RMS after it.
4. **Timing** of one fit of 10,000 samples (median of repeated runs, this machine).
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import replace

import numpy as np

from bench import calibration_synthetic as synthetic
from magmesh import magcal, maths, paths
from services.calibration import arls, online_ekf, sufficiency, two_step
from services.calibration.core import CalibrationSettings, OnlineSettings, VehicleCalibration

GOAL_PCT = 1.0
GOAL_HEADING_DEG = 2.0
STEP_NT = (1500.0, -1000.0, 0.0)  # hard-iron step of the service-logic scenario (≈ 3° of heading)
SIM_FRACS = (0.0, 0.1, 0.2)
GROSS_SIZE = {"2d": 0.10, "3d": 0.20}
REAL_DATASETS = {
    "hmc5883l_full_sphere": ("hmc5883l_full-sphere_mag.csv", "3d"),
    "hmc5883l_rotate_z": ("hmc5883l_rotate-ccw-around-z-pointing-up_mag.csv", "2d"),
    "vn100_car_circles": ("car_circles_vn100.csv", "2d"),
}


# ---- 1. simulated clouds ----------------------------------------------------------------------


def _errors(res: two_step.FitResult, cloud: synthetic.Cloud, model: str) -> tuple[float, float]:
    if not res.ok:
        return math.inf, math.inf
    p = res.params
    oe = magcal.offset_error_pct(p.offset, cloud.offset_nt, cloud.radius_nt)
    if model == "2d":
        me = magcal.matrix_error_pct(p.M[:2, :2], p.field_radius_nt, cloud.M[:2, :2], cloud.radius_nt)
    else:
        me = magcal.matrix_error_pct(p.M, p.field_radius_nt, cloud.M, cloud.radius_nt)
    return oe, me


def eval_sim(seeds: int, n_samples: int) -> dict:
    out: dict = {}
    for model in ("3d", "2d"):
        for frac in SIM_FRACS:
            rows: dict[str, list] = {"ls": [], "arls": []}
            for seed in range(seeds):
                cloud = synthetic.make_cloud(synthetic.CloudSettings(
                    model=model, n_samples=n_samples, gross_frac=frac, gross_size_rel=GROSS_SIZE[model], seed=seed))
                for name, fit in (("ls", two_step.fit_ls), ("arls", arls.fit_arls)):
                    res = fit(cloud.m_nt, model)
                    oe, me = _errors(res, cloud, model)
                    clean = ~cloud.gross
                    rm = two_step.rmse(cloud.m_nt[clean], res.params) if res.ok else math.inf
                    rows[name].append((oe, me, rm, res.n_gross_rejected, int(cloud.gross.sum())))
            cell = {}
            for name, r in rows.items():
                a = np.array(r, float)
                cell[name] = {
                    "offset_err_pct_worst": float(a[:, 0].max()), "offset_err_pct_median": float(np.median(a[:, 0])),
                    "matrix_err_pct_worst": float(a[:, 1].max()), "matrix_err_pct_median": float(np.median(a[:, 1])),
                    "rmse_clean_nt_median": float(np.median(a[:, 2])),
                    "gross_rejected_median": float(np.median(a[:, 3])), "gross_injected": int(a[0, 4]),
                }
            out[f"{model}_gross{int(round(100 * frac))}"] = cell
    return out


# ---- 2. real clouds ---------------------------------------------------------------------------


def load_real(name: str) -> np.ndarray:
    """N×3 magnetometer samples of a bundled recording, nT."""
    fname, _ = REAL_DATASETS[name]
    path = paths.DATA_DIR / "calibration" / fname
    if name == "vn100_car_circles":
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["magnetic_field_x"]]
        return np.array([[float(r[f"magnetic_field_{a}"]) for a in "xyz"] for r in rows]) * 1e9  # T → nT
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=(1, 2, 3)) * 1e5  # gauss → nT


def inject_gross(m: np.ndarray, model: str, frac: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    size = GROSS_SIZE[model] * float(np.median(np.linalg.norm(m, axis=1)))
    mask = synthetic.burst_mask(len(m), frac, 4, rng)
    out = m.copy()
    labels = np.cumsum(np.diff(np.concatenate([[0], mask.astype(int)])) == 1)[mask]
    dirs = rng.normal(size=(labels.max() + 1 if mask.any() else 1, 3))
    if model == "2d":
        dirs[:, 2] = 0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    out[mask] += dirs[labels] * size * rng.uniform(0.8, 1.2, (mask.sum(), 1))
    return out


def _spread(m_eval: np.ndarray, params: magcal.MagParams) -> float:
    h = params.apply(m_eval)
    s = np.hypot(h[:, 0], h[:, 1]) if params.model == "2d" else np.linalg.norm(h, axis=1)
    return magcal.spread(s)


def eval_real(seed: int = 0) -> dict:
    out = {}
    suf = sufficiency.SufficiencySettings()
    for name, (_, model) in REAL_DATASETS.items():
        m = load_real(name)
        entry: dict = {"model": model, "n_samples": int(len(m)),
                       "raw_spread": magcal.spread(np.linalg.norm(m[:, :2] if model == "2d" else m, axis=1))}
        for tag, data in (("clean", m), ("gross20", inject_gross(m, model, 0.20, seed))):
            idx = sufficiency.balanced_subset(data, model, suf)
            for meth, fit in (("ls", two_step.fit_ls), ("arls", arls.fit_arls)):
                res = fit(data[idx], model)
                entry[f"{meth}_{tag}"] = _spread(m, res.params) if res.ok else math.inf
                entry[f"{meth}_{tag}_gross_rejected"] = res.n_gross_rejected
            entry[f"coverage_{tag}"] = sufficiency.coverage(data[idx], model, suf)
        out[name] = entry
    return out


# ---- 3. online EKF on the simulated car ---------------------------------------------------------


def _window_mean(t: np.ndarray, x: np.ndarray, t_end: float, width: float) -> np.ndarray:
    i1 = int(np.searchsorted(t, t_end, side="right"))
    i0 = int(np.searchsorted(t, t_end - width, side="left"))
    return x[max(0, min(i0, i1 - 1)):max(i1, 1)].mean(axis=0)


def run_ekf_on_drive(drive, sensor: str = "1", settings: online_ekf.EkfSettings | None = None,
                     offset0=(0.0, 0.0, 0.0), matrix=None, tilt_source: str = "level") -> dict:
    """The EKF alone on a simulated drive, fed at every GNSS epoch as the service feeds it
    (``tilt_source`` "level": roll = pitch = 0; "accel": from the IMU with the motion removed)."""
    settings = settings or online_ekf.EkfSettings()
    g = drive.gnss
    m = drive.mag_b_nt[sensor]
    ekf = online_ekf.HardIronEkf(settings, offset0, matrix)
    t_hist, off_hist, mat_hist = [], [], []
    t_conv = None
    speed_rate = online_ekf.SpeedRate()
    for k in range(len(g.t_s)):
        tk = float(g.t_s[k])
        mk = _window_mean(drive.t_mag_s, m, tk, 0.2)
        ak = _window_mean(drive.t_imu_s, drive.accel_m_s2, tk, 1.0)
        wz = float(_window_mean(drive.t_imu_s, drive.gyro_rad_s, tk, 1.0)[2])
        sp = float(g.speed_m_s[k])
        rate = speed_rate.update(tk, sp)
        roll, pitch = online_ekf.car_roll_pitch(ak, rate, sp, wz) if tilt_source == "accel" else (0.0, 0.0)
        ok, _ = online_ekf.gnss_usable(str(g.fix_type[k]), int(g.num_sats[k]), float(g.pdop[k]), sp, settings)
        ekf.update(tk, mk, float(g.course_rad[k]), roll, pitch, drive.declination_rad, sp, wz, ok)
        if t_conv is None and ekf.converged:
            t_conv = tk
        t_hist.append(tk)
        off_hist.append(ekf.applied_offset())
        mat_hist.append(ekf.applied_matrix().ravel())
    return {"ekf": ekf, "t": np.array(t_hist), "offset": np.array(off_hist), "matrix": np.array(mat_hist),
            "t_conv": t_conv}


def heading_errors_deg(drive, sensor: str, offsets_at_mag: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Magnetic heading error per magnetometer sample, levelled with the true attitude, degrees.
    ``M`` is one 3×3 matrix or one per sample (N×3×3)."""
    d = drive.mag_b_nt[sensor] - offsets_at_mag
    h = np.einsum("ij,nj->ni", M, d) if np.ndim(M) == 2 else np.einsum("nij,nj->ni", M, d)
    return _level_heading_err(drive, h, np.ones(len(h), bool))


def _at(t_query: np.ndarray, t: np.ndarray, values: np.ndarray, default) -> np.ndarray:
    i = np.searchsorted(t, t_query, side="right") - 1
    out = np.where((i >= 0)[:, None], values[np.clip(i, 0, len(values) - 1)], np.asarray(default)[None, :])
    return out


def eval_online(seeds: int, duration_s: float, layout: str = "urban_a") -> dict:
    from sim_publishers.car import core as car

    per_seed = []
    for seed in range(1, seeds + 1):
        drive = car.simulate(seed=seed, layout=layout, duration_s=duration_s)
        for sensor in ("1", "2"):
            truth = drive.true_params[sensor]
            r = run_ekf_on_drive(drive, sensor)
            ekf = r["ekf"]
            offs = _at(drive.t_mag_s, r["t"], r["offset"], np.zeros(3))
            mats = _at(drive.t_mag_s, r["t"], r["matrix"], np.eye(3).ravel()).reshape(-1, 3, 3)
            err = heading_errors_deg(drive, sensor, offs, mats)
            sel = ~drive.truth.disturbed & (drive.t_mag_s > (r["t_conv"] if r["t_conv"] is not None else np.inf))
            # the same with the true matrix: what is left when only the offset is estimated online
            r_m = run_ekf_on_drive(drive, sensor, matrix=truth.matrix)
            offs_m = _at(drive.t_mag_s, r_m["t"], r_m["offset"], np.zeros(3))
            mats_m = _at(drive.t_mag_s, r_m["t"], r_m["matrix"], truth.matrix.ravel()).reshape(-1, 3, 3)
            err_m = heading_errors_deg(drive, sensor, offs_m, mats_m)
            sel_m = ~drive.truth.disturbed & (drive.t_mag_s > (r_m["t_conv"] if r_m["t_conv"] is not None else np.inf))
            raw_err = heading_errors_deg(drive, sensor, np.zeros_like(drive.mag_b_nt[sensor]), np.eye(3))
            per_seed.append({
                "seed": seed, "sensor": sensor,
                "converge_s": r["t_conv"],
                "offset_err_xy_nt": float(np.linalg.norm(ekf.x[:2] - truth.offset_nt[:2])),
                "offset_err_xy_nt_true_matrix": float(np.linalg.norm(r_m["ekf"].x[:2] - truth.offset_nt[:2])),
                "observable": list(ekf.observable),
                "heading_rms_deg": float(np.sqrt(np.mean(err[sel] ** 2))) if sel.any() else math.inf,
                "heading_rms_deg_true_matrix": float(np.sqrt(np.mean(err_m[sel_m] ** 2))) if sel_m.any() else math.inf,
                "raw_heading_rms_deg": float(np.sqrt(np.mean(raw_err[~drive.truth.disturbed] ** 2))),
                "fused": ekf.n_fused, "gated": ekf.n_rejected,
                "mount_yaw_deg": math.degrees(ekf.mount_yaw_rad), "mount_yaw_std_deg": math.degrees(ekf.mount_yaw_std_rad),
            })
    conv = [p["converge_s"] for p in per_seed]
    return {
        "layout": layout, "duration_s": duration_s, "runs": per_seed,
        "converge_s_worst": max((c if c is not None else math.inf) for c in conv),
        "offset_err_xy_nt_worst": max(p["offset_err_xy_nt"] for p in per_seed),
        "heading_rms_deg_worst": max(p["heading_rms_deg"] for p in per_seed),
        "raw_heading_rms_deg_median": float(np.median([p["raw_heading_rms_deg"] for p in per_seed])),
        "vertical_observable_any": any(p["observable"][2] for p in per_seed),
    }


def eval_service_logic(seed: int, duration_s: float, layout: str = "urban_a", step_nt=None,
                       step_t_s: float | None = None, online: OnlineSettings | None = None) -> dict:
    """The service's per-vehicle logic fed a simulated drive's messages in time order (no mesh),
    with the online EKF and with static fits only. ``step_nt`` adds a hard-iron step (both sensors, sensor
    frame) from ``step_t_s`` on: new cargo, a magnetised part — the case the online EKF is for."""
    from sim_publishers.car import core as car

    drive = car.simulate(seed=seed, layout=layout, duration_s=duration_s)
    if step_nt is not None:
        after = drive.t_mag_s >= step_t_s
        for sid in drive.mag_b_nt:
            drive.mag_b_nt[sid] = drive.mag_b_nt[sid].copy()
            drive.mag_b_nt[sid][after] += np.asarray(step_nt, float)
    out: dict = {"seed": seed, "layout": layout, "step_nt": None if step_nt is None else list(step_nt),
                 "step_t_s": step_t_s}
    for mode in ("online", "static"):
        vc = VehicleCalibration("car", CalibrationSettings(),
                                replace(online or OnlineSettings(), enabled=mode == "online"))
        t0 = time.perf_counter()
        history: dict[str, list] = {"1": [], "2": []}  # (t, param_id, status, method, params)
        for t_s, key, _mtype, fields in car.iter_messages(drive, "car", truth=False):
            if "/mag/" in key:
                sid = fields["sensor"]
                sc = vc.on_mag(sid, t_s, fields["b_nt"])
                if sc.due(t_s):
                    sc.fit(t_s)
                cur = sc.current
                if cur is not None and (not history[sid] or history[sid][-1][1] != cur.param_id):
                    history[sid].append((t_s, cur.param_id, cur.status, cur.method, cur.params))
            elif key.endswith("/imu"):
                vc.on_imu(t_s, fields["gyro_rad_s"], fields["accel_m_s2"])
            elif key.endswith("/gnss"):
                vc.on_gnss(t_s, fields)
        res: dict = {"wall_s": time.perf_counter() - t0, "sensors": {}}
        for sid, hist in history.items():
            ok = [h for h in hist if h[2] == "ok"]
            if not ok:
                res["sensors"][sid] = {"first_ok_s": None, "sets": len(hist)}
                continue
            errs = np.full(len(drive.t_mag_s), np.nan)
            for j, h in enumerate(hist):
                t_end = hist[j + 1][0] if j + 1 < len(hist) else np.inf
                sel = (drive.t_mag_s >= h[0]) & (drive.t_mag_s < t_end)
                if h[2] == "ok" and sel.any():
                    errs[sel] = _heading_err_subset(drive, sid, sel, h[4])
            use = ~np.isnan(errs) & ~drive.truth.disturbed
            late = use & (drive.t_mag_s >= (step_t_s if step_t_s is not None else 0.0) + 60.0)
            res["sensors"][sid] = {
                "heading_rms_deg_from_step_plus_60s": float(np.sqrt(np.mean(errs[late] ** 2))) if late.any() else None,
                "first_ok_s": float(ok[0][0]), "calib_turn_end_s": float(drive.calib_turn_t_s[1]),
                "sets": len(hist), "ok_sets": len(ok), "methods": sorted({h[3] for h in ok}),
                "final_offset_err_xy_nt": float(np.linalg.norm(hist[-1][4].offset[:2] - drive.true_params[sid].offset_nt[:2]
                                                               - (0.0 if step_nt is None else np.asarray(step_nt)[:2]))),
                "set_times_s": [round(float(h[0]), 1) for h in ok],
                "heading_rms_deg": float(np.sqrt(np.mean(errs[use] ** 2))) if use.any() else math.inf,
            }
        out[mode] = res
    return out


def _heading_err_subset(drive, sid: str, sel: np.ndarray, p: magcal.MagParams) -> np.ndarray:
    return _level_heading_err(drive, p.apply(drive.mag_b_nt[sid][sel]), sel)


def _level_heading_err(drive, h: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Heading error (deg) of compensated samples h (rows of ``sel``), levelled with the true attitude:
    Ry(−θ) Rx(φ) row-wise, as maths.tilt_compensated_heading."""
    th, ph = drive.truth.pitch_rad[sel], drive.truth.roll_rad[sel]
    cy, sy = np.cos(-th), np.sin(-th)
    cx, sx = np.cos(ph), np.sin(ph)
    y1 = cx * h[:, 1] - sx * h[:, 2]
    z1 = sx * h[:, 1] + cx * h[:, 2]
    lx = cy * h[:, 0] + sy * z1
    psi = maths.mag_heading_flu(lx, y1, drive.declination_rad)
    return np.degrees(maths.angle_diff(psi, drive.truth.heading_rad[sel]))


# ---- 4. timing --------------------------------------------------------------------------------


def eval_timing(repeats: int = 7) -> dict:
    """Time one fit of 10,000 samples (3-D, 20% gross errors), in this process."""
    cloud = synthetic.make_cloud(synthetic.CloudSettings(n_samples=10_000, gross_frac=0.2, seed=99))
    out = {}
    for name, fit in (("ls", two_step.fit_ls), ("arls", arls.fit_arls)):
        ts, cpu = [], []
        for _ in range(repeats):
            c0 = time.process_time()
            ts.append(fit(cloud.m_nt, "3d").duration_ms)
            cpu.append(1e3 * (time.process_time() - c0))
        out[f"{name}_fit_10k_ms_median"] = float(np.median(ts))
        out[f"{name}_fit_10k_ms_min"] = float(np.min(ts))
        out[f"{name}_fit_10k_cpu_ms_median"] = float(np.median(cpu))  # CPU time of this process (all threads)
    return out


def eval_timing_single_thread(repeats: int = 7) -> dict:
    """The same timing in a fresh process with single-threaded BLAS, as the service runs
    (services/calibration/__main__.py): on a shared 2-core machine BLAS threads only spin."""
    import json
    import os
    import subprocess
    import sys

    code = f"import json; from bench.eval_calibration import eval_timing; print(json.dumps(eval_timing({repeats})))"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": str(paths.REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    try:
        r = subprocess.run([sys.executable, "-c", code], env=env, cwd=paths.REPO, capture_output=True, text=True,
                           timeout=120, check=True)
        return json.loads(r.stdout.strip().splitlines()[-1])
    except (subprocess.SubprocessError, ValueError, IndexError) as e:
        return {"error": f"{type(e).__name__}: {e}"}


# ---- entry points -----------------------------------------------------------------------------


def add_arguments(parser) -> None:
    parser.add_argument("--seeds", type=int, default=10, help="simulated clouds per cell (default 10)")
    parser.add_argument("--samples", type=int, default=3000, help="samples per simulated cloud")
    parser.add_argument("--car-seeds", type=int, default=3, help="simulated car drives for the online EKF")
    parser.add_argument("--car-duration", type=float, default=300.0, help="simulated drive length, s")
    parser.add_argument("--no-service", action="store_true", help="skip the service-logic replay")
    parser.add_argument("--timing-repeats", type=int, default=7, help="fits timed per method")


def run(args) -> dict:
    t0 = time.perf_counter()
    sim = eval_sim(args.seeds, args.samples)
    real = eval_real()
    online = eval_online(args.car_seeds, args.car_duration)
    service = step = None
    if not getattr(args, "no_service", False):
        service = eval_service_logic(1, args.car_duration)
        step = eval_service_logic(1, args.car_duration, step_nt=STEP_NT, step_t_s=0.4 * args.car_duration)
    reps = getattr(args, "timing_repeats", 7)
    timing = eval_timing(reps)
    timing_1t = eval_timing_single_thread(reps)
    h = sim["3d_gross20"]
    result = {
        "arls_offset_err_pct": h["arls"]["offset_err_pct_worst"],
        "arls_matrix_err_pct": h["arls"]["matrix_err_pct_worst"],
        "ls_offset_err_pct": h["ls"]["offset_err_pct_worst"],
        "ls_matrix_err_pct": h["ls"]["matrix_err_pct_worst"],
        "arls_goal_met": bool(h["arls"]["offset_err_pct_worst"] <= GOAL_PCT
                              and h["arls"]["matrix_err_pct_worst"] <= GOAL_PCT),
        "ls_fails": bool(h["ls"]["offset_err_pct_worst"] > GOAL_PCT or h["ls"]["matrix_err_pct_worst"] > GOAL_PCT),
        "real_spread": {k: {"ls": v["ls_gross20"], "arls": v["arls_gross20"]} for k, v in real.items()},
        "real_spread_clean": {k: {"ls": v["ls_clean"], "arls": v["arls_clean"]} for k, v in real.items()},
        "arls_beats_ls_real": bool(all(v["arls_gross20"] < v["ls_gross20"] for v in real.values())),
        "online_heading_rms_deg": online["heading_rms_deg_worst"],
        "online_converge_s": online["converge_s_worst"],
        "online_offset_err_xy_nt": online["offset_err_xy_nt_worst"],
        "online_goal_met": bool(online["heading_rms_deg_worst"] <= GOAL_HEADING_DEG),
        **timing,
        "timing_single_thread_blas": timing_1t,
        "sim": sim,
        "real": real,
        "online": online,
        "service_logic": service,
        "service_logic_hard_iron_step": step,
        "settings": {"seeds": args.seeds, "samples": args.samples, "car_seeds": args.car_seeds,
                     "car_duration_s": args.car_duration, "gross_size_rel": GROSS_SIZE},
        "eval_wall_s": time.perf_counter() - t0,
    }
    return _plain(result)


def _plain(v):
    """JSON-safe plain Python: numpy scalars to Python, non-finite floats to None (strict JSON has no inf)."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def _f(x, nd=3) -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return "inf"
    return f"{x:.{nd}f}"


def format_text(r: dict) -> str:
    lines = ["Calibration evaluation", "",
             f"Simulated clouds ({r['settings']['seeds']} seeds × {r['settings']['samples']} samples; "
             "worst over seeds; offset % of |B|, matrix % of shape)",
             f"{'case':<14}{'LS off%':>9}{'LS mat%':>9}{'ARLS off%':>11}{'ARLS mat%':>11}{'ARLS rej':>10}{'injected':>10}"]
    for k, v in r["sim"].items():
        lines.append(f"{k:<14}{_f(v['ls']['offset_err_pct_worst']):>9}{_f(v['ls']['matrix_err_pct_worst']):>9}"
                     f"{_f(v['arls']['offset_err_pct_worst']):>11}{_f(v['arls']['matrix_err_pct_worst']):>11}"
                     f"{v['arls']['gross_rejected_median']:>10.0f}{v['arls']['gross_injected']:>10d}")
    lines += ["", f"goal (3-D, 20% gross): ARLS ≤ {GOAL_PCT}% → {'met' if r['arls_goal_met'] else 'NOT met'}; "
              f"LS {'fails' if r['ls_fails'] else 'also passes'}", "",
              "Real clouds: spread std/median of the calibrated field strength (recorded samples)",
              f"{'dataset':<24}{'model':>6}{'raw':>8}{'LS':>8}{'ARLS':>8}{'LS+gross':>10}{'ARLS+gross':>12}"]
    for k, v in r["real"].items():
        lines.append(f"{k:<24}{v['model']:>6}{_f(v['raw_spread'], 4):>8}{_f(v['ls_clean'], 4):>8}"
                     f"{_f(v['arls_clean'], 4):>8}{_f(v['ls_gross20'], 4):>10}{_f(v['arls_gross20'], 4):>12}")
    o = r["online"]
    lines += ["", f"Online hard-iron EKF, simulated car ({o['layout']}, {len(o['runs'])} runs, identity start)",
              f"{'seed':>5}{'sensor':>7}{'conv s':>8}{'off err nT':>12}{'hdg RMS°':>10}{'raw RMS°':>10}{'obs':>10}"]
    for p in o["runs"]:
        obs = "".join("xyz"[i] if p["observable"][i] else "-" for i in range(3))
        lines.append(f"{p['seed']:>5}{p['sensor']:>7}{_f(p['converge_s'], 1):>8}{p['offset_err_xy_nt']:>12.0f}"
                     f"{_f(p['heading_rms_deg'], 2):>10}{_f(p['raw_heading_rms_deg'], 1):>10}{obs:>10}")
    lines.append(f"worst heading RMS after convergence {_f(r['online_heading_rms_deg'], 2)}° "
                 f"(goal ≤ {GOAL_HEADING_DEG}°: {'met' if r['online_goal_met'] else 'NOT met'})")
    s = r.get("service_logic")
    if s:
        lines += ["", f"Service logic on drive seed {s['seed']} ({s['layout']}), heading RMS outside zones "
                  "from the first fitted set on:"]
        for mode in ("online", "static"):
            for sid, v in s[mode]["sensors"].items():
                lines.append(f"  {mode:<7} sensor {sid}: first fit {_f(v.get('first_ok_s'), 1)} s (circle ends "
                             f"{_f(v.get('calib_turn_end_s'), 1)} s), {v.get('ok_sets')} sets "
                             f"{'/'.join(v.get('methods', []))}, heading RMS {_f(v.get('heading_rms_deg'), 2)}°, "
                             f"final offset err {_f(v.get('final_offset_err_xy_nt'), 0)} nT")
    s = r.get("service_logic_hard_iron_step")
    if s:
        lines += [f"Same drive with a hard-iron step {s['step_nt']} nT at {s['step_t_s']:.0f} s: heading RMS from "
                  "60 s after the step"]
        for mode in ("online", "static"):
            for sid, v in s[mode]["sensors"].items():
                lines.append(f"  {mode:<7} sensor {sid}: {_f(v.get('heading_rms_deg_from_step_plus_60s'), 2)}° "
                             f"({v.get('ok_sets')} sets {'/'.join(v.get('methods', []))})")
    lines += ["", f"10,000-sample fit: LS {r['ls_fit_10k_ms_median']:.1f} ms, ARLS {r['arls_fit_10k_ms_median']:.1f} ms "
              f"(median; min {r['arls_fit_10k_ms_min']:.1f} ms), this process"]
    t1 = r.get("timing_single_thread_blas", {})
    if "arls_fit_10k_ms_median" in t1:
        lines.append(f"  single-threaded BLAS (as the service runs): LS {t1['ls_fit_10k_ms_median']:.1f} ms, "
                     f"ARLS {t1['arls_fit_10k_ms_median']:.1f} ms (median; min {t1['arls_fit_10k_ms_min']:.1f} ms); "
                     f"CPU time LS {t1['ls_fit_10k_cpu_ms_median']:.1f} ms, ARLS {t1['arls_fit_10k_cpu_ms_median']:.1f} ms "
                     "(wall time grows when other jobs share the cores)")
    return "\n".join(lines)
