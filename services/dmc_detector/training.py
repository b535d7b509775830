"""Offline side of the DMC detectors: features of recorded or simulated drives, FCM training, metrics.

Pure numpy (the car simulator is imported only when a drive is simulated). Used by
``magmesh train dmc`` and ``magmesh eval dmc``.

Metrics (ALGORITHMS.md §1): a sample is *good* when its heading error is < 5°.
RP (recognition rate) = recognised-as-valid good samples / all good samples;
MP (error rate) = recognised-as-valid samples that are not good / all recognised-as-valid;
WP = heading accuracy of the recognised-as-valid samples (reported as RMS and mean |error|).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magmesh import maths

from . import core, fcm
from .core import CompassParams, Features, Thresholds

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
    gyro_t_s: np.ndarray | None = None
    gyro_rad_s: np.ndarray | None = None
    accel_m_s2: np.ndarray | None = None
    mag1_nt: np.ndarray | None = None
    params1: CompassParams | None = None

    @property
    def good(self) -> np.ndarray:
        return self.heading_err_deg < GOOD_DEG


def params_from_sim(mp) -> CompassParams:
    return CompassParams(tuple(float(x) for x in mp.offset_nt), tuple(float(x) for x in np.ravel(mp.matrix)),
                         float(mp.field_radius_nt), "3d", "sim-true")


def simulate_drive(layout: str, seed: int, duration_s: float = 300.0,
                   settings: core.FeatureSettings | None = None) -> DriveData:
    """Simulate a car drive and compute its DMC features with the true static compensation."""
    from sim_publishers.car.core import simulate

    d = simulate(seed=seed, layout=layout, duration_s=duration_s)
    p1, p2 = params_from_sim(d.true_params["1"]), params_from_sim(d.true_params["2"])
    f = core.features_batch(d.t_mag_s, d.mag_b_nt["1"], d.mag_b_nt["2"], p1, p2, d.declination_rad, settings)
    err = np.degrees(np.abs(maths.angle_diff(f.heading_rad, d.truth.heading_rad)))
    return DriveData(f"{layout}/seed{seed}", layout, seed, f, err, d.t_mag_s, np.asarray(d.truth.disturbed, bool),
                     d.t_imu_s, d.gyro_rad_s, d.accel_m_s2, d.mag_b_nt["1"], p1)


@dataclass
class Metrics:
    rp_pct: float
    mp_pct: float
    wp_deg: float  # RMS heading error of the valid samples
    wp_mean_deg: float
    n: int
    n_valid: int
    n_good: int
    onset_delay_s: float | None = None  # median delay from a disturbance's start to the alarm
    missed_zones: int = 0
    false_alarms: int = 0

    def as_dict(self) -> dict:
        return {k: (None if v is None else (round(v, 4) if isinstance(v, float) else v))
                for k, v in self.__dict__.items()}


def metrics(valid: np.ndarray, err_deg: np.ndarray) -> Metrics:
    valid = np.asarray(valid, bool)
    good = err_deg < GOOD_DEG
    nv, ng = int(valid.sum()), int(good.sum())
    rp = 100.0 * (valid & good).sum() / ng if ng else float("nan")
    mp = 100.0 * (valid & ~good).sum() / nv if nv else 0.0
    wp = float(np.sqrt(np.mean(err_deg[valid] ** 2))) if nv else float("nan")
    wpm = float(np.mean(err_deg[valid])) if nv else float("nan")
    return Metrics(float(rp), float(mp), wp, wpm, int(len(valid)), nv, ng)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where mask is True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def alarm_timing(t_s: np.ndarray, bad: np.ndarray, alarm: np.ndarray, disturbed: np.ndarray | None = None,
                 merge_s: float = 3.0, min_len_s: float = 0.5) -> tuple[list[float], int, int]:
    """Alarm timing against the bad-heading zones of a drive.

    Zones: runs of bad samples merged across gaps < ``merge_s``, ignoring zones shorter than
    ``min_len_s``. Returns (onset delays, zones missed, false alarms). The onset delay of a zone is the
    time from its first bad sample to the alarm; it is negative when the alarm was already raised (by
    the approach to the source) and counts from that raise. A false alarm is an alarm run with no bad
    or truth-disturbed sample within ``merge_s`` of it.
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


def evaluate(valid: np.ndarray, drives: list[DriveData], hysteresis: core.HysteresisSettings | None = None) -> Metrics:
    """Metrics over several drives (valid: concatenated per-epoch decisions in the drives' order)."""
    err = np.concatenate([d.heading_err_deg for d in drives])
    m = metrics(valid, err)
    delays, missed, false = [], 0, 0
    i = 0
    for d in drives:
        n = len(d.t_s)
        v = np.asarray(valid[i:i + n], bool)
        i += n
        alarm = core.latch_batch(d.t_s, v, hysteresis)
        dl, ms, fa = alarm_timing(d.t_s, ~d.good, alarm, d.disturbed)
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


def train_fcm(drives: list[DriveData], feature_set: str = "extended", seed: int = 0, **kw) -> fcm.FcmModel:
    info = {"drives": [d.name for d in drives], "source": "sim_publishers.car"}
    return fcm.train([d.features for d in drives], feature_set=feature_set, seed=seed, training_info=info, **kw)
