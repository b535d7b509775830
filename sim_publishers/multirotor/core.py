"""Multirotor flying a planned line A → B in mission mode, with a magnetometer that can be disturbed.

Pure numpy; never imports zenoh. :func:`simulate` returns every stream as arrays, seeded.

The model follows He, Luo, Wu (seed paper 003, §2):

* horizontal dynamics of a multirotor at constant height (eq. 1–3):
  ṗ_h = v_h,  v̇_h = horizontal part of the thrust (g · R e3 / (R e3)_z) + linear drag − c_d (v_h − w);
* the position controller commands a horizontal acceleration and turns it into roll/pitch set points with
  the *estimated* heading ψ̂ (eq. 4); the airframe has the true heading ψ, so a heading error Δψ = ψ̂ − ψ
  rotates the acceleration actually produced by Δψ (eq. 5) and the track drifts off the line;
* the flight controller's heading ψ̂ comes from a complementary filter that integrates the gyro and follows
  the tilt-compensated magnetometer heading ψ_m with gain k: dψ̂/dt = ω + k (ψ_m − ψ̂), with a gyro-bias
  integrator (the structure of PX4's attitude_estimator_q);
* the yaw controller holds ψ̂ on the route's course, so a magnetometer disturbance physically turns the
  airframe;
* a disturbance on one body axis of the magnetometer: a step, a fast ramp (+0.06 G/s), a slow ramp
  (+0.0125 G/s) (paper §5), in an Earth field of ≈ 0.6 G.

Besides the paper's ingredients the simulation has the error sources that make magnetic-heading
monitoring hard in practice: gyro bias random walk, roll/pitch estimation error (it enters the
tilt compensation), throttle-dependent motor field, a hard-iron residual, white noise and rare short
magnetometer glitches (bursts from power electronics), Gauss–Markov wind gusts, RTK GNSS noise.

Frames: ENU navigation frame with origin at the take-off point, body FLU; heading clockwise from north.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from magmesh.maths import G0

GAUSS_NT = 1.0e5  # 1 G = 100 000 nT

DISTURBANCES = ("none", "step", "fast_ramp", "slow_ramp", "ramp")
#: ramp rates of the paper's flight tests (§5), G/s
PAPER_RAMP_G_S = {"fast_ramp": 0.06, "slow_ramp": 0.0125}


@dataclass(frozen=True)
class MultirotorSettings:
    """Flight, sensor and disturbance parameters (units in the names)."""

    seed: int = 1
    duration_s: float = 150.0
    dt_s: float = 0.02  # dynamics, IMU, magnetometer and attitude rate (50 Hz)
    # mission: the line A → B (local ENU, m), flown at cruise speed and constant height
    a_enu_m: tuple = (0.0, 0.0, 20.0)
    b_enu_m: tuple = (0.0, 1000.0, 20.0)  # due north (sensor Y axis then points west: the paper's case)
    cruise_speed_m_s: float = 6.0
    start_offset_m: float = 0.0  # lateral start offset from the line, m (0: start on it)
    # airframe and controllers
    drag_per_s: float = 0.35  # linear drag coefficient c_d, 1/s
    attitude_tau_s: float = 0.12  # roll/pitch follow their set points with this time constant
    max_tilt_deg: float = 30.0
    pos_gain_per_s: float = 0.5  # cross-track position → velocity set point (mission line following)
    vel_gain_per_s: float = 1.2  # velocity error → acceleration command
    vel_int_per_s2: float = 0.3  # velocity-error integrator (learns drag and wind)
    yaw_gain_per_s: float = 1.5  # heading error → yaw rate command
    max_yaw_rate_deg_s: float = 45.0
    # wind: mean + first-order Gauss–Markov gusts (light wind, ≤ force 4 as in the paper)
    wind_mean_m_s: float = 2.0
    wind_dir_deg: float = 60.0  # direction the wind blows towards, clockwise from north
    gust_std_m_s: float = 0.6
    gust_tau_s: float = 4.0
    # Earth field (paper §5: total ≈ 0.6 G)
    earth_field_nt: float = 60000.0
    inclination_deg: float = 45.0
    declination_deg: float = -3.0
    # magnetometer errors
    mag_noise_nt: float = 120.0  # white, per axis, 1-σ
    hard_iron_residual_nt: tuple = (150.0, -100.0, 80.0)
    motor_field_nt_per_m_s2: float = 60.0  # field per m/s² of thrust above hover, body axes (0.3, 0.2, 1)
    glitch_rate_per_s: float = 1.0 / 40.0  # rare bursts (power electronics, radio)
    glitch_duration_s: float = 0.2
    glitch_amplitude_nt: float = 9000.0
    # flight-controller estimation errors
    gyro_noise_rad_s: float = 0.003
    gyro_bias_walk_rad_s_sqrt_s: float = 0.0002
    gyro_bias_init_rad_s: float = 0.005
    tilt_error_std_deg: float = 0.4  # roll/pitch estimate error (Gauss–Markov)
    tilt_error_tau_s: float = 3.0
    mag_gain_per_s: float = 1.0  # complementary filter: heading follows the magnetometer heading, k
    bias_gain_per_s2: float = 0.02  # complementary filter gyro-bias integrator
    # GNSS (RTK fixed, centimetre noise)
    gnss_rate_hz: float = 10.0
    gnss_noise_m: float = 0.015
    gnss_vel_noise_m_s: float = 0.02
    gnss_vert_noise_m: float = 0.03
    origin_lat_deg: float = 28.2  # Changsha (the paper's site)
    origin_lon_deg: float = 112.9
    origin_alt_m: float = 60.0
    # magnetic disturbance on one body axis of the magnetometer
    disturbance: str = "none"
    onset_s: float = 60.0
    ramp_rate_g_s: float = 0.0  # 0: the paper's rate for fast_ramp/slow_ramp
    step_g: float = 0.2  # step size (disturbance = "step")
    disturbance_axis: str = "y"
    disturbance_sign: float = 1.0
    disturbance_max_g: float = 0.5  # ramp stops growing here
    disturbance_hold_s: float = 0.0  # after reaching its peak, hold then remove (0: stay until the end)

    def __post_init__(self) -> None:
        if self.disturbance not in DISTURBANCES:
            raise ValueError(f"disturbance must be one of {', '.join(DISTURBANCES)}, got {self.disturbance!r}")
        if self.disturbance_axis not in ("x", "y", "z"):
            raise ValueError(f"disturbance_axis must be x, y or z, got {self.disturbance_axis!r}")
        if not (0 < self.dt_s <= 0.1):
            raise ValueError(f"dt_s must be in (0, 0.1] s, got {self.dt_s}")
        if not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")
        if not (0 < self.gnss_rate_hz <= 1.0 / self.dt_s):
            raise ValueError(f"gnss_rate_hz must be in (0, {1.0 / self.dt_s:g}] Hz, got {self.gnss_rate_hz}")
        if math.dist(self.a_enu_m[:2], self.b_enu_m[:2]) < 1.0:
            raise ValueError("the route A → B must be at least 1 m long")
        if not self.cruise_speed_m_s > 0:
            raise ValueError(f"cruise_speed_m_s must be > 0, got {self.cruise_speed_m_s}")

    @property
    def ramp_g_s(self) -> float:
        if self.ramp_rate_g_s > 0:
            return self.ramp_rate_g_s
        return PAPER_RAMP_G_S.get(self.disturbance, 0.0)

    def replace(self, **changes) -> MultirotorSettings:
        vals = {f.name: getattr(self, f.name) for f in fields(self)}
        vals.update(changes)
        return MultirotorSettings(**vals)


def disturbance_g(s: MultirotorSettings, t_s: np.ndarray) -> np.ndarray:
    """Disturbance amplitude (G) on the chosen magnetometer axis at times t_s."""
    t = np.asarray(t_s, float)
    out = np.zeros_like(t)
    if s.disturbance == "none":
        return out
    dt = t - s.onset_s
    if s.disturbance == "step":
        out = np.where(dt >= 0, s.step_g, 0.0)
        t_peak = 0.0
    else:
        out = np.clip(dt * s.ramp_g_s, 0.0, s.disturbance_max_g)
        t_peak = s.disturbance_max_g / s.ramp_g_s if s.ramp_g_s > 0 else math.inf
    if s.disturbance_hold_s > 0:
        out = np.where(dt > t_peak + s.disturbance_hold_s, 0.0, out)
    return out * s.disturbance_sign


def earth_field_enu(s: MultirotorSettings) -> np.ndarray:
    inc, dec = math.radians(s.inclination_deg), math.radians(s.declination_deg)
    h = s.earth_field_nt * math.cos(inc)
    return np.array([h * math.sin(dec), h * math.cos(dec), -s.earth_field_nt * math.sin(inc)])


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float, std: float, dims: int) -> np.ndarray:
    """First-order Gauss–Markov process x_{k+1} = a x_k + sqrt(1 − a²) σ w_k, stationary from the start."""
    if std <= 0:
        return np.zeros((n, dims))
    a = math.exp(-dt / tau)
    w = rng.standard_normal((n, dims)) * std * math.sqrt(1 - a * a)
    x = np.empty((n, dims))
    x[0] = rng.standard_normal(dims) * std
    for k in range(1, n):
        x[k] = a * x[k - 1] + w[k]
    return x


def _glitches(rng: np.random.Generator, s: MultirotorSettings, n: int) -> np.ndarray:
    out = np.zeros((n, 3))
    if s.glitch_rate_per_s <= 0 or s.glitch_amplitude_nt <= 0:
        return out
    count = rng.poisson(s.glitch_rate_per_s * n * s.dt_s)
    width = max(1, int(round(s.glitch_duration_s / s.dt_s)))
    for _ in range(count):
        k0 = int(rng.integers(0, n))
        v = rng.standard_normal(3)
        v *= s.glitch_amplitude_nt * rng.uniform(0.5, 1.0) / np.linalg.norm(v)
        out[k0:k0 + width] += v
    return out


@dataclass
class Flight:
    """Every stream of one simulated flight (arrays over the sample index, times in s)."""

    settings: MultirotorSettings
    t_s: np.ndarray  # N, dynamics / IMU / magnetometer / attitude samples
    pos_enu_m: np.ndarray  # N×3 true position
    vel_enu_m_s: np.ndarray  # N×3 true velocity
    heading_rad: np.ndarray  # N true heading
    pitch_rad: np.ndarray
    roll_rad: np.ndarray
    gyro_rad_s: np.ndarray  # N×3 measured
    accel_m_s2: np.ndarray  # N×3 measured specific force
    mag_nt: np.ndarray  # N×3 measured field, body FLU
    b_earth_body_nt: np.ndarray  # N×3 undisturbed Earth field in the body frame
    disturbance_nt: np.ndarray  # N×3 disturbance added to the magnetometer, body frame
    att_heading_rad: np.ndarray  # N flight controller's heading ψ̂ (complementary filter)
    att_pitch_rad: np.ndarray
    att_roll_rad: np.ndarray
    mag_heading_rad: np.ndarray  # N tilt-compensated magnetometer heading ψ_m used by the filter
    gnss_idx: np.ndarray  # M indices into t_s of the GNSS epochs
    gnss_pos_enu_m: np.ndarray  # M×3 measured
    gnss_vel_enu_m_s: np.ndarray  # M×3 measured
    wind_enu_m_s: np.ndarray  # N×2

    @property
    def gnss_t_s(self) -> np.ndarray:
        return self.t_s[self.gnss_idx]

    @property
    def route(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.settings.a_enu_m, float), np.asarray(self.settings.b_enu_m, float)

    def true_cross_track_m(self) -> np.ndarray:
        a, b = self.route
        return cross_track_signed(self.pos_enu_m[:, :2], a[:2], b[:2])


def cross_track_signed(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed horizontal distance from the line A → B (positive left of the direction of travel), m.

    |d| = |(X − A) × (B − A)| / |B − A| (paper eq. 6).
    """
    u = (b - a) / np.linalg.norm(b - a)
    r = np.asarray(p, float) - a
    return u[0] * r[..., 1] - u[1] * r[..., 0]


def simulate(s: MultirotorSettings) -> Flight:
    """Fly the mission once; seeded by ``s.seed``."""
    rng = np.random.default_rng(s.seed)
    dt = s.dt_s
    n = int(round(s.duration_s / dt)) + 1
    t = np.arange(n) * dt

    a = np.asarray(s.a_enu_m, float)
    b = np.asarray(s.b_enu_m, float)
    seg = b[:2] - a[:2]
    length = float(np.linalg.norm(seg))
    u = seg / length
    left = np.array([-u[1], u[0]])
    course = math.atan2(u[0], u[1])  # clockwise from north

    # exogenous processes, drawn up front so that the random stream does not depend on the control path
    wd = math.radians(s.wind_dir_deg)
    wind = np.array([math.sin(wd), math.cos(wd)]) * s.wind_mean_m_s + _gauss_markov(
        rng, n, dt, s.gust_tau_s, s.gust_std_m_s, 2)
    tilt_err = np.radians(_gauss_markov(rng, n, dt, s.tilt_error_tau_s, s.tilt_error_std_deg, 2))
    gyro_bias = s.gyro_bias_init_rad_s * rng.standard_normal(3) + np.cumsum(
        rng.standard_normal((n, 3)) * s.gyro_bias_walk_rad_s_sqrt_s * math.sqrt(dt), axis=0)
    gyro_noise = rng.standard_normal((n, 3)) * s.gyro_noise_rad_s
    mag_noise = rng.standard_normal((n, 3)) * s.mag_noise_nt + _glitches(rng, s, n)
    accel_noise = rng.standard_normal((n, 3)) * 0.05
    dist = np.zeros((n, 3))
    dist[:, "xyz".index(s.disturbance_axis)] = disturbance_g(s, t) * GAUSS_NT
    b_enu = earth_field_enu(s)
    hard_iron = np.asarray(s.hard_iron_residual_nt, float)
    motor_dir = np.array([0.3, 0.2, 1.0])
    decl = math.radians(s.declination_deg)

    gnss_step = max(1, int(round(1.0 / (s.gnss_rate_hz * dt))))
    gnss_idx = np.arange(0, n, gnss_step)
    gnss_pos_noise = rng.standard_normal((len(gnss_idx), 3)) * [s.gnss_noise_m, s.gnss_noise_m, s.gnss_vert_noise_m]
    gnss_vel_noise = rng.standard_normal((len(gnss_idx), 3)) * s.gnss_vel_noise_m_s

    # the loop runs on Python floats (small numpy operations would cost ~10× more per step)
    wind_l = wind.tolist()
    tilt_l = tilt_err.tolist()
    gbias_l = (gyro_bias + gyro_noise).tolist()
    magn_l = (mag_noise + dist).tolist()
    accn_l = accel_noise.tolist()
    gpn_l = gnss_pos_noise.tolist()
    gvn_l = gnss_vel_noise.tolist()
    gnss_set = {int(k): i for i, k in enumerate(gnss_idx)}
    bE, bN, bU = (float(x) for x in b_enu)
    hx, hy, hz = (float(x) for x in hard_iron)
    mdx, mdy, mdz = (float(x) for x in motor_dir)
    ux, uy = float(u[0]), float(u[1])
    lx, ly = float(left[0]), float(left[1])
    ax0, ay0, alt = float(a[0]), float(a[1]), float(a[2])

    rows = []  # per step: true pos/vel/attitude, sensors, estimates
    gnss_pos = np.empty((len(gnss_idx), 3))
    gnss_vel = np.empty((len(gnss_idx), 3))

    # state
    px, py = ax0 + lx * s.start_offset_m, ay0 + ly * s.start_offset_m
    vx = vy = 0.0
    psi = course
    theta = phi = 0.0
    psi_dot = 0.0
    psi_hat = course
    bias_hat = 0.0
    ix = iy = 0.0  # velocity-error integrator
    pmx, pmy, vmx, vmy = px, py, 0.0, 0.0  # controller's GNSS-held measurement
    max_tilt = math.radians(s.max_tilt_deg)
    max_rate = math.radians(s.max_yaw_rate_deg_s)
    aax = aay = 0.0  # aerodynamic (thrust + drag) horizontal acceleration
    R = _body_to_enu(psi, theta, phi)
    alpha = dt / s.attitude_tau_s
    yaw_alpha = min(1.0, dt / 0.1)
    two_pi = 2 * math.pi

    for k in range(n):
        # --- sensors at the current state (R: the attitude reached at the end of the previous step) ---
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
        # b_body = Rᵀ b_enu
        bbx = r00 * bE + r10 * bN + r20 * bU
        bby = r01 * bE + r11 * bN + r21 * bU
        bbz = r02 * bE + r12 * bN + r22 * bU
        thrust_excess = G0 / max(math.cos(theta) * math.cos(phi), 0.5) - G0
        mn = magn_l[k]
        mot = s.motor_field_nt_per_m_s2 * thrust_excess
        m0 = bbx + hx + mot * mdx + mn[0]
        m1 = bby + hy + mot * mdy + mn[1]
        m2 = bbz + hz + mot * mdz + mn[2]
        # specific force (thrust + drag, i.e. acceleration minus gravity), body frame: Rᵀ [aax, aay, g]
        an = accn_l[k]
        f0 = r00 * aax + r10 * aay + r20 * G0 + an[0]
        f1 = r01 * aax + r11 * aay + r21 * G0 + an[1]
        f2 = r02 * aax + r12 * aay + r22 * G0 + an[2]
        # body rates: yaw about body up = −ψ̇ (roll/pitch rates are small and left out)
        gb = gbias_l[k]
        g0, g1, g2 = gb[0], gb[1], -psi_dot + gb[2]
        gi = gnss_set.get(k)
        if gi is not None:
            gp, gv = gpn_l[gi], gvn_l[gi]
            pmx, pmy = px + gp[0], py + gp[1]
            vmx, vmy = vx + gv[0], vy + gv[1]
            gnss_pos[gi] = (pmx, pmy, alt + gp[2])
            gnss_vel[gi] = (vmx, vmy, gv[2])

        # --- flight controller: attitude estimate ---
        te = tilt_l[k]
        theta_hat = theta + te[0]
        phi_hat = phi + te[1]
        # tilt compensation (level the field with the estimated roll/pitch): b_l = Ry(−θ̂) Rx(φ̂) m
        cp, sp = math.cos(phi_hat), math.sin(phi_hat)
        ct, st = math.cos(theta_hat), math.sin(theta_hat)
        my = cp * m1 - sp * m2
        mz = sp * m1 + cp * m2
        mx = ct * m0 - st * mz
        psi_m = math.atan2(my, mx) + decl
        e = _wrap(psi_m - psi_hat)
        # complementary filter: ψ̂̇ = −(ω_z − b̂) + k e ; b̂̇ = k_b e  (heading rate = −body-z rate)
        psi_hat = _wrap(psi_hat + dt * (-(g2 - bias_hat) + s.mag_gain_per_s * e))
        bias_hat += dt * s.bias_gain_per_s2 * e
        rows.append((px, py, vx, vy, psi % two_pi, theta, phi, g0, g1, g2, f0, f1, f2, m0, m1, m2,
                     bbx, bby, bbz, psi_hat % two_pi, theta_hat, phi_hat, psi_m % two_pi))

        # --- position controller (mission line following, NE frame) ---
        rx, ry = pmx - ax0, pmy - ay0
        along = rx * ux + ry * uy
        cross = rx * lx + ry * ly
        v_along = min(s.cruise_speed_m_s, math.sqrt(max(0.0, 2 * 1.0 * (length - along))))
        spx = ux * v_along - lx * s.pos_gain_per_s * cross
        spy = uy * v_along - ly * s.pos_gain_per_s * cross
        evx, evy = spx - vmx, spy - vmy
        ix += dt * s.vel_int_per_s2 * evx
        iy += dt * s.vel_int_per_s2 * evy
        acx = s.vel_gain_per_s * evx + ix
        acy = s.vel_gain_per_s * evy + iy
        # eq. 4: roll/pitch set points from the commanded acceleration using the ESTIMATED heading
        sh, ch = math.sin(psi_hat), math.cos(psi_hat)
        a_fwd = acx * sh + acy * ch  # forward unit (sin ψ̂, cos ψ̂)
        a_left = -acx * ch + acy * sh  # left unit (−cos ψ̂, sin ψ̂)
        theta_d = -math.atan(a_fwd / G0)
        phi_d = -math.atan(a_left * math.cos(theta_d) / G0)
        theta_d = max(-max_tilt, min(max_tilt, theta_d))
        phi_d = max(-max_tilt, min(max_tilt, phi_d))
        # yaw: hold the estimated heading on the route's course
        rate_cmd = max(-max_rate, min(max_rate, s.yaw_gain_per_s * _wrap(course - psi_hat)))

        # --- airframe ---
        theta += alpha * (theta_d - theta)
        phi += alpha * (phi_d - phi)
        psi_dot += yaw_alpha * (rate_cmd - psi_dot)
        psi = _wrap(psi + dt * psi_dot)
        # thrust: vertical component = g (height hold); horizontal from the TRUE attitude (eq. 1–3, 5)
        R = _body_to_enu(psi, theta, phi)
        tz = R[8]
        w = wind_l[k]
        aax = G0 * R[2] / tz - s.drag_per_s * (vx - w[0])
        aay = G0 * R[5] / tz - s.drag_per_s * (vy - w[1])
        vx += dt * aax
        vy += dt * aay
        px += dt * vx
        py += dt * vy

    arr = np.asarray(rows)
    out_pos = np.column_stack([arr[:, 0], arr[:, 1], np.full(n, alt)])
    out_vel = np.column_stack([arr[:, 2], arr[:, 3], np.zeros(n)])
    out_psi, out_theta, out_phi = arr[:, 4], arr[:, 5], arr[:, 6]
    out_gyro, out_acc, out_mag, out_bearth = arr[:, 7:10], arr[:, 10:13], arr[:, 13:16], arr[:, 16:19]
    out_att = arr[:, 19:22]
    out_psim = arr[:, 22]

    return Flight(
        settings=s, t_s=t, pos_enu_m=out_pos, vel_enu_m_s=out_vel, heading_rad=out_psi, pitch_rad=out_theta,
        roll_rad=out_phi, gyro_rad_s=out_gyro, accel_m_s2=out_acc, mag_nt=out_mag, b_earth_body_nt=out_bearth,
        disturbance_nt=dist, att_heading_rad=out_att[:, 0], att_pitch_rad=out_att[:, 1], att_roll_rad=out_att[:, 2],
        mag_heading_rad=out_psim, gnss_idx=gnss_idx, gnss_pos_enu_m=gnss_pos, gnss_vel_enu_m_s=gnss_vel,
        wind_enu_m_s=wind,
    )


def _wrap(x: float) -> float:
    return (x + math.pi) % (2 * math.pi) - math.pi


def _body_to_enu(psi: float, theta: float, phi: float) -> tuple:
    """R = Rz(π/2 − ψ) Ry(−θ) Rx(φ), row-major 9-tuple (magmesh.maths.body_to_enu, inlined for speed)."""
    yaw = math.pi / 2 - psi
    cy, sy = math.cos(yaw), math.sin(yaw)
    ct, st = math.cos(theta), math.sin(theta)
    cr, sr = math.cos(phi), math.sin(phi)
    return (cy * ct, -cy * st * sr - sy * cr, -cy * st * cr + sy * sr,
            sy * ct, -sy * st * sr + cy * cr, -sy * st * cr - cy * sr,
            st, ct * sr, ct * cr)
