"""Taichi kernels of the 3DGS renderer: projection, tile sort and alpha blending.

Each module holds a cached factory that returns compiled ``@ti.kernel``s for a given ``RasterConfig``
(and SH degree). Kernels take ``ti.types.ndarray`` arguments, so array shapes never cause a recompile;
``launch.py`` launches them with Taichi's per-call argument checks made once per argument signature.
The Python entry points live in ``hgsloc_plugin.render``; the independent references live in ``tests/reference``.
"""

from .config import RasterConfig

__all__ = ["RasterConfig"]
