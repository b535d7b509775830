"""Correlation geomagnetic matching: Hausdorff scoring, one-cell pre-match with SSDA, bilinear fine match, M-of-N.

Pure numpy; never imports zenoh. Method: Liu, Zhou, Yang, Li, *Geomagnetic matching location using
correlative method* (docs/methods.md#geomag). Notation follows the paper:

- measured sequence H_N = [h_1 … h_N] (anomaly, nT) with the INS positions S_N; increments
  Δx_i, Δy_i give, for a candidate start S_0 = (I_0, J_0), the reference positions
  I_i = I_{i−1} + Δx_i, J_i = J_{i−1} + Δy_i (§2.2) and the reference strip H'_N sampled there;
- score: Hausdorff distance d_H(A, B) = max(d_h(A, B), d_h(B, A)), d_h(A, B) = max_a min_b |a − b| (§2.3);
- pre-match (§3.1): candidate starts one grid cell apart, a point inside a cell takes the mean of
  the cell's four corners, a cell is scored at its centre ("centre") or by the mean of its four
  corners' distances ("corners"); cells with score < λ form the feasible set U;
- SSDA (§3.1, Barnea–Silverman): every term min_b |a − b| is a lower bound of d_H, so a candidate
  is abandoned as soon as one term exceeds λ;
- fine match (§3.2): the cells of U are densified by k = 2–4 subdivisions and the strip is
  resampled with bilinear interpolation; the global minimum is the match;
- acceptance (§5): M/N rule — accept a fix only if at least M of the last N fixes agree.

Beyond the paper (each a setting, the paper's choice available):

- ``window_samples``: the unordered set Hausdorff of the paper ignores the order of the samples,
  so a long strip can be "covered" by any strip with a similar range of values (it gets *worse* as
  N grows). Treating the samples as points (i, h_i) and matching each only to samples at most
  ``window_samples`` away along the strip restores the order; 0 compares h_i with h'_i (the
  Hausdorff distance of the two graphs under the Chebyshev norm with a large index scale).
  ``None`` is the paper's unordered set.
- ``rank_frac``: partial Hausdorff (Huttenlocher): the K-th ranked term, K = ⌈rank_frac·N⌉,
  instead of the maximum, to survive a few outliers. SSDA stays exact: a candidate is abandoned
  once more than N − K terms exceed λ.
- λ grows (× ``lambda_growth``) when fewer than ``min_feasible_cells`` cells survive, so a noisier
  sequence than expected widens the feasible set instead of losing the fix.
- SSDA visits the samples most different from the map mean first (they abandon most candidates
  early); the result does not depend on the order.
- a runner-up margin (best distance among candidates farther than ``runner_up_exclusion_m``)
  flags ambiguous matches, which are never reported as fixes.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from magmesh.geomap import GridMap

PREMATCH_SCORES = ("centre", "corners")


# ---- settings ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class MatchSettings:
    """How one sequence is matched against the map."""

    n_samples: int = 20  # match length N, samples
    window_samples: int | None = 0  # pairing window along the strip; None: the paper's unordered set
    rank_frac: float = 1.0  # partial Hausdorff rank (1.0: classic max)
    lambda_nt: float = 8.4  # SSDA / feasibility threshold λ, nT (paper: 0.5 σ of its map)
    lambda_growth: float = 2.0  # λ multiplier when too few cells are feasible
    max_lambda_nt: float = 500.0  # give up (no match) beyond this λ, nT
    min_feasible_cells: int = 4  # widen λ until at least this many cells are feasible
    prematch_score: str = "centre"  # "centre" or "corners" (paper §3.1 a / b)
    subdivisions: int = 3  # fine-match subdivisions per cell (paper: 2–4)
    search_radius_m: float = 3000.0  # half-width of the square search area around the INS start; 0: whole map
    runner_up_exclusion_m: float = 200.0  # runner-up must start farther than this from the best, m
    demean: bool = False  # match sequences with their means removed (unknown constant bias)
    heading_search_deg: float = 0.0  # also try the INS track rotated by up to ± this (INS heading error); 0: off
    heading_step_deg: float = 1.0  # rotation step of that search

    def __post_init__(self):
        if self.n_samples < 2:
            raise ValueError(f"n_samples must be ≥ 2, got {self.n_samples}")
        if self.window_samples is not None and self.window_samples < 0:
            raise ValueError(f"window_samples must be ≥ 0 or None, got {self.window_samples}")
        if not 0 < self.rank_frac <= 1:
            raise ValueError(f"rank_frac must be in (0, 1], got {self.rank_frac}")
        if not self.lambda_nt > 0 or not self.lambda_growth > 1:
            raise ValueError("lambda_nt must be > 0 and lambda_growth > 1")
        if self.prematch_score not in PREMATCH_SCORES:
            raise ValueError(f"prematch_score must be one of {PREMATCH_SCORES}, got {self.prematch_score!r}")
        if not 1 <= self.subdivisions <= 16:
            raise ValueError(f"subdivisions must be in 1..16 (paper: 2–4), got {self.subdivisions}")
        if self.search_radius_m < 0:
            raise ValueError(f"search_radius_m must be ≥ 0, got {self.search_radius_m}")
        if not (0 <= self.heading_search_deg <= 45 and self.heading_step_deg > 0):
            raise ValueError("heading_search_deg must be in 0..45 and heading_step_deg > 0")


# ---- Hausdorff scoring ------------------------------------------------------------------------


def _kth(terms: np.ndarray, rank_frac: float) -> np.ndarray:
    """K-th smallest of the last axis, K = ⌈rank_frac·n⌉ (rank_frac = 1: the maximum)."""
    n = terms.shape[-1]
    k = max(1, math.ceil(rank_frac * n - 1e-9))
    if k == n:
        return terms.max(axis=-1)
    return np.partition(terms, k - 1, axis=-1)[..., k - 1]


def directed_terms(a: np.ndarray, b: np.ndarray, window: int | None) -> np.ndarray:
    """min_{b_j} |a_i − b_j| for every a_i (…×N), b_j restricted to |i − j| ≤ window (None: all j)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if window == 0:
        return np.abs(a - b)
    d = np.abs(a[..., :, None] - b[..., None, :])
    if window is not None:
        n = a.shape[-1]
        idx = np.arange(n)
        d = np.where(np.abs(idx[:, None] - idx[None, :]) <= window, d, np.inf)
    return d.min(axis=-1)


def hausdorff(h: np.ndarray, r: np.ndarray, window: int | None = None, rank_frac: float = 1.0) -> np.ndarray:
    """d_H(H, H') = max(d_h(H, H'), d_h(H', H)) for a measured sequence h (N) and strips r (…×N).

    With ``window=None`` and ``rank_frac=1`` this is the paper's scalar Hausdorff distance
    (scipy.spatial.distance.directed_hausdorff of the values as 1-D points, both ways).
    """
    h = np.broadcast_to(np.asarray(h, float), np.shape(r))
    fwd = _kth(directed_terms(h, r, window), rank_frac)
    if window == 0:
        return fwd  # symmetric already
    back = _kth(directed_terms(r, h, window), rank_frac)
    return np.maximum(fwd, back)


# ---- candidates -------------------------------------------------------------------------------


@dataclass
class MatchResult:
    """Outcome of one sequence match (positions in grid units and map-frame metres)."""

    found: bool
    start_ij: np.ndarray  # matched start S_0, grid units
    end_ij: np.ndarray  # matched position of the last sample, grid units
    end_m: np.ndarray  # same, map-frame metres
    hausdorff_nt: float
    runner_up_nt: float | None  # best distance farther than the exclusion radius (None: none scored)
    margin_nt: float | None  # runner_up − best; if no runner-up was scored: λ − best (a lower bound)
    lambda_nt: float  # λ finally used
    search_area_m2: float
    n_prematch: int = 0  # candidate cells of the pre-match
    n_abandoned: int = 0  # pre-match candidates abandoned early by SSDA
    n_feasible: int = 0  # cells in U
    n_fine: int = 0  # fine candidates scored
    term_evaluations: int = 0  # Hausdorff terms computed (a cost figure)
    reason: str = ""
    rotation_deg: float = 0.0  # rotation of the INS track (clockwise) that matched best


def _search_box(m: GridMap, centre_ij: np.ndarray, radius_m: float, extent_ij: np.ndarray) -> tuple:
    """Integer node range [lo, hi] per axis of candidate starts whose whole strip stays on the map."""
    nx, ny = m.shape
    lo_off = np.minimum(extent_ij.min(axis=0), 0.0)
    hi_off = np.maximum(extent_ij.max(axis=0), 0.0)
    lo = np.array([math.ceil(-lo_off[0]), math.ceil(-lo_off[1])])
    hi = np.array([math.floor(nx - 1 - hi_off[0]), math.floor(ny - 1 - hi_off[1])])
    if radius_m > 0:
        r = np.array([radius_m / m.dx_m, radius_m / m.dy_m])
        lo = np.maximum(lo, np.ceil(centre_ij - r).astype(int))
        hi = np.minimum(hi, np.floor(centre_ij + r).astype(int))
    return lo.astype(int), hi.astype(int)


def _prepare(h_nt, settings: MatchSettings):
    h = np.asarray(h_nt, float)
    if settings.demean:
        h = h - h.mean()
    return h


def _strip(m: GridMap, starts: np.ndarray, offsets: np.ndarray, cols, coarse: bool) -> np.ndarray:
    """Reference strips H'_N: the map at start + INS offsets (cell means for the pre-match, else bilinear)."""
    gi = starts[:, 0:1] + offsets[None, cols, 0]
    gj = starts[:, 1:2] + offsets[None, cols, 1]
    r = m.cell_mean(gi, gj) if coarse else m.bilinear(gi, gj)
    return r


def _ssda_scores(
    m: GridMap, h: np.ndarray, starts: np.ndarray, offsets: np.ndarray, lam: float, s: MatchSettings, coarse: bool
) -> tuple[np.ndarray, int]:
    """Scores of candidate starts with SSDA early abandon at λ: inf where abandoned.

    The measured samples are visited most-informative first; for each, the lower-bound term of
    every live candidate is computed from only the strip columns it needs; a candidate whose
    count of terms > λ exceeds N − K is abandoned (K = ⌈rank_frac·N⌉; K = N: any term > λ).
    Survivors get their full (symmetric) Hausdorff distance.
    """
    n = h.size
    k = max(1, math.ceil(s.rank_frac * n - 1e-9))
    allowed = n - k
    c = starts.shape[0]
    live = np.arange(c)
    over = np.zeros(c, dtype=np.int32)
    evals = 0
    w = s.window_samples
    ref = m.values_nt.mean()
    order = np.argsort(-np.abs(h - (h.mean() if s.demean else ref)), kind="stable")
    if s.demean:
        # demeaned strips need every column first: no column-wise abandon, score all
        r = _strip(m, starts, offsets, slice(None), coarse)
        r = r - r.mean(axis=1, keepdims=True)
        return hausdorff(h, r, w, s.rank_frac), c * n
    for i in order:
        if live.size == 0:
            break
        if w is None:
            cols = np.arange(n)
        else:
            cols = np.arange(max(0, i - w), min(n, i + w + 1))
        r = _strip(m, starts[live], offsets, cols, coarse)
        term = np.abs(h[i] - r).min(axis=1)
        evals += live.size * cols.size
        over[live] += term > lam
        live = live[over[live] <= allowed]
    scores = np.full(c, np.inf)
    if live.size:
        r = _strip(m, starts[live], offsets, slice(None), coarse)
        scores[live] = hausdorff(h, r, w, s.rank_frac)
        evals += live.size * n * (1 if w == 0 else 2)
    return scores, evals


def _offsets_ij(m: GridMap, ins_m: np.ndarray) -> np.ndarray:
    p = np.asarray(ins_m, float)[:, :2]
    return np.stack([(p[:, 0] - p[0, 0]) / m.dx_m, (p[:, 1] - p[0, 1]) / m.dy_m], axis=-1)


def _finish(
    m: GridMap, starts: np.ndarray, scores: np.ndarray, offsets: np.ndarray, lam: float, s: MatchSettings,
    area: float,
) -> MatchResult:
    b = int(np.argmin(scores))
    best = float(scores[b])
    start = starts[b]
    d_m = np.hypot((starts[:, 0] - start[0]) * m.dx_m, (starts[:, 1] - start[1]) * m.dy_m)
    far = (d_m > s.runner_up_exclusion_m) & np.isfinite(scores)
    runner = float(scores[far].min()) if np.any(far) else None
    margin = (runner - best) if runner is not None else max(lam - best, 0.0)
    end = start + offsets[-1]
    return MatchResult(True, start.copy(), end, m.to_metres(end), best, runner, margin, lam, area)


def match_sequence(m: GridMap, h_nt, ins_m, settings: MatchSettings, centre_m=None) -> MatchResult:
    """Match a measured sequence with the paper's pipeline: pre-match + SSDA, then bilinear fine match.

    ``h_nt``: N anomaly values; ``ins_m``: N×2 (or N×3) INS positions in the map frame, m (their
    increments build the strip; the first one centres the search area unless ``centre_m`` is given).

    With ``heading_search_deg`` > 0 the INS track is also rotated about its first point by every
    step in ± that range (an INS heading error rotates the dead-reckoned increments — the paper's
    stated weakness, §5) and the rotation with the smallest distance wins. The runner-up is then
    the best distance at any rotation of a start farther than the exclusion radius.
    """
    s = settings
    if s.heading_search_deg <= 0:
        return _match_once(m, h_nt, ins_m, s, centre_m)
    ins = np.asarray(ins_m, float)[:, :2]
    n_side = int(math.floor(s.heading_search_deg / s.heading_step_deg + 1e-9))
    angles = np.concatenate([[0.0], np.arange(1, n_side + 1) * s.heading_step_deg,
                             -np.arange(1, n_side + 1) * s.heading_step_deg])
    results = []
    for a in angles:
        c, sn = math.cos(math.radians(a)), math.sin(math.radians(a))
        rot = np.array([[c, sn], [-sn, c]])  # clockwise by a (headings grow clockwise)
        r = _match_once(m, h_nt, ins[0] + (ins - ins[0]) @ rot.T, s, centre_m if centre_m is not None else ins[0])
        r.rotation_deg = float(a)
        results.append(r)
    found = [r for r in results if r.found]
    if not found:
        return results[0]
    best = min(found, key=lambda r: (r.hausdorff_nt, abs(r.rotation_deg)))
    rivals = [best.runner_up_nt] if best.runner_up_nt is not None else []
    for r in found:
        if r is best:
            continue
        far = math.hypot(*((r.start_ij - best.start_ij) * [m.dx_m, m.dy_m])) > s.runner_up_exclusion_m
        if far:
            rivals.append(r.hausdorff_nt)
        elif r.runner_up_nt is not None:
            rivals.append(r.runner_up_nt)
    if rivals:
        best.runner_up_nt = float(min(rivals))
        best.margin_nt = best.runner_up_nt - best.hausdorff_nt
    for r in results:
        if r is not best:
            best.n_prematch += r.n_prematch
            best.n_abandoned += r.n_abandoned
            best.n_fine += r.n_fine
            best.term_evaluations += r.term_evaluations
    return best


def _match_once(m: GridMap, h_nt, ins_m, settings: MatchSettings, centre_m=None) -> MatchResult:
    s = settings
    h = _prepare(h_nt, s)
    ins = np.asarray(ins_m, float)
    offsets = _offsets_ij(m, ins)
    centre = m.to_grid(ins[0, :2] if centre_m is None else np.asarray(centre_m, float)[:2])
    lo, hi = _search_box(m, centre, s.search_radius_m, offsets)
    # a cell (i, j) spans nodes i..i+1, j..j+1: cells whose four corners are valid starts
    ci = np.arange(lo[0], hi[0])
    cj = np.arange(lo[1], hi[1])
    if ci.size == 0 or cj.size == 0:
        return _empty(m, s, "the strip does not fit on the map inside the search area")
    area = float(ci.size * cj.size * m.cell_area_m2)
    CI, CJ = np.meshgrid(ci, cj, indexing="ij")
    cells = np.stack([CI.ravel(), CJ.ravel()], axis=-1).astype(float)
    lam = s.lambda_nt
    evals = 0
    while True:
        if s.prematch_score == "centre":
            cell_scores, e = _ssda_scores(m, h, cells + 0.5, offsets, lam, s, coarse=True)
            evals += e
        else:
            # mean of the four corners' distances < λ needs every corner < 4λ: abandon nodes at 4λ
            ni = np.arange(lo[0], hi[0] + 1)
            nj = np.arange(lo[1], hi[1] + 1)
            NI, NJ = np.meshgrid(ni, nj, indexing="ij")
            nodes = np.stack([NI.ravel(), NJ.ravel()], axis=-1).astype(float)
            node_scores, e = _ssda_scores(m, h, nodes, offsets, 4 * lam, s, coarse=True)
            evals += e
            g = node_scores.reshape(ni.size, nj.size)
            cell_scores = (0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])).ravel()
        feasible = np.flatnonzero(cell_scores < lam)
        if feasible.size >= min(s.min_feasible_cells, cells.shape[0]) or lam * s.lambda_growth > s.max_lambda_nt:
            break
        lam *= s.lambda_growth
    n_abandoned = int(np.sum(~np.isfinite(cell_scores)))
    if feasible.size == 0:
        r = _empty(m, s, f"no cell scored below λ = {lam:.3g} nT")
        r.lambda_nt, r.search_area_m2, r.n_prematch, r.n_abandoned = lam, area, cells.shape[0], n_abandoned
        r.term_evaluations = evals
        return r
    # fine match: lattice points (i + a/k, j + b/k), a, b ∈ 0..k, of every feasible cell (§3.2)
    k = s.subdivisions
    a = np.arange(k + 1)
    A, B = np.meshgrid(a, a, indexing="ij")
    fc = cells[feasible].astype(np.int64) * k
    lat = (fc[:, None, 0] + A.ravel()[None, :]).ravel(), (fc[:, None, 1] + B.ravel()[None, :]).ravel()
    lattice = np.unique(np.stack(lat, axis=-1), axis=0)
    starts = lattice / k
    r = _strip(m, starts, offsets, slice(None), coarse=False)
    if s.demean:
        r = r - r.mean(axis=1, keepdims=True)
    scores = hausdorff(h, r, s.window_samples, s.rank_frac)
    evals += starts.shape[0] * h.size * (1 if s.window_samples == 0 else 2)
    res = _finish(m, starts, scores, offsets, lam, s, area)
    res.n_prematch, res.n_abandoned, res.n_feasible, res.n_fine = cells.shape[0], n_abandoned, feasible.size, len(starts)
    res.term_evaluations = evals
    return res


def match_exhaustive(m: GridMap, h_nt, ins_m, settings: MatchSettings, centre_m=None, chunk: int = 4096) -> MatchResult:
    """Reference search: full Hausdorff distance at every fine lattice start of the search area."""
    s = settings
    h = _prepare(h_nt, s)
    ins = np.asarray(ins_m, float)
    offsets = _offsets_ij(m, ins)
    centre = m.to_grid(ins[0, :2] if centre_m is None else np.asarray(centre_m, float)[:2])
    lo, hi = _search_box(m, centre, s.search_radius_m, offsets)
    if hi[0] <= lo[0] or hi[1] <= lo[1]:
        return _empty(m, s, "the strip does not fit on the map inside the search area")
    k = s.subdivisions
    gi = np.arange(lo[0] * k, hi[0] * k + 1) / k
    gj = np.arange(lo[1] * k, hi[1] * k + 1) / k
    GI, GJ = np.meshgrid(gi, gj, indexing="ij")
    starts = np.stack([GI.ravel(), GJ.ravel()], axis=-1)
    scores = np.empty(starts.shape[0])
    for c0 in range(0, starts.shape[0], chunk):
        r = _strip(m, starts[c0:c0 + chunk], offsets, slice(None), coarse=False)
        if s.demean:
            r = r - r.mean(axis=1, keepdims=True)
        scores[c0:c0 + chunk] = hausdorff(h, r, s.window_samples, s.rank_frac)
    area = float((hi[0] - lo[0]) * (hi[1] - lo[1]) * m.cell_area_m2)
    res = _finish(m, starts, scores, offsets, s.lambda_nt, s, area)
    res.n_fine = starts.shape[0]
    res.term_evaluations = starts.shape[0] * h.size * (1 if s.window_samples == 0 else 2)
    return res


def _empty(m: GridMap, s: MatchSettings, reason: str) -> MatchResult:
    nan2 = np.full(2, np.nan)
    return MatchResult(False, nan2, nan2, nan2, math.inf, None, None, s.lambda_nt, 0.0, reason=reason)


# ---- M-of-N acceptance ------------------------------------------------------------------------


@dataclass(frozen=True)
class AcceptSettings:
    m_agree: int = 2  # M: fixes that must agree (the current one included)
    n_window: int = 3  # N: last fixes considered
    agree_radius_m: float = 250.0  # two fixes agree when their INS corrections differ by less than this
    min_margin_nt: float = 0.3  # runner-up margin below this: ambiguous, never a fix
    max_hausdorff_nt: float = 30.0  # best distance above this: rejected

    def __post_init__(self):
        if not 1 <= self.m_agree <= self.n_window:
            raise ValueError(f"need 1 ≤ m_agree ≤ n_window, got {self.m_agree} of {self.n_window}")
        if self.agree_radius_m <= 0:
            raise ValueError("agree_radius_m must be > 0")


class MofNAcceptor:
    """M/N rule (paper §5): a fix is accepted when ≥ M of the last N candidate fixes agree with it.

    Fixes are compared by the INS correction they imply (matched − INS position), which moves
    only with the slow INS drift, so fixes taken at different places can be compared.
    """

    def __init__(self, settings: AcceptSettings = AcceptSettings()):
        self.settings = settings
        self.reset()

    def reset(self):
        self._history: deque = deque(maxlen=self.settings.n_window)
        self.last_status = "pending"
        self.agreeing = 0

    def update(self, result: MatchResult, ins_end_m) -> str:
        """Classify a match: 'accepted', 'pending', 'ambiguous' or 'rejected'."""
        s = self.settings
        if not result.found or result.hausdorff_nt > s.max_hausdorff_nt:
            status = "rejected"
            self._history.append(None)
        elif result.margin_nt is not None and result.margin_nt < s.min_margin_nt:
            status = "ambiguous"
            self._history.append(None)
        else:
            corr = np.asarray(result.end_m, float) - np.asarray(ins_end_m, float)[:2]
            self._history.append(corr)
            self.agreeing = sum(
                1 for c in self._history if c is not None and float(np.hypot(*(c - corr))) < s.agree_radius_m
            )
            status = "accepted" if self.agreeing >= s.m_agree else "pending"
        if status in ("rejected", "ambiguous"):
            self.agreeing = 0
        self.last_status = status
        return status


# ---- the streaming matcher (x-io Fusion shape: settings, update, internal_states, flags, reset) ---


@dataclass(frozen=True)
class FilterSettings:
    fix_std_m: float = 50.0  # 1-σ per axis of an accepted fix
    drift_rate_noise_m_s2: float = 0.005  # √q of the random walk of the INS drift rate, m/s^1.5
    init_drift_std_m_s: float = 1.0  # 1-σ of the drift rate at the first fix
    gate_sigma: float = 5.0  # innovation gate, standard deviations
    reset_after_rejections: int = 3  # consecutive gated fixes that restart the filter at the new fix

    def __post_init__(self):
        if not (self.fix_std_m > 0 and self.drift_rate_noise_m_s2 >= 0 and self.gate_sigma > 0):
            raise ValueError("fix_std_m and gate_sigma must be > 0, drift_rate_noise_m_s2 ≥ 0")


class InsErrorFilter:
    """Kalman filter of the INS correction c = truth − INS and its rate (the paper's §5 alternative).

    State x = [c_E, c_N, ċ_E, ċ_N]; c(t + Δt) = c + ċ Δt, ċ a random walk (q = drift_rate_noise²);
    measurement z = the correction an accepted fix implies, R = fix_std² I. Innovations are gated
    PX4 style: test_ratio = νᵀ S⁻¹ ν / gate²; a fix with test_ratio > 1 is not fused, and after
    ``reset_after_rejections`` of them in a row the filter restarts at the new fix (the INS jumped).
    """

    def __init__(self, settings: FilterSettings = FilterSettings()):
        self.settings = settings
        self.reset()

    def reset(self):
        self.x: np.ndarray | None = None
        self.P = np.zeros((4, 4))
        self.t_s: float | None = None
        self.test_ratio: float | None = None
        self.rejections = 0

    def _predict_to(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        dt = max(0.0, t_s - self.t_s) if self.t_s is not None else 0.0
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.settings.drift_rate_noise_m_s2 ** 2
        Q1 = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])  # integrated random walk
        Q = np.zeros((4, 4))
        Q[np.ix_([0, 2], [0, 2])] = Q1
        Q[np.ix_([1, 3], [1, 3])] = Q1
        return F @ self.x, F @ self.P @ F.T + Q

    def correction_at(self, t_s: float) -> np.ndarray | None:
        if self.x is None:
            return None
        return self._predict_to(t_s)[0][:2]

    def update(self, t_s: float, correction_m) -> bool:
        """Fuse one accepted fix's correction; return whether it was fused."""
        s = self.settings
        z = np.asarray(correction_m, float)[:2]
        r2 = s.fix_std_m ** 2
        if self.x is None or self.rejections >= s.reset_after_rejections:
            self.x = np.array([z[0], z[1], 0.0, 0.0])
            self.P = np.diag([r2, r2, s.init_drift_std_m_s ** 2, s.init_drift_std_m_s ** 2])
            self.t_s, self.test_ratio, self.rejections = float(t_s), 0.0, 0
            return True
        x, P = self._predict_to(t_s)
        H = np.hstack([np.eye(2), np.zeros((2, 2))])
        nu = z - H @ x
        S = H @ P @ H.T + r2 * np.eye(2)
        self.test_ratio = float(nu @ np.linalg.solve(S, nu)) / s.gate_sigma ** 2
        self.x, self.P, self.t_s = x, P, float(t_s)
        if self.test_ratio > 1.0:
            self.rejections += 1
            return False
        K = P @ H.T @ np.linalg.inv(S)
        self.x = x + K @ nu
        self.P = (np.eye(4) - K @ H) @ P
        self.P = 0.5 * (self.P + self.P.T)
        self.rejections = 0
        return True


@dataclass(frozen=True)
class MatcherSettings:
    match: MatchSettings = field(default_factory=MatchSettings)
    accept: AcceptSettings = field(default_factory=AcceptSettings)
    filter: FilterSettings = field(default_factory=FilterSettings)
    match_every_samples: int = 5  # run a match each time this many new samples arrived
    divergence_alarm_m: float = 500.0  # raise when an accepted fix is this far from the INS
    main_field_nt: float = 0.0  # subtracted from the measured total field to get the anomaly


@dataclass
class Fix:
    """One published matching outcome."""

    t_s: float
    status: str
    accepted: bool
    result: MatchResult
    ins_end_m: np.ndarray
    correction_m: np.ndarray  # matched − INS at the last sample (NaN if no match)
    divergence_m: float
    filtered_correction_m: np.ndarray | None = None  # INS-error filter's correction after this fix
    test_ratio: float | None = None  # filter innovation test ratio of an accepted fix (> 1: not fused)
    fused: bool = False


class GeomagMatcher:
    """Collects (t, field, INS position) samples and matches the last N whenever enough are new."""

    def __init__(self, grid: GridMap, settings: MatcherSettings = MatcherSettings()):
        self.map = grid
        self.settings = settings
        self.acceptor = MofNAcceptor(settings.accept)
        self.filter = InsErrorFilter(settings.filter)
        self.reset()

    def reset(self):
        n = self.settings.match.n_samples
        self._t: deque = deque(maxlen=n)
        self._h: deque = deque(maxlen=n)
        self._p: deque = deque(maxlen=n)
        self._new = 0
        self.acceptor.reset()
        self.filter.reset()
        self.last_fix: Fix | None = None
        self.last_accepted: Fix | None = None
        self.divergence_m = 0.0
        self.diverged = False
        self.n_matches = 0
        self.n_accepted = 0
        self.last_match_ms = 0.0

    def update(self, t_s: float, f_nt: float, ins_pos_m) -> Fix | None:
        """Add one sample (total field and the INS position at the same time); return a Fix when matched."""
        import time

        s = self.settings
        self._t.append(float(t_s))
        self._h.append(float(f_nt) - s.main_field_nt)
        self._p.append(np.asarray(ins_pos_m, float)[:2])
        self._new += 1
        if len(self._h) < s.match.n_samples or self._new < s.match_every_samples:
            return None
        self._new = 0
        t0 = time.perf_counter()
        ins = np.array(self._p)
        # once a fix was accepted, search around the corrected INS start instead of the raw one
        centre = ins[0] if self.last_accepted is None else ins[0] + self.last_accepted.correction_m
        res = match_sequence(self.map, np.array(self._h), ins, s.match, centre_m=centre)
        self.last_match_ms = (time.perf_counter() - t0) * 1e3
        status = self.acceptor.update(res, ins[-1])
        corr = res.end_m - ins[-1] if res.found else np.full(2, np.nan)
        div = float(np.hypot(*corr)) if res.found else float("nan")
        fix = Fix(float(t_s), status, status == "accepted", res, ins[-1], corr, div)
        self.n_matches += 1
        if fix.accepted:
            fix.fused = self.filter.update(fix.t_s, corr)
            fix.test_ratio = self.filter.test_ratio
            self.n_accepted += 1
            self.last_accepted = fix
            self.divergence_m = div
            self.diverged = div > s.divergence_alarm_m
        fix.filtered_correction_m = self.filter.correction_at(fix.t_s)
        self.last_fix = fix
        return fix

    def corrected_position(self, ins_pos_m, t_s: float | None = None) -> np.ndarray | None:
        """INS position corrected by the INS-error filter at t_s (None before the first accepted fix)."""
        if self.filter.x is None:
            return None
        t = self.filter.t_s if t_s is None else t_s
        return np.asarray(ins_pos_m, float)[:2] + self.filter.correction_at(t)

    @property
    def internal_states(self) -> dict:
        f = self.last_fix
        return {
            "buffered_samples": len(self._h),
            "n_matches": self.n_matches,
            "n_accepted": self.n_accepted,
            "last_hausdorff_nt": None if f is None or not f.result.found else f.result.hausdorff_nt,
            "last_margin_nt": None if f is None else f.result.margin_nt,
            "last_lambda_nt": None if f is None else f.result.lambda_nt,
            "last_feasible_cells": None if f is None else f.result.n_feasible,
            "divergence_m": self.divergence_m,
            "last_match_ms": self.last_match_ms,
        }

    @property
    def flags(self) -> dict:
        return {
            "collecting": len(self._h) < self.settings.match.n_samples,
            "diverged": self.diverged,
            "last_status": None if self.last_fix is None else self.last_fix.status,
        }
