"""The implementations of the ``heading_fuser`` role, by name.

``ekf``   the project's error-state quaternion EKF with DMC switching (core.py; the default)
``vqf``   VQF (Laidig & Seel 2023, the ``vqf`` package) online with its defaults (vqf_impl.py)

Both consume the same keys and publish the same ``heading`` contract, so ``magmesh swap heading_fuser
vqf`` changes one for the other in a running mesh.
"""

from __future__ import annotations

from magmesh import runtime

from .service import HeadingFuser
from .vqf_impl import VqfHeadingFuser

IMPLEMENTATIONS = {"ekf": HeadingFuser, "vqf": VqfHeadingFuser}
DEFAULT_IMPL = "ekf"


def pop_impl_arg(argv: list[str]) -> tuple[str, list[str]]:
    """Take ``--impl NAME`` / ``--impl=NAME`` out of argv; an unknown name exits with the known ones."""
    return runtime.pop_impl_arg(argv, "heading_fuser", IMPLEMENTATIONS, DEFAULT_IMPL)
