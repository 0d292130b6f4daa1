"""VL-Map: language as a calibrated sensor for robots.

A namespace of rooms, one package each (`api`, `sessions`, `stores`, `belief`, `grounding`, `lsm`, ...):
import from the rooms, each of which states its public API in its own `__init__`. Only the version is
defined here.
"""

__all__ = ["__version__"]

__version__ = "0.1.0"
