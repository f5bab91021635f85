"""The Taichi 3DGS renderer.

- ``api``: ``render``, ``render_full``, ``render_cost`` and the per-scene renderer cache (``get_renderer``);
- ``renderer``: :class:`Renderer`, a scene resident on the device (projection, tile sort, blending, costs);
- ``derivatives``: the pose-derivative path (images' derivatives, the cs cost's gradient and Hessian);
- ``buffers``: the device buffers as typed records, and their pool;
- ``prepare``: host-side preparation (covariances, Morton order, pose lists);
- ``protocol``: :class:`RendererLike`, what the refinement needs of a renderer; :class:`BatchingRenderer`, what
  lockstep batching needs besides.
"""

from .api import get_renderer, render, render_cost, render_full
from .buffers import read_rows, sort_mode
from .prepare import as_pose_list, covariances_3d, morton_order
from .protocol import BatchingRenderer, RendererLike
from .renderer import Renderer

__all__ = ["BatchingRenderer", "Renderer", "RendererLike", "as_pose_list", "covariances_3d", "get_renderer",
           "morton_order", "read_rows", "render", "render_cost", "render_full", "sort_mode"]
