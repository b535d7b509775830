"""Magnetometer calibration parameters: the model, applying it, and the quadric decomposition.

Model (docs/methods.md#calibration): the sensor reads ``m = K⁻¹ h + b + n`` where ``h`` is the
true field (|h| = R at the site), ``b`` the hard-iron offset and ``K⁻¹`` soft iron, scale factor
and misalignment lumped together. The compensation is::

    h = M (m − b)                                  (M = K)

From magnitudes alone only ``MᵀM`` is identifiable (a rotation of ``h`` leaves |h| unchanged), so
fitted matrices are the symmetric positive-definite root ``M = R · sqrtm(W)`` of the quadric
``(m − b)ᵀ W (m − b) = 1``.

2-D (horizontal ellipse, §1): only the x/y block is fitted; z passes through unchanged
(offset_z = 0, M[2, 2] = 1, M[0:2, 2] = M[2, 0:2] = 0) and ``field_radius_nt`` is the
horizontal field strength.

This module is shared by the calibration service (which fits parameters) and every consumer of
``cal/params`` (the DMC detector, the heading fuser), which only apply them: :class:`MagParams` is the one
parameter type of all of them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class MagParams:
    """One calibration parameter set, ``h = M (m − offset)``: the one type of it in the code base (the calibration
    service fits it; the DMC detector and the heading fuser apply it). Mirrors the ``cal_params`` message fields
    (see schemas/messages.py).

    ``model`` "3d": ``field_radius_nt`` is the total field strength (a tilt-invariant |h|); "2d": the horizontal
    field strength of a horizontal (ellipse) fit, and :meth:`strength` takes the horizontal components.
    ``param_id`` is the set's id where its holder keeps it with the parameters (a consumer of ``cal/params``;
    "manifest" for a manifest table); the calibration service keeps it in its ``ParamRecord`` instead.
    """

    offset_nt: tuple[float, float, float] = (0.0, 0.0, 0.0)
    matrix: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # row-major 3×3
    field_radius_nt: float = 50_000.0
    model: str = "3d"  # "2d" | "3d"
    param_id: str = ""
    observable: tuple[bool, bool, bool] = (True, True, True)
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if len(self.offset_nt) != 3 or len(self.matrix) != 9:
            raise ValueError("offset_nt needs 3 values and matrix 9 (row-major 3×3)")
        if not (self.field_radius_nt > 0 and math.isfinite(self.field_radius_nt)):
            raise ValueError(f"field_radius_nt must be a positive number, got {self.field_radius_nt!r}")
        if self.model not in ("2d", "3d"):
            raise ValueError(f"model must be '2d' or '3d', got {self.model!r}")

    @property
    def offset(self) -> np.ndarray:
        return np.asarray(self.offset_nt, float)

    @property
    def M(self) -> np.ndarray:
        return np.asarray(self.matrix, float).reshape(3, 3)

    @classmethod
    def from_arrays(cls, offset, M, radius: float, model: str = "3d", observable=(True, True, True)) -> MagParams:
        return cls(
            offset_nt=tuple(float(x) for x in np.asarray(offset, float).ravel()),
            matrix=tuple(float(x) for x in np.asarray(M, float).ravel()),
            field_radius_nt=float(radius),
            model=model,
            observable=tuple(bool(x) for x in observable),
        )

    @classmethod
    def from_message(cls, msg: Mapping) -> MagParams:
        """From a decoded ``cal_params`` message or a manifest ``mag_params`` table, a missing field taken as the
        identity's (what the calibration service and the heading fuser read)."""
        return cls(
            offset_nt=tuple(float(x) for x in msg.get("offset_nt", (0.0, 0.0, 0.0))),
            matrix=tuple(float(x) for x in msg.get("matrix", (1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0))),
            field_radius_nt=float(msg.get("field_radius_nt", 50_000.0)),
            model=str(msg.get("model", "3d")),
            observable=tuple(bool(x) for x in msg.get("observable", (True, True, True))),
        )

    @classmethod
    def from_mapping(cls, d: Mapping, param_id: str | None = None) -> MagParams:
        """From a manifest table or a ``cal_params`` message that must give offset_nt, matrix and field_radius_nt
        (``KeyError`` otherwise; the DMC detector's reading), with its ``param_id`` (given, the mapping's, else
        "manifest")."""
        matrix = np.asarray(d["matrix"], float).ravel()
        return cls(
            offset_nt=tuple(float(x) for x in d["offset_nt"]),
            matrix=tuple(float(x) for x in matrix),
            field_radius_nt=float(d["field_radius_nt"]),
            model=str(d.get("model", "3d")),
            param_id=str(param_id if param_id is not None else d.get("param_id", "manifest")),
            observable=tuple(bool(x) for x in d.get("observable", (True, True, True))),
        )

    def apply(self, m_nt) -> np.ndarray:
        """Compensated field h = M (m − offset) for one sample (3,) or many (N×3), nT."""
        return apply(m_nt, self.offset, self.M)

    def strength(self, h) -> np.ndarray:
        """Field strength of compensated samples: |h|, or for a 2-D model the horizontal |h_xy|, nT."""
        h = np.asarray(h, float)
        if self.model == "2d":
            return np.hypot(h[..., 0], h[..., 1])
        return np.linalg.norm(h, axis=-1)


IDENTITY = MagParams()


def apply(m_nt, offset_nt, M) -> np.ndarray:
    """h = M (m − offset), for (3,) or (N×3) samples."""
    m = np.asarray(m_nt, float)
    d = m - np.asarray(offset_nt, float)
    return d @ np.asarray(M, float).T


def sqrtm_spd(W: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric positive-definite matrix (eigen-decomposition)."""
    W = 0.5 * (W + W.T)
    w, V = np.linalg.eigh(W)
    if w.min() <= 0:
        raise ValueError(f"matrix is not positive definite (eigenvalues {w})")
    return (V * np.sqrt(w)) @ V.T


def symmetric_part(M: np.ndarray) -> np.ndarray:
    """The identifiable (symmetric positive-definite) part of a compensation matrix: sqrtm(MᵀM)."""
    M = np.asarray(M, float)
    return sqrtm_spd(M.T @ M)


def decompose_quadric(Q: np.ndarray, u: np.ndarray, k: float, radius_nt: float | None = None):
    """Centre and compensation matrix of the quadric ``mᵀ Q m + uᵀ m + k = 0``.

    Centre (hard iron) ``b = −½ Q⁻¹ u``; then ``(m − b)ᵀ Q (m − b) = bᵀ Q b − k = s`` so
    ``W = Q / s`` and ``M = R · sqrtm(W)``. When ``radius_nt`` is None, R is the geometric-mean
    radius ``det(W)^(−1/2n)`` (so det M = 1): the field strength the sensor sees after removing the
    distortion's volume change. Works for n = 2 (ellipse) and n = 3 (ellipsoid).

    Returns ``(b, M, R)``; raises ValueError when the quadric is not an ellipse/ellipsoid.
    """
    Q = 0.5 * (np.asarray(Q, float) + np.asarray(Q, float).T)
    n = Q.shape[0]
    b = -0.5 * np.linalg.solve(Q, np.asarray(u, float))
    s = float(b @ Q @ b - k)
    W = Q / s
    if not np.all(np.isfinite(W)) or np.linalg.eigvalsh(W).min() <= 0:
        raise ValueError("fitted quadric is not an ellipsoid (not positive definite)")
    R = float(np.linalg.det(W) ** (-1.0 / (2 * n))) if radius_nt is None else float(radius_nt)
    M = R * sqrtm_spd(W)
    return b, M, R


def embed_2d(b2, M2) -> tuple[np.ndarray, np.ndarray]:
    """3-D offset and matrix of a horizontal (x/y) fit: z passes through unchanged."""
    b = np.zeros(3)
    b[:2] = b2
    M = np.eye(3)
    M[:2, :2] = M2
    return b, M


def field_strength_residual(m_nt, params: MagParams) -> np.ndarray:
    """|h| − R per sample (2-D models use the horizontal components), nT."""
    return params.strength(params.apply(m_nt)) - params.field_radius_nt


def offset_error_pct(b_est, b_true, field_nt: float) -> float:
    """Offset error as a percentage of the field strength: 100 · |b̂ − b| / |B|."""
    return float(100.0 * np.linalg.norm(np.asarray(b_est) - np.asarray(b_true)) / field_nt)


def matrix_error_pct(M_est, R_est: float, M_true, R_true: float) -> float:
    """Relative error of the identifiable shape ``sqrtm(MᵀM)/R`` (spectral norm), percent.

    ``sqrtm(MᵀM)/R`` maps the raw ellipsoid to the unit sphere; it is what a magnitude-only fit
    can recover (rotation of h is not identifiable). 1% means the calibrated field direction and
    strength are off by at most ~1% of the field.
    """
    A = symmetric_part(M_est) / R_est
    B = symmetric_part(M_true) / R_true
    return float(100.0 * np.linalg.norm(A - B, 2) / np.linalg.norm(B, 2))


def spread(values) -> float:
    """std/median of a field-strength series (a unitless spread; 0 for a perfect calibration)."""
    v = np.asarray(values, float)
    med = float(np.median(v))
    return float(np.std(v) / med) if med != 0 else math.inf
