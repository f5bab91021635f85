"""Real-photo benchmark: refine real photographs against imperfect 3DGS maps, every heuristic, one run.

Usage: python benchmarks/real_photos.py [--datasets snow lego] [--heuristics cs ssim sad affine] [--seeds 1]
                                        [--out benchmarks/real_photos.md]

Data (read in place, skipped with a message when absent):
- ``../shared/data/snow``: 6 held-out real phone photos with SfM poses against two 3DGS maps fitted to 85 other
  photos: ``snow`` (snow.ply, an imperfect map) and ``snow_sharp`` (snow_sharp.ply, a good one). Errors are in %
  of the query's median depth (about 4.5 units; 1 % = 2 cm-eq, 7-Scenes-equivalent cm at a 2 m depth) and degrees.
- ``../shared/data/lego``: a 3DGS fitted to Blender renders, 15 held-out renders (white background); errors in
  scene units and degrees.

Rows per heuristic (default config otherwise; ``cs`` is the default):
- ``truth``: started at the true pose. ``search`` is where the search ends (the drift of the cost minimum),
  ``returned`` what the refiner returns after its acceptance rule (``refine/trust.py``).
- ``a% / b deg``: camera-frame priors of exactly a % of depth (lego: 0.05 units) and b degrees, random directions.
- ``ACE-shaped`` / ``Marepo-shaped``: the camera-frame errors of the real ACE / Marepo estimates of 7-Scenes
  against the SfM pGT (``../shared/data/poses/7scenes``), one drawn per query, translation scaled by the query's
  depth over 2 m.
Each row: median and worst error of the prior and of the returned pose, queries ending worse than their prior
(in translation or rotation), accepted queries, renders and seconds per query.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"

import hgsloc_plugin as hp  # noqa: E402
from hgsloc_plugin.core.image import load_image  # noqa: E402
from hgsloc_plugin.evaluation.noise import se3_noise  # noqa: E402
from hgsloc_plugin.refine.plan import median_depth  # noqa: E402

#: dataset -> (folder under ../shared/data, map file): snow has an imperfect map and a good one
MAPS = {"snow": ("snow", "snow.ply"), "snow_sharp": ("snow", "snow_sharp.ply"), "lego": ("lego", "lego.ply")}


def load_dataset(name: str):
    """(camera, scene, [(image name, true pose, image [H, W, 3], median depth)], background) or None."""
    folder, ply = MAPS.get(name, (name, f"{name}.ply"))
    d = DATA / folder
    if not (d / ply).exists():
        print(f"skipping {name}: {d / ply} not found", file=sys.stderr)
        return None
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(d / ply)
    white = name == "lego"
    queries = []
    for line in (d / "gt.txt").read_text().splitlines():
        t = line.split()
        gt = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
        if white:  # RGBA renders: composite on the white background the map was trained with
            from PIL import Image

            rgba = np.asarray(Image.open(d / "queries" / t[0]).convert("RGBA"), np.float32) / 255.0
            img = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        else:
            img = load_image(d / "queries" / t[0])
        queries.append((t[0], gt, img, median_depth(scene, cam, gt)))
    return cam, scene, queries, (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)


def localizer_errors(method: str, inliers: list | None = None) -> list[hp.Pose]:
    """Camera-frame errors E = T_est T_gt^-1 of a localizer on all 7-Scenes test frames (pGT frame); each
    estimate's inlier count (None where the file has none) is appended to ``inliers`` when given."""
    from hgsloc_plugin.adapters import read_poses
    from hgsloc_plugin.adapters.confidence import record_inliers

    out = []
    for scene_dir in sorted((DATA / "poses" / "7scenes").glob("*")):
        est, gt = read_poses(scene_dir / f"{method}.txt"), read_poses(scene_dir / "pgt_sfm_test.txt")
        by_key = {n.replace("/", "-"): n for n in est}
        for n, g in gt.items():
            k = by_key.get(n.replace("/", "-"))
            if k is not None and est[k] is not None and g is not None:
                out.append(est[k] @ g.inv())
                if inliers is not None:
                    inliers.append(record_inliers(est.dialect, est.record(k).tokens))
    return out


def shaped_prior(gt: hp.Pose, err: hp.Pose, depth: float) -> hp.Pose:
    """Apply a camera-frame error with its translation scaled by depth / 2 m (7-Scenes' typical depth)."""
    return hp.Pose(err.qvec, err.tvec * depth / 2.0) @ gt


def worse_count(e0: np.ndarray, e1: np.ndarray) -> int:
    """How many returned poses (errors ``e1`` [n, 2]) are further from the truth than their priors (``e0``)."""
    return int(np.sum((e1[:, 0] > e0[:, 0] + 1e-9) | (e1[:, 1] > e0[:, 1] + 1e-9)))


def write_keeping_notes(path: Path, lines: list[str], section: str = "## Notes") -> None:
    """Write ``lines`` as a Markdown file at ``path`` (atomically), keeping what the file already has from its
    first line starting with ``section`` (default: its ``## Notes``; ``"## "``: every level-2 section, for a
    benchmark whose own lines hold none): a benchmark regenerates its figures, not the discussion beside them."""
    from hgsloc_plugin.core.fileio import atomic_write_bytes

    old = path.read_text() if path.exists() else ""
    mark = "\n" + section
    notes = ["", old[old.index(mark) + 1:].rstrip("\n")] if mark in old else []
    atomic_write_bytes(path, ("\n".join(lines + notes) + "\n").encode())


def protocols(dataset: str, queries, seeds: int):
    """name -> list of (query index, prior pose)."""
    out = {"truth": [(i, q[1]) for i, q in enumerate(queries)]}
    for pct, deg in ((1, 0.5), (2, 1.0), (5, 2.0)):
        label = f"{pct}% / {deg:g} deg" if dataset != "lego" else f"{0.05 * pct / 2:.3f} u / {deg:g} deg"
        rows = []
        for s in range(seeds):
            rng = np.random.default_rng(100 + s)
            for i, (_, gt, _, depth) in enumerate(queries):
                shift = pct / 100 * depth if dataset != "lego" else 0.05 * pct / 2
                rows.append((i, se3_noise(gt, deg, shift, rng)))
        out[label] = rows
    if (DATA / "poses" / "7scenes").exists():
        for method in ("ace", "marepo"):
            errs = localizer_errors(method)
            rows = []
            for s in range(seeds):
                rng = np.random.default_rng(200 + s)
                for i, (_, gt, _, depth) in enumerate(queries):
                    rows.append((i, shaped_prior(gt, errs[int(rng.integers(len(errs)))], depth)))
            out[f"{'ACE' if method == 'ace' else 'Marepo'}-shaped"] = rows
    else:
        print("skipping localizer-shaped priors: ../shared/data/poses/7scenes not found", file=sys.stderr)
    return out


def run(dataset: str, heuristics: list[str], seeds: int) -> list[str]:
    loaded = load_dataset(dataset)
    if loaded is None:
        return []
    cam, scene, queries, bg = loaded
    scale, unit = (lambda i: 100.0 / queries[i][3], "% depth") if dataset != "lego" else (lambda i: 1.0, "units")
    lines = [f"\n### {dataset}: {len(queries)} real {'photos' if dataset != 'lego' else 'renders'}, "
             f"{scene.num_gaussians} Gaussians; translation in {unit}, rotation in degrees\n",
             "| heuristic | start | prior median (worst) | search median | returned median (worst) | worse | "
             "accepted | renders | s / query |", "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    prots = protocols(dataset, queries, seeds)
    for h in heuristics:
        refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(metric=h, background=bg))
        for label, items in prots.items():
            e0, e1, es, acc, ren = [], [], [], 0, []
            t0 = time.perf_counter()
            for i, prior in items:
                name, gt, img, _ = queries[i]
                r = refiner.refine(img, cam, prior, name=name)
                for lst, p in ((e0, prior), (e1, r.pose), (es, r.search_pose)):
                    t, a = p.errors_to(gt)
                    lst.append((t * scale(i), a))
                acc += r.accepted
                ren.append(r.renders)
            sec = (time.perf_counter() - t0) / len(items)
            e0, e1, es = np.array(e0), np.array(e1), np.array(es)
            worse = worse_count(e0, e1)

            def fmt(e, worst=True):
                m = f"{np.median(e[:, 0]):.3f} / {np.median(e[:, 1]):.2f}"
                return m + (f" ({e[:, 0].max():.2f} / {e[:, 1].max():.2f})" if worst else "")

            row = (f"| {h}{' (default)' if h == hp.RefineConfig().metric else ''} | {label} | {fmt(e0)} | "
                   f"{fmt(es, False)} | {fmt(e1)} | {worse} / {len(items)} | {acc} / {len(items)} | "
                   f"{np.median(ren):.0f} | {sec:.1f} |")
            print(row, flush=True)
            lines.append(row)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["snow", "snow_sharp", "lego"])
    ap.add_argument("--heuristics", nargs="+", default=["cs", "ssim", "sad", "affine"])
    ap.add_argument("--seeds", type=int, default=1, help="prior draws per query and protocol")
    ap.add_argument("--out", default=None, help="also write the tables as Markdown here")
    args = ap.parse_args()
    hp.init()
    lines = ["# Real-photo benchmark (`benchmarks/real_photos.py`)",
             f"\nDefault config, scoring side {hp.RefineConfig().score_max_side} px; seeds {args.seeds}."]
    for ds in args.datasets:
        lines += run(ds, args.heuristics, args.seeds)
    if args.out:
        from hgsloc_plugin.core.fileio import atomic_write_bytes

        atomic_write_bytes(Path(args.out), ("\n".join(lines) + "\n").encode())


if __name__ == "__main__":
    main()
