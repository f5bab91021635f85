"""hgsloc_plugin: heuristic 3DGS camera-pose refinement (HGSLoc-style), fast and drop-in.

Conventions: poses are world-to-camera (COLMAP ``cam_from_world``), quaternions w, x, y, z, OpenCV axes.
Importing the package loads Taichi but does not start it (``init`` or the first render does); Taichi's banner
is kept off stdout so that machine-readable output stays pure.
"""

import os

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

from .core.backend import current_arch, init  # noqa: E402
from .core.camera import Camera  # noqa: E402
from .core.pose import Pose  # noqa: E402
from .core.prior import QueryPrior  # noqa: E402
from .core.scene import GaussianScene  # noqa: E402
from .kernels import RasterConfig  # noqa: E402
from .refine import RefineConfig, RefineResult, Tuning  # noqa: E402
from .render import Renderer, render, render_cost, render_full  # noqa: E402
from .run.plugin import HGSLocPlugin  # noqa: E402

__all__ = [
    "Camera",
    "GaussianScene",
    "HGSLocPlugin",
    "Pose",
    "QueryPrior",
    "RasterConfig",
    "RefineConfig",
    "RefineResult",
    "Renderer",
    "Tuning",
    "current_arch",
    "init",
    "render",
    "render_cost",
    "render_full",
]
__version__ = "0.1.0"
