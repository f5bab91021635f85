"""Ray mechanics for :mod:`hgsloc_plugin.run.batch`: a pool of refiner actors (optional extra ``[ray]``).

Each worker is a Ray actor that starts Taichi once (CUDA when the cluster has GPUs, else the CPU; the caller's
``HGSLOC_ARCH`` decides when set) and builds one :class:`~hgsloc_plugin.refine.Refiner` from the scene (sent once
through Ray's object store), the search config and the raster config, so it renders exactly as the caller's
refiner does. Workers share the GPUs
(:func:`worker_resources`): a query's host side (Python, launches, read-backs) takes longer than its kernels on a
GPU, so several processes keep one device busy. Queries go out in small chunks; a worker that dies has its
unfinished chunk re-queued on a fresh worker (bounded retries).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence

from ..core.backend import DEFAULT_BATCH_SIZE, requested_arch

logger = logging.getLogger("hgsloc_plugin")

#: resolution of Ray's fractional resources (four decimals): a GPU share is rounded down to it, so that
#: ``workers per GPU`` shares never add up to more than one GPU
_RAY_RESOURCE_STEP = 1e-4


def worker_resources(gpus: float, workers: int, threads: int = 1, arch: str | None = None) -> tuple[dict, str]:
    """Ray resources of one worker and the backend it starts: (``{"num_cpus", "num_gpus"}``, "cuda" or "cpu").

    Args:
        gpus: the cluster's GPUs (``ray.cluster_resources()["GPU"]``); workers: the pool's size; threads: CPU
            threads per worker; arch: "auto", "cpu" or "cuda" (``backend.requested_arch``: None reads
            ``HGSLOC_ARCH``; "cuda" without a GPU is an error).

    With GPUs ("auto", "cuda"), every worker runs on CUDA and ``ceil(workers / gpus)`` of them share a GPU (a share
    of 1 / that, rounded down to Ray's resolution: all of them fit at once); otherwise on the CPU.
    """
    if int(workers) != workers or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    arch = requested_arch(arch)
    whole = int(gpus)  # a fractional cluster total (a GPU already shared out) offers its whole GPUs only
    if arch == "cuda" and whole < 1:
        raise RuntimeError(f"CUDA workers requested (HGSLOC_ARCH=cuda) but the Ray cluster has {gpus:g} GPUs")
    if whole < 1 or arch == "cpu":
        return {"num_cpus": threads, "num_gpus": 0}, "cpu"
    per_gpu = math.ceil(workers / whole)
    share = 1.0 if per_gpu == 1 else math.floor(1.0 / per_gpu / _RAY_RESOURCE_STEP) * _RAY_RESOURCE_STEP
    return {"num_cpus": threads, "num_gpus": share}, "cuda"


def _require_ray():
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise RuntimeError('distributed refinement needs Ray: pip install "hgsloc-plugin[ray]"') from exc
    return ray


def _worker_class(ray):
    @ray.remote
    class RefineWorker:
        def __init__(self, scene, config, raster, arch: str, threads: int, renderer=None):
            from ..core.backend import init
            from ..refine import Refiner

            init(arch, cpu_threads=threads or None)
            self.refiner = Refiner(scene, config, raster, renderer=renderer)

        def refine_chunk(self, queries, batch_size: int | None):
            from ..core.backend import default_batch_size
            from .lockstep import refine_queries

            batch_size = batch_size or default_batch_size()  # None: this worker's backend's default
            return [(q.index, res) for q, res in refine_queries(self.refiner, queries, batch_size)]

    return RefineWorker


def ray_results(scene, config, raster, queries: Sequence, *, workers: int = 2, address: str | None = None,
                chunk_size: int = 2, batch_size: int | None = 1, max_retries: int = 2, threads_per_worker: int = 1,
                renderer=None, _after_chunk: Callable | None = None) -> Iterator[tuple]:
    """Yield (query, RefineResult) for every query as workers finish them (any order).

    Args:
        scene: a GaussianScene. config / raster: the RefineConfig and RasterConfig every worker uses.
        queries: :class:`~hgsloc_plugin.run.batch.Query` objects.
        address: an existing cluster ("auto" or "ray://host:port"); None starts a local Ray with ``workers``
            CPUs (or joins the one already initialised in this process).
        chunk_size: queries sent to a worker at a time (at least its batch size).
        batch_size: queries a worker advances together (``lockstep.refine_queries``); None: the default of the
            workers' backend (``backend.DEFAULT_BATCH_SIZE``; :func:`worker_resources` decides it).
        threads_per_worker: CPU threads each worker's Taichi uses (and the CPUs Ray reserves for it).
        max_retries: times a chunk is re-queued after its worker died.
        renderer: a picklable ``RendererLike`` each worker refines with (another backend); None: each builds the
            package's renderer from ``scene`` and ``raster``.
    """
    ray = _require_ray()
    from ..refine import RefineResult

    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=max(1, workers * threads_per_worker), log_to_driver=False, include_dashboard=False)
        started = True
    Worker = _worker_class(ray)
    resources, arch = worker_resources(ray.cluster_resources().get("GPU", 0), workers, threads_per_worker)
    opts = {**resources, "max_restarts": 0}
    logger.info("%d Ray workers on %s (%s GPU each)", workers, arch, resources["num_gpus"])
    scene_ref = ray.put(scene)
    renderer_ref = None if renderer is None else ray.put(renderer)
    by_index = {q.index: q for q in queries}

    def spawn():
        return Worker.options(**opts).remote(scene_ref, config, raster, arch, threads_per_worker, renderer_ref)

    chunk_size = max(chunk_size, batch_size or DEFAULT_BATCH_SIZE[arch])
    queue = [(list(queries[i:i + chunk_size]), 0) for i in range(0, len(queries), chunk_size)]
    running = {}  # future -> (actor, chunk, tries)

    def feed(actor):
        if queue:
            chunk, tries = queue.pop(0)
            running[actor.refine_chunk.remote(chunk, batch_size)] = (actor, chunk, tries)

    try:
        for _ in range(max(1, min(workers, len(queue)))):
            feed(spawn())
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            actor, chunk, tries = running.pop(done[0])
            try:
                pairs = ray.get(done[0])
            except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as exc:
                logger.warning("worker died (%s); re-queueing %d queries", type(exc).__name__, len(chunk))
                if tries + 1 > max_retries:
                    for q in chunk:
                        yield q, RefineResult.failed(q.coarse_pose, f"worker died {tries + 1} times", q.name)
                else:
                    queue.insert(0, (chunk, tries + 1))
                feed(spawn())
                continue
            for idx, res in pairs:
                yield by_index[idx], res
            if _after_chunk:
                _after_chunk(actor)
            feed(actor)
    finally:
        if started:
            ray.shutdown()
