"""Two-Step least-squares ellipse (2-D) and ellipsoid (3-D) calibration (docs/methods.md#calibration).

Step 1 (linear least squares). With |h| = R the raw samples lie on the quadric
``(m − b)ᵀ W (m − b) = 1``. Written in the paper's linear form ``A X = L`` with ``L = 1``
(reconstructed; n = 9 unknowns in 3-D, 5 in 2-D)::

    3-D row:  [x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] · X = 1
    2-D row:  [x², y², 2xy, 2x, 2y] · X = 1

``X = (AᵀPA)⁻¹ AᵀPL`` (P = I for plain LS; ARLS re-weights P, see arls.py).

Step 2 (algebraic decomposition) turns X into the offset b and matrix M
(:func:`magmesh.magcal.decompose_quadric`).

Samples are centred and scaled before the design matrix is built (x = (m − μ)/s): with a hard
iron several times the field the raw design matrix is badly conditioned, and the normalisation
also keeps the right-hand side 1 far from the degenerate case of a quadric through the origin.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from magmesh import magcal

MODELS = ("2d", "3d")


@dataclass(frozen=True)
class Normalisation:
    """x = (m − centre) / scale for the model's axes."""

    centre: np.ndarray
    scale: float


def normalise(m: np.ndarray) -> tuple[np.ndarray, Normalisation]:
    centre = np.median(m, axis=0)
    d = m - centre
    scale = float(np.median(np.linalg.norm(d, axis=1)))
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError("samples have no spread")
    return d / scale, Normalisation(centre, scale)


def design_matrix(x: np.ndarray) -> np.ndarray:
    """Rows of A for normalised samples x (N×2 or N×3)."""
    if x.shape[1] == 3:
        X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
        return np.column_stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z])
    X, Y = x[:, 0], x[:, 1]
    return np.column_stack([X * X, Y * Y, 2 * X * Y, 2 * X, 2 * Y])


def quadric_from_solution(X: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(Q, u, k) of ``xᵀQx + uᵀx + k = 0`` from the solution vector."""
    if n == 3:
        a, b, c, d, e, f, g, h, i = X
        Q = np.array([[a, d, e], [d, b, f], [e, f, c]])
        u = 2.0 * np.array([g, h, i])
    else:
        a, b, c, d, e = X
        Q = np.array([[a, c], [c, b]])
        u = 2.0 * np.array([d, e])
    return Q, u, -1.0


def solve_weighted(A: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """X = (AᵀPA)⁻¹ AᵀPL with L = 1 and P = diag(w) (normal equations, well conditioned after scaling)."""
    if w is None:
        N = A.T @ A
        r = A.sum(axis=0)
    else:
        Aw = A * w[:, None]
        N = Aw.T @ A
        r = Aw.sum(axis=0)
    return np.linalg.solve(N, r)


@dataclass
class FitResult:
    """Outcome of one fit; ``params`` is None when the quadric was not an ellipse/ellipsoid."""

    params: magcal.MagParams | None
    method: str
    model: str
    n_samples: int
    rmse_nt: float | None = None
    n_gross_rejected: int = 0
    iterations: int = 1
    converged: bool = True
    weights: np.ndarray | None = field(default=None, repr=False)
    duration_ms: float = 0.0
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.params is not None


def solution_to_params(X: np.ndarray, norm: Normalisation, model: str, radius_nt: float | None) -> magcal.MagParams:
    """Step 2: decompose X (normalised units) into offset and matrix in sensor units."""
    n = 3 if model == "3d" else 2
    Q, u, k = quadric_from_solution(X, n)
    c, M_unit_scaled, _ = magcal.decompose_quadric(Q, u, k, radius_nt=1.0)
    # x = (m − μ)/s → b = μ + s c; W_m = W_x / s²; M = R sqrtm(W_m)
    b = norm.centre + norm.scale * c
    W = (M_unit_scaled @ M_unit_scaled) / norm.scale**2
    R = float(np.linalg.det(W) ** (-1.0 / (2 * n))) if radius_nt is None else float(radius_nt)
    M = R * magcal.sqrtm_spd(W)
    if model == "2d":
        b3, M3 = magcal.embed_2d(b, M)
        return magcal.MagParams.from_arrays(b3, M3, R, "2d", (True, True, False))
    return magcal.MagParams.from_arrays(b, M, R, "3d", (True, True, True))


def model_axes(m_nt: np.ndarray, model: str) -> np.ndarray:
    m = np.asarray(m_nt, float)  # pragma: no mutate (dtype: normalise divides, the design matrix is float either way)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"samples must be N×3, got shape {m.shape}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    return m[:, :2] if model == "2d" else m


def rmse(m_nt: np.ndarray, params: magcal.MagParams, weights: np.ndarray | None = None) -> float:
    """RMS of |h| − R over the samples (only those with non-zero weight when weights are given), nT."""
    r = magcal.field_strength_residual(m_nt, params)
    if weights is not None:
        r = r[weights > 0]
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def fit_ls(m_nt, model: str = "3d", radius_nt: float | None = None) -> FitResult:
    """Plain Two-Step LS fit of N×3 samples (nT). ``radius_nt`` fixes R (e.g. the IGRF field strength)."""
    t0 = time.perf_counter()
    m = np.asarray(m_nt, float)  # pragma: no mutate (dtype: model_axes and magcal.apply convert again)
    x, norm = normalise(model_axes(m, model))
    A = design_matrix(x)
    try:
        X = solve_weighted(A)
        params = solution_to_params(X, norm, model, radius_nt)
    except (ValueError, np.linalg.LinAlgError) as e:
        return FitResult(None, "ls", model, len(m), reason=f"least squares gave no ellipsoid: {e}",
                         duration_ms=1e3 * (time.perf_counter() - t0))
    res = FitResult(params, "ls", model, len(m), rmse(m, params))
    res.duration_ms = 1e3 * (time.perf_counter() - t0)
    return res
