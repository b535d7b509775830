"""magmesh: distributed magnetic sensing for navigation over Eclipse Zenoh."""

__version__ = "0.1.0"
