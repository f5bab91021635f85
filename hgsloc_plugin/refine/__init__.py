"""The heuristic pose search for one query: config, scorer, lattice search and the Refiner."""

from .config import PRESETS, RefineConfig
from .refiner import LevelStats, Refiner, RefineResult

__all__ = ["PRESETS", "LevelStats", "RefineConfig", "RefineResult", "Refiner"]
