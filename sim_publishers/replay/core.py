"""Readers of the bundled real recordings, turned into magmesh message streams.

Each reader loads one recording from :data:`magmesh.paths.DATA_DIR` into plain numpy arrays (body frame
FLU, nT, rad, s from the start of the recording) and :func:`stream` turns it into the time-ordered
``(t_s, key, msg_type, fields)`` tuples a :class:`magmesh.runtime.SimPublisher` yields: ``raw`` keys like a
simulated vehicle, the recording's ground truth on ``truth`` keys. numpy/scipy/h5py only, no Zenoh.

Datasets (see ``data/README.md`` for sources and licences):

- ``broad:<trial>`` — BROAD (Laidig et al. 2021, CC-BY-4.0): IMU + magnetometer at 285.7 Hz with optical
  motion-capture orientation. Published: ``raw/imu``, ``raw/mag/1`` (block means at ``imu_rate_hz``),
  ``truth/pose`` (orientation and position from the cameras), ``truth/field`` (the undisturbed field in the
  body frame) and ``truth/sources`` (whether the magnetometer is disturbed: the measured field rotated into
  ENU with the optical orientation departs from the undisturbed field by more than ``disturbed_deg`` in
  horizontal direction or ``disturbed_frac`` in strength).
- ``car_circles`` — a car driving three laps of a roundabout with a VN-100 (MIT): ``raw/imu``,
  ``raw/mag/1`` at 40 Hz (sensor frame FRD turned into FLU), ``raw/gnss`` at 1 Hz; ``truth/pose`` is the
  GNSS course and position (a reference, not an independent truth), published while the car moves.
- ``kok:eight`` / ``kok:square`` — indoor walks of Kok & Solin (MIT): a phone's magnetometer at 10 Hz,
  ``raw/ins`` from the phone's visual-inertial odometry, ``truth/pose`` from the same odometry and
  orientation. Headings there are in the walk's local frame, not from true north.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from magmesh import maths
from magmesh.paths import DATA_DIR
from schemas import keys

BROAD_DIR = DATA_DIR / "broad"
CAR_CSV = DATA_DIR / "calibration" / "car_circles_vn100.csv"
KOK_DIR = DATA_DIR / "maps"

#: undisturbed field of the BROAD lab, ENU, nT (data/README.md)
BROAD_FIELD_ENU_NT = np.array([100.0, 15800.0, -40800.0])

# sensor-frame conversions into body FLU (x forward, y left, z up)
FRD_TO_FLU = np.diag([1.0, -1.0, -1.0])
# phone camera frame (x right, y up, z backwards) → FLU: forward = −z, left = −x, up = y
CAMERA_TO_FLU = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass
class Recording:
    """One real recording as arrays; every optional stream may be absent (None)."""

    name: str
    source: str  # attribution, one line
    mag_t_s: np.ndarray
    mag_nt: np.ndarray  # N×3 body FLU
    imu_t_s: np.ndarray | None = None
    gyro_rad_s: np.ndarray | None = None
    accel_m_s2: np.ndarray | None = None
    truth_t_s: np.ndarray | None = None
    truth_quat: np.ndarray | None = None  # body → nav, [w, x, y, z]
    truth_pos_m: np.ndarray | None = None
    truth_heading_rad: np.ndarray | None = None  # when there is no full orientation (car: GNSS course)
    field_earth_enu_nt: np.ndarray | None = None
    disturbed: np.ndarray | None = None  # bool per truth sample
    gnss: dict | None = None  # arrays: t_s, lat_deg, lon_deg, alt_m, pos_enu_m, vel_enu_m_s
    ins: dict | None = None  # arrays: t_s, pos_enu_m, vel_enu_m_s, heading_rad
    notes: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return float(self.mag_t_s[-1] - self.mag_t_s[0]) if len(self.mag_t_s) else 0.0


def quat_to_matrices(q: np.ndarray) -> np.ndarray:
    """N×4 quaternions [w, x, y, z] → N×3×3 rotation matrices (vectorised ``maths.quat_to_matrix``)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def euler_from_matrices(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(heading, pitch, roll) arrays from N×3×3 body → ENU matrices (vectorised ``maths.euler_from_matrix``)."""
    pitch = np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    heading = maths.yaw_to_heading(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    return heading, pitch, roll


def _block_mean(a: np.ndarray, n: int) -> np.ndarray:
    m = (len(a) // n) * n
    return a[:m].reshape(-1, n, *a.shape[1:]).mean(axis=1)


# ---- BROAD ------------------------------------------------------------------------------------


def broad_trials() -> list[str]:
    """Names of the BROAD trials bundled in the repository."""
    return sorted(p.stem for p in BROAD_DIR.glob("*.hdf5"))


def broad_description(trial: str) -> str:
    try:
        return json.loads((BROAD_DIR / "trials.json").read_text())["trials"][trial]["description"]
    except (OSError, KeyError, ValueError):
        return ""


def load_broad(trial: str, rate_hz: float = 100.0, truth_rate_hz: float = 10.0,
               disturbed_deg: float = 10.0, disturbed_frac: float = 0.1) -> Recording:
    """Load a BROAD trial, averaged down to about ``rate_hz`` (block means keep the integrated rotation)."""
    import h5py

    path = BROAD_DIR / f"{trial}.hdf5"
    if not path.exists():
        raise FileNotFoundError(f"BROAD trial {trial!r} is not bundled; available: {', '.join(broad_trials())}")
    with h5py.File(path, "r") as f:
        fs = float(f.attrs["sampling_rate"])
        gyr = f["imu_gyr"][:]
        acc = f["imu_acc"][:]
        mag = f["imu_mag"][:] * 1000.0  # µT → nT
        quat = f["opt_quat"][:]
        pos = f["opt_pos"][:]
    t = np.arange(len(gyr)) / fs
    n = max(1, int(round(fs / rate_hz)))
    imu_t = _block_mean(t, n)
    rec = Recording(
        name=f"broad:{trial}",
        source="BROAD, Laidig et al., Data 6(7):72, 2021, CC-BY-4.0",
        mag_t_s=imu_t,
        mag_nt=_block_mean(mag, n),
        imu_t_s=imu_t,
        gyro_rad_s=_block_mean(gyr, n),
        accel_m_s2=_block_mean(acc, n),
        field_earth_enu_nt=BROAD_FIELD_ENU_NT.copy(),
        notes={"sampling_rate_hz": fs, "block": n, "description": broad_description(trial)},
    )
    # truth at truth_rate_hz: the sample at the block centre (quaternions are not averaged)
    nt = max(1, int(round(fs / truth_rate_hz)))
    idx = np.arange(nt // 2, len(t), nt)
    q = quat[idx]
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(pos[idx]), axis=1)
    idx, q = idx[ok], q[ok]
    rec.truth_t_s = t[idx]
    rec.truth_quat = q
    rec.truth_pos_m = pos[idx]
    # disturbance truth: each raw sample rotated into ENU with its own optical orientation, averaged over
    # the truth block, compared with the lab field (camera gaps leave NaN and are skipped)
    good = np.all(np.isfinite(quat), axis=1)
    b_enu_raw = np.zeros_like(mag)
    b_enu_raw[good] = np.einsum("nij,nj->ni", quat_to_matrices(quat[good]), mag[good])
    cs = np.vstack([np.zeros(3), np.cumsum(b_enu_raw, axis=0)])
    cn = np.concatenate([[0], np.cumsum(good)])
    lo = np.clip(idx - nt // 2, 0, len(t))
    hi = np.clip(lo + nt, 0, len(t))
    b_enu = (cs[hi] - cs[lo]) / np.maximum(cn[hi] - cn[lo], 1)[:, None]
    ref = rec.field_earth_enu_nt
    dir_err = np.abs(maths.angle_diff(np.arctan2(b_enu[:, 0], b_enu[:, 1]), math.atan2(ref[0], ref[1])))
    strength_err = np.abs(np.linalg.norm(b_enu, axis=1) / np.linalg.norm(ref) - 1.0)
    rec.disturbed = (dir_err > math.radians(disturbed_deg)) | (strength_err > disturbed_frac)
    rec.notes.update(truth_block=nt, disturbed_deg=disturbed_deg, disturbed_frac=disturbed_frac)
    return rec


# ---- the car circles (VN-100) -----------------------------------------------------------------


def utm_convergence_rad(lat_deg: float, lon_deg: float, zone: int) -> float:
    """Grid convergence γ of a UTM zone: grid north is rotated by γ from true north (east positive)."""
    lon0 = -183.0 + 6.0 * zone
    return math.atan(math.tan(math.radians(lon_deg - lon0)) * math.sin(math.radians(lat_deg)))


def load_car_circles(min_speed_m_s: float = 1.0) -> Recording:
    with open(CAR_CSV, newline="") as fh:
        rows = list(csv.DictReader(fh))

    def col(rs, name):
        return np.array([float(r[name]) for r in rs])

    imu = [r for r in rows if r["timestamp_sec_imu"]]
    gps = [r for r in rows if r["timestamp_sec_gps"] and r["latitude"]]
    t_imu = col(imu, "timestamp_sec_imu") + col(imu, "timestamp_nanosec_imu") * 1e-9
    t_gps = col(gps, "timestamp_sec_gps") + col(gps, "timestamp_nanosec_gps") * 1e-9
    t0 = min(t_imu[0], t_gps[0])
    mag = np.stack([col(imu, f"magnetic_field_{a}") for a in "xyz"], 1) * 1e9 @ FRD_TO_FLU.T  # T → nT
    acc = np.stack([col(imu, f"linear_acceleration_{a}") for a in "xyz"], 1) @ FRD_TO_FLU.T
    gyr = np.stack([col(imu, f"angular_velocity_{a}") for a in "xyz"], 1) @ FRD_TO_FLU.T
    lat, lon, alt = col(gps, "latitude"), col(gps, "longitude"), col(gps, "altitude")
    east, north = col(gps, "utm_easting"), col(gps, "utm_northing")
    zone = int(float(gps[0]["zone"]))
    # UTM grid → local ENU at the first fix: rotate by the grid convergence
    gamma = utm_convergence_rad(float(lat[0]), float(lon[0]), zone)
    de, dn = east - east[0], north - north[0]
    c, s = math.cos(gamma), math.sin(gamma)
    pos = np.stack([c * de + s * dn, -s * de + c * dn, alt - alt[0]], 1)
    tg = t_gps - t0
    vel = np.stack([np.gradient(pos[:, k], tg) for k in range(3)], 1)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    course = maths.wrap_2pi(np.arctan2(vel[:, 0], vel[:, 1]))
    rec = Recording(
        name="car_circles",
        source="Aryaman22102002/Sensor_Fusion_of_GPS_and_IMU_Data_for_Automotive_Dead_Reckoning (MIT)",
        mag_t_s=t_imu - t0,
        mag_nt=mag,
        imu_t_s=t_imu - t0,
        gyro_rad_s=gyr,
        accel_m_s2=acc,
        gnss=dict(t_s=tg, lat_deg=lat, lon_deg=lon, alt_m=alt, pos_enu_m=pos, vel_enu_m_s=vel,
                  course_rad=course, speed_m_s=speed),
        notes={"utm_zone": zone, "grid_convergence_rad": gamma, "t0_unix_s": float(t0)},
    )
    moving = speed >= min_speed_m_s
    rec.truth_t_s = tg[moving]
    rec.truth_pos_m = pos[moving]
    rec.truth_heading_rad = course[moving]
    return rec


# ---- Kok & Solin indoor walks -----------------------------------------------------------------


def load_kok(walk: str) -> Recording:
    from scipy.io import loadmat

    path = KOK_DIR / f"{walk}.mat"
    if not path.exists():
        raise FileNotFoundError(f"indoor walk {walk!r} is not bundled (eight, square)")
    d = loadmat(path)
    t = d["t"].ravel().astype(float)
    t = t - t[0]
    R_cam = quat_to_matrices(d["quat"])  # phone frame → walk frame (z up)
    R = R_cam @ CAMERA_TO_FLU.T  # FLU body → walk frame
    mag = d["m"] * 1000.0 @ CAMERA_TO_FLU.T  # µT → nT, FLU
    pos = np.vstack([d["initPos"].reshape(1, 3), d["initPos"].reshape(1, 3) + np.cumsum(d["dPos"], axis=0)])
    n = min(len(t), len(pos), len(R))
    t, pos, R, mag = t[:n], pos[:n], R[:n], mag[:n]
    vel = np.stack([np.gradient(pos[:, k], t) for k in range(3)], 1)
    quat = np.array([maths.quat_from_matrix(r) for r in R])
    heading, _, _ = euler_from_matrices(R)
    return Recording(
        name=f"kok:{walk}",
        source="Kok & Solin, online 1-D magnetic field SLAM, manonkok/1d-magnetic-field-slam (MIT)",
        mag_t_s=t,
        mag_nt=mag,
        truth_t_s=t,
        truth_quat=quat,
        truth_pos_m=pos,
        ins=dict(t_s=t, pos_enu_m=pos, vel_enu_m_s=vel, heading_rad=heading),
        notes={"frame": "local frame of the walk (z up); headings are not from true north"},
    )


DATASETS = ("broad:<trial>", "car_circles", "kok:eight", "kok:square")


def load(dataset: str, rate_hz: float = 100.0, truth_rate_hz: float = 10.0) -> Recording:
    """Load a dataset by name: ``broad:<trial>``, ``car_circles``, ``kok:eight``, ``kok:square``."""
    kind, _, arg = dataset.partition(":")
    if kind == "broad":
        return load_broad(arg or "32_disturbed_attached_magnet_1cm", rate_hz, truth_rate_hz)
    if kind == "car_circles":
        return load_car_circles()
    if kind == "kok":
        return load_kok(arg or "eight")
    raise ValueError(f"unknown dataset {dataset!r}; known: {', '.join(DATASETS)}")


# ---- the message stream ----------------------------------------------------------------------


@dataclass(frozen=True)
class StreamSettings:
    sensor: str = "1"
    assumed_num_sats: int = 8  # the car CSV has no satellite count or PDOP: these are stated assumptions
    assumed_pdop: float = 1.5
    assumed_horiz_std_m: float = 2.5


def _v(a) -> list[float]:
    return [float(x) for x in a]


def stream(rec: Recording, vehicle: str, settings: StreamSettings = StreamSettings(),
           time_offset_s: float = 0.0) -> Iterator[tuple[float, str, str, dict]]:
    """Yield ``(t_s, key, msg_type, fields)`` for every sample of a recording, in time order."""
    events: list[tuple[float, int, str, str, dict]] = []
    sensor = settings.sensor
    k_mag = keys.raw_mag(vehicle, sensor)
    for i in range(len(rec.mag_t_s)):
        events.append((rec.mag_t_s[i], 1, k_mag, "mag", {"sensor": sensor, "b_nt": _v(rec.mag_nt[i])}))
    if rec.imu_t_s is not None:
        k_imu = keys.raw_imu(vehicle)
        for i in range(len(rec.imu_t_s)):
            events.append((rec.imu_t_s[i], 0, k_imu, "imu",
                           {"gyro_rad_s": _v(rec.gyro_rad_s[i]), "accel_m_s2": _v(rec.accel_m_s2[i])}))
    if rec.gnss is not None:
        g = rec.gnss
        k = keys.raw_gnss(vehicle)
        for i in range(len(g["t_s"])):
            events.append((g["t_s"][i], 2, k, "gnss", {
                "lat_deg": float(g["lat_deg"][i]), "lon_deg": float(g["lon_deg"][i]), "alt_m": float(g["alt_m"][i]),
                "pos_enu_m": _v(g["pos_enu_m"][i]), "vel_enu_m_s": _v(g["vel_enu_m_s"][i]),
                "course_rad": float(g["course_rad"][i]), "speed_m_s": float(g["speed_m_s"][i]),
                "fix_type": "3d", "num_sats": int(settings.assumed_num_sats), "pdop": float(settings.assumed_pdop),
                "horiz_std_m": float(settings.assumed_horiz_std_m)}))
    if rec.ins is not None:
        ins = rec.ins
        k = keys.raw_ins(vehicle)
        for i in range(len(ins["t_s"])):
            events.append((ins["t_s"][i], 2, k, "ins", {
                "pos_enu_m": _v(ins["pos_enu_m"][i]), "vel_enu_m_s": _v(ins["vel_enu_m_s"][i]),
                "heading_rad": float(maths.wrap_2pi(ins["heading_rad"][i]))}))
    if rec.truth_t_s is not None:
        k_pose = keys.truth(vehicle, "pose")
        k_field = keys.truth(vehicle, "field")
        k_src = keys.truth(vehicle, "sources")
        if rec.truth_quat is not None:
            heading, pitch, roll = euler_from_matrices(quat_to_matrices(rec.truth_quat))
        else:
            heading, pitch, roll = rec.truth_heading_rad, None, None
        for i in range(len(rec.truth_t_s)):
            t = rec.truth_t_s[i]
            pose = {"what": "pose", "heading_rad": float(maths.wrap_2pi(heading[i]))}
            if pitch is not None:
                pose.update(pitch_rad=float(pitch[i]), roll_rad=float(roll[i]))
            if rec.truth_pos_m is not None:
                pose["pos_enu_m"] = _v(rec.truth_pos_m[i])
            events.append((t, 3, k_pose, "truth", pose))
            if rec.field_earth_enu_nt is not None and rec.truth_quat is not None:
                b_body = quat_to_matrices(rec.truth_quat[i:i + 1])[0].T @ rec.field_earth_enu_nt
                events.append((t, 4, k_field, "truth", {"what": "field", "b_earth_nt": _v(b_body)}))
            if rec.disturbed is not None:
                d = bool(rec.disturbed[i])
                events.append((t, 5, k_src, "truth", {"what": "sources", "disturbed": d,
                                                      "active_sources": ["magnet"] if d else []}))
    events.sort(key=lambda e: (e[0], e[1]))
    for t, _, key, mtype, fields in events:
        yield float(t) + time_offset_s, key, mtype, fields
