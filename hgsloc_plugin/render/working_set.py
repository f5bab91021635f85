"""A query's working set that follows its search: Gaussians selected for a small region around the poses scored,
re-selected when the search leaves it.

A search scores poses within a few pixels of image motion of each other, while its trust region allows tens:
selecting once for the whole trust region (``Renderer.working_set``) keeps the Gaussians seen by any pose of
it, 2-3x those seen by the poses actually scored (975k-Gaussian room: 368k vs about 110k in the coarse image).
:class:`WorkingSet` selects for a region of ``radius_shift`` / ``radius_rotation_deg`` around the first batch it renders
and, when a batch has a pose outside that region, selects again around that batch. Each selection is the
conservative test of ``kernels/cull.py`` and keeps the resident order, so every image and cost equals the
whole map's bit for bit, whichever selection rendered it (a batch that does not fit one region is rendered
from the whole map). The workspaces are the parent renderer's (``render.buffers.Pool``), so a re-selection costs
one pass over the map's centres and a gather into new arrays of the selected Gaussians.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera
from ..core.pose import Pose, rotation_angle_deg
from . import RendererLike


def mean_pose(poses: list[Pose]) -> Pose:
    """The pose with the mean camera centre and the chordal mean rotation (projection of the mean rotation
    matrix onto SO(3)) of ``poses``."""
    if len(poses) == 1:
        return poses[0]
    M = np.mean([p.R for p in poses], axis=0)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return Pose.from_centre(R, np.mean([p.centre() for p in poses], axis=0))


class WorkingSet:
    """Renders like ``renderer`` (``window_cost``, ``cost_stats``, ``pose_gradient``, ``render_full``) from the
    Gaussians some pose near the poses asked for can see.

    Args:
        renderer: the whole map's renderer.
        cameras: every camera (size, intrinsics) that will be rendered with.
        radius_shift / radius_rotation_deg: the selection region's camera-centre shift (scene units) and rotation
            (degrees) around its centre.
        select: makes a selection, called as ``renderer.working_set`` is (the default); another one (a level of
            detail's cut: ``hierarchy.CutSelection``) renders approximately, and a batch that does not fit one
            region is then rendered from the exact map.
        per_camera: one selection per camera rendered with (for that camera alone) instead of one for all of
            ``cameras`` (a cut per image size).

    Attributes:
        selections: selections made; fallback_poses: poses rendered from the whole map (their batch did not
        fit one region); largest: the largest selection's size.
    """

    def __init__(self, renderer: RendererLike, cameras: list[Camera], radius_shift: float, radius_rotation_deg: float,
                 select=None, per_camera: bool = False):
        if not (radius_shift > 0 and radius_rotation_deg > 0):
            raise ValueError(f"working-set radii must be > 0, got {radius_shift}, {radius_rotation_deg}")
        self.full = renderer
        self.select = renderer.working_set if select is None else select
        self.cameras = list(cameras)
        self.radius_shift = float(radius_shift)
        self.radius_rotation_deg = float(radius_rotation_deg)
        self.selections = 0
        self.fallback_poses = 0
        self.largest = 0
        self.per_camera = per_camera
        self._sub: RendererLike | None = None  # the last selection made
        self._selected: dict[Camera | None, tuple[Pose, RendererLike]] = {}  # per camera (or None): centre, selection

    @property
    def config(self):
        return self.full.config

    def upload_window_query(self, image: np.ndarray):
        return self.full.upload_window_query(image)

    def upload_image(self, image: np.ndarray):
        return self.full.upload_image(image)

    @property
    def n(self) -> int:
        """Gaussians of the current selection (the whole map before the first)."""
        return self._sub.n if self._sub is not None else self.full.n

    def _inside(self, centre: Pose, poses: list[Pose]) -> bool:
        c0, R0 = centre.centre(), centre.R
        return all(np.linalg.norm(p.centre() - c0) <= self.radius_shift
                   and rotation_angle_deg(R0, p.R) <= self.radius_rotation_deg for p in poses)

    def covering(self, poses: list[Pose], camera: Camera | None = None) -> RendererLike:
        """A renderer whose images of ``poses`` (at ``camera``) equal the whole map's: the current selection
        (for ``camera`` when ``per_camera``) when its region holds them all, else a new selection around them (or
        the whole map when they do not fit one region)."""
        key = camera if self.per_camera and isinstance(camera, Camera) else None
        centre, sub = self._selected.get(key, (None, None))
        if centre is not None and self._inside(centre, poses):
            return sub
        centre = mean_pose(poses)
        if not self._inside(centre, poses):
            self.fallback_poses += len(poses)
            return self.full
        cameras = self.cameras if key is None else [camera]
        self._sub = self.select(cameras, centre, self.radius_shift, self.radius_rotation_deg)
        self._selected[key] = (centre, self._sub)
        self.selections += 1
        self.largest = max(self.largest, self._sub.n)
        return self._sub

    def window_cost(self, camera: Camera, poses: list[Pose], *args, **kwargs) -> np.ndarray:
        return self.covering(poses, camera).window_cost(camera, poses, *args, **kwargs)

    def cost_stats(self, camera: Camera, poses: list[Pose], *args, **kwargs) -> np.ndarray:
        return self.covering(poses, camera).cost_stats(camera, poses, *args, **kwargs)

    def pose_gradient(self, camera: Camera, poses: list[Pose], *args, **kwargs):
        return self.covering(poses, camera).pose_gradient(camera, poses, *args, **kwargs)

    def pose_gradient_noise(self, camera: Camera, pose: Pose, *args, **kwargs):
        return self.covering([pose], camera).pose_gradient_noise(camera, pose, *args, **kwargs)

    def render_full(self, camera: Camera, poses: list[Pose], *args, **kwargs):
        return self.covering(poses, camera).render_full(camera, poses, *args, **kwargs)

    def working_set(self, cameras: list[Camera], pose: Pose, max_shift: float, max_rotation_deg: float):
        return self.full.working_set(cameras, pose, max_shift, max_rotation_deg)
