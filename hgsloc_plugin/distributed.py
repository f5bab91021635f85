"""Scale-out on Ray: refine many queries across worker processes or a cluster (optional extra ``[ray]``).

Each worker is a Ray actor that starts Taichi once (CUDA when the node gives it a GPU, else the CPU) and builds
one :class:`~hgsloc_plugin.HGSLocPlugin` from the scene, which travels once through Ray's object store.
Queries go out in small chunks; results stream back to the caller's ``on_result`` as they finish and are also
returned in input order. A worker that dies has its unfinished chunk re-queued on a fresh worker (bounded
retries); a query that fails for its own reasons comes back as a failed result. The refinement logic itself
is :meth:`HGSLocPlugin.refine`, the same as in a single process.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

logger = logging.getLogger("hgsloc_plugin")


def _require_ray():
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise RuntimeError('distributed refinement needs Ray: pip install "hgsloc-plugin[ray]"') from exc
    return ray


@dataclass
class Task:
    """One query: its position in the input, name, image (path or array), camera and coarse pose."""

    index: int
    name: str
    image: object
    camera: object
    coarse_pose: object


def _worker_class(ray):
    @ray.remote
    class RefineWorker:
        def __init__(self, scene, config, arch: str, threads: int):
            from .backend import init
            from .refine import HGSLocPlugin

            init(arch, cpu_threads=threads or None)
            self.refiner = HGSLocPlugin(scene, config)

        def refine_chunk(self, tasks: list[Task]):
            out = []
            for t in tasks:
                res = self.refiner.refine_many([(t.image, t.camera, t.coarse_pose, t.name)], progress=False)[0]
                out.append((t.index, res))
            return out

        def pid(self) -> int:
            import os

            return os.getpid()

    return RefineWorker


def refine_distributed(scene, tasks: Sequence[Task], config=None, *, workers: int = 2, address: str | None = None,
                       chunk_size: int = 2, max_retries: int = 2, threads_per_worker: int = 1,
                       progress: bool = True, on_result: Callable | None = None, _after_chunk=None) -> list:
    """Refine ``tasks`` on ``workers`` Ray actors; returns the RefineResults in input order.

    Args:
        scene: a GaussianScene (sent once through the object store) or a path to a .ply.
        address: an existing cluster ("auto" or "ray://host:port"); None starts a local Ray with ``workers`` CPUs
            (or joins the one already initialised in this process).
        on_result: called as ``on_result(index, result)`` as each query finishes (any order).
        max_retries: times a chunk is re-queued after its worker died.
    """
    ray = _require_ray()
    from tqdm import tqdm

    from .refine import RefineConfig, RefineResult
    from .scene import GaussianScene

    if not isinstance(scene, GaussianScene):
        scene = GaussianScene.from_ply(scene)
    config = config or RefineConfig()
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=max(1, workers * threads_per_worker), log_to_driver=False, include_dashboard=False)
        started = True
    Worker = _worker_class(ray)
    gpus = ray.cluster_resources().get("GPU", 0)
    opts = {"num_cpus": threads_per_worker, "num_gpus": 1 if gpus >= workers else 0, "max_restarts": 0}
    arch = "cuda" if opts["num_gpus"] else "cpu"
    scene_ref = ray.put(scene)

    def spawn():
        return Worker.options(**opts).remote(scene_ref, config, arch, threads_per_worker)

    tasks = list(tasks)
    chunks = [tasks[i:i + chunk_size] for i in range(0, len(tasks), chunk_size)]
    queue = [(c, 0) for c in chunks]
    results: dict[int, RefineResult] = {}
    actors = [spawn() for _ in range(max(1, min(workers, len(chunks))))]
    running = {}  # future -> (actor, chunk, tries)
    bar = tqdm(total=len(tasks), desc="refining", unit="query", disable=not progress)
    try:
        def feed(actor):
            if queue:
                chunk, tries = queue.pop(0)
                running[actor.refine_chunk.remote(chunk)] = (actor, chunk, tries)

        for a in actors:
            feed(a)
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            fut = done[0]
            actor, chunk, tries = running.pop(fut)
            try:
                for idx, res in ray.get(fut):
                    results[idx] = res
                    bar.update(1)
                    if on_result:
                        on_result(idx, res)
                if _after_chunk:
                    _after_chunk(actor)
                feed(actor)
            except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as exc:
                logger.warning("worker died (%s); re-queueing %d queries", type(exc).__name__, len(chunk))
                if tries + 1 > max_retries:
                    for t in chunk:
                        res = RefineResult(pose=t.coarse_pose, initial_pose=t.coarse_pose, name=t.name,
                                           error=f"worker died {tries + 1} times")
                        results[t.index] = res
                        bar.update(1)
                        if on_result:
                            on_result(t.index, res)
                else:
                    queue.insert(0, (chunk, tries + 1))
                new = spawn()
                feed(new)
    finally:
        bar.close()
        if started:
            ray.shutdown()
    return [results[t.index] for t in tasks]
