"""A second rendering backend: ``RendererLike`` on the PyTorch reference (``render_torch.py``), for the seam tests.

Every image is a float64 reference render; the pose derivatives are central differences of it (step ``h`` in the
increment ``xi = (w, v)`` of ``Pose.perturbed_in_camera``); the windowed cs cost, its gradient and its Gauss-Newton
Hessian come by autograd through the reference window, as ``tests/test_pose_grad.py`` checks the kernels against.
It batches nothing (not a ``BatchingRenderer``) and selects nothing (its working set is itself). Slow: a few
hundred Gaussians at 64-96 px. Picklable (it holds the scene), so it travels to Ray workers.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import torch

from hgsloc_plugin.kernels import RasterConfig
from hgsloc_plugin.kernels.layout import Stat

from .render_torch import cs_gradient_noise, cs_system, render_reference, window_cost


def _cameras(camera, n: int) -> list:
    return list(camera) if isinstance(camera, (list, tuple)) else [camera] * n


class TorchRenderer:
    """``RendererLike`` of ``scene`` on the PyTorch reference (see the module docstring); ``calls`` counts each
    method's calls."""

    selections = 0

    def __init__(self, scene, config: RasterConfig | None = None, h: float = 1e-6):
        self.scene, self.config, self.h = scene, config or RasterConfig(), float(h)
        self.calls: Counter = Counter()

    # ---- RendererLike: the Gaussians ----

    @property
    def n(self) -> int:
        return self.scene.num_gaussians

    @property
    def full(self) -> TorchRenderer:
        return self

    @property
    def largest(self) -> int:
        return self.n

    def working_set(self, cameras, pose, max_shift, max_rotation_deg) -> TorchRenderer:
        return self

    # ---- images ----

    def _image(self, camera, pose, background) -> tuple[np.ndarray, np.ndarray]:
        return render_reference(self.scene, camera, pose, tuple(background), dtype=torch.float64)

    def upload_image(self, image: np.ndarray) -> np.ndarray:
        return np.asarray(image, np.float64)

    def upload_window_query(self, image: np.ndarray) -> np.ndarray:
        return np.asarray(image, np.float64)[None]  # one query slot

    @staticmethod
    def stack_window_queries(stats, out=None, slots=None) -> np.ndarray:
        return np.concatenate(list(stats))

    def render_full(self, camera, poses, background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W] and a zero depth [B, H, W] (the reference blends no depth)."""
        self.calls["render_full"] += 1
        out = [self._image(c, p, background) for c, p in zip(_cameras(camera, len(poses)), poses)]
        rgb = np.stack([o[0] for o in out]).astype(np.float32)
        alpha = np.stack([o[1] for o in out]).astype(np.float32)
        return rgb, alpha, np.zeros_like(alpha)

    # ---- costs ----

    def cost_stats(self, camera, poses, target, background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0):
        """``Stat`` sums [B, Stat.SIZE] of each rendering against ``target`` over its valid pixels."""
        self.calls["cost_stats"] += 1
        out = np.zeros((len(poses), Stat.SIZE))
        for b, (c, p) in enumerate(zip(_cameras(camera, len(poses)), poses)):
            r, a = self._image(c, p, background)
            valid = a >= mask_alpha
            rv, qv = r[valid], np.asarray(target, np.float64)[valid]
            out[b, Stat.N] = valid.sum()
            out[b, Stat.SAD] = np.abs(rv - qv).sum()
            out[b, Stat.SSD] = ((rv - qv) ** 2).sum()
            for ch in range(3):
                x, y = rv[:, ch], qv[:, ch]
                for field, v in ((Stat.SR, x.sum()), (Stat.SQ, y.sum()), (Stat.SRR, (x * x).sum()),
                                 (Stat.SQQ, (y * y).sum()), (Stat.SRQ, (x * y).sum())):
                    out[b, Stat.at(ch, field)] = v
        return out

    def window_cost(self, camera, poses, qstats, background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0,
                    luminance: bool = False, query_index=None) -> np.ndarray:
        """[B, 2]: the sum of the channel-mean cs (or SSIM) over valid pixels, and their count."""
        self.calls["window_cost"] += 1
        qi = np.zeros(len(poses), int) if query_index is None else np.asarray(query_index)
        out = np.zeros((len(poses), 2))
        for b, (c, p) in enumerate(zip(_cameras(camera, len(poses)), poses)):
            r, a = self._image(c, p, background)
            out[b] = window_cost(r, a, qstats[qi[b]], mask_alpha, luminance)
        return out

    # ---- pose derivatives ----

    def _derivatives(self, camera, pose, background) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rgb [H, W, 3], alpha [H, W] and d rgb / d xi [H, W, 3, 6] by central differences at ``h`` and ``2 h``:
        where they disagree a Gaussian crossed a cut-off (the alpha threshold, a tile's edge) within the step,
        and the derivative there is 0, as the kernels' analytic one ignores such jumps."""
        r, a = self._image(camera, pose, background)
        J = np.empty(r.shape + (6,))
        for k in range(6):
            fd = []
            for step in (self.h, 2 * self.h):
                xi = np.zeros(6)
                xi[k] = step
                plus = self._image(camera, pose.perturbed_in_camera(xi[:3], xi[3:]), background)[0]
                minus = self._image(camera, pose.perturbed_in_camera(-xi[:3], -xi[3:]), background)[0]
                fd.append((plus - minus) / (2 * step))
            jump = np.abs(fd[0] - fd[1]) > 0.05 * np.abs(fd[0]) + 1e-3
            J[..., k] = np.where(jump, 0.0, fd[0])
        return r, a, J

    def _cs_system(self, camera, pose, query, background, mask_alpha):
        """cs cost, per-pixel gradient contributions [H, W, 6] and the Gauss-Newton Hessian [6, 6] at ``pose``."""
        r, a, J = self._derivatives(camera, pose, background)
        cost, per_pixel, H = cs_system(r, query, J, a >= mask_alpha)
        return cost, per_pixel, 0.5 * (H + H.T)

    def pose_gradient(self, camera, poses, qstats, background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0,
                      query_index=None):
        """cs cost [B], gradient [B, 6] and Gauss-Newton Hessian [B, 6, 6] in ``xi`` (float64)."""
        self.calls["pose_gradient"] += 1
        qi = np.zeros(len(poses), int) if query_index is None else np.asarray(query_index)
        costs, grads, hessians = [], [], []
        for b, (c, p) in enumerate(zip(_cameras(camera, len(poses)), poses)):
            cost, per_pixel, H = self._cs_system(c, p, qstats[qi[b]], background, mask_alpha)
            costs.append(cost)
            grads.append(per_pixel.sum(axis=(0, 1)))
            hessians.append(H)
        return np.array(costs), np.array(grads), np.array(hessians)

    def pose_gradient_noise(self, camera, pose, qstats, background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0,
                            bands: int = 12):
        """The Gauss-Newton Hessian [6, 6], the gradient per horizontal band of rows [bands, 6] and the gradient's
        covariance [6, 6] under independent pixel noise of the query (``render_torch.cs_gradient_noise``)."""
        self.calls["pose_gradient_noise"] += 1
        r, a, J = self._derivatives(camera, pose, background)
        _, per_pixel, H = cs_system(r, qstats[0], J, a >= mask_alpha)
        rows = per_pixel.sum(axis=1)
        return (0.5 * (H + H.T), np.array([band.sum(0) for band in np.array_split(rows, bands)]),
                cs_gradient_noise(r, qstats[0], J, a >= mask_alpha))
