"""Offline side of the DMC detectors: features of recorded or simulated drives, FCM training, metrics.

Pure numpy (the car simulator is imported only when a drive is simulated). Used by
``magmesh train dmc`` and ``magmesh eval dmc``.

Metrics (docs/methods.md#metrics): a sample is *good* when its heading error is < 5°.
RP (recognition rate) = recognised-as-valid good samples / all good samples;
MP (error rate) = recognised-as-valid samples that are not good / all recognised-as-valid;
WP = heading accuracy of the recognised-as-valid samples (reported as RMS and mean |error|).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magmesh import maths
from services.dmc_detector import core, fcm
from services.dmc_detector.core import CompassParams, Features, Thresholds

GOOD_DEG = 5.0


@dataclass
class DriveData:
    """Features and truth of one drive (one row per paired magnetometer epoch)."""

    name: str
    layout: str
    seed: int
    features: Features
    heading_err_deg: np.ndarray  # |published heading − true heading|
    t_s: np.ndarray
    disturbed: np.ndarray  # truth: a source disturbs either compass noticeably
    source_active: np.ndarray | None = None  # truth: some source's field at the car exceeds the sim's level
    gyro_t_s: np.ndarray | None = None
    gyro_rad_s: np.ndarray | None = None
    accel_m_s2: np.ndarray | None = None
    mag1_nt: np.ndarray | None = None
    params1: CompassParams | None = None
    declination_rad: float = 0.0
    true_heading_rad: np.ndarray | None = None
    # simulator truth of the disturbance itself (source statistics, not detector inputs): the change of the true
    # field strength at each sensor, |b_k| − |b_earth| (N×2, nT), and the relative heading difference of the two
    # true fields (N, rad; level compasses)
    true_dm_nt: np.ndarray | None = None
    true_dh_rad: np.ndarray | None = None

    @property
    def good(self) -> np.ndarray:
        return self.heading_err_deg < GOOD_DEG


#: typical error of a static calibration: offset (nT) and matrix entries (fraction), 1-σ
CAL_OFFSET_ERR_NT = 50.0
CAL_MATRIX_ERR = 0.003


def params_from_sim(mp, rng: np.random.Generator | None = None, offset_err_nt: float = CAL_OFFSET_ERR_NT,
                    matrix_err: float = CAL_MATRIX_ERR) -> CompassParams:
    """The simulator's true compensation, or (with ``rng``) a calibration of it with typical errors."""
    off = np.asarray(mp.offset_nt, float)
    M = np.asarray(mp.matrix, float)
    pid = "sim-true"
    if rng is not None:
        off = off + rng.normal(0.0, offset_err_nt, 3)
        M = M @ (np.eye(3) + rng.normal(0.0, matrix_err, (3, 3)))
        pid = "sim-calibrated"
    return CompassParams(tuple(float(x) for x in off), tuple(float(x) for x in M.ravel()),
                         float(mp.field_radius_nt), "3d", pid)


#: the paper-streets drives (``paper_*`` layouts, HMR3300 at 8 Hz): rates between consecutive samples as in
#: the paper (the window of one sample, the rate over one 0.125 s period)
PAPER_FEATURES = core.FeatureSettings(smooth_window_s=0.1, rate_window_s=0.125)
#: calibration error of an HMR3300 pair compensated on the initial circle: offset (nT) and matrix (fraction),
#: 1-σ; gives the undisturbed single-compass heading error of ~1° RMS of the datasheet (level, 1.0° RMS)
#: and the paper's "< 1.2° after static compensation"
PAPER_CAL_OFFSET_ERR_NT = 250.0
PAPER_CAL_MATRIX_ERR = 0.006


def is_paper_layout(layout: str) -> bool:
    return layout.startswith("paper_")


def simulate_drive(layout: str, seed: int, duration_s: float = 300.0,
                   settings: core.FeatureSettings | None = None, calibration_error: bool = True,
                   cal_seed: int = 0) -> DriveData:
    """Simulate a car drive and compute its DMC features.

    The static compensation is the simulator's truth plus a calibration's typical error unless
    ``calibration_error`` is False. ``cal_seed`` picks the calibration: the same car keeps the same
    calibration from drive to drive (cal_seed fixed); another cal_seed is a recalibrated car.
    A ``paper_*`` layout is driven with the paper-streets profile (``sim_publishers.car.core.PAPER_STREETS``),
    its features taken between consecutive samples (:data:`PAPER_FEATURES`) and its calibration error
    that of an HMR3300 pair.
    """
    from sim_publishers.car.core import paper_streets_settings, simulate

    paper = is_paper_layout(layout)
    if paper:
        d = simulate(paper_streets_settings(layout, seed, duration_s=duration_s))
        settings = settings or PAPER_FEATURES
        err_kw = {"offset_err_nt": PAPER_CAL_OFFSET_ERR_NT, "matrix_err": PAPER_CAL_MATRIX_ERR}
    else:
        d = simulate(seed=seed, layout=layout, duration_s=duration_s)
        err_kw = {}
    rng = np.random.default_rng([cal_seed, 0xDC]) if calibration_error else None
    p1, p2 = params_from_sim(d.true_params["1"], rng, **err_kw), params_from_sim(d.true_params["2"], rng, **err_kw)
    f = core.features_batch(d.t_mag_s, d.mag_b_nt["1"], d.mag_b_nt["2"], p1, p2, d.declination_rad, settings)
    err = np.degrees(np.abs(maths.angle_diff(f.heading_rad, d.truth.heading_rad)))
    name = f"{layout}/seed{seed}" + (f"/cal{cal_seed}" if calibration_error and cal_seed else "")
    b1, b2 = d.truth.b_sensor_nt["1"], d.truth.b_sensor_nt["2"]
    earth = np.linalg.norm(d.truth.b_earth_body_nt, axis=1)
    true_dm = np.stack([np.linalg.norm(b1, axis=1) - earth, np.linalg.norm(b2, axis=1) - earth], axis=-1)
    true_dh = maths.angle_diff(np.arctan2(b1[:, 1], b1[:, 0]), np.arctan2(b2[:, 1], b2[:, 0]))
    return DriveData(name, layout, seed, f, err, d.t_mag_s, np.asarray(d.truth.disturbed, bool),
                     np.asarray(d.truth.active, bool).any(axis=1) if d.truth.active.size else np.zeros(len(err), bool),
                     d.t_imu_s, d.gyro_rad_s, d.accel_m_s2, d.mag_b_nt["1"], p1, float(d.declination_rad),
                     np.asarray(d.truth.heading_rad), true_dm, np.asarray(true_dh))


def lab_feature_settings(step_s: float) -> core.FeatureSettings:
    """Features between consecutive fixed-point samples ``step_s`` apart (the paper's turntable data)."""
    return core.FeatureSettings(smooth_window_s=0.5 * step_s, rate_window_s=step_s, max_gap_s=1.5 * step_s)


def simulate_lab(run: str, seed: int, turns: int = 24, **overrides) -> DriveData:
    """One run of the paper's turntable experiment (``sim_publishers.car.turntable``) as a drive.

    The compasses are level, so the static compensation is the paper's 2-D one (horizontal strength, radius =
    the horizontal Earth field); the simulator already applied its calibration errors to the samples."""
    from sim_publishers.car.turntable import TurntableSettings, simulate

    r = simulate(TurntableSettings(seed=seed, run=run, turns=turns, **overrides))
    p = CompassParams((0.0, 0.0, 0.0), (1, 0, 0, 0, 1, 0, 0, 0, 1), r.horizontal_field_nt, "2d", "turntable")
    step = float(r.t_s[1] - r.t_s[0])
    f = core.features_batch(r.t_s, r.mag_b_nt["1"], r.mag_b_nt["2"], p, p, r.declination_rad,
                            lab_feature_settings(step))
    err = np.degrees(np.abs(maths.angle_diff(f.heading_rad, r.heading_rad)))
    b1, b2 = r.b_sensor_nt["1"], r.b_sensor_nt["2"]
    h0 = r.horizontal_field_nt
    true_dm = np.stack([np.hypot(b1[:, 0], b1[:, 1]) - h0, np.hypot(b2[:, 0], b2[:, 1]) - h0], axis=-1)
    true_dh = maths.angle_diff(np.arctan2(b1[:, 1], b1[:, 0]), np.arctan2(b2[:, 1], b2[:, 0]))
    active = r.source_kind != "none"
    return DriveData(f"lab_{run}/seed{seed}", f"lab_{run}", seed, f, err, r.t_s, err >= 2.0, active,
                     gyro_t_s=r.gyro_t_s, gyro_rad_s=r.gyro_rad_s, true_heading_rad=r.heading_rad,
                     true_dm_nt=true_dm, true_dh_rad=np.asarray(true_dh),
                     declination_rad=float(r.declination_rad))


@dataclass
class Metrics:
    rp_pct: float
    mp_pct: float
    wp_deg: float  # RMS heading error of the valid samples
    wp_mean_deg: float
    n: int
    n_valid: int
    n_good: int
    wp_max_deg: float = float("nan")  # worst heading error of the valid samples
    #: 95th percentile of the valid samples' heading error (the paper does not say which statistic its WP is;
    #: docs/methods.md "How hard the test data are")
    wp_p95_deg: float = float("nan")
    onset_delay_s: float | None = None  # median delay from a disturbance's start to the alarm
    missed_zones: int | None = 0
    false_alarms: int | None = 0

    def as_dict(self) -> dict:
        return {k: (None if v is None else (round(v, 4) if isinstance(v, float) else v))
                for k, v in self.__dict__.items()}


def metrics(valid: np.ndarray, err_deg: np.ndarray) -> Metrics:
    valid = np.asarray(valid, bool)
    good = err_deg < GOOD_DEG
    nv, ng = int(valid.sum()), int(good.sum())
    rp = 100.0 * (valid & good).sum() / ng if ng else float("nan")
    mp = 100.0 * (valid & ~good).sum() / nv if nv else 0.0
    if not nv:
        nan = float("nan")
        return Metrics(float(rp), float(mp), nan, nan, int(len(valid)), nv, ng, nan, wp_p95_deg=nan)
    e = err_deg[valid]  # the accepted samples' errors: RMS, mean, worst, 95th percentile
    return Metrics(float(rp), float(mp), float(np.sqrt(np.mean(e ** 2))), float(np.mean(e)), int(len(valid)), nv, ng,
                   float(np.max(e)), wp_p95_deg=float(np.percentile(e, 95)))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where mask is True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=False))


def alarm_timing(t_s: np.ndarray, bad: np.ndarray, alarm: np.ndarray, disturbed: np.ndarray | None = None,
                 merge_s: float = 3.0, min_len_s: float = 0.5) -> tuple[list[float], int, int]:
    """Alarm timing against the bad-heading zones of a drive.

    Zones: runs of bad samples merged across gaps < ``merge_s``, ignoring zones shorter than
    ``min_len_s``. Returns (onset delays, zones missed, false alarms). The onset delay of a zone is the
    time from its first bad sample to the alarm; it is negative when the alarm was already raised (by
    the approach to the source) and counts from that raise. A false alarm is an alarm run with no bad,
    truth-disturbed or source-active sample within ``merge_s`` of it.
    """
    t_s = np.asarray(t_s, float)
    alarm = np.asarray(alarm, bool)
    zones: list[tuple[int, int]] = []
    for a, b in _runs(bad):
        if zones and t_s[a] - t_s[zones[-1][1] - 1] < merge_s:
            zones[-1] = (zones[-1][0], b)
        else:
            zones.append((a, b))
    zones = [(a, b) for a, b in zones if t_s[b - 1] - t_s[a] >= min_len_s]
    alarm_runs = _runs(alarm)
    delays, missed = [], 0
    for a, b in zones:
        if alarm[a]:
            start = max(s for s, e in alarm_runs if s <= a < e)
            delays.append(float(t_s[start] - t_s[a]))
            continue
        hit = np.flatnonzero(alarm[a:b])
        if hit.size:
            delays.append(float(t_s[a + hit[0]] - t_s[a]))
        else:
            missed += 1
    explained = np.asarray(bad, bool) | (np.asarray(disturbed, bool) if disturbed is not None else False)
    false = 0
    for a, e in alarm_runs:
        lo = np.searchsorted(t_s, t_s[a] - merge_s)
        hi = np.searchsorted(t_s, t_s[e - 1] + merge_s, side="right")
        if not explained[lo:hi].any():
            false += 1
    return delays, missed, false


def evaluate(valid: np.ndarray, drives: list[DriveData], hysteresis: core.HysteresisSettings | None = None,
             err_deg: np.ndarray | None = None) -> Metrics:
    """Metrics over several drives (valid: concatenated per-epoch decisions in the drives' order).

    ``err_deg`` replaces the drives' heading errors (a detector publishing another heading)."""
    err = np.concatenate([d.heading_err_deg for d in drives]) if err_deg is None else np.asarray(err_deg)
    m = metrics(valid, err)
    delays, missed, false = [], 0, 0
    i = 0
    for d in drives:
        n = len(d.t_s)
        v = np.asarray(valid[i:i + n], bool)
        i += n
        alarm = core.latch_batch(d.t_s, v, hysteresis)
        bad = err[i - n:i] >= GOOD_DEG
        explained = d.disturbed if d.source_active is None else (d.disturbed | d.source_active)
        dl, ms, fa = alarm_timing(d.t_s, bad, alarm, explained)
        delays += dl
        missed += ms
        false += fa
    m.onset_delay_s = float(np.median(delays)) if delays else None
    m.missed_zones = missed
    m.false_alarms = false
    return m


def threshold_valid(drives: list[DriveData], th: Thresholds) -> np.ndarray:
    return np.concatenate([core.threshold_test(d.features, th) for d in drives])


def single_valid(drives: list[DriveData], th: Thresholds) -> np.ndarray:
    return np.concatenate([np.all(core.single_compass_ratios(d.features, th) < 1.0, axis=-1) for d in drives])


def fcm_valid(drives: list[DriveData], model: fcm.FcmModel) -> np.ndarray:
    return np.concatenate([model.classify(d.features)[0] for d in drives])


def gyro_track_valid(drives: list[DriveData], stage1: Thresholds, settings=None) -> np.ndarray:
    """The gyro-checked second stage (``quasistatic.gyro_track_batch``) after the stage-1 ``stage1`` thresholds."""
    from services.dmc_detector.quasistatic import gyro_track_batch

    out = []
    for d in drives:
        if d.gyro_t_s is None or d.gyro_rad_s is None:
            raise ValueError(f"drive {d.name} has no gyro stream for the gyro-checked second stage")
        out.append(gyro_track_batch(d.features, core.threshold_test(d.features, stage1), d.gyro_t_s, d.gyro_rad_s,
                                    settings).valid)
    return np.concatenate(out)


#: the settings the gyro-checked second stage chooses from, on its training drives only (``choose_gyro_track``):
#: the stage-1 set (the paper's loosest, scaled) and, per way of carrying the reference heading, that way's gate and
#: time constants. The "consensus" reference estimates the undisturbed compass heading itself, so its gate is not
#: chosen but the accuracy asked for: a good heading errs by < 5°, less the compensated compass's own undisturbed
#: error (about 1°) — 4°; the "blend" reference follows the compass within seconds, its gate a tolerance of that
#: (chosen)
GYRO_TRACK_GRID = {"stage1_scale": (1.0, 1.5, 2.0), "reference": ("blend",), "gate_deg": (3.0, 4.0, 5.0),
                   "blend_tau_s": (2.0, 5.0), "bias_tau_s": (100.0, 300.0), "trust_dm_nt": (300.0, 600.0)}
GYRO_TRACK_CONSENSUS_GRID = {"stage1_scale": (1.0, 1.5, 2.0), "reference": ("consensus",), "gate_deg": (4.0,),
                             "consensus_window_s": (250.0, 400.0),
                             "consensus_scale_deg": (1.5, 3.0)}
#: the consensus fit's inlier band is two thirds of its biweight scale (1° at 1.5°, 2° at 3°)
CONSENSUS_INLIER_OF_SCALE = 2.0 / 3.0
#: its training drives: the FCM's training layout (paper_a), three seeds, none of them judged
GYRO_TRACK_TRAIN_DRIVES = (("paper_a", 1), ("paper_a", 2), ("paper_a", 3))
#: its operating rule: the highest RP on the training drives with MP at most this (ties: lower MP, then WP)
GYRO_TRACK_MAX_TRAIN_MP_PCT = 2.0


def gyro_track_grid() -> list[tuple[float, object]]:
    """Every (stage-1 scale, GyroTrackSettings) of the two grids, in a fixed order."""
    import itertools

    from services.dmc_detector.quasistatic import GyroTrackSettings

    out = []
    for grid in (GYRO_TRACK_GRID, GYRO_TRACK_CONSENSUS_GRID):
        keys = list(grid)
        for values in itertools.product(*(grid[k] for k in keys)):
            p = dict(zip(keys, values, strict=True))
            k = p.pop("stage1_scale")
            if "consensus_scale_deg" in p:
                p["consensus_inlier_deg"] = round(p["consensus_scale_deg"] * CONSENSUS_INLIER_OF_SCALE, 6)
            out.append((k, GyroTrackSettings(**p)))
    return out


def score_gyro_track(drives: list[DriveData], loose: Thresholds | None = None) -> list[tuple[float, object, Metrics]]:
    """(stage-1 scale, settings, metrics on ``drives``) for every point of the grids (training drives only)."""
    from services.dmc_detector.quasistatic import gyro_track_batch

    loose = loose or fcm.LOOSE
    err = np.concatenate([d.heading_err_deg for d in drives])
    stage1: dict[float, list] = {}
    out = []
    for k, st in gyro_track_grid():
        if k not in stage1:
            stage1[k] = [core.threshold_test(d.features, loose.scaled(k)) for d in drives]
        v = np.concatenate([gyro_track_batch(d.features, stage1[k][i], d.gyro_t_s, d.gyro_rad_s, st).valid
                            for i, d in enumerate(drives)])
        out.append((k, st, metrics(v, err)))
    return out


def choose_gyro_track(drives: list[DriveData], loose: Thresholds | None = None,
                      max_mp_pct: float = GYRO_TRACK_MAX_TRAIN_MP_PCT, scored=None) -> dict:
    """Choose the second stage's settings on ``drives`` (training drives only): every point of the grids, the
    highest RP with MP ≤ ``max_mp_pct`` (none within it: the lowest MP). ``scored``: ``score_gyro_track``'s result
    for the same drives, to choose under another cap without running the grid again. Returns the chosen stage-1
    thresholds, settings, their training metrics and the grid's size."""
    loose = loose or fcm.LOOSE
    scored = scored if scored is not None else score_gyro_track(drives, loose)
    best = None
    lowest = None  # the lowest MP of the grid, taken when no setting keeps within the cap
    for k, st, m in scored:
        low_key = (m.mp_pct, -m.rp_pct, m.wp_deg)
        if lowest is None or low_key < lowest[0]:
            lowest = (low_key, k, st, m)
        if m.mp_pct > max_mp_pct:
            continue
        key = (-m.rp_pct, m.mp_pct, m.wp_deg)
        if best is None or key < best[0]:
            best = (key, k, st, m)
    within = best is not None
    _, k, st, m = best if within else lowest
    return {"stage1": loose.scaled(k), "stage1_scale": k, "settings": st, "train_metrics": m,
            "grid_size": len(scored), "within_cap": within, "scored": scored,
            "rule": f"highest RP on the training drives with MP ≤ {max_mp_pct:g} % (ties: lower MP, then WP); "
                    "if no setting keeps within it, the lowest MP"}


def train_fcm(drives: list[DriveData], feature_set: str = "extended", seed: int = 0, use_reference: bool = True,
              **kw) -> fcm.FcmModel:
    """Train FCM centres on drives; ``use_reference`` orders clusters by the drives' true heading error."""
    info = {"drives": [d.name for d in drives], "source": "sim_publishers.car"}
    errs = [d.heading_err_deg for d in drives] if use_reference else None
    if drives and all(is_paper_layout(d.layout) for d in drives) and "feature_settings" not in kw:
        kw["feature_settings"] = PAPER_FEATURES  # the windows the features were computed with
    return fcm.train([d.features for d in drives], feature_set=feature_set, seed=seed, training_info=info,
                     heading_err_deg=errs, **kw)


def quasistatic_run(drive: DriveData, settings=None) -> tuple[np.ndarray, np.ndarray]:
    """Run the one-magnetometer quasi-static detector (§2) over a drive in time order.

    Returns (valid, heading error in degrees) per magnetometer epoch (compass 1).
    """
    from services.dmc_detector.quasistatic import QuasiStaticDetector

    if drive.gyro_t_s is None or drive.mag1_nt is None or drive.params1 is None:
        raise ValueError(f"drive {drive.name} has no IMU/magnetometer streams for the quasi-static detector")
    det = QuasiStaticDetector(settings)
    t_mag, t_imu = drive.t_s, drive.gyro_t_s
    decisions = []
    i = j = 0
    decl = drive.declination_rad
    while i < len(t_mag):
        if j < len(t_imu) and t_imu[j] <= t_mag[i]:
            decisions += det.add_imu(float(t_imu[j]), drive.gyro_rad_s[j], drive.accel_m_s2[j])
            j += 1
        else:
            decisions += det.add_mag(float(t_mag[i]), drive.mag1_nt[i], drive.params1, decl)
            i += 1
    while j < len(t_imu):
        decisions += det.add_imu(float(t_imu[j]), drive.gyro_rad_s[j], drive.accel_m_s2[j])
        j += 1
    valid = np.array([d.valid for d in decisions], bool)
    heading = np.array([d.heading_rad for d in decisions])
    err = np.degrees(np.abs(maths.angle_diff(heading, drive.true_heading_rad[:len(heading)])))
    return valid, err


#: the recipe of the committed model (``magmesh train dmc`` defaults; ``magmesh eval dmc`` re-trains with it)
DEFAULT_TRAIN_DRIVES = (("urban_a", 1),)
#: the training drive of the paper-streets model (``magmesh eval dmc`` trains on it, applies to the rest)
PAPER_TRAIN_DRIVES = (("paper_a", 1),)
DEFAULT_FEATURE_SET = "paper"
DEFAULT_USE_REFERENCE = True
