"""Seeded synthetic magnetometer clouds with known calibration truth (for tests and the evaluation).

Sensor model (the inverse of the compensation, magmesh.magcal): ``m = D h + b + n`` with
``M_true = D⁻¹``. Gross errors are injected the way the ARLS paper did (docs/methods.md#calibration): a
fraction of the samples, in a few contiguous bursts, displaced by a disturbance of a given size
relative to the field (10% in its 2-D test, 20% in its 3-D test).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CloudSettings:
    model: str = "3d"  # "3d": sensor tumbled over the sphere; "2d": rotated about its z axis, level
    n_samples: int = 3000
    field_nt: float = 50_000.0  # |B| at the site
    inclination_rad: float = 0.8  # 2-D only: dip of the field below the horizontal
    hard_iron_max_ratio: float = 5.0  # |b| drawn uniformly in [0, ratio · |B|]
    soft_iron_max: float = 0.30  # diagonal scale factors in [1 − x, 1 + x]
    cross_axis_max: float = 0.10  # off-diagonal terms in [−x, x] (misalignment + soft iron)
    noise_nt: float = 50.0  # white noise per axis, 1 σ
    gross_frac: float = 0.0  # fraction of samples with gross errors
    gross_size_rel: float = 0.20  # size of a gross error relative to |B|
    gross_bursts: int = 4  # the gross errors come in this many contiguous bursts
    seed: int = 0


@dataclass
class Cloud:
    m_nt: np.ndarray  # N×3 measured samples
    h_nt: np.ndarray  # N×3 true field (sensor frame)
    offset_nt: np.ndarray  # true hard-iron offset (2-D: z component 0)
    M: np.ndarray  # true compensation matrix D⁻¹ (2-D: z row/column identity)
    radius_nt: float  # |h| (2-D: horizontal field strength)
    gross: np.ndarray  # bool mask of samples with gross errors
    settings: CloudSettings


def burst_mask(n: int, frac: float, k: int, rng) -> np.ndarray:
    mask = np.zeros(n, bool)
    total = int(round(frac * n))
    if total == 0:
        return mask
    k = max(1, min(k, total))
    sizes = np.full(k, total // k)
    sizes[: total - sizes.sum()] += 1
    # place the bursts in disjoint slots of equal length
    slot = n // k
    for i, s in enumerate(sizes):
        start = i * slot + int(rng.integers(0, max(1, slot - s)))
        mask[start: start + s] = True
    return mask


def make_cloud(s: CloudSettings = CloudSettings()) -> Cloud:
    rng = np.random.default_rng(s.seed)
    n = s.n_samples
    if s.model == "3d":
        # a smooth tumble that covers the sphere: spiral in latitude, several turns in longitude
        u = np.linspace(-1, 1, n) + rng.normal(0, 0.01, n)
        u = np.clip(u, -1, 1)
        lon = np.linspace(0, 2 * np.pi * 12, n) + rng.normal(0, 0.05, n)
        h = s.field_nt * np.column_stack([np.sqrt(1 - u * u) * np.cos(lon), np.sqrt(1 - u * u) * np.sin(lon), u])
        b = rng.normal(size=3)
        b *= rng.uniform(0, s.hard_iron_max_ratio) * s.field_nt / np.linalg.norm(b)
        D = np.diag(rng.uniform(1 - s.soft_iron_max, 1 + s.soft_iron_max, 3))
        off = rng.uniform(-s.cross_axis_max, s.cross_axis_max, (3, 3))
        np.fill_diagonal(off, 0)
        D = D + off
        radius = s.field_nt
    elif s.model == "2d":
        th = np.linspace(0, 2 * np.pi * 3, n) + rng.normal(0, 0.02, n)
        bh = s.field_nt * np.cos(s.inclination_rad)
        bz = -s.field_nt * np.sin(s.inclination_rad)
        h = np.column_stack([bh * np.cos(th), bh * np.sin(th), np.full(n, bz)])
        b = np.zeros(3)
        b2 = rng.normal(size=2)
        b[:2] = b2 * rng.uniform(0, s.hard_iron_max_ratio) * s.field_nt / np.linalg.norm(b2)
        D = np.eye(3)
        D[:2, :2] = np.diag(rng.uniform(1 - s.soft_iron_max, 1 + s.soft_iron_max, 2))
        D[0, 1], D[1, 0] = rng.uniform(-s.cross_axis_max, s.cross_axis_max, 2)
        radius = bh
    else:
        raise ValueError(f"model must be '2d' or '3d', got {s.model!r}")
    m = h @ D.T + b + rng.normal(0, s.noise_nt, (n, 3))
    gross = burst_mask(n, s.gross_frac, s.gross_bursts, rng)
    if gross.any():
        # one disturbance vector per burst (a passing magnetic object), ± 20% jitter inside it
        labels = np.cumsum(np.diff(np.concatenate([[0], gross.astype(int)])) == 1)[gross]
        dirs = rng.normal(size=(labels.max() + 1, 3))
        if s.model == "2d":
            dirs[:, 2] = 0
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        size = s.gross_size_rel * s.field_nt * rng.uniform(0.8, 1.2, gross.sum())
        m[gross] += dirs[labels] * size[:, None]
    return Cloud(m, h, b, np.linalg.inv(D), float(radius), gross, s)
