"""The DMC detector's cores on a whole fleet: many vehicles' state in arrays, a frame's epochs in one call.

Pure numpy + numba; never imports zenoh. The maths is :mod:`services.dmc_detector.core`'s and
:mod:`services.dmc_detector.fcm`'s, step for step (docs/methods.md#dmc): the per-vehicle classes
(:class:`~core.ThresholdDetector`, :class:`~fcm.FcmDetector`, :class:`~core.SingleCompassDetector`, and
:class:`magmesh.align.TimeAligner` for the pairing) stay the reference, and ``tests/test_dmc_fleet.py`` holds
both to the same output.

A fleet detector holds *slots* (one per vehicle) and steps every paired epoch of a frame at once:

    det = FleetDetector(core.ThresholdDetectorSettings(), capacity=512)
    s = det.add()
    det.set_params(s, p_a, p_b, declination_rad, dh_ref_rad)
    out = det.step(slot, t_s, b_a_nt, b_b_nt)        # rows of one slot in time order; slots may interleave
    out.valid, out.transition, det.describe(out, i)

One slot's rows are applied in the order given, exactly as the reference's ``update`` calls would be. A
parameter change takes effect between two ``step`` calls (``set_params`` + ``restart_features``, as the
service does on a new ``cal/params``): split a frame there.

Where the work is done. Everything per epoch runs in one compiled kernel (``_step_kernel``): static
compensation with the slot's matrix and offset, strengths, headings, Δh, the smooth and rate windows (per-slot
ring buffers, restarted at gaps over ``max_gap_s``), the four ratios, the FCM memberships and K_c, and the
alarm latch. The stateless part (compensation, strengths, headings, Δh; the memberships) computed in numpy
over the whole frame instead costs more, alone, than the whole fused step at 1, 50 and 500 vehicles
(``magmesh bench cores``, row ``dmc_detector_per_epoch``), so it is compiled with the rest.
Ring buffers start small and double when a slot's window holds more epochs than they fit (a faster
compass); the kernel stops before the row that needs more room, the rings grow, and the step resumes there.

Numbers agree with the reference to rounding, not to the bit (the tests hold the features within 1e-9; on
their drives the largest differences are 6e-11 nT in Δm, 1.2e-10 nT/s in dΔm, 3e-15 rad/s in dΔh, 6e-14 in a
ratio): the reference's small matrix products go through BLAS (fused multiply-adds, in an order that depends
on the CPU's BLAS kernel) and its ``arctan2`` through numpy's SIMD code, the kernel through plain arithmetic
and libm. Sums are taken in the reference's order, so the windows add the same numbers the same way.

Pairing: :func:`pair_frame` joins a frame's two compass streams with the samples still waiting from earlier
frames, by :class:`~magmesh.align.TimeAligner`'s rule, in one compiled pass; :class:`FleetPairer` keeps the
waiting samples and the per-slot counts between frames.

Kernels compile on first use and are cached on disk (``__pycache__``); ``python -m
services.dmc_detector.fleet --warm`` compiles (or loads) every one of them and prints how long it took.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from magmesh.align import REASONS
from magmesh.magcal import MagParams

from . import core
from . import fcm as fcm_mod

MODE_THRESHOLD, MODE_FCM, MODE_SINGLE = 0, 1, 2
#: transition codes of :attr:`FleetOutput.transition`
NO_TRANSITION, RAISED, CLEARED = 0, 1, 2
TRANSITIONS = (None, "raised", "cleared")

# ---- array layouts (shared by the kernels and the Python side) ----------------------------------------------------

# settings vector
(C_SMOOTH, C_RATE, C_MAX_GAP, C_HISTORY_MIN, C_TH_DM, C_TH_DDM, C_TH_DH, C_TH_DDH, C_RAISE_MIN, C_CLEAR_MIN, C_MODE,
 C_KC_MIN, C_M, C_N_GOOD, C_EXTENDED) = range(15)
N_CFG = 15
# per-slot parameters: compass a, compass b (offset 3, matrix 9 row-major, radius, 1.0 if 2-D), declination, Δh_r
P_A, P_B = 0, 14
P_OFF, P_MAT, P_R, P_2D = 0, 3, 12, 13
P_DECL, P_DHREF = 28, 29
N_PARAM = 30
# per-slot latch floats (NaN = None)
L_RAISED_T, L_INVALID_SINCE, L_VALID_SINCE = range(3)
# per-slot last decision: floats (ratios ×4, kc, credibility), ints (has one, valid, ready)
LAST_KC, LAST_CRED = 4, 5
LI_HAS, LI_VALID, LI_READY = range(3)
# output rows (floats, int8)
(F_T, F_DM, F_DM1, F_DDM, F_DDM1, F_DH, F_DDH, F_HEADING, F_CRED, F_KC, F_R, F_R1, F_R2, F_R3,
 F_RAISED_T) = range(15)
N_OUT_F = 15
I_STAGE1, I_VALID, I_READY, I_TRANSITION = range(4)
N_OUT_I = 4

_RAW_CAP0 = 16  # epochs a smooth window holds before its ring doubles (0.2 s at 50 Hz: 10)
_MEANS_CAP0 = 32  # window means a rate window holds (0.5 s at 50 Hz: 26)


# ---- the compiled kernels (plain Python here; numba-compiled on first use) -----------------------------------------


def _step_kernel(slot, t_in, b_a, b_b, start, cfg, centres, usable, params, seg_start, last_t, raw, raw_head, raw_n,
                 means, means_head, means_n, latch_f, raised, last_f, last_i, out_f, out_i):
    """Steps rows ``start…`` of a frame; returns the row it stopped at (``len(t_in)`` when done, earlier when a
    slot's ring is full: nothing of that row has been applied), or −1 − i when row i names a slot that is not
    usable (checked before anything is applied)."""
    n = t_in.shape[0]
    if start == 0:
        for i in range(n):
            if slot[i] < 0 or slot[i] >= usable.shape[0] or not usable[slot[i]]:
                return -1 - i
    two_pi = 2.0 * math.pi
    deg = 180.0 / math.pi
    nan = math.nan
    smooth = cfg[C_SMOOTH]
    rate = cfg[C_RATE]
    max_gap = cfg[C_MAX_GAP]
    history_min = cfg[C_HISTORY_MIN]
    th_dm, th_ddm, th_dh, th_ddh = cfg[C_TH_DM], cfg[C_TH_DDM], cfg[C_TH_DH], cfg[C_TH_DDH]
    raise_min, clear_min = cfg[C_RAISE_MIN], cfg[C_CLEAR_MIN]
    mode = int(cfg[C_MODE])
    kc_min = cfg[C_KC_MIN]
    m_fuzz = cfg[C_M]
    n_good = int(cfg[C_N_GOOD])
    extended = cfg[C_EXTENDED] != 0.0
    n_c = centres.shape[0]
    n_d = centres.shape[1]
    cap_raw = raw.shape[1]
    cap_means = means.shape[1]
    hv = np.empty(3)
    dm = np.empty(2)
    hd = np.empty(2)
    kcs = np.empty(2)
    x = np.empty(4)
    vv = np.empty(max(n_c, 1))
    inv = np.empty(max(n_c, 1))
    # ‖v_i‖² of the centres, summed in numpy's order
    for ci in range(n_c):
        acc = centres[ci, 0] * centres[ci, 0]
        for j in range(1, n_d):
            acc += centres[ci, j] * centres[ci, j]
        vv[ci] = acc
    for i in range(start, n):
        s = slot[i]
        t = t_in[i]
        # a gap (or time going back) restarts the windows (FeatureTracker.update)
        lt = last_t[s]
        if lt == lt and (t - lt > max_gap or t <= lt):
            raw_n[s] = 0
            raw_head[s] = 0
            means_n[s] = 0
            means_head[s] = 0
            seg_start[s] = nan
            last_t[s] = nan
        if raw_n[s] >= cap_raw or means_n[s] >= cap_means:
            return i  # the rings need room: nothing of this row is applied yet
        if seg_start[s] != seg_start[s]:
            seg_start[s] = t
        last_t[s] = t
        # ---- stateless: compensation h = M (m − offset), Δm, headings, Δh
        for k in range(2):
            if mode == MODE_SINGLE:
                p0 = P_A
                src = b_a
            else:
                p0 = P_A if k == 0 else P_B
                src = b_a if k == 0 else b_b
            v0 = src[i, 0] - params[s, p0 + P_OFF]
            v1 = src[i, 1] - params[s, p0 + P_OFF + 1]
            v2 = src[i, 2] - params[s, p0 + P_OFF + 2]
            for j in range(3):
                mj = p0 + P_MAT + 3 * j
                hv[j] = v0 * params[s, mj] + v1 * params[s, mj + 1] + v2 * params[s, mj + 2]
            if params[s, p0 + P_2D] != 0.0:
                strength = math.hypot(hv[0], hv[1])
            else:
                strength = math.sqrt(hv[0] * hv[0] + hv[1] * hv[1] + hv[2] * hv[2])
            dm[k] = strength - params[s, p0 + P_R]
            hd[k] = (math.atan2(hv[1], hv[0]) + params[s, P_DECL]) % two_pi
        dh = ((hd[0] - (hd[1] + params[s, P_DHREF])) + math.pi) % two_pi - math.pi
        # ---- the smooth window: append, drop what fell out, mean
        c = raw_n[s]
        h0 = raw_head[s]
        w = (h0 + c) % cap_raw
        raw[s, w, 0] = t
        raw[s, w, 1] = dm[0]
        raw[s, w, 2] = dm[1]
        raw[s, w, 3] = dh
        raw[s, w, 4] = math.sin(dh)  # each epoch's sine and cosine once: the window sums add the same numbers
        raw[s, w, 5] = math.cos(dh)
        c += 1
        lim = t - smooth
        while c > 0 and raw[s, h0, 0] <= lim:
            h0 = (h0 + 1) % cap_raw
            c -= 1
        raw_head[s] = h0
        raw_n[s] = c
        sdm0 = 0.0
        sdm1 = 0.0
        ssin = 0.0
        scos = 0.0
        r = h0
        for k in range(c):
            if k == 0:
                sdm0 = raw[s, r, 1]
                sdm1 = raw[s, r, 2]
            else:
                sdm0 += raw[s, r, 1]
                sdm1 += raw[s, r, 2]
            ssin += raw[s, r, 4]
            scos += raw[s, r, 5]
            r += 1
            if r == cap_raw:
                r = 0
        mdm0 = sdm0 / c
        mdm1 = sdm1 / c
        mdh = math.atan2(ssin, scos)
        # ---- the rate window: the newest mean at or before t − rate_window_s, and everything after it
        mc = means_n[s]
        mh = means_head[s]
        w = (mh + mc) % cap_means
        means[s, w, 0] = t
        means[s, w, 1] = mdm0
        means[s, w, 2] = mdm1
        means[s, w, 3] = mdh
        mc += 1
        lim = t - rate
        while mc >= 2 and means[s, (mh + 1) % cap_means, 0] <= lim:
            mh = (mh + 1) % cap_means
            mc -= 1
        means_head[s] = mh
        means_n[s] = mc
        ready = t - seg_start[s] >= history_min and means[s, mh, 0] <= lim
        ddm0 = 0.0
        ddm1 = 0.0
        ddh = 0.0
        if ready:
            dt = t - means[s, mh, 0]
            ddm0 = (mdm0 - means[s, mh, 1]) / dt
            ddm1 = (mdm1 - means[s, mh, 2]) / dt
            ddh = (((mdh - means[s, mh, 3]) + math.pi) % two_pi - math.pi) / dt
        if mode == MODE_SINGLE:
            dm1_out = 0.0
            ddm1 = 0.0
        else:
            dm1_out = dm[1]
        # ---- ratios (|feature| / threshold; np.max propagates NaN) and stage 1
        a0 = abs(dm[0])
        a1 = abs(dm1_out)
        if mode == MODE_SINGLE:
            r0 = a0 / th_dm
            r1 = abs(ddm0) / th_ddm
            r2 = nan
            r3 = nan
        else:
            r0 = (nan if (a0 != a0 or a1 != a1) else max(a0, a1)) / th_dm
            a0 = abs(ddm0)
            a1 = abs(ddm1)
            r1 = (nan if (a0 != a0 or a1 != a1) else max(a0, a1)) / th_ddm
            r2 = abs(dh * deg) / th_dh
            r3 = abs(ddh * deg) / th_ddh
        stage1 = not (r0 >= 1.0 or r1 >= 1.0 or r2 >= 1.0 or r3 >= 1.0)
        kc = nan
        if mode == MODE_FCM:
            # K_c = min over the compasses of the memberships summed over the good clusters (FcmModel.credibility)
            for k in range(2):
                x[0] = abs(dm[k]) / th_dm
                if extended:
                    x[1] = abs(ddm0 if k == 0 else ddm1) / th_ddm
                    x[2] = r2
                    x[3] = r3
                else:
                    x[1] = r2
                for j in range(n_d):  # np.clip(x, 0, 1), NaN kept
                    if x[j] < 0.0:
                        x[j] = 0.0
                    elif x[j] > 1.0:
                        x[j] = 1.0
                xx = x[0] * x[0]
                for j in range(1, n_d):
                    xx += x[j] * x[j]
                tot = 0.0
                for ci in range(n_c):
                    vx = centres[ci, 0] * x[0]
                    for j in range(1, n_d):
                        vx += centres[ci, j] * x[j]
                    d2 = vv[ci] + xx - 2.0 * vx
                    if not d2 >= 1e-18:  # np.maximum(d2, 1e-18), NaN kept
                        d2 = d2 if d2 != d2 else 1e-18
                    inv[ci] = 1.0 / d2 if m_fuzz == 2.0 else d2 ** (-1.0 / (m_fuzz - 1.0))
                    tot = inv[ci] if ci == 0 else tot + inv[ci]
                acc = 0.0
                for ci in range(n_good):
                    u = inv[ci] / tot
                    acc = u if ci == 0 else acc + u
                kcs[k] = acc
            kc_all = nan if (kcs[0] != kcs[0] or kcs[1] != kcs[1]) else min(kcs[0], kcs[1])
            kc = kc_all if stage1 else 0.0
            valid = stage1 and kc > kc_min
            cred = kc
        else:
            valid = stage1
            cred = 1.0 if stage1 else 0.0
        cred = cred if cred > 0.0 else 0.0  # min(1, max(0, K_c)) as Python's min/max take NaN
        cred = cred if cred < 1.0 else 1.0
        # ---- the alarm latch (AlarmLatch.update; NaN = None)
        code = 0
        if valid:
            latch_f[s, L_INVALID_SINCE] = nan
            if latch_f[s, L_VALID_SINCE] != latch_f[s, L_VALID_SINCE]:
                latch_f[s, L_VALID_SINCE] = t
            if raised[s] and t - latch_f[s, L_VALID_SINCE] >= clear_min:
                raised[s] = False
                code = 2
        else:
            latch_f[s, L_VALID_SINCE] = nan
            if latch_f[s, L_INVALID_SINCE] != latch_f[s, L_INVALID_SINCE]:
                latch_f[s, L_INVALID_SINCE] = t
            if not raised[s] and t - latch_f[s, L_INVALID_SINCE] >= raise_min:
                raised[s] = True
                latch_f[s, L_RAISED_T] = t
                code = 1
        # ---- outputs
        out_f[F_T, i] = t
        out_f[F_DM, i] = dm[0]
        out_f[F_DM1, i] = dm1_out
        out_f[F_DDM, i] = ddm0
        out_f[F_DDM1, i] = ddm1
        out_f[F_DH, i] = dh
        out_f[F_DDH, i] = ddh
        out_f[F_HEADING, i] = hd[0]
        out_f[F_CRED, i] = cred
        out_f[F_KC, i] = kc
        out_f[F_R, i] = r0
        out_f[F_R1, i] = r1
        out_f[F_R2, i] = r2
        out_f[F_R3, i] = r3
        out_f[F_RAISED_T, i] = latch_f[s, L_RAISED_T]
        out_i[I_STAGE1, i] = stage1
        out_i[I_VALID, i] = valid
        out_i[I_READY, i] = ready
        out_i[I_TRANSITION, i] = code
        last_f[s, 0] = r0
        last_f[s, 1] = r1
        last_f[s, 2] = r2
        last_f[s, 3] = r3
        last_f[s, LAST_KC] = kc
        last_f[s, LAST_CRED] = cred
        last_i[s, LI_HAS] = 1
        last_i[s, LI_VALID] = valid
        last_i[s, LI_READY] = ready
    return n


def _pair_kernel(w_slot, w_stream, w_t, w_b, w_arr, a_slot, a_t, a_b, b_slot, b_t, b_b, now, tol, max_wait,
                 max_pending, ep_slot, ep_t, ep_tb, ep_ba, ep_bb, g_slot, g_stream, g_t, g_b, g_reason, s_slot,
                 s_stream, s_t, s_b, s_arr):
    """TimeAligner's two-stream join, slot by slot, over the waiting samples (sorted by slot, then stream, then
    queue order) and a frame's two streams (each sorted by slot, each slot's rows in time order). A slot's queue
    of stream s is its waiting samples of s followed by its frame rows of s; the frame's rows are pushed in time
    order, stream a first at equal times, all arriving at ``now``. Writes the epochs, the samples given up (in
    the order TimeAligner returns them) and those still waiting (sorted as the input); returns their counts."""
    nw = w_t.shape[0]
    na = a_t.shape[0]
    nb = b_t.shape[0]
    lim = now - max_wait
    n_ep = 0
    n_g = 0
    n_s = 0
    iw = 0
    ia = 0
    ib = 0
    big = np.iinfo(np.int64).max
    while iw < nw or ia < na or ib < nb:
        u = big
        if iw < nw:
            u = w_slot[iw]
        if ia < na and a_slot[ia] < u:
            u = a_slot[ia]
        if ib < nb and b_slot[ib] < u:
            u = b_slot[ib]
        wa_lo = iw
        while iw < nw and w_slot[iw] == u and w_stream[iw] == 0:
            iw += 1
        wb_lo = iw
        while iw < nw and w_slot[iw] == u:
            iw += 1
        npa = wb_lo - wa_lo
        npb = iw - wb_lo
        fa_lo = ia
        while ia < na and a_slot[ia] == u:
            ia += 1
        fb_lo = ib
        while ib < nb and b_slot[ib] == u:
            ib += 1
        ea_end = npa + ia - fa_lo  # queue positions: [0, np) waiting, then this frame's rows
        eb_end = npb + ib - fb_lo
        ha = 0
        hb = 0
        ea = npa
        eb = npb
        while ea < ea_end or eb < eb_end:
            # ---- push the next sample (time order, stream a first at equal times); overflow drops the oldest
            if ea < ea_end and (eb >= eb_end or a_t[fa_lo + ea - npa] <= b_t[fb_lo + eb - npb]):
                ea += 1
                st = 0 if ea - ha > max_pending else -1
            else:
                eb += 1
                st = 1 if eb - hb > max_pending else -1
            reason = 2
            # ---- then join while both streams wait, give up heads passed; then expire (TimeAligner.push)
            while True:
                if st < 0:
                    if ha < ea and hb < eb:
                        t0 = w_t[wa_lo + ha] if ha < npa else a_t[fa_lo + ha - npa]
                        t1 = w_t[wb_lo + hb] if hb < npb else b_t[fb_lo + hb - npb]
                        hi = t1 if t1 > t0 else t0
                        lo = t1 if t1 < t0 else t0
                        if hi - lo <= tol:
                            ep_slot[n_ep] = u
                            ep_t[n_ep] = t0
                            ep_tb[n_ep] = t1
                            for c in range(3):
                                ep_ba[n_ep, c] = w_b[wa_lo + ha, c] if ha < npa else a_b[fa_lo + ha - npa, c]
                                ep_bb[n_ep, c] = w_b[wb_lo + hb, c] if hb < npb else b_b[fb_lo + hb - npb, c]
                            n_ep += 1
                            ha += 1
                            hb += 1
                            continue
                        reason = 0
                        st = 0 if t0 < hi - tol else 1  # the older head can never be joined
                    else:
                        reason = 1
                        if ha < ea and not ((w_arr[wa_lo + ha] if ha < npa else now) > lim):
                            st = 0
                        elif hb < eb and not ((w_arr[wb_lo + hb] if hb < npb else now) > lim):
                            st = 1
                        else:
                            break
                # give up the head of stream st for `reason`
                g_slot[n_g] = u
                g_stream[n_g] = st
                g_reason[n_g] = reason
                if st == 0:
                    g_t[n_g] = w_t[wa_lo + ha] if ha < npa else a_t[fa_lo + ha - npa]
                    for c in range(3):
                        g_b[n_g, c] = w_b[wa_lo + ha, c] if ha < npa else a_b[fa_lo + ha - npa, c]
                    ha += 1
                else:
                    g_t[n_g] = w_t[wb_lo + hb] if hb < npb else b_t[fb_lo + hb - npb]
                    for c in range(3):
                        g_b[n_g, c] = w_b[wb_lo + hb, c] if hb < npb else b_b[fb_lo + hb - npb, c]
                    hb += 1
                n_g += 1
                st = -1
        # ---- what still waits
        for q in range(ha, ea):
            s_slot[n_s] = u
            s_stream[n_s] = 0
            s_t[n_s] = w_t[wa_lo + q] if q < npa else a_t[fa_lo + q - npa]
            s_arr[n_s] = w_arr[wa_lo + q] if q < npa else now
            for c in range(3):
                s_b[n_s, c] = w_b[wa_lo + q, c] if q < npa else a_b[fa_lo + q - npa, c]
            n_s += 1
        for q in range(hb, eb):
            s_slot[n_s] = u
            s_stream[n_s] = 1
            s_t[n_s] = w_t[wb_lo + q] if q < npb else b_t[fb_lo + q - npb]
            s_arr[n_s] = w_arr[wb_lo + q] if q < npb else now
            for c in range(3):
                s_b[n_s, c] = w_b[wb_lo + q, c] if q < npb else b_b[fb_lo + q - npb, c]
            n_s += 1
    return n_ep, n_g, n_s


class _Kernels:
    step = None
    pair = None


def _kernels() -> type[_Kernels]:
    """The compiled kernels (numba is imported, and each kernel compiled or loaded from the disk cache, on
    first use: importing this module stays fast)."""
    if _Kernels.step is None:
        import numba

        _Kernels.step = numba.njit(cache=True, nogil=True)(_step_kernel)
        _Kernels.pair = numba.njit(cache=True, nogil=True)(_pair_kernel)
    return _Kernels


# ---- the fleet detector --------------------------------------------------------------------------------------------


class FleetOutput:
    """A frame's decisions, one row per epoch (the row order of the ``step`` input); columns are array views."""

    __slots__ = ("slot", "f", "i")

    def __init__(self, slot: np.ndarray, f: np.ndarray, i: np.ndarray):
        self.slot = slot  # int32[N]
        self.f = f  # float64[N_OUT_F, N]
        self.i = i  # int8[N_OUT_I, N]

    def __len__(self) -> int:
        return self.f.shape[1]

    t_s = property(lambda self: self.f[F_T])
    dm_nt = property(lambda self: self.f[F_DM:F_DM + 2].T)  # N×2
    ddm_nt_s = property(lambda self: self.f[F_DDM:F_DDM + 2].T)  # N×2
    dh_rad = property(lambda self: self.f[F_DH])
    ddh_rad_s = property(lambda self: self.f[F_DDH])
    heading_rad = property(lambda self: self.f[F_HEADING])  # compass a
    credibility = property(lambda self: self.f[F_CRED])  # K_c for fcm (0 when stage 1 fails), else 1 / 0
    kc = property(lambda self: self.f[F_KC])  # fcm: K_c as the reference's ratios["kc"]; NaN otherwise
    ratios = property(lambda self: self.f[F_R:F_R + 4].T)  # N×4: dm, ddm, dh, ddh (NaN: not tested, single)
    raised_t_s = property(lambda self: self.f[F_RAISED_T])  # the latch's raised_t_s after the epoch (NaN = None)
    stage1_pass = property(lambda self: self.i[I_STAGE1].view(bool))
    valid = property(lambda self: self.i[I_VALID].view(bool))
    ready = property(lambda self: self.i[I_READY].view(bool))
    transition = property(lambda self: self.i[I_TRANSITION])  # 0 none, 1 raised, 2 cleared


def _none(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def _as_threshold_settings(settings) -> core.ThresholdDetectorSettings:
    """A core ``ThresholdDetectorSettings`` or anything with ``thresholds()``, ``feature_settings()`` and
    ``hysteresis()`` (the service's ``Settings``)."""
    if settings is None:
        return core.ThresholdDetectorSettings()
    if isinstance(settings, core.ThresholdDetectorSettings):
        return settings
    return core.ThresholdDetectorSettings(settings.thresholds(), settings.feature_settings(), settings.hysteresis())


class FleetDetector:
    """The ``threshold`` detector (stage 1 only) for many vehicles, one slot each (docs/methods.md#dmc)."""

    impl = "threshold"
    _mode = MODE_THRESHOLD
    TESTS = core.TEST_NAMES

    def __init__(self, settings=None, capacity: int = 64):
        s = _as_threshold_settings(settings)
        self.settings = s
        self.thresholds = s.thresholds
        self._setup(s.features, s.hysteresis, s.thresholds, kc_min=math.nan, m=2.0, n_good=0, extended=False,
                    centres=np.zeros((0, 1)))
        self._alloc(max(1, int(capacity)))

    # ---- construction -----------------------------------------------------------------------------------------
    def _setup(self, fs: core.FeatureSettings, hy: core.HysteresisSettings, th: core.Thresholds, kc_min: float,
               m: float, n_good: int, extended: bool, centres: np.ndarray) -> None:
        cfg = np.zeros(N_CFG)
        cfg[C_SMOOTH], cfg[C_RATE], cfg[C_MAX_GAP] = fs.smooth_window_s, fs.rate_window_s, fs.max_gap_s
        cfg[C_HISTORY_MIN] = fs.history_s - 1e-9  # FeatureTracker's readiness rule
        cfg[C_TH_DM], cfg[C_TH_DDM], cfg[C_TH_DH], cfg[C_TH_DDH] = th.dm_nt, th.ddm_nt_s, th.dh_deg, th.ddh_deg_s
        cfg[C_RAISE_MIN] = hy.raise_after_s - 1e-9  # AlarmLatch's rule
        cfg[C_CLEAR_MIN] = hy.clear_after_s - 1e-9
        cfg[C_MODE], cfg[C_KC_MIN], cfg[C_M], cfg[C_N_GOOD] = self._mode, kc_min, m, n_good
        cfg[C_EXTENDED] = 1.0 if extended else 0.0
        self._cfg = cfg
        self._centres = np.ascontiguousarray(centres, float)
        self.feature_settings = fs
        self.default_dh_ref_rad = fs.dh_ref_rad

    def _alloc(self, cap: int) -> None:
        self.capacity = cap
        self._in_use = np.zeros(cap, bool)
        self._has_params = np.zeros(cap, bool)
        self._usable = np.zeros(cap, bool)  # in use and with parameters
        self._params = np.zeros((cap, N_PARAM))
        self._param_objs: list[tuple | None] = [None] * cap
        self._seg_start = np.full(cap, math.nan)
        self._last_t = np.full(cap, math.nan)
        self._raw = np.zeros((cap, _RAW_CAP0, 6))  # t, Δm a, Δm b, Δh, sin Δh, cos Δh
        self._raw_head = np.zeros(cap, np.int64)
        self._raw_n = np.zeros(cap, np.int64)
        self._means = np.zeros((cap, _MEANS_CAP0, 4))
        self._means_head = np.zeros(cap, np.int64)
        self._means_n = np.zeros(cap, np.int64)
        self._latch = np.full((cap, 3), math.nan)
        self._raised = np.zeros(cap, bool)
        self._last_f = np.full((cap, 6), math.nan)
        self._last_i = np.zeros((cap, 3), np.int64)

    def _grow_slots(self) -> None:
        old = {k: getattr(self, k) for k in ("_in_use", "_has_params", "_usable", "_params", "_seg_start", "_last_t", "_raw",
                                             "_raw_head", "_raw_n", "_means", "_means_head", "_means_n", "_latch",
                                             "_raised", "_last_f", "_last_i")}
        objs = self._param_objs
        n = self.capacity
        raw_cap, means_cap = self._raw.shape[1], self._means.shape[1]
        self._alloc(2 * n)
        self._raw = np.zeros((2 * n, raw_cap, 6))
        self._means = np.zeros((2 * n, means_cap, 4))
        for k, a in old.items():
            getattr(self, k)[:n] = a
        self._param_objs[:n] = objs

    @staticmethod
    def _grow_ring(ring: np.ndarray, head: np.ndarray) -> np.ndarray:
        """Twice the room, each slot's entries moved to the front in order (heads become 0)."""
        s, c, w = ring.shape
        idx = (head[:, None] + np.arange(c)[None, :]) % c
        new = np.zeros((s, 2 * c, w))
        new[:, :c] = ring[np.arange(s)[:, None], idx]
        head[:] = 0
        return new

    # ---- slots --------------------------------------------------------------------------------------------------
    def add(self) -> int:
        """A free slot for a vehicle (reset, no parameters yet)."""
        free = np.flatnonzero(~self._in_use)
        if free.size == 0:
            self._grow_slots()
            free = np.flatnonzero(~self._in_use)
        s = int(free[0])
        self._in_use[s] = True
        self.reset(s)
        self._has_params[s] = self._usable[s] = False
        self._param_objs[s] = None
        return s

    def free(self, slot: int) -> None:
        self._check_slot(slot)
        self.reset(slot)
        self._in_use[slot] = False
        self._has_params[slot] = self._usable[slot] = False
        self._param_objs[slot] = None

    def reset(self, slot: int) -> None:
        """Windows, alarm latch and last decision back to the start (ThresholdDetector.reset)."""
        self.restart_features(slot)
        self._latch[slot] = math.nan
        self._raised[slot] = False
        self._last_f[slot] = math.nan
        self._last_i[slot] = 0

    def restart_features(self, slot: int) -> None:
        """Parameters changed: the feature windows restart, the alarm keeps its state."""
        self._raw_n[slot] = self._raw_head[slot] = 0
        self._means_n[slot] = self._means_head[slot] = 0
        self._seg_start[slot] = self._last_t[slot] = math.nan

    def set_params(self, slot: int, p_a: MagParams, p_b: MagParams | None,
                   declination_rad: float = 0.0, dh_ref_rad: float | None = None) -> None:
        """Static compensation of the slot's two compasses (``single``: ``p_b`` is not used), its declination and
        Δh_r (None: the settings' ``dh_ref_rad``). The windows are not restarted: call :meth:`restart_features`
        as the service does on new parameters."""
        self._check_slot(slot)
        if p_b is None and self._mode != MODE_SINGLE:
            raise ValueError(f"{self.impl}: set_params needs both compasses' parameters")
        dh_ref = self.default_dh_ref_rad if dh_ref_rad is None else float(dh_ref_rad)
        row = self._params[slot]
        for p, base in ((p_a, P_A), (p_b if p_b is not None else p_a, P_B)):
            row[base + P_OFF:base + P_OFF + 3] = p.offset_nt
            row[base + P_MAT:base + P_MAT + 9] = p.matrix
            row[base + P_R] = p.field_radius_nt
            row[base + P_2D] = 1.0 if p.model == "2d" else 0.0
        row[P_DECL] = float(declination_rad)
        row[P_DHREF] = dh_ref
        self._has_params[slot] = self._usable[slot] = True
        self._param_objs[slot] = (p_a, p_b, float(declination_rad), dh_ref)

    def params(self, slot: int) -> tuple | None:
        """(p_a, p_b, declination_rad, dh_ref_rad) as last set, or None."""
        return self._param_objs[slot]

    def _check_slot(self, slot: int) -> None:
        if not (0 <= slot < self.capacity and self._in_use[slot]):
            raise ValueError(f"slot {slot} is not in use")

    @property
    def slots(self) -> np.ndarray:
        return np.flatnonzero(self._in_use)

    # ---- alarm latch ----------------------------------------------------------------------------------------------
    @property
    def raised(self) -> np.ndarray:
        """Per slot: the latch holds the alarm raised (a copy)."""
        return self._raised.copy()

    @property
    def raised_t_s(self) -> np.ndarray:
        """Per slot: when the alarm was last raised (NaN = None; kept after a clear, as AlarmLatch does)."""
        return self._latch[:, L_RAISED_T].copy()

    def adopt(self, slot: int, raised: bool, raised_t_s: float | None = None) -> None:
        """Take over an alarm state decided elsewhere (AlarmLatch.adopt): the run timers are kept."""
        self._check_slot(slot)
        self._raised[slot] = bool(raised)
        self._latch[slot, L_RAISED_T] = (math.nan if raised_t_s is None else float(raised_t_s)) if raised else math.nan

    def latch_state(self, slot: int) -> dict:
        """As AlarmLatch.state(): raised, raised_t_s, invalid_since, valid_since (None where unset)."""
        lf = self._latch[slot]
        return {"raised": bool(self._raised[slot]), "raised_t_s": _none(lf[L_RAISED_T]),
                "invalid_since": _none(lf[L_INVALID_SINCE]), "valid_since": _none(lf[L_VALID_SINCE])}

    def restore_latch(self, slot: int, state: dict) -> None:
        """Put back a :meth:`latch_state` (a restart or a live hand-over carries it)."""
        self._check_slot(slot)
        self._raised[slot] = bool(state["raised"])
        for col, key in ((L_RAISED_T, "raised_t_s"), (L_INVALID_SINCE, "invalid_since"),
                         (L_VALID_SINCE, "valid_since")):
            v = state.get(key)
            self._latch[slot, col] = math.nan if v is None else float(v)

    def flags(self, slot: int) -> dict:
        """As the reference's ``flags``: alarm_raised, valid (the last epoch), warming (rates not ready yet)."""
        has, valid, ready = (bool(x) for x in self._last_i[slot])
        return {"alarm_raised": bool(self._raised[slot]), "valid": has and valid, "warming": not has or not ready}

    def internal_states(self, slot: int) -> dict:
        """As the reference's ``internal_states``: the last epoch's ratios and credibility ({} before one)."""
        if not self._last_i[slot, LI_HAS]:
            return {}
        lf = self._last_f[slot]
        return {"ratios": self._ratios_dict(lf[:4], lf[LAST_KC]), "credibility": float(lf[LAST_CRED])}

    # ---- the frame step ------------------------------------------------------------------------------------------
    def step(self, slot, t_s, b_a_nt, b_b_nt=None) -> FleetOutput:
        """Decide every epoch of a frame: ``slot`` int[N], ``t_s`` [N], ``b_a_nt``/``b_b_nt`` [N, 3] (raw
        compass readings; ``single`` reads ``b_a_nt`` only). Rows of one slot are applied in the order given."""
        slot = np.ascontiguousarray(slot, np.int32)
        t = np.ascontiguousarray(t_s, float)
        n = t.shape[0]
        b_a = np.ascontiguousarray(b_a_nt, float).reshape(n, 3)
        if b_b_nt is None and self._mode != MODE_SINGLE:
            raise ValueError(f"{self.impl}: step needs both compasses' readings")
        b_b = b_a if b_b_nt is None else np.ascontiguousarray(b_b_nt, float).reshape(n, 3)
        if slot.shape != (n,):
            raise ValueError(f"slot needs one entry per epoch ({n}), got shape {slot.shape}")
        out_f = np.empty((N_OUT_F, n))
        out_i = np.zeros((N_OUT_I, n), np.int8)
        if n == 0:
            return FleetOutput(slot, out_f, out_i)
        k = _kernels().step
        i = 0
        while True:
            i = k(slot, t, b_a, b_b, i, self._cfg, self._centres, self._usable, self._params, self._seg_start,
                  self._last_t, self._raw, self._raw_head, self._raw_n, self._means, self._means_head,
                  self._means_n, self._latch, self._raised, self._last_f, self._last_i, out_f, out_i)
            if i >= n:
                break
            if i < 0:
                s = int(slot[-1 - i])
                why = ("has no compensation parameters (set_params first)" if 0 <= s < self.capacity
                       and self._in_use[s] else "is not in use")
                raise ValueError(f"step: row {-1 - i} names slot {s}, which {why}")
            s = slot[i]  # this slot's windows hold more epochs than the rings fit: double them and go on
            if self._raw_n[s] >= self._raw.shape[1]:
                self._raw = self._grow_ring(self._raw, self._raw_head)
            if self._means_n[s] >= self._means.shape[1]:
                self._means = self._grow_ring(self._means, self._means_head)
        return FleetOutput(slot, out_f, out_i)

    # ---- the reference's view of a row -----------------------------------------------------------------------------
    def _ratios_dict(self, r, kc: float) -> dict:
        return {name: float(r[j]) for j, name in enumerate(self.TESTS)}

    def _failed(self, ratios: dict, stage1: bool, valid: bool) -> tuple[str, ...]:
        return tuple(sorted((k for k, v in ratios.items() if v >= 1.0), key=lambda k: -ratios[k]))

    def decision(self, out: FleetOutput, i: int) -> core.Decision:
        """Row ``i`` as the reference's :class:`~core.Decision` (ratios, failing tests worst first, transition)."""
        f = out.f[:, i]
        stage1, valid, ready, code = (int(x) for x in out.i[:, i])
        ratios = self._ratios_dict(f[F_R:F_R + 4], f[F_KC])
        return core.Decision(
            t_s=float(f[F_T]), dm_nt=[float(f[F_DM]), float(f[F_DM1])], ddm_nt_s=[float(f[F_DDM]), float(f[F_DDM1])],
            dh_rad=float(f[F_DH]), ddh_rad_s=float(f[F_DDH]), heading_rad=float(f[F_HEADING]),
            stage1_pass=bool(stage1), credibility=float(f[F_CRED]), valid=bool(valid), ready=bool(ready),
            ratios=ratios, failed=self._failed(ratios, bool(stage1), bool(valid)), transition=TRANSITIONS[code])

    def describe(self, out: FleetOutput, i: int) -> tuple[str, float | None, float | None, str]:
        """(reason, value, threshold, unit) for row ``i`` — the reference's ``describe`` of that decision."""
        d = self.decision(out, i)
        th = self.thresholds
        if d.transition == "cleared" or not d.failed:
            return core.reason_sentence((), {}, {}), None, None, ""
        units = {k: core.test_value_and_threshold(k, d.ratios[k], th)[:2] for k in d.failed}
        value, thr, unit = core.test_value_and_threshold(d.failed[0], d.ratios[d.failed[0]], th)
        return core.reason_sentence(d.failed, d.ratios, units), value, thr, unit


class FleetSingleDetector(FleetDetector):
    """The ``single`` baseline for many vehicles: compass a only, |Δm| and |dΔm| (core.SingleCompassDetector)."""

    impl = "single"
    _mode = MODE_SINGLE
    TESTS = ("dm", "ddm")

    def _ratios_dict(self, r, kc: float) -> dict:
        return {"dm": float(r[0]), "ddm": float(r[1])}


class FleetFcmDetector(FleetDetector):
    """The ``fcm`` detector for many vehicles: loose stage 1, then K_c from the trained centres (fcm.FcmDetector)."""

    impl = "fcm"
    _mode = MODE_FCM

    def __init__(self, model: fcm_mod.FcmModel, settings: fcm_mod.FcmDetectorSettings | None = None,
                 capacity: int = 64):
        s = settings or fcm_mod.FcmDetectorSettings()
        self.model = model
        self.kc_min = float(s.kc_min if s.kc_min is not None else model.kc_min)
        ms = model.feature_settings
        fs = core.FeatureSettings(ms.smooth_window_s, ms.rate_window_s, s.dh_ref_rad, ms.max_gap_s)
        self.settings = core.ThresholdDetectorSettings(model.loose, fs, s.hysteresis)
        self.thresholds = model.loose
        self._setup(fs, s.hysteresis, model.loose, kc_min=self.kc_min, m=float(model.m),
                    n_good=int(model.n_good_clusters), extended=model.feature_set == "extended",
                    centres=model.centres)
        self._alloc(max(1, int(capacity)))

    def _ratios_dict(self, r, kc: float) -> dict:
        out = {name: float(r[j]) for j, name in enumerate(core.TEST_NAMES)}
        out["kc"] = float(kc)
        return out

    def _failed(self, ratios: dict, stage1: bool, valid: bool) -> tuple[str, ...]:
        if stage1 and not valid:
            return ("kc",)
        r = {k: v for k, v in ratios.items() if k != "kc"}
        return tuple(sorted((k for k, v in r.items() if v >= 1.0), key=lambda k: -r[k]))

    def describe(self, out: FleetOutput, i: int) -> tuple[str, float | None, float | None, str]:
        d = self.decision(out, i)
        if d.transition == "raised" and d.failed == ("kc",):
            return (f"Magnetic interference suspected: credibility K_c {d.credibility:.2f} is not above "
                    f"{self.kc_min:.2f} (fuzzy c-means on the DMC features).", d.credibility, self.kc_min, "")
        return super().describe(out, i)


# ---- pairing the two compasses of every vehicle in a frame ----------------------------------------------------------


@dataclass
class Samples:
    """Compass samples, one row each: ``stream`` 0 = compass a, 1 = compass b. Waiting samples are kept sorted by
    slot, then stream, then queue order; ``arrived`` is the wall-clock time they came in (for ``max_wait_s``)."""

    slot: np.ndarray  # int32[N]
    stream: np.ndarray  # int8[N]
    t_s: np.ndarray  # float64[N]
    b_nt: np.ndarray  # float64[N, 3]
    arrived: np.ndarray  # float64[N]

    @classmethod
    def empty(cls) -> Samples:
        return cls(np.zeros(0, np.int32), np.zeros(0, np.int8), np.zeros(0), np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        return self.t_s.shape[0]

    def take(self, idx) -> Samples:
        return Samples(self.slot[idx], self.stream[idx], self.t_s[idx], self.b_nt[idx], self.arrived[idx])


@dataclass
class Epochs:
    """Paired epochs, sorted by slot then time: ``t_s`` is compass a's sample time (TimeAligner's reference)."""

    slot: np.ndarray  # int32[N]
    t_s: np.ndarray
    t_b_s: np.ndarray  # compass b's sample time
    b_a_nt: np.ndarray  # N×3
    b_b_nt: np.ndarray  # N×3

    def __len__(self) -> int:
        return self.t_s.shape[0]


@dataclass
class GivenUp:
    """Samples given up, in the order TimeAligner returns them per slot: ``reason`` indexes
    :data:`magmesh.align.REASONS` (0 passed, 1 expired, 2 overflow)."""

    slot: np.ndarray
    stream: np.ndarray  # int8: 0 = compass a, 1 = compass b
    t_s: np.ndarray
    b_nt: np.ndarray
    reason: np.ndarray  # int8

    def __len__(self) -> int:
        return self.t_s.shape[0]


def _by_slot(slot: np.ndarray) -> np.ndarray | None:
    """The stable order sorting rows by slot (None when they already are)."""
    if slot.size < 2 or bool(np.all(slot[1:] >= slot[:-1])):
        return None
    return np.argsort(slot, kind="stable")


def pair_frame(waiting: Samples, slot_a, t_a, b_a_nt, slot_b, t_b, b_b_nt, now: float, tolerance_s: float = 0.005,
               max_wait_s: float = 10.0, max_pending: int = 8192) -> tuple[Epochs, Samples, GivenUp]:
    """Join a frame's two compass streams with the samples still waiting from earlier frames.

    Per slot the rule is :class:`~magmesh.align.TimeAligner`'s (``tolerance_s``, ``max_wait_s`` of wall-clock
    time, ``max_pending`` per stream), its samples pushed in time order (compass a first at equal times), all
    arriving at ``now``. Each stream's rows of one slot must be in time order (ingest guarantees it); rows of
    several slots may come in any slot order. Returns (epochs, still waiting, given up).
    """
    if not tolerance_s >= 0:
        raise ValueError(f"tolerance_s must be ≥ 0, got {tolerance_s}")
    if not max_wait_s > 0:
        raise ValueError(f"max_wait_s must be > 0 (wall-clock seconds), got {max_wait_s}")
    frame = []
    for sl, t, b in ((slot_a, t_a, b_a_nt), (slot_b, t_b, b_b_nt)):
        sl = np.ascontiguousarray(sl, np.int32)
        t = np.ascontiguousarray(t, float)
        b = np.ascontiguousarray(b, float).reshape(t.shape[0], 3)
        if sl.shape != t.shape:
            raise ValueError("pair_frame: a stream needs one slot per sample")
        o = _by_slot(sl)
        if o is not None:
            sl, t, b = sl[o], t[o], b[o]
        frame.append((sl, t, b))
    (fa_slot, fa_t, fa_b), (fb_slot, fb_t, fb_b) = frame
    w = waiting
    key = w.slot.astype(np.int64) * 2 + w.stream
    if key.size > 1 and not bool(np.all(key[1:] >= key[:-1])):  # sorted by slot then stream, queues kept
        w = w.take(np.argsort(key, kind="stable"))
    w_slot = np.ascontiguousarray(w.slot, np.int32)
    w_stream = np.ascontiguousarray(w.stream, np.int8)
    w_t = np.ascontiguousarray(w.t_s, float)
    w_b = np.ascontiguousarray(w.b_nt, float).reshape(w_t.shape[0], 3)
    w_arr = np.ascontiguousarray(w.arrived, float)
    n_all = w_t.shape[0] + fa_t.shape[0] + fb_t.shape[0]
    n_ep_max = min(int(np.count_nonzero(w_stream == 0)) + fa_t.shape[0],
                   int(np.count_nonzero(w_stream == 1)) + fb_t.shape[0])
    ep = Epochs(np.empty(n_ep_max, np.int32), np.empty(n_ep_max), np.empty(n_ep_max), np.empty((n_ep_max, 3)),
                np.empty((n_ep_max, 3)))
    g = GivenUp(np.empty(n_all, np.int32), np.empty(n_all, np.int8), np.empty(n_all), np.empty((n_all, 3)),
                np.empty(n_all, np.int8))
    still = Samples(np.empty(n_all, np.int32), np.empty(n_all, np.int8), np.empty(n_all), np.empty((n_all, 3)),
                    np.empty(n_all))
    n_ep, n_g, n_s = _kernels().pair(w_slot, w_stream, w_t, w_b, w_arr, fa_slot, fa_t, fa_b, fb_slot, fb_t, fb_b,
                                     float(now), float(tolerance_s), float(max_wait_s), int(max_pending),
                                     ep.slot, ep.t_s, ep.t_b_s, ep.b_a_nt, ep.b_b_nt, g.slot, g.stream, g.t_s,
                                     g.b_nt, g.reason, still.slot, still.stream, still.t_s, still.b_nt, still.arrived)
    ep = Epochs(ep.slot[:n_ep], ep.t_s[:n_ep], ep.t_b_s[:n_ep], ep.b_a_nt[:n_ep], ep.b_b_nt[:n_ep])
    g = GivenUp(g.slot[:n_g], g.stream[:n_g], g.t_s[:n_g], g.b_nt[:n_g], g.reason[:n_g])
    return ep, still.take(slice(0, n_s)), g


def expire_waiting(waiting: Samples, now: float, max_wait_s: float = 10.0) -> tuple[Samples, GivenUp]:
    """Give up waiting samples that waited ``max_wait_s`` of wall-clock time (TimeAligner.expire on every slot,
    e.g. from a tick): returns (still waiting, given up as ``expired``, in slot then stream order)."""
    lim = float(now) - float(max_wait_s)
    w = waiting.take(np.lexsort((waiting.stream, waiting.slot)))  # slot, then stream, queue order kept
    n = len(w)
    if n == 0:
        return w, GivenUp(w.slot, w.stream, w.t_s, w.b_nt, np.zeros(0, np.int8))
    # a queue gives up from its head while the head waited long enough: the run of old samples at its front
    start = np.ones(n, bool)
    start[1:] = (w.slot[1:] != w.slot[:-1]) | (w.stream[1:] != w.stream[:-1])
    young = np.cumsum(~(w.arrived <= lim))
    first = np.maximum.accumulate(np.where(start, np.arange(n), 0))
    before = np.where(first > 0, young[first - 1], 0)
    old = young - before == 0
    g = w.take(old)
    return w.take(~old), GivenUp(g.slot, g.stream, g.t_s, g.b_nt, np.ones(len(g), np.int8))


class FleetPairer:
    """Keeps the waiting samples of every slot between frames and counts as TimeAligner does, per slot."""

    def __init__(self, streams: tuple = ("1", "2"), tolerance_s: float = 0.005, max_wait_s: float = 10.0,
                 max_pending: int = 8192, clock=time.monotonic):
        if len(streams) != 2 or streams[0] == streams[1]:
            raise ValueError(f"need two different streams, got {streams!r}")
        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be ≥ 0, got {tolerance_s}")
        if not max_wait_s > 0:
            raise ValueError(f"max_wait_s must be > 0 (wall-clock seconds), got {max_wait_s}")
        self.streams = tuple(streams)
        self.tolerance_s = float(tolerance_s)
        self.max_wait_s = float(max_wait_s)
        self.max_pending = int(max_pending)
        self.clock = clock
        self.waiting = Samples.empty()
        self._joined = np.zeros(0, np.int64)
        self._gave_up = np.zeros((0, len(REASONS), 2), np.int64)

    def _ensure(self, n: int) -> None:
        if n > self._joined.shape[0]:
            m = max(n, 2 * self._joined.shape[0], 64)
            j = np.zeros(m, np.int64)
            g = np.zeros((m, len(REASONS), 2), np.int64)
            j[:self._joined.shape[0]] = self._joined
            g[:self._gave_up.shape[0]] = self._gave_up
            self._joined, self._gave_up = j, g

    def _count(self, joined_slot: np.ndarray, given_up: GivenUp) -> None:
        top = max([-1] + [int(x.max()) for x in (joined_slot, given_up.slot) if len(x)])
        self._ensure(top + 1)
        np.add.at(self._joined, joined_slot, 1)
        np.add.at(self._gave_up, (given_up.slot, given_up.reason, given_up.stream), 1)

    def pair(self, slot_a, t_a, b_a_nt, slot_b, t_b, b_b_nt, now: float | None = None) -> tuple[Epochs, GivenUp]:
        """A frame's two compass streams in; the epochs they complete and the samples given up out."""
        now = self.clock() if now is None else float(now)
        epochs, self.waiting, given_up = pair_frame(self.waiting, slot_a, t_a, b_a_nt, slot_b, t_b, b_b_nt, now,
                                                    self.tolerance_s, self.max_wait_s, self.max_pending)
        self._count(epochs.slot, given_up)
        return epochs, given_up

    def expire(self, now: float | None = None) -> GivenUp:
        now = self.clock() if now is None else float(now)
        self.waiting, given_up = expire_waiting(self.waiting, now, self.max_wait_s)
        self._count(np.zeros(0, np.int32), given_up)
        return given_up

    def reset(self, slot: int) -> None:
        """Drop the slot's waiting samples (TimeAligner.reset: its counts stay)."""
        self.waiting = self.waiting.take(self.waiting.slot != slot)

    def free(self, slot: int) -> None:
        """The slot's vehicle is gone: waiting samples and counts dropped (a new vehicle may take the slot)."""
        self.reset(slot)
        if slot < self._joined.shape[0]:
            self._joined[slot] = 0
            self._gave_up[slot] = 0

    def waiting_count(self, slot: int) -> int:
        return int(np.count_nonzero(self.waiting.slot == slot))

    def counts(self, slot: int) -> dict:
        """As TimeAligner.counts(): ``{"joined": n, "gave_up": {reason: {stream: n}}, "gave_up_total": n}``."""
        self._ensure(slot + 1)
        g = self._gave_up[slot]
        gave = {r: {str(self.streams[k]): int(g[j, k]) for k in range(2) if g[j, k]} for j, r in enumerate(REASONS)}
        return {"joined": int(self._joined[slot]), "gave_up": {r: d for r, d in gave.items() if d},
                "gave_up_total": int(g.sum())}


# ---- warm-up -------------------------------------------------------------------------------------------------------


def warm() -> dict:
    """Compile (or load from the disk cache) every kernel on a tiny input; seconds per kernel."""
    out = {}
    t0 = time.perf_counter()
    k = _kernels()
    out["import_numba_s"] = time.perf_counter() - t0
    p = MagParams((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 5e4)
    det = FleetDetector(capacity=1)
    s = det.add()
    det.set_params(s, p, p)
    t0 = time.perf_counter()
    det.step(np.array([s]), np.array([0.0]), np.array([[5e4, 0.0, 0.0]]), np.array([[5e4, 0.0, 0.0]]))
    out["step_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pair_frame(Samples.empty(), [0], [0.0], [[1.0, 0.0, 0.0]], [0], [0.0], [[1.0, 0.0, 0.0]], now=0.0)
    out["pair_s"] = time.perf_counter() - t0
    out["signatures"] = {"step": len(k.step.signatures), "pair": len(k.pair.signatures)}
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(description="DMC fleet kernels: compile and cache them on disk (--warm)")
    ap.add_argument("--warm", action="store_true", help="compile (or load) every kernel and print the seconds taken")
    a = ap.parse_args(argv)
    if not a.warm:
        ap.print_help()
        return 2
    t0 = time.perf_counter()
    res = warm()
    res["total_s"] = time.perf_counter() - t0
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in res.items()}))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
