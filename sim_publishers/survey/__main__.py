from magmesh.runtime import main

from .publisher import SurveyPublisher

if __name__ == "__main__":
    main(SurveyPublisher)
