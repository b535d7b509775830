from magmesh.runtime import main

from .publisher import MultirotorPublisher

if __name__ == "__main__":
    main(MultirotorPublisher)
