"""The one batch runner: refine many queries in this process or on Ray, with progress and failure records.

Every multi-query path (``HGSLocPlugin.refine_many``, pose files through :mod:`hgsloc_plugin.run.pipeline`, the
CLI, the HLoc step) comes here. In this process (and in each Ray worker) ``batch_size`` queries advance together,
their renders sharing launches (:mod:`hgsloc_plugin.run.lockstep`; the same poses as one at a time). One failed query
never stops the batch: it comes back as a failed :class:`~hgsloc_plugin.refine.RefineResult` naming its error.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from ..core.prior import QueryPrior
from ..refine import Refiner, RefineResult
from .lockstep import refine_queries

logger = logging.getLogger("hgsloc_plugin")


@dataclass
class Query:
    """One query: its position in the batch, name, image (path or array), camera, coarse pose and its own
    settings (:class:`QueryPrior`: trust region, prior error)."""

    index: int
    name: str | None
    image: object
    camera: object
    coarse_pose: object
    prior: QueryPrior = QueryPrior()

    def refine_with(self, refiner: Refiner) -> RefineResult:
        """``refiner.try_refine`` on this query."""
        return refiner.try_refine(self.image, self.camera, self.coarse_pose, name=self.name, prior=self.prior)


_QUERY_KEYS = {"image", "camera", "coarse_pose", "name", "prior", *QueryPrior.names()}


def as_queries(items: Iterable) -> list[Query]:
    """Queries from (image, camera, coarse_pose[, name]) tuples or dicts with those keys (and optionally
    the per-query keywords of ``Refiner.refine``: ``max_shift``, ``max_rotation_deg``, ``prior_error``, ...)."""
    out = []
    for k, it in enumerate(items):
        if isinstance(it, Query):
            out.append(it)
        elif isinstance(it, dict):
            unknown = sorted(set(it) - _QUERY_KEYS)
            if unknown:  # a misspelt region or error would otherwise be dropped without a word
                raise ValueError(f"query {k}: unknown keys {unknown}; a query dict takes {sorted(_QUERY_KEYS)}")
            prior = it.get("prior") or QueryPrior.from_mapping(
                {key: it[key] for key in QueryPrior.names() if key in it}, f"query {k}")
            out.append(Query(k, it.get("name"), it["image"], it["camera"], it["coarse_pose"], prior))
        else:
            image, camera, coarse, *rest = it
            out.append(Query(k, rest[0] if rest else None, image, camera, coarse))
    return out


def run_batch(refiner: Refiner, queries: Sequence[Query], *, workers: int = 0, ray_address: str | None = None,
              batch_size: int | None = None, progress: bool = True,
              on_result: Callable[[Query, RefineResult], None] | None = None,
              desc: str = "refining") -> list[RefineResult]:
    """Refine ``queries``; returns their results in input order.

    Args:
        refiner: scene, search and raster settings (Ray workers rebuild the same refiner from them).
        workers / ray_address: N local Ray worker processes, or an existing cluster ("auto", "ray://...");
            by default everything runs in this process. Results are identical either way.
        batch_size: queries advanced together, their renders in shared launches (``lockstep.py``; each Ray
            worker too); 1: one query at a time; None: :func:`~hgsloc_plugin.core.backend.default_batch_size` (on
            Ray, each worker's backend's).
            The poses are the same for every batch size.
        on_result: called as ``on_result(query, result)`` as each query finishes (in any order).
    """
    from tqdm import tqdm

    queries = list(queries)
    if batch_size is not None or not (workers or ray_address):
        batch_size = check_batch_size(batch_size)
    results: dict[int, RefineResult] = {}
    with tqdm(total=len(queries), desc=desc, unit="query", disable=not progress) as bar:
        for q, res in _results(refiner, queries, workers, ray_address, batch_size):
            results[q.index] = res
            bar.update(1)
            if on_result is not None:
                on_result(q, res)
    out = [results[q.index] for q in queries]
    logger.info("Refined %d / %d queries", sum(r.accepted for r in out), len(out))
    return out


def check_batch_size(batch_size: int | None) -> int:
    """``batch_size``, or the backend's default when None; a clear error when it is not a positive integer."""
    if batch_size is None:
        from ..core.backend import default_batch_size

        return default_batch_size()
    if isinstance(batch_size, bool) or int(batch_size) != batch_size or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    return int(batch_size)


def _results(refiner: Refiner, queries: list[Query], workers: int, ray_address: str | None,
             batch_size: int | None):
    """(query, result) pairs as they finish (``batch_size`` None only on Ray: each worker's default)."""
    if workers or ray_address:
        if refiner.renderer_given:
            try:
                pickle.dumps(refiner.renderer)
            except Exception as exc:  # noqa: BLE001 - any failure to pickle means it cannot travel
                raise ValueError("a renderer given to the refiner does not travel to Ray workers unless it pickles "
                                 f"({type(refiner.renderer).__name__}: {exc}); the package's renderer is rebuilt "
                                 "on each worker from the scene and RasterConfig: refine in this process "
                                 "(workers=0, no ray_address) or give a picklable backend") from exc
        from .distributed import ray_results

        yield from ray_results(refiner.scene, refiner.config, refiner.raster, queries,
                               workers=max(1, workers or 1), address=ray_address, batch_size=batch_size,
                               renderer=refiner.renderer if refiner.renderer_given else None)
        return
    yield from refine_queries(refiner, queries, batch_size)
