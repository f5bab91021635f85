"""Synthetic queries on the demo room: ground-truth views and photo-like degradations."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ...core.camera import Camera
from ...core.pose import Pose
from ...core.scene import GaussianScene
from ...render import render


def query_poses(n: int, seed: int = 0) -> list[Pose]:
    """n ground-truth camera poses inside the room, looking at walls with some pitch and roll."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(1.1, 1.7)])
        yaw = rng.uniform(0, 2 * np.pi)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.35, 0.1)])
        up = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 1.0])
        out.append(Pose.look_at(eye, target, up))
    return out


def degrade(img: np.ndarray, rng: np.random.Generator, *, gain=(0.8, 1.2), gamma=(0.85, 1.15),
            noise_std=0.02, blur_sigma=0.6, occluder=True) -> np.ndarray:
    """Make a rendering look like a photo: gain/offset and gamma, blur, sensor noise, an unmodelled occluder.

    Args:
        img: [H, W, 3] float in [0, 1]. Returns the same shape, float32, clipped to [0, 1].
    """
    h, w, _ = img.shape
    out = img.astype(np.float32)
    out = np.clip(out, 0, 1) ** np.float32(rng.uniform(*gamma))
    gains = (rng.uniform(*gain) * rng.uniform(0.95, 1.05, size=3)).astype(np.float32)
    out = (out * gains + np.float32(rng.uniform(-0.03, 0.03))).astype(np.float32)
    if blur_sigma > 0:
        r = max(1, int(round(2 * blur_sigma)))
        x = torch.arange(-r, r + 1, dtype=torch.float32)
        k = torch.exp(-0.5 * (x / blur_sigma) ** 2)
        k = k / k.sum()
        t = torch.from_numpy(np.ascontiguousarray(out)).permute(2, 0, 1)[:, None]
        t = F.conv2d(F.pad(t, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
        t = F.conv2d(F.pad(t, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
        out = t[:, 0].permute(1, 2, 0).numpy()
    if occluder:
        ow, oh = int(w * rng.uniform(0.08, 0.15)), int(h * rng.uniform(0.1, 0.2))
        x0, y0 = rng.integers(0, w - ow), rng.integers(0, h - oh)
        out[y0:y0 + oh, x0:x0 + ow] = rng.uniform(0.1, 0.9, size=3)
    out = out + rng.normal(scale=noise_std, size=out.shape)
    return np.clip(out, 0, 1).astype(np.float32)


def make_queries(scene: GaussianScene, camera: Camera, poses: list[Pose], seed: int = 0,
                 realistic: bool = True) -> list[np.ndarray]:
    """Render the ground-truth views and (if ``realistic``) degrade them; list of [H, W, 3] float32."""
    rng = np.random.default_rng(seed + 1000)
    imgs = render(scene, camera, poses)
    return [degrade(im, rng) if realistic else im for im in imgs]
