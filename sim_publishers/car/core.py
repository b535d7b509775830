"""Car drive simulator: an urban route with a differential magnetic compass (DMC), IMU and GNSS.

Pure numpy (never imports zenoh). :func:`simulate` returns a :class:`CarDrive` of arrays;
:func:`iter_messages` turns it into ``(t_s, key, msg_type, fields)`` tuples in time order.

Model
-----
* Route: stationary start, a slow full-circle turn (``calib_turns`` turns, what a 2-D calibration
  needs), then urban streets: straights with acceleration/cruise/braking, stops at lights,
  ±90° turns. Generated on a fine time grid (``internal_rate_hz``) from speed v(t) and yaw rate
  r(t), integrated to heading and position, then interpolated to each sensor's sample times.
* Attitude: heading ψ from r; pitch θ = road grade + k_pitch · a_long (nose dives when braking);
  roll φ = road camber + k_roll · a_lat (body leans out of a turn). Body → ENU rotation
  ``R = Rz(π/2 − ψ) Ry(−θ) Rx(φ)`` (magmesh.maths conventions).
* Gyro (FLU): ω = Cᵀ Bᵀ e_z ẏ − Cᵀ e_y θ̇ + e_x φ̇ with A = Rz(yaw), B = Ry(−θ), C = Rx(φ)
  (from Rᵀ Ṙ = [ω]×), plus a constant bias, a bias random walk and white noise.
* Accelerometer: specific force f_b = Rᵀ (a_enu + [0, 0, g]) plus bias and white noise.
* Magnetometers: Earth field from IGRF at the origin and date (``maths.earth_field_enu_nt``) plus
  every interference source (point dipoles as in ``maths.dipole_field_nt``, line currents with
  ``maths.line_current_field_nt``), rotated into the body frame at each sensor's own position
  (sensor 1 at +baseline/2 along body x, sensor 2 at −baseline/2). Each sensor sees
  ``m = S C_kᵀ h + o + e(t) + n``: mounting rotation C_k (≤ 1°), soft iron S (I + small non-symmetric
  part), hard iron o (vehicle + sensor, a few 1000 nT), the car's switched electrical loads e(t)
  (hard-iron steps of ~60 nT) and white noise n, all different per sensor. The contract's
  calibration form is ``h = M (m − offset)`` with M = C_k S⁻¹ (:func:`true_mag_params`).
* GNSS: truth + Gauss–Markov position error (σ ``gnss_pos_std_m``, time constant
  ``gnss_pos_tau_s``) + white velocity noise. Under a steel bridge or viaduct the fix degrades
  (fewer satellites, higher PDOP, larger errors); in a tunnel it is lost (``fix_type = "none"``,
  last position held, zero velocity) and re-acquired a few seconds after the exit.
* Interference layouts (:data:`LAYOUTS`): steel bridges (deck girders under the road + truss
  walls), viaducts / tunnels (steel overhead along ~100 m, pillars, floor rebar, expansion joints),
  passing trucks (moving dipoles in the next lane), buried DC cables (line currents) and street
  clutter (manhole covers, parked cars). Each big source is placed on a given straight of the
  route, so every seed's route meets the same kinds of zone.

Determinism: the route, the noise and GNSS errors come from ``seed``; the sensors' hard/soft iron
from ``vehicle_seed`` (a property of the car, so a stored calibration stays valid across drives);
the moments of a layout's steel from the layout name. All through ``numpy.random.default_rng``.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from magmesh import maths
from schemas import keys

SENSORS = ("1", "2")


# ---- settings ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class CarSimSettings:
    """Settings of one simulated drive. Units are in the names."""

    seed: int = 1  # route, sensor noise, GNSS errors
    vehicle_seed: int = 7  # hard/soft iron of the two magnetometers (a property of the car)
    layout: str = "urban_a"  # interference layout, a key of LAYOUTS
    duration_s: float = 300.0
    mag_rate_hz: float = 50.0
    imu_rate_hz: float = 100.0
    gnss_rate_hz: float = 5.0
    truth_rate_hz: float = 10.0  # truth/pose, truth/field, truth/sources messages
    internal_rate_hz: float = 1000.0  # fine grid the trajectory is integrated on
    origin_lat_deg: float = 32.06  # Nanjing
    origin_lon_deg: float = 118.80
    origin_alt_m: float = 10.0
    date: str = "2026-06-01"  # IGRF epoch
    # route
    stationary_start_s: float = 3.0
    calib_turns: float = 1.25  # full turns of the initial circle (≥ 1)
    calib_speed_m_s: float = 3.0
    calib_radius_m: float = 8.0
    city_speed_min_m_s: float = 8.0
    city_speed_max_m_s: float = 14.0
    turn_speed_m_s: float = 4.5
    turn_radius_m: float = 10.0
    straight_min_m: float = 120.0
    straight_max_m: float = 280.0
    stop_probability: float = 0.35  # chance of a stop (traffic light) on a straight
    stop_min_s: float = 4.0
    stop_max_s: float = 15.0
    accel_m_s2: float = 1.5  # mean acceleration / braking
    grade_amplitude_rad: float = 0.015  # road grade
    camber_amplitude_rad: float = 0.01  # road camber / roughness roll
    pitch_per_accel_rad_per_m_s2: float = 0.006  # nose down when braking
    roll_per_accel_rad_per_m_s2: float = 0.008  # lean out of a turn
    # sensors
    baseline_m: float = 0.10  # distance between the two magnetometers along body x
    mount_height_m: float = 1.0  # magnetometers above the road surface
    mag_noise_nt: float = 30.0  # 1-σ white noise per axis
    hard_iron_max_nt: float = 3000.0  # |offset| components drawn up to this
    soft_iron_max: float = 0.10  # off-identity entries of S drawn up to ±this
    mount_misalignment_max_rad: float = math.radians(1.0)  # mounting yaw of each sensor up to ±this
    gyro_noise_rad_s: float = 0.0017  # 1-σ white noise per sample (≈ 0.1 °/s at 100 Hz)
    gyro_bias_max_rad_s: float = 0.01  # initial bias components drawn up to ±this
    gyro_bias_walk_rad_s_sqrt_s: float = 2e-4  # bias random walk
    electrical_step_nt: float = 60.0  # car's switched loads: hard-iron steps of about this size
    electrical_events_per_min: float = 1.0  # how often a load switches on (each lasts 5–60 s)
    clutter_per_km: float = 15.0  # manhole covers and parked cars along the streets (not in "clean")
    mag_resolution_nt: float = 0.0  # output quantisation step of the magnetometers (0 = none)
    car_loads: str = "steps"  # the car's own fields: "steps" (generic hard-iron steps) or "dipoles" (PAPER_STREETS)
    accel_noise_m_s2: float = 0.03
    accel_bias_max_m_s2: float = 0.08
    gnss_pos_std_m: float = 1.5  # 1-σ horizontal error per axis (open sky)
    gnss_pos_tau_s: float = 10.0  # correlation time of the position error
    gnss_alt_std_m: float = 3.0
    gnss_vel_std_m_s: float = 0.08
    gnss_reacquire_s: float = 3.0  # no fix for this long after leaving a tunnel
    # truth
    active_field_nt: float = 500.0  # a source is "active" when its field at the car exceeds this
    disturbed_heading_rad: float = math.radians(2.0)  # truth "disturbed" threshold (either compass)

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout {self.layout!r} is unknown; choose one of {', '.join(LAYOUTS)}")
        for name in ("duration_s", "mag_rate_hz", "imu_rate_hz", "gnss_rate_hz", "truth_rate_hz",
                     "internal_rate_hz", "calib_speed_m_s", "calib_radius_m", "city_speed_min_m_s",
                     "turn_speed_m_s", "turn_radius_m", "straight_min_m", "accel_m_s2", "baseline_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.calib_turns < 1.0:
            raise ValueError(f"calib_turns must be ≥ 1 (a full circle), got {self.calib_turns}")
        if self.city_speed_max_m_s < self.city_speed_min_m_s:
            raise ValueError("city_speed_max_m_s must be ≥ city_speed_min_m_s")
        if self.straight_max_m < self.straight_min_m:
            raise ValueError("straight_max_m must be ≥ straight_min_m")
        if max(self.mag_rate_hz, self.imu_rate_hz, self.gnss_rate_hz) > self.internal_rate_hz:
            raise ValueError("internal_rate_hz must be at least the highest sensor rate")
        if not 0 <= self.stop_probability <= 1:
            raise ValueError("stop_probability must be in [0, 1]")
        if self.car_loads not in ("steps", "dipoles"):
            raise ValueError(f"car_loads must be 'steps' or 'dipoles', got {self.car_loads!r}")
        if not self.mag_resolution_nt >= 0:
            raise ValueError(f"mag_resolution_nt must be ≥ 0, got {self.mag_resolution_nt!r}")


# ---- interference layouts ---------------------------------------------------------------------


@dataclass(frozen=True)
class SourceSpec:
    """One interference source of a layout, placed on straight ``straight`` of the street route
    (0 = the first straight after the calibration circle) at fraction ``frac`` of its length."""

    name: str
    kind: str  # bridge | viaduct | tunnel | truck | cable | deck | vehicle | plates | tram
    straight: int
    frac: float = 0.5
    strength: float = 1.0  # scales the moments / current
    length_m: float = 40.0  # along the road (bridge, viaduct, tunnel)
    lateral_m: float = 0.0  # centre offset, + to the left of the travel direction
    speed_m_s: float = 14.0  # truck: its own speed
    same_direction: bool = False  # truck: overtaking (True) or oncoming (False)
    stop_s: float = 0.0  # the car stops at the source's centre for this long (a red light)
    height_m: float = 5.5  # deck: height of its girders above the road (< 0: under the road, a bridge deck)
    pace: float = 0.15  # vehicle: its speed relative to the car's, as a fraction of the car's speed
    vehicle: str = "car"  # vehicle: "car" or "bus"
    leak: float = 0.2  # tram: share of the traction current that returns through the ground, not the rails


LAYOUTS: dict[str, tuple[SourceSpec, ...]] = {
    "clean": (),
    "urban_a": (
        SourceSpec("bridge_1", "bridge", straight=1, frac=0.5, length_m=40.0),
        SourceSpec("truck_1", "truck", straight=2, frac=0.55, speed_m_s=13.0),
        SourceSpec("tunnel_1", "tunnel", straight=3, frac=0.5, length_m=100.0),
        SourceSpec("viaduct_1", "viaduct", straight=5, frac=0.5, length_m=90.0),
    ),
    "urban_b": (
        SourceSpec("viaduct_1", "viaduct", straight=0, frac=0.55, length_m=110.0, strength=1.0, stop_s=8.0),
        SourceSpec("truck_1", "truck", straight=2, frac=0.5, speed_m_s=15.0, same_direction=True),
        SourceSpec("bridge_1", "bridge", straight=3, frac=0.4, length_m=60.0, strength=0.8),
        SourceSpec("cable_1", "cable", straight=4, frac=0.5, strength=1.0),
    ),
    "urban_c": (
        SourceSpec("cable_1", "cable", straight=0, frac=0.4, strength=0.7),
        SourceSpec("tunnel_1", "tunnel", straight=1, frac=0.5, length_m=120.0, strength=0.8),
        SourceSpec("truck_1", "truck", straight=2, frac=0.35, speed_m_s=12.0),
        SourceSpec("bridge_1", "bridge", straight=2, frac=0.75, length_m=35.0, strength=1.3, stop_s=5.0),
        SourceSpec("truck_2", "truck", straight=4, frac=0.5, speed_m_s=16.0, same_direction=True, strength=1.3),
    ),
    # "paper streets": the conditions of the DMC paper's road data (docs/methods.md#dmc) (see PAPER_STREETS and the README):
    # extended steel structures at metres (field nearly uniform over the 10 cm baseline), vehicles keeping
    # pace in the next lane and queueing beside the car, steel bridge decks with rebar and expansion joints
    "paper_a": (
        SourceSpec("elevated_1", "deck", straight=0, frac=0.55, length_m=120.0, height_m=5.5, stop_s=10.0),
        SourceSpec("bus_1", "vehicle", straight=1, frac=0.5, lateral_m=3.2, vehicle="bus", pace=0.12, stop_s=6.0),
        SourceSpec("bridge_1", "deck", straight=2, frac=0.5, length_m=60.0, height_m=-1.0),
        SourceSpec("car_1", "vehicle", straight=3, frac=0.4, lateral_m=2.4, vehicle="car", pace=0.2),
        SourceSpec("sidewall_1", "deck", straight=4, frac=0.5, length_m=100.0, height_m=4.0, lateral_m=-9.0),
        SourceSpec("roadworks_1", "plates", straight=5, frac=0.5, length_m=9.0),
        SourceSpec("bus_2", "vehicle", straight=6, frac=0.5, lateral_m=-2.2, vehicle="bus", pace=0.1, stop_s=8.0),
        SourceSpec("tram_1", "tram", straight=4, frac=0.5, length_m=240.0, lateral_m=3.4, height_m=5.8),
    ),
    "paper_b": (
        SourceSpec("bridge_1", "deck", straight=0, frac=0.5, length_m=80.0, height_m=-1.2, stop_s=6.0,
                   strength=1.2),
        SourceSpec("truck_1", "vehicle", straight=1, frac=0.45, lateral_m=-3.4, vehicle="bus", pace=0.08, stop_s=8.0),
        SourceSpec("elevated_1", "deck", straight=2, frac=0.5, length_m=100.0, height_m=6.5, strength=1.3),
        SourceSpec("cable_1", "cable", straight=3, frac=0.5, strength=0.8),
        SourceSpec("car_1", "vehicle", straight=4, frac=0.5, lateral_m=-2.6, vehicle="car", pace=0.25),
        SourceSpec("roadworks_1", "plates", straight=5, frac=0.4, length_m=6.0, stop_s=5.0),
        SourceSpec("elevated_2", "deck", straight=6, frac=0.5, length_m=120.0, height_m=5.5, lateral_m=1.5),
        SourceSpec("tram_1", "tram", straight=3, frac=0.5, length_m=240.0, lateral_m=0.0, height_m=5.8),
    ),
    "paper_c": (
        SourceSpec("sidewall_1", "deck", straight=0, frac=0.5, length_m=120.0, height_m=5.0, lateral_m=8.0,
                   stop_s=8.0),
        SourceSpec("elevated_1", "deck", straight=1, frac=0.5, length_m=90.0, height_m=5.0, strength=0.8),
        SourceSpec("bus_1", "vehicle", straight=2, frac=0.5, lateral_m=3.0, vehicle="bus", pace=0.15),
        SourceSpec("bridge_1", "deck", straight=3, frac=0.5, length_m=50.0, height_m=-0.9, strength=0.9),
        SourceSpec("car_1", "vehicle", straight=4, frac=0.45, lateral_m=2.3, vehicle="car", pace=0.1, stop_s=5.0),
        SourceSpec("bus_2", "vehicle", straight=5, frac=0.5, lateral_m=2.1, vehicle="bus", pace=0.06, stop_s=10.0),
        SourceSpec("roadworks_1", "plates", straight=6, frac=0.5, length_m=12.0),
        SourceSpec("tram_1", "tram", straight=0, frac=0.5, length_m=240.0, lateral_m=-3.6, height_m=5.8),
    ),
}

#: settings of the "paper streets" profile (use with a ``paper_*`` layout: :func:`paper_streets_settings`).
#: Sensor: Honeywell HMR3300 (datasheet: 8 Hz update in the magnetometer/heading modes, 16-bit ADC on the
#: HMC1021/HMC1022 bridges over ±2 gauss; output in units of ~0.1 mG = 10 nT, the resolution used here;
#: bridge noise 85 µgauss ≈ 8.5 nT (HMC1021/1022 datasheet, 10 Hz bandwidth)). Streets: slower, congested
#: traffic with more stops (exposure to a source grows as the speed falls), road grades of ±3 % (ramps of
#: elevated roads) and camber of ±0.9°, the car's own switched loads as dipoles in the body.
PAPER_STREETS: dict[str, Any] = {
    "mag_rate_hz": 8.0, "mag_noise_nt": 8.5, "mag_resolution_nt": 10.0, "truth_rate_hz": 8.0,
    "city_speed_min_m_s": 4.0, "city_speed_max_m_s": 12.0, "stop_probability": 0.5,
    "grade_amplitude_rad": 0.03, "camber_amplitude_rad": 0.015, "clutter_per_km": 25.0, "car_loads": "dipoles",
}
PAPER_LAYOUTS = ("paper_a", "paper_b", "paper_c")


def paper_streets_settings(layout: str = "paper_a", seed: int = 1, **overrides: Any) -> CarSimSettings:
    """CarSimSettings of the paper-streets profile (HMR3300 sensors, congested streets, the car's own loads)."""
    return CarSimSettings(**{**PAPER_STREETS, "layout": layout, "seed": seed, **overrides})


#: GNSS sky view under each kind of source: "blocked" (no fix) or "degraded"
_SKY = {"tunnel": "blocked", "bridge": "degraded", "viaduct": "degraded"}


def _dipoles_field_nt(moments_am2: np.ndarray, positions_m: np.ndarray, points_m: np.ndarray,
                      chunk: int = 4096) -> np.ndarray:
    """Summed field of K point dipoles at N points, nT (maths.dipole_field_nt, broadcast over K).

    B = μ0/4π · Σ_k (3 r̂_k (m_k·r̂_k) − m_k) / r_k³, r_k = point − position_k (≥ 5 cm)."""
    out = np.empty_like(points_m)
    for a in range(0, points_m.shape[0], chunk):
        r = points_m[a:a + chunk, None, :] - positions_m[None, :, :]  # (n, K, 3)
        d = np.maximum(np.sqrt(np.einsum("nki,nki->nk", r, r)), 0.05)
        rh = r / d[..., None]
        mr = np.einsum("nki,ki->nk", rh, moments_am2)
        b = (3.0 * rh * mr[..., None] - moments_am2[None, :, :]) / (d**3)[..., None]
        out[a:a + chunk] = b.sum(axis=1) * (maths.MU0_4PI * 1e9)
    return out


@dataclass
class Source:
    """A physical interference source placed in the local ENU frame."""

    name: str
    kind: str
    centre_enu_m: np.ndarray  # (3,) where it is (for a truck: where it passes the car)
    dipole_pos_m: np.ndarray  # (n, 3) static dipoles (trucks: offsets at t_pass)
    dipole_moment_am2: np.ndarray  # (n, 3)
    segments_m: np.ndarray  # (k, 2, 3) line-current segments
    current_a: float = 0.0
    velocity_enu_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))  # moving sources
    t_pass_s: float = 0.0  # truck: time it is beside the car
    radius_m: float = 60.0  # beyond this from its extent the field is neglected
    s_range_m: tuple[float, float] = (0.0, 0.0)  # along-route extent (static sources)
    sky: str = "open"  # GNSS sky view under it
    dipole_radius_m: float = math.inf  # static dipoles: field neglected beyond this distance
    body_track: Any = None  # vehicle beside the car: t_s (n,) → dipole positions (n, K, 3) in the car's body frame
    body_moment_am2: np.ndarray | None = None  # (K, 3) its moments in the car's body frame
    segment_weights: np.ndarray | None = None  # (k,) current of each segment as a multiple of the source's current
    current_of_t: Any = None  # t_s (n,) → current (n,), A: a time-varying current (tram); else current_a

    def field_body_nt(self, t_s: np.ndarray, point_body_m: np.ndarray) -> np.ndarray:
        """Field (N×3, nT, car body frame) of a vehicle beside the car at one body-frame point."""
        pos = self.body_track(np.asarray(t_s, float))
        out = np.zeros((pos.shape[0], 3))
        for k, m in enumerate(self.body_moment_am2):
            out += maths.dipole_field_nt(m, pos[:, k, :], point_body_m[None, :])
        return out

    def field_nt(self, t_s: np.ndarray, points_m: np.ndarray) -> np.ndarray:
        """Field of the source at points (N×3) at times t_s (N,), ENU, nT."""
        out = np.zeros_like(points_m)
        moving = bool(np.any(self.velocity_enu_m_s))
        if moving:
            for p, m in zip(self.dipole_pos_m, self.dipole_moment_am2, strict=True):
                pos = p[None, :] + (t_s - self.t_pass_s)[:, None] * self.velocity_enu_m_s[None, :]
                out += maths.dipole_field_nt(m, pos, points_m)
        elif math.isfinite(self.dipole_radius_m):
            for p, m in zip(self.dipole_pos_m, self.dipole_moment_am2, strict=True):
                near = np.flatnonzero(np.sum((points_m - p) ** 2, axis=1) < self.dipole_radius_m**2)
                out[near] += maths.dipole_field_nt(m, p, points_m[near])
        elif self.dipole_pos_m.size:
            out += _dipoles_field_nt(self.dipole_moment_am2, self.dipole_pos_m, points_m)
        weights = np.ones(len(self.segments_m)) if self.segment_weights is None else self.segment_weights
        if self.current_of_t is not None and len(self.segments_m):
            unit = np.zeros_like(points_m)
            for seg, w in zip(self.segments_m, weights, strict=True):
                unit += maths.line_current_field_nt(float(w), seg[0], seg[1], points_m)
            return out + unit * np.asarray(self.current_of_t(np.asarray(t_s, float)), float)[:, None]
        for seg, w in zip(self.segments_m, weights, strict=True):
            out += maths.line_current_field_nt(self.current_a * float(w), seg[0], seg[1], points_m)
        return out


# ---- output -----------------------------------------------------------------------------------


@dataclass
class MagParams:
    """Calibration parameters in the contract's form: h = M (m − offset), |h| ≈ field_radius_nt."""

    offset_nt: np.ndarray  # (3,)
    matrix: np.ndarray  # (3, 3)
    field_radius_nt: float

    def apply(self, m_nt: np.ndarray) -> np.ndarray:
        """Compensated field h (N×3) from raw samples m (N×3)."""
        return (np.asarray(m_nt, float) - self.offset_nt) @ self.matrix.T


@dataclass
class GnssEpochs:
    """GNSS output, one row per epoch (every field of the ``gnss`` message)."""

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    pos_enu_m: np.ndarray  # (N, 3)
    vel_enu_m_s: np.ndarray  # (N, 3)
    course_rad: np.ndarray
    speed_m_s: np.ndarray
    fix_type: np.ndarray  # (N,) str
    num_sats: np.ndarray  # (N,) int
    pdop: np.ndarray
    horiz_std_m: np.ndarray  # reported 1-σ per horizontal axis
    true_pos_enu_m: np.ndarray  # (N, 3) truth at the epochs, for error statistics


@dataclass
class CarTruth:
    """Ground truth at the magnetometer sample times."""

    heading_rad: np.ndarray
    pitch_rad: np.ndarray
    roll_rad: np.ndarray
    pos_enu_m: np.ndarray  # (N, 3) vehicle reference point (midway between the sensors)
    vel_enu_m_s: np.ndarray  # (N, 3)
    b_earth_body_nt: np.ndarray  # (N, 3) undisturbed Earth field in the body frame
    b_sensor_nt: dict[str, np.ndarray]  # true field at each sensor, body frame (before sensor errors)
    heading_error_rad: dict[str, np.ndarray]  # single-compass heading error from the true field
    source_names: tuple[str, ...]
    active: np.ndarray  # (N, n_sources) bool
    disturbed: np.ndarray  # (N,) bool: either compass's true-field heading error > threshold
    gyro_bias_rad_s: np.ndarray  # (N_imu, 3) true gyro bias at the IMU times
    hard_iron_change_nt: dict[str, np.ndarray] = field(default_factory=dict)  # car's switched loads, per sensor

    def active_names(self, i: int) -> list[str]:
        return [n for n, a in zip(self.source_names, self.active[i], strict=True) if a]


@dataclass
class CarDrive:
    """One simulated drive: sensor outputs and truth, all numpy arrays."""

    settings: CarSimSettings
    t_mag_s: np.ndarray
    mag_b_nt: dict[str, np.ndarray]  # sensor id → (N, 3) measured field, body frame
    t_imu_s: np.ndarray
    gyro_rad_s: np.ndarray  # (N_imu, 3)
    accel_m_s2: np.ndarray  # (N_imu, 3)
    gnss: GnssEpochs
    truth: CarTruth
    true_params: dict[str, MagParams]  # sensor id → the true compensation
    declination_rad: float
    earth_field_enu_nt: np.ndarray  # (3,)
    sensor_offsets_body_m: dict[str, np.ndarray]  # lever arm of each magnetometer, body frame
    sources: list[Source]
    calib_turn_t_s: tuple[float, float]  # start and end of the initial circle

    @property
    def duration_s(self) -> float:
        return float(self.settings.duration_s)


# ---- geodesy ----------------------------------------------------------------------------------


enu_to_geodetic = maths.enu_to_geodetic  # ENU (m) about the drive's origin → lat/lon/alt (WGS-84)


# ---- route ------------------------------------------------------------------------------------


def _speed_change(v0: float, v1: float, accel: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth speed change v0 → v1 (raised cosine, mean acceleration ``accel``); returns (v, r)."""
    if abs(v1 - v0) < 1e-9:
        return np.empty(0), np.empty(0)
    n = max(2, int(round(abs(v1 - v0) / accel / dt)))
    tau = (np.arange(n) + 0.5) / n
    v = v0 + (v1 - v0) * 0.5 * (1 - np.cos(math.pi * tau))
    return v, np.zeros(n)


def _cruise(v: float, dist_m: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    n = max(0, int(round(dist_m / max(v, 1e-6) / dt)))
    return np.full(n, v), np.zeros(n)


def _hold(duration_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    n = max(0, int(round(duration_s / dt)))
    return np.zeros(n), np.zeros(n)


def _turn(v: float, angle_rad: float, radius_m: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Turn by ``angle_rad`` (+ clockwise) at speed v: yaw rate sin² profile peaking at 2 v/R."""
    mean_rate = v / radius_m
    duration = abs(angle_rad) / mean_rate
    n = max(2, int(round(duration / dt)))
    tau = (np.arange(n) + 0.5) / n
    shape = np.sin(math.pi * tau) ** 2
    r = shape / shape.sum() * angle_rad / dt  # integrates exactly to angle_rad
    return np.full(n, v), r


def _circle(v: float, angle_rad: float, radius_m: float, ramp_s: float, dt: float):
    """Constant-radius circle with smooth yaw-rate ramps in and out; total turn ``angle_rad``."""
    rate = math.copysign(v / radius_m, angle_rad)
    n_ramp = max(2, int(round(ramp_s / dt)))
    tau = (np.arange(n_ramp) + 0.5) / n_ramp
    up = rate * 0.5 * (1 - np.cos(math.pi * tau))
    ramp_angle = 2 * up.sum() * dt
    n_flat = max(0, int(round((angle_rad - ramp_angle) / rate / dt)))
    flat = np.full(n_flat, rate)
    r = np.concatenate([up, flat, up[::-1]])
    r *= angle_rad / (r.sum() * dt)  # exact total angle
    return np.full(r.size, v), r


@dataclass
class _Plan:
    v: np.ndarray  # speed on the fine grid
    r: np.ndarray  # yaw rate (clockwise +) on the fine grid
    straights: list[tuple[int, int]]  # fine-grid index ranges of the straights
    stops: dict[int, tuple[float, float]]  # straight index → (fraction, seconds) of forced stops
    calib: tuple[int, int]


def _plan_route(s: CarSimSettings, specs: tuple[SourceSpec, ...], rng: np.random.Generator) -> _Plan:
    dt = 1.0 / s.internal_rate_hz
    vs: list[np.ndarray] = []
    rs: list[np.ndarray] = []
    n_total = 0

    def add(piece):
        nonlocal n_total
        vs.append(piece[0])
        rs.append(piece[1])
        n_total += piece[0].size

    add(_hold(s.stationary_start_s, dt))
    add(_speed_change(0.0, s.calib_speed_m_s, s.accel_m_s2 * 0.5, dt))
    c0 = n_total
    direction = 1.0 if rng.random() < 0.5 else -1.0
    add(_circle(s.calib_speed_m_s, direction * s.calib_turns * 2 * math.pi, s.calib_radius_m, 2.0, dt))
    calib = (c0, n_total)

    # minimum straight lengths and forced stops required by the layout
    need_len: dict[int, float] = {}
    forced: dict[int, tuple[float, float]] = {}
    for sp in specs:
        extent = sp.length_m if sp.kind in ("bridge", "viaduct", "tunnel", "deck", "plates") else 60.0
        lo = (extent / 2 + 50.0) / max(min(sp.frac, 1 - sp.frac), 0.1)
        need_len[sp.straight] = max(need_len.get(sp.straight, 0.0), lo)
        if sp.stop_s > 0:
            forced[sp.straight] = (sp.frac, sp.stop_s)

    v_in = s.calib_speed_m_s
    straights: list[tuple[int, int]] = []
    k = 0
    net_turn = 0
    n_end = int(math.ceil(s.duration_s / dt)) + 1
    while n_total < n_end:
        length = float(rng.uniform(s.straight_min_m, s.straight_max_m))
        length = max(length, need_len.get(k, 0.0))
        v_c = float(rng.uniform(s.city_speed_min_m_s, s.city_speed_max_m_s))
        stop = forced.get(k)
        if stop is None and rng.random() < s.stop_probability:
            stop = (float(rng.uniform(0.3, 0.9)), float(rng.uniform(s.stop_min_s, s.stop_max_s)))
        v_out = s.turn_speed_m_s
        # legs of the straight: [0, f L] and [f L, L] around a stop, else one leg
        legs = [(v_in, 0.0, stop[0] * length), (0.0, v_out, (1 - stop[0]) * length)] if stop else [
            (v_in, v_out, length)]
        s0 = n_total
        for i, (a, b, dist) in enumerate(legs):
            vc = v_c
            while True:  # lower the cruise speed until both speed changes fit in 80 % of the leg
                d1 = (a + vc) / 2 * abs(vc - a) / s.accel_m_s2
                d2 = (vc + b) / 2 * abs(vc - b) / s.accel_m_s2
                if d1 + d2 <= 0.8 * dist or vc <= max(a, b) + 0.1:
                    break
                vc *= 0.9
            vc = max(vc, max(a, b))
            add(_speed_change(a, vc, s.accel_m_s2, dt))
            add(_cruise(vc, max(dist - d1 - d2, 0.0), dt))
            add(_speed_change(vc, b, s.accel_m_s2, dt))
            if stop and i == 0:
                add(_hold(stop[1], dt))
        straights.append((s0, n_total))
        # staircase street pattern: the net turn stays within ±90° of the first street, so the
        # route never comes back across itself (or through a bridge's walls)
        if net_turn == 0:
            turn = 1 if rng.random() < 0.5 else -1
        else:
            turn = -net_turn
        net_turn += turn
        angle = math.radians(90.0) * turn
        add(_turn(v_out, angle, s.turn_radius_m, dt))
        v_in = v_out
        k += 1

    v = np.concatenate(vs)[:n_end]
    r = np.concatenate(rs)[:n_end]
    straights = [(a, min(b, n_end)) for a, b in straights if a < n_end]
    return _Plan(v, r, straights, forced, calib)


def _smooth_profile(rng: np.random.Generator, s_m: np.ndarray, amplitude: float) -> np.ndarray:
    """Smooth random function of distance: a few sinusoids of wavelength 15–400 m."""
    out = np.zeros_like(s_m)
    for wl in (400.0, 150.0, 60.0, 15.0):
        out += math.sqrt(wl / 400.0) * np.sin(2 * math.pi * s_m / wl + rng.uniform(0, 2 * math.pi))
    return amplitude * out / 2.0


@dataclass
class _Trajectory:
    t: np.ndarray
    heading: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    pos: np.ndarray  # (n, 3)
    vel: np.ndarray  # (n, 3)
    acc: np.ndarray  # (n, 3)
    omega: np.ndarray  # (n, 3) body rate, FLU
    dist: np.ndarray  # distance travelled


def _integrate(s: CarSimSettings, plan: _Plan, rng: np.random.Generator) -> _Trajectory:
    dt = 1.0 / s.internal_rate_hz
    n = plan.v.size
    t = np.arange(n) * dt
    v, r = plan.v, plan.r
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * dt)]) + rng.uniform(0, 2 * math.pi)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    grade = _smooth_profile(rng, dist, s.grade_amplitude_rad)
    camber = _smooth_profile(rng, dist, s.camber_amplitude_rad)
    a_long = np.gradient(v, dt)
    a_lat = -v * r  # FLU y (left): a right turn (r > 0) accelerates the car to the right
    pitch = grade + s.pitch_per_accel_rad_per_m_s2 * a_long
    roll = camber + s.roll_per_accel_rad_per_m_s2 * a_lat
    vh = v * np.cos(grade)
    vel = np.stack([vh * np.sin(heading), vh * np.cos(heading), v * np.sin(grade)], axis=1)
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, axis=0)])
    acc = np.gradient(vel, dt, axis=0)
    # body rates from Euler rates (module docstring): yaw = π/2 − ψ, so ẏ = −r
    yaw_rate = -np.gradient(np.unwrap(heading), dt)
    pitch_rate = np.gradient(pitch, dt)
    roll_rate = np.gradient(roll, dt)
    cth, sth = np.cos(pitch), np.sin(pitch)
    cph, sph = np.cos(roll), np.sin(roll)
    # Bᵀ e_z with B = Ry(−θ): (−sin θ... ) → Ry(−θ)ᵀ = Ry(θ); Ry(θ) e_z = (sin θ, 0, cos θ)
    # Cᵀ = Rx(−φ): (x, y, z) → (x, cos φ y + sin φ z, −sin φ y + cos φ z)
    wz_x, wz_y, wz_z = sth, sph * cth, cph * cth
    # Cᵀ e_y · (−θ̇): Rx(−φ) e_y = (0, cos φ, −sin φ)
    omega = np.stack(
        [
            wz_x * yaw_rate + roll_rate,
            wz_y * yaw_rate - cph * pitch_rate,
            wz_z * yaw_rate + sph * pitch_rate,
        ],
        axis=1,
    )
    return _Trajectory(t, maths.wrap_2pi(heading), pitch, roll, pos, vel, acc, omega, dist)


def _rotations(heading, pitch, roll) -> np.ndarray:
    """Body → ENU matrices (N×3×3), R = Rz(π/2 − ψ) Ry(−θ) Rx(φ)."""
    yaw = math.pi / 2 - np.asarray(heading)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    n = cy.size
    R = np.empty((n, 3, 3))
    # Rz(y) Ry(−p) Rx(r), Ry(−p) = [[cp, 0, −sp], [0, 1, 0], [sp, 0, cp]]
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = -sy * cr - cy * sp * sr
    R[:, 0, 2] = sy * sr - cy * sp * cr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = cy * cr - sy * sp * sr
    R[:, 1, 2] = -cy * sr - sy * sp * cr
    R[:, 2, 0] = sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


def _interp(t_new: np.ndarray, t: np.ndarray, y: np.ndarray) -> np.ndarray:
    if y.ndim == 1:
        return np.interp(t_new, t, y)
    return np.stack([np.interp(t_new, t, y[:, j]) for j in range(y.shape[1])], axis=1)


# ---- sources ----------------------------------------------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _steel_moments(rng, n: int, b_earth_enu: np.ndarray, m_am2: float) -> np.ndarray:
    """Moments of steel parts: induced (along the Earth field) plus a random remanent part."""
    induced = _unit(b_earth_enu)[None, :] * 0.7
    remanent = _unit(rng.normal(size=(n, 3))) * 0.7
    mag = m_am2 * rng.uniform(0.6, 1.4, size=(n, 1))
    return (induced + remanent) * mag


def _along(half_m: float, step_m: float) -> np.ndarray:
    return np.arange(-half_m, half_m + 1e-6, step_m)


def _grid(frame, xs, ys, zs) -> list[np.ndarray]:
    """Points at road-frame offsets (x along, y left, z above the road surface) from a source centre.

    The road surface follows the route's own altitude profile, so a girder 0.3 m under the road
    stays 0.3 m under the car wherever the road climbs."""
    centre, fwd, left, up, road_z = frame
    dz = road_z(np.asarray(xs, float)) - centre[2]
    return [centre + x * fwd + y * left + (dzx + z) * up for x, dzx in zip(xs, dz, strict=True) for y in ys
            for z in zs]


def _place_sources(s: CarSimSettings, specs, plan: _Plan, traj: _Trajectory, b_earth_enu) -> list[Source]:
    out: list[Source] = []
    h = s.mount_height_m
    for sp in specs:
        if sp.straight >= len(plan.straights):
            continue  # the drive ends before this straight
        i0, i1 = plan.straights[sp.straight]
        d0, d1 = traj.dist[i0], traj.dist[max(i1 - 1, i0)]
        s_c = d0 + sp.frac * (d1 - d0)
        ic = int(np.searchsorted(traj.dist, s_c))
        ic = min(ic, traj.dist.size - 1)
        psi = traj.heading[ic]
        fwd = np.array([math.sin(psi), math.cos(psi), 0.0])
        left = np.array([-math.cos(psi), math.sin(psi), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        road = traj.pos[ic] - h * up  # road surface under the car at the source centre
        centre = road + sp.lateral_m * left
        rng = np.random.default_rng(zlib.crc32(f"{s.layout}/{sp.name}".encode()))
        k = sp.strength
        segs = np.zeros((0, 2, 3))
        current = 0.0
        vel = np.zeros(3)
        t_pass = 0.0
        weights = current_of_t = None
        half = sp.length_m / 2
        if sp.kind == "tram":  # the line runs along the street: at most the straight, 10 m short of either end
            half = max(min(half, sp.frac * (d1 - d0) - 10.0, (1 - sp.frac) * (d1 - d0) - 10.0), 10.0)
        frame = (centre, fwd, left, up,
                 lambda x, s_c=s_c: np.interp(s_c + x, traj.dist, traj.pos[:, 2]) - h)
        if sp.kind == "bridge":
            # steel deck: cross-girders 0.3 m under the road every 1.5 m (3 dipoles across the
            # carriageway, one under the car's lane), truss walls at ±5 m from 0.5 to 5 m high
            groups = [(_grid(frame, _along(half, 1.5), (-3.0, 0.0, 3.0), (-0.3,)), 200.0),
                      (_grid(frame, _along(half, 5.0), (-5.0, 5.0), (0.5, 5.0)), 3000.0)]
        elif sp.kind == "viaduct":
            # elevated road overhead (two rows of steel beams 5.5 m up, every 3 m), pillars at ±6.5 m
            # every 30 m, and a steel expansion joint in the road surface at every pillar
            groups = [(_grid(frame, _along(half, 3.0), (-2.5, 2.5), (5.5,)), 5000.0),
                      (_grid(frame, _along(half, 30.0), (-6.5, 6.5), (1.0, 3.5)), 10000.0),
                      (_grid(frame, _along(half, 30.0), (-2.0, 0.0, 2.0), (-0.15,)), 60.0)]
        elif sp.kind == "tunnel":
            # steel roof ribs 4.5 m up every 3 m, wall ribs at ±5 m every 6 m, and a reinforced floor
            # slab (rebar mats every 1.5 m, 0.3 m under the road)
            groups = [(_grid(frame, _along(half, 3.0), (-2.5, 2.5), (4.5,)), 3500.0),
                      (_grid(frame, _along(half, 6.0), (-5.0, 5.0), (1.5,)), 2000.0),
                      (_grid(frame, _along(half, 1.5), (-1.0, 1.0), (-0.3,)), 70.0)]
        sky = _SKY.get(sp.kind, "open")
        body_track = body_moment = None
        if sp.kind == "plates":
            # roadworks: steel road plates (1.5 m × 3 m × 25 mm) laid over a trench on the car's lane, one every
            # 3 m over ``length_m``; each as 3 × 6 cells of 0.5 m, 20 A·m² per cell (magnetisation of order
            # 3·10³ A/m in 6 dm³ of mild steel): tens of µT one metre above, strongly non-uniform over 10 cm
            cells = _grid(frame, np.concatenate([x + np.arange(-1.25, 1.3, 0.5) for x in _along(half, 3.0)]),
                          (-0.5, 0.0, 0.5), (0.02,))
            pos = np.array(cells)
            mom = np.concatenate([_member_moments(rng, 18, b_earth_enu, 20.0 * k)
                                  for _ in range(len(cells) // 18)] + [np.zeros((len(cells) % 18, 3))])
            extent = half
        elif sp.kind == "deck":
            pos, mom, sky = _deck(frame, sp, half, rng, b_earth_enu)
            extent = half
        elif sp.kind == "vehicle":
            body_track, body_moment = _vehicle(sp, s_c, traj, rng, b_earth_enu, psi, h)
            pos, mom = np.zeros((0, 3)), np.zeros((0, 3))
            t_pass = float(np.interp(s_c, traj.dist, traj.t))
            extent = 30.0 / max(sp.pace, 0.02)
        elif sp.kind in ("bridge", "viaduct", "tunnel"):
            pos = np.array([p for pts, _ in groups for p in pts])
            mom = np.concatenate([_steel_moments(rng, len(pts), b_earth_enu, m * k) for pts, m in groups])
            extent = half
        elif sp.kind == "truck":
            # three dipoles along a 12 m truck in the next lane (left, 3.5 m), passing at t_pass
            t_pass = float(np.interp(s_c, traj.dist, traj.t))
            direction = 1.0 if sp.same_direction else -1.0
            lane = 3.5 * left + sp.lateral_m * left
            body = traj.pos[ic] + lane + (0.8 - h) * up
            pos = np.array([body + x * direction * fwd for x in (-5.0, 0.0, 5.0)])
            mom = _steel_moments(rng, 3, b_earth_enu, 4000.0 * k)
            truck_v = sp.speed_m_s * direction * fwd
            vel = truck_v
            centre = body
            extent = 8.0
        elif sp.kind == "tram":
            segs, weights, current_of_t = _tram(s, sp, frame, half)
            pos, mom = np.zeros((0, 3)), np.zeros((0, 3))
            extent = half
        elif sp.kind == "cable":
            # buried DC feeder crossing the road 1.5 m deep, 60 m long
            across = 30.0 * left
            segs = np.array([[road - 1.5 * up - across, road - 1.5 * up + across]])
            pos = np.zeros((0, 3))
            mom = np.zeros((0, 3))
            current = 150.0 * k
            extent = 2.0
        else:
            raise ValueError(f"unknown source kind {sp.kind!r} in layout {s.layout!r}")
        out.append(Source(
            name=sp.name, kind=sp.kind, centre_enu_m=centre, dipole_pos_m=pos, dipole_moment_am2=mom,
            segments_m=segs, current_a=current, velocity_enu_m_s=vel, t_pass_s=t_pass,
            radius_m=extent + 60.0, s_range_m=(s_c - extent, s_c + extent), sky=sky,
            body_track=body_track, body_moment_am2=body_moment, segment_weights=weights,
            current_of_t=current_of_t,
        ))
    return out


def _line(frame, x0: float, x1: float, y: float, z0: float, z1: float, step_m: float = 1.0) -> list[np.ndarray]:
    """Points every ``step_m`` along a straight steel member from (x0, y, z0) to (x1, y, z1) (road frame)."""
    n = max(2, int(round(max(abs(x1 - x0), abs(z1 - z0)) / step_m)) + 1)
    xs, zs = np.linspace(x0, x1, n), np.linspace(z0, z1, n)
    centre, fwd, left, up, road_z = frame
    dz = road_z(xs) - centre[2]
    return [centre + x * fwd + y * left + (d + z) * up for x, z, d in zip(xs, zs, dz, strict=True)]


def _member_moments(rng, n: int, b_earth_enu: np.ndarray, per_m_am2: float, step_m: float = 1.0) -> np.ndarray:
    """Moments of the n points of one steel member: induced (along the Earth field) plus a remanent part
    coherent along the member (one direction per member, ±20 % in size from point to point)."""
    remanent = _unit(rng.normal(size=3))
    mag = per_m_am2 * step_m * rng.uniform(0.8, 1.2, size=(n, 1))
    return (_unit(b_earth_enu)[None, :] * 0.7 + remanent[None, :] * 0.7) * mag


def _deck(frame, sp: SourceSpec, half: float, rng, b_earth_enu) -> tuple[np.ndarray, np.ndarray, str]:
    """An extended steel structure as lines of dipoles (1 m apart, like a continuous magnetised member).

    ``height_m`` > 0: an elevated road or overhead structure — four longitudinal girders at that height
    across ±4.5 m (1000 A·m² per m each: steel box girders) and pillars every 30 m at ±7 m (vertical members, 600 A·m² per m):
    at 4–6 m its field is several µT and nearly uniform over the 10 cm baseline. With ``lateral_m`` far
    from 0 it stands beside the road (an elevated road or steel wall alongside). ``height_m`` < 0: a steel
    bridge deck — four girders that far under the road (150 A·m² per m), truss walls at ±5.5 m (vertical
    members every 5 m and top chords at 5 m, 500 A·m² per m), rebar in the concrete slab (10 A·m² every
    1.5 m, 0.3 m under the road) and a steel expansion joint at each end (60 A·m² points at 0.15 m).
    Moments: the field of the structure at the car is calibrated to the paper's report that heading errors
    near such structures exceed 20–25° (a perpendicular field of 10–15 µT against ~34 µT horizontal)."""
    k = sp.strength
    members: list[tuple[list[np.ndarray], float, float]] = []  # (points, A·m² per m, spacing)
    if sp.height_m > 0:
        for y in (-4.5, -1.5, 1.5, 4.5):
            members.append((_line(frame, -half, half, y, sp.height_m, sp.height_m), 1000.0 * k, 1.0))
        # pillars: either side of an overhead deck; beside the road, under the structure (≥ 3.5 m from the car)
        pillar_y = (-7.0, 7.0) if abs(sp.lateral_m) < 6.0 else (-4.5, 4.5)
        for x in _along(half, 30.0):
            for y in pillar_y:
                members.append((_line(frame, x, x, y, 0.0, sp.height_m), 600.0 * k, 1.0))
        sky = "degraded" if abs(sp.lateral_m) < 6.0 else "open"
    else:
        for y in (-3.0, -1.0, 1.0, 3.0):
            members.append((_line(frame, -half, half, y, sp.height_m, sp.height_m), 150.0 * k, 1.0))
        for y in (-5.5, 5.5):
            members.append((_line(frame, -half, half, y, 5.0, 5.0), 500.0 * k, 1.0))
            for x in _along(half, 5.0):
                members.append((_line(frame, x, x, y, 0.0, 5.0), 500.0 * k, 1.0))
        members.append((_grid(frame, _along(half, 1.5), (-1.5, 0.0, 1.5), (-0.3,)), 10.0 * k, 1.0))
        members.append((_grid(frame, (-half, half), (-1.5, 0.0, 1.5), (-0.15,)), 60.0 * k, 1.0))
        sky = "degraded"
    pos = np.array([p for pts, _, _ in members for p in pts])
    mom = np.concatenate([_member_moments(rng, len(pts), b_earth_enu, per_m, step) for pts, per_m, step in members])
    return pos, mom, sky


#: a DC tram line: contact wire and running rails (standard gauge 1435 mm, rail heads 0.72 m either side of the
#: track centre). Traction supply 750 V DC (IEC 60850); a 30 m low-floor tram draws 400–700 A while it accelerates
#: (≈ 4 × 120 kW of motors) and feeds back about half of that while braking regeneratively; heating, ventilation and
#: auxiliaries of the trams in a feeding section draw some tens of A all the time.
TRAM_RAIL_HALF_GAUGE_M = 0.72
TRAM_BASE_A = (20.0, 80.0)  # auxiliaries, drawn per drive
TRAM_PEAK_A = (350.0, 650.0)  # a tram accelerating in the section
TRAM_STARTS_PER_MIN = 1.2  # trams starting from a stop in the feeding section (both directions)


def _tram_current(s: CarSimSettings, name: str):
    """Current of the feeding section, A, as a function of time: auxiliaries plus tram starts (ramp up in 2 s,
    hold 10–20 s while accelerating, fall in 5 s) and regenerative braking (−0.3…−0.5 of the peak for 8–12 s,
    20–60 s after the start). Seeded by the drive and the source (the trams run on their own timetable)."""
    rng = np.random.default_rng([s.seed, zlib.crc32(name.encode()), 0x7A])
    base = float(rng.uniform(*TRAM_BASE_A))
    n = int(rng.poisson(TRAM_STARTS_PER_MIN * (s.duration_s + 120.0) / 60.0))
    t0 = np.sort(rng.uniform(-60.0, s.duration_s + 60.0, n))
    peak = rng.uniform(*TRAM_PEAK_A, n)
    hold = rng.uniform(10.0, 20.0, n)
    brake_at = t0 + rng.uniform(20.0, 60.0, n)
    brake = -peak * rng.uniform(0.3, 0.5, n)
    brake_len = rng.uniform(8.0, 12.0, n)

    def trapezoid(t, a, rise, flat, fall):
        x = t[:, None] - a[None, :]
        up = np.clip(x / rise, 0.0, 1.0)
        down = np.clip(1.0 - (x - rise - flat[None, :]) / fall, 0.0, 1.0)
        return np.minimum(up, down) * (x >= 0)

    def current(t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, float)
        i = base + (trapezoid(t, t0, 2.0, hold, 5.0) * peak[None, :]).sum(axis=1)
        return i + (trapezoid(t, brake_at, 1.0, brake_len, 2.0) * brake[None, :]).sum(axis=1)

    return current


def _tram(s: CarSimSettings, sp: SourceSpec, frame, half: float):
    """A DC tram line along the street: the contact wire ``height_m`` above the track centre (``lateral_m`` from
    the car's lane; 0 = the car drives on the track), the current returning through the two rails at road level
    except ``leak`` of it, which returns through the ground far away. Line currents (Biot–Savart), so the field
    is perpendicular to the street and the same at two sensors lined up along it: a street running north–south
    turns the heading without changing the field strength much, one running east–west changes the strength."""
    wire = _line(frame, -half, half, sp.lateral_m, sp.height_m, sp.height_m, step_m=10.0)
    segs = [[a, b] for a, b in zip(wire[:-1], wire[1:], strict=True)]
    weights = [1.0] * len(segs)
    for dy in (-TRAM_RAIL_HALF_GAUGE_M, TRAM_RAIL_HALF_GAUGE_M):
        rail = _line(frame, -half, half, sp.lateral_m + dy, 0.0, 0.0, step_m=10.0)
        segs += [[a, b] for a, b in zip(rail[:-1], rail[1:], strict=True)]
        weights += [-(1.0 - sp.leak) / 2.0] * (len(rail) - 1)
    return np.array(segs), np.array(weights) * sp.strength, _tram_current(s, f"{s.layout}/{sp.name}")


def _vehicle(sp: SourceSpec, s_c: float, traj: _Trajectory, rng, b_earth_enu, psi: float, h: float):
    """A vehicle in the next lane keeping pace with the car: beside it when the car is at ``s_c``, drifting
    along it at ``pace`` × the car's speed (so it queues beside the car at a stop). Dipoles in the car's
    body frame: a car as two (engine, rear axle: 150 A·m² each), a bus or truck as four 1500 A·m² along
    its 11 m (vehicle detection literature models cars and trucks as magnetic dipoles of this order)."""
    if sp.vehicle == "bus":
        xs, m0, z = np.array([-4.5, -1.5, 1.5, 4.5]), 1500.0, 0.9
    else:
        xs, m0, z = np.array([-1.2, 1.2]), 150.0, 0.5
    mom_enu = _steel_moments(rng, len(xs), b_earth_enu, m0 * sp.strength)
    # moments fixed in the vehicle, which heads as the car does: take them in the car's body frame at the zone
    R0 = _rotations(np.array([psi]), np.array([0.0]), np.array([0.0]))[0]
    mom_body = mom_enu @ R0  # Rᵀ m per row
    t_grid, d_grid = traj.t, traj.dist

    def track(t_s: np.ndarray) -> np.ndarray:
        x = sp.pace * (np.interp(t_s, t_grid, d_grid) - s_c)
        pos = np.empty((t_s.size, len(xs), 3))
        pos[:, :, 0] = x[:, None] + xs[None, :]
        pos[:, :, 1] = sp.lateral_m
        pos[:, :, 2] = z - h
        return pos

    return track, mom_body


def _relevant(src: Source, t: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Samples close enough to the source to evaluate its field."""
    if np.any(src.velocity_enu_m_s):
        return np.abs(t - src.t_pass_s) < 10.0
    if src.kind == "clutter":
        return np.ones(t.size, bool)
    d = np.linalg.norm(pos[:, :2] - src.centre_enu_m[None, :2], axis=1)
    return d < src.radius_m


def _place_clutter(s: CarSimSettings, plan: _Plan, traj: _Trajectory, b_earth_enu,
                   sources: list[Source]) -> Source | None:
    """Small street clutter along the street part of the route (not the calibration circle):
    manhole covers / drain grates under the lane and parked cars at the kerb (right side)."""
    if s.clutter_per_km <= 0 or not plan.straights:
        return None
    rng = np.random.default_rng([s.seed, 0xC1])
    s0 = traj.dist[plan.straights[0][0]]
    s1 = traj.dist[-1]
    n = int(rng.poisson(s.clutter_per_km * (s1 - s0) / 1000.0))
    if n == 0:
        return None
    where = np.sort(rng.uniform(s0, s1, size=n))
    for src in sources:  # none inside the big zones (their own steel dominates there)
        if src.kind in ("bridge", "viaduct", "tunnel", "cable", "deck", "plates"):
            where = where[(where < src.s_range_m[0] - 20.0) | (where > src.s_range_m[1] + 20.0)]
    n = where.size
    if n == 0:
        return None
    i = np.minimum(np.searchsorted(traj.dist, where), traj.dist.size - 1)
    psi = traj.heading[i]
    left = np.stack([-np.cos(psi), np.sin(psi), np.zeros(n)], axis=1)
    road = traj.pos[i] - np.array([0.0, 0.0, s.mount_height_m])
    parked = rng.random(n) < 0.5
    lateral = np.where(parked, -rng.uniform(2.5, 3.5, n), rng.uniform(-1.5, 1.5, n))
    height = np.where(parked, 0.5, -0.1)
    pos = road + lateral[:, None] * left + height[:, None] * np.array([0.0, 0.0, 1.0])
    size = np.where(parked, rng.uniform(80.0, 250.0, n), rng.uniform(2.0, 10.0, n))
    mom = (_unit(b_earth_enu)[None, :] * 0.7 + _unit(rng.normal(size=(n, 3))) * 0.7) * size[:, None]
    return Source(name="clutter", kind="clutter", centre_enu_m=pos.mean(axis=0), dipole_pos_m=pos,
                  dipole_moment_am2=mom, segments_m=np.zeros((0, 2, 3)), radius_m=math.inf,
                  s_range_m=(float(s0), float(s1)), dipole_radius_m=25.0)


def _electrical_offsets(s: CarSimSettings, t: np.ndarray) -> dict[str, np.ndarray]:
    """The car's own switched loads (fans, wipers, compressor clutch, lights): hard-iron steps that
    come and go, seen differently by the two sensors (different distances to the wiring)."""
    out = {sid: np.zeros((t.size, 3)) for sid in SENSORS}
    if s.electrical_step_nt <= 0 or s.electrical_events_per_min <= 0:
        return out
    rng = np.random.default_rng([s.seed, 0xE1])
    n = int(rng.poisson(s.electrical_events_per_min * s.duration_s / 60.0))
    for _ in range(n):
        t_on = rng.uniform(0.0, s.duration_s)
        t_off = t_on + rng.uniform(5.0, 60.0)
        v = _unit(rng.normal(size=3)) * s.electrical_step_nt * rng.uniform(0.5, 1.5)
        on = (t >= t_on) & (t < t_off)
        for sid in SENSORS:
            out[sid][on] += v * rng.uniform(0.6, 1.4)
    return out


#: the car's own switched loads as dipoles in the body frame (x forward, y left, z up, m from the midpoint
#: of the two sensors; moments A·m²): position, moment size, and what switches it. A small DC motor with
#: its ferrite magnet and a wiring loop of a few A have moments of 0.01–0.5 A·m²; the sizes give
#: 50–400 nT at the nearer sensor (the dipole formula), unequal at the two sensors 10 cm apart.
CAR_LOADS = (
    ("blower_fan", (0.45, 0.25, -0.30), 0.30, "on_off"),  # HVAC blower behind the dashboard
    ("wiper_motor", (0.95, -0.20, -0.35), 0.40, "wipers"),  # front cowl: runs in showers, current pulses per sweep
    ("indicator_relay", (0.15, 0.12, -0.10), 0.01, "indicator"),  # flasher 1.5 Hz near sensor 1, while turning
    ("alternator_cable", (1.40, -0.30, -0.40), 1.50, "engine"),  # charging current: engine speed and the loads
)


def _car_load_fields(s: CarSimSettings, t: np.ndarray, traj: _Trajectory, lever: dict,
                     calib_end_s: float) -> dict[str, np.ndarray]:
    """Field of the car's own loads at each sensor (body frame, nT) over the magnetometer epochs.

    Fan: on/off periods of 30–180 s. Wipers: one shower per drive with probability 0.5 (60–200 s), the motor
    current pulsing with each 0.75 Hz sweep. Indicator: a 1.5 Hz square wave from 3 s before to the end of
    every street turn. Alternator cable: a moment following engine speed (∝ car speed) and the load of fan
    and wipers, relative to its value during the initial calibration circle (where the calibration absorbed it)."""
    rng = np.random.default_rng([s.seed, 0xCA7])
    mrng = np.random.default_rng([s.vehicle_seed, 0xCA7])  # directions: a property of the car
    n = t.size
    fan = np.zeros(n)
    t_on = rng.uniform(0.0, 60.0)
    while t_on < s.duration_s:
        t_off = t_on + rng.uniform(30.0, 180.0)
        fan[(t >= t_on) & (t < t_off)] = 1.0
        t_on = t_off + rng.uniform(30.0, 240.0)
    wipers = np.zeros(n)
    if rng.random() < 0.5:
        w0 = rng.uniform(0.0, max(s.duration_s - 60.0, 1.0))
        on = (t >= w0) & (t < w0 + rng.uniform(60.0, 200.0))
        wipers[on] = 0.5 * (1.0 - np.cos(2 * math.pi * 0.75 * (t[on] - w0)))
    yaw_rate = np.abs(np.interp(t, traj.t, traj.omega[:, 2]))
    # street turns only (the initial circle is the calibration manoeuvre), with a 3 s lead before each
    turning = (yaw_rate > 0.08) & (t > calib_end_s)
    ahead = np.interp(t + 3.0, t, turning.astype(float), right=0.0) > 0
    indicator = np.where(turning | ahead, (np.floor(t * 3.0) % 2 == 0).astype(float), 0.0)
    speed = np.interp(t, traj.t, np.linalg.norm(traj.vel, axis=1))
    engine = 0.2 + 0.5 * np.clip(speed / 14.0, 0, 1) + 0.15 * fan + 0.15 * wipers
    out = {sid: np.zeros((n, 3)) for sid in SENSORS}
    switch = {"on_off": fan, "wipers": wipers, "indicator": indicator, "engine": engine}
    for _name, where, size, what in CAR_LOADS:
        m = _unit(mrng.normal(size=3)) * size
        a = switch[what]
        if what == "engine":  # the calibration absorbed its level on the circle (3 m/s, no other load)
            a = a - (0.2 + 0.5 * 3.0 / 14.0)
        p = np.asarray(where, float)
        for sid in SENSORS:
            out[sid] += a[:, None] * maths.dipole_field_nt(m, p, lever[sid])[None, :]
    return out


# ---- sensors ----------------------------------------------------------------------------------


def mount_rotations(s: CarSimSettings) -> dict[str, np.ndarray]:
    """Sensor → body rotation C_k of each magnetometer's mounting (yaw up to ±``mount_misalignment_max_rad``,
    pitch and roll up to half that), drawn from ``vehicle_seed``."""
    rng = np.random.default_rng([s.vehicle_seed, 0xA1])
    out = {}
    for sid in SENSORS:
        yaw, pitch, roll = rng.uniform(-1, 1, size=3) * s.mount_misalignment_max_rad * np.array([1.0, 0.5, 0.5])
        out[sid] = maths.rot_z(yaw) @ maths.rot_y(pitch) @ maths.rot_x(roll)
    return out


def true_mag_params(s: CarSimSettings, field_radius_nt: float) -> dict[str, MagParams]:
    """The true compensation of each magnetometer for ``vehicle_seed`` (h = M (m − offset)).

    Sensor model ``m = S_k C_kᵀ h + o_k``: C_k the mounting rotation (:func:`mount_rotations`), S_k the
    soft iron (scale, non-orthogonality, induced vehicle field), o_k the hard iron. So M = C_k S_k⁻¹:
    the body-frame field. A symmetric (ellipse/ellipsoid) fit cannot see C_k; what remains of it is the
    static heading offset between the compasses (the paper's Δh_r)."""
    rng = np.random.default_rng([s.vehicle_seed, 0xCA11])
    vehicle_hard = rng.uniform(-1, 1, size=3) * s.hard_iron_max_nt * 0.7
    mounts = mount_rotations(s)
    out = {}
    for sid in SENSORS:
        offset = vehicle_hard + rng.uniform(-1, 1, size=3) * s.hard_iron_max_nt * 0.3
        S = np.eye(3) + rng.uniform(-1, 1, size=(3, 3)) * s.soft_iron_max * np.array(
            [[1.0, 0.3, 0.3], [0.3, 1.0, 0.3], [0.3, 0.3, 1.0]])
        out[sid] = MagParams(offset_nt=offset, matrix=mounts[sid] @ np.linalg.inv(S), field_radius_nt=field_radius_nt)
    return out


def _gnss(s: CarSimSettings, traj: _Trajectory, sources: list[Source], rng) -> GnssEpochs:
    t = np.arange(0.0, s.duration_s + 1e-9, 1.0 / s.gnss_rate_hz)
    n = t.size
    pos = _interp(t, traj.t, traj.pos)
    vel = _interp(t, traj.t, traj.vel)
    # sky view per epoch
    sky = np.zeros(n, dtype=np.int8)  # 0 open, 1 degraded, 2 blocked
    for src in sources:
        if src.sky == "open":
            continue
        d = np.linalg.norm(pos[:, :2] - src.centre_enu_m[None, :2], axis=1)
        half = (src.s_range_m[1] - src.s_range_m[0]) / 2
        inside = d < half + 3.0
        sky = np.maximum(sky, np.where(inside, 2 if src.sky == "blocked" else 1, 0).astype(np.int8))
    # re-acquisition delay after a blocked sky
    blocked = sky == 2
    if blocked.any():
        hold_n = int(round(s.gnss_reacquire_s * s.gnss_rate_hz))
        ends = np.flatnonzero(blocked[:-1] & ~blocked[1:]) + 1
        for e in ends:
            blocked[e:e + hold_n] = True
    # Gauss–Markov position error, σ and τ as set; inflated under degraded sky
    phi = math.exp(-1.0 / (s.gnss_rate_hz * s.gnss_pos_tau_s))
    q = math.sqrt(1 - phi * phi)
    w = rng.normal(size=(n, 3)) * q
    err = np.empty((n, 3))
    err[0] = rng.normal(size=3)
    for i in range(1, n):  # first-order recursion (n ≈ 1500): cheap
        err[i] = phi * err[i - 1] + w[i]
    scale = np.array([s.gnss_pos_std_m, s.gnss_pos_std_m, s.gnss_alt_std_m])
    degrade = np.where(sky == 1, 3.0, 1.0)[:, None]
    multipath = rng.normal(size=(n, 3)) * 0.2 * scale * (degrade - 1.0)
    pos_meas = pos + err * scale * degrade + multipath
    vel_meas = vel + rng.normal(size=(n, 3)) * s.gnss_vel_std_m_s * degrade * np.array([1, 1, 2])
    # satellites and DOP: slowly varying in open sky, fewer under steel
    base_sats = np.clip(np.round(12 + 2.5 * np.sin(2 * math.pi * t / 180 + rng.uniform(0, 6.3))
                                 + rng.normal(size=n) * 0.4), 8, 18).astype(int)
    num_sats = np.where(sky == 1, np.maximum(base_sats - 6, 4), base_sats)
    pdop = 1.0 + 8.0 / num_sats + np.abs(rng.normal(size=n)) * 0.1
    fix = np.where(sky == 1, "2d", "3d").astype(object)
    horiz_std = s.gnss_pos_std_m * degrade[:, 0] * pdop / 1.7
    # lost fix: hold the last position, zero velocity, no satellites
    if blocked.any():
        last = 0
        for i in range(n):
            if blocked[i]:
                pos_meas[i] = pos_meas[last] if last != i else pos_meas[i]
                vel_meas[i] = 0.0
            else:
                last = i
        num_sats = np.where(blocked, rng.integers(0, 4, size=n), num_sats)
        pdop = np.where(blocked, 99.0, pdop)
        fix = np.where(blocked, "none", fix).astype(object)
        horiz_std = np.where(blocked, 100.0, horiz_std)
    speed = np.hypot(vel_meas[:, 0], vel_meas[:, 1])
    course = maths.wrap_2pi(np.arctan2(vel_meas[:, 0], vel_meas[:, 1]))
    # like a receiver's heading-of-motion hold: below 0.5 m/s the last course is kept (0 before any motion)
    moving = speed >= 0.5
    last = np.maximum.accumulate(np.where(moving, np.arange(n), -1))
    course = np.where(last >= 0, course[np.maximum(last, 0)], 0.0)
    lat, lon, alt = enu_to_geodetic(pos_meas, s.origin_lat_deg, s.origin_lon_deg, s.origin_alt_m)
    return GnssEpochs(t, lat, lon, alt, pos_meas, vel_meas, course, speed, fix.astype(str),
                      num_sats.astype(int), pdop, horiz_std, pos)


# ---- simulate ---------------------------------------------------------------------------------


def simulate(settings: CarSimSettings | None = None, **overrides: Any) -> CarDrive:
    """Simulate one drive. ``simulate(CarSimSettings(seed=3))`` or ``simulate(seed=3)``."""
    s = settings or CarSimSettings()
    if overrides:
        s = replace(s, **overrides)
    rng = np.random.default_rng([s.seed, 0xCA12])
    specs = LAYOUTS[s.layout]
    b_earth = np.array(maths.earth_field_enu_nt(s.origin_lat_deg, s.origin_lon_deg, s.origin_alt_m, s.date))
    decl = maths.declination_rad(b_earth)
    radius = float(np.linalg.norm(b_earth))

    plan = _plan_route(s, specs, rng)
    traj = _integrate(s, plan, rng)
    sources = _place_sources(s, specs, plan, traj, b_earth)
    clutter = _place_clutter(s, plan, traj, b_earth, sources) if s.layout != "clean" else None
    if clutter is not None:
        sources.append(clutter)

    # magnetometer epochs
    t_mag = np.arange(0.0, s.duration_s + 1e-9, 1.0 / s.mag_rate_hz)
    t_mag = t_mag[t_mag <= traj.t[-1]]
    hd = np.unwrap(traj.heading)
    heading = maths.wrap_2pi(np.interp(t_mag, traj.t, hd))
    pitch = np.interp(t_mag, traj.t, traj.pitch)
    roll = np.interp(t_mag, traj.t, traj.roll)
    pos = _interp(t_mag, traj.t, traj.pos)
    vel = _interp(t_mag, traj.t, traj.vel)
    R = _rotations(heading, pitch, roll)  # body → ENU
    b_earth_body = np.einsum("nji,j->ni", R, b_earth)
    lever = {"1": np.array([s.baseline_m / 2, 0, 0]), "2": np.array([-s.baseline_m / 2, 0, 0])}
    n = t_mag.size
    active = np.zeros((n, len(sources)), bool)
    b_true: dict[str, np.ndarray] = {}
    b_src_enu = {sid: np.zeros((n, 3)) for sid in SENSORS}
    sensor_pos = {sid: pos + np.einsum("nij,j->ni", R, lever[sid]) for sid in SENSORS}
    for j, src in enumerate(sources):
        if src.body_track is not None:  # a vehicle beside the car: its dipoles are given in the body frame
            idx = np.flatnonzero(np.min(np.abs(src.body_track(t_mag)[:, :, 0]), axis=1) < 30.0)
        else:
            idx = np.flatnonzero(_relevant(src, t_mag, pos))
        if idx.size == 0:
            continue
        for sid in SENSORS:
            if src.body_track is not None:
                f = np.einsum("nij,nj->ni", R[idx], src.field_body_nt(t_mag[idx], lever[sid]))
            else:
                f = src.field_nt(t_mag[idx], sensor_pos[sid][idx])
            b_src_enu[sid][idx] += f
            if sid == "1":
                active[idx, j] = np.linalg.norm(f, axis=1) > s.active_field_nt
    params = true_mag_params(s, radius)
    if s.car_loads == "dipoles":
        loads_body = _car_load_fields(s, t_mag, traj, lever, plan.calib[1] / s.internal_rate_hz)
        electrical = {sid: loads_body[sid] @ np.linalg.inv(params[sid].matrix).T for sid in SENSORS}
    else:
        electrical = _electrical_offsets(s, t_mag)
    mag_b: dict[str, np.ndarray] = {}
    herr: dict[str, np.ndarray] = {}
    # levelling: Ry(−θ) Rx(φ) = _rotations with yaw 0, i.e. heading π/2 (maths.tilt_compensated_heading)
    Rlevel = _rotations(np.full(n, math.pi / 2), pitch, roll)
    for sid in SENSORS:
        h = np.einsum("nji,nj->ni", R, b_earth[None, :] + b_src_enu[sid])
        b_true[sid] = h
        S = np.linalg.inv(params[sid].matrix)
        mag_b[sid] = (h @ S.T + params[sid].offset_nt + electrical[sid]
                      + rng.normal(size=(n, 3)) * s.mag_noise_nt)
        if s.mag_resolution_nt > 0:  # the sensor's output unit
            mag_b[sid] = np.round(mag_b[sid] / s.mag_resolution_nt) * s.mag_resolution_nt
        lev = np.einsum("nij,nj->ni", Rlevel, h)
        h_mag = maths.mag_heading_flu(lev[:, 0], lev[:, 1], decl)
        herr[sid] = maths.angle_diff(h_mag, heading)
    disturbed = (np.abs(herr["1"]) > s.disturbed_heading_rad) | (np.abs(herr["2"]) > s.disturbed_heading_rad)

    # IMU
    t_imu = np.arange(0.0, s.duration_s + 1e-9, 1.0 / s.imu_rate_hz)
    t_imu = t_imu[t_imu <= traj.t[-1]]
    ni = t_imu.size
    hi = maths.wrap_2pi(np.interp(t_imu, traj.t, hd))
    Ri = _rotations(hi, np.interp(t_imu, traj.t, traj.pitch), np.interp(t_imu, traj.t, traj.roll))
    omega = _interp(t_imu, traj.t, traj.omega)
    acc = _interp(t_imu, traj.t, traj.acc)
    f_body = np.einsum("nji,nj->ni", Ri, acc + np.array([0.0, 0.0, maths.G0]))
    bias0 = rng.uniform(-1, 1, size=3) * s.gyro_bias_max_rad_s
    walk = np.cumsum(rng.normal(size=(ni, 3)) * s.gyro_bias_walk_rad_s_sqrt_s * math.sqrt(1.0 / s.imu_rate_hz),
                     axis=0)
    gyro_bias = bias0 + walk
    gyro = omega + gyro_bias + rng.normal(size=(ni, 3)) * s.gyro_noise_rad_s
    accel = f_body + rng.uniform(-1, 1, size=3) * s.accel_bias_max_m_s2 + rng.normal(size=(ni, 3)) * s.accel_noise_m_s2

    gnss = _gnss(s, traj, sources, rng)
    dt = 1.0 / s.internal_rate_hz
    truth = CarTruth(
        heading_rad=heading, pitch_rad=pitch, roll_rad=roll, pos_enu_m=pos, vel_enu_m_s=vel,
        b_earth_body_nt=b_earth_body, b_sensor_nt=b_true, heading_error_rad=herr,
        source_names=tuple(src.name for src in sources), active=active, disturbed=disturbed,
        gyro_bias_rad_s=gyro_bias, hard_iron_change_nt=electrical,
    )
    return CarDrive(
        settings=s, t_mag_s=t_mag, mag_b_nt=mag_b, t_imu_s=t_imu, gyro_rad_s=gyro, accel_m_s2=accel,
        gnss=gnss, truth=truth, true_params=params, declination_rad=decl, earth_field_enu_nt=b_earth,
        sensor_offsets_body_m=lever, sources=sources,
        calib_turn_t_s=(plan.calib[0] * dt, plan.calib[1] * dt),
    )


# ---- messages ---------------------------------------------------------------------------------

# order of streams at equal times: magnetometers, IMU, GNSS, truth
_STREAM_ORDER = ("mag1", "mag2", "imu", "gnss", "pose", "field", "sources")


def _floats(row) -> list[float]:
    return [float(x) for x in row]


def iter_messages(drive: CarDrive, vehicle: str, t_offset_s: float = 0.0,
                  truth: bool = True) -> Iterator[tuple[float, str, str, dict]]:
    """Yield ``(t_s, key, msg_type, fields)`` in time order for every output of the drive.

    Keys: raw/mag/1, raw/mag/2, raw/imu, raw/gnss and (if ``truth``) truth/pose, truth/field,
    truth/sources at ``truth_rate_hz`` (sampled from the magnetometer epochs). ``t_offset_s`` is
    added to every time (a looping publisher continues its clock). Fields exclude the header
    (type, version, vehicle, t_s, seq): the publisher adds those.
    """
    s = drive.settings
    k_mag = {sid: keys.raw_mag(vehicle, sid) for sid in SENSORS}
    k_imu, k_gnss = keys.raw_imu(vehicle), keys.raw_gnss(vehicle)
    k_pose, k_field, k_src = keys.truth(vehicle, "pose"), keys.truth(vehicle, "field"), keys.truth(vehicle, "sources")
    tr = drive.truth
    g = drive.gnss
    step = max(1, int(round(s.mag_rate_hz / s.truth_rate_hz)))
    i_truth = np.arange(0, drive.t_mag_s.size, step)

    streams = [
        (drive.t_mag_s, 0), (drive.t_mag_s, 1), (drive.t_imu_s, 2), (g.t_s, 3),
    ]
    if truth:
        streams += [(drive.t_mag_s[i_truth], 4), (drive.t_mag_s[i_truth], 5), (drive.t_mag_s[i_truth], 6)]
    t_all = np.concatenate([t for t, _ in streams])
    code = np.concatenate([np.full(t.size, c, dtype=np.int8) for t, c in streams])
    idx = np.concatenate([np.arange(t.size) for t, _ in streams])
    order = np.lexsort((code, t_all))  # by time, then stream order

    mag_rows = {sid: drive.mag_b_nt[sid].tolist() for sid in SENSORS}
    gyro, accel = drive.gyro_rad_s.tolist(), drive.accel_m_s2.tolist()
    b_true = np.concatenate([tr.b_sensor_nt[sid] for sid in SENSORS], axis=1)
    for o in order:
        c, i = int(code[o]), int(idx[o])
        t = float(t_all[o]) + t_offset_s
        if c <= 1:
            sid = SENSORS[c]
            yield t, k_mag[sid], "mag", {"sensor": sid, "b_nt": mag_rows[sid][i]}
        elif c == 2:
            yield t, k_imu, "imu", {"gyro_rad_s": gyro[i], "accel_m_s2": accel[i]}
        elif c == 3:
            yield t, k_gnss, "gnss", {
                "lat_deg": float(g.lat_deg[i]), "lon_deg": float(g.lon_deg[i]), "alt_m": float(g.alt_m[i]),
                "pos_enu_m": _floats(g.pos_enu_m[i]), "vel_enu_m_s": _floats(g.vel_enu_m_s[i]),
                "course_rad": float(g.course_rad[i]), "speed_m_s": float(g.speed_m_s[i]),
                "fix_type": str(g.fix_type[i]), "num_sats": int(g.num_sats[i]), "pdop": float(g.pdop[i]),
                "horiz_std_m": float(g.horiz_std_m[i]),
            }
        else:
            j = int(i_truth[i])
            if c == 4:
                yield t, k_pose, "truth", {
                    "what": "pose", "heading_rad": float(tr.heading_rad[j]), "pitch_rad": float(tr.pitch_rad[j]),
                    "roll_rad": float(tr.roll_rad[j]), "pos_enu_m": _floats(tr.pos_enu_m[j]),
                    "vel_enu_m_s": _floats(tr.vel_enu_m_s[j]),
                }
            elif c == 5:
                yield t, k_field, "truth", {
                    "what": "field", "b_earth_nt": _floats(tr.b_earth_body_nt[j]), "b_sensor_nt": _floats(b_true[j]),
                }
            else:
                yield t, k_src, "truth", {
                    "what": "sources", "active_sources": tr.active_names(j), "disturbed": bool(tr.disturbed[j]),
                }
