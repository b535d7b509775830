"""The heading fuser's time join and output rules for many vehicles at once: state in per-slot arrays and ring
buffers, a whole fleet frame's rows in one compiled call (numba). Pure: no zenoh, no service.

The join (``_drain``'s rule, one vehicle slot at a time)
------------------------------------------------------
A slot receives four streams on separate subscriptions or in separate fleet frames, each in time order but
not in step with the others: IMU samples (they drive the filter's clock), calibrated magnetometer samples
(``cal/mag``; or ``clean/mag`` compensated here with the slot's parameters — the latest ``cal/params`` or the
manifest's — while no ``cal/mag`` came for ``cal_timeout_s`` of sample time) and DMC verdicts. The filter must
see IMU and magnetometer samples interleaved by time, each magnetometer sample with the verdict for its time:

* a magnetometer sample waits until the IMU has reached its time (``t_mag ≤ t_imu + 1 µs``) and, while the
  slot's DMC stream is alive, until a verdict at or after its time has arrived; it is then given to the filter
  with the latest verdict at or before its time (levelled with the attitude of its own time);
* the verdict wait is bounded in *wall-clock* time (``dmc_wait_wall_s`` since the sample arrived), so at any
  replay speed a merely late verdict is still used and one that never comes holds the heading back at most
  that long; it ends at once when the detector's last verdict is more than ``dmc_timeout_s`` of sample time
  older than the sample (the detector has fallen silent). A sample that goes on without its verdict is
  counted (``mag_without_verdict``, ``dmc_silent``);
* an IMU sample waits for the magnetometer stream when it is ahead of the newest magnetometer sample, but
  only while the newest IMU sample is at most ``mag_wait_s`` of sample time ahead of it; it also waits
  behind a magnetometer sample that waits for its verdict;
* both queues are bounded (:data:`MAX_PENDING`): a full IMU queue steps the IMU on regardless (counted
  ``imu_past_waiting_mag``), a full magnetometer queue gives up its oldest sample (counted, by its stream);
* an IMU sample not after the previous one, a magnetometer sample before any IMU sample, a ``clean/mag``
  sample while ``cal/mag`` is in use or without parameters are given up at the door (counted);
* an IMU gap longer than ``max_imu_gap_s`` restarts the slot's filter (the event carries ``reset``).

The join runs after every pushed sample, exactly as the per-sample service drained after every message, so a
frame's rows (pushed per vehicle in sample-time order, ties in the frame's stream order: the order in which
the runtime would hand them to ``on_message`` one by one) give the same events as those samples alone.
:class:`ReferenceJoin` is the same rule in plain Python, one vehicle at a time (the tests hold the kernel to it).

Relation to :mod:`magmesh.align`: this is the project's time-aligner concept specialised to one three-way
join. The IMU → magnetometer wait is a :class:`~magmesh.align.CoverWait` (a sample waits until another
stream's time covers it) bounded in *sample* time rather than wall time (the magnetometer is the slower,
sparser stream: an IMU that waited on wall time would stall the heading at a fast replay), and the verdict
wait is a join with the DMC stream bounded in wall time like :class:`~magmesh.align.TimeAligner`, but a
sample whose verdict does not come is used without it (not given up), and it takes the verdict *at or
before* its time rather than one within a tolerance. Given-up samples are counted by reason, as there.

Outputs (``_step_imu``, ``_check_alarm``, ``_publish``'s cadence)
-----------------------------------------------------------------
After the filter has stepped the events, :meth:`FleetJoin.decide` walks them with the slots' output state:
after each IMU event of an aligned filter, the heading alarm latch (raise when the filter flags its heading
uncertain; clear when it is magnetic again or its σ falls below ``alarm_clear_std_rad``), then a ``heading``
message when ``publish_period_s`` of sample time has passed since the slot's last one; every mode change
with the mode it left.

``python -m services.heading_fuser.fleet --warm`` compiles (or loads from numba's disk cache) every kernel.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from typing import NamedTuple

import numpy as np
from numba import njit

from . import compiled

#: samples a slot's IMU or magnetometer queue holds at most (the per-sample service's bound)
MAX_PENDING = 2000
#: verdicts a slot remembers (the per-sample service's deque(maxlen=4096))
DMC_HISTORY = 4096
_RING0 = 64  # first ring capacity; doubled on demand up to the bounds above

# ---- push rows: what a pushed sample is ------------------------------------------------------------------
R_IMU, R_CAL, R_CLEAN, R_DMC = 0, 1, 2, 3
# ---- event kinds (FleetHeading.step's) ---------------------------------------------------------------------
E_IMU, E_MAG = 0, 1

# ---- float state per slot ----------------------------------------------------------------------------------
F_LAST_IMU = 0  # time of the last IMU sample stepped (NaN: none)
F_NEWEST_IMU = 1  # newest IMU sample received (NaN: none)
F_NEWEST_MAG = 2  # newest magnetometer sample queued (NaN: none)
F_LAST_CAL = 3  # newest cal/mag sample (−inf: none)
F_DMC_T = 4  # the last verdict's time, validity, credibility
F_DMC_CRED = 5
F_OFF = 6  # 3: clean/mag compensation h = M (m − offset)
F_M = 9  # 9, row-major
F_LAST_PUB = 18  # output state: time of the last heading message (−inf: none)
F_RAISED_T = 19  # time the heading alarm was raised (NaN: unknown)
N_F = 20

# ---- int state per slot ------------------------------------------------------------------------------------
I_USED = 0
I_HAS_PARAMS = 1
I_DMC_VALID = 2  # −1: no verdict yet
I_PM_HEAD = 3  # magnetometer queue ring: head, count
I_PM_N = 4
I_PI_HEAD = 5  # IMU queue ring
I_PI_N = 6
I_DH_HEAD = 7  # verdict history ring
I_DH_N = 8
I_RAISED = 9  # output state: heading alarm raised
I_MODE = 10  # the filter's mode after the last event (mode codes of compiled.MODES)
N_I = 12

# ---- counters per slot (cumulative, and since the last report) ---------------------------------------------
C_IMU_NOT_AFTER = 0
C_NO_IMU_CAL = 1
C_NO_IMU_CLEAN = 2
C_CAL_IN_USE = 3
C_NO_PARAMS = 4
C_OVERFLOW_CAL = 5
C_OVERFLOW_CLEAN = 6
C_WAITED_OUT = 7
C_DMC_SILENT = 8
C_IMU_FORCED = 9
N_C = 10
#: counter names (status) and, for the samples given up, the stream they are counted on and the drop reason
COUNTERS = ("imu_not_after_previous", "mag_before_any_imu", "mag_before_any_imu", "clean_mag_while_cal_in_use",
            "clean_mag_without_params", "mag_queue_overflow", "mag_queue_overflow", "mag_without_verdict",
            "dmc_silent", "imu_past_waiting_mag")
DROPS = {C_IMU_NOT_AFTER: ("imu", "IMU sample not after the previous one"),
         C_NO_IMU_CAL: ("cal", "no IMU sample yet"),
         C_NO_IMU_CLEAN: ("clean", "no IMU sample yet"),
         C_CAL_IN_USE: ("clean", "calibrated stream cal/mag in use"),
         C_NO_PARAMS: ("clean", "no calibration parameters yet (cal/params or manifest mag_params)"),
         C_OVERFLOW_CAL: ("cal", "neither the IMU nor the DMC verdict reached its time"),
         C_OVERFLOW_CLEAN: ("clean", "neither the IMU nor the DMC verdict reached its time")}

# ---- settings column ----------------------------------------------------------------------------------------
S_CAL_TIMEOUT = 0
S_DMC_TIMEOUT = 1
S_DMC_WAIT_WALL = 2
S_MAG_WAIT = 3
S_MAX_GAP = 4
S_MAX_PENDING = 5
S_PERIOD = 6
S_CLEAR_STD = 7
N_S = 8

# ---- event buffer columns: floats (EF) and integers (EI) ---------------------------------------------------
V_T, V_A, V_B, V_DT, V_GAP, N_V = 0, 1, 4, 7, 8, 9
W_SLOT, W_KIND, W_DMC, W_RESET, N_W = 0, 1, 2, 3, 4

# ---- what a push call stopped for --------------------------------------------------------------------------
_DONE, _GROW_PM, _GROW_PI, _GROW_DH, _GROW_EV = 0, 1, 2, 3, 4

M_INIT, M_MAG = 0, 1  # compiled.MODES codes the output rules read


# =========================================================================================================
# kernels
# =========================================================================================================
@njit(cache=True, inline="always")
def _newest_verdict_t(IS, DHT, k):
    cap = DHT.shape[1]
    return DHT[k, (IS[k, I_DH_HEAD] + IS[k, I_DH_N] - 1) % cap]


@njit(cache=True, inline="always")
def _verdict_at(IS, DHT, DHV, k, t):
    """The validity of the latest-arrived verdict at or before ``t`` (−1: none)."""
    cap = DHT.shape[1]
    h, n = IS[k, I_DH_HEAD], IS[k, I_DH_N]
    for j in range(n - 1, -1, -1):
        i = (h + j) % cap
        if DHT[k, i] <= t + 1e-6:
            return DHV[k, i]
    return -1


@njit(cache=True, inline="always")
def _verdict_due(IS, DHT, PM, k, pm_i, now, S):
    """(still waiting, why not: 0 waits / 1 no verdict stream / 2 detector silent / 3 wall-clock wait over)."""
    if IS[k, I_DH_N] == 0:
        return False, 1
    if PM[k, pm_i, 0] - _newest_verdict_t(IS, DHT, k) > S[S_DMC_TIMEOUT]:
        return False, 2
    if now - PM[k, pm_i, 4] < S[S_DMC_WAIT_WALL]:
        return True, 0
    return False, 3


@njit(cache=True, inline="always")
def _event(EF, EI, n_ev, k, kind, t, a0, a1, a2, b0, b1, b2, dt, dmc, reset, gap):
    EF[n_ev, V_T] = t
    EF[n_ev, V_A] = a0
    EF[n_ev, V_A + 1] = a1
    EF[n_ev, V_A + 2] = a2
    EF[n_ev, V_B] = b0
    EF[n_ev, V_B + 1] = b1
    EF[n_ev, V_B + 2] = b2
    EF[n_ev, V_DT] = dt
    EF[n_ev, V_GAP] = gap
    EI[n_ev, W_SLOT] = k
    EI[n_ev, W_KIND] = kind
    EI[n_ev, W_DMC] = dmc
    EI[n_ev, W_RESET] = reset


@njit(cache=True, inline="always")
def _drain(F, IS, PM, PI, DHT, DHV, C, k, now, S, EF, EI, n_ev):
    """The per-sample service's ``_drain`` for slot ``k``: events appended from ``n_ev``; returns the new count."""
    pm_cap, pi_cap = PM.shape[1], PI.shape[1]
    maxp = S[S_MAX_PENDING]
    while True:
        has_mag = IS[k, I_PM_N] > 0
        mi = IS[k, I_PM_HEAD]
        mt = PM[k, mi, 0] if has_mag else 0.0
        last_imu = F[k, F_LAST_IMU]
        if has_mag and not math.isnan(last_imu) and mt <= last_imu + 1e-6:
            dmc = -1
            ready = True
            if IS[k, I_DH_N] > 0:
                if _newest_verdict_t(IS, DHT, k) >= mt - 1e-6:
                    dmc = _verdict_at(IS, DHT, DHV, k, mt)
                else:
                    due, why = _verdict_due(IS, DHT, PM, k, mi, now, S)
                    if due:
                        ready = False  # the verdict for this time is on its way
                    elif why == 3:
                        C[k, C_WAITED_OUT] += 1
                    elif why == 2:
                        C[k, C_DMC_SILENT] += 1
            if ready:
                _event(EF, EI, n_ev, k, E_MAG, mt, PM[k, mi, 1], PM[k, mi, 2], PM[k, mi, 3], 0.0, 0.0, 0.0, 0.0, dmc,
                       0, 0.0)
                n_ev += 1
                IS[k, I_PM_HEAD] = (mi + 1) % pm_cap
                IS[k, I_PM_N] -= 1
                continue
        if IS[k, I_PI_N] == 0:
            break
        ii = IS[k, I_PI_HEAD]
        it = PI[k, ii, 0]
        if has_mag and mt < it - 1e-9 and not math.isnan(last_imu) and mt <= last_imu + 1e-6:
            # that magnetometer sample waits for its verdict: the IMU goes on (up to the bound)
            due, why = _verdict_due(IS, DHT, PM, k, mi, now, S)
            if due:
                if IS[k, I_PI_N] < maxp:
                    break
                C[k, C_IMU_FORCED] += 1
        elif (not math.isnan(F[k, F_NEWEST_MAG]) and it > F[k, F_NEWEST_MAG] + 1e-6
              and F[k, F_NEWEST_IMU] - F[k, F_NEWEST_MAG] <= S[S_MAG_WAIT] and IS[k, I_PI_N] < maxp):
            break  # the magnetometer stream has not reached this time yet: wait a little for it
        IS[k, I_PI_HEAD] = (ii + 1) % pi_cap
        IS[k, I_PI_N] -= 1
        dt = 0.0 if math.isnan(last_imu) else it - last_imu
        gap = dt
        reset = 0
        if dt > S[S_MAX_GAP]:
            reset = 1
            dt = 0.0
        F[k, F_LAST_IMU] = it
        _event(EF, EI, n_ev, k, E_IMU, it, PI[k, ii, 1], PI[k, ii, 2], PI[k, ii, 3], PI[k, ii, 4], PI[k, ii, 5],
               PI[k, ii, 6], dt, -1, reset, gap)
        n_ev += 1
    return n_ev


@njit(cache=True, inline="always")
def _count(C, D, k, c):
    C[k, c] += 1
    D[k, c] += 1


@njit(cache=True, inline="always")
def _push_row(F, IS, PM, PI, DHT, DHV, C, D, k, code, t, v0, v1, v2, w0, w1, w2, now, S, EF, EI, n_ev):
    """One pushed sample of slot ``k`` and its slot's drain: returns (events written, why stopped) — stopped
    before the row (nothing changed) when a ring, or the event buffer, has to grow first."""
    pm_cap, pi_cap, dh_cap = PM.shape[1], PI.shape[1], DHT.shape[1]
    if n_ev + IS[k, I_PM_N] + IS[k, I_PI_N] + 1 > EF.shape[0]:
        return n_ev, _GROW_EV
    if code == R_IMU:
        if IS[k, I_PI_N] >= pi_cap:
            return n_ev, _GROW_PI
        if not math.isnan(F[k, F_NEWEST_IMU]) and t <= F[k, F_NEWEST_IMU]:
            _count(C, D, k, C_IMU_NOT_AFTER)
            return n_ev, _DONE
        F[k, F_NEWEST_IMU] = t
        j = (IS[k, I_PI_HEAD] + IS[k, I_PI_N]) % pi_cap
        PI[k, j, 0] = t
        PI[k, j, 1] = v0
        PI[k, j, 2] = v1
        PI[k, j, 3] = v2
        PI[k, j, 4] = w0
        PI[k, j, 5] = w1
        PI[k, j, 6] = w2
        IS[k, I_PI_N] += 1
    elif code == R_DMC:
        n = IS[k, I_DH_N]
        if n >= dh_cap and dh_cap < DMC_HISTORY:
            return n_ev, _GROW_DH
        valid = 1 if v0 != 0.0 else 0
        IS[k, I_DMC_VALID] = valid
        F[k, F_DMC_CRED] = v1
        F[k, F_DMC_T] = t
        if n >= dh_cap:  # full: the oldest verdict goes (deque(maxlen))
            IS[k, I_DH_HEAD] = (IS[k, I_DH_HEAD] + 1) % dh_cap
            n -= 1
        j = (IS[k, I_DH_HEAD] + n) % dh_cap
        DHT[k, j] = t
        DHV[k, j] = valid
        IS[k, I_DH_N] = n + 1
        if IS[k, I_PM_N] == 0:
            return n_ev, _DONE  # nothing waits for a verdict: the drain would release nothing new
    else:
        if IS[k, I_PM_N] >= pm_cap:
            return n_ev, _GROW_PM
        b0, b1, b2 = v0, v1, v2
        if code == R_CAL:
            F[k, F_LAST_CAL] = t
            src = 0
        else:
            if t - F[k, F_LAST_CAL] <= S[S_CAL_TIMEOUT]:
                _count(C, D, k, C_CAL_IN_USE)
                return n_ev, _DONE
            if IS[k, I_HAS_PARAMS] == 0:
                _count(C, D, k, C_NO_PARAMS)
                return n_ev, _DONE
            d0, d1, d2 = v0 - F[k, F_OFF], v1 - F[k, F_OFF + 1], v2 - F[k, F_OFF + 2]
            m = F_M
            b0 = F[k, m] * d0 + F[k, m + 1] * d1 + F[k, m + 2] * d2
            b1 = F[k, m + 3] * d0 + F[k, m + 4] * d1 + F[k, m + 5] * d2
            b2 = F[k, m + 6] * d0 + F[k, m + 7] * d1 + F[k, m + 8] * d2
            src = 1
        if math.isnan(F[k, F_NEWEST_IMU]):
            _count(C, D, k, C_NO_IMU_CAL if src == 0 else C_NO_IMU_CLEAN)
            return n_ev, _DONE
        nm = F[k, F_NEWEST_MAG]
        F[k, F_NEWEST_MAG] = t if math.isnan(nm) else max(nm, t)
        j = (IS[k, I_PM_HEAD] + IS[k, I_PM_N]) % pm_cap
        PM[k, j, 0] = t
        PM[k, j, 1] = b0
        PM[k, j, 2] = b1
        PM[k, j, 3] = b2
        PM[k, j, 4] = now
        PM[k, j, 5] = src
        IS[k, I_PM_N] += 1
        if IS[k, I_PM_N] > S[S_MAX_PENDING]:
            h = IS[k, I_PM_HEAD]
            _count(C, D, k, C_OVERFLOW_CAL if PM[k, h, 5] == 0 else C_OVERFLOW_CLEAN)
            IS[k, I_PM_HEAD] = (h + 1) % pm_cap
            IS[k, I_PM_N] -= 1
    return _drain(F, IS, PM, PI, DHT, DHV, C, k, now, S, EF, EI, n_ev), _DONE


@njit(cache=True)
def _push(F, IS, PM, PI, DHT, DHV, C, D, r_slot, r_code, r_t, r_v, r_w, start, now, S, EF, EI, n_ev):
    """Push rows start… (each followed by its slot's drain). Returns (rows done, events written, why stopped):
    a call stops before a row whose ring, or the event buffer, has to grow first (the caller grows it and calls
    again from there)."""
    for r in range(start, r_slot.shape[0]):
        n_ev, why = _push_row(F, IS, PM, PI, DHT, DHV, C, D, r_slot[r], r_code[r], r_t[r], r_v[r, 0], r_v[r, 1],
                              r_v[r, 2], r_w[r, 0], r_w[r, 1], r_w[r, 2], now, S, EF, EI, n_ev)
        if why != _DONE:
            return r, n_ev, why
    return r_slot.shape[0], n_ev, _DONE


@njit(cache=True)
def _push1(F, IS, PM, PI, DHT, DHV, C, D, k, code, t, v0, v1, v2, w0, w1, w2, now, S, EF, EI):
    """One sample (the per-sample path): (events written from 0, why stopped)."""
    return _push_row(F, IS, PM, PI, DHT, DHV, C, D, k, code, t, v0, v1, v2, w0, w1, w2, now, S, EF, EI, 0)


@njit(cache=True, inline="always")
def _decide_row(F, IS, S, k, kind, t, reset, mode, unc, hstd):
    """The output rules after one stepped event of slot ``k``: returns (publish, alarm: −1 none / 1 raised / 0
    cleared, the cleared alarm's raise time, the mode code the row left)."""
    if reset:
        IS[k, I_MODE] = M_INIT
    left = IS[k, I_MODE]
    IS[k, I_MODE] = mode
    if kind != E_IMU or mode == M_INIT:
        return False, -1, math.nan, left
    alarm = -1
    raised_t = math.nan
    if IS[k, I_RAISED] == 0 and unc:
        IS[k, I_RAISED] = 1
        F[k, F_RAISED_T] = t
        alarm = 1
        raised_t = t
    elif IS[k, I_RAISED] != 0 and (mode == M_MAG or hstd < S[S_CLEAR_STD]):
        IS[k, I_RAISED] = 0
        alarm = 0
        raised_t = F[k, F_RAISED_T]
    publish = False
    if t - F[k, F_LAST_PUB] >= S[S_PERIOD] - 1e-9:
        F[k, F_LAST_PUB] = t
        publish = True
    return publish, alarm, raised_t, left


@njit(cache=True)
def _decide(F, IS, S, e_slot, e_kind, e_t, e_reset, o_mode, o_unc, o_hstd, o_reason, pub, al_row, al_state,
            al_raised_t, tr_row, tr_from):
    """The output rules over stepped events (module docstring); returns (published, alarm, transition) counts."""
    n_pub, n_al, n_tr = 0, 0, 0
    for r in range(e_slot.shape[0]):
        publish, alarm, raised_t, left = _decide_row(F, IS, S, e_slot[r], e_kind[r], e_t[r], e_reset[r], o_mode[r],
                                                     o_unc[r], o_hstd[r])
        if o_reason[r] != 0:
            tr_row[n_tr] = r
            tr_from[n_tr] = left
            n_tr += 1
        if alarm >= 0:
            al_row[n_al] = r
            al_state[n_al] = alarm
            al_raised_t[n_al] = raised_t
            n_al += 1
        if publish:
            pub[n_pub] = r
            n_pub += 1
    return n_pub, n_al, n_tr


@njit(cache=True)
def _decide1(F, IS, S, k, kind, t, reset, mode, unc, hstd):
    return _decide_row(F, IS, S, k, kind, t, reset, mode, unc, hstd)


# =========================================================================================================
# Python API
# =========================================================================================================
class Events(NamedTuple):
    """What the join released, in order (views into the join's buffers: valid until its next push).
    ``slot``, ``kind`` (0 IMU, 1 magnetometer), ``t_s``, ``a`` (gyro rad/s or calibrated field nT), ``b``
    (accelerometer m/s²), ``dt_s``, ``dmc`` (−1 none, 0 invalid, 1 valid), ``reset`` (an IMU gap restarts the
    slot's filter before this event), ``gap_s`` (the IMU step before the reset)."""

    n: int
    slot: np.ndarray
    kind: np.ndarray
    t_s: np.ndarray
    a: np.ndarray
    b: np.ndarray
    dt_s: np.ndarray
    dmc: np.ndarray
    reset: np.ndarray
    gap_s: np.ndarray

    def rows(self, idx=None) -> list[tuple]:
        """Rows ``idx`` (all when None) as :meth:`FleetJoin.push_one` gives them."""
        idx = range(self.n) if idx is None else idx
        sl, kd, dm, rs = self.slot.tolist(), self.kind.tolist(), self.dmc.tolist(), self.reset.tolist()
        t, a, b, dt, gap = self.t_s.tolist(), self.a.tolist(), self.b.tolist(), self.dt_s.tolist(), self.gap_s.tolist()
        return [(sl[r], kd[r], dm[r], rs[r], t[r], a[r], b[r], dt[r], gap[r]) for r in idx]


class Decisions(NamedTuple):
    """Rows of the events to act on: ``publish`` (a heading message after the row), ``alarm_row`` with
    ``alarm_state`` (1 raised, 0 cleared) and ``alarm_raised_t_s`` (when the alarm cleared was raised; NaN
    unknown), ``transition_row`` with ``transition_from`` (the mode code the row left)."""

    publish: np.ndarray
    alarm_row: np.ndarray
    alarm_state: np.ndarray
    alarm_raised_t_s: np.ndarray
    transition_row: np.ndarray
    transition_from: np.ndarray


class FleetJoin:
    """The join and output state of many vehicle slots (module docstring)."""

    def __init__(self, capacity: int = 16, cal_timeout_s: float = 1.0, dmc_timeout_s: float = 2.0,
                 dmc_wait_wall_s: float = 1.0, mag_wait_s: float = 0.2, max_imu_gap_s: float = 1.0,
                 publish_period_s: float = 0.1, alarm_clear_std_rad: float = 0.0, max_pending: int = MAX_PENDING):
        self.S = np.zeros(N_S)
        self.S[S_CAL_TIMEOUT], self.S[S_DMC_TIMEOUT], self.S[S_DMC_WAIT_WALL] = cal_timeout_s, dmc_timeout_s, dmc_wait_wall_s
        self.S[S_MAG_WAIT], self.S[S_MAX_GAP], self.S[S_MAX_PENDING] = mag_wait_s, max_imu_gap_s, max_pending
        self.S[S_PERIOD], self.S[S_CLEAR_STD] = publish_period_s, alarm_clear_std_rad
        self.max_pending = int(max_pending)
        cap = max(1, int(capacity))
        self.F = np.zeros((cap, N_F))
        self.IS = np.zeros((cap, N_I), np.int64)
        self.C = np.zeros((cap, N_C), np.int64)
        self.D = np.zeros((cap, N_C), np.int64)
        r0 = min(_RING0, self.max_pending + 1)
        self.PM = np.zeros((cap, r0, 6))
        self.PI = np.zeros((cap, r0, 7))
        self.DHT = np.zeros((cap, min(_RING0, DMC_HISTORY)))
        self.DHV = np.zeros((cap, min(_RING0, DMC_HISTORY)), np.int8)
        self.EF = np.zeros((256, N_V))  # released events (floats, integers): see Events
        self.EI = np.zeros((256, N_W), np.int64)

    @property
    def capacity(self) -> int:
        return self.F.shape[0]

    # ---- slots ----
    def add(self) -> int:
        free = np.flatnonzero(self.IS[:, I_USED] == 0)
        if not len(free):
            self._grow_slots(2 * self.capacity)
            free = np.flatnonzero(self.IS[:, I_USED] == 0)
        k = int(free[0])
        self.F[k] = 0.0
        self.F[k, [F_LAST_IMU, F_NEWEST_IMU, F_NEWEST_MAG, F_DMC_CRED, F_RAISED_T]] = math.nan
        self.F[k, [F_LAST_CAL, F_DMC_T, F_LAST_PUB]] = -math.inf
        self.IS[k] = 0
        self.IS[k, I_DMC_VALID] = -1
        self.IS[k, I_USED] = 1
        self.C[k] = 0
        self.D[k] = 0
        return k

    def free(self, slot: int) -> None:
        self.IS[slot] = 0
        self.D[slot] = 0

    def set_params(self, slot: int, offset_nt, matrix) -> None:
        """clean/mag compensation of the slot: h = M (m − offset) (``matrix`` 3×3 or 9 row-major)."""
        self.F[slot, F_OFF:F_OFF + 3] = np.asarray(offset_nt, float).reshape(3)
        self.F[slot, F_M:F_M + 9] = np.asarray(matrix, float).reshape(9)
        self.IS[slot, I_HAS_PARAMS] = 1

    def set_alarm(self, slot: int, raised: bool, raised_t_s: float | None) -> None:
        """The heading alarm latch as the mesh holds it (after a restart, a swap)."""
        self.IS[slot, I_RAISED] = int(bool(raised))
        self.F[slot, F_RAISED_T] = math.nan if raised_t_s is None else float(raised_t_s)

    def set_mode(self, slot: int, mode: int) -> None:
        """The filter's mode code now (after a change outside the stepped events: a field re-base)."""
        self.IS[slot, I_MODE] = mode

    def alarm_raised(self, slot: int) -> bool:
        return bool(self.IS[slot, I_RAISED])

    def dmc(self, slot: int) -> tuple[bool | None, float | None, float]:
        """(validity, credibility, time) of the slot's last verdict."""
        v = int(self.IS[slot, I_DMC_VALID])
        c = float(self.F[slot, F_DMC_CRED])
        return (None if v < 0 else bool(v)), (None if math.isnan(c) else c), float(self.F[slot, F_DMC_T])

    def last_imu_t(self, slot: int) -> float | None:
        t = float(self.F[slot, F_LAST_IMU])
        return None if math.isnan(t) else t

    def counts(self, slot: int) -> dict[str, int]:
        """Cumulative counts of the slot's samples given up (or used without a verdict), by reason."""
        out: dict[str, int] = {}
        for c in range(N_C):
            n = int(self.C[slot, c])
            if n:
                out[COUNTERS[c]] = out.get(COUNTERS[c], 0) + n
        return out

    def pending_mag(self, slot: int) -> list[tuple[float, list[float], str, float]]:
        """The slot's waiting magnetometer samples, oldest first: (t_s, field nT, "cal" | "clean", arrived)."""
        cap = self.PM.shape[1]
        h, n = int(self.IS[slot, I_PM_HEAD]), int(self.IS[slot, I_PM_N])
        rows = self.PM[slot, (h + np.arange(n)) % cap]
        return [(float(r[0]), r[1:4].tolist(), "cal" if r[5] == 0 else "clean", float(r[4])) for r in rows]

    def pending_imu(self, slot: int) -> int:
        return int(self.IS[slot, I_PI_N])

    def take_drops(self, slot: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(slots, counts by counter) of the samples given up since the last call (of one slot, or of all); the
        report is then cleared."""
        D = self.D
        if slot is not None:
            if not D[slot].any():
                return np.zeros(0, np.int64), D[:0]
            out = D[slot:slot + 1].copy()
            D[slot] = 0
            return np.array([slot]), out
        rows = np.flatnonzero(D.any(axis=1))
        if not len(rows):
            return rows, D[:0]
        out = D[rows].copy()
        D[rows] = 0
        return rows, out

    # ---- growth ----
    def _grow_slots(self, cap: int) -> None:
        n = self.capacity

        def grown(a):
            b = np.zeros((cap,) + a.shape[1:], a.dtype)
            b[:n] = a
            return b

        self.F, self.IS, self.C, self.D = grown(self.F), grown(self.IS), grown(self.C), grown(self.D)
        self.PM, self.PI, self.DHT, self.DHV = grown(self.PM), grown(self.PI), grown(self.DHT), grown(self.DHV)

    @staticmethod
    def _unrolled(ring: np.ndarray, head: np.ndarray, count: np.ndarray, new_cap: int) -> np.ndarray:
        """The rings with a new capacity, oldest item first (heads then 0)."""
        slots, cap = ring.shape[:2]
        out = np.zeros((slots, new_cap) + ring.shape[2:], ring.dtype)
        j = np.arange(cap)
        idx = (head[:, None] + j[None, :]) % cap
        keep = j[None, :] < count[:, None]
        src = ring[np.arange(slots)[:, None], idx]
        out[:, :cap][keep] = src[keep]
        return out

    def _grow_ring(self, which: int) -> None:
        IS = self.IS
        if which == _GROW_PM:
            new = min(2 * self.PM.shape[1], self.max_pending + 1)
            self.PM = self._unrolled(self.PM, IS[:, I_PM_HEAD], IS[:, I_PM_N], new)
            IS[:, I_PM_HEAD] = 0
        elif which == _GROW_PI:
            new = min(2 * self.PI.shape[1], self.max_pending + 1)
            self.PI = self._unrolled(self.PI, IS[:, I_PI_HEAD], IS[:, I_PI_N], new)
            IS[:, I_PI_HEAD] = 0
        else:
            new = min(2 * self.DHT.shape[1], DMC_HISTORY)
            self.DHT = self._unrolled(self.DHT, IS[:, I_DH_HEAD], IS[:, I_DH_N], new)
            self.DHV = self._unrolled(self.DHV, IS[:, I_DH_HEAD], IS[:, I_DH_N], new)
            IS[:, I_DH_HEAD] = 0

    def _grow_events(self, n_ev: int, more: int) -> None:
        cap = max(2 * self.EF.shape[0], n_ev + more)
        EF, EI = np.zeros((cap, N_V)), np.zeros((cap, N_W), np.int64)
        EF[:n_ev], EI[:n_ev] = self.EF[:n_ev], self.EI[:n_ev]
        self.EF, self.EI = EF, EI

    # ---- the join ----
    def push(self, slot, code, t_s, v, w, now: float) -> Events:
        """Push rows (each followed by its slot's drain): ``code`` R_IMU (``v`` gyro, ``w`` accelerometer),
        R_CAL (``v`` calibrated field), R_CLEAN (``v`` raw field, compensated here), R_DMC (``v[:, 0]`` validity
        1/0, ``v[:, 1]`` credibility); rows of one slot in the order its samples arrived. ``now``: wall-clock
        (monotonic) seconds. Returns the events released, in order."""
        n = len(slot)
        slot = np.ascontiguousarray(slot, np.int64)
        code = np.ascontiguousarray(code, np.int8)
        t_s = np.ascontiguousarray(t_s, float)
        v = np.ascontiguousarray(v, float)
        w = np.ascontiguousarray(w, float)
        done, n_ev = 0, 0
        while True:
            done, n_ev, why = _push(self.F, self.IS, self.PM, self.PI, self.DHT, self.DHV, self.C, self.D, slot, code,
                                    t_s, v, w, done, float(now), self.S, self.EF, self.EI, n_ev)
            if why == _DONE:
                break
            self._grow(why, n_ev, 2 * self.max_pending + 2 * (n - done) + 2)
        ef, ei = self.EF[:n_ev], self.EI[:n_ev]
        return Events(n_ev, ei[:, W_SLOT].copy(), ei[:, W_KIND].astype(np.int8), ef[:, V_T].copy(),
                      ef[:, V_A:V_A + 3].copy(), ef[:, V_B:V_B + 3].copy(), ef[:, V_DT].copy(),
                      ei[:, W_DMC].astype(np.int8), ei[:, W_RESET].astype(np.int8), ef[:, V_GAP].copy())

    def _grow(self, why: int, n_ev: int, more: int) -> None:
        if why == _GROW_EV:
            self._grow_events(n_ev, more)
        else:
            self._grow_ring(why)

    def push_one(self, slot: int, code: int, t_s: float, v, w, now: float) -> list[tuple]:
        """One sample (the per-sample path; ``w`` None: zeros): the events released, each a tuple (slot, kind,
        dmc, reset, t_s, a, b, dt_s, gap_s) — see :class:`Events`."""
        w0, w1, w2 = (0.0, 0.0, 0.0) if w is None else (float(w[0]), float(w[1]), float(w[2]))
        while True:
            n_ev, why = _push1(self.F, self.IS, self.PM, self.PI, self.DHT, self.DHV, self.C, self.D, int(slot),
                               int(code), float(t_s), float(v[0]), float(v[1]), float(v[2]), w0, w1, w2, float(now),
                               self.S, self.EF, self.EI)
            if why == _DONE:
                break
            self._grow(why, 0, 2 * self.max_pending + 2)
        if not n_ev:
            return []
        ef, ei = self.EF[:n_ev].tolist(), self.EI[:n_ev].tolist()
        return [(i[0], i[1], i[2], i[3], f[0], f[1:4], f[4:7], f[7], f[8]) for i, f in zip(ei, ef, strict=True)]

    # ---- the output rules ----
    def decide(self, ev: Events, mode, uncertain, heading_std_rad, reason) -> Decisions:
        """Walk stepped events with the slots' output state (module docstring): per row the filter's mode code
        after it, its heading-uncertain flag, heading σ (rad) and mode-change reason code (0: none)."""
        n = ev.n
        pub = np.empty(n, np.int64)
        al_row = np.empty(n, np.int64)
        al_state = np.empty(n, np.int8)
        al_t = np.empty(n)
        tr_row = np.empty(n, np.int64)
        tr_from = np.empty(n, np.int64)
        n_pub, n_al, n_tr = _decide(self.F, self.IS, self.S, ev.slot, ev.kind, ev.t_s, ev.reset,
                                    np.ascontiguousarray(mode, np.int64), np.ascontiguousarray(uncertain, np.bool_),
                                    np.ascontiguousarray(heading_std_rad, float), np.ascontiguousarray(reason, np.int64),
                                    pub, al_row, al_state, al_t, tr_row, tr_from)
        return Decisions(pub[:n_pub], al_row[:n_al], al_state[:n_al], al_t[:n_al], tr_row[:n_tr], tr_from[:n_tr])

    def decide_one(self, slot: int, kind: int, t_s: float, reset: bool, mode: int, uncertain: bool,
                   heading_std_rad: float) -> tuple[bool, int, float]:
        """:meth:`decide` for one event (a filter stepped row by row): (publish, alarm −1 none / 1 raised / 0 cleared,
        the cleared alarm's raise time)."""
        p, a, t, _ = _decide1(self.F, self.IS, self.S, int(slot), int(kind), float(t_s), bool(reset), int(mode),
                              bool(uncertain), float(heading_std_rad))
        return p, a, t


class SlotFilter(compiled.CompiledHeadingFilter):
    """One slot of a shared :class:`compiled.FleetHeading` behind the per-vehicle filter's API (what the service's
    status, re-base and tests read). The fleet is stepped by its owner, which appends the slot's mode changes to
    ``transitions`` and keeps this view's count of them (``_ntr``) in step."""

    def __init__(self, fleet: compiled.FleetHeading, slot: int):  # no fleet of its own: the base's __init__ not run
        self.settings = fleet.settings[slot]
        self._fleet, self._slot = fleet, slot
        self.transitions: list[tuple[float, str, str, str]] = []
        self._ntr = fleet.mode_changes(slot)

    @property
    def slot(self) -> int:
        return self._slot


# =========================================================================================================
# the reference: the same rule in plain Python, one vehicle
# =========================================================================================================
class ReferenceJoin:
    """One vehicle's join as the per-sample service ran it (deques, a verdict history), for the tests."""

    def __init__(self, cal_timeout_s: float = 1.0, dmc_timeout_s: float = 2.0, dmc_wait_wall_s: float = 1.0,
                 mag_wait_s: float = 0.2, max_imu_gap_s: float = 1.0, max_pending: int = MAX_PENDING):
        self.cal_timeout_s, self.dmc_timeout_s, self.dmc_wait_wall_s = cal_timeout_s, dmc_timeout_s, dmc_wait_wall_s
        self.mag_wait_s, self.max_imu_gap_s, self.max_pending = mag_wait_s, max_imu_gap_s, max_pending
        self.last_imu_t = self.newest_imu_t = self.newest_mag_t = None
        self.last_cal_t = -math.inf
        self.dmc_hist: deque = deque(maxlen=DMC_HISTORY)
        self.pending_mag: deque = deque()  # (t, b, src, arrived)
        self.pending_imu: deque = deque()  # (t, gyro, accel)
        self.params = None  # (offset, M)
        self.counts = [0] * N_C
        self.events: list[tuple] = []  # (kind, t, a, b, dt, dmc, reset, gap)

    def push(self, code: int, t: float, v, w, now: float) -> list[tuple]:
        n0 = len(self.events)
        if code == R_IMU:
            if self.newest_imu_t is not None and t <= self.newest_imu_t:
                self.counts[C_IMU_NOT_AFTER] += 1
                return []
            self.newest_imu_t = t
            self.pending_imu.append((t, tuple(v), tuple(w)))
            self._drain(now)
        elif code == R_DMC:
            self.dmc_hist.append((t, 1 if v[0] else 0))
            self._drain(now)
        else:
            b = tuple(float(x) for x in v)
            if code == R_CAL:
                self.last_cal_t = t
                src = 0
            else:
                if t - self.last_cal_t <= self.cal_timeout_s:
                    self.counts[C_CAL_IN_USE] += 1
                    return []
                if self.params is None:
                    self.counts[C_NO_PARAMS] += 1
                    return []
                off, M = self.params
                d = [b[i] - off[i] for i in range(3)]
                b = tuple(M[i][0] * d[0] + M[i][1] * d[1] + M[i][2] * d[2] for i in range(3))
                src = 1
            if self.newest_imu_t is None:
                self.counts[C_NO_IMU_CAL if src == 0 else C_NO_IMU_CLEAN] += 1
                return []
            self.newest_mag_t = t if self.newest_mag_t is None else max(self.newest_mag_t, t)
            self.pending_mag.append((t, b, src, now))
            if len(self.pending_mag) > self.max_pending:
                self.counts[C_OVERFLOW_CAL if self.pending_mag.popleft()[2] == 0 else C_OVERFLOW_CLEAN] += 1
            self._drain(now)
        return self.events[n0:]

    def _drain(self, now: float) -> None:
        while True:
            mag = self.pending_mag[0] if self.pending_mag else None
            if mag is not None and self.last_imu_t is not None and mag[0] <= self.last_imu_t + 1e-6:
                t = mag[0]
                dmc, ready = -1, True
                if self.dmc_hist:
                    if self.dmc_hist[-1][0] >= t - 1e-6:
                        dmc = self._verdict_at(t)
                    else:
                        due, why = self._verdict_due(mag, now)
                        if due:
                            ready = False
                        elif why == 3:
                            self.counts[C_WAITED_OUT] += 1
                        elif why == 2:
                            self.counts[C_DMC_SILENT] += 1
                if ready:
                    self.pending_mag.popleft()
                    self.events.append((E_MAG, t, mag[1], (0.0, 0.0, 0.0), 0.0, dmc, 0, 0.0))
                    continue
            imu = self.pending_imu[0] if self.pending_imu else None
            if imu is None:
                break
            if (mag is not None and mag[0] < imu[0] - 1e-9 and self.last_imu_t is not None
                    and mag[0] <= self.last_imu_t + 1e-6):
                if self._verdict_due(mag, now)[0]:
                    if len(self.pending_imu) < self.max_pending:
                        break
                    self.counts[C_IMU_FORCED] += 1
            elif (self.newest_mag_t is not None and imu[0] > self.newest_mag_t + 1e-6
                    and self.newest_imu_t - self.newest_mag_t <= self.mag_wait_s
                    and len(self.pending_imu) < self.max_pending):
                break
            self.pending_imu.popleft()
            t, g, a = imu
            dt = 0.0 if self.last_imu_t is None else t - self.last_imu_t
            gap, reset = dt, 0
            if dt > self.max_imu_gap_s:
                reset, dt = 1, 0.0
            self.last_imu_t = t
            self.events.append((E_IMU, t, g, a, dt, -1, reset, gap))

    def _verdict_due(self, mag: tuple, now: float) -> tuple[bool, int]:
        if not self.dmc_hist:
            return False, 1
        if mag[0] - self.dmc_hist[-1][0] > self.dmc_timeout_s:
            return False, 2
        if now - mag[3] < self.dmc_wait_wall_s:
            return True, 0
        return False, 3

    def _verdict_at(self, t: float) -> int:
        for tv, valid in reversed(self.dmc_hist):
            if tv <= t + 1e-6:
                return valid
        return -1


# =========================================================================================================
# warm-up
# =========================================================================================================
KERNELS = (_push, _push1, _decide, _decide1)


def warm() -> float:
    """Compile (or load from numba's disk cache) every kernel of this module; returns the seconds it took."""
    t0 = time.perf_counter()
    j = FleetJoin(2, max_pending=4)
    k = j.add()
    j.set_params(k, (1.0, 2.0, 3.0), np.eye(3))
    rows = [(R_IMU, 0.0), (R_CLEAN, 0.0), (R_DMC, 0.0), (R_IMU, 0.01), (R_CAL, 0.01), (R_IMU, 0.02), (R_DMC, 0.01)]
    n = len(rows)
    ev = j.push(np.full(n, k, np.int64), np.array([c for c, _ in rows], np.int8), np.array([t for _, t in rows]),
                np.ones((n, 3)), np.ones((n, 3)), 0.0)
    m = ev.n
    j.decide(ev, np.ones(m, np.int64), np.zeros(m, bool), np.zeros(m), np.zeros(m, np.int64))
    j.decide_one(k, E_IMU, 1.0, False, M_MAG, True, 0.1)
    j.push_one(k, R_IMU, 1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 9.8), 0.0)
    j.push_one(k, R_DMC, 1.0, (1.0, 1.0, 0.0), None, 0.0)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] != "--warm":
        print("usage: python -m services.heading_fuser.fleet --warm   (compile the join's kernels into numba's disk "
              "cache)")
        return 2
    took = warm()
    print(f"heading_fuser fleet join kernels ready in {took:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
