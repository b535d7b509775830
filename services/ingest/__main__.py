from magmesh.runtime import main

from .service import Ingest

if __name__ == "__main__":
    main(Ingest)
