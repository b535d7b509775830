"""A survey vehicle crossing a gridded anomaly map: true track, scalar magnetometer, drifting INS.

Pure numpy (never imports zenoh); deterministic for a seed. The vehicle's local ENU frame is the
map frame (metres). The vehicle flies a closed pattern of straight legs through waypoints at
constant speed, sampling every ``period_s``:

- true position/velocity/heading along the legs;
- total field F = |B_core| + ΔT(x, y) + noise: the core field from IGRF at the map's reference
  place (uniform over the map), the anomaly ΔT from the map's bicubic surface, Gaussian noise
  with σ = σ_map / SNR (the paper's definition of SNR); the co-located vector sensor reads
  (|B_core| + ΔT + noise) along the core-field direction, rotated into the body frame (level flight);
- INS: dead reckoning that starts ``ins_error0_m`` off and drifts by a constant velocity error
  plus a random walk (m/√s), so the INS increments between samples are nearly, not exactly, true.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magmesh import maths
from magmesh.geomap import GridMap, core_field_enu_nt, load_map


@dataclass(frozen=True)
class SurveySettings:
    map: str = "synthetic:7"  # map spec (magmesh.geomap.load_map)
    speed_m_s: float = 30.0  # ground speed (paper: 30 m/s)
    period_s: float = 5.0  # sample period (paper: 5 s)
    snr: float = 10.0  # σ_map / σ_noise
    laps: int = 1  # times around the pattern
    waypoints_frac: tuple = ((0.2, 0.2), (0.8, 0.55), (0.8, 0.85), (0.25, 0.8), (0.45, 0.45))  # of the map extent
    ins_error0_m: tuple = (1000.0, 500.0)  # initial INS position error E, N (paper: 10 × 5 cells)
    ins_drift_m_s: tuple = (0.25, -0.15)  # constant INS velocity error E, N
    ins_walk_m_sqrt_s: float = 0.5  # INS position random walk
    ins_heading_bias_deg: float = 0.0  # INS heading error: dead-reckoned track rotated clockwise by this
    lat_deg: float = 45.4  # reference place of the map for the core field (IGRF)
    lon_deg: float = -75.7
    alt_m: float = 300.0
    seed: int = 1

    def __post_init__(self):
        if not (self.speed_m_s > 0 and self.period_s > 0 and self.snr > 0):
            raise ValueError("speed_m_s, period_s and snr must be > 0")
        if len(self.waypoints_frac) < 2:
            raise ValueError("need at least two waypoints")


@dataclass
class SurveyRun:
    t_s: np.ndarray  # (n,)
    pos_m: np.ndarray  # (n, 2) true
    vel_m_s: np.ndarray  # (n, 2)
    heading_rad: np.ndarray  # (n,)
    ins_pos_m: np.ndarray  # (n, 2)
    anomaly_nt: np.ndarray  # (n,) true anomaly at the true position
    f_nt: np.ndarray  # (n,) scalar reading
    b_body_nt: np.ndarray  # (n, 3) vector reading, FLU body frame
    core_field_nt: float
    noise_nt: float


def _track(grid: GridMap, s: SurveySettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    nx, ny = grid.shape
    wp = np.array([[grid.x0_m + fx * (nx - 1) * grid.dx_m, grid.y0_m + fy * (ny - 1) * grid.dy_m]
                   for fx, fy in s.waypoints_frac])
    loop = np.vstack([wp, wp[:1]])
    seg = np.diff(loop, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1] * s.laps
    t = np.arange(0.0, total / s.speed_m_s, s.period_s)
    d = (t * s.speed_m_s) % cum[-1]
    k = np.clip(np.searchsorted(cum, d, side="right") - 1, 0, len(seg) - 1)
    u = seg[k] / seg_len[k, None]
    pos = loop[k] + u * (d - cum[k])[:, None]
    vel = u * s.speed_m_s
    heading = maths.wrap_2pi(np.arctan2(u[:, 0], u[:, 1]))  # clockwise from north
    return t, pos, vel, heading


def simulate(s: SurveySettings, grid: GridMap | None = None) -> SurveyRun:
    grid = grid if grid is not None else load_map(s.map)
    rng = np.random.default_rng(s.seed)
    t, pos, vel, heading = _track(grid, s)
    g = grid.to_grid(pos)
    anomaly = grid.cubic(g[:, 0], g[:, 1])
    noise_nt = grid.std_nt / s.snr
    b_core = core_field_enu_nt(s.lat_deg, s.lon_deg, s.alt_m)
    f_core = float(np.linalg.norm(b_core))
    f = f_core + anomaly + rng.normal(0.0, noise_nt, t.size)
    unit = b_core / f_core
    # level flight: v_body = Rz(yaw)ᵀ v_enu, yaw = π/2 − heading (maths.body_to_enu)
    yaw = maths.heading_to_yaw(heading)
    b_enu = unit[None, :] * f[:, None]
    b_body = np.stack([np.cos(yaw) * b_enu[:, 0] + np.sin(yaw) * b_enu[:, 1],
                       -np.sin(yaw) * b_enu[:, 0] + np.cos(yaw) * b_enu[:, 1], b_enu[:, 2]], axis=-1)
    dt = np.diff(t, prepend=t[0])
    walk = np.cumsum(rng.normal(0.0, 1.0, (t.size, 2)) * np.sqrt(dt)[:, None], axis=0) * s.ins_walk_m_sqrt_s
    b = math.radians(s.ins_heading_bias_deg)
    rot = np.array([[math.cos(b), math.sin(b)], [-math.sin(b), math.cos(b)]])  # clockwise by the bias
    dead_reckoned = pos[0] + (pos - pos[0]) @ rot.T
    ins = dead_reckoned + np.asarray(s.ins_error0_m, float) + np.outer(t - t[0], s.ins_drift_m_s) + walk
    return SurveyRun(t, pos, vel, heading, ins, anomaly, f, b_body, f_core, noise_nt)


def scale_check(s: SurveySettings) -> str:
    """One line describing the run (for logs)."""
    return (f"survey: {s.speed_m_s:g} m/s, sample every {s.period_s:g} s ({s.speed_m_s * s.period_s:g} m), "
            f"SNR {s.snr:g}, INS error {math.hypot(*s.ins_error0_m):.0f} m + drift {math.hypot(*s.ins_drift_m_s):.2f} m/s")
