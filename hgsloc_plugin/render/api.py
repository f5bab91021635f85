"""The functional API: ``render``, ``render_full``, ``render_cost`` on a scene, through a per-scene renderer cache."""

from __future__ import annotations

import weakref

import numpy as np

from ..core.camera import Camera
from ..core.costs import cost_from_stats
from ..core.scene import GaussianScene
from ..kernels import RasterConfig
from .prepare import as_pose_list
from .renderer import Renderer

_RENDERERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def get_renderer(scene: GaussianScene, config: RasterConfig | None = None) -> Renderer:
    """The cached :class:`Renderer` of a scene (one per scene object and config; released with the scene)."""
    config = config or RasterConfig()
    per_scene = _RENDERERS.setdefault(scene, {})
    r = per_scene.get(config)
    if r is None:
        r = per_scene[config] = Renderer(scene, config)
    return r


def _check(scene, camera):
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"scene must be a GaussianScene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")


def render(scene: GaussianScene, camera: Camera, poses, background=(0.0, 0.0, 0.0), *,
           config: RasterConfig | None = None) -> np.ndarray:
    """Render colour images.

    Args:
        scene: the Gaussians. camera: pinhole intrinsics and size.
        poses: one world-to-camera :class:`Pose` or a list of them.
        background: RGB added with the remaining transmittance.

    Returns:
        float32 [H, W, 3] in [0, 1] for one pose, [B, H, W, 3] for a list.
    """
    rgb, _, _ = render_full(scene, camera, poses, background, config=config)
    return rgb


def render_full(scene: GaussianScene, camera: Camera, poses, background=(0.0, 0.0, 0.0), *,
                config: RasterConfig | None = None):
    """Like :func:`render` but returns (rgb [.., H, W, 3], alpha [.., H, W], depth [.., H, W]).

    ``depth`` is the expected camera z of the blended Gaussians (accumulated depth / alpha; 0 where alpha = 0).
    """
    _check(scene, camera)
    plist, single = as_pose_list(poses)
    rgb, alpha, dacc = get_renderer(scene, config).render_full(camera, plist, background)
    depth = np.where(alpha > 0, dacc / np.maximum(alpha, 1e-12), 0.0).astype(np.float32)
    if single:
        return rgb[0], alpha[0], depth[0]
    return rgb, alpha, depth


def render_cost(scene: GaussianScene, camera: Camera, poses, target_image, metric: str = "sad",
                background=(0.0, 0.0, 0.0), *, mask_alpha: float = 0.0, config: RasterConfig | None = None):
    """Image cost of each pose's rendering against ``target_image``, fused in the blending kernel; lower is better.

    Args:
        target_image: [H, W, 3] float in [0, 1] or uint8.
        metric: a pixel metric of ``costs.METRICS``: "sad" (sum of absolute differences over every pixel and RGB
            channel, on the 0-1 scale: up to 3 x H x W), "ssd", "psnr" (100 - PSNR), "ncc" (1 - mean per-channel
            zero-mean normalised cross-correlation, in [0, 2]) or "affine".
        mask_alpha: pixels whose rendered alpha is below this are ignored.

    Returns:
        float64 [B] (a float for a single pose).
    """
    _check(scene, camera)
    plist, single = as_pose_list(poses)
    img = np.asarray(target_image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    if img.shape != (camera.height, camera.width, 3):
        raise ValueError(f"target image must be [{camera.height}, {camera.width}, 3], got {img.shape}")
    r = get_renderer(scene, config)
    stats = r.cost_stats(camera, plist, r.upload_image(img), background, mask_alpha)
    cost = cost_from_stats(stats, metric, camera.width * camera.height)
    return float(cost[0]) if single else cost
