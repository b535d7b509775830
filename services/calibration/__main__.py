import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small matrices on a shared machine: threads only spin

from magmesh.runtime import main  # noqa: E402

from .service import Calibration  # noqa: E402

if __name__ == "__main__":
    main(Calibration)
