"""Refine ACE's 7-Scenes poses with per-scene 3DGS maps; one loop over a scene list, no per-scene copies.

Usage:
    python examples/refine_ace_7scenes.py --dataset /data/7scenes --maps /data/3dgs_7scenes --out out/ace \
        [--poses-root ../shared/data/poses/7scenes] [--scenes chess fire] [--limit 20]

Expects ``<maps>/<scene>/point_cloud.ply`` (trained in the SfM pGT frame), ``<dataset>/<scene>/test`` with the
query images (``seq-XX/frame-XXXXXX.color.png``), and ``<poses-root>/<scene>/{ace.txt,pgt_sfm_test.txt}``.

ACE's file gives each pose's expected error (its inlier count). A localizer without a per-pose confidence can be
given its typical error, e.g. Marepo's published 7-Scenes median against the SfM pGT (``../shared/docs/PEERS.md``:
``--prior-error 2.9cm --prior-rotation-error 1.04deg``); each refined pose is then fused with its prior.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.intrinsics import from_pgt
from hgsloc_plugin.evaluate import evaluate, mean_over_scenes
from hgsloc_plugin.pipeline import refine_pose_file
from hgsloc_plugin.refine import RefineConfig
from hgsloc_plugin.refine.config import PRESET_HELP, PRESETS
from hgsloc_plugin.units import prior_error_overrides

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"]


def main(localizer: str = "ace") -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--maps", type=Path, required=True)
    ap.add_argument("--poses-root", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data"
                    / "poses" / "7scenes")
    ap.add_argument("--out", type=Path, default=Path(f"out/{localizer}"))
    ap.add_argument("--scenes", nargs="+", default=SCENES)
    ap.add_argument("--config", default="default", choices=sorted(PRESETS), help=PRESET_HELP)
    ap.add_argument("--limit", type=int)
    ap.add_argument("--prior-error", help="the localizer's typical camera-centre error, e.g. 2.9cm (default: unknown)")
    ap.add_argument("--prior-rotation-error", help="its typical rotation error, e.g. 1.04deg")
    a = ap.parse_args()
    try:
        config = RefineConfig.preset(a.config, **prior_error_overrides(a.prior_error, a.prior_rotation_error))
    except ValueError as exc:
        ap.error(str(exc))
    before, after = [], []
    for scene in a.scenes:
        coarse = a.poses_root / scene / f"{localizer}.txt"
        gt = a.poses_root / scene / "pgt_sfm_test.txt"
        out = a.out / scene / f"{localizer}_refined.txt"
        refine_pose_file(a.maps / scene / "point_cloud.ply", coarse, a.dataset / scene / "test", from_pgt(gt), out,
                         config=config, limit=a.limit, gt_variant="sfm")
        before.append(evaluate(read_poses(coarse), read_poses(gt)))
        after.append(evaluate(read_poses(out), read_poses(gt)))
        print(f"{scene}: {before[-1]['median_translation_cm']:.2f} cm -> {after[-1]['median_translation_cm']:.2f} cm")
    b, f = mean_over_scenes(before), mean_over_scenes(after)
    print(f"mean over scenes: {b['median_translation_cm']:.2f} cm / {b['median_rotation_deg']:.2f} deg -> "
          f"{f['median_translation_cm']:.2f} cm / {f['median_rotation_deg']:.2f} deg")


if __name__ == "__main__":
    main()
