"""Refine a localizer's pose file end to end: read, refine every query, write the same dialect + a JSON report.

This is the code path of ``hgsloc refine``, the HLoc step and ``hgsloc demo``. Outputs are written atomically
and regularly, so an interrupted run leaves a valid file; a rerun resumes (queries in the report are skipped,
no line is duplicated).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from .adapters.names import resolve_image
from .adapters.posefile import read_poses, write_poses
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
                     save_every: int = 10, settings: dict | None = None) -> dict:
    """Refine the poses in ``poses`` and write ``output`` (same dialect) and ``output + '.json'``.

    Args:
        scene: the 3DGS map (object or .ply path), in the frame of the poses.
        poses: the localizer's pose file. images: folder holding the query images (any name style).
        intrinsics: (name, width, height) -> Camera. output: refined pose file (must differ from ``poses``).
        limit: refine only the first N queries (the rest keep their input pose).
        gt_variant: recorded in the report ("sfm", "dslam", ...).
        figures: folder for comparison figures of each refined query.

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

    try:
        for k, name in enumerate(tqdm(todo, desc="refining", unit="query", disable=not progress)):
            coarse = pf[name]
            t0 = time.perf_counter()
            if coarse is None:
                report["queries"][name] = {"accepted": False, "error": "failed prior (non-finite or zero pose)",
                                           "renders": 0, "seconds": 0.0}
                continue
            try:
                img_path = resolve_image(name, images)
                img = load_image(img_path)
                cam = intrinsics(name, img.shape[1], img.shape[0])
                res = refiner.refine(img, cam, coarse, name=name)
                if res.accepted:
                    refined[name] = res.pose
                entry = res.to_dict()
                if figures is not None and res.accepted:
                    from .viz import comparison_figure

                    comparison_figure(refiner.scene, cam, img, coarse, res.pose,
                                      Path(figures) / (name.replace("/", "_") + ".png"),
                                      background=config.background)
            except Exception as exc:  # one bad query never stops the run
                logger.warning("%s: %s", name, exc)
                entry = {"accepted": False, "error": f"{type(exc).__name__}: {exc}", "renders": 0,
                         "seconds": round(time.perf_counter() - t0, 4)}
            entry.pop("name", None)
            report["queries"][name] = entry
            if save_every and (k + 1) % save_every == 0:
                save()
    finally:
        save()
    return report
