"""The map's floor: how far the map's own cost minimum lies from views whose poses are known.

A map fitted to photos renders each view a little off (geometry, exposure, the photos' own pose errors), so the
refined pose of a perfect prior is not the prior: it is the map's nearest minimum. Over views with known poses
(training views, or any the user trusts) the offsets of those minima are the map's floor, which no statistic of
one query image shows (``benchmarks/map_floor.md``). As 3-D standard deviations it goes into every polished
pose's covariance (``Tuning.map_floor_depth`` / ``map_floor_deg``): the sigmas then cover the map's error, and a
prior of known error is fused with the refined pose by the map's real precision.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..core.pose import rotation_angle_deg


@dataclass(frozen=True)
class MapFloor:
    """The map's floor over ``n`` views.

    Attributes:
        depth: root mean square of the camera-centre offsets, as a fraction of each view's median depth (the
            3-D standard deviation ``Tuning.map_floor_depth`` takes).
        deg: root mean square of the rotation offsets in degrees (``Tuning.map_floor_deg``).
        offsets: [n, 2] per view: (centre offset / median depth, rotation offset in degrees), in input order.
        names: the views' names, in input order.
    """

    depth: float
    deg: float
    offsets: np.ndarray
    names: tuple[str, ...]

    @property
    def n(self) -> int:
        return len(self.names)

    def flag(self) -> str:
        """The ``hgsloc refine --map-floor`` value that declares this floor."""
        return f"{100.0 * self.depth:.3g}%,{self.deg:.3g}deg"

    def tuning(self) -> dict:
        """The ``Tuning`` fields that declare this floor."""
        return {"map_floor_depth": self.depth, "map_floor_deg": self.deg}

    def without(self, name: str) -> MapFloor:
        """This floor measured without view ``name`` (for a query that is one of the views measured)."""
        keep = [i for i, n in enumerate(self.names) if n != name]
        return floor_from_offsets(self.offsets[keep], [self.names[i] for i in keep])


def floor_from_offsets(offsets: np.ndarray, names: Iterable[str]) -> MapFloor:
    """:class:`MapFloor` of ``offsets`` [n, 2] (centre offset / median depth, degrees); ValueError when n = 0."""
    offsets = np.asarray(offsets, np.float64).reshape(-1, 2)
    if len(offsets) == 0:
        raise ValueError("the map's floor needs at least one view with a known pose")
    rms = np.sqrt(np.mean(offsets ** 2, axis=0))
    return MapFloor(float(rms[0]), float(rms[1]), offsets, tuple(names))


def map_floor(refiner, views: Iterable[tuple]) -> MapFloor:
    """Measure the map's floor on views with known poses.

    Args:
        refiner: an ``HGSLocPlugin`` / ``Refiner`` on the map (its configuration's routes and sizes are the ones
            measured; the offset is taken before any fusion with a declared prior error).
        views: (image, camera, known world-to-camera ``Pose``, name) per view.

    Returns:
        :class:`MapFloor`: each view refined from its own known pose; its offset is the distance from the known
        pose to the pose the acceptance rule judged (``RefineResult.search_pose``: the map's nearest minimum).
    """
    from ..refine.plan import median_depth

    offsets, names = [], []
    for image, camera, pose, name in views:
        r = refiner.refine(image, camera, pose, name=name)
        if r.search_pose is None:
            raise ValueError(f"{name}: no refined pose to measure the map's floor with ({r.rejected})")
        depth = median_depth(refiner.scene, camera, pose)
        found = r.search_pose
        offsets.append((float(np.linalg.norm(found.centre() - pose.centre())) / depth,
                        rotation_angle_deg(found.R, pose.R)))
        names.append(name)
    if not all(math.isfinite(v) for o in offsets for v in o):
        raise ValueError("the map's floor: a non-finite offset (a view the map does not render?)")
    return floor_from_offsets(np.array(offsets), names)
