"""A figure check that fails on an empty or blank picture (not just on a missing file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def assert_figure_drawn(png: Path, min_ink: float = 0.015, min_colours: int = 20) -> None:
    """``png`` is a PNG of a real plot: big enough, with ink on it and more than a few colours."""
    import matplotlib.image as mpimg

    assert png.exists(), f"{png.name} was not written"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{png.name} is not a PNG"
    img = mpimg.imread(png)[..., :3]
    ink = float(np.mean(np.any(img < 0.9, axis=-1)))  # share of pixels that are not (near) white
    q = (img * 15).astype(np.int64).reshape(-1, 3)
    colours = len(np.unique(q[:, 0] * 256 + q[:, 1] * 16 + q[:, 2]))
    assert img.shape[0] > 150 and img.shape[1] > 500, f"{png.name} is only {img.shape[1]}×{img.shape[0]} px"
    assert ink > min_ink and colours > min_colours, f"{png.name} looks empty (ink {ink:.3f}, {colours} colours)"
