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
