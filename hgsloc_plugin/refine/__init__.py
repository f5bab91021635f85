"""Refinement of one query: settings (``config``), plan, routes (``routes``: gradient, search), the acceptance
rule (``trust``), the result, and the :class:`Refiner` that runs them in that order."""

from .config import PRESETS, RefineConfig, Tuning
from .refiner import PER_QUERY, Refiner
from .result import LevelStats, RefineResult

__all__ = ["PER_QUERY", "PRESETS", "LevelStats", "RefineConfig", "RefineResult", "Refiner", "Tuning"]
