"""The calibration service's logic on a whole fleet: state in arrays over vehicle × sensor *slots*, a frame's rows
in one compiled pass.

Pure numpy + numba; never imports zenoh. The per-vehicle classes of :mod:`services.calibration.core`
(:class:`~core.SensorCalibrator`, :class:`~core.VehicleCalibration`) and :class:`~online_ekf.HardIronEkf` stay the
reference; ``tests/test_calibration_fleet.py`` holds this form to the same parameter sets, compensated fields and
EKF estimates on simulated drives. The methods are theirs, unchanged (docs/methods.md#calibration): the fits are
the same Two-Step LS / ARLS (IGG-III) calls on the same windows (:func:`core.fit_window`).

A *vehicle slot* holds what the reference's :class:`~core.VehicleCalibration` keeps per vehicle (the IMU window,
the GNSS speed-rate window, declination, whether its online EKF runs); a *sensor slot* what a
:class:`~core.SensorCalibrator` and a :class:`~core.SensorOnline` keep per magnetometer (the fit window, the last
64 samples for the GNSS epochs, the parameter set in use, the EKF and its fused epochs)::

    fc = FleetCalibration(CalibrationSettings(), OnlineSettings(), fit_budget_frac=0.04)
    v = fc.add_vehicle("car-1", online=True)
    step = fc.step([MagIn("1", vi, fc.sensor_slots(v_of_rows, "1"), t, b), ImuIn(...), GnssIn(...)])
    step.h[0], step.usable[0], step.param_ids(0), step.events

**Order.** :meth:`FleetCalibration.step` takes a frame's streams in the frame's order and handles each vehicle's
rows in sample-time order across its streams, rows at equal times in stream order: the order in which the
runtime hands the same frame's samples one by one to ``on_message``. A row is handled exactly as the reference
handles that sample: a magnetometer row updates its window (decimation at ``sample_interval_s``, the clock-went-back
reset, ``window_s``), the ring of its last 64 samples, may fall due for a fit, and is compensated with the set in
use (``h = M (m − offset)``); an IMU row enters its vehicle's IMU window; a GNSS row updates the speed rate and runs
the EKF of every sensor of its vehicle (window means of the IMU and of the recent magnetometer samples, a re-base
on a new static fit, the update, the fused-epoch ring) and decides whether the estimate becomes a parameter set.
All of this runs in one compiled kernel (``_run``) over the whole frame. It stops, hands over to Python and resumes
at the same row only where Python objects change: a fit falls due (:func:`core.fit_window`), an EKF estimate
becomes a parameter set (the :class:`~core.ParamRecord` with its sentence), or a vehicle's IMU or speed window
needs a larger ring.

**Fit scheduling.** A fit costs milliseconds (ARLS on the balanced subset of a window of up to 12,000 samples):
at 500 vehicles × 2 sensors every ``refit_interval_s`` (5 s) that is 200 fits/s, far more than a stage's share of
a core. ``fit_budget_frac`` caps the CPU time fits take (thread CPU time, a token bucket refilled at that share of
wall time, at most 1 s of it banked): a fit that falls due runs at its row while no fit is waiting and the budget
has time left, else it waits in a queue; waiting fits run at the start of the next :meth:`~FleetCalibration.step`
or :meth:`~FleetCalibration.run_queued` (the service's tick), the most overdue first (sample time since it fell
due), on the window as it is then. Every due fit runs eventually; none is dropped; a sensor waiting for its fit
keeps compensating with the set in use. ``fit_lag_s`` (how overdue each fit ran, max and median over the last
1,000) is in :meth:`~FleetCalibration.scheduler_status`. With ``fit_budget_frac = 0`` (no limit) every fit runs
at the row at which it falls due, as the reference's.

**Memory.** The fit window keeps each sample's field as float32 and its time as float64 (20 bytes; the
reference rounds the same way, see :class:`core.SensorCalibrator`): a 600 s window decimated to 20 Hz is at most
12,002 samples, 240 kB per sensor, 240 MB for 500 vehicles × 2 sensors once every window is full (the rings are
allocated zeroed, so pages are committed only as they fill). float32 keeps 24 significant bits: ≤ 0.004 nT at
the Earth's field, far below any magnetometer's noise (tens of nT), so the fits do not change measurably. A
bound on the samples kept that preserves heading/attitude coverage (fewer samples where the window holds many
of one direction) would cut the memory further, but it changes which samples the fit sees — the paper's fit on
the window — so it is not done; ``window_max_samples`` bounds the count plainly (oldest first) for settings
without decimation.

**Numbers.** Windows, decimation, due times, the IMU and recent-magnetometer means (summed in the reference's
order) and so the fits' inputs agree with the reference to the bit, and so do the fitted sets on the test drives.
The EKF, the GNSS speed rate and the compensation agree to rounding, not to the bit: the reference's 3 × 3 products
and dot products go through BLAS, the kernel through plain loops (tests: 1e-9 relative; measured ≤ 3e-16 on the
compensated field, ≤ 3e-12 nT on the EKF estimate). Declinations come from :class:`Declinations` (IGRF as
``maths.earth_field_enu_nt``, computed for many positions at once).

Kernels compile on first use and are cached on disk (``__pycache__``); ``python -m services.calibration.fleet
--warm`` compiles (or loads) them and says how long it took. Only the 3-state EKF (the service's) runs here:
``EkfSettings.estimate_mount_yaw`` is refused.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from magmesh import magcal

from . import online_ekf
from .core import (
    USABLE,
    CalibrationSettings,
    FitAttempt,
    OnlineSettings,
    ParamRecord,
    fit_window,
    new_param_id,
    sensor_states,
)

# ---- layouts shared by the kernels and Python ----------------------------------------------------------------------

#: status of the set in use, by code
ST_NONE, ST_OK, ST_MANIFEST, ST_CONVERGING, ST_REFUSED = range(5)
STATUS_CODE = {"ok": ST_OK, "manifest": ST_MANIFEST, "converging": ST_CONVERGING, "refused": ST_REFUSED}

# sensor slot floats (SF)
(F_LAST_KEPT, F_LAST_FIT, F_DUE_T, F_LAST_T, F_T_LAST, F_INNOV, F_INNOV_VAR, F_TEST_RATIO, F_TILT_SQ,
 F_LAST_CONV_T, F_LAST_OK_T, F_EV_RMS_NEW, F_EV_RMS_OLD) = range(13)
F_CUR_OFF = 13  # 3: offset of the set in use
F_CUR_M = 16  # 9: its matrix, row-major
F_X = 25  # 3: EKF estimate
F_PRIOR = 28  # 3: EKF prior
F_P = 31  # 9: EKF covariance
F_EKF_M = 40  # 9: the EKF's matrix (of the set it was based on)
F_EV_OFF = 49  # 3: the applied offset of an EKF record
N_F = 52
# sensor slot ints (SI)
(I_VSLOT, I_W_HEAD, I_W_N, I_R_HEAD, I_R_N, I_EP_HEAD, I_EP_N, I_CUR_STATUS, I_CUR_EKF, I_CUR_VER, I_BASE_VER,
 I_EKF_ON, I_N_FUSED, I_N_REJ, I_N_SKIP, I_FUSED, I_PENDING, I_IN_USE, I_EV_KIND, I_EV_INUSE) = range(20)
I_CUR_OBS = 20  # 3
I_EV_OBS = 23  # 3
N_I = 26
# vehicle slot floats (VF): the declination override (NaN: from the GNSS position), a GNSS row's pre-work, the
# rounded position of its last GNSS row and the declination there, its last GNSS row's PDOP and speed (status)
(VF_DECL, VF_RATE, VF_ROLL, VF_PITCH, VF_YAW_RATE, VF_CELL_LAT, VF_CELL_LON, VF_CELL_ALT, VF_CELL_DECL, VF_G_PDOP,
 VF_G_SPEED) = range(11)
N_VF = 11
# vehicle slot ints (VI): its last GNSS row's fix (index in GNSS_FIXES, −1 none) and satellites; its sensor slots
# from VI_SENS on, in the order they were created
VI_IN_USE, VI_ONLINE, VI_IMU_HEAD, VI_IMU_N, VI_SR_HEAD, VI_SR_N, VI_NSENS, VI_G_FIX, VI_G_SATS = range(9)
VI_SENS = 9
#: fix types of the gnss message (schemas/messages.py), by their code in VI_G_FIX
GNSS_FIXES = ("none", "2d", "3d", "dgps", "rtk_float", "rtk_fixed")
_FIX_CODE = {f: i for i, f in enumerate(GNSS_FIXES)}
_GOOD_FIX = np.array([f in online_ekf.GOOD_FIX for f in GNSS_FIXES])
# settings vector
(C_WINDOW, C_INTERVAL, C_REFIT, C_IMU_WINDOW, C_RW2, C_HN2, C_VEL_STD, C_MIN_SPEED, C_MAX_YAW, C_GATE2, C_OBS_RATIO,
 C_CONV_STD, C_MIN_TILT, C_PRIOR_STD, C_CONV_PUB, C_MIN_CHANGE, C_EKF_IMPROVE, C_MIN_INTERVAL, C_MIN_EPOCHS,
 C_TILT_ACCEL, C_SR_WINDOW, C_MIN_SATS, C_MAX_PDOP) = range(23)
N_CFG = 23
# GNSS input columns: speed, course, declination, satellites, PDOP, fix type (its code in GNSS_FIXES, −1 another)
# and whether that fix type is good enough (online_ekf.GOOD_FIX)
G_SPEED, G_COURSE, G_DECL, G_SATS, G_PDOP, G_FIX, G_GOOD_FIX = range(7)
N_G = 7
# epoch ring columns: m (3), course, roll, pitch, declination
N_EP = 7
#: samples of a sensor kept for the GNSS epochs (the reference's deque(maxlen=64))
RECENT = 64
# what the kernel returns
DONE, STOP_FIT, STOP_EKF, STOP_GROW_IMU, STOP_GROW_SR = range(5)
# EKF record kinds
EV_CONVERGING, EV_OK = 1, 2
# input kinds in the merged order
K_MAG, K_IMU, K_GNSS = 0, 1, 2

_TWO_PI = 2.0 * math.pi
_PI = math.pi


# ---- the kernels (plain Python here; compiled by numba on first use, see _kernels) -----------------------------


def _merge_py(vi, t, starts, ends, out):
    """Rows of several streams, each sorted by (vehicle, time), merged by (vehicle, time, stream)."""
    ns = starts.shape[0]
    cur = starts.copy()
    k = 0
    while True:
        best = -1
        for s in range(ns):
            c = cur[s]
            if c < ends[s]:
                if best < 0:
                    best = s
                else:
                    b = cur[best]
                    if vi[c] < vi[b] or (vi[c] == vi[b] and t[c] < t[b]):
                        best = s
        if best < 0:
            return k
        out[k] = cur[best]
        cur[best] += 1
        k += 1


def _rot_py(roll, pitch):
    """Ry(−θ) Rx(φ) (maths.rot_y(−pitch) @ maths.rot_x(roll)), row-major 9 (a tuple: no allocation)."""
    c = math.cos(-pitch)
    s = math.sin(-pitch)
    cr = math.cos(roll)
    sr = math.sin(roll)
    return (c, s * sr, s * cr, 0.0, cr, -sr, -s, c * sr, c * cr)


def _heading_rms_py(EP, s, n_ep, head, off, M):
    """RMS of course − magnetic heading over a sensor's fused epochs (SensorOnline.heading_rms)."""
    if n_ep == 0:
        return math.inf
    cap = EP.shape[1]
    acc = 0.0
    for q in range(n_ep):
        e = head + q
        if e >= cap:
            e -= cap
        d0 = EP[s, e, 0] - off[0]
        d1 = EP[s, e, 1] - off[1]
        d2 = EP[s, e, 2] - off[2]
        h0 = M[0] * d0 + M[1] * d1 + M[2] * d2
        h1 = M[3] * d0 + M[4] * d1 + M[5] * d2
        h2 = M[6] * d0 + M[7] * d1 + M[8] * d2
        R = _rot(EP[s, e, 4], EP[s, e, 5])
        l0 = R[0] * h0 + R[1] * h1 + R[2] * h2
        l1 = R[3] * h0 + R[4] * h1 + R[5] * h2
        psi = (math.atan2(l1, l0) + EP[s, e, 6]) % _TWO_PI
        err = (EP[s, e, 3] - psi + _PI) % _TWO_PI - _PI
        acc += err * err
    return math.sqrt(acc / n_ep)


def _rebase_py(s, cfg, SF, SI):
    """Restart a sensor's EKF around the set in use (SensorOnline.rebase)."""
    p2 = cfg[C_PRIOR_STD] * cfg[C_PRIOR_STD]
    for i in range(3):
        SF[s, F_PRIOR + i] = SF[s, F_CUR_OFF + i]
        SF[s, F_X + i] = SF[s, F_CUR_OFF + i]
    for i in range(9):
        SF[s, F_P + i] = 0.0
        SF[s, F_EKF_M + i] = SF[s, F_CUR_M + i]
    SF[s, F_P + 0] = p2
    SF[s, F_P + 4] = p2
    SF[s, F_P + 8] = p2
    SF[s, F_T_LAST] = math.nan
    SF[s, F_INNOV] = math.nan
    SF[s, F_INNOV_VAR] = math.nan
    SF[s, F_TEST_RATIO] = math.nan
    SF[s, F_TILT_SQ] = 0.0
    SI[s, I_N_FUSED] = 0
    SI[s, I_N_REJ] = 0
    SI[s, I_N_SKIP] = 0
    SI[s, I_FUSED] = 0
    SI[s, I_EP_HEAD] = 0
    SI[s, I_EP_N] = 0
    SI[s, I_BASE_VER] = SI[s, I_CUR_VER]


def _ekf_update_py(s, t, m, course, roll, pitch, decl, speed, yaw_rate, ok, cfg, SF, SI, scr):
    """One GNSS epoch of a sensor's EKF (HardIronEkf.update, 3 states). True when fused. ``scr``: scratch."""
    tl = SF[s, F_T_LAST]
    if not math.isnan(tl) and t >= tl:
        dt = max(0.0, t - tl)
        q = cfg[C_RW2] * dt
        SF[s, F_P + 0] += q
        SF[s, F_P + 4] += q
        SF[s, F_P + 8] += q
    SF[s, F_T_LAST] = t
    SI[s, I_FUSED] = 0
    if not ok or speed < cfg[C_MIN_SPEED] or abs(yaw_rate) > cfg[C_MAX_YAW]:
        SI[s, I_N_SKIP] += 1
        return False
    M = SF[s, F_EKF_M:F_EKF_M + 9]
    d0 = m[0] - SF[s, F_X]
    d1 = m[1] - SF[s, F_X + 1]
    d2 = m[2] - SF[s, F_X + 2]
    h0 = M[0] * d0 + M[1] * d1 + M[2] * d2
    h1 = M[3] * d0 + M[4] * d1 + M[5] * d2
    h2 = M[6] * d0 + M[7] * d1 + M[8] * d2
    R = _rot(roll, pitch)
    l0 = R[0] * h0 + R[1] * h1 + R[2] * h2
    l1 = R[3] * h0 + R[4] * h1 + R[5] * h2
    psi = (math.atan2(l1, l0) + decl) % _TWO_PI
    lh2 = max(l0 * l0 + l1 * l1, 1e-9)
    g0 = -l1 / lh2
    g1 = l0 / lh2
    # H = −(dψ/dl · R · M), dψ/dl = [g0, g1, 0]
    a0 = g0 * R[0] + g1 * R[3]
    a1 = g0 * R[1] + g1 * R[4]
    a2 = g0 * R[2] + g1 * R[5]
    H = scr[0:3]
    H[0] = -(a0 * M[0] + a1 * M[3] + a2 * M[6])
    H[1] = -(a0 * M[1] + a1 * M[4] + a2 * M[7])
    H[2] = -(a0 * M[2] + a1 * M[5] + a2 * M[8])
    nf = SI[s, I_N_FUSED]
    excited = nf >= 10 and math.sqrt(SF[s, F_TILT_SQ] / nf) >= cfg[C_MIN_TILT]
    if not excited:
        H[2] = 0.0
    z = (course - psi - 0.0 + _PI) % _TWO_PI - _PI
    cn = cfg[C_VEL_STD] / max(speed, 0.1)
    r = cfg[C_HN2] + cn * cn
    P = SF[s, F_P:F_P + 9]
    HP0 = H[0] * P[0] + H[1] * P[3] + H[2] * P[6]
    HP1 = H[0] * P[1] + H[1] * P[4] + H[2] * P[7]
    HP2 = H[0] * P[2] + H[1] * P[5] + H[2] * P[8]
    S = HP0 * H[0] + HP1 * H[1] + HP2 * H[2] + r
    SF[s, F_INNOV] = z
    SF[s, F_INNOV_VAR] = S
    tr = z * z / (cfg[C_GATE2] * S)
    SF[s, F_TEST_RATIO] = tr
    if tr > 1.0:
        SI[s, I_N_REJ] += 1
        return False
    K = scr[3:6]
    for i in range(3):
        K[i] = (P[3 * i] * H[0] + P[3 * i + 1] * H[1] + P[3 * i + 2] * H[2]) / S
    for i in range(3):
        SF[s, F_X + i] = SF[s, F_X + i] + K[i] * z
    A = scr[6:15]  # I − K Hᵀ
    for i in range(3):
        for j in range(3):
            A[3 * i + j] = (1.0 if i == j else 0.0) - K[i] * H[j]
    AP = scr[15:24]
    for i in range(3):
        for j in range(3):
            AP[3 * i + j] = A[3 * i] * P[j] + A[3 * i + 1] * P[3 + j] + A[3 * i + 2] * P[6 + j]
    for i in range(3):
        for j in range(3):
            P[3 * i + j] = (AP[3 * i] * A[3 * j] + AP[3 * i + 1] * A[3 * j + 1] + AP[3 * i + 2] * A[3 * j + 2]
                            + K[i] * K[j] * r)
    SI[s, I_N_FUSED] = nf + 1
    SF[s, F_TILT_SQ] += roll * roll + pitch * pitch
    SI[s, I_FUSED] = 1
    return True


def _record_check_py(s, t, cfg, SF, SI, EP, scr):
    """Whether the EKF estimate becomes a parameter set now (VehicleCalibration._maybe_ekf_record's decisions):
    0 no, EV_CONVERGING, EV_OK; the record's offset, observability and heading residuals are left in the slot."""
    nf = SI[s, I_N_FUSED]
    if nf == 0:
        return 0
    excited = nf >= 10 and math.sqrt(SF[s, F_TILT_SQ] / nf) >= cfg[C_MIN_TILT]
    std = scr[24:27]
    obs = scr[27:30]  # 1.0 observable, 0.0 not
    off = scr[30:33]
    any_obs = False
    for i in range(3):
        std[i] = math.sqrt(SF[s, F_P + 4 * i])
        obs[i] = 1.0 if std[i] / cfg[C_PRIOR_STD] < cfg[C_OBS_RATIO] else 0.0
    if not excited:
        obs[2] = 0.0
    converged = False
    for i in range(3):
        off[i] = SF[s, F_X + i] if obs[i] != 0.0 else SF[s, F_PRIOR + i]
        any_obs = any_obs or obs[i] != 0.0
    if any_obs:
        converged = True
        for i in range(3):
            if obs[i] != 0.0 and not std[i] < cfg[C_CONV_STD]:
                converged = False
    st = SI[s, I_CUR_STATUS]
    has_cur = st != ST_NONE
    trusted = st == ST_OK or st == ST_MANIFEST
    for i in range(3):
        o = obs[i] != 0.0
        if trusted and SI[s, I_CUR_OBS + i] != 0:
            o = True
        SI[s, I_EV_OBS + i] = 1 if o else 0
        SF[s, F_EV_OFF + i] = off[i]
    if not converged:
        if trusted or t - SF[s, F_LAST_CONV_T] < cfg[C_CONV_PUB]:
            return 0
        SI[s, I_EV_INUSE] = 0
        return EV_CONVERGING
    base_off = scr[33:36]
    base_M = scr[36:45]
    for i in range(3):
        base_off[i] = 0.0
    for i in range(9):
        base_M[i] = 1.0 if i % 4 == 0 else 0.0
    if has_cur:
        for i in range(3):
            base_off[i] = SF[s, F_CUR_OFF + i]
        for i in range(9):
            base_M[i] = SF[s, F_CUR_M + i]
    if trusted:
        sh = 0.0
        for i in range(3):
            sh += (off[i] - base_off[i]) ** 2
        sig = 0.0
        if any_obs:
            for i in range(3):
                if obs[i] != 0.0:
                    sig += std[i] * std[i]
            sig = math.sqrt(sig)
        else:
            sig = math.inf
        if math.sqrt(sh) < max(cfg[C_MIN_CHANGE], 4.0 * sig):
            return 0
        if t - SF[s, F_LAST_OK_T] < cfg[C_MIN_INTERVAL]:
            return 0
    n_ep = SI[s, I_EP_N]
    if n_ep < cfg[C_MIN_EPOCHS]:
        return 0
    rms_new = _heading_rms(EP, s, n_ep, SI[s, I_EP_HEAD], off, SF[s, F_EKF_M:F_EKF_M + 9])
    rms_old = _heading_rms(EP, s, n_ep, SI[s, I_EP_HEAD], base_off, base_M) if has_cur else math.inf
    if trusted and not rms_new < cfg[C_EKF_IMPROVE] * rms_old:
        return 0
    SF[s, F_EV_RMS_NEW] = rms_new
    SF[s, F_EV_RMS_OLD] = rms_old
    SI[s, I_EV_INUSE] = 1 if trusted else 0
    return EV_OK


def _run_py(k0, phase0, allow_fit, order, kind, kidx, mag_slot, mag_t, mag_b, imu_v, imu_t, imu_g, imu_a, g_v, g_t,
            g_f, cfg, SF, SI, VF, VI, WT, WM, RT, RM, EP, IT, IG, IA, ST, SV, out_h, out_ver, out_use, pend, npend):
    """Rows ``order[k0:]`` of a frame (see the module's description). Returns (code, k, j): DONE, or where it
    stopped: STOP_FIT at mag row k (resume with phase 1: compensate it), STOP_EKF at GNSS row k after sensor j
    (resume with phase j + 2), STOP_GROW_* before row k changed anything (resume with phase 0)."""
    phase = phase0
    wcap = WT.shape[1]
    ecap = EP.shape[1]
    m = np.empty(3)
    scr = np.empty(48)  # the EKF's scratch: no allocation per epoch
    for k in range(k0, order.shape[0]):
        i = order[k]
        kd = kind[i]
        r = kidx[i]
        if kd == K_MAG:
            s = mag_slot[r]
            t = mag_t[r]
            if phase == 0:
                # the fit window (SensorCalibrator.update)
                if t < SF[s, F_LAST_KEPT] - 1.0:  # the clock went back: the window starts again
                    SI[s, I_W_HEAD] = 0
                    SI[s, I_W_N] = 0
                    SF[s, F_LAST_KEPT] = -math.inf
                    SF[s, F_LAST_FIT] = -math.inf
                if not t - SF[s, F_LAST_KEPT] < cfg[C_INTERVAL]:
                    SF[s, F_LAST_KEPT] = t
                    head = SI[s, I_W_HEAD]
                    n = SI[s, I_W_N]
                    if n == wcap:  # full (window_max_samples): the oldest leaves
                        head += 1
                        if head == wcap:
                            head = 0
                        n -= 1
                    pos = head + n
                    if pos >= wcap:
                        pos -= wcap
                    WT[s, pos] = t
                    WM[s, pos, 0] = mag_b[r, 0]
                    WM[s, pos, 1] = mag_b[r, 1]
                    WM[s, pos, 2] = mag_b[r, 2]
                    n += 1
                    lim = t - cfg[C_WINDOW]
                    while n > 0 and WT[s, head] < lim:
                        head += 1
                        if head == wcap:
                            head = 0
                        n -= 1
                    SI[s, I_W_HEAD] = head
                    SI[s, I_W_N] = n
                # the last 64 samples (for the GNSS epochs)
                rn = SI[s, I_R_N]
                rpos = SI[s, I_R_HEAD] + rn
                if rpos >= RECENT:
                    rpos -= RECENT
                RT[s, rpos] = t
                RM[s, rpos, 0] = mag_b[r, 0]
                RM[s, rpos, 1] = mag_b[r, 1]
                RM[s, rpos, 2] = mag_b[r, 2]
                if rn == RECENT:
                    h2 = SI[s, I_R_HEAD] + 1
                    SI[s, I_R_HEAD] = 0 if h2 == RECENT else h2
                else:
                    SI[s, I_R_N] = rn + 1
                SF[s, F_LAST_T] = t
                if SI[s, I_PENDING] == 0 and t - SF[s, F_LAST_FIT] >= cfg[C_REFIT]:
                    if allow_fit:
                        return STOP_FIT, k, 0
                    SI[s, I_PENDING] = 1
                    SF[s, F_DUE_T] = t
                    pend[npend[0]] = s
                    npend[0] += 1
            st = SI[s, I_CUR_STATUS]
            if st == ST_OK or st == ST_MANIFEST or st == ST_CONVERGING:
                d0 = mag_b[r, 0] - SF[s, F_CUR_OFF]
                d1 = mag_b[r, 1] - SF[s, F_CUR_OFF + 1]
                d2 = mag_b[r, 2] - SF[s, F_CUR_OFF + 2]
                for a in range(3):
                    out_h[r, a] = d0 * SF[s, F_CUR_M + 3 * a] + d1 * SF[s, F_CUR_M + 3 * a + 1] + \
                        d2 * SF[s, F_CUR_M + 3 * a + 2]
                out_use[r] = 1
                out_ver[r] = SI[s, I_CUR_VER]
            else:
                out_use[r] = 0
                out_ver[r] = SI[s, I_CUR_VER]
        elif kd == K_IMU:
            v = imu_v[r]
            t = imu_t[r]
            icap = IT.shape[1]
            n = VI[v, VI_IMU_N]
            if n == icap:
                return STOP_GROW_IMU, k, 0
            head = VI[v, VI_IMU_HEAD]
            pos = head + n
            if pos >= icap:
                pos -= icap
            IT[v, pos] = t
            for a in range(3):
                IG[v, pos, a] = imu_g[r, a]
                IA[v, pos, a] = imu_a[r, a]
            n += 1
            lim = t - cfg[C_IMU_WINDOW]
            while n > 0 and IT[v, head] < lim:
                head += 1
                if head == icap:
                    head = 0
                n -= 1
            VI[v, VI_IMU_HEAD] = head
            VI[v, VI_IMU_N] = n
        else:
            v = g_v[r]
            if VI[v, VI_ONLINE] == 0:
                phase = 0
                continue
            t = g_t[r]
            speed = g_f[r, G_SPEED]
            pdop = g_f[r, G_PDOP]
            sats = g_f[r, G_SATS]
            if phase == 0:
                # what the status names as the reason an epoch was not used: the vehicle's last GNSS row
                VI[v, VI_G_FIX] = int(g_f[r, G_FIX])
                VI[v, VI_G_SATS] = int(sats)
                VF[v, VF_G_PDOP] = pdop
                VF[v, VF_G_SPEED] = speed
                # the speed rate (online_ekf.SpeedRate.update)
                scap = ST.shape[1]
                sn = VI[v, VI_SR_N]
                sh = VI[v, VI_SR_HEAD]
                if sn > 0:
                    last = sh + sn - 1
                    if last >= scap:
                        last -= scap
                    if t < ST[v, last]:
                        sn = 0
                        sh = 0
                if sn == scap:
                    return STOP_GROW_SR, k, 0
                pos = sh + sn
                if pos >= scap:
                    pos -= scap
                ST[v, pos] = t
                SV[v, pos] = speed
                sn += 1
                lim = t - cfg[C_SR_WINDOW]
                while sn > 0 and ST[v, sh] < lim:
                    sh += 1
                    if sh == scap:
                        sh = 0
                    sn -= 1
                VI[v, VI_SR_HEAD] = sh
                VI[v, VI_SR_N] = sn
                rate = 0.0
                if sn >= 2:
                    lastp = sh + sn - 1
                    if lastp >= scap:
                        lastp -= scap
                    t_end = ST[v, lastp]
                    tm = 0.0
                    vm = 0.0
                    for q in range(sn):
                        p = sh + q
                        if p >= scap:
                            p -= scap
                        tm += ST[v, p] - t_end
                        vm += SV[v, p]
                    tm /= sn
                    vm /= sn
                    den = 0.0
                    num = 0.0
                    for q in range(sn):
                        p = sh + q
                        if p >= scap:
                            p -= scap
                        tc = (ST[v, p] - t_end) - tm
                        den += tc * tc
                        num += tc * (SV[v, p] - vm)
                    rate = num / den if den > 0 else 0.0
                # IMU window means
                icap = IT.shape[1]
                ni = VI[v, VI_IMU_N]
                yaw_rate = 0.0
                roll = 0.0
                pitch = 0.0
                if ni > 0:
                    g2 = 0.0
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    for q in range(ni):
                        p = VI[v, VI_IMU_HEAD] + q
                        if p >= icap:
                            p -= icap
                        g2 += IG[v, p, 2]
                        a0 += IA[v, p, 0]
                        a1 += IA[v, p, 1]
                        a2 += IA[v, p, 2]
                    yaw_rate = g2 / ni
                    if cfg[C_TILT_ACCEL] != 0.0:  # online_ekf.car_roll_pitch
                        ax = a0 / ni - rate
                        ay = a1 / ni - speed * yaw_rate
                        az = a2 / ni
                        pitch = math.atan2(ax, math.hypot(ay, az))
                        roll = math.atan2(ay, az)
                VF[v, VF_RATE] = rate
                VF[v, VF_ROLL] = roll
                VF[v, VF_PITCH] = pitch
                VF[v, VF_YAW_RATE] = yaw_rate
                j0 = 0
            else:
                j0 = phase - 1
            roll = VF[v, VF_ROLL]
            pitch = VF[v, VF_PITCH]
            yaw_rate = VF[v, VF_YAW_RATE]
            # online_ekf.gnss_usable
            ok = g_f[r, G_GOOD_FIX] != 0.0 and sats >= cfg[C_MIN_SATS] and not pdop > cfg[C_MAX_PDOP] and \
                not speed < cfg[C_MIN_SPEED]
            decl = g_f[r, G_DECL]
            course = g_f[r, G_COURSE]
            for j in range(j0, VI[v, VI_NSENS]):
                s = VI[v, VI_SENS + j]
                if SI[s, I_EKF_ON] == 0:
                    continue
                cnt = 0
                m[0] = 0.0
                m[1] = 0.0
                m[2] = 0.0
                lo = t - 0.25
                hi = t + 0.05
                for q in range(SI[s, I_R_N]):
                    p = SI[s, I_R_HEAD] + q
                    if p >= RECENT:
                        p -= RECENT
                    tb = RT[s, p]
                    if lo <= tb and tb <= hi:
                        m[0] += RM[s, p, 0]
                        m[1] += RM[s, p, 1]
                        m[2] += RM[s, p, 2]
                        cnt += 1
                if cnt == 0:
                    continue
                m[0] /= cnt
                m[1] /= cnt
                m[2] /= cnt
                if SI[s, I_CUR_STATUS] != ST_NONE and SI[s, I_CUR_VER] != SI[s, I_BASE_VER] and SI[s, I_CUR_EKF] == 0:
                    _rebase(s, cfg, SF, SI)  # a new static fit: restart the EKF around it
                if _ekf_update(s, t, m, course, roll, pitch, decl, speed, yaw_rate, ok, cfg, SF, SI, scr):
                    en = SI[s, I_EP_N]
                    eh = SI[s, I_EP_HEAD]
                    if en == ecap:
                        e = eh
                        eh += 1
                        if eh == ecap:
                            eh = 0
                        SI[s, I_EP_HEAD] = eh
                    else:
                        e = eh + en
                        if e >= ecap:
                            e -= ecap
                        SI[s, I_EP_N] = en + 1
                    EP[s, e, 0] = m[0]
                    EP[s, e, 1] = m[1]
                    EP[s, e, 2] = m[2]
                    EP[s, e, 3] = course
                    EP[s, e, 4] = roll
                    EP[s, e, 5] = pitch
                    EP[s, e, 6] = decl
                ev = _record_check(s, t, cfg, SF, SI, EP, scr)
                if ev != 0:
                    SI[s, I_EV_KIND] = ev
                    return STOP_EKF, k, j
        phase = 0
    return DONE, order.shape[0], 0


def _compensate_py(b, off, M, out):
    """h = M (m − offset) of rows with each row's own offset (n × 3) and matrix (n × 9)."""
    for r in range(b.shape[0]):
        d0 = b[r, 0] - off[r, 0]
        d1 = b[r, 1] - off[r, 1]
        d2 = b[r, 2] - off[r, 2]
        for a in range(3):
            out[r, a] = d0 * M[r, 3 * a] + d1 * M[r, 3 * a + 1] + d2 * M[r, 3 * a + 2]


# the kernels: plain Python until _kernels() compiles them (numba loads in ~0.4 s: importing this module does not)
_rot, _heading_rms, _rebase, _ekf_update, _record_check = (_rot_py, _heading_rms_py, _rebase_py, _ekf_update_py,
                                                            _record_check_py)
_run, _merge = _run_py, _merge_py
_compiled = False


def _kernels():
    """The compiled kernels (compiled on first use in a process, or loaded from numba's on-disk cache)."""
    global _rot, _heading_rms, _rebase, _ekf_update, _record_check, _run, _merge, _compiled
    if not _compiled:
        import numba

        jit = numba.njit(cache=True)
        # callees first: a kernel binds the compiled functions it calls when it is compiled
        _rot = jit(_rot_py)
        _heading_rms = jit(_heading_rms_py)
        _rebase = jit(_rebase_py)
        _ekf_update = jit(_ekf_update_py)
        _record_check = jit(_record_check_py)
        _run = jit(_run_py)
        _merge = jit(_merge_py)
        _compiled = True
    return _run


# ---- declination ----------------------------------------------------------------------------------------------


class Declinations:
    """Magnetic declination at GNSS positions, as :meth:`core.VehicleCalibration.declination` computes it (IGRF at
    the position rounded to 0.01° and 100 m, :func:`magmesh.maths.earth_field_enu_nt`), remembered per rounded
    position and computed for all new positions of a frame at once.

    ``ppigrf.igrf`` reads its coefficient file and interpolates the coefficients to the date on every call (about
    50 ms); at 500 vehicles a car enters a new 0.01° cell several times a second, which would cost a third of a
    core. Here the same steps run with the coefficients read and interpolated once (``ppigrf.ppigrf.read_shc``, the
    same interpolation in time), then ppigrf's own ``geod2geoc``, ``get_legendre``, sums and ``geoc2geod`` for a
    batch of positions (about 3 ms for one position or 50). Values agree with ``maths.earth_field_enu_nt`` to
    rounding (matrix products over a batch instead of one row; tests: 1e-12 relative)."""

    #: cells computed around a new one, each way (7 × 7 cells of 0.01°: about 7 km × 7 km at mid latitudes)
    NEAR = 3

    def __init__(self, date: str = "2026-06-01", max_entries: int = 500_000):
        self.date = date
        self.max_entries = max_entries
        self.memo: dict[tuple, float] = {}
        self._coef = None
        self.computed = 0
        self.batches = 0

    def warm(self) -> None:
        """Read and interpolate the coefficients now (a service does this before serving)."""
        self._coefficients()

    def _coefficients(self):
        if self._coef is None:
            import datetime as _dt

            from ppigrf import ppigrf  # the module: read_shc, get_legendre, geod2geoc, geoc2geod, RE

            d = np.array([_dt.datetime.fromisoformat(self.date)])
            g, h = ppigrf.read_shc(ppigrf.shc_fn)
            keys = g.keys()
            n, m = np.array([k for k in g.columns]).T
            index = g.index.union(d)
            g = g.reindex(index).groupby(index).first().interpolate(method="time").loc[d, :]
            h = h.reindex(index).groupby(index).first().interpolate(method="time").loc[d, :]
            self._coef = (ppigrf, keys, n.reshape((1, -1)), m.reshape((1, -1)), np.hstack((g.values, h.values)).T)
        return self._coef

    def field_enu_nt(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """IGRF field (east, north, up; nT) at positions (arrays; alt in m), as ppigrf.igrf."""
        ppigrf, keys, n, m, gh = self._coefficients()
        lat = np.asarray(lat_deg, float).ravel()
        lon = np.asarray(lon_deg, float).ravel()
        hkm = np.asarray(alt_m, float).ravel() / 1000.0
        theta, r, _, __ = ppigrf.geod2geoc(lat, hkm, hkm, hkm)
        r, theta, phi = (x.reshape((-1, 1)) for x in (r, theta, lon))
        P, dP = ppigrf.get_legendre(theta, keys)
        phi_rad = np.radians(phi)
        cosmphi = np.cos(phi_rad * m)
        sinmphi = np.sin(phi_rad * m)
        nn, mm = np.tile(n, 2), np.tile(m, 2)
        n_map = ((nn >= 1) & (nn <= 13)).astype(int)
        RE = ppigrf.RE
        G = n_map * (RE / r) ** (nn + 2) * (nn + 1) * np.hstack((P * cosmphi, P * sinmphi))
        Br = G.dot(gh).T
        G = - n_map * (RE / r) ** (nn + 1) * np.hstack((dP * cosmphi, dP * sinmphi)) * RE / r
        Bt = G.dot(gh).T
        G = - n_map * (RE / r) ** (nn + 1) * mm * np.hstack((-P * sinmphi, P * cosmphi)) * RE / r / \
            np.sin(np.radians(theta))
        Bp = G.dot(gh).T
        _, __, Bn, Bu = ppigrf.geoc2geod(theta.ravel(), r.ravel(), Bt, Br)
        return np.stack([np.ravel(Bp), np.ravel(Bn), np.ravel(Bu)], axis=1)

    @staticmethod
    def cells(lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray) -> tuple:
        """The rounded positions: Python's ``round(lat, 2)``, ``round(lon, 2)``, ``round(alt, -2)``, element by
        element (numpy's rounding agrees with it except next to a tie, where Python's is taken)."""
        out = []
        for x, nd in ((lat_deg, 2), (lon_deg, 2), (alt_m, -2)):
            x = np.asarray(x, float)
            y = x * 10.0 ** nd
            r = np.rint(y)
            r = r / 10.0 ** nd if nd > 0 else r * 10.0 ** -nd
            near = np.abs(np.abs(y - np.floor(y)) - 0.5) < 1e-6
            if near.any():
                r = r.copy()
                for i in np.flatnonzero(near).tolist():
                    r[i] = round(float(x[i]), nd)
            out.append(r)
        return tuple(out)

    def __call__(self, lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray, rounded: bool = False) -> np.ndarray:
        """Declination (rad, east positive) per position (``rounded``: already :meth:`cells`). A position in a cell
        not seen yet is computed together with the cells around it (``NEAR`` cells each way, same altitude): the
        next cells a vehicle enters are then known already, and one ppigrf pass serves several crossings."""
        cells = (lat_deg, lon_deg, alt_m) if rounded else self.cells(lat_deg, lon_deg, alt_m)
        k = list(zip(*(c.tolist() for c in cells), strict=True))
        memo = self.memo
        new = list({x for x in k if x not in memo})
        if new:
            if len(memo) + len(new) * (2 * self.NEAR + 1) ** 2 > self.max_entries:
                memo.clear()
            c = np.array(new)
            d = np.arange(-self.NEAR, self.NEAR + 1, dtype=float)
            # neighbours as round() gives them: the double nearest to (k ± i) / 100
            la = (np.rint(c[:, 0] * 100.0)[:, None, None] + d[None, :, None]) / 100.0
            lo = (np.rint(c[:, 1] * 100.0)[:, None, None] + d[None, None, :]) / 100.0
            la, lo = np.broadcast_arrays(la, lo)
            al = np.broadcast_to(c[:, 2][:, None, None], la.shape)
            pts = {}
            for x in zip(la.ravel().tolist(), lo.ravel().tolist(), al.ravel().tolist(), strict=True):
                if x not in memo and -90.0 <= x[0] <= 90.0:
                    pts[x] = None
            for x in new:
                pts[x] = None  # (a latitude at the pole's edge still gets its own value)
            todo = list(pts)
            b = self.field_enu_nt(*np.array(todo).T)
            for x, dd in zip(todo, np.arctan2(b[:, 0], b[:, 1]).tolist(), strict=True):
                memo[x] = dd
            self.computed += len(todo)
            self.batches += 1
        return np.array([memo[x] for x in k], float)


# ---- inputs and outputs -------------------------------------------------------------------------------------------


@dataclass
class MagIn:
    """One magnetometer stream's rows: ``vi`` the frame's vehicle index (the merge key), ``slots`` their sensor
    slots, sorted by vehicle then time like a frame's rows."""

    sid: str
    vi: np.ndarray
    slots: np.ndarray
    t_s: np.ndarray
    b_nt: np.ndarray


@dataclass
class ImuIn:
    vi: np.ndarray
    vslots: np.ndarray
    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray


@dataclass
class GnssIn:
    """GNSS rows; ``cols`` the message's fields as columns (``fix_type`` one string or a list)."""

    vi: np.ndarray
    vslots: np.ndarray
    t_s: np.ndarray
    cols: dict


@dataclass
class Event:
    """A parameter-set decision to publish: a fit attempt (``attempt``) or an EKF set (``record``)."""

    vslot: int
    vehicle: str
    sensor: str
    kind: str  # "fit" | "ekf"
    t_s: float
    record: ParamRecord | None
    attempt: FitAttempt | None = None
    had: ParamRecord | None = None  # the set in use before a fit


class Step:
    """What :meth:`FleetCalibration.step` gives per magnetometer input (in the order given): ``h[i]`` the
    compensated field (n × 3), ``usable[i]`` whether a set with status ok, manifest or converging was in use for
    the row, :meth:`param_ids` the id of that set; ``events`` the parameter-set decisions in the order they
    happened."""

    __slots__ = ("h", "usable", "events", "_bounds", "_ver", "_slots", "_code_now", "_ver_now", "_pids", "_table")

    def __init__(self, h, use, ver, slots, bounds, events, pids, code_now, ver_now, table):
        self.h = [h[a:b] for a, b in bounds]
        self.usable = [use[a:b] for a, b in bounds]
        self.events = events
        self._bounds, self._ver, self._slots = bounds, ver, slots
        self._code_now, self._ver_now, self._pids, self._table = code_now, ver_now, pids, table

    def _late(self, a: int, b: int) -> np.ndarray:
        """Rows compensated with a set that was replaced later in the same step."""
        return np.flatnonzero(self._ver[a:b] != self._ver_now[a:b])

    def param_ids(self, i: int) -> list:
        """The id of the set that compensated each row of magnetometer input ``i`` (None where none was usable)."""
        a, b = self._bounds[i]
        table = self._table
        out = [None if c < 0 else table[c] for c in self._code_now[a:b].tolist()]
        for r in self._late(a, b).tolist():
            out[r] = self._pids.get((int(self._slots[a + r]), int(self._ver[a + r])))
        use = self.usable[i]
        if not use.all():
            for r in np.flatnonzero(~use).tolist():
                out[r] = None
        return out

    def param_id_column(self, i: int, rows: np.ndarray | None = None) -> str | list:
        """:meth:`param_ids` of the rows ``rows`` (all when None) as a frame column: one string when every row
        has the same set (the ids compared as codes, no string per row), else a list."""
        a, b = self._bounds[i]
        codes = self._code_now[a:b] if rows is None else self._code_now[a:b][rows]
        if codes.size and codes[0] >= 0 and (codes == codes[0]).all() and not self._late(a, b).size:
            return self._table[int(codes[0])]
        ids = self.param_ids(i)
        return ids if rows is None else [ids[r] for r in rows.tolist()]


_E1 = np.zeros(0)
_E1I = np.zeros(0, np.int64)
_E3 = np.zeros((0, 3))
_EG = np.zeros((0, N_G))


def _cat(xs: list, f: str, dt, empty: np.ndarray) -> np.ndarray:
    """One input column over the inputs, contiguous and writable (a frame's columns are read-only views of its
    payload: the kernel would be compiled once more for read-only arrays)."""
    if not xs:
        return empty
    if len(xs) == 1:
        a = np.ascontiguousarray(getattr(xs[0], f), dt)
        return a if a.flags.writeable else a.copy()
    return np.ascontiguousarray(np.concatenate([np.asarray(getattr(x, f), dt) for x in xs]))


def _grow_ring(arr: np.ndarray, head: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The ring array with twice the width, every slot's ring unwrapped to start at 0 (heads become 0)."""
    rows, w = arr.shape[0], arr.shape[1]
    new = np.zeros((rows, 2 * w) + arr.shape[2:], arr.dtype)
    idx = (head[:, None] + np.arange(w)[None, :]) % w
    new[:, :w] = arr[np.arange(rows)[:, None], idx]
    return new


class FleetCalibration:
    """The calibration service's per-sample logic over many vehicles and sensors (see the module's description)."""

    def __init__(self, settings: CalibrationSettings | None = None, online: OnlineSettings | None = None,
                 fit_budget_frac: float = 0.0, capacity: int = 16, wall=time.monotonic, cpu=time.thread_time):
        settings = CalibrationSettings() if settings is None else settings
        online = OnlineSettings() if online is None else online
        if online.ekf.estimate_mount_yaw:
            raise ValueError("the fleet form runs the 3-state EKF only (estimate_mount_yaw = False)")
        if not fit_budget_frac >= 0:
            raise ValueError("fit_budget_frac must be ≥ 0 (0: no limit)")
        self.settings, self.online = settings, online
        self.unlimited = not (0 < fit_budget_frac < math.inf)
        self.fit_budget_frac = float(fit_budget_frac)
        self._wall, self._cpu = wall, cpu
        e = online.ekf
        c = np.zeros(N_CFG)
        c[C_WINDOW], c[C_INTERVAL], c[C_REFIT] = settings.window_s, settings.sample_interval_s, settings.refit_interval_s
        c[C_IMU_WINDOW], c[C_SR_WINDOW] = online.imu_window_s, online_ekf.SpeedRate().window_s
        c[C_RW2], c[C_HN2] = e.random_walk_nt_sqrt_s ** 2, e.heading_noise_rad ** 2
        c[C_VEL_STD], c[C_MIN_SPEED], c[C_MAX_YAW] = e.gnss_vel_std_m_s, e.min_speed_m_s, e.max_yaw_rate_rad_s
        c[C_GATE2], c[C_OBS_RATIO], c[C_CONV_STD] = e.gate_sigma ** 2, e.observable_ratio, e.converged_std_nt
        c[C_MIN_TILT], c[C_PRIOR_STD] = e.min_tilt_for_vertical_rad, e.prior_std_nt
        c[C_CONV_PUB], c[C_MIN_CHANGE], c[C_EKF_IMPROVE] = (online.converging_publish_s, online.min_change_nt,
                                                            online.improve_ratio)
        c[C_MIN_INTERVAL], c[C_MIN_EPOCHS] = online.min_interval_s, min(30, online.gnss_window)
        c[C_TILT_ACCEL] = 1.0 if online.tilt_source == "accel" else 0.0
        c[C_MIN_SATS], c[C_MAX_PDOP] = e.min_sats, e.max_pdop
        self.cfg = c
        self.wcap = settings.window_capacity
        cap = max(1, int(capacity))
        self.SF = np.zeros((cap, N_F))
        self.SI = np.zeros((cap, N_I), np.int64)
        self.WT = np.zeros((cap, self.wcap))
        self.WM = np.zeros((cap, self.wcap, 3), np.float32)
        self.RT = np.zeros((cap, RECENT))
        self.RM = np.zeros((cap, RECENT, 3))
        self.EP = np.zeros((cap, max(1, online.gnss_window), N_EP))
        self.VF = np.zeros((cap, N_VF))
        self.VI = np.zeros((cap, VI_SENS + 4), np.int64)
        self.IT = np.zeros((cap, 128))
        self.IG = np.zeros((cap, 128, 3))
        self.IA = np.zeros((cap, 128, 3))
        self.ST = np.zeros((cap, 16))
        self.SV = np.zeros((cap, 16))
        # Python objects per sensor slot
        self.records: list[ParamRecord | None] = [None] * cap
        self.attempts: list[FitAttempt | None] = [None] * cap
        self.sids: list[str | None] = [None] * cap
        self.n_fits = np.zeros(cap, np.int64)
        self.n_refused = np.zeros(cap, np.int64)
        self.n_replaced = np.zeros(cap, np.int64)
        self.cur_pid = np.full(cap, None, object)
        # the id of the set in use as a code (an index in _pid_list; −1: none usable), read per row cheaply
        self.cur_code = np.full(cap, -1, np.int64)
        self._pid_list: list[str] = []
        self._pid_code: dict[str, int] = {}
        # per vehicle slot
        self.vnames: list[str | None] = [None] * cap
        self.vsensors: list[dict[str, int]] = [{} for _ in range(cap)]
        self._odd_fix: dict[int, str] = {}  # vehicle slot → a fix type outside GNSS_FIXES (its last GNSS row's)
        self._free_s: list[int] = list(range(cap - 1, -1, -1))
        self._free_v: list[int] = list(range(cap - 1, -1, -1))
        self._sid_slots: dict[str, np.ndarray] = {}  # sensor id → sensor slot per vehicle slot (−1: none)
        # the fit scheduler
        self.queue: set[int] = set()
        self.tokens = self._burst
        self._t_refill = wall()
        self.lags: deque[float] = deque(maxlen=1000)
        self.fit_cpu: deque[float] = deque(maxlen=1000)
        self.fits_run = 0
        self.fits_delayed = 0
        self.fit_cpu_s = 0.0
        self.declinations = Declinations()
        self._events: list[Event] = []
        self._pids: dict[tuple[int, int], str] = {}

    def set_fit_budget(self, frac: float) -> None:
        """A new ``fit_budget_frac`` (a group member's share of its role's budget, as the membership changes); a
        limit set to 0 stays no limit, and what is banked is kept up to the new burst."""
        if self.unlimited or not 0 < frac < math.inf or frac == self.fit_budget_frac:
            return
        self._refill()
        self.fit_budget_frac = float(frac)
        self.tokens = min(self.tokens, self._burst)

    # ---- slots ------------------------------------------------------------------------------------------------
    @property
    def _burst(self) -> float:
        return 0.0 if self.unlimited else self.fit_budget_frac * 1.0

    def _grow(self, what: str) -> None:
        """Double the vehicle or sensor slot capacity."""
        if what == "s":
            old = self.SF.shape[0]
            new = 2 * old
            for name in ("SF", "SI", "WT", "WM", "RT", "RM", "EP"):
                a = getattr(self, name)
                b = np.zeros((new,) + a.shape[1:], a.dtype)
                b[:old] = a
                setattr(self, name, b)
            for name in ("n_fits", "n_refused", "n_replaced"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.zeros(old, a.dtype)]))
            self.cur_pid = np.concatenate([self.cur_pid, np.full(old, None, object)])
            self.cur_code = np.concatenate([self.cur_code, np.full(old, -1, np.int64)])
            self.records += [None] * old
            self.attempts += [None] * old
            self.sids += [None] * old
            self._free_s = list(range(new - 1, old - 1, -1)) + self._free_s
        else:
            old = self.VF.shape[0]
            new = 2 * old
            for name in ("VF", "VI", "IT", "IG", "IA", "ST", "SV"):
                a = getattr(self, name)
                b = np.zeros((new,) + a.shape[1:], a.dtype)
                b[:old] = a
                setattr(self, name, b)
            self.vnames += [None] * old
            self.vsensors += [{} for _ in range(old)]
            self._free_v = list(range(new - 1, old - 1, -1)) + self._free_v
            for sid, a in self._sid_slots.items():
                self._sid_slots[sid] = np.concatenate([a, np.full(old, -1, np.int64)])

    def add_vehicle(self, name: str, online: bool = True, declination_rad: float | None = None,
                    initial: dict[str, ParamRecord] | None = None) -> int:
        """A vehicle slot; ``online``: run its GNSS-aided EKF; ``initial``: sets in use from the start (its
        sensors are created now, in this order)."""
        if not self._free_v:
            self._grow("v")
        v = self._free_v.pop()
        self.VF[v] = math.nan
        self.VF[v, VF_DECL] = math.nan if declination_rad is None else float(declination_rad)
        self.VI[v] = 0
        self.VI[v, VI_IN_USE] = 1
        self.VI[v, VI_ONLINE] = 1 if (online and self.online.enabled) else 0
        self.VI[v, VI_G_FIX] = -2  # no GNSS row yet
        self.vnames[v] = name
        self.vsensors[v] = {}
        self._odd_fix.pop(v, None)
        for sid, rec in (initial or {}).items():
            self.add_sensor(v, sid, rec)
        return v

    def add_sensor(self, v: int, sid: str, initial: ParamRecord | None = None) -> int:
        """A sensor slot of vehicle slot ``v`` (VehicleCalibration.sensor)."""
        have = self.vsensors[v].get(sid)
        if have is not None:
            return have
        if not self._free_s:
            self._grow("s")
        s = self._free_s.pop()
        self.SF[s] = 0.0
        self.SI[s] = 0
        self.SF[s, F_LAST_KEPT] = -math.inf
        self.SF[s, F_LAST_FIT] = -math.inf
        self.SF[s, F_DUE_T] = math.nan
        self.SF[s, F_LAST_T] = -math.inf
        self.SF[s, F_LAST_CONV_T] = -math.inf
        self.SF[s, F_LAST_OK_T] = -math.inf
        self.SI[s, I_VSLOT] = v
        self.SI[s, I_IN_USE] = 1
        self.SI[s, I_EKF_ON] = self.VI[v, VI_ONLINE]
        self.records[s] = None
        self.attempts[s] = None
        self.sids[s] = sid
        self.n_fits[s] = self.n_refused[s] = self.n_replaced[s] = 0
        self.cur_pid[s] = None
        self.cur_code[s] = -1
        self.SF[s, F_CUR_M:F_CUR_M + 9] = np.eye(3).ravel()
        self.SI[s, I_CUR_OBS:I_CUR_OBS + 3] = 1
        if initial is not None:
            self._set_current(s, initial)
        # the EKF around the set in use (SensorOnline.__init__), identity without one
        p = initial.params if initial is not None else magcal.IDENTITY
        self.SF[s, F_PRIOR:F_PRIOR + 3] = p.offset
        self.SF[s, F_X:F_X + 3] = p.offset
        self.SF[s, F_P:F_P + 9] = np.diag([self.online.ekf.prior_std_nt ** 2] * 3).ravel()
        self.SF[s, F_EKF_M:F_EKF_M + 9] = p.M.ravel()
        for f in (F_T_LAST, F_INNOV, F_INNOV_VAR, F_TEST_RATIO):
            self.SF[s, f] = math.nan
        self.SI[s, I_BASE_VER] = self.SI[s, I_CUR_VER]
        # the vehicle's list of sensor slots
        k = int(self.VI[v, VI_NSENS])
        if VI_SENS + k >= self.VI.shape[1]:
            self.VI = np.concatenate([self.VI, np.zeros((self.VI.shape[0], self.VI.shape[1] - VI_SENS), np.int64)],
                                     axis=1)
        self.VI[v, VI_SENS + k] = s
        self.VI[v, VI_NSENS] = k + 1
        self.vsensors[v][sid] = s
        a = self._sid_slots.get(sid)
        if a is None:
            a = self._sid_slots[sid] = np.full(self.VF.shape[0], -1, np.int64)
        a[v] = s
        return s

    def free_vehicle(self, v: int) -> None:
        """Give a vehicle's slots back (an evicted vehicle)."""
        for sid, s in self.vsensors[v].items():
            self.SI[s] = 0
            self.records[s] = self.attempts[s] = self.sids[s] = None
            self.cur_pid[s] = None
            self.cur_code[s] = -1
            self.queue.discard(s)
            self._sid_slots[sid][v] = -1
            self._free_s.append(s)
        self.vsensors[v] = {}
        self.VI[v] = 0
        self.vnames[v] = None
        self._odd_fix.pop(v, None)
        self._free_v.append(v)

    def sensor_slots(self, vslots: np.ndarray, sid: str) -> np.ndarray:
        """The sensor slot of ``sid`` for each vehicle slot (−1 where the vehicle has no such sensor yet)."""
        a = self._sid_slots.get(sid)
        if a is None:
            return np.full(len(vslots), -1, np.int64)
        return a[vslots]

    def sensors(self, v: int) -> dict[str, int]:
        """The sensor slots of vehicle slot ``v`` by sensor id, in the order they were created."""
        return self.vsensors[v]

    def vslot_of(self, s: int) -> int:
        return int(self.SI[s, I_VSLOT])

    # ---- the set in use -------------------------------------------------------------------------------------
    def _set_current(self, s: int, rec: ParamRecord) -> None:
        p = rec.params
        self.records[s] = rec
        self.SF[s, F_CUR_OFF:F_CUR_OFF + 3] = p.offset_nt
        self.SF[s, F_CUR_M:F_CUR_M + 9] = p.matrix
        self.SI[s, I_CUR_OBS:I_CUR_OBS + 3] = [1 if o else 0 for o in p.observable]
        self.SI[s, I_CUR_STATUS] = STATUS_CODE.get(rec.status, ST_REFUSED)
        self.SI[s, I_CUR_EKF] = 1 if rec.method == "ekf" else 0
        ver = int(self.SI[s, I_CUR_VER])
        self._pids.setdefault((s, ver), self.cur_pid[s])  # rows of this step compensated before the change
        self.SI[s, I_CUR_VER] = ver + 1
        pid = rec.param_id if rec.status in USABLE else None
        self.cur_pid[s] = pid
        self.cur_code[s] = -1 if pid is None else self._code(pid)

    def _code(self, pid: str) -> int:
        c = self._pid_code.get(pid)
        if c is None:
            if len(self._pid_list) >= 4 * len(self.cur_pid) + 1024:  # ids no longer in use: start the table again
                self._pid_list, self._pid_code = [], {}
                for i in np.flatnonzero(self.cur_code >= 0).tolist():
                    self.cur_code[i] = self._code(self.cur_pid[i])
            c = self._pid_code[pid] = len(self._pid_list)
            self._pid_list.append(pid)
        return c

    def window(self, s: int) -> np.ndarray:
        """The fit window of sensor slot ``s`` (N × 3 float64, oldest first), as SensorCalibrator.window()."""
        n, head = int(self.SI[s, I_W_N]), int(self.SI[s, I_W_HEAD])
        if head + n <= self.wcap:
            return self.WM[s, head:head + n].astype(float)
        return np.concatenate([self.WM[s, head:], self.WM[s, :head + n - self.wcap]]).astype(float)

    def window_times(self, s: int) -> np.ndarray:
        n, head = int(self.SI[s, I_W_N]), int(self.SI[s, I_W_HEAD])
        return self.WT[s, (head + np.arange(n)) % self.wcap]

    # ---- fits and their budget --------------------------------------------------------------------------------
    def _refill(self) -> None:
        now = self._wall()
        self.tokens = min(self.tokens + self.fit_budget_frac * max(0.0, now - self._t_refill), self._burst)
        self._t_refill = now

    def _allow_now(self) -> bool:
        if self.unlimited:
            return True
        if self.queue:
            return False
        self._refill()
        return self.tokens > 0

    def _fit(self, s: int, t_s: float, due_t_s: float) -> None:
        c0 = self._cpu()
        had = self.records[s]
        sid = self.sids[s]
        attempt = fit_window(sid, self.window(s), t_s, had, self.settings)
        self.SF[s, F_LAST_FIT] = t_s
        self.n_fits[s] += 1
        self.attempts[s] = attempt
        if attempt.record is not None and attempt.record.status == "refused":
            self.n_refused[s] += 1
        if attempt.accepted:
            self._set_current(s, attempt.record)
            self.n_replaced[s] += 1
        cost = self._cpu() - c0
        self.fit_cpu_s += cost
        self.fit_cpu.append(cost)
        if not self.unlimited:
            self.tokens -= cost
        self.fits_run += 1
        self.lags.append(max(0.0, t_s - due_t_s))
        v = int(self.SI[s, I_VSLOT])
        self._events.append(Event(v, self.vnames[v], sid, "fit", t_s, attempt.record, attempt, had))

    def run_queued(self) -> list[Event]:
        """Run waiting fits, the most overdue first, while the budget allows; returns their events."""
        self._events = []
        self._run_queue()
        return self._events

    def _run_queue(self) -> None:
        if not self.queue:
            return
        if not self.unlimited:
            self._refill()
            if self.tokens <= 0:
                return
        q = np.fromiter(self.queue, np.int64, len(self.queue))
        lag = self.SF[q, F_LAST_T] - self.SF[q, F_DUE_T]
        for s in q[np.argsort(-lag, kind="stable")].tolist():
            if not self.unlimited and self.tokens <= 0:
                break
            self.queue.discard(s)
            self.SI[s, I_PENDING] = 0
            self.fits_delayed += 1
            self._fit(s, float(self.SF[s, F_LAST_T]), float(self.SF[s, F_DUE_T]))

    def scheduler_status(self) -> dict:
        lags = np.fromiter(self.lags, float, len(self.lags))
        cpu = np.fromiter(self.fit_cpu, float, len(self.fit_cpu))
        q = np.fromiter(self.queue, np.int64, len(self.queue))
        waiting = self.SF[q, F_LAST_T] - self.SF[q, F_DUE_T] if q.size else np.zeros(0)
        return {
            "fit_budget_frac": None if self.unlimited else self.fit_budget_frac,
            "fits": self.fits_run, "fits_delayed": self.fits_delayed, "fits_waiting": int(q.size),
            "fit_lag_s": {"max": round(float(lags.max()), 3) if lags.size else None,
                          "median": round(float(np.median(lags)), 3) if lags.size else None, "n": int(lags.size)},
            "waiting_lag_s_max": round(float(waiting.max()), 3) if waiting.size else None,
            "fit_cpu_ms": {"median": round(1e3 * float(np.median(cpu)), 2) if cpu.size else None,
                           "total_s": round(self.fit_cpu_s, 3)},
        }

    # ---- EKF sets ---------------------------------------------------------------------------------------------
    def _ekf_record(self, s: int, t_s: float) -> None:
        """Turn the kernel's decision into a parameter set (the rest of VehicleCalibration._maybe_ekf_record)."""
        sid = self.sids[s]
        cur = self.records[s]
        base = cur.params if cur is not None else magcal.IDENTITY
        offset = self.SF[s, F_EV_OFF:F_EV_OFF + 3].copy()
        observable = tuple(bool(o) for o in self.SI[s, I_EV_OBS:I_EV_OBS + 3])
        M = self.SF[s, F_EKF_M:F_EKF_M + 9].reshape(3, 3).copy()
        params = magcal.MagParams.from_arrays(offset, M, base.field_radius_nt, base.model, observable)
        n_fused, n_rej = int(self.SI[s, I_N_FUSED]), int(self.SI[s, I_N_REJ])
        if self.SI[s, I_EV_KIND] == EV_CONVERGING:
            self.SF[s, F_LAST_CONV_T] = t_s
            std = np.sqrt(self.SF[s, [F_P, F_P + 4, F_P + 8]])
            rec = ParamRecord(params, new_param_id(sid, "ekf", t_s), "converging", "ekf", None, 0.0, n_fused, n_rej,
                              t_s, 0.0, f"online hard-iron EKF converging: offset σ {np.round(std).tolist()} nT")
            self._set_current(s, rec)
            self.SI[s, I_BASE_VER] = self.SI[s, I_CUR_VER]
        else:
            rms_new, rms_old = float(self.SF[s, F_EV_RMS_NEW]), float(self.SF[s, F_EV_RMS_OLD])
            self.SF[s, F_LAST_OK_T] = t_s
            rec = ParamRecord(params, new_param_id(sid, "ekf", t_s), "ok", "ekf", None, 1.0, n_fused, n_rej, t_s, 0.0,
                              f"GNSS heading residual {math.degrees(rms_new):.2f}° (was "
                              f"{math.degrees(rms_old):.2f}°); vertical offset "
                              f"{'estimated' if observable[2] else 'not observable, kept'}")
            self._set_current(s, rec)
            self.SI[s, I_BASE_VER] = self.SI[s, I_CUR_VER]
            self.SF[s, F_PRIOR:F_PRIOR + 3] = offset
            if self.SI[s, I_EV_INUSE]:
                # the hard iron changed: the next static fit must come from fresh coverage (the fit time stays)
                self.SI[s, I_W_HEAD] = 0
                self.SI[s, I_W_N] = 0
                self.SF[s, F_LAST_KEPT] = -math.inf
        v = int(self.SI[s, I_VSLOT])
        self._events.append(Event(v, self.vnames[v], sid, "ekf", t_s, rec))

    # ---- GNSS inputs ------------------------------------------------------------------------------------------
    def _gnss_columns(self, g: GnssIn) -> np.ndarray:
        """Per GNSS row: speed, course, declination, and what decides whether the epoch is usable."""
        n = len(g.t_s)
        cols = g.cols
        out = np.empty((n, N_G))
        out[:, G_SPEED] = cols["speed_m_s"]
        out[:, G_COURSE] = cols["course_rad"]
        out[:, G_SATS] = cols["num_sats"]
        out[:, G_PDOP] = cols["pdop"]
        fix = cols["fix_type"]
        if isinstance(fix, str):
            code = _FIX_CODE.get(fix, -1)
            out[:, G_FIX] = code
            out[:, G_GOOD_FIX] = code >= 0 and _GOOD_FIX[code]
        else:
            fcode = np.fromiter((_FIX_CODE.get(f, -1) for f in fix), np.int64, n)
            out[:, G_FIX] = fcode
            out[:, G_GOOD_FIX] = (fcode >= 0) & _GOOD_FIX[fcode]
        vs = np.asarray(g.vslots, np.int64)
        if (out[:, G_FIX] < 0).any():  # a fix type this version does not know: kept by name for the status
            for i in np.flatnonzero(out[:, G_FIX] < 0).tolist():
                self._odd_fix[int(vs[i])] = fix if isinstance(fix, str) else fix[i]
        VF = self.VF
        decl = VF[vs, VF_DECL]
        need = np.isnan(decl) & (self.VI[vs, VI_ONLINE] != 0)
        if need.any():
            # the declination at the rounded position: the vehicle's last one when it has not left its cell
            ni = np.flatnonzero(need)
            la, lo, al = Declinations.cells(*(np.asarray(cols[c], float)[ni] for c in ("lat_deg", "lon_deg", "alt_m")))
            vn = vs[ni]
            same = (la == VF[vn, VF_CELL_LAT]) & (lo == VF[vn, VF_CELL_LON]) & (al == VF[vn, VF_CELL_ALT])
            d = VF[vn, VF_CELL_DECL]
            moved = ~same
            if moved.any():
                d[moved] = self.declinations(la[moved], lo[moved], al[moved], rounded=True)
                VF[vn[moved], VF_CELL_LAT] = la[moved]
                VF[vn[moved], VF_CELL_LON] = lo[moved]
                VF[vn[moved], VF_CELL_ALT] = al[moved]
                VF[vn[moved], VF_CELL_DECL] = d[moved]
            decl[ni] = d
        out[:, G_DECL] = decl
        return out

    # ---- the step ---------------------------------------------------------------------------------------------
    def step(self, inputs: list) -> Step:
        """Handle one frame's rows (``inputs``: :class:`MagIn`, :class:`ImuIn`, :class:`GnssIn` in the frame's
        stream order; every magnetometer row must have its sensor slot). Waiting fits run first, within the
        budget."""
        run = _run if _compiled else _kernels()
        self._events = []
        self._pids = {}
        if self.queue:
            self._run_queue()
        mags, imus, gnss, kinds, n_each = [], [], [], [], []
        for x in inputs:
            tp = type(x)
            if tp is MagIn:
                mags.append(x)
                kinds.append(K_MAG)
            elif tp is ImuIn:
                imus.append(x)
                kinds.append(K_IMU)
            else:
                gnss.append(x)
                kinds.append(K_GNSS)
            n_each.append(len(x.t_s))
        if len(inputs) == 1:
            n = n_each[0]
            kind = np.full(n, kinds[0], np.int8)
            kidx = order = np.arange(n, dtype=np.int64)
        else:
            kind = np.repeat(np.array(kinds, np.int8), n_each)
            ends = np.cumsum(n_each).astype(np.int64)
            starts = ends - np.asarray(n_each, np.int64)
            kidx = np.empty(int(ends[-1]) if len(ends) else 0, np.int64)
            offs = [0, 0, 0]
            for kd, a, n in zip(kinds, starts.tolist(), n_each, strict=True):
                kidx[a:a + n] = np.arange(offs[kd], offs[kd] + n)
                offs[kd] += n
            vi = np.concatenate([np.asarray(x.vi, np.int64) for x in inputs])
            t_all = np.concatenate([np.asarray(x.t_s, float) for x in inputs])
            order = np.empty(kidx.shape[0], np.int64)
            _merge(vi, t_all, starts, ends, order)
        mag_slot = _cat(mags, "slots", np.int64, _E1I)
        mag_t = _cat(mags, "t_s", float, _E1)
        mag_b = _cat(mags, "b_nt", float, _E3).reshape(-1, 3)
        imu_v = _cat(imus, "vslots", np.int64, _E1I)
        imu_t = _cat(imus, "t_s", float, _E1)
        imu_g = _cat(imus, "gyro_rad_s", float, _E3).reshape(-1, 3)
        imu_a = _cat(imus, "accel_m_s2", float, _E3).reshape(-1, 3)
        g_v = _cat(gnss, "vslots", np.int64, _E1I)
        g_t = _cat(gnss, "t_s", float, _E1)
        g_f = (self._gnss_columns(gnss[0]) if len(gnss) == 1 else
               np.concatenate([self._gnss_columns(g) for g in gnss])) if gnss else _EG
        nm = mag_t.shape[0]
        if nm and mag_slot.min() < 0:
            raise ValueError("every magnetometer row needs its sensor slot (add_sensor)")
        out_h = np.empty((nm, 3))
        out_ver = np.empty(nm, np.int64)
        out_use = np.empty(nm, np.uint8)
        pend = np.empty(max(nm, 1), np.int64)
        npend = np.zeros(1, np.int64)
        k, phase = 0, 0
        while True:
            code, k, j = run(k, phase, self._allow_now(), order, kind, kidx, mag_slot, mag_t, mag_b, imu_v, imu_t,
                             imu_g, imu_a, g_v, g_t, g_f, self.cfg, self.SF, self.SI, self.VF, self.VI, self.WT,
                             self.WM, self.RT, self.RM, self.EP, self.IT, self.IG, self.IA, self.ST, self.SV, out_h,
                             out_ver, out_use, pend, npend)
            if code == DONE:
                break
            r = int(kidx[order[k]])
            if code == STOP_FIT:
                t = float(mag_t[r])
                self._fit(int(mag_slot[r]), t, t)
                phase = 1
            elif code == STOP_EKF:
                v = int(g_v[r])
                self._ekf_record(int(self.VI[v, VI_SENS + j]), float(g_t[r]))
                phase = j + 2
            elif code == STOP_GROW_IMU:
                self.IT, self.IG, self.IA = (_grow_ring(a, self.VI[:, VI_IMU_HEAD], self.VI[:, VI_IMU_N])
                                             for a in (self.IT, self.IG, self.IA))
                self.VI[:, VI_IMU_HEAD] = 0
                phase = 0
            else:  # STOP_GROW_SR
                self.ST, self.SV = (_grow_ring(a, self.VI[:, VI_SR_HEAD], self.VI[:, VI_SR_N])
                                    for a in (self.ST, self.SV))
                self.VI[:, VI_SR_HEAD] = 0
                phase = 0
        if npend[0]:
            self.queue.update(pend[:npend[0]].tolist())
        bounds, a = [], 0
        for x in mags:
            bounds.append((a, a + len(x.t_s)))
            a += len(x.t_s)
        return Step(out_h, out_use.view(bool), out_ver, mag_slot, bounds, self._events, self._pids,
                    self.cur_code[mag_slot], self.SI[mag_slot, I_CUR_VER], self._pid_list)

    # ---- what the status shows --------------------------------------------------------------------------------
    def sensor_entry(self, s: int) -> dict:
        """A sensor's status entry as the reference's (SensorCalibrator.internal_states, plus params and ekf)."""
        return sensor_states(int(self.SI[s, I_W_N]), int(self.n_fits[s]), int(self.n_refused[s]),
                             int(self.n_replaced[s]), self.records[s], self.attempts[s])

    def ekf_states(self, s: int) -> dict | None:
        """The sensor's EKF as HardIronEkf.internal_states | flags (None when its vehicle runs no EKF)."""
        if not self.SI[s, I_EKF_ON]:
            return None
        SF, SI = self.SF, self.SI
        std = np.sqrt(SF[s, [F_P, F_P + 4, F_P + 8]])
        nf = int(SI[s, I_N_FUSED])
        tilt = math.sqrt(SF[s, F_TILT_SQ] / nf) if nf else 0.0
        e = self.online.ekf
        excited = nf >= 10 and tilt >= e.min_tilt_for_vertical_rad
        obs = [bool(r < e.observable_ratio) for r in std / e.prior_std_nt]
        obs[2] = obs[2] and excited
        obs_a = np.array(obs)
        conv = bool(obs_a.any() and np.all(std[obs_a] < e.converged_std_nt))

        def opt(f):
            x = float(SF[s, f])
            return None if math.isnan(x) else x

        return {"offset_nt": [float(x) for x in SF[s, F_X:F_X + 3]], "offset_std_nt": [float(x) for x in std],
                "innovation_rad": opt(F_INNOV), "innovation_var_rad2": opt(F_INNOV_VAR),
                "test_ratio": opt(F_TEST_RATIO), "n_fused": nf, "n_rejected": int(SI[s, I_N_REJ]),
                "n_skipped": int(SI[s, I_N_SKIP]), "tilt_rms_rad": tilt, "mount_yaw_rad": 0.0,
                "mount_yaw_std_rad": 0.0, "converged": conv, "observable": obs, "fused": bool(SI[s, I_FUSED])}

    def ekf_estimate(self, s: int) -> dict:
        """The EKF's state for comparisons: estimate, covariance, prior, matrix and counters."""
        return {"x": self.SF[s, F_X:F_X + 3].copy(), "P": self.SF[s, F_P:F_P + 9].reshape(3, 3).copy(),
                "prior": self.SF[s, F_PRIOR:F_PRIOR + 3].copy(), "M": self.SF[s, F_EKF_M:F_EKF_M + 9].reshape(3, 3).copy(),
                "n_fused": int(self.SI[s, I_N_FUSED]), "n_rejected": int(self.SI[s, I_N_REJ]),
                "n_skipped": int(self.SI[s, I_N_SKIP]), "epochs": int(self.SI[s, I_EP_N])}

    def gnss_reason(self, v: int) -> str:
        """Why the vehicle's last GNSS epoch was not usable ("" when it was, or before any)."""
        code = int(self.VI[v, VI_G_FIX])
        if code == -2:
            return ""
        fix = GNSS_FIXES[code] if code >= 0 else self._odd_fix.get(v, "")
        return online_ekf.gnss_usable(fix, int(self.VI[v, VI_G_SATS]), float(self.VF[v, VF_G_PDOP]),
                                      float(self.VF[v, VF_G_SPEED]), self.online.ekf)[1]


# ---- warm-up ----------------------------------------------------------------------------------------------------


def warm() -> dict:
    """Compile (or load from the on-disk cache) every kernel by running a small fleet through each path."""
    t0 = time.perf_counter()
    _kernels()
    fc = FleetCalibration(CalibrationSettings(min_samples=3, refit_interval_s=0.05), OnlineSettings(),
                          fit_budget_frac=0.0, capacity=1)
    v = fc.add_vehicle("warm", online=True, declination_rad=0.0)
    s = fc.add_sensor(v, "1")
    one = np.zeros(1, np.int64)
    t = np.array([0.0])
    for k in range(2):
        tt = t + 0.1 * k
        fc.step([MagIn("1", one, np.array([s]), tt, np.array([[2e4, 0.0, -4e4]])),
                 ImuIn(one, np.array([v]), tt, np.zeros((1, 3)), np.array([[0.0, 0.0, 9.8]])),
                 GnssIn(one, np.array([v]), tt, {"speed_m_s": [10.0], "course_rad": [0.5], "fix_type": "3d",
                                                  "num_sats": [10], "pdop": [1.0], "lat_deg": [0.0],
                                                  "lon_deg": [0.0], "alt_m": [0.0]})])
    st = _run.stats
    return {"first_call_s": round(time.perf_counter() - t0, 3), "cache_hits": sum(st.cache_hits.values()),
            "cache_misses": sum(st.cache_misses.values()), "cache_dir": str(getattr(st, "cache_path", ""))}


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m services.calibration.fleet",
                                 description="the calibration service's logic over a fleet (numba kernels)")
    ap.add_argument("--warm", action="store_true", help="compile the kernels into numba's on-disk cache, or load "
                    "them from there, and say how long it took")
    a = ap.parse_args(argv)
    if not a.warm:
        ap.print_help()
        return 2
    r = warm()
    how = "loaded from the cache" if r["cache_hits"] and not r["cache_misses"] else "compiled and cached"
    print(f"calibration fleet kernels {how} in {r['first_call_s']:.2f} s ({r['cache_dir']})")
    return 0


if __name__ == "__main__":
    from services.calibration import (
        fleet as _fleet,  # the module's own kernels (and cache), not a __main__ copy
    )

    sys.exit(_fleet.main())
