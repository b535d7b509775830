"""``magmesh eval dmc``: DMC interference recognition on seeded simulated drives (docs/methods.md#dmc, #quasi-static).

Drives come from the car simulator's paper-streets profile (``sim_publishers.car.core.PAPER_STREETS``:
HMR3300 compasses at 8 Hz, layouts ``paper_a``/``paper_b``/``paper_c``), each compensated with the
simulator's true calibration plus an HMR3300 calibration's typical error. The FCM centres are trained once
on one drive (``paper_a`` seed 1) and applied to the other drives, including layouts never seen in training
(the paper's Table 4). Every row is printed beside the paper's figure for the same threshold set.

Keys of ``--json``:
  baselines.single_threshold  the paper's four threshold sets on one compass (|Δm|, dΔm only): its Table 2
  baselines.dmc_threshold     the same sets, all four DMC tests (stage 1 only): its Table 1
                              (each row: set, thresholds, rp_pct, mp_pct, wp_deg, paper {rp_pct, mp_pct, wp_deg})
  table3_fcm_train            FCM on its own training drive (paper / extended features; centre or error order)
  table4_fcm_apply            the trained centres applied per unseen drive, and pooled
  fcm_unseen                  {rp_pct, mp_pct, wp_deg} of the chosen FCM over the unseen layouts (paper beside)
  fcm_gain                    FCM against the threshold stage it starts from, on the same drives: RP gained at
                              equal MP and MP saved at equal RP (the threshold curve: the loose set scaled by
                              0.2–1.0), per unseen drive, and the seed-to-seed spread of that gain
  quasistatic                 the one-magnetometer detector of §2 (paper's form and the project's)
  quasistatic_broad           the same on real recordings (BROAD): handheld IMU board, magnets (full run only)
  second_stage                magmesh's own second stage (gyro_track): the compass heading checked against a heading
                              the gyro carries, either pulled towards each trusted epoch (reference "blend") or fitted
                              to the stage-1 epochs of the last minutes (reference "consensus"); the reference and its
                              settings chosen on training drives of the training layout only (rule and grids
                              recorded); same drives and keys as fcm_unseen
  second_stage_gain           as fcm_gain, for second_stage (threshold curve up to twice the loose set)
  fcm_speed                   10,000 × 2 samples: this FCM vs scikit-fuzzy and a plain loop implementation

  lab                         the paper's own experiment (sim_publishers.car.turntable): its conditions, baselines,
                              fcm_unseen and fcm_gain as above, and second_stage / second_stage_gain (the table's rate
                              gyro; settings chosen on magnet runs by the same grids and rule; second_stage also carries
                              meets_paper_table4 — RP above, MP and WP95 below the paper's Table 4 ranges — and, reported
                              only, rule_sensitivity and gate_sensitivity); lab.seed_sets: the FCM and the second stage
                              on the judged runs and on two more sets of cabinet and mixed runs (LAB_MORE_SEED_SETS), each
                              with its gain over the threshold curve; fcm_gain / second_stage_gain then also carry the
                              gains per set and their spread (seed_set_values_*, seed_set_spread_*)

Threshold sets: the paper's field units are HMR3300 output units, 32 nT each (FIELD_UNIT_NT); headings in degrees.
RP, MP, WP as the paper defines them ("good" = heading error < 5°); WP is the RMS heading error of the samples
recognised as valid (wp_mean_deg: mean |error|; wp_max_deg: the worst; wp_p95_deg: the 95th percentile, the reading
under which the paper's tables hang together). Each baseline row carries inside_paper_range and outside_paper_by. Onset delay: median time from the first bad sample of a
disturbance zone to the alarm (negative: the alarm was raised on the approach).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

#: the goal: beat the paper's DMC + FCM figures (Tables 3–4: RP 74–80 %, MP 5.4–6.1 %, WP 5.5–5.9°)
GOAL = {"rp_pct": 80.0, "mp_pct": 5.4, "wp_deg": 5.5}
# (layout, seed, cal_seed): cal_seed 0 is the car's calibration the training drive had; another
# cal_seed is the same car recalibrated (different calibration errors)
UNSEEN_FULL = [("paper_a", 12, 0), ("paper_a", 13, 0), ("paper_b", 11, 0), ("paper_b", 12, 0), ("paper_b", 13, 0),
               ("paper_c", 11, 0), ("paper_c", 12, 0), ("paper_c", 13, 0),
               ("paper_b", 14, 5), ("paper_c", 14, 6), ("paper_a", 14, 7)]
UNSEEN_QUICK = [("paper_b", 11, 0), ("paper_c", 11, 0), ("paper_c", 14, 6)]
#: the paper's own experiment (sim_publishers.car.turntable): trained on one run (its Table 4 protocol: sample 1),
#: judged on runs of the other kinds of source and other seeds; seeds 101–103 calibrated the simulator
LAB_TRAIN = ("magnet", 1)
#: turns per turntable run: 72 (2.5 hours of table time at 126 s a turn); with 24 the same settings' RP and MP moved
#: by several points from one three-seed set to the next
LAB_TURNS = 72
LAB_JUDGED_FULL = [("cabinet", 11), ("cabinet", 12), ("mixed", 11), ("mixed", 12), ("mixed", 13)]
LAB_JUDGED_QUICK = [("cabinet", 11), ("mixed", 11)]
#: more sets of judged runs (cabinet and mixed, these seeds): the experiment repeated, for its seed-to-seed spread
LAB_MORE_SEED_SETS = ((21, 22, 23), (31, 32, 33))
#: the runs the gyro-checked second stage chooses its settings on (magnet runs, as the FCM's training run)
LAB_GYRO_TRACK_TRAIN = [("magnet", 1), ("magnet", 2), ("magnet", 3)]
#: the paper's figures per threshold set: [min, max] over its three samples (Table 1: DMC, Table 2: one compass)
PAPER_TABLE1 = [{"wp_deg": [12.9, 15.5], "rp_pct": [81.3, 82.9], "mp_pct": [18.6, 20.5]},
                {"wp_deg": [9.9, 10.4], "rp_pct": [72.9, 76.5], "mp_pct": [11.3, 14.9]},
                {"wp_deg": [6.6, 7.1], "rp_pct": [59.4, 63.4], "mp_pct": [7.2, 9.9]},
                {"wp_deg": [5.7, 6.1], "rp_pct": [42.8, 47.2], "mp_pct": [5.0, 5.9]}]
PAPER_TABLE2 = [{"wp_deg": [40.1, 49.6], "rp_pct": [86.2, 89.7], "mp_pct": [25.6, 35.2]},
                {"wp_deg": [30.8, 34.1], "rp_pct": [77.3, 78.7], "mp_pct": [20.1, 24.2]},
                {"wp_deg": [18.8, 20.9], "rp_pct": [64.9, 70.2], "mp_pct": [14.3, 18.9]},
                {"wp_deg": [15.3, 15.6], "rp_pct": [55.4, 60.9], "mp_pct": [13.5, 15.6]}]
#: FCM trained on sample 1, applied to samples 2 and 3 (Table 4); on its own samples (Table 3)
PAPER_FCM_UNSEEN = {"rp_pct": [73.9, 75.1], "mp_pct": [5.8, 5.9], "wp_deg": [5.7, 5.9]}
PAPER_FCM_TRAIN = {"rp_pct": [76.9, 80.2], "mp_pct": [5.4, 6.1], "wp_deg": [5.5, 5.8]}
#: the paper's data as its Tables 1 and 2 imply them, per sample [min, max] (docs/methods.md#dmc-conditions):
#: a threshold set's accepted bad samples per good sample are MP/(1 − MP) · RP; the bad share is at least the
#: loosest set's accepted bad / (1 + accepted bad); the RMS error of the accepted bad samples follows from
#: WP² = (1 − MP) · e_good² + MP · e_bad² with e_good = 2° RMS. Measured on the drives from the simulator's truth
#: (true field strength and direction at the two sensors), so they describe the disturbances, not a detector.
PAPER_CONDITIONS = {
    "bad_pct": [23.6, 100.0],  # at least
    "hidden_bad_per_good_200units": [0.309, 0.480],  # Table 2 set 1: bad with |Δm| < 200 units, per good sample
    "hidden_bad_per_good_40units": [0.087, 0.113],  # Table 2 set 4 (40 units)
    "dmc_hidden_bad_per_good_200units_8deg": [0.189, 0.210],  # Table 1 set 1: also |Δh| < 8°
    "dmc_hidden_bad_per_good_40units_3deg": [0.024, 0.027],  # Table 1 set 4: also |Δh| < 3°
    "good_strength_changed_pct": [10.3, 13.8],  # Table 2 set 1: good samples rejected (1 − RP)
    "hidden_bad_rms_err_deg": [67.5, 97.6],  # Table 2 set 1: RMS error of the accepted bad samples
    "dmc_hidden_bad_rms_err_deg": [28.9, 34.3],  # Table 1 set 1
}
#: nT per HMR3300 output unit: the paper's field thresholds (200, 100, …) are in these units. The paper does not give
#: it; at 10 nT no randomly directed disturbance gives its Table 2, and the turntable simulator's calibration
#: (bench.turntable_calibration, docs/methods.md#dmc-lab) fits the tables at 32–51 nT: 32 is its chosen fit's
FIELD_UNIT_NT = 32.0
#: scales of the loose set (2000 nT, 1000 nT/s, 8°, 8°/s) that trace the threshold stage's RP–MP curve
CURVE_SCALES = tuple(round(0.2 + 0.05 * i, 2) for i in range(17))
#: the same curve up to twice the loose set: the gyro-checked stage may start from a looser stage 1 than the FCM
SECOND_STAGE_CURVE_SCALES = tuple(round(0.2 + 0.05 * i, 2) for i in range(37))
#: other caps on the training MP, to show how the second stage's result depends on its operating rule (reported only)
SECOND_STAGE_RULE_CAPS = (1.0, 3.0)
#: other gates for the chosen setting, to show how the turntable's result depends on it (reported only)
SECOND_STAGE_GATE_SENSITIVITY_DEG = (3.0, 3.5, 4.5, 5.0)


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be a positive number of nT, got {text!r}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="fewer drives (the default test's size)")
    p.add_argument("--duration-s", type=float, default=300.0, help="length of each simulated drive, s")
    p.add_argument("--features", choices=["paper", "extended"], default=None,
                   help="FCM feature set for fcm_unseen (default: the committed model's recipe; both are tabulated)")
    p.add_argument("--field-unit-nt", type=_positive, default=FIELD_UNIT_NT,
                   help="nT per HMR3300 field unit for the paper's threshold sets (default 32: docs/methods.md#dmc-lab)")
    p.add_argument("--no-speed", action="store_true", help="skip the FCM speed comparison")
    p.add_argument("--no-quasistatic", action="store_true", help="skip the quasi-static detector")


def _row(name: str, m, **extra) -> dict:
    return {"name": name, **m.as_dict(), **extra}


def paper_sets(unit_nt: float) -> list:
    """The paper's four threshold sets (its Table 1, loosest first) in nT at ``unit_nt`` per field unit."""
    from services.dmc_detector import core

    return [core.Thresholds(a * unit_nt, b * unit_nt, c, d) for a, b, c, d in core.PAPER_TABLE1_SETS]


def _figures(m) -> dict:
    """RP, MP, WP (RMS) and WP as a 95 % bound of a Metrics, rounded as the report gives them."""
    return {"rp_pct": round(m.rp_pct, 3), "mp_pct": round(m.mp_pct, 3), "wp_deg": round(m.wp_deg, 3),
            "wp_p95_deg": round(m.wp_p95_deg, 3)}


def _brief(st) -> dict:
    """The settings of a gyro_track choice that the grids vary (the reference's own only)."""
    keys = ("reference", "gate_deg") + (("consensus_window_s", "consensus_scale_deg", "consensus_inlier_deg")
                                        if st.reference == "consensus" else ("blend_tau_s", "bias_tau_s", "trust_dm_nt"))
    return {k: getattr(st, k) for k in keys}


def _rule_sensitivity(track_train, judged, pick: dict, loose=None) -> list[dict]:
    """The gyro-checked stage chosen from the same scored grid under each of SECOND_STAGE_RULE_CAPS, judged on
    ``judged`` (reported only: how the outcome depends on the operating rule)."""
    from bench import dmc_training as T

    err = np.concatenate([d.heading_err_deg for d in judged])
    out = []
    for cap in SECOND_STAGE_RULE_CAPS:
        alt = T.choose_gyro_track(track_train, loose=loose, max_mp_pct=cap, scored=pick["scored"])
        ma = T.metrics(T.gyro_track_valid(judged, alt["stage1"], alt["settings"]), err)
        out.append({"max_train_mp_pct": cap, "within_cap": alt["within_cap"], "stage1_scale": alt["stage1_scale"],
                    "settings": _brief(alt["settings"]), **_figures(ma)})
    return out


def _beats(row: dict, paper: dict) -> bool:
    """Whether a row's RP is above the paper's range and its MP and WP (as a 95 % bound) below it."""
    return bool(row["rp_pct"] > paper["rp_pct"][1] and row["mp_pct"] < paper["mp_pct"][0]
                and row["wp_p95_deg"] < paper["wp_deg"][0])


def _against_paper(row: dict) -> None:
    """A baseline row's place against the paper's range: ``inside_paper_range`` per figure (WP both as RMS and as
    a 95 % bound, the reading under which the paper's tables hang together: docs/methods.md "Which statistic WP
    is"), and ``outside_paper_by``: how far outside the range each figure lies (0 inside)."""
    p = row["paper"]
    figs = {"rp_pct": row["rp_pct"], "mp_pct": row["mp_pct"], "wp_deg": row["wp_deg"], "wp_p95_deg": row["wp_p95_deg"]}
    rng = {k: p["wp_deg" if k.startswith("wp") else k] for k in figs}
    row["inside_paper_range"] = {k: bool(rng[k][0] <= v <= rng[k][1]) for k, v in figs.items()}
    row["outside_paper_by"] = {k: round(max(rng[k][0] - v, v - rng[k][1], 0.0), 2) for k, v in figs.items()}


def fcm_loop_reference(X: np.ndarray, u0: np.ndarray, m: float, n_iter: int) -> np.ndarray:
    """A plain per-sample, per-cluster FCM (the textbook equations, no vectorisation) for agreement checks."""
    c, n = u0.shape
    u = u0 / u0.sum(0)
    V = np.zeros((c, X.shape[1]))
    for _ in range(n_iter):
        for i in range(c):
            w = u[i] ** m
            V[i] = (w[:, None] * X).sum(0) / w.sum()
        d = np.empty((c, n))
        for i in range(c):
            for k in range(n):
                d[i, k] = max(float(np.sqrt(((X[k] - V[i]) ** 2).sum())), 1e-9)
        un = np.empty_like(u)
        for k in range(n):
            for i in range(c):
                un[i, k] = 1.0 / sum((d[i, k] / d[j, k]) ** (2.0 / (m - 1.0)) for j in range(c))
        u = un
    return V


def fcm_speed(n: int = 10_000, seed: int = 0, repeats: int = 5) -> dict:
    """Timing and agreement of this FCM against scikit-fuzzy (same initial memberships) and a loop."""
    from services.dmc_detector import fcm

    rng = np.random.default_rng(seed)
    centres = np.array([[0.05, 0.05], [0.3, 0.1], [0.1, 0.5], [0.7, 0.3], [0.8, 0.8]])
    X = np.concatenate([rng.normal(cn, 0.07, (n // 5, 2)) for cn in centres])
    u0 = rng.random((5, len(X)))
    u0 /= u0.sum(0)
    out: dict = {"n_samples": int(len(X)), "c": 5, "m": 2.0, "tol": 0.01}
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        r = fcm.fcm_fit(X, 5, 2.0, 0.01, u0=u0)
        best = min(best, time.perf_counter() - t)
    out["magmesh_ms"] = round(best * 1e3, 3)
    out["magmesh_iterations"] = r.n_iter
    try:
        import skfuzzy

        best = np.inf
        for _ in range(repeats):
            t = time.perf_counter()
            res = skfuzzy.cmeans(X.T, 5, 2.0, error=0.01, maxiter=300, init=u0.copy(), seed=seed)
            best = min(best, time.perf_counter() - t)
        out["skfuzzy_ms"] = round(best * 1e3, 3)
        out["skfuzzy_iterations"] = int(res[5])
        out["speedup_vs_skfuzzy"] = round(out["skfuzzy_ms"] / out["magmesh_ms"], 2)
        # agreement: both run the same 30 iterations from the same memberships
        mine = fcm.fcm_fit(X, 5, 2.0, tol=0.0, max_iter=30, u0=u0)
        sk = skfuzzy.cmeans(X.T, 5, 2.0, error=0.0, maxiter=30, init=u0.copy())
        out["max_centre_diff_vs_skfuzzy"] = float(np.abs(mine.centres - sk[0]).max())
        out["max_membership_diff_vs_skfuzzy"] = float(np.abs(mine.u - sk[1]).max())
    except ImportError:
        out["skfuzzy_ms"] = None
    # the loop reference on a subsample (it is slow by design)
    sub = slice(0, len(X), 20)
    mine = fcm.fcm_fit(X[sub], 5, 2.0, tol=0.0, max_iter=10, u0=u0[:, sub])
    ref = fcm_loop_reference(X[sub], u0[:, sub], 2.0, 10)
    out["max_centre_diff_vs_loop"] = float(np.abs(mine.centres - ref).max())
    return out


BROAD_TRIALS = ("02_undisturbed_slow_rotation_B", "07_undisturbed_fast_rotation_B", "30_disturbed_stationary_magnet_C",
                "32_disturbed_attached_magnet_1cm", "36_disturbed_attached_magnet_5cm")


def quasistatic_broad(trials=BROAD_TRIALS, max_tilt_deg: float = 60.0) -> list[dict]:
    """The quasi-static detector on real recordings (BROAD, Laidig et al. 2021, CC-BY-4.0).

    A handheld IMU board turned every way in a lab, magnets fixed or attached in some trials; truth from
    optical motion capture. Levelled by the accelerometer (``level = "accel"``); the heading is compared
    with the optical heading where the board is tilted less than ``max_tilt_deg`` (heading is undefined
    near vertical). ``disturbed_flagged``: fraction of the dataset's disturbed samples marked invalid;
    ``undisturbed_valid``: fraction of the others marked valid.
    """
    from bench import dmc_training as T
    from magmesh import maths
    from services.dmc_detector import core, quasistatic
    from sim_publishers.replay.core import load_broad

    forms = (("paper_form", quasistatic.QuasiStaticSettings(level="accel", variance_of="components",
                                                             dm_threshold_nt=0.0, var_threshold_nt2=8e6,
                                                             dpsi_threshold_deg=2.0)),
             ("default", quasistatic.QuasiStaticSettings(level="accel")))
    rows = []
    for trial in trials:
        rec = load_broad(trial, rate_hz=50.0)
        radius = float(np.linalg.norm(rec.field_earth_enu_nt))
        decl = maths.declination_rad(rec.field_earth_enu_nt)
        params = core.CompassParams((0.0, 0.0, 0.0), (1, 0, 0, 0, 1, 0, 0, 0, 1), radius, "3d", "broad")
        true_heading = maths.heading_of_quat_array(rec.truth_quat)
        tilt = np.degrees(np.array([math.acos(max(-1.0, min(1.0, maths.quat_to_matrix(q)[2, 2])))
                                    for q in rec.truth_quat]))
        use = tilt < max_tilt_deg
        for name, st in forms:
            det = quasistatic.QuasiStaticDetector(st)
            dec = []
            i = j = 0
            tm, ti = rec.mag_t_s, rec.imu_t_s
            while i < len(tm):
                if j < len(ti) and ti[j] <= tm[i]:
                    dec += det.add_imu(float(ti[j]), rec.gyro_rad_s[j], rec.accel_m_s2[j])
                    j += 1
                else:
                    dec += det.add_mag(float(tm[i]), rec.mag_nt[i], params, decl)
                    i += 1
            dt = np.array([d.t_s for d in dec])
            k = np.clip(np.searchsorted(dt, rec.truth_t_s), 0, len(dt) - 1)
            valid = np.array([d.valid for d in dec])[k][use]
            err = np.degrees(np.abs(maths.angle_diff(np.array([d.heading_rad for d in dec])[k], true_heading)))[use]
            m = T.metrics(valid, err)
            dist = rec.disturbed[use]
            m.missed_zones = m.false_alarms = None  # no zone timing on these recordings
            rows.append({"name": f"{name}:{trial}", **m.as_dict(),
                         "disturbed_flagged": round(float((~valid[dist]).mean()), 4) if dist.any() else None,
                         "undisturbed_valid": round(float(valid[~dist].mean()), 4) if (~dist).any() else None})
    return rows


def conditions(drives, field_unit_nt: float = FIELD_UNIT_NT) -> dict:
    """Source statistics of the drives beside the paper's (``PAPER_CONDITIONS``), from the simulator's truth.

    A sample is bad when its published heading error is ≥ 5° (as in the metrics). It is *hidden* from the
    field-strength test when the true field strength at both sensors is within the threshold (200 or 40 units of
    ``field_unit_nt``: the paper's loosest and tightest sets) of the Earth's
    (|b_k| − |b_earth|, no sensor or calibration error, no rate test), and from the DMC's heading test when
    the two true fields' level headings also differ by less than its threshold."""
    err = np.concatenate([d.heading_err_deg for d in drives])
    if any(d.true_dm_nt is None for d in drives):
        return {"error": "drives without simulator truth"}
    dm = np.concatenate([np.abs(d.true_dm_nt).max(axis=1) for d in drives])
    dh = np.degrees(np.abs(np.concatenate([d.true_dh_rad for d in drives])))
    bad = err >= 5.0
    n_good = max(int((~bad).sum()), 1)

    def per_good(mask):
        return round(float((bad & mask).sum()) / n_good, 4)

    def rms(mask):
        m = bad & mask
        return round(float(np.sqrt(np.mean(err[m] ** 2))), 2) if m.any() else None

    loose, tight = 200.0 * field_unit_nt, 40.0 * field_unit_nt
    out = {"field_unit_nt": field_unit_nt,
           "bad_pct": round(100.0 * float(bad.mean()), 2),
           "hidden_bad_per_good_200units": per_good(dm < loose),
           "hidden_bad_per_good_40units": per_good(dm < tight),
           "dmc_hidden_bad_per_good_200units_8deg": per_good((dm < loose) & (dh < 8.0)),
           "dmc_hidden_bad_per_good_40units_3deg": per_good((dm < tight) & (dh < 3.0)),
           "good_strength_changed_pct": round(100.0 * float((~bad & (dm >= loose)).sum()) / n_good, 2),
           "hidden_bad_rms_err_deg": rms(dm < loose),
           "dmc_hidden_bad_rms_err_deg": rms((dm < loose) & (dh < 8.0)),
           "bad_err_deg_p50_p90_p99": [round(float(x), 1) for x in np.percentile(err[bad], [50, 90, 99])]
           if bad.any() else None,
           "bad_share_with_dh_below_3deg_pct": round(100.0 * float((dh[bad] < 3.0).mean()), 1) if bad.any() else None}
    out["paper"] = PAPER_CONDITIONS
    return out


def lab_rows(judged_spec, unit: float) -> dict:
    """The baselines, FCM and its gain on the paper's turntable experiment (runs it never trained on)."""
    from bench import dmc_training as T

    train = [T.simulate_lab(*LAB_TRAIN, turns=LAB_TURNS)]
    judged = [T.simulate_lab(run, seed, turns=LAB_TURNS) for run, seed in judged_spec]
    out: dict = {"train": [d.name for d in train], "judged": [d.name for d in judged],
                 "conditions": conditions(judged, unit), "baselines": {"single_threshold": [], "dmc_threshold": []}}
    sets = paper_sets(unit)
    for i, th in enumerate(sets):
        thr = {"dm_nt": th.dm_nt, "ddm_nt_s": th.ddm_nt_s, "dh_deg": th.dh_deg, "ddh_deg_s": th.ddh_deg_s}
        for key, valid, paper in (("single_threshold", T.single_valid(judged, th), PAPER_TABLE2[i]),
                                  ("dmc_threshold", T.threshold_valid(judged, th), PAPER_TABLE1[i])):
            row = _row(f"paper_set{i + 1}", T.evaluate(valid, judged), thresholds=thr, paper=paper)
            _against_paper(row)
            out["baselines"][key].append(row)
    loose = sets[0]  # the paper's loosest set: the FCM's and the gyro-checked stage's stage 1
    # the paper's FCM as it states it: clusters ordered by the size of their centres, the two smallest make up K_c
    # (magmesh's order by the training run's heading error, the streets' default, picks the same two on this table)
    model = T.train_fcm(train, T.DEFAULT_FEATURE_SET, use_reference=False, loose=loose,
                        feature_settings=T.lab_feature_settings(float(train[0].t_s[1] - train[0].t_s[0])))
    m = T.evaluate(T.fcm_valid(judged, model), judged)
    out["fcm_unseen"] = {"rp_pct": round(m.rp_pct, 3), "mp_pct": round(m.mp_pct, 3), "wp_deg": round(m.wp_deg, 3),
                         "wp_p95_deg": round(m.wp_p95_deg, 3), "cluster_order": model.training["cluster_order"],
                         "paper": PAPER_FCM_UNSEEN, "trained_on": out["train"], "drives": out["judged"]}
    out["fcm_gain"] = fcm_gain_against_thresholds(judged, model, loose)
    # magmesh's own second stage (the compass heading checked against the gyro-carried one), settings chosen on
    # magnet runs by the streets' rule, judged on the same runs as the FCM
    track_train = [T.simulate_lab(run, seed, turns=LAB_TURNS) for run, seed in LAB_GYRO_TRACK_TRAIN]
    pick = T.choose_gyro_track(track_train, loose=loose)

    def track_valid(ds):
        return T.gyro_track_valid(ds, pick["stage1"], pick["settings"])

    mt = T.evaluate(track_valid(judged), judged)
    m1 = T.evaluate(T.threshold_valid(judged, pick["stage1"]), judged)
    st, tm = pick["settings"], pick["train_metrics"]
    err = np.concatenate([d.heading_err_deg for d in judged])
    out["second_stage"] = {
        "name": "gyro_track", "rp_pct": round(mt.rp_pct, 3), "mp_pct": round(mt.mp_pct, 3),
        "wp_deg": round(mt.wp_deg, 3), "wp_p95_deg": round(mt.wp_p95_deg, 3),
        "stage1": {"scale_of_loose_set": pick["stage1_scale"], "dm_nt": pick["stage1"].dm_nt,
                   "ddm_nt_s": pick["stage1"].ddm_nt_s, "dh_deg": pick["stage1"].dh_deg,
                   "ddh_deg_s": pick["stage1"].ddh_deg_s},
        "stage1_alone": {"rp_pct": round(m1.rp_pct, 3), "mp_pct": round(m1.mp_pct, 3), "wp_deg": round(m1.wp_deg, 3)},
        "settings": {k: getattr(st, k) for k in st.__dataclass_fields__},
        "chosen_on": [d.name for d in track_train], "selection_rule": pick["rule"], "within_cap": pick["within_cap"],
        "grid_size": pick["grid_size"],
        "on_training_runs": {"rp_pct": round(tm.rp_pct, 3), "mp_pct": round(tm.mp_pct, 3),
                             "wp_deg": round(tm.wp_deg, 3)},
        "drives": out["judged"], "paper": PAPER_FCM_UNSEEN}
    out["second_stage"]["meets_paper_table4"] = _beats(out["second_stage"], PAPER_FCM_UNSEEN)
    # how much the outcome depends on choices not made on the training runs (reported only, never chosen from):
    # the operating rule's cap, and the gate of the chosen setting
    out["second_stage"]["rule_sensitivity"] = _rule_sensitivity(track_train, judged, pick, loose)
    gates = []
    for g in SECOND_STAGE_GATE_SENSITIVITY_DEG:
        sg = dataclasses.replace(st, gate_deg=g)
        ma = T.metrics(T.gyro_track_valid(judged, pick["stage1"], sg), err)
        gates.append({"gate_deg": g, **_figures(ma)})
    out["second_stage"]["gate_sensitivity"] = gates
    out["second_stage_gain"] = stage_gain_against_thresholds(judged, track_valid, loose,
                                                             scales=SECOND_STAGE_CURVE_SCALES)
    # the whole experiment again on other seeds (cabinet and mixed runs; no setting was chosen on them):
    # how far the headline moves from one set of runs to the next
    first = {"seeds": [d.seed for d in judged if d.layout == "lab_mixed"], "drives": out["judged"]}
    for name, row, gain in (("fcm", out["fcm_unseen"], out["fcm_gain"]),
                            ("second_stage", out["second_stage"], out["second_stage_gain"])):
        first[name] = {k: row[k] for k in ("rp_pct", "mp_pct", "wp_deg", "wp_p95_deg")}
        first[name]["meets_paper_table4"] = _beats(row, PAPER_FCM_UNSEEN)
        first[f"{name}_gain"] = gain["pooled"]
    sets = [first]
    for seeds in LAB_MORE_SEED_SETS:
        runs = [T.simulate_lab(run, sd, turns=LAB_TURNS) for run in ("cabinet", "mixed") for sd in seeds]
        sets.append({"seeds": list(seeds), "drives": [d.name for d in runs],
                     **_lab_set_rows(runs, model, track_valid, loose)})
    out["seed_sets"] = sets
    met = sum(x["second_stage"]["meets_paper_table4"] for x in sets)
    out["second_stage"]["meets_paper_table4_seed_sets"] = f"{met}/{len(sets)}"
    for key in ("rp_gained_at_equal_mp_pct", "mp_saved_at_equal_rp_pct"):
        for name in ("second_stage", "fcm"):
            vals = [x[f"{name}_gain"][key] for x in sets]
            vals = [v for v in vals if v is not None]
            out[f"{name}_gain"][f"seed_set_spread_{key}"] = round(float(np.std(vals)), 3) if len(vals) > 1 else None
            out[f"{name}_gain"][f"seed_set_values_{key}"] = vals
    return out


def _lab_set_rows(runs, model, track_valid, loose) -> dict:
    """The FCM and the gyro-checked stage on one set of turntable runs, each with its gain over the threshold curve."""
    from bench import dmc_training as T

    err = np.concatenate([d.heading_err_deg for d in runs])
    out = {}
    for name, valid, scales in (("fcm", T.fcm_valid(runs, model), CURVE_SCALES),
                                ("second_stage", track_valid(runs), SECOND_STAGE_CURVE_SCALES)):
        m = T.metrics(valid, err)
        row = _figures(m)
        row["meets_paper_table4"] = _beats(row, PAPER_FCM_UNSEEN)
        out[name] = row
        out[f"{name}_gain"] = _gain(threshold_curve(runs, loose, scales), m.rp_pct, m.mp_pct)
    return out


def _dense(curve: list[dict], steps: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(RP, MP) along the threshold curve, linear between consecutive scales."""
    rp = np.array([c["rp_pct"] for c in curve], float)
    mp = np.array([c["mp_pct"] for c in curve], float)
    f = np.linspace(0.0, 1.0, steps, endpoint=False)
    rr = np.concatenate([rp[:-1, None] + (rp[1:] - rp[:-1])[:, None] * f[None, :]]).ravel()
    mm = np.concatenate([mp[:-1, None] + (mp[1:] - mp[:-1])[:, None] * f[None, :]]).ravel()
    return np.append(rr, rp[-1]), np.append(mm, mp[-1])


def threshold_curve(drives, loose=None, scales=CURVE_SCALES) -> list[dict]:
    """RP, MP, WP of the stage-1 threshold test with the loose set scaled by each of ``scales``."""
    from bench import dmc_training as T
    from services.dmc_detector import fcm

    err = np.concatenate([d.heading_err_deg for d in drives])
    out = []
    for k in scales:
        m = T.metrics(T.threshold_valid(drives, (loose or fcm.LOOSE).scaled(k)), err)
        out.append({"scale": k, "rp_pct": m.rp_pct, "mp_pct": m.mp_pct, "wp_deg": m.wp_deg})
    return out


def _gain(curve: list[dict], rp: float, mp: float) -> dict:
    """FCM's (rp, mp) against the threshold curve: the curve's best RP at an MP no higher than ``mp``, and
    its lowest MP at an RP no lower than ``rp`` (None where the curve does not reach)."""
    rr, mm = _dense(curve)
    at_mp = rr[mm <= mp + 1e-9]
    at_rp = mm[rr >= rp - 1e-9]
    rp_thr = float(at_mp.max()) if at_mp.size else None
    mp_thr = float(at_rp.min()) if at_rp.size else None
    return {"rp_pct": round(rp, 3), "mp_pct": round(mp, 3),
            "threshold_rp_at_equal_mp_pct": None if rp_thr is None else round(rp_thr, 3),
            "threshold_mp_at_equal_rp_pct": None if mp_thr is None else round(mp_thr, 3),
            "rp_gained_at_equal_mp_pct": None if rp_thr is None else round(rp - rp_thr, 3),
            "mp_saved_at_equal_rp_pct": None if mp_thr is None else round(mp_thr - mp, 3)}


def fcm_gain_against_thresholds(drives, model, loose=None) -> dict:
    """What the FCM stage adds to the threshold stage it starts from, on the same drives.

    The threshold stage's operating curve is traced by scaling the loose set (CURVE_SCALES); the FCM's
    (RP, MP) is compared with the curve at the same MP (RP gained) and at the same RP (MP saved). The same
    is done per drive; the seed-to-seed spread is the standard deviation of the per-drive gains."""
    from bench import dmc_training as T

    return stage_gain_against_thresholds(drives, lambda ds: T.fcm_valid(ds, model), loose)


def stage_gain_against_thresholds(drives, valid_of, loose=None, scales=CURVE_SCALES) -> dict:
    """What a second stage (``valid_of(drives)`` → valid per epoch) adds to the threshold stage, on the same
    drives: its (RP, MP) against the threshold curve (``scales`` of the loose set) at equal MP and at equal RP,
    pooled and per drive; the seed-to-seed spread is the standard deviation of the per-drive gains."""
    from bench import dmc_training as T

    err = np.concatenate([d.heading_err_deg for d in drives])
    m = T.metrics(valid_of(drives), err)
    pooled = _gain(threshold_curve(drives, loose, scales), m.rp_pct, m.mp_pct)
    per_drive = []
    for d in drives:
        md = T.metrics(valid_of([d]), d.heading_err_deg)
        per_drive.append({"drive": d.name, **_gain(threshold_curve([d], loose, scales), md.rp_pct, md.mp_pct)})
    out: dict = {"pooled": pooled, "per_drive": per_drive, "curve_scales": list(scales)}
    for key in ("rp_gained_at_equal_mp_pct", "mp_saved_at_equal_rp_pct"):
        vals = [r[key] for r in per_drive if r[key] is not None]
        out[f"spread_{key}"] = round(float(np.std(vals)), 3) if len(vals) > 1 else None
    g, sp = pooled["rp_gained_at_equal_mp_pct"], out["spread_rp_gained_at_equal_mp_pct"]
    g2, sp2 = pooled["mp_saved_at_equal_rp_pct"], out["spread_mp_saved_at_equal_rp_pct"]
    for key in ("rp_gained_at_equal_mp_pct", "mp_saved_at_equal_rp_pct"):
        vals = [r[key] for r in per_drive if r[key] is not None]
        out[f"drives_positive_{key}"] = f"{sum(v > 0 for v in vals)}/{len(vals)}"
    out["beats_thresholds_beyond_spread"] = bool(
        (g is not None and sp is not None and g > sp) or (g2 is not None and sp2 is not None and g2 > sp2))
    # the same per seed: each seed's drives (one of every judged layout) pooled, one gain per seed; the spread of
    # those is the seed-to-seed spread of the whole experiment (the per-drive one mixes layouts and seeds)
    seeds = sorted({d.seed for d in drives})
    if len(seeds) > 1 and len(seeds) < len(drives):
        per_seed = []
        for sd in seeds:
            ds = [d for d in drives if d.seed == sd]
            ms = T.metrics(valid_of(ds), np.concatenate([d.heading_err_deg for d in ds]))
            per_seed.append({"seed": sd, "drives": [d.name for d in ds],
                             **_gain(threshold_curve(ds, loose, scales), ms.rp_pct, ms.mp_pct)})
        out["per_seed"] = per_seed
        for key in ("rp_gained_at_equal_mp_pct", "mp_saved_at_equal_rp_pct"):
            vals = [r[key] for r in per_seed if r[key] is not None]
            out[f"seed_spread_{key}"] = round(float(np.std(vals)), 3) if len(vals) > 1 else None
            out[f"seeds_positive_{key}"] = f"{sum(v > 0 for v in vals)}/{len(vals)}"
        ss, ss2 = out["seed_spread_rp_gained_at_equal_mp_pct"], out["seed_spread_mp_saved_at_equal_rp_pct"]
        out["beats_thresholds_beyond_seed_spread"] = bool(
            (g is not None and ss is not None and g > ss) or (g2 is not None and ss2 is not None and g2 > ss2))
    return out


def run(args: argparse.Namespace) -> dict:
    from bench import dmc_training as T
    from services.dmc_detector import fcm, quasistatic

    t_start = time.perf_counter()
    quick = bool(getattr(args, "quick", False))
    dur = float(getattr(args, "duration_s", 300.0))
    unseen_spec = UNSEEN_QUICK if quick else UNSEEN_FULL
    train = [T.simulate_drive(lay, seed, dur) for lay, seed in T.PAPER_TRAIN_DRIVES]
    unseen = [T.simulate_drive(lay, seed, dur, cal_seed=cal) for lay, seed, cal in unseen_spec]
    unseen_layouts = [d for d in unseen if d.layout not in {t.layout for t in train}]
    judged = unseen_layouts or unseen  # every headline row is scored on the layouts never seen in training

    # baselines: the paper's threshold sets, one compass (its Table 2) and the DMC stage 1 (its Table 1)
    unit = float(getattr(args, "field_unit_nt", FIELD_UNIT_NT))
    sets = [(f"paper_set{i + 1}", th) for i, th in enumerate(paper_sets(unit))]
    single_rows, dmc_rows = [], []
    for i, (name, th) in enumerate(sets):
        thr = {"dm_nt": th.dm_nt, "ddm_nt_s": th.ddm_nt_s, "dh_deg": th.dh_deg, "ddh_deg_s": th.ddh_deg_s}
        single_rows.append(_row(name, T.evaluate(T.single_valid(judged, th), judged), thresholds=thr,
                                paper=PAPER_TABLE2[i]))
        dmc_rows.append(_row(name, T.evaluate(T.threshold_valid(judged, th), judged), thresholds=thr,
                             paper=PAPER_TABLE1[i]))
    for rows in (single_rows, dmc_rows):
        for row in rows:
            _against_paper(row)

    # Tables 3 / 4: FCM trained on the training drive, applied to the others
    models = {}
    for fs in ("paper", "extended"):
        models[f"{fs}/centre_norm"] = T.train_fcm(train, fs, use_reference=False)  # the paper, literally
        models[f"{fs}/heading_error"] = T.train_fcm(train, fs, use_reference=True)
    table3 = [_row(fs, T.evaluate(T.fcm_valid(train, mdl), train), centres=mdl.centres.round(4).tolist(),
                   iterations=mdl.training["n_iter"], n_train=mdl.training["n_samples"],
                   n_good_clusters=mdl.n_good_clusters)
              for fs, mdl in models.items()]
    table4 = []
    for fs, mdl in models.items():
        for d in unseen:
            table4.append(_row(f"{fs}:{d.name}", T.evaluate(T.fcm_valid([d], mdl), [d])))
        table4.append(_row(f"{fs}:all_unseen", T.evaluate(T.fcm_valid(unseen, mdl), unseen)))
        if unseen_layouts:
            table4.append(_row(f"{fs}:unseen_layouts_only",
                               T.evaluate(T.fcm_valid(unseen_layouts, mdl), unseen_layouts)))
    fs = getattr(args, "features", None) or T.DEFAULT_FEATURE_SET
    chosen = models[f"{fs}/{'heading_error' if T.DEFAULT_USE_REFERENCE else 'centre_norm'}"]
    m_unseen = T.evaluate(T.fcm_valid(judged, chosen), judged)
    fcm_unseen = {"rp_pct": round(m_unseen.rp_pct, 3), "mp_pct": round(m_unseen.mp_pct, 3),
                  "wp_deg": round(m_unseen.wp_deg, 3), "wp_mean_deg": round(m_unseen.wp_mean_deg, 3),
                  "onset_delay_s": m_unseen.onset_delay_s, "missed_zones": m_unseen.missed_zones,
                  "false_alarms": m_unseen.false_alarms, "feature_set": chosen.feature_set,
                  "cluster_order": chosen.training["cluster_order"], "n_good_clusters": chosen.n_good_clusters,
                  "trained_on": chosen.training["drives"], "drives": [d.name for d in judged],
                  "paper": PAPER_FCM_UNSEEN}
    fcm_unseen["meets_goal"] = bool(fcm_unseen["rp_pct"] > GOAL["rp_pct"] and fcm_unseen["mp_pct"] < GOAL["mp_pct"]
                                    and fcm_unseen["wp_deg"] < GOAL["wp_deg"])
    fcm_gain = fcm_gain_against_thresholds(judged, chosen)

    # magmesh's own second stage: the compass heading checked against the gyro-carried heading, its settings
    # chosen on its training drives (the training layout) only
    track_train = [T.simulate_drive(lay, seed, dur) for lay, seed in T.GYRO_TRACK_TRAIN_DRIVES]
    pick = T.choose_gyro_track(track_train)
    st = pick["settings"]

    def track_valid(ds):
        return T.gyro_track_valid(ds, pick["stage1"], st)

    m_track = T.evaluate(track_valid(judged), judged)
    tm = pick["train_metrics"]
    second_stage = {"name": "gyro_track", "rp_pct": round(m_track.rp_pct, 3), "mp_pct": round(m_track.mp_pct, 3),
                    "wp_deg": round(m_track.wp_deg, 3), "wp_mean_deg": round(m_track.wp_mean_deg, 3),
                    "wp_max_deg": round(m_track.wp_max_deg, 2), "onset_delay_s": m_track.onset_delay_s,
                    "missed_zones": m_track.missed_zones, "false_alarms": m_track.false_alarms,
                    "stage1": {"scale_of_loose_set": pick["stage1_scale"], "dm_nt": pick["stage1"].dm_nt,
                               "ddm_nt_s": pick["stage1"].ddm_nt_s, "dh_deg": pick["stage1"].dh_deg,
                               "ddh_deg_s": pick["stage1"].ddh_deg_s},
                    "settings": {k: getattr(st, k) for k in st.__dataclass_fields__},
                    "chosen_on": [d.name for d in track_train], "selection_rule": pick["rule"],
                    "within_cap": pick["within_cap"],
                    "grid_size": pick["grid_size"],
                    "on_training_drives": {"rp_pct": round(tm.rp_pct, 3), "mp_pct": round(tm.mp_pct, 3),
                                           "wp_deg": round(tm.wp_deg, 3)},
                    "drives": [d.name for d in judged], "paper": PAPER_FCM_UNSEEN}
    # against the stage 1 it starts from, alone (the same thresholds, no second stage), pooled and per drive
    m_s1 = T.evaluate(T.threshold_valid(judged, pick["stage1"]), judged)
    per = []
    for d in judged:
        a = T.metrics(T.threshold_valid([d], pick["stage1"]), d.heading_err_deg)
        b = T.metrics(track_valid([d]), d.heading_err_deg)
        per.append({"drive": d.name, "rp_gained_pct": round(b.rp_pct - a.rp_pct, 3),
                    "mp_saved_pct": round(a.mp_pct - b.mp_pct, 3)})
    second_stage["against_its_stage1_alone"] = {
        "stage1_alone": {"rp_pct": round(m_s1.rp_pct, 3), "mp_pct": round(m_s1.mp_pct, 3), "wp_deg": round(m_s1.wp_deg, 3)},
        "rp_gained_pct": round(m_track.rp_pct - m_s1.rp_pct, 3), "mp_saved_pct": round(m_s1.mp_pct - m_track.mp_pct, 3),
        "per_drive": per,
        "spread_rp_gained_pct": round(float(np.std([x["rp_gained_pct"] for x in per])), 3),
        "spread_mp_saved_pct": round(float(np.std([x["mp_saved_pct"] for x in per])), 3)}
    # how much the outcome depends on the operating rule: the same grid, other caps on the training MP
    second_stage["rule_sensitivity"] = _rule_sensitivity(track_train, judged, pick)
    a = second_stage["against_its_stage1_alone"]
    a["beats_it_beyond_spread"] = bool(a["rp_gained_pct"] >= 0 and a["mp_saved_pct"] > a["spread_mp_saved_pct"])
    second_stage["meets_goal"] = bool(second_stage["rp_pct"] > GOAL["rp_pct"] and second_stage["mp_pct"] < GOAL["mp_pct"]
                                      and second_stage["wp_deg"] < GOAL["wp_deg"])
    second_stage_gain = stage_gain_against_thresholds(judged, track_valid, scales=SECOND_STAGE_CURVE_SCALES)

    # the committed model, if any: is it what this recipe trains?
    committed = None
    try:
        cm = fcm.FcmModel.load(fcm.PAPER_STREETS_MODEL)
        mc = T.evaluate(T.fcm_valid(judged, cm), judged)
        committed = {"path": str(fcm.PAPER_STREETS_MODEL), "feature_set": cm.feature_set,
                     "trained_on": cm.training.get("drives"), "rp_pct": round(mc.rp_pct, 3),
                     "mp_pct": round(mc.mp_pct, 3), "wp_deg": round(mc.wp_deg, 3)}
    except (FileNotFoundError, ValueError) as e:
        committed = {"error": str(e)}

    result: dict = {
        "drives": {"train": [d.name for d in train], "unseen": [d.name for d in unseen],
                   "judged": [d.name for d in judged], "bad_pct": round(100.0 * float(np.mean(np.concatenate(
                       [d.heading_err_deg for d in judged]) >= T.GOOD_DEG)), 2),
                   "duration_s": dur, "calibration_error": {"offset_nt": T.CAL_OFFSET_ERR_NT,
                                                            "matrix_frac": T.CAL_MATRIX_ERR}},
        "good_deg": T.GOOD_DEG,
        "field_unit_nt": unit,
        "goal": GOAL,
        "conditions": conditions(judged, unit),
        "baselines": {"single_threshold": single_rows, "dmc_threshold": dmc_rows},
        "table3_fcm_train": table3,
        "table4_fcm_apply": table4,
        "fcm_unseen": fcm_unseen,
        "fcm_gain": fcm_gain,
        "second_stage": second_stage,
        "second_stage_gain": second_stage_gain,
        "fcm_committed_model_unseen": committed,
        "paper": {"table1_threshold": {"rp_pct": [43, 83], "mp_pct": [5, 20], "wp_deg": [5.7, 15.5]},
                  "table2_single": {"mp_pct": [13, 35], "wp_deg": [15, 50]},
                  "table3_fcm_train": PAPER_FCM_TRAIN, "table4_fcm_unseen": PAPER_FCM_UNSEEN},
    }
    result["lab"] = lab_rows(LAB_JUDGED_QUICK if quick else LAB_JUDGED_FULL, unit)
    if not getattr(args, "no_quasistatic", False):
        qs_rows = []
        qs_drives = judged[:2] if quick else judged
        for name, st in (("paper_form", quasistatic.QuasiStaticSettings(variance_of="components",
                                                                         dm_threshold_nt=0.0)),
                         ("default", quasistatic.QuasiStaticSettings())):
            vs, es = zip(*(T.quasistatic_run(d, st) for d in qs_drives), strict=False)
            m = T.evaluate(np.concatenate(vs), qs_drives, err_deg=np.concatenate(es))
            qs_rows.append(_row(name, m, drives=[d.name for d in qs_drives]))
        result["quasistatic"] = qs_rows
        if not quick:
            try:
                result["quasistatic_broad"] = quasistatic_broad()
            except (FileNotFoundError, ImportError) as e:
                result["quasistatic_broad"] = [{"name": "unavailable", "error": str(e)}]
    if not getattr(args, "no_speed", False):
        result["fcm_speed"] = fcm_speed()
    result["elapsed_s"] = round(time.perf_counter() - t_start, 2)
    return result


def _i(v) -> str:
    return "-" if v is None else str(int(v))


def _gain_line(name: str, g: dict) -> str:
    """One line of a second stage's gain over the threshold stage (``fcm_gain``, ``second_stage_gain``)."""
    p = g["pooled"]

    def f(v):
        return "-" if v is None else f"{v:+.2f}"

    return (f"{name} over the threshold stage (same drives): RP gained at equal MP {f(p['rp_gained_at_equal_mp_pct'])} "
            f"(spread {g['spread_rp_gained_at_equal_mp_pct']}), MP saved at equal RP {f(p['mp_saved_at_equal_rp_pct'])} "
            f"(spread {g['spread_mp_saved_at_equal_rp_pct']}): "
            f"{'beats' if g['beats_thresholds_beyond_spread'] else 'does NOT beat'} the thresholds beyond the "
            "per-drive spread" + (
                "" if "per_seed" not in g else
                f"; per seed (layouts pooled) spread {g['seed_spread_rp_gained_at_equal_mp_pct']} / "
                f"{g['seed_spread_mp_saved_at_equal_rp_pct']}, positive on {g['seeds_positive_rp_gained_at_equal_mp_pct']}"
                f" seeds: {'beats' if g['beats_thresholds_beyond_seed_spread'] else 'does NOT beat'} them beyond it"))


def format_text(r: dict) -> str:
    lines = [f"DMC interference recognition — trained on {', '.join(r['drives']['train'])}; "
             f"unseen: {', '.join(r['drives']['unseen'])}",
             "good = heading error < {:.0f}°; WP = RMS error of valid samples".format(r["good_deg"]), ""]

    def table(title, rows, extra=""):
        lines.append(title)
        lines.append(f"  {'name':44s} {'RP %':>7s} {'MP %':>7s} {'WP °':>6s} {'mean°':>6s} {'onset s':>8s} "
                     f"{'missed':>6s} {'false':>5s} {extra}")
        for row in rows:
            on = row["onset_delay_s"]
            ex = ""
            if extra and "thresholds" in row:
                t = row["thresholds"]
                ex = f"({t['dm_nt']:.0f}, {t['ddm_nt_s']:.0f}, {t['dh_deg']:.0f}, {t['ddh_deg_s']:.0f})"
            lines.append(f"  {row['name']:44s} {row['rp_pct']:7.2f} {row['mp_pct']:7.3f} {row['wp_deg']:6.2f} "
                         f"{row['wp_mean_deg']:6.2f} {('-' if on is None else f'{on:.2f}'):>8s} "
                         f"{_i(row['missed_zones']):>6s} {_i(row['false_alarms']):>5s} {ex}")
        lines.append("")

    def rng(v):
        return f"{v[0]:g}–{v[1]:g}"

    c0 = r.get("conditions") or {}
    if "bad_pct" in c0:
        lines.append("Conditions of the judged drives (simulator truth) beside the paper's, as its Tables 1–2 imply them")
        for k, v in c0.items():
            if k == "paper":
                continue
            pv = c0["paper"].get(k)
            lines.append(f"  {k:40s} {str(v):>22s}   paper {('-' if pv is None else rng(pv))}")
        lines.append("")
    for title, key in (("Table 2 baseline — single compass, paper's threshold sets (unseen drives)", "single_threshold"),
                       ("Table 1 baseline — DMC thresholds only (unseen drives)", "dmc_threshold")):
        lines.append(title)
        lines.append(f"  {'set':10s} {'thresholds':>24s} {'RP %':>7s} {'paper':>11s} {'MP %':>7s} {'paper':>11s} "
                     f"{'WP °':>6s} {'paper':>11s} {'WP max °':>8s}")
        for row in r["baselines"][key]:
            t, pp = row["thresholds"], row["paper"]
            th = f"({t['dm_nt']:.0f}, {t['ddm_nt_s']:.0f}, {t['dh_deg']:.0f}, {t['ddh_deg_s']:.0f})"
            lines.append(f"  {row['name']:10s} {th:>24s} {row['rp_pct']:7.2f} {rng(pp['rp_pct']):>11s} "
                         f"{row['mp_pct']:7.2f} {rng(pp['mp_pct']):>11s} {row['wp_deg']:6.2f} {rng(pp['wp_deg']):>11s} "
                         f"{row['wp_max_deg']:8.1f}")
        lines.append("")
    lab = r.get("lab")
    if lab:
        lines.append(f"The paper's own experiment (turntable, magnet / iron cabinet; trained on {', '.join(lab['train'])}, "
                     f"judged on {', '.join(lab['judged'])})")
        lc = lab["conditions"]
        lines.append("  conditions: " + ", ".join(f"{k} {lc[k]} (paper {rng(lc['paper'][k])})" for k in lc["paper"]))
        for key in ("single_threshold", "dmc_threshold"):
            for row in lab["baselines"][key]:
                pp = row["paper"]
                lines.append(f"  {key:17s} {row['name']:10s} RP {row['rp_pct']:6.2f} ({rng(pp['rp_pct'])})  "
                             f"MP {row['mp_pct']:6.2f} ({rng(pp['mp_pct'])})  WP {row['wp_deg']:6.2f} "
                             f"WP95 {row['wp_p95_deg']:6.2f} ({rng(pp['wp_deg'])})")
        for name, u0, g0 in (("fcm_unseen", lab["fcm_unseen"], lab["fcm_gain"]),
                             ("second_stage", lab["second_stage"], lab["second_stage_gain"])):
            lines.append(f"  {name} RP {u0['rp_pct']:.2f} MP {u0['mp_pct']:.2f} WP {u0['wp_deg']:.2f} WP95 "
                         f"{u0['wp_p95_deg']:.2f}; gain RP at equal MP {g0['pooled']['rp_gained_at_equal_mp_pct']} "
                         f"(spread {g0['spread_rp_gained_at_equal_mp_pct']}), MP saved at equal RP "
                         f"{g0['pooled']['mp_saved_at_equal_rp_pct']} (spread {g0['spread_mp_saved_at_equal_rp_pct']})")
        ls = lab["second_stage"]
        lines.append(f"  second_stage: reference {ls['settings']['reference']}, gate {ls['settings']['gate_deg']:g}°, "
                     f"chosen on {', '.join(ls['chosen_on'])}; against the paper's Table 4 (RP "
                     f"{rng(ls['paper']['rp_pct'])}, MP {rng(ls['paper']['mp_pct'])}, WP {rng(ls['paper']['wp_deg'])}): "
                     f"{'beaten' if ls['meets_paper_table4'] else 'NOT beaten'}; other gates (reported only): "
                     + ", ".join(f"{g['gate_deg']:g}° RP {g['rp_pct']:.1f} MP {g['mp_pct']:.2f}"
                                 for g in ls["gate_sensitivity"]))
        for x in lab.get("seed_sets", []):
            a, b = x["second_stage"], x["fcm"]
            lines.append(f"  runs of seeds {', '.join(map(str, x['seeds']))}: second_stage RP {a['rp_pct']:.1f} MP "
                         f"{a['mp_pct']:.2f} WP95 {a['wp_p95_deg']:.2f} ({'beats' if a['meets_paper_table4'] else 'not'} "
                         f"Table 4; MP saved at equal RP {x['second_stage_gain']['mp_saved_at_equal_rp_pct']}), FCM RP "
                         f"{b['rp_pct']:.1f} MP {b['mp_pct']:.2f} WP95 {b['wp_p95_deg']:.2f}")
        lines.append("")
    table("Table 3 — FCM on its training drive", r["table3_fcm_train"])
    table("Table 4 — FCM trained once, applied to other drives", r["table4_fcm_apply"])
    if "quasistatic" in r:
        table("Quasi-static detector (§2), one magnetometer + gyro", r["quasistatic"])
    qb = [row for row in r.get("quasistatic_broad", []) if "rp_pct" in row]
    if qb:
        table("Quasi-static detector on real data (BROAD, Laidig et al. 2021, CC-BY-4.0; tilt < 60°)", qb)
        lines.insert(-1, "  disturbed samples flagged / undisturbed samples valid: " + ", ".join(
            f"{row['name'].split(':')[1][:2]} {row['name'].split(':')[0][:5]} "
            f"{'-' if row['disturbed_flagged'] is None else format(row['disturbed_flagged'], '.2f')}/"
            f"{row['undisturbed_valid']:.2f}" for row in qb))
    u = r["fcm_unseen"]
    lines.append(f"fcm_unseen ({u['feature_set']} features, unseen layouts): RP {u['rp_pct']:.2f} %  "
                 f"MP {u['mp_pct']:.3f} %  WP {u['wp_deg']:.2f}°  — goal: beat the paper, RP > {r['goal']['rp_pct']:g}, "
                 f"MP < {r['goal']['mp_pct']:g}, WP < {r['goal']['wp_deg']:g}°: {'met' if u['meets_goal'] else 'NOT met'}")
    u["paper"] = u.get("paper", {})
    if u["paper"]:
        lines.append(f"  paper (Table 4, unseen samples): RP {rng(u['paper']['rp_pct'])} %  MP {rng(u['paper']['mp_pct'])} %  "
                     f"WP {rng(u['paper']['wp_deg'])}°")
    g = r.get("fcm_gain")
    if g:
        lines.append(_gain_line("fcm_gain", g))
    ss = r.get("second_stage")
    if ss:
        t1 = ss["stage1"]
        lines.append(f"second_stage ({ss['name']}: the compass heading checked against the gyro-carried heading after stage 1 "
                     f"({t1['dm_nt']:.0f}, {t1['ddm_nt_s']:.0f}, {t1['dh_deg']:g}, {t1['ddh_deg_s']:g}); settings chosen on "
                     f"{', '.join(ss['chosen_on'])}): RP {ss['rp_pct']:.2f} %  MP {ss['mp_pct']:.3f} %  WP {ss['wp_deg']:.2f}°  "
                     f"— goal {'met' if ss['meets_goal'] else 'NOT met'}")
        lines.append(_gain_line("second_stage_gain", r["second_stage_gain"]))
    c = r.get("fcm_committed_model_unseen") or {}
    if "rp_pct" in c:
        lines.append(f"committed model {c['path']}: RP {c['rp_pct']:.2f} %  MP {c['mp_pct']:.3f} %  "
                     f"WP {c['wp_deg']:.2f}°")
    elif c:
        lines.append(f"committed model: {c.get('error')}")
    p = r["paper"]
    lines.append(f"paper: DMC thresholds RP {rng(p['table1_threshold']['rp_pct'])} % MP {rng(p['table1_threshold']['mp_pct'])} % "
                 f"WP {rng(p['table1_threshold']['wp_deg'])}°; single compass MP {rng(p['table2_single']['mp_pct'])} % "
                 f"WP {rng(p['table2_single']['wp_deg'])}°; FCM on unseen samples RP {rng(p['table4_fcm_unseen']['rp_pct'])} % "
                 f"MP {rng(p['table4_fcm_unseen']['mp_pct'])} % WP {rng(p['table4_fcm_unseen']['wp_deg'])}°")
    s = r.get("fcm_speed")
    if s:
        lines.append("")
        lines.append(f"FCM {s['n_samples']} × 2, c = 5, m = 2, ε = 0.01: magmesh {s['magmesh_ms']:.1f} ms "
                     f"({s['magmesh_iterations']} it)"
                     + (f", scikit-fuzzy {s['skfuzzy_ms']:.1f} ms ({s['skfuzzy_iterations']} it), "
                        f"{s['speedup_vs_skfuzzy']:.1f}× faster; same 30 iterations from the same start: "
                        f"max centre diff {s['max_centre_diff_vs_skfuzzy']:.2e}, membership diff "
                        f"{s['max_membership_diff_vs_skfuzzy']:.2e}" if s.get("skfuzzy_ms") else "")
                     + f"; vs plain loop FCM: max centre diff {s['max_centre_diff_vs_loop']:.2e}")
    lines.append(f"(elapsed {r['elapsed_s']:.1f} s)")
    return "\n".join(lines)


if __name__ == "__main__":
    import json
    import sys

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(ap)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    res = run(a)
    print(json.dumps(res) if a.json else format_text(res))
    sys.exit(0)
