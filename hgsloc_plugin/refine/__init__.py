"""The heuristic pose search: config, scorer, lattice search and the HGSLocPlugin API."""

from .config import PRESETS, RefineConfig
from .plugin import HGSLocPlugin, LevelStats, RefineResult

__all__ = ["PRESETS", "HGSLocPlugin", "LevelStats", "RefineConfig", "RefineResult"]
