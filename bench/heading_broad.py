"""BROAD replay for the heading evaluation: load a trial, run the fuser core and three peer AHRS
(``vqf``, Laidig & Seel's VQF, online with its defaults; x-io Fusion via ``imufusion``; the ``ahrs``
package's EKF) on it, score the heading error.

BROAD (Laidig et al., Data 6(7):72, 2021, CC-BY-4.0): myon aktos-t IMU with optical ground truth at
285.714 Hz. ``opt_quat`` is sensor → ENU. The heading error is BROAD's own metric
(``example_code/broad_utils.py``): the error quaternion in the Earth frame ``q_est ⊗ q_opt⁻¹`` and the
angle of its rotation about the vertical, ``2·atan(|z / w|)``, RMS over the ``movement`` samples.

All three estimators start from the same attitude: the one given by the first sample's accelerometer
and magnetometer (BROAD's ``quatFromAccMag`` convention), with no start-up phase.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from magmesh import maths
from magmesh.paths import DATA_DIR
from services.heading_fuser.core import HeadingFilter, Settings

BROAD_DIR = DATA_DIR / "broad"
UT_TO_NT = 1000.0


@dataclass
class Trial:
    name: str
    rate_hz: float
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    mag_nt: np.ndarray
    quat_true: np.ndarray  # sensor → ENU, NaN where the cameras lost the board
    movement: np.ndarray  # bool

    def sliced(self, n: int) -> Trial:
        return Trial(self.name, self.rate_hz, self.gyro_rad_s[:n], self.accel_m_s2[:n], self.mag_nt[:n],
                     self.quat_true[:n], self.movement[:n])


TRIAL_SUFFIXES = (".hdf5", ".h5", ".mat")
_FIELDS = ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement", "sampling_rate")


class TrialError(ValueError):
    """A file that is not a readable BROAD trial (the message says why)."""


def trial_files(directory: Path | str = BROAD_DIR) -> list[Path]:
    """Every candidate trial file (HDF5 or BROAD's MATLAB files), one per trial name (HDF5 preferred)."""
    by_name: dict[str, Path] = {}
    for p in sorted(Path(directory).iterdir()) if Path(directory).is_dir() else []:
        if p.suffix.lower() in TRIAL_SUFFIXES and (p.stem not in by_name or p.suffix.lower() != ".mat"):
            by_name[p.stem] = p
    return [by_name[k] for k in sorted(by_name)]


def _load_mat(path: Path) -> dict:
    import scipy.io

    try:
        d = scipy.io.loadmat(path, squeeze_me=False)
        get = {k: np.asarray(d[k]) for k in _FIELDS if k in d}
    except NotImplementedError:  # MATLAB v7.3 files are HDF5 with every matrix transposed
        with h5py.File(path, "r") as f:
            get = {k: np.asarray(f[k]).T for k in _FIELDS if k in f}
    return get


def load_trial(path: Path | str) -> Trial:
    """Load one BROAD trial (``.hdf5`` or BROAD's ``.mat``); :class:`TrialError` says what is wrong."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".mat":
            d = _load_mat(path)
            rate = float(np.asarray(d.get("sampling_rate", np.nan)).ravel()[0]) if "sampling_rate" in d else None
        else:
            with h5py.File(path, "r") as f:
                d = {k: np.asarray(f[k]) for k in _FIELDS[:-1] if k in f}
                rate = float(f.attrs["sampling_rate"]) if "sampling_rate" in f.attrs else None
    except (OSError, ValueError) as e:
        raise TrialError(f"{path.name}: not readable as a BROAD trial ({e})") from None
    missing = [k for k in _FIELDS[:-1] if k not in d] + ([] if rate else ["sampling_rate"])
    if missing:
        raise TrialError(f"{path.name}: not a BROAD trial, missing {', '.join(missing)}")
    n = len(d["imu_gyr"])
    for k in ("imu_acc", "imu_mag", "opt_quat"):
        if np.shape(d[k])[0] != n:
            raise TrialError(f"{path.name}: {k} has {np.shape(d[k])[0]} rows, imu_gyr {n}")
    return Trial(path.stem, rate, np.asarray(d["imu_gyr"], float), np.asarray(d["imu_acc"], float),
                 np.asarray(d["imu_mag"], float) * UT_TO_NT, np.asarray(d["opt_quat"], float),
                 np.asarray(d["movement"], bool).ravel())


def scorable_trials(directory: Path | str | None = None, max_s: float | None = None,
                    skipped: dict[str, str] | None = None):
    """Each trial of ``directory`` (default ``data/broad``) that can be scored, in file order (the first
    ``max_s`` seconds if given); a file that cannot goes into ``skipped`` (name → why) instead."""
    where = Path(directory or BROAD_DIR)
    if not where.is_dir():
        raise FileNotFoundError(f"BROAD directory {where} does not exist")
    files = trial_files(where)
    if not files:
        raise FileNotFoundError(f"no BROAD trial files (*.hdf5, *.mat) in {where}")
    skipped = {} if skipped is None else skipped
    for path in files:
        try:
            trial = load_trial(path)
        except TrialError as e:
            skipped[path.stem] = str(e)
            continue
        if max_s is not None:
            trial = trial.sliced(int(max_s * trial.rate_hz))
        if not trial.movement.any():
            skipped[trial.name] = "no samples marked as movement (nothing to score)"
            continue
        if not np.isfinite(trial.quat_true[trial.movement]).any():
            skipped[trial.name] = "no optical reference during the movement samples"
            continue
        yield trial


def is_disturbed(name: str) -> bool:
    return "disturbed" in name and "undisturbed" not in name


# ---- metric -----------------------------------------------------------------------------------


def quat_mul_rows(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, px, py, pz = p.T
    qw, qx, qy, qz = q.T
    return np.column_stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def heading_errors_rad(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """BROAD heading error per sample: rotation about the vertical of ``q_est ⊗ q_true⁻¹`` (rad)."""
    qt = q_true * np.array([1.0, -1.0, -1.0, -1.0])
    d = quat_mul_rows(q_est, qt)
    return 2.0 * np.arctan(np.abs(d[:, 3] / d[:, 0]))


def heading_rms_deg(q_est: np.ndarray, trial: Trial) -> float:
    e = heading_errors_rad(q_est, trial.quat_true)[trial.movement]
    return float(np.degrees(np.sqrt(np.nanmean(e**2))))


def initial_quat(trial: Trial) -> np.ndarray:
    """Attitude from the first accelerometer + magnetometer sample (sensor → ENU, magnetic north)."""
    f = HeadingFilter(Settings())
    f.align(trial.accel_m_s2[0], trial.mag_nt[0])
    return f.quaternion()


# ---- the three estimators ---------------------------------------------------------------------


def broad_settings(**overrides) -> Settings:
    """Fuser settings for BROAD's handheld board: fast rotations with large linear accelerations, and a
    magnetometer whose field direction wanders by several degrees with motion even when undisturbed
    (measured with the optical attitude: dip 61–76° for 5–95 % of the fast trial), so the field
    checks are wider and the magnetometer trusted less than on a car."""
    # the imu_only profile without the three things it adds (inertial-frame gravity low-pass, rest detection,
    # online lag estimate): the settings this eval used before that profile existed
    from services.heading_fuser import profiles

    base = dict(profiles.values(profiles.IMU_ONLY), gravity_lpf_tau_s=0.0, rest_detection=False,
                mag_delay_online=False)
    base.update(overrides)
    return Settings(**base)


def broad_settings_for(trial: Trial, **overrides) -> Settings:
    """:func:`broad_settings` plus the magnetometer lag estimated from the trial's own gyro and
    magnetometer (no ground truth used)."""
    from services.heading_fuser.core import estimate_mag_delay_s

    delay = estimate_mag_delay_s(trial.gyro_rad_s, trial.mag_nt, trial.rate_hz)
    return broad_settings(mag_delay_s=delay, **overrides)


def run_magmesh(trial: Trial, settings: Settings | None = None, impl: str = "compiled") -> tuple[np.ndarray, dict]:
    """The fuser over a whole trial: each sample an IMU step (the first of 0 s, then 1/rate) and its
    magnetometer sample; the attitude after each sample. ``impl`` ``compiled`` (the default: the compiled
    filter, the whole trial in one call) or ``reference`` (:class:`core.HeadingFilter`, sample by sample);
    the two agree within 1e-9 rad (``tests/test_heading_compiled.py``)."""
    settings = settings or broad_settings()
    n = len(trial.gyro_rad_s)
    dt = 1.0 / trial.rate_hz
    names = ("initialising", "magnetic", "gyro_only", "recovering")
    if impl == "compiled":
        from services.heading_fuser import compiled

        compiled.warm()  # compile (or load) outside the timed part
        t0 = time.perf_counter()
        res, _, pos_mag, _ = compiled.run_recording(settings, trial.gyro_rad_s, trial.accel_m_s2, trial.mag_nt, dt)
        elapsed = time.perf_counter() - t0
        out = np.array(res.quaternion[pos_mag])
        counts = np.bincount(res.mode[pos_mag][1:].astype(np.int64), minlength=4)
        modes = {m: int(c) for m, c in zip(names, counts, strict=False)}
        transitions = int(np.count_nonzero(res.reason))
    elif impl == "reference":
        f = HeadingFilter(settings)
        out = np.empty((n, 4))
        modes = {m: 0 for m in names}
        gyro, acc, mag = trial.gyro_rad_s.tolist(), trial.accel_m_s2, trial.mag_nt
        f.update_imu(gyro[0], acc[0], 0.0)
        f.update_mag(mag[0])
        t0 = time.perf_counter()
        out[0] = f.q
        for i in range(1, n):
            f.update_imu(gyro[i], acc[i], dt)
            f.update_mag(mag[i])
            out[i] = f.q
            modes[f.mode] += 1
        elapsed = time.perf_counter() - t0
        transitions = len(f.transitions)
    else:
        raise ValueError(f"unknown impl {impl!r} (compiled or reference)")
    info = {"impl": impl, "us_per_sample": 1e6 * elapsed / max(n - 1, 1),
            "mode_frac": {k: v / max(n - 1, 1) for k, v in modes.items()}, "transitions": transitions}
    return out, info


_S = math.sqrt(0.5)
Q_NWU_TO_ENU = np.array([_S, 0.0, 0.0, _S])  # +90° about up: north (1, 0, 0)_NWU → (0, 1, 0)_ENU


def run_imufusion(trial: Trial) -> np.ndarray:
    """x-io Fusion with its magnetic rejection on (the README's example settings), same start attitude.

    Run in its own North-West-Up convention (its ENU option does not give an ENU output: a board lying
    with x east, y north converges to yaw −90°) and turned into ENU, ``q_ENU = q_z(+90°) ⊗ q_NWU``.
    """
    import imufusion

    rate = int(round(trial.rate_hz))
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(imufusion.AhrsSettings(
        convention=imufusion.CONVENTION_NWU, gain=0.5, gyroscope_range=2000.0,
        acceleration_rejection=10.0, magnetic_rejection=10.0, rejection_timeout=5 * rate, sample_rate=rate))
    to_nwu = Q_NWU_TO_ENU * np.array([1.0, -1.0, -1.0, -1.0])
    ahrs.set_quaternion(quat_mul_rows(to_nwu[None], initial_quat(trial)[None])[0])
    ahrs.skip_startup()
    gyro_deg = np.degrees(trial.gyro_rad_s)
    acc_g = trial.accel_m_s2 / maths.G0
    mag_ut = trial.mag_nt / UT_TO_NT
    out = np.empty((len(gyro_deg), 4))
    for i in range(len(gyro_deg)):
        ahrs.update(gyro_deg[i], acc_g[i], mag_ut[i])
        out[i] = ahrs.get_quaternion()
    return quat_mul_rows(np.repeat(Q_NWU_TO_ENU[None], len(out), axis=0), out)


def run_vqf(trial: Trial) -> np.ndarray:
    """VQF (Laidig & Seel 2023, the ``vqf`` package), online, its default parameters, 9-D output.

    ``vqf``'s quaternions are scalar-first, sensor → ENU (x east, y north, z up; magnetic north), the
    convention of BROAD's ``opt_quat``; it aligns itself from its first samples. ``updateBatch`` runs
    the online (causal) filter over the arrays in compiled code.
    """
    from vqf import VQF

    ts = 1.0 / trial.rate_hz
    out = VQF(ts).updateBatch(np.ascontiguousarray(trial.gyro_rad_s), np.ascontiguousarray(trial.accel_m_s2),
                              np.ascontiguousarray(trial.mag_nt / UT_TO_NT))
    return np.asarray(out["quat9D"])


def run_ahrs_ekf(trial: Trial) -> np.ndarray:
    """The ``ahrs`` package's quaternion EKF (its default noises), same start attitude.

    ``ahrs``' ENU mode pairs the accelerometer reading (+up at rest) with a gravity reference of
    ``[0, 0, −1]``: its Earth frame is West-North-Down, ENU turned 180° about north. Given a field
    reference of the matching sign (``magnetic_ref = −dip``) it is consistent in that frame, so the
    start attitude is turned into it and its output turned back: ``q_ENU = q_flip ⊗ q_WND``.
    """
    from ahrs.filters import EKF

    mag_ut = trial.mag_nt / UT_TO_NT
    flip = np.array([[0.0, 0.0, 1.0, 0.0]])  # 180° about north: v_ENU = diag(−1, 1, −1) v_WND
    q0 = quat_mul_rows(flip * np.array([1.0, -1.0, -1.0, -1.0]), initial_quat(trial)[None])[0]
    dip_deg = float(np.degrees(_dip_of_first_sample(trial)))
    ekf = EKF(gyr=trial.gyro_rad_s, acc=trial.accel_m_s2, mag=mag_ut, frequency=trial.rate_hz, frame="ENU",
              q0=q0, magnetic_ref=-dip_deg)
    q = np.asarray(ekf.Q)
    return quat_mul_rows(np.repeat(flip, len(q), axis=0), q)


def _dip_of_first_sample(trial: Trial) -> float:
    q = initial_quat(trial)
    mn = maths.quat_rotate(q, trial.mag_nt[0])
    return math.atan2(-mn[2], math.hypot(mn[0], mn[1]))


PEERS = {"vqf": run_vqf, "imufusion": run_imufusion, "ahrs_ekf": run_ahrs_ekf}
