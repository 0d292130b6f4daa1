"""VL-Map: language as a calibrated sensor for robots."""

__version__ = "0.1.0"
