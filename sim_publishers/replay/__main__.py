from magmesh.runtime import main

from .publisher import ReplayPublisher

if __name__ == "__main__":
    main(ReplayPublisher)
