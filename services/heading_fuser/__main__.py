from magmesh.runtime import main

from .service import HeadingFuser

if __name__ == "__main__":
    main(HeadingFuser)
