"""Heuristics: image cost of rendered candidate poses against the query, batched."""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera
from ..core.costs import METRICS, cost_from_stats, cost_from_window
from ..core.image import resize_image
from ..core.pose import Pose
from ..render import RendererLike


class Scorer:
    """Scores batches of poses against one query image at one resolution; owns that image.

    Pixel metrics (sad, psnr, ncc, affine) run in the blending kernel against the query uploaded once per
    resolution; window metrics (cs, ssim) in a follow-up kernel on the rendered images, which stay on the device.
    The window metrics' query statistics are made once per image and size (:meth:`window_query`).
    """

    def __init__(self, renderer: RendererLike, metric: str, background, mask_alpha: float):
        self.renderer = renderer
        self.metric = metric
        self.background = tuple(background)
        self.mask_alpha = float(mask_alpha)
        self.camera: Camera | None = None
        self.renders = 0
        self._cache: dict[bytes, float] = {}  # costs at the current query resolution, keyed by exact pose
        self._image: np.ndarray | None = None  # the full-size query the statistics below are of (held: no id reuse)
        self._windows: dict[tuple[int, int], tuple[np.ndarray, object]] = {}  # (w, h) -> (resized, statistics)

    def set_query(self, camera: Camera, image_full: np.ndarray, renderer=None) -> None:
        """Prepare the query [H, W, 3] at ``camera``'s (scoring) size; ``renderer``: render with it from now on
        (e.g. a coarse level of detail; the cache is per resolution and renderer)."""
        if renderer is not None:
            self.renderer = renderer
        self.camera = camera
        self._cache = {}
        if METRICS[self.metric].windowed:
            self._target = self.window_query(camera, image_full)
            self.query = self._windows[camera.width, camera.height][0]
        else:
            self.query = resize_image(image_full, camera.width, camera.height)
            self._target = self.renderer.upload_image(self.query)

    def window_query(self, camera: Camera, image_full: np.ndarray):
        """The window statistics (``upload_window_query``) of ``image_full`` [H, W, 3] resized to ``camera``'s size,
        made on the first call per image and size (the polish and the rule of one query share them). An image is
        the same array object: one changed in place between calls is not noticed."""
        if image_full is not self._image:
            self._image, self._windows = image_full, {}
        key = (camera.width, camera.height)
        if key not in self._windows:
            small = resize_image(image_full, camera.width, camera.height)
            self._windows[key] = (small, self.renderer.upload_window_query(small))
        return self._windows[key][1]

    def remember(self, pose: Pose, cost: float, metric: str) -> None:
        """Record ``pose``'s ``cost`` under ``metric``, computed elsewhere from a plain render at this scorer's size,
        renderer, query image and settings (the polish's line search): it is not rendered again. Ignored when
        ``metric`` is not the scorer's."""
        if metric == self.metric:
            self._cache.setdefault(pose.as_array().tobytes(), float(cost))

    def gradient_noise(self, pose: Pose, bands: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cs cost's Gauss-Newton Hessian [6, 6] at ``pose``, its gradient per horizontal band of rows
        [bands, 6] and the gradient's covariance [6, 6] under independent pixel noise, at this scorer's size, query
        and renderer (one derivative pass; the metric must be cs)."""
        if self.metric != "cs":
            raise ValueError(f"the gradient's noise is the cs cost's, the scorer's metric is {self.metric}")
        return self.renderer.pose_gradient_noise(self.camera, pose, self._target, self.background, self.mask_alpha,
                                                 bands)

    def __call__(self, poses: list[Pose]) -> np.ndarray:
        """Costs [B] (float64) of the poses; lower is better. A pose already scored at this resolution
        (bit-identical, e.g. a coarse level's node met again by a finer lattice) is not rendered again."""
        keys = [p.as_array().tobytes() for p in poses]
        todo = [k for k in dict.fromkeys(keys) if k not in self._cache]
        if todo:
            by_key = dict(zip(keys, poses))
            costs = self._score([by_key[k] for k in todo])
            self._cache.update(zip(todo, (float(c) for c in costs)))
        return np.array([self._cache[k] for k in keys], dtype=np.float64)

    def _score(self, poses: list[Pose]) -> np.ndarray:
        if not poses:
            return np.zeros(0)
        self.renders += len(poses)
        cam = self.camera
        if METRICS[self.metric].windowed:
            sums = self.renderer.window_cost(cam, poses, self._target, self.background, self.mask_alpha,
                                             luminance=self.metric == "ssim")
            return cost_from_window(sums)
        stats = self.renderer.cost_stats(cam, poses, self._target, self.background, self.mask_alpha)
        return cost_from_stats(stats, self.metric, cam.width * cam.height)
