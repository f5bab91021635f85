"""The pose-derivative path, a base class of the renderer: images with their derivatives in the pose increment,
and the cs cost's gradient.

``xi = (w, v)`` is the increment of ``Pose.perturbed_in_camera(w, v)`` (rotation, then camera-frame shift). The
kernels are ``kernels/pose_grad.py`` (per-Gaussian derivative records, derivative blending) and
``kernels/window_grad.py`` (the windowed cs cost's gradient and Gauss-Newton system). :class:`PoseDerivatives`
uses the renderer's own workspaces, geometry pass and batching (``Renderer.workspace``, ``_geometry``,
``_chunks``, ``_query_parts``): it is the renderer's derivative half, kept in a module of its own.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from ..core.backend import current_arch
from ..core.camera import Camera
from ..core.costs import cost_from_window
from ..core.pose import Pose
from ..kernels import window, window_grad
from ..kernels.launch import launcher
from ..kernels.pose_grad import NXI, derivative_images_kernel
from .buffers import DerivativeWorkspace, WindowGradBuffers, read_rows
from .gradient_noise import gradient_noise


def _read_images(g: DerivativeWorkspace, n: int, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first ``n`` poses' colour [n, H, W, 3], alpha [n, H, W] and d colour / d xi [n, H, W, 3, 6] of a
    derivative pass at ``camera``'s size, read back to the host (float32)."""
    return (read_rows(g.rgb, n), read_rows(g.alpha, n),
            read_rows(g.drgb, n).reshape(n, camera.height, camera.width, 3, NXI))


class PoseDerivatives:
    """The renderer's pose-derivative methods (``Renderer`` inherits them); ``self`` is the renderer."""

    @property
    def grad_chunk(self) -> int:
        """Poses per derivative launch (the per-Gaussian derivative records take 30 floats per pose): at most 4
        on the CPU, 32 on CUDA (the derivative passes of a lockstep batch in one launch); a pose's numbers do not
        depend on the others of its launch."""
        return max(1, min(32 if current_arch() == "cuda" else 4, 4_000_000 // self.n))

    def derivative_workspace(self, camera: Camera, batch: int) -> DerivativeWorkspace:
        """The derivative pass's image-sized buffers at ``camera``'s size (grown when ``batch`` needs more), with the
        pool's derivative records sized for it."""
        key = (camera.width, camera.height)
        ws = self.pool.derivative_workspaces.get(key)
        if ws is None or ws.batch < batch:
            batch = max(batch, ws.batch if ws is not None else 0)
            ws = DerivativeWorkspace.allocate(batch, camera.height, camera.width)
            self.pool.derivative_workspaces[key] = ws
        self.pool.derivative_records_for(ws.batch, self.n)
        return ws


    def derivative_images(self, cams: list[Camera], part: list[Pose], background) -> DerivativeWorkspace:
        """Geometry, derivative records and derivative blending of up to ``self.grad_chunk`` poses (a camera each, one
        image size); the images stay on the device (``rgb``, ``alpha``, ``drgb`` of the returned workspace)."""
        camera = cams[0]
        ws = self.workspace(camera, len(part), grad=True)
        self._geometry(cams, part, ws, background)
        g = self.derivative_workspace(camera, min(self.grad_chunk, len(part)))
        rec, drec, gs = self.pool.records, self.pool.derivative_records, self.gaussians
        n = len(part)
        # the blend layout of the renders (RasterConfig.blend): one task per tile on the CPU, per pixel on CUDA, where
        # each pixel may skip the Gaussians of its tile's list that cannot reach it on one bit of their pixel mask
        tx, ty = ws.tiles
        masks = self.pool.pixel_masks() if self.grad_masks else self.pool.placeholder(ti.u64)
        launcher(derivative_images_kernel(self.config, self.blend_mode == "splat", self.grad_masks))(
            gs.means, gs.cov3d, ws.viewmats, ws.cams, camera.width, camera.height, n, rec.ntiles, drec.dpacked,
            rec.packed, ws.tile_start, self.pool.lists.isect, ws.isect_base, masks, ws.background, tx, ty, g.rgb,
            g.alpha, g.drgb)
        return g


    def render_derivatives(self, camera, poses: list[Pose], background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W] and d colour / d xi [B, H, W, 3, 6] of each pose (float32);
        ``camera``: one, or one per pose (one image size)."""
        rgbs, alphas, ders = [], [], []
        for cams, part in self._chunks(camera, poses, self.grad_chunk):
            g = self.derivative_images(cams, part, background)
            n = len(part)
            camera = cams[0]
            rgb, alpha, der = _read_images(g, n, camera)
            rgbs.append(rgb)
            alphas.append(alpha)
            ders.append(der)
        return np.concatenate(rgbs), np.concatenate(alphas), np.concatenate(ders)


    def cs_gradient(self, camera, poses: list[Pose], qstats, background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0,
                    query_index=None):
        """cs cost [B], its gradient [B, 6] and Gauss-Newton Hessian [B, 6, 6] in ``xi`` (float64) of each pose
        against the query statistics ``qstats`` [Q, H, W, 3, window.NQ] at slot ``query_index`` [B] (None: 0)."""
        costs, grads, hessians = [], [], []
        iu = np.triu_indices(NXI)
        for cams, part, qi in self._query_parts(camera, poses, query_index, self.grad_chunk):
            g = self.derivative_images(cams, part, background)
            n = len(part)
            if g.window is None:
                g.window = WindowGradBuffers.allocate(*g.alpha.shape)
            w = g.window
            out = np.empty((n, window_grad.ROW_SYS + window_grad.NSYS), np.float64)
            launcher(window_grad.cs_system_kernel())(g.rgb, g.alpha, g.drgb, qstats, qi, float(mask_alpha), n, w.h,
                                                     w.wts, w.means, w.tmpj, w.jbar, w.tmpw, w.hat, w.rows, out)
            sums, sys = out[:, :window_grad.ROW_SYS], out[:, window_grad.ROW_SYS:]
            scale = 2.0 / (3.0 * np.maximum(sums[:, 1], 1.0))
            hess = np.zeros((n, NXI, NXI))
            hess[:, iu[0], iu[1]] = sys[:, :window_grad.NH]
            hess = hess + np.triu(hess, 1).transpose(0, 2, 1)
            costs.append(cost_from_window(sums))
            grads.append(sys[:, window_grad.NH:] * scale[:, None])
            hessians.append(hess * scale[:, None, None])
        return np.concatenate(costs), np.concatenate(grads), np.concatenate(hessians)


    def pose_gradient_noise(self, camera: Camera, pose: Pose, qstats, background=(0.0, 0.0, 0.0),
                            mask_alpha: float = 0.0, bands: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cs cost's Gauss-Newton Hessian [6, 6] at ``pose``, its gradient split by image rows into ``bands``
        horizontal bands of (nearly) equal height [bands, 6] (the bands sum to the whole gradient) and the
        gradient's covariance [6, 6] under independent noise in the query's pixels (``render/gradient_noise.py``),
        float64, from one derivative pass against the query statistics ``qstats`` [Q, H, W, 3, window.NQ] (slot 0):
        what the pose's two covariances need (``refine/uncertainty.py``)."""
        if len(qstats.shape) != 5 or tuple(qstats.shape[1:3]) != (camera.height, camera.width):
            raise ValueError(f"query statistics are {tuple(qstats.shape)}, camera needs (Q, {camera.height}, "
                             f"{camera.width}, 3, {window.NQ})")
        iu = np.triu_indices(NXI)
        (cams, part, qi), = self._query_parts(camera, [pose], None, 1)
        g = self.derivative_images(cams, part, background)
        if g.window is None:
            g.window = WindowGradBuffers.allocate(*g.alpha.shape)
        w = g.window
        out = np.empty((1, window_grad.ROW_SYS + window_grad.NSYS), np.float64)
        launcher(window_grad.cs_system_kernel())(g.rgb, g.alpha, g.drgb, qstats, qi, float(mask_alpha), 1, w.h,
                                                 w.wts, w.means, w.tmpj, w.jbar, w.tmpw, w.hat, w.rows, out)
        sums, sys = out[0, :window_grad.ROW_SYS], out[0, window_grad.ROW_SYS:]
        scale = 2.0 / (3.0 * max(float(sums[1]), 1.0))
        hess = np.zeros((NXI, NXI))
        hess[iu] = sys[:window_grad.NH]
        hess = (hess + np.triu(hess, 1).T) * scale
        rows = w.rows.to_numpy()[0, :camera.height, 0, window_grad.ROW_SYS + window_grad.NH:].astype(np.float64)
        rgb, alpha, der = _read_images(g, 1, camera)
        noise = gradient_noise(rgb[0], alpha[0], der[0], read_rows(qstats, 1)[0], mask_alpha)
        return hess, np.array([b.sum(0) for b in np.array_split(rows, bands)]) * scale, noise
