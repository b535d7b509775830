from magmesh.runtime import main

from .publisher import CarPublisher

if __name__ == "__main__":
    main(CarPublisher)
