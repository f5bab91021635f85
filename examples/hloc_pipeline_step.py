"""Insert the 3DGS refinement into an hloc 7-Scenes run, after localize_sfm and before evaluate.

Usage:
    python examples/hloc_pipeline_step.py --outputs outputs/7scenes --dataset /data/7scenes \
        --maps /data/3dgs_7scenes [--scenes chess heads]

For each scene it reads ``<outputs>/<scene>/results_sparse.txt`` and ``query_list_with_intrinsics.txt`` (as
written by hloc's pipeline) and writes ``results_refined.txt`` beside them, in hloc's format.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hgsloc_plugin import hloc_step as hgsloc_step
from hgsloc_plugin.core.units import count_arg

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--outputs", type=Path, required=True,
                    help="hloc's outputs: <outputs>/<scene>/results_sparse.txt (+ _logs.pkl) and "
                         "query_list_with_intrinsics.txt")
    ap.add_argument("--dataset", type=Path, required=True, help="the 7-Scenes folder: <dataset>/<scene>/seq-XX/...")
    ap.add_argument("--maps", type=Path, required=True,
                    help="the 3DGS maps: <maps>/<scene>/point_cloud.ply, in the frame of hloc's reconstruction")
    ap.add_argument("--scenes", nargs="+", default=SCENES, choices=SCENES, help="default: all seven")
    ap.add_argument("--limit", type=count_arg, help="refine only the first N queries of each scene")
    a = ap.parse_args(argv)
    need = [p for s in a.scenes for p in (a.maps / s / "point_cloud.ply", a.outputs / s / "results_sparse.txt",
                                          a.outputs / s / "query_list_with_intrinsics.txt", a.dataset / s)]
    missing = [p for p in need if not p.exists()]
    if missing:
        print(f"error: {len(missing)} input(s) not found, first {missing[0]} (expected layout: see --help)",
              file=sys.stderr)
        return 2
    for scene in a.scenes:
        run = a.outputs / scene
        # ... localize_sfm.main(ref_sfm, query_list, retrieval, features, loc_matches, results) ran before this
        try:
            refined = hgsloc_step.main(a.maps / scene / "point_cloud.ply", run / "query_list_with_intrinsics.txt",
                                       run / "results_sparse.txt", a.dataset / scene, run / "results_refined.txt",
                                       limit=a.limit, gt_variant="sfm")
        except (ValueError, OSError, KeyError) as exc:
            print(f"error: {scene}: {exc}", file=sys.stderr)
            return 2
        print(f"{scene}: {refined}")
        # ... then evaluate(gt_dir, refined, gt_dir / "list_test.txt") as hloc does
    return 0


if __name__ == "__main__":
    sys.exit(main())
