"""Adaptive robust least squares (ARLS) with the IGG-III weight function (docs/methods.md#calibration).

Same model as Two-Step (two_step.py), ``V = A X − L`` with equivalent weights P re-computed from
the standardised residuals at every iteration (Yang 1996, the paper's ref. [8])::

    p_i = 1                                          |v'_i| ≤ k0
    p_i = (k0/|v'_i|) · ((k1 − |v'_i|)/(k1 − k0))²   k0 < |v'_i| ≤ k1
    p_i = 0                                          |v'_i| > k1

    X⁽ʲ⁺¹⁾ = (AᵀP⁽ʲ⁾A)⁻¹ AᵀP⁽ʲ⁾L                    until ‖X⁽ʲ⁺¹⁾ − X⁽ʲ⁾‖ / ‖X⁽ʲ⁾‖ < tol

The standardised residual is ``v'_i = v_i / σ̂`` with the robust scale σ̂ = 1.4826 · MAD of the
residuals (so the gross errors do not inflate the scale that is meant to expose them), floored
at ``min_sigma_rel`` of the median absolute residual to avoid dividing by zero on perfect data.

Improvement over the paper (``refine`` setting, on by default): the algebraic residual weights
every sample by its distance to the origin of the normalised cloud, which biases the fit under
noise. After the algebraic ARLS has converged, a few IGG-weighted Gauss–Newton steps on the
geometric residual ``|M̃ (m − b)| − 1`` (M̃ symmetric, 9 parameters in 3-D, 5 in 2-D) remove that
bias; gross errors already found keep weight 0 and the weights keep being updated.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from magmesh import magcal

from . import two_step

MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class ArlsSettings:
    k0: float = 1.5  # IGG-III: full weight up to k0 standardised residuals (paper: 1.0–1.5)
    k1: float = 3.0  # IGG-III: zero weight beyond k1 (paper: ≈ 3.0)
    max_iterations: int = 50
    tolerance: float = 1e-7  # relative change of X that ends the iteration
    min_sigma_rel: float = 1e-6  # floor of σ̂, relative to the median |v|
    refine: bool = True  # geometric IGG re-weighted Gauss–Newton after the algebraic ARLS
    refine_iterations: int = 5

    def __post_init__(self):
        if not (0 < self.k0 < self.k1):
            raise ValueError(f"IGG thresholds need 0 < k0 < k1, got k0={self.k0}, k1={self.k1}")
        if self.max_iterations < 1:
            raise ValueError("max_iterations must be ≥ 1")


def igg3_weights(v_std: np.ndarray, k0: float, k1: float) -> np.ndarray:
    """IGG-III equivalent weights of standardised residuals."""
    a = np.abs(v_std)
    p = np.ones_like(a)
    mid = (a > k0) & (a <= k1)
    p[mid] = (k0 / a[mid]) * ((k1 - a[mid]) / (k1 - k0)) ** 2
    p[a > k1] = 0.0
    return p


def robust_sigma(v: np.ndarray, min_sigma_rel: float = 1e-6) -> float:
    """σ̂ = 1.4826 · median(|v − median(v)|), floored."""
    med = np.median(v)
    s = MAD_TO_SIGMA * float(np.median(np.abs(v - med)))
    floor = min_sigma_rel * max(float(np.median(np.abs(v))), 1e-300)
    return max(s, floor, 1e-300)


def _refine_geometric(x: np.ndarray, X0: np.ndarray, n: int, st: ArlsSettings):
    """IGG re-weighted Gauss–Newton on r_i = |S (x_i − c)| − 1 in normalised units.

    S symmetric (upper triangle parameters), c the centre. Starts from the algebraic solution.
    Returns (c, S, w) or None when the algebraic solution is not an ellipsoid.
    """
    Q, u, k = two_step.quadric_from_solution(X0, n)
    try:
        c, S, _ = magcal.decompose_quadric(Q, u, k, radius_nt=1.0)
    except (ValueError, np.linalg.LinAlgError):
        return None
    iu = np.triu_indices(n)
    for _ in range(st.refine_iterations):
        d = x - c  # N×n
        y = d @ S  # S symmetric: y = S d
        r_norm = np.linalg.norm(y, axis=1)
        r = r_norm - 1.0
        g = y / np.maximum(r_norm, 1e-12)[:, None]  # ∂|y|/∂y
        # ∂r/∂c = −g S ; ∂r/∂S_ij (sym) = g_i d_j + g_j d_i (i ≠ j), g_i d_i (i = j)
        J_c = -(g @ S)
        cols = []
        for i, j in zip(iu[0], iu[1], strict=True):  # pragma: no mutate (strict=: triu_indices gives equal lengths)
            cols.append(g[:, i] * d[:, j] + (g[:, j] * d[:, i] if i != j else 0.0))
        J = np.column_stack([J_c, *cols])
        sig = robust_sigma(r, st.min_sigma_rel)
        w = igg3_weights(r / sig, st.k0, st.k1)
        Jw = J * w[:, None]
        try:
            step = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
        except np.linalg.LinAlgError:
            break
        c = c + step[:n]
        dS = np.zeros((n, n))
        dS[iu] = step[n:]
        dS = dS + np.triu(dS, 1).T
        S = S + dS
        if np.linalg.norm(step) < 1e-9:
            break
    if np.linalg.eigvalsh(0.5 * (S + S.T)).min() <= 0:
        return None
    # final weights on the final residuals
    r = np.linalg.norm((x - c) @ S, axis=1) - 1.0
    w = igg3_weights(r / robust_sigma(r, st.min_sigma_rel), st.k0, st.k1)
    return c, 0.5 * (S + S.T), w


def fit_arls(m_nt, model: str = "3d", radius_nt: float | None = None,
             settings: ArlsSettings = ArlsSettings()) -> two_step.FitResult:
    """ARLS fit of N×3 samples (nT). Returns the parameters, the final weights and the gross-error count."""
    t0 = time.perf_counter()
    m = np.asarray(m_nt, float)  # pragma: no mutate (dtype: model_axes and magcal.apply convert again)
    x, norm = two_step.normalise(two_step.model_axes(m, model))
    n = x.shape[1]
    A = two_step.design_matrix(x)
    p = A.shape[1]
    # rows' outer products, once: AᵀPA = Σ w_i a_i a_iᵀ becomes one matrix-vector product per iteration
    outer = (A[:, :, None] * A[:, None, :]).reshape(len(A), p * p)
    w = np.ones(len(x))
    converged = False
    iterations = 0
    try:
        X = two_step.solve_weighted(A)  # step 0: plain LS
        for it in range(1, settings.max_iterations + 1):
            iterations = it
            v = A @ X - 1.0  # V = A X − L
            sig = robust_sigma(v, settings.min_sigma_rel)
            w = igg3_weights(v / sig, settings.k0, settings.k1)
            if np.count_nonzero(w) < 2 * p:
                raise ValueError("too few samples keep a non-zero weight")
            X_new = np.linalg.solve((w @ outer).reshape(p, p), w @ A)  # X = (AᵀPA)⁻¹ AᵀPL, L = 1
            change = np.linalg.norm(X_new - X) / max(np.linalg.norm(X), 1e-300)
            X = X_new
            if change < settings.tolerance:
                converged = True
                break
        params = two_step.solution_to_params(X, norm, model, radius_nt)
        if settings.refine:
            ref = _refine_geometric(x, X, n, settings)
            if ref is not None:
                c, S, w = ref
                b = norm.centre + norm.scale * c
                W = (S @ S) / norm.scale**2
                R = float(np.linalg.det(W) ** (-1.0 / (2 * n))) if radius_nt is None else float(radius_nt)
                M = R * magcal.sqrtm_spd(W)
                if model == "2d":
                    b, M = magcal.embed_2d(b, M)
                    params = magcal.MagParams.from_arrays(b, M, R, "2d", (True, True, False))
                else:
                    params = magcal.MagParams.from_arrays(b, M, R, "3d", (True, True, True))
    except (ValueError, np.linalg.LinAlgError) as e:
        return two_step.FitResult(None, "arls", model, len(m), iterations=iterations, converged=False,
                                  reason=f"robust fit gave no ellipsoid: {e}",
                                  duration_ms=1e3 * (time.perf_counter() - t0))
    res = two_step.FitResult(
        params, "arls", model, len(m),
        rmse_nt=two_step.rmse(m, params, w),
        n_gross_rejected=int(np.count_nonzero(w == 0)),
        iterations=iterations, converged=converged, weights=w,
    )
    res.duration_ms = 1e3 * (time.perf_counter() - t0)
    return res
