"""HGSLocPlugin: the public refiner, one query (``refine``) or many (``refine_many``)."""

from __future__ import annotations

from collections.abc import Iterable

from ..refine import Refiner, RefineResult
from .batch import as_queries, run_batch


class HGSLocPlugin(Refiner):
    """Pose refiner over one 3DGS scene.

    Example:
        >>> refiner = HGSLocPlugin("point_cloud.ply")
        >>> result = refiner.refine(image, camera, coarse_pose)
        >>> result.pose, result.accepted

    Convention: poses are world-to-camera (COLMAP cam_from_world), quaternions w, x, y, z.
    """

    def refine_many(self, items: Iterable, *, progress: bool = True, desc: str = "refining", workers: int = 0,
                    ray_address: str | None = None, batch_size: int | None = None) -> list[RefineResult]:
        """Refine many queries in order; one failure is recorded in its result, never raised.

        Args:
            items: iterable of (image, camera, coarse_pose) or (image, camera, coarse_pose, name) tuples,
                or dicts with those keys (and optionally each query's
                ``max_shift`` / ``max_rotation_deg`` / ``prior_error`` / ``prior_error_deg``: ``Refiner.refine``).
            workers / ray_address: spread the queries over N Ray worker processes or an existing cluster
                (:mod:`hgsloc_plugin.run.distributed`); results are identical and in the same order.
            batch_size: queries advanced together, their renders sharing launches (:mod:`hgsloc_plugin.run.lockstep`);
                1: one at a time; None: the backend's default (``backend.DEFAULT_BATCH_SIZE``). Same poses.
        """
        return run_batch(self, as_queries(items), workers=workers, ray_address=ray_address, progress=progress,
                         desc=desc, batch_size=batch_size)
