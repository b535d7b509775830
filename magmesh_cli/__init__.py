"""magmesh's operator app: the ``magmesh`` command (``cli`` and ``commands``), the mesh supervisor (``magmesh up``),
live swaps, recording and replay, reports, and the bridges to Foxglove, ROS 2 and the Zenoh tools.

It is built on the runtime library :mod:`magmesh` (services, frames, journals, the shared maths) and may import
it, the services and the evaluations; the library never imports the app.
"""

import magmesh  # noqa: F401 - first: one BLAS/OpenMP/numba thread per process unless the user set otherwise
