from magmesh.runtime import main

from .service import Calibration

if __name__ == "__main__":
    main(Calibration)
