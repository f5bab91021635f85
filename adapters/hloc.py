"""HLoc: its results file (8 columns ``name qw qx qy qz tx ty tz``) and a refinement step in hloc's style.

Run it after ``localize_sfm.main(...)`` and before ``evaluate(...)`` in a pipeline such as
``hloc/pipelines/7Scenes/pipeline.py::run_scene``::

    from hgsloc_plugin.adapters import hloc as hgsloc_step
    results_refined = hgsloc_step.main(scene_ply, query_list, results, images, results.with_name("results_refined.txt"))

or from the shell: ``python -m hgsloc_plugin.adapters.hloc --scene S.ply --queries Q.txt --results R.txt
--image_dir DIR --output OUT.txt``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from .posefile import PoseFile, read_poses as _read, write_poses

logger = logging.getLogger("hgsloc_plugin")
__all__ = ["main", "read_poses", "write_poses"]


def read_poses(path) -> PoseFile:
    return _read(path, "hloc")


def main(scene: Path, queries: Path, results: Path, image_dir: Path, output: Path, config=None,
         limit: int | None = None, gt_variant: str | None = None, allow_distortion: bool = False) -> Path:
    """Refine hloc's ``results`` with the 3DGS ``scene``; intrinsics from ``queries`` (with intrinsics).

    Returns the path of the refined results (HLoc dialect), with a JSON report beside it.
    """
    from hgsloc_plugin.pipeline import refine_pose_file

    from .intrinsics import from_query_list

    logger.info("Refining %s with %s", results, scene)
    rep = refine_pose_file(scene, Path(results), Path(image_dir),
                           from_query_list(queries, allow_distortion=allow_distortion), Path(output),
                           config=config, limit=limit, gt_variant=gt_variant)
    t = rep["totals"]
    logger.info("Refined %d / %d queries", t["accepted"], t["queries"])
    return Path(output)


if __name__ == "__main__":
    import sys

    from hgsloc_plugin.refine import RefineConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--queries", type=Path, required=True, help="queries_with_intrinsics.txt")
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--image_dir", type=Path, required=True)
    ap.add_argument("--output", type=Path, required=True)
    ap.add_argument("--config", default="default")
    ap.add_argument("--limit", type=int)
    ap.add_argument("--allow_distortion", action="store_true")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    try:
        main(a.scene, a.queries, a.results, a.image_dir, a.output, RefineConfig.preset(a.config), a.limit,
             allow_distortion=a.allow_distortion)
    except (ValueError, FileNotFoundError, KeyError, OSError) as exc:
        print(f"hloc step: error: {exc}", file=sys.stderr)
        sys.exit(2)
