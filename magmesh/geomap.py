"""Gridded magnetic anomaly maps: loading, the synthetic paper map, bilinear sampling.

Shared by the geomagnetic matcher, the survey-vehicle simulator and the evaluation. numpy/scipy
only; never imports zenoh.

A :class:`GridMap` holds a scalar field (nT) on a regular grid indexed ``[ix, iy]``: node
``(ix, iy)`` sits at ``x = x0_m + ix·dx_m`` (east), ``y = y0_m + iy·dy_m`` (north) of the map frame.
Positions are handled either in metres (map frame, ENU) or in *grid units* (fractional indices).

Map file formats (:func:`load_map`):

- ``.npz`` with ``map_nt`` (nx×ny), ``x_m`` (nx), ``y_m`` (ny); optional ``alt_m``;
- ``.hdf5``/``.h5`` in the MagNav/WDMAM layout: ``map`` (nx×ny, nT), ``xx`` (m), ``yy`` (m), ``alt``;
- ``synthetic`` or ``synthetic:<seed>``: :func:`synthetic_paper_map`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: statistics of the paper's 150 × 150 anomaly map (Liu et al., §4): mean and std, nT
PAPER_MAP_MEAN_NT = 1.8303
PAPER_MAP_STD_NT = 16.8425


@dataclass(frozen=True)
class GridMap:
    """A scalar anomaly field on a regular grid (see module docstring for the frame)."""

    values_nt: np.ndarray  # (nx, ny)
    x0_m: float = 0.0
    y0_m: float = 0.0
    dx_m: float = 100.0
    dy_m: float = 100.0
    alt_m: float = 0.0
    name: str = "map"

    def __post_init__(self):
        v = np.asarray(self.values_nt, dtype=float)
        if v.ndim != 2 or min(v.shape) < 2:
            raise ValueError(f"map {self.name!r}: values must be a 2-D grid of at least 2×2, got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"map {self.name!r}: values contain {int(np.sum(~np.isfinite(v)))} non-finite cells")
        if not (self.dx_m > 0 and self.dy_m > 0):
            raise ValueError(f"map {self.name!r}: grid spacing must be positive, got {self.dx_m}, {self.dy_m}")
        object.__setattr__(self, "values_nt", v)

    # ---- geometry ------------------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        return self.values_nt.shape  # type: ignore[return-value]

    @property
    def std_nt(self) -> float:
        return float(np.std(self.values_nt))

    @property
    def cell_area_m2(self) -> float:
        return self.dx_m * self.dy_m

    def to_grid(self, xy_m) -> np.ndarray:
        """Map-frame metres (…×2) → fractional grid indices (…×2)."""
        p = np.asarray(xy_m, float)
        return np.stack([(p[..., 0] - self.x0_m) / self.dx_m, (p[..., 1] - self.y0_m) / self.dy_m], axis=-1)

    def to_metres(self, ij) -> np.ndarray:
        """Fractional grid indices (…×2) → map-frame metres (…×2)."""
        g = np.asarray(ij, float)
        return np.stack([self.x0_m + g[..., 0] * self.dx_m, self.y0_m + g[..., 1] * self.dy_m], axis=-1)

    def inside(self, ij, margin: float = 0.0) -> np.ndarray:
        """True where fractional indices lie inside the grid (bilinear sampling defined)."""
        g = np.asarray(ij, float)
        nx, ny = self.shape
        return (
            (g[..., 0] >= margin) & (g[..., 0] <= nx - 1 - margin) & (g[..., 1] >= margin) & (g[..., 1] <= ny - 1 - margin)
        )

    # ---- sampling ------------------------------------------------------------------------------

    def bilinear(self, gi, gj) -> np.ndarray:
        """Bilinear interpolation at fractional indices (arrays broadcast together).

        H_Q = (1−u)(1−v)H_A1 + u(1−v)H_A2 + (1−u)v H_A3 + uv H_A4 (Liu et al. §3.2), with
        u, v the position inside the cell. Points outside the grid are clamped to its edge;
        callers that care test :meth:`inside` first.
        """
        v = self.values_nt
        nx, ny = v.shape
        gi = np.clip(np.asarray(gi, float), 0.0, nx - 1.0)
        gj = np.clip(np.asarray(gj, float), 0.0, ny - 1.0)
        i0 = np.minimum(np.floor(gi).astype(np.intp), nx - 2)
        j0 = np.minimum(np.floor(gj).astype(np.intp), ny - 2)
        u = gi - i0
        w = gj - j0
        a1 = v[i0, j0]
        a2 = v[i0 + 1, j0]
        a3 = v[i0, j0 + 1]
        a4 = v[i0 + 1, j0 + 1]
        return (1 - u) * (1 - w) * a1 + u * (1 - w) * a2 + (1 - u) * w * a3 + u * w * a4

    def cell_mean(self, gi, gj) -> np.ndarray:
        """Pre-match value of a point inside a cell: the mean of the cell's four corners (Liu et al. §3.1)."""
        v = self.values_nt
        nx, ny = v.shape
        i0 = np.clip(np.floor(np.asarray(gi, float)).astype(np.intp), 0, nx - 2)
        j0 = np.clip(np.floor(np.asarray(gj, float)).astype(np.intp), 0, ny - 2)
        return 0.25 * (v[i0, j0] + v[i0 + 1, j0] + v[i0, j0 + 1] + v[i0 + 1, j0 + 1])

    def sample_m(self, xy_m) -> np.ndarray:
        """Bilinear field at map-frame positions in metres (…×2)."""
        g = self.to_grid(xy_m)
        return self.bilinear(g[..., 0], g[..., 1])

    def cubic(self, gi, gj) -> np.ndarray:
        """Smooth (bicubic spline) field at fractional indices: a 'true' field between the nodes.

        The simulator measures this surface while the matcher interpolates bilinearly, so a match
        also carries the map's own representation error.
        """
        spline = _spline_cache(self)
        nx, ny = self.shape
        gi = np.clip(np.asarray(gi, float), 0.0, nx - 1.0)
        gj = np.clip(np.asarray(gj, float), 0.0, ny - 1.0)
        return spline(gi, gj, grid=False)


def _spline_cache(m: GridMap):
    """The map's bicubic spline, built once and kept on the map itself (it lives and dies with the map)."""
    s = m.__dict__.get("_spline")
    if s is None:
        from scipy.interpolate import RectBivariateSpline

        nx, ny = m.shape
        s = RectBivariateSpline(np.arange(nx), np.arange(ny), m.values_nt, kx=3, ky=3, s=0)
        object.__setattr__(m, "_spline", s)  # a cache, not a field: frozen dataclasses allow it this way
    return s


def core_field_enu_nt(lat_deg: float, lon_deg: float, alt_m: float = 0.0) -> np.ndarray:
    """IGRF main field at a map's reference place, ENU, nT: anomaly = total field − its magnitude.

    Over a map of some ten kilometres the core field is treated as uniform.
    """
    from .maths import earth_field_enu_nt

    return np.array(earth_field_enu_nt(float(lat_deg), float(lon_deg), float(alt_m)))


def synthetic_paper_map(
    seed: int = 7,
    n_cells: int = 150,
    spacing_m: float = 100.0,
    correlation_cells: float = 3.0,
    mean_nt: float = PAPER_MAP_MEAN_NT,
    std_nt: float = PAPER_MAP_STD_NT,
) -> GridMap:
    """A spatially correlated anomaly map with the paper's statistics (deterministic for a seed).

    White Gaussian noise smoothed by a Gaussian kernel of ``correlation_cells`` standard deviation
    (computed on a padded grid so the edges are as rough as the middle), then scaled to exactly
    the requested mean and standard deviation (the paper: 150 × 150 cells of 100 m, mean
    1.8303 nT, std 16.8425 nT).
    """
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    pad = int(np.ceil(4 * correlation_cells)) + 1
    noise = rng.standard_normal((n_cells + 2 * pad, n_cells + 2 * pad))
    field = gaussian_filter(noise, correlation_cells, mode="wrap")[pad:-pad, pad:-pad]
    field = (field - field.mean()) / field.std() * std_nt + mean_nt
    return GridMap(field, 0.0, 0.0, spacing_m, spacing_m, 0.0, f"synthetic:{seed}")


def load_wdmam(path: str | Path) -> GridMap:
    """The MagNav/WDMAM HDF5 layout: ``map`` [x, y] nT, ``xx``/``yy`` node coordinates in m."""
    import h5py

    with h5py.File(path, "r") as f:
        v = np.asarray(f["map"], dtype=float)
        xx = np.asarray(f["xx"], dtype=float).ravel()
        yy = np.asarray(f["yy"], dtype=float).ravel()
        alt = float(np.asarray(f["alt"])) if "alt" in f else 0.0
    return _from_axes(v, xx, yy, alt, Path(path).name)


def _from_axes(v: np.ndarray, xx: np.ndarray, yy: np.ndarray, alt: float, name: str) -> GridMap:
    if v.shape != (xx.size, yy.size):
        raise ValueError(f"map {name!r}: grid shape {v.shape} does not match axes ({xx.size}, {yy.size})")
    dx = np.diff(xx)
    dy = np.diff(yy)
    if not (np.allclose(dx, dx[0], rtol=1e-6) and np.allclose(dy, dy[0], rtol=1e-6)):
        raise ValueError(f"map {name!r}: axes are not regularly spaced")
    return GridMap(v, float(xx[0]), float(yy[0]), float(dx[0]), float(dy[0]), alt, name)


def load_map(spec: str | Path) -> GridMap:
    """Load a map from a file path or ``synthetic[:seed]`` (see module docstring)."""
    s = str(spec)
    if s.startswith("synthetic"):
        _, _, seed = s.partition(":")
        return synthetic_paper_map(int(seed) if seed else 7)
    p = Path(s)
    if not p.is_absolute() and not p.exists():
        from .paths import DATA_DIR

        p = DATA_DIR / p
    if not p.exists():
        raise FileNotFoundError(f"map file {p} does not exist")
    if p.suffix in (".h5", ".hdf5"):
        return load_wdmam(p)
    if p.suffix == ".npz":
        with np.load(p) as z:
            alt = float(z["alt_m"]) if "alt_m" in z else 0.0
            return _from_axes(np.asarray(z["map_nt"], float), np.asarray(z["x_m"], float).ravel(),
                              np.asarray(z["y_m"], float).ravel(), alt, p.name)
    raise ValueError(f"map file {p}: unknown format {p.suffix!r} (expected .npz, .h5, .hdf5 or 'synthetic[:seed]')")
