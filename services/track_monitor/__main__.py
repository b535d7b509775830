from magmesh.runtime import main

from .service import TrackMonitorService

if __name__ == "__main__":
    main(TrackMonitorService)
