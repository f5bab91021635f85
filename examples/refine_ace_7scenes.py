"""Refine a localizer's 7-Scenes poses with per-scene 3DGS maps; one loop over a scene list, no per-scene copies.

Usage:
    python examples/refine_ace_7scenes.py --dataset /data/7scenes --maps /data/3dgs_7scenes --out out/ace \
        [--poses-root ../shared/data/poses/7scenes] [--scenes chess fire] [--limit 20]

Expects ``<maps>/<scene>/point_cloud.ply`` (trained in the SfM pGT frame), ``<dataset>/<scene>/test`` with the
query images (``seq-XX/frame-XXXXXX.color.png``), and ``<poses-root>/<scene>/{<localizer>.txt,pgt_sfm_test.txt}``.
A missing file is named before anything runs; a rerun resumes each scene.

ACE's file gives each pose's expected error (its inlier count). A localizer without a per-pose confidence can be
given its typical error, e.g. Marepo's published 7-Scenes median against the SfM pGT (``../shared/docs/PEERS.md``:
``--prior-error 2.9cm --prior-rotation-error 1.04deg``); each refined pose is then fused with its prior.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.intrinsics import from_pgt
from hgsloc_plugin.core.units import count_arg, prior_error_overrides
from hgsloc_plugin.evaluation.evaluate import evaluate, mean_over_scenes
from hgsloc_plugin.refine import RefineConfig
from hgsloc_plugin.refine.config import PRESET_HELP, PRESETS
from hgsloc_plugin.run.pipeline import refine_pose_file

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"]
NAMES = {"ace": "ACE", "glace": "GLACE", "marepo": "Marepo", "dfnet": "DFNet", "hloc": "HLoc"}


def parser(localizer: str) -> argparse.ArgumentParser:
    name = NAMES.get(localizer, localizer)
    ap = argparse.ArgumentParser(description=f"Refine {name}'s 7-Scenes poses with per-scene 3DGS maps and evaluate "
                                             "them against the SfM pseudo ground truth.")
    ap.add_argument("--dataset", type=Path, required=True,
                    help="the 7-Scenes folder: <dataset>/<scene>/test/seq-XX/frame-XXXXXX.color.png")
    ap.add_argument("--maps", type=Path, required=True,
                    help="the 3DGS maps: <maps>/<scene>/point_cloud.ply, trained in the SfM pGT's frame")
    ap.add_argument("--poses-root", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data"
                    / "poses" / "7scenes", help=f"<poses-root>/<scene>/{localizer}.txt and pgt_sfm_test.txt "
                                            "(default: ../shared/data/poses/7scenes)")
    ap.add_argument("--out", type=Path, default=Path(f"out/{localizer}"),
                    help=f"refined files go to <out>/<scene>/{localizer}_refined.txt (+ .json reports)")
    ap.add_argument("--scenes", nargs="+", default=SCENES, choices=SCENES, help="default: all seven")
    ap.add_argument("--config", default="default", choices=sorted(PRESETS), help=PRESET_HELP)
    ap.add_argument("--limit", type=count_arg, help="refine only the first N queries of each scene")
    ap.add_argument("--prior-error", help="the localizer's typical camera-centre error, e.g. 2.9cm (default: unknown)")
    ap.add_argument("--prior-rotation-error", help="its typical rotation error, e.g. 1.04deg")
    return ap


def missing_inputs(a, localizer: str) -> list[Path]:
    """The files and folders the run needs that are not there."""
    need = []
    for scene in a.scenes:
        need += [a.maps / scene / "point_cloud.ply", a.dataset / scene / "test",
                 a.poses_root / scene / f"{localizer}.txt", a.poses_root / scene / "pgt_sfm_test.txt"]
    return [p for p in need if not p.exists()]


def main(localizer: str = "ace", argv=None) -> int:
    ap = parser(localizer)
    a = ap.parse_args(argv)
    try:
        config = RefineConfig.preset(a.config, **prior_error_overrides(a.prior_error, a.prior_rotation_error))
    except ValueError as exc:
        ap.error(str(exc))
    missing = missing_inputs(a, localizer)
    if missing:
        print(f"error: {len(missing)} input(s) not found, first {missing[0]} (expected layout: see --help)",
              file=sys.stderr)
        return 2
    before, after = [], []
    for scene in a.scenes:
        coarse = a.poses_root / scene / f"{localizer}.txt"
        gt = a.poses_root / scene / "pgt_sfm_test.txt"
        out = a.out / scene / f"{localizer}_refined.txt"
        try:
            refine_pose_file(a.maps / scene / "point_cloud.ply", coarse, a.dataset / scene / "test", from_pgt(gt),
                             out, config=config, limit=a.limit, gt_variant="sfm")
        except (ValueError, OSError, KeyError) as exc:
            print(f"error: {scene}: {exc}", file=sys.stderr)
            return 2
        before.append(evaluate(read_poses(coarse), read_poses(gt)))
        after.append(evaluate(read_poses(out), read_poses(gt)))
        print(f"{scene}: {before[-1]['median_translation_cm']:.2f} cm -> {after[-1]['median_translation_cm']:.2f} cm")
    b, f = mean_over_scenes(before), mean_over_scenes(after)
    print(f"mean over scenes: {b['median_translation_cm']:.2f} cm / {b['median_rotation_deg']:.2f} deg -> "
          f"{f['median_translation_cm']:.2f} cm / {f['median_rotation_deg']:.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
