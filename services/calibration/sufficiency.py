"""Data sufficiency: does a sample set cover enough heading/attitude to be fitted?

A least-squares ellipse through a 90° arc is a guess, not a calibration. Before a fit is
published its samples must cover the circle (2-D: the share of ``heading_bin_deg`` bins of the
horizontal direction around the fitted centre that hold at least ``min_per_bin`` samples) or the
sphere (3-D: the share of ``sphere_cells`` equal-area cells — a Fibonacci lattice — of the field
direction). The fitted shape must also be plausible (axis ratio, radius range).

:func:`balanced_subset` caps the number of samples per direction cell so that a vehicle parked
(or driving straight) for minutes does not outvote the turn that carries the information — the
same reason ArduPilot's compass calibrator accepts a sample only far from the ones it has.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magmesh import magcal


@dataclass(frozen=True)
class SufficiencySettings:
    min_samples: int = 150
    heading_bin_deg: float = 10.0  # 2-D coverage bin width
    min_coverage_2d: float = 0.75  # share of heading bins that must be filled
    sphere_cells: int = 60  # 3-D coverage cells (equal area)
    min_coverage_3d: float = 0.55  # share of sphere cells that must be filled
    min_per_bin: int = 2  # samples a bin/cell needs to count as covered
    max_per_bin: int = 40  # balanced subset: at most this many samples per bin/cell
    max_axis_ratio: float = 3.0  # largest/smallest singular value of the fitted matrix
    radius_range_nt: tuple[float, float] = (5_000.0, 120_000.0)  # plausible fitted field strength
    max_residual_rel: float = 0.12  # robust spread of |h|/R − 1 beyond this: not an ellipse/ellipsoid
    max_vertical_ratio: float = 0.6  # 2-D: 5–95% range of m_z over the circle's diameter beyond this: tilting

    def __post_init__(self):
        if not (0 < self.min_coverage_2d <= 1 and 0 < self.min_coverage_3d <= 1):
            raise ValueError("coverage thresholds must be in (0, 1]")
        if self.heading_bin_deg <= 0 or self.sphere_cells < 6:
            raise ValueError("heading_bin_deg must be > 0 and sphere_cells ≥ 6")


def _fibonacci_cells(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    lon = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(lon), r * np.sin(lon), z])


def direction_bins(d: np.ndarray, model: str, st: SufficiencySettings) -> tuple[np.ndarray, int]:
    """Bin index of each direction vector (rows of d, already centred) and the number of bins."""
    if model == "2d":
        nb = int(round(360.0 / st.heading_bin_deg))
        ang = np.arctan2(d[:, 1], d[:, 0]) % (2 * math.pi)
        return np.minimum((ang / (2 * math.pi) * nb).astype(int), nb - 1), nb
    cells = _fibonacci_cells(st.sphere_cells)
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return np.argmax(u @ cells.T, axis=1), st.sphere_cells


def rough_centre(m: np.ndarray) -> np.ndarray:
    """Midpoint of the per-axis 2nd–98th percentile range: a centre that needs no fit."""
    lo, hi = np.percentile(m, [2, 98], axis=0)
    return 0.5 * (lo + hi)


def coverage(m_nt: np.ndarray, model: str, st: SufficiencySettings, params: magcal.MagParams | None = None,
             centre=None) -> float:
    """Share of direction bins holding ≥ min_per_bin samples (directions of the compensated field
    when ``params`` is given, else of the samples around their rough centre; ``centre``: that centre, when the
    caller has it already)."""
    m = np.asarray(m_nt, float)
    if len(m) == 0:
        return 0.0
    d = params.apply(m) if params is not None else m - (rough_centre(m) if centre is None else centre)
    d = d[:, :2] if model == "2d" else d
    idx, nb = direction_bins(d, model, st)
    counts = np.bincount(idx, minlength=nb)
    return float(np.count_nonzero(counts >= st.min_per_bin) / nb)


def balanced_subset(m_nt: np.ndarray, model: str, st: SufficiencySettings, centre=None) -> np.ndarray:
    """Indices of at most ``max_per_bin`` samples per direction bin, spread evenly in time."""
    m = np.asarray(m_nt, float)
    c = rough_centre(m) if centre is None else np.asarray(centre, float)
    d = m - c
    d = d[:, :2] if model == "2d" else d
    idx, nb = direction_bins(d, model, st)
    keep = []
    order = np.argsort(idx, kind="stable")
    bounds = np.searchsorted(idx[order], np.arange(nb + 1))
    for b in range(nb):
        members = order[bounds[b]: bounds[b + 1]]
        if len(members) > st.max_per_bin:
            members = members[np.linspace(0, len(members) - 1, st.max_per_bin).round().astype(int)]
        keep.append(members)
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, int)


@dataclass(frozen=True)
class Verdict:
    ok: bool
    coverage_frac: float
    reason: str = ""


def check_samples(m_nt: np.ndarray, model: str, st: SufficiencySettings, centre=None) -> Verdict:
    """Before fitting: enough samples, enough spread around a rough centre (``centre``: ``rough_centre(m_nt)``
    when the caller has it already)."""
    n = len(m_nt)
    if n < st.min_samples:
        return Verdict(False, 0.0, f"only {n} samples, need at least {st.min_samples}")
    cov = coverage(m_nt, model, st, centre=centre)
    need = st.min_coverage_2d if model == "2d" else st.min_coverage_3d
    if cov < need:
        what = "heading (turn through a full circle)" if model == "2d" else "attitude (tumble the sensor)"
        return Verdict(False, cov, f"samples cover {100 * cov:.0f}% of {what}, need {100 * need:.0f}%")
    return Verdict(True, cov)


def check_fit(m_nt: np.ndarray, params: magcal.MagParams, st: SufficiencySettings,
              weights: np.ndarray | None = None) -> Verdict:
    """After fitting: coverage around the fitted centre and a plausible shape."""
    m = np.asarray(m_nt, float)
    if weights is not None:
        m = m[weights > 0]
    model = params.model
    cov = coverage(m, model, st, params)
    need = st.min_coverage_2d if model == "2d" else st.min_coverage_3d
    if cov < need:
        return Verdict(False, cov, f"fitted samples cover {100 * cov:.0f}% of the {'circle' if model == '2d' else 'sphere'}, "
                                   f"need {100 * need:.0f}%")
    M = params.M[:2, :2] if model == "2d" else params.M
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[-1] <= 0 or sv[0] / sv[-1] > st.max_axis_ratio:
        return Verdict(False, cov, f"fitted axis ratio {sv[0] / max(sv[-1], 1e-300):.2f} exceeds {st.max_axis_ratio:g}: "
                                   "not a plausible soft iron")
    lo, hi = st.radius_range_nt
    if not (lo <= params.field_radius_nt <= hi):
        return Verdict(False, cov, f"fitted field strength {params.field_radius_nt:.0f} nT is outside {lo:.0f}–{hi:.0f} nT")
    if model == "2d":
        z_range = float(np.percentile(m[:, 2], 95) - np.percentile(m[:, 2], 5))
        ratio = z_range / (2 * params.field_radius_nt)
        if ratio > st.max_vertical_ratio:
            return Verdict(False, cov, f"the sensor tilts: its vertical field varies by {100 * ratio:.0f}% of the "
                                       "horizontal circle, too much for a level (2-D) fit; tumble it for a 3-D fit")
    r = magcal.field_strength_residual(m, params) / params.field_radius_nt
    spread = float(1.4826 * np.median(np.abs(r - np.median(r))))
    if spread > st.max_residual_rel:
        return Verdict(False, cov, f"samples do not lie on an {'ellipse' if model == '2d' else 'ellipsoid'} "
                                   f"(robust residual {100 * spread:.1f}% > {100 * st.max_residual_rel:.0f}%): "
                                   "the field is disturbed or the sensor moves out of the fitted model")
    return Verdict(True, cov)
