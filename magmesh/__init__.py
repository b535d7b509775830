"""magmesh: distributed magnetic sensing for navigation over Eclipse Zenoh."""

import os as _os

# Every magmesh process works on small arrays (a sample, a window, a vehicle's batch) and shares the machine's cores
# with the other stages. A multi-threaded BLAS gains nothing on such sizes, and its worker threads spin-wait for
# work: on a busy 2-core machine that starved whole pipelines (a DMC mesh test took > 125 s instead of 14 s with
# two other busy processes beside it). One BLAS / OpenMP thread per process is the default; a user who sets these
# variables keeps theirs. This runs before numpy loads: ``services``, ``sim_publishers`` and ``bench`` import
# this package first.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
