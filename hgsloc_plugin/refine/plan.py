"""One query's plan: the scoring cameras, the search's step levels, its median depth, trust region and prior."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.pose import Pose, rotation_angle_deg
from ..core.prior import QueryPrior
from ..core.scene import GaussianScene
from .config import RefineConfig


def median_depth(scene: GaussianScene, camera: Camera, T_cam_world: Pose) -> float:
    """Median camera z of the Gaussian centres that project into the image (scene extent if none do)."""
    p = scene.means.astype(np.float64) @ T_cam_world.R.T + T_cam_world.tvec
    z = p[:, 2]
    front = z > 1e-6
    u = camera.fx * p[front, 0] / z[front] + camera.cx
    v = camera.fy * p[front, 1] / z[front] + camera.cy
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    zs = z[front][inside]
    return float(np.median(zs)) if zs.size else max(scene.extent(), 1e-6)


@dataclass(frozen=True)
class Plan:
    """What one query runs on.

    Attributes:
        coarse_pose: the prior (world-to-camera).
        cam_final / cam_coarse / cam_polish / cam_wide: the fine levels', the pyramid levels', the polish's and
            the wide search's cameras (with ``Tuning.antialias``, the first three, where smaller than the query
            image, marked as its reduction: :func:`reduced`).
        levels: (rotation step in degrees, translation step in scene units) per search level, coarse to fine.
        depth: the coarse pose's median scene depth (scene units).
        max_shift / max_rotation_deg: the trust region around ``coarse_pose``.
        prior_error / prior_error_deg: the prior's expected error (None: unknown).
    """

    coarse_pose: Pose
    cam_final: Camera
    cam_coarse: Camera
    cam_polish: Camera
    cam_wide: Camera
    levels: tuple[tuple[float, float], ...]
    depth: float
    max_shift: float
    max_rotation_deg: float
    prior_error: float | None = None
    prior_error_deg: float | None = None

    def allows(self, pose: Pose) -> bool:
        """Whether ``pose`` lies in the trust region."""
        if np.linalg.norm(pose.centre() - self.coarse_pose.centre()) > self.max_shift:
            return False
        return rotation_angle_deg(self.coarse_pose.R, pose.R) <= self.max_rotation_deg

    def pixels_apart(self, a: Pose, b: Pose, cam: Camera | None = None) -> float:
        """Image motion between two poses at the final size (pixels): camera-centre distance at the plan's depth
        plus the rotation between them, both times the mean focal length; at ``cam``'s size (one of the plan's
        cameras) when given, scaled by its focal length over the final size's."""
        f = 0.5 * (self.cam_final.fx + self.cam_final.fy)
        shift, deg = a.errors_to(b)
        px = shift / self.depth * f + math.radians(deg) * f
        return px if cam is None else px * cam.fx / self.cam_final.fx

    def travel(self, pose: Pose) -> float:
        """The larger of ``pose``'s centre shift / max_shift and rotation / max_rotation_deg from the prior."""
        return max(float(np.linalg.norm(self.coarse_pose.centre() - pose.centre())) / self.max_shift,
                   rotation_angle_deg(self.coarse_pose.R, pose.R) / self.max_rotation_deg)


def reduced(cam: Camera, full: Camera) -> Camera:
    """``cam`` (a scoring size of ``full``'s image) marked as that image reduced: ``Camera.downsample`` the mean
    of the two axes' factors (1: ``full``'s own size)."""
    factor = 0.5 * (full.width / cam.width + full.height / cam.height)
    return cam if cam.width >= full.width else dataclasses.replace(cam, downsample=max(1.0, factor))


def make_plan(config: RefineConfig, scene: GaussianScene, camera: Camera, coarse_pose: Pose,
              prior: QueryPrior, step_pixels: tuple[float, ...] | None = None) -> Plan:
    """The plan of one query: ``prior``'s settings first, then ``config``'s, then the automatic trust region
    (``trust_steps`` coarsest steps; half the depth and 10 degrees for the paper's raw-component steps).
    ``step_pixels``: the automatic levels' image motion instead of ``config.step_pixels`` (the wide search's
    ``config.tuning.wide_step_pixels``)."""
    cfg = config
    cam_final = camera.with_max_side(cfg.score_max_side)
    coarse_side = max(cfg.tuning.coarse_scale * max(cam_final.width, cam_final.height), cfg.tuning.coarse_min_side)
    cam_coarse = cam_final.with_max_side(int(round(coarse_side)))
    cam_polish = camera.with_max_side(cfg.polish_max_side)
    cam_wide = cam_final.with_max_side(cfg.tuning.wide_max_side)
    if cfg.tuning.antialias:  # each scoring size renders as the query image reduced to it; the wide search's
        # lattice (``wide_step_pixels``) was tuned on plain renders and keeps them
        cam_final, cam_coarse, cam_polish = (reduced(c, camera) for c in (cam_final, cam_coarse, cam_polish))
    depth = median_depth(scene, cam_final, coarse_pose)
    if cfg.tuning.neighbourhood == "paper":
        levels = [(cfg.tuning.paper_step_q, cfg.tuning.paper_step_t)]
    elif cfg.tuning.levels:
        levels = list(cfg.tuning.levels)
    else:
        f = 0.5 * (cam_final.fx + cam_final.fy)
        levels = [(math.degrees(px / f), px * depth / f) for px in (step_pixels or cfg.step_pixels)]
    if cfg.tuning.neighbourhood == "paper":  # raw-component steps: no image-motion scale
        auto_shift, auto_rotation = 0.5 * depth, 10.0
    else:
        auto_shift, auto_rotation = cfg.tuning.trust_steps * levels[0][1], cfg.tuning.trust_steps * levels[0][0]
    return Plan(coarse_pose, cam_final, cam_coarse, cam_polish, cam_wide, tuple(levels), depth,
                _first(prior.shift_bound(depth), cfg.max_shift, auto_shift),
                _first(prior.max_rotation_deg, cfg.max_rotation_deg, auto_rotation),
                _first(prior.centre_error(depth), cfg.prior_error), _first(prior.prior_error_deg, cfg.prior_error_deg))


def _first(*values):
    return next((v for v in values if v is not None), None)
