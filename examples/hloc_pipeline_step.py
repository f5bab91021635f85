"""Insert the 3DGS refinement into an hloc 7-Scenes run, after localize_sfm and before evaluate.

Usage:
    python examples/hloc_pipeline_step.py --outputs outputs/7scenes --dataset /data/7scenes \
        --maps /data/3dgs_7scenes [--scenes chess heads]

For each scene it reads ``<outputs>/<scene>/results_sparse.txt`` and ``query_list_with_intrinsics.txt`` (as
written by hloc's pipeline) and writes ``results_refined.txt`` beside them, in hloc's format.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hgsloc_plugin import hloc_step as hgsloc_step

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"]

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--outputs", type=Path, required=True)
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--maps", type=Path, required=True)
    ap.add_argument("--scenes", nargs="+", default=SCENES)
    ap.add_argument("--limit", type=int)
    a = ap.parse_args()
    for scene in a.scenes:
        run = a.outputs / scene
        # ... localize_sfm.main(ref_sfm, query_list, retrieval, features, loc_matches, results) ran before this
        refined = hgsloc_step.main(a.maps / scene / "point_cloud.ply", run / "query_list_with_intrinsics.txt",
                                   run / "results_sparse.txt", a.dataset / scene, run / "results_refined.txt",
                                   limit=a.limit, gt_variant="sfm")
        print(f"{scene}: {refined}")
        # ... then evaluate(gt_dir, refined, gt_dir / "list_test.txt") as hloc does
