"""The heading fuser's filter compiled: :class:`core.HeadingFilter`'s per-sample logic as numba kernels over
state held in arrays, stepping many vehicle *slots* through a time-ordered list of events in one call.

``core.HeadingFilter`` stays the reference; this module is the same filter, operation for operation:
alignment, prediction, accelerometer (raw, inertial-frame low-pass, at rest), rest detection with its learned
noise and zero-rate update, magnetometer heading and field-direction updates, the quasi-static window, field
checks, innovation gate, the modes ``magnetic`` / ``gyro_only`` / ``recovering`` with their holds and slew,
weak fusion of a disturbed field, hard-iron tracking, the causal magnetometer-lag estimate
(``core.MagLagEstimator``), late samples levelled with the attitude of their time, and the field re-base.
Every :class:`core.Settings` option is honoured, per slot.

* :class:`FleetHeading` — many filters (slots), each with its own settings::

      fleet = FleetHeading(capacity=500)
      slot = fleet.add(core.Settings(...))
      out = fleet.step(slot, kind, t_s, a, b, dt_s, dmc)   # rows of one slot in time order
      out.heading_rad, out.mode, out.mag_fused, ...        # per row, after the row
      fleet.euler(slot); fleet.mode(slot); fleet.last_transition(slot); fleet.flags(slot)

  ``kind`` 0 is an IMU sample (``a`` the gyro, rad/s; ``b`` the accelerometer, m/s²; ``dt_s`` its step), 1 a
  magnetometer sample (``a`` the calibrated field, nT; ``dmc`` −1 no verdict, 0 invalid, 1 valid). A ``t_s`` of
  NaN is the reference's ``t_s=None``: an IMU sample then advances the filter's clock by ``dt_s``, a
  magnetometer sample takes the filter's current time.
* :class:`CompiledHeadingFilter` — one vehicle behind :class:`core.HeadingFilter`'s public API (what the
  heading service drives), on the same kernels.
* :func:`run_recording` — a whole recording (IMU and magnetometer sample by sample) in one call.

Agreement with the reference (``tests/test_heading_compiled.py``): the same operations in the same order,
except that numpy's BLAS/LAPACK small matrix products and solves sum in an order of their own, so states
differ at the level of the last bits (≈1e-16 relative); the heading agrees within 1e-9 rad on BROAD trials and
simulated drives, with identical mode sequences and flags.

Warm-up: ``python -m services.heading_fuser.compiled --warm`` compiles every kernel into numba's disk cache
(``__pycache__`` beside this file), so that a service start loads them instead of compiling.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import fields
from typing import NamedTuple

import numpy as np
from numba import njit

from magmesh import maths

from . import core

# ---- settings columns (the order of core.Settings' fields; checked at import) -------------------------------
GYRO_NOISE_RAD_S_RT_HZ = 0
GYRO_RATE_NOISE_FRAC_RT_HZ = 1
GYRO_BIAS_WALK_RAD_S2_RT_HZ = 2
GYRO_BIAS_INIT_STD_RAD_S = 3
INIT_TILT_STD_RAD = 4
INIT_HEADING_STD_RAD = 5
INIT_DURATION_S = 6
ACCEL_NOISE_M_S2 = 7
ACCEL_NOISE_PER_RATE_M_S2_PER_RAD_S = 8
ACCEL_REJECTION_M_S2 = 9
ACCEL_UPDATE_PERIOD_S = 10
GRAVITY_LPF_TAU_S = 11
GRAVITY_LPF_NOISE_M_S2 = 12
GRAVITY_LPF_ORDER = 13
GRAVITY_LPF_IN_ESTIMATE = 14
REST_DETECTION = 15
REST_GYRO_RAD_S = 16
REST_ACCEL_M_S2 = 17
REST_MIN_S = 18
REST_FILTER_TAU_S = 19
REST_ACCEL_NOISE_M_S2 = 20
REST_GYRO_NOISE_RAD_S = 21
MAG_NOISE_NT = 22
MAG_HEADING_NOISE_FLOOR_RAD = 23
MAG_GATE_SIGMA = 24
MAG_UPDATE_PERIOD_S = 25
MAG_DELAY_S = 26
MAG_DELAY_ONLINE = 27
MAG_DELAY_MAX_S = 28
DECLINATION_RAD = 29
REF_FIELD_NT = 30
REF_DIP_RAD = 31
FIELD_STRENGTH_TOL_FRAC = 32
FIELD_DIP_TOL_RAD = 33
SAMPLE_STRENGTH_TOL_FRAC = 34
SAMPLE_DIP_TOL_RAD = 35
USE_FIELD_CHECK = 36
MAG_VECTOR_FUSION = 37
ADAPTIVE_NOISE = 38
QUASI_STATIC_WINDOW_S = 39
QUASI_STATIC_VAR_NT2 = 40
QUASI_STATIC_DIP_VAR_RAD2 = 41
QUASI_STATIC_HEADING_RAD = 42
ADAPTIVE_GAIN_VARIANCE = 43
ADAPTIVE_GAIN_HEADING = 44
USE_DMC = 45
CLEAR_HOLD_S = 46
RECOVERY_HOLD_S = 47
RECOVERY_SLEW_RAD_S = 48
RECOVERY_NOISE_GAIN = 49
DISTURBED_NOISE_GAIN = 50
DISTURBED_GATE_RAD = 51
HARD_IRON_TRACKING = 52
HARD_IRON_TAU_S = 53
HARD_IRON_NOISE_GAIN = 54
HARD_IRON_FROM_ROTATION = 55
HARD_IRON_MIN_INFO = 56
RECOVERY_EXIT_RAD = 57
HOLDS_SCALE_WITH_OUTAGE = 58
MIN_HOLD_S = 59
AGREEMENT_FROM_CLEAR = 60
REJECTION_TIMEOUT_S = 61
HEADING_ALARM_STD_RAD = 62
GRAVITY_LPF_LOOP_GAIN = 63
HEADING_TEST_GYRO_FRAME = 64
RECOVERY_EXIT_MEAN = 65
N_SETTINGS = 66

ATTITUDE_VAR_MAX_RAD2 = core.ATTITUDE_VAR_MAX_RAD2

SETTING_NAMES = tuple(f.name for f in fields(core.Settings))
assert len(SETTING_NAMES) == N_SETTINGS and all(globals()[n.upper()] == i for i, n in enumerate(SETTING_NAMES)), (
    "core.Settings changed: update the settings columns of services/heading_fuser/compiled.py")

# ---- float state columns per slot --------------------------------------------------------------------------
X_Q = 0  # 4: attitude body → ENU
X_BIAS = 4  # 3
X_T = 7  # the filter's clock
X_REF_B = 8
X_REF_DIP = 9
X_INIT_Q = 10  # 4
X_INIT_ACC = 14  # 3
X_INIT_MAG = 17  # 3
X_INIT_T0 = 20  # NaN: None
X_QG = 21  # 4: gyro-only attitude
X_HI = 25  # 3: tracked hard iron
X_HI_T = 28
X_GYAW = 29
X_LAST_ACC_T = 30
X_LAST_MAG_T = 31
X_LAST_FUSED_T = 32
X_MODE_SINCE = 33
X_CLEAR_SINCE = 34  # NaN: None (and the next ones)
X_CONS_SINCE = 35
X_INSIDE_SINCE = 36
X_REJ_SINCE = 37
X_GO_SINCE = 38
X_LEFT_MAG_T = 39
X_OUTAGE_S = 40
X_DELAY = 41  # mag_delay_s in use
X_ACC_LP = 42  # 3 (NaN in the first: None)
X_REST_GLP = 45  # 3
X_REST_ALP = 48  # 3 (NaN in the first: None)
X_REST_SINCE = 51
X_NGV = 52  # learned gyro noise variance at rest
X_NAV = 53  # learned accelerometer noise variance at rest
X_WS = 54  # 4: window sums strength, strength², dip, dip²
X_INNOV = 58  # internal states (NaN: None)
X_INNOV_VAR = 59
X_RATIO = 60
X_GAIN = 61
X_SERR = 62
X_DERR = 63
X_AERR = 64
X_TSF = 65
X_GOD = 66
X_HSTD = 67
X_LQ = 68  # 4: lag estimator's gyro attitude
X_LT_PREV = 72  # NaN: None
X_LW_PREV = 73  # 3 (NaN in the first: None)
X_LLAST_T = 76
X_LDELAY = 77
X_LOFF = 78  # 3
X_TR_T = 81  # time of the last mode change
X_HR_A = 84  # 9: HardIronFromRotation's information matrix
X_HR_B = 93  # 3
X_HR_LAST = 96  # its last sample time (−inf: none)
X_LP_S0 = 97  # 3: the second-order gravity low-pass's states
X_LP_S1 = 100  # 3
X_LP_DT = 103  # the step its coefficients below are for (NaN: none yet)
X_LP_C = 104  # 5: b0, b1, b2, a1, a2
X_INSIDE_SUM = 109  # the innovations' sum and count since X_INSIDE_SINCE (recovery_exit_mean)
X_INSIDE_N = 110
N_X = 112

# ---- int state columns per slot ----------------------------------------------------------------------------
I_MODE = 0
I_INIT_N0 = 1
I_INIT_N1 = 2
I_FL_INIT = 3  # flags
I_FL_FUSED = 4
I_FL_REJ = 5
I_FL_INCONS = 6
I_FL_QS = 7
I_FL_DMC = 8
I_FL_ACCIGN = 9
I_FL_UNC = 10
I_AT_REST = 11
I_OUT_BAD = 12
I_REBASE = 13
I_NREBASE = 14
I_WH = 15  # window ring head, count
I_WN = 16
I_HH = 17  # history ring head, count
I_HN = 18
I_LI = 19  # lag estimator: gyro samples, pairs
I_LN = 20
I_MH = 21  # lag estimator's field ring head, count
I_MN = 22
I_G = 23  # lag grid length (0: no online lag estimate)
I_TR_FROM = 24
I_TR_TO = 25
I_TR_REASON = 26
I_NTR = 27  # mode changes since reset
I_USED = 28
I_HRH = 29  # HardIronFromRotation's sample ring head, count
I_HRN = 30
N_I = 32

# ---- layout of the per-slot buffers (offsets into the float state row) -------------------------------------
W_STRIDE = 7  # a window item: t, strength, dip, mag − gyro yaw, the field in the gyro-only frame (3)
L_WCAP = 0
L_MCAP = 1
L_GMAX = 2
L_P = 3
L_HIST = 4
L_WIN = 5
L_GT = 6
L_GQ = 7
L_GRID = 8
L_A = 9
L_B = 10
L_C = 11
L_COST = 12
L_MAGS = 13
L_TOTAL = 14
L_HIR = 15
N_L = 16

HIST_LEN = 1024  # the reference's deque(maxlen=1024)
HIR_LEN = 16  # HardIronFromRotation's samples (one per 50 ms over 0.2–0.4 s: at most 6 kept)
LAG_NBUF = 512  # MagLagEstimator's n_buf

# ---- per-row outputs ---------------------------------------------------------------------------------------
O_HEADING = 0
O_PITCH = 1
O_ROLL = 2
O_HSTD = 3
O_PSTD = 4
O_RSTD = 5
O_MODE = 6
O_REASON = 7  # mode change in this row (0: none)
O_FUSED = 8  # flags.mag_fused after the row
O_RET = 9  # update_mag's return value (magnetometer rows)
O_INNOV = 10
O_RATIO = 11
O_UNCERTAIN = 12
O_TSF = 13
O_Q = 14  # 4
O_T = 18  # the filter's clock after the row
N_O = 19

MODES = core.MODES  # codes 0..3
M_INIT, M_MAG, M_GYRO, M_REC = 0, 1, 2, 3
REASONS = (
    "",
    "aligned",
    "DMC says invalid",
    "field strength/dip off reference",
    "innovation outside the gate for too long",
    "disturbance cleared",
    "disturbed again while recovering",
    "magnetometer consistent and its heading agrees",
    "calibration changed: field reference re-based",
)

G0 = maths.G0
TWO_PI = 2 * math.pi
NAN = math.nan


# =========================================================================================================
# scalar helpers
# =========================================================================================================
@njit(cache=True, error_model="numpy")
def _remainder_2pi(x):
    """CPython's math.remainder(x, 2π) (IEEE remainder, exact)."""
    y = TWO_PI
    absx = abs(x)
    m = np.fmod(absx, y)
    c = y - m
    if m < c:
        r = m
    elif m > c:
        r = -c
    else:
        r = m - 2.0 * np.fmod(0.5 * (absx - m), y)
    return math.copysign(1.0, x) * r


@njit(cache=True, error_model="numpy")
def _quat_exp(rv0, rv1, rv2):
    a = math.sqrt(rv0 * rv0 + rv1 * rv1 + rv2 * rv2)
    if a < 1e-9:
        return 1.0, 0.5 * rv0, 0.5 * rv1, 0.5 * rv2
    s = math.sin(0.5 * a) / a
    return math.cos(0.5 * a), rv0 * s, rv1 * s, rv2 * s


@njit(cache=True, error_model="numpy")
def _qmul(pw, px, py, pz, qw, qx, qy, qz):
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


@njit(cache=True, error_model="numpy")
def _qmat(w, x, y, z, R):
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True, error_model="numpy")
def _qrot(w, x, y, z, v0, v1, v2):
    """The vector (v0, v1, v2) turned by the unit quaternion (w, x, y, z): _qmat's matrix times it."""
    return ((1 - 2 * (y * y + z * z)) * v0 + 2 * (x * y - w * z) * v1 + 2 * (x * z + w * y) * v2,
            2 * (x * y + w * z) * v0 + (1 - 2 * (x * x + z * z)) * v1 + 2 * (y * z - w * x) * v2,
            2 * (x * z - w * y) * v0 + 2 * (y * z + w * x) * v1 + (1 - 2 * (x * x + y * y)) * v2)


@njit(cache=True, error_model="numpy")
def _solve3(S, B, X):
    """X = S⁻¹ B (S 3×3, B 3×k): LU with partial pivoting (LAPACK dgesv's method); S, B are overwritten."""
    k = B.shape[1]
    for c in range(3):
        p = c
        big = abs(S[c, c])
        for r in range(c + 1, 3):
            if abs(S[r, c]) > big:
                big = abs(S[r, c])
                p = r
        if p != c:
            for j in range(3):
                S[c, j], S[p, j] = S[p, j], S[c, j]
            for j in range(k):
                B[c, j], B[p, j] = B[p, j], B[c, j]
        inv = 1.0 / S[c, c]
        for r in range(c + 1, 3):
            f = S[r, c] * inv
            S[r, c] = f
            for j in range(c + 1, 3):
                S[r, j] -= f * S[c, j]
            for j in range(k):
                B[r, j] -= f * B[c, j]
    for j in range(k):
        for r in range(2, -1, -1):
            v = B[r, j]
            for c in range(r + 1, 3):
                v -= S[r, c] * X[c, j]
            X[r, j] = v / S[r, r]


# =========================================================================================================
# the filter, one slot (s: settings row, x: float state row, iv: int state row, L: layout, W: scratch)
# =========================================================================================================
@njit(cache=True, error_model="numpy")
def _P(x, L):
    return x[L[L_P]:L[L_P] + 36].reshape((6, 6))


@njit(cache=True, error_model="numpy")
def _inject(x, d0, d1, d2, d3, d4, d5):
    q = _qmul(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], *_quat_exp(d0, d1, d2))
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x[X_Q] = q[0] / n
    x[X_Q + 1] = q[1] / n
    x[X_Q + 2] = q[2] / n
    x[X_Q + 3] = q[3] / n
    x[X_BIAS] = x[X_BIAS] + d3
    x[X_BIAS + 1] = x[X_BIAS + 1] + d4
    x[X_BIAS + 2] = x[X_BIAS + 2] + d5


@njit(cache=True, error_model="numpy")
def _symmetrise(P, T):
    for i in range(6):
        for j in range(6):
            P[i, j] = 0.5 * (T[i, j] + T[j, i])


@njit(cache=True, error_model="numpy")
def _set_mode(x, iv, mode, reason):
    if mode == iv[I_MODE]:
        return
    t = x[X_T]
    iv[I_TR_FROM] = iv[I_MODE]
    iv[I_TR_TO] = mode
    iv[I_TR_REASON] = reason
    iv[I_NTR] += 1
    x[X_TR_T] = t
    if iv[I_MODE] == M_MAG:
        x[X_LEFT_MAG_T] = t
        x[X_OUTAGE_S] = NAN
    elif mode == M_MAG:
        iv[I_OUT_BAD] = 0
    if mode == M_GYRO:
        x[X_GO_SINCE] = t
    elif mode == M_MAG:
        x[X_GO_SINCE] = NAN
        x[X_HI] = 0.0
        x[X_HI + 1] = 0.0
        x[X_HI + 2] = 0.0
        x[X_HI_T] = 0.0
    iv[I_MODE] = mode
    x[X_MODE_SINCE] = t
    x[X_CONS_SINCE] = NAN
    x[X_INSIDE_SINCE] = NAN
    x[X_REJ_SINCE] = NAN
    x[X_CLEAR_SINCE] = NAN


@njit(cache=True, error_model="numpy")
def _agreement_add(x, t, nu):
    """One usable innovation into the agreement hold: it starts the hold when none runs (returns False), else it is
    added to the hold's sum and count (returns True)."""
    if math.isnan(x[X_INSIDE_SINCE]):
        x[X_INSIDE_SINCE] = t
        x[X_INSIDE_SUM] = nu
        x[X_INSIDE_N] = 1.0
        return False
    x[X_INSIDE_SUM] += nu
    x[X_INSIDE_N] += 1.0
    return True


@njit(cache=True, error_model="numpy")
def _hold(s, x, full_s):
    o = x[X_OUTAGE_S]
    if math.isnan(o):
        return full_s
    return min(full_s, max(s[MIN_HOLD_S], o))


@njit(cache=True, error_model="numpy")
def _align(s, x, iv, a0, a1, a2, m0, m1, m2):
    """core.HeadingFilter.align: attitude from one accel + mag pair."""
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    u0, u1, u2 = a0 / na, a1 / na, a2 / na
    e0 = m1 * u2 - m2 * u1  # east = m × up
    e1 = m2 * u0 - m0 * u2
    e2 = m0 * u1 - m1 * u0
    ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / ne, e1 / ne, e2 / ne
    n0 = u1 * e2 - u2 * e1  # north = up × east
    n1 = u2 * e0 - u0 * e2
    n2 = u0 * e1 - u1 * e0
    # maths.quat_from_matrix of the rows (east, north, up)
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = e0, e1, e2, n0, n1, n2, u0, u1, u2
    tr = R00 + R11 + R22
    if tr > 0:
        sq = math.sqrt(tr + 1.0) * 2
        qw, qx, qy, qz = 0.25 * sq, (R21 - R12) / sq, (R02 - R20) / sq, (R10 - R01) / sq
    elif R00 > R11 and R00 > R22:
        sq = math.sqrt(1.0 + R00 - R11 - R22) * 2
        qw, qx, qy, qz = (R21 - R12) / sq, 0.25 * sq, (R01 + R10) / sq, (R02 + R20) / sq
    elif R11 > R22:
        sq = math.sqrt(1.0 + R11 - R00 - R22) * 2
        qw, qx, qy, qz = (R02 - R20) / sq, (R01 + R10) / sq, 0.25 * sq, (R12 + R21) / sq
    else:
        sq = math.sqrt(1.0 + R22 - R00 - R11) * 2
        qw, qx, qy, qz = (R10 - R01) / sq, (R02 + R20) / sq, (R12 + R21) / sq, 0.25 * sq
    nq = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if nq > 0:
        qw, qx, qy, qz = qw / nq, qx / nq, qy / nq, qz / nq
    else:
        qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
    if not qw >= 0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    qd = _quat_exp(0.0, 0.0, -s[DECLINATION_RAD])
    q = _qmul(qd[0], qd[1], qd[2], qd[3], qw, qx, qy, qz)
    x[X_Q] = q[0]
    x[X_Q + 1] = q[1]
    x[X_Q + 2] = q[2]
    x[X_Q + 3] = q[3]
    w, qx, qy, qz = q
    mn0 = (1 - 2 * (qy * qy + qz * qz)) * m0 + 2 * (qx * qy - w * qz) * m1 + 2 * (qx * qz + w * qy) * m2
    mn1 = 2 * (qx * qy + w * qz) * m0 + (1 - 2 * (qx * qx + qz * qz)) * m1 + 2 * (qy * qz - w * qx) * m2
    mn2 = 2 * (qx * qz - w * qy) * m0 + 2 * (qy * qz + w * qx) * m1 + (1 - 2 * (qx * qx + qy * qy)) * m2
    if not x[X_REF_B]:
        x[X_REF_B] = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if not math.isfinite(x[X_REF_DIP]):
        x[X_REF_DIP] = math.atan2(-mn2, math.hypot(mn0, mn1))
    _set_mode(x, iv, M_MAG, 1)
    x[X_LAST_FUSED_T] = x[X_T]


@njit(cache=True, error_model="numpy")
def _predict(s, x, P, g0, g1, g2, dt, W6):
    w0, w1, w2 = g0 - x[X_BIAS], g1 - x[X_BIAS + 1], g2 - x[X_BIAS + 2]
    dq = _quat_exp(w0 * dt, w1 * dt, w2 * dt)
    qg = _qmul(x[X_QG], x[X_QG + 1], x[X_QG + 2], x[X_QG + 3], dq[0], dq[1], dq[2], dq[3])
    ng = math.sqrt(qg[0] * qg[0] + qg[1] * qg[1] + qg[2] * qg[2] + qg[3] * qg[3])
    x[X_QG] = qg[0] / ng
    x[X_QG + 1] = qg[1] / ng
    x[X_QG + 2] = qg[2] / ng
    x[X_QG + 3] = qg[3] / ng
    q = _qmul(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], dq[0], dq[1], dq[2], dq[3])
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    qw, qx, qy, qz = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    x[X_Q] = qw
    x[X_Q + 1] = qx
    x[X_Q + 2] = qy
    x[X_Q + 3] = qz
    x[X_GYAW] += ((2 * (qx * qz - qw * qy)) * w0 + (2 * (qy * qz + qw * qx)) * w1
                  + (1 - 2 * (qx * qx + qy * qy)) * w2) * dt
    # F = [[I − [ωT]×, −T I], [0, I]];  P ← F P Fᵀ
    v0, v1, v2 = w0 * dt, w1 * dt, w2 * dt
    M00, M01, M02 = 1.0, v2, -v1
    M10, M11, M12 = -v2, 1.0, v0
    M20, M21, M22 = v1, -v0, 1.0
    mdt = -dt
    FP = W6
    for j in range(6):
        FP[0, j] = M00 * P[0, j] + M01 * P[1, j] + M02 * P[2, j] + mdt * P[3, j]
        FP[1, j] = M10 * P[0, j] + M11 * P[1, j] + M12 * P[2, j] + mdt * P[4, j]
        FP[2, j] = M20 * P[0, j] + M21 * P[1, j] + M22 * P[2, j] + mdt * P[5, j]
        FP[3, j] = P[3, j]
        FP[4, j] = P[4, j]
        FP[5, j] = P[5, j]
    for i in range(6):
        a0, a1, a2 = FP[i, 0], FP[i, 1], FP[i, 2]
        P[i, 0] = a0 * M00 + a1 * M01 + a2 * M02 + FP[i, 3] * mdt
        P[i, 1] = a0 * M10 + a1 * M11 + a2 * M12 + FP[i, 4] * mdt
        P[i, 2] = a0 * M20 + a1 * M21 + a2 * M22 + FP[i, 5] * mdt
        P[i, 3] = FP[i, 3]
        P[i, 4] = FP[i, 4]
        P[i, 5] = FP[i, 5]
    qgn = (s[GYRO_NOISE_RAD_S_RT_HZ] ** 2 + s[GYRO_RATE_NOISE_FRAC_RT_HZ] ** 2 * (w0 * w0 + w1 * w1 + w2 * w2)) * dt
    qb = s[GYRO_BIAS_WALK_RAD_S2_RT_HZ] ** 2 * dt
    P[0, 0] += qgn
    P[1, 1] += qgn
    P[2, 2] += qgn
    P[3, 3] += qb
    P[4, 4] += qb
    P[5, 5] += qb
    m = max(P[0, 0], P[1, 1], P[2, 2])
    if m > ATTITUDE_VAR_MAX_RAD2:  # core.HeadingFilter._predict: the attitude block scaled back (a congruence)
        k = math.sqrt(ATTITUDE_VAR_MAX_RAD2 / m)
        for i in range(3):
            for j in range(6):
                P[i, j] *= k
        for i in range(6):
            for j in range(3):
                P[i, j] *= k


@njit(cache=True, error_model="numpy")
def _vector_update(x, P, h0, h1, h2, z0, z1, z2, var, project_up, W):
    """The gravity / field-direction update: measurement z (unit, body) against h, H = [[h]×, 0], noise var
    per axis; the gain's rotation about the nav vertical zeroed when ``project_up`` (gravity never moves the
    heading). Joseph form."""
    PHt = W.pht
    S = W.s3
    B = W.b36
    K = W.k63
    # H rows: [0, −h2, h1], [h2, 0, −h0], [−h1, h0, 0]
    for i in range(6):
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        PHt[i, 0] = p0 * 0.0 + p1 * -h2 + p2 * h1
        PHt[i, 1] = p0 * h2 + p1 * 0.0 + p2 * -h0
        PHt[i, 2] = p0 * -h1 + p1 * h0 + p2 * 0.0
    for j in range(3):
        S[0, j] = -h2 * PHt[1, j] + h1 * PHt[2, j]
        S[1, j] = h2 * PHt[0, j] - h0 * PHt[2, j]
        S[2, j] = -h1 * PHt[0, j] + h0 * PHt[1, j]
    S[0, 0] += var
    S[1, 1] += var
    S[2, 2] += var
    for i in range(3):
        for j in range(6):
            B[i, j] = PHt[j, i]
    X = W.x36
    _solve3(S, B, X)
    for i in range(6):
        for j in range(3):
            K[i, j] = X[j, i]
    if project_up:
        qw, qx, qy, qz = x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3]
        u0 = 2 * (qx * qz - qw * qy)
        u1 = 2 * (qy * qz + qw * qx)
        u2 = 1 - 2 * (qx * qx + qy * qy)
        for j in range(3):
            c = u0 * K[0, j] + u1 * K[1, j] + u2 * K[2, j]
            K[0, j] -= u0 * c
            K[1, j] -= u1 * c
            K[2, j] -= u2 * c
    r0, r1, r2 = z0 - h0, z1 - h1, z2 - h2
    dx = W.dx
    for i in range(6):
        dx[i] = K[i, 0] * r0 + K[i, 1] * r1 + K[i, 2] * r2
    _inject(x, dx[0], dx[1], dx[2], dx[3], dx[4], dx[5])
    # A = I − K H (A[:, 3:] = I);  P ← A P Aᵀ + var K Kᵀ
    A = W.a63
    for i in range(6):
        k0, k1, k2 = K[i, 0], K[i, 1], K[i, 2]
        A[i, 0] = (1.0 if i == 0 else 0.0) - (k1 * h2 - k2 * h1)
        A[i, 1] = (1.0 if i == 1 else 0.0) - (-k0 * h2 + k2 * h0)
        A[i, 2] = (1.0 if i == 2 else 0.0) - (k0 * h1 - k1 * h0)
    AP = W.m6
    for i in range(6):
        for j in range(6):
            v = A[i, 0] * P[0, j] + A[i, 1] * P[1, j] + A[i, 2] * P[2, j]
            if i >= 3:
                v += P[i, j]
            AP[i, j] = v
    T = W.t6
    for i in range(6):
        for j in range(6):
            v = AP[i, 0] * A[j, 0] + AP[i, 1] * A[j, 1] + AP[i, 2] * A[j, 2]
            if j >= 3:
                v += AP[i, j]
            T[i, j] = v + var * (K[i, 0] * K[j, 0] + K[i, 1] * K[j, 1] + K[i, 2] * K[j, 2])
    _symmetrise(P, T)


@njit(cache=True, error_model="numpy")
def _fuse_accel(s, x, iv, P, a0, a1, a2, rate, noise, floor, W):
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    err = na - G0
    x[X_AERR] = err
    if abs(err) > s[ACCEL_REJECTION_M_S2] or na < 1e-6:
        iv[I_FL_ACCIGN] = 1
        return
    iv[I_FL_ACCIGN] = 0
    z0, z1, z2 = a0 / na, a1 / na, a2 / na
    qw, qx, qy, qz = x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3]
    g0 = 2 * (qx * qz - qw * qy)
    g1 = 2 * (qy * qz + qw * qx)
    g2 = 1 - 2 * (qx * qx + qy * qy)
    base = s[ACCEL_NOISE_M_S2] if math.isnan(noise) else noise
    sig = max((base + 2.0 * abs(err) + s[ACCEL_NOISE_PER_RATE_M_S2_PER_RAD_S] * rate) / G0, floor)
    _vector_update(x, P, g0, g1, g2, z0, z1, z2, sig * sig, True, W)


@njit(cache=True, error_model="numpy")
def _lpf_loop_floor(s, x, P, interval, R):
    """core.HeadingFilter._lpf_loop_floor."""
    k = 1.0 - math.exp(-interval * s[GRAVITY_LPF_LOOP_GAIN] / s[GRAVITY_LPF_TAU_S])
    if k >= 1.0:
        return 0.0
    _qmat(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], R)
    # the nav-frame tilt (east, north) covariance: rows 0 and 1 of R times P times their transpose
    v00 = R[0, 0] * P[0, 0] + R[0, 1] * P[1, 0] + R[0, 2] * P[2, 0]
    v01 = R[0, 0] * P[0, 1] + R[0, 1] * P[1, 1] + R[0, 2] * P[2, 1]
    v02 = R[0, 0] * P[0, 2] + R[0, 1] * P[1, 2] + R[0, 2] * P[2, 2]
    v10 = R[1, 0] * P[0, 0] + R[1, 1] * P[1, 0] + R[1, 2] * P[2, 0]
    v11 = R[1, 0] * P[0, 1] + R[1, 1] * P[1, 1] + R[1, 2] * P[2, 1]
    v12 = R[1, 0] * P[0, 2] + R[1, 1] * P[1, 2] + R[1, 2] * P[2, 2]
    a = v00 * R[0, 0] + v01 * R[0, 1] + v02 * R[0, 2]
    b = v00 * R[1, 0] + v01 * R[1, 1] + v02 * R[1, 2]
    c = v10 * R[1, 0] + v11 * R[1, 1] + v12 * R[1, 2]
    lam = 0.5 * (a + c) + math.sqrt(0.25 * (a - c) * (a - c) + b * b)
    return math.sqrt(max(lam, 0.0) * (1.0 - k) / k)


@njit(cache=True, error_model="numpy")
def _zero_rate(x, P, g0, g1, g2, W):
    r = x[X_NGV]
    S = W.s3
    B = W.b36
    X = W.x36
    for i in range(3):
        for j in range(3):
            S[i, j] = P[3 + i, 3 + j]
        S[i, i] += r
        for j in range(6):
            B[i, j] = P[3 + i, j]
    _solve3(S, B, X)  # X = S⁻¹ P[3:, :];  K = Xᵀ
    e0, e1, e2 = g0 - x[X_BIAS], g1 - x[X_BIAS + 1], g2 - x[X_BIAS + 2]
    dx = W.dx
    for i in range(6):
        dx[i] = X[0, i] * e0 + X[1, i] * e1 + X[2, i] * e2
    _inject(x, dx[0], dx[1], dx[2], dx[3], dx[4], dx[5])
    T = W.t6
    for i in range(6):
        for j in range(6):
            T[i, j] = P[i, j] - (X[0, i] * P[3, j] + X[1, i] * P[4, j] + X[2, i] * P[5, j])
    _symmetrise(P, T)


@njit(cache=True, error_model="numpy")
def _detect_rest(s, x, iv, g0, g1, g2, a0, a1, a2, dt):
    k = min(1.0, dt / s[REST_FILTER_TAU_S])
    if math.isnan(x[X_REST_ALP]):
        x[X_REST_ALP] = a0
        x[X_REST_ALP + 1] = a1
        x[X_REST_ALP + 2] = a2
    x[X_REST_GLP] += k * (g0 - x[X_REST_GLP])
    x[X_REST_ALP] += k * (a0 - x[X_REST_ALP])
    x[X_REST_GLP + 1] += k * (g1 - x[X_REST_GLP + 1])
    x[X_REST_ALP + 1] += k * (a1 - x[X_REST_ALP + 1])
    x[X_REST_GLP + 2] += k * (g2 - x[X_REST_GLP + 2])
    x[X_REST_ALP + 2] += k * (a2 - x[X_REST_ALP + 2])
    da0, da1, da2 = a0 - x[X_REST_ALP], a1 - x[X_REST_ALP + 1], a2 - x[X_REST_ALP + 2]
    gl0, gl1, gl2 = x[X_REST_GLP], x[X_REST_GLP + 1], x[X_REST_GLP + 2]
    dg0, dg1, dg2 = gl0 - x[X_BIAS], gl1 - x[X_BIAS + 1], gl2 - x[X_BIAS + 2]
    quiet = (dg0 * dg0 + dg1 * dg1 + dg2 * dg2 < s[REST_GYRO_RAD_S] ** 2
             and da0 * da0 + da1 * da1 + da2 * da2 < s[REST_ACCEL_M_S2] ** 2)
    if not quiet:
        x[X_REST_SINCE] = NAN
        iv[I_AT_REST] = 0
        return
    if math.isnan(x[X_REST_SINCE]):
        x[X_REST_SINCE] = x[X_T]
    at_rest = x[X_T] - x[X_REST_SINCE] >= s[REST_MIN_S]
    iv[I_AT_REST] = 1 if at_rest else 0
    if at_rest:
        kn = min(1.0, dt / 10.0)
        e0, e1, e2 = g0 - gl0, g1 - gl1, g2 - gl2
        x[X_NGV] += kn * ((e0 * e0 + e1 * e1 + e2 * e2) / 3.0 - x[X_NGV])
        x[X_NAV] += kn * ((da0 * da0 + da1 * da1 + da2 * da2) / 3.0 - x[X_NAV])


@njit(cache=True, error_model="numpy")
def _lag_add_gyro(x, iv, L, t, g0, g1, g2):
    tp = x[X_LT_PREV]
    dt = 0.0 if math.isnan(tp) else t - tp
    x[X_LT_PREV] = t
    if math.isnan(x[X_LW_PREV]):
        p0, p1, p2 = g0, g1, g2
    else:
        p0, p1, p2 = x[X_LW_PREV], x[X_LW_PREV + 1], x[X_LW_PREV + 2]
    x[X_LW_PREV] = g0
    x[X_LW_PREV + 1] = g1
    x[X_LW_PREV + 2] = g2
    if dt > 0.0:
        h = 0.5 * dt
        q = _qmul(x[X_LQ], x[X_LQ + 1], x[X_LQ + 2], x[X_LQ + 3], *_quat_exp((p0 + g0) * h, (p1 + g1) * h, (p2 + g2) * h))
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        x[X_LQ] = q[0] / n
        x[X_LQ + 1] = q[1] / n
        x[X_LQ + 2] = q[2] / n
        x[X_LQ + 3] = q[3] / n
    j = iv[I_LI] % LAG_NBUF
    x[L[L_GT] + j] = t
    o = L[L_GQ] + 4 * j
    x[o] = x[X_LQ]
    x[o + 1] = x[X_LQ + 1]
    x[o + 2] = x[X_LQ + 2]
    x[o + 3] = x[X_LQ + 3]
    iv[I_LI] += 1


@njit(cache=True, error_model="numpy")
def _lag_attitude_at(x, L, first, k, tq, lo):
    """MagLagEstimator._attitudes_at for one time: normalised linear interpolation of the ring buffer's
    filled part (logical index j ↔ physical (first + j) % n_buf). ``lo`` (≥ the answer, or −1) starts the
    search for searchsorted(side=left); returns the attitude and that index (times asked in decreasing order
    walk down from the last answer)."""
    ogt = L[L_GT]
    if lo < 0:
        lo, hi = 0, k  # searchsorted, side left
        while lo < hi:
            mid = (lo + hi) >> 1
            if x[ogt + (first + mid) % LAG_NBUF] < tq:
                lo = mid + 1
            else:
                hi = mid
    else:
        while lo > 0 and x[ogt + (first + lo - 1) % LAG_NBUF] >= tq:
            lo -= 1
    found = lo
    idx = min(max(lo, 1), k - 1)
    i0 = (first + idx - 1) % LAG_NBUF
    i1 = (first + idx) % LAG_NBUF
    t0, t1 = x[ogt + i0], x[ogt + i1]
    f = (tq - t0) / max(t1 - t0, 1e-9)
    f = min(max(f, 0.0), 1.0)
    o0 = L[L_GQ] + 4 * i0
    o1 = L[L_GQ] + 4 * i1
    a = 1.0 - f
    w = x[o0] * a + x[o1] * f
    qx = x[o0 + 1] * a + x[o1 + 1] * f
    qy = x[o0 + 2] * a + x[o1 + 2] * f
    qz = x[o0 + 3] * a + x[o1 + 3] * f
    n = math.sqrt(w * w + qx * qx + qy * qy + qz * qz)
    return w / n, qx / n, qy / n, qz / n, found


@njit(cache=True, error_model="numpy")
def _lag_solve(x, iv, L, W):
    G = iv[I_G]
    oA, oB, oC, oK, og = L[L_A], L[L_B], L[L_C], L[L_COST], L[L_GRID]
    S = W.s3
    B = W.b31
    X = W.x31
    H = W.h_g3
    best = 0
    for g in range(G):
        a = oA + 9 * g
        eps = 1e-9 * (x[a] + x[a + 4] + x[a + 8]) + 1e-12
        for i in range(3):
            for j in range(3):
                S[i, j] = x[a + 3 * i + j] + (eps if i == j else 0.0)
            B[i, 0] = x[oB + 3 * g + i]
        _solve3(S, B, X)
        H[g, 0], H[g, 1], H[g, 2] = X[0, 0], X[1, 0], X[2, 0]
        c = x[oC + g] - (x[oB + 3 * g] * X[0, 0] + x[oB + 3 * g + 1] * X[1, 0] + x[oB + 3 * g + 2] * X[2, 0])
        x[oK + g] = c
        if c < x[oK + best]:
            best = g
    j = best
    x[X_LOFF] = H[j, 0]
    x[X_LOFF + 1] = H[j, 1]
    x[X_LOFF + 2] = H[j, 2]
    frac = 0.0
    if 0 < j < G - 1:
        c0, c1, c2 = x[oK + j - 1], x[oK + j], x[oK + j + 1]
        den = c0 - 2 * c1 + c2
        frac = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    x[X_LDELAY] = max(0.0, x[og + j] + frac * 0.001)


@njit(cache=True, error_model="numpy")
def _lag_add_mag(x, iv, L, t, m0, m1, m2, ref_nt, W):
    """MagLagEstimator.add_mag (its default parameters: 1 ms grid, 0.5 rad/s, 200 pairs, 50 ms, 0.2 s)."""
    if ref_nt and abs(math.sqrt(m0 * m0 + m1 * m1 + m2 * m2) / ref_nt - 1.0) > 0.1:
        return
    baseline = 0.2
    cap = L[L_MCAP]
    om = L[L_MAGS]
    # append, then drop the oldest while the second oldest is a baseline old
    j = (iv[I_MH] + iv[I_MN]) % cap
    x[om + 4 * j] = t
    x[om + 4 * j + 1] = m0
    x[om + 4 * j + 2] = m1
    x[om + 4 * j + 3] = m2
    iv[I_MN] += 1
    while iv[I_MN] > 1 and x[om + 4 * ((iv[I_MH] + 1) % cap)] <= t - baseline:
        iv[I_MH] = (iv[I_MH] + 1) % cap
        iv[I_MN] -= 1
    if t - x[X_LLAST_T] < 0.05 or iv[I_LI] < 2:
        return
    h = iv[I_MH]
    t0 = x[om + 4 * h]
    if t - t0 < 0.8 * baseline or t - t0 > 2.0 * baseline:
        return
    n_i = iv[I_LI]
    k = min(n_i, LAG_NBUF)
    first = (n_i - k) % LAG_NBUF
    og = L[L_GRID]
    G = iv[I_G]
    ogt = L[L_GT]
    if t0 - x[og + G - 1] < x[ogt + first] or t > x[ogt + (first + k - 1) % LAG_NBUF] + 1e-6:
        return
    x[X_LLAST_T] = t
    p0, p1, p2 = x[om + 4 * h + 1], x[om + 4 * h + 2], x[om + 4 * h + 3]
    oA, oB, oC = L[L_A], L[L_B], L[L_C]
    lo1 = lo0 = -1
    for g in range(G):
        d = x[og + g]
        w1, x1, y1, z1, lo1 = _lag_attitude_at(x, L, first, k, t - d, lo1)
        w0, x0, y0, z0, lo0 = _lag_attitude_at(x, L, first, k, t0 - d, lo0)
        w = w1 * w0 + x1 * x0 + y1 * y0 + z1 * z0
        qx = w1 * x0 - x1 * w0 - y1 * z0 + z1 * y0
        qy = w1 * y0 + x1 * z0 - y1 * w0 - z1 * x0
        qz = w1 * z0 - x1 * y0 + y1 * x0 - z1 * w0
        if g == 0 and 2.0 * math.acos(min(1.0, abs(w))) < 0.5 * 0.2 * 0.5:
            return  # not turned enough over the baseline (the reference has set its last time already)
        D00 = 1 - 2 * (qy * qy + qz * qz)
        D01 = 2 * (qx * qy - w * qz)
        D02 = 2 * (qx * qz + w * qy)
        D10 = 2 * (qx * qy + w * qz)
        D11 = 1 - 2 * (qx * qx + qz * qz)
        D12 = 2 * (qy * qz - w * qx)
        D20 = 2 * (qx * qz - w * qy)
        D21 = 2 * (qy * qz + w * qx)
        D22 = 1 - 2 * (qx * qx + qy * qy)
        r0 = m0 - (D00 * p0 + D01 * p1 + D02 * p2)
        r1 = m1 - (D10 * p0 + D11 * p1 + D12 * p2)
        r2 = m2 - (D20 * p0 + D21 * p1 + D22 * p2)
        M00, M01, M02 = 1.0 - D00, -D01, -D02
        M10, M11, M12 = -D10, 1.0 - D11, -D12
        M20, M21, M22 = -D20, -D21, 1.0 - D22
        a = oA + 9 * g
        # A += Mᵀ M
        x[a + 0] += M00 * M00 + M10 * M10 + M20 * M20
        x[a + 1] += M00 * M01 + M10 * M11 + M20 * M21
        x[a + 2] += M00 * M02 + M10 * M12 + M20 * M22
        x[a + 3] += M01 * M00 + M11 * M10 + M21 * M20
        x[a + 4] += M01 * M01 + M11 * M11 + M21 * M21
        x[a + 5] += M01 * M02 + M11 * M12 + M21 * M22
        x[a + 6] += M02 * M00 + M12 * M10 + M22 * M20
        x[a + 7] += M02 * M01 + M12 * M11 + M22 * M21
        x[a + 8] += M02 * M02 + M12 * M12 + M22 * M22
        b = oB + 3 * g
        x[b] += M00 * r0 + M10 * r1 + M20 * r2
        x[b + 1] += M01 * r0 + M11 * r1 + M21 * r2
        x[b + 2] += M02 * r0 + M12 * r1 + M22 * r2
        x[oC + g] += r0 * r0 + r1 * r1 + r2 * r2
    iv[I_LN] += 1
    if iv[I_LN] >= 200 and iv[I_LN] % 10 == 0:
        _lag_solve(x, iv, L, W)


@njit(cache=True, error_model="numpy")
def _attitude_at(x, iv, L, t):
    """(q, gyro yaw) at an earlier time t: the current estimate turned back by the gyro's motion since t."""
    n = iv[I_HN]
    if n == 0:
        return (x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], x[X_GYAW], x[X_QG], x[X_QG + 1], x[X_QG + 2],
                x[X_QG + 3])
    oh = L[L_HIST]
    head = iv[I_HH]
    e = head  # the oldest, unless a later one is at or before t
    for k in range(n - 1, -1, -1):
        j = (head + k) % HIST_LEN
        if x[oh + 6 * j] <= t + 1e-9:
            e = j
            break
    o = oh + 6 * e
    rel = _qmul(x[X_QG], -x[X_QG + 1], -x[X_QG + 2], -x[X_QG + 3], x[o + 1], x[o + 2], x[o + 3], x[o + 4])
    q = _qmul(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], rel[0], rel[1], rel[2], rel[3])
    return q[0], q[1], q[2], q[3], x[o + 5], x[o + 1], x[o + 2], x[o + 3], x[o + 4]


@njit(cache=True, error_model="numpy")
def butterworth2(tau_s, dt):
    """core.butterworth2: a second-order Butterworth low-pass's coefficients (b0, b1, b2, a1, a2)."""
    fc = (math.sqrt(2.0) / (2.0 * math.pi)) / tau_s
    c = math.tan(math.pi * fc * dt)
    d = c * c + math.sqrt(2.0) * c + 1.0
    b0 = c * c / d
    return b0, 2.0 * b0, b0, 2.0 * (c * c - 1.0) / d, (1.0 - math.sqrt(2.0) * c + c * c) / d


@njit(cache=True, error_model="numpy")
def min_eig_sym3(a00, a01, a02, a11, a12, a22):
    """core.min_eig_sym3: the smallest eigenvalue of a symmetric 3×3 matrix (closed form)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) * (a00 - q) + (a11 - q) * (a11 - q) + (a22 - q) * (a22 - q) + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p == 0.0:
        return q
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = max(-1.0, min(1.0, r))
    return q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)


@njit(cache=True, error_model="numpy")
def _hir_add(s, x, iv, L, t, m0, m1, m2, qw, qx, qy, qz):
    """core.HardIronFromRotation.add (spacing 0.05 s, baseline 0.2 s, turn ≥ 0.05 rad)."""
    if t - x[X_HR_LAST] < 0.05 - 1e-9:
        return
    last = x[X_HR_LAST]
    a = min(1.0, (t - last) / s[HARD_IRON_TAU_S]) if math.isfinite(last) else 0.0
    x[X_HR_LAST] = t
    o = L[L_HIR]
    if iv[I_HRN] == HIR_LEN:  # (never: at most 6 samples are kept)
        iv[I_HRH] = (iv[I_HRH] + 1) % HIR_LEN
        iv[I_HRN] -= 1
    j = o + 8 * ((iv[I_HRH] + iv[I_HRN]) % HIR_LEN)
    x[j] = t
    x[j + 1] = m0
    x[j + 2] = m1
    x[j + 3] = m2
    x[j + 4] = qw
    x[j + 5] = qx
    x[j + 6] = qy
    x[j + 7] = qz
    iv[I_HRN] += 1
    while iv[I_HRN] > 1 and x[o + 8 * ((iv[I_HRH] + 1) % HIR_LEN)] <= t - 0.2:
        iv[I_HRH] = (iv[I_HRH] + 1) % HIR_LEN
        iv[I_HRN] -= 1
    k = o + 8 * iv[I_HRH]
    if t - x[k] < 0.8 * 0.2:
        return
    c = 1.0 - a
    for i in range(9):
        x[X_HR_A + i] = c * x[X_HR_A + i]
    for i in range(3):
        x[X_HR_B + i] = c * x[X_HR_B + i]
    w, rx, ry, rz = _qmul(qw, -qx, -qy, -qz, x[k + 4], x[k + 5], x[k + 6], x[k + 7])
    if 2.0 * math.acos(min(1.0, abs(w))) < 0.05:
        return
    D00 = 1 - 2 * (ry * ry + rz * rz)
    D01 = 2 * (rx * ry - w * rz)
    D02 = 2 * (rx * rz + w * ry)
    D10 = 2 * (rx * ry + w * rz)
    D11 = 1 - 2 * (rx * rx + rz * rz)
    D12 = 2 * (ry * rz - w * rx)
    D20 = 2 * (rx * rz - w * ry)
    D21 = 2 * (ry * rz + w * rx)
    D22 = 1 - 2 * (rx * rx + ry * ry)
    p0, p1, p2 = x[k + 1], x[k + 2], x[k + 3]
    r0 = m0 - (D00 * p0 + D01 * p1 + D02 * p2)
    r1 = m1 - (D10 * p0 + D11 * p1 + D12 * p2)
    r2 = m2 - (D20 * p0 + D21 * p1 + D22 * p2)
    M00, M01, M02 = 1.0 - D00, -D01, -D02
    M10, M11, M12 = -D10, 1.0 - D11, -D12
    M20, M21, M22 = -D20, -D21, 1.0 - D22
    A = X_HR_A
    x[A + 0] = x[A + 0] + (M00 * M00 + M10 * M10 + M20 * M20)
    x[A + 1] = x[A + 1] + (M00 * M01 + M10 * M11 + M20 * M21)
    x[A + 2] = x[A + 2] + (M00 * M02 + M10 * M12 + M20 * M22)
    x[A + 3] = x[A + 3] + (M01 * M00 + M11 * M10 + M21 * M20)
    x[A + 4] = x[A + 4] + (M01 * M01 + M11 * M11 + M21 * M21)
    x[A + 5] = x[A + 5] + (M01 * M02 + M11 * M12 + M21 * M22)
    x[A + 6] = x[A + 6] + (M02 * M00 + M12 * M10 + M22 * M20)
    x[A + 7] = x[A + 7] + (M02 * M01 + M12 * M11 + M22 * M21)
    x[A + 8] = x[A + 8] + (M02 * M02 + M12 * M12 + M22 * M22)
    x[X_HR_B] = x[X_HR_B] + (M00 * r0 + M10 * r1 + M20 * r2)
    x[X_HR_B + 1] = x[X_HR_B + 1] + (M01 * r0 + M11 * r1 + M21 * r2)
    x[X_HR_B + 2] = x[X_HR_B + 2] + (M02 * r0 + M12 * r1 + M22 * r2)


@njit(cache=True, error_model="numpy")
def _imu(s, x, iv, L, g0, g1, g2, a0, a1, a2, dt, t_in, W):
    """core.HeadingFilter.update_imu."""
    x[X_T] = x[X_T] + dt if math.isnan(t_in) else t_in
    P = _P(x, L)
    if iv[I_MODE] == M_INIT:
        if iv[I_INIT_N0] or iv[I_INIT_N1]:
            q = _qmul(x[X_INIT_Q], x[X_INIT_Q + 1], x[X_INIT_Q + 2], x[X_INIT_Q + 3], *_quat_exp(g0 * dt, g1 * dt, g2 * dt))
            x[X_INIT_Q] = q[0]
            x[X_INIT_Q + 1] = q[1]
            x[X_INIT_Q + 2] = q[2]
            x[X_INIT_Q + 3] = q[3]
        R = W.r3
        _qmat(x[X_INIT_Q], x[X_INIT_Q + 1], x[X_INIT_Q + 2], x[X_INIT_Q + 3], R)
        for i in range(3):
            x[X_INIT_ACC + i] += R[i, 0] * a0 + R[i, 1] * a1 + R[i, 2] * a2
        iv[I_INIT_N0] += 1
        return
    _predict(s, x, P, g0, g1, g2, dt, W.m6)
    # history (maxlen HIST_LEN): (t, gyro-only q, gyro yaw)
    oh = L[L_HIST]
    if iv[I_HN] < HIST_LEN:
        j = (iv[I_HH] + iv[I_HN]) % HIST_LEN
        iv[I_HN] += 1
    else:
        j = iv[I_HH]
        iv[I_HH] = (iv[I_HH] + 1) % HIST_LEN
    o = oh + 6 * j
    x[o] = x[X_T]
    x[o + 1] = x[X_QG]
    x[o + 2] = x[X_QG + 1]
    x[o + 3] = x[X_QG + 2]
    x[o + 4] = x[X_QG + 3]
    x[o + 5] = x[X_GYAW]
    if iv[I_G] > 0:
        _lag_add_gyro(x, iv, L, x[X_T], g0, g1, g2)
    rate = math.sqrt(g0 ** 2 + g1 ** 2 + g2 ** 2)
    c0, c1, c2 = a0, a1, a2
    if s[REST_DETECTION]:
        _detect_rest(s, x, iv, g0, g1, g2, a0, a1, a2, dt)
    lpf = s[GRAVITY_LPF_TAU_S] > 0.0
    if lpf:
        R = W.r3
        if s[GRAVITY_LPF_IN_ESTIMATE]:  # the filter's own attitude (VQF's frame), else the gyro-only one
            _qmat(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], R)
        else:
            _qmat(x[X_QG], x[X_QG + 1], x[X_QG + 2], x[X_QG + 3], R)
        i0 = R[0, 0] * a0 + R[0, 1] * a1 + R[0, 2] * a2
        i1 = R[1, 0] * a0 + R[1, 1] * a1 + R[1, 2] * a2
        i2 = R[2, 0] * a0 + R[2, 1] * a1 + R[2, 2] * a2
        if s[GRAVITY_LPF_ORDER] == 2.0:
            if dt != x[X_LP_DT]:  # a fixed rate: computed once (the same values as every step)
                c = butterworth2(s[GRAVITY_LPF_TAU_S], dt)
                for j in range(5):
                    x[X_LP_C + j] = c[j]
                x[X_LP_DT] = dt
            b0, b1, b2, fa1, fa2 = x[X_LP_C], x[X_LP_C + 1], x[X_LP_C + 2], x[X_LP_C + 3], x[X_LP_C + 4]
            if math.isnan(x[X_ACC_LP]) or iv[I_AT_REST]:
                x[X_ACC_LP] = i0
                x[X_ACC_LP + 1] = i1
                x[X_ACC_LP + 2] = i2
                for j in range(3):
                    v = x[X_ACC_LP + j]
                    x[X_LP_S0 + j] = v * (1.0 - b0)
                    x[X_LP_S1 + j] = v * (b2 - fa2)
            else:
                for j in range(3):
                    v = i0 if j == 0 else (i1 if j == 1 else i2)
                    y = b0 * v + x[X_LP_S0 + j]
                    x[X_LP_S0 + j] = b1 * v - fa1 * y + x[X_LP_S1 + j]
                    x[X_LP_S1 + j] = b2 * v - fa2 * y
                    x[X_ACC_LP + j] = y
        elif math.isnan(x[X_ACC_LP]) or iv[I_AT_REST]:
            x[X_ACC_LP] = i0
            x[X_ACC_LP + 1] = i1
            x[X_ACC_LP + 2] = i2
        else:
            k = min(1.0, dt / s[GRAVITY_LPF_TAU_S])
            x[X_ACC_LP] = x[X_ACC_LP] + k * (i0 - x[X_ACC_LP])
            x[X_ACC_LP + 1] = x[X_ACC_LP + 1] + k * (i1 - x[X_ACC_LP + 1])
            x[X_ACC_LP + 2] = x[X_ACC_LP + 2] + k * (i2 - x[X_ACC_LP + 2])
        l0, l1, l2 = x[X_ACC_LP], x[X_ACC_LP + 1], x[X_ACC_LP + 2]
        c0 = R[0, 0] * l0 + R[1, 0] * l1 + R[2, 0] * l2
        c1 = R[0, 1] * l0 + R[1, 1] * l1 + R[2, 1] * l2
        c2 = R[0, 2] * l0 + R[1, 2] * l1 + R[2, 2] * l2
    if x[X_T] - x[X_LAST_ACC_T] >= s[ACCEL_UPDATE_PERIOD_S] - 1e-9:
        interval = x[X_T] - x[X_LAST_ACC_T]
        x[X_LAST_ACC_T] = x[X_T]
        if iv[I_AT_REST]:
            _fuse_accel(s, x, iv, P, a0, a1, a2, 0.0, math.sqrt(x[X_NAV]), 0.0, W)
            _zero_rate(x, P, g0, g1, g2, W)
        elif lpf:
            floor = 0.0
            if s[GRAVITY_LPF_LOOP_GAIN] > 0.0 and s[GRAVITY_LPF_IN_ESTIMATE]:
                floor = _lpf_loop_floor(s, x, P, interval, W.r3)
            _fuse_accel(s, x, iv, P, c0, c1, c2, 0.0, s[GRAVITY_LPF_NOISE_M_S2], floor, W)
        else:
            _fuse_accel(s, x, iv, P, a0, a1, a2, rate, NAN, 0.0, W)
    x[X_TSF] = x[X_T] - x[X_LAST_FUSED_T]
    x[X_GOD] = 0.0 if math.isnan(x[X_GO_SINCE]) else x[X_T] - x[X_GO_SINCE]
    qw, qx, qy, qz = x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3]
    u0 = 2 * (qx * qz - qw * qy)
    u1 = 2 * (qy * qz + qw * qx)
    u2 = 1 - 2 * (qx * qx + qy * qy)
    v0 = u0 * P[0, 0] + u1 * P[1, 0] + u2 * P[2, 0]
    v1 = u0 * P[0, 1] + u1 * P[1, 1] + u2 * P[2, 1]
    v2 = u0 * P[0, 2] + u1 * P[1, 2] + u2 * P[2, 2]
    h_std = math.sqrt(max(v0 * u0 + v1 * u1 + v2 * u2, 0.0))
    x[X_HSTD] = h_std
    iv[I_FL_UNC] = 1 if (iv[I_MODE] != M_MAG and h_std > s[HEADING_ALARM_STD_RAD]) else 0


@njit(cache=True, error_model="numpy")
def _window_full(x, iv, L, t, length_s):
    n = iv[I_WN]
    return n >= 3 and t - x[L[L_WIN] + W_STRIDE * iv[I_WH]] >= 0.8 * length_s


@njit(cache=True, error_model="numpy")
def _hard_iron_innovation(s, x, Rm, m0, m1, m2, dt, mean_b, W):
    """The heading innovation of the field without the tracked hard iron, or NaN (None); ``mean_b`` the
    window's mean strength."""
    D, dip = s[DECLINATION_RAD], x[X_REF_DIP]
    B = x[X_REF_B]
    if s[HARD_IRON_FROM_ROTATION]:  # from the rotation alone
        A = x[X_HR_A:X_HR_A + 9]
        if min_eig_sym3(A[0], A[1], A[2], A[4], A[5], A[8]) < s[HARD_IRON_MIN_INFO]:
            return NAN
        S3, B31, X31 = W.s3, W.b31, W.x31
        for i in range(3):
            for j in range(3):
                S3[i, j] = A[3 * i + j]
            B31[i, 0] = x[X_HR_B + i]
        _solve3(S3, B31, X31)
        h0, h1, h2 = X31[0, 0], X31[1, 0], X31[2, 0]
        # at least the strength tolerance and the window's strength offset (|b + h| − |b| ≤ |h|)
        if math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) < max(s[FIELD_STRENGTH_TOL_FRAC] * B, abs(mean_b - B)):
            return NAN
    else:  # the slow mean of measured − expected field
        b0 = B * (math.cos(dip) * math.sin(D))
        b1 = B * (math.cos(dip) * math.cos(D))
        b2 = B * -math.sin(dip)
        a = min(1.0, dt / s[HARD_IRON_TAU_S])
        e0 = Rm[0, 0] * b0 + Rm[1, 0] * b1 + Rm[2, 0] * b2
        e1 = Rm[0, 1] * b0 + Rm[1, 1] * b1 + Rm[2, 1] * b2
        e2 = Rm[0, 2] * b0 + Rm[1, 2] * b1 + Rm[2, 2] * b2
        x[X_HI] = (1.0 - a) * x[X_HI] + a * (m0 - e0)
        x[X_HI + 1] = (1.0 - a) * x[X_HI + 1] + a * (m1 - e1)
        x[X_HI + 2] = (1.0 - a) * x[X_HI + 2] + a * (m2 - e2)
        x[X_HI_T] += dt
        if x[X_HI_T] < s[HARD_IRON_TAU_S]:
            return NAN
        h0, h1, h2 = x[X_HI], x[X_HI + 1], x[X_HI + 2]
    c0, c1, c2 = m0 - h0, m1 - h1, m2 - h2
    mn0 = Rm[0, 0] * c0 + Rm[0, 1] * c1 + Rm[0, 2] * c2
    mn1 = Rm[1, 0] * c0 + Rm[1, 1] * c1 + Rm[1, 2] * c2
    mn2 = Rm[2, 0] * c0 + Rm[2, 1] * c1 + Rm[2, 2] * c2
    h = math.hypot(mn0, mn1)
    strength = math.sqrt(h * h + mn2 * mn2)
    if (abs(strength / B - 1.0) > s[SAMPLE_STRENGTH_TOL_FRAC]
            or abs(math.atan2(-mn2, h) - dip) > s[SAMPLE_DIP_TOL_RAD]):
        return NAN
    return _remainder_2pi(math.atan2(mn0, mn1) - D)


@njit(cache=True, error_model="numpy")
def _scalar_update(x, P, PHt, S, nu, W):
    """The heading update: K = P Hᵀ / S, state += K ν, P −= K (P Hᵀ)ᵀ."""
    for i in range(6):
        W.dx[i] = (PHt[i] / S) * nu
    _inject(x, W.dx[0], W.dx[1], W.dx[2], W.dx[3], W.dx[4], W.dx[5])
    T = W.t6
    for i in range(6):
        for j in range(6):
            T[i, j] = P[i, j] - (PHt[i] / S) * PHt[j]
    _symmetrise(P, T)


@njit(cache=True, error_model="numpy")
def _mag(s, x, iv, L, m0, m1, m2, dmc, t_in, W):
    """core.HeadingFilter.update_mag; returns its return value (0/1)."""
    t = x[X_T] if math.isnan(t_in) else t_in
    P = _P(x, L)
    if iv[I_MODE] == M_INIT:
        if math.isnan(x[X_INIT_T0]):
            x[X_INIT_T0] = t
        R = W.r3
        _qmat(x[X_INIT_Q], x[X_INIT_Q + 1], x[X_INIT_Q + 2], x[X_INIT_Q + 3], R)
        for i in range(3):
            x[X_INIT_MAG + i] += R[i, 0] * m0 + R[i, 1] * m1 + R[i, 2] * m2
        iv[I_INIT_N1] += 1
        if t - x[X_INIT_T0] >= s[INIT_DURATION_S] - 1e-9 and iv[I_INIT_N0]:
            n0, n1 = float(iv[I_INIT_N0]), float(iv[I_INIT_N1])
            ma0, ma1, ma2 = x[X_INIT_ACC] / n0, x[X_INIT_ACC + 1] / n0, x[X_INIT_ACC + 2] / n0
            mm0, mm1, mm2 = x[X_INIT_MAG] / n1, x[X_INIT_MAG + 1] / n1, x[X_INIT_MAG + 2] / n1
            _align(s, x, iv,
                   R[0, 0] * ma0 + R[1, 0] * ma1 + R[2, 0] * ma2,
                   R[0, 1] * ma0 + R[1, 1] * ma1 + R[2, 1] * ma2,
                   R[0, 2] * ma0 + R[1, 2] * ma1 + R[2, 2] * ma2,
                   R[0, 0] * mm0 + R[1, 0] * mm1 + R[2, 0] * mm2,
                   R[0, 1] * mm0 + R[1, 1] * mm1 + R[2, 1] * mm2,
                   R[0, 2] * mm0 + R[1, 2] * mm1 + R[2, 2] * mm2)
            x[X_LAST_MAG_T] = t
            iv[I_FL_INIT] = 0
        return 0
    if iv[I_G] > 0:
        _lag_add_mag(x, iv, L, t, m0, m1, m2, x[X_REF_B], W)
        x[X_DELAY] = x[X_LDELAY]
    if t - x[X_LAST_MAG_T] < s[MAG_UPDATE_PERIOD_S] - 1e-9:
        return iv[I_FL_FUSED]
    dt_mag = max(0.0, min(t - x[X_LAST_MAG_T], 1.0))
    x[X_LAST_MAG_T] = t
    R = W.r3
    _qmat(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], R)
    t_att = t - x[X_DELAY]
    if t_att < x[X_T] - 1e-9:
        qm0, qm1, qm2, qm3, gyaw_m, g0, g1, g2, g3 = _attitude_at(x, iv, L, t_att)
    else:
        qm0, qm1, qm2, qm3, gyaw_m = x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], x[X_GYAW]
        g0, g1, g2, g3 = x[X_QG], x[X_QG + 1], x[X_QG + 2], x[X_QG + 3]
    Rm = W.rm3
    _qmat(qm0, qm1, qm2, qm3, Rm)
    if s[HARD_IRON_FROM_ROTATION]:
        _hir_add(s, x, iv, L, t_att, m0, m1, m2, g0, g1, g2, g3)
    mn0 = Rm[0, 0] * m0 + Rm[0, 1] * m1 + Rm[0, 2] * m2
    mn1 = Rm[1, 0] * m0 + Rm[1, 1] * m1 + Rm[1, 2] * m2
    mn2 = Rm[2, 0] * m0 + Rm[2, 1] * m1 + Rm[2, 2] * m2
    h2 = mn0 * mn0 + mn1 * mn1
    strength = math.sqrt(h2 + mn2 * mn2)
    dip = math.atan2(-mn2, math.sqrt(h2))
    azimuth = math.atan2(mn0, mn1)
    # ---- checks ----
    ref_b, ref_dip = x[X_REF_B], x[X_REF_DIP]
    serr = (strength - ref_b) / ref_b
    derr = dip - ref_dip
    x[X_SERR] = serr
    x[X_DERR] = derr
    use_check = s[USE_FIELD_CHECK] != 0.0
    sample_bad = use_check and (abs(serr) > s[SAMPLE_STRENGTH_TOL_FRAC] or abs(derr) > s[SAMPLE_DIP_TOL_RAD])
    dmc_valid = True if (dmc < 0 or s[USE_DMC] == 0.0) else dmc != 0
    iv[I_FL_DMC] = 1 if dmc_valid else 0
    nu = _remainder_2pi(azimuth - s[DECLINATION_RAD])
    mag_yaw = math.atan2(Rm[1, 0], Rm[0, 0]) + nu
    # the quasi-static window: add, then drop what is older than its length
    wl = s[QUASI_STATIC_WINDOW_S]
    ow = L[L_WIN]
    wcap = L[L_WCAP]
    j = (iv[I_WH] + iv[I_WN]) % wcap
    x[ow + W_STRIDE * j] = t
    x[ow + W_STRIDE * j + 1] = strength
    x[ow + W_STRIDE * j + 2] = dip
    x[ow + W_STRIDE * j + 3] = _remainder_2pi(mag_yaw - gyaw_m)
    gframe = s[HEADING_TEST_GYRO_FRAME] != 0.0
    if gframe:  # the field in the gyro-only frame
        f0, f1, f2 = _qrot(g0, g1, g2, g3, m0, m1, m2)
    else:
        f0 = f1 = f2 = 0.0
    x[ow + W_STRIDE * j + 4] = f0
    x[ow + W_STRIDE * j + 5] = f1
    x[ow + W_STRIDE * j + 6] = f2
    iv[I_WN] += 1
    x[X_WS] += strength
    x[X_WS + 1] += strength * strength
    x[X_WS + 2] += dip
    x[X_WS + 3] += dip * dip
    while iv[I_WN] > 0 and t - x[ow + W_STRIDE * iv[I_WH]] > wl:
        h = iv[I_WH]
        bb, dd = x[ow + W_STRIDE * h + 1], x[ow + W_STRIDE * h + 2]
        x[X_WS] -= bb
        x[X_WS + 1] -= bb * bb
        x[X_WS + 2] -= dd
        x[X_WS + 3] -= dd * dd
        iv[I_WH] = (h + 1) % wcap
        iv[I_WN] -= 1
    gain = 1.0
    quasi_static = True
    window_bad = False
    var_fail = head_fail = False
    mb = md = 0.0
    full = _window_full(x, iv, L, t, wl)
    if full:
        n = float(iv[I_WN])
        mb, md = x[X_WS] / n, x[X_WS + 2] / n
        var_b = max(0.0, x[X_WS + 1] / n - mb * mb)
        var_d = max(0.0, x[X_WS + 3] / n - md * md)
        last = (iv[I_WH] + iv[I_WN] - 1) % wcap
        fi, la = ow + W_STRIDE * iv[I_WH], ow + W_STRIDE * last
        if gframe:
            # the window's first and last field, carried into the nav frame through the gyro-only attitude now
            u0, u1, u2 = _qrot(x[X_QG], -x[X_QG + 1], -x[X_QG + 2], -x[X_QG + 3], x[fi + 4], x[fi + 5], x[fi + 6])
            v0, v1, v2 = _qrot(x[X_QG], -x[X_QG + 1], -x[X_QG + 2], -x[X_QG + 3], x[la + 4], x[la + 5], x[la + 6])
            az_a = math.atan2(R[0, 0] * u0 + R[0, 1] * u1 + R[0, 2] * u2, R[1, 0] * u0 + R[1, 1] * u1 + R[1, 2] * u2)
            az_b = math.atan2(R[0, 0] * v0 + R[0, 1] * v1 + R[0, 2] * v2, R[1, 0] * v0 + R[1, 1] * v1 + R[1, 2] * v2)
            dpsi = abs(_remainder_2pi(az_b - az_a))
        else:
            dpsi = abs(_remainder_2pi(x[la + 3] - x[fi + 3]))
        window_bad = use_check and (abs(mb - ref_b) > s[FIELD_STRENGTH_TOL_FRAC] * ref_b
                                    or abs(md - ref_dip) > s[FIELD_DIP_TOL_RAD])
        var_fail = var_b > s[QUASI_STATIC_VAR_NT2] or var_d > s[QUASI_STATIC_DIP_VAR_RAD2]
        head_fail = dpsi > s[QUASI_STATIC_HEADING_RAD]
        quasi_static = not (var_fail or head_fail)
        if s[ADAPTIVE_NOISE]:
            gain = max(s[ADAPTIVE_GAIN_VARIANCE] if var_fail else 1.0, s[ADAPTIVE_GAIN_HEADING] if head_fail else 1.0)
    iv[I_FL_QS] = 1 if quasi_static else 0
    if iv[I_REBASE]:
        sample_bad = window_bad = False
        if full and not (var_fail or head_fail):
            x[X_REF_B] = mb
            x[X_REF_DIP] = md
            iv[I_REBASE] = 0
            iv[I_NREBASE] += 1
    field_inconsistent = window_bad or sample_bad
    iv[I_FL_INCONS] = 1 if field_inconsistent else 0
    window_ok = full and not window_bad
    disturbed = window_bad or not dmc_valid
    # ---- innovation ----
    Hr0, Hr1, Hr2 = R[2, 0], R[2, 1], R[2, 2]
    var_m = s[MAG_NOISE_NT] ** 2 / max(h2, 1.0)
    leak = 0.0
    if h2 > 1.0:
        # Pn[:2, :2] of R P[:3, :3] Rᵀ
        T = W.s3b
        for a in range(2):
            for c in range(3):
                T[a, c] = R[a, 0] * P[0, c] + R[a, 1] * P[1, c] + R[a, 2] * P[2, c]
        p00 = T[0, 0] * R[0, 0] + T[0, 1] * R[0, 1] + T[0, 2] * R[0, 2]
        p01 = T[0, 0] * R[1, 0] + T[0, 1] * R[1, 1] + T[0, 2] * R[1, 2]
        p10 = T[1, 0] * R[0, 0] + T[1, 1] * R[0, 1] + T[1, 2] * R[0, 2]
        p11 = T[1, 0] * R[1, 0] + T[1, 1] * R[1, 1] + T[1, 2] * R[1, 2]
        f = mn2 / h2
        j0, j1 = f * mn0, f * mn1  # ∂azimuth/∂(φ_east, φ_north), as core.py
        leak = (j0 * p00 + j1 * p10) * j0 + (j0 * p01 + j1 * p11) * j1
    r = max(var_m, s[MAG_HEADING_NOISE_FLOOR_RAD] ** 2) * gain + leak
    mode = iv[I_MODE]
    if mode == M_REC:
        r *= s[RECOVERY_NOISE_GAIN]
    x[X_GAIN] = gain
    PHt = W.dx6
    for i in range(6):
        PHt[i] = P[i, 0] * Hr0 + P[i, 1] * Hr1 + P[i, 2] * Hr2
    HPH = Hr0 * PHt[0] + Hr1 * PHt[1] + Hr2 * PHt[2]
    S = HPH + r
    ratio = nu * nu / (s[MAG_GATE_SIGMA] ** 2 * S)
    x[X_INNOV] = nu
    x[X_INNOV_VAR] = S
    x[X_RATIO] = ratio
    rejected = ratio > 1.0
    iv[I_FL_REJ] = 1 if rejected else 0
    usable = not rejected and not sample_bad
    # ---- mode logic ----
    fused = fused_weak = False
    if window_bad:
        iv[I_OUT_BAD] = 1
    if mode == M_MAG:
        if disturbed:
            _set_mode(x, iv, M_GYRO, 2 if not dmc_valid else 3)
        elif not usable:
            if math.isnan(x[X_REJ_SINCE]):
                x[X_REJ_SINCE] = t
            elif t - x[X_REJ_SINCE] > s[REJECTION_TIMEOUT_S]:
                _set_mode(x, iv, M_REC, 4)
        else:
            x[X_REJ_SINCE] = NAN
            fused = True
    elif mode == M_GYRO:
        if disturbed:
            x[X_CLEAR_SINCE] = NAN
            x[X_INSIDE_SINCE] = NAN
            gain_weak = s[DISTURBED_NOISE_GAIN]
            if s[HARD_IRON_TRACKING] and dmc_valid:
                nu_c = _hard_iron_innovation(s, x, Rm, m0, m1, m2, dt_mag, mb if full else ref_b, W)
                if not math.isnan(nu_c):
                    nu, gain_weak = nu_c, s[HARD_IRON_NOISE_GAIN]
                    if s[HARD_IRON_FROM_ROTATION]:  # the compensated field: the sensor's own noise
                        r = max(var_m, s[MAG_HEADING_NOISE_FLOOR_RAD] ** 2) + leak
            if gain_weak > 0.0 and dmc_valid and abs(nu) < s[DISTURBED_GATE_RAD]:
                S = HPH + r * gain_weak
                fused_weak = True
        else:
            if math.isnan(x[X_CLEAR_SINCE]):
                x[X_CLEAR_SINCE] = t
                since = x[X_LEFT_MAG_T]
                scaled = s[HOLDS_SCALE_WITH_OUTAGE] != 0.0 and not iv[I_OUT_BAD] and not math.isnan(since)
                x[X_OUTAGE_S] = t - since if scaled else NAN
            if s[AGREEMENT_FROM_CLEAR] != 0.0:
                # recovering's agreement test runs from here, on the estimate the gyro alone has carried
                if not usable or (s[RECOVERY_EXIT_MEAN] == 0.0 and abs(nu) > s[RECOVERY_EXIT_RAD]):
                    x[X_INSIDE_SINCE] = NAN
                else:
                    _agreement_add(x, t, nu)
            if t - x[X_CLEAR_SINCE] >= _hold(s, x, s[CLEAR_HOLD_S]):
                inside_since = x[X_INSIDE_SINCE]
                _set_mode(x, iv, M_REC, 5)
                x[X_INSIDE_SINCE] = inside_since
    elif mode == M_REC:
        if disturbed:
            _set_mode(x, iv, M_GYRO, 6)
        else:
            if window_ok:
                if math.isnan(x[X_CONS_SINCE]):
                    x[X_CONS_SINCE] = t
            else:
                x[X_CONS_SINCE] = NAN
            consistent = not math.isnan(x[X_CONS_SINCE]) and t - x[X_CONS_SINCE] >= s[RECOVERY_HOLD_S]
            if usable:
                fused = True
                if s[RECOVERY_EXIT_MEAN] == 0.0 and abs(nu) > s[RECOVERY_EXIT_RAD]:
                    x[X_INSIDE_SINCE] = NAN
                elif _agreement_add(x, t, nu) and t - x[X_INSIDE_SINCE] >= _hold(s, x, s[RECOVERY_HOLD_S]):
                    if s[RECOVERY_EXIT_MEAN] == 0.0 or abs(x[X_INSIDE_SUM] / x[X_INSIDE_N]) <= s[RECOVERY_EXIT_RAD]:
                        _set_mode(x, iv, M_MAG, 7)
                    else:  # the mean over the hold is off: judge the next hold afresh
                        x[X_INSIDE_SINCE] = NAN
                        _agreement_add(x, t, nu)
            else:
                x[X_INSIDE_SINCE] = NAN
                if consistent and not sample_bad and quasi_static:
                    lim = s[RECOVERY_SLEW_RAD_S] * dt_mag
                    step = max(-lim, min(lim, nu))
                    _inject(x, Hr0 * step, Hr1 * step, Hr2 * step, 0.0, 0.0, 0.0)
    if fused_weak:
        _scalar_update(x, P, PHt, S, nu, W)
    if fused:
        if s[MAG_VECTOR_FUSION] and iv[I_MODE] == M_MAG and quasi_static and not field_inconsistent:
            D, rdip = s[DECLINATION_RAD], x[X_REF_DIP]
            u0 = math.cos(rdip) * math.sin(D)
            u1 = math.cos(rdip) * math.cos(D)
            u2 = -math.sin(rdip)
            h0 = Rm[0, 0] * u0 + Rm[1, 0] * u1 + Rm[2, 0] * u2
            h1 = Rm[0, 1] * u0 + Rm[1, 1] * u1 + Rm[2, 1] * u2
            hh2 = Rm[0, 2] * u0 + Rm[1, 2] * u1 + Rm[2, 2] * u2
            nm = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
            var_unit = max(var_m, s[MAG_HEADING_NOISE_FLOOR_RAD] ** 2) * h2 / strength ** 2
            _vector_update(x, P, h0, h1, hh2, m0 / nm, m1 / nm, m2 / nm, var_unit, False, W)
        else:
            dx = W.dx
            for i in range(6):
                dx[i] = (PHt[i] / S) * nu
            if iv[I_MODE] == M_REC:
                # re-acquisition never steps the heading faster than recovery_slew_rad_s
                st = abs(Hr0 * dx[0] + Hr1 * dx[1] + Hr2 * dx[2])
                lim = s[RECOVERY_SLEW_RAD_S] * dt_mag
                if st > lim:
                    sc = lim / st
                    for i in range(6):
                        dx[i] *= sc
            _inject(x, dx[0], dx[1], dx[2], dx[3], dx[4], dx[5])
            T = W.t6
            for i in range(6):
                for jj in range(6):
                    T[i, jj] = P[i, jj] - (PHt[i] / S) * PHt[jj]
            _symmetrise(P, T)
        x[X_LAST_FUSED_T] = t
    iv[I_FL_FUSED] = 1 if fused else 0
    return 1 if fused else 0


# =========================================================================================================
# scratch (views into one flat buffer per fleet), outputs, the entry kernels
# =========================================================================================================
class _Work(NamedTuple):
    r3: np.ndarray
    rm3: np.ndarray
    s3: np.ndarray
    s3b: np.ndarray
    m6: np.ndarray
    t6: np.ndarray
    pht: np.ndarray
    k63: np.ndarray
    a63: np.ndarray
    b36: np.ndarray
    x36: np.ndarray
    dx: np.ndarray
    dx6: np.ndarray
    b31: np.ndarray
    x31: np.ndarray
    pn3: np.ndarray
    t3: np.ndarray
    h_g3: np.ndarray


_WORK_FIXED = 9 + 9 + 9 + 6 + 36 + 36 + 18 + 18 + 18 + 18 + 18 + 6 + 6 + 3 + 3 + 9 + 9


def _work_size(gmax: int) -> int:
    return _WORK_FIXED + 3 * max(gmax, 1)


@njit(cache=True, error_model="numpy")
def _work(wb, gmax):
    o = 0
    r3 = wb[o:o + 9].reshape((3, 3))
    o += 9
    rm3 = wb[o:o + 9].reshape((3, 3))
    o += 9
    s3 = wb[o:o + 9].reshape((3, 3))
    o += 9
    s3b = wb[o:o + 6].reshape((2, 3))
    o += 6
    m6 = wb[o:o + 36].reshape((6, 6))
    o += 36
    t6 = wb[o:o + 36].reshape((6, 6))
    o += 36
    pht = wb[o:o + 18].reshape((6, 3))
    o += 18
    k63 = wb[o:o + 18].reshape((6, 3))
    o += 18
    a63 = wb[o:o + 18].reshape((6, 3))
    o += 18
    b36 = wb[o:o + 18].reshape((3, 6))
    o += 18
    x36 = wb[o:o + 18].reshape((3, 6))
    o += 18
    dx = wb[o:o + 6]
    o += 6
    dx6 = wb[o:o + 6]
    o += 6
    b31 = wb[o:o + 3].reshape((3, 1))
    o += 3
    x31 = wb[o:o + 3].reshape((3, 1))
    o += 3
    pn3 = wb[o:o + 9].reshape((3, 3))
    o += 9
    t3 = wb[o:o + 9].reshape((3, 3))
    o += 9
    g = max(gmax, 1)
    h_g3 = wb[o:o + 3 * g].reshape((g, 3))
    return _Work(r3, rm3, s3, s3b, m6, t6, pht, k63, a63, b36, x36, dx, dx6, b31, x31, pn3, t3, h_g3)


@njit(cache=True, error_model="numpy")
def _euler(x):
    """maths.euler_from_matrix of the attitude: (heading, pitch, roll)."""
    w, qx, qy, qz = x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3]
    r00 = 1 - 2 * (qy * qy + qz * qz)
    r10 = 2 * (qx * qy + w * qz)
    r20 = 2 * (qx * qz - w * qy)
    r21 = 2 * (qy * qz + w * qx)
    r22 = 1 - 2 * (qx * qx + qy * qy)
    pitch = math.asin(max(-1.0, min(1.0, r20)))
    roll = math.atan2(r21, r22)
    yaw = math.atan2(r10, r00)
    return (math.pi / 2 - yaw) % TWO_PI, pitch, roll


@njit(cache=True, error_model="numpy")
def _attitude_std(x, L, R, Pn, T):
    """core.HeadingFilter.attitude_std: 1-σ (heading, pitch, roll)."""
    P = _P(x, L)
    _qmat(x[X_Q], x[X_Q + 1], x[X_Q + 2], x[X_Q + 3], R)
    for a in range(3):
        for c in range(3):
            T[a, c] = R[a, 0] * P[0, c] + R[a, 1] * P[1, c] + R[a, 2] * P[2, c]
    for a in range(3):
        for c in range(3):
            Pn[a, c] = T[a, 0] * R[c, 0] + T[a, 1] * R[c, 1] + T[a, 2] * R[c, 2]
    h = math.sqrt(max(Pn[2, 2], 0.0))
    f0, f1 = R[0, 0], R[1, 0]
    n = math.hypot(f0, f1)
    if n > 1e-6:
        f0, f1 = f0 / n, f1 / n
    else:
        f0, f1 = 1.0, 0.0
    r0, r1 = f1, -f0
    pr = (r0 * Pn[0, 0] + r1 * Pn[1, 0]) * r0 + (r0 * Pn[0, 1] + r1 * Pn[1, 1]) * r1
    pf = (f0 * Pn[0, 0] + f1 * Pn[1, 0]) * f0 + (f0 * Pn[0, 1] + f1 * Pn[1, 1]) * f1
    return h, math.sqrt(max(pr, 0.0)), math.sqrt(max(pf, 0.0))


@njit(cache=True, error_model="numpy")
def _output(x, iv, L, o, full_out, ret, changed, W):
    o[O_MODE] = iv[I_MODE]
    o[O_REASON] = iv[I_TR_REASON] if changed else 0
    o[O_FUSED] = iv[I_FL_FUSED]
    o[O_RET] = ret
    o[O_INNOV] = x[X_INNOV]
    o[O_RATIO] = x[X_RATIO]
    o[O_UNCERTAIN] = iv[I_FL_UNC]
    o[O_TSF] = x[X_TSF]
    o[O_Q] = x[X_Q]
    o[O_Q + 1] = x[X_Q + 1]
    o[O_Q + 2] = x[X_Q + 2]
    o[O_Q + 3] = x[X_Q + 3]
    o[O_T] = x[X_T]
    if full_out:
        h, p, r = _euler(x)
        o[O_HEADING] = h
        o[O_PITCH] = p
        o[O_ROLL] = r
        hs, ps, rs = _attitude_std(x, L, W.r3, W.pn3, W.t3)
        o[O_HSTD] = hs
        o[O_PSTD] = ps
        o[O_RSTD] = rs


@njit(cache=True, error_model="numpy")
def _step(S, X, IS, L, wb, slots, kind, t_s, a, b, dt_s, dmc, out, full_out, start):
    """Step the slots through rows start… in order. Returns the number of rows done: fewer than all when a
    slot's window or field ring is full (the caller grows them and calls again from there)."""
    W = _work(wb, L[L_GMAX])
    wcap, mcap = L[L_WCAP], L[L_MCAP]
    for r in range(start, slots.shape[0]):
        k = slots[r]
        s = S[k]
        x = X[k]
        iv = IS[k]
        ntr = iv[I_NTR]
        if kind[r] == 0:
            _imu(s, x, iv, L, a[r, 0], a[r, 1], a[r, 2], b[r, 0], b[r, 1], b[r, 2], dt_s[r], t_s[r], W)
            ret = 0
        else:
            if iv[I_WN] >= wcap or iv[I_MN] >= mcap:
                return r
            ret = _mag(s, x, iv, L, a[r, 0], a[r, 1], a[r, 2], np.int64(dmc[r]), t_s[r], W)
        _output(x, iv, L, out[r], full_out, ret, iv[I_NTR] != ntr, W)
    return slots.shape[0]


@njit(cache=True, error_model="numpy")
def _imu1(S, X, IS, L, wb, k, g0, g1, g2, a0, a1, a2, dt, t):
    """One IMU sample of one slot (the single-vehicle API); returns the slot's mode-change count."""
    W = _work(wb, L[L_GMAX])
    _imu(S[k], X[k], IS[k], L, g0, g1, g2, a0, a1, a2, dt, t, W)
    return IS[k, I_NTR]


@njit(cache=True, error_model="numpy")
def _mag1(S, X, IS, L, wb, k, m0, m1, m2, dmc, t):
    """One magnetometer sample of one slot; returns update_mag's value, or −1 when a ring is full."""
    iv = IS[k]
    if iv[I_WN] >= L[L_WCAP] or iv[I_MN] >= L[L_MCAP]:
        return -1
    W = _work(wb, L[L_GMAX])
    return _mag(S[k], X[k], iv, L, m0, m1, m2, dmc, t, W)


@njit(cache=True, error_model="numpy")
def _align1(S, X, IS, L, k, a0, a1, a2, m0, m1, m2):
    _align(S[k], X[k], IS[k], a0, a1, a2, m0, m1, m2)


@njit(cache=True, error_model="numpy")
def _rebase1(X, IS, L, k):
    """core.HeadingFilter.rebase_field_reference."""
    x, iv = X[k], IS[k]
    if iv[I_MODE] == M_INIT:
        return
    iv[I_REBASE] = 1
    iv[I_WH] = 0
    iv[I_WN] = 0
    x[X_WS] = 0.0
    x[X_WS + 1] = 0.0
    x[X_WS + 2] = 0.0
    x[X_WS + 3] = 0.0
    if iv[I_MODE] == M_GYRO and iv[I_FL_DMC]:
        _set_mode(x, iv, M_REC, 8)


@njit(cache=True, error_model="numpy")
def _euler_std1(X, L, k):
    R = np.empty((3, 3))
    h, p, r = _euler(X[k])
    hs, ps, rs = _attitude_std(X[k], L, R, np.empty((3, 3)), np.empty((3, 3)))
    return h, p, r, hs, ps, rs


# =========================================================================================================
# Python API
# =========================================================================================================
def _layout(wcap: int, mcap: int, gmax: int) -> np.ndarray:
    L = np.zeros(N_L, np.int64)
    L[L_WCAP], L[L_MCAP], L[L_GMAX] = wcap, mcap, gmax
    o = N_X
    for key, size in ((L_P, 36), (L_HIST, 6 * HIST_LEN), (L_WIN, W_STRIDE * wcap), (L_GT, LAG_NBUF), (L_GQ, 4 * LAG_NBUF),
                      (L_GRID, gmax), (L_A, 9 * gmax), (L_B, 3 * gmax), (L_C, gmax), (L_COST, gmax),
                      (L_MAGS, 4 * mcap), (L_HIR, 8 * HIR_LEN)):
        L[key] = o
        o += size
    L[L_TOTAL] = o
    return L


def _lag_grid(s: core.Settings) -> np.ndarray:
    """MagLagEstimator's grid of candidate lags (empty without the online estimate)."""
    if not s.mag_delay_online:
        return np.zeros(0)
    return np.arange(0.0, s.mag_delay_max_s + 1e-12, 0.001)


def settings_row(s: core.Settings) -> np.ndarray:
    return np.array([float(getattr(s, n)) for n in SETTING_NAMES])


class StepOutput(NamedTuple):
    """Per row of a :meth:`FleetHeading.step` call, after the row."""

    heading_rad: np.ndarray  # clockwise from true north, [0, 2π)
    pitch_rad: np.ndarray
    roll_rad: np.ndarray
    heading_std_rad: np.ndarray
    pitch_std_rad: np.ndarray
    roll_std_rad: np.ndarray
    mode: np.ndarray  # int8 code into MODES
    reason: np.ndarray  # int8: the mode change in this row, code into REASONS (0: none)
    mag_fused: np.ndarray  # bool: flags.mag_fused
    mag_return: np.ndarray  # bool: update_mag's return value (magnetometer rows)
    mag_innovation_rad: np.ndarray  # NaN: none yet
    mag_test_ratio: np.ndarray
    heading_uncertain: np.ndarray  # bool
    time_since_mag_fused_s: np.ndarray
    quaternion: np.ndarray  # (N, 4) body → ENU
    t_s: np.ndarray  # the filter's clock


def _as_output(out: np.ndarray) -> StepOutput:
    return StepOutput(out[:, O_HEADING], out[:, O_PITCH], out[:, O_ROLL], out[:, O_HSTD], out[:, O_PSTD],
                      out[:, O_RSTD], out[:, O_MODE].astype(np.int8), out[:, O_REASON].astype(np.int8),
                      out[:, O_FUSED] != 0, out[:, O_RET] != 0, out[:, O_INNOV], out[:, O_RATIO],
                      out[:, O_UNCERTAIN] != 0, out[:, O_TSF], out[:, O_Q:O_Q + 4], out[:, O_T])


class FleetHeading:
    """Many heading filters (slots) in arrays, stepped together by compiled kernels (module docstring)."""

    def __init__(self, capacity: int = 16, window_capacity: int = 128, field_capacity: int = 128):
        self._cap = max(1, int(capacity))
        self._L = _layout(int(window_capacity), int(field_capacity), 51)
        self.S = np.zeros((self._cap, N_SETTINGS))
        self.X = np.zeros((self._cap, int(self._L[L_TOTAL])))
        self.IS = np.zeros((self._cap, N_I), np.int64)
        self._wb = np.zeros(_work_size(int(self._L[L_GMAX])))
        self.settings: list[core.Settings | None] = [None] * self._cap

    # ---- slots ----
    @property
    def capacity(self) -> int:
        return self._cap

    def add(self, settings: core.Settings) -> int:
        """A new filter with these settings; returns its slot."""
        free = np.flatnonzero(self.IS[:, I_USED] == 0)
        if len(free) == 0:
            self._grow(capacity=2 * self._cap)
            free = np.flatnonzero(self.IS[:, I_USED] == 0)
        slot = int(free[0])
        g = len(_lag_grid(settings))
        if g > self._L[L_GMAX]:
            self._grow(gmax=g)
        self.settings[slot] = settings
        self.S[slot] = settings_row(settings)
        self.reset(slot)
        return slot

    def free(self, slot: int) -> None:
        self.IS[slot] = 0
        self.settings[slot] = None

    def reset(self, slot: int) -> None:
        """core.HeadingFilter.reset for one slot."""
        s = self.settings[slot]
        if s is None:
            raise KeyError(f"slot {slot} is not in use")
        L, x, iv = self._L, self.X[slot], self.IS[slot]
        x[:] = 0.0
        iv[:] = 0
        x[X_Q:X_Q + 4] = (1.0, 0.0, 0.0, 0.0)
        x[L[L_P]:L[L_P] + 36] = np.diag([s.init_tilt_std_rad**2] * 2 + [s.init_heading_std_rad**2]
                                        + [s.gyro_bias_init_std_rad_s**2] * 3).ravel()
        x[X_REF_B] = s.ref_field_nt
        x[X_REF_DIP] = s.ref_dip_rad
        x[X_INIT_Q:X_INIT_Q + 4] = (1.0, 0.0, 0.0, 0.0)
        x[X_QG:X_QG + 4] = (1.0, 0.0, 0.0, 0.0)
        x[X_LQ:X_LQ + 4] = (1.0, 0.0, 0.0, 0.0)
        x[X_LAST_ACC_T] = x[X_LAST_MAG_T] = -1e9
        for c in (X_INIT_T0, X_CLEAR_SINCE, X_CONS_SINCE, X_INSIDE_SINCE, X_REJ_SINCE, X_GO_SINCE, X_LEFT_MAG_T,
                  X_OUTAGE_S, X_ACC_LP, X_REST_ALP, X_REST_SINCE, X_INNOV, X_INNOV_VAR, X_RATIO, X_LT_PREV,
                  X_LW_PREV, X_TR_T, X_LP_DT):
            x[c] = math.nan
        x[X_DELAY] = s.mag_delay_s
        x[X_NGV] = s.rest_gyro_noise_rad_s**2
        x[X_NAV] = s.rest_accel_noise_m_s2**2
        x[X_GAIN] = 1.0
        x[X_LLAST_T] = -math.inf
        x[X_HR_LAST] = -math.inf
        x[L[L_GT]:L[L_GT] + LAG_NBUF] = -math.inf
        grid = _lag_grid(s)
        x[L[L_GRID]:L[L_GRID] + len(grid)] = grid
        iv[I_FL_INIT] = iv[I_FL_QS] = iv[I_FL_DMC] = 1
        iv[I_G] = len(grid)
        iv[I_USED] = 1

    def _grow(self, capacity: int | None = None, wcap: int | None = None, mcap: int | None = None,
              gmax: int | None = None) -> None:
        oL = self._L
        cap = capacity or self._cap
        nL = _layout(wcap or int(oL[L_WCAP]), mcap or int(oL[L_MCAP]), gmax or int(oL[L_GMAX]))
        X = np.zeros((cap, int(nL[L_TOTAL])))
        n = self._cap
        X[:n, :N_X] = self.X[:, :N_X]
        for key, size in ((L_P, 36), (L_HIST, 6 * HIST_LEN), (L_GT, LAG_NBUF), (L_GQ, 4 * LAG_NBUF),
                          (L_HIR, 8 * HIR_LEN)):
            X[:n, nL[key]:nL[key] + size] = self.X[:, oL[key]:oL[key] + size]
        og = int(oL[L_GMAX])
        for key, per in ((L_GRID, 1), (L_A, 9), (L_B, 3), (L_C, 1), (L_COST, 1)):
            X[:n, nL[key]:nL[key] + per * og] = self.X[:, oL[key]:oL[key] + per * og]
        IS = np.zeros((cap, N_I), np.int64)
        IS[:n] = self.IS
        # the rings are unrolled: oldest item first
        for key, ih, inn, ocap, w in ((L_WIN, I_WH, I_WN, int(oL[L_WCAP]), W_STRIDE),
                                      (L_MAGS, I_MH, I_MN, int(oL[L_MCAP]), 4)):
            for k in range(n):
                cnt, head = int(IS[k, inn]), int(IS[k, ih])
                idx = (head + np.arange(cnt)) % ocap
                old = self.X[k, oL[key]:oL[key] + w * ocap].reshape(ocap, w)
                X[k, nL[key]:nL[key] + w * cnt] = old[idx].ravel()
                IS[k, ih] = 0
        S = np.zeros((cap, N_SETTINGS))
        S[:n] = self.S
        self.S, self.X, self.IS, self._L, self._cap = S, X, IS, nL, cap
        self.settings += [None] * (cap - n)
        self._wb = np.zeros(_work_size(int(nL[L_GMAX])))

    def _grow_rings(self) -> None:
        full_w = bool((self.IS[:, I_WN] >= self._L[L_WCAP]).any())
        full_m = bool((self.IS[:, I_MN] >= self._L[L_MCAP]).any())
        self._grow(wcap=2 * int(self._L[L_WCAP]) if full_w else None,
                   mcap=2 * int(self._L[L_MCAP]) if full_m else None)

    # ---- stepping ----
    def step(self, slot, kind, t_s, a, b, dt_s, dmc=None, full_output: bool = True) -> StepOutput:
        """Step the slots through the rows (see the module docstring); per-row outputs after each row.
        ``full_output=False`` skips the Euler angles and their σ (NaN then): what a replay that only needs the
        quaternion saves."""
        slot = np.ascontiguousarray(slot, np.int64).reshape(-1)
        n = len(slot)
        kind = np.ascontiguousarray(kind, np.int8).reshape(-1)
        t_s = np.ascontiguousarray(t_s, float).reshape(-1)
        a = np.ascontiguousarray(a, float).reshape(n, 3)
        b = np.ascontiguousarray(b, float).reshape(n, 3) if b is not None else np.zeros((n, 3))
        dt_s = np.ascontiguousarray(dt_s, float).reshape(-1)
        dmc = np.full(n, -1, np.int8) if dmc is None else np.ascontiguousarray(dmc, np.int8).reshape(-1)
        if not (len(kind) == len(t_s) == len(dt_s) == len(dmc) == n):
            raise ValueError("slot, kind, t_s, a, b, dt_s and dmc need one row each")
        if n and (slot.min() < 0 or slot.max() >= self._cap or not self.IS[slot, I_USED].all()):
            raise KeyError("a row names a slot that is not in use")
        out = np.full((n, N_O), math.nan)
        done = 0
        while done < n:
            done = _step(self.S, self.X, self.IS, self._L, self._wb, slot, kind, t_s, a, b, dt_s, dmc, out,
                         full_output, done)
            if done < n:
                self._grow_rings()
        return _as_output(out)

    def rebase_field_reference(self, slot: int) -> None:
        _rebase1(self.X, self.IS, self._L, slot)

    def align(self, slot: int, accel_m_s2, mag_nt) -> None:
        a, m = np.asarray(accel_m_s2, float), np.asarray(mag_nt, float)
        _align1(self.S, self.X, self.IS, self._L, slot, a[0], a[1], a[2], m[0], m[1], m[2])

    # ---- per-slot accessors ----
    def quaternion(self, slot: int) -> np.ndarray:
        return self.X[slot, X_Q:X_Q + 4].copy()

    def euler(self, slot: int) -> tuple[float, float, float]:
        return _euler_std1(self.X, self._L, slot)[:3]

    def attitude_std(self, slot: int) -> tuple[float, float, float]:
        return _euler_std1(self.X, self._L, slot)[3:]

    def heading_rad(self, slot: int) -> float:
        w, x, y, z = self.X[slot, X_Q:X_Q + 4]
        return float(maths.yaw_to_heading(math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))))

    def mode(self, slot: int) -> str:
        return MODES[int(self.IS[slot, I_MODE])]

    def aligned(self, slot: int) -> bool:
        return int(self.IS[slot, I_MODE]) != M_INIT

    def mode_changes(self, slot: int) -> int:
        return int(self.IS[slot, I_NTR])

    def last_transition(self, slot: int) -> tuple[float, str, str, str] | None:
        """(t_s, from, to, reason) of the slot's last mode change, None before the first."""
        iv = self.IS[slot]
        if not iv[I_NTR]:
            return None
        return (float(self.X[slot, X_TR_T]), MODES[int(iv[I_TR_FROM])], MODES[int(iv[I_TR_TO])],
                REASONS[int(iv[I_TR_REASON])])

    def internal_states(self, slot: int) -> core.InternalStates:
        x = self.X[slot]

        def opt(v):
            return None if math.isnan(v) else float(v)

        return core.InternalStates(
            mag_innovation_rad=opt(x[X_INNOV]), mag_innovation_var_rad2=opt(x[X_INNOV_VAR]),
            mag_test_ratio=opt(x[X_RATIO]), mag_noise_gain=float(x[X_GAIN]),
            field_strength_error_frac=float(x[X_SERR]), field_dip_error_rad=float(x[X_DERR]),
            accel_error_m_s2=float(x[X_AERR]), time_since_mag_fused_s=float(x[X_TSF]),
            gyro_only_duration_s=float(x[X_GOD]), heading_std_rad=float(x[X_HSTD]))

    def flags(self, slot: int) -> core.Flags:
        iv = self.IS[slot]
        return core.Flags(initialising=bool(iv[I_FL_INIT]), mag_fused=bool(iv[I_FL_FUSED]),
                          mag_rejected_gate=bool(iv[I_FL_REJ]), field_inconsistent=bool(iv[I_FL_INCONS]),
                          quasi_static=bool(iv[I_FL_QS]), dmc_valid=bool(iv[I_FL_DMC]),
                          accel_ignored=bool(iv[I_FL_ACCIGN]), heading_uncertain=bool(iv[I_FL_UNC]))

    def bias(self, slot: int) -> np.ndarray:
        return self.X[slot, X_BIAS:X_BIAS + 3].copy()

    def covariance(self, slot: int) -> np.ndarray:
        o = int(self._L[L_P])
        return self.X[slot, o:o + 36].reshape(6, 6).copy()

    def field_reference(self, slot: int) -> tuple[float, float]:
        return float(self.X[slot, X_REF_B]), float(self.X[slot, X_REF_DIP])

    def n_rebases(self, slot: int) -> int:
        return int(self.IS[slot, I_NREBASE])

    def at_rest(self, slot: int) -> bool:
        return bool(self.IS[slot, I_AT_REST])

    def mag_delay_s(self, slot: int) -> float:
        return float(self.X[slot, X_DELAY])


class CompiledHeadingFilter:
    """:class:`core.HeadingFilter`'s public API on the compiled kernels (one slot of its own fleet)."""

    def __init__(self, settings: core.Settings | None = None):
        self.settings = settings or core.Settings()
        self._fleet = FleetHeading(1)
        self._slot = self._fleet.add(self.settings)
        self.transitions: list[tuple[float, str, str, str]] = []
        self._ntr = 0

    # ---- state ----
    def reset(self) -> None:
        self._fleet.reset(self._slot)
        self.transitions = []
        self._ntr = 0

    def _note_transitions(self, ntr: int) -> None:
        if ntr != self._ntr:
            self._ntr = ntr
            self.transitions.append(self._fleet.last_transition(self._slot))

    @property
    def mode(self) -> str:
        return MODES[self._fleet.IS[self._slot, I_MODE]]

    @property
    def aligned(self) -> bool:
        return self._fleet.IS[self._slot, I_MODE] != M_INIT

    @property
    def internal_states(self) -> core.InternalStates:
        return self._fleet.internal_states(self._slot)

    @property
    def states(self) -> core.InternalStates:
        return self._fleet.internal_states(self._slot)

    @property
    def flags(self) -> core.Flags:
        return self._fleet.flags(self._slot)

    @property
    def q(self) -> tuple:
        return tuple(float(v) for v in self._fleet.X[self._slot, X_Q:X_Q + 4])

    @property
    def bias(self) -> np.ndarray:
        return self._fleet.bias(self._slot)

    @property
    def P(self) -> np.ndarray:
        return self._fleet.covariance(self._slot)

    @property
    def t_s(self) -> float:
        return float(self._fleet.X[self._slot, X_T])

    @property
    def ref_field_nt(self) -> float:
        return self._fleet.field_reference(self._slot)[0]

    @property
    def ref_dip_rad(self) -> float:
        return self._fleet.field_reference(self._slot)[1]

    @property
    def n_rebases(self) -> int:
        return self._fleet.n_rebases(self._slot)

    @property
    def at_rest(self) -> bool:
        return self._fleet.at_rest(self._slot)

    @property
    def mag_delay_s(self) -> float:
        return self._fleet.mag_delay_s(self._slot)

    def quaternion(self) -> np.ndarray:
        return self._fleet.quaternion(self._slot)

    def euler(self) -> tuple[float, float, float]:
        return self._fleet.euler(self._slot)

    def heading_rad(self) -> float:
        return self._fleet.heading_rad(self._slot)

    def attitude_std(self) -> tuple[float, float, float]:
        return self._fleet.attitude_std(self._slot)

    # ---- updates ----
    def align(self, accel_m_s2, mag_nt) -> None:
        self._fleet.align(self._slot, accel_m_s2, mag_nt)
        self._note_transitions(self._fleet.mode_changes(self._slot))

    def rebase_field_reference(self) -> None:
        self._fleet.rebase_field_reference(self._slot)
        self._note_transitions(self._fleet.mode_changes(self._slot))

    def update(self, gyro_rad_s, accel_m_s2, mag_nt=None, dt_s: float = 0.01, dmc_valid: bool | None = None):
        self.update_imu(gyro_rad_s, accel_m_s2, dt_s)
        if mag_nt is not None:
            self.update_mag(mag_nt, dmc_valid)
        return self.mode

    def update_imu(self, gyro_rad_s, accel_m_s2, dt_s: float, t_s: float | None = None) -> None:
        f = self._fleet
        g, a = gyro_rad_s, accel_m_s2
        ntr = _imu1(f.S, f.X, f.IS, f._L, f._wb, self._slot, float(g[0]), float(g[1]), float(g[2]), float(a[0]),
                    float(a[1]), float(a[2]), float(dt_s), math.nan if t_s is None else float(t_s))
        if ntr != self._ntr:
            self._note_transitions(ntr)

    def update_mag(self, mag_nt, dmc_valid: bool | None = None, t_s: float | None = None) -> bool:
        f = self._fleet
        m = mag_nt
        d = -1 if dmc_valid is None else (1 if dmc_valid else 0)
        t = math.nan if t_s is None else float(t_s)
        while True:
            ret = _mag1(f.S, f.X, f.IS, f._L, f._wb, self._slot, float(m[0]), float(m[1]), float(m[2]), d, t)
            if ret >= 0:
                break
            f._grow_rings()
        ntr = int(f.IS[self._slot, I_NTR])
        if ntr != self._ntr:
            self._note_transitions(ntr)
        return bool(ret)


# =========================================================================================================
# whole recordings in one call
# =========================================================================================================
def recording_rows(gyro_rad_s, accel_m_s2, mag_nt, dt_s, dmc=None, t_imu_s=None, t_mag_s=None):
    """Event rows for one vehicle: (kind, t_s, a, b, dt_s, dmc, imu_index_of_row).

    Without times (``t_imu_s`` None): sample i is an IMU step of ``dt_s`` (the first of 0) then, when
    ``mag_nt`` has a row i that is not NaN, that magnetometer sample — ``heading_broad.run_magmesh``'s order,
    on the filter's own clock. With ``t_imu_s`` and ``t_mag_s``: the IMU samples step by their time
    differences (the first by 0) on the dt clock, and each magnetometer sample follows the IMU samples at
    or before its time (+1e-9) — ``eval_heading.run_filter_on_drive``'s order."""
    g = np.asarray(gyro_rad_s, float)
    acc = np.asarray(accel_m_s2, float)
    n = len(g)
    if t_imu_s is None:
        m = np.asarray(mag_nt, float)
        has = ~np.isnan(m).any(axis=1)
        n_rows = n + int(has.sum())
        pos_imu = np.arange(n) + np.concatenate([[0], np.cumsum(has)[:-1]])
        pos_mag = pos_imu[has] + 1
        kind = np.zeros(n_rows, np.int8)
        kind[pos_mag] = 1
        a = np.empty((n_rows, 3))
        b = np.zeros((n_rows, 3))
        a[pos_imu], b[pos_imu] = g, acc
        a[pos_mag] = m[has]
        dts = np.zeros(n_rows)
        dts[pos_imu] = np.where(np.arange(n) == 0, 0.0, dt_s) if np.ndim(dt_s) == 0 else np.asarray(dt_s, float)
        dm = np.full(n_rows, -1, np.int8)
        if dmc is not None:
            dm[pos_mag] = np.asarray(dmc, np.int8)[has]
        return kind, np.full(n_rows, math.nan), a, b, dts, dm, pos_imu, pos_mag
    t_imu = np.asarray(t_imu_s, float)
    t_mag = np.asarray(t_mag_s, float)
    m = np.asarray(mag_nt, float)
    # magnetometer sample i goes after the IMU samples with t_imu <= t_mag[i] + 1e-9
    after = np.searchsorted(t_imu, t_mag + 1e-9, side="right")  # IMU rows before it
    n_rows = n + len(t_mag)
    pos_mag = after + np.arange(len(t_mag))
    is_mag = np.zeros(n_rows, bool)
    is_mag[pos_mag] = True
    pos_imu = np.flatnonzero(~is_mag)
    kind = is_mag.astype(np.int8)
    a = np.empty((n_rows, 3))
    b = np.zeros((n_rows, 3))
    a[pos_imu], b[pos_imu] = g, acc
    a[pos_mag] = m
    dts = np.zeros(n_rows)
    dts[pos_imu] = np.diff(t_imu, prepend=t_imu[0])
    dm = np.full(n_rows, -1, np.int8)
    if dmc is not None:
        dm[pos_mag] = np.asarray(dmc, np.int8)
    return kind, np.full(n_rows, math.nan), a, b, dts, dm, pos_imu, pos_mag


def run_recording(settings: core.Settings, gyro_rad_s, accel_m_s2, mag_nt, dt_s=None, dmc=None, t_imu_s=None,
                  t_mag_s=None, full_output: bool = False):
    """A whole recording of one vehicle in one compiled call (see :func:`recording_rows`); returns
    (StepOutput of every row, IMU row indices, magnetometer row indices, the fleet)."""
    kind, t, a, b, dts, dm, pos_imu, pos_mag = recording_rows(gyro_rad_s, accel_m_s2, mag_nt, dt_s, dmc, t_imu_s,
                                                              t_mag_s)
    fleet = FleetHeading(1)
    slot = fleet.add(settings)
    out = fleet.step(np.full(len(kind), slot), kind, t, a, b, dts, dm, full_output=full_output)
    return out, pos_imu, pos_mag, fleet


# =========================================================================================================
# warm-up
# =========================================================================================================
ENTRY_KERNELS = (_step, _imu1, _mag1, _align1, _rebase1, _euler_std1)
_READY = False
_WARMING = None  # the background warm-up process this process started


def kernels_ready() -> bool:
    """Whether every entry kernel is compiled in this process or loads from numba's disk cache (a first use
    then costs a fraction of a second, not a compile)."""
    global _READY
    if _READY:
        return True
    try:
        ok = all(k.signatures or k._cache._cache_file._load_index() for k in ENTRY_KERNELS)
    except Exception:  # noqa: BLE001 — numba's cache internals changed: treat as not cached
        ok = all(k.signatures for k in ENTRY_KERNELS)
    _READY = bool(ok)
    return _READY


def warm_in_background(log=None) -> None:
    """Start ``python -m services.heading_fuser.compiled --warm`` once per process (it compiles every kernel
    into the disk cache, and leaves at once when another warm-up holds the lock)."""
    global _WARMING
    if _WARMING is not None:
        return
    import os
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    _WARMING = subprocess.Popen([sys.executable, "-m", "services.heading_fuser.compiled", "--warm", "--quiet"],
                                cwd=root, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True, env=dict(os.environ))
    if log is not None:
        log.info("heading_fuser: compiled kernels not cached yet: compiling them in the background (pid %d); "
                 "the reference filter serves until then", _WARMING.pid)


def warm() -> float:
    """Compile (or load from numba's disk cache) every kernel; returns the seconds it took."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    for s in (core.Settings(init_duration_s=0.0), core.Settings(mag_delay_online=True, rest_detection=True,
                                                                  gravity_lpf_tau_s=3.0, init_duration_s=0.0,
                                                                  hard_iron_tracking=True)):
        f = CompiledHeadingFilter(s)
        f.update_imu((0.0, 0.0, 0.1), (0.0, 0.0, 9.8), 0.01)
        f.update_mag((20000.0, 0.0, -40000.0), True)
        f.align((0.0, 0.0, 9.8), (20000.0, 0.0, -40000.0))
        f.rebase_field_reference()
        f.euler()
        f.attitude_std()
        n = 4
        fleet = FleetHeading(2)
        k = fleet.add(s)
        fleet.step(np.full(n, k), np.array([0, 1, 0, 1]), np.full(n, math.nan), rng.normal(size=(n, 3)),
                   rng.normal(size=(n, 3)), np.full(n, 0.01), np.array([-1, 1, -1, 0]))
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] != "--warm":
        print("usage: python -m services.heading_fuser.compiled --warm [--quiet]   (compile every kernel into "
              "numba's disk cache; a no-op that takes < 1 s when it is warm)")
        return 2
    import fcntl
    from pathlib import Path

    lock_dir = Path(__file__).resolve().parent / "__pycache__"
    try:
        lock_dir.mkdir(exist_ok=True)
        lock = open(lock_dir / "compiled.warm.lock", "w")  # noqa: SIM115 — held until the process ends
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        if "--quiet" not in argv:
            print("heading_fuser compiled kernels: another warm-up is compiling them")
        return 0
    except OSError:
        pass  # a read-only tree: numba caches elsewhere (NUMBA_CACHE_DIR) or not at all; compile anyway
    cold = not kernels_ready()
    took = warm()
    if "--quiet" not in argv:
        print(f"heading_fuser compiled kernels ready in {took:.1f} s ({'compiled' if cold else 'from the disk cache'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
