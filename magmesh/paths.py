"""Where the repository's bundled files live (data, manifests, trained models)."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DATA_DIR = REPO / "data"
DEPLOY_DIR = REPO / "deploy"
MODELS_DIR = REPO / "models"


def state_dir() -> Path:
    """Directory for persisted service state (calibration parameters, filter state).

    ``MAGMESH_STATE_DIR`` overrides the default ``~/.local/state/magmesh``.
    """
    d = Path(os.environ.get("MAGMESH_STATE_DIR", Path.home() / ".local" / "state" / "magmesh"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def write_atomic(path: Path, text: str) -> None:
    """Replace the file ``path`` with ``text`` atomically: written to a temporary file beside it (``path`` with the
    suffix ``.tmp``), then renamed over it (``os.replace``), so a crash never leaves half a file. One writer per file
    at a time (the temporary file is shared)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
