"""Heuristics: image cost of rendered candidate poses against the query, batched."""

from __future__ import annotations

import numpy as np
import torch

from ..camera import Camera
from ..costs import cost_from_stats
from ..image import resize_image
from ..pose import Pose
from ..render import Renderer


class Scorer:
    """Scores batches of poses against one query image at one resolution; owns that image.

    Fused metrics (sad, psnr, ncc, affine) run in the blending kernel against the query uploaded once per
    resolution; "ssim" renders images and uses kornia.
    """

    def __init__(self, renderer: Renderer, metric: str, background, mask_alpha: float):
        self.renderer = renderer
        self.metric = metric
        self.background = tuple(background)
        self.mask_alpha = float(mask_alpha)
        self.camera: Camera | None = None
        self.renders = 0
        self._cache: dict[bytes, float] = {}  # costs at the current query resolution, keyed by exact pose

    def set_query(self, camera: Camera, image_full: np.ndarray) -> None:
        """Prepare the query [H, W, 3] at ``camera``'s (scoring) size."""
        self.camera = camera
        self._cache = {}
        self.query = resize_image(image_full, camera.width, camera.height)
        if self.metric == "ssim":
            self._q = torch.from_numpy(self.query).permute(2, 0, 1)[None]
        else:
            self._target = self.renderer.upload_image(self.query)

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
        if self.metric == "ssim":
            import kornia

            rgb, alpha, _ = self.renderer.render_full(cam, poses, self.background)
            r = torch.from_numpy(rgb).permute(0, 3, 1, 2)
            q = self._q.expand(len(poses), -1, -1, -1)
            s = kornia.metrics.ssim(r, q, window_size=11)  # [B, 3, H, W]
            if self.mask_alpha > 0:
                m = torch.from_numpy(alpha >= self.mask_alpha)[:, None].float()
                return (1.0 - (s * m).sum((1, 2, 3)) / (3 * m.sum((1, 2, 3)).clamp(min=1))).double().numpy()
            return (1.0 - s.mean((1, 2, 3))).double().numpy()
        stats = self.renderer.cost_stats(cam, poses, self._target, self.background, self.mask_alpha)
        return cost_from_stats(stats, self.metric, cam.width * cam.height)
