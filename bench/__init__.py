"""bench: importing magmesh first sets its process defaults (one BLAS thread) before numpy loads."""

import magmesh  # noqa: F401
