"""Refine a localizer's pose file end to end: read, refine every query, write the same dialect + a JSON report.

This is the code path of ``hgsloc refine``, the HLoc step and ``hgsloc demo``. Outputs are written atomically
and regularly, so an interrupted run leaves a valid file; a rerun resumes (queries in the report are skipped,
no line is duplicated).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

from .adapters.names import resolve_image
from .adapters.posefile import read_poses, write_poses
from .distributed import Task
from .camera import Camera
from .pose import Pose
from .refine import HGSLocPlugin, RefineConfig
from .refine.image import load_image
from .scene import GaussianScene, atomic_write_bytes

logger = logging.getLogger("hgsloc_plugin")


def report_path(output: Path) -> Path:
    return Path(str(output) + ".json")


def refine_pose_file(scene: GaussianScene | str | Path, poses: Path, images: Path,
                     intrinsics: Callable[[str, int, int], Camera], output: Path, *,
                     config: RefineConfig | None = None, limit: int | None = None, dialect: str = "auto",
                     gt_variant: str | None = None, figures: Path | None = None, progress: bool = True,
                     save_every: int = 10, settings: dict | None = None, workers: int = 0,
                     ray_address: str | None = None) -> dict:
    """Refine the poses in ``poses`` and write ``output`` (same dialect) and ``output + '.json'``.

    Args:
        scene: the 3DGS map (object or .ply path), in the frame of the poses.
        poses: the localizer's pose file. images: folder holding the query images (any name style).
        intrinsics: (name, width, height) -> Camera. output: refined pose file (must differ from ``poses``).
        limit: refine only the first N queries (the rest keep their input pose).
        gt_variant: recorded in the report ("sfm", "dslam", ...).
        figures: folder for comparison figures of each refined query.
        workers / ray_address: refine on N local Ray worker processes, or on an existing Ray cluster
            (see :mod:`hgsloc_plugin.distributed`); by default everything runs in this process.

    Returns:
        The report dict (also written as JSON).
    """
    from tqdm import tqdm

    poses, images, output = Path(poses), Path(images), Path(output)
    if output.exists() and output.resolve() == poses.resolve():
        raise ValueError(f"{output}: refusing to overwrite the input pose file")
    pf = read_poses(poses, dialect)
    refiner = scene if isinstance(scene, HGSLocPlugin) else HGSLocPlugin(scene, config)
    config = refiner.config
    rep_path = report_path(output)
    done: dict[str, dict] = {}
    refined: dict[str, Pose] = {}
    if output.exists() and rep_path.exists():  # resume
        old = json.loads(rep_path.read_text())
        prev = read_poses(output, pf.dialect)
        for name, q in old.get("queries", {}).items():
            if name in pf and name in prev:
                done[name] = q
                if prev[name] is not None:
                    refined[name] = prev[name]
        logger.info("resuming: %d queries already done", len(done))
    names = list(pf)[: limit if limit is not None else None]
    todo = [n for n in names if n not in done]
    report = {
        "input": str(poses), "output": str(output), "dialect": pf.dialect, "scene": str(getattr(
            refiner.scene, "source", None)), "gt_variant": gt_variant, "config": config.to_dict(),
        "settings": settings or {}, "queries": done,
    }

    def save():
        write_poses(output, refined, like=pf)
        q = report["queries"].values()
        report["totals"] = {
            "queries": len(report["queries"]), "accepted": sum(1 for v in q if v.get("accepted")),
            "failed": sum(1 for v in q if v.get("error")), "renders": sum(v.get("renders", 0) for v in q),
            "seconds": round(sum(v.get("seconds", 0.0) for v in q), 3),
        }
        atomic_write_bytes(rep_path, json.dumps(report, indent=1).encode())

    def record(name: str, coarse: Pose, res=None, error: str | None = None, img=None, cam=None) -> None:
        if res is not None and res.error:
            error = res.error
        if error is not None:
            entry = {"accepted": False, "error": error, "renders": 0,
                     "seconds": round(res.seconds, 4) if res is not None else 0.0}
        else:
            entry = res.to_dict()
            entry.pop("name", None)
            if res.accepted:
                refined[name] = res.pose
                if figures is not None and img is not None:
                    from .viz import comparison_figure

                    comparison_figure(refiner.scene, cam, load_image(img), coarse, res.pose,
                                      Path(figures) / (name.replace("/", "_") + ".png"),
                                      background=config.background)
        report["queries"][name] = entry

    # prepare tasks in the driver: name, image path, intrinsics, prior (errors are recorded at once)
    tasks = []
    for name in todo:
        coarse = pf[name]
        if coarse is None:
            record(name, coarse, error="failed prior (non-finite or zero pose)")
            continue
        try:
            img_path = resolve_image(name, images)
            from PIL import Image

            with Image.open(img_path) as im:
                w, h = im.size
            tasks.append(Task(len(tasks), name, str(img_path), intrinsics(name, w, h), coarse))
        except Exception as exc:  # one bad query never stops the run
            logger.warning("%s: %s", name, exc)
            record(name, coarse, error=f"{type(exc).__name__}: {exc}")

    count = 0

    def on_result(index: int, res) -> None:
        nonlocal count
        t = tasks[index]
        record(t.name, t.coarse_pose, res, img=t.image, cam=t.camera)
        count += 1
        if save_every and count % save_every == 0:
            save()

    try:
        if workers and workers > 0 or ray_address:
            from .distributed import refine_distributed

            refine_distributed(refiner.scene, tasks, config, workers=max(1, workers or 1), address=ray_address,
                               progress=progress, on_result=on_result)
        else:
            for t in tqdm(tasks, desc="refining", unit="query", disable=not progress):
                res = refiner.refine_many([(t.image, t.camera, t.coarse_pose, t.name)], progress=False)[0]
                on_result(t.index, res)
    finally:
        save()
    return report
