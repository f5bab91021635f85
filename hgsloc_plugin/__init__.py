"""hgsloc_plugin: heuristic 3DGS camera-pose refinement (HGSLoc-style), fast and drop-in.

Conventions: poses are world-to-camera (COLMAP ``cam_from_world``), quaternions w, x, y, z, OpenCV axes.
"""

from .backend import current_arch, init
from .camera import Camera
from .kernels import RasterConfig
from .pose import Pose
from .refine import HGSLocPlugin, RefineConfig, RefineResult
from .render import Renderer, render, render_cost, render_full
from .scene import GaussianScene

__all__ = [
    "Camera",
    "GaussianScene",
    "HGSLocPlugin",
    "Pose",
    "RasterConfig",
    "RefineConfig",
    "RefineResult",
    "Renderer",
    "current_arch",
    "init",
    "render",
    "render_cost",
    "render_full",
]
__version__ = "0.1.0"
