"""Shared maths: angles, headings, rotations and quaternions, Earth field, dipoles.

The one place for numerics used by more than one core. numpy only; never imports zenoh.

Conventions (also in schemas/messages.py): navigation frame ENU, body frame FLU (x forward, y left,
z up). Heading ψ is clockwise from true north. Yaw (the ENU rotation angle about up, counter-clockwise
from east) is ``π/2 − ψ``. Pitch θ is positive nose up, roll φ positive right side down.
Body → ENU rotation: ``R = Rz(yaw) · Ry(−θ) · Rx(φ)``. Quaternions are ``[w, x, y, z]``, Hamilton
product, and rotate body vectors into ENU: ``v_enu = q ⊗ v_body ⊗ q*``.
"""

from __future__ import annotations

import datetime as _dt
import math
from functools import lru_cache

import numpy as np

TWO_PI = 2.0 * math.pi
MU0_4PI = 1e-7  # μ0 / 4π, T·m/A
G0 = 9.80665  # standard gravity, m/s²


# ---- angles -----------------------------------------------------------------------------------


def wrap_pi(a):
    """Wrap angle(s) to [−π, π)."""
    return (np.asarray(a) + math.pi) % TWO_PI - math.pi


def wrap_2pi(a):
    """Wrap angle(s) to [0, 2π)."""
    return np.asarray(a) % TWO_PI


def angle_diff(a, b):
    """Smallest signed difference a − b, in [−π, π)."""
    return wrap_pi(np.asarray(a) - np.asarray(b))


def heading_to_yaw(heading):
    return wrap_pi(math.pi / 2 - np.asarray(heading))


def yaw_to_heading(yaw):
    return wrap_2pi(math.pi / 2 - np.asarray(yaw))


def mag_heading_flu(bx, by, declination_rad: float = 0.0):
    """Heading from the horizontal body-frame field of a level FLU sensor.

    For a level vehicle with heading ψ and horizontal field of declination D:
    b_x = B_h cos(ψ − D), b_y = B_h sin(ψ − D), so ψ = atan2(b_y, b_x) + D.
    """
    return wrap_2pi(np.arctan2(by, bx) + declination_rad)


def tilt_compensated_heading(b_body, accel_body, declination_rad: float = 0.0):
    """Heading from a body-frame field levelled with the accelerometer's roll and pitch (FLU)."""
    b = np.asarray(b_body, float)
    roll, pitch = roll_pitch_from_accel(accel_body)
    # undo roll then pitch: b_level = Ry(−θ) Rx(φ) b
    R = rot_y(-pitch) @ rot_x(roll)
    bl = R @ b if b.ndim == 1 else b @ R.T
    return mag_heading_flu(bl[..., 0], bl[..., 1], declination_rad)


def roll_pitch_from_accel(accel_body):
    """Roll φ and pitch θ of a static FLU body from specific force (≈ +g up at rest)."""
    a = np.asarray(accel_body, float)
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    pitch = np.arctan2(ax, np.hypot(ay, az))  # nose up → specific force has +x component
    roll = np.arctan2(ay, az)
    return roll, pitch


# ---- rotations --------------------------------------------------------------------------------


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def body_to_enu(heading: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation matrix R with v_enu = R v_body."""
    return rot_z(math.pi / 2 - heading) @ rot_y(-pitch) @ rot_x(roll)


def euler_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """(heading, pitch, roll) from a body → ENU rotation matrix."""
    # R = Rz(yaw) Ry(-θ) Rx(φ): R[2,0] = sin θ, R[2,1] = cos θ sin φ, R[2,2] = cos θ cos φ
    pitch = math.asin(max(-1.0, min(1.0, R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return float(yaw_to_heading(yaw)), pitch, roll


# ---- quaternions ([w, x, y, z], body → ENU) ---------------------------------------------------


def quat_mul(p, q) -> np.ndarray:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quat_conj(q) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_normalize(q) -> np.ndarray:
    q = np.asarray(q, float)
    n = np.linalg.norm(q)
    q = q / n if n > 0 else np.array([1.0, 0, 0, 0])
    return q if q[0] >= 0 else -q


def quat_to_matrix(q) -> np.ndarray:
    w, x, y, z = quat_normalize(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, float)
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    return quat_normalize(q)


def quat_from_euler(heading: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    return quat_from_matrix(body_to_enu(heading, pitch, roll))


def euler_from_quat(q) -> tuple[float, float, float]:
    """(heading, pitch, roll) of a body → ENU quaternion."""
    return euler_from_matrix(quat_to_matrix(q))


def quat_rotate(q, v) -> np.ndarray:
    """Rotate body vector(s) v (…×3) into ENU."""
    return np.asarray(v, float) @ quat_to_matrix(q).T


def quat_from_rotvec(rv) -> np.ndarray:
    rv = np.asarray(rv, float)
    a = float(np.linalg.norm(rv))
    if a < 1e-12:
        return quat_normalize([1.0, *(0.5 * rv)])
    s = math.sin(a / 2) / a
    return np.array([math.cos(a / 2), rv[0] * s, rv[1] * s, rv[2] * s])


def heading_of_quat_array(q: np.ndarray) -> np.ndarray:
    """Headings (rad, clockwise from north) of an N×4 array of body → ENU quaternions (FLU body)."""
    q = np.asarray(q, float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r00 = 1 - 2 * (y * y + z * z)
    r10 = 2 * (x * y + w * z)
    return yaw_to_heading(np.arctan2(r10, r00))


# ---- Earth field and sources ------------------------------------------------------------------


@lru_cache(maxsize=256)
def earth_field_enu_nt(lat_deg: float, lon_deg: float, alt_m: float = 0.0, date: str = "2026-06-01") -> tuple:
    """IGRF main field at a place and date, ENU, nT (ppigrf)."""
    import ppigrf

    d = _dt.datetime.fromisoformat(date)
    be, bn, bu = ppigrf.igrf(lon_deg, lat_deg, alt_m / 1000.0, d)
    return (float(np.ravel(be)[0]), float(np.ravel(bn)[0]), float(np.ravel(bu)[0]))


def declination_rad(b_enu) -> float:
    """Magnetic declination (east positive) of an ENU field."""
    return math.atan2(b_enu[0], b_enu[1])


def dipole_field_nt(moment_am2, source_pos_m, points_m) -> np.ndarray:
    """Field of a point dipole at points (…×3), nT. B = μ0/4π · (3 r̂ (m·r̂) − m) / r³."""
    m = np.asarray(moment_am2, float)
    r = np.asarray(points_m, float) - np.asarray(source_pos_m, float)
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    d = np.maximum(d, 0.05)
    rh = r / d
    b_t = MU0_4PI * (3 * rh * np.sum(rh * m, axis=-1, keepdims=True) - m) / d**3
    return b_t * 1e9


def line_current_field_nt(current_a: float, p0_m, p1_m, points_m) -> np.ndarray:
    """Field of a finite straight current segment p0 → p1 at points (…×3), nT (Biot–Savart)."""
    p0 = np.asarray(p0_m, float)
    p1 = np.asarray(p1_m, float)
    P = np.asarray(points_m, float)
    L = p1 - p0
    ll = np.linalg.norm(L)
    u = L / ll
    r0 = P - p0
    r1 = P - p1
    perp = r0 - np.sum(r0 * u, axis=-1, keepdims=True) * u
    d = np.maximum(np.linalg.norm(perp, axis=-1, keepdims=True), 0.05)
    cos1 = np.sum(r0 * u, axis=-1, keepdims=True) / np.maximum(np.linalg.norm(r0, axis=-1, keepdims=True), 1e-9)
    cos2 = np.sum(r1 * u, axis=-1, keepdims=True) / np.maximum(np.linalg.norm(r1, axis=-1, keepdims=True), 1e-9)
    mag = MU0_4PI * current_a / d * (cos1 - cos2)
    direction = np.cross(u, perp / d)
    return mag * direction * 1e9


# ---- local tangent plane ----------------------------------------------------------------------

WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3


def enu_to_geodetic(pos_enu_m, lat0_deg: float, lon0_deg: float, alt0_m: float = 0.0):
    """Local tangent-plane ENU (m) about an origin → (lat_deg, lon_deg, alt_m), with the WGS-84 radii of
    curvature at the origin (centimetres over a few km)."""
    p = np.asarray(pos_enu_m, float)
    lat0 = math.radians(lat0_deg)
    s2 = math.sin(lat0) ** 2
    r_n = WGS84_A_M / math.sqrt(1 - WGS84_E2 * s2)  # prime vertical
    r_m = r_n * (1 - WGS84_E2) / (1 - WGS84_E2 * s2)  # meridian
    lat = lat0_deg + np.degrees(p[..., 1] / r_m)
    lon = lon0_deg + np.degrees(p[..., 0] / (r_n * math.cos(lat0)))
    return lat, lon, alt0_m + p[..., 2]
