from magmesh.runtime import main

from .service import GeomagMatcherService

if __name__ == "__main__":
    main(GeomagMatcherService)
