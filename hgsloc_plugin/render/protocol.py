"""What the refinement needs of a renderer (:class:`RendererLike`), and what lockstep batching needs besides
(:class:`BatchingRenderer`): the seam a second backend plugs into."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from ..core.camera import Camera
from ..core.pose import Pose
from ..kernels import RasterConfig


@runtime_checkable
class RendererLike(Protocol):
    """A scene's Gaussians, rendered and scored in batches of world-to-camera poses.

    Implemented by :class:`~hgsloc_plugin.render.Renderer` and :class:`~hgsloc_plugin.render.working_set.WorkingSet`,
    and by the PyTorch reference in the tests (``tests/reference/backend.py``, a second backend that refines through
    ``refine``, ``refine_many`` and Ray workers); the scorer, the polish, the working set, the level of detail and
    ``hgsloc check`` use only these.
    """

    config: RasterConfig

    @property
    def n(self) -> int:
        """Gaussians rendered."""

    @property
    def full(self) -> RendererLike:
        """The renderer of the whole map this one renders from: itself, or the map under a selection that follows
        the poses asked for (a working set)."""

    @property
    def largest(self) -> int:
        """The most Gaussians one render used so far (a working set's largest selection; else ``n``)."""

    @property
    def selections(self) -> int:
        """Selections of Gaussians made so far (a working set's; 0 for a renderer of fixed Gaussians)."""

    def upload_image(self, image: np.ndarray) -> object:
        """A comparison image [H, W, 3] float in [0, 1] on the device (for :meth:`cost_stats`)."""

    def upload_window_query(self, image: np.ndarray) -> object:
        """A query's windowed statistics on the device (for :meth:`window_cost`, :meth:`pose_gradient`)."""

    def render_full(self, camera: Camera, poses: list[Pose], background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W], accumulated depth [B, H, W] (float32)."""

    def cost_stats(self, camera: Camera, poses: list[Pose], target, background=(0.0, 0.0, 0.0),
                   mask_alpha: float = 0.0) -> np.ndarray:
        """Photometric statistics [B, Stat.SIZE] float64 of each rendering against ``target``."""

    def window_cost(self, camera: Camera, poses: list[Pose], qstats, background=(0.0, 0.0, 0.0),
                    mask_alpha: float = 0.0, luminance: bool = False, query_index=None) -> np.ndarray:
        """[B, 2] float64: sum of the windowed similarity over valid pixels, and their count; pose ``b`` against
        query slot ``query_index[b]`` of ``qstats`` (default 0)."""

    def pose_gradient(self, camera: Camera, poses: list[Pose], qstats, background=(0.0, 0.0, 0.0),
                      mask_alpha: float = 0.0, query_index=None):
        """cs cost [B], gradient [B, 6], Gauss-Newton Hessian [B, 6, 6] in ``xi = (w, v)`` (float64)."""

    def pose_gradient_noise(self, camera: Camera, pose: Pose, qstats, background=(0.0, 0.0, 0.0),
                            mask_alpha: float = 0.0, bands: int = 12):
        """cs Gauss-Newton Hessian [6, 6] at ``pose``, the gradient per horizontal band of rows [bands, 6] and the
        gradient's covariance [6, 6] under independent noise in the query's pixels (``render/gradient_noise.py``)."""

    def working_set(self, cameras: Sequence[Camera], pose: Pose, max_shift: float,
                    max_rotation_deg: float) -> RendererLike:
        """A renderer of the Gaussians some pose within the region around ``pose`` can see (same images)."""


@runtime_checkable
class BatchingRenderer(RendererLike, Protocol):
    """A renderer whose ``window_cost`` and ``pose_gradient`` calls from several queries go into one launch
    (``run/lockstep.py``): calls on renderers of one ``root`` are grouped; ``union`` gives the renderer of their
    Gaussians together; ``stack_window_queries`` puts the queries' statistics side by side, and each pose names
    its query's slot (``query_index``). A renderer without these runs each query's calls alone (the same poses,
    no shared launches). Implemented by :class:`~hgsloc_plugin.render.Renderer`.
    """

    @property
    def root(self) -> BatchingRenderer:
        """The renderer this one's Gaussians were selected from (itself when it is not a selection)."""

    def union(self, renderers: Sequence[BatchingRenderer]) -> BatchingRenderer:
        """A renderer of the union of ``renderers``' Gaussians (all selections of this one), rendering each pose
        as each of them does."""

    @staticmethod
    def stack_window_queries(stats: Sequence[object], out: object | None = None, slots=None) -> object:
        """Query statistics of one size stacked on the device, query ``k`` in slot ``slots[k]`` (default ``k``) of
        ``out`` (default: a new array of ``len(stats)`` slots); returns ``out``."""
