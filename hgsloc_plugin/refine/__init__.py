"""The heuristic pose search for one query: config, scorer, lattice search and the Refiner."""

from .config import PRESETS, RefineConfig
from .refiner import PER_QUERY, LevelStats, Refiner, RefineResult

__all__ = ["PER_QUERY", "PRESETS", "LevelStats", "RefineConfig", "RefineResult", "Refiner"]
