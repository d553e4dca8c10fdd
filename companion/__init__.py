"""companion: monocular terrain mapping and terrain avoidance on a drone's companion computer."""

__version__ = "0.1.0"
